"""Review of :mod:`jaxslam.stats`: chi-square quantiles far in the lower tail, and bool inputs.

Oracles: SciPy (``scipy.stats.chi2``, a test dependency) for the quantiles; messages by hand.
"""

import jax
import numpy as np
import pytest
from scipy import stats as sps

from jaxslam import stats
from jaxslam.errors import InputError


@pytest.mark.parametrize("jit", [False, True], ids=["eager", "jit"])
def test_chi2_ppf_far_lower_tail_matches_scipy(jit):
    # the lower tail underflowed below the root and Newton cycled at its floor:
    # p = 1e-300, dof = 1000 gave 93.17 for 103.27 (float64), p = 1e-37, dof = 100 7.09 for 7.64 (float32)
    f = jax.jit(stats.chi2_ppf) if jit else stats.chi2_ppf
    p = np.array([1e-300, 1e-290, 1.4691569065845399e-300, 1e-30, 0.025])
    k = np.array([1000.0, 1000.0, 891.3948930054613, 1000.0, 1000.0])
    got = np.asarray(f(p, k))
    assert got.dtype == np.float64
    np.testing.assert_allclose(got, sps.chi2.ppf(p, k), rtol=1e-9)
    p32 = np.array([1e-37, 1e-37, 1e-30, 0.5], np.float32)
    k32 = np.array([100.0, 300.0, 100.0, 3.0], np.float32)
    got32 = np.asarray(f(p32, k32))
    assert got32.dtype == np.float32
    np.testing.assert_allclose(got32, sps.chi2.ppf(p32.astype(np.float64), k32.astype(np.float64)), rtol=1e-3)


def test_chi2_quantiles_refuse_bools():
    # True was read as p = 1 (a quantile of inf) or dof = 1
    for call, needle in ((lambda: stats.chi2_ppf_np(True, 3), "^p: expected numbers, got dtype bool"),
                         (lambda: stats.chi2_ppf_np(0.5, True), "^dof: expected numbers, got dtype bool"),
                         (lambda: stats.chi2_ppf(np.array([True, False]), 3), "^p: expected numbers, got dtype bool"),
                         (lambda: jax.jit(stats.chi2_ppf)(0.5, np.array(True)), "^dof: expected numbers"),
                         (lambda: stats.student_t_d2_ppf_np(True, 3.0), "^p: expected numbers"),
                         (lambda: stats.student_t_d2_ppf_np(0.5, True), "^nu: expected numbers"),
                         (lambda: stats.mean_chi2_bounds(True, 3), "^dof_total: expected numbers"),
                         (lambda: stats.mean_chi2_bounds(3, True), "^count: expected numbers")):
        with pytest.raises(InputError, match=needle):
            call()
    # numbers are unchanged
    assert stats.chi2_ppf_np(0.975, 1) == pytest.approx(sps.chi2.ppf(0.975, 1), rel=1e-10)
    assert float(stats.chi2_ppf(0.99, 2)) == pytest.approx(sps.chi2.ppf(0.99, 2), rel=1e-9)


@pytest.mark.parametrize("jit", [False, True], ids=["eager", "jit"])
def test_half_precision_inputs_are_computed_in_float32(jit):
    # float16 raised a bare NotImplementedError (Cholesky) / TypeError (gammainc)
    import jax.numpy as jnp
    nees = jax.jit(stats.nees) if jit else stats.nees
    chi2_ppf = jax.jit(stats.chi2_ppf) if jit else stats.chi2_ppf
    P = np.array([[2.0, 0.5], [0.5, 1.0]])
    e = np.array([1.0, -1.0])
    ref = 4.0 / 1.75  # by hand: P⁻¹ = [[1, -0.5], [-0.5, 2]] / 1.75, eᵀ P⁻¹ e = (1 + 1 + 2) / 1.75
    for dt in (np.float16, jnp.bfloat16):
        got = nees(jnp.asarray(e, dt), jnp.asarray(P, dt))
        assert got.dtype == jnp.float32
        assert float(got) == pytest.approx(ref, rel=1e-2)
        q = chi2_ppf(jnp.asarray([0.025, 0.99], dt), 3)
        assert q.dtype == jnp.float32
        np.testing.assert_allclose(np.asarray(q), sps.chi2.ppf(np.asarray(jnp.asarray([0.025, 0.99], dt), np.float64), 3),
                                   rtol=1e-3)


@pytest.mark.parametrize("jit", [False, True], ids=["eager", "jit"])
def test_nees_of_an_infinite_error_is_inf(jit):
    # eᵀ P⁻¹ e ≥ λ_min(P⁻¹) |e|² = inf for a PD P; the triangular solve's 0 · inf gave NaN
    nees = jax.jit(stats.nees) if jit else stats.nees
    nis = jax.jit(stats.nis) if jit else stats.nis
    inf, nan = np.inf, np.nan
    P = np.array([[1.0, 0.9], [0.9, 1.0]])
    e = np.array([[inf, 0.0], [inf, inf], [-inf, -inf], [1.0, 2.0], [inf, nan], [nan, 0.0]])
    want = np.array([inf, inf, inf, (1.0 - 3.6 + 4.0) / 0.19, nan, nan])  # by hand: P⁻¹ = [[1, -.9], [-.9, 1]] / .19
    for dt in (np.float64, np.float32):
        got = np.asarray(nees(e.astype(dt), P.astype(dt)))
        np.testing.assert_allclose(got, want, rtol=1e-5)
        np.testing.assert_allclose(np.asarray(nis(e.astype(dt), P.astype(dt))), want, rtol=1e-5)
        got = np.asarray(nees(np.array([[inf, 0.0], [0.0, -inf], [3.0, 4.0]], dt), np.diag([2.0, 4.0]).astype(dt)))
        np.testing.assert_allclose(got, [inf, inf, 4.5 + 4.0], rtol=1e-6)  # 9/2 + 16/4
    # a covariance that is not PD stays NaN, the infinite error notwithstanding
    assert np.isnan(float(nees(np.array([inf, 0.0]), -np.eye(2))))
