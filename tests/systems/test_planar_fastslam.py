"""Synthetic tests of the 2D range-bearing FastSLAM system (jaxslam.systems.planar_fastslam)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam import errors
from jaxslam.data.events import merge_events
from jaxslam.dynamics import planar
from jaxslam.errors import InputError
from jaxslam.sensors import range_bearing2d as rb
from jaxslam.systems import planar_fastslam as pf

DT_U = 0.05      # odometry period [s]
DT_Z = 0.25      # measurement period [s]
DURATION = 40.0  # one loop [s]
SIG_V, SIG_W = 0.05, 0.05      # per-sample odometry noise (m/s, rad/s)
SIG_R, SIG_B = 0.05, 0.01      # measurement noise (m, rad)
MAX_RANGE = 7.0


def _landmarks():
    # 12 landmarks, ≥ 4 m apart, inside and outside a circle of radius ~6.4 m
    ang = np.linspace(0, 2 * np.pi, 6, endpoint=False)
    inner = np.stack([3.0 * np.cos(ang), 3.0 * np.sin(ang)], 1)
    outer = np.stack([10.0 * np.cos(ang + 0.5), 10.0 * np.sin(ang + 0.5)], 1)
    c = np.array([0.0, 6.37])
    return np.concatenate([inner, outer]) + c


@jax.jit
def _integrate(s0, u, dt):
    """Exact-arc unicycle integrated over steps (u_k held over dt_k): (n, 3) poses after each."""
    def body(s, inp):
        s = planar.unicycle(s, inp[0], inp[1])
        return s, s

    return jax.lax.scan(body, s0, (u, dt))[1]


_observe_all = jax.jit(jax.vmap(jax.vmap(rb.observe, in_axes=(None, 0)), in_axes=(0, None)))


def _simulate(seed, K=12):
    rng = np.random.default_rng(seed)
    lms = _landmarks()
    tu = np.arange(0.0, DURATION, DT_U)
    u_true = np.stack([np.full(tu.size, 1.0), np.full(tu.size, 2 * np.pi / DURATION)], 1)
    u_meas = u_true + rng.normal(size=u_true.shape) * [SIG_V, SIG_W]
    # ground truth at a fine grid (exact arcs with the true inputs), one scan
    t_z = np.arange(DT_Z, DURATION, DT_Z)
    all_t = np.union1d(tu, t_z)
    j = np.searchsorted(tu, all_t[:-1], side="right") - 1
    poses = np.asarray(_integrate(jnp.zeros(3), jnp.asarray(u_true[j]), jnp.asarray(np.diff(all_t))))
    gt_t, gt = all_t, np.concatenate([np.zeros((1, 3)), poses])
    # measurements at the scan times: every landmark in range, noise drawn in the same order
    at_z = np.isclose(all_t[1:, None], t_z[None, :]).any(axis=1)
    tz, sz = all_t[1:][at_z], poses[at_z]
    Z = np.asarray(_observe_all(jnp.asarray(sz), jnp.asarray(lms)))  # (n_z, L, 2)
    zt, zz, zid = [], [], []
    for k in range(tz.size):
        for i in range(len(lms)):
            if Z[k, i, 0] < MAX_RANGE:
                zt.append(tz[k]); zz.append(Z[k, i] + rng.normal(size=2) * [SIG_R, SIG_B]); zid.append(i)
    log = merge_events(tu, u_meas, np.array(zt), np.array(zz), np.array(zid), K=K)
    return log, np.array(gt_t), np.array(gt), lms, set(zid)


@pytest.fixture(scope="module")
def sim():
    return _simulate(0)


def _params(dtype=None):
    # M_c = per-sample variance × sample period (density of the held-rate noise)
    return pf.default_params(sigma_r=SIG_R, sigma_b=SIG_B, sigma_v=SIG_V * np.sqrt(DT_U),
                             sigma_w=SIG_W * np.sqrt(DT_U), floor=(1e-6, 1e-6, 1e-7),
                             pose0_sigma=(1e-3, 1e-3, 1e-3), dtype=dtype)


def _err(res, log, gt_t, gt):
    gx = np.interp(log.t, gt_t, gt[:, 0])
    gy = np.interp(log.t, gt_t, gt[:, 1])
    est = np.asarray(res.pose_mean)
    return float(np.sqrt(np.mean((est[:, 0] - gx) ** 2 + (est[:, 1] - gy) ** 2)))


def _dead_reckoning_err(log, gt_t, gt):
    out = np.asarray(_integrate(jnp.zeros(3), jnp.asarray(log.u), jnp.asarray(log.dt)))
    gx = np.interp(log.t, gt_t, gt[:, 0])
    gy = np.interp(log.t, gt_t, gt[:, 1])
    return float(np.sqrt(np.mean((out[:, 0] - gx) ** 2 + (out[:, 1] - gy) ** 2)))


def test_known_ids_tracks_over_seeds():
    cfg = pf.Config(motion="unicycle", n_particles=50, capacity=12, K=12, association="known")
    errs, dr = [], []
    for seed in range(3):
        log, gt_t, gt, lms, seen = _simulate(seed)
        res = pf.run(pf.log_from_events(log, jnp.zeros(3)), cfg, _params(), key=jax.random.PRNGKey(seed))
        errs.append(_err(res, log, gt_t, gt))
        dr.append(_dead_reckoning_err(log, gt_t, gt))
        assert int(res.overflow) == 0
        m = res.map
        assert int(jnp.sum(m.active)) == len(seen)
        act = np.asarray(m.active)
        lm_err = np.linalg.norm(np.asarray(m.mean)[act] - lms[np.asarray(m.ids)[act]], axis=1)
        assert np.max(lm_err) < 0.3, lm_err
    assert max(errs) < 0.15, (errs, dr)
    assert np.median(errs) < 0.5 * np.median(dr), (errs, dr)


def test_ml_association_map_size(sim):
    log, gt_t, gt, lms, seen = sim
    cfg = pf.Config(motion="unicycle", n_particles=30, capacity=24, K=12, association="ml")
    prm = _params()._replace(gate=9.21, new_threshold=30.0)
    res = pf.run(pf.log_from_events(log, jnp.zeros(3)), cfg, prm, key=jax.random.PRNGKey(1))
    n_map = int(jnp.sum(res.map.active))
    assert n_map == len(seen), (n_map, len(seen))
    assert int(res.overflow) == 0
    assert _err(res, log, gt_t, gt) < 0.2
    # every mapped landmark lies near a distinct true one
    act = np.asarray(res.map.active)
    d = np.linalg.norm(np.asarray(res.map.mean)[act][:, None] - lms[None], axis=2)
    assert np.max(np.min(d, axis=1)) < 0.3
    assert len(set(np.argmin(d, axis=1))) == n_map
    assert int(jnp.sum(res.n_obs)) > 0


def test_ml_association_with_the_optimal_proposal(sim):
    """Ids unknown, FastSLAM 2.0: each particle associates with its pose covariance in S, then
    draws; with 10 particles the map has one landmark per true one seen and the loop is
    tracked.  Oracle: the truth of the simulation."""
    log, gt_t, gt, lms, seen = sim
    cfg = pf.Config(motion="unicycle", n_particles=10, capacity=24, K=12, association="ml", proposal="optimal")
    res = pf.run(pf.log_from_events(log, jnp.zeros(3)), cfg, _params()._replace(gate=9.21, new_threshold=30.0),
                 key=jax.random.PRNGKey(1))
    n_map = int(jnp.sum(res.map.active))
    assert n_map == len(seen) and int(res.overflow) == 0
    assert _err(res, log, gt_t, gt) < 0.1
    act = np.asarray(res.map.active)
    d = np.linalg.norm(np.asarray(res.map.mean)[act][:, None] - lms[None], axis=2)
    assert np.max(np.min(d, axis=1)) < 0.2 and len(set(np.argmin(d, axis=1))) == n_map


@pytest.mark.parametrize("proposal,robust", [("motion", False), ("optimal", True)])
def test_float32_run_finite(sim, proposal, robust):
    log, gt_t, gt, lms, seen = sim
    cfg = pf.Config(motion="unicycle", n_particles=20, capacity=12, K=12, association="known", proposal=proposal,
                    robust=robust)
    res = pf.run(pf.log_from_events(log, jnp.zeros(3, jnp.float32)), cfg, _params(jnp.float32), key=jax.random.PRNGKey(2))
    assert res.pose_mean.dtype == jnp.float32
    assert bool(jnp.all(jnp.isfinite(res.pose_mean)))
    assert bool(jnp.all(jnp.isfinite(res.map.mean)))
    assert not int(res.status) & (errors.NON_FINITE | errors.NOT_PSD)
    assert _err(res, log, gt_t, gt) < 0.3


def test_capacity_overflow_counted(sim):
    log, gt_t, gt, lms, seen = sim
    cfg = pf.Config(motion="unicycle", n_particles=10, capacity=4, K=12, association="known")
    res = pf.run(pf.log_from_events(log, jnp.zeros(3)), cfg, _params(), key=jax.random.PRNGKey(3))
    n_beyond = int(np.sum(log.mask & (log.ids >= 4)))
    assert int(res.overflow) == n_beyond > 0
    assert int(res.status) & errors.CAPACITY_OVERFLOW


def test_bad_config_rejected(sim):
    log = sim[0]
    with pytest.raises(InputError):
        pf.run(pf.log_from_events(log, jnp.zeros(3)), pf.Config(K=3), _params(), key=jax.random.PRNGKey(0))
    with pytest.raises(InputError):
        pf.run(pf.log_from_events(log, jnp.zeros(3)), pf.Config(K=12, motion="bike"), _params(), key=jax.random.PRNGKey(0))


def test_gated_known_sightings_raise_diverged(sim):
    """Known ids behind a gate: the EKF's rule — more than 10 % of the sightings of mapped
    landmarks gated sets DIVERGED.  A clean log gates few and is not flagged; a stretch of
    corrupted odometry (turn rate off by 2 rad/s for 1 s: 2 rad of heading the particles do
    not spread over) makes the particles' maps disagree with every later sighting.  Oracle: the
    fraction recomputed here from the run's own used/gated counts, and the truth of the
    simulation for which log is corrupted."""
    log, gt_t, gt, lms, seen = sim
    # 50 particles: the configurations of the motion runs in test_known_ids_tracks_over_seeds
    # (no gate) and test_optimal_proposal_tracks_with_few_particles (gate 13.82), compiled once
    cfg = pf.Config(motion="unicycle", n_particles=50, capacity=12, K=12, association="known")
    prm = _params()._replace(gate=13.82)
    key = jax.random.PRNGKey(4)
    clean = pf.run(pf.log_from_events(log, jnp.zeros(3)), cfg, prm, key=key)
    frac = float(clean.gated) / (float(clean.used) + float(clean.gated))
    assert frac < 0.10, frac
    assert not int(clean.status) & errors.DIVERGED
    u = np.array(log.u)
    bad = (log.t >= 15.0) & (log.t < 16.0)
    u[bad, 1] += 2.0
    res = pf.run(pf.log_from_events(log._replace(u=u), jnp.zeros(3)), cfg, prm, key=key)
    frac_bad = float(res.gated) / (float(res.used) + float(res.gated))
    assert frac_bad > 0.10, frac_bad
    assert int(res.status) & errors.DIVERGED
    assert int(res.status) & errors.GATED
    # no gate, or ids unknown: the rule does not apply (nothing is cut off as an outlier of a
    # known landmark)
    ungated = pf.run(pf.log_from_events(log._replace(u=u), jnp.zeros(3)), cfg, _params(), key=key)
    assert not int(ungated.status) & errors.DIVERGED


def test_robust_update_rides_out_gross_outliers_and_counts_them(sim):
    """``Config(robust=True)`` (Student-t, ν = 5, no gate): a quarter of the ranges replaced by
    gross errors (+2 m) neither throw the estimate off nor register as anything but outliers.
    The clean log has few rows beyond the Student-t's 99 % quantile and is not DIVERGED; the
    corrupted one has more than 10 % and is.  The Gaussian filter without a gate, on the same
    corrupted log, is thrown off (the oracle for "robust" doing something: the truth of the
    simulation)."""
    log, gt_t, gt, lms, seen = sim
    # 50 particles: the Gaussian run below is then test_known_ids_tracks_over_seeds' program
    cfg = pf.Config(motion="unicycle", n_particles=50, capacity=12, K=12, association="known", robust=True)
    key = jax.random.PRNGKey(5)
    clean = pf.run(pf.log_from_events(log, jnp.zeros(3)), cfg, _params(), key=key)
    frac = float(clean.outliers) / float(clean.used)
    assert frac < 0.05, frac
    assert not int(clean.status) & errors.DIVERGED
    assert _err(clean, log, gt_t, gt) < 0.15
    z = np.array(log.z)
    rng = np.random.default_rng(9)
    bad = np.asarray(log.mask) & (rng.random(log.mask.shape) < 0.25)
    z[..., 0] = np.where(bad, z[..., 0] + 2.0, z[..., 0])
    corrupt = log._replace(z=z)
    res = pf.run(pf.log_from_events(corrupt, jnp.zeros(3)), cfg, _params(), key=key)
    frac_bad = float(res.outliers) / float(res.used)
    assert 0.10 < frac_bad < 0.5, frac_bad
    assert int(res.status) & errors.DIVERGED
    err_robust = _err(res, log, gt_t, gt)
    gauss = pf.run(pf.log_from_events(corrupt, jnp.zeros(3)), cfg._replace(robust=False), _params(), key=key)
    err_gauss = _err(gauss, log, gt_t, gt)
    assert err_robust < 0.2 and err_gauss > 2 * err_robust, (err_robust, err_gauss)
    with pytest.raises(InputError, match="robust_nu"):
        pf.run(pf.log_from_events(log, jnp.zeros(3)), cfg, _params()._replace(robust_nu=-1.0), key=key)


def test_optimal_proposal_tracks_with_few_particles():
    """``Config(proposal="optimal")`` (FastSLAM 2.0): with 5 particles it tracks the loop as well
    as the motion proposal does with 50, resamples far less often, and its sightings agree
    with the particles' maps (few gated at 99.9 %), on three seeds.  Oracle: the truth of the
    simulation.  An unknown proposal is an InputError naming config.proposal."""
    errs, gated, res_opt, res_mot = [], [], [], []
    for seed in range(3):
        log, gt_t, gt, lms, seen = _simulate(seed)
        prm = _params()._replace(gate=13.82)
        key = jax.random.PRNGKey(seed)
        opt = pf.run(pf.log_from_events(log, jnp.zeros(3)),
                     pf.Config(motion="unicycle", n_particles=5, capacity=12, K=12, proposal="optimal"), prm, key=key)
        mot = pf.run(pf.log_from_events(log, jnp.zeros(3)),
                     pf.Config(motion="unicycle", n_particles=50, capacity=12, K=12), prm, key=key)
        errs.append((_err(opt, log, gt_t, gt), _err(mot, log, gt_t, gt)))
        gated.append(float(opt.gated) / float(opt.used + opt.gated))
        res_opt.append(int(opt.resamples))
        res_mot.append(int(mot.resamples))
        assert not int(opt.status) & errors.DIVERGED
    e_opt, e_mot = np.array(errs).T
    assert np.max(e_opt) < 0.1 and np.median(e_opt) <= 1.5 * np.median(e_mot), errs
    assert max(gated) < 0.01, gated
    assert max(res_opt) < 0.5 * min(res_mot), (res_opt, res_mot)
    log = _simulate(0)[0]
    with pytest.raises(InputError, match="config.proposal"):
        pf.run(pf.log_from_events(log, jnp.zeros(3)), pf.Config(K=12, proposal="fastslam2"), _params(),
               key=jax.random.PRNGKey(0))


def test_mrclam_fastslam_presets():
    """The MRCLAM FastSLAM presets: "fitted" (default, known ids) is FastSLAM 2.0 with the
    Student-t model and the EKF's learned noise, no gate; "hand" the FastSLAM 1.0 setting with
    the 99.9 % gate; ids hidden keep FastSLAM 1.0; any other preset is an InputError naming it."""
    from jaxslam.data import presets

    cfg, prm = presets.mrclam_fastslam_setup()
    f = presets.MRCLAM_FITTED
    assert cfg.proposal == "optimal" and cfg.robust and prm.gate is None
    np.testing.assert_allclose(np.diag(np.asarray(prm.R)), [f["sigma_r"] ** 2, f["sigma_b"] ** 2])
    np.testing.assert_allclose(np.diag(np.asarray(prm.M_c)), [f["sigma_v"] ** 2, f["sigma_w"] ** 2])
    cfg_h, prm_h = presets.mrclam_fastslam_setup(preset="hand")
    assert cfg_h.proposal == "motion" and not cfg_h.robust and float(prm_h.gate) == 13.82
    cfg_ml, _ = presets.mrclam_fastslam_setup(association="ml")
    assert cfg_ml.proposal == "motion" and cfg_ml.capacity == 32
    with pytest.raises(InputError, match="preset"):
        presets.mrclam_fastslam_setup(preset="learned")


@pytest.mark.parametrize("motion", ["unicycle", "ackermann"])
def test_optimal_moments_match_the_motion_samplers_spread(motion):
    """The "optimal" proposal moves each particle's Gaussian by the same noise model as the
    motion proposal draws from: the moment function's covariance (prior Σ₀ ≠ 0) equals the
    sample covariance of 40 000 draws of the motion sampler started from N(s, Σ₀) (the
    oracle), to the Monte Carlo error (a few %), for the unicycle and the Ackermann car."""
    f = pf.motion_fn(pf.Config(motion=motion))
    sample = pf._sample_fn(f, False)
    moments = pf._moment_fn(f, False)
    s = jnp.asarray([1.0, -2.0, 0.7])
    u = jnp.asarray([2.0, 0.3] if motion == "unicycle" else [3.0, 0.2])
    dt = jnp.asarray(0.05)
    L_M = jnp.linalg.cholesky(jnp.diag(jnp.asarray([0.04, 0.01])))
    floor = jnp.asarray([1e-4, 1e-4, 1e-5])
    S0 = jnp.diag(jnp.asarray([1e-4, 2e-4, 1e-5]))
    # each piece jitted: one program each, not one per operation
    mean, aux = jax.jit(lambda s, S0: moments(s, ((), (), S0), None, u, dt, True, L_M, floor))(s, S0)
    n = 40000

    @jax.jit
    def draw(key):
        k0, k1 = jax.random.split(key)
        starts = s + jax.random.normal(k0, (n, 3)) @ jnp.linalg.cholesky(S0).T
        return jax.vmap(lambda p, k: sample(p, (), k, u, dt, True, L_M, floor)[0])(starts, jax.random.split(k1, n))

    draws = draw(jax.random.PRNGKey(0))
    emp = np.cov(np.asarray(draws).T)
    cov = np.asarray(aux[2])
    np.testing.assert_allclose(np.asarray(mean), np.asarray(jax.jit(f)(s, u, dt)), rtol=1e-12)
    np.testing.assert_allclose(np.diag(emp), np.diag(cov), rtol=0.05)
    corr = lambda c: c / np.sqrt(np.outer(np.diag(c), np.diag(c)))  # noqa: E731
    np.testing.assert_allclose(corr(emp), corr(cov), atol=0.03)


def _fd_jac(fun, x, h=1e-6):
    """Central differences of a vector function (the oracle of the Jacobians below)."""
    x = np.asarray(x, float)
    cols = []
    for i in range(x.size):
        e = np.zeros_like(x)
        e[i] = h
        cols.append((np.asarray(fun(x + e)) - np.asarray(fun(x - e))) / (2 * h))
    return np.stack(cols, axis=1)


@pytest.mark.parametrize("increment", [False, True])
def test_optimal_moments_equal_the_linearised_propagation(increment):
    """The moment function's covariance, term by term: Σ' = F Σ Fᵀ + J_u M J_uᵀ·s_u² +
    diag(floor)·s_f², F and J_u by central differences of the motion model (the oracle), with
    s_u² = 1/Δt, s_f² = Δt for held rates (0 and 0 at Δt = 0) and 1 / 0 on input / non-input
    events of increment logs.  Each term is checked to move the result."""
    f = pf.motion_fn(pf.Config(motion="increment" if increment else "unicycle"))
    moments = jax.jit(pf._moment_fn(f, increment), static_argnums=())
    s = np.array([1.0, -2.0, 0.7])
    u = np.array([0.3, 0.1] if increment else [2.0, 0.3])
    L_M = np.linalg.cholesky(np.diag([0.04, 0.01]))
    floor = np.array([1e-3, 2e-3, 5e-4])
    S0 = np.array([[1e-2, 2e-3, 1e-3], [2e-3, 2e-2, -1e-3], [1e-3, -1e-3, 5e-3]])
    for dt, is_in in ((0.05, True), (0.0, True), (0.05, False)):
        mean, aux = moments(jnp.asarray(s), ((), (), jnp.asarray(S0)), None, jnp.asarray(u), jnp.asarray(dt),
                            jnp.asarray(is_in), jnp.asarray(L_M), jnp.asarray(floor))
        F = _fd_jac(lambda x: f(jnp.asarray(x), jnp.asarray(u), jnp.asarray(dt)), s)
        Ju = _fd_jac(lambda v: f(jnp.asarray(s), jnp.asarray(v), jnp.asarray(dt)), u)
        if increment:
            su2 = sf2 = 1.0 if is_in else 0.0
        else:
            su2, sf2 = (1.0 / dt, dt) if dt > 0 else (0.0, 0.0)
        ref = F @ S0 @ F.T + Ju @ L_M @ L_M.T @ Ju.T * su2 + np.diag(floor) * sf2
        np.testing.assert_allclose(np.asarray(aux[2]), ref, rtol=1e-7, atol=1e-12)
        np.testing.assert_allclose(np.asarray(mean)[:2], np.asarray(f(s, u, dt))[:2], rtol=1e-12)
        if su2 > 0:  # neither the floor nor the input term is negligible here
            assert np.abs(Ju @ L_M @ L_M.T @ Ju.T * su2).max() > 1e-4
            assert np.abs(np.diag(floor) * sf2).max() > 1e-5


def test_ml_association_puts_the_pose_covariance_in_S():
    """``associate_ml(pose_cov=Σ_s)``: S = H Σ_l Hᵀ + R + G_s Σ_s G_sᵀ (NumPy oracle with
    Jacobians by central differences).  A detection whose d² is between the gate and the
    new-landmark threshold without Σ_s (ignored) matches the landmark once the pose is uncertain
    enough; the same d² in NumPy decides both."""
    pose = np.array([0.0, 0.0, 0.1])
    lm = np.array([4.0, 1.0])
    C = np.diag([1e-3, 1e-3])
    R = np.diag([0.05**2, 0.01**2])
    zhat = np.asarray(rb.observe(jnp.asarray(pose), jnp.asarray(lm)))
    z = zhat + np.array([0.0, 0.06])  # a bearing off by 0.06 rad
    mean = np.zeros((4, 2)); mean[0] = lm
    cov = np.tile(np.eye(2), (4, 1, 1)); cov[0] = C
    active = np.array([True, False, False, False])
    Sig = np.diag([0.01, 0.01, 0.01**2 * 4])
    H = _fd_jac(lambda l: rb.observe(jnp.asarray(pose), jnp.asarray(l)), lm)
    Gs = _fd_jac(lambda x: rb.observe(jnp.asarray(x), jnp.asarray(lm)), pose)
    nu = z - zhat
    gate, new_thr = 9.21, 30.0
    assoc = jax.jit(pf.associate_ml)
    for pc in (None, Sig):
        S = H @ C @ H.T + R + (0 if pc is None else Gs @ pc @ Gs.T)
        d2 = nu @ np.linalg.solve(S, nu)
        want = 0 if d2 <= gate else (1 if d2 > new_thr else -1)  # id 1 = counter of a new landmark
        ids, counter, new, amb = assoc(jnp.asarray(pose), jnp.asarray(mean), jnp.asarray(cov), jnp.asarray(active),
                                       jnp.asarray(1, jnp.int32), jnp.asarray(z[None]), jnp.asarray([True]),
                                       jnp.asarray(R), gate, new_thr,
                                       None if pc is None else jnp.asarray(pc))
        assert int(ids[0]) == want, (pc is None, d2)
        assert bool(amb[0]) == (want == -1)
        if pc is None:
            assert gate < d2 < new_thr  # the case is the one the docstring describes
        else:
            assert d2 <= gate


def test_prune_bookkeeping_by_hand():
    """``_prune`` on one particle, cases written out: window 2 s, 2 matches needed.  Slot 0:
    tentative, 3 s old, one match in its window and one more row now (too late to count) →
    removed; slot 1: 3 s old with 2 matches → confirmed and kept; slot 2: 1 s old → matched
    now, stays tentative; slot 3: registered in this event → age 0, no match."""
    from jaxslam.filters import fastslam as fs

    p = fs.init(jnp.zeros(3), 1, 4, 2, aux=(jnp.zeros((1,), jnp.int32), jnp.asarray([[5, 3, 1, 1]], jnp.int32),
                                             jnp.asarray([[3.0, 3.0, 1.0, 7.0]]), jnp.asarray([[1, 2, 0, 9]], jnp.int32),
                                             jnp.zeros((1, 4), bool)), aux_per_particle=True)
    p = p._replace(active=jnp.asarray([[True, True, True, True]]), ids=jnp.asarray([[0, 1, 2, 3]], jnp.int32))
    before = jnp.asarray([[True, True, True, False]])
    pids = jnp.asarray([[0, 2, 3, -1]], jnp.int32)
    used = jnp.asarray([[True, True, False, False]])
    prm = pf.default_params()._replace(prune_window_s=2.0, prune_min_obs=2.0)
    q, n = pf._prune(p, before, pids, used, 2, prm)
    age, n_match, confirmed = (np.asarray(a)[0] for a in q.aux[2:5])
    assert int(n) == 1
    np.testing.assert_array_equal(np.asarray(q.active)[0], [False, True, True, True])
    np.testing.assert_array_equal(np.asarray(q.ids)[0], [-1, 1, 2, 3])
    np.testing.assert_array_equal(age, [3.0, 3.0, 1.0, 0.0])
    np.testing.assert_array_equal(n_match, [0, 2, 1, 0])
    np.testing.assert_array_equal(confirmed, [False, True, False, False])
    np.testing.assert_array_equal(np.asarray(q.aux[1])[0], [0, 3, 1, 1])  # the removed slot's count cleared


@pytest.mark.parametrize("proposal", ["optimal", "motion"])
def test_ml_pruning_removes_clutter_and_frees_slots(sim, proposal):
    """Ids unknown with clutter: one spurious detection in 30 % of the scans (seen once each).
    Without pruning every clutter row takes a slot and the map overflows; with the planar EKF's
    pruning rule (2 matches within 2 s) each particle removes the clutter landmarks, reuses
    their slots, and keeps one landmark per true one seen.  Oracle: the simulation's truth and
    the count of clutter rows added."""
    log, gt_t, gt, lms, seen = sim
    L = pf.log_from_events(log, jnp.zeros(3))
    rng = np.random.default_rng(3)
    z, mask = np.asarray(L.z).copy(), np.asarray(L.mask).copy()
    n_clutter = 0
    for t in np.flatnonzero(mask.any(axis=1)):
        free = np.flatnonzero(~mask[t])
        if free.size and rng.random() < 0.3:
            z[t, free[0]] = (rng.uniform(2.0, 6.0), rng.uniform(-1.0, 1.0))
            mask[t, free[0]] = True
            n_clutter += 1
    L = L._replace(z=jnp.asarray(z), mask=jnp.asarray(mask))
    cfg = pf.Config(motion="unicycle", n_particles=10 if proposal == "optimal" else 40, capacity=24, K=12,
                    association="ml", proposal=proposal)
    prm = _params()._replace(gate=9.21, new_threshold=30.0)
    run = jax.jit(pf.run, static_argnames="config")
    if proposal == "optimal":  # (the motion proposal's run without pruning: the same overflow)
        # pf.run itself: the configuration of test_ml_association_with_the_optimal_proposal, whose
        # compiled run serves this one (the jit above would compile it again)
        plain = pf.run(L, cfg, prm, key=jax.random.PRNGKey(1))
        assert int(plain.overflow) > 0 and int(plain.status) & errors.CAPACITY_OVERFLOW
        assert float(plain.pruned) == 0.0
    res = run(L, config=cfg, params=prm._replace(prune_window_s=2.0, prune_min_obs=2.0), key=jax.random.PRNGKey(1))
    assert int(res.overflow) == 0
    act = np.asarray(res.map.active)
    d = np.linalg.norm(np.asarray(res.map.mean)[act][:, None] - lms[None], axis=2)
    assert act.sum() == len(seen) and np.max(np.min(d, axis=1)) < 0.2 and len(set(np.argmin(d, axis=1))) == act.sum()
    assert 0.9 * n_clutter <= float(res.pruned) <= n_clutter, (float(res.pruned), n_clutter)
    assert _err(res, log, gt_t, gt) < 0.1


def test_ml_new_landmarks_take_free_slots_in_order():
    """``associate_ml(free_slots=True)``: the k-th new detection of an event takes the particle's
    k-th free slot (slots freed by pruning reused), one beyond the free slots gets id ``cap``
    (the core's capacity overflow); without it, the ids counter, counter + 1, …"""
    cap = 5
    mean = np.zeros((cap, 2)); mean[1] = (3.0, 0.0); mean[3] = (0.0, 3.0)
    active = np.array([False, True, False, True, False])
    cov = np.tile(0.01 * np.eye(2), (cap, 1, 1))
    z = np.array([[5.0, 1.0], [3.0, 0.0], [6.0, -1.0], [7.0, 2.0], [8.0, -2.0]])  # row 1 sees slot 1
    R = np.diag([0.05**2, 0.01**2])
    args = (jnp.zeros(3), jnp.asarray(mean), jnp.asarray(cov), jnp.asarray(active), jnp.asarray(7, jnp.int32),
            jnp.asarray(z), jnp.ones(5, bool), jnp.asarray(R), 9.21, 30.0)
    assoc = jax.jit(pf.associate_ml, static_argnames="free_slots")  # one program each, not one per operation
    ids, counter, new, _ = assoc(*args, free_slots=True)
    np.testing.assert_array_equal(np.asarray(ids), [0, 1, 2, 4, cap])
    assert int(counter) == 11 and np.asarray(new).tolist() == [True, False, True, True, True]
    ids_c, _, _, _ = assoc(*args)
    np.testing.assert_array_equal(np.asarray(ids_c), [7, 1, 8, 9, 10])


def test_pruning_needs_ml_and_sane_numbers(sim):
    log = pf.log_from_events(sim[0], jnp.zeros(3))
    prm = _params()._replace(prune_window_s=2.0)
    with pytest.raises(InputError, match="prune_window_s.*ml"):
        pf.run(log, pf.Config(K=12, association="known"), prm, key=jax.random.PRNGKey(0))
    with pytest.raises(InputError, match="prune_window_s.*ml"):  # under jit too (a static choice)
        jax.jit(pf.run, static_argnames="config")(log, config=pf.Config(K=12, association="known"), params=prm,
                                                  key=jax.random.PRNGKey(0))
    cfg = pf.Config(K=12, association="ml")
    with pytest.raises(InputError, match="prune_window_s"):
        pf.run(log, cfg, prm._replace(prune_window_s=-1.0), key=jax.random.PRNGKey(0))
    with pytest.raises(InputError, match="prune_min_obs"):
        pf.run(log, cfg, prm._replace(prune_min_obs=1.5), key=jax.random.PRNGKey(0))
