"""The four loaders on the committed excerpts (tests/data), checked against plain-Python parsing."""

import gzip
import math
import shutil

import numpy as np
import pytest
from data_loader_paths import EXCERPTS, data_lines

import jaxslam.data as D
from jaxslam.data import (AckermannGeometry, DataFormatError, MissingDataError, load_mrclam,
                          load_plaza, load_util, load_victoria_park, tag_positions)
from jaxslam.errors import InputError

MR = EXCERPTS / "mrclam6"


def test_public_api():
    assert D.DATASETS == ("mrclam", "victoria-park", "util-uwb", "plaza")
    for name in D.__all__:
        assert hasattr(D, name), name
    assert issubclass(DataFormatError, InputError)
    assert D.EventLog is D.events.EventLog and D.merge_events is D.events.merge_events


# ---------------------------------------------------------------------------------- MRCLAM
def _barcode_table():
    return {int(b): int(s) for _, (s, b) in data_lines(MR / "Barcodes.dat")}


@pytest.mark.parametrize("robot", [1, 2])
def test_mrclam_counts_match_plain_parsing(robot):
    d = load_mrclam(EXCERPTS, robot)
    b2s = _barcode_table()
    meas = data_lines(MR / f"Robot{robot}_Measurement.dat")
    subj = [b2s.get(int(f[1])) for _, f in meas]
    n_robot = sum(s is not None and s <= 5 for s in subj)
    n_unknown = sum(s is None for s in subj)
    lm = [(float(f[0]), float(f[2]), float(f[3]), s) for (_, f), s in zip(meas, subj)
          if s is not None and s > 5]
    odo = data_lines(MR / f"Robot{robot}_Odometry.dat")
    gt = data_lines(MR / f"Robot{robot}_Groundtruth.dat")
    r = d.report
    assert r["rows"] == {"odometry": len(odo), "groundtruth": len(gt), "measurement": len(meas),
                         "landmark_groundtruth": 15, "barcodes": 20}
    assert (r["landmark_rows"], r["robot_rows"], r["unknown_barcode_rows"]) == (len(lm), n_robot, n_unknown)
    assert r["landmark_rows"] + r["robot_rows"] + r["unknown_barcode_rows"] == len(meas)
    assert n_robot > 0  # the excerpts were cut to hold rows of other robots
    # shapes, units and times relative to t0 = first ground-truth time
    t0 = float(gt[0][1][0])
    assert d.t0 == t0 and d.gt_t[0] == 0.0
    assert d.odom.shape == (len(odo), 2) and d.odom_t.shape == (len(odo),)
    assert d.gt.shape == (len(gt), 3)
    assert d.meas.shape == (len(lm), 2) and d.meas_id.dtype == np.int32
    np.testing.assert_allclose(d.meas_t, [round(t - t0, 6) for t, *_ in lm], atol=1e-9)
    np.testing.assert_array_equal(d.meas, [(rg, br) for _, rg, br, _ in lm])
    np.testing.assert_array_equal(d.meas_id, [s for *_, s in lm])
    assert set(d.meas_id.tolist()) <= set(range(6, 21))
    np.testing.assert_allclose(d.odom_t[0], float(odo[0][1][0]) - t0, atol=1e-6)
    assert d.odom_t[0] > 0  # odometry starts after ground truth in both excerpts
    np.testing.assert_array_equal(d.odom[:, 0], [float(f[1]) for _, f in odo])
    assert np.all(np.abs(d.gt[:, 2]) <= np.pi)
    # landmark table and barcodes
    assert d.landmark_id.tolist() == list(range(6, 21))
    assert d.landmark_xy.shape == (15, 2) and d.landmark_std.shape == (15, 2)
    assert np.all(d.landmark_std > 0)
    assert d.barcodes.shape == (20, 2) and dict(zip(d.barcodes[:, 1], d.barcodes[:, 0])) == b2s
    assert d.landmark_positions()[6] == pytest.approx((0.58831396, -4.28264845))


def test_mrclam_robot1_unknown_barcode_dropped_or_strict():
    meas = data_lines(MR / "Robot1_Measurement.dat")
    bad = [ln for ln, f in meas if int(f[1]) not in _barcode_table()]
    assert bad == [33]  # barcode 43, source line 1098
    d = load_mrclam(MR, 1)
    assert d.report["unknown_barcodes"] == [43]
    assert d.report["unknown_barcode_lines"] == [f"{MR / 'Robot1_Measurement.dat'}:33"]
    with pytest.raises(DataFormatError, match=r"Robot1_Measurement\.dat:33: unknown barcode 43") as ei:
        load_mrclam(MR, 1, strict=True)
    assert ei.value.line == 33


def test_mrclam_robot2_duplicate_odometry_time_and_repeats():
    odo = data_lines(MR / "Robot2_Odometry.dat")
    dup = [ln for (ln, f), (_, g) in zip(odo[1:], odo[:-1]) if f[0] == g[0]]
    assert dup == [480]
    d = load_mrclam(EXCERPTS / "mrclam6", 2)
    assert d.report["odometry_duplicate_lines"] == [f"{MR / 'Robot2_Odometry.dat'}:480"]
    assert d.report["odometry_duplicate_times"] == [pytest.approx(899.705 - 893.014)]
    assert d.report["unknown_barcode_rows"] == 0
    # repeated readings: a barcode's (range, bearing) equal to its previous reading
    last, rep = {}, 0
    for _, f in data_lines(MR / "Robot2_Measurement.dat"):
        rep += last.get(f[1]) == (f[2], f[3])
        last[f[1]] = (f[2], f[3])
    assert d.report["repeated_readings"] == rep
    assert d.report["duplicate_rows"] == 0


def test_mrclam_bad_arguments(tmp_path):
    for robot in (0, 6, "1", 1.0, True):
        with pytest.raises(InputError, match="robot"):
            load_mrclam(EXCERPTS, robot)
    with pytest.raises(MissingDataError, match="Robot3_Odometry.dat") as ei:
        load_mrclam(EXCERPTS, 3)  # robot 3 has no files in the excerpt
    assert "looked in" in str(ei.value)
    with pytest.raises(FileNotFoundError, match="no dataset files found"):
        load_mrclam(tmp_path, 1)


# ---------------------------------------------------------------------------------- Victoria Park
def test_victoria_park_excerpt():
    v = load_victoria_park(EXCERPTS)
    vp = EXCERPTS / "victoria_park"
    inp, mea, gps = (data_lines(vp / f) for f in ("inputs.dat", "measurements.dat", "gps.dat"))
    assert v.inputs.shape == (len(inp), 2) == (800, 2)
    assert v.det.shape == (len(mea), 2) and v.gps.shape == (len(gps), 2)
    raw_b = np.array([float(f[2]) for _, f in mea])
    np.testing.assert_array_equal(v.det_bearing_laser, raw_b)
    np.testing.assert_allclose(v.det[:, 1], raw_b - np.pi / 2, atol=0, rtol=0)
    assert np.all(np.abs(v.det[:, 1]) < np.pi / 2)
    np.testing.assert_array_equal(v.det[:, 0], [float(f[1]) for _, f in mea])
    np.testing.assert_array_equal(v.det_diameter, [float(f[3]) for _, f in mea])
    times = [f[0] for _, f in mea]
    per_scan = {t: times.count(t) for t in set(times)}
    assert v.report["scans"] == len(per_scan) == 95
    assert v.report["max_detections_per_scan"] == max(per_scan.values())
    assert v.report["detections"] == len(mea)
    assert v.geometry == AckermannGeometry() == AckermannGeometry(2.83, 0.76, 3.78, 0.50)
    assert v.geometry.L == 2.83 and v.geometry.b == 0.5
    assert v.input_t[0] == 0.973 and v.det_t[0] == 0.852 and v.gps_t[0] == 0.0
    assert load_victoria_park(vp).report["rows"] == v.report["rows"]


# ---------------------------------------------------------------------------------- Plaza
@pytest.mark.parametrize("which", [1, 2])
def test_plaza_excerpt(which):
    p = load_plaza(EXCERPTS, which)
    g = EXCERPTS / "gtsam"
    dr = data_lines(g / f"Plaza{which}_DR.txt")
    td = data_lines(g / f"Plaza{which}_TD.txt")
    gt = data_lines(g / f"Plaza{which}_GT.txt")
    assert p.dr.shape == (len(dr), 2) == (300, 2)
    assert p.gt.shape == (len(gt), 3) == (301, 3) and p.drp.shape == (301, 3)
    assert p.td_range.shape == (len(td),) and p.td_node.dtype.kind == "i"
    np.testing.assert_array_equal(p.td_node, [int(float(f[2])) for _, f in td])
    assert set(p.td_sender.tolist()) == {2}
    assert set(p.td_node.tolist()) <= {0, 1, 5, 6} and sorted(p.node_id.tolist()) == [0, 1, 5, 6]
    assert p.dr_t[0] == p.gt_t[1]  # GT has the initial pose first
    assert p.report["td_out_of_order"] == 0
    assert p.heading_offset == (np.pi if which == 2 else 0.0)
    x, y, th = p.start_pose()
    if which == 2:  # gtsam's RangeISAMExample_plaza2.cpp: Pose2(-34.2086, 45.3008, pi - 2.021089)
        assert (x, y) == pytest.approx((-34.2086, 45.3008), abs=1e-4)
        assert th == pytest.approx(np.pi - 2.021089, abs=1e-12)
    else:
        assert (x, y) == (0.0, 0.0)
        assert th == pytest.approx(math.atan2(math.sin(4.222432), math.cos(4.222432)))


def test_plaza2_heading_offset_follows_travel_direction():
    """Over the excerpt, DR from start_pose() follows GT better than DR from raw GT heading."""
    p = load_plaza(EXCERPTS, 2)

    def dr_error(pose):
        x, y, th = pose
        err = []
        for (d, dth), gxy in zip(p.dr, p.gt[1:, :2]):
            x += d * math.cos(th)
            y += d * math.sin(th)
            th += dth
            err.append(math.hypot(x - gxy[0], y - gxy[1]))
        return max(err)

    assert dr_error(p.start_pose()) < 0.5 * dr_error(p.gt[0])


def test_plaza_td_out_of_order_is_sorted(tmp_path):
    g = tmp_path / "gtsam"
    shutil.copytree(EXCERPTS / "gtsam", g)
    lines = (g / "Plaza1_TD.txt").read_bytes().split(b"\n")
    lines[40], lines[41] = lines[41], lines[40]  # time goes back at line 42
    (g / "Plaza1_TD.txt").write_bytes(b"\n".join(lines))
    p = load_plaza(tmp_path, 1)
    ref = load_plaza(EXCERPTS, 1)
    assert p.report["td_out_of_order"] == 1
    assert p.report["td_out_of_order_lines"] == [f"{g / 'Plaza1_TD.txt'}:42"]
    np.testing.assert_array_equal(p.td_t, ref.td_t)
    np.testing.assert_array_equal(p.td_range, ref.td_range)


def test_plaza_bad_arguments():
    for which in (0, 3, "1", True):
        with pytest.raises(InputError, match="which"):
            load_plaza(EXCERPTS, which)


# ---------------------------------------------------------------------------------- UTIL
def _csv(path):
    opener = gzip.open if str(path).endswith(".gz") else open
    with opener(path, "rt") as f:
        rows = f.read().splitlines()
    return rows[0].split(","), np.array([[float(x) for x in r.split(",")] for r in rows[1:]])


def test_util_twr_excerpt_units_and_shapes():
    u = load_util(EXCERPTS)  # default flight: twr_obs_log1
    fl = EXCERPTS / "util_uwb" / "twr_obs_log1"
    _, twr = _csv(fl / "uwb_twr.csv")
    _, imu = _csv(fl / "imu.csv.gz")
    _, gt = _csv(fl / "groundtruth.csv")
    assert u.flight == "twr_obs_log1"
    assert u.twr_range.shape == (len(twr),) == (84,)
    np.testing.assert_array_equal(u.twr_anchor, twr[:, 1].astype(int))
    assert u.tdoa.shape == (0,) and u.tdoa_pair.shape == (0, 2)
    assert u.acc.shape == (len(imu), 3) == (1009, 3)
    np.testing.assert_allclose(u.acc, imu[:, 1:4] * 9.81, rtol=1e-15)
    np.testing.assert_allclose(u.gyro, imu[:, 5:8] * np.pi / 180, rtol=1e-15)
    assert np.median(np.linalg.norm(u.acc, axis=1)) == pytest.approx(9.81, abs=1.0)  # hovering
    np.testing.assert_array_equal(u.imu_t, imu[:, 0])
    np.testing.assert_array_equal(u.imu_t_gyro, imu[:, 4])
    np.testing.assert_array_equal(u.gt_q, gt[:, 4:8])  # (qx, qy, qz, qw) kept
    np.testing.assert_allclose(np.linalg.norm(u.gt_q, axis=1), 1.0, atol=1e-5)
    assert u.gt_p.shape == (199, 3) and np.all(u.gt_p[:, 2] > 0.3)  # airborne window
    assert u.anchor_id.tolist() == list(range(8)) and u.anchor_p.shape == (8, 3)
    assert u.anchor_q.shape == (8, 4)
    assert tuple(u.tag_offset) == D.TAG_OFFSET == (-0.01245, 0.00127, 0.0908)
    assert u.report["rows"] == {"anchors": 8, "groundtruth": 199, "imu": 1009, "uwb_twr": 84}
    assert sum(u.report["ranges_per_anchor"].values()) == 84
    assert 20.0 <= u.twr_t[0] and u.twr_t[-1] <= 21.0


def test_util_tdoa_excerpt():
    u = load_util(EXCERPTS / "util_uwb", flight="tdoa2_obs_log1")
    _, td = _csv(EXCERPTS / "util_uwb" / "tdoa2_obs_log1" / "uwb_tdoa.csv")
    assert u.tdoa.shape == (len(td),) == (426,)
    np.testing.assert_array_equal(u.tdoa_pair, td[:, 1:3].astype(int))
    np.testing.assert_array_equal(u.tdoa, td[:, 3])
    assert u.twr_range.shape == (0,)
    assert sum(u.report["tdoa_pairs"].values()) == 426


def test_util_flight_folder_itself_is_accepted():
    # --data pointing at the flight: the same data as through util_uwb/, the anchors from its parent
    a = load_util(EXCERPTS / "util_uwb" / "tdoa2_obs_log1", flight="tdoa2_obs_log1")
    b = load_util(EXCERPTS / "util_uwb", flight="tdoa2_obs_log1")
    np.testing.assert_array_equal(a.tdoa, b.tdoa)
    np.testing.assert_array_equal(a.anchor_p, b.anchor_p)
    from jaxslam.data import catalogue  # `jaxslam list --data FLIGHT` finds it too

    flight = EXCERPTS / "util_uwb" / "twr_obs_log1"
    assert catalogue.find("util-uwb", flight) == flight
    assert catalogue.find("util-uwb", EXCERPTS) == EXCERPTS / "util_uwb"  # the usual forms unchanged
    assert catalogue.find("util-uwb", EXCERPTS / "mrclam6") is None


def test_util_missing_flight_lists_found_flights():
    with pytest.raises(MissingDataError, match=r"flight 'nope' not found.*tdoa2_obs_log1.*twr_obs_log1"):
        load_util(EXCERPTS, "nope")


def _rotmat(q):
    x, y, z, w = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def test_tag_positions():
    off = np.array(D.TAG_OFFSET)
    p = np.array([1.0, 2.0, 3.0])
    np.testing.assert_allclose(tag_positions(p, [0, 0, 0, 1]), p + off)
    yaw90 = [0, 0, math.sin(math.pi / 4), math.cos(math.pi / 4)]
    np.testing.assert_allclose(tag_positions(p, yaw90), p + [-off[1], off[0], off[2]], atol=1e-15)
    u = load_util(EXCERPTS)
    want = u.gt_p + np.einsum("nij,j->ni", np.stack([_rotmat(q) for q in u.gt_q]), off)
    np.testing.assert_allclose(u.tag_positions(), want, atol=1e-12)
    np.testing.assert_allclose(tag_positions(u.gt_p, 2.0 * u.gt_q, off), want, atol=1e-12)  # normalised


def test_loaders_feed_merge_events():
    d = load_mrclam(EXCERPTS, 1)
    log = D.merge_events(d.odom_t, d.odom, d.meas_t, d.meas, d.meas_id)
    assert log.stats["n_meas"] == d.report["landmark_rows"] and log.stats["dropped_overflow"] == 0
    assert log.stats["n_meas_events"] == d.report["distinct_landmark_times"]
    p = load_plaza(EXCERPTS, 2)
    log = D.merge_events(p.dr_t, p.dr, p.td_t, p.td_range, p.td_node, input_mode="increment")
    np.testing.assert_allclose(log.u.sum(axis=0), p.dr.sum(axis=0))
    v = load_victoria_park(EXCERPTS)
    log = D.merge_events(v.input_t, v.inputs, v.det_t, v.det)
    assert log.stats["K"] == v.report["max_detections_per_scan"]
    u = load_util(EXCERPTS)
    log = D.merge_events(u.imu_t, np.hstack([u.acc, u.gyro]), u.twr_t, u.twr_range, u.twr_anchor)
    assert log.stats["n_meas_events"] == log.stats["n_meas"] == 84


def test_util_tof_excerpt_optional():
    u = load_util(EXCERPTS)
    _, tof = _csv(EXCERPTS / "util_uwb" / "twr_obs_log1" / "tof.csv")
    assert u.tof.shape == u.tof_t.shape == (len(tof),) == (23,)
    np.testing.assert_array_equal(u.tof_t, tof[:, 0])
    np.testing.assert_array_equal(u.tof, tof[:, 1])
    assert u.report["tof_rows"] == 23 and 20.0 <= u.tof_t[0] and u.tof_t[-1] <= 21.0
    # airborne excerpt: laser height ≈ body height − 2 cm (data README §4)
    zb = np.interp(u.tof_t, u.gt_t, u.gt_p[:, 2])
    assert abs(np.median(u.tof - zb)) < 0.05
    v = load_util(EXCERPTS / "util_uwb", flight="tdoa2_obs_log1")  # no tof.csv: empty
    assert v.tof.shape == v.tof_t.shape == (0,) and v.report["tof_rows"] == 0


def test_util_flight_folder_given_as_dot(monkeypatch):
    """``load_util(".")`` from inside the flight folder: the anchors are in its parent ("."'s
    unresolved parent is "." again: the loader looked for them in the flight folder)."""
    monkeypatch.chdir(EXCERPTS / "util_uwb" / "tdoa2_obs_log1")
    a = load_util(".", flight="tdoa2_obs_log1")
    b = load_util(EXCERPTS / "util_uwb", flight="tdoa2_obs_log1")
    np.testing.assert_array_equal(a.tdoa, b.tdoa)
    np.testing.assert_array_equal(a.anchor_p, b.anchor_p)
