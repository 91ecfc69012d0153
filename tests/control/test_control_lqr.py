"""CARE / LQR gain against SciPy, closed forms, implicit gradients, status flag, validation."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg as sl
from jax.test_util import check_grads

from jaxslam.control.flatness import linear_model
from jaxslam.control.lqr import care, lqr_gain, lyapunov, validate_weights
from jaxslam.errors import InputError

Q000 = np.diag([0.01] * 6 + [0.04])
R000 = np.diag([0.2, 0.2, 0.32, 0.1])  # Table 2 per errata


def _rel(a, b):
    return np.max(np.abs(np.asarray(a) - b)) / np.max(np.abs(b))


def _paper_model():
    A, B, _ = linear_model(jnp.float64)
    return np.asarray(A), np.asarray(B)


def test_paper_model_matches_scipy_and_closed_form():
    A, B = _paper_model()
    P, ok = jax.jit(lambda *a: care(*a, return_status=True))(A, B, Q000, R000)
    assert bool(ok)
    P_ref = sl.solve_continuous_are(A, B, Q000, R000)
    assert _rel(P, P_ref) < 1e-9
    K, P2 = lqr_gain(A, B, Q000, R000)
    K_ref = np.linalg.solve(R000, B.T @ P_ref)
    assert _rel(K, K_ref) < 1e-9
    # Decoupled double integrator per axis: K = [√(q1/r), √(q2/r + 2√(q1/r))]; yaw √(q/r).
    for i, r in enumerate([0.2, 0.2, 0.32]):
        k1 = math.sqrt(0.01 / r)
        np.testing.assert_allclose(K[i, i], k1, rtol=1e-12)
        np.testing.assert_allclose(K[i, i + 3], math.sqrt(0.01 / r + 2 * k1), rtol=1e-12)
    np.testing.assert_allclose(K[3, 6], math.sqrt(0.04 / 0.1), rtol=1e-12)


def _random_system(rng, n, m):
    A = rng.normal(size=(n, n))
    B = rng.normal(size=(n, m))
    L = rng.normal(size=(n, n))
    Q = L @ L.T / n + 0.05 * np.eye(n)
    M = rng.normal(size=(m, m))
    R = M @ M.T / m + 0.3 * np.eye(m)
    return A, B, Q, R


def _rel_residual(A, B, Q, R, P):
    P = np.asarray(P)
    G = B @ np.linalg.solve(R, B.T)
    res = A.T @ P + P @ A - P @ G @ P + Q
    return np.linalg.norm(res) / (np.linalg.norm(Q) + 2 * np.linalg.norm(A.T @ P)
                                  + np.linalg.norm(P @ G @ P))


def test_random_systems_match_scipy():
    """Well-conditioned draws (cond P < 1e5) agree to 1e-9; ill-conditioned ones (a random
    single-input 5-state system reached cond 1.7e7, where SciPy itself is only 7e-9 from a
    Newton-refined solution) must have a CARE residual no worse than SciPy's."""
    rng = np.random.default_rng(42)
    f = jax.jit(lambda *a: care(*a, return_status=True))
    worst, n_ill = 0.0, 0
    for n, m in [(3, 1), (5, 1), (6, 2), (9, 3)]:
        for _ in range(4):
            A, B, Q, R = _random_system(rng, n, m)
            P, ok = f(A, B, Q, R)
            assert bool(ok)
            P_ref = sl.solve_continuous_are(A, B, Q, R)
            if np.linalg.cond(P_ref) < 1e5:
                worst = max(worst, _rel(P, P_ref))
            else:
                n_ill += 1
                assert _rel_residual(A, B, Q, R, P) <= 2 * _rel_residual(A, B, Q, R, P_ref)
                assert _rel(P, P_ref) < 1e-6
    assert worst < 1e-9, worst
    assert n_ill <= 2


def test_vmap_over_weights():
    A, B = _paper_model()
    scales = jnp.array([0.5, 1.0, 4.0])
    Ks = jax.jit(jax.vmap(lambda s: lqr_gain(A, B, s * Q000, R000)[0]))(scales)
    for s, K in zip(np.asarray(scales), Ks):
        P = sl.solve_continuous_are(A, B, s * Q000, R000)
        assert _rel(K, np.linalg.solve(R000, B.T @ P)) < 1e-9


def test_gradients_q_r_paper_model():
    A, B = _paper_model()
    check_grads(jax.jit(lambda Q, R: lqr_gain(A, B, Q, R)[0]), (Q000, R000), order=1,
                modes=["fwd", "rev"], eps=1e-6)


def test_gradients_random_system_all_arguments():
    A, B, Q, R = _random_system(np.random.default_rng(3), 4, 2)
    check_grads(jax.jit(lambda A, B, Q, R: lqr_gain(A, B, Q, R)[0]), (A, B, Q, R), order=1,
                modes=["fwd", "rev"], eps=1e-6)


def test_gradient_matches_scipy_finite_difference():
    """d tr(P)/d q_ii against central differences of SciPy's solution."""
    A, B = _paper_model()
    g = jax.jit(jax.grad(lambda d: jnp.trace(care(A, B, jnp.diag(d), R000))))(jnp.diag(Q000))
    h = 1e-6
    fd = []
    for i in range(7):
        e = np.zeros(7)
        e[i] = h
        tr_p = np.trace(sl.solve_continuous_are(A, B, np.diag(np.diag(Q000) + e), R000))
        tr_m = np.trace(sl.solve_continuous_are(A, B, np.diag(np.diag(Q000) - e), R000))
        fd.append((tr_p - tr_m) / (2 * h))
    np.testing.assert_allclose(g, fd, rtol=1e-6)


def test_float32():
    A, B = _paper_model()
    f32 = [jnp.asarray(x, jnp.float32) for x in (A, B, Q000, R000)]
    K, P, ok = jax.jit(lambda *a: lqr_gain(*a, return_status=True))(*f32)
    assert P.dtype == K.dtype == jnp.float32 and bool(ok)
    assert _rel(P, sl.solve_continuous_are(A, B, Q000, R000)) < 1e-5
    A2, B2, Q2, R2 = _random_system(np.random.default_rng(5), 6, 2)
    P2, ok2 = jax.jit(lambda *a: care(*a, return_status=True))(
        *[jnp.asarray(x, jnp.float32) for x in (A2, B2, Q2, R2)])
    assert bool(ok2) and _rel(P2, sl.solve_continuous_are(A2, B2, Q2, R2)) < 1e-4


def test_failure_is_flagged_and_finite():
    # Unstable mode not reachable from the input: no stabilising solution.
    A = np.diag([1.0, -1.0])
    B = np.array([[0.0], [1.0]])
    P, ok = care(A, B, np.eye(2), np.eye(1), return_status=True)
    assert not bool(ok) and np.all(np.isfinite(P))
    # Undetectable marginal mode (eigenvalue 0 on the axis, Q blind to it, B blind too).
    A = np.diag([0.0, -1.0])
    P, ok = care(A, B, np.diag([0.0, 1.0]), np.eye(1), return_status=True)
    assert not bool(ok) and np.all(np.isfinite(P))


def test_lyapunov_matches_scipy():
    rng = np.random.default_rng(7)
    A = rng.normal(size=(5, 5)) - 4 * np.eye(5)
    C = rng.normal(size=(5, 5))
    X = lyapunov(jnp.asarray(A), jnp.asarray(C))
    # SciPy solves a X + X aᴴ = q; ours is Aᵀ X + X A + C = 0.
    np.testing.assert_allclose(X, sl.solve_continuous_lyapunov(A.T, -C), rtol=1e-10, atol=1e-12)


def test_validate_weights():
    validate_weights(Q000, R000, n=7, m=4)
    bad_q = Q000.copy()
    bad_q[0, 0] = -0.1
    with pytest.raises(InputError, match="Q_t"):
        validate_weights(bad_q, R000, names=("Q_t", "R_t"))
    with pytest.raises(InputError, match="R"):
        validate_weights(Q000, np.diag([0.2, 0.2, 0.0, 0.1]))  # PSD but not PD
    nonsym = Q000.copy()
    nonsym[0, 1] = 0.5
    with pytest.raises(InputError, match="Q.*symmetric"):
        validate_weights(nonsym, R000)
    with pytest.raises(InputError, match="Q"):
        validate_weights(np.eye(6), R000, n=7, m=4)
    with pytest.raises(InputError, match="R"):
        validate_weights(Q000, np.eye(3), n=7, m=4)
    with pytest.raises(InputError, match="Q"):
        validate_weights(np.ones(7), R000)
    with pytest.raises(InputError, match="R"):
        validate_weights(Q000, np.full((4, 4), np.nan))


def test_review_2026_12_07_no_nan_gain_and_no_indefinite_newton_step():
    """(1) A traced singular R: P was zeroed but K = R⁻¹BᵀP came back NaN (ok False, yet the NaN
    reached the controller); now zeros.  (2) float32, the paper's flat model with a yaw weight of
    1e-12: the sign iteration's P is off in the decoupled altitude block and the Newton steps
    from it, whose closed loop is not stable, reached an indefinite CARE solution (P[5,5] = -90
    where SciPy gives 0.199) and a destabilising altitude gain (K[2,5] = -282 against 0.620).
    A step is now kept only while P stays PSD (the sign iteration's P, still off, stays); the
    failure is still reported (ok False)."""
    A, B, _ = linear_model(jnp.float64)
    Q = jnp.eye(7)
    Rs = jnp.diag(jnp.array([0.2, 0.0, 0.32, 0.1]))
    K, P, ok = jax.jit(lambda R: lqr_gain(A, B, Q, R, return_status=True))(Rs)
    assert not bool(ok) and np.all(np.asarray(K) == 0) and np.all(np.isfinite(np.asarray(P)))
    A32, B32, _ = linear_model(jnp.float32)
    R32 = jnp.diag(jnp.array([0.2, 0.2, 0.32, 0.1], jnp.float32))
    Q32 = jnp.diag(jnp.array([0.01] * 6 + [1e-12], jnp.float32))
    K, P, ok = lqr_gain(A32, B32, Q32, R32, return_status=True)
    Ps = sl.solve_continuous_are(np.asarray(A32, float), np.asarray(B32, float), np.asarray(Q32, float),
                                 np.asarray(R32, float))
    Ks = np.linalg.solve(np.asarray(R32, float), np.asarray(B32, float).T @ Ps)
    assert np.abs(np.asarray(P, float)).max() <= 2 * np.abs(Ps).max()  # (was P[5,5] = -90)
    assert np.abs(np.asarray(K, float)).max() <= 2 * np.abs(Ks).max()  # no gain blown up
    assert not bool(ok)  # the altitude block is still off: reported
    K64, _, ok64 = lqr_gain(A, B, Q32.astype(jnp.float64), R32.astype(jnp.float64), return_status=True)
    assert bool(ok64)
    np.testing.assert_allclose(np.asarray(K64), Ks, rtol=1e-6, atol=1e-9)  # float64: the right gain
