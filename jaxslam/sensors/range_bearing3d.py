"""World-frame 3D range/bearing model of paper 001 (eq. 13-15), independent of attitude.

For sensor position p = [x, y, z] and landmark m_j = [x_j, y_j, z_j] (same world frame, m),
with d = m_j − p:

* azimuth   α = atan2(d_y, d_x) ∈ (−π, π], measured in the world x-y plane from +x towards +y;
* elevation β = arcsin(d_z / r) ∈ [−π/2, π/2], positive where the landmark has the larger
  z coordinate: **above** the sensor in paper 001's z-up frame (its eq. 3: z̈ = −g + …),
  **below** it when the positions are NED (as in the paper-000 state);
* range     r = ‖d‖ [m].

Inverse (eq. 15): m_j = p + r [cos β cos α, cos β sin α, sin β].

Decisions (also in docs/papers.md):

* **Order.**  Paper 001 stacks z^S = [β, α, r] (text after eq. 13).  jaxslam returns
  y = [α, β, r], the order of the body-frame model :mod:`jaxslam.sensors.lidar3d`, so a system
  can swap the two models with the same R and the same :func:`innovation`.  ``y[...,
  PAPER001_ORDER]`` gives the paper's order.
* **Elevation formula.**  β is computed as atan2(d_z, √(d_x² + d_y²)), which equals
  arcsin(d_z / r) for every r > 0 and keeps a finite derivative up to ±90°.
* **Noise.**  Paper 001 does not give R^S (its LiDAR is a simulated Velodyne VLP-16).
  :data:`PAPER001_RANGE_BEARING` uses paper 000's Table 4 σ's (0.33°, 0.3°, 0.1 m).
* No field of view: paper 001's LiDAR is 360° and the model has no mask.  Use
  :func:`jaxslam.sensors.lidar3d.in_fov` with a custom spec where one is wanted.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..dynamics._checks import real_float
from ..errors import InputError
from ..linalg import check_float_dtype, check_numbers, is_concrete
from .lidar3d import cartesian_from_spherical, innovation, spherical_from_cartesian

__all__ = [
    "RangeBearingSpec",
    "PAPER001_RANGE_BEARING",
    "PAPER001_ORDER",
    "check_range_bearing_spec",
    "measure",
    "inverse",
    "innovation",
    "measurement_cov",
    "sample_noise",
]

PAPER001_ORDER = (1, 0, 2)
"""Index that turns jaxslam's [α, β, r] into paper 001's z^S = [β, α, r] (and back)."""


class RangeBearingSpec(NamedTuple):
    """Noise of the world-frame range/bearing model (paper 001 eq. 14, R^S = diag(σ²))."""

    sigma_az: Any = math.radians(0.33)
    """Azimuth noise std [rad] (paper 001 silent; paper 000 Table 4 value)."""
    sigma_el: Any = math.radians(0.3)
    """Elevation noise std [rad] (paper 001 silent; paper 000 Table 4 value)."""
    sigma_range: Any = 0.1
    """Range noise std [m] (paper 001 silent; paper 000 Table 4 value)."""


PAPER001_RANGE_BEARING = RangeBearingSpec()
"""σ = (0.33°, 0.3°, 0.1 m): paper 001 gives none, so paper 000's Table 4 values are used."""


def check_range_bearing_spec(spec: RangeBearingSpec, name: str = "spec") -> RangeBearingSpec:
    """Host-side validation: finite, non-negative scalar σ's; raises InputError naming the field."""
    if not isinstance(spec, RangeBearingSpec):
        raise InputError(f"{name}: expected a RangeBearingSpec, got {type(spec).__name__}")
    for f in RangeBearingSpec._fields:
        v = check_numbers(getattr(spec, f), f"{name}.{f}")  # a string was a bare ValueError
        if v.shape != () or not np.isfinite(v) or v < 0:
            raise InputError(f"{name}.{f}: expected a finite scalar >= 0, got {v}")
    return spec


def _check(spec) -> None:
    """:func:`check_range_bearing_spec` when the σ's are concrete, as
    :func:`jaxslam.sensors.lidar3d.measurement_cov` does (a negative σ gave the covariance of
    its absolute value, a NaN one a NaN R); traced σ's (a tuned noise) pass."""
    if not isinstance(spec, RangeBearingSpec) or is_concrete(tuple(spec)):
        check_range_bearing_spec(spec)


def measure(pos, landmark):
    """Range/bearing h_j(x, m_j) of paper 001 eq. 13, returned as y = [α, β, r].

    Args:
      pos: (3,) sensor position [x, y, z] in the world frame [m] (paper 001 x^D[0:3]).
      landmark: (3,) or (L, 3) landmark position(s) in the same frame [m].

    Returns: (3,) or (L, 3) [α rad, β rad, r m] (module docstring for conventions).
    """
    pos = real_float(pos, "pos", (3,))  # lists are converted (``list - list`` was a TypeError)
    if np.ndim(landmark) not in (1, 2) or np.shape(landmark)[-1] != 3:
        raise InputError(f"landmark: expected shape (3,) or (L, 3), got {np.shape(landmark)}")
    return spherical_from_cartesian(real_float(landmark, "landmark") - pos)


def inverse(pos, y):
    """Inverse model m_j = h_j⁻¹(x, z) of paper 001 eq. 15.

    Args: pos: (3,) [m].  y: (3,) or (L, 3) [α, β, r] (jaxslam order).
    Returns: (3,) or (L, 3) landmark position(s) [m].
    """
    pos = real_float(pos, "pos", (3,))
    if np.ndim(y) not in (1, 2) or np.shape(y)[-1] != 3:
        raise InputError(f"y: expected shape (3,) or (L, 3), got {np.shape(y)}")
    return pos + cartesian_from_spherical(real_float(y, "y"))


def measurement_cov(spec: RangeBearingSpec = PAPER001_RANGE_BEARING, dtype=None):
    """R^S = diag(σ_α², σ_β², σ_r²) of paper 001 eq. 14 (jaxslam order), shape (3, 3)."""
    _check(spec)
    dtype = jnp.result_type(float) if dtype is None else check_float_dtype(dtype)  # an int dtype made zeros
    s = jnp.stack([jnp.asarray(spec.sigma_az, dtype), jnp.asarray(spec.sigma_el, dtype),
                   jnp.asarray(spec.sigma_range, dtype)])
    return jnp.diag(s * s)


def sample_noise(key, spec: RangeBearingSpec = PAPER001_RANGE_BEARING, shape_prefix=(),
                 dtype=None):
    """Gaussian noise v^S ~ N(0, R^S) of paper 001 eq. 14.

    Returns (*shape_prefix, 3) with stds (σ_α rad, σ_β rad, σ_r m); ``shape_prefix`` static.
    """
    _check(spec)
    dtype = jnp.result_type(float) if dtype is None else check_float_dtype(dtype)  # an int dtype made zeros
    s = jnp.stack([jnp.asarray(spec.sigma_az, dtype), jnp.asarray(spec.sigma_el, dtype),
                   jnp.asarray(spec.sigma_range, dtype)])
    shape = tuple(int(d) for d in shape_prefix) + (3,)
    # Flat draw + reshape: XLA on CPU compiles it several times faster than an (N, 3) draw.
    return jax.random.normal(key, (int(np.prod(shape)),), dtype).reshape(shape) * s
