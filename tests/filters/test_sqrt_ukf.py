"""Tests of the square-root sigma-point filter (jaxslam.filters.sqrt_ukf).

Oracles: the closed-form KF of test_ukf (linear model), the covariance-form sigma-point filter
(jaxslam.filters.ukf, itself checked against NumPy and filterpy) on the pendulum, and the float32
long run of test_sqrt_ekf (float64 reference; the covariance-form UKF shown to fail there).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam import errors
from jaxslam.errors import InputError
from jaxslam.filters import sqrt_ekf as se
from jaxslam.filters import sqrt_ukf as su
from jaxslam.filters import ukf

from test_sqrt_ekf import H_LR, P0_LR, Q_LR, R_LR, T_LR, f_rw, h_lr

from cv_model import DT, F_CV, G_CV, H_CV, P0_CV, Q_CV, R_CV, X0_CV, f_cv, h_pos  # noqa: F401

# One-update tests call these, jitted once for speed only (run eagerly, each update compiled
# dozens of one-operation programs); the functions and options are static.
_STATIC = ("h", "residual", "gate", "points")
su_update = jax.jit(su.update, static_argnames=_STATIC)
ukf_update = jax.jit(ukf.update, static_argnames=_STATIC)
se_update = jax.jit(se.update, static_argnames=_STATIC[:3])


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


G_GRAV, DT_P = 9.81, 0.05
QP = np.diag([1e-4, 4e-3])
RP = np.array([[0.02]])


def f_pend(x, u):
    return jnp.stack([x[0] + DT_P * x[1], x[1] - DT_P * G_GRAV * jnp.sin(x[0])])


def h_pend(x):
    return jnp.sin(x[:1])


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



RULES = [ukf.unscented(), ukf.cubature()]


@pytest.mark.parametrize("rule", RULES, ids=["unscented", "cubature"])
@pytest.mark.parametrize("predict_first", [True, False])
def test_linear_equals_kalman_filter(rule, predict_first):
    rng = np.random.default_rng(0)
    T = 20
    us = rng.normal(0, 0.5, (T, 2))
    zs = rng.normal(0, 1.0, (T, 2))
    masks = rng.random((T, 2)) > 0.3
    masks[4] = False
    post = su.filter_scan(f_cv, h_pos, X0_CV, P0_CV, us, zs, masks, Q_CV, R_CV, predict_first=predict_first,
                          points=rule, save_chol=True)
    m, P = np_kf(us, zs, masks, predict_first)
    np.testing.assert_allclose(np.asarray(post.means), m, atol=1e-10)
    L = np.asarray(post.chols)
    np.testing.assert_allclose(L @ np.swapaxes(L, 1, 2), P, atol=1e-10)


@pytest.mark.parametrize("dtype,tol", [(np.float64, 1e-10), (np.float32, 2e-4)])
def test_pendulum_equals_covariance_form(dtype, tol):
    _, zs = _pendulum(4)
    x0, P0 = np.array([1.0, 0.1], dtype), np.diag([0.1, 0.1]).astype(dtype)
    a = su.filter_scan(f_pend, h_pend, x0, P0, None, zs.astype(dtype), None, QP.astype(dtype), RP.astype(dtype))
    b = ukf.filter_scan(f_pend, h_pend, np.array([1.0, 0.1]), np.diag([0.1, 0.1]), None, zs, None, QP, RP)
    assert a.means.dtype == dtype
    np.testing.assert_allclose(np.asarray(a.means, np.float64), np.asarray(b.means), atol=tol)
    np.testing.assert_allclose(np.asarray(a.cov_diags, np.float64), np.asarray(b.cov_diags), atol=tol, rtol=tol)
    np.testing.assert_allclose(np.asarray(a.nis, np.float64), np.asarray(b.nis), rtol=max(tol, 1e-8) * 50)


def test_update_masks_gate_and_logdet():
    st = se.from_gaussian(ukf.Gaussian(jnp.asarray(X0_CV), jnp.asarray(P0_CV)))
    g = ukf.Gaussian(jnp.asarray(X0_CV), jnp.asarray(P0_CV))
    z = np.array([0.3, np.nan])
    mk = np.array([True, False])
    a, ia = su_update(st, z, h_pos, R_CV, mask=mk)
    b, ib = ukf_update(g, z, h_pos, R_CV, mask=mk)
    np.testing.assert_allclose(np.asarray(a.mean), np.asarray(b.mean), atol=1e-12)
    np.testing.assert_allclose(np.asarray(se.to_gaussian(a).cov), np.asarray(b.cov), atol=1e-12)
    np.testing.assert_allclose(float(ia.logdet), float(ib.logdet), atol=1e-12)
    _, ig = su_update(st, np.array([50.0, 50.0]), h_pos, R_CV, gate=9.21)
    assert int(ig.status) & errors.GATED and not bool(ig.accepted)
    with pytest.raises(InputError, match="W\\^c_0"):
        su.update(st, z, h_pos, R_CV, points=ukf.unscented(alpha=1e-3))  # W^c_0 < 0


def test_float32_long_poorly_observable_run():
    """10⁵ float32 steps of test_sqrt_ekf's model: the covariance-form UKF loses definiteness
    (NOT_PSD on most updates), the square-root form stays PD and follows float64."""
    rng = np.random.default_rng(5)
    xs = rng.normal(size=2) * np.sqrt(P0_LR) + np.cumsum(rng.normal(size=(T_LR, 2)) * np.sqrt(Q_LR), 0)
    zs = (xs @ H_LR + rng.normal(size=T_LR) * np.sqrt(R_LR))[:, None]

    def args(z):
        dt = z.dtype
        return (jnp.zeros(2, dt), P0_LR * jnp.eye(2, dtype=dt), None, z, None, Q_LR * jnp.eye(2, dtype=dt),
                jnp.full((1, 1), R_LR, dt))

    run_s = jax.jit(lambda z: su.filter_scan(f_rw, h_lr, *args(z), points=ukf.cubature()))
    run_c = jax.jit(lambda z: ukf.filter_scan(f_rw, h_lr, *args(z), points=ukf.cubature()))
    ref = run_s(zs)
    s32 = run_s(zs.astype(np.float32))
    c32 = run_c(zs.astype(np.float32))
    not_psd_c = int(np.sum((np.asarray(c32.status) & errors.NOT_PSD) != 0))
    assert not_psd_c > 0.9 * T_LR  # the covariance form fails
    assert np.all(np.asarray(s32.status) == 0) and np.all(np.isfinite(np.asarray(s32.means)))
    L = np.asarray(s32.final.chol)
    assert np.all(np.diagonal(L) > 0)
    hph_ref = float(np.asarray(ref.final.chol @ ref.final.chol.T) @ H_LR @ H_LR)
    err = np.abs((np.asarray(s32.means, np.float64) - np.asarray(ref.means)) @ H_LR) / np.sqrt(hph_ref)
    assert float(np.max(err[1000:])) < 0.1


def test_bearing_near_pi_and_failed_factor_flag():
    """The sigma mean is angle-safe as in ukf.update; a failed S factor is NOT_PSD, not GATED."""
    from jaxslam.filters import ekf

    def h_bearing(x):
        return jnp.arctan2(x[1:2], x[:1])

    x = np.array([-1.0, 1e-3])
    P = np.diag([0.01, 0.01])
    z = np.array([np.pi - 0.005])
    res = ekf.angle_residual([True])
    a, ia = su_update(se.from_gaussian(ukf.Gaussian(jnp.asarray(x), jnp.asarray(P))), z, h_bearing,
                      np.array([[1e-4]]), residual=res)
    b, ib = ukf_update(ukf.Gaussian(jnp.asarray(x), jnp.asarray(P)), z, h_bearing, np.array([[1e-4]]),
                       residual=res)
    np.testing.assert_allclose(np.asarray(a.mean), np.asarray(b.mean), atol=1e-10)
    np.testing.assert_allclose(float(ia.nis), float(ib.nis), rtol=1e-8)
    st = se.from_gaussian(ukf.Gaussian(jnp.asarray(X0_CV), jnp.asarray(P0_CV)))
    for upd in (lambda: se_update(st, np.array([5.0]), lambda v: v[:1], np.array([[-1.0]]), gate=3.84),
                lambda: su_update(st, np.array([5.0]), lambda v: v[:1], np.array([[-1.0]]), gate=3.84)):
        _, info = upd()
        assert int(info.status) & errors.NOT_PSD and not int(info.status) & errors.GATED
        assert float(info.nis) == 0.0
