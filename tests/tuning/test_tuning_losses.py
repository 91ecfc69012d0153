"""Losses against SciPy / NumPy oracles; the EKF-SLAM innovation terms against hand Jacobians."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.stats import multivariate_normal

from jaxslam.filters import ekf_slam as es
from jaxslam.systems import ekf_slam_3d as sys3d
from jaxslam.tuning import losses as L

import sensors_oracle_np as ref  # noqa: E402  (hand-derived LiDAR Jacobians)


def _spd(rng, n):
    A = rng.normal(size=(n, n))
    return A @ A.T + 0.5 * np.eye(n)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_nll_terms_match_scipy_logpdf(dtype):
    rng = np.random.default_rng(0)
    S = _spd(rng, 4)
    nu = rng.normal(size=4)
    nis, logdet, dof = L.nll_terms(jnp.asarray(nu, dtype), jnp.asarray(S, dtype))
    assert nis.dtype == dtype
    nll = 0.5 * (float(nis) + float(logdet) + float(dof) * math.log(2 * math.pi))
    want = -multivariate_normal(mean=np.zeros(4), cov=S).logpdf(nu)
    np.testing.assert_allclose(nll, want, rtol=1e-5 if dtype == jnp.float32 else 1e-12)


def test_masked_components_add_nothing():
    rng = np.random.default_rng(1)
    S2 = _spd(rng, 2)
    S = np.eye(4)
    S[:2, :2] = S2  # invalid rows carry identity, as the EKF reports S
    nu = np.r_[rng.normal(size=2), 123.0, -7.0]
    mask = np.array([True, True, False, False])
    nis, logdet, dof = L.nll_terms(jnp.asarray(nu), jnp.asarray(S), jnp.asarray(mask))
    assert float(dof) == 2
    want = -multivariate_normal(mean=np.zeros(2), cov=S2).logpdf(nu[:2])
    np.testing.assert_allclose(0.5 * (float(nis) + float(logdet) + 2 * math.log(2 * math.pi)), want, rtol=1e-12)


def test_innovation_nll_is_mean_negative_log_density():
    rng = np.random.default_rng(2)
    terms, tot = [], 0.0
    want = 0.0
    for k in range(5):
        m = [3, 0, 2, 3, 1][k]
        if m == 0:
            terms.append((0.0, 0.0, 0.0))
            continue
        S = _spd(rng, m)
        nu = rng.normal(size=m)
        want += -multivariate_normal(mean=np.zeros(m), cov=S).logpdf(nu)
        tot += m
        terms.append((float(nu @ np.linalg.solve(S, nu)), float(np.linalg.slogdet(S)[1]), float(m)))
    nis, logdet, dof = (jnp.asarray(v) for v in zip(*terms))
    np.testing.assert_allclose(float(L.innovation_nll(nis, logdet, dof)), want / tot, rtol=1e-12)


def test_mse_and_nees_loss_closed_forms():
    rng = np.random.default_rng(3)
    e = rng.normal(size=(50, 3))
    w = np.array([1.0, 2.0, 0.5])
    np.testing.assert_allclose(float(L.mse(jnp.asarray(e))), np.mean(np.sum(e**2, 1)), rtol=1e-12)
    np.testing.assert_allclose(float(L.mse(jnp.asarray(e), w)), np.mean(e**2 @ w), rtol=1e-12)
    mask = np.arange(50) >= 20
    np.testing.assert_allclose(float(L.mse(jnp.asarray(e), None, jnp.asarray(mask))),
                               np.mean(np.sum(e[mask] ** 2, 1)), rtol=1e-12)
    nees = rng.uniform(5, 15, size=40)
    np.testing.assert_allclose(float(L.nees_loss(jnp.asarray(nees), 9)), np.log(nees.mean() / 9) ** 2, rtol=1e-12)
    np.testing.assert_allclose(float(L.nees_loss(jnp.asarray(nees), 9, jnp.asarray(np.arange(40) < 10))),
                               np.log(nees[:10].mean() / 9) ** 2, rtol=1e-12)
    assert float(L.nees_loss(jnp.full(7, 9.0), 9)) == 0.0


def test_slam_innovation_terms_against_dense_numpy_and_engine():
    """Joint S of K LiDAR measurements: dense H from the hand Jacobians of sensors_oracle_np."""
    rng = np.random.default_rng(4)
    cap, K = 6, 4
    n = 9 + 3 * cap
    model = sys3d.make_model()
    s = np.array([0.3, -0.2, -3.0, 0.5, 0.1, -0.05, 0.05, -0.04, 0.3])
    lms = s[:3] + np.array([[10, 1, 0.5], [8, -2, 1.0], [12, 3, -1.0], [9, 0, 2.0], [7, 1, 1], [11, -1, 0]], float)
    x = np.r_[s, lms.ravel()]
    B = rng.normal(size=(n, n)) * 0.05
    Pm = B @ B.T + 1e-3 * np.eye(n)
    st = es.init(jnp.asarray(s), jnp.asarray(Pm[:9, :9]), cap, 3)._replace(
        x=jnp.asarray(x), P=jnp.asarray(Pm), active=jnp.ones(cap, bool), ids=jnp.arange(cap, dtype=jnp.int32))
    slots = np.array([4, 1, 2, 0])
    valid = np.array([True, True, False, True])
    R = np.diag([1e-4, 2e-4, 4e-3])
    z = np.stack([ref.lidar_measure(s[:3], s[6:9], lms[j]) for j in slots]) + rng.normal(size=(K, 3)) * 0.01
    mp = (0.01, 9.81, "3axis")
    # One jitted program each (eager op-by-op dispatch of these is many times slower to run).
    nis, logdet, dof = jax.jit(lambda *a: L.slam_innovation_terms(st, model, *a, mp))(
        jnp.asarray(z), jnp.asarray(slots), jnp.asarray(valid), jnp.asarray(R))
    rows, nus = [], []
    for k in np.flatnonzero(valid):
        Hs, Hl = ref.lidar_H(s, lms[slots[k]])
        H = np.zeros((3, n))
        H[:, :9] = Hs
        H[:, 9 + 3 * slots[k]: 12 + 3 * slots[k]] = Hl
        rows.append(H)
        nu = z[k] - ref.lidar_measure(s[:3], s[6:9], lms[slots[k]])
        nu[0] = (nu[0] + np.pi) % (2 * np.pi) - np.pi
        nus.append(nu)
    H = np.concatenate(rows)
    nu = np.concatenate(nus)
    S = H @ Pm @ H.T + np.kron(np.eye(len(rows)), R)
    assert float(dof) == 3 * valid.sum()
    np.testing.assert_allclose(float(nis), nu @ np.linalg.solve(S, nu), rtol=1e-9)
    np.testing.assert_allclose(float(logdet), np.linalg.slogdet(S)[1], rtol=1e-10)
    # The engine's own NIS of the same update (gathered columns, explicit S⁻¹) agrees.
    _, info = jax.jit(lambda *a: es.update(st, model, *a, mp))(
        jnp.asarray(z), jnp.asarray(slots), jnp.asarray(valid), jnp.asarray(R))
    np.testing.assert_allclose(float(nis), float(info.nis), rtol=1e-9)
