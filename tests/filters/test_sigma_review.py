"""Review of the sigma-point and square-root filters (ukf, sqrt_ukf, sqrt_ekf): input checks and
status flags, each against an independent expectation (hand-computed values, a NumPy Kalman
filter)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam import errors
from jaxslam.errors import InputError
from jaxslam.filters import sqrt_ekf, sqrt_ukf, ukf
from jaxslam.filters.sqrt_ekf import SqrtGaussian

jax.config.update("jax_enable_x64", True)

F = np.array([[1.0, 0.1], [0.0, 1.0]])
H = np.array([[1.0, 0.0]])
Q = 0.01 * np.eye(2)
R = np.array([[0.1]])
ZS = np.array([[0.3], [-0.1], [0.5], [0.2], [0.4], [0.1]])


def f_lin(x, u):
    return jnp.asarray(F) @ x


def h_lin(x):
    return jnp.asarray(H) @ x


def numpy_kf(x0, P0, predict_first):
    """Plain Kalman filter: the filtered means and variances."""
    x, P = np.array(x0, float), np.array(P0, float)
    means, var = [], []
    for z in ZS:
        if predict_first:
            x, P = F @ x, F @ P @ F.T + Q
        S = H @ P @ H.T + R
        K = P @ H.T @ np.linalg.inv(S)
        x = x + K @ (z - H @ x)
        P = P - K @ S @ K.T
        means.append(x.copy())
        var.append(np.diag(P).copy())
        if not predict_first:
            x, P = F @ x, F @ P @ F.T + Q
    return np.array(means), np.array(var)


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_sqrt_ekf_predict_rejects_non_finite_q_chol(bad):
    # sqrt_ekf.filter_scan and sqrt_ukf.predict refuse it; sqrt_ekf.predict returned a NaN factor
    s = SqrtGaussian(jnp.zeros(2), jnp.eye(2))
    C = np.array([[0.1, 0.0], [bad, 0.1]])
    with pytest.raises(InputError, match=r"^Q_chol: contains NaN or Inf"):
        sqrt_ekf.predict(s, f_lin, None, None, Q_chol=C)
    # a finite root still works: L' L'ᵀ = F Fᵀ + C Cᵀ (hand formula)
    C = np.array([[0.1, 0.0], [0.05, 0.2]])
    out = sqrt_ekf.predict(s, f_lin, None, None, Q_chol=C)
    L = np.asarray(out.chol)
    np.testing.assert_allclose(L @ L.T, F @ F.T + C @ C.T, atol=1e-14)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("q", [0.5, np.array([0.5])])
def test_sqrt_ukf_predict_scalar_q_of_one_component_state(q, dtype):
    # the project's convention (ukf.predict, sqrt_ekf.predict): a scalar Q of an n = 1 state is
    # its variance; sqrt_ukf.predict refused it with an InputError
    s = SqrtGaussian(jnp.asarray([0.2], dtype), jnp.asarray([[1.0]], dtype))
    out = sqrt_ukf.predict(s, lambda x, u: 0.9 * x, None, q)
    # linear f: mean 0.9·0.2, variance 0.9²·1 + 0.5
    assert out.mean.dtype == dtype and out.chol.dtype == dtype
    tol = 1e-6 if dtype == np.float32 else 1e-14
    np.testing.assert_allclose(np.asarray(out.mean, float), [0.18], rtol=tol)
    np.testing.assert_allclose(np.asarray(out.chol, float), [[np.sqrt(0.81 + 0.5)]], rtol=tol)
    with pytest.raises(InputError, match=r"^Q: "):  # still refused for n = 2
        sqrt_ukf.predict(SqrtGaussian(jnp.zeros(2), jnp.eye(2)), None, None, q)


@pytest.mark.parametrize("rule", [ukf.SigmaPoints("unscented", 1.0, float("nan"), 0.0),
                                  ukf.SigmaPoints("unscented", 1.0, float("inf"), 0.0),
                                  ukf.SigmaPoints("unscented", float("inf"), 2.0, 0.0)])
def test_directly_built_rule_with_non_finite_parameter_is_refused(rule):
    # ukf.unscented() refuses these; a SigmaPoints built directly gave NaN weights silently
    with pytest.raises(InputError, match=r"^points: (alpha|beta) must be a finite number"):
        ukf.sigma_points(jnp.zeros(2), jnp.eye(2), rule)
    with pytest.raises(InputError, match=r"^points: "):
        sqrt_ukf.predict(SqrtGaussian(jnp.zeros(2), jnp.eye(2)), None, None, np.eye(2), points=rule)


def test_directly_built_valid_rule_matches_hand_weights():
    # α = 0.5, β = 3, κ = 1, n = 3: λ = 0.25·4 − 3 = −2, n + λ = 1
    wm, wc, c = ukf.SigmaPoints("unscented", 0.5, 3.0, 1.0).weights(3)
    np.testing.assert_allclose(wm, [-2.0] + [0.5] * 6)
    np.testing.assert_allclose(wc, [-2.0 + 1 - 0.25 + 3] + [0.5] * 6)
    assert c == pytest.approx(1.0)


@pytest.mark.parametrize("rule", [ukf.cubature(), ukf.unscented()])
def test_empty_state_sigma_points_input_error(rule):
    # cubature divided by zero (ZeroDivisionError); unscented blamed alpha/kappa
    with pytest.raises(InputError, match=r"^points: a sigma-point rule needs a state of at least one"):
        ukf.sigma_points(jnp.zeros(0), jnp.zeros((0, 0)), rule)


def test_sqrt_ukf_scan_update_first_refuses_singular_p0():
    # ukf.filter_scan refuses it; sqrt_ukf failed its first update (NOT_PSD, prior kept)
    P0 = np.diag([1.0, 0.0])
    with pytest.raises(InputError, match=r"^P0: not positive definite"):
        sqrt_ukf.filter_scan(f_lin, h_lin, np.zeros(2), P0, None, ZS, None, Q, R, predict_first=False)
    # predict first: the predict makes the prior PD, the run equals the Kalman filter
    out = sqrt_ukf.filter_scan(f_lin, h_lin, np.zeros(2), P0, None, ZS, None, Q, R, predict_first=True)
    means, var = numpy_kf(np.zeros(2), P0, True)
    assert not np.any(np.asarray(out.status))
    np.testing.assert_allclose(np.asarray(out.means), means, atol=1e-12)
    np.testing.assert_allclose(np.asarray(out.cov_diags), var, atol=1e-12)
    # a PD P0 with the update first still equals the Kalman filter
    P0 = np.diag([1.0, 0.5])
    out = sqrt_ukf.filter_scan(f_lin, h_lin, np.zeros(2), P0, None, ZS, None, Q, R, predict_first=False)
    means, var = numpy_kf(np.zeros(2), P0, False)
    np.testing.assert_allclose(np.asarray(out.means), means, atol=1e-12)
    np.testing.assert_allclose(np.asarray(out.cov_diags), var, atol=1e-12)


@pytest.mark.parametrize("predict_first", [True, False])
def test_sqrt_ekf_scan_flags_non_finite_prediction(predict_first):
    # f is NaN for the control of step 2; the prior it makes is that of step 2 (predict first)
    # or step 3 (update first): that step must carry NON_FINITE, not only NOT_PSD
    def f(x, u):
        return jnp.where(u > 0, jnp.nan, 1.0) * (jnp.asarray(F) @ x)

    us = np.array([0.0, 0.0, 1.0, 0.0, 0.0, 0.0])
    out = sqrt_ekf.filter_scan(f, h_lin, np.zeros(2), np.eye(2), us, ZS, None, Q, R,
                               predict_first=predict_first)
    bad = 2 if predict_first else 3
    status = np.asarray(out.status)
    assert int(status[bad]) & errors.NON_FINITE
    assert not np.any(status[:bad])
    means, _ = numpy_kf(np.zeros(2), np.eye(2), predict_first)
    np.testing.assert_allclose(np.asarray(out.means)[:bad], means[:bad], atol=1e-12)
