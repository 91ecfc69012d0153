"""Delayed initialisation from buffered ranges (filters/delayed_init.py): exact recovery on
noise-free rows, the outlier cut of the robust fit against a NumPy least-squares oracle, the
(D1) covariance, degenerate buffers reported not ready."""

import jax
import jax.numpy as jnp
import numpy as np

from jaxslam.filters import delayed_init as di

L_TRUE = np.array([3.0, -2.0])


def _rows(W=20, seed=0):
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-5, 5, size=(W, 2))
    return pts, np.linalg.norm(pts - L_TRUE, axis=1)


def _nlls_oracle(pts, r):
    """Nonlinear least squares of ‖p − l‖ = r by Gauss-Newton in NumPy (independent of the
    linearised trilateration)."""
    l = pts.mean(0)
    for _ in range(50):
        d = np.linalg.norm(pts - l, axis=1)
        J = (l - pts) / d[:, None]
        l = l - np.linalg.lstsq(J, d - r, rcond=None)[0]
    return l


def test_noise_free_rows_give_the_landmark():
    pts, r = _rows()
    fit, P = di.from_buffer(jnp.asarray(pts), jnp.zeros(20), jnp.asarray(r), jnp.ones(20, bool), 0.01)
    assert bool(fit.ok)
    np.testing.assert_allclose(np.asarray(fit.position), L_TRUE, atol=1e-9)


def test_robust_fit_drops_an_outlier_and_matches_the_oracle_on_the_rest():
    pts, r = _rows(W=30, seed=1)
    r = r + np.random.default_rng(2).normal(0, 0.05, 30)
    r_bad = r.copy()
    r_bad[7] += 6.0  # an NLOS range
    valid = jnp.ones(30, bool)
    plain, _ = di.from_buffer(jnp.asarray(pts), jnp.zeros(30), jnp.asarray(r_bad), valid, 0.05**2)
    robust, _ = di.from_buffer(jnp.asarray(pts), jnp.zeros(30), jnp.asarray(r_bad), valid, 0.05**2, robust=True)
    keep = np.arange(30) != 7
    oracle = _nlls_oracle(pts[keep], r[keep])
    assert np.linalg.norm(np.asarray(robust.position) - oracle) < 0.05
    assert np.linalg.norm(np.asarray(plain.position) - L_TRUE) > 3 * np.linalg.norm(np.asarray(robust.position) - L_TRUE)


def test_covariance_adds_the_mean_buffered_position_variance():
    pts, r = _rows()
    valid = jnp.asarray(np.arange(20) < 15)
    pv = jnp.asarray(np.linspace(0.01, 0.2, 20))
    fit0, P0 = di.from_buffer(jnp.asarray(pts), jnp.zeros(20), jnp.asarray(r), valid, 0.04)
    fit1, P1 = di.from_buffer(jnp.asarray(pts), pv, jnp.asarray(r), valid, 0.04)
    np.testing.assert_allclose(np.asarray(P1 - P0), np.mean(np.asarray(pv)[:15]) * np.eye(2), atol=1e-12)
    # a shared buffer averages the variances of other rows (var_rows)
    _, P2 = di.from_buffer(jnp.asarray(pts), pv, jnp.asarray(r), valid, 0.04, var_rows=jnp.ones(20, bool))
    np.testing.assert_allclose(np.asarray(P2 - P0), np.mean(np.asarray(pv)) * np.eye(2), atol=1e-12)
    assert np.all(np.linalg.eigvalsh(np.asarray(P1)) > 0)


def test_collinear_or_short_buffers_are_not_ready_and_stay_finite():
    x = np.linspace(-4, 4, 10)
    pts = np.stack([x, np.zeros(10)], 1)  # a straight line: mirror ambiguity
    r = np.linalg.norm(pts - L_TRUE, axis=1)
    fit, P = jax.jit(lambda p, r: di.from_buffer(p, jnp.zeros(10), r, jnp.ones(10, bool), 0.01, robust=True))(
        jnp.asarray(pts), jnp.asarray(r))
    assert not bool(fit.ok)
    assert np.all(np.isfinite(np.asarray(fit.position))) and np.all(np.isfinite(np.asarray(P)))
    pts2, r2 = _rows()
    few = jnp.asarray(np.arange(20) < 2)
    fit2, _ = di.from_buffer(jnp.asarray(pts2), jnp.zeros(20), jnp.asarray(r2), few, 0.01, min_points=5)
    assert not bool(fit2.ok)
