"""3-2-1 Euler angles (paper 000 eq. 1, 3) against SciPy and hand formulas."""

import jax
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from jaxslam.geometry import euler as eu

dcm_j = jax.jit(eu.dcm_from_euler)
inv_j = jax.jit(eu.euler_from_dcm)
D_j = jax.jit(eu.euler_rate_matrix)
rates_j = jax.jit(eu.euler_rates)


def random_euler(rng, n):
    return np.stack(
        [rng.uniform(-np.pi, np.pi, n), rng.uniform(-np.pi / 2 + 1e-3, np.pi / 2 - 1e-3, n), rng.uniform(-np.pi, np.pi, n)],
        axis=-1,
    )


def scipy_dcm(e):
    # intrinsic Z-Y'-X'' with angles (ψ, θ, φ) is C3(ψ) C2(θ) C1(φ)
    return Rotation.from_euler("ZYX", np.asarray(e)[..., ::-1]).as_matrix()


elem_j = jax.jit(lambda a: (eu.C1(a), eu.C2(a), eu.C3(a)))


def test_elementary_matrices_as_printed():
    angles = np.array([-2.0, 0.3, 1.4])
    m1, m2, m3 = (np.asarray(m) for m in elem_j(angles))  # batched over the angles
    for k, a in enumerate(angles):
        c, s = np.cos(a), np.sin(a)
        np.testing.assert_allclose(m1[k], [[1, 0, 0], [0, c, -s], [0, s, c]], atol=1e-15)
        np.testing.assert_allclose(m2[k], [[c, 0, s], [0, 1, 0], [-s, 0, c]], atol=1e-15)
        np.testing.assert_allclose(m3[k], [[c, -s, 0], [s, c, 0], [0, 0, 1]], atol=1e-15)
        np.testing.assert_allclose(m1[k], Rotation.from_euler("x", a).as_matrix(), atol=1e-15)
        np.testing.assert_allclose(m2[k], Rotation.from_euler("y", a).as_matrix(), atol=1e-15)
        np.testing.assert_allclose(m3[k], Rotation.from_euler("z", a).as_matrix(), atol=1e-15)
    assert elem_j(np.zeros((2, 5)))[0].shape == (2, 5, 3, 3)


def test_dcm_matches_scipy_batched():
    rng = np.random.default_rng(0)
    e = random_euler(rng, 200).reshape(10, 20, 3)
    C = dcm_j(e)
    assert C.shape == (10, 20, 3, 3)
    np.testing.assert_allclose(C, scipy_dcm(e.reshape(-1, 3)).reshape(10, 20, 3, 3), atol=1e-15)
    # product of the elementary matrices of eq. 1
    m1, m2, m3 = (np.asarray(m) for m in elem_j(e[0, 0]))
    np.testing.assert_allclose(C[0, 0], m3[2] @ m2[1] @ m1[0], atol=1e-15)
    # body-to-NED: the body x axis of a pure yaw of 90° points East
    np.testing.assert_allclose(np.asarray(dcm_j(np.array([0, 0, np.pi / 2]))) @ [1, 0, 0], [0, 1, 0], atol=1e-15)


def test_dcm_derivatives_match_central_differences_of_scipy():
    """Forward and reverse derivatives of C_NB (the filters' Jacobians and the tuning gradients
    both go through them) against central differences of SciPy's matrix."""
    rng = np.random.default_rng(3)
    for e in random_euler(rng, 5):
        h = 1e-6
        fd = np.stack([(scipy_dcm((e + h * d)[None])[0] - scipy_dcm((e - h * d)[None])[0]) / (2 * h)
                       for d in np.eye(3)], axis=-1)
        np.testing.assert_allclose(np.asarray(jax.jacfwd(eu.dcm_from_euler)(e)), fd, atol=1e-9)
        np.testing.assert_allclose(np.asarray(jax.jacrev(eu.dcm_from_euler)(e)), fd, atol=1e-9)


def test_euler_from_dcm_interior():
    rng = np.random.default_rng(1)
    e = random_euler(rng, 500)
    C = scipy_dcm(e)
    out = np.asarray(inv_j(C))
    np.testing.assert_allclose(out, e, atol=1e-11)
    np.testing.assert_allclose(out, Rotation.from_matrix(C).as_euler("ZYX")[:, ::-1], atol=1e-11)


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_dcm_round_trip_near_gimbal_lock(sign):
    rng = np.random.default_rng(2)
    n = 100
    e = np.stack([rng.uniform(-np.pi, np.pi, n), np.full(n, sign * (np.pi / 2 - 1e-6)), rng.uniform(-np.pi, np.pi, n)], -1)
    C = scipy_dcm(e)
    out = np.asarray(inv_j(C))
    np.testing.assert_allclose(scipy_dcm(out), C, atol=1e-12)
    np.testing.assert_allclose(out[:, 1], e[:, 1], atol=1e-9)
    # θ = ±(π/2 − 1e-8), ±(π/2 − 1e-12) and exactly ±π/2 also round-trip on the DCM level
    for d in (1e-8, 1e-12, 0.0):
        e2 = e.copy()
        e2[:, 1] = sign * (np.pi / 2 - d)
        C2 = scipy_dcm(e2)
        np.testing.assert_allclose(scipy_dcm(np.asarray(inv_j(C2))), C2, atol=1e-12)


def test_exact_gimbal_lock_convention():
    # θ = +90°: C depends on ψ − φ only; jaxslam returns φ = 0, ψ = ψ − φ.
    Rp = Rotation.from_euler("ZYX", [0.7, np.pi / 2, 0.2]).as_matrix()
    np.testing.assert_allclose(inv_j(Rp), [0.0, np.pi / 2, 0.5], atol=1e-12)
    # θ = −90°: C depends on ψ + φ only.
    Rm = Rotation.from_euler("ZYX", [0.7, -np.pi / 2, 0.2]).as_matrix()
    np.testing.assert_allclose(inv_j(Rm), [0.0, -np.pi / 2, 0.9], atol=1e-12)
    # gradients stay finite at the lock
    Jac = jax.jit(jax.vmap(jax.jacrev(eu.euler_from_dcm)))(np.stack([Rp, Rm]))
    assert np.all(np.isfinite(Jac))


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_dtype_preserved(dtype):
    rng = np.random.default_rng(3)
    e = random_euler(rng, 50).astype(dtype)
    e[:10, 1] = np.pi / 2 - 1e-6
    e[10:20, 1] = -np.pi / 2
    C = dcm_j(e)
    assert C.dtype == dtype
    out = inv_j(C)
    assert out.dtype == dtype
    tol = 2e-6 if dtype == np.float32 else 1e-13
    np.testing.assert_allclose(np.asarray(dcm_j(out), float), np.asarray(C, float), atol=tol)
    w = rng.normal(size=(50, 3)).astype(dtype)
    assert rates_j(e, w).dtype == dtype


def test_euler_rate_matrix_complex_step_oracle():
    """Λ̇ = D ω with ω from the DCM derivative [ω]× = Cᵀ Ċ (complex step, exact)."""
    rng = np.random.default_rng(4)

    def c_np(e):  # complex-capable C3 C2 C1
        f, t, p = e
        c1 = np.array([[1, 0, 0], [0, np.cos(f), -np.sin(f)], [0, np.sin(f), np.cos(f)]])
        c2 = np.array([[np.cos(t), 0, np.sin(t)], [0, 1, 0], [-np.sin(t), 0, np.cos(t)]])
        c3 = np.array([[np.cos(p), -np.sin(p), 0], [np.sin(p), np.cos(p), 0], [0, 0, 1]])
        return c3 @ c2 @ c1

    es = random_euler(rng, 20)
    edots = rng.normal(size=(20, 3))
    omegas = []
    for e, edot in zip(es, edots):
        h = 1e-30
        Cdot = np.imag(c_np(e + 1j * h * edot)) / h
        W = c_np(e).T @ Cdot
        omega = np.array([W[2, 1], W[0, 2], W[1, 0]])
        np.testing.assert_allclose(W + W.T, 0, atol=1e-12)
        omegas.append(omega)
    np.testing.assert_allclose(rates_j(es, np.stack(omegas)), edots, atol=1e-11)
    Ds = np.asarray(D_j(es))
    for e, Dj in zip(es, Ds):
        # D as printed in eq. 3 (1/cos θ factored out)
        f, t = e[0], e[1]
        D3 = np.array([[np.cos(t), np.sin(f) * np.sin(t), np.cos(f) * np.sin(t)],
                       [0, np.cos(f) * np.cos(t), -np.sin(f) * np.cos(t)],
                       [0, np.sin(f), np.cos(f)]]) / np.cos(t)
        np.testing.assert_allclose(Dj, D3, atol=1e-13)


def test_vmap_matches_batch():
    rng = np.random.default_rng(5)
    e = random_euler(rng, 8)
    run = jax.jit(lambda e: (jax.vmap(eu.dcm_from_euler)(e), jax.vmap(eu.euler_rate_matrix)(e),
                             jax.vmap(eu.euler_from_dcm)(jax.vmap(eu.dcm_from_euler)(e))))
    C, D, back = run(e)
    np.testing.assert_allclose(C, dcm_j(e), atol=1e-15)
    np.testing.assert_allclose(D, D_j(e), atol=1e-15)
    np.testing.assert_allclose(back, inv_j(dcm_j(e)), atol=1e-15)


def test_rotate_and_unrotate_jacobians_match_central_differences_and_autodiff():
    import jax.numpy as jnp
    rng = np.random.default_rng(11)
    h = 1e-6
    for e, v in zip(random_euler(rng, 5), rng.normal(size=(5, 3)) * 4):
        for fn, jac in ((lambda a: np.asarray(eu.dcm_from_euler(a)) @ v, eu.rotate_jacobian),
                        (lambda a: np.asarray(eu.dcm_from_euler(a)).T @ v, eu.unrotate_jacobian)):
            J = np.asarray(jac(jnp.asarray(e), jnp.asarray(v)))
            fd = np.stack([(fn(e + h * d) - fn(e - h * d)) / (2 * h) for d in np.eye(3)], axis=1)
            np.testing.assert_allclose(J, fd, rtol=1e-7, atol=1e-8)
        np.testing.assert_allclose(np.asarray(eu.rotate_jacobian(jnp.asarray(e), jnp.asarray(v))),
                                   np.asarray(jax.jacfwd(lambda a: eu.dcm_from_euler(a) @ jnp.asarray(v))(jnp.asarray(e))),
                                   rtol=1e-12, atol=1e-13)
        Jf = eu.unrotate_jacobian(jnp.asarray(e, jnp.float32), jnp.asarray(v, jnp.float32))
        assert Jf.dtype == jnp.float32
        np.testing.assert_allclose(np.asarray(Jf), np.asarray(eu.unrotate_jacobian(jnp.asarray(e), jnp.asarray(v))),
                                   rtol=1e-4, atol=1e-4)


def test_euler_from_dcm_stays_in_its_half_open_range():
    """arctan2(−0, −1) is −π: diag(−1, −1, 1) (ψ = π) and diag(1, −1, −1) (φ = π) read −π, outside
    the documented (−π, π] (review of 2026-12-07)."""
    from jaxslam.geometry.euler import euler_from_dcm

    for C, want in ((np.diag([-1.0, -1.0, 1.0]), [0.0, 0.0, np.pi]),
                    (np.array([[1.0, 0, 0], [0, -1.0, 0], [-0.0, -0.0, -1.0]]), [np.pi, 0.0, 0.0])):
        e = np.asarray(euler_from_dcm(jax.numpy.asarray(C)))
        np.testing.assert_allclose(e, want, atol=1e-15)
        assert np.all(e > -np.pi) and np.all(e <= np.pi)
