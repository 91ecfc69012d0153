"""2D scanning laser range-finder: ray casting against vertical walls (paper 004, Table 5.1).

Frames: a z-up world frame; the 2D pose is ``[x, y, yaw]`` (m, m, rad, yaw counter-clockwise
from +x).  Beam ``i`` leaves the sensor at the scan-plane angle ``a_i = angle_min + i·angle_step``
(counter-clockwise from the sensor's x axis).  Walls are vertical segments given by their
footprints ``(W, 2, 2)`` (two endpoints each, world frame, m) and a mask ``(W,)``.

The scan plane is the body x-y plane (paper 004, ch. 4.1: "the laser plane is parallel to the xy
body plane").  An optional ``tilt = (roll, pitch)`` tilts it: the beam direction in the level
frame that shares the sensor's yaw (the *yaw frame*) is ``v = R_y(pitch) R_x(roll) [cos a, sin a, 0]``
(Z-Y-X Euler angles, z up).  Walls are vertical and unbounded in height, so a tilted beam meets a
wall where its horizontal projection ``h = v[:2]`` does: at horizontal distance ``s`` along
``h/‖h‖`` and slant range ``t = s / ‖h‖``.  :func:`scan_points` inverts this: the point of a return
``t`` projected onto the ground plane is ``t·h`` in the yaw frame (the "groundProjection" of
paper 004, Alg. 2).  Floors and ceilings are not modelled (a steep tilt would hit them first).

URG-04LX preset (Table 5.1): 240° scan, 20 mm - 4 m.  The table rounds the angular resolution to
0.36°; the sensor's real step is 360°/1024 = 0.3516°, and its 682 usable beams cover
682 · 0.3516° = 239.8° ≈ 240° (beam centres 681 · 0.3516° = 239.4° apart), centred on the
sensor's x axis.  Accuracy is given as
"±30 mm for 20 mm - 1 m, ±3 % of the measurement up to 4 m".  jaxslam reads these bounds as 3σ of
zero-mean Gaussian range noise: σ = 10 mm up to ``near`` = 1 m and σ = 1 % of the range beyond
(the two pieces meet at 1 m).  (A reading as 1σ would triple the noise; the bounds as stated
by the maker are usually quoted as maximum errors, hence 3σ.)

Validity: a beam returns when its nearest wall hit lies in ``[range_min, range_max]``; otherwise
(no wall, too near, too far) it is invalid.  Inside ``jit`` nothing raises: invalid returns are
masked, their range reads NaN (a real sensor reports an error code there) and their wall index
reads −1; :func:`scan_points` turns invalid returns into 0 with the mask, never NaN.

Outliers (clutter, people, furniture in front of the wall): with probability ``outlier_prob`` a
valid return is replaced by a range uniform in ``[range_min, true range]``; its wall index reads
−1 (it does not lie on a wall).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..dynamics._checks import real_float
from ..errors import InputError
from ..linalg import check_mask, check_real, check_scalar, is_concrete, reworded

__all__ = [
    "LaserSpec",
    "URG04LX",
    "range_sigma",
    "beam_angles",
    "walls_from_polygon",
    "cast",
    "scan_points",
    "scan",
    "check_scan",
]


class LaserSpec(NamedTuple):
    """Static description of a 2D scanning laser (hashable; pass it as a static argument)."""

    n_beams: int  # number of beams per scan
    angle_min: float  # [rad] scan-plane angle of beam 0 (counter-clockwise from sensor x)
    angle_step: float  # [rad] angle between consecutive beams
    range_min: float  # [m] shortest valid return
    range_max: float  # [m] longest valid return
    sigma_near: float  # [m] range noise σ for ranges ≤ near
    near: float  # [m] where the noise switches from absolute to relative
    sigma_rel: float  # [-] range noise σ / range for ranges > near


_URG_STEP = 2.0 * math.pi / 1024.0
URG04LX = LaserSpec(
    n_beams=682,
    angle_min=-(682 - 1) / 2.0 * _URG_STEP,
    angle_step=_URG_STEP,
    range_min=0.02,
    range_max=4.0,
    sigma_near=0.01,  # Table 5.1: ±30 mm read as 3σ
    near=1.0,
    sigma_rel=0.01,  # Table 5.1: ±3 % read as 3σ
)
"""Hokuyo URG-04LX(-UG01), paper 004 Table 5.1 (accuracy bounds read as 3σ; module docstring)."""


def _check_spec(spec):
    if not isinstance(spec, LaserSpec):
        raise InputError(f"spec: expected a LaserSpec, got {type(spec).__name__}")
    if not isinstance(spec.n_beams, (int, np.integer)) or isinstance(spec.n_beams, bool) or spec.n_beams < 1:
        raise InputError(f"spec.n_beams: expected a positive int, got {spec.n_beams!r}")
    for f in ("angle_min", "angle_step"):
        check_scalar(getattr(spec, f), f"spec.{f}")
    for f in ("range_min", "sigma_near", "near", "sigma_rel"):
        check_scalar(getattr(spec, f), f"spec.{f}", lower=0)
    if not check_scalar(spec.range_max, "spec.range_max") > spec.range_min:
        raise InputError(f"spec.range_max: must exceed spec.range_min = {spec.range_min:g}, got {spec.range_max:g}")


def _fdtype(x):
    dt = jnp.result_type(x)
    return dt if jnp.issubdtype(dt, jnp.floating) else jnp.result_type(float)


def range_sigma(ranges, spec):
    """Range-noise standard deviation [m] at the (true) range ``ranges`` (any shape)."""
    _check_spec(spec)
    r = real_float(ranges, "ranges")  # integer ranges cast sigma_near to int: 0.01 read as 0
    return jnp.where(r <= spec.near, jnp.asarray(spec.sigma_near, r.dtype), spec.sigma_rel * r)


def beam_angles(spec, dtype=None):
    """Scan-plane angles ``(n_beams,)`` [rad] of the beams: ``angle_min + i·angle_step``.

    ``dtype`` defaults to JAX's default float (float64 only when x64 is on).
    """
    _check_spec(spec)
    dtype = jax.dtypes.canonicalize_dtype(jnp.result_type(float) if dtype is None else dtype)
    if not jnp.issubdtype(dtype, jnp.floating):  # int32 angles were truncated to -2, -2, ...
        raise InputError(f"dtype: beam angles need a floating dtype, got {dtype}")
    i = jnp.arange(spec.n_beams, dtype=dtype)
    return jnp.asarray(spec.angle_min, dtype) + i * jnp.asarray(spec.angle_step, dtype)


def walls_from_polygon(vertices, closed=True):
    """Wall segments ``(W, 2, 2)`` (NumPy, float64) from a polyline of vertices ``(V, 2)`` [m].

    Host-side.  ``closed=True`` adds the segment from the last vertex back to the first
    (``W = V``); otherwise ``W = V − 1``.

    Raises:
      InputError: not a (V, 2) array of finite numbers, too few vertices, or a zero-length
        segment (repeated consecutive vertices).
    """
    try:
        v = np.asarray(vertices, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise InputError(f"vertices: expected a (V, 2) array of numbers ({e})") from None
    if v.ndim != 2 or v.shape[1] != 2:
        raise InputError(f"vertices: expected shape (V, 2), got {v.shape}")
    need = 3 if closed else 2
    if v.shape[0] < need:
        raise InputError(f"vertices: a {'closed' if closed else 'open'} polygon needs at least {need} "
                         f"vertices, got {v.shape[0]}")
    if not np.all(np.isfinite(v)):
        raise InputError("vertices: contains NaN or Inf")
    end = np.roll(v, -1, axis=0) if closed else v[1:]
    start = v if closed else v[:-1]
    walls = np.stack([start, end], axis=1)
    lengths = np.linalg.norm(walls[:, 1] - walls[:, 0], axis=1)
    if np.any(lengths == 0.0):
        raise InputError(f"vertices: zero-length wall(s) at segment index {np.flatnonzero(lengths == 0).tolist()} "
                         "(repeated consecutive vertices)")
    return walls


def _directions(spec, dtype, tilt):
    """Yaw-frame horizontal beam directions h ``(n, 2)`` (unit length when level)."""
    a = beam_angles(spec, dtype)
    ca, sa = jnp.cos(a), jnp.sin(a)
    if tilt is None:
        return jnp.stack([ca, sa], axis=-1)
    check_real(tilt, "tilt")
    tilt = jnp.asarray(tilt, dtype)
    if tilt.shape != (2,):
        raise InputError(f"tilt: expected shape (2,) = (roll, pitch), got {tilt.shape}")
    roll, pitch = tilt[0], tilt[1]
    # v = R_y(pitch) R_x(roll) [cos a, sin a, 0]; keep its horizontal part.
    hx = ca * jnp.cos(pitch) + sa * jnp.sin(roll) * jnp.sin(pitch)
    hy = sa * jnp.cos(roll)
    return jnp.stack([hx, hy], axis=-1)


def _check_geometry(pose, walls, wall_mask):
    if pose.shape != (3,):
        raise InputError(f"pose: expected shape (3,) = [x, y, yaw], got {pose.shape}")
    if walls.ndim != 3 or walls.shape[1:] != (2, 2):
        raise InputError(f"walls: expected shape (W, 2, 2), got {walls.shape}")
    if wall_mask.shape != walls.shape[:1]:
        raise InputError(f"wall_mask: expected shape ({walls.shape[0]},), got {wall_mask.shape}")


def cast(pose, walls, wall_mask, spec, tilt=None):
    """Noise-free ray casting of every beam against every wall (nearest hit wins).

    Args:
      pose: ``(3,)`` [x, y, yaw] of the sensor (world frame; m, m, rad).  Sets the dtype.
      walls: ``(W, 2, 2)`` wall footprints (world frame, m).
      wall_mask: ``(W,)`` bool, False for unused wall slots.
      spec: :class:`LaserSpec` (static).
      tilt: optional ``(2,)`` (roll, pitch) [rad] of the scan plane (module docstring).

    Returns:
      ``(ranges, valid, wall)``: slant ranges ``(n,)`` [m] (NaN where invalid), ``valid (n,)``
      bool (a wall hit within [range_min, range_max]), ``wall (n,)`` int32 index of the wall hit
      (−1 where invalid).
    """
    _check_spec(spec)
    check_real(pose, "pose")  # complex inputs lost their imaginary part with only a warning
    check_real(walls, "walls")
    check_mask(wall_mask, "wall_mask")  # a float 0.1 or NaN counted as a used wall
    pose = jnp.asarray(pose)
    dtype = _fdtype(pose)
    pose = pose.astype(dtype)
    walls = jnp.asarray(walls, dtype)
    wall_mask = jnp.asarray(wall_mask, bool)
    _check_geometry(pose, walls, wall_mask)
    if walls.shape[0] == 0:  # no wall: no beam returns (argmin over no wall used to fail)
        n = spec.n_beams
        if tilt is not None:
            _directions(spec, dtype, tilt)  # the same checks of tilt as with walls
        return jnp.full((n,), jnp.nan, dtype), jnp.zeros((n,), bool), jnp.full((n,), -1, jnp.int32)
    h = _directions(spec, dtype, tilt)  # (n, 2) yaw frame
    hn = jnp.sqrt(jnp.sum(h * h, axis=-1))  # ‖h‖ ≤ 1 (cos of the beam's elevation)
    c, s = jnp.cos(pose[2]), jnp.sin(pose[2])
    u = jnp.stack([c * h[:, 0] - s * h[:, 1], s * h[:, 0] + c * h[:, 1]], axis=-1)  # world, (n, 2)
    u = u / jnp.maximum(hn, jnp.finfo(dtype).tiny)[:, None]
    a, b = walls[:, 0], walls[:, 1]  # (W, 2)
    e = b - a
    w = a - pose[:2]
    # p + s·u = a + v·e  →  s = (w × e)/(u × e), v = (w × u)/(u × e)
    den = u[:, None, 0] * e[None, :, 1] - u[:, None, 1] * e[None, :, 0]  # (n, W)
    w_e = (w[:, 0] * e[:, 1] - w[:, 1] * e[:, 0])[None, :]
    w_u = w[None, :, 0] * u[:, None, 1] - w[None, :, 1] * u[:, None, 0]
    scale = jnp.sqrt(jnp.sum(e * e, axis=-1))[None, :]
    ok_den = jnp.abs(den) > 64 * jnp.finfo(dtype).eps * scale
    safe_den = jnp.where(ok_den, den, 1.0)
    dist = w_e / safe_den
    v = w_u / safe_den
    hit = ok_den & (dist > 0) & (v >= 0) & (v <= 1) & wall_mask[None, :]
    dist = jnp.where(hit, dist, jnp.inf)
    k = jnp.argmin(dist, axis=1)
    s_best = jnp.take_along_axis(dist, k[:, None], axis=1)[:, 0]
    any_hit = jnp.any(hit, axis=1)
    t = jnp.where(any_hit, s_best, 0.0) / jnp.maximum(hn, jnp.finfo(dtype).tiny)
    valid = any_hit & (t >= spec.range_min) & (t <= spec.range_max)
    ranges = jnp.where(valid, t, jnp.nan)
    wall = jnp.where(valid, k.astype(jnp.int32), -1)
    return ranges, valid, wall


def scan_points(ranges, valid, spec, tilt=None):
    """Ground-plane points ``(n, 2)`` [m] of a scan in the sensor's yaw frame (paper 004 Alg. 2).

    A return ``t`` on beam ``a`` lands at ``t · h(a)``, ``h`` the horizontal part of the tilted
    beam direction (module docstring); without tilt ``t·[cos a, sin a]``.  Invalid returns
    (``valid`` False, or non-finite ranges) come back as ``[0, 0]``; the returned mask
    ``(n,)`` is ``valid & isfinite(ranges)``.
    """
    _check_spec(spec)
    check_real(ranges, "ranges")
    r = jnp.asarray(ranges)
    dtype = _fdtype(r)
    r = r.astype(dtype)
    if r.shape != (spec.n_beams,):
        raise InputError(f"ranges: expected shape ({spec.n_beams},), got {r.shape}")
    if np.shape(valid) != (spec.n_beams,):  # a (1,) mask broadcast over every beam
        raise InputError(f"valid: expected shape ({spec.n_beams},), got {np.shape(valid)}")
    check_mask(valid, "valid")  # a float 0.5 counted as a valid return
    mask = jnp.asarray(valid, bool) & jnp.isfinite(r)
    r = jnp.where(mask, r, 0.0)
    h = _directions(spec, dtype, tilt)
    return r[:, None] * h, mask


def scan(key, pose, walls, wall_mask, spec, tilt=None, outlier_prob=0.0):
    """A noisy scan: :func:`cast` + Gaussian range noise (Table 5.1 read as 3σ) + clutter outliers.

    Args: as :func:`cast`, plus ``key`` (PRNG key) and ``outlier_prob`` (probability that a valid
    return is replaced by a uniform range in ``[range_min, true range]``; traced).

    Returns:
      ``(ranges, valid, wall)``: noisy ranges ``(n,)`` [m] (NaN where invalid), ``valid (n,)``
      (a wall or clutter return whose *measured* range lies in [range_min, range_max]),
      ``wall (n,)`` int32 index of the wall the return lies on (−1 for clutter and invalid).
    """
    if is_concrete(outlier_prob):  # 2.0 made every return clutter, -1 or NaN none, without a word
        reworded(lambda: check_scalar(outlier_prob, "outlier_prob", lower=0),
                 f"outlier_prob: expected a probability in [0, 1], got {outlier_prob!r}", upper=1.0)
    t, valid, wall = cast(pose, walls, wall_mask, spec, tilt)
    dtype = t.dtype
    k_noise, k_out, k_u = jax.random.split(key, 3)
    t0 = jnp.where(valid, t, spec.range_min)
    noisy = t0 + range_sigma(t0, spec) * jax.random.normal(k_noise, t0.shape, dtype)
    is_out = valid & (jax.random.uniform(k_out, t0.shape, dtype) < outlier_prob)
    u = jax.random.uniform(k_u, t0.shape, dtype)
    clutter = spec.range_min + u * (t0 - spec.range_min)
    meas = jnp.where(is_out, clutter, noisy)
    ok = valid & (meas >= spec.range_min) & (meas <= spec.range_max)
    ranges = jnp.where(ok, meas, jnp.nan)
    wall = jnp.where(ok & ~is_out, wall, -1)
    return ranges, ok, wall


def check_scan(ranges, spec):
    """Host-side check of a measured scan; returns the NumPy bool mask ``(n,)`` of usable returns.

    Usable: finite and within ``[range_min, range_max]`` (NaN/Inf/0 are the usual "no return"
    codes of real drivers).

    Raises:
      InputError: ``ranges`` is not numeric, not 1-D, or its length is not ``spec.n_beams``.
    """
    _check_spec(spec)
    arr = np.asarray(ranges)
    if arr.dtype.kind not in "fiu" or arr.dtype == bool:
        raise InputError(f"ranges: expected numbers, got dtype {arr.dtype}")
    if arr.ndim != 1:
        raise InputError(f"ranges: expected a 1-D scan of {spec.n_beams} ranges, got shape {arr.shape}")
    if arr.shape[0] != spec.n_beams:
        raise InputError(f"ranges: expected {spec.n_beams} ranges (spec.n_beams), got {arr.shape[0]}")
    r = arr.astype(np.float64)
    with np.errstate(invalid="ignore"):
        return np.isfinite(r) & (r >= spec.range_min) & (r <= spec.range_max)
