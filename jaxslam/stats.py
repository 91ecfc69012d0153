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

from .errors import InputError

__all__ = ["nees", "nis", "student_t_nll", "student_t_d2_ppf_np", "chi2_ppf", "chi2_ppf_np", "mean_chi2_bounds",
           "anees_bounds"]


# ---------------------------------------------------------------------------
# NEES / NIS
# ---------------------------------------------------------------------------

def nees(err, cov):
    """Normalised estimation error squared ``eᵀ P⁻¹ e`` via Cholesky.

    Args:
        err: (..., n) estimation errors (estimate − truth).
        cov: (..., n, n) estimated covariances (broadcast against ``err``).

    Returns:
        (...) NEES values; χ²(n)-distributed for a consistent filter.  NaN
        where ``cov`` is not positive definite.
    """
    err = jnp.asarray(err)
    cov = jnp.asarray(cov)
    batch = jnp.broadcast_shapes(err.shape[:-1], cov.shape[:-2])
    n = err.shape[-1]
    err = jnp.broadcast_to(err, batch + (n,))
    cov = jnp.broadcast_to(cov, batch + (n, n))
    L = jnp.linalg.cholesky(0.5 * (cov + jnp.swapaxes(cov, -1, -2)))
    y = jax.scipy.linalg.solve_triangular(L, err[..., None], lower=True)[..., 0]
    return jnp.sum(y * y, axis=-1)


def nis(innovation, S):
    """Normalised innovation squared ``νᵀ S⁻¹ ν`` via Cholesky.

    Args:
        innovation: (..., m) innovations.
        S: (..., m, m) innovation covariances.

    Returns:
        (...) NIS values, χ²(m) for a consistent filter.
    """
    return nees(innovation, S)


# ---------------------------------------------------------------------------
# Chi-square quantiles
# ---------------------------------------------------------------------------

_NEWTON_ITERS = 8  # 5 reach 1e-12 from the Wilson–Hilferty start


def student_t_nll(d2, logdet, nu, dim):
    """Negative log density of a d-variate Student-t with ν degrees of freedom and scale S at a
    point of squared Mahalanobis distance ``d2`` (νᵀ S⁻¹ ν) and ``logdet`` = log det S::

        ½ log det S + (ν + d)/2 · log(1 + d²/ν) + log Γ(ν/2) − log Γ((ν + d)/2) + (d/2) log(νπ)

    (elementwise over arrays of rows; ``dim`` = d, static).  ν → ∞ is the Gaussian's
    ½ (d² + log det S + d log 2π).  The robust EKF updates (``robust=ν`` of
    :func:`jaxslam.filters.ekf_slam.update`) are the EM steps of this likelihood.
    """
    from jax.scipy.special import gammaln

    return (0.5 * logdet + 0.5 * (nu + dim) * jnp.log1p(d2 / nu) + gammaln(0.5 * nu)
            - gammaln(0.5 * (nu + dim)) + 0.5 * dim * jnp.log(nu * jnp.pi))


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
        Python numbers); 0 at p = 0, inf at p = 1, NaN outside [0, 1] or for
        dof ≤ 0.  Float64: ~1e-10 relative for dof 1..10⁵.
    """
    p = jnp.asarray(p)
    if not jnp.issubdtype(p.dtype, jnp.floating):
        p = p.astype(jnp.result_type(float))
    dtype = p.dtype
    k = jnp.asarray(dof).astype(dtype)
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
        logF = jnp.where(upper, jnp.log(Q), jnp.log(P))
        # d log P / d log x = x f(x) / P, f the gamma(a) density.
        log_xf = a_s * y - x - lga
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


def _betainc_np(a: float, b: float, x: float) -> float:
    """Regularised incomplete beta I_x(a, b) in float64 Python (modified Lentz continued
    fraction, on the side of x where it converges fast)."""
    if x <= 0.0:
        return 0.0
    if x >= 1.0:
        return 1.0
    if x > (a + 1.0) / (a + b + 2.0):
        return 1.0 - _betainc_np(b, a, 1.0 - x)
    log_front = a * math.log(x) + b * math.log1p(-x) - (math.lgamma(a) + math.lgamma(b) - math.lgamma(a + b)) - math.log(a)
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


def student_t_d2_ppf_np(p: float, nu: float) -> float:
    """Quantile of d² = t² for a one-dimensional Student-t with ν degrees of freedom (an F(1, ν)
    variable; χ²(1) as ν → ∞), in float64 on the host (pure Python, no SciPy).

    P(t² ≤ x) = 1 − I_{ν/(ν+x)}(ν/2, ½); solved by bisection in w = ν/(ν + x) to double
    precision.  The outlier gate of a Student-t range model at probability ``p``.
    """
    p, nu = float(p), float(nu)
    if not (nu > 0) or not (0.0 <= p < 1.0):
        raise InputError(f"student_t_d2_ppf_np: need 0 <= p < 1 and nu > 0, got p={p}, nu={nu}")
    if p == 0.0:
        return 0.0
    lo, hi = 0.0, 1.0  # I_w(ν/2, ½) rises with w from 0 to 1; the root: I = 1 − p
    for _ in range(200):
        w = 0.5 * (lo + hi)
        if not lo < w < hi:  # lo and hi are adjacent doubles: the bracket cannot shrink further
            break
        if _betainc_np(0.5 * nu, 0.5, w) < 1.0 - p:
            lo = w
        else:
            hi = w
    w = 0.5 * (lo + hi)
    return nu * (1.0 - w) / w


def chi2_ppf_np(p: float, dof: float) -> float:
    """Chi-square quantile in float64 on the host (pure Python, no SciPy).

    Same method as :func:`chi2_ppf` with an own regularised incomplete gamma,
    so host-side bounds are float64-accurate even when JAX x64 is off.

    Args:
        p: probability in [0, 1].  dof: degrees of freedom > 0.

    Returns:
        Python float quantile (0 at p = 0, inf at p = 1).
    """
    p = float(p)
    k = float(dof)
    if not (k > 0) or not (0.0 <= p <= 1.0):
        raise InputError(f"chi2_ppf_np: need 0 <= p <= 1 and dof > 0, got p={p}, dof={k}")
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


def mean_chi2_bounds(dof_total, count, alpha: float = 0.05) -> tuple[float, float]:
    """Two-sided (1 − α) bounds for a mean of χ² statistics.

    If ``count`` independent statistics have ``dof_total`` degrees of freedom
    in all, their sum is χ²(dof_total) and their mean lies in
    ``[χ²_{α/2}(dof_total), χ²_{1−α/2}(dof_total)] / count`` with probability
    1 − α.  Serves mean NIS (dof_total = Σ dof) and ANEES.

    Returns:
        ``(lo, hi)`` Python floats (float64).
    """
    dof_total = float(dof_total)
    count = float(count)
    if not dof_total > 0:
        raise InputError(f"dof_total: must be > 0, got {dof_total}")
    if not count > 0:
        raise InputError(f"count: must be > 0, got {count}")
    if not 0.0 < alpha < 1.0:
        raise InputError(f"alpha: must be in (0, 1), got {alpha}")
    lo = chi2_ppf_np(0.5 * alpha, dof_total) / count
    hi = chi2_ppf_np(1.0 - 0.5 * alpha, dof_total) / count
    return lo, hi


def anees_bounds(n_state: int, n_runs: int, alpha: float = 0.05) -> tuple[float, float]:
    """Two-sided (1 − α) bounds of the average NEES over ``n_runs`` runs.

    ``(χ²_{α/2}(N n)/N, χ²_{1−α/2}(N n)/N)`` with N = ``n_runs`` and n =
    ``n_state`` (Bar-Shalom's ANEES test; per time step or per window).
    """
    if int(n_state) < 1:
        raise InputError(f"n_state: must be >= 1, got {n_state}")
    if int(n_runs) < 1:
        raise InputError(f"n_runs: must be >= 1, got {n_runs}")
    return mean_chi2_bounds(int(n_state) * int(n_runs), int(n_runs), alpha)
