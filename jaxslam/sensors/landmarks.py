"""Landmark sets of the paper scenarios (paper 000 Table 3; paper 001 Sec. IV-B).

Decisions (also in docs/papers.md):

* Paper 000 places 40 landmarks "randomly around the trajectory within the region set by the
  azimuth range, elevation range, and radial range" of Table 3 and does not say what the
  angles are measured from.  jaxslam draws azimuth, elevation and range independently and
  uniformly in their intervals (uniform in each box, not uniform in volume) around a centre
  the scenario states, and maps them with the LiDAR's spherical convention in NED:
  l = centre + r [cos β cos α, cos β sin α, sin β], so α is measured from north towards east
  and **positive elevation points below the horizontal plane** through the centre (n̂3 is
  down), the same sign as the LiDAR elevation of :mod:`jaxslam.sensors.lidar3d`.  Table 3's
  elevation interval is symmetric, so the sign convention does not change the distribution.
* Paper 001's four poles are returned exactly as printed, m_j = [±2, ±2, −1], in its own
  world frame, which is z-up (its eq. 3: z̈ = −g + …): z = −1 lies 1 m below that frame's
  origin.  A NED scenario that wants the poles below the flight must map the frame itself.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import InputError
from ..linalg import check_float_dtype, check_key, check_numbers, check_real, is_concrete
from .lidar3d import cartesian_from_spherical

__all__ = ["generate_landmarks", "pole_landmarks"]


def _interval(v, name):
    try:
        if isinstance(v, (str, bytes)):  # "12" was read as the pair (1, 2)
            raise TypeError
        lo, hi = (float(t) for t in v)
    except (TypeError, ValueError):
        raise InputError(f"{name}: expected a (low, high) pair, got {v!r}")
    if not (math.isfinite(lo) and math.isfinite(hi)) or lo > hi:
        raise InputError(f"{name}: expected finite low <= high, got ({lo}, {hi})")
    return lo, hi


def generate_landmarks(key, n: int = 40, center=(0.0, 0.0, 0.0),
                       az_range=(-math.pi, math.pi),
                       el_range=(-math.radians(50.0), math.radians(50.0)),
                       range_range=(8.0, 20.0), dtype=None):
    """Random landmarks in the region of paper 000 Table 3.

    Args:
      key: PRNG key (the landmark set is a pure function of it).
      n: number of landmarks (static; Table 3: 40).
      center: (3,) centre of the region in N (NED) [m]; the scenario states it.
      az_range: (lo, hi) azimuth [rad]; Table 3: [−180°, 180°].
      el_range: (lo, hi) elevation [rad], positive below the horizontal; Table 3: [−50°, 50°].
      range_range: (lo, hi) distance from the centre [m]; Table 3: [8, 20] m.
      dtype: float dtype (default: JAX's default float); another is an InputError.

    Returns:
      (n, 3) landmark positions in N [m]; azimuth, elevation and range are independent and
      uniform in their intervals.
    """
    try:  # a NaN, an inf or None raised a bare ValueError / OverflowError / TypeError
        bad = isinstance(n, bool) or int(n) != n or n < 1
    except (TypeError, ValueError, OverflowError):
        bad = True
    if bad:
        raise InputError(f"n: expected a positive integer, got {n!r}")
    n = int(n)
    check_key(key)  # an int seed was JAX's bare TypeError from inside the sampler
    az = _interval(az_range, "az_range")
    el = _interval(el_range, "el_range")
    if el[0] < -math.pi / 2 or el[1] > math.pi / 2:
        raise InputError(f"el_range: must lie in [-pi/2, pi/2] rad, got {el}")
    rg = _interval(range_range, "range_range")
    if rg[0] < 0:
        raise InputError(f"range_range: ranges must be >= 0, got {rg}")
    check_real(center, "center")  # a complex centre lost its imaginary part silently
    if np.shape(center) != (3,):
        raise InputError(f"center: expected shape (3,), got {np.shape(center)}")
    if is_concrete(center) and not np.all(np.isfinite(check_numbers(center, "center"))):
        raise InputError(f"center: must be finite, got {center!r}")
    dtype = jnp.result_type(float) if dtype is None else check_float_dtype(dtype)
    lo = jnp.asarray([az[0], el[0], rg[0]], dtype)
    hi = jnp.asarray([az[1], el[1], rg[1]], dtype)
    u = jax.random.uniform(key, (3 * n,), dtype).reshape(n, 3)
    y = lo + u * (hi - lo)
    return jnp.asarray(center, dtype) + cartesian_from_spherical(y)


def pole_landmarks(dtype=None):
    """Paper 001's four pole landmarks m_1..m_4 = [2, 2, −1], [−2, 2, −1], [−2, −2, −1],
    [2, −2, −1] (Sec. IV-B), in paper 001's z-up world frame [m].  Returns (4, 3).
    """
    dtype = jnp.result_type(float) if dtype is None else jnp.dtype(dtype)
    return jnp.asarray([[2.0, 2.0, -1.0], [-2.0, 2.0, -1.0], [-2.0, -2.0, -1.0],
                        [2.0, -2.0, -1.0]], dtype)
