"""Tests of the sigma-point filter (jaxslam.filters.ukf).

Oracles: a closed-form Kalman filter in NumPy (linear model: every sigma-point rule is exact),
an independent NumPy UKF written here from the textbook equations (pendulum), the RTS
smoother's dense-posterior oracle through ``tests/filters/test_smoother.py``'s model, central
finite differences, and chi-square Monte Carlo bounds (SciPy).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

from jaxslam import errors
from jaxslam.errors import InputError
from jaxslam.filters import ekf, smoother, ukf

from cv_model import DT, F_CV, G_CV, H_CV, P0_CV, Q_CV, R_CV, X0_CV, f_cv, h_pos  # noqa: F401
RULES = {"unscented": ukf.unscented(), "unscented_a05": ukf.unscented(0.5, 2.0, 1.0),
         "cubature": ukf.cubature()}


def np_kf(us, zs, masks, predict_first=True):
    x, P = X0_CV.copy(), P0_CV.copy()
    out = []
    for t in range(len(zs)):
        if predict_first:
            x, P = F_CV @ x + G_CV @ us[t], F_CV @ P @ F_CV.T + Q_CV
        mk = masks[t]
        if mk.any():
            H, Rm = H_CV[mk], R_CV[np.ix_(mk, mk)]
            S = H @ P @ H.T + Rm
            K = np.linalg.solve(S, H @ P).T
            x = x + K @ (zs[t][mk] - H @ x)
            P = P - K @ S @ K.T
        out.append((x.copy(), P.copy()))
        if not predict_first:
            x, P = F_CV @ x + G_CV @ us[t], F_CV @ P @ F_CV.T + Q_CV
    return np.array([o[0] for o in out]), np.array([o[1] for o in out])


@pytest.fixture(scope="module")
def lin_data():
    rng = np.random.default_rng(0)
    T = 20
    us = rng.normal(0, 0.5, (T, 2))
    zs = rng.normal(0, 1.0, (T, 2))
    masks = rng.random((T, 2)) > 0.3
    masks[4] = False
    return us, zs, masks


@pytest.mark.parametrize("rule", sorted(RULES))
@pytest.mark.parametrize("predict_first", [True, False])
def test_linear_model_equals_kalman_filter(lin_data, rule, predict_first):
    us, zs, masks = lin_data
    post = ukf.filter_scan(f_cv, h_pos, X0_CV, P0_CV, us, zs, masks, Q_CV, R_CV, save_cov=True,
                           predict_first=predict_first, points=RULES[rule])
    m, P = np_kf(us, zs, masks, predict_first)
    np.testing.assert_allclose(np.asarray(post.means), m, atol=1e-10)
    np.testing.assert_allclose(np.asarray(post.covs), P, atol=1e-10)
    # same log-likelihood as the EKF (both exact on a linear model)
    e = ekf.filter_scan(f_cv, h_pos, X0_CV, P0_CV, us, zs, masks, Q_CV, R_CV, predict_first=predict_first)
    np.testing.assert_allclose(np.asarray(post.log_likelihood), np.asarray(e.log_likelihood), atol=1e-10)


def test_linear_unscented_rts_equals_ekf_rts(lin_data):
    """The sigma-point cross-covariances make rts() the unscented RTS smoother (exact here)."""
    us, zs, masks = lin_data
    a = smoother.rts(ukf.filter_scan(f_cv, h_pos, X0_CV, P0_CV, us, zs, masks, Q_CV, R_CV,
                                     save_smoother=True))
    b = smoother.rts(ekf.filter_scan(f_cv, h_pos, X0_CV, P0_CV, us, zs, masks, Q_CV, R_CV,
                                     save_smoother=True))
    np.testing.assert_allclose(np.asarray(a.means), np.asarray(b.means), atol=1e-10)
    np.testing.assert_allclose(np.asarray(a.covs), np.asarray(b.covs), atol=1e-10)


# --------------------------------------------------------------------------
# Pendulum: an independent NumPy UKF (Wan & van der Merwe), written here
# --------------------------------------------------------------------------

G_GRAV, DT_P = 9.81, 0.05
QP = np.diag([1e-4, 4e-3])
RP = np.array([[0.02]])


def f_pend(x, u):
    return jnp.stack([x[0] + DT_P * x[1], x[1] - DT_P * G_GRAV * jnp.sin(x[0])])


def h_pend(x):
    return jnp.sin(x[:1])


def np_ukf(x, P, zs, alpha, beta, kappa):
    n = 2
    lam = alpha**2 * (n + kappa) - n
    wm = np.full(2 * n + 1, 1 / (2 * (n + lam)))
    wm[0] = lam / (n + lam)
    wc = wm.copy()
    wc[0] += 1 - alpha**2 + beta

    def points(x, P):
        L = np.linalg.cholesky(P) * np.sqrt(n + lam)
        return np.vstack([x, x + L.T, x - L.T])

    out = []
    for z in zs:
        X = points(x, P)
        Y = np.array([[p[0] + DT_P * p[1], p[1] - DT_P * G_GRAV * np.sin(p[0])] for p in X])
        x = wm @ Y
        P = (Y - x).T @ np.diag(wc) @ (Y - x) + QP
        X = points(x, P)
        Z = np.sin(X[:, :1])
        zh = wm @ Z
        S = (Z - zh).T @ np.diag(wc) @ (Z - zh) + RP
        C = (X - x).T @ np.diag(wc) @ (Z - zh)
        K = C @ np.linalg.inv(S)
        x = x + K @ (z - zh)
        P = P - K @ S @ K.T
        out.append(x)
    return np.array(out)


def _pendulum(seed, T=100):
    rng = np.random.default_rng(seed)
    x = np.array([1.2, 0.0])
    xs, zs = [], []
    for _ in range(T):
        x = np.array([x[0] + DT_P * x[1], x[1] - DT_P * G_GRAV * np.sin(x[0])])
        x = x + rng.multivariate_normal(np.zeros(2), QP)
        xs.append(x)
        zs.append(np.sin(x[:1]) + rng.normal(0, np.sqrt(RP[0, 0]), 1))
    return np.array(xs), np.array(zs)


@pytest.mark.parametrize("abk", [(1.0, 2.0, 0.0), (0.5, 2.0, 1.0)])
def test_pendulum_equals_numpy_ukf(abk):
    _, zs = _pendulum(1)
    x0, P0 = np.array([1.0, 0.1]), np.diag([0.1, 0.1])
    post = ukf.filter_scan(f_pend, h_pend, x0, P0, None, zs, None, QP, RP, points=ukf.unscented(*abk))
    np.testing.assert_allclose(np.asarray(post.means), np_ukf(x0, P0, zs, *abk), atol=1e-10)


def test_pendulum_against_filterpy():
    fp = pytest.importorskip("filterpy.kalman")
    _, zs = _pendulum(2)
    pts = fp.MerweScaledSigmaPoints(2, alpha=1.0, beta=2.0, kappa=0.0)
    k = fp.UnscentedKalmanFilter(2, 1, DT_P, hx=lambda x: np.sin(x[:1]),
                                 fx=lambda x, dt: np.array([x[0] + dt * x[1], x[1] - dt * G_GRAV * np.sin(x[0])]),
                                 points=pts)
    k.x, k.P, k.Q, k.R = np.array([1.0, 0.1]), np.diag([0.1, 0.1]), QP, RP
    want = []
    for z in zs:
        k.predict()
        k.update(z)
        want.append(k.x.copy())
    post = ukf.filter_scan(f_pend, h_pend, np.array([1.0, 0.1]), np.diag([0.1, 0.1]), None, zs, None,
                           QP, RP)
    np.testing.assert_allclose(np.asarray(post.means), np.array(want), atol=1e-9)


def test_float32_follows_dtype():
    _, zs = _pendulum(3)
    post = ukf.filter_scan(f_pend, h_pend, np.array([1.0, 0.1], np.float32), np.diag([0.1, 0.1]).astype(np.float32),
                           None, zs.astype(np.float32), None, QP.astype(np.float32), RP.astype(np.float32))
    assert post.means.dtype == jnp.float32
    ref = np_ukf(np.array([1.0, 0.1]), np.diag([0.1, 0.1]), zs, 1.0, 2.0, 0.0)
    np.testing.assert_allclose(np.asarray(post.means), ref, atol=2e-4)


def test_masks_vmapped_equal_one_by_one(lin_data):
    us, zs, _ = lin_data
    M = np.random.default_rng(5).random((5,) + zs.shape) > 0.4

    def one(mk):
        return ukf.filter_scan(f_cv, h_pos, X0_CV, P0_CV, us, zs, mk, Q_CV, R_CV).means

    batch = jax.vmap(one)(jnp.asarray(M))
    for i in range(5):
        np.testing.assert_allclose(np.asarray(batch[i]), np.asarray(one(M[i])), atol=1e-12)


def test_gate_and_failures_keep_the_prior():
    st = ekf.Gaussian(jnp.asarray(X0_CV), jnp.asarray(P0_CV))
    post, info = ukf.update(st, np.array([50.0, 50.0]), h_pos, R_CV, gate=9.21)
    assert int(info.status) & errors.GATED and not bool(info.accepted)
    np.testing.assert_array_equal(np.asarray(post.mean), X0_CV)
    bad = ekf.Gaussian(jnp.asarray(X0_CV), jnp.asarray(-np.eye(4)))
    post, info = ukf.update(bad, np.array([0.1, 0.2]), h_pos, R_CV)
    assert int(info.status) & errors.NOT_PSD and np.all(np.isfinite(np.asarray(post.mean)))
    # a fully masked update changes nothing, whatever z holds
    post, info = ukf.update(st, np.array([np.nan, np.inf]), h_pos, R_CV, mask=np.array([False, False]))
    np.testing.assert_array_equal(np.asarray(post.cov), P0_CV)
    assert int(info.dof) == 0 and float(info.logdet) == 0.0
    with pytest.raises(InputError, match="alpha"):
        ukf.unscented(alpha=0.0)


def test_nees_within_chi2_bounds_over_100_runs():
    """ANEES of the UKF on the pendulum (100 runs, 100 steps) inside χ² bounds, per step and overall."""
    runs = 100
    data = [_pendulum(100 + i) for i in range(runs)]
    xs = np.stack([d[0] for d in data])
    zs = jnp.asarray(np.stack([d[1] for d in data]))
    x0 = np.array([1.2, 0.0])
    P0 = np.diag([1e-4, 1e-4])

    @jax.jit
    def run(z):
        p = ukf.filter_scan(f_pend, h_pend, x0, P0, None, z, None, QP, RP, save_cov=True)
        return p.means, p.covs

    m, P = jax.vmap(run)(zs)
    e = np.asarray(m) - xs
    nees = np.einsum("rti,rtij,rtj->rt", e, np.linalg.inv(np.asarray(P)), e)
    # four checks: each at 99 % so that the family's false-alarm rate stays ≈ 4 % (Bonferroni)
    lo, hi = stats.chi2.ppf([0.005, 0.995], runs * 2) / runs
    for t in (10, 50, 99):
        assert lo <= nees[:, t].mean() <= hi, (t, nees[:, t].mean(), lo, hi)
    assert lo <= nees.mean() <= hi, (nees.mean(), lo, hi)


def test_log_likelihood_gradient_matches_finite_differences():
    _, zs = _pendulum(7, T=60)

    def nll(log_sr):
        R = jnp.exp(2 * log_sr) * jnp.eye(1)
        p = ukf.filter_scan(f_pend, h_pend, np.array([1.0, 0.1]), np.diag([0.1, 0.1]), None, zs, None, QP, R)
        return -jnp.sum(p.log_likelihood)

    x = jnp.asarray(np.log(0.2))
    g = float(jax.grad(nll)(x))
    eps = 1e-5
    fd = float((nll(x + eps) - nll(x - eps)) / (2 * eps))
    np.testing.assert_allclose(g, fd, rtol=1e-5)


def test_compile_once():
    traces = []

    @jax.jit
    def run(zs, R):
        traces.append(1)
        return ukf.filter_scan(f_pend, h_pend, np.array([1.0, 0.1]), np.diag([0.1, 0.1]), None, zs, None,
                               QP, R).means

    _, z1 = _pendulum(8, T=30)
    _, z2 = _pendulum(9, T=30)
    run(z1, RP)
    run(z2, 2 * RP)
    assert len(traces) == 1
