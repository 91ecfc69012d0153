"""Parametrisations: PD for any θ, exact round trips, independent NumPy construction, errors."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam.errors import InputError
from jaxslam.tuning import params as P


def _random_spd(rng, n):
    A = rng.normal(size=(n, n))
    return A @ A.T + 0.1 * np.eye(n)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
@pytest.mark.parametrize("n", [1, 4])
def test_log_chol_round_trip_and_numpy_oracle(dtype, n):
    rng = np.random.default_rng(n)
    M = _random_spd(rng, n)
    th = P.log_chol_from_cov(M, dtype=dtype)
    assert th.dtype == dtype and th.shape == (n * (n + 1) // 2,)
    back = P.cov_from_log_chol(th, n)
    assert back.dtype == dtype
    tol = 1e-5 if dtype == jnp.float32 else 1e-12
    np.testing.assert_allclose(np.asarray(back), M, rtol=tol, atol=tol * np.abs(M).max())
    # Independent construction of M from θ: L_ii = exp θ_i, L_ij = exp θ_i · θ_off (row-major tril).
    t = np.asarray(th, np.float64)
    L = np.diag(np.exp(t[:n]))
    r, c = np.tril_indices(n, -1)
    for k, (i, j) in enumerate(zip(r, c)):
        L[i, j] = np.exp(t[i]) * t[n + k]
    np.testing.assert_allclose(L, np.linalg.cholesky(M), rtol=10 * tol, atol=10 * tol)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_log_diag_round_trip(dtype):
    d = np.array([1e-8, 3e-3, 2.0, 50.0])
    th = P.log_diag_from_cov(np.diag(d), dtype=dtype)
    np.testing.assert_allclose(np.asarray(th), np.log(d), rtol=1e-6)
    back = P.cov_from_log_diag(th)
    assert back.dtype == dtype
    np.testing.assert_allclose(np.diag(np.asarray(back)), d, rtol=1e-6 if dtype == jnp.float32 else 1e-14)
    assert np.count_nonzero(np.asarray(back) - np.diag(np.diag(np.asarray(back)))) == 0
    # A vector of variances is accepted as the diagonal.
    np.testing.assert_allclose(np.asarray(P.log_diag_from_cov(d, dtype=dtype)), np.asarray(th))


def test_any_theta_gives_positive_definite():
    rng = np.random.default_rng(0)
    for n in (2, 5):
        for _ in range(20):
            th = jnp.asarray(rng.normal(scale=3.0, size=n * (n + 1) // 2))
            M = np.asarray(P.cov_from_log_chol(th, n))
            np.testing.assert_allclose(M, M.T, atol=1e-12 * np.abs(M).max())
            assert np.linalg.eigvalsh(M).min() > 0
            assert np.all(np.diag(np.asarray(P.cov_from_log_diag(th[:n]))) > 0)


def test_theta_round_trip_from_theta():
    rng = np.random.default_rng(1)
    th = jnp.asarray(rng.normal(size=10))
    M = P.cov_from_log_chol(th, 4)
    np.testing.assert_allclose(np.asarray(P.log_chol_from_cov(np.asarray(M))), np.asarray(th), atol=1e-10)


def test_pack_unpack_specs_and_jacobian():
    specs = {"Q": P.CovSpec("diag", 3), "R": P.CovSpec("chol", 2)}
    mats = {"Q": np.diag([1.0, 2.0, 3.0]), "R": np.array([[2.0, 0.5], [0.5, 1.0]])}
    th = P.pack(specs, mats)
    assert P.n_params(specs["Q"]) == 3 and P.n_params(specs["R"]) == 3
    out = P.unpack(specs, th)
    for k in mats:
        np.testing.assert_allclose(np.asarray(out[k]), mats[k], atol=1e-12)
    # d diag(exp θ)/dθ = diag(exp θ): a closed form for the Jacobian.
    J = jax.jacfwd(lambda t: jnp.diag(P.cov_from_theta(specs["Q"], t)))(th["Q"])
    np.testing.assert_allclose(np.asarray(J), np.diag([1.0, 2.0, 3.0]), atol=1e-12)


def test_errors_name_the_argument():
    with pytest.raises(InputError, match="Qc"):
        P.log_diag_from_cov(np.diag([0.0, 1.0]), name="Qc")
    with pytest.raises(InputError, match="R"):
        P.log_chol_from_cov(np.array([[1.0, 2.0], [2.0, 1.0]]), name="R")  # indefinite
    with pytest.raises(InputError, match="kind"):
        P.n_params(P.CovSpec("full", 2))
    with pytest.raises(InputError, match="M"):
        P.theta_from_cov(P.CovSpec("diag", 3), np.eye(2))
    with pytest.raises(InputError, match="NaN"):
        P.log_diag_from_cov(np.array([1.0, np.nan]))
    with pytest.raises(InputError, match="mats"):
        P.pack({"Q": P.CovSpec("diag", 2)}, {})


def test_floor_lifts_zero_entries():
    th = P.log_diag_from_cov(np.diag([0.0, 2.0]), floor=1e-9)
    np.testing.assert_allclose(np.exp(np.asarray(th)), [1e-9, 2.0])
    th = P.log_chol_from_cov(np.zeros((2, 2)), floor=1e-6)
    np.testing.assert_allclose(np.asarray(P.cov_from_log_chol(th, 2)), 1e-6 * np.eye(2), rtol=1e-12)
    with pytest.raises(InputError, match="floor"):
        P.log_diag_from_cov(np.eye(2), floor=-1.0)


def test_theta_of_the_wrong_size_and_missing_names_are_named():
    # a (4,) θ for a 3×3 log-Cholesky spec (6 parameters) used to broadcast one off-diagonal
    # value onto all three entries; a (4,) θ for a 3×3 diagonal gave a 4×4 matrix
    with pytest.raises(InputError, match=r"^theta: CovSpec\('chol', 3\) needs shape \(6,\), got \(4,\)"):
        P.cov_from_theta(P.CovSpec("chol", 3), jnp.zeros(4))
    with pytest.raises(InputError, match=r"^theta: CovSpec\('diag', 3\) needs shape \(3,\), got \(4,\)"):
        P.cov_from_theta(P.CovSpec("diag", 3), jnp.zeros(4))
    with pytest.raises(InputError, match=r"^kind: expected one of"):
        P.cov_from_theta(P.CovSpec("cholesky", 3), jnp.zeros(6))
    with pytest.raises(InputError, match=r"^thetas: no parameters for \['R'\]"):
        P.unpack({"Q": P.CovSpec("diag", 2), "R": P.CovSpec("diag", 1)}, {"Q": jnp.zeros(2)})
    np.testing.assert_allclose(np.asarray(P.cov_from_theta(P.CovSpec("chol", 2), jnp.zeros(3))), np.eye(2))
