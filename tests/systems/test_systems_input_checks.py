"""Bad input to the systems' run functions and the controllers, named before anything compiles.

Each case was found by a probe of the public API (2026-12-06): before, it ran silently
(a negative σ as its absolute value, a repeated anchor id losing that anchor's ranges
uncounted, a negative dt running backwards) or failed deep inside JAX.  The expected messages
are written by hand; the well-formed call beside each shows the check does not refuse it.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam.control import lqr, smc
from jaxslam.data import presets
from jaxslam.errors import InputError
from jaxslam.systems import planar_fastslam as pf
from jaxslam.systems import plaza_range as pr
from jaxslam.systems import util_range as ur

ANCHORS = np.array([[-3.0, -4.0, 0.2], [-3.2, 3.8, 2.9], [3.7, 3.7, 0.2], [4.1, -4.3, 3.2]])
T = 40


def _util_log(aid=np.arange(4), ids=None):
    t = np.arange(T) * 0.01
    ids = np.arange(T) % 4 if ids is None else ids
    r = np.linalg.norm(ANCHORS[np.arange(T) % 4], axis=1)
    return ur.log_from_events(ur.util_events(t, ids, r), aid, anchors=ANCHORS, dtype=jnp.float64)


def test_util_range_names_bad_params_ids_and_anchors():
    cfg = ur.Config(height=False, n_fix=4)
    ref = ur.run(_util_log(), cfg, ur.PARAMS)
    assert int(ref.n_unmapped) == 0
    for change, msg in [(dict(sigma_r=-1.0), r"^params\.sigma_r: expected a positive finite scalar"),
                        (dict(sigma_r=0.0), r"^params\.sigma_r: expected a positive"),
                        (dict(q_acc=float("nan")), r"^params\.q_acc: expected a non-negative finite scalar"),
                        (dict(gate=-1.0), r"^params\.gate: expected a positive")]:
        with pytest.raises(InputError, match=msg):
            ur.run(_util_log(), cfg, ur.PARAMS._replace(**change))
    with pytest.raises(InputError, match=r"^log\.anchor_ids: repeated id\(s\) \[0\]"):
        ur.run(_util_log(aid=np.array([0, 1, 2, 0])), cfg, ur.PARAMS)
    bad = _util_log()
    with pytest.raises(InputError, match=r"^log\.anchors: contains NaN or Inf"):
        ur.run(bad._replace(anchors=jnp.asarray(ANCHORS).at[1, 0].set(jnp.nan)), cfg, ur.PARAMS)
    with pytest.raises(InputError, match=r"^config\.n_fix: expected an int"):
        ur.run(_util_log(), cfg._replace(n_fix=0), ur.PARAMS)
    # a range to an id that is no anchor of the log is never used, and now counted
    ids = np.arange(T) % 4
    ids[7] = 99
    res = ur.run(_util_log(ids=ids), cfg, ur.PARAMS)
    assert int(res.n_unmapped) == 1 and int(res.n_used) == int(ref.n_used) - 1


def test_plaza_range_names_bad_params_positions_and_ids():
    t = np.arange(1, 31) * 0.2
    u = np.tile([0.2, 0.01], (30, 1))
    beacons = np.array([[5.0, 0.0], [0.0, 5.0], [-5.0, 0.0]])
    t_r, node = t[::3], np.array([10, 11, 12] * 4)[:10]
    rr = np.linalg.norm(beacons[np.arange(10) % 3], axis=1)
    ev = pr.plaza_events(t, u, t_r, node, rr)
    bids = np.array([10, 11, 12])

    def log(pose0=np.zeros(3), bids=bids, **kw):
        return pr.log_from_events(ev, pose0, bids, beacons=kw.get("beacons", beacons), dtype=jnp.float64)

    pr.run(log(), pr.Config(), pr.PARAMS)
    with pytest.raises(InputError, match=r"^params\.sigma_r: expected a positive"):
        pr.run(log(), pr.Config(), pr.PARAMS._replace(sigma_r=-1.2))  # ran as +1.2 before
    with pytest.raises(InputError, match=r"^params\.alpha_d: expected a non-negative finite"):
        pr.run(log(), pr.Config(), pr.PARAMS._replace(alpha_d=float("nan")))
    with pytest.raises(InputError, match=r"^log\.pose0: contains NaN or Inf"):
        pr.run(log(pose0=np.array([np.nan, 0.0, 0.0])), pr.Config(), pr.PARAMS)
    with pytest.raises(InputError, match=r"^log\.beacons: contains NaN or Inf"):
        pr.run(log(beacons=np.array([[np.nan, 0.0], [0.0, 5.0], [-5.0, 0.0]])), pr.Config(), pr.PARAMS)
    with pytest.raises(InputError, match=r"^log\.beacon_ids: repeated id\(s\) \[10\]"):
        pr.run(log(bids=np.array([10, 11, 10])), pr.Config(), pr.PARAMS)
    with pytest.raises(InputError, match=r"^config\.window: expected an int"):
        pr.run(log(), pr.Config(window=0), pr.PARAMS)


def test_planar_fastslam_checks_what_the_planar_ekf_checks():
    cfg, prm = presets.mrclam_fastslam_setup(n_particles=4)
    K = int(cfg.K)
    n = 6
    log = pf.Log(dt=np.full(n, 0.1), u=np.tile([0.1, 0.0], (n, 1)), z=np.full((n, K, 2), np.nan),
                 ids=np.zeros((n, K), np.int32), mask=np.zeros((n, K), bool), pose0=np.zeros(3),
                 is_input=None)
    key = jax.random.PRNGKey(0)
    pf.run(log, cfg, prm, key=key)
    dt = log.dt.copy()
    dt[3] = -1.0  # ran backwards, unflagged
    with pytest.raises(InputError, match=r"^log\.dt: must be finite and >= 0"):
        pf.run(log._replace(dt=dt), cfg, prm, key=key)
    with pytest.raises(InputError, match=r"^log\.pose0: contains NaN or Inf"):
        pf.run(log._replace(pose0=np.array([np.nan, 0.0, 0.0])), cfg, prm, key=key)
    with pytest.raises(InputError, match=r"^params\.P0: not positive semi-definite"):
        pf.run(log, cfg, prm._replace(P0=-np.eye(3)), key=key)  # every pose NaN before
    with pytest.raises(InputError, match=r"^params\.R: not positive definite"):
        pf.run(log, cfg, prm._replace(R=np.zeros((2, 2))), key=key)
    with pytest.raises(InputError, match=r"^key: expected a PRNG key"):
        pf.run(log, cfg, prm, key=0)


def test_lqr_and_smc_name_bad_weights_shapes_and_eps():
    A = np.array([[0.0, 1.0], [0.0, 0.0]])
    B = np.array([[0.0], [1.0]])
    K, P = lqr.lqr_gain(A, B, np.eye(2), np.eye(1))
    assert np.all(np.isfinite(np.asarray(K)))
    with pytest.raises(InputError, match=r"^Q: contains NaN or Inf"):
        lqr.lqr_gain(A, B, np.full((2, 2), np.nan), np.eye(1))  # gave K = 0, P = 0 before
    with pytest.raises(InputError, match=r"^R: not positive definite"):
        lqr.lqr_gain(A, B, np.eye(2), -np.eye(1))
    with pytest.raises(InputError, match=r"^Q: expected shape \(2, 2\)"):
        lqr.care(A, B, np.eye(3), np.eye(1))
    with pytest.raises(InputError, match=r"^B: expected shape \(2, m\)"):
        lqr.care(A, B.T, np.eye(2), np.eye(1))
    with pytest.raises(InputError, match=r"^A, C: expected two square matrices of one size"):
        lqr.lyapunov(np.zeros((2, 3)), np.eye(2))
    # under jit the weights are traced: only shapes are checked, the status speaks
    K_j, _, ok = jax.jit(lambda Q: lqr.lqr_gain(A, B, Q, np.eye(1), return_status=True))(jnp.eye(2))
    np.testing.assert_allclose(np.asarray(K_j), np.asarray(K), rtol=1e-12)
    gains = smc.SMCGains(jnp.ones((3, 6)), jnp.ones((3, 6)))
    q = jnp.array([1.0, 0.0, 0.0, 0.0])
    args = (q, jnp.zeros(3), q, gains, jnp.array([0.01, 0.01, 0.02]))
    smc.control(*args, eps=0.5)
    with pytest.raises(InputError, match=r"^eps: expected a finite positive scalar"):
        smc.control(*args, eps=0.0)  # a NaN torque before
    # closed_loop is jitted (its numbers are traced): its static options are named (a KeyError before)
    with pytest.raises(InputError, match=r"^perturbation: expected one of"):
        smc.closed_loop(jnp.concatenate([q, jnp.zeros(3)]), q, gains, jnp.array([0.01, 0.01, 0.02]), 0.01, 3,
                        jax.random.PRNGKey(0), (0.1, 0.1), perturbation_name="gusts")


def test_event_builders_name_a_nan_window_and_ragged_rows():
    t = np.arange(10) * 0.1
    r = np.ones(10)
    ur.util_events(t, np.arange(10) % 4, r, t_start=0.2, t_end=0.7)
    for lo, hi in ((float("nan"), 0.5), (0.2, float("nan"))):  # kept no event before: zeros, degenerate
        with pytest.raises(InputError, match=r"^t_start, t_end: expected numbers"):
            ur.util_events(t, np.arange(10) % 4, r, t_start=lo, t_end=hi)
    with pytest.raises(InputError, match=r"^util_events: t, anchor_id and ranges need one entry per range"):
        ur.util_events(t, np.arange(10) % 4, r[:-1], tof_t=t, tof=r)  # an IndexError before


def test_event_ids_must_be_whole_numbers_and_uwb_config_sizes_positive():
    from jaxslam.data.events import merge_events
    from jaxslam.systems import uwb_slam_2d as U

    t = np.arange(4) * 0.1
    merge_events(t, np.zeros((4, 1)), t, np.ones((4, 1)), meas_ids=np.array([1.0, 2.0, 3.0, 1.0]))
    with pytest.raises(InputError, match=r"^meas_ids: expected whole-number ids"):
        merge_events(t, np.zeros((4, 1)), t, np.ones((4, 1)), meas_ids=np.array([1.0, 2.5, 3.0, 1.0]))
    for change, msg in [(dict(buffer_size=0), r"^config\.buffer_size: expected an int"),
                        (dict(buffer_stride=0), r"^config\.buffer_stride: expected an int"),
                        (dict(dt=float("nan")), r"^config\.dt: expected a positive"),
                        (dict(dt=0.0), r"^config\.dt: expected a positive")]:
        with pytest.raises(InputError, match=msg):
            U._check(None, U.Config()._replace(**change), None)  # config is checked first


# --- a third probe (2026-12-06): logs only partly checked, empty logs, negative gates ---

def _plaza_log(T_=6, **kw):
    d = dict(t=np.arange(T_) * 0.1, dt=np.full(T_, 0.1), u=np.tile([0.1, 0.0], (T_, 1)),
             z=np.tile([[[10.0], [14.0]]], (T_, 1, 1)), ids=np.tile([0, 1], (T_, 1)), mask=np.ones((T_, 2), bool),
             pose0=np.zeros(3), beacon_ids=np.array([0, 1, 2]), beacons=np.array([[10.0, 0], [0, 10.0], [-10.0, 0]]))
    d.update(kw)
    return pr.Log(**d)


def _range_log_cases(T_):
    """(change, message) pairs for a range-only log of T_ events (ids one row too many, mask one too few:
    a (T, 1) mask used to broadcast silently)."""
    return [(lambda lg: lg._replace(dt=np.full(T_, -0.1)), r"^log\.dt: must be finite and >= 0"),
            (lambda lg: lg._replace(dt=np.zeros(0), t=np.zeros(0), z=lg.z[:0], ids=lg.ids[:0], mask=lg.mask[:0],
                                    **({"u": lg.u[:0]} if hasattr(lg, "u") else {})),
             r"^log\.dt: expected at least one event"),
            (lambda lg: lg._replace(dt=lg.dt[:-1]), rf"^log\.dt: expected shape \({T_},\)"),
            (lambda lg: lg._replace(ids=np.zeros((T_, lg.z.shape[1] + 1), int)), rf"^log\.ids: expected shape \({T_}, "),
            (lambda lg: lg._replace(mask=np.ones((T_, lg.z.shape[1] - 1), bool)), rf"^log\.mask: expected shape \({T_}, "),
            (lambda lg: lg._replace(z=np.asarray(lg.z).astype(int)), r"^log\.z: expected floating ranges"),
            (lambda lg: lg._replace(ids=np.asarray(lg.ids) + 0.5), r"^log\.ids: expected whole-number"),
            # the event times the run reports and is scored at (a step back misplaced them, silently)
            (lambda lg: lg._replace(t=np.asarray(lg.t)[::-1].copy()), r"^log\.t: time decreases at index 1"),
            (lambda lg: lg._replace(t=np.where(np.arange(T_) == 2, np.nan, lg.t)), r"^log\.t: non-finite time at index 2")]


@pytest.mark.parametrize("k", range(9))
def test_plaza_and_util_range_check_the_whole_log(k):
    change, msg = _range_log_cases(6)[k]
    with pytest.raises(InputError, match=msg):  # each failed inside the scan, or ran silently
        pr.run(change(_plaza_log()))
    change, msg = _range_log_cases(T)[k]
    with pytest.raises(InputError, match=msg):
        ur.run(change(_util_log()), ur.Config(height=False, n_fix=4), ur.PARAMS)


def test_plaza_and_util_range_name_ids_u_and_a_negative_outlier_gate():
    with pytest.raises(InputError, match=r"^log\.u: expected shape \(6, 2\)"):
        pr.run(_plaza_log(u=np.zeros((5, 2))))
    with pytest.raises(InputError, match=r"^log\.beacon_ids: expected shape \(N,\)"):  # named log.beacons before
        pr.run(_plaza_log(beacon_ids=np.array([[0, 1, 2]])))
    with pytest.raises(InputError, match=r"^log\.beacon_ids: expected whole-number"):
        pr.run(_plaza_log(beacon_ids=np.array([0.0, 1.0, 2.5])))
    with pytest.raises(InputError, match=r"^params\.outlier_gate: expected a scalar >= 0"):  # DIVERGED before
        pr.run(_plaza_log(), params=pr.PARAMS._replace(outlier_gate=-1.0))
    with pytest.raises(InputError, match=r"^params\.outlier_gate: expected a scalar >= 0"):
        ur.run(_util_log(), ur.Config(height=False, n_fix=4), ur.PARAMS._replace(outlier_gate=-1.0))
    with pytest.raises(InputError, match=r"^params\.anchor_offset: contains NaN or Inf"):
        ur.run(_util_log(), ur.Config(height=False, n_fix=4),
               ur.PARAMS._replace(anchor_offset=np.array([np.nan, 0.0, 0.0, 0.0])))


def _planar_log(T_=6, **kw):
    from jaxslam.systems import planar_ekf_slam as pe

    d = dict(dt=np.full(T_, 0.1), u=np.tile([1.0, 0.1], (T_, 1)), z=np.tile([[5.0, 0.3], [4.0, -0.2]], (T_, 1, 1)),
             ids=np.tile(np.array([0, 1], np.int32), (T_, 1)), mask=np.ones((T_, 2), bool), pose0=np.zeros(3))
    d.update(kw)
    return pe.Log(**d)


EMPTY = dict(dt=np.zeros(0), u=np.zeros((0, 2)), z=np.zeros((0, 2, 2)), ids=np.zeros((0, 2), np.int32),
             mask=np.zeros((0, 2), bool))


def test_planar_ekf_slam_names_an_empty_log_a_negative_gate_and_takes_an_integer_pose0():
    from jaxslam.systems import planar_ekf_slam as pe

    cfg = pe.Config(capacity=4)
    prm = pe.Params(M_c=0.01 * np.eye(2), Q_floor=1e-4 * np.eye(3), R=np.diag([0.1, 0.01]), P0=1e-3 * np.eye(3))
    with pytest.raises(InputError, match=r"^log\.dt: expected at least one event"):  # an IndexError before
        pe.run(_planar_log(**EMPTY), cfg, prm)
    with pytest.raises(InputError, match=r"^params\.update_gate: need > 0"):  # every row GATED before
        pe.run(_planar_log(), cfg, prm._replace(update_gate=-1.0))
    with pytest.raises(InputError, match=r"^log\.ids: expected whole-number"):
        pe.run(_planar_log(ids=np.tile([0.5, 1.5], (6, 1))), cfg, prm)
    # an integer start pose runs in the default float dtype (a scan carry type error before)
    a = pe.run(_planar_log(pose0=np.zeros(3, int)), cfg, prm)
    b = pe.run(_planar_log(pose0=np.zeros(3)), cfg, prm)
    np.testing.assert_array_equal(np.asarray(a.pose), np.asarray(b.pose))


def test_planar_fastslam_names_an_empty_log_a_negative_gate_and_its_resample_fraction():
    cfg = pf.Config(n_particles=8, capacity=4, K=2)
    prm = pf.Params(M_c=0.01 * np.eye(2), pose_floor=1e-4 * np.ones(3), R=np.diag([0.1, 0.01]), P0=1e-3 * np.eye(3),
                    log_p_new=0.0)
    key = jax.random.PRNGKey(0)
    with pytest.raises(InputError, match=r"^log\.dt: expected at least one event"):
        pf.run(_planar_log(**EMPTY), cfg, prm, key=key)
    with pytest.raises(InputError, match=r"^params\.gate: need > 0"):  # status 68 before
        pf.run(_planar_log(), cfg, prm._replace(gate=-1.0), key=key)
    for thr in (5.0, -1.0, 0.0):
        with pytest.raises(InputError, match=r"^params\.resample_threshold: expected None or a fraction in \(0, 1\]"):
            pf.run(_planar_log(), cfg, prm._replace(resample_threshold=thr), key=key)


def test_planar_fastslam_names_a_non_finite_log_p_new_and_non_integer_sizes():
    """Left open before: a NaN log_p_new made every weight NaN; a float size was truncated
    (capacity 16.5 -> 16, n_particles True -> 1 particle)."""
    cfg = pf.Config(n_particles=8, capacity=4, K=2)
    prm = pf.Params(M_c=0.01 * np.eye(2), pose_floor=1e-4 * np.ones(3), R=np.diag([0.1, 0.01]), P0=1e-3 * np.eye(3),
                    log_p_new=0.0)
    key = jax.random.PRNGKey(0)
    for bad in (np.nan, np.inf, -np.inf):
        with pytest.raises(InputError, match=r"^params\.log_p_new: expected a finite scalar"):
            pf.run(_planar_log(), cfg, prm._replace(log_p_new=bad), key=key)
    for field, bad in (("capacity", 4.5), ("capacity", 4.0), ("n_particles", True), ("K", 2.0), ("n_particles", 0)):
        with pytest.raises(InputError, match=rf"^config\.{field}: expected an int"):
            pf.run(_planar_log(), cfg._replace(**{field: bad}), prm, key=key)


def _e3_case(e3, F, L):
    """A tiny valid ekf_slam_3d (log, params, config): F frames of L landmarks, still and level."""
    log = e3.Log(s0=np.zeros(9), imu=np.tile([0.0, 0, -9.81, 0, 0, 0], (2 * F + 1, 1)),
                 y=np.tile([[0.1, 0.1, 5.0], [0.2, -0.1, 6.0]], (F, 1, 1)), visible=np.ones((F, L), bool),
                 ids=np.arange(L, dtype=np.int32))
    prm = e3.Params(P0=1e-3 * np.eye(9), Qc=1e-4 * np.eye(9), Qimu=1e-4 * np.eye(6), R=1e-4 * np.eye(3))
    return log, prm, e3.Config(capacity=4, max_obs=2)


@pytest.mark.parametrize("change, msg", [
    (dict(dt=0.0), r"^config\.dt: expected a positive finite scalar"),  # the estimate froze
    (dict(dt=-0.01), r"^config\.dt: expected a positive finite scalar"),  # ran backwards
    (dict(g=float("nan")), r"^config\.g: expected a finite scalar"),
    (dict(capacity=0), r"^config\.capacity: expected an int"),
    (dict(max_obs=0), r"^config\.max_obs: expected an int"),  # named z before
    (dict(accel_mode="AZ"), r"^config\.accel_mode: expected '3axis' or 'az', got 'AZ'"),  # ran "3axis"
    ("s0", r"^log\.s0: contains NaN or Inf"),  # all-NaN means before
    ("nn", r"^params\.nn_new: need nn_gate <= nn_new"),
])
def test_ekf_slam_3d_names_bad_config_start_and_association_thresholds(change, msg):
    from jaxslam.systems import ekf_slam_3d as e3

    F, L = 3, 2
    log, prm, cfg = _e3_case(e3, F, L)
    if change == "s0":
        log = log._replace(s0=np.full(9, np.nan))
    elif change == "nn":
        cfg, prm = cfg._replace(association="nn"), prm._replace(nn_gate=30.0, nn_new=1.0)
    else:
        cfg = cfg._replace(**change)
    with pytest.raises(InputError, match=msg):
        e3.run(log, cfg, prm)


# --- a fifth probe (2026-12-06): line SLAM 004, UWB SLAM 2D and FastSLAM 001 ---

def _ls_log(T_=3, **kw):
    from jaxslam.systems import line_slam_004 as LS

    n = LS.Config().spec.n_beams
    d = dict(ranges=np.ones((T_, n)), valid=np.ones((T_, n), bool), tilt=np.zeros((T_, 2)),
             flow=np.zeros((T_, 2)), gyro=np.zeros(T_), s0=np.zeros(6))
    d.update(kw)
    return LS.Log(**d)


@pytest.mark.parametrize("change, msg", [
    ("empty", r"^log\.ranges: expected shape \(T, 682\)"),
    (dict(flow=np.zeros((2, 2))), r"^log\.flow: expected shape \(3, 2\)"),  # one step short
    (dict(tilt=np.zeros((2, 3))), r"^log\.tilt: expected shape \(3, 2\)"),  # transposed
    (dict(s0=["a"] * 6), r"^log\.s0: expected numbers"),  # a TypeError deep in JAX before
    (dict(tilt=np.full((3, 2), np.nan)), r"^log\.tilt: contains NaN or Inf"),  # nothing mapped, status 0
    (dict(s0=np.full(6, np.inf)), r"^log\.s0: contains non-finite"),
    ("dt-", r"^config\.dt: expected a positive finite scalar"),  # named params.Q before
    ("dt0", r"^config\.dt: expected a positive finite scalar"),
    ("cap", r"^config\.capacity: expected an int >= 1"),  # named "capacity:" before
    ("Q", r"^params\.Q: expected shape \(6, 6\)"),
    ("gate", r"^params\.nis_gate: expected a non-negative finite scalar"),
])
def test_line_slam_004_names_bad_logs_config_and_params(change, msg):
    from jaxslam.systems import line_slam_004 as LS

    log, cfg, prm = _ls_log(), LS.Config(), None
    if change == "empty":
        log = _ls_log(0)
    elif change in ("dt-", "dt0"):
        cfg = cfg._replace(dt=-0.1 if change == "dt-" else 0.0)
    elif change == "cap":
        cfg = cfg._replace(capacity="4")
    elif change == "Q":
        prm = LS.default_params()._replace(Q=jnp.eye(5))
    elif change == "gate":
        prm = LS.default_params()._replace(nis_gate=-1.0)
    else:
        log = log._replace(**change)
    with pytest.raises(InputError, match=msg):
        LS.run(log, cfg, prm, key=jax.random.PRNGKey(0))
    if isinstance(change, dict) and "tilt" in change and change["tilt"].shape == (3, 2):
        with pytest.raises(InputError, match=msg):
            LS.validate_log(log)


def test_line_slam_004_takes_an_integer_start_state_as_float():
    """An integer s0 made the run's dtype integer: the default P0 and R_odo became 0 and the
    run was refused naming params.R_odo."""
    from jaxslam.systems import line_slam_004 as LS

    out = jax.eval_shape(lambda: LS.run(_ls_log(2, s0=np.zeros(6, int)), key=jax.random.PRNGKey(0)))
    assert out.steps.mean.dtype == jnp.float64


_UA = np.array([[0.0, 0.0], [5.0, 0.0], [2.0, 4.0], [3.0, -4.0]])


def _uwb_log(T_=4, **kw):
    from jaxslam.systems import uwb_slam_2d as U

    ps = np.stack([np.linspace(0.2, 5, 6), np.zeros(6)], 1)
    pr_ = np.stack([np.linspace(5, 6, T_ + 1)[1:], np.linspace(0, 1, T_ + 1)[1:]], 1)
    d = dict(startup_ranges=np.linalg.norm(ps[:, None] - _UA[None], axis=-1), startup_mask=np.ones((6, 4), bool),
             ranges=np.linalg.norm(pr_[:, None] - _UA[None], axis=-1), range_mask=np.ones((T_, 4), bool),
             gyro=np.zeros((T_, 3)))
    d.update(kw)
    return U.Log(**d)


@pytest.mark.parametrize("change, msg", [
    ("empty", r"^log\.ranges: expected at least one step, got an empty log \(T = 0\)"),  # IndexError
    (dict(gyro=np.zeros((3, 3))), r"^log\.gyro: expected shape \(4, 3\)"),
    (dict(range_mask=np.full((4, 4), 0.5)), r"^log\.range_mask: expected a bool mask"),  # TypeError
    (dict(ranges=np.full((4, 4), "a")), r"^log\.ranges: expected numbers"),  # TypeError in JAX
    ("anchors", r"^log\.anchors: expected numbers"),  # NumPy's bare ValueError
    ("start", r"^config\.start_anchor: expected an int >= 0"),  # a float indexer failed deep
    ("Q", r"^params\.Q: expected numbers"),  # was "expected shape (10, 10), got ()"
    ("gate", r"^params\.gate: expected a non-negative finite scalar"),
])
def test_uwb_slam_2d_names_bad_logs_config_and_params(change, msg):
    from jaxslam.systems import uwb_slam_2d as U

    log, cfg, prm = _uwb_log(), U.Config(), None
    if change == "empty":
        log = _uwb_log(0)
    elif change == "anchors":
        log, cfg = log._replace(anchors=[["a", "b"]] * 4), cfg._replace(mode="localization")
    elif change == "start":
        cfg = cfg._replace(start_anchor=0.5)
    elif change == "Q":
        prm = U.paper_params()._replace(Q="x")
    elif change == "gate":
        prm = U.paper_params()._replace(gate=-1.0)
    else:
        log = log._replace(**change)
    with pytest.raises(InputError, match=msg):
        U.run(log, cfg, prm)
    if prm is None:
        with pytest.raises(InputError, match=msg):
            U.validate_log(log, cfg)


def test_uwb_slam_2d_validate_log_passes_the_small_valid_log():
    from jaxslam.systems import uwb_slam_2d as U

    U.validate_log(_uwb_log(), U.Config())
    U.validate_log(_uwb_log(anchors=_UA.astype(int)), U.Config(mode="localization"))


def _fs1_log(F=2, E=2, L=2, **kw):
    from jaxslam.systems import fastslam_001 as fs1

    T_ = F * E
    d = dict(x0=np.zeros(12), rotor_w=np.full((T_, 4), 400.0), imu=np.tile([0, 0, 9.81, 0, 0, 0.0], (T_, 1)),
             z=np.tile(np.array([[0.3, 0.1, 5.0], [-0.5, 0.2, 4.0]]), (F, 1, 1)), ids=np.arange(L),
             mask=np.ones((F, L), bool))
    d.update(kw)
    return fs1.Log(**d)


@pytest.mark.parametrize("change, msg", [
    ("empty", r"^log\.z: expected at least one LiDAR frame"),  # an IndexError before
    (dict(rotor_w=np.zeros((3, 4))), r"^log\.rotor_w: expected shape \(4, 4\)"),
    (dict(ids=np.array([0.0, 1.5])), r"^log\.ids: expected whole-number landmark ids"),  # truncated to 1
    (dict(mask=np.full((2, 2), 0.5)), r"^log\.mask: expected a bool mask"),  # read as True
    (dict(rotor_w=np.full((4, 4), np.nan)), r"^log\.rotor_w: contains NaN or Inf"),  # NaN poses
    (dict(x0=["a"] * 12), r"^log\.x0: expected numbers"),  # a TypeError in NumPy
    (dict(rotor_w=np.full((4, 4), "a")), r"^log\.rotor_w: expected numbers"),  # a TypeError in jit
    (dict(capacity=4.5), r"^config\.capacity: expected an int >= 1"),  # truncated to 4
    (dict(lidar_every=2.0), r"^config\.lidar_every: expected an int >= 1"),
    (dict(dt="x"), r"^config\.dt: must be a positive number of seconds"),  # NumPy's ValueError
    ("soft", r"^params\.soft_alpha: expected a value in \[0, 1\]"),  # NumPy's ValueError
    ("thr", r"^params\.resample_threshold: expected None or a fraction"),
])
def test_fastslam_001_names_bad_logs_config_and_params(change, msg):
    from jaxslam.systems import fastslam_001 as fs1

    log, cfg, prm = _fs1_log(), fs1.Config(n_particles=8, lidar_every=2), fs1.default_params()
    if change == "empty":
        log = _fs1_log(F=0)
    elif change == "soft":
        prm = prm._replace(soft_alpha="x")
    elif change == "thr":
        prm = prm._replace(resample_threshold="x")
    elif any(k in change for k in fs1.Config._fields):
        cfg = cfg._replace(**change)
    else:
        log = log._replace(**change)
    with pytest.raises(InputError, match=msg):
        fs1.run(log, cfg, prm, key=jax.random.PRNGKey(0))


def test_fastslam_001_checks_pass_a_small_valid_log():
    from jaxslam.systems import fastslam_001 as fs1

    cfg = fs1.Config(n_particles=8, lidar_every=2)
    fs1.validate_config(cfg)
    fs1.validate_params_001(fs1.default_params())
    for log in (_fs1_log(), _fs1_log(ids=np.array([0.0, 1.0]), x0=np.zeros(12, int)),
                _fs1_log(ids=np.array([0.0, 1.5]), mask=np.array([[True, False]] * 2))):  # unused row
        fs1._check_log(log, cfg)


def test_range_model_and_update_name_a_bad_argument():
    from jaxslam.systems import biased_range as br

    s = jnp.array([1.0, 2.0, 0.0, 0.0, 0.1])  # position (2), velocity (2), bias
    np.testing.assert_allclose(np.asarray(br.range_observe(s, jnp.array([4.0, 6.0]))), [5.1])
    np.testing.assert_allclose(np.asarray(br.range_observe(list(s), [4.0, 6.0])), [5.1])  # lists read
    for s_bad, l_bad, needle in ((s, jnp.array(4.0), r"^l: expected a landmark position of shape \(d,\)"),
                                 (s[:2], jnp.array([4.0, 6.0]), r"^s: expected a state of shape \(n,\) with n >= d \+ 1 = 3")):
        with pytest.raises(InputError, match=needle):
            br.range_observe(s_bad, l_bad)
    params = pr.PARAMS._replace(sigma_r=-0.3)  # squared, it was a valid R
    with pytest.raises(InputError, match=r"^params.sigma_r: expected a positive"):
        br.update_ranges(None, None, None, None, None, params)


# --- a sixth probe: float masks, a float capacity, a NaN known map, slots outside the map ---

def test_planar_ekf_slam_refuses_a_float_mask_and_a_non_integer_capacity():
    """A float mask of 0.5 was read as True (the row used); capacity 16.5 (or 16.0, True, "4")
    was truncated by int() into a map of another size."""
    from jaxslam.systems import planar_ekf_slam as pe

    cfg = pe.Config(capacity=4)
    prm = pe.Params(M_c=0.01 * np.eye(2), Q_floor=1e-4 * np.eye(3), R=np.diag([0.1, 0.01]), P0=1e-3 * np.eye(3))
    for m in (np.ones((6, 2)), np.full((6, 2), 0.5)):
        with pytest.raises(InputError, match=r"^log\.mask: expected a bool mask \(or 0/1 integers\)"):
            pe.run(_planar_log(mask=m), cfg, prm)
    for c in (16.0, 16.5, True, "4"):
        with pytest.raises(InputError, match=r"^config\.capacity: expected an int"):
            pe.run(_planar_log(), cfg._replace(capacity=c), prm)
    with pytest.raises(InputError, match=r"^config\.K: expected an int"):
        pe.run(_planar_log(), cfg._replace(K=8.0), prm)
    for field, bad in (("block", 2.5), ("block", -1), ("jcbb_cand", 2.5), ("jcbb_budget", 0)):
        with pytest.raises(InputError, match=rf"^config\.{field}: expected an int"):
            pe.run(_planar_log(), cfg._replace(association="jcbb", **{field: bad}), prm)
    # an integer 0/1 mask and a NumPy integer capacity run as before; a traced bool mask under jit too
    ref = pe.run(_planar_log(), cfg, prm)
    a = pe.run(_planar_log(mask=np.ones((6, 2), np.int32)), cfg._replace(capacity=np.int64(4)), prm)
    np.testing.assert_array_equal(np.asarray(a.pose), np.asarray(ref.pose))
    b = jax.jit(lambda mk: pe.run(_planar_log(mask=mk), cfg, prm).pose)(jnp.ones((6, 2), bool))
    np.testing.assert_allclose(np.asarray(b), np.asarray(ref.pose), rtol=1e-6, atol=1e-9)


def test_ekf_slam_3d_names_bad_log_ids_and_visible():
    """log.ids of shape (F', L), F' != F, and a float log.visible passed the checks and failed
    inside the jitted run (raw ValueError / TypeError)."""
    from jaxslam.systems import ekf_slam_3d as e3

    F, L = 3, 2
    log, prm, cfg = _e3_case(e3, F, L)
    with pytest.raises(InputError, match=r"^log\.ids: expected shape \(2,\) or \(3, 2\), got \(4, 2\)"):
        e3.run(log._replace(ids=np.tile(np.arange(L, dtype=np.int32), (F + 1, 1))), cfg, prm)
    with pytest.raises(InputError, match=r"^log\.visible: expected a bool mask"):
        e3.run(log._replace(visible=np.ones((F, L))), cfg, prm)
    ref = e3.run(log, cfg, prm)
    # 0/1 integers read as the bool mask they spell
    a = e3.run(log._replace(visible=np.ones((F, L), np.int32)), cfg, prm)
    np.testing.assert_array_equal(np.asarray(a.means), np.asarray(ref.means))
    np.testing.assert_array_equal(np.asarray(a.frames.dof), np.asarray(ref.frames.dof))


def test_ekf_slam_3d_refuses_a_non_finite_known_map():
    """A NaN/Inf in log.landmarks (mode "known") was preloaded inside the jitted run: every
    frame's update non-finite (status NON_FINITE | NOT_PSD, the robot mean zeroed)."""
    from jaxslam.systems import ekf_slam_3d as e3

    F, L = 3, 2
    lm = np.array([[5.0, 0.5, 0.5], [6.0, -0.6, 1.2]])
    log = e3.Log(s0=np.zeros(9), imu=np.tile([0.0, 0, -9.81, 0, 0, 0], (2 * F + 1, 1)),
                 y=np.tile([[0.1, 0.1, 5.0], [0.2, -0.1, 6.0]], (F, 1, 1)), visible=np.ones((F, L), bool),
                 ids=np.arange(L, dtype=np.int32), landmarks=lm)
    prm = e3.Params(P0=1e-3 * np.eye(9), Qc=1e-4 * np.eye(9), Qimu=1e-4 * np.eye(6), R=1e-4 * np.eye(3))
    cfg = e3.Config(capacity=4, max_obs=2, mode="known")
    for bad in (np.nan, np.inf):
        lm_bad = lm.copy()
        lm_bad[1, 2] = bad
        with pytest.raises(InputError, match=r"^log\.landmarks: contains NaN or Inf"):
            e3.run(log._replace(landmarks=lm_bad), cfg, prm)
        with pytest.raises(InputError, match=r"^landmarks_true: contains NaN or Inf"):
            e3.make_estimator(cfg, prm, lm_bad)
    res = e3.run(log, cfg, prm)  # the finite map runs, unflagged
    assert int(res.final.slam.status) == 0 and np.all(np.isfinite(np.asarray(res.final.slam.x)))


def test_update_ranges_names_a_slot_outside_the_map_and_a_float_mapped_mask():
    """A mapped row's slot outside [0, capacity) was dropped by the engine (MASKED_INPUT), the
    caller's bug unnamed; a float ``mapped`` of 0.5 was read as True (the row used)."""
    from jaxslam import errors
    from jaxslam.filters import ekf_slam as es
    from jaxslam.systems import biased_range as br

    M = pr.MODEL
    st = es.init(jnp.zeros(M.robot_dim), 0.01 * jnp.eye(M.robot_dim), 3, 2)
    st = es.preload(st, M, jnp.array([[3.0, 4.0], [-3.0, 4.0]]))
    p = br.resolve_outlier_gate(pr.PARAMS)
    z = jnp.array([[5.0], [5.2]])
    for bad in (5, 3, -1):
        with pytest.raises(InputError, match=r"^slots: mapped row\(s\) \[1\] name slot\(s\) \[" + str(bad)):
            br.update_ranges(st, M, z, jnp.array([0, bad]), jnp.array([True, True]), p)
    for m in (jnp.array([1.0, 0.5]), np.array([1.0, 0.0])):
        with pytest.raises(InputError, match=r"^mapped: expected a bool mask \(or 0/1 integers\)"):
            br.update_ranges(st, M, z, jnp.array([0, 1]), m, p)
    # an unmapped row may carry any slot; a 0/1 integer mask is the bool one
    ref = br.update_ranges(st, M, z, jnp.array([0, 1]), jnp.array([True, False]), p)
    for slots, mapped in ((jnp.array([0, 5]), jnp.array([True, False])), (jnp.array([0, 1]), jnp.array([1, 0]))):
        out = br.update_ranges(st, M, z, slots, mapped, p)
        np.testing.assert_array_equal(np.asarray(out[0].x), np.asarray(ref[0].x))
        assert float(out[2]) == float(ref[2])
    # traced slots: no check, the engine drops the row and flags it, as before
    s2 = jax.jit(lambda sl: br.update_ranges(st, M, z, sl, jnp.array([True, True]), p)[0])(jnp.array([0, 5]))
    assert int(s2.status) & errors.MASKED_INPUT


def test_fastslam_001_counts_landmark_ids_beyond_capacity_as_overflow():
    """Not a defect: an id >= config.capacity (slot = id) is counted in the particles' overflow
    and flags CAPACITY_OVERFLOW, never clipped into the last slot."""
    from jaxslam import errors
    from jaxslam.systems import fastslam_001 as fs1

    cfg = fs1.Config(n_particles=8, lidar_every=2)  # capacity 4
    res = fs1.run(_fs1_log(ids=np.array([3, 9])), cfg, fs1.default_params(), key=jax.random.PRNGKey(0))
    p = res.final.particles
    assert int(p.overflow) == 2  # id 9 in each of the 2 frames
    assert int(p.status) & errors.CAPACITY_OVERFLOW
    np.testing.assert_array_equal(np.asarray(p.ids), np.tile([-1, -1, -1, 3], (8, 1)))


def test_review_2026_12_07_config_switches_and_a_text_dt():
    """A string "no" for a switch read as True (uwb_slam_2d: debias, r_scaled, smooth,
    delayed_init; fastslam_001: save_particles, regen_noise); a text dt with params=None was
    NumPy's own error, raised while the default parameters were built."""
    import numpy as np

    from jaxslam.errors import InputError
    from jaxslam.systems import fastslam_001 as f001, uwb_slam_2d as u

    A = np.array([[0, 0], [10, 0], [5, 8.0], [2, 6]])
    pos = np.array([[3.0, 3.0]] * 5)
    r = np.linalg.norm(pos[:, None] - A[None], axis=-1)
    log = u.Log(r[:1], np.ones_like(r[:1], bool), r, np.ones_like(r, bool), np.zeros((5, 3)), A)
    for name in ("debias", "r_scaled", "smooth", "delayed_init"):
        with pytest.raises(InputError, match=rf"^config\.{name}: expected True or False, got 'no'"):
            u.run(log, u.Config(mode="localization", **{name: "no"}))
    with pytest.raises(InputError, match=r"^config\.dt: expected a positive finite scalar, got 'a'"):
        u.run(log, u.Config(mode="localization", dt="a"))
    for name in ("save_particles", "regen_noise"):
        with pytest.raises(InputError, match=rf"^config\.{name}: expected True or False, got 'no'"):
            f001.validate_config(f001.Config(**{name: "no"}))
    f001.validate_config(f001.Config())
