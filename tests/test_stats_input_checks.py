"""Bad input to :mod:`jaxslam.stats`: an InputError naming the argument (never a silent
broadcast, a truncated count or a ZeroDivisionError), and the Student-t d² quantile's ν → ∞
limit.

Oracles: SciPy (``scipy.stats.f`` / ``t`` / ``chi2``, a test dependency) and Fisher's expansion
of the t quantile written out here; shapes and messages by hand.
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats as sps

from jaxslam import stats
from jaxslam.errors import InputError

I3 = np.eye(3)


# ---------------------------------------------------------------------------
# NEES / NIS
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("jit", [False, True], ids=["eager", "jit"])
def test_nees_and_nis_name_shapes_that_do_not_fit(jit):
    nees = jax.jit(stats.nees) if jit else stats.nees
    nis = jax.jit(stats.nis) if jit else stats.nis
    cases = ((np.ones(3), np.array([1.0, 2.0, 3.0]), r"^cov: expected shape \(\.\.\., 3, 3\)"),  # was NaN
             (np.ones(3), np.eye(2), r"^cov: expected shape \(\.\.\., 3, 3\)"),
             (np.ones(3), np.ones((3, 2)), r"^cov: expected shape \(\.\.\., 3, 3\)"),
             (np.ones((4, 3)), np.ones((5, 3, 3)) * I3, r"^cov: batch shape \(5,\) does not broadcast against err's \(4,\)"))
    for e, c, needle in cases:
        with pytest.raises(InputError, match=needle):
            nees(e, c)
    with pytest.raises(InputError, match=r"^S: expected shape \(\.\.\., 2, 2\)"):
        nis(np.ones(2), np.eye(3))
    if not jit:  # a Python scalar is a concrete value: named before any tracing
        with pytest.raises(InputError, match=r"^err: expected shape \(\.\.\., n\), got \(\)"):
            nees(1.0, I3)
        with pytest.raises(InputError, match=r"^err: expected numbers"):
            nees("abc", I3)
        with pytest.raises(InputError, match=r"^innovation: expected numbers"):
            nis([1.0, "a"], np.eye(2))


def test_nees_values_broadcasting_and_dtypes_are_unchanged():
    P = np.array([[2.0, 0.5, 0.0], [0.5, 1.0, 0.2], [0.0, 0.2, 3.0]])
    e = np.array([[1.0, -1.0, 0.5], [0.2, 0.3, -2.0]])
    ref = np.einsum("ki,ki->k", e, np.linalg.solve(P, e.T).T)
    np.testing.assert_allclose(np.asarray(stats.nees(e, P)), ref, rtol=1e-12)  # one cov, two errors
    np.testing.assert_allclose(np.asarray(stats.nis(e.tolist(), P.tolist())), ref, rtol=1e-12)  # lists
    assert stats.nees(e.astype(np.float32), P.astype(np.float32)).dtype == jnp.float32
    got = stats.nees(np.array([1, 1, 0]), np.eye(3, dtype=int) * 2)  # integers: the default float
    assert jnp.issubdtype(got.dtype, jnp.floating) and float(got) == pytest.approx(1.0, rel=1e-15)
    assert np.isnan(float(stats.nees(np.ones(3), -I3)))  # not PD: NaN, as documented


# ---------------------------------------------------------------------------
# Student-t
# ---------------------------------------------------------------------------

def test_student_t_nll_checks_nu_and_dim_when_concrete():
    for nu in (0.0, -1.0, float("nan"), np.array([3.0, 0.0])):  # 0: ZeroDivisionError; -1: NaN
        with pytest.raises(InputError, match="^nu: the Student-t degrees of freedom must be > 0"):
            stats.student_t_nll(1.0, 0.0, nu, 1)
    for dim in (0, 1.5, True):
        with pytest.raises(InputError, match="^dim: expected an int >= 1"):
            stats.student_t_nll(1.0, 0.0, 3.0, dim)
    # traced ν: not checked (the value is unknown); a valid one gives the same as eager
    eager = stats.student_t_nll(1.0, 0.2, 3.0, 2)
    traced = jax.jit(lambda nu: stats.student_t_nll(1.0, 0.2, nu, 2))(3.0)
    np.testing.assert_allclose(float(traced), float(eager), rtol=1e-14)
    assert np.isnan(float(jax.jit(lambda nu: stats.student_t_nll(1.0, 0.0, nu, 1))(-1.0)))


def test_student_t_nll_at_infinite_nu_is_the_gaussian():
    d2, ld = np.array([0.0, 0.3, 4.0]), np.array([-1.0, 0.0, 2.0])
    got = np.asarray(stats.student_t_nll(jnp.asarray(d2), jnp.asarray(ld), math.inf, 2))
    np.testing.assert_allclose(got, 0.5 * (d2 + ld + 2 * math.log(2 * math.pi)), rtol=1e-15)
    g = jax.grad(lambda nu: stats.student_t_nll(1.0, 0.0, nu, 1))(jnp.inf)
    assert np.isfinite(float(g))  # the inf branch never reaches the formula
    # float32 rows keep their dtype with a Python ν
    assert stats.student_t_nll(jnp.ones(2, jnp.float32), jnp.zeros(2, jnp.float32), 5.0, 1).dtype == jnp.float32


@pytest.mark.parametrize("p", [1e-6, 0.1, 0.5, 0.9, 0.99, 0.999999])
def test_student_t_d2_quantile_at_infinite_nu_is_chi2_one(p):
    # ν = inf returned inf; the docstring's limit is the χ²(1) quantile (0.455 at p = 0.5)
    assert stats.student_t_d2_ppf_np(p, math.inf) == pytest.approx(sps.chi2.ppf(p, 1), rel=1e-12)


@pytest.mark.parametrize("nu", [0.5, 1.0, 3.0, 30.0, 1e3, 1e5])
def test_student_t_d2_quantile_matches_scipy(nu):
    for p in (1e-6, 0.1, 0.5, 0.9, 0.99, 1 - 1e-9):
        assert stats.student_t_d2_ppf_np(p, nu) == pytest.approx(sps.f.ppf(p, 1, nu), rel=1e-9)


def test_student_t_d2_quantile_approaches_chi2_as_nu_grows():
    # Fisher's expansion t_p = z + (z³ + z)/(4ν) + O(ν⁻²): d² / χ²(1) − 1 = (z² + 1)/(2ν) + O(ν⁻²),
    # z the normal quantile of (1 + p)/2.  The old bisection was 7e-5 off χ²(1) at ν = 1e12.
    for p in (0.1, 0.5, 0.99):
        chi = sps.chi2.ppf(p, 1)
        z2 = chi  # z² is the χ²(1) quantile
        prev = math.inf
        for nu in (1e4, 1e6, 1e9, 1e12):
            got = stats.student_t_d2_ppf_np(p, nu)
            rel = got / chi - 1.0
            assert 0 < rel < prev
            assert rel == pytest.approx((z2 + 1.0) / (2.0 * nu), rel=1e-3 if nu < 1e12 else 1e-2), (p, nu)
            prev = rel
        assert stats.student_t_d2_ppf_np(p, 1e17) == pytest.approx(chi, rel=1e-15)


def test_student_t_d2_quantile_names_its_arguments():
    with pytest.raises(InputError, match="^p: expected a number"):
        stats.student_t_d2_ppf_np("a", 3.0)
    with pytest.raises(InputError, match="^nu: expected a number"):
        stats.student_t_d2_ppf_np(0.5, None)
    with pytest.raises(InputError, match="nu > 0"):
        stats.student_t_d2_ppf_np(0.5, -math.inf)
    with pytest.raises(InputError, match="0 <= p < 1"):
        stats.student_t_d2_ppf_np(1.0, 3.0)


# ---------------------------------------------------------------------------
# Chi-square quantiles and bounds
# ---------------------------------------------------------------------------

def test_chi2_quantiles_name_arguments_that_are_not_numbers():
    with pytest.raises(InputError, match="^dof: expected a number"):
        stats.chi2_ppf_np(0.5, "x")
    with pytest.raises(InputError, match="^p: expected a number"):
        stats.chi2_ppf_np(float("nan"), 3)
    with pytest.raises(InputError, match="^p: expected numbers"):
        stats.chi2_ppf("0.5", 3)
    assert stats.chi2_ppf_np(np.float32(0.5), np.int64(3)) == pytest.approx(sps.chi2.ppf(0.5, 3), rel=1e-10)


def test_mean_chi2_bounds_name_their_arguments():
    for args, needle in (((3, math.inf), "^count: expected a positive finite scalar"),  # was (0, 0)
                         ((math.inf, 3), "^dof_total: expected a positive finite scalar"),  # was (inf, inf)
                         (("a", 3), "^dof_total: "), ((np.array([3, 4]), 3), "^dof_total: "),
                         ((3, 0), "^count: "), ((3, 3, "0.05"), r"^alpha: must be in \(0, 1\)"),
                         ((3, 3, float("nan")), r"^alpha: must be in \(0, 1\)"),
                         ((3, 3, 1.0), r"^alpha: must be in \(0, 1\)")):
        with pytest.raises(InputError, match=needle):
            stats.mean_chi2_bounds(*args)
    lo, hi = stats.mean_chi2_bounds(np.int64(30), 10.0)
    np.testing.assert_allclose((lo, hi), (sps.chi2.ppf(0.025, 30) / 10, sps.chi2.ppf(0.975, 30) / 10), rtol=1e-10)


def test_anees_bounds_take_whole_counts():
    for args, needle in (((2.5, 3), "^n_state: expected an int >= 1, got 2.5"),  # was truncated to 2
                         ((0, 3), "^n_state: "), ((None, 3), "^n_state: "), ((True, 3), "^n_state: "),
                         ((3, "x"), "^n_runs: expected an int"), ((3, float("nan")), "^n_runs: "),
                         ((3, 3.0), "^n_runs: ")):
        with pytest.raises(InputError, match=needle):
            stats.anees_bounds(*args)
    lo, hi = stats.anees_bounds(np.int64(3), 4)
    np.testing.assert_allclose((lo, hi), (sps.chi2.ppf(0.025, 12) / 4, sps.chi2.ppf(0.975, 12) / 4), rtol=1e-10)


def test_student_t_nll_refuses_a_negative_concrete_d2():
    # a squared distance < 0 gave a finite, meaningless NLL (d2 = -1, ν = 5, d = 2: 1.0569)
    for d2 in (-1.0, np.array([1.0, -0.5]), -math.inf):
        with pytest.raises(InputError, match="^d2: expected squared distances >= 0"):
            stats.student_t_nll(d2, 0.0, 5.0, 2)
    with pytest.raises(InputError, match="^d2: expected squared distances >= 0"):
        stats.student_t_nll(-1.0, 0.0, math.inf, 2)  # the Gaussian branch too
    with pytest.raises(InputError, match="^d2: expected numbers"):
        stats.student_t_nll("a", 0.0, 5.0, 2)  # was a bare TypeError
    # zero, +inf and NaN are let through: 0 is valid, +inf gives +inf, NaN gives NaN (not silent)
    assert np.isfinite(float(stats.student_t_nll(0.0, 0.0, 5.0, 2)))
    assert float(stats.student_t_nll(math.inf, 0.0, 5.0, 2)) == math.inf
    assert np.isnan(float(stats.student_t_nll(math.nan, 0.0, 5.0, 2)))
    # traced d2: not checked (nothing raises under jit) and unchanged
    got = jax.jit(lambda d: stats.student_t_nll(d, 0.2, 3.0, 2))(jnp.asarray([1.0, -0.5]))
    assert got.shape == (2,)
    np.testing.assert_allclose(float(got[0]), float(stats.student_t_nll(1.0, 0.2, 3.0, 2)), rtol=1e-6)
