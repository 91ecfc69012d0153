"""Tests of the generic EKF core (jaxslam.filters.ekf).

Oracles: a closed-form linear Kalman filter written here in NumPy, stacked
NumPy updates, SciPy chi-square quantiles, finite differences (check_grads)
and chi-square Monte Carlo bounds at fixed seeds.
"""

import functools

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

from jaxslam import errors
from jaxslam.errors import InputError
from jaxslam.filters import ekf
from jaxslam.metrics import anees_bounds, mean_chi2_bounds, windowed_mean

from cv_model import DT, F_CV, G_CV, H_CV, P0_CV, Q_CV, R_CV, X0_CV, f_cv, h_pos  # noqa: F401


# --------------------------------------------------------------------------
# NumPy oracle
# --------------------------------------------------------------------------

def np_kf(x0, P0, us, zs, masks=None, predict_first=True, F=F_CV, G=G_CV, H=H_CV,
          Q=Q_CV, R=R_CV):
    """Closed-form Kalman filter; masked components dropped from the update."""
    x, P = x0.copy(), P0.copy()
    means, covs = [], []
    for t in range(zs.shape[0]):
        def upd(x, P):
            mk = np.ones(zs.shape[1], bool) if masks is None else masks[t]
            if not mk.any():
                return x, P
            Hs, Rs, zv = H[mk], R[np.ix_(mk, mk)], zs[t][mk]
            S = Hs @ P @ Hs.T + Rs
            K = np.linalg.solve(S, Hs @ P).T
            x = x + K @ (zv - Hs @ x)
            A = np.eye(len(x)) - K @ Hs
            return x, A @ P @ A.T + K @ Rs @ K.T

        if predict_first:
            x, P = F @ x + G @ us[t], F @ P @ F.T + Q
            x, P = upd(x, P)
            means.append(x), covs.append(P)
        else:
            x, P = upd(x, P)
            means.append(x), covs.append(P)
            x, P = F @ x + G @ us[t], F @ P @ F.T + Q
    return np.array(means), np.array(covs)


def simulate_cv(rng, T, runs=None):
    shape = (T,) if runs is None else (runs, T)
    us = rng.normal(size=shape + (2,)) * 0.3
    lead = () if runs is None else (runs,)
    x = X0_CV + rng.multivariate_normal(np.zeros(4), P0_CV, size=lead or None)
    xs, zs = [], []
    Lq = np.linalg.cholesky(Q_CV)
    Lr = np.linalg.cholesky(R_CV)
    for t in range(T):
        u = us[..., t, :]
        x = x @ F_CV.T + u @ G_CV.T + rng.normal(size=lead + (4,)) @ Lq.T
        xs.append(x)
        zs.append(x @ H_CV.T + rng.normal(size=lead + (2,)) @ Lr.T)
    ax = 0 if runs is None else 1
    return np.stack(xs, ax), us, np.stack(zs, ax)


_JIT = {}


def _cached(kind, h, residual, gate, mask, extra):
    """One jitted update per (model, static options): masks and numeric gates
    are traced, so tests reuse compilations (eager dispatch is slow)."""
    gstatic = gate if callable(gate) else None
    key = (kind, h, residual, gstatic, mask is None, gate is None, extra)
    if key not in _JIT:
        def fn(s, z, R, args, mask, gate_v):
            g = gstatic if gstatic is not None else gate_v
            if kind == "u":
                return ekf.update(s, z, h, R, *args, mask=mask, gate=g, residual=residual)
            return ekf.update_batch(s, z, h, R, *args, masks=mask, gate=g,
                                    residual=residual, sequential=extra)
        _JIT[key] = jax.jit(fn)
    return _JIT[key]


def jupdate(s, z, h, R, *args, mask=None, gate=None, residual=None):
    fn = _cached("u", h, residual, gate, mask, None)
    return fn(s, z, R, args, mask, None if callable(gate) else gate)


def jupdate_batch(s, zs, h, R, *args, masks=None, gate=None, residual=None, sequential=False):
    fn = _cached("b", h, residual, gate, masks, sequential)
    return fn(s, zs, R, args, masks, None if callable(gate) else gate)


@functools.lru_cache(maxsize=None)
def cv_runner(predict_first=True):
    """Jitted CV-model filter_scan shared by several tests (one compilation
    per dtype/shape)."""

    @jax.jit
    def run(x0, P0, us, zs, masks, gate):
        return ekf.filter_scan(f_cv, h_pos, x0, P0, us, zs, masks, Q_CV, R_CV, gate=gate,
                               save_cov=True, predict_first=predict_first)

    return run


def np_nees(err, covs):
    return np.einsum("...i,...i->...", err, np.linalg.solve(covs, err[..., None])[..., 0])


def assert_close(a, b, tol=1e-12):
    a = np.asarray(a)
    b = np.asarray(b)
    scale = max(1.0, float(np.max(np.abs(b))))
    np.testing.assert_allclose(a, b, rtol=0, atol=tol * scale)


# --------------------------------------------------------------------------
# Linear-Gaussian oracle
# --------------------------------------------------------------------------

def test_predict_update_equal_closed_form_kf():
    rng = np.random.default_rng(0)
    _, us, zs = simulate_cv(rng, 30)
    ref_m, ref_P = np_kf(X0_CV, P0_CV, us, zs)
    step = jax.jit(lambda s, u, z: ekf.update(ekf.predict(s, f_cv, u, Q_CV), z, h_pos, R_CV))
    s = ekf.Gaussian(jnp.asarray(X0_CV), jnp.asarray(P0_CV))
    for t in range(zs.shape[0]):
        s, info = step(s, us[t], zs[t])
        assert_close(s.mean, ref_m[t])
        assert_close(s.cov, ref_P[t])
        assert bool(info.accepted) and int(info.status) == 0 and int(info.dof) == 2
    # The NIS uses the prior S of the last step: recompute it in NumPy.
    Pp = F_CV @ ref_P[-2] @ F_CV.T + Q_CV
    xp = F_CV @ ref_m[-2] + G_CV @ us[-1]
    nu = zs[-1] - H_CV @ xp
    S = H_CV @ Pp @ H_CV.T + R_CV
    np.testing.assert_allclose(float(info.nis), nu @ np.linalg.solve(S, nu), rtol=1e-12)
    np.testing.assert_allclose(np.asarray(info.S), S, rtol=1e-12)


@pytest.mark.parametrize("predict_first", [True, False])
def test_filter_scan_equals_closed_form_kf(predict_first):
    rng = np.random.default_rng(1)
    _, us, zs = simulate_cv(rng, 60)
    masks = rng.random(zs.shape) > 0.3
    masks[10] = False  # a step with nothing valid
    zs = np.where(masks, zs, np.nan)  # garbage where masked
    ref_m, ref_P = np_kf(X0_CV, P0_CV, us, zs, masks, predict_first=predict_first)
    post = cv_runner(predict_first)(X0_CV, P0_CV, us, zs, masks, np.float64(np.inf))
    assert_close(post.means, ref_m)
    assert_close(post.covs, ref_P)
    assert_close(post.cov_diags, np.diagonal(ref_P, axis1=1, axis2=2))
    assert_close(post.final.mean, ref_m[-1])
    assert_close(post.final.cov, ref_P[-1])
    np.testing.assert_array_equal(np.asarray(post.dof), masks.sum(1))
    assert int(post.nis[10]) == 0 and np.all(np.asarray(post.status) == 0)


def test_predict_with_noise_jacobian():
    rng = np.random.default_rng(2)
    A = rng.normal(size=(4, 4))
    P = A @ A.T + np.eye(4)
    L = rng.normal(size=(4, 2))
    Qw = np.array([[0.3, 0.1], [0.1, 0.2]])
    s = ekf.Gaussian(jnp.asarray(X0_CV), jnp.asarray(P))
    u = np.array([0.2, -0.1])
    ref = F_CV @ P @ F_CV.T + L @ Qw @ L.T
    for out in (
        ekf.predict(s, f_cv, u, Qw, noise_jac=L),
        ekf.predict(s, f_cv, u, Qw, noise_jac=lambda x, u: jnp.asarray(L)),
        ekf.predict_additive(s, f_cv, u, Qw, L),
    ):
        assert_close(out.cov, ref)
        assert_close(out.mean, F_CV @ X0_CV + G_CV @ u)


# --------------------------------------------------------------------------
# Monte Carlo consistency
# --------------------------------------------------------------------------

def _mc_linear(runs, T, seed):
    rng = np.random.default_rng(seed)
    xs, us, zs = simulate_cv(rng, T, runs)
    run = jax.jit(jax.vmap(
        lambda us, zs: ekf.filter_scan(f_cv, h_pos, X0_CV, P0_CV, us, zs, None, Q_CV,
                                       R_CV, save_cov=True)
    ))
    post = run(us, zs)
    err = np.asarray(post.means) - xs
    nees = np_nees(err, np.asarray(post.covs))
    return nees, np.asarray(post.nis)


def _check_consistency(nees, nis, min_inside):
    runs, T = nees.shape
    n, m = 4, 2
    # Bounds from SciPy: they also check jaxslam's chi-square quantiles.
    lo = stats.chi2.ppf(0.025, runs * n) / runs
    hi = stats.chi2.ppf(0.975, runs * n) / runs
    np.testing.assert_allclose(anees_bounds(n, runs), (lo, hi), rtol=1e-9)
    anees_t = nees.mean(0)  # independent across runs at each time step
    inside = np.mean((anees_t > lo) & (anees_t < hi))
    assert inside >= min_inside, (inside, anees_t.min(), anees_t.max())
    # A time average of equally distributed, correlated per-step ANEES values
    # has at most the variance of one step, so the one-step bounds are
    # conservative for the whole-run mean and for each window's mean (early
    # under- and late over-confidence must not cancel).
    assert lo < anees_t.mean() < hi, anees_t.mean()
    win = windowed_mean(nees, DT * np.arange(1, T + 1), window_s=DT * T / 4)
    assert win.mean.shape == (4,) and np.all(win.count == runs * T // 4)
    assert np.all((win.mean > lo) & (win.mean < hi)), win.mean
    # Innovations of the exact KF are white, so all NIS pool into one test.
    nlo, nhi = mean_chi2_bounds(m * runs * T, runs * T)
    np.testing.assert_allclose(
        (nlo, nhi),
        (stats.chi2.ppf(0.025, m * runs * T) / (runs * T),
         stats.chi2.ppf(0.975, m * runs * T) / (runs * T)),
        rtol=1e-9,
    )
    assert nlo < nis.mean() < nhi, (nlo, nis.mean(), nhi)
    return anees_t


def test_monte_carlo_linear_consistency():
    nees, nis = _mc_linear(runs=200, T=40, seed=3)
    _check_consistency(nees, nis, min_inside=0.85)


@pytest.mark.slow
def test_monte_carlo_linear_consistency_long():
    nees, nis = _mc_linear(runs=1000, T=300, seed=4)
    _check_consistency(nees, nis, min_inside=0.9)


def test_monte_carlo_range_bearing_nearly_consistent():
    """Nonlinear: a CV robot measures range/bearing to a known beacon."""
    beacon = np.array([6.0, 8.0])
    Rrb = np.diag([0.05**2, np.deg2rad(2.0) ** 2])

    def h_rb(x, b):
        d = b - x[:2]
        return jnp.stack([jnp.sqrt(d @ d), jnp.arctan2(d[1], d[0])])

    runs, T = 200, 60
    rng = np.random.default_rng(5)
    xs, us, _ = simulate_cv(rng, T, runs)
    d = beacon - xs[..., :2]
    zs = np.stack([np.hypot(d[..., 0], d[..., 1]), np.arctan2(d[..., 1], d[..., 0])], -1)
    zs = zs + rng.normal(size=zs.shape) * np.sqrt(np.diag(Rrb))
    zs[..., 1] = (zs[..., 1] + np.pi) % (2 * np.pi) - np.pi
    res = ekf.angle_residual([False, True])
    run = jax.jit(jax.vmap(
        lambda us, zs: ekf.filter_scan(lambda x, u, b: f_cv(x, u), h_rb, X0_CV, P0_CV, us, zs,
                                       None, Q_CV, Rrb,
                                       jnp.asarray(beacon), residual=res, save_cov=True)
    ))
    post = run(us, zs)
    err = np.asarray(post.means) - xs
    nees = np_nees(err, np.asarray(post.covs))
    assert np.all(np.isfinite(nees))
    anees = nees.mean()
    assert 0.75 * 4 < anees < 1.35 * 4, anees
    assert 0.8 * 2 < np.asarray(post.nis).mean() < 1.25 * 2


# --------------------------------------------------------------------------
# Masks, angles, gating, failures
# --------------------------------------------------------------------------

def _prior(dtype=np.float64):
    rng = np.random.default_rng(7)
    A = rng.normal(size=(4, 4))
    return ekf.Gaussian(jnp.asarray(X0_CV, dtype), jnp.asarray(A @ A.T + np.eye(4), dtype))


def h3(x):
    return jnp.stack([x[0], x[1] * x[2], jnp.sin(x[3]) + x[0]])


def test_mask_all_false_leaves_state_exactly_unchanged():
    s = _prior()
    z = jnp.full((3,), jnp.nan)
    post, info = jupdate(s, z, h3, np.eye(3), mask=np.zeros(3, bool))
    np.testing.assert_array_equal(post.mean, s.mean)
    np.testing.assert_array_equal(post.cov, s.cov)
    assert int(info.dof) == 0 and float(info.nis) == 0 and not bool(info.accepted)
    assert int(info.status) == 0


def test_masked_subset_equals_update_with_valid_rows_only():
    s = _prior()
    R = np.array([[0.2, 0.05, 0.01], [0.05, 0.3, 0.02], [0.01, 0.02, 0.4]])
    z = np.array([0.3, np.nan, 1.0])  # NaN in the masked component
    mask = np.array([True, False, True])
    post, info = jupdate(s, z, h3, R, mask=mask)
    assert np.all(np.isfinite(post.mean)) and np.all(np.isfinite(post.cov))
    assert int(info.dof) == 2 and float(info.innovation[1]) == 0.0

    # NumPy oracle with hand Jacobian rows 0 and 2 of h3.
    x = np.asarray(s.mean)
    P = np.asarray(s.cov)
    H = np.array([[1.0, 0, 0, 0], [1.0, 0, 0, np.cos(x[3])]])
    zh = np.array([x[0], np.sin(x[3]) + x[0]])
    Rs = R[np.ix_(mask, mask)]
    S = H @ P @ H.T + Rs
    K = np.linalg.solve(S, H @ P).T
    A = np.eye(4) - K @ H
    assert_close(post.mean, x + K @ (z[mask] - zh))
    assert_close(post.cov, A @ P @ A.T + K @ Rs @ K.T)
    nu = z[mask] - zh
    np.testing.assert_allclose(float(info.nis), nu @ np.linalg.solve(S, nu), rtol=1e-12)



def test_masked_nan_gives_finite_gradient():
    s = _prior()
    mask = np.array([True, False, True])

    def loss(mean, z):
        post, _ = ekf.update(ekf.Gaussian(mean, s.cov), z, h3, np.eye(3) * 0.1, mask=mask)
        return jnp.sum(post.mean**2) + jnp.sum(post.cov)

    g_x, g_z = jax.jit(jax.grad(loss, argnums=(0, 1)))(s.mean, jnp.array([0.3, jnp.nan, 1.0]))
    assert np.all(np.isfinite(g_x)) and np.all(np.isfinite(g_z[np.array([0, 2])]))


def test_angle_residual_wraps_near_pi():
    res = ekf.angle_residual([False, True])
    nu = res(jnp.array([1.0, np.pi - 0.01]), jnp.array([0.5, -np.pi + 0.01]))
    np.testing.assert_allclose(np.asarray(nu), [0.5, -0.02], atol=1e-12)
    # Through an update: state is an angle measured directly.
    s = ekf.Gaussian(jnp.array([-np.pi + 0.01]), jnp.array([[0.1]]))
    post, info = jupdate(
        s, jnp.array([np.pi - 0.01]), lambda x: x, jnp.array([[0.1]]),
        residual=ekf.angle_residual([True]),
    )
    np.testing.assert_allclose(float(info.innovation[0]), -0.02, atol=1e-12)
    np.testing.assert_allclose(float(post.mean[0]), -np.pi + 0.01 - 0.01, atol=1e-12)


_GATE99 = ekf.chi2_gate(0.99, 2)  # one object, so tests share one compilation


def test_gate_rejects_outlier_and_flags():
    s = ekf.Gaussian(jnp.zeros(4), jnp.eye(4))
    R = np.eye(2) * 0.1
    both = np.ones(2, bool)
    gate = _GATE99
    np.testing.assert_allclose(np.asarray(jax.vmap(gate)(jnp.arange(3))),
                               [np.inf, *stats.chi2.ppf(0.99, [1, 2])], rtol=1e-10)
    post, info = jupdate(s, jnp.array([10.0, 0.0]), h_pos, R, mask=both, gate=gate)
    assert not bool(info.accepted)
    assert int(info.status) & errors.GATED
    np.testing.assert_allclose(float(info.nis), 100 / 1.1, rtol=1e-12)
    np.testing.assert_array_equal(post.mean, s.mean)
    np.testing.assert_array_equal(post.cov, s.cov)
    post, info = jupdate(s, jnp.array([1.0, 0.5]), h_pos, R, mask=both, gate=gate)
    assert bool(info.accepted) and int(info.status) == 0
    # The threshold follows the number of valid components:
    # NIS = 2.9²/1.1 = 7.65, above χ²_0.99(1) = 6.63, below χ²_0.99(2) = 9.21.
    z = jnp.array([2.9, 0.0])
    _, info = jupdate(s, z, h_pos, R, mask=np.array([True, False]), gate=gate)
    assert int(info.dof) == 1 and int(info.status) & errors.GATED
    _, info = jupdate(s, z, h_pos, R, mask=both, gate=gate)
    assert bool(info.accepted) and int(info.status) == 0


def test_non_finite_and_not_psd_keep_prior():
    s = _prior()
    ones = np.ones(3, bool)
    post, info = jupdate(s, jnp.array([jnp.nan, 0.0, 1.0]), h3, np.eye(3), mask=ones)
    assert int(info.status) & errors.NON_FINITE and not bool(info.accepted)
    np.testing.assert_array_equal(post.mean, s.mean)
    np.testing.assert_array_equal(post.cov, s.cov)
    bad = ekf.Gaussian(s.mean, -10.0 * jnp.eye(4))
    post, info = jupdate(bad, jnp.array([0.0, 0.0, 1.0]), h3, np.eye(3), mask=ones)
    assert int(info.status) & errors.NOT_PSD and not bool(info.accepted)
    np.testing.assert_array_equal(post.cov, bad.cov)


# --------------------------------------------------------------------------
# Batched measurements
# --------------------------------------------------------------------------

def h_range(x, b):
    d = x[:2] - b
    return jnp.sqrt(d @ d)[None]


def _batch_oracle(x, P, zs, beacons, R, keep):
    Hs, nus = [], []
    for z, b in zip(zs[keep], beacons[keep]):
        d = x[:2] - b
        r = np.linalg.norm(d)
        Hs.append(np.concatenate([d / r, [0, 0]]))
        nus.append(z[0] - r)
    H = np.array(Hs)
    nu = np.array(nus)
    Rb = np.eye(len(nu)) * R
    S = H @ P @ H.T + Rb
    K = np.linalg.solve(S, H @ P).T
    A = np.eye(4) - K @ H
    return x + K @ nu, A @ P @ A.T + K @ Rb @ K.T


def test_update_batch_joint_matches_oracle_and_masks():
    s = _prior()
    beacons = np.array([[5.0, 0.0], [0.0, 6.0], [-4.0, -3.0], [3.0, 3.0]])
    rng = np.random.default_rng(8)
    x = np.asarray(s.mean)
    zs = np.linalg.norm(x[:2] - beacons, axis=1)[:, None] + 0.1 * rng.normal(size=(4, 1))
    masks = np.array([True, False, True, True])
    zs_bad = zs.copy()
    zs_bad[1] = np.nan
    post, info = jupdate_batch(s, zs_bad, h_range, 0.04 * np.eye(1), jnp.asarray(beacons),
                                  masks=masks)
    m_ref, P_ref = _batch_oracle(x, np.asarray(s.cov), zs, beacons, 0.04, masks)
    assert_close(post.mean, m_ref)
    assert_close(post.cov, P_ref)
    np.testing.assert_array_equal(np.asarray(info.dof), [1, 0, 1, 1])
    np.testing.assert_array_equal(np.asarray(info.accepted), masks)
    assert info.nis.shape == (4,) and float(info.nis[1]) == 0.0
    # Marginal NIS of measurement 0 from the prior.
    d = x[:2] - beacons[0]
    Hm = np.concatenate([d / np.linalg.norm(d), [0, 0]])
    S0 = Hm @ np.asarray(s.cov) @ Hm + 0.04
    nu0 = zs[0, 0] - np.linalg.norm(d)
    np.testing.assert_allclose(float(info.nis[0]), nu0**2 / S0, rtol=1e-12)


def h_rel(x, o):
    return x[:2] - o


def test_update_batch_sequential_equals_joint_and_gates():
    s = ekf.Gaussian(jnp.array([0.0, 0.0, 1.0, 1.0]), jnp.diag(jnp.array([1.0, 2.0, 1.0, 1.0])))
    # Linear measurements (beacon-relative position), for which joint == sequential.
    offsets = jnp.array([[1.0, 2.0], [-1.0, 0.5], [0.3, -0.7]])
    zs = np.array([[-0.8, -1.9], [1.2, -0.3], [-0.1, 0.9]])
    R = np.array([[0.2, 0.05], [0.05, 0.1]])
    ones = np.ones(3, bool)
    inf = np.float64(np.inf)  # gates as float64 arrays: one compilation for all values
    joint, ji = jupdate_batch(s, zs, h_rel, R, offsets, masks=ones, gate=inf)
    seq, si = jupdate_batch(s, zs, h_rel, R, offsets, masks=ones, gate=inf, sequential=True)
    assert_close(seq.mean, joint.mean)
    assert_close(seq.cov, joint.cov)
    assert si.nis.shape == (3,) and np.all(np.asarray(si.accepted))
    # An outlier in measurement 1 is gated alone.
    zs_out = zs.copy()
    zs_out[1] += 50.0
    thr = np.float64(stats.chi2.ppf(0.99, 2))
    post, info = jupdate_batch(s, zs_out, h_rel, R, offsets, masks=ones, gate=thr)
    np.testing.assert_array_equal(np.asarray(info.accepted), [True, False, True])
    assert int(info.status[1]) & errors.GATED and int(info.status[0]) == 0
    ref, _ = jupdate_batch(s, zs, h_rel, R, offsets, masks=np.array([True, False, True]),
                           gate=inf)
    assert_close(post.mean, ref.mean)
    assert_close(post.cov, ref.cov)
    post, info = jupdate_batch(s, zs_out, h_rel, R, offsets, masks=ones, gate=thr,
                               sequential=True)
    np.testing.assert_array_equal(np.asarray(info.accepted), [True, False, True])
    assert_close(post.mean, ref.mean)


# --------------------------------------------------------------------------
# Numerics: Joseph form, dtypes, retracing, gradients
# --------------------------------------------------------------------------

@pytest.mark.parametrize(
    "dtype, r, q", [(np.float64, 1e-8, 1e-12), (np.float32, 1e-6, 1e-10)]
)
def test_joseph_keeps_covariance_pd_over_long_run(dtype, r, q):
    """10⁴ steps: a precise position sensor, a weakly observable velocity and
    an unobservable constant (P0 large, R tiny; condition number ~1e14/1e10)."""
    F = np.array([[1.0, DT, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], dtype)
    Q = np.diag([q, q, 0.0]).astype(dtype)
    R = np.array([[r]], dtype)
    P0 = np.diag([1e4, 1e4, 1e4]).astype(dtype)
    T = 10_000
    zs = np.zeros((T, 1), dtype)

    post = jax.jit(lambda zs: ekf.filter_scan(
        lambda x, u: jnp.asarray(F) @ x, lambda x: x[:1], np.zeros(3, dtype), P0, None, zs,
        None, Q, R, save_cov=True,
    ))(zs)
    covs = np.asarray(post.covs)
    assert covs.dtype == dtype
    np.testing.assert_array_equal(covs, np.swapaxes(covs, 1, 2))
    assert np.linalg.eigvalsh(covs.astype(np.float64)).min() > 0
    assert np.all(np.asarray(post.status) == 0)
    np.testing.assert_allclose(covs[-1, 2, 2], 1e4, rtol=1e-6)  # unobservable: untouched

    if dtype == np.float32:
        # Contrast: the simple form P − K S Kᵀ (NumPy, float32, symmetrised)
        # loses positive definiteness on the same problem.
        Ps = P0.copy()
        H = np.array([[1.0, 0.0, 0.0]], dtype)
        min_eig = np.inf
        for _ in range(2000):
            Ps = F @ Ps @ F.T + Q
            S = H @ Ps @ H.T + R
            K = Ps @ H.T / S
            Ps = (0.5 * (Ps - K @ S @ K.T + (Ps - K @ S @ K.T).T)).astype(dtype)
            min_eig = min(min_eig, np.linalg.eigvalsh(Ps.astype(np.float64)).min())
        assert min_eig < 0


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_float32_and_float64_run_without_nan(dtype):
    rng = np.random.default_rng(9)
    _, us, zs = simulate_cv(rng, 60)
    masks = np.ones(zs.shape, bool)
    post = cv_runner(True)(X0_CV.astype(dtype), P0_CV.astype(dtype), us.astype(dtype),
                       zs.astype(dtype), masks, dtype(50.0))
    assert post.means.dtype == dtype and post.final.cov.dtype == dtype
    assert post.nis.dtype == dtype
    assert np.all(np.isfinite(post.means)) and np.all(np.isfinite(post.cov_diags))
    assert np.all(np.asarray(post.status) == 0)
    ref_m, _ = np_kf(X0_CV, P0_CV, us, zs)
    tol = 1e-4 if dtype == np.float32 else 1e-12
    assert_close(post.means, ref_m, tol)


def test_filter_scan_does_not_retrace():
    @jax.jit
    @chex.assert_max_traces(n=1)
    def run(x0, P0, us, zs, masks, Q, R, gate):
        return ekf.filter_scan(f_cv, h_pos, x0, P0, us, zs, masks, Q, R, gate=gate)

    chex.clear_trace_counter()
    rng = np.random.default_rng(10)
    _, us, zs = simulate_cv(rng, 20)
    m = np.ones(zs.shape, bool)
    run(X0_CV, P0_CV, us, zs, m, Q_CV, R_CV, 9.0)
    run(X0_CV + 1, 2 * P0_CV, us * 2, zs + 1, ~m, 2 * Q_CV, 3 * R_CV, 5.0)


def test_gradients_match_finite_differences():
    """grad through the whole scan (tuning Q and R) against central differences."""
    rng = np.random.default_rng(11)
    _, us, zs = simulate_cv(rng, 15)

    def loss(log_q, log_r):
        post = ekf.filter_scan(f_cv, h_pos, X0_CV, P0_CV, us, zs, None,
                               jnp.exp(log_q) * Q_CV, jnp.exp(log_r) * R_CV)
        return jnp.sum(post.nis) + jnp.sum(jnp.log(post.cov_diags))

    theta = np.array([0.1, -0.2])
    vg = jax.jit(jax.value_and_grad(lambda th: loss(th[0], th[1])))  # one compilation
    _, grad = vg(theta)
    eps = 1e-5
    fd = [(vg(theta + eps * e)[0] - vg(theta - eps * e)[0]) / (2 * eps) for e in np.eye(2)]
    np.testing.assert_allclose(np.asarray(grad), np.array(fd), rtol=1e-7, atol=1e-7)


# --------------------------------------------------------------------------
# Host validators
# --------------------------------------------------------------------------

def test_validators_name_the_argument():
    g = ekf.validate_gaussian(np.zeros(2), np.eye(2), "prior")
    assert g.mean.shape == (2,)
    with pytest.raises(InputError, match="prior.mean"):
        ekf.validate_gaussian(np.zeros((2, 1)), np.eye(2), "prior")
    with pytest.raises(InputError, match="prior.mean"):
        ekf.validate_gaussian(np.array([0.0, np.nan]), np.eye(2), "prior")
    with pytest.raises(InputError, match="prior.cov"):
        ekf.validate_gaussian(np.zeros(2), np.eye(3), "prior")
    with pytest.raises(InputError, match="prior.cov"):
        ekf.validate_gaussian(np.zeros(2), -np.eye(2), "prior")
    with pytest.raises(InputError, match="prior.cov"):
        ekf.validate_gaussian(np.zeros(2), np.array([[1.0, 0.5], [0.0, 1.0]]), "prior")
    ekf.validate_noise_cov(np.eye(2), 2, "R", strict=True)
    with pytest.raises(InputError, match="R"):
        ekf.validate_noise_cov(np.zeros((2, 2)), 2, "R", strict=True)
    with pytest.raises(InputError, match="Q"):
        ekf.validate_noise_cov(np.eye(3), 2, "Q")


def test_run_inputs_that_ran_before_the_filter_core_are_accepted():
    """Per-step R with NaN on masked rows, a float32 P0 symmetric to float32 precision and a
    scalar R for one measurement are accepted (the run checks only what it uses, at the input's
    precision); what is used stays checked, naming the step."""
    rng = np.random.default_rng(7)
    _, us, zs = simulate_cv(rng, 30)
    masks = rng.random(zs.shape) > 0.3
    Rs = np.broadcast_to(R_CV, (30, 2, 2)).copy()
    Rnan = Rs.copy()
    for t in range(30):
        Rnan[t][~masks[t], :] = np.nan
        Rnan[t][:, ~masks[t]] = np.nan
    a = ekf.filter_scan(f_cv, h_pos, X0_CV, P0_CV, us, zs, masks, Q_CV, Rs, save_cov=True)
    b = ekf.filter_scan(f_cv, h_pos, X0_CV, P0_CV, us, zs, masks, Q_CV, Rnan, save_cov=True)
    ref_m, ref_P = np_kf(X0_CV, P0_CV, us, zs, masks)
    assert_close(a.means, ref_m)
    np.testing.assert_array_equal(np.asarray(b.means), np.asarray(a.means))
    np.testing.assert_array_equal(np.asarray(b.covs), np.asarray(a.covs))
    t0 = int(np.argmax(masks[:, 0]))
    Rbad = Rs.copy()
    Rbad[t0, 0, 0] = np.nan
    with pytest.raises(InputError, match=rf"R\[{t0}\]: contains NaN"):
        ekf.filter_scan(f_cv, h_pos, X0_CV, P0_CV, us, zs, masks, Q_CV, Rbad)
    Rneg = Rs.copy()
    Rneg[-1] = -np.eye(2)
    with pytest.raises(InputError, match=r"R\[29\]: not positive definite"):
        ekf.filter_scan(f_cv, h_pos, X0_CV, P0_CV, us, zs, masks, Q_CV, Rneg)
    # float32 P0 asymmetric at its own precision: accepted; the same asymmetry in float64 is not
    P_asym = P0_CV.copy()
    P_asym[0, 1] += 2e-7
    p32 = ekf.filter_scan(f_cv, h_pos, X0_CV.astype(np.float32), P_asym.astype(np.float32), us, zs, masks,
                          Q_CV, R_CV)
    assert np.all(np.isfinite(np.asarray(p32.means)))
    with pytest.raises(InputError, match="P0: not symmetric"):
        ekf.filter_scan(f_cv, h_pos, X0_CV, P_asym, us, zs, masks, Q_CV, R_CV)
    # a scalar variance for one measurement equals the (1, 1) matrix, and the closed-form KF
    one = ekf.filter_scan(f_cv, lambda x: x[:1], X0_CV, P0_CV, us, zs[:, :1], masks[:, :1], Q_CV, 0.04)
    ref_m1, _ = np_kf(X0_CV, P0_CV, us, zs[:, :1], masks[:, :1], H=H_CV[:1], R=np.array([[0.04]]))
    assert_close(one.means, ref_m1)


def test_step_log_likelihood_is_nan_where_the_update_failed_and_takes_logdet_from_S():
    from jaxslam.filters import gaussian as G

    info = G.UpdateInfo(nis=jnp.asarray(1.5), dof=jnp.asarray(2, jnp.int32), innovation=jnp.zeros(2),
                        S=jnp.asarray(R_CV), accepted=jnp.asarray(True), status=jnp.int32(0))  # no logdet
    want = -0.5 * (1.5 + np.log(np.linalg.det(R_CV)) + 2 * np.log(2 * np.pi))
    np.testing.assert_allclose(float(G.step_log_likelihood(info)), want, rtol=1e-12)
    with_ld = info._replace(logdet=jnp.asarray(np.log(np.linalg.det(R_CV))))
    np.testing.assert_allclose(float(G.step_log_likelihood(with_ld)), want, rtol=1e-12)
    gated = with_ld._replace(status=jnp.int32(errors.GATED), accepted=jnp.asarray(False))
    np.testing.assert_allclose(float(G.step_log_likelihood(gated)), want, rtol=1e-12)  # defined: kept
    for bit in (errors.NOT_PSD, errors.NON_FINITE):
        failed = with_ld._replace(status=jnp.int32(bit), logdet=jnp.asarray(0.0))
        assert np.isnan(float(G.step_log_likelihood(failed)))
    # a failed step without a valid component (its predict failed: the sigma-point filters
    # report that through the step's status) is NaN too; a clean one is 0
    assert np.isnan(float(G.step_log_likelihood(failed._replace(dof=jnp.asarray(0, jnp.int32)))))
    assert float(G.step_log_likelihood(with_ld._replace(dof=jnp.asarray(0, jnp.int32)))) == 0.0

    # a user-written filter whose UpdateInfo has no logdet runs, with the EKF's likelihood
    rng = np.random.default_rng(5)
    _, us, zs = simulate_cv(rng, 20)
    flt = ekf.make_filter(f_cv, h_pos)

    def update(state, z, mask, R, c):
        post, inf = flt.update(state, z, mask, R, c)
        return post, inf._replace(logdet=None)

    ref = G.run(flt, X0_CV, P0_CV, us, zs, None, Q_CV, R_CV)
    mine = G.run(G.GaussianFilter(flt.predict, update), X0_CV, P0_CV, us, zs, None, Q_CV, R_CV)
    np.testing.assert_allclose(np.asarray(mine.log_likelihood), np.asarray(ref.log_likelihood), rtol=1e-12)


def test_check_psd_stack_names_the_first_bad_matrix():
    from jaxslam.linalg import check_psd

    A = np.broadcast_to(np.eye(3), (5, 3, 3)).copy()
    check_psd(A, "Q", stack=True)
    with pytest.raises(InputError, match="expected a square matrix"):
        check_psd(A, "Q")  # a stack only where asked for
    A[3, 2, 2] = -1.0
    with pytest.raises(InputError, match=r"Q\[3\]: not positive semi-definite"):
        check_psd(A, "Q", stack=True)
    valid = np.ones((5, 3), bool)
    valid[3, 2] = False  # that row unused at step 3
    check_psd(A, "Q", stack=True, valid=valid)


# --------------------------------------------------------------------------
# Iterated EKF update
# --------------------------------------------------------------------------

def test_iterated_update_linear_is_kf():
    rng = np.random.default_rng(11)
    T = 15
    us = rng.normal(0, 0.3, (T, 2))
    zs = rng.normal(0, 1.0, (T, 2))
    masks = rng.random((T, 2)) > 0.3
    post = ekf.filter_scan(f_cv, h_pos, X0_CV, P0_CV, us, zs, masks, Q_CV, R_CV, num_iter=3)
    want = np_kf(X0_CV, P0_CV, us, zs, masks)
    np.testing.assert_allclose(np.asarray(post.means), want[0], atol=1e-10)
    assert not np.any(np.asarray(post.status) & errors.NOT_CONVERGED)


def test_iterated_update_is_map_of_one_update():
    """num_iter Gauss-Newton steps reach argmin ‖z − h(x)‖²_R⁻¹ + ‖x − m‖²_P⁻¹ (NumPy GN)."""
    m = np.array([1.0, 0.5, 0.2, -0.1])
    P = np.diag([0.8, 0.6, 0.1, 0.1])
    R = np.diag([0.01, 0.001])
    beacon = np.array([0.2, -0.4])

    def h(x):
        d = x[:2] - jnp.asarray(beacon, x.dtype)
        return jnp.stack([jnp.sqrt(d @ d), jnp.arctan2(d[1], d[0])])

    z = np.array([1.6, 1.2])
    x = m.copy()
    Pi, Ri = np.linalg.inv(P), np.linalg.inv(R)
    for _ in range(100):
        d = x[:2] - beacon
        r2 = d @ d
        H = np.array([[d[0] / np.sqrt(r2), d[1] / np.sqrt(r2), 0, 0],
                      [-d[1] / r2, d[0] / r2, 0, 0]])
        res = z - np.array([np.sqrt(r2), np.arctan2(d[1], d[0])])
        g = -H.T @ Ri @ res + Pi @ (x - m)
        x = x - np.linalg.solve(H.T @ Ri @ H + Pi, g)
    upd = jax.jit(ekf.update, static_argnames=("h", "num_iter"))  # jitted for speed only
    post, info = upd(ekf.Gaussian(jnp.asarray(m), jnp.asarray(P)), z, h, R, num_iter=12)
    np.testing.assert_allclose(np.asarray(post.mean), x, atol=1e-10)
    assert int(info.status) == 0
    plain, _ = upd(ekf.Gaussian(jnp.asarray(m), jnp.asarray(P)), z, h, R)
    assert np.max(np.abs(np.asarray(plain.mean) - x)) > 1e-3  # one linearisation is not the MAP
    few, info2 = upd(ekf.Gaussian(jnp.asarray(m), jnp.asarray(P)), z, h, R, num_iter=2)
    assert int(info2.status) & errors.NOT_CONVERGED
    with pytest.raises(InputError, match="num_iter"):
        ekf.update(ekf.Gaussian(jnp.asarray(m), jnp.asarray(P)), z, h, R, num_iter=0)


# --------------------------------------------------------------------------
# Many means, one covariance
# --------------------------------------------------------------------------

@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_linear_update_shared_equals_separate_numpy_kalman_updates(dtype):
    """Oracle: a NumPy Kalman update (explicit inverse, Joseph form) of each mean alone."""
    rng = np.random.default_rng(21)
    B, n, m = 6, 5, 3
    A = rng.normal(size=(n, n))
    P = A @ A.T + 0.5 * np.eye(n)
    H = rng.normal(size=(m, n))
    R = np.diag(rng.uniform(0.1, 0.5, m))
    xs = rng.normal(size=(B, n))
    nus = rng.normal(size=(B, m))
    mask = np.array([True, False, True])
    out = jax.jit(ekf.linear_update_shared)(*(jnp.asarray(a, dtype) for a in (xs, P, nus, H, R)),
                                            jnp.asarray(mask))
    xs_post, P_post, S, num, nis, ok, logdet = (np.asarray(o) for o in out)
    Hm, num_ref = H[mask], nus[:, mask]
    S_ref = Hm @ P @ Hm.T + R[np.ix_(mask, mask)]
    K = P @ Hm.T @ np.linalg.inv(S_ref)
    IKH = np.eye(n) - K @ Hm
    P_ref = IKH @ P @ IKH.T + K @ R[np.ix_(mask, mask)] @ K.T
    tol = 1e-10 if dtype == np.float64 else 2e-4
    assert bool(ok) and xs_post.dtype == dtype
    for b in range(B):
        np.testing.assert_allclose(xs_post[b], xs[b] + K @ num_ref[b], rtol=tol, atol=tol)
        np.testing.assert_allclose(nis[b], num_ref[b] @ np.linalg.solve(S_ref, num_ref[b]),
                                   rtol=tol)
    np.testing.assert_allclose(P_post, P_ref, rtol=tol, atol=tol)
    np.testing.assert_allclose(logdet, np.log(np.linalg.det(S_ref)), rtol=tol, atol=tol)
    assert np.all(num[:, 1] == 0)
    # B = 1 is linear_update (the EKF's own correction)
    one = jax.jit(ekf.linear_update)(*(jnp.asarray(a, dtype) for a in (xs[0], P, nus[0], H, R)),
                                     jnp.asarray(mask))  # jitted for speed only
    np.testing.assert_allclose(np.asarray(one[0]), xs_post[0], rtol=tol, atol=tol)


def test_iterated_update_tolerance_is_checked():
    """Review of 2026-12-07: a concrete tol was never checked (NaN or inf never flagged
    NOT_CONVERGED, -1 always); a traced NaN now counts as not converged."""
    from jaxslam import errors
    from jaxslam.errors import InputError

    G = ekf.Gaussian(np.array([1.0, 2.0]), 4 * np.eye(2))
    h = lambda v: jnp.array([v[0] ** 3 + v[1] ** 2])  # noqa: E731 (far from converged in 2 steps)
    z, R = np.array([40.0]), np.array([[0.01]])
    for bad in (-1.0, 0.0, np.nan, np.inf, "1e-3"):
        with pytest.raises(InputError, match=r"^tol: expected a positive finite scalar"):
            ekf.update(G, z, h, R, num_iter=2, tol=bad)
    _, info = ekf.update(G, z, h, R, num_iter=2)
    assert int(info.status) & errors.NOT_CONVERGED
    _, info = jax.jit(lambda t: ekf.update(G, z, h, R, num_iter=2, tol=t))(jnp.nan)
    assert int(info.status) & errors.NOT_CONVERGED
    _, info = ekf.update(G, z, h, R, num_iter=2, tol=1e6)  # a loose tolerance: converged
    assert not int(info.status) & errors.NOT_CONVERGED
