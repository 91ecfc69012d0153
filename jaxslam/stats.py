"""Gaussian consistency statistics and chi-square quantiles: NEES / NIS and their bounds.

Pure JAX and NumPy (SciPy is a test-only oracle).  A models-level module: the filters, the
systems and the evaluation (:mod:`jaxslam.metrics`, which re-exports these names) all use it.

* NEES ``eᵀ P⁻¹ e`` and NIS ``νᵀ S⁻¹ ν`` go through a Cholesky factor and a triangular
  solve, never an inverse.  A non-PD covariance yields NaN (it is not hidden).
* Chi-square quantiles.  ``chi2_ppf`` (JAX, jit-able, follows the input dtype) solves
  ``P(k/2, x/2) = p`` by Newton's method on the *log* CDF in ``log x`` (lower tail for
  p ≤ 1/2, log survival for p > 1/2).  Both are concave in ``log x`` (the log-gamma density
  is log-concave), so after the first step the iterates approach the root monotonically from
  one side and never overshoot; steps are clipped to ±1 in ``log x`` and the start is a
  Wilson–Hilferty guess, floored (as are all iterates) by the lower bound of the root that
  follows from ``P(a, x) ≤ x^a / Γ(a+1)``.  In float32 the regularised incomplete gamma itself
  carries ~1e-2 relative error at dof ~ 10⁵, so ``chi2_ppf`` is then only good to ~1e-4.
  Host-side bounds (``anees_bounds``, ``mean_chi2_bounds``) therefore use ``chi2_ppf_np``:
  the same Newton scheme in float64 Python with its own incomplete gamma (power series for
  x < a + 1, Lentz continued fraction otherwise), independent of whether JAX x64 is enabled.
  Both match ``scipy.stats.chi2.ppf`` to 1e-9 relative for dof 1..10⁵ in float64.
* Average-NEES bounds.  For N runs of an n-state filter the sum of N independent NEES values
  is χ²(N n), so the two-sided (1 − α) bounds on the average are ``χ²_{α/2}(N n)/N`` and
  ``χ²_{1−α/2}(N n)/N``.  The same helper gives bounds for a mean NIS over ``count`` updates
  with ``dof_total`` degrees of freedom in all.  Averages over *time* as well are not
  independent samples; use these bounds per time step (or per window, with ``count`` the
  number of samples) and read whole-run averages as indicative.
"""

from __future__ import annotations

import math
import statistics

import jax
import jax.numpy as jnp
import numpy as np

from .compilation import call_compiled
from .errors import InputError
from .linalg import check_int, check_numbers, check_real, check_scalar, float_array, is_concrete

__all__ = ["nees", "nis", "student_t_nll", "student_t_d2_ppf_np", "chi2_ppf", "chi2_ppf_np", "mean_chi2_bounds",
           "anees_bounds"]


# ---------------------------------------------------------------------------
# NEES / NIS
# ---------------------------------------------------------------------------

def _quadratic_form(err, cov, e_name: str, c_name: str):
    """``eᵀ C⁻¹ e`` of (..., n) and (..., n, n), shapes and dtypes checked (static: free under
    ``jit``; a complex array is refused, its imaginary part is not dropped)."""
    check_real(err, e_name)
    check_real(cov, c_name)
    err = float_array(err, e_name)
    cov = float_array(cov, c_name)
    if err.ndim < 1:
        raise InputError(f"{e_name}: expected shape (..., n), got {tuple(err.shape)}")
    n = err.shape[-1]
    if cov.ndim < 2 or cov.shape[-2:] != (n, n):
        raise InputError(f"{c_name}: expected shape (..., {n}, {n}) ({e_name}'s size n = {n}), "
                         f"got {tuple(cov.shape)}")
    try:  # the batch shapes must broadcast (the program broadcasts them)
        jnp.broadcast_shapes(err.shape[:-1], cov.shape[:-2])
    except ValueError:
        raise InputError(f"{c_name}: batch shape {tuple(cov.shape[:-2])} does not broadcast against "
                         f"{e_name}'s {tuple(err.shape[:-1])}") from None
    dtype = jnp.result_type(err.dtype, cov.dtype)
    if jnp.finfo(dtype).bits < 32:  # float16 / bfloat16: no Cholesky for them (a bare NotImplementedError)
        dtype = jnp.dtype(jnp.float32)
    # called eagerly: one kept program per shape and dtype (op by op, a first NEES took 0.6 s)
    return call_compiled(("stats.quadratic_form",), _solve_form, (err.astype(dtype), cov.astype(dtype)),
                         after="auto")


def _solve_form(err, cov):
    """``eᵀ C⁻¹ e`` of checked arrays of one dtype (batch shapes broadcast here)."""
    n = err.shape[-1]
    batch = jnp.broadcast_shapes(err.shape[:-1], cov.shape[:-2])
    err = jnp.broadcast_to(err, batch + (n,))
    cov = jnp.broadcast_to(cov, batch + (n, n))
    L = jnp.linalg.cholesky(0.5 * (cov + jnp.swapaxes(cov, -1, -2)))
    y = jax.scipy.linalg.solve_triangular(L, err[..., None], lower=True)[..., 0]
    q = jnp.sum(y * y, axis=-1)
    # an infinite (not NaN) error with a PD covariance: eᵀ C⁻¹ e ≥ λ_min |e|² = inf (the solve's
    # 0 · inf gave NaN, as for a non-PD covariance)
    inf_err = (jnp.any(jnp.isinf(err), axis=-1) & ~jnp.any(jnp.isnan(err), axis=-1)
               & jnp.all(jnp.isfinite(L), axis=(-2, -1)))
    return jnp.where(inf_err, jnp.inf, q)


def nees(err, cov):
    """Normalised estimation error squared ``eᵀ P⁻¹ e`` via Cholesky.

    Args:
        err: (..., n) estimation errors (estimate − truth).
        cov: (..., n, n) estimated covariances (broadcast against ``err``).

    Returns:
        (...) NEES values; χ²(n)-distributed for a consistent filter.  NaN
        where ``cov`` is not positive definite (or ``err`` has a NaN); inf where ``err`` has an
        infinite entry and ``cov`` is PD (it was NaN).  Shapes are checked (also under ``jit``):
        :class:`InputError` naming ``err`` / ``cov`` (a (n,) ``cov`` used to be broadcast to
        a matrix of equal rows, giving NaN); so is a complex dtype (``1j`` gave a NEES of −1).
        A float16 / bfloat16 pair is computed, and returned, in float32 (it raised a bare
        NotImplementedError).  Called eagerly it is compiled once per shape and dtype
        (:func:`jaxslam.compilation.call_compiled`), as :func:`nis`.
    """
    return _quadratic_form(err, cov, "err", "cov")


def nis(innovation, S):
    """Normalised innovation squared ``νᵀ S⁻¹ ν`` via Cholesky.

    Args:
        innovation: (..., m) innovations.
        S: (..., m, m) innovation covariances.

    Returns:
        (...) NIS values, χ²(m) for a consistent filter (shapes checked as :func:`nees`'s,
        naming ``innovation`` / ``S``).
    """
    return _quadratic_form(innovation, S, "innovation", "S")


# ---------------------------------------------------------------------------
# Chi-square quantiles
# ---------------------------------------------------------------------------

_NEWTON_ITERS = 8  # 5 reach 1e-12 from the Wilson–Hilferty start


def student_t_nll(d2, logdet, nu, dim):
    """Negative log density of a d-variate Student-t with ν degrees of freedom and scale S at a
    point of squared Mahalanobis distance ``d2`` (νᵀ S⁻¹ ν) and ``logdet`` = log det S::

        ½ log det S + (ν + d)/2 · log(1 + d²/ν) + log Γ(ν/2) − log Γ((ν + d)/2) + (d/2) log(νπ)

    (elementwise over arrays of rows; ``dim`` = d, static).  ν → ∞ is the Gaussian's
    ½ (d² + log det S + d log 2π), and ν = inf gives it exactly.  The robust EKF updates
    (``robust=ν`` of :func:`jaxslam.filters.ekf_slam.update`) are the EM steps of this
    likelihood.

    From ν/2 = 30 on, ``log Γ((ν + d)/2) − log Γ(ν/2)`` comes from Stirling's series (as in
    :func:`student_t_d2_ppf_np`), not from the difference of two ``gammaln`` values of size
    ν/2 · log(ν/2), which cancelled (float32 ν = 10⁶, d² = 1, d = 2 gave 2.46 for 2.338; float64
    ν = 10¹⁷ gave 40.3): the NLL approaches the Gaussian smoothly, with finite gradients in ν
    and d².

    ``dim`` must be an int ≥ 1 and, when known now, ``nu`` > 0 (NaN refused) and ``d2`` ≥ 0
    (a NaN d2 gives a NaN NLL): :class:`InputError` naming it (ν = 0 raised ZeroDivisionError
    for Python numbers, ν < 0 gave NaN, d2 < 0 a finite wrong value).  Traced values are not
    checked; a complex ``d2``, ``logdet`` or ``nu`` is refused always (its dtype is known).
    """
    dim = check_int(dim, "dim")
    check_real(d2, "d2")
    check_real(logdet, "logdet")
    check_student_t_nu(nu)
    if is_concrete(d2):  # a squared distance: a negative one gave a finite, meaningless NLL
        a = check_numbers(d2, "d2")
        if np.any(a < 0):  # NaN is not < 0: it propagates to a NaN NLL, as before
            raise InputError(f"d2: expected squared distances >= 0, got minimum {float(np.nanmin(a)):.6g}")
    # a list (of rows) as an array (JAX's operators refused it with a bare TypeError); a Python
    # number stays as it is (weakly typed: the other arguments' dtype decides)
    d2, logdet = (float_array(x, name) if isinstance(x, (list, tuple)) else x
                  for x, name in ((d2, "d2"), (logdet, "logdet")))
    return _student_t_nll(d2, logdet, nu, dim)


def check_student_t_nu(nu) -> None:
    """A concrete ν must be numbers > 0 (NaN refused), and no ν complex: :class:`InputError`
    naming ``nu``."""
    check_real(nu, "nu")
    if is_concrete(nu):
        v = check_numbers(nu, "nu")
        if not np.all(v > 0):
            raise InputError(f"nu: the Student-t degrees of freedom must be > 0, got {nu!r}")


#: from this ν/2 on, log Γ((ν + d)/2) − log Γ(ν/2) is Stirling's series (:func:`_lgamma_shift`'s
#: threshold; its truncation error there is ~1e-20, the gammaln difference's ~1e-14)
_STIRLING_HALF_NU = 30.0
#: Stirling's series of log Γ: coefficient and power of 1/x of each term (to x⁻⁹)
_STIRLING_TERMS = ((1.0 / 12.0, 1), (-1.0 / 360.0, 3), (1.0 / 1260.0, 5), (-1.0 / 1680.0, 7), (1.0 / 1188.0, 9))


def _student_t_nll(d2, logdet, nu, dim: int):
    """:func:`student_t_nll` without its checks: the filters' per-update call (their d² are
    sums of squares and ν is checked where the filter takes it), so an eager update makes no
    host round-trip for them."""
    from jax.scipy.special import gammaln

    nu = jnp.asarray(nu)  # a Python number stays weakly typed: the rows' dtype decides
    # ν = inf, or a ν beyond the rows' float range (1e300 with float32 rows gave NaN): the Gaussian
    gauss = jnp.isinf(nu.astype(jnp.result_type(d2, logdet, nu)))
    big = 0.5 * nu >= _STIRLING_HALF_NU  # inf included; NaN is not: it stays NaN below
    # each branch sees only its own ν (the other gets a harmless stand-in), so neither can put a
    # NaN into the value or the gradient of the one selected
    nu_s = jnp.where(big, jnp.ones_like(nu), nu)
    t = (0.5 * logdet + 0.5 * (nu_s + dim) * jnp.log1p(d2 / nu_s) + gammaln(0.5 * nu_s)
         - gammaln(0.5 * (nu_s + dim)) + 0.5 * dim * jnp.log(nu_s * jnp.pi))
    # large ν: with b = ν/2, a = d/2, w = b + a, Stirling's series gives
    # log Γ(w) − log Γ(b) = (w − ½) log1p(a/b) + a log b − a + Σ c_k (w⁻ᵏ − b⁻ᵏ), and
    # a log(νπ) − a log b = a log 2π, so nothing of size ν log ν is formed (as _lgamma_shift)
    nu_b = jnp.where(big & ~gauss, nu, jnp.full_like(nu, 2.0 * _STIRLING_HALF_NU))
    a = 0.5 * dim
    b = 0.5 * nu_b
    w = b + a
    shift = (w - 0.5) * jnp.log1p(a / b) - a
    for c, k in _STIRLING_TERMS:
        shift = shift + c * (w ** -k - b ** -k)
    t_big = (0.5 * logdet + 0.5 * (nu_b + dim) * jnp.log1p(d2 / nu_b) - shift
             + a * math.log(2.0 * math.pi))
    t = jnp.where(big, t_big, t)
    return jnp.where(gauss, 0.5 * (d2 + logdet + dim * math.log(2.0 * math.pi)), t)


def chi2_ppf(p, dof):
    """Chi-square quantile (inverse CDF) without SciPy; jit- and vmap-safe.

    Solves ``gammainc(dof/2, x/2) = p`` by clipped Newton steps on the log CDF
    (or log survival function for ``p > 1/2``) in ``log x``; see the module
    docstring.  Used for gates inside ``jit`` (e.g.
    ``gate=lambda d: chi2_ppf(0.99, d)``).

    Args:
        p: probability in [0, 1] (array, broadcast with ``dof``).
        dof: degrees of freedom > 0 (int or float array).

    Returns:
        Quantile(s) in the floating dtype of ``p`` (default float dtype for
        Python numbers; float32 for a float16 / bfloat16 ``p``, which raised a bare TypeError); 0 at p = 0, inf at p = 1, NaN outside [0, 1] or for
        dof ≤ 0.  Float64: ~1e-10 relative for dof 1..10⁵, also for p down to 1e-300 (a lower
        tail that underflows is replaced by its leading term; p = 1e-300, dof = 1000 gave 93.2
        for 103.3).  A complex or bool ``p`` or ``dof`` is an :class:`InputError` (its dtype is
        known, also under ``jit``; ``True`` was read as p = 1, a quantile of inf).  Called eagerly it runs a
        program compiled once (:func:`jaxslam.compilation.call_compiled`): uncompiled, every
        call traced and compiled its Newton loop again (0.28 s a call) and kept it.
    """
    check_real(p, "p", allow_bool=False)
    check_real(dof, "dof", allow_bool=False)
    p = float_array(p, "p")  # a string is named; an integer p becomes the default float
    if jnp.finfo(p.dtype).bits < 32:  # float16 / bfloat16: JAX's gammainc refuses them (a bare TypeError)
        p = p.astype(jnp.float32)
    k = float_array(dof, "dof").astype(p.dtype)
    return call_compiled(("stats.chi2_ppf",), _chi2_ppf, (p, k), after="auto")


def _chi2_ppf(p, k):
    """:func:`chi2_ppf` of float arrays of one dtype."""
    dtype = p.dtype
    p, k = jnp.broadcast_arrays(p, k)
    a = 0.5 * k
    upper = p > 0.5
    q = 1.0 - p
    # Interior values only; the ends are patched at the return.
    inside = (p > 0) & (p < 1) & (k > 0)
    a_s = jnp.where(inside, a, jnp.ones((), dtype))
    p_s = jnp.where(inside, p, jnp.full((), 0.5, dtype))
    q_s = jnp.where(inside, q, jnp.full((), 0.5, dtype))
    log_target = jnp.where(upper, jnp.log(q_s), jnp.log(p_s))
    lga = jax.scipy.special.gammaln(a_s)

    # Wilson–Hilferty start, floored by the small-x lower bound of the root.
    z = jax.scipy.special.ndtri(p_s)
    c = 2.0 / (9.0 * 2.0 * a_s)
    wh = 2.0 * a_s * (1.0 - c + z * jnp.sqrt(c)) ** 3  # chi-square scale
    tiny = jnp.finfo(dtype).tiny
    y_wh = jnp.log(jnp.maximum(0.5 * wh, tiny))
    y_lb = (jnp.log(p_s) + jax.scipy.special.gammaln(a_s + 1.0)) / a_s
    y = jnp.maximum(y_wh, y_lb)

    def body(_, y):
        x = jnp.exp(y)
        P = jax.scipy.special.gammainc(a_s, x)
        Q = jax.scipy.special.gammaincc(a_s, x)
        # d log P / d log x = x f(x) / P, f the gamma(a) density.
        log_xf = a_s * y - x - lga
        # A lower tail that underflowed (far below a root with p ~ 1e-300) gave log P = -inf, a
        # blind +1 step, a clipped Newton step back to the floor, and so a 2-cycle that never
        # left it (p = 1e-300, dof = 1000 gave 93.2 for 103.3): there use the leading term
        # log P ≈ log(x f(x)/a) − log(1 − x/(a+1)) (P's series, x < a + 1 where P underflows).
        r = jnp.clip(x / (a_s + 1.0), 0.0, jnp.asarray(0.99, dtype))
        logP = jnp.where(P >= tiny, jnp.log(jnp.maximum(P, tiny)), log_xf - jnp.log(a_s) - jnp.log1p(-r))
        logF = jnp.where(upper, jnp.log(Q), logP)
        slope = jnp.exp(log_xf - logF)
        slope = jnp.where(upper, -slope, slope)
        diff = logF - log_target
        step = diff / slope
        # A slope that underflowed (far from the root): move by the clip
        # limit in the direction that reduces |diff|.
        fallback = jnp.where(upper, -jnp.sign(diff), jnp.sign(diff))
        step = jnp.where(jnp.isfinite(step), step, fallback)
        y_new = y - jnp.clip(step, -1.0, 1.0)
        # The root is never below the small-x bound (P(x) ≤ x^a / Γ(a+1)).
        return jnp.maximum(y_new, y_lb)

    y = jax.lax.fori_loop(0, _NEWTON_ITERS, body, y)
    x = 2.0 * jnp.exp(y)
    nan = jnp.full((), jnp.nan, dtype)
    x = jnp.where(inside, x, nan)
    x = jnp.where((p == 0) & (k > 0), jnp.zeros((), dtype), x)
    x = jnp.where((p == 1) & (k > 0), jnp.full((), jnp.inf, dtype), x)
    return x


def _log_gammainc_np(a: float, x: float) -> tuple[float, float]:
    """(log P(a, x), log Q(a, x)) in float64 Python (series / continued fraction)."""
    if x <= 0.0:
        return -math.inf, 0.0
    log_pref = a * math.log(x) - x - math.lgamma(a)
    eps = 1e-17
    if x < a + 1.0:
        term = 1.0 / a
        total = term
        ap = a
        for _ in range(100000):
            ap += 1.0
            term *= x / ap
            total += term
            if term < total * eps:
                break
        logP = log_pref + math.log(total)
        P = math.exp(logP)
        logQ = math.log1p(-P) if P < 0.5 else math.log(max(-math.expm1(logP), 1e-320))
        return logP, logQ
    # Modified Lentz continued fraction for Q.
    tiny = 1e-300
    b = x + 1.0 - a
    cc = 1.0 / tiny
    d = 1.0 / b
    hh = d
    for i in range(1, 100000):
        an = -i * (i - a)
        b += 2.0
        d = an * d + b
        if abs(d) < tiny:
            d = tiny
        cc = b + an / cc
        if abs(cc) < tiny:
            cc = tiny
        d = 1.0 / d
        delta = d * cc
        hh *= delta
        if abs(delta - 1.0) < eps:
            break
    logQ = log_pref + math.log(hh)
    Q = math.exp(logQ)
    logP = math.log1p(-Q) if Q < 0.5 else math.log(max(-math.expm1(logQ), 1e-320))
    return logP, logQ


def _lgamma_shift(b: float, a: float) -> float:
    """``log Γ(b + a) − log Γ(b)`` for a, b > 0, to double precision also when b ≫ a: the plain
    difference of two ``lgamma`` values of size b log b loses all of it (at b = 5·10¹¹ the
    Student-t quantile of ν = 10¹² was 7e-5 off).  Stirling's series (terms to b⁻⁹) for b ≥ 30."""
    if b < 30.0:
        return math.lgamma(b + a) - math.lgamma(b)
    w = b + a
    out = (w - 0.5) * math.log1p(a / b) + a * math.log(b) - a
    for c, k in ((1.0 / 12.0, 1), (-1.0 / 360.0, 3), (1.0 / 1260.0, 5), (-1.0 / 1680.0, 7), (1.0 / 1188.0, 9)):
        out += c * (w ** -k - b ** -k)
    return out


def _lbeta(a: float, b: float) -> float:
    """``log B(a, b)`` = log Γ(a) + log Γ(b) − log Γ(a + b), accurate when one argument is large."""
    small, big = min(a, b), max(a, b)
    return math.lgamma(small) - _lgamma_shift(big, small)


def _betainc_cf(a: float, b: float, x: float, log_x: float, log_y: float) -> float:
    """``I_x(a, b)`` by its continued fraction (modified Lentz), which converges fast for
    x ≤ (a + 1)/(a + b + 2); ``log x`` and ``log y``, y = 1 − x, are passed by the caller, who
    can form them without rounding (b log y with b = 5·10¹¹ and y = 1 − 4.5·10⁻¹³ rounded to a
    double is off by 5·10⁻⁵)."""
    log_front = a * log_x + b * log_y - _lbeta(a, b) - math.log(a)
    tiny, eps = 1e-300, 1e-16
    c, d = 1.0, 1.0 - (a + b) * x / (a + 1.0)
    d = 1.0 / (d if abs(d) > tiny else tiny)
    f = d
    for m in range(1, 100000):
        for num in (m * (b - m) * x / ((a + 2 * m - 1) * (a + 2 * m)),
                    -(a + m) * (a + b + m) * x / ((a + 2 * m) * (a + 2 * m + 1))):
            d = 1.0 + num * d
            d = 1.0 / (d if abs(d) > tiny else tiny)
            c = 1.0 + num / c
            c = c if abs(c) > tiny else tiny
            f *= c * d
        if abs(c * d - 1.0) < eps:
            break
    return math.exp(log_front) * f


def _betainc_tails(a: float, b: float, x: float, y: float, log_x=None, log_y=None) -> tuple[float, float]:
    """``(I_x(a, b), 1 − I_x(a, b))`` in float64 Python, ``x + y = 1`` both given (and, when the
    caller has them without rounding, their logs): the side the continued fraction converges
    on is computed directly (full relative precision), the other as its complement."""
    if x <= 0.0:
        return 0.0, 1.0
    if y <= 0.0:
        return 1.0, 0.0
    log_x = math.log(x) if log_x is None else log_x
    log_y = math.log(y) if log_y is None else log_y
    if x > (a + 1.0) / (a + b + 2.0):
        upper = _betainc_cf(b, a, y, log_y, log_x)
        return 1.0 - upper, upper
    lower = _betainc_cf(a, b, x, log_x, log_y)
    return lower, 1.0 - lower


#: above this ν the F(1, ν) quantile equals the χ²(1) one to double precision (they differ by
#: a relative O(x/ν), x ≤ 70 for any p < 1 in double)
_NU_CHI2 = 1e18
#: from this ν on, quantiles above the median come from Fisher's expansion in 1/ν
_NU_SERIES = 1e4


def student_t_d2_ppf_np(p: float, nu: float) -> float:
    """Quantile of d² = t² for a one-dimensional Student-t with ν degrees of freedom (an F(1, ν)
    variable; χ²(1) as ν → ∞), in float64 on the host (pure Python, no SciPy).

    P(t² ≤ x) = I_{x/(ν+x)}(½, ν/2), with ``x/(ν+x)`` and its complement ``ν/(ν+x)`` both
    formed from x (no rounding of 1 − w) and the smaller tail computed directly; solved by
    bisection in log x to double precision (inf when the quantile is beyond the largest
    double).  Above the median with ν ≥ 10⁴, Fisher's expansion of the t quantile in 1/ν
    (Abramowitz & Stegun 26.7.5, four terms) instead.  ν = inf (and ν > 10¹⁸, where the two agree to
    double precision) is the χ²(1) quantile :func:`chi2_ppf_np` ``(p, 1)``, the limit the
    finite ν approach (ν = 10¹² used to be 7e-5 off it, inf returned inf).  The outlier gate of
    a Student-t range model at probability ``p``.  A bool ``p`` or ``nu`` is an
    :class:`InputError` naming it.
    """
    check_real(p, "p", allow_bool=False)
    check_real(nu, "nu", allow_bool=False)
    p, nu = check_scalar(p, "p", finite=False), check_scalar(nu, "nu", finite=False)
    if not (nu > 0) or not (0.0 <= p < 1.0):
        raise InputError(f"student_t_d2_ppf_np: need 0 <= p < 1 and nu > 0, got p={p}, nu={nu}")
    if p == 0.0:
        return 0.0
    if nu > _NU_CHI2:
        return chi2_ppf_np(p, 1.0)
    q = 1.0 - p  # exact for p >= 1/2, the side where it is compared
    if p > 0.5 and nu >= _NU_SERIES:
        # the upper tail I_{ν/(ν+x)}(ν/2, ½) by the continued fraction cancels (error ~ eps ν/2);
        # Fisher's expansion of t_p (Abramowitz & Stegun 26.7.5) is exact to double precision here
        z = -statistics.NormalDist().inv_cdf(0.5 * q)
        z2 = z * z
        g = (z * (z2 + 1.0) / 4.0,
             z * ((5.0 * z2 + 16.0) * z2 + 3.0) / 96.0,
             z * (((3.0 * z2 + 19.0) * z2 + 17.0) * z2 - 15.0) / 384.0,
             z * ((((79.0 * z2 + 776.0) * z2 + 1482.0) * z2 - 1920.0) * z2 - 945.0) / 92160.0)
        t = z + sum(gk / nu ** (k + 1) for k, gk in enumerate(g))
        return t * t

    log_nu = math.log(nu)

    def below(lx):  # P(t² ≤ e^lx) < p, from the tail that is computed directly there
        x = math.exp(lx)
        # v = x/(ν+x), 1 − v = ν/(ν+x) and their logs, each without a rounded 1 − (·)
        if lx < log_nu:
            l1 = math.log1p(x / nu)  # log((ν + x)/ν)
            log_v, log_w = lx - log_nu - l1, -l1
        else:
            l1 = math.log1p(nu / x)  # log((ν + x)/x)
            log_v, log_w = -l1, log_nu - lx - l1
        lower, upper = _betainc_tails(0.5, 0.5 * nu, math.exp(log_v), math.exp(log_w), log_v, log_w)
        return lower < p if p <= 0.5 else upper > q

    lo, hi = -750.0, 709.0  # e^lo = 0, e^hi near the largest double: F(lo) < p <= F(hi)
    if below(hi):  # the quantile is beyond the largest double (ν ≪ 1, p near 1)
        return math.inf
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if not lo < mid < hi or hi - lo <= 1e-16:  # relative 1e-16 in x
            break
        if below(mid):
            lo = mid
        else:
            hi = mid
    return math.exp(0.5 * (lo + hi))


def chi2_ppf_np(p: float, dof: float) -> float:
    """Chi-square quantile in float64 on the host (pure Python, no SciPy).

    Same method as :func:`chi2_ppf` with an own regularised incomplete gamma,
    so host-side bounds are float64-accurate even when JAX x64 is off.

    Args:
        p: probability in [0, 1].  dof: degrees of freedom > 0.

    Returns:
        Python float quantile (0 at p = 0, inf at p = 1).  A bool ``p`` or ``dof`` is an
        :class:`InputError` naming it (``True`` was read as 1).
    """
    check_real(p, "p", allow_bool=False)
    check_real(dof, "dof", allow_bool=False)
    p = check_scalar(p, "p", finite=False)
    k = check_scalar(dof, "dof", finite=False)
    if not (0 < k < math.inf) or not (0.0 <= p <= 1.0):
        raise InputError(f"chi2_ppf_np: need 0 <= p <= 1 and a finite dof > 0, got p={p}, dof={k}")
    if p == 0.0:
        return 0.0
    if p == 1.0:
        return math.inf
    a = 0.5 * k
    upper = p > 0.5
    log_target = math.log1p(-p) if upper else math.log(p)
    z = statistics.NormalDist().inv_cdf(p)
    c = 2.0 / (9.0 * k)
    wh = k * (1.0 - c + z * math.sqrt(c)) ** 3
    y = math.log(max(0.5 * wh, 1e-300))
    y_lb = (math.log(p) + math.lgamma(a + 1.0)) / a
    y = max(y, y_lb)
    lga = math.lgamma(a)
    for _ in range(200):
        x = math.exp(y)
        logP, logQ = _log_gammainc_np(a, x)
        logF = logQ if upper else logP
        slope = math.exp(a * y - x - lga - logF)
        if upper:
            slope = -slope
        diff = logF - log_target
        step = diff / slope if slope != 0 else math.inf
        if not math.isfinite(step):
            step = math.copysign(1.0, -diff if upper else diff)
        step = min(max(step, -1.0), 1.0)
        y_new = max(y - step, y_lb)
        if abs(y_new - y) < 1e-15:
            y = y_new
            break
        y = y_new
    return 2.0 * math.exp(y)


def _alpha(alpha) -> float:
    """A two-sided test's level: a number in (0, 1), else :class:`InputError` naming ``alpha``."""
    try:
        check_real(alpha, "alpha")
        a = check_scalar(alpha, "alpha")
    except InputError:
        a = math.nan
    if not 0.0 < a < 1.0:
        raise InputError(f"alpha: must be in (0, 1), got {alpha!r}")
    return a


def mean_chi2_bounds(dof_total, count, alpha: float = 0.05) -> tuple[float, float]:
    """Two-sided (1 − α) bounds for a mean of χ² statistics.

    If ``count`` independent statistics have ``dof_total`` degrees of freedom
    in all, their sum is χ²(dof_total) and their mean lies in
    ``[χ²_{α/2}(dof_total), χ²_{1−α/2}(dof_total)] / count`` with probability
    1 − α.  Serves mean NIS (dof_total = Σ dof) and ANEES.

    Returns:
        ``(lo, hi)`` Python floats (float64).

    ``dof_total`` and ``count`` must be positive finite numbers and ``alpha`` in (0, 1):
    :class:`InputError` naming the argument (an infinite count gave (0, 0), a string NumPy's
    bare ValueError; a bool is refused, as ``alpha``'s).
    """
    check_real(dof_total, "dof_total", allow_bool=False)
    check_real(count, "count", allow_bool=False)
    dof_total = check_scalar(dof_total, "dof_total", lower=0, strict=True)
    count = check_scalar(count, "count", lower=0, strict=True)
    alpha = _alpha(alpha)
    lo = chi2_ppf_np(0.5 * alpha, dof_total) / count
    hi = chi2_ppf_np(1.0 - 0.5 * alpha, dof_total) / count
    return lo, hi


def anees_bounds(n_state: int, n_runs: int, alpha: float = 0.05) -> tuple[float, float]:
    """Two-sided (1 − α) bounds of the average NEES over ``n_runs`` runs.

    ``(χ²_{α/2}(N n)/N, χ²_{1−α/2}(N n)/N)`` with N = ``n_runs`` and n =
    ``n_state`` (Bar-Shalom's ANEES test; per time step or per window).  Both are counts: ints
    ≥ 1 (:class:`InputError` naming the argument; 2.5 used to be truncated to 2).
    """
    n_state = check_int(n_state, "n_state")
    n_runs = check_int(n_runs, "n_runs")
    return mean_chi2_bounds(n_state * n_runs, n_runs, alpha)
