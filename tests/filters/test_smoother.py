"""Tests of the smoothers (jaxslam.filters.smoother) and the run outputs they consume.

Oracles: the closed-form joint posterior of a linear-Gaussian batch problem (dense
least squares in NumPy), a dense Gauss-Newton / IRLS MAP solve in NumPy with hand
Jacobians, central finite differences, and chi-square Monte Carlo bounds (SciPy).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

from jaxslam import errors
from jaxslam.errors import InputError
from jaxslam.filters import ekf, gaussian, smoother

from cv_model import DT, F_CV, G_CV, H_CV, P0_CV, Q_CV, R_CV, X0_CV, f_cv, h_pos  # noqa: F401
BEACON = np.array([3.0, -2.0])


def make_h_rb(beacon):
    def h(x):
        """Range and bearing from a fixed beacon (nonlinear)."""
        d = x[:2] - jnp.asarray(beacon, x.dtype)
        return jnp.stack([jnp.sqrt(d @ d), jnp.arctan2(d[1], d[0])])

    return h


h_rb = make_h_rb(BEACON)
# Monte Carlo model: the beacon farther off, so that the EKF itself is consistent (near the
# beacon with P0's 1 m spread the linearisation error makes the EKF's NEES 10x too large).
BEACON_MC = np.array([10.0, 8.0])


def simulate(seed, T, h_np, R=R_CV, Q=Q_CV):
    rng = np.random.default_rng(seed)
    us = rng.normal(0, 0.5, (T, 2))
    x = X0_CV + rng.multivariate_normal(np.zeros(4), P0_CV)
    xs, zs = [], []
    for t in range(T):
        x = F_CV @ x + G_CV @ us[t] + rng.multivariate_normal(np.zeros(4), Q)
        xs.append(x)
        zs.append(h_np(x) + rng.multivariate_normal(np.zeros(R.shape[0]), R))
    return us, np.array(xs), np.array(zs)


def dense_linear_posterior(us, zs, masks, predict_first=True):
    """Joint Gaussian posterior of all states by dense least squares (information form).

    predict_first: states x_{-1} (prior), x_0..x_{T-1}; z_t measures x_t.
    update-first: states x_0 (prior), ..., z_t measures x_t, x_{t+1} = F x_t + G u_t.
    Returns the means and covariances of the T measured states.
    """
    T = zs.shape[0]
    K = T + 1 if predict_first else T
    n = 4
    N = K * n
    Lam = np.zeros((N, N))
    eta = np.zeros(N)
    Pi = np.linalg.inv(P0_CV)
    Lam[:n, :n] += Pi
    eta[:n] += Pi @ X0_CV
    Qi = np.linalg.inv(Q_CV)
    for k in range(K - 1):
        u = us[k]
        a, b = k * n, (k + 1) * n
        # residual x_{k+1} - F x_k - G u
        J = np.zeros((n, N))
        J[:, a:a + n] = -F_CV
        J[:, b:b + n] = np.eye(n)
        Lam += J.T @ Qi @ J
        eta += J.T @ Qi @ (G_CV @ u)
    off = 1 if predict_first else 0
    for t in range(T):
        mk = masks[t]
        if not mk.any():
            continue
        k = t + off
        Hs = np.zeros((mk.sum(), N))
        Hs[:, k * n:(k + 1) * n] = H_CV[mk]
        Ri = np.linalg.inv(R_CV[np.ix_(mk, mk)])
        Lam += Hs.T @ Ri @ Hs
        eta += Hs.T @ Ri @ zs[t][mk]
    Sig = np.linalg.inv(Lam)
    mu = Sig @ eta
    means = mu.reshape(K, n)[off:]
    covs = np.array([Sig[(k + off) * n:(k + off + 1) * n, (k + off) * n:(k + off + 1) * n]
                     for k in range(T)])
    return means, covs


@pytest.fixture(scope="module")
def linear_run():
    T = 25
    us, _, zs = simulate(0, T, lambda x: H_CV @ x)
    rng = np.random.default_rng(1)
    masks = rng.random((T, 2)) > 0.3
    masks[5] = False
    return us, zs, masks


@pytest.mark.parametrize("predict_first", [True, False])
def test_rts_equals_dense_joint_posterior(linear_run, predict_first):
    us, zs, masks = linear_run
    post = ekf.filter_scan(f_cv, h_pos, X0_CV, P0_CV, us, zs, masks, Q_CV, R_CV,
                           predict_first=predict_first, save_smoother=True)
    sm = smoother.rts(post)
    mu, cov = dense_linear_posterior(us, zs, masks, predict_first)
    np.testing.assert_allclose(np.asarray(sm.means), mu, atol=1e-9)
    np.testing.assert_allclose(np.asarray(sm.covs), cov, atol=1e-9)
    assert not np.any(np.asarray(sm.status))
    # the last smoothed estimate is the filtered one
    np.testing.assert_allclose(np.asarray(sm.means[-1]), np.asarray(post.means[-1]), atol=0)


def test_log_likelihood_equals_dense_marginal(linear_run):
    """Σ log-likelihood of the run = log N(z; E z, Cov z) of the stacked valid measurements."""
    us, zs, masks = linear_run
    post = ekf.filter_scan(f_cv, h_pos, X0_CV, P0_CV, us, zs, masks, Q_CV, R_CV)
    T = zs.shape[0]
    # stacked linear model: x_t = F^{t+1} x_{-1} + sum ... ; build by propagating moments
    n = 4
    A = np.zeros((T * n, n))
    Bw = np.zeros((T * n, T * n))
    c = np.zeros(T * n)
    x_mean = X0_CV.copy()
    Phi = np.eye(n)
    for t in range(T):
        Phi = F_CV @ Phi
        x_mean = F_CV @ x_mean + G_CV @ us[t]
        A[t * n:(t + 1) * n] = Phi
        c[t * n:(t + 1) * n] = x_mean - Phi @ X0_CV
        for s in range(t + 1):
            Bw[t * n:(t + 1) * n, s * n:(s + 1) * n] = np.linalg.matrix_power(F_CV, t - s)
    mean_x = A @ X0_CV + c
    cov_x = A @ P0_CV @ A.T + Bw @ np.kron(np.eye(T), Q_CV) @ Bw.T
    rows = [t * n + i for t in range(T) for i in range(2) if masks[t, i]]
    Hbig = np.kron(np.eye(T), H_CV)
    sel = [t * 2 + i for t in range(T) for i in range(2) if masks[t, i]]
    Hs = Hbig[sel]
    del rows
    Rs = np.kron(np.eye(T), R_CV)[np.ix_(sel, sel)]
    mz = Hs @ mean_x
    Sz = Hs @ cov_x @ Hs.T + Rs
    want = stats.multivariate_normal(mz, Sz).logpdf(zs.reshape(-1)[sel])
    np.testing.assert_allclose(float(jnp.sum(post.log_likelihood)), want, rtol=1e-10)


def test_per_step_noise_equals_shared(linear_run):
    us, zs, masks = linear_run
    T = zs.shape[0]
    a = ekf.filter_scan(f_cv, h_pos, X0_CV, P0_CV, us, zs, masks, Q_CV, R_CV)
    b = ekf.filter_scan(f_cv, h_pos, X0_CV, P0_CV, us, zs, masks, np.broadcast_to(Q_CV, (T, 4, 4)),
                        np.broadcast_to(R_CV, (T, 2, 2)))
    np.testing.assert_allclose(np.asarray(a.means), np.asarray(b.means), atol=1e-14)
    with pytest.raises(InputError, match="R"):
        ekf.filter_scan(f_cv, h_pos, X0_CV, P0_CV, us, zs, masks, Q_CV, np.eye(3))
    with pytest.raises(InputError, match="Q"):
        ekf.filter_scan(f_cv, h_pos, X0_CV, P0_CV, us, zs, masks, np.ones((T - 1, 4, 4)), R_CV)
    with pytest.raises(InputError, match="zs"):
        ekf.filter_scan(f_cv, h_pos, X0_CV, P0_CV, us, zs[:, :, None], None, Q_CV, R_CV)
    with pytest.raises(InputError, match="Q"):
        ekf.filter_scan(f_cv, h_pos, X0_CV, P0_CV, us, zs, masks, -np.eye(4), R_CV)
    with pytest.raises(InputError, match="masks"):
        ekf.filter_scan(f_cv, h_pos, X0_CV, P0_CV, us, zs, masks[:, :1], Q_CV, R_CV)


@pytest.mark.parametrize("predict_first", [True, False])
def test_fixed_lag(linear_run, predict_first):
    us, zs, masks = linear_run
    T = zs.shape[0]
    flt = ekf.make_filter(f_cv, h_pos)
    post = gaussian.run(flt, X0_CV, P0_CV, us, zs, masks, Q_CV, R_CV,
                        predict_first=predict_first, save_smoother=True)
    full = smoother.rts(post)
    for lag in (T - 1, T + 5):
        fl = smoother.fixed_lag(flt, X0_CV, P0_CV, us, zs, masks, Q_CV, R_CV, lag=lag,
                                predict_first=predict_first)
        np.testing.assert_allclose(np.asarray(fl.means), np.asarray(full.means), atol=1e-12)
        np.testing.assert_allclose(np.asarray(fl.cov_diags), np.asarray(full.cov_diags), atol=1e-12)
    # lag 0 is the filter
    f0 = smoother.fixed_lag(flt, X0_CV, P0_CV, us, zs, masks, Q_CV, R_CV, lag=0,
                            predict_first=predict_first)
    np.testing.assert_allclose(np.asarray(f0.means), np.asarray(post.means), atol=1e-14)
    # lag 4: x_{t | t+4} is the RTS estimate of the run cut after step t+4.  The cut run is
    # the whole run with every measurement after step t+4 masked off (the later steps only
    # predict, and carry nothing back to step t): the same information, the same shapes as
    # `post`, so the run and its RTS pass compiled above serve every t (a run cut to each
    # length compiled a scan and a backward pass per length).
    lag = 4
    fl = smoother.fixed_lag(flt, X0_CV, P0_CV, us, zs, masks, Q_CV, R_CV, lag=lag,
                            predict_first=predict_first)
    for t in (0, 7, 13, T - lag - 1, T - 2):
        end = min(t + lag, T - 1) + 1
        m_cut = masks.copy()
        m_cut[end:] = False
        p_cut = gaussian.run(flt, X0_CV, P0_CV, us, zs, m_cut, Q_CV, R_CV,
                             predict_first=predict_first, save_smoother=True)
        want = smoother.rts(p_cut).means[t]
        np.testing.assert_allclose(np.asarray(fl.means[t]), np.asarray(want), atol=1e-12)
    with pytest.raises(InputError, match="lag"):
        smoother.fixed_lag(flt, X0_CV, P0_CV, us, zs, masks, Q_CV, R_CV, lag=-1)


def test_rts_needs_saved_moments(linear_run):
    us, zs, masks = linear_run
    post = ekf.filter_scan(f_cv, h_pos, X0_CV, P0_CV, us, zs, masks, Q_CV, R_CV)
    with pytest.raises(InputError, match="save_smoother"):
        smoother.rts(post)
    # moments of two different runs (or a cut one) mixed into one Posterior: named, not a deep error
    full = ekf.filter_scan(f_cv, h_pos, X0_CV, P0_CV, us, zs, masks, Q_CV, R_CV, save_smoother=True)
    with pytest.raises(InputError, match=r"^post.cross_covs: expected shape \(\d+, 4, 4\) to match post.means"):
        smoother.rts(full._replace(cross_covs=full.cross_covs[:-1]))
    with pytest.raises(InputError, match=r"^post.means: expected shape \(T, n\)"):
        smoother.rts(full._replace(means=full.means[0]))


def test_iterated_linear_is_rts(linear_run):
    us, zs, masks = linear_run
    post = ekf.filter_scan(f_cv, h_pos, X0_CV, P0_CV, us, zs, masks, Q_CV, R_CV, save_smoother=True)
    want = smoother.rts(post)
    it = smoother.iterated(f_cv, h_pos, X0_CV, P0_CV, us, zs, masks, Q_CV, R_CV, num_iter=2)
    np.testing.assert_allclose(np.asarray(it.means), np.asarray(want.means), atol=1e-10)
    np.testing.assert_allclose(np.asarray(it.cov_diags), np.asarray(want.cov_diags), atol=1e-10)
    assert float(it.step_sizes[-1]) < 1e-8
    assert not np.any(np.asarray(it.status) & errors.NOT_CONVERGED)


# --------------------------------------------------------------------------
# Nonlinear: MAP by dense Gauss-Newton in NumPy (hand Jacobians)
# --------------------------------------------------------------------------

def np_h_rb(x, beacon=BEACON):
    d = x[:2] - beacon
    return np.array([np.hypot(d[0], d[1]), np.arctan2(d[1], d[0])])


def np_H_rb(x):
    d = x[:2] - BEACON
    r2 = d @ d
    r = np.sqrt(r2)
    return np.array([[d[0] / r, d[1] / r, 0, 0], [-d[1] / r2, d[0] / r2, 0, 0]])


def wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


def dense_gn_map(us, zs, R, weight=None, iters=60, x_init=None):
    """MAP of (x_{-1}, x_0..x_{T-1}) by dense Gauss-Newton; IRLS weights if given."""
    T = zs.shape[0]
    n = 4
    K = T + 1
    X = np.zeros((K, n)) if x_init is None else x_init.copy()
    Pi = np.linalg.inv(P0_CV)
    Qi = np.linalg.inv(Q_CV)
    sig = np.sqrt(np.diag(R))
    for _ in range(iters):
        N = K * n
        Lam = np.zeros((N, N))
        g = np.zeros(N)
        r0 = X[0] - X0_CV
        Lam[:n, :n] += Pi
        g[:n] += Pi @ r0
        for k in range(T):
            a, b = k * n, (k + 1) * n
            r = X[k + 1] - F_CV @ X[k] - G_CV @ us[k]
            J = np.zeros((n, N))
            J[:, a:a + n] = -F_CV
            J[:, b:b + n] = np.eye(n)
            Lam += J.T @ Qi @ J
            g += J.T @ Qi @ r
        for t in range(T):
            x = X[t + 1]
            r = zs[t] - np_h_rb(x)
            r[1] = wrap(r[1])
            Ri = np.linalg.inv(R)
            if weight is not None:
                w = weight(r / sig)
                sw = np.sqrt(w)
                Ri = np.linalg.inv(R / np.outer(sw, sw))
            J = np.zeros((2, N))
            J[:, (t + 1) * n:(t + 2) * n] = np_H_rb(x)
            Lam += J.T @ Ri @ J
            g -= J.T @ Ri @ r
        dx = np.linalg.solve(Lam, -g)
        X = X + dx.reshape(K, n)
        if np.max(np.abs(dx)) < 1e-13:
            break
    return X


R_RB = np.diag([0.05**2, 0.02**2])
# one residual function for the eager iterated-smoother calls: it is part of their compiled
# program's key, so one made per test compiled the same smoother again
RES_RB = ekf.angle_residual([False, True])


def _rb_data(seed=3, T=30, outliers=False, beacon=BEACON):
    us, xs, zs = simulate(seed, T, lambda x: np_h_rb(x, beacon), R=R_RB)
    if outliers:
        zs = zs.copy()
        zs[[4, 11, 20], 0] += np.array([1.5, -2.0, 3.0])
    return us, xs, zs


def test_iterated_converges_to_map():
    us, _, zs = _rb_data()
    res = RES_RB
    it = smoother.iterated(f_cv, h_rb, X0_CV, P0_CV, us, zs, None, Q_CV, R_RB, num_iter=8,
                           residual=res)
    X = dense_gn_map(us, zs, R_RB)
    np.testing.assert_allclose(np.asarray(it.means), X[1:], atol=1e-8)
    np.testing.assert_allclose(np.asarray(it.initial.mean), X[0], atol=1e-8)
    assert not np.any(np.asarray(it.status) & errors.NOT_CONVERGED)
    # one pass (filter linearised at its own estimates, then RTS) is not the MAP here
    post = ekf.filter_scan(f_cv, h_rb, X0_CV, P0_CV, us, zs, None, Q_CV, R_RB, residual=res,
                           save_smoother=True)
    gap = np.max(np.abs(np.asarray(smoother.rts(post).means) - X[1:]))
    assert gap > 1e-6
    # Levenberg-Marquardt damping changes the path, not the fixed point
    itd = smoother.iterated(f_cv, h_rb, X0_CV, P0_CV, us, zs, None, Q_CV, R_RB, num_iter=25,
                            residual=res, damping=1.0)
    np.testing.assert_allclose(np.asarray(itd.means), X[1:], atol=1e-7)


def test_iterated_robust_equals_dense_irls():
    us, xs, zs = _rb_data(outliers=True)
    res = RES_RB
    k = 1.345
    it = smoother.iterated(f_cv, h_rb, X0_CV, P0_CV, us, zs, None, Q_CV, R_RB, num_iter=40,
                           residual=res, robust=smoother.huber_weight(k))

    def huber_np(r):
        a = np.abs(r)
        return np.where(a <= k, 1.0, k / np.maximum(a, k))

    X = dense_gn_map(us, zs, R_RB, weight=huber_np, iters=200)
    np.testing.assert_allclose(np.asarray(it.means), X[1:], atol=1e-7)
    # num_iter as in test_iterated_converges_to_map: the same compiled smoother
    plain = smoother.iterated(f_cv, h_rb, X0_CV, P0_CV, us, zs, None, Q_CV, R_RB, num_iter=8,
                              residual=res)
    assert not np.any(np.asarray(plain.status) & errors.NOT_CONVERGED)
    err_r = np.sqrt(np.mean(np.sum((np.asarray(it.means)[:, :2] - xs[:, :2]) ** 2, 1)))
    err_p = np.sqrt(np.mean(np.sum((np.asarray(plain.means)[:, :2] - xs[:, :2]) ** 2, 1)))
    assert err_r < err_p  # the outliers pull the least-squares trajectory, not the robust one


def test_robust_weights():
    r = jnp.array([0.0, 1.0, 2.0, 10.0])
    np.testing.assert_allclose(smoother.huber_weight(1.345)(r), [1, 1, 1.345 / 2, 0.1345])
    np.testing.assert_allclose(smoother.cauchy_weight(2.0)(r), [1, 0.8, 0.5, 1 / 26])
    np.testing.assert_allclose(smoother.tukey_weight(4.0)(r), [1, (15 / 16) ** 2, 0.5625, 0])


def test_smoothed_loss_gradient_matches_finite_differences():
    us, xs, zs = _rb_data(seed=5, T=20)
    res = ekf.angle_residual([False, True])

    def loss(theta):
        Q = jnp.exp(theta[0]) * jnp.asarray(Q_CV)
        R = jnp.diag(jnp.exp(theta[1:]))
        post = ekf.filter_scan(f_cv, h_rb, X0_CV, P0_CV, us, zs, None, Q, R, residual=res,
                               save_smoother=True)
        sm = smoother.rts(post)
        return jnp.mean(jnp.sum((sm.means[:, :2] - xs[:, :2]) ** 2, 1))

    th = jnp.array([0.0, np.log(0.05**2), np.log(0.02**2)])
    loss_j = jax.jit(loss)  # one program each, not one per operation
    g = jax.jit(jax.grad(loss))(th)
    eps = 1e-5
    fd = np.array([(loss_j(th.at[i].add(eps)) - loss_j(th.at[i].add(-eps))) / (2 * eps)
                   for i in range(3)])
    np.testing.assert_allclose(np.asarray(g), fd, rtol=1e-4)


def test_masks_vmapped_equal_one_by_one(linear_run):
    us, zs, _ = linear_run
    T = zs.shape[0]
    rng = np.random.default_rng(7)
    M = rng.random((4, T, 2)) > 0.4

    def one(mk):
        post = ekf.filter_scan(f_cv, h_pos, X0_CV, P0_CV, us, zs, mk, Q_CV, R_CV,
                               save_smoother=True)
        return smoother.rts(post).means

    batch = jax.jit(jax.vmap(one))(jnp.asarray(M))
    one = jax.jit(one)  # one program for the four runs, not one per operation
    for i in range(4):
        np.testing.assert_allclose(np.asarray(batch[i]), np.asarray(one(M[i])), atol=1e-12)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_smoother_dtype(linear_run, dtype):
    us, zs, masks = linear_run
    post = ekf.filter_scan(f_cv, h_pos, X0_CV.astype(dtype), P0_CV.astype(dtype),
                           us.astype(dtype), zs.astype(dtype), masks, Q_CV.astype(dtype),
                           R_CV.astype(dtype), save_smoother=True)
    sm = smoother.rts(post)
    assert sm.means.dtype == dtype and sm.covs.dtype == dtype
    mu, _ = dense_linear_posterior(us, zs, masks)
    tol = 1e-4 if dtype == np.float32 else 1e-9
    np.testing.assert_allclose(np.asarray(sm.means), mu, atol=tol)


def _mc_consistency(runs, T, seed0=100):
    res = ekf.angle_residual([False, True])
    data = [_rb_data(seed=seed0 + i, T=T, beacon=BEACON_MC) for i in range(runs)]
    h = make_h_rb(BEACON_MC)
    us = jnp.asarray(np.stack([d[0] for d in data]))
    xs = np.stack([d[1] for d in data])
    zs = jnp.asarray(np.stack([d[2] for d in data]))

    @jax.jit
    def one(u, z):
        post = ekf.filter_scan(f_cv, h, X0_CV, P0_CV, u, z, None, Q_CV, R_RB, residual=res,
                               save_smoother=True)
        sm = smoother.rts(post)
        return post.means, post.covs, sm.means, sm.covs

    fm, fc, sm, sc = jax.vmap(one)(us, zs)
    e_f = np.asarray(fm) - xs
    e_s = np.asarray(sm) - xs
    nees_s = np.einsum("rti,rtij,rtj->rt", e_s, np.linalg.inv(np.asarray(sc)), e_s)
    nees_f = np.einsum("rti,rtij,rtj->rt", e_f, np.linalg.inv(np.asarray(fc)), e_f)
    return e_f, e_s, nees_f, nees_s


def _anees_bounds(runs, dim=4, p=0.99):
    lo, hi = stats.chi2.ppf([(1 - p) / 2, (1 + p) / 2], runs * dim) / runs
    return lo, hi


def test_smoother_consistency_and_rmse():
    """ANEES of the EKF-RTS smoother inside χ² bounds over 100 runs; RMSE below the filter's."""
    runs, T = 100, 40
    e_f, e_s, nees_f, nees_s = _mc_consistency(runs, T)
    # five checks, each at 99 % (family-wise false-alarm rate ≈ 5 %, Bonferroni)
    lo, hi = _anees_bounds(runs)
    for t in (0, 5, 20, 39):  # per time step across runs (early and late, not only a run mean)
        assert lo <= nees_s[:, t].mean() <= hi, (t, nees_s[:, t].mean(), lo, hi)
    # time-averaged: the steps of a run are correlated, so the bounds of `runs` samples apply
    assert lo <= nees_s.mean() <= hi, (nees_s.mean(), lo, hi)
    rmse_f = np.sqrt(np.mean(np.sum(e_f[:, :, :2] ** 2, -1)))
    rmse_s = np.sqrt(np.mean(np.sum(e_s[:, :, :2] ** 2, -1)))
    assert rmse_s < 0.8 * rmse_f, (rmse_s, rmse_f)


def _random_walk_posterior(T, q, r, p0, zs):
    """Dense oracle: s_0 ~ N(0, p0), s_t = s_{t-1} + N(0, q), z_t = s_t + N(0, r), t = 1..T;
    the means and variances of s_1..s_T from the information matrix of the whole batch."""
    J, b = np.zeros((T + 1, T + 1)), np.zeros(T + 1)
    J[0, 0] += 1 / p0
    for t in range(1, T + 1):
        J[t - 1:t + 1, t - 1:t + 1] += np.array([[1, -1], [-1, 1]]) / q
        J[t, t] += 1 / r
        b[t] += zs[t - 1] / r
    C = np.linalg.inv(J)
    return (C @ b)[1:], np.diag(C)[1:]


def test_damped_iterations_keep_their_option_and_return_undamped_covariances():
    """Review of 2026-12-07: (1) the compiled program was keyed without damping, so a damped call
    after an undamped one with the same f and h ran undamped Gauss–Newton; (2) the damped run
    returned the covariances of its last damped pass (the pseudo-measurements' information in
    them): 0.29-0.37 against the true 0.45-0.62 here."""
    T = 5
    zs = np.arange(1.0, T + 1)[:, None]
    mo, vo = _random_walk_posterior(T, 1.0, 1.0, 1.0, zs[:, 0])
    f, h = (lambda x, u: x), (lambda x: x)
    x0, P0, Q, R = np.zeros(1), np.eye(1), np.eye(1), np.eye(1)
    a = smoother.iterated(f, h, x0, P0, None, zs, None, Q, R, num_iter=3)
    b = smoother.iterated(f, h, x0, P0, None, zs, None, Q, R, num_iter=3, damping=1.0)
    g, k = (lambda x, u: x), (lambda x: x)  # new functions: nothing compiled before
    c = smoother.iterated(g, k, x0, P0, None, zs, None, Q, R, num_iter=3, damping=1.0)
    np.testing.assert_allclose(np.asarray(b.step_sizes), np.asarray(c.step_sizes), rtol=1e-12)
    assert float(b.step_sizes[1]) > 0 and float(a.step_sizes[1]) < 1e-12  # damped: not one exact step
    d = smoother.iterated(f, h, x0, P0, None, zs, None, Q, R, num_iter=300, damping=1.0, save_cov=True)
    np.testing.assert_allclose(np.asarray(d.means)[:, 0], mo, atol=1e-10)
    np.testing.assert_allclose(np.asarray(d.cov_diags)[:, 0], vo, rtol=1e-10)
    np.testing.assert_allclose(np.asarray(a.cov_diags)[:, 0], vo, rtol=1e-10)  # undamped: the same
    assert not np.asarray(d.status).any()


@pytest.mark.parametrize("call, msg", [
    (lambda fl, z: smoother.fixed_lag(fl, X0_CV, P0_CV, None, z, None, Q_CV, R_CV, lag=2, difference=5),
     r"^difference: expected None or a function"),
    (lambda fl, z: smoother.fixed_lag(None, X0_CV, P0_CV, None, z, None, Q_CV, R_CV, lag=2), r"^flt: expected a"),
    (lambda fl, z: smoother.fixed_lag(fl, X0_CV, P0_CV, None, z, None, Q_CV, R_CV, lag=2, predict_first="no"),
     r"^predict_first: expected True or False"),
    (lambda fl, z: smoother.rts(gaussian.run(fl, X0_CV, P0_CV, np.zeros((6, 2)), z, None, Q_CV, R_CV,
                                             save_smoother=True), save_cov="no"), r"^save_cov: expected True or False"),
    (lambda fl, z: smoother.iterated(f_cv, h_pos, X0_CV, P0_CV, None, z, None, Q_CV, R_CV, save_cov="no"),
     r"^save_cov: expected True or False"),
    (lambda fl, z: smoother.iterated(f_cv, h_pos, X0_CV, P0_CV, None, z, None, Q_CV, R_CV, residual=5),
     r"^residual: expected None or a function"),
    (lambda fl, z: smoother.iterated(f_cv, h_pos, X0_CV, P0_CV, None, z, None, Q_CV, R_CV, difference=5),
     r"^difference: expected None or a function"),
], ids=["fixed_lag-difference", "fixed_lag-flt", "fixed_lag-predict_first", "rts-save_cov",
        "iterated-save_cov", "iterated-residual", "iterated-difference"])
def test_smoother_switches_and_functions_are_checked(call, msg):
    zs = np.zeros((6, H_CV.shape[0]))
    with pytest.raises(InputError, match=msg):
        call(ekf.make_filter(f_cv, h_pos), zs)
