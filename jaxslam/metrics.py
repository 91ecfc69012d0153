"""Accuracy and consistency metrics: RMSE, NEES/NIS, chi-square bounds, ATE.

Pure NumPy/JAX; SciPy is never imported at run time (it is a test-only
dependency used as an oracle).

Decisions (the papers report RMSE and plots but define neither precisely)
------------------------------------------------------------------------
* RMSE.  ``rmse(err)`` is per component, ``sqrt(mean_t err_t,i²)``;
  ``rmse_norm(err)`` is the RMSE of the Euclidean error norm,
  ``sqrt(mean_t ‖err_t‖²)`` — the "3D position RMSE" of paper 000's
  reported figures (0.04 m etc.).  Note ``rmse_norm² = Σ_i rmse_i²``.
  Attitude errors must be wrapped (or computed on SO(3)) by the caller.
* NEES ``eᵀ P⁻¹ e`` and NIS ``νᵀ S⁻¹ ν`` go through a Cholesky factor and a
  triangular solve, never an inverse.  A non-PD covariance yields NaN (it is
  not hidden).
* Chi-square quantiles.  ``chi2_ppf`` (JAX, jit-able, follows the input
  dtype) solves ``P(k/2, x/2) = p`` by Newton's method on the *log* CDF in
  ``log x`` (lower tail for p ≤ 1/2, log survival for p > 1/2).  Both are
  concave in ``log x`` (the log-gamma density is log-concave), so after the
  first step the iterates approach the root monotonically from one side and
  never overshoot; steps are clipped to ±1 in ``log x`` and the start is a
  Wilson–Hilferty guess, floored (as are all iterates) by the lower bound
  of the root that follows from ``P(a, x) ≤ x^a / Γ(a+1)``.
  In float32 the regularised incomplete gamma itself carries ~1e-2 relative
  error at dof ~ 10⁵, so ``chi2_ppf`` is then only good to ~1e-4.
  Host-side bounds (``anees_bounds``, ``mean_chi2_bounds``) therefore use
  ``chi2_ppf_np``: the same Newton scheme in float64 Python with its own
  incomplete gamma (power series for x < a + 1, Lentz continued fraction
  otherwise), independent of whether JAX x64 is enabled.  Both match
  ``scipy.stats.chi2.ppf`` to 1e-9 relative for dof 1..10⁵ in float64.
* Average-NEES bounds.  For N runs of an n-state filter the sum of N
  independent NEES values is χ²(N n), so the two-sided (1 − α) bounds on the
  average are ``χ²_{α/2}(N n)/N`` and ``χ²_{1−α/2}(N n)/N``.  The same helper
  gives bounds for a mean NIS over ``count`` updates with ``dof_total``
  degrees of freedom in all.  Averages over *time* as well are not
  independent samples; use these bounds per time step (or per window, with
  ``count`` the number of samples) and read whole-run averages as indicative.
* ``windowed_mean`` ignores NaN entries (steps without a value) and returns
  the count per window, so bounds can be computed per window.
* ``summarize`` does not hide a diverged run: NaN propagates to the mean and
  the maximum.
* ATE: positions are aligned by the closed-form least-squares similarity or
  rigid transform (Umeyama 1991) before the RMSE of the position error; RPE
  here is translational: the RMSE of the error of displacements over a fixed
  step lag (no rotation term), which needs no orientation estimates.
  ``rpe_se2`` is the pose RPE of Sturm et al. (2012) / evo for planar poses:
  the relative motion over a lag, ``E_i = (Q_i⁻¹ Q_{i+Δ})⁻¹ (P_i⁻¹ P_{i+Δ})``,
  with the RMSE of its translation and of its (wrapped) angle; it is
  invariant to any rigid transform of either trajectory.
* Map error: landmark positions are compared by id after a rigid transform
  (the trajectory's ATE alignment, so map and path are judged in one frame,
  or the map's own Umeyama alignment); the RMSE of the position error.
* TUM format (for ``evo``): one pose per line, ``t tx ty tz qx qy qz qw``;
  planar poses get z = 0 and a yaw quaternion.
"""

from __future__ import annotations

import math
import statistics
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .errors import InputError
from .linalg import wrap_angle

__all__ = [
    "rmse",
    "rmse_norm",
    "nees",
    "nis",
    "chi2_ppf",
    "chi2_ppf_np",
    "mean_chi2_bounds",
    "anees_bounds",
    "WindowedMean",
    "windowed_mean",
    "summarize",
    "umeyama",
    "ate",
    "rpe",
    "rpe_se2",
    "apply_transform",
    "map_error",
    "interp_poses",
    "write_tum",
    "read_tum",
]


# ---------------------------------------------------------------------------
# RMSE
# ---------------------------------------------------------------------------

def rmse(err, axis=0):
    """Per-component root-mean-square error.

    Args:
        err: (T, d) errors (estimate − truth), in the state's units; any
            shape works, the mean runs over ``axis``.
        axis: axis (or tuple of axes) averaged over; default the time axis 0.

    Returns:
        ``sqrt(mean(err², axis))``, e.g. (d,) per-axis RMSE for (T, d) input.
    """
    err = jnp.asarray(err)
    return jnp.sqrt(jnp.mean(err * err, axis=axis))


def rmse_norm(err, axis=0):
    """RMSE of the Euclidean error norm: ``sqrt(mean_t ‖err_t‖²)``.

    This is the "position RMSE" of a trajectory (paper 000 reports 0.04 m /
    0.012 m for it).  Equal to ``sqrt(Σ_i rmse(err)_i²)``.

    Args:
        err: (T, d) errors; the norm is over the last axis.
        axis: axis averaged over after taking the norm (default 0, time), on
            the array with the last axis removed.

    Returns:
        Scalar for (T, d) input; (R,) for (R, T, d) with ``axis=1``.
    """
    err = jnp.asarray(err)
    return jnp.sqrt(jnp.mean(jnp.sum(err * err, axis=-1), axis=axis))


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


# What a value outside its χ² bounds means, by kind of statistic: (below, above).
_OUTSIDE_MEANS = {
    "nees": ("below: conservative (covariance larger than the errors)",
             "above: over-confident (errors larger than the covariance)"),
    "nis": ("below: innovations smaller than predicted (R or P too large)",
            "above: innovations larger than predicted (R or P too small, or outliers)"),
}


def consistency_verdict(value, bounds, kind: str | None = "nees") -> str:
    """A NEES/NIS statistic against its bounds, in words (the console report and the figures).

    Returns ``"ok"``, ``"OUTSIDE, below: conservative (covariance larger than the errors)"``
    (what the side means for ``kind`` ``"nees"`` or ``"nis"``; bare ``"OUTSIDE"`` for
    ``kind=None``), or ``"undefined"`` when the value or a bound is missing or non-finite.
    """
    try:
        v = float(value)
        lo, hi = (float(b) for b in bounds)
    except (TypeError, ValueError):
        return "undefined"
    if not all(math.isfinite(x) for x in (v, lo, hi)):
        return "undefined"
    if lo <= v <= hi:
        return "ok"
    return "OUTSIDE" + ("" if kind is None else ", " + _OUTSIDE_MEANS[kind][0 if v < lo else 1])


# ---------------------------------------------------------------------------
# Windows and summaries (host side)
# ---------------------------------------------------------------------------

class WindowedMean(NamedTuple):
    """Means over consecutive time windows.

    Fields:
        t_start: (W,) window start times [s].
        t_end: (W,) window end times [s] (exclusive, except the last).
        mean: (W,) mean of the finite values in the window (NaN if none).
        count: (W,) int number of finite values averaged (runs × steps).
    """

    t_start: np.ndarray
    t_end: np.ndarray
    mean: np.ndarray
    count: np.ndarray


def windowed_mean(x, t, window_s: float) -> WindowedMean:
    """Average a per-step statistic (e.g. NEES) over time windows (host side).

    Windows are ``[t0 + k w, t0 + (k+1) w)`` from the first time ``t0``; the
    last window is closed and may be shorter.  For (R, T) input all runs of a
    window are pooled, so ``mean`` is the windowed ANEES and
    ``anees_bounds``-style bounds use ``mean_chi2_bounds(n·count, count)``.

    Args:
        x: (T,) or (R, T) values; NaN marks a missing value.
        t: (T,) nondecreasing times [s].
        window_s: window length [s] > 0.

    Returns:
        :class:`WindowedMean`.
    """
    x = np.asarray(x, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    if x.ndim == 1:
        x = x[None, :]
    if x.ndim != 2:
        raise InputError(f"x: expected shape (T,) or (R, T), got {np.shape(x)}")
    if t.ndim != 1 or t.shape[0] != x.shape[1]:
        raise InputError(f"t: expected shape ({x.shape[1]},), got {t.shape}")
    if not window_s > 0:
        raise InputError(f"window_s: must be > 0, got {window_s}")
    if t.size == 0:
        e = np.zeros(0)
        return WindowedMean(e, e, e, np.zeros(0, dtype=np.int64))
    if np.any(np.diff(t) < 0):
        raise InputError("t: must be nondecreasing")
    t0 = t[0]
    n_win = max(1, int(math.ceil((t[-1] - t0) / window_s - 1e-9)))
    idx = np.minimum(np.floor((t - t0) / window_s + 1e-12).astype(np.int64), n_win - 1)
    finite = np.isfinite(x)
    vals = np.where(finite, x, 0.0)
    sums = np.zeros(n_win)
    counts = np.zeros(n_win, dtype=np.int64)
    np.add.at(sums, idx, vals.sum(axis=0))
    np.add.at(counts, idx, finite.sum(axis=0))
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(counts > 0, sums / np.maximum(counts, 1), np.nan)
    starts = t0 + window_s * np.arange(n_win)
    ends = starts + window_s
    return WindowedMean(starts, ends, mean, counts)


def summarize(per_run) -> dict:
    """Summary of a per-run metric for reports and JSON.

    Args:
        per_run: (R,) values, one per Monte Carlo run.

    Returns:
        ``{"mean", "median", "p95", "max", "per_run"}`` as Python floats (p95
        with linear interpolation); NaN propagates to mean/median/p95/max.
    """
    v = np.asarray(per_run, dtype=np.float64).reshape(-1)
    if v.size == 0:
        raise InputError("per_run: empty")
    return {
        "mean": float(np.mean(v)),
        "median": float(np.median(v)),
        "p95": float(np.percentile(v, 95.0)),
        "max": float(np.max(v)),
        "per_run": [float(a) for a in v],
    }


# ---------------------------------------------------------------------------
# Trajectory alignment
# ---------------------------------------------------------------------------

def umeyama(src, dst, with_scale: bool = False):
    """Least-squares transform ``dst ≈ s R src + t`` (Umeyama 1991), closed form.

    Args:
        src: (N, d) points (e.g. estimated positions).
        dst: (N, d) corresponding points (e.g. true positions).
        with_scale: static; also estimate the scale ``s`` (similarity).

    Returns:
        ``(R (d, d) proper rotation, t (d,), s ())``; ``s`` is 1 unless
        ``with_scale``.
    """
    src = jnp.asarray(src)
    dst = jnp.asarray(dst)
    dtype = jnp.result_type(src, dst)
    src = src.astype(dtype)
    dst = dst.astype(dtype)
    d = src.shape[-1]
    mu_s = jnp.mean(src, axis=0)
    mu_d = jnp.mean(dst, axis=0)
    xs = src - mu_s
    xd = dst - mu_d
    C = xd.T @ xs / src.shape[0]
    U, D, Vt = jnp.linalg.svd(C)
    # Reflection guard: force det(R) = +1.
    sign = jnp.sign(jnp.linalg.det(U) * jnp.linalg.det(Vt))
    sign = jnp.where(sign == 0, jnp.ones((), dtype), sign)
    e = jnp.ones((d,), dtype).at[-1].set(sign)
    R = (U * e) @ Vt
    if with_scale:
        var_s = jnp.mean(jnp.sum(xs * xs, axis=1))
        s = jnp.sum(D * e) / var_s
    else:
        s = jnp.ones((), dtype)
    t = mu_d - s * R @ mu_s
    return R, t, s


def ate(est_pos, true_pos, align: str = "rigid"):
    """Absolute trajectory error: position RMSE after alignment.

    Args:
        est_pos: (T, d) estimated positions [m].
        true_pos: (T, d) true positions [m].
        align: ``"rigid"`` (rotation + translation, default), ``"sim"`` (with
            scale) or ``"none"``.

    Returns:
        Scalar ``sqrt(mean_t ‖s R p̂_t + t − p_t‖²)`` [m].
    """
    if align not in ("rigid", "sim", "none"):
        raise InputError(f"align: expected 'rigid', 'sim' or 'none', got {align!r}")
    est = jnp.asarray(est_pos)
    tru = jnp.asarray(true_pos)
    if align != "none":
        R, t, s = umeyama(est, tru, with_scale=(align == "sim"))
        est = s * est @ R.T + t
    return rmse_norm(est - tru)


def rpe(est_pos, true_pos, lag: int = 1):
    """Translational relative pose error over a fixed step lag.

    ``sqrt(mean_t ‖(p̂_{t+lag} − p̂_t) − (p_{t+lag} − p_t)‖²)`` [m]; invariant to
    a constant offset, not to a rotation (no alignment is applied).

    Args:
        est_pos, true_pos: (T, d) positions [m].
        lag: static step lag ≥ 1, < T.
    """
    lag = int(lag)
    est = jnp.asarray(est_pos)
    tru = jnp.asarray(true_pos)
    if lag < 1 or lag >= est.shape[0]:
        raise InputError(f"lag: must be in [1, {est.shape[0] - 1}], got {lag}")
    de = est[lag:] - est[:-lag]
    dt = tru[lag:] - tru[:-lag]
    return rmse_norm(de - dt)


def rpe_se2(est_pose, true_pose, lag: int = 1):
    """Planar pose RPE (Sturm et al. 2012): RMSE of the relative-motion error over ``lag`` steps.

    Args:
        est_pose, true_pose: (T, 3) poses (x, y, θ) [m, rad].
        lag: static step lag ≥ 1, < T.

    Returns:
        ``(trans_rmse [m], rot_rmse [rad])`` of ``E_i = (Q_i⁻¹ Q_{i+lag})⁻¹ (P_i⁻¹ P_{i+lag})``.
    """
    lag = int(lag)
    est = jnp.asarray(est_pose)
    tru = jnp.asarray(true_pose)
    if est.ndim != 2 or est.shape[1] != 3 or est.shape != tru.shape:
        raise InputError(f"rpe_se2: expected two (T, 3) pose arrays, got {est.shape} and {tru.shape}")
    if lag < 1 or lag >= est.shape[0]:
        raise InputError(f"lag: must be in [1, {est.shape[0] - 1}], got {lag}")

    def rel(P):
        a, b = P[:-lag], P[lag:]
        c, s = jnp.cos(a[:, 2]), jnp.sin(a[:, 2])
        dx, dy = b[:, 0] - a[:, 0], b[:, 1] - a[:, 1]
        return c * dx + s * dy, -s * dx + c * dy, b[:, 2] - a[:, 2]

    ex, ey, eth = rel(est)
    tx, ty, tth = rel(tru)
    # E = T_true⁻¹ T_est for the relative motions T = (t, θ).
    c, s = jnp.cos(tth), jnp.sin(tth)
    dx, dy = ex - tx, ey - ty
    etx, ety = c * dx + s * dy, -s * dx + c * dy
    eang = wrap_angle(eth - tth)
    return jnp.sqrt(jnp.mean(etx ** 2 + ety ** 2)), jnp.sqrt(jnp.mean(eang ** 2))


def apply_transform(points, R, t, s=1.0):
    """``s R p + t`` for each row of ``points`` (N, d) — e.g. the ATE alignment of :func:`umeyama`."""
    return s * jnp.asarray(points) @ jnp.asarray(R).T + jnp.asarray(t)


class MapError(NamedTuple):
    """Landmark map error after alignment: per-landmark errors [m], their RMSE and max, ids compared."""

    errors: np.ndarray
    rmse: float
    max: float
    ids: np.ndarray


def map_error(est_lm, est_ids, true_lm, true_ids, transform=None) -> MapError:
    """Map error of landmarks matched by id, after a rigid alignment.

    Args:
        est_lm: (M, d) estimated landmark positions; est_ids: (M,) their ids
            (entries with id < 0 or non-finite positions are ignored).
        true_lm: (L, d) true positions; true_ids: (L,).
        transform: ``(R, t)`` or ``(R, t, s)`` to apply to the estimates (e.g.
            the trajectory's ATE alignment), or None to align the matched
            landmarks themselves by :func:`umeyama` (needs ≥ d of them).

    Raises:
        InputError: shapes disagree, or no estimated id is in ``true_ids``.
    """
    est = np.asarray(est_lm, np.float64)
    tru = np.asarray(true_lm, np.float64)
    eid = np.asarray(est_ids).reshape(-1)
    tid = np.asarray(true_ids).reshape(-1)
    if est.ndim != 2 or tru.ndim != 2 or est.shape[1] != tru.shape[1]:
        raise InputError(f"map_error: expected (M, d) and (L, d) landmarks, got {est.shape} and {tru.shape}")
    if eid.shape[0] != est.shape[0] or tid.shape[0] != tru.shape[0]:
        raise InputError("map_error: one id per landmark row expected")
    lookup = {int(i): k for k, i in enumerate(tid)}
    pairs = [(k, lookup[int(i)]) for k, i in enumerate(eid)
             if int(i) >= 0 and int(i) in lookup and np.all(np.isfinite(est[k]))]
    if not pairs:
        raise InputError("map_error: no estimated landmark id matches a true id")
    a = est[[k for k, _ in pairs]]
    b = tru[[j for _, j in pairs]]
    if transform is None:
        if len(pairs) < a.shape[1]:
            raise InputError(f"map_error: {len(pairs)} matched landmarks cannot fix a {a.shape[1]}-D alignment")
        R, t, s = umeyama(a, b)
    else:
        R, t = transform[0], transform[1]
        s = transform[2] if len(transform) > 2 else 1.0
    e = np.linalg.norm(np.asarray(apply_transform(a, R, t, s)) - b, axis=1)
    return MapError(e, float(np.sqrt(np.mean(e ** 2))), float(np.max(e)),
                    np.asarray([int(eid[k]) for k, _ in pairs]))


def interp_poses(t_query, t, poses):
    """Linear interpolation of planar poses (x, y, θ) at ``t_query`` (host side, NumPy).

    The heading is interpolated on the unwrapped angle and re-wrapped.  Query
    times outside ``[t[0], t[-1]]`` give NaN (ground truth must not be
    extrapolated).
    """
    tq = np.asarray(t_query, np.float64)
    t = np.asarray(t, np.float64)
    P = np.asarray(poses, np.float64)
    out = np.empty((tq.shape[0], P.shape[1]))
    for j in range(P.shape[1]):
        col = np.unwrap(P[:, j]) if j == 2 and P.shape[1] == 3 else P[:, j]
        out[:, j] = np.interp(tq, t, col)
    if P.shape[1] == 3:
        out[:, 2] = np.asarray(wrap_angle(out[:, 2]), np.float64)
    out[(tq < t[0]) | (tq > t[-1])] = np.nan
    return out


def write_tum(path, t, positions, yaw=None, quat_xyzw=None):
    """Write a trajectory in TUM format (``t tx ty tz qx qy qz qw`` per line) for ``evo``.

    Args:
        path: output file (parent folders are created; written atomically).
        t: (T,) times [s].
        positions: (T, 2) or (T, 3) [m]; planar positions get z = 0.
        yaw: optional (T,) heading [rad] (planar); quat_xyzw: optional (T, 4).
            With neither, the identity orientation is written.
    """
    t = np.asarray(t, np.float64).reshape(-1)
    p = np.asarray(positions, np.float64)
    if p.ndim != 2 or p.shape[0] != t.shape[0] or p.shape[1] not in (2, 3):
        raise InputError(f"write_tum: positions must be (T, 2|3) with T = {t.shape[0]}, got {p.shape}")
    if p.shape[1] == 2:
        p = np.concatenate([p, np.zeros((p.shape[0], 1))], axis=1)
    if quat_xyzw is not None and yaw is not None:
        raise InputError("write_tum: give yaw or quat_xyzw, not both")
    if quat_xyzw is not None:
        q = np.asarray(quat_xyzw, np.float64).reshape(t.shape[0], 4)
    else:
        h = np.zeros_like(t) if yaw is None else np.asarray(yaw, np.float64).reshape(-1)
        if h.shape != t.shape:
            raise InputError(f"write_tum: yaw must be (T,) with T = {t.shape[0]}, got {h.shape}")
        q = np.stack([np.zeros_like(h), np.zeros_like(h), np.sin(h / 2), np.cos(h / 2)], axis=1)
    from jaxslam.files import atomic_write

    table = np.concatenate([t[:, None], p, q], axis=1)
    return atomic_write(path, lambda f: np.savetxt(f, table, fmt="%.9f",
                                                   header="timestamp tx ty tz qx qy qz qw"))


def read_tum(path):
    """Read a TUM trajectory: ``(t (T,), positions (T, 3), quat_xyzw (T, 4))``."""
    a = np.loadtxt(path, comments="#", ndmin=2)
    if a.shape[1] != 8:
        raise InputError(f"{path}: TUM lines have 8 columns, found {a.shape[1]}")
    return a[:, 0], a[:, 1:4], a[:, 4:8]
