"""Range-only systems (issue 9): range model vs hand Jacobians, a 3D CV tag with a common
bias (bias bound, ANEES and mean NIS in their χ² bounds over vmapped Monte-Carlo runs),
a Plaza-style 2D odometry + unknown-beacon SLAM with bias and outliers, float32; the UTIL ToF
height update (H1) and Plaza localisation with surveyed beacons."""

import jax
import jax.numpy as jnp
import numpy as np

from jaxslam import errors, metrics
from jaxslam.data.events import merge_events
from jaxslam.systems import plaza_range as pr
from jaxslam.systems import util_range as ur
from jaxslam.systems.biased_range import _cast_params, range_observe

ANCHORS = np.array([[-3.0, -4.0, 0.2], [-3.2, 3.8, 2.9], [3.7, 3.7, 0.2], [4.1, -4.3, 3.2],
                    [-3.0, -4.4, 3.0], [3.9, -3.8, 0.2], [4.1, 3.9, 3.1], [-3.2, 3.4, 0.2]])


# one compiled program per shape (eager jacfwd compiles every primitive it dispatches)
_range_and_jac = jax.jit(lambda s, l: (range_observe(s, l),
                                       jax.jacfwd(range_observe, argnums=(0, 1))(s, l)))


def test_range_jacobian_matches_hand_oracle():
    rng = np.random.default_rng(0)
    for d, nr in ((3, 7), (2, 4)):
        s = rng.normal(size=nr)
        l = rng.normal(size=d) * 3
        z, (Hs, Hl) = _range_and_jac(jnp.asarray(s), jnp.asarray(l))
        u = (s[:d] - l) / np.linalg.norm(s[:d] - l)
        Hs_hand = np.zeros((1, nr))
        Hs_hand[0, :d] = u
        Hs_hand[0, -1] = 1.0  # ∂z/∂b
        np.testing.assert_allclose(np.asarray(Hs), Hs_hand, atol=1e-14)
        np.testing.assert_allclose(np.asarray(Hl), -u[None, :], atol=1e-14)
        assert float(z[0]) == np.linalg.norm(s[:d] - l) + s[-1]
    # coincident point: finite Jacobian, no NaN
    _, (Hs, _) = _range_and_jac(jnp.zeros(7), jnp.zeros(3))
    assert np.all(np.isfinite(np.asarray(Hs)))


def test_odometry_jacobians_match_hand_oracle():
    s = np.array([1.0, -2.0, 0.7, 2.5])
    u = np.array([0.4, 0.05])
    p = pr.PARAMS
    jac_and_q = jax.jit(lambda s, u, p: (jax.jacfwd(pr.odo_motion)(s, u),
                                         pr.odo_process_noise(s, u, 0.2, p)))
    F, Q = jac_and_q(jnp.asarray(s), jnp.asarray(u), _cast_params(p, jnp.float64))
    F, Q = np.asarray(F), np.asarray(Q)
    c, sn = np.cos(s[2]), np.sin(s[2])
    F_hand = np.eye(4)
    F_hand[0, 2] = -u[0] * sn
    F_hand[1, 2] = u[0] * c
    np.testing.assert_allclose(F, F_hand, atol=1e-15)
    G = np.array([[c, 0], [sn, 0], [0, 1], [0, 0]])
    sd = p.alpha_d * 0.4 + p.sigma_d0 * np.sqrt(0.2)
    st = p.alpha_th * 0.05 + p.beta_th * 0.4 + p.sigma_th0 * np.sqrt(0.2)
    Q_hand = G @ np.diag([sd**2, st**2]) @ G.T
    Q_hand[3, 3] += p.q_bias * 0.2
    np.testing.assert_allclose(Q, Q_hand, rtol=1e-12, atol=1e-18)


# --- 3D constant-velocity tag, 8 known anchors, common bias -------------------------------

DT3, T3, Q_ACC, SIG_R, BIAS = 0.012, 1500, 0.5, 0.1, -0.2


@jax.jit  # one program for every run's simulation (eager, it compiled each primitive)
def _sim_tag(key):
    """WNA constant-velocity truth (exact discretisation) and round-robin biased ranges."""
    k1, k2 = jax.random.split(key)
    Qd = ur.cv_process_noise(DT3, Q_ACC, 0.0, jnp.float64)[:6, :6]
    Lq = jnp.linalg.cholesky(Qd + 1e-18 * jnp.eye(6))
    F = jax.jacfwd(lambda x: ur.cv_motion(jnp.concatenate([x, jnp.zeros(1)]), None, DT3)[:6])(jnp.zeros(6))
    x0 = jnp.array([0.5, -0.5, 1.2, 0.0, 0.0, 0.0])

    def step(x, w):
        x = F @ x + Lq @ w
        return x, x

    _, X = jax.lax.scan(step, x0, jax.random.normal(k1, (T3, 6)))
    X = jnp.concatenate([x0[None], X[:-1]])  # truth at the event times, first at x0
    aid = jnp.arange(T3) % 8
    r = jnp.linalg.norm(X[:, :3] - jnp.asarray(ANCHORS)[aid], axis=1) + BIAS
    return X, r + SIG_R * jax.random.normal(k2, (T3,))


def test_cv_tag_bias_and_consistency_monte_carlo():
    n_runs = 24
    t = np.arange(T3) * DT3
    aid = np.arange(T3) % 8
    log = ur.log_from_events(ur.util_events(t, aid, np.ones(T3)), np.arange(8), anchors=ANCHORS,
                             dtype=jnp.float64)
    # one call of the compiled _sim_tag per run (the draws of vmapping it over the keys)
    X, R = (jnp.stack(a) for a in zip(*map(_sim_tag, jax.random.split(jax.random.PRNGKey(3), n_runs))))
    p = _cast_params(ur.Params(sigma_r=SIG_R, q_acc=Q_ACC, q_bias=1e-12, p0_pos=0.3,
                               p0_vel=0.1, p0_bias=0.5, gate=None), jnp.float64)
    cfg = ur.Config(height=False)
    # the public run under an outer jit + vmap (the Monte Carlo runs batch the ranges)
    res = jax.jit(jax.vmap(lambda z: ur.run(log._replace(z=z[:, None, None]), cfg, p)))(R)
    x_true = np.concatenate([np.asarray(X[:, -1]), np.full((n_runs, 1), BIAS)], axis=1)
    x_est = np.asarray(res.final.x[:, :7])
    P_est = np.asarray(res.final.P[:, :7, :7])
    e = x_est - x_true
    nees = np.einsum("ri,rij,rj->r", e, np.linalg.inv(P_est), e)
    lo, hi = metrics.anees_bounds(7, n_runs)
    assert lo <= nees.mean() <= hi, (nees.mean(), lo, hi)
    # bias: every run within 4 σ of the truth, and σ_b well below the prior's 0.5 m
    sb = np.asarray(res.bias_sigma)
    assert np.all(np.abs(np.asarray(res.bias_final) - BIAS) < 4 * sb)
    assert np.all(sb < 0.03)
    # NIS over all updates after the first second (white for a consistent filter)
    nis = np.asarray(res.nis)[:, 100:]
    lo, hi = metrics.mean_chi2_bounds(nis.size, nis.size)
    assert lo <= nis.mean() <= hi, (nis.mean(), lo, hi)
    assert np.all(np.asarray(res.n_used) == T3)
    assert np.all(np.asarray(res.status) == 0)


# --- Plaza-style 2D odometry + beacons, unknown beacons, bias, outliers -------------------

_ate = jax.jit(metrics.ate)  # one program per dtype instead of one per primitive

BEACONS = np.array([[-18.0, 5.0], [12.0, -14.0], [20.0, 12.0], [-5.0, 22.0]])
BIDS = np.array([0, 1, 5, 6])
BIAS2 = 2.0


def _sim_plaza(seed=0, n=3000, dt=0.2):
    rng = np.random.default_rng(seed)
    # a lawn-mower-ish loop: speed 1 m/s, turning rate varying slowly
    d_true = np.full(n, 1.0 * dt)
    w = 0.08 * np.sin(np.arange(n) * dt / 40.0) + 0.05
    dth_true = w * dt
    pose = np.zeros((n + 1, 3))
    pose[0] = (0.0, 0.0, 0.3)
    for k in range(n):
        x, y, th = pose[k]
        pose[k + 1] = (x + d_true[k] * np.cos(th), y + d_true[k] * np.sin(th), th + dth_true[k])
    t_dr = (np.arange(n) + 1) * dt
    d_meas = d_true * (1 + 0.02 * rng.normal(size=n))
    dth_meas = dth_true + 0.02 * np.abs(dth_true) * rng.normal(size=n) + 0.001 * rng.normal(size=n)
    # ranges every 0.5 s, round-robin, at DR times (pose after that increment)
    k_r = np.arange(2, n, 5)
    node = BIDS[np.arange(k_r.size) % 4]
    bpos = BEACONS[np.arange(k_r.size) % 4]
    rr = np.linalg.norm(pose[k_r + 1, :2] - bpos, axis=1) + BIAS2 + 0.3 * rng.normal(size=k_r.size)
    out = rng.random(k_r.size) < 0.05
    rr[out] += rng.uniform(3.0, 7.0, size=out.sum())
    return t_dr, np.stack([d_meas, dth_meas], 1), t_dr[k_r], node, rr, pose, out.sum()


def _plaza_run(dtype):
    t_dr, dr, t_r, node, rr, pose, n_out = _sim_plaza()
    log = pr.plaza_events(t_dr, dr, t_r, node, rr)
    params = pr.Params(sigma_r=0.4, sigma_bias0=3.0, min_points=20, min_spread=4.0)
    res = pr.run(pr.log_from_events(log, pose[0], BIDS, dtype=dtype), pr.Config(window=60), params)
    # truth at the events: DR-event poses (ranges share DR times)
    k = np.searchsorted(t_dr, log.t)
    return res, pose[k + 1, :2], n_out


def test_plaza_style_slam_converges_with_bias_and_outliers():
    res, true, n_out = _plaza_run(jnp.float64)
    assert int(res.n_registered) == 4 and bool(np.all(np.asarray(res.active)))
    ate = float(_ate(res.pos, jnp.asarray(true)))
    assert ate < 1.0, ate
    B = np.asarray(res.landmarks)
    order = [list(BIDS).index(i) for i in np.asarray(res.landmark_ids)]
    berr = np.linalg.norm(B - BEACONS[order], axis=1)
    assert np.all(berr < 1.5), berr
    assert abs(float(res.bias_final) - BIAS2) < max(0.5, 3 * float(res.bias_sigma)), float(res.bias_final)
    assert int(res.n_gated) >= 0.5 * n_out  # most outliers rejected
    assert not (int(res.status) & (errors.NON_FINITE | errors.NOT_PSD))


def test_plaza_nan_range_of_an_unmapped_beacon_is_flagged():
    # a mapped beacon's NaN range is flagged by the update; an unmapped one's used to be dropped
    # from the initialisation buffer with no flag
    t_dr, dr, t_r, node, rr, pose, _ = _sim_plaza()
    rr = rr.copy()
    rr[0] = np.nan  # the first range: no beacon is mapped yet
    log = pr.plaza_events(t_dr, dr, t_r, node, rr)
    params = pr.Params(sigma_r=0.4, sigma_bias0=3.0, min_points=20, min_spread=4.0)
    res = pr.run(pr.log_from_events(log, pose[0], BIDS), pr.Config(window=60), params)
    status = np.asarray(res.status)
    assert int(status) & errors.MASKED_INPUT
    assert int(res.n_registered) == 4 and np.all(np.isfinite(np.asarray(res.pos)))


def test_float32_runs_finite():
    res, true, _ = _plaza_run(jnp.float32)
    assert res.pos.dtype == jnp.float32
    assert np.all(np.isfinite(np.asarray(res.pos))) and np.isfinite(float(res.bias_final))
    assert not (int(res.status) & (errors.NON_FINITE | errors.NOT_PSD))
    assert float(_ate(res.pos, jnp.asarray(true, jnp.float32))) < 1.5
    # UTIL path in float32 as well
    t = np.arange(400) * DT3
    X, R = _sim_tag(jax.random.PRNGKey(0))
    log = ur.util_events(t, np.arange(400) % 8, np.asarray(R[:400]))
    r = ur.run(ur.log_from_events(log, np.arange(8), anchors=ANCHORS, dtype=jnp.float32))
    assert r.pos.dtype == jnp.float32 and np.all(np.isfinite(np.asarray(r.pos)))
    assert not (int(r.status) & (errors.NON_FINITE | errors.NOT_PSD))


def test_merge_events_contract_used():
    # util_events: K = 1, one event per range, no input
    log = ur.util_events([0.0, 0.1, 0.2], [0, 1, 2], [1.0, 2.0, 3.0])
    assert log.z.shape == (3, 1, 1) and log.stats["K"] == 1 and merge_events is not None


# --- UTIL ToF height update (H1) -------------------------------------------------------------

SIG_H, C_TOF = 0.02, -0.014


def test_height_update_reduces_vertical_error():
    X, R = _sim_tag(jax.random.PRNGKey(7))
    X, R = np.asarray(X), np.asarray(R)
    t = np.arange(T3) * DT3
    aid = np.arange(T3) % 8
    rng = np.random.default_rng(7)
    # laser rows at every 4th range time (coincident times: K = 2 slots), 5 outliers (+0.5 m)
    kh = np.arange(0, T3, 4)
    h = X[kh, 2] - ur.TAG_Z + C_TOF + SIG_H * rng.normal(size=kh.size)
    bad = rng.choice(np.arange(20, kh.size), 5, replace=False)
    h[bad] += 0.5
    params = ur.Params(sigma_r=SIG_R, q_acc=Q_ACC, q_bias=1e-12, sigma_h=SIG_H, tof_offset=C_TOF, gate=9.0)
    log0 = ur.util_events(t, aid, R)
    logh = ur.util_events(t, aid, R, tof_t=t[kh], tof=h)
    assert logh.z.shape == (T3, 2, 1) and logh.stats["n_meas"] == T3 + kh.size
    cfg = ur.Config()
    r0 = ur.run(ur.log_from_events(log0, np.arange(8), anchors=ANCHORS), cfg, params)
    rh = ur.run(ur.log_from_events(logh, np.arange(8), anchors=ANCHORS), cfg, params)
    # range-only path: no height rows, counts zero; (almost) every range used in both runs
    assert int(r0.n_height_used) == 0 and int(r0.n_height_gated) == 0
    assert min(int(rh.n_used), int(r0.n_used)) >= T3 - 10
    assert int(rh.n_height_gated) >= 5 and np.all(np.asarray(rh.height_gated)[kh[bad]] == 1)
    assert int(rh.n_height_used) + int(rh.n_height_gated) == kh.size
    late = slice(200, None)
    ez0 = np.asarray(r0.pos)[late, 2] - X[late, 2]
    ezh = np.asarray(rh.pos)[late, 2] - X[late, 2]
    rz0, rzh = np.sqrt(np.mean(ez0**2)), np.sqrt(np.mean(ezh**2))
    assert rzh < 0.6 * rz0, (rzh, rz0)
    # stated σ bound: vertical errors consistent with the filter's own variance
    vz = np.asarray(rh.pos_var)[late, 2]
    assert np.mean(ezh**2 / vz) < 2.0
    assert np.mean(vz) < np.mean(np.asarray(r0.pos_var)[late, 2])
    assert not (int(rh.status) & (errors.NON_FINITE | errors.NOT_PSD))


# --- Plaza localisation with surveyed beacons ------------------------------------------------

def test_plaza_known_beacons_recover_bias():
    t_dr, dr, t_r, node, rr, pose, n_out = _sim_plaza(seed=1)
    log = pr.plaza_events(t_dr, dr, t_r, node, rr)
    params = pr.Params(sigma_r=0.4, sigma_bias0=3.0)
    res = pr.run(pr.log_from_events(log, pose[0], BIDS, beacons=BEACONS), pr.Config(), params)
    k = np.searchsorted(t_dr, log.t)
    true = pose[k + 1, :2]
    b, sb = float(res.bias_final), float(res.bias_sigma)
    assert abs(b - BIAS2) < 3 * sb and sb < 0.3, (b, sb)  # prior σ 3 m; q_b walk sets the floor
    # beacons held exactly (zero covariance), all counted as registered, none buffered
    np.testing.assert_array_equal(np.asarray(res.landmarks), BEACONS)
    assert np.all(np.asarray(res.landmark_cov) == 0) and int(res.n_registered) == 4
    assert int(res.n_unmapped) == 0
    err = np.linalg.norm(np.asarray(res.pos) - true, axis=1)
    assert np.sqrt(np.mean(err**2)) < 0.5  # raw (no alignment): the map frame is the survey's
    assert int(res.n_gated) >= 0.5 * n_out
    assert not (int(res.status) & (errors.NON_FINITE | errors.NOT_PSD))
