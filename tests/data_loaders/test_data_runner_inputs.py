"""Python-API inputs of the dataset runners and presets (jaxslam.data.runners / presets).

Bad input is an early :class:`InputError` naming the argument (before any log is read or any
filter compiled where the runner is involved); the evaluation helpers pair, count and refuse as
their docstrings say.  Small excerpts (tests/data) only; nothing here runs a filter.
"""

import jax
import numpy as np
import pytest
from data_loader_paths import EXCERPTS

from jaxslam.data import presets as P
from jaxslam.data import runners as R
from jaxslam.data.mrclam import load_mrclam
from jaxslam.errors import InputError


class _Reached(Exception):
    """Raised by a stand-in once the runner has got past its checks."""


# ---------------------------------------------------------------------------------- item 2: dtype
def test_float64_with_x64_off_is_refused():
    with jax.enable_x64(False):
        with pytest.raises(InputError, match=r"^dtype: float64 needs JAX's 64-bit mode"):
            R.run_dataset("plaza", EXCERPTS, dtype=np.float64)
    with pytest.raises(InputError, match=r"^dtype: expected float32 or float64"):
        R.run_dataset("plaza", EXCERPTS, dtype=np.int32)


@pytest.mark.parametrize("x64, want", [(False, np.float32), (True, np.float64)])
def test_default_dtype_is_what_jax_computes_in(monkeypatch, x64, want):
    from jaxslam.systems import plaza_range as pr

    seen = {}

    def stop(*a, dtype=None, **kw):
        seen["dtype"] = np.dtype(dtype)
        raise _Reached

    monkeypatch.setattr(pr, "log_from_events", stop)
    with jax.enable_x64(x64), pytest.raises(_Reached):
        R.run_dataset("plaza", EXCERPTS)
    assert seen["dtype"] == want


# ---------------------------------------------------------------------------------- item 3: particle counts
def test_particle_counts_are_not_replaced_or_truncated():
    subjects = np.arange(6, 21, dtype=np.int32)
    with pytest.raises(InputError, match=r"^n_particles: expected an int >= 1, got 0"):
        R._mrclam_fastslam(1, 0, "known", subjects, 8)
    with pytest.raises(InputError, match=r"^n_particles: expected an int >= 1, got 0"):
        R._vp_fastslam(0)
    assert R._mrclam_fastslam(1, None, "known", subjects, 8)[0].n_particles == 100
    assert R._vp_fastslam(None)[0].n_particles == 50
    for kw, name in ((dict(n_particles=2.5), "n_particles"), (dict(K="8"), "K"), (dict(capacity=15.5), "capacity")):
        with pytest.raises(InputError, match=rf"^{name}: expected an int >= 1"):
            P.mrclam_fastslam_setup(**kw)
    for kw, name in ((dict(capacity=700.9), "capacity"), (dict(n_particles=True), "n_particles"),
                     (dict(K=17.0), "K")):
        with pytest.raises(InputError, match=rf"^{name}: expected an int >= 1"):
            P.victoria_park_fastslam_setup(**kw)
    for run in (R.run_mrclam, R.run_victoria_park):  # before the log is read
        with pytest.raises(InputError, match=r"^particles: expected an int >= 1, got 0"):
            run(EXCERPTS, filter="fastslam", particles=0)


# ---------------------------------------------------------------------------------- item 7: rpe_pairs
def test_rpe_pairs_takes_the_partner_nearest_to_t_plus_lag():
    ref = np.zeros((3, 2))
    # 0.95 s is within 1 ± 0.1 s of 0: paired (it lies before t + lag, where the old search never looked)
    assert R.rpe_pairs([0.0, 0.95], [[0, 0], [1, 0]], ref[:2]) == (1.0, 1)
    # with 1.2 s also there, the nearer 0.95 s is the partner, not the first sample after 1 s
    assert R.rpe_pairs([0.0, 0.95, 1.2], [[0, 0], [1, 0], [5, 0]], ref) == (1.0, 1)
    # a tie: the later sample
    assert R.rpe_pairs([0.0, 0.95, 1.05], [[0, 0], [1, 0], [3, 0]], ref) == (3.0, 1)
    # none within the tolerance: (NaN, 0)
    rpe, n = R.rpe_pairs([0.0, 1.5], [[0, 0], [1, 0]], ref[:2])
    assert np.isnan(rpe) and n == 0


@pytest.mark.parametrize("kw, match", [
    (dict(lag_s=0.0), r"^lag_s: expected a positive finite scalar"),
    (dict(lag_s=-1.0), r"^lag_s: expected a positive finite scalar"),
    (dict(tol_s=-0.1), r"^tol_s: expected a non-negative finite scalar"),
    (dict(lag_s=1.0, tol_s=1.0), r"^tol_s: expected less than lag_s"),
    (dict(t=[1.0, 0.0]), r"^t: expected non-decreasing times"),
    (dict(t=[0.0, np.nan]), r"^t: expected finite times"),
    (dict(est=[[0, 0]]), r"^est: expected shape \(2, d\)"),
    (dict(ref=[[0, 0, 0], [0, 0, 0]]), r"^ref: expected shape \(2, 2\)"),
])
def test_rpe_pairs_refuses_bad_arguments(kw, match):
    args = dict(t=[0.0, 1.0], est=[[0, 0], [1, 0]], ref=[[0, 0], [0, 0]])
    args.update(kw)
    with pytest.raises(InputError, match=match):
        R.rpe_pairs(args.pop("t"), args.pop("est"), args.pop("ref"), **args)


# ---------------------------------------------------------------------------------- items 11, 22: evaluate_planar
def _track(n=101):
    t = np.linspace(0.0, 10.0, n)
    return t, np.stack([t, np.sin(t), 0.1 * t], 1)


def test_evaluate_planar_counts_a_nonfinite_estimate():
    t, pose = _track()
    m, _ = R.evaluate_planar(t, pose, t, pose)
    assert "nonfinite_estimate_samples" not in m and m["ate_m"] < 1e-9
    est = pose.copy()
    est[50, 0] = np.nan
    m, _ = R.evaluate_planar(t, est, t, pose)
    assert m["nonfinite_estimate_samples"] == 1 and np.isnan(m["ate_m"])
    m, _ = R.evaluate_planar(t, est, t[::5], pose[::5, :2], at_ref_times=True)
    assert m["nonfinite_estimate_samples"] == 1
    assert R._nonfinite_notes(m) and "NaN or Inf at 1 of the 21" in R._nonfinite_notes(m)[0]


def test_evaluate_planar_at_ref_times_leaves_out_nonfinite_reference_rows():
    t, pose = _track()
    ref = pose[::5, :2].copy()
    ref[3] = np.nan
    m, ev = R.evaluate_planar(t, pose, t[::5], ref, at_ref_times=True)
    assert m["eval_samples"] == 20 and m["ate_m"] < 1e-9
    assert np.all(np.isfinite(ev["ref_xy"]))


@pytest.mark.parametrize("change, match", [
    (dict(ref=np.zeros((101, 4))), r"^ref: expected shape \(101, 2 or 3\)"),
    (dict(ref=np.zeros((101, 1))), r"^ref: expected shape \(101, 2 or 3\)"),
    (dict(ref=np.zeros((100, 2))), r"^ref: expected shape \(101, 2 or 3\)"),
    (dict(t_est=np.linspace(0, 10, 100)), r"^est_pose: expected shape \(100, 2 or 3\)"),
    (dict(dr_pose=np.zeros((100, 3))), r"^dr_pose: expected shape \(101, 2 or 3\)"),
    (dict(lm=np.zeros((3, 3))), r"^lm: expected shape \(N, 2\)"),
    (dict(lm=np.zeros((3, 2)), lm_cov=np.zeros((2, 2, 2))), r"^lm_cov: expected shape \(3, 2, 2\)"),
    (dict(lm=np.zeros((3, 2)), lm_ids=[1, 2]), r"^lm_ids: expected one id per row of lm"),
    (dict(lm_true=np.zeros((3, 3))), r"^lm_true: expected shape \(N, 2\)"),
    (dict(t_ref=np.linspace(10, 0, 101)), r"^t_ref: expected non-decreasing times"),
    (dict(t_est=np.array([]), est_pose=np.zeros((0, 3)), at_ref_times=True),
     r"^t_est: expected at least one estimate time"),
    (dict(at_ref_times="yes"), r"^at_ref_times: expected True or False"),
])
def test_evaluate_planar_refuses_bad_shapes(change, match):
    t, pose = _track()
    args = dict(t_est=t, est_pose=pose, t_ref=t, ref=pose)
    args.update(change)
    with pytest.raises(InputError, match=match):
        R.evaluate_planar(**args)


def test_evaluate_planar_wants_poses_against_a_pose_reference():
    # 2-column positions against (N, 3) poses reached metrics.rpe_se2, whose error named no argument
    t, pose = _track()
    for kw in (dict(), dict(at_ref_times=True)):
        with pytest.raises(InputError, match=r"^est_pose: expected shape \(101, 3\) \(poses: ref holds poses"):
            R.evaluate_planar(t, pose[:, :2], t, pose, **kw)
    # positions against positions, and poses against positions, as before; a 2-column dead
    # reckoning only enters the ATE (its x, y)
    m, _ = R.evaluate_planar(t, pose[:, :2], t, pose[:, :2])
    assert m["ate_m"] < 1e-9
    m, _ = R.evaluate_planar(t, pose, t, pose[:, :2])
    assert m["ate_m"] < 1e-9
    m, _ = R.evaluate_planar(t, pose, t, pose, dr_pose=pose[:, :2])
    assert m["ate_m"] < 1e-9 and m["dead_reckoning_ate_m"] < 1e-9 and m["rpe_m"] < 1e-9


# ---------------------------------------------------------------------------------- items 12, 22: split_ate
@pytest.mark.parametrize("args, match", [
    ((np.nan, "x"), r"^t_cut: expected a finite scalar"),
    ((np.inf, "x"), r"^t_cut: expected a finite scalar"),
    ((1.5, 2), r"^label: expected a str"),
])
def test_split_ate_refuses_a_cut_that_splits_nothing(args, match):
    ev = {"t": np.array([1.0, 2.0]), "est_xy": np.zeros((2, 2)), "ref_xy": np.ones((2, 2))}
    with pytest.raises(InputError, match=match):
        R.split_ate(ev, *args)


def test_split_ate_refuses_mismatched_arrays():
    ev = {"t": np.array([1.0, 2.0]), "est_xy": np.zeros((3, 2)), "ref_xy": np.ones((2, 2))}
    with pytest.raises(InputError, match=r"^ev\['est_xy'\]: expected shape \(2, 2\)"):
        R.split_ate(ev, 1.5, "x")


# ---------------------------------------------------------------------------------- item 10: mrclam_log
@pytest.fixture(scope="module")
def mrclam1():
    return load_mrclam(EXCERPTS, 1)


@pytest.mark.parametrize("rm, match", [
    ((1.0, -100.0), r"^range_model: k0 \+ k2·β² must be positive at every measured bearing"),
    ((0.0, 0.0), r"^range_model: k0 \+ k2·β² must be positive"),
    ((1.0,), r"^range_model: expected two finite numbers \(k0, k2\)"),
    ("ab", r"^range_model: expected two finite numbers"),
    ((1.0, np.nan), r"^range_model: expected two finite numbers"),
])
def test_mrclam_log_refuses_a_range_model_that_breaks_ranges(mrclam1, rm, match):
    with pytest.raises(InputError, match=match):
        P.mrclam_log(mrclam1, range_model=rm)


def test_mrclam_log_checks_its_numbers(mrclam1):
    with pytest.raises(InputError, match=r"^odometry_delay: expected a finite scalar"):
        P.mrclam_raw_log(mrclam1, odometry_delay="x")
    with pytest.raises(InputError, match=r"^K: expected an int >= 1"):
        P.mrclam_log(mrclam1, K=2.5)
    log, pose0 = P.mrclam_log(mrclam1)  # the shipped model passes
    assert np.all(log.z[..., 0][log.mask] > 0) and pose0.shape == (3,)


def test_mrclam_log_takes_an_infinite_end(mrclam1):
    # t_end=+inf is an open end, as before this session (refused by its first check_scalar)
    log, _ = P.mrclam_raw_log(mrclam1, t_end=np.inf)
    assert log.t[-1] == max(mrclam1.odom_t[-1], mrclam1.meas_t[-1]) and log.stats["outside_window"] == 0
    with pytest.raises(InputError, match=r"^t_end: expected a time \[s\] \(None or \+inf"):
        P.mrclam_raw_log(mrclam1, t_end=-np.inf)
    with pytest.raises(InputError, match=r"^t_end: expected a number, got nan"):
        P.mrclam_raw_log(mrclam1, t_end=np.nan)


# ---------------------------------------------------------------------------------- items 15-18: --params objects, robot
def test_params_object_checked_before_its_log_entries():
    with pytest.raises(InputError, match=r"^--params: expected a JSON object, got str"):
        R.run_dataset("mrclam", EXCERPTS, params="x.json")
    with pytest.raises(InputError, match=r"^--params: expected a JSON object, got NoneType"):
        R.dataset_log_options(None, "mrclam")


@pytest.mark.parametrize("robot", ["1", None, 1.0, 0, 6, True])
def test_mrclam_robot_must_be_an_int_in_range(robot):
    with pytest.raises(InputError, match=r"^mrclam: --robot must be 1\.\.5"):
        R.run_mrclam(EXCERPTS, robot=robot)


@pytest.mark.parametrize("robot", [True, 1.0, "1", 3])
def test_plaza_robot_must_be_1_or_2(robot):
    with pytest.raises(InputError, match=r"^plaza: --robot selects the sequence, 1 or 2"):
        R.run_plaza_dataset(EXCERPTS, robot=robot)


@pytest.mark.parametrize("name", ["mrclam", "victoria-park"])
@pytest.mark.parametrize("noise, match", [
    ({"gate": -1}, r"noise\.gate"),
    ({"range_model": "x"}, r"noise\.range_model"),
    ({"robust_nu": -1}, r"noise\.robust_nu"),
    ({"calib0": "abc"}, r"noise\.calib0"),
    ({"calib0": [1.0, 2.0]}, r"noise\.calib0"),
    ({"gate": "abc"}, r"noise\.gate: expected a number"),  # (named params.gate before)
    ({"monitor": {"alpha": "abc"}}, r"noise\.monitor\.alpha: expected a number"),  # (a bare ValueError)
    ({"monitor": {"alpha": [0.1, 0.2]}}, r"noise\.monitor\.alpha: expected a number"),  # (a TypeError)
])
def test_ekf_params_values_checked_before_the_log(name, noise, match):
    with pytest.raises(InputError, match=r"^--params: " + match):
        R.dataset_params({"dataset": name, "noise": noise}, name)


def test_mixed_type_keys_are_named_not_a_sort_error():
    with pytest.raises(InputError, match=r"^--params: noise: unknown key\(s\) \[1, 'x'\]"):
        P.util_params_from_dict({1: 0.1, "x": 2})
    with pytest.raises(InputError, match=r"^--params: noise: unknown key\(s\) \[1, 'x'\]"):
        R.dataset_params({"dataset": "mrclam", "noise": {1: 0.1, "x": 2}}, "mrclam")
    with pytest.raises(InputError, match=r"^--params: unknown key\(s\) \[1, 'x'\]"):
        R.dataset_params({"dataset": "mrclam", "noise": {}, 1: 2, "x": 1}, "mrclam")
    with pytest.raises(InputError, match=r"^--params: log: unknown key\(s\) \[1, 'x'\]"):
        R.dataset_log_options({"log": {1: 2, "x": 1}}, "mrclam")


# ---------------------------------------------------------------------------------- items 19, 24: range-only --params
@pytest.mark.parametrize("offsets", [["a"], [True, False], [0.1, True], "0.1"])
def test_anchor_offset_must_be_numbers(offsets):
    with pytest.raises(InputError, match=r"^--params: noise\.anchor_offset: expected a list of finite offsets"):
        P.util_params_from_dict({"anchor_offset": offsets})


def test_numpy_numbers_and_zero_densities_read_back():
    p = P.util_params_from_dict({"sigma_r": np.float32(0.25), "q_acc": np.int64(1), "q_bias": 0.0})
    assert (p.sigma_r, p.q_acc, p.q_bias) == (pytest.approx(0.25), 1.0, 0.0)
    # a Params the run accepts (densities and spreads may be 0) survives the --params round trip
    up = P.util_params()._replace(q_acc=0.0, q_bias=0.0)
    assert P.util_params_from_dict(P.util_params_to_dict(up)) == up
    pp = P.plaza_params()._replace(q_bias=0.0, alpha_d=0.0, min_spread=0.0, sigma_d0=0.0)
    assert P.plaza_params_from_dict(P.plaza_params_to_dict(pp)) == pp
    with pytest.raises(InputError, match=r"^--params: noise\.q_bias: expected a non-negative number"):
        P.util_params_from_dict({"q_bias": -1e-5})
    with pytest.raises(InputError, match=r"^--params: noise\.sigma_r: expected a positive number"):
        P.util_params_from_dict({"sigma_r": 0.0})
    with pytest.raises(InputError, match=r"^--params: noise\.sigma_r: expected a finite number"):
        P.util_params_from_dict({"sigma_r": np.bool_(True)})


# ---------------------------------------------------------------------------------- item 25: presets, timed_run
def test_fitted_mrclam_params_do_not_read_robot():
    # the docstring: with preset="fitted" ``robot`` is not read (robot=None was refused this session)
    ref = P.mrclam_params(1)
    for robot in (None, "x"):
        got = P.mrclam_params(robot)
        assert all(np.array_equal(a, b) for a, b in zip(got, ref))
    got = P.mrclam_params(None, corrected=True)
    assert np.allclose(np.diag(got.R), np.square(P.MRCLAM_CORRECTED_SIGMA) * 4.0)


def test_preset_arguments_are_checked():
    with pytest.raises(InputError, match=r"^robot: expected an int >= 1, got 'x'"):
        P.mrclam_params("x", preset="hand")
    with pytest.raises(InputError, match=r"^robot: expected an int >= 1, got 'x'"):
        P.mrclam_raw_sigma("x")
    with pytest.raises(InputError, match=r"^robot: expected an int >= 1, got 1\.9"):
        P.mrclam_raw_sigma(1.9)
    assert P.mrclam_raw_sigma(np.int64(1)) == P.mrclam_raw_sigma(1) != P.mrclam_raw_sigma(2)
    assert P.mrclam_raw_sigma(3) == P.mrclam_raw_sigma(2)  # no figure of its own: robot 2's
    with pytest.raises(InputError, match=r"^datas: expected one or more MRCLAM logs"):
        P.mrclam_layout([])
    with pytest.raises(InputError, match=r"^fn: expected a callable"):
        R.timed_run(5)
    with pytest.raises(InputError, match=r"^twice: expected True or False"):
        R.timed_run(lambda: 1, twice="no")
