"""Least-squares trilateration: a point from its ranges to known points (paper 003 eq. 22-26).

Given K known points a_k (poses of a vehicle, or surveyed anchors) and the
measured distances d_k from them to an unknown point x, the circle equations
‖x − a_k‖² = d_k² (eq. 22) are made linear by subtracting the first one
(eq. 25):

    2 (a_k − a_1)ᵀ x = d_1² − d_k² + ‖a_k‖² − ‖a_1‖²,   k = 2..K      (eq. 26: A x = b)

and solved in the least-squares sense (eq. 24).  **Erratum**: the paper's
eq. 25-26 write the rows of A as 2 (a_1 − a_k)ᵀ with this b; subtracting the
k-th circle equation from the first gives 2 (a_k − a_1)ᵀ x = b (the paper's
sign yields the point reflected through the origin — checked on noise-free
ranges in the tests).  Everything here is pure,
jit- and vmap-safe, and follows the inputs' dtype; nothing raises inside
``jit`` — degenerate geometry is reported by an ``ok`` flag and the
``DEGENERATE`` status bit, and the returned estimate is always finite.

Decisions (paper silent or wrong):

* **Masks.**  Invalid samples (mask False, non-finite or non-positive range)
  become zero rows of A and b, which leaves the least-squares solution of the
  remaining rows unchanged; the reference row of eq. 26 is the first *valid*
  sample.  Static shapes, so a log with dropouts never recompiles.
* **Solver.**  The minimum-norm least-squares solution through an SVD of A
  with singular values below ``rcond · s_max`` dropped (``numpy.linalg.lstsq``
  semantics, ``rcond`` = machine epsilon × max(K, d) by default).  A
  rank-deficient A therefore yields a finite (minimum-norm) point with
  ``ok = False`` instead of a NaN or a garbage inverse.
* **Degeneracy** (collinear or coincident points in 2D, coplanar in 3D): ``ok``
  requires (i) at least ``min_points`` valid samples (default d + 1),
  (ii) full column rank of A (smallest singular value above ``cond_tol`` times
  the largest), and (iii) the smallest principal standard
  deviation of the valid points (``spread``) ≥ ``min_spread`` [m]; a caller
  that wants a *usable* estimate, not just a defined one, sets ``min_spread``
  to a few range-noise standard deviations (delayed initialisation).
* **Covariance.**  With a range variance σ², b carries the noise of the
  squared ranges, var(d_k²) ≈ 4 d_k² σ² + 2σ⁴, and every row shares the
  reference's; so Σ_b = v_1 𝟙𝟙ᵀ + diag(v_k) and cov(x̂) = A⁺ Σ_b A⁺ᵀ (linear
  propagation; the known points are taken as exact — a caller adds their
  uncertainty).
* **Derivatives.**  A filter differentiates through its trilaterations (noise tuning through a
  delayed initialisation), also through those that are not ready.  A well-conditioned system
  is solved through its QR factors (the same solution as the SVD's, to rounding), whose
  derivative is finite wherever A has full rank — an SVD's divides by s_i² − s_j², NaN for
  equal singular values (three points at a right angle).  A degenerate one is solved by the
  SVD of A held constant, on an identity in place of A for the QR, and distances use a norm
  with a finite derivative at 0; ``spread`` is held constant (it is only compared).  No
  derivative is NaN, whatever the input.
* **Points on a line** (:func:`trilaterate_line`, paper 003's forced
  straight-line start-up, positions (−d(k), 0)): A of eq. 26 then has a zero
  second column, so eq. 26 fixes only the along-line coordinate u (MATLAB's
  ``A\\b``, which the paper uses, returns the basic solution y = 0 with a rank
  warning).  jaxslam solves u from eq. 26's first column and the offset from
  the line from the mean of y² = d_k² − (u − x_k)²; the sign of y is not
  observable from points on a line (a range-only map is defined up to a
  reflection as well as a rigid motion), so the caller chooses it (``side``),
  which fixes the reflection of the map frame.  y² ≤ 0 (the point on the line)
  is flagged ``DEGENERATE`` and returns y = 0.
"""

from __future__ import annotations

from typing import NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np

from .. import errors
from ..compilation import call_compiled
from ..errors import InputError
from ..linalg import check_mask, is_concrete, list_array, safe_norm

__all__ = [
    "TrilaterationResult",
    "linear_system",
    "trilaterate",
    "trilaterate_line",
    "point_spread",
]


class TrilaterationResult(NamedTuple):
    """Result of a least-squares trilateration.

    position: (d,) estimate [m] (always finite; minimum-norm when degenerate).
    cov: (d, d) propagated covariance [m²] (zeros when no range variance is given).
    ok: () bool — enough valid samples, full rank, spread ≥ ``min_spread``.
    status: () int32 bit flags (``DEGENERATE`` when not ok, ``MASKED_INPUT``
      when samples were dropped as invalid).
    n_used: () int32 valid samples.
    spread: () smallest principal standard deviation of the valid points [m].
    residual_max: () max_k |‖x̂ − a_k‖ − d_k| over the valid samples [m].
    """

    position: jax.Array
    cov: jax.Array
    ok: jax.Array
    status: jax.Array
    n_used: jax.Array
    spread: jax.Array
    residual_max: jax.Array


def _valid(points, ranges, mask):
    """Rows that can enter a fit: a finite range > 0 from a finite point (and ``mask``)."""
    ok = jnp.isfinite(ranges) & (jnp.where(jnp.isfinite(ranges), ranges, 0.0) > 0)
    ok = ok & jnp.all(jnp.isfinite(points), axis=-1)
    if mask is not None:
        ok = ok & mask
    return ok


def _bad_input_flag(points, ranges, mask):
    # A sample offered (mask True) whose range is NaN/Inf or <= 0, or whose point is not finite,
    # is bad input, not a choice.
    offered = jnp.ones(ranges.shape, bool) if mask is None else mask
    bad = offered & ~_valid(points, ranges, None)
    return jnp.where(jnp.any(bad), errors.MASKED_INPUT, 0)


def _check_number(value, name: str, what: str, shapes=((),)):
    """Static: ``value`` numeric (int or float; a bool or a string is no number) of one of
    ``shapes``; else :class:`InputError` naming ``name``."""
    dt = getattr(value, "dtype", None)
    if dt is None:
        try:
            dt = np.asarray(value).dtype
        except (TypeError, ValueError):
            dt = None
    if dt is None or np.dtype(dt).kind not in "iuf" or np.shape(value) not in shapes:
        raise InputError(f"{name}: expected {what}, got {value!r}"[:300])


def _check_inputs(points, ranges, mask, range_var=None, points_name: str = "points", mask_name: str = "mask"):
    """Shapes (static: free under ``jit`` and ``vmap``) and, when concrete, ``range_var`` ≥ 0:
    :class:`InputError` naming the argument (a (1,) mask or range broadcast over every sample, a
    negative σ² gave a negative covariance with ``ok``)."""
    ps = np.shape(points)
    want_d = points_name == "points"
    if (len(ps) != 2 or ps[1] < 1) if want_d else len(ps) != 1:
        raise InputError(f"{points_name}: expected shape {'(K, d)' if want_d else '(K,)'}, got {ps}")
    K = ps[0]
    if K < 1:
        raise InputError(f"{points_name}: no sample (K = 0)")
    if np.shape(ranges) != (K,):
        raise InputError(f"ranges: expected shape ({K},) (one per point), got {np.shape(ranges)}")
    if mask is not None and np.shape(mask) != (K,):
        raise InputError(f"{mask_name}: expected shape ({K},) (one per point), got {np.shape(mask)}")
    check_mask(mask, mask_name)  # concrete: bool or 0/1 integers (0.5 or 2 is no mask)
    if range_var is not None:
        if np.shape(range_var) not in ((), (K,)):
            raise InputError(f"range_var: expected a scalar or ({K},), got shape {np.shape(range_var)}")
        _check_number(range_var, "range_var", f"range variances [m²] (a number or ({K},) numbers)",
                      ((), (K,)))
        if is_concrete(range_var):
            v = np.asarray(range_var, dtype=float)
            if not np.all(np.isfinite(v) & (v >= 0)):
                raise InputError(f"range_var: expected finite range variances >= 0 [m²], got {range_var!r}")


def _dtype_of(points, ranges):
    dt = jnp.result_type(points, ranges)
    return dt if jnp.issubdtype(dt, jnp.floating) else jnp.result_type(float)


def linear_system(points, ranges, mask=None):
    """Rows of eq. 26 for every sample, with the first valid sample as reference.

    Paper 003, eq. 25-26 (sign of A corrected: rows 2 (a_k − a_1)ᵀ, b_k = d_1² − d_k² +
    ‖a_k‖² − ‖a_1‖²).  points: (K, d) known positions a_k [m]; ranges: (K,)
    measured distances d_k [m]; mask: optional (K,) bool (a row with a non-finite point or
    range, or a range ≤ 0, is invalid whatever the mask says).  Returns
    ``(A (K, d), b (K,), valid (K,) bool, ref ())`` where the reference row and
    the invalid rows are zero (they do not change the least-squares solution).
    """
    dtype = _dtype_of(points, ranges)
    points = jnp.asarray(points, dtype)
    ranges = jnp.asarray(ranges, dtype)
    valid = _valid(points, ranges, mask)
    d = jnp.where(valid, ranges, 0.0)
    p = jnp.where(valid[:, None], points, 0.0)
    ref = jnp.argmax(valid)
    a1 = p[ref]
    d1 = d[ref]
    use = valid & (jnp.arange(valid.shape[0]) != ref)
    A = 2.0 * (p - a1[None, :])  # eq. 26 with its sign corrected (module docstring)
    b = d1 * d1 - d * d + jnp.sum(p * p, axis=1) - jnp.sum(a1 * a1)
    A = jnp.where(use[:, None], A, 0.0)
    b = jnp.where(use, b, 0.0)
    return A, b, valid, ref


def point_spread(points, weights):
    """Smallest principal standard deviation [m] of the points with weight 1 (0 = unused).

    points: (K, d); weights: (K,) 0/1.  sqrt(λ_min) of the centred second moment.
    """
    w = weights.astype(points.dtype)
    n = jnp.maximum(jnp.sum(w), 1.0)
    mu = jnp.sum(points * w[:, None], axis=0) / n
    c = (points - mu) * w[:, None]
    C = c.T @ c / n
    lam = jnp.linalg.eigvalsh(0.5 * (C + C.T))
    return jnp.sqrt(jnp.clip(lam[0], 0.0))


def _lstsq(A, b, rcond, cond_tol):
    """Least squares; returns (x, pinv (d, K), well_conditioned).

    Well conditioned (smallest singular value > ``cond_tol`` · largest): x = R⁻¹ Qᵀ b from the
    QR factors of A — the same solution as the SVD's to rounding, with a derivative that is
    finite wherever A has full rank (the SVD's divides by s_i² − s_j², infinite for equal
    singular values).  Otherwise: the minimum-norm solution by the SVD (singular values ≤
    ``rcond`` · largest cut) of A held constant under differentiation (a degenerate fit, flagged
    by the caller; its derivative with respect to b stays).  The QR runs on an identity in
    place of a degenerate A, so neither branch's derivative is ever NaN.
    """
    K, d = A.shape
    if K < d:  # fewer rows than unknowns (static): zero rows change no solution, and the QR's R is
        # square (a K×d R made solve_triangular raise inside jit); the fit is then rank-deficient
        A = jnp.concatenate([A, jnp.zeros((d - K, d), A.dtype)], axis=0)
        x, pinv, good = _lstsq(A, jnp.concatenate([b, jnp.zeros((d - K,) + b.shape[1:], b.dtype)]), rcond,
                               cond_tol)
        return x, pinv[:, :K], good
    U, sv, Vt = jnp.linalg.svd(jax.lax.stop_gradient(A), full_matrices=False)
    smax = sv[0]
    good = (sv[-1] > cond_tol * smax) & (smax > 0)
    Q, R = jnp.linalg.qr(jnp.where(good, A, jnp.eye(K, d, dtype=A.dtype)))
    pinv_qr = jax.scipy.linalg.solve_triangular(R, Q.T, lower=False)
    keep = sv > rcond * smax
    s_inv = jnp.where(keep, 1.0 / jnp.where(keep, sv, 1.0), 0.0)
    pinv = jnp.where(good, pinv_qr, (Vt.T * s_inv[None, :]) @ U.T)
    return pinv @ b, pinv, good


def trilaterate(points, ranges, mask=None, range_var=None, min_points: Optional[int] = None,
                min_spread=0.0, rcond=None, cond_tol=None) -> TrilaterationResult:
    """Least-squares trilateration of one point from K known points (paper 003 eq. 22-26).

    The general multi-point initialiser: works for any K ≥ d + 1 known points
    in general position (vehicle poses along a curved path, surveyed anchors).

    Args:
      points: (K, d) known positions a_k [m] (d = 2 in paper 003; 3 works too).
      ranges: (K,) measured distances d_k [m]; non-finite or ≤ 0 entries are dropped, as are
        rows whose point is not finite (both set ``MASKED_INPUT`` when offered by ``mask``).
      mask: optional (K,) bool, False drops a sample.
      range_var: optional σ² [m²] of each range, for the covariance (module docstring); a
        concrete negative or non-finite one is an :class:`InputError`, a traced one makes ``ok``
        False.
      min_points: minimum of valid samples for ``ok`` (default d + 1; may be traced: only compared).
      min_spread: smallest principal standard deviation of the valid points
        required for ``ok`` [m] (0: only rank is checked).
      rcond: relative singular-value cut-off of the solve (default eps · max(K, d),
        as ``numpy.linalg.lstsq``).
      cond_tol: A counts as rank deficient (collinear points) when its smallest
        singular value is ≤ ``cond_tol`` · largest (default sqrt(eps): 1.5e-8 in
        float64, 3.5e-4 in float32); such a solve is still returned, with ok False.

    Returns:
      :class:`TrilaterationResult`.  Called eagerly it is compiled once per shape
      (:func:`jaxslam.compilation.call_compiled`; op by op the first call took 3 s).
    """
    points = list_array(points, "points")
    ranges = list_array(ranges, "ranges")
    range_var = list_array(range_var, "range_var")
    _check_inputs(points, ranges, mask, range_var)
    if min_points is not None:
        _check_number(min_points, "min_points", "a number of valid samples (an int)")
    _check_number(min_spread, "min_spread", "a spread [m] (a number)")
    mask = list_array(mask, "mask")  # an array: a list of bools would join the program's key

    def solve(opts, points, ranges):
        return _trilaterate(points, ranges, *opts)

    return call_compiled(("trilateration.trilaterate",), solve, (points, ranges),
                         (mask, range_var, min_points, min_spread, rcond, cond_tol), after="auto")


def _trilaterate(points, ranges, mask, range_var, min_points, min_spread, rcond, cond_tol):
    """:func:`trilaterate`'s computation (the values were checked by the caller)."""
    dtype = _dtype_of(points, ranges)
    points = jnp.asarray(points, dtype)
    ranges = jnp.asarray(ranges, dtype)
    K, d = points.shape
    if min_points is None:
        min_points = d + 1
    eps = float(jnp.finfo(dtype).eps)
    if rcond is None:
        rcond = eps * max(K, d)
    if cond_tol is None:
        cond_tol = eps ** 0.5
    A, b, valid, ref = linear_system(points, ranges, mask)
    x, pinv, full_rank = _lstsq(A, b, jnp.asarray(rcond, dtype), jnp.asarray(cond_tol, dtype))
    n_used = jnp.sum(valid).astype(jnp.int32)
    # only compared (ok): held constant, so its eigenvalue derivative (NaN for equal ones) never enters
    spread = point_spread(jax.lax.stop_gradient(jnp.where(valid[:, None], points, 0.0)), valid)
    ok = (n_used >= min_points) & full_rank & (spread >= jnp.asarray(min_spread, dtype))
    ok = ok & jnp.all(jnp.isfinite(x))
    if range_var is not None and not is_concrete(range_var):
        # a traced negative or NaN σ² (a concrete one is refused) gave a negative or NaN cov with ok
        rv = jnp.asarray(range_var)
        ok = ok & jnp.all(jnp.isfinite(rv) & (rv >= 0))
    x = jnp.where(jnp.isfinite(x), x, 0.0)
    rng = jnp.where(valid, ranges, 0.0)
    dist = safe_norm(x[None, :] - points, axis=1)
    residual_max = jnp.max(jnp.where(valid, jnp.abs(dist - rng), 0.0))
    if range_var is None:
        cov = jnp.zeros((d, d), dtype)
    else:
        s2 = jnp.asarray(range_var, dtype)
        v = jnp.where(valid, 4.0 * rng * rng * s2 + 2.0 * s2 * s2, 0.0)
        use = valid & (jnp.arange(K) != ref)
        u = use.astype(dtype)
        # Σ_b = v_ref 𝟙𝟙ᵀ + diag(v_k) on the used rows (every row contains d_ref²).
        g = pinv @ u  # A⁺ 𝟙
        cov = v[ref] * jnp.outer(g, g) + (pinv * (v * u)[None, :]) @ pinv.T
        cov = 0.5 * (cov + cov.T)
    status = jnp.where(ok, 0, errors.DEGENERATE) | _bad_input_flag(points, ranges, mask)
    return TrilaterationResult(position=x, cov=cov, ok=ok, status=jnp.asarray(status, jnp.int32),
                               n_used=n_used, spread=spread, residual_max=residual_max)


def trilaterate_line(xs, ranges, mask=None, side=1.0, min_points: int = 3,
                     min_baseline=0.0) -> TrilaterationResult:
    """Trilateration from points on a straight line (x_k, 0): paper 003's start-up, eq. 22-26.

    The along-line coordinate u comes from eq. 26 (its only non-zero column);
    the offset from the line from the mean of y² = d_k² − (u − x_k)², with the
    sign ``side`` (±1) chosen by the caller (module docstring).

    Args:
      xs: (K,) positions along the line [m] (the paper's −d(k)).
      ranges: (K,) measured distances to the unknown point [m].
      mask: optional (K,) bool.
      side: ±1, sign of the returned y (the reflection gauge of the map); a concrete other
        value is an :class:`InputError`, a traced one makes ``ok`` False.
      min_points: minimum of valid samples (two unknowns u, y²: ≥ 2; default 3; may be traced).
      min_baseline: minimum standard deviation of the valid x_k [m] (0: only
        distinct points are required).

    Returns:
      :class:`TrilaterationResult` with ``position`` (2,) = (u, y); ``cov`` is
      zero (the paper sets this variance from ``residual_max``); ``spread`` is
      the standard deviation of the valid x_k; ``ok`` is False (and
      ``DEGENERATE`` set) with too few samples, no baseline, or y² ≤ 0.  Called eagerly it
      is compiled once per shape (:func:`jaxslam.compilation.call_compiled`).
    """
    xs = list_array(xs, "xs")
    ranges = list_array(ranges, "ranges")
    _check_inputs(xs, ranges, mask, points_name="xs")
    _check_number(min_points, "min_points", "a number of valid samples (an int)")
    _check_number(min_baseline, "min_baseline", "a baseline [m] (a number)")
    _check_number(side, "side", "+1 or -1 (the sign of the offset from the line)")
    side_known = is_concrete(side)
    if side_known and float(np.asarray(side)) not in (-1.0, 1.0):
        raise InputError(f"side: expected +1 or -1 (the sign of the offset from the line), got {side!r}")
    mask = list_array(mask, "mask")

    def solve(opts, xs, ranges):
        return _trilaterate_line(xs, ranges, *opts, side_known=side_known)

    return call_compiled(("trilateration.trilaterate_line", side_known), solve, (xs, ranges),
                         (mask, side, min_points, min_baseline), after="auto")


def _trilaterate_line(xs, ranges, mask, side, min_points, min_baseline, side_known):
    """:func:`trilaterate_line`'s computation (the values were checked by the caller; with
    ``side_known`` False a traced ``side`` other than ±1 makes ``ok`` False)."""
    dtype = _dtype_of(xs, ranges)
    xs = jnp.asarray(xs, dtype)
    ranges = jnp.asarray(ranges, dtype)
    pts = jnp.stack([xs, jnp.zeros_like(xs)], axis=1)
    A, b, valid, ref = linear_system(pts, ranges, mask)
    a = A[:, 0]
    aa = jnp.sum(a * a)
    n_used = jnp.sum(valid).astype(jnp.int32)
    spread = point_spread(jnp.where(valid[:, None], pts[:, :1], 0.0), valid)  # (a dropped NaN row: no NaN)
    has_base = (aa > 0) & (spread > jnp.asarray(min_baseline, dtype))
    u = jnp.where(has_base, jnp.sum(a * b) / jnp.where(aa > 0, aa, 1.0), 0.0)
    d = jnp.where(valid, ranges, 0.0)
    n = jnp.maximum(n_used, 1).astype(dtype)
    y2 = jnp.sum(jnp.where(valid, d * d - (u - xs) ** 2, 0.0)) / n
    off_line = y2 > 0
    y = jnp.asarray(side, dtype) * jnp.sqrt(jnp.where(off_line, y2, 0.0))
    ok = (n_used >= min_points) & has_base & off_line
    if not side_known:  # a traced side other than ±1 scaled y (a concrete one is refused)
        ok = ok & (jnp.abs(jnp.asarray(side, dtype)) == 1)
    pos = jnp.stack([u, y])
    pos = jnp.where(jnp.isfinite(pos), pos, 0.0)
    dist = jnp.sqrt((pos[0] - xs) ** 2 + pos[1] ** 2)
    residual_max = jnp.max(jnp.where(valid, jnp.abs(dist - d), 0.0))
    status = jnp.where(ok, 0, errors.DEGENERATE) | _bad_input_flag(pts, ranges, mask)
    return TrilaterationResult(position=pos, cov=jnp.zeros((2, 2), dtype), ok=ok,
                               status=jnp.asarray(status, jnp.int32), n_used=n_used,
                               spread=spread, residual_max=residual_max)
