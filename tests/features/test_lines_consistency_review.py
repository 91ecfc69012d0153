"""Review of jaxslam.features.lines and jaxslam.filters.consistency: eq. 4.1's count for large
counts, match_predicted's gate check, the DIVERGED ratio, and the monitor's input checks.

Every expectation is computed independently (exact decimal / integer arithmetic, hand values).
"""

import math
from decimal import Decimal, getcontext

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam import errors
from jaxslam.errors import InputError
from jaxslam.features import lines as F
from jaxslam.filters import consistency as C
from jaxslam.filters import ekf_slam as es


def _exact_n_hyp(p, eps, m):
    """⌈log(1 − p) / log(1 − (1 − ε)^m)⌉ in 50-digit decimal arithmetic (of the same doubles)."""
    getcontext().prec = 50
    n = (1 - Decimal(p)).ln() / (1 - (1 - Decimal(eps)) ** m).ln()
    return math.ceil(n)


@pytest.mark.parametrize("p, eps, m", [(0.999, 0.7, 20), (0.99, 0.5, 30), (0.99, 0.6, 25),
                                       (0.99, 0.5, 20), (0.99, 0.9, 2), (0.99, 0.5, 2)])
def test_n_hypotheses_meets_the_bound_for_large_counts(p, eps, m):
    # Old code: 1e-9·n was taken off before the ceiling, 198 hypotheses too few at 2·10¹¹.
    assert F.n_hypotheses(p, eps, m) == _exact_n_hyp(p, eps, m)
    assert F.n_hypotheses(0.99, 0.9, 2) == 459 and F.n_hypotheses(0.99, 0.5, 2) == 17  # defaults kept


_PTS = jnp.stack([jnp.linspace(0.0, 1.0, 30), jnp.ones(30)], axis=1)  # the line y = 1: ρ = 1, θ = π/2
_CFG = F.RansacConfig(n_hyp=16, max_lines=2)


def _match(gate):
    return F.match_predicted(_PTS, jnp.ones(30, bool), jnp.array([1.0]), jnp.array([np.pi / 2]),
                             jnp.array([True]), _CFG, gate)


@pytest.mark.parametrize("gate", ["0.2", True, np.bool_(True), 0.2 + 0j, np.complex128(0.2)])
def test_match_predicted_gate_must_be_a_real_number(gate):
    # Old code: "0.2" and True (1 m) were taken as gates, a complex one raised a bare TypeError.
    with pytest.raises(InputError, match=r"^gate: expected a distance > 0 \[m\]"):
        _match(gate)


def test_match_predicted_good_gates_still_match():
    for gate in (0.2, np.float32(0.2), jnp.asarray(0.2), 1):
        lines, rem = _match(gate)
        assert bool(lines.valid[0]) and int(lines.n_inliers[0]) == 30 and not np.asarray(rem).any()
        assert float(lines.rho[0]) == pytest.approx(1.0, abs=1e-12)
        assert float(lines.theta[0]) == pytest.approx(np.pi / 2, abs=1e-12)


def test_status_bits_more_than_fraction_is_exact():
    # 29 of 100 is not more than 29 % (old code: 0.29·100 = 28.999999999999996 < 29: DIVERGED).
    assert int(C.status_bits(29, 100, 0.29)) == 0
    assert int(C.status_bits(30, 100, 0.29)) == errors.DIVERGED
    assert int(jax.jit(C.status_bits)(29, 100, 0.29)) == 0  # traced, the same rule
    for f32 in (np.float32(0.29), jnp.float32(0.29)):  # a float32 fraction: compared at its precision
        assert int(C.status_bits(29, 100, f32)) == 0 and int(C.status_bits(30, 100, f32)) == errors.DIVERGED
        assert int(jax.jit(C.status_bits)(29, 100, f32)) == 0
    assert int(C.status_bits(1, 1, 1)) == 0 and int(C.status_bits(1, 2, 0)) == errors.DIVERGED  # int fractions
    # Whole grids against exact integer arithmetic: n_out/n > a/b ⇔ b·n_out > a·n.
    n = np.arange(1, 401)
    n_rows = np.repeat(n, n + 1)
    n_out = np.concatenate([np.arange(k + 1) for k in n])
    for frac, (a, b) in ((0.29, (29, 100)), (0.1, (1, 10)), (0.7, (7, 10)), (0.57, (57, 100))):
        got = np.asarray(C.status_bits(jnp.asarray(n_out), jnp.asarray(n_rows), frac))
        want = np.where(b * n_out > a * n_rows, errors.DIVERGED, 0)
        np.testing.assert_array_equal(got, want, err_msg=f"fraction {frac}")
    got = np.asarray(C.status_bits(jnp.asarray(n_out), jnp.asarray(n_rows)))  # the default 0.1: as before
    np.testing.assert_array_equal(got, np.where(10 * n_out > n_rows, errors.DIVERGED, 0))
    assert int(C.status_bits(0, 0)) == 0 and int(C.status_bits(1, 0)) == errors.DIVERGED  # n_rows 0 read as 1


def _slam2():
    m = es.SlamModel(2, 2, 2, lambda s, u, p=None: s + u, lambda s, l, p=None: l - s,
                     lambda s, z, p=None: s + z)
    st = es.preload(es.init(jnp.zeros(2), 0.1 * jnp.eye(2), 3, 2), m, jnp.array([[1.0, 0.0], [0.0, 1.0]]),
                    jnp.stack([0.1 * jnp.eye(2)] * 2), ids=jnp.array([0, 1]))
    return m, st


_OK = C.MonitorParams(alpha=0.1, threshold=1.5, max_factor=4.0, outlier_gate=9.21)


def test_monitor_rejects_an_infinite_max_factor():
    # Old code: accepted; an inf d² then made f = inf: P NaN under jit, a "factor:" error eagerly.
    m, st = _slam2()
    mon = C.init(jnp.float64)
    d2, v = jnp.array([jnp.inf, 1.0]), jnp.array([True, True])
    with pytest.raises(InputError, match=r"^params\.max_factor: must be finite"):
        C.observe(mon, st, m, d2, v, _OK._replace(max_factor=float("inf")))
    # A finite cap with the same inf row: P_rr × 4, P_rl × 2, P_ll kept (hand values), mean reset.
    mon2, st2 = C.observe(mon, st, m, d2, v, _OK)
    D = np.diag([2.0, 2.0] + [1.0] * (st.P.shape[0] - 2))
    np.testing.assert_allclose(np.asarray(st2.P), D @ np.asarray(st.P) @ D, rtol=1e-15)
    assert float(mon2.mean) == 1.0 and int(mon2.inflations) == 1


def test_monitor_rejects_negative_d2_on_a_valid_row():
    # Old code: a d² of −inf held the running mean at −inf; the monitor never tripped again.
    m, st = _slam2()
    mon = C.init(jnp.float64)
    v = jnp.array([True, True])
    for bad in (jnp.array([-jnp.inf, 1.0]), jnp.array([-50.0, 1.0])):
        with pytest.raises(InputError, match=r"^d2: negative on a valid row"):
            C.observe(mon, st, m, bad, v, _OK)
    # On an invalid row it is ignored: r = 2 / (2·1) = 1, m = 0.9·1 + 0.1·1 = 1 (hand value).
    mon2, _ = C.observe(mon, st, m, jnp.array([-jnp.inf, 2.0]), jnp.array([False, True]), _OK)
    assert float(mon2.mean) == pytest.approx(1.0, abs=1e-15) and int(mon2.inflations) == 0
    # float32 monitor and rows: r = 200 / 4 = 50, m = 0.9 + 5 = 5.9 > 1.5: one inflation.
    mon3, st3 = C.observe(C.init(jnp.float32), st, m, jnp.array([100.0, 100.0], jnp.float32), v, _OK)
    assert mon3.mean.dtype == jnp.float32 and int(mon3.inflations) == 1


_TWO = jnp.array([[0.0, 1.0], [1.0, 1.0]])  # the line y = 1 (ρ = 1, θ = π/2), s = −x: s̄ = −½, Σu² = ½


@pytest.mark.parametrize("sigma", ["0.1", True, np.bool_(True), jnp.asarray(True)])
def test_fit_line_cov_sigma_must_be_a_real_number(sigma):
    # Old code: "0.1" was parsed as 0.1 m, True read as σ = 1 m.
    with pytest.raises(InputError, match=r"^sigma: expected a point noise σ > 0 \[m\] \(finite\)"):
        F.fit_line_cov(_TWO, jnp.ones(2), sigma)


def test_fit_line_cov_good_sigmas_give_the_closed_form():
    # var ρ = σ²(1/N + s̄²/Σu²) = 0.01, cov = σ² s̄/Σu² = −0.01, var θ = σ²/Σu² = 0.02 (σ = 0.1).
    want = np.array([[0.01, -0.01], [-0.01, 0.02]])
    for sigma in (0.1, np.float64(0.1), jnp.asarray(0.1)):
        np.testing.assert_allclose(np.asarray(F.fit_line_cov(_TWO, jnp.ones(2), sigma)), want, rtol=1e-12)
    np.testing.assert_allclose(np.asarray(jax.jit(F.fit_line_cov)(_TWO, jnp.ones(2), 0.1)), want, rtol=1e-12)
    c32 = F.fit_line_cov(_TWO.astype(jnp.float32), jnp.ones(2, jnp.float32), np.float32(0.1))
    assert c32.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(c32), want, rtol=1e-5)


def test_segment_endpoints_takes_one_line():
    pts, w = jnp.array([[0.0, 1.0], [2.0, 1.0], [1.0, 1.2]]), jnp.ones(3)
    # Old code: a (1,) ρ, θ gave (1, 2, 1) endpoints; a (2,) pair a bare ValueError.
    for rho, theta in ((jnp.array([1.0]), jnp.array([np.pi / 2])), (jnp.array([1.0, 1.0]), np.pi / 2)):
        with pytest.raises(InputError, match=r"^rho: expected a scalar \(one line\)"):
            F.segment_endpoints(pts, w, rho, theta)
        with pytest.raises(InputError, match=r"^rho: expected a scalar \(one line\)"):
            jax.jit(F.segment_endpoints)(pts, w, rho, theta)
    with pytest.raises(InputError, match=r"^theta: expected a scalar \(one line\), got shape \(1,\)"):
        F.segment_endpoints(pts, w, 1.0, jnp.array([np.pi / 2]))
    # On y = 1 the direction [−sin θ, cos θ] = [−1, 0]: ends ordered by −x, projections onto y = 1.
    np.testing.assert_allclose(np.asarray(F.segment_endpoints(pts, w, 1.0, np.pi / 2)),
                               [[2.0, 1.0], [0.0, 1.0]], atol=1e-15)


def test_status_bits_counts_must_not_be_negative():
    # Old code: n_rows = −3 was read as 1 row, so 5 "outliers" flagged DIVERGED; −1 outliers passed.
    for args, name in (((5, -3), "n_rows"), ((-1, 10), "n_outliers"), ((float("nan"), 10), "n_outliers"),
                       ((jnp.array([1, -2]), 10), "n_outliers")):
        with pytest.raises(InputError, match=rf"^{name}: expected a count >= 0"):
            C.status_bits(*args)
    assert int(C.status_bits(0, 0)) == 0 and int(jax.jit(C.status_bits)(5, 10)) == errors.DIVERGED  # 50 % > 10 %
