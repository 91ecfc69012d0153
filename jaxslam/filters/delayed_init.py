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

from ..linalg import safe_norm
from . import trilateration as tri

__all__ = ["robust_trilaterate", "from_buffer"]


def robust_trilaterate(points, ranges, valid, range_var, min_points: Optional[int] = None,
                       min_spread=0.0) -> tri.TrilaterationResult:
    """Two-pass trilateration: fit, drop |residual − median| > max(3·1.4826·MAD, 1 m), refit.

    points: (W, d); ranges: (W,); valid: (W,) bool.  The row selection is held constant under
    differentiation (``stop_gradient``).  Returns the second fit's
    :class:`~jaxslam.filters.trilateration.TrilaterationResult`."""
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
      valid: (W,) bool rows to fit.
      range_var: σ_r² [m²] of one range.
      min_points, min_spread: :func:`~jaxslam.filters.trilateration.trilaterate`'s
        readiness conditions (count, spread [m]); numbers or traced scalars (both are only
        compared, so a system may keep them in its traced parameters).
      robust: two-pass fit (:func:`robust_trilaterate`).
      var_rows: (W,) bool rows whose variances are averaged (default ``valid``; a shared buffer
        averages every filled row).

    Returns:
      ``(fit, P_ll)``: the trilateration result (``fit.ok``: ready) and the (d, d) covariance.
    """
    fit = (robust_trilaterate if robust else _plain)(points, ranges, valid, range_var, min_points, min_spread)
    rows = valid if var_rows is None else var_rows
    n = jnp.maximum(jnp.sum(rows), 1).astype(fit.cov.dtype)
    mean_var = jnp.sum(jnp.where(rows, point_var, 0.0)) / n
    d = points.shape[-1]
    return fit, fit.cov + mean_var * jnp.eye(d, dtype=fit.cov.dtype)


def _plain(points, ranges, valid, range_var, min_points, min_spread):
    return tri.trilaterate(points, ranges, mask=valid, range_var=range_var, min_points=min_points,
                           min_spread=min_spread)
