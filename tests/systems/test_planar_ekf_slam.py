"""2D range-bearing EKF-SLAM system (issue 9) on synthetic logs.

Oracles: hand-derived Jacobians of the unicycle (exact arc), the Ackermann step and the
range-bearing observation against ``jax.jacfwd``; a Monte-Carlo ANEES of the robot pose
inside Bar-Shalom's two-sided 95 % bounds; known vs nearest-neighbour association on clean
data; the bearing wrap at ±π; capacity overflow counted and flagged; float32 finite.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam import errors, metrics
from jaxslam.data.events import merge_events
from jaxslam.dynamics import planar
from jaxslam.errors import InputError
from jaxslam.sensors import range_bearing2d as rb
from jaxslam.systems import planar_ekf_slam as P

DT = 0.1
T_STEPS = 320  # one loop of the circle (v/ω = 5 m radius, 2π/0.2 ≈ 31.4 s)
V, W = 1.0, 0.2
SIG_V, SIG_W = 0.05, 0.02  # input noise densities [(m/s)·√s, (rad/s)·√s]
SIG_R, SIG_B = 0.1, 0.01
MAX_RANGE = 6.0
MEAS_EVERY = 5


def _wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


def _scenario(seed=0, n_lm=15, n_steps=T_STEPS):
    """True trajectory, landmarks, and the visible (step, landmark) pairs (also used by
    test_planar_divergence.py, with two loops)."""
    rng = np.random.default_rng(seed)
    ang = np.linspace(0, 2 * np.pi, n_lm, endpoint=False) + 0.1
    rad = np.where(np.arange(n_lm) % 2 == 0, 3.0, 7.0)
    lms = np.stack([rad * np.cos(ang), 5.0 + rad * np.sin(ang)], 1)  # circle centred at (0, 5)
    s = np.array([0.0, 0.0, 0.0])
    traj = [s]
    for _ in range(n_steps):
        s = np.asarray(planar.unicycle(jnp.asarray(s), jnp.array([V, W]), DT))
        traj.append(s)
    traj = np.array(traj)
    vis = []
    for k in range(MEAS_EVERY, n_steps + 1, MEAS_EVERY):
        for j, l in enumerate(lms):
            d = l - traj[k, :2]
            b = _wrap(np.arctan2(d[1], d[0]) - traj[k, 2])
            if np.hypot(*d) < MAX_RANGE and abs(b) < 1.2:
                vis.append((k, j))
    del rng
    return traj, lms, vis


def _logs(traj, lms, vis, n_runs, seed=1, sig_scale=1.0):
    """Event structure (shared) and per-run noisy inputs and measurements."""
    rng = np.random.default_rng(seed)
    t_in = DT * np.arange(T_STEPS)
    u_true = np.tile([V, W], (T_STEPS, 1))
    mt = np.array([DT * k for k, _ in vis])
    ids = np.array([j for _, j in vis])
    z_true = np.array([np.asarray(rb.observe(jnp.asarray(traj[k]), jnp.asarray(lms[j]))) for k, j in vis])
    base = merge_events(t_in, u_true, mt, z_true, ids, K=8)
    us, zs = [], []
    for _ in range(n_runs):
        un = u_true + sig_scale * rng.normal(size=u_true.shape) * np.array([SIG_V, SIG_W]) / np.sqrt(DT)
        zn = z_true + sig_scale * rng.normal(size=z_true.shape) * np.array([SIG_R, SIG_B])
        lg = merge_events(t_in, un, mt, zn, ids, K=8)
        us.append(lg.u)
        zs.append(lg.z)
    return base, np.array(us), np.array(zs)


def _params(dtype=jnp.float64, p0=1e-8):
    return P.Params(
        M_c=jnp.diag(jnp.asarray([SIG_V**2, SIG_W**2], dtype)),
        Q_floor=jnp.zeros((3, 3), dtype),
        R=jnp.diag(jnp.asarray([SIG_R**2, SIG_B**2], dtype)),
        P0=jnp.eye(3, dtype=dtype) * p0,
    )


# ---------------------------------------------------------------------------
# Jacobian oracles (hand-derived) against the autodiff the engine uses
# ---------------------------------------------------------------------------

def test_unicycle_jacobians_hand_vs_jacfwd():
    s = jnp.array([1.0, -2.0, 0.7])
    for u, dt in ((jnp.array([0.8, 0.3]), 0.2), (jnp.array([0.5, 0.0]), 0.1)):
        F, Ju = jax.jacfwd(planar.unicycle, argnums=(0, 1))(s, u, dt)
        v, w = float(u[0]), float(u[1])
        phi = float(s[2])
        if w != 0.0:
            a = phi + w * dt
            F_h = np.array([[1, 0, v / w * (np.cos(a) - np.cos(phi))],
                            [0, 1, v / w * (np.sin(a) - np.sin(phi))], [0, 0, 1]])
            Ju_h = np.array([
                [(np.sin(a) - np.sin(phi)) / w, v * (np.cos(a) * dt / w - (np.sin(a) - np.sin(phi)) / w**2)],
                [-(np.cos(a) - np.cos(phi)) / w, v * (np.sin(a) * dt / w + (np.cos(a) - np.cos(phi)) / w**2)],
                [0, dt]])
        else:  # straight line; ∂/∂ω from the limit: (−½ v dt² sin φ, ½ v dt² cos φ)
            F_h = np.array([[1, 0, -v * dt * np.sin(phi)], [0, 1, v * dt * np.cos(phi)], [0, 0, 1]])
            Ju_h = np.array([[dt * np.cos(phi), -0.5 * v * dt**2 * np.sin(phi)],
                             [dt * np.sin(phi), 0.5 * v * dt**2 * np.cos(phi)], [0, dt]])
        np.testing.assert_allclose(np.asarray(F), F_h, atol=1e-12)
        np.testing.assert_allclose(np.asarray(Ju), Ju_h, atol=1e-9)


def test_ackermann_jacobian_hand_vs_jacfwd():
    g = planar.VICTORIA_PARK
    s = jnp.array([3.0, 1.0, -0.4])
    u = jnp.array([4.0, 0.15])
    dt = 0.025
    F = np.asarray(jax.jacfwd(planar.ackermann)(s, u, dt))
    ve, al = 4.0, 0.15
    vc = ve / (1 - np.tan(al) * g.H / g.L)
    k = vc / g.L * np.tan(al)
    c, sn = np.cos(-0.4), np.sin(-0.4)
    F_h = np.eye(3)
    F_h[0, 2] = dt * (-vc * sn - k * (g.a * c - g.b * sn))
    F_h[1, 2] = dt * (vc * c + k * (-g.a * sn - g.b * c))
    np.testing.assert_allclose(F, F_h, atol=1e-12)


def test_range_bearing_jacobians_hand_vs_jacfwd():
    s = jnp.array([1.0, 2.0, 0.3])
    lm = jnp.array([4.0, -1.0])
    Hs, Hl = jax.jacfwd(rb.observe, argnums=(0, 1))(s, lm)
    dx, dy = 3.0, -3.0
    q = dx * dx + dy * dy
    r = np.sqrt(q)
    Hl_h = np.array([[dx / r, dy / r], [-dy / q, dx / q]])
    Hs_h = np.concatenate([-Hl_h, np.array([[0.0], [-1.0]])], axis=1)
    np.testing.assert_allclose(np.asarray(Hs), Hs_h, atol=1e-14)
    np.testing.assert_allclose(np.asarray(Hl), Hl_h, atol=1e-14)


# ---------------------------------------------------------------------------
# Filter behaviour on simulated logs
# ---------------------------------------------------------------------------

@pytest.fixture(scope="module")
def scenario():
    return _scenario()


def _run_batch(base, us, zs, cfg, params, pose0):
    f = jax.vmap(lambda u, z: P.run(P.Log(base.dt, u, z, base.ids, base.mask, pose0), cfg, params))
    return f(jnp.asarray(us), jnp.asarray(zs))


def test_monte_carlo_pose_anees_within_bounds(scenario):
    traj, lms, vis = scenario
    n_runs = 12
    base, us, zs = _logs(traj, lms, vis, n_runs)
    cfg = P.Config(motion="unicycle", capacity=16, K=8, association="known")
    res = _run_batch(base, us, zs, cfg, _params(), jnp.asarray(traj[0]))
    # truth at each event (events are the input times; measurement times coincide with them)
    k_of_event = np.rint(base.t / DT).astype(int)
    truth = traj[k_of_event]
    err = np.asarray(res.pose) - truth[None]
    err[..., 2] = _wrap(err[..., 2])
    nees = np.asarray(metrics.nees(jnp.asarray(err), res.pose_cov))  # (R, T)
    assert np.all(np.asarray(res.status) == 0)
    assert np.all(np.asarray(res.active).sum(axis=1) == len(lms))
    anees = nees[:, 10:].mean(axis=0)  # per event, across runs
    lo, hi = metrics.anees_bounds(3, n_runs)
    mean_anees = float(anees.mean())
    # the time average of per-step ANEES (each a mean of R χ²(3)/R) must sit well inside
    assert lo < mean_anees < hi, (mean_anees, lo, hi)
    # and most individual steps inside the per-step 95 % bounds
    frac = float(np.mean((anees > lo) & (anees < hi)))
    assert frac > 0.8, frac


def test_known_and_nn_agree_on_clean_data(scenario):
    traj, lms, vis = scenario
    base, us, zs = _logs(traj, lms, vis, 1, sig_scale=0.05)
    prm = _params()
    pose0 = jnp.asarray(traj[0])
    rk = P.run(P.Log(base.dt, us[0], zs[0], base.ids, base.mask, pose0), P.Config(capacity=16, association="known"), prm)
    rn = P.run(P.Log(base.dt, us[0], zs[0], base.ids, base.mask, pose0), P.Config(capacity=16, association="nn"), prm)
    assert int(rn.active.sum()) == int(rk.active.sum()) == len(lms)
    assert int(rn.n_rejected.sum()) == 0 and int(rn.n_used.sum()) == int(rk.n_used.sum())
    np.testing.assert_allclose(np.asarray(rn.pose), np.asarray(rk.pose), atol=1e-9)
    # same map up to slot order
    Lk = np.asarray(rk.landmarks)[np.asarray(rk.active)]
    Ln = np.asarray(rn.landmarks)[np.asarray(rn.active)]
    d = np.linalg.norm(Lk[:, None] - Ln[None], axis=-1)
    assert np.all(d.min(axis=1) < 1e-9)
    # nn slots carry no log id
    assert np.all(np.asarray(rn.ids)[np.asarray(rn.active)] == -1)


def test_bearing_wrap_landmark_behind():
    """A landmark straight behind: bearings alternate at +π−ε / −π+ε; innovations stay small."""
    n = 40
    t = DT * np.arange(n)
    u = np.zeros((n, 2))
    eps = 1e-3
    z = np.stack([np.full(n, 5.0), np.where(np.arange(n) % 2 == 0, np.pi - eps, -np.pi + eps)], 1)
    log = merge_events(t, u, t, z, np.zeros(n, int), K=1)
    for assoc in ("known", "nn"):
        res = P.run(P.log_from_events(log, jnp.zeros(3)), P.Config(capacity=4, K=1, association=assoc), _params(p0=1e-4))
        assert int(res.status) == 0
        assert int(res.active.sum()) == 1
        assert int(res.n_used.sum()) == n - 1
        nis = np.asarray(res.nis)[1:]
        assert np.all(nis < 1.0), nis.max()
        np.testing.assert_allclose(np.asarray(res.landmarks)[0], [-5.0, 0.0], atol=0.02)
        assert abs(float(res.pose[-1, 2])) < 1e-2


def test_capacity_overflow_counted_and_flagged(scenario):
    traj, lms, vis = scenario
    base, us, zs = _logs(traj, lms, vis, 1)
    res = P.run(P.log_from_events(base._replace(u=us[0], z=zs[0]), jnp.asarray(traj[0])), P.Config(capacity=4, association="known"), _params())
    assert int(res.active.sum()) == 4
    assert int(res.overflow) > 0
    assert int(res.status) & errors.CAPACITY_OVERFLOW
    assert np.all(np.isfinite(np.asarray(res.pose)))


def test_float32_run_is_finite_and_close(scenario):
    traj, lms, vis = scenario
    base, us, zs = _logs(traj, lms, vis, 1)
    log = base._replace(u=us[0], z=zs[0])
    r32 = P.run(P.log_from_events(log, jnp.asarray(traj[0], jnp.float32)), P.Config(capacity=16), _params(jnp.float32, p0=1e-6))
    r64 = P.run(P.log_from_events(log, jnp.asarray(traj[0])), P.Config(capacity=16), _params(p0=1e-6))
    assert r32.pose.dtype == jnp.float32
    assert np.all(np.isfinite(np.asarray(r32.pose))) and np.all(np.isfinite(np.asarray(r32.pose_cov)))
    assert int(r32.status) == 0
    np.testing.assert_allclose(np.asarray(r32.pose[:, :2]), np.asarray(r64.pose[:, :2]), atol=2e-3)


def test_limits_and_k_selection_are_counted():
    n = 5
    t = DT * np.arange(n)
    z = np.array([[2.0, 0.1], [9.0, 0.2], [3.0, -0.2], [4.0, 0.3], [1.0, 0.0]])
    mt = np.zeros(n)
    log = merge_events(t, np.zeros((n, 2)), mt, z, np.arange(n), K=5)
    cfg = P.Config(capacity=8, K=2)
    res = P.run(P.log_from_events(log, jnp.zeros(3)), cfg, _params(p0=1e-4)._replace(range_max=5.0, range_min=1.5))
    assert int(res.n_limited.sum()) == 2  # 9 m and 1 m
    assert int(res.n_meas.sum()) == 3
    assert int(res.n_dropped.sum()) == 1  # the 4 m row (the two nearest are kept)
    assert int(res.n_registered.sum()) == 2
    assert sorted(np.asarray(res.ids)[np.asarray(res.active)].tolist()) == [0, 2]


def test_validation_errors():
    log = merge_events(np.arange(3.0), np.zeros((3, 2)), np.arange(3.0), np.ones((3, 2)), K=1)
    with pytest.raises(InputError, match="motion"):
        P.run(P.log_from_events(log, jnp.zeros(3)), P.Config(motion="bike"), _params())
    with pytest.raises(InputError, match="params.R"):
        P.run(P.log_from_events(log, jnp.zeros(3)), P.Config(), _params()._replace(R=jnp.zeros((2, 2))))
    with pytest.raises(InputError, match="log.u"):
        P.run(P.log_from_events(log._replace(u=np.zeros((3, 3))), jnp.zeros(3)), P.Config(), _params())


def test_mrclam_log_applies_range_model_and_odometry_delay():
    """Synthetic MrclamData: ranges divided by k0 + k2 β², odometry stamps shifted by the delay."""
    from jaxslam.data import presets
    from jaxslam.data.mrclam import MrclamData

    gt_t = np.linspace(0.0, 10.0, 101)
    gt = np.stack([gt_t * 0.1, np.zeros_like(gt_t), np.full_like(gt_t, 0.3)], 1)
    odom_t = np.array([1.0, 2.0, 3.0])
    odom = np.array([[0.1, 0.0], [0.1, 0.01], [0.0, 0.0]])
    meas_t = np.array([2.5, 2.5, 4.0])
    meas = np.array([[2.0, 0.0], [3.0, 0.5], [4.0, -0.3]])
    ids = np.array([6, 7, 8], np.int32)
    data = MrclamData(robot=1, t0=0.0, odom_t=odom_t, odom=odom, gt_t=gt_t, gt=gt, meas_t=meas_t,
                      meas=meas, meas_id=ids, landmark_id=ids, landmark_xy=np.zeros((3, 2)),
                      landmark_std=np.zeros((3, 2)), barcodes=np.zeros((0, 2), np.int32), report={})
    k = (1.02, -0.5)
    log, pose0 = presets.mrclam_log(data, range_model=k, odometry_delay=0.2)
    assert np.allclose(log.t[log.is_input], odom_t + 0.2)
    rows = log.z[log.mask]
    assert np.allclose(rows[:, 0], meas[:, 0] / (k[0] + k[1] * meas[:, 1] ** 2))
    assert np.allclose(rows[:, 1], meas[:, 1])
    assert np.allclose(pose0, [0.12, 0.0, 0.3])  # GT at the first event (t = 1.2 s)
    raw, _ = presets.mrclam_log(data, range_model=None, odometry_delay=0.0)
    assert np.allclose(raw.z[raw.mask], meas) and np.allclose(raw.t[raw.is_input], odom_t)
    assert log.t[-1] <= gt_t[-1]


def test_tentative_landmark_pruning():
    """A one-off detection (clutter) is removed after the window; a repeated one is kept.

    Robot at rest; landmark A seen at every event, B only once (t = 0.3 s).  With a 1 s
    window and 3 matches required, B is pruned (its slot, mean and P rows/columns zeroed)
    and A stays; with pruning off both stay.  The estimate of A and the pose do not change.
    """
    n = 30
    t = DT * np.arange(n)
    zA = np.tile([[5.0, 0.2]], (n, 1))
    mt = list(t)
    z = list(zA)
    mt.append(0.3)
    z.append([8.0, -0.9])
    order = np.argsort(mt, kind="stable")
    log = merge_events(t, np.zeros((n, 2)), np.asarray(mt)[order], np.asarray(z)[order], K=2)
    prm = _params(p0=1e-4)
    off = P.run(P.log_from_events(log, jnp.zeros(3)), P.Config(capacity=4, K=2, association="nn"), prm)
    on = P.run(P.log_from_events(log, jnp.zeros(3)), P.Config(capacity=4, K=2, association="nn"),
               prm._replace(prune_window_s=1.0, prune_min_obs=3))
    assert int(off.active.sum()) == 2 and int(off.n_pruned.sum()) == 0
    assert int(on.active.sum()) == 1 and int(on.n_pruned.sum()) == 1
    # pruned right after the window closes (registered at 0.3 s, window 1 s)
    k = int(np.flatnonzero(np.asarray(on.n_pruned))[0])
    assert 1.3 < log.t[k] <= 1.5
    s = int(np.flatnonzero(~np.asarray(on.active))[0])
    for res in (on,):
        assert np.all(np.asarray(res.landmark_covs)[~np.asarray(res.active)] == 0)
        assert np.all(np.asarray(res.landmarks)[~np.asarray(res.active)] == 0)
    del s
    lm_on = np.asarray(on.landmarks)[np.asarray(on.active)]
    np.testing.assert_allclose(lm_on[0], [5 * np.cos(0.2), 5 * np.sin(0.2)], atol=1e-3)
    assert int(on.status) == 0 and np.all(np.isfinite(np.asarray(on.pose)))
    with pytest.raises(InputError, match="prune"):
        P.run(P.log_from_events(log, jnp.zeros(3)), P.Config(), prm._replace(prune_window_s=-1.0))


def test_joint_compatibility_drops_the_inconsistent_match():
    """Heading uncertain (σ_φ 0.1 rad), 3 precise landmarks: rows 0 and 1 are rotated by +0.08
    rad (a heading error; each d² small), row 2 by −0.08 rad (also small alone).  Jointly only
    one heading explains them: the check drops row 2 and keeps 0 and 1.  An unrotated scan
    keeps every row; so does the planar run with ``joint_gate`` on clean data.
    """
    from jaxslam.filters import ekf_slam as es

    model = P.make_model(P.Config(motion="unicycle", association="nn"))
    st = es.init(jnp.zeros(3), jnp.diag(jnp.asarray([1e-4, 1e-4, 0.1**2])), 4, 2)
    R = jnp.diag(jnp.asarray([0.05**2, 0.01**2]))
    lms = np.array([[10.0, 0.0], [0.0, 10.0], [-7.0, -7.0]])
    add = jax.jit(lambda st, i, l: es.add_landmark(st, model, i, l, 1e-6 * jnp.eye(2), jnp.zeros((2, 11)), -1))
    for i, l in enumerate(lms):  # jitted here and below: one program each, not one per operation
        st = add(st, i, jnp.asarray(l))
    zt = np.stack([np.linalg.norm(lms, axis=1), np.arctan2(lms[:, 1], lms[:, 0])], 1)
    slots = jnp.arange(3, dtype=jnp.int32)
    m = jnp.ones(3, bool)
    thr = P._chi2_table(0.99, 3, 2)
    assoc = jax.jit(lambda st, z: es.associate_nn(st, model, z, m, R))
    joint = jax.jit(lambda st, z: es.joint_compatibility(st, model, z, slots, m, R, None, thr))
    for rot, keep in (([0.08, 0.08, -0.08], [True, True, False]), ([0.0, 0.0, 0.0], [True] * 3)):
        z = jnp.asarray(zt + np.stack([np.zeros(3), rot], 1))
        _, ok, _, d2 = assoc(st, z)
        assert np.all(np.asarray(ok)) and np.all(np.asarray(d2) < 9.21)  # each row alone passes
        kept, dropped, nis = joint(st, z)
        assert list(np.asarray(kept)) == keep and list(np.asarray(dropped)) == [not k for k in keep]
        assert float(nis) < thr[int(np.sum(keep)) - 1]


def test_joint_gate_is_a_no_op_on_clean_data(scenario):
    traj, lms, vis = scenario
    base, us, zs = _logs(traj, lms, vis, 1, sig_scale=0.05)
    prm = _params()
    pose0 = jnp.asarray(traj[0])
    r0 = P.run(P.Log(base.dt, us[0], zs[0], base.ids, base.mask, pose0), P.Config(capacity=16, association="nn"), prm)
    r1 = P.run(P.Log(base.dt, us[0], zs[0], base.ids, base.mask, pose0), P.Config(capacity=16, association="nn", joint_gate=0.99), prm)
    assert int(r1.n_rejected.sum()) == 0 and int(r1.n_used.sum()) == int(r0.n_used.sum())
    np.testing.assert_allclose(np.asarray(r1.pose), np.asarray(r0.pose), atol=1e-9)
    with pytest.raises(InputError, match="joint_gate"):
        P.validate_config(P.Config(association="nn", joint_gate=1.5))


def test_online_input_calibration_recovers_odometry_scale(scenario):
    """``calibrate=True``: logged odometry with a 10 % speed and −8 % turn-rate scale error.

    On the constant-rate loop the turn scale and the turn bias are observable only in the
    combination c_1 ω + c_2, so that (the true turn rate) and the speed scale are checked.
    """
    traj, lms, vis = scenario
    base, us, zs = _logs(traj, lms, vis, 1, sig_scale=0.2)
    c_true = np.array([1.10, 0.92])
    u_log = np.asarray(us[0]) / c_true  # the log under-reports speed by 10 %, over-reports turn by 8 %
    pose0 = jnp.asarray(traj[0])
    prm = _params()._replace(calib0=jnp.asarray([1.0, 1.0, 0.0]),
                             calib_P0=jnp.diag(jnp.asarray([0.2, 0.2, 0.05]) ** 2),
                             calib_Q=jnp.zeros((3, 3)))
    on = P.run(P.Log(base.dt, u_log, zs[0], base.ids, base.mask, pose0), P.Config(capacity=16, association="known", calibrate=True), prm)
    off = P.run(P.Log(base.dt, u_log, zs[0], base.ids, base.mask, pose0), P.Config(capacity=16, association="known"), _params(p0=1e-8))
    c = np.asarray(on.calib[-1])
    assert abs(c[0] - c_true[0]) < 0.02, c
    assert abs(c[1] * W / c_true[1] + c[2] - W) < 0.02 * abs(W), c  # c_1 ω_log + c_2 = ω
    k = np.rint(base.t / DT).astype(int)
    e_on = np.linalg.norm(np.asarray(on.pose)[:, :2] - traj[k, :2], axis=1)
    e_off = np.linalg.norm(np.asarray(off.pose)[:, :2] - traj[k, :2], axis=1)
    assert np.sqrt(np.mean(e_on[len(k) // 2:] ** 2)) < np.sqrt(np.mean(e_off[len(k) // 2:] ** 2))
    assert int(on.status) == 0


def test_range_model_likelihood_is_that_of_the_measured_range(scenario):
    """Oracle: the filter on ranges transformed by hand, (r_meas − a)/k0, with the change of
    variables added by hand: −log p(r_meas) = −log p(r) + log k0 per used range row."""
    traj, lms, vis = scenario
    base, us, zs = _logs(traj, lms, vis, 1)
    k0, a = 1.07, 0.05
    z_meas = np.array(zs[0])
    z_meas[..., 0] = z_meas[..., 0] * k0 + a  # a camera with scale k0 and offset a
    cfg = P.Config(capacity=16, association="known", robust=True)
    pose0 = jnp.asarray(traj[0])
    with_model = P.run(P.Log(base.dt, us[0], z_meas, base.ids, base.mask, pose0), cfg, _params()._replace(range_model=jnp.asarray([k0, 0.0, a])))
    by_hand = P.run(P.Log(base.dt, us[0], zs[0], base.ids, base.mask, pose0), cfg, _params())
    np.testing.assert_allclose(np.asarray(with_model.pose), np.asarray(by_hand.pose), rtol=0, atol=1e-9)
    used_rows = float(np.sum(np.asarray(by_hand.n_used)))
    assert used_rows > 100
    np.testing.assert_allclose(float(np.sum(with_model.nll)), float(np.sum(by_hand.nll)) + used_rows * np.log(k0),
                               rtol=1e-10)


def test_input_model_equals_corrected_inputs(scenario):
    traj, lms, vis = scenario
    base, us, zs = _logs(traj, lms, vis, 1)
    c = np.array([0.96, 1.08, -0.004])
    u_corr = np.stack([c[0] * us[0][:, 0], c[1] * us[0][:, 1] + c[2]], -1)
    cfg = P.Config(capacity=16, association="known")
    pose0 = jnp.asarray(traj[0])
    a = P.run(P.Log(base.dt, us[0], zs[0], base.ids, base.mask, pose0), cfg, _params()._replace(input_model=jnp.asarray(c)))
    b = P.run(P.Log(base.dt, u_corr, zs[0], base.ids, base.mask, pose0), cfg, _params())
    np.testing.assert_allclose(np.asarray(a.pose), np.asarray(b.pose), rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(a.nll), np.asarray(b.nll), rtol=1e-12, atol=1e-12)
    with pytest.raises(InputError, match="params.input_model"):
        P.validate_params(_params()._replace(input_model=jnp.asarray([1.0, 1.0])))


def test_pruning_zeroes_rows_and_columns_in_place_with_a_masked_derivative():
    """_zero_slots (the pruning's write of P) against NumPy: the dropped slots' rows and columns
    zero, the rest bit-equal; its JVP is the same mask on the tangent; reverse mode works
    through the loop of traced length (custom JVP)."""
    rng = np.random.default_rng(0)
    n = 3 + 2 * 6
    A = rng.normal(size=(n, n))
    Pm = A @ A.T
    drop = np.array([False, True, False, False, True, False])
    keep = np.r_[np.ones(3, bool), np.repeat(~drop, 2)]
    want = np.where(keep[:, None] & keep[None, :], Pm, 0.0)
    out = jax.jit(P._zero_slots, static_argnums=(2, 3))(jnp.asarray(Pm), jnp.asarray(drop), 3, 2)
    np.testing.assert_array_equal(np.asarray(out), want)
    dP = rng.normal(size=(n, n))
    _, t = jax.jvp(lambda M: P._zero_slots(M, jnp.asarray(drop), 3, 2), (jnp.asarray(Pm),), (jnp.asarray(dP),))
    np.testing.assert_array_equal(np.asarray(t), np.where(keep[:, None] & keep[None, :], dP, 0.0))
    W = rng.normal(size=(n, n))
    g = jax.grad(lambda M: jnp.sum(W * P._zero_slots(M, jnp.asarray(drop), 3, 2)))(jnp.asarray(Pm))
    np.testing.assert_array_equal(np.asarray(g), np.where(keep[:, None] & keep[None, :], W, 0.0))
