"""Line features of 2D scans: Hesse normal form, least-squares fits, RANSAC (paper 004, ch. 4.1).

**Representation.**  Paper 004 stores a wall as ``F = ρ + θ k̂`` (eq. 4.2-4.3): ``ρ`` the distance
from the scan origin, ``θ`` the angle of the line's normal.  jaxslam keeps the two reals: the line
is the set of points ``p`` with ``p · [cos θ, sin θ] = ρ``, normalised to ``ρ ≥ 0`` and
``θ ∈ (−π, π]`` (:func:`hesse_normalize`; a line through the origin keeps the θ it was given).

**Fits.**  :func:`fit_line` is the weighted total-least-squares line (minimises
``Σ w_i (p_i·n − ρ)²``): through the weighted centroid, with the normal along the smallest
principal axis of the 2×2 scatter matrix, in closed form (``φ = ½ atan2(2 s_xy, s_xx − s_yy)`` is
the principal direction; no ``eigh``).  :func:`fit_line_cov` is its first-order covariance under
isotropic point noise σ: with residuals ``r_i = n(θ)·p_i − ρ`` and Jacobian rows
``j_i = ∂r_i/∂(ρ, θ) = [−1, s_i]``, ``s_i = p_i · [−sin θ, cos θ]``, the Gauss-Newton step gives
``Σ = σ² A⁻¹ B A⁻¹`` with ``A = Σ w_i j_i j_iᵀ`` and ``B = Σ w_i² j_i j_iᵀ`` (``= σ² A⁻¹`` for 0/1
weights).  Written about the centroid (``s_i = s̄ + u_i``): ``var θ = σ²/Σu²``,
``var ρ = σ² (1/N + s̄²/Σu²)``, ``cov(ρ, θ) = σ² s̄/Σu²`` for unit weights.

**Eq. 4.1** (:func:`n_hypotheses`), ``n_hyp = ⌈log(1 − p) / log(1 − (1 − ε)^m)⌉``: the thesis calls
``m`` "the minimum number of points that are considered to be a valid line".  In the standard
derivation (Fischler & Bolles; Zuliani 2009, cited by the thesis) ``m`` is the size of the
*minimal sample* that defines a hypothesis — 2 points for a line — and ``(1 − ε)^m`` is the
probability that a sample is outlier-free; that is what Algorithm 1 draws ("two random points are
selected").  With the thesis' reading (m = min_inliers ≈ 20) the count is astronomically large
(p = 0.99, ε = 0.5 → 4.8·10⁶).  jaxslam's default uses the minimal-sample reading, m = 2;
``m`` stays a parameter.  Default: p = 0.99, ε = 0.9 (a line may hold only 10 % of the points still
unexplained: the last walls of a room scan among 30 % clutter), m = 2 → **n_hyp = 459**.
Other defaults: ``threshold`` = 5 cm (2.5 σ for the URG-04LX's σ ≈ 2 cm at 2 m, ``point_sigma``):
with 3σ = 6 cm the clutter that grazing beams leave just in front of a wall tilted the side walls
of the acceptance room (tests) by up to 0.8° and 98.3 % of 1000 scans met the 2 cm / 0.5°
criterion; with 5 cm, 99.8 %.  ``min_inliers`` = 20, ``max_lines`` = 8.

**Algorithm 1** (:func:`extract_lines`) with static shapes: ``max_lines`` rounds in one
``lax.scan``; each round draws ``n_hyp`` two-point hypotheses at once (vmapped, no Python loop):
two *distinct* ranks ``r₁ ∈ [0, K)``, ``r₂ ∈ [0, K−1)`` (shifted past ``r₁``) among the ``K``
points still remaining, mapped to indices by ``searchsorted`` on the cumulative mask (no
``n_hyp × N`` random matrix).  Support of a hypothesis = remaining points within ``threshold`` of
it (ties → the first hypothesis).  Then: least-squares refit on the best hypothesis' inliers
("clearInliersModel"), rescued inliers = remaining points within ``threshold`` of that fit,
final least-squares fit on bestInliers ∪ rescued ("rescuedInliersModel"), those points leave the
scan.  A round whose best support is below ``min_inliers`` yields ``valid = False`` and removes
nothing; with ``stop_on_fail=True`` (default, Algorithm 1's "Break while loop") every later round
is invalid as well, otherwise later rounds try again with fresh samples.  The thesis'
``bestInliers ≤ m`` break is read as ``< min_inliers``.

**Feature matching** (thesis p. "Feature matching", Alg. 2): :func:`match_predicted` looks for
each predicted line (from the EKF prior) without random samples: the remaining points within
``gate`` of the prediction are fitted, inliers re-selected within ``threshold`` of that fit,
fitted and re-selected once more (a second round sheds points of a neighbouring wall that the
wide gate let in), and fitted again; the line is matched if it keeps ≥ ``min_inliers`` points,
which then leave the scan.  :func:`extract_guided` runs RANSAC on what is left to find new lines.

**Runs of beams** (jaxslam addition, off by default = the thesis): with ``max_gap > 0`` a line
keeps only the largest run of its inliers whose consecutive beam indices differ by at most
``max_gap`` (:func:`largest_run`), and ``trim_ends`` drops that many inliers at each end of the
run (:func:`trim_run`; ``trim_ends > 0`` with ``max_gap = 0`` is an ``InputError``: there is no
run to trim).  A wall is one run of beams; an infinite line also collects clutter and
the faces of other objects on its extension (a pillar face nearly collinear with a wall behind
it), and the few points of the neighbouring wall within the threshold at a corner tilt the fit
of a short segment.  The line-feature SLAM of paper 004 (``jaxslam.systems.line_slam_004``) uses
``max_gap = 10``, ``trim_ends = 3``.

**Statics.**  ``RansacConfig`` is a hashable NamedTuple of Python numbers: pass it as a static
argument (``jax.jit(extract_lines, static_argnames="cfg")``) or close over it; ``n_hyp`` and
``max_lines`` set shapes.  Changing a threshold recompiles; ``gate`` is traced.

Inside ``jit`` nothing raises: invalid points (mask False or non-finite) are ignored, degenerate
fits give finite numbers with ``valid = False``; invalid line slots read 0 (never NaN).  All
functions follow the dtype of ``points``.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import InputError
from ..geometry.euler import _as_real_array, _exact_shape, _last_axis
from ..compilation import call_compiled
from ..linalg import (check_int, check_key, check_mask, check_numbers, check_real, float_array, is_concrete,
                      wrap_angle)

__all__ = [
    "Lines",
    "RansacConfig",
    "DEFAULT_RANSAC",
    "check_ransac_config",
    "hesse_normalize",
    "line_through",
    "fit_line",
    "fit_line_cov",
    "point_line_distance",
    "segment_endpoints",
    "largest_run",
    "trim_run",
    "n_hypotheses",
    "extract_lines",
    "match_predicted",
    "extract_guided",
]


# ----------------------------------------------------------------------------- eq. 4.1


def n_hypotheses(p, outlier_ratio, m=2):
    """Paper 004 eq. 4.1: ``⌈log(1 − p) / log(1 − (1 − ε)^m)⌉`` hypotheses (host-side, int).

    Args:
      p: wanted probability that at least one hypothesis is outlier-free, in (0, 1).
      outlier_ratio: ε, fraction of points *not* on the line sought, in (0, 1).
      m: points per sample; 2 (the minimal sample of a line, jaxslam's default) or the thesis'
        reading "minimum number of points of a valid line" (module docstring).  int ≥ 2.

    Raises:
      InputError: arguments out of range, or a count too large to represent.
    """
    for name, v in (("p", p), ("outlier_ratio", outlier_ratio)):
        if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
            raise InputError(f"{name}: expected a number in (0, 1), got {v!r}")
        if not (0.0 < float(v) < 1.0):
            raise InputError(f"{name}: expected a number in (0, 1), got {v!r}")
    if isinstance(m, bool) or not isinstance(m, (int, np.integer)) or m < 2:
        raise InputError(f"m: expected an integer ≥ 2 (points per sample), got {m!r}")
    good = (1.0 - float(outlier_ratio)) ** int(m)
    if good >= 1.0:  # ε so small that (1 − ε)^m rounds to 1: the count is < 1 (log1p(−1) raised)
        return 1
    den = math.log1p(-good)
    if den == 0.0:
        raise InputError(f"n_hypotheses: (1 − ε)^m = {good:.3g} is too small; the count overflows "
                         f"(outlier_ratio={outlier_ratio}, m={m})")
    n = math.log1p(-float(p)) / den
    if not math.isfinite(n) or n > 2**62:
        raise InputError(f"n_hypotheses: count {n:.3g} too large (outlier_ratio={outlier_ratio}, m={m})")
    # Guard against 48.000000001 style round-off before the ceiling.  The guard is capped at
    # 1e-6: n itself is good to a few ulp, and an uncapped 1e-9·n took up to ~200 hypotheses off
    # a count of 2·10¹¹ (p = 0.999, ε = 0.7, m = 20), below the bound the formula guarantees.
    return max(1, int(math.ceil(n - min(1e-9 * max(1.0, n), 1e-6))))


# ----------------------------------------------------------------------------- containers


class RansacConfig(NamedTuple):
    """RANSAC settings (static: hashable Python numbers; module docstring for defaults)."""

    n_hyp: int = 459  # hypotheses per round, eq. 4.1 with p = 0.99, ε = 0.9, m = 2
    max_lines: int = 8  # rounds of Algorithm 1 = line slots returned
    threshold: float = 0.05  # [m] inlier distance, 2.5σ at point_sigma (module docstring)
    min_inliers: int = 20  # support needed for a line
    point_sigma: float = 0.02  # [m] isotropic point noise for fit_line_cov (URG-04LX at 2 m)
    stop_on_fail: bool = True  # Algorithm 1's break: after a failed round, no more lines
    max_gap: int = 0  # > 0: keep the largest run of inliers with beam gaps <= max_gap (one wall)
    trim_ends: int = 0  # with max_gap > 0: drop this many inliers at each end of the run (corners)


DEFAULT_RANSAC = RansacConfig()


class Lines(NamedTuple):
    """Fixed-capacity set of L line features (invalid slots are zero)."""

    rho: jax.Array  # (L,) [m] ≥ 0
    theta: jax.Array  # (L,) [rad] in (−π, π]
    cov: jax.Array  # (L, 2, 2) covariance of (ρ, θ)
    valid: jax.Array  # (L,) bool
    n_inliers: jax.Array  # (L,) int32
    endpoints: jax.Array  # (L, 2, 2) [m] extreme inlier projections on the line
    inliers: jax.Array  # (L, N) bool, the points assigned to each line


def check_ransac_config(cfg):
    """Host-side validation of a :class:`RansacConfig`; returns it.  Raises InputError (also
    for ``trim_ends > 0`` with ``max_gap = 0``, which trimmed nothing)."""
    if not isinstance(cfg, RansacConfig):
        raise InputError(f"cfg: expected a RansacConfig, got {type(cfg).__name__}")
    for name in ("n_hyp", "max_lines", "min_inliers"):
        v = getattr(cfg, name)
        if isinstance(v, jax.core.Tracer):
            raise InputError(f"cfg.{name} is traced: pass the RansacConfig as a static argument "
                             "(static_argnames='cfg') or close over it")
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < (2 if name == "min_inliers" else 1):
            raise InputError(f"cfg.{name}: expected an integer ≥ {2 if name == 'min_inliers' else 1}, got {v!r}")
    for name in ("max_gap", "trim_ends"):  # 0 switches the run finder / the trimming off
        check_int(getattr(cfg, name), f"cfg.{name}", lower=0, what="an integer")
    if cfg.trim_ends > 0 and cfg.max_gap == 0:  # it trims the run max_gap keeps: none without it
        raise InputError(f"cfg.trim_ends: trims the ends of the run of beams that max_gap > 0 keeps; "
                         f"got trim_ends={cfg.trim_ends} with max_gap=0 (the run finder off: it did nothing)")
    if not isinstance(cfg.stop_on_fail, (bool, np.bool_)):
        raise InputError(f"cfg.stop_on_fail: expected True or False, got {cfg.stop_on_fail!r}")
    for name in ("threshold", "point_sigma"):
        v = getattr(cfg, name)
        if isinstance(v, jax.core.Tracer):
            raise InputError(f"cfg.{name} is traced: pass the RansacConfig as a static argument")
        if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)) or not (
                float(v) > 0 and math.isfinite(v)):
            raise InputError(f"cfg.{name}: expected a positive finite number, got {v!r}")
    return cfg


# ----------------------------------------------------------------------------- geometry


def _wrap_pi(a):
    """Wrap to (−π, π] (``linalg.wrap_angle`` wraps to [−π, π))."""
    return -wrap_angle(-a)


def hesse_normalize(rho, theta):
    """Hesse normal form: if ρ < 0 then ρ → −ρ, θ → θ + π; θ wrapped to (−π, π]."""
    rho, theta = _as_real_array(rho, "rho"), _as_real_array(theta, "theta")
    flip = rho < 0
    return jnp.where(flip, -rho, rho), _wrap_pi(jnp.where(flip, theta + jnp.pi, theta))


def line_through(p1, p2):
    """Line ``(ρ, θ)`` through two points ``(2,)``.  Coincident points give a finite, arbitrary line.

    Another shape (a (1,) or (3,) point: JAX clamps out-of-range indices, so the missing
    coordinate was read from a wrong entry) or a complex point is an
    :class:`~jaxslam.errors.InputError` naming it (static: under ``jit`` too).
    """
    p1 = _exact_shape(p1, (2,), "p1", "line_through")
    p2 = _exact_shape(p2, (2,), "p2", "line_through")
    e = p2 - p1
    theta = jnp.arctan2(e[0], -e[1])  # normal [−e_y, e_x]
    rho = p1[0] * jnp.cos(theta) + p1[1] * jnp.sin(theta)
    return hesse_normalize(rho, theta)


def point_line_distance(points, rho, theta):
    """Unsigned distances ``(N,)`` [m] of points ``(N, 2)`` from the line ``p·[cos θ, sin θ] = ρ``.

    ``points`` may be any ``(..., 2)`` (one point ``(2,)`` gives a scalar); a last axis of
    another size (an ``(N, 1)`` array was read as x with y from a clamped index) or a complex
    argument is an :class:`~jaxslam.errors.InputError` naming it (static).
    """
    points = _last_axis(points, 2, "points", "point_line_distance")
    rho, theta = _as_real_array(rho, "rho"), _as_real_array(theta, "theta")
    return jnp.abs(points[..., 0] * jnp.cos(theta) + points[..., 1] * jnp.sin(theta) - rho)


def _moments(points, weights):
    w = jnp.asarray(weights).astype(points.dtype)
    W = jnp.sum(w)
    c = jnp.sum(w[:, None] * points, axis=0) / jnp.maximum(W, jnp.finfo(points.dtype).tiny)
    d = points - c
    sxx = jnp.sum(w * d[:, 0] * d[:, 0])
    syy = jnp.sum(w * d[:, 1] * d[:, 1])
    sxy = jnp.sum(w * d[:, 0] * d[:, 1])
    return w, W, c, sxx, syy, sxy


def _points_weights(points, weights):
    """Points ``(N, 2)`` as a float array and weights of shape ``(N,)``, both real, else
    :class:`InputError` naming the argument.  Static checks (free under ``jit``): a (1,) weight
    broadcast over every point, an (N, 3) scan lost its third column, a complex array dropped
    its imaginary part with only a warning."""
    check_real(points, "points")
    points = float_array(points, "points")
    if points.ndim != 2 or points.shape[1] != 2:
        raise InputError(f"points: expected shape (N, 2), got {tuple(points.shape)}")
    check_real(weights, "weights")
    if np.shape(weights) != points.shape[:1]:
        raise InputError(f"weights: expected shape ({points.shape[0]},) (one per point), got {np.shape(weights)}")
    return points


def _fit_inputs(points, weights, sigma=None):
    """Points ``(N, 2)`` as a float array; weights ``(N,)`` (finite and ≥ 0 when concrete); σ a
    scalar (finite and > 0 when concrete): :class:`InputError` naming the argument
    (:func:`_points_weights` for the static checks)."""
    points = _points_weights(points, weights)
    if is_concrete(weights):
        w = np.asarray(weights)
        if np.any(w < 0):
            raise InputError("weights: must be >= 0")
        if not np.all(np.isfinite(w)):  # NaN passed the test above, and NaN or inf made the fit NaN
            raise InputError("weights: must be finite (got NaN or inf)")
    if sigma is not None:
        check_real(sigma, "sigma")
        if np.shape(sigma) != ():
            raise InputError(f"sigma: expected a scalar point noise σ [m], got shape {np.shape(sigma)}")
        _positive_number(sigma, "sigma", InputError(f"sigma: expected a point noise σ > 0 [m] (finite), got {sigma!r}"),
                         finite=True)
    return points


def _positive_number(value, name: str, bad: InputError, finite: bool) -> None:
    """Raise ``bad`` unless ``value`` is a real number > 0 (finite when ``finite``) when known: a
    string ("0.1") was parsed as a number, True read as 1 m, and a complex value raised a bare
    TypeError from float() (``check_numbers``: real numbers only).  A traced value passes."""
    if isinstance(value, (bool, np.bool_, str, bytes)):
        raise bad
    if is_concrete(value):
        try:
            v = float(check_numbers(value, name))
        except InputError:
            raise bad from None
        if not (v > 0 and (v < np.inf or not finite)) or np.asarray(value).dtype.kind == "b":
            raise bad


def fit_line(points, weights):
    """Weighted total-least-squares line ``(ρ, θ)`` of points ``(N, 2)`` with weights ``(N,)`` ≥ 0.

    Closed form (module docstring).  Zero total weight gives a finite, meaningless line; callers
    mask it.  Points with zero weight must be finite (NaN · 0 = NaN).
    """
    points = _fit_inputs(points, weights)
    return _fit_line(points, weights)


def _fit_line(points, weights):
    _, _, c, sxx, syy, sxy = _moments(points, weights)
    phi = 0.5 * jnp.arctan2(2.0 * sxy, sxx - syy)  # direction of largest spread
    theta = phi + 0.5 * jnp.pi
    rho = c[0] * jnp.cos(theta) + c[1] * jnp.sin(theta)
    return hesse_normalize(rho, theta)


def _cov_about(points, w, W, c, rho, theta, sigma):
    d = jnp.stack([-jnp.sin(theta), jnp.cos(theta)])
    sbar = c @ d
    u = (points - c) @ d
    suu = jnp.sum(w * u * u)
    finfo = jnp.finfo(points.dtype)
    # Fewer than two distinct weighted points (to working precision): the weighted spread
    # along the line is within a few ulp of the centroid's coordinates (h [m²]), or W = 0.
    # A⁻¹ then overflowed (one point: [[-inf, inf], [inf, 0]]; two identical points: NaN).
    h = float(4 * finfo.eps) ** 2 * jnp.maximum(c @ c, 1.0)
    deg = suu <= W * h
    # A = [[W, −W s̄], [−W s̄, W s̄² + Σwu²]] (ρ, θ order), det A = W Σwu².
    det = jnp.where(deg, 1.0, jnp.maximum(W * suu, finfo.tiny))  # double where: finite gradients
    Ainv = jnp.stack([jnp.stack([W * sbar**2 + suu, W * sbar]), jnp.stack([W * sbar, W])]) / det
    s = sbar + u
    w2 = w * w
    B = jnp.stack([jnp.stack([jnp.sum(w2), -jnp.sum(w2 * s)]),
                   jnp.stack([-jnp.sum(w2 * s), jnp.sum(w2 * s * s)])])
    cov = (sigma**2) * (Ainv @ B @ Ainv)
    cov = 0.5 * (cov + cov.T)
    # Degenerate: the unit-weight variances about the centroid (module docstring) with Σu² := h and
    # s̄² := max(|c̄|², 1), scaled by Σw²/W² (1 for W = 0), without the correlation: huge but
    # finite (var ρ = σ² r (1 + 1/(16 eps²))) and positive definite in float32 and float64 (the
    # correlated form's condition number, ~1/(16 eps²), rounded it indefinite in float32).
    Wd = jnp.where(W > 0, W, 1.0)
    r = jnp.where(W > 0, jnp.sum(w2) / (Wd * Wd), 1.0)
    z = jnp.zeros_like(h)
    var_rho = 1.0 + 1.0 / float(4 * finfo.eps) ** 2  # 1 + max(|c̄|², 1)/h
    cov_deg = (sigma**2) * r * jnp.stack([jnp.stack([var_rho, z]), jnp.stack([z, 1.0 / h])])
    return jnp.where(deg, cov_deg, cov)


def fit_line_cov(points, weights, sigma):
    """First-order covariance ``(2, 2)`` of :func:`fit_line`'s ``(ρ, θ)`` under isotropic point noise σ [m].

    ``σ² A⁻¹ B A⁻¹`` (module docstring).  Fewer than two distinct weighted points (a spread along
    the line within a few ulp of the centroid's coordinates, or zero total weight) give a huge but
    finite covariance, ``σ² (Σw²/W²) diag(1 + 1/(16 eps²), 1/h)`` with ``h = (4 eps)² max(|c̄|², 1 m²)``
    (``c̄`` the weighted centroid, ``eps`` of the dtype; ``Σw²/W²`` read as 1 for W = 0): positive
    definite, ``var θ`` ≈ ``σ²/(16 eps² max(|c̄|², 1 m²))``.  Concrete weights must be finite and ≥ 0, σ finite
    and > 0 (:class:`~jaxslam.errors.InputError`).
    """
    points = _fit_inputs(points, weights, sigma)
    rho, theta = _fit_line(points, weights)
    w, W, c, _, _, _ = _moments(points, weights)
    return _cov_about(points, w, W, c, rho, theta, jnp.asarray(sigma, points.dtype))


def segment_endpoints(points, weights, rho, theta):
    """Endpoints ``(2, 2)`` [m] of the segment spanned by the points with weight > 0 on the line.

    The extreme projections of those points onto the line, ordered along ``[−sin θ, cos θ]``.
    No such point → zeros.  ``points`` ``(N, 2)`` and ``weights`` ``(N,)`` real (static checks,
    as :func:`fit_line`: a (1,) weight broadcast over every point); ``rho``, ``theta`` scalars
    (static check: a (1,) pair gave ``(1, 2, 1)`` endpoints).
    """
    points = _points_weights(points, weights)
    rho, theta = _as_real_array(rho, "rho"), _as_real_array(theta, "theta")
    for name, v in (("rho", rho), ("theta", theta)):  # (1,) gave (1, 2, 1) ends, (2,) a bare ValueError
        if v.ndim != 0:
            raise InputError(f"{name}: expected a scalar (one line), got shape {tuple(v.shape)}")
    m = jnp.asarray(weights) > 0
    n = jnp.stack([jnp.cos(theta), jnp.sin(theta)])
    d = jnp.stack([-jnp.sin(theta), jnp.cos(theta)])
    u = points @ d
    any_ = jnp.any(m)
    umin = jnp.where(any_, jnp.min(jnp.where(m, u, jnp.inf)), 0.0)
    umax = jnp.where(any_, jnp.max(jnp.where(m, u, -jnp.inf)), 0.0)
    ends = rho * n[None, :] + jnp.stack([umin, umax])[:, None] * d[None, :]
    return jnp.where(any_, ends, 0.0)


# ----------------------------------------------------------------------------- RANSAC


def _prepare(points, valid):
    check_real(points, "points")  # a complex scan dropped its imaginary part with only a warning
    points = float_array(points, "points")
    if points.ndim != 2 or points.shape[1] != 2:
        raise InputError(f"points: expected shape (N, 2), got {points.shape}")
    if np.shape(valid) != points.shape[:1]:
        raise InputError(f"valid: expected shape ({points.shape[0]},), got {np.shape(valid)}")
    check_mask(valid, "valid")  # a float 0.3 or NaN, an integer 2, counted as a valid point
    valid = jnp.asarray(valid)
    if points.shape[0] == 0:  # a static size: nothing to sample or search (N = 0 would index nothing)
        raise InputError("points: expected at least one point (N >= 1; mark missing returns with valid), "
                         "got shape (0, 2)")
    ok = valid.astype(bool) & jnp.all(jnp.isfinite(points), axis=1)
    return jnp.where(ok[:, None], points, 0.0), ok


def largest_run(mask, max_gap):
    """The largest run of ``mask`` (N,) whose consecutive True indices differ by ≤ ``max_gap``.

    A wall is seen as one run of consecutive beams; scattered clutter that happens to lie
    within the inlier threshold of a line's infinite extension is not part of that run.
    Ties go to the first run.  An all-False mask returns all False, an empty one an empty mask.
    ``mask``: bool (or 0/1 integers), one axis (:class:`~jaxslam.errors.InputError` otherwise).
    """
    max_gap = check_int(max_gap, "max_gap", lower=0)
    mask = _run_mask(mask)
    n = mask.shape[0]
    if n == 0:  # nothing to search (argmax of an empty array raised a bare ValueError)
        return mask
    idx = jnp.arange(n)
    last = jax.lax.cummax(jnp.where(mask, idx, -1))
    prev = jnp.concatenate([jnp.full((1,), -1, last.dtype), last[:-1]])
    start = mask & ((prev < 0) | (idx - prev > max_gap))
    seg = jnp.where(mask, jnp.cumsum(start) - 1, n)
    counts = jnp.zeros((n + 1,), jnp.int32).at[seg].add(mask.astype(jnp.int32))[:n]
    return mask & (seg == jnp.argmax(counts))


def trim_run(mask, k):
    """``mask`` without its first and last ``k`` True entries (all False if ≤ 2k are True).

    ``mask`` as :func:`largest_run` (an empty one comes back empty).
    """
    k = check_int(k, "k", lower=0)
    mask = _run_mask(mask)
    if mask.shape[0] == 0:  # rank[-1] of nothing raised a bare IndexError
        return mask
    rank = jnp.cumsum(mask)
    return mask & (rank > k) & (rank <= rank[-1] - k)


def _run_mask(mask):
    """``mask`` (N,) as a bool array; another rank or a non-mask dtype or value is an
    :class:`InputError` (a 2-D mask was flattened by ``cumsum``; a float 0.5 read as True)."""
    if np.ndim(mask) != 1:
        raise InputError(f"mask: expected shape (N,), got {np.shape(mask)}")
    check_mask(mask, "mask")
    return jnp.asarray(mask, bool)


def _in_run(mask, cfg):
    if cfg.max_gap <= 0:
        return mask
    run = largest_run(mask, cfg.max_gap)
    return trim_run(run, cfg.trim_ends) if cfg.trim_ends > 0 else run


def _record(points, mask, ok, cfg):
    """One Lines slot from its inlier mask; zero where not ok."""
    rho, theta = fit_line(points, mask)
    w, W, c, _, _, _ = _moments(points, mask)
    cov = _cov_about(points, w, W, c, rho, theta, jnp.asarray(cfg.point_sigma, points.dtype))
    ends = segment_endpoints(points, mask, rho, theta)
    z = jnp.zeros((), points.dtype)
    return Lines(rho=jnp.where(ok, rho, z), theta=jnp.where(ok, theta, z), cov=jnp.where(ok, cov, z),
                 valid=ok, n_inliers=jnp.where(ok, jnp.sum(mask, dtype=jnp.int32), 0),
                 endpoints=jnp.where(ok, ends, z), inliers=mask & ok)


def _sample_pairs(key, remaining, n_hyp):
    """``n_hyp`` pairs of distinct indices among the remaining points; ``K`` = how many remain."""
    cum = jnp.cumsum(remaining.astype(jnp.int32))
    K = cum[-1]
    k1, k2 = jax.random.split(key)
    r1 = jax.random.randint(k1, (n_hyp,), 0, jnp.maximum(K, 1))
    r2 = jax.random.randint(k2, (n_hyp,), 0, jnp.maximum(K - 1, 1))
    r2 = r2 + (r2 >= r1)
    i1 = jnp.searchsorted(cum, r1 + 1, side="left", method="scan_unrolled")
    i2 = jnp.searchsorted(cum, r2 + 1, side="left", method="scan_unrolled")
    n = remaining.shape[0]
    return jnp.minimum(i1, n - 1), jnp.minimum(i2, n - 1), K


def _ransac_round(points, remaining, key, cfg):
    """One round of Algorithm 1 → (best support, bestInliers ∪ rescued mask)."""
    thr = jnp.asarray(cfg.threshold, points.dtype)
    i1, i2, K = _sample_pairs(key, remaining, cfg.n_hyp)
    p1, p2 = points[i1], points[i2]  # (H, 2)
    # Implicit line a x + b y + c = 0 through p1, p2 with (a, b) = (−e_y, e_x) unnormalised:
    # inlier ⇔ (a x + b y + c)² ≤ thr² (a² + b²); no trigonometry per hypothesis.
    a = -(p2[:, 1] - p1[:, 1])
    b = p2[:, 0] - p1[:, 0]
    c = -(a * p1[:, 0] + b * p1[:, 1])
    lim = thr * thr * (a * a + b * b)

    def support(ai, bi, ci, li):
        r = ai * points[:, 0] + bi * points[:, 1] + ci
        return (r * r <= li) & remaining

    counts = jax.vmap(lambda ai, bi, ci, li: jnp.sum(support(ai, bi, ci, li), dtype=jnp.int32))(a, b, c, lim)
    counts = jnp.where(lim > 0, counts, 0)  # coincident points define no line
    best = jnp.argmax(counts)  # ties → first
    best_in = support(a[best], b[best], c[best], lim[best])
    rho1, th1 = fit_line(points, best_in)  # clearInliersModel
    rescued = remaining & (point_line_distance(points, rho1, th1) <= thr)
    final = best_in | rescued
    support_n = jnp.where(K >= 2, counts[best], 0)
    return support_n, final


def extract_lines(key, points, valid, cfg=DEFAULT_RANSAC):
    """RANSAC line extraction, paper 004 Algorithm 1 with n_hyp of eq. 4.1 (module docstring).

    Args:
      key: PRNG key (results are deterministic given it).
      points: ``(N, 2)`` [m] scan points (e.g. :func:`jaxslam.sensors.laser2d.scan_points`).
      valid: ``(N,)`` bool; non-finite points are treated as invalid.
      cfg: :class:`RansacConfig` (static).

    Returns:
      ``(lines, remaining)``: :class:`Lines` with ``L = cfg.max_lines`` slots in extraction order,
      and the ``(N,)`` mask of valid points no line took.

    Raises:
      InputError: a bad ``cfg``, ``key`` (not a PRNG key), ``points`` (not real ``(N, 2)``,
        N ≥ 1) or ``valid`` (not a bool / 0-1 mask of shape ``(N,)``).

    Called eagerly it is compiled once per ``cfg`` (:func:`jaxslam.compilation.call_compiled`):
    uncompiled, every call traced its rounds afresh and compiled them again (1.1 s a call for
    60 points, the programs kept: ~320 memory mappings a call).
    """
    check_ransac_config(cfg)
    check_key(key)
    pts, remaining = _prepare(points, valid)  # the values known now, checked now
    return call_compiled(("lines.extract_lines", cfg), lambda k, p, r: _extract_lines(k, p, r, cfg),
                         (key, pts, remaining), after="auto")


def _extract_lines(key, points, valid, cfg):
    """:func:`extract_lines`' computation."""
    check_ransac_config(cfg)
    pts, remaining = _prepare(points, valid)

    def dead(remaining, k):
        return jnp.zeros((), jnp.int32), jnp.zeros_like(remaining)

    def body(carry, k):
        remaining, alive = carry
        if cfg.stop_on_fail:  # after Algorithm 1's break the hypotheses need not be drawn
            support_n, final = jax.lax.cond(alive, lambda r, k: _ransac_round(pts, r, k, cfg), dead,
                                            remaining, k)
        else:
            support_n, final = _ransac_round(pts, remaining, k, cfg)
        run = _in_run(final, cfg)
        ok = alive & (support_n >= cfg.min_inliers) & (jnp.sum(run) >= cfg.min_inliers)
        rec = _record(pts, run, ok, cfg)
        remaining = remaining & ~rec.inliers
        alive = alive & ok if cfg.stop_on_fail else alive
        return (remaining, alive), rec

    keys = jax.random.split(key, cfg.max_lines)
    (remaining, _), lines = jax.lax.scan(body, (remaining, jnp.asarray(True)), keys)
    return lines, remaining


def match_predicted(points, valid, pred_rho, pred_theta, pred_mask, cfg=DEFAULT_RANSAC, gate=0.2):
    """Search the scan for M predicted lines first (paper 004, "Feature matching"), in order.

    For each predicted line (``lax.scan``): remaining points within ``gate`` [m] of it are fitted
    by least squares, inliers re-selected within ``cfg.threshold`` of that fit, fitted and
    re-selected once more, and fitted again;
    matched when ``pred_mask`` is set and ≥ ``cfg.min_inliers`` points remain, which then leave
    the scan.

    Args:
      points, valid: as :func:`extract_lines`.
      pred_rho, pred_theta: ``(M,)`` predicted lines in the scan frame (Hesse form).
      pred_mask: ``(M,)`` bool (or 0/1 integers), False for unused prediction slots.
      cfg: :class:`RansacConfig` (static).  gate: [m], traced; a real scalar > 0 (a string,
        a bool or a complex number is an :class:`~jaxslam.errors.InputError` naming ``gate``).

    Returns:
      ``(lines, remaining)``: :class:`Lines` of length M aligned with the predictions
      (``valid`` = matched), and the ``(N,)`` mask of valid points left over.  Called eagerly
      it is compiled once per ``cfg`` (as :func:`extract_lines`).
    """
    args = _check_match(points, valid, pred_rho, pred_theta, pred_mask, cfg, gate)  # values known now
    return call_compiled(("lines.match_predicted", cfg), lambda *a: _match_predicted(*a, cfg), args, after="auto")


def _check_match(points, valid, pred_rho, pred_theta, pred_mask, cfg, gate):
    """:func:`match_predicted`'s checks: ``(points, valid, pred_rho, pred_theta, pred_mask, gate)``
    as arrays (the points zeroed and invalid where not finite)."""
    check_ransac_config(cfg)
    pts, remaining = _prepare(points, valid)
    dt = pts.dtype
    check_real(pred_rho, "pred_rho")
    check_real(pred_theta, "pred_theta")
    check_mask(pred_mask, "pred_mask")  # a float 0.2 counted as a prediction in use
    pred_rho = jnp.asarray(pred_rho, dt)
    pred_theta = jnp.asarray(pred_theta, dt)
    pred_mask = jnp.asarray(pred_mask, bool)
    if pred_rho.ndim != 1 or pred_theta.shape != pred_rho.shape or pred_mask.shape != pred_rho.shape:
        raise InputError(f"pred_rho, pred_theta, pred_mask: expected equal shapes (M,), got "
                         f"{pred_rho.shape}, {pred_theta.shape}, {pred_mask.shape}")
    bad_gate = InputError(f"gate: expected a distance > 0 [m] (a scalar), got {gate!r}")
    if not isinstance(gate, (str, bytes)) and np.ndim(gate) != 0:
        raise bad_gate
    _positive_number(gate, "gate", bad_gate, finite=False)
    if not is_concrete(gate):
        check_real(gate, "gate")  # a traced complex gate (static dtype)
    return pts, remaining, pred_rho, pred_theta, pred_mask, jnp.asarray(gate, dt)


def _match_predicted(points, valid, pred_rho, pred_theta, pred_mask, gate, cfg):
    """:func:`match_predicted`'s computation."""
    pts, remaining, pred_rho, pred_theta, pred_mask, gate = _check_match(points, valid, pred_rho, pred_theta,
                                                                         pred_mask, cfg, gate)
    dt = pts.dtype
    thr = jnp.asarray(cfg.threshold, dt)

    def match(remaining, pred):
        r0, t0, m = pred
        gated = remaining & (point_line_distance(pts, r0, t0) <= gate) & m
        r1, t1 = fit_line(pts, gated)
        inl = remaining & (point_line_distance(pts, r1, t1) <= thr) & m
        # A second refit/reselect round sheds the points of a neighbouring wall that the wide
        # gate let into the first fit (near corners they tilt it).
        r2, t2 = fit_line(pts, inl)
        inl = _in_run(remaining & (point_line_distance(pts, r2, t2) <= thr) & m, cfg)
        ok = m & (jnp.sum(gated) >= 2) & (jnp.sum(inl) >= cfg.min_inliers)
        rec = _record(pts, inl, ok, cfg)
        return remaining & ~rec.inliers, rec

    def skip(remaining, pred):
        return remaining, jax.tree.map(jnp.zeros_like, jax.eval_shape(match, remaining, pred)[1])

    def body(remaining, pred):
        # An unused prediction slot costs nothing (under vmap both branches run, as before).
        return jax.lax.cond(pred[2], match, skip, remaining, pred)

    remaining, lines = jax.lax.scan(body, remaining, (pred_rho, pred_theta, pred_mask))
    return lines, remaining


def extract_guided(key, points, valid, pred_rho, pred_theta, pred_mask, cfg=DEFAULT_RANSAC, gate=0.2):
    """Predicted lines first (:func:`match_predicted`), then RANSAC (:func:`extract_lines`) on the rest.

    Returns ``(matched, new, remaining)``: Lines (M) aligned with the predictions, Lines
    (``cfg.max_lines``) of new features, and the ``(N,)`` mask of points neither took.
    """
    check_key(key)  # before the matching runs
    matched, remaining = match_predicted(points, valid, pred_rho, pred_theta, pred_mask, cfg, gate)
    new, remaining = extract_lines(key, points, remaining, cfg)
    return matched, new, remaining
