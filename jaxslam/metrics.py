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
* NEES / NIS, chi-square quantiles and average-NEES bounds live in :mod:`jaxslam.stats`
  (re-exported here); their decisions are stated there.
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
  invariant to any rigid transform of either trajectory.  Called eagerly (outside the caller's
  ``jit``), ``umeyama``, ``ate``, ``rpe`` and ``rpe_se2`` check their arguments and run a
  program compiled once per shape and static option (:func:`jaxslam.compilation.call_compiled`;
  op by op a first ``ate`` took 1.2 s and every later one 2.6 ms).
* Map error: landmark positions are compared by id after a rigid transform
  (the trajectory's ATE alignment, so map and path are judged in one frame,
  or the map's own Umeyama alignment); the RMSE of the position error.
* TUM format (for ``evo``): one pose per line, ``t tx ty tz qx qy qz qw``;
  planar poses get z = 0 and a yaw quaternion.
"""

from __future__ import annotations

import math
import warnings
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .compilation import call_compiled
from .errors import InputError
from .linalg import check_mask, check_numbers, check_real, check_scalar, check_whole_ids, float_array, to_jax, wrap_angle
from .stats import anees_bounds, chi2_ppf, chi2_ppf_np, mean_chi2_bounds, nees, nis  # noqa: F401 (re-exported)

__all__ = [
    "rmse",
    "rmse_norm",
    "rmse_norm_where",
    "nees",
    "nis",
    "chi2_ppf",
    "chi2_ppf_np",
    "mean_chi2_bounds",
    "anees_bounds",
    "STEPS_INSIDE_MIN",
    "steps_inside",
    "steps_inside_text",
    "percent_text",
    "consistency_verdict",
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

def _sqrt0(ms):
    """``sqrt(ms)`` of a mean square, with the gradient 0 (a subgradient) instead of NaN where
    ``ms`` is 0: an exact estimate's RMSE stays differentiable.  Same values (NaN stays NaN)."""
    zero = ms == 0
    return jnp.where(zero, 0.0, jnp.sqrt(jnp.where(zero, 1.0, ms)))


def rmse(err, axis=0):
    """Per-component root-mean-square error.

    Args:
        err: (T, d) errors (estimate − truth), in the state's units; any
            shape works, the mean runs over ``axis``.
        axis: axis (or tuple of axes) averaged over; default the time axis 0.

    Returns:
        ``sqrt(mean(err², axis))``, e.g. (d,) per-axis RMSE for (T, d) input; its gradient
        at zero error is 0 (was NaN), as for :func:`rmse_norm`, :func:`rmse_norm_where`,
        :func:`ate`, :func:`rpe` and :func:`rpe_se2`.  An integer ``err`` is read as floats;
        a complex one is an :class:`InputError`.
    """
    err = float_array(err, "err")
    return _sqrt0(jnp.mean(err * err, axis=axis))


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
    err = float_array(err, "err")
    return _sqrt0(jnp.mean(jnp.sum(err * err, axis=-1), axis=axis))


def rmse_norm_where(err, where):
    """:func:`rmse_norm` over the steps where ``where`` holds: ``sqrt(Σ_t w_t ‖err_t‖² / Σ_t w_t)``.

    ``err`` (T, d), ``where`` (T,) bool (e.g. a settled window).  NaN when no step is selected
    (a flight shorter than its window has no figure there, not 0).  jit/vmap-safe.

    ``where`` must be a mask (bool, or 0/1 integers) of ``err``'s shape without its last axis:
    :class:`InputError` naming it (a (1,) or (T, 1) mask was broadcast to a wrong figure, a float
    one was read as weights).
    """
    err = float_array(err, "err")
    if err.ndim < 1:
        raise InputError(f"err: expected shape (T, d), got {tuple(err.shape)}")
    check_mask(where, "where")
    if np.shape(where) != err.shape[:-1]:
        raise InputError(f"where: expected shape {tuple(err.shape[:-1])} (one flag per row of err), "
                         f"got {tuple(np.shape(where))}")
    w = jnp.asarray(where, err.dtype)
    n = jnp.sum(w)
    return jnp.where(n > 0, _sqrt0(jnp.sum(jnp.sum(err * err, axis=-1) * w) / jnp.maximum(n, 1)), jnp.nan)


# What a value outside its χ² bounds means, by kind of statistic: (below, above).
_OUTSIDE_MEANS = {
    "nees": ("below: conservative (covariance larger than the errors)",
             "above: over-confident (errors larger than the covariance)"),
    "nis": ("below: innovations smaller than predicted (R or P too large)",
            "above: innovations larger than predicted (R or P too small, or outliers)"),
}


# The per-step check (Bar-Shalom et al., ch. 5.4): a consistent filter's ANEES over the runs lies
# inside its per-step 95 % bounds at about 95 % of the steps.  The steps of one flight are
# correlated, so the count is not binomial; below this fraction the report says LOW (a rule of
# thumb with room for that correlation, not a test).
STEPS_INSIDE_MIN = 0.90


def steps_inside(per_step, bounds) -> float:
    """Fraction of steps whose per-step ANEES lies inside ``bounds`` = (lo, hi) (a NaN step counts
    as outside): the per-step check that :func:`steps_inside_text` puts in words.  NaN when a
    bound is not finite (no check possible); reversed bounds, or ``bounds`` that are not two
    numbers, are an :class:`InputError`."""
    lo, hi = _two_bounds(bounds)
    if not (math.isfinite(lo) and math.isfinite(hi)):
        return float("nan")
    if lo > hi:
        raise InputError(f"bounds: expected (lo, hi) with lo <= hi, got ({lo}, {hi})")
    a = np.asarray(per_step, float)
    return float(np.mean((a >= lo) & (a <= hi)))


def _two_bounds(bounds) -> tuple:
    """``bounds`` as the floats (lo, hi), else :class:`InputError` naming ``bounds`` (three
    values were a bare unpacking error)."""
    try:
        lo, hi = (float(b) for b in bounds)
    except (TypeError, ValueError):
        raise InputError(f"bounds: expected two numbers (lo, hi), got {bounds!r}"[:300]) from None
    return lo, hi


def steps_inside_text(fraction) -> str:
    """The per-step check in words: ``"96.2 % of steps inside (95 % expected): ok"``, ``... LOW``
    below :data:`STEPS_INSIDE_MIN`, or ``"undefined"`` without a finite fraction.  A time
    average inside the per-step bounds can hide steps far outside on both sides; this says so."""
    try:
        f = float(fraction)
    except (TypeError, ValueError):
        return "undefined"
    if not math.isfinite(f):
        return "undefined"
    return f"{percent_text(f)} of steps inside (95 % expected): " + ("ok" if f >= STEPS_INSIDE_MIN else "LOW")


def percent_text(fraction) -> str:
    """A fraction as ``"89.9 %"``, rounded down (0.8996 reads 89.9 %, never a LOW-looking 90.0 %);
    ``"-"`` without a finite value."""
    try:
        f = float(fraction)
    except (TypeError, ValueError):
        return "-"
    return f"{math.floor(1000 * f + 1e-9) / 10:.1f} %" if math.isfinite(f) else "-"


def consistency_verdict(value, bounds, kind: str | None = "nees") -> str:
    """A NEES/NIS statistic against its bounds, in words (the console report and the figures).

    Returns ``"ok"``, ``"OUTSIDE, below: conservative (covariance larger than the errors)"``
    (what the side means for ``kind`` ``"nees"`` or ``"nis"``; bare ``"OUTSIDE"`` for
    ``kind=None``), or ``"undefined"`` when the value or a bound is missing or non-finite.
    Reversed finite bounds are an :class:`InputError`, as in :func:`steps_inside` (a value
    between them read "OUTSIDE").
    """
    if kind is not None and kind not in _OUTSIDE_MEANS:
        raise InputError(f"kind: expected one of {sorted(_OUTSIDE_MEANS)} or None, got {kind!r}")
    try:
        v = float(value)
        bl = [float(b) for b in bounds]
    except (TypeError, ValueError):
        return "undefined"
    if len(bl) != 2:
        raise InputError(f"bounds: expected two numbers (lo, hi), got {bounds!r}"[:300])
    lo, hi = bl
    if not all(math.isfinite(x) for x in (v, lo, hi)):
        return "undefined"
    if lo > hi:
        raise InputError(f"bounds: expected (lo, hi) with lo <= hi, got ({lo}, {hi})")
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
        mean: (W,) mean of the values present (not NaN) in the window (NaN if none; an
            infinite value, a diverged run, makes it infinite, as in :func:`summarize`).
        count: (W,) int number of values averaged (runs × steps).
    """

    t_start: np.ndarray
    t_end: np.ndarray
    mean: np.ndarray
    count: np.ndarray


#: most windows :func:`windowed_mean` makes (unless ``t`` has more steps): 4 arrays of 10⁷
#: windows are 320 MB; a window of 1 µs over a 10⁶ s span asked for 7 TiB
_WINDOWS_MAX = 10_000_000


def _host_numbers(x, name: str) -> np.ndarray:
    """A host-side input as float64 NumPy: complex or non-numbers are an :class:`InputError`
    naming ``name`` (NumPy dropped the imaginary part with only a warning, or raised a bare
    ValueError)."""
    check_real(x, name)
    return check_numbers(x, name)


def windowed_mean(x, t, window_s: float) -> WindowedMean:
    """Average a per-step statistic (e.g. NEES) over time windows (host side).

    Windows are ``[t0 + k w, t0 + (k+1) w)`` from the first time ``t0``; the
    last window is closed and may be shorter.  For (R, T) input all runs of a
    window are pooled, so ``mean`` is the windowed ANEES and
    ``anees_bounds``-style bounds use ``mean_chi2_bounds(n·count, count)``.

    Args:
        x: (T,) or (R, T) values; NaN marks a missing value.
        t: (T,) finite nondecreasing times [s].
        window_s: finite window length [s] > 0, giving at most 10⁷ windows (or T, if
            more) over the span of ``t``.

    Returns:
        :class:`WindowedMean`.

    Raises:
        InputError: naming ``x``, ``t`` or ``window_s`` (a NaN or infinite time, an infinite
        window or one so short that the windows would not fit in memory used to fail inside
        NumPy or return NaN window starts).
    """
    x = _host_numbers(x, "x")
    t = _host_numbers(t, "t")
    if x.ndim == 1:
        x = x[None, :]
    if x.ndim != 2:
        raise InputError(f"x: expected shape (T,) or (R, T), got {np.shape(x)}")
    if t.ndim != 1 or t.shape[0] != x.shape[1]:
        raise InputError(f"t: expected shape ({x.shape[1]},), got {t.shape}")
    try:
        check_real(window_s, "window_s", allow_bool=False)
        window_s = check_scalar(window_s, "window_s", lower=0, strict=True)
    except InputError:
        raise InputError(f"window_s: must be a finite number > 0, got {window_s!r}") from None
    if t.size == 0:
        e = np.zeros(0)
        return WindowedMean(e, e, e, np.zeros(0, dtype=np.int64))
    if not np.all(np.isfinite(t)):
        raise InputError("t: the times must be finite (NaN or inf found)")
    if np.any(np.diff(t) < 0):
        raise InputError("t: must be nondecreasing")
    t0 = t[0]
    n_float = float(np.ceil((t[-1] - t0) / window_s - 1e-9))  # inf for a tiny window: no OverflowError
    if n_float > max(_WINDOWS_MAX, t.size):
        raise InputError(f"window_s: {window_s:g} s splits the {t[-1] - t0:g} s span of t into {n_float:g} "
                         f"windows (at most {max(_WINDOWS_MAX, t.size)}): use a longer window")
    n_win = max(1, int(n_float))
    idx = np.minimum(np.floor((t - t0) / window_s + 1e-12).astype(np.int64), n_win - 1)
    present = ~np.isnan(x)  # NaN marks a missing value; an inf (a diverged run) stays in
    vals = np.where(present, x, 0.0)
    sums = np.zeros(n_win)
    counts = np.zeros(n_win, dtype=np.int64)
    np.add.at(sums, idx, vals.sum(axis=0))
    np.add.at(counts, idx, present.sum(axis=0))
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
        with linear interpolation); NaN propagates to mean/median/p95/max.  An infinite run
        (a diverged one) is kept: a p95 between a finite value and +inf is +inf (NumPy's
        interpolation gave NaN).
    """
    v = _host_numbers(per_run, "per_run").reshape(-1)
    if v.size == 0:
        raise InputError("per_run: empty")
    with np.errstate(invalid="ignore"):
        return {
            "mean": float(np.mean(v)),
            "median": float(np.median(v)),
            "p95": _percentile(v, 95.0),
            "max": float(np.max(v)),
            "per_run": [float(a) for a in v],
        }


def _percentile(v: np.ndarray, q: float) -> float:
    """``np.percentile(v, q)`` (linear interpolation), except where NumPy forms ``inf − inf``
    between an infinite and a finite neighbour: there the infinite end is the answer (both
    infinite, of opposite signs: NaN).  NaN in ``v`` gives NaN."""
    p = float(np.percentile(v, q))
    if not np.isnan(p) or np.isnan(v).any():
        return p
    lo = float(np.percentile(v, q, method="lower"))
    hi = float(np.percentile(v, q, method="higher"))
    if lo == hi:
        return lo
    if math.isinf(lo) and math.isinf(hi):
        return math.nan
    return lo if math.isinf(lo) else hi


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

    Integer points are read as floats (they were kept as integers and the scale truncated:
    1 for 1.5).  Two (N, d) arrays of one shape, N ≥ 1, and real dtypes are expected:
    :class:`InputError` naming ``src`` / ``dst`` otherwise (static checks).
    """
    src = float_array(src, "src")
    dst = float_array(dst, "dst")
    for name, a in (("src", src), ("dst", dst)):
        if a.ndim != 2 or a.shape[0] < 1:
            raise InputError(f"{name}: expected shape (N, d), one point per row, got {tuple(a.shape)}")
    if src.shape != dst.shape:
        raise InputError(f"src and dst: the same (N, d) shape expected (corresponding points), got "
                         f"{tuple(src.shape)} and {tuple(dst.shape)}")
    dtype = jnp.result_type(src, dst)
    ws = bool(with_scale)  # the key names all the program closes over: the dtype comes with the arguments
    return call_compiled(("metrics.umeyama", ws), lambda a, b: _umeyama(a, b, ws),
                         (src.astype(dtype), dst.astype(dtype)), after="auto")


def _umeyama(src, dst, with_scale: bool):
    """:func:`umeyama`'s computation (two checked (N, d) arrays of one floating dtype)."""
    dtype = src.dtype
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
        # A source without spread (every point equal) has no scale: any s maps it onto mu_d,
        # so s = 1 there instead of 0/0 (a NaN ATE for an estimate that never moved).
        # (In 1-D the reflection guard makes sum(D e) = -D: a mirrored estimate.  A similarity
        # has s >= 0, and the best s >= 0 is then 0.)
        s = jnp.where(var_s > 0, jnp.maximum(jnp.sum(D * e), 0) / jnp.where(var_s > 0, var_s, 1), 1).astype(dtype)
    else:
        s = jnp.ones((), dtype)
    t = mu_d - s * R @ mu_s
    return R, t, s


def _trajectories(est_pos, true_pos):
    """Two (T, d) position arrays of one trajectory, d in 1..3 (static checks):
    :class:`InputError` naming the argument (an off-by-one length or a transposed (d, T) array
    would otherwise broadcast into a wrong number)."""
    est, tru = float_array(est_pos, "est_pos"), float_array(true_pos, "true_pos")
    for name, a in (("est_pos", est), ("true_pos", tru)):
        if a.ndim != 2 or not 1 <= a.shape[1] <= 3 or a.shape[0] < 1:
            raise InputError(f"{name}: expected shape (T, d) with d in 1..3 (one position per row), "
                             f"got {tuple(a.shape)}")
    if est.shape != tru.shape:
        raise InputError(f"est_pos and true_pos: the same (T, d) shape expected (one estimate per "
                         f"true position), got {tuple(est.shape)} and {tuple(tru.shape)}")
    return est, tru


def _lag(lag) -> int:
    if isinstance(lag, bool) or not isinstance(lag, (int, np.integer)):
        raise InputError(f"lag: must be an int (a number of steps), got {lag!r}")
    return int(lag)


def ate(est_pos, true_pos, align: str = "rigid"):
    """Absolute trajectory error: position RMSE after alignment.

    Args:
        est_pos: (T, d) estimated positions [m].
        true_pos: (T, d) true positions [m].
        align: ``"rigid"`` (rotation + translation, default), ``"sim"`` (with
            scale) or ``"none"``.

    Returns:
        Scalar ``sqrt(mean_t ‖s R p̂_t + t − p_t‖²)`` [m].

    Gradient: the alignment is held fixed (``stop_gradient``).  It minimises this same error, so
    at its optimum the error's derivative with respect to (R, t, s) is zero and the gradient is
    the partial one (envelope theorem): the same values as differentiating through the SVD
    (checked against finite differences), and finite where that is NaN — a trajectory with no
    spread (an estimate that never moved), whose optimal rotation is not unique.
    """
    if align not in ("rigid", "sim", "none"):
        raise InputError(f"align: expected 'rigid', 'sim' or 'none', got {align!r}")
    est, tru = _trajectories(est_pos, true_pos)
    return call_compiled(("metrics.ate", align), lambda e, t: _ate(e, t, align), (est, tru), after="auto")


def _ate(est, tru, align: str):
    if align != "none":
        R, t, s = jax.lax.stop_gradient(umeyama(est, tru, with_scale=(align == "sim")))
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
    lag = _lag(lag)
    est, tru = _trajectories(est_pos, true_pos)
    if lag < 1 or lag >= est.shape[0]:
        raise InputError(f"lag: must be in [1, {est.shape[0] - 1}], got {lag}")
    return call_compiled(("metrics.rpe", lag), lambda e, t: _rpe(e, t, lag), (est, tru), after="auto")


def _rpe(est, tru, lag: int):
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
    lag = _lag(lag)
    est = float_array(est_pose, "est_pose")
    tru = float_array(true_pose, "true_pose")
    if est.ndim != 2 or est.shape[1] != 3 or est.shape != tru.shape:
        raise InputError(f"rpe_se2: expected two (T, 3) pose arrays, got {est.shape} and {tru.shape}")
    if lag < 1 or lag >= est.shape[0]:
        raise InputError(f"lag: must be in [1, {est.shape[0] - 1}], got {lag}")
    return call_compiled(("metrics.rpe_se2", lag), lambda e, t: _rpe_se2(e, t, lag), (est, tru), after="auto")


def _rpe_se2(est, tru, lag: int):
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
    return _sqrt0(jnp.mean(etx ** 2 + ety ** 2)), _sqrt0(jnp.mean(eang ** 2))


def apply_transform(points, R, t, s=1.0):
    """``s R p + t`` for each row of ``points`` (N, d) — e.g. the ATE alignment of :func:`umeyama`."""
    return s * to_jax(points) @ to_jax(R).T + to_jax(t)


class MapError(NamedTuple):
    """Landmark map error after alignment: per-landmark errors [m], their RMSE and max, ids compared."""

    errors: np.ndarray
    rmse: float
    max: float
    ids: np.ndarray


def _ids(ids, name: str) -> np.ndarray:
    """Landmark ids as a flat NumPy array of numbers (an integer dtype kept: large ids stay
    exact); strings, complex, bool or ragged ids are an :class:`InputError` naming ``name``."""
    try:
        a = np.asarray(ids)
    except (TypeError, ValueError):  # a ragged list
        a = None
    if a is None or a.dtype.kind not in "iuf":
        raise InputError(f"{name}: expected numeric landmark ids, got {ids!r}"[:300])
    return a.reshape(-1)


def map_error(est_lm, est_ids, true_lm, true_ids, transform=None, *,
              names=("est_lm", "est_ids", "true_lm", "true_ids")) -> MapError:
    """Map error of landmarks matched by id, after a rigid alignment.

    Args:
        est_lm: (M, d) estimated landmark positions; est_ids: (M,) their ids
            (entries with id < 0 or non-finite positions are ignored).
        true_lm: (L, d) true positions; true_ids: (L,).
        transform: ``(R, t)`` or ``(R, t, s)`` to apply to the estimates (e.g.
            the trajectory's ATE alignment), or None to align the matched
            landmarks themselves by :func:`umeyama` (needs ≥ d of them).
        names: the names the messages give ``est_lm``, ``est_ids``, ``true_lm`` and
            ``true_ids``, in that order (a caller passing its own arguments names them, e.g.
            ``("lm", "lm_ids", "lm_true", "lm_true_ids")``).

    Raises:
        InputError: shapes disagree, an id repeats in ``true_ids`` (or among the rows of
        ``est_ids`` in use), ``transform`` is not (R, t[, s]) of the landmarks' size, no estimated id is in
        ``true_ids``, or an id is not a whole number (a fractional or non-finite one in
        ``true_ids``, or in ``est_ids`` on a row in use: it was truncated onto another id).
    """
    if (not isinstance(names, (tuple, list)) or len(names) != 4
            or not all(isinstance(n, str) and n for n in names)):
        raise InputError(f"names: expected four argument names (est_lm, est_ids, true_lm, true_ids), "
                         f"got {names!r}"[:300])
    n_est, n_eid, n_tru, n_tid = names
    est = _host_numbers(est_lm, n_est)
    tru = _host_numbers(true_lm, n_tru)
    eid = _ids(est_ids, n_eid)
    tid = _ids(true_ids, n_tid)
    if est.ndim != 2 or tru.ndim != 2 or est.shape[1] != tru.shape[1]:
        raise InputError(f"{n_est} and {n_tru}: expected (M, d) and (L, d) landmarks of one size d, got "
                         f"{est.shape} and {tru.shape}")
    if eid.shape[0] != est.shape[0] or tid.shape[0] != tru.shape[0]:
        raise InputError(f"{n_eid} and {n_tid}: one id per landmark row expected ({est.shape[0]} rows of {n_est}, "
                         f"{tru.shape[0]} of {n_tru}), got {eid.shape[0]} and {tid.shape[0]} ids")
    check_whole_ids(tid, n_tid)
    # rows ignored (id < 0, or a position not finite) may hold any id; NaN is not < 0: checked
    check_whole_ids(eid, n_eid, used=~(eid < 0) & np.all(np.isfinite(est), axis=1))
    uniq, counts = np.unique(tid, return_counts=True)
    if np.any(counts > 1):
        raise InputError(f"{n_tid}: each true landmark id must appear once, repeated: "
                         f"{[int(i) for i in uniq[counts > 1]][:10]}")
    used = (eid >= 0) & np.all(np.isfinite(est), axis=1)
    uniq, counts = np.unique(eid[used], return_counts=True)
    if np.any(counts > 1):  # one true landmark's error would count twice
        raise InputError(f"{n_eid}: each id may appear once among the rows in use, repeated: "
                         f"{[int(i) for i in uniq[counts > 1]][:10]}")
    if transform is not None:
        transform = _check_transform(transform, est.shape[1])
    lookup = {int(i): k for k, i in enumerate(tid)}
    pairs = [(k, lookup[int(i)]) for k, i in enumerate(eid) if used[k] and int(i) in lookup]
    if not pairs:
        raise InputError(f"{n_eid}: no estimated landmark id matches an id of {n_tid} (of the {int(used.sum())} "
                         f"rows of {n_est} in use: id >= 0 and a finite position); no landmark to compare")
    a = est[[k for k, _ in pairs]]
    b = tru[[j for _, j in pairs]]
    if transform is None:
        if len(pairs) < a.shape[1]:
            raise InputError(f"{n_eid}: {len(pairs)} estimated landmark(s) match an id of {n_tid}; aligning "
                             f"{a.shape[1]}-D landmarks needs {a.shape[1]} (or give transform)")
        R, t, s = umeyama(a, b)
    else:
        R, t, s = transform
    e = np.linalg.norm(np.asarray(apply_transform(a, R, t, s)) - b, axis=1)
    return MapError(e, float(np.sqrt(np.mean(e ** 2))), float(np.max(e)),
                    np.asarray([int(eid[k]) for k, _ in pairs]))


def _check_transform(transform, d: int) -> tuple:
    """``transform`` = (R, t) or (R, t, s) for d-dimensional points: R (d, d), t (d,), s a
    finite scalar; else :class:`InputError` naming ``transform``."""
    if not isinstance(transform, (tuple, list)) or len(transform) not in (2, 3):
        raise InputError(f"transform: expected (R, t) or (R, t, s), got {type(transform).__name__}"
                         + (f" of {len(transform)}" if isinstance(transform, (tuple, list)) else ""))
    R = _host_numbers(transform[0], "transform R")
    t = _host_numbers(transform[1], "transform t")
    if R.shape != (d, d) or t.shape != (d,):
        raise InputError(f"transform: expected R ({d}, {d}) and t ({d},) for {d}-D landmarks, got "
                         f"{R.shape} and {t.shape}")
    s = 1.0
    if len(transform) == 3:
        s = _host_numbers(transform[2], "transform s")
        if s.shape != () or not np.isfinite(s):
            raise InputError(f"transform: expected a finite scalar scale s, got {transform[2]!r}"[:300])
        s = float(s)
    return R, t, s


def interp_poses(t_query, t, poses):
    """Linear interpolation of planar poses (x, y, θ) at ``t_query`` (host side, NumPy).

    The heading is interpolated on the unwrapped angle and re-wrapped.  Query
    times outside ``[t[0], t[-1]]`` give NaN (ground truth must not be
    extrapolated).
    """
    tq = np.asarray(t_query, np.float64)
    t = np.asarray(t, np.float64)
    P = np.asarray(poses, np.float64)
    if tq.ndim != 1 or t.ndim != 1:
        raise InputError(f"t_query and t: 1-D arrays of times expected, got shapes {tq.shape} and {t.shape}")
    if P.ndim != 2 or P.shape[0] != t.shape[0] or t.shape[0] < 1:
        raise InputError(f"poses: expected one (d,) row per time of t ({t.shape[0]}), got shape {P.shape}")
    if not np.all(np.isfinite(t)) or np.any(np.diff(t) < 0):
        raise InputError("t: the pose times must be finite and non-decreasing (np.interp would "
                         "return wrong poses otherwise)")
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
        yaw: optional (T,) heading [rad] (planar); quat_xyzw: optional (T, 4), one
            quaternion per row (a (4, T) array is an :class:`InputError`, not reshaped).
            With neither, the identity orientation is written.
    """
    t = _host_numbers(t, "t").reshape(-1)
    if t.size == 0:  # a header alone, which read_tum (and evo) refuse
        raise InputError("t: no poses to write (T = 0)")
    p = _host_numbers(positions, "positions")
    if p.ndim != 2 or p.shape[0] != t.shape[0] or p.shape[1] not in (2, 3):
        raise InputError(f"write_tum: positions must be (T, 2|3) with T = {t.shape[0]}, got {p.shape}")
    if p.shape[1] == 2:
        p = np.concatenate([p, np.zeros((p.shape[0], 1))], axis=1)
    if quat_xyzw is not None and yaw is not None:
        raise InputError("write_tum: give yaw or quat_xyzw, not both")
    if quat_xyzw is not None:
        q = _host_numbers(quat_xyzw, "quat_xyzw")
        if q.shape != (t.shape[0], 4):  # a (4, T) array was reshaped into scrambled quaternions
            raise InputError(f"quat_xyzw: expected shape ({t.shape[0]}, 4), one (x, y, z, w) per time, "
                             f"got {q.shape}")
    else:
        h = np.zeros_like(t) if yaw is None else _host_numbers(yaw, "yaw").reshape(-1)
        if h.shape != t.shape:
            raise InputError(f"write_tum: yaw must be (T,) with T = {t.shape[0]}, got {h.shape}")
        q = np.stack([np.zeros_like(h), np.zeros_like(h), np.sin(h / 2), np.cos(h / 2)], axis=1)
    from jaxslam.files import atomic_write

    table = np.concatenate([t[:, None], p, q], axis=1)
    return atomic_write(path, lambda f: np.savetxt(f, table, fmt="%.9f",
                                                   header="timestamp tx ty tz qx qy qz qw"))


def read_tum(path):
    """Read a TUM trajectory: ``(t (T,), positions (T, 3), quat_xyzw (T, 4))``.

    A missing file, a folder, an unreadable file or lines that are not 8 numbers each are an
    :class:`InputError` naming ``path`` (NumPy's bare errors before).
    """
    try:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", "loadtxt: input contained no data", UserWarning)
            a = np.loadtxt(path, comments="#", ndmin=2)
    except FileNotFoundError:
        raise InputError(f"{path}: TUM file not found") from None
    except IsADirectoryError:
        raise InputError(f"{path}: is a folder, not a TUM file") from None
    except OSError as e:
        raise InputError(f"{path}: cannot read the TUM file: {e.strerror or e}") from None
    except ValueError as e:  # a ragged line or a word where a number belongs
        raise InputError(f"{path}: not a TUM trajectory (8 numbers per line): {e}"[:400]) from None
    if a.size == 0:
        raise InputError(f"{path}: no trajectory lines (only comments or nothing)")
    if a.shape[1] != 8:
        raise InputError(f"{path}: TUM lines have 8 columns, found {a.shape[1]}")
    return a[:, 0], a[:, 1:4], a[:, 4:8]
