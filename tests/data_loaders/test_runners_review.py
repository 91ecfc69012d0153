"""Review of jaxslam.data.runners: evaluation helpers and runner checks.

Each test compares against an independent expectation (hand-computed values, NumPy).
"""

import shutil

import numpy as np
import pytest
from data_loader_paths import EXCERPTS

from jaxslam.data import runners as R
from jaxslam.errors import InputError


class _Reached(Exception):
    """Raised by a stand-in once the runner has got past its checks."""


def _track(n=101):
    t = np.linspace(0.0, 10.0, n)
    return t, np.stack([t, np.sin(t), 0.1 * t], 1)


# ------------------------------------------------------------------------ evaluate_planar
@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_evaluate_planar_leaves_out_a_nonfinite_reference_row_when_interpolating(bad):
    # one non-finite heading in a pose reference: np.unwrap spread it to every later row, and the
    # evaluation silently covered only the 10 samples before it (no RPE); it is left out instead,
    # as with at_ref_times
    t = np.linspace(0.0, 10.0, 101)
    pose = np.stack([t, 0.5 * t, 0.1 * t], 1)  # linear: interpolating across row 10 is exact
    ref = pose.copy()
    ref[10, 2] = bad
    m, ev = R.evaluate_planar(t, pose, t, ref)
    assert m["eval_samples"] == 101  # every estimate time inside the span (row 10 interpolated)
    assert m["ate_m"] < 1e-9 and m["rpe_m"] < 1e-9 and m["rpe_deg"] < 1e-6
    assert np.all(np.isfinite(ev["ref_xy"]))
    # a whole NaN row in a positions-only reference, likewise
    ref2 = pose[:, :2].copy()
    ref2[10] = np.nan
    m, _ = R.evaluate_planar(t, pose, t, ref2)
    assert m["eval_samples"] == 101 and m["ate_m"] < 1e-9


@pytest.mark.parametrize("width", [2, 3])
def test_evaluate_planar_without_a_finite_reference_row_is_an_input_error(width):
    # an empty (or all-NaN) reference: NumPy's "array of sample points is empty" / a message
    # naming "poses" (an argument evaluate_planar does not have)
    t, pose = _track()
    for t_ref, ref in ((np.zeros(0), np.zeros((0, width))), (t[:3], np.full((3, width), np.nan))):
        with pytest.raises(InputError, match=r"^evaluation: fewer than 3 samples"):
            R.evaluate_planar(t, pose, t_ref, ref)


def test_evaluate_planar_lm_cov_must_be_numbers():
    t, pose = _track()
    with pytest.raises(InputError, match=r"^lm_cov: expected numbers"):
        R.evaluate_planar(t, pose, t, pose, lm=np.zeros((1, 2)), lm_cov=[[["a", "b"], ["c", "d"]]])


# ------------------------------------------------------------------------ split_ate
def test_split_ate_refuses_nonfinite_times():
    # a NaN time fell on neither side of the cut: a silently smaller figure
    ev = {"t": np.array([1.0, np.nan, 3.0]), "est_xy": np.zeros((3, 2)), "ref_xy": np.ones((3, 2))}
    with pytest.raises(InputError, match=r"^ev\['t'\]: expected finite times"):
        R.split_ate(ev, 2.0, "x")
    ev["t"] = np.array([1.0, 2.0, 3.0])
    ev["est_xy"] = np.array([[0.0, 0.0], [1.0, 1.0], [4.0, 1.0]])
    out = R.split_ate(ev, 2.0, "x")
    assert out == {"ate_t_lt_xs_m": pytest.approx(np.sqrt(2.0)),
                   "ate_t_ge_xs_m": pytest.approx(np.sqrt((0.0 + 9.0) / 2))}


# ------------------------------------------------------------------------ dead_reckoning
def test_dead_reckoning_checks_its_shapes():
    def motion(s, u, dt):
        return s + u * dt

    with pytest.raises(InputError, match=r"^dt: expected shape \(5,\)"):
        R.dead_reckoning(motion, np.zeros(3), np.ones((5, 3)), np.ones(4))
    with pytest.raises(InputError, match=r"^u: expected shape \(T, m\)"):
        R.dead_reckoning(motion, np.zeros(3), np.ones(5), np.ones(5))
    with pytest.raises(InputError, match=r"^motion: expected a callable"):
        R.dead_reckoning(None, np.zeros(3), np.ones((5, 3)), np.ones(5))
    u = np.arange(15.0).reshape(5, 3)
    dt = np.array([0.1, 0.2, 0.3, 0.4, 0.5])
    out = np.asarray(R.dead_reckoning(motion, np.ones(3), u, dt))
    np.testing.assert_allclose(out, 1.0 + np.cumsum(u * dt[:, None], axis=0), rtol=1e-6)


# ------------------------------------------------------------------------ runners called directly
@pytest.mark.parametrize("run, kw, match", [
    (R.run_plaza_dataset, dict(anchors="surveyed"), r"^plaza: --anchors: expected one of"),
    (R.run_util_uwb, dict(anchors="Unknown"), r"^util-uwb: --anchors: expected one of"),
    (R.run_util_uwb, dict(filter="fastslam"), r"^util-uwb: --filter do\(es\) not apply here"),
    (R.run_victoria_park, dict(smooth=True), r"^victoria-park: --smooth do\(es\) not apply here"),
    (R.run_victoria_park, dict(filter="fast-slam"), r"^victoria-park: --filter: expected one of"),
    (R.run_mrclam, dict(ids="hiden"), r"^mrclam: --ids: expected one of"),
    (R.run_mrclam, dict(filter="fastslam", smooth=True), r"^mrclam: --smooth smooths the EKF's run"),
])
def test_runners_called_directly_check_their_options(run, kw, match):
    # a misspelt choice ran another method (plaza: SLAM for "surveyed"), an option the dataset
    # does not take was ignored: refused as run_dataset refuses it
    with pytest.raises(InputError, match=match):
        run(EXCERPTS, **kw)


# ------------------------------------------------------------------------ plaza pos_rmse_m
def test_plaza_pos_rmse_is_nan_when_the_estimate_is(monkeypatch):
    from jaxslam.data.plaza import load_plaza
    from jaxslam.systems import plaza_range as pr

    real = pr.run
    poison = {"on": False}

    def run(*a, **kw):
        res = real(*a, **kw)
        return res._replace(pos=res.pos.at[res.pos.shape[0] // 2].set(np.nan)) if poison["on"] else res

    monkeypatch.setattr(pr, "run", run)
    out = R.run_dataset("plaza", EXCERPTS, anchors="known")
    # the unaligned error over the estimate times inside the ground truth's span, by NumPy
    d = load_plaza(EXCERPTS, 1)
    t, pos, _ = out.trajectory
    t = np.asarray(t)
    inside = (t >= d.gt_t[0]) & (t <= d.gt_t[-1])
    gt_xy = np.stack([np.interp(t, d.gt_t, np.asarray(d.gt)[:, j]) for j in range(2)], 1)
    want = np.sqrt(np.mean(np.sum((np.asarray(pos)[inside] - gt_xy[inside]) ** 2, 1)))
    assert out.metrics["pos_rmse_m"] == pytest.approx(want, rel=1e-9)
    poison["on"] = True
    out = R.run_dataset("plaza", EXCERPTS, anchors="known")
    assert out.metrics["nonfinite_estimate_samples"] == 1 and np.isnan(out.metrics["ate_m"])
    # nanmean left out the NaN sample: a finite figure beside a note saying the figures are NaN
    assert np.isnan(out.metrics["pos_rmse_m"])


# ------------------------------------------------------------------------ util-uwb start-up
def test_util_startup_fits_only_ranges_with_motion_capture(tmp_path, monkeypatch):
    """Ranges before the motion capture starts reached the start-up with the first motion-capture
    position held (np.interp), though the window's own count leaves them out."""
    from jaxslam.systems import util_range as ur

    src = EXCERPTS / "util_uwb"
    dst = tmp_path / "util_uwb" / "twr_obs_log1"
    dst.mkdir(parents=True)
    shutil.copy(src / "anchors_const3.csv", tmp_path / "util_uwb" / "anchors_const3.csv")
    shutil.copy(src / "twr_obs_log1" / "imu.csv.gz", dst / "imu.csv.gz")
    (dst / "tof.csv").write_text("t,tof\n" + "".join(f"{t:.3f},1.000\n" for t in np.arange(0.5, 10.0, 0.1)))
    # motion capture over [0.5, 10] s (a slow circle at 1 m), ranges to 8 anchors over [0, 10] s
    tg = np.arange(0.5, 10.0005, 0.01)
    (dst / "groundtruth.csv").write_text("t,x,y,z,qx,qy,qz,qw\n" + "".join(
        f"{t:.3f},{np.cos(0.3 * t):.4f},{np.sin(0.3 * t):.4f},1.0,0,0,0,1\n" for t in tg))
    tr = np.arange(0.0, 10.0, 0.01)
    (dst / "uwb_twr.csv").write_text("t,anchor_id,range\n" + "".join(
        f"{t:.3f},{i % 8},4.0\n" for i, t in enumerate(tr)))
    seen = {}

    def stop(t, *a, **kw):
        seen["t"] = np.asarray(t)
        raise _Reached

    monkeypatch.setattr(ur, "startup", stop)
    with pytest.raises(_Reached):
        R.run_util_uwb(tmp_path, anchors="unknown", t_window=3.0)
    assert seen["t"].size and seen["t"].min() >= 0.5 - 1e-9
    assert np.sum(seen["t"] <= 3.0) == np.sum((tr >= 0.5 - 1e-9) & (tr <= 3.0))
