"""Delayed landmark initialisation from buffered ranges (range-only SLAM).

A range does not fix a landmark, so a range-only filter keeps, while a landmark is unmapped, a
buffer of (robot position, its variance, range) rows and initialises the landmark once the rows
are many and spread enough: a least-squares trilateration
(:func:`jaxslam.filters.trilateration.trilaterate`) of the buffered positions, with the
covariance of the fit plus the buffered positions' own uncertainty::

    l̂ = trilaterate(p_1..W, r_1..W),   P_ll = cov(l̂) + mean(σ²_p) I                  (D1)

mean(σ²_p) the mean of the buffered position variances (½ tr of the robot's 2×2 position block
at each row); the buffered positions are treated as exact in the fit and their uncertainty is
added as isotropic noise of that size (a conservative stand-in for the cross-covariance with
poses that are no longer in the state).  ``robust=True`` fits twice: a first fit, then rows with
|residual − median| > max(3 · 1.4826 · MAD, 1 m) dropped (NLOS and multipath outliers) and a
refit.

The buffer layout (one ring per landmark, or one shared ring of all ranges) and the moment of
registration are the system's choice; this module holds the arithmetic both share.  Pure,
jit- and vmap-safe; degenerate geometry is ``ok = False``, never NaN.
"""

from __future__ import annotations

from typing import Optional

import jax
import jax.numpy as jnp
import numpy as np

from ..compilation import call_compiled
from ..errors import InputError
from ..linalg import check_mask, float_array, is_concrete, safe_norm
from . import trilateration as tri

__all__ = ["robust_trilaterate", "from_buffer"]


def _rows_in(points, ranges, valid, range_var):
    """The buffer's rows checked (trilateration's shape and ``range_var`` checks, static) and as
    arrays: ``(points (W, d), ranges (W,), valid (W,) bool)``; ``valid`` may also hold 0/1
    integers (a concrete float or another integer is an :class:`InputError` naming it)."""
    points = float_array(points, "points")
    ranges = float_array(ranges, "ranges")
    if valid is None:
        raise InputError("valid: expected a (W,) bool mask of the rows to fit, got None")
    tri._check_inputs(points, ranges, valid, range_var, mask_name="valid")
    return points, ranges, jnp.asarray(valid).astype(bool)


def robust_trilaterate(points, ranges, valid, range_var, min_points: Optional[int] = None,
                       min_spread=0.0) -> tri.TrilaterationResult:
    """Two-pass trilateration: fit, drop |residual − median| > max(3·1.4826·MAD, 1 m), refit.

    points: (W, d); ranges: (W,); valid: (W,) bool (or 0/1 integers).  Shapes, a concrete
    ``valid``'s values and a concrete ``range_var`` are checked first (:class:`InputError`
    naming the argument).  The row selection is held constant under differentiation
    (``stop_gradient``).  Returns the second fit's
    :class:`~jaxslam.filters.trilateration.TrilaterationResult`.  Called eagerly it is compiled
    once per shape (:func:`jaxslam.compilation.call_compiled`; op by op the first call took 1.3 s)."""
    points, ranges, valid = _rows_in(points, ranges, valid, range_var)
    return call_compiled(("delayed_init.robust_trilaterate",), lambda opts, p, r, v: _robust(p, r, v, *opts),
                         (points, ranges, valid), (range_var, min_points, min_spread), after="auto")


def _robust(points, ranges, valid, range_var, min_points, min_spread):
    """:func:`robust_trilaterate` of checked arrays."""
    r1 = tri.trilaterate(points, ranges, mask=valid)
    res = safe_norm(points - r1.position, axis=1) - ranges
    resn = jnp.where(valid, res, jnp.nan)
    med = jnp.nanmedian(resn)
    mad = jnp.nanmedian(jnp.abs(resn - med))
    cut = jnp.maximum(3.0 * 1.4826 * mad, 1.0)
    keep = jax.lax.stop_gradient(valid & (jnp.abs(res - med) <= cut))
    return tri.trilaterate(points, ranges, mask=keep, range_var=range_var, min_points=min_points,
                           min_spread=min_spread)


def from_buffer(points, point_var, ranges, valid, range_var, min_points: Optional[int] = None,
                min_spread=0.0, robust: bool = False, var_rows=None):
    """(D1): a landmark and its covariance from buffered rows.

    Args:
      points: (W, d) robot positions at the buffered ranges [m].
      point_var: (W,) their variances [m²] (per axis).
      ranges: (W,) ranges [m] (bias already removed by the caller).
      valid: (W,) bool rows to fit (or 0/1 integers; checked when concrete).
      range_var: σ_r² [m²] of one range.
      min_points, min_spread: :func:`~jaxslam.filters.trilateration.trilaterate`'s
        readiness conditions (count, spread [m]); numbers or traced scalars (both are only
        compared, so a system may keep them in its traced parameters).
      robust: two-pass fit (:func:`robust_trilaterate`).
      var_rows: (W,) bool rows whose variances are averaged (default ``valid``; a shared buffer
        averages every filled row).

    Returns:
      ``(fit, P_ll)``: the trilateration result (``fit.ok``: ready) and the (d, d) covariance.

    Shapes are checked (static; ``point_var`` may also be one scalar for every row) and, when
    concrete, ``range_var`` and ``point_var`` on the averaged rows (finite, ≥ 0: a negative
    variance shrank P_ll): :class:`InputError` naming the argument.  ``points`` and
    ``point_var`` may be lists.  Called eagerly it is compiled once per shape and ``robust``
    (:func:`jaxslam.compilation.call_compiled`).
    """
    points, ranges, valid = _rows_in(points, ranges, valid, range_var)
    W = points.shape[0]
    point_var = float_array(point_var, "point_var")
    if point_var.shape not in ((), (W,)):
        raise InputError(f"point_var: expected shape ({W},) (one per row of points) or a scalar, "
                         f"got {tuple(point_var.shape)}")
    if var_rows is not None and np.shape(var_rows) != (W,):
        raise InputError(f"var_rows: expected shape ({W},) (one per row of points), got {np.shape(var_rows)}")
    check_mask(var_rows, "var_rows")  # a 0.5 or a 2 was read as True
    rows = valid if var_rows is None else jnp.asarray(var_rows).astype(bool)
    if is_concrete(point_var, rows):
        v = np.broadcast_to(np.asarray(point_var), (W,))[np.asarray(rows)]
        if not np.all(np.isfinite(v) & (v >= 0)):
            raise InputError(f"point_var: expected finite variances >= 0 [m²] on the averaged rows, got "
                             f"{v[~(np.isfinite(v) & (v >= 0))][0]}")
    robust = bool(robust)
    return call_compiled(("delayed_init.from_buffer", robust),
                         lambda opts, *a: _from_buffer(*a, *opts, robust),
                         (points, point_var, ranges, valid, rows), (range_var, min_points, min_spread), after="auto")


def _from_buffer(points, point_var, ranges, valid, rows, range_var, min_points, min_spread, robust: bool):
    """:func:`from_buffer` of checked arrays (``rows``: the rows whose variances are averaged)."""
    fit = (_robust if robust else _plain)(points, ranges, valid, range_var, min_points, min_spread)
    n = jnp.maximum(jnp.sum(rows), 1).astype(fit.cov.dtype)
    mean_var = jnp.sum(jnp.where(rows, point_var, 0.0)) / n
    d = points.shape[-1]
    return fit, fit.cov + mean_var * jnp.eye(d, dtype=fit.cov.dtype)


def _plain(points, ranges, valid, range_var, min_points, min_spread):
    return tri.trilaterate(points, ranges, mask=valid, range_var=range_var, min_points=min_points,
                           min_spread=min_spread)
