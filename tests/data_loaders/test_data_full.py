"""The loaders on the full data files against the data README's reference facts.

Skipped when the full data folder is absent ($JAXSLAM_DATA_DIR, else ../shared/data next to
the repository): a fresh clone has only the excerpts.  The dead-reckoning checks are written
independently of the library (plain Euler steps, as the README describes its method).
"""

import math

import numpy as np
import pytest
from data_loader_paths import FULL, needs_full

from jaxslam.data import DataFormatError, load_mrclam, load_plaza, load_util, load_victoria_park


@pytest.fixture(scope="module")
def mrclam1():
    return load_mrclam(FULL, 1)


@needs_full("mrclam6")
def test_mrclam_robot1_reference_facts(mrclam1):
    d, r = mrclam1, mrclam1.report
    assert r["rows"]["odometry"] == 61785 and r["rows"]["groundtruth"] == 49241
    assert r["rows"]["measurement"] == 1942
    assert (r["landmark_rows"], r["robot_rows"], r["unknown_barcode_rows"]) == (1534, 407, 1)
    assert r["unknown_barcodes"] == [43]
    assert r["unknown_barcode_lines"] == [f"{FULL / 'mrclam6' / 'Robot1_Measurement.dat'}:1098"]
    assert r["landmarks_seen"] == 15 and set(d.meas_id.tolist()) == set(range(6, 21))
    assert r["distinct_measurement_times"] == 1234
    assert r["repeated_readings"] == 37 and r["duplicate_rows"] == 0
    assert r["odometry_duplicate_times"] == []
    assert d.t0 == 1248444175.103
    assert d.odom_t[0] == 12.053 and d.gt_t[-1] == 771.873 and r["t_end"] == 900.0
    assert d.odom_t[-1] - d.odom_t[0] == pytest.approx(887.947, abs=1e-9)
    assert d.meas_t[-1] - d.meas_t[0] <= 737.567 + 1e-9
    assert (d.meas[:, 0].min(), d.meas[:, 0].max()) == pytest.approx((1.1, 8.6), abs=0.05)  # "1.1 to 8.6 m"
    assert 0.55 < np.abs(d.meas[:, 1]).max() <= 0.58  # "within ±0.58 rad"
    assert tuple(d.gt[0]) == (1.41277290, -3.89107760, 2.2696)


@needs_full("mrclam6")
def test_mrclam_robot1_dead_reckoning_rms(mrclam1):
    """README method: start at GT₀, rest until the first odometry row, hold each (v, ω) until the
    next row, Euler steps; interpolate x, y at every GT time inside the odometry span."""
    d = mrclam1
    x, y, th = (float(v) for v in d.gt[0])
    t = d.odom_t.tolist()
    xs, ys = [x], [y]
    for k, (v, w) in enumerate(d.odom[:-1].tolist()):
        dt = t[k + 1] - t[k]
        x, y, th = x + v * math.cos(th) * dt, y + v * math.sin(th) * dt, th + w * dt
        xs.append(x)
        ys.append(y)
    inside = (d.gt_t >= t[0]) & (d.gt_t <= t[-1])
    assert inside.sum() == 48561
    ex = np.interp(d.gt_t[inside], t, xs) - d.gt[inside, 0]
    ey = np.interp(d.gt_t[inside], t, ys) - d.gt[inside, 1]
    err = np.hypot(ex, ey)
    assert math.sqrt(np.mean(err ** 2)) == pytest.approx(2.729, abs=0.01)
    assert err.max() == pytest.approx(8.336, abs=0.01)


@needs_full("mrclam6")
def test_mrclam_robot2_reference_facts():
    d = load_mrclam(FULL / "mrclam6", 2)
    r = d.report
    assert (r["rows"]["odometry"], r["rows"]["groundtruth"], r["rows"]["measurement"]) == (65005, 59705, 4031)
    assert (r["landmark_rows"], r["robot_rows"], r["unknown_barcode_rows"]) == (3239, 792, 0)
    assert len(r["odometry_duplicate_times"]) == 1
    assert r["odometry_duplicate_lines"] == [f"{FULL / 'mrclam6' / 'Robot2_Odometry.dat'}:51866"]
    assert d.odom.shape == (65005, 2) and d.meas.shape == (3239, 2)


@needs_full("mrclam6")
def test_mrclam_strict_raises_on_the_real_unknown_barcode():
    with pytest.raises(DataFormatError, match=r"Robot1_Measurement\.dat:1098: unknown barcode 43"):
        load_mrclam(FULL, 1, strict=True)


@needs_full("victoria_park")
def test_victoria_park_reference_facts():
    v = load_victoria_park(FULL)
    r = v.report
    assert r["rows"] == {"inputs": 61945, "measurements": 52974, "gps": 4466}
    assert r["scans"] == 7230 and r["max_detections_per_scan"] == 18
    assert (v.input_t[0], v.input_t[-1], r["t_end"]) == (0.973, 1549.573, 1549.573)
    assert (v.det_t[0], v.det_t[-1]) == (0.852, 1549.241)
    assert v.det[:, 0].min() == pytest.approx(1.48, abs=0.005)
    assert v.det[:, 0].max() == pytest.approx(75.30, abs=0.005)
    assert v.det_bearing_laser.min() == pytest.approx(0.113, abs=5e-4)
    assert v.det_bearing_laser.max() == pytest.approx(3.089, abs=5e-4)
    np.testing.assert_allclose(v.det[:, 1], v.det_bearing_laser - np.pi / 2)
    assert v.inputs[:, 0].max() <= 6.6 + 0.05
    # README (informational): Ackermann dead reckoning travels 4110.7 m
    g = v.geometry
    x = y = ph = dist = 0.0
    t = v.input_t.tolist()
    for k, (ve, a) in enumerate(v.inputs[:-1].tolist()):
        dt = t[k + 1] - t[k]
        ta = math.tan(a)
        vc = ve / (1.0 - ta * g.H / g.L)
        dx = vc * math.cos(ph) - vc / g.L * ta * (g.a * math.sin(ph) + g.b * math.cos(ph))
        dy = vc * math.sin(ph) + vc / g.L * ta * (g.a * math.cos(ph) - g.b * math.sin(ph))
        x, y, ph = x + dx * dt, y + dy * dt, ph + vc / g.L * ta * dt
        dist += math.hypot(dx, dy) * dt
    assert dist == pytest.approx(4110.7, abs=0.5)


def _plaza_dr_rms(p):
    x, y, th = p.start_pose()
    err = [math.hypot(x - p.gt[0, 0], y - p.gt[0, 1])]
    for (d, dth), (gx, gy) in zip(p.dr.tolist(), p.gt[1:, :2].tolist()):
        x, y, th = x + d * math.cos(th), y + d * math.sin(th), th + dth  # Pose2(d, 0, dθ)
        err.append(math.hypot(x - gx, y - gy))
    return math.sqrt(np.mean(np.square(err)))


@needs_full("gtsam", "Plaza1_DR.txt")
def test_plaza1_reference_facts():
    p = load_plaza(FULL, 1)
    r = p.report
    assert (r["rows"]["DR"], r["rows"]["TD"], r["rows"]["GT"], r["rows"]["DRp"]) == (9657, 3529, 9658, 9658)
    assert p.gt_t[-1] - p.gt_t[0] == pytest.approx(1933.4, abs=0.05)
    assert p.heading_offset == 0.0 and tuple(p.gt[0, :2]) == (0.0, 0.0)
    assert _plaza_dr_rms(p) == pytest.approx(2.0, abs=0.05)
    # quirk: two blocks of Plaza1_TD.txt jump back in time; loaded sorted, lines reported
    f = FULL / "gtsam" / "Plaza1_TD.txt"
    assert r["td_out_of_order_lines"] == [f"{f}:1989", f"{f}:2867"]
    assert np.all(np.diff(p.td_t) >= 0)
    assert {n: int(np.sum(p.td_node == n)) for n in (0, 1, 5, 6)} == pytest.approx(
        {n: 880 for n in (0, 1, 5, 6)}, abs=40)


@needs_full("gtsam", "Plaza2_DR.txt")
def test_plaza2_reference_facts():
    p = load_plaza(FULL, 2)
    r = p.report
    assert (r["rows"]["DR"], r["rows"]["TD"], r["rows"]["GT"]) == (4090, 1816, 4091)
    assert p.gt_t[-1] - p.gt_t[0] == pytest.approx(409.5, abs=0.05)
    assert r["td_out_of_order"] == 0
    assert p.heading_offset == pytest.approx(np.pi)
    rms = _plaza_dr_rms(p)
    assert rms == pytest.approx(31.6, abs=0.1)
    drp_rms = math.sqrt(np.mean(np.sum((p.drp[:, :2] - p.gt[:, :2]) ** 2, axis=1)))
    assert rms == pytest.approx(drp_rms, abs=0.2)  # "the same as the DRp in the file"


@needs_full("util_uwb")
def test_util_reference_facts():
    u = load_util(FULL, "twr_obs_log1")
    assert u.twr_range.size == 5509 and u.gt_t.size == 13309 and u.imu_t.size == 66740
    assert u.report["t_end"] == pytest.approx(66.150, abs=0.002)
    assert all(abs(c - 690) < 15 for c in u.report["ranges_per_anchor"].values())
    assert np.sum(np.linalg.norm(np.diff(u.gt_p, axis=0), axis=1)) == pytest.approx(30.7, abs=0.05)
    assert u.report["imu_pairing_max_dt"] <= 0.13e-3 + 1e-9
    airborne = u.gt_t[u.gt_p[:, 2] > 0.3]
    assert (airborne[0], airborne[-1]) == pytest.approx((9.6, 59.0), abs=0.06)
    # TWR bias (README: median of measured − true about −0.25 m)
    tag = u.tag_positions()
    true = np.linalg.norm(np.stack([np.interp(u.twr_t, u.gt_t, tag[:, i]) for i in range(3)], 1)
                          - u.anchor_p[u.twr_anchor], axis=1)
    assert np.median(u.twr_range - true) == pytest.approx(-0.25, abs=0.03)

    v = load_util(FULL / "util_uwb", "tdoa2_obs_log1")
    assert v.tdoa.size == 29349 and v.gt_t.size == 13645 and v.imu_t.size == 68483
    assert v.report["tdoa_pairs"][(4, 6)] == 1 and v.report["tdoa_pairs"][(7, 1)] == 2
    assert np.sum(np.linalg.norm(np.diff(v.gt_p, axis=0), axis=1)) == pytest.approx(33.7, abs=0.05)


@needs_full("util_uwb")
def test_util_anchors_unknown_needs_ranges_of_every_anchor_in_its_start_up_window(tmp_path):
    """The full TWR flight without its ranges before 35 s: the start-up window [0, 30] s holds
    none, so there is nothing to fit the anchors to (it used to run and report anchors 4.35 m
    off with a confident bias)."""
    from jaxslam.data import runners
    from jaxslam.errors import InputError

    src = FULL / "util_uwb"
    dst = tmp_path / "util_uwb"
    (dst / "twr_obs_log1").mkdir(parents=True)
    (dst / "anchors_const3.csv").write_bytes((src / "anchors_const3.csv").read_bytes())
    for f in (src / "twr_obs_log1").iterdir():
        (dst / "twr_obs_log1" / f.name).symlink_to(f)
    twr = dst / "twr_obs_log1" / "uwb_twr.csv"
    lines = (src / "twr_obs_log1" / "uwb_twr.csv").read_text().splitlines()
    twr.unlink()
    twr.write_text("\n".join([lines[0]] + [ln for ln in lines[1:] if float(ln.split(",")[0]) >= 35.0]) + "\n")
    with pytest.raises(InputError, match=r"anchors \[0, 1, 2, 3, 4, 5, 6, 7\] have fewer than 10 ranges"):
        runners.run_util_uwb(tmp_path, anchors="unknown")
