"""2D range-bearing observation of point landmarks (real-data systems, issue 9).

Robot pose ``s = (x, y, φ, …)`` (only the first three entries are read), landmark
``l = (l_x, l_y)``; the sensor sits at the pose (Victoria Park's state is the
laser's position, MRCLAM's camera is at the robot centre)::

    r = ‖l − p‖,   β = wrap(atan2(l_y − y, l_x − x) − φ)            (observe)
    l = p + r (cos(φ + β), sin(φ + β))                               (inverse)

Bearing is counter-clockwise positive from the sensor's forward axis (MRCLAM:
data README §1 confirms the sign; Victoria Park: the loader subtracts the
laser's π/2 offset).  :func:`residual` wraps the bearing component, so a
measurement at +179° against a prediction at −179° is a 2° innovation, not
358°.  Jacobians come from ``jax.jacfwd`` in the filters; the range uses
:func:`jaxslam.linalg.safe_norm` so its derivative at zero distance is finite.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from ..errors import InputError
from ..linalg import check_numbers, check_real, is_concrete, safe_norm, wrap_angle

__all__ = ["observe", "inverse", "residual"]


def _vec(x, n: int, name: str, exact: bool = True):
    """``x`` as a 1-D array of ``n`` entries (``exact=False``: at least ``n``), checked statically
    (free under ``jit``): a (2,) pose used to be read with its heading from a clamped index.
    A complex ``x`` is refused (its imaginary part was dropped or leaked into the bearing), and so
    are a bool one (True read as 1 m / 1 rad) and non-numbers (a string was JAX's bare TypeError)."""
    check_real(x, name, allow_bool=False)
    dt = getattr(x, "dtype", None)
    if dt is None and is_concrete(x):
        check_numbers(x, name)
    elif dt is not None and np.dtype(dt).kind not in "iuf":
        raise InputError(f"{name}: expected numbers, got dtype {np.dtype(dt)}")
    x = jnp.asarray(x)
    if x.ndim != 1 or (x.shape[0] != n if exact else x.shape[0] < n):
        raise InputError(f"{name}: expected shape ({n}{'' if exact else '+'},), got {tuple(np.shape(x))}")
    return x


def observe(s, l, params=None):
    """Predicted ``(r, β)`` of landmark ``l`` from pose ``s``."""
    del params
    s, l = _vec(s, 3, "s", exact=False), _vec(l, 2, "l", exact=False)
    d = l[:2] - s[:2]
    # Double-where guard: at l = p the bearing is undefined; it is evaluated as atan2(0, 1) = 0
    # (atan2(0, 0) = 0 too) with zero partials, so jacfwd's bearing row is finite, not NaN.
    has = (d[0] != 0) | (d[1] != 0)
    bearing = jnp.arctan2(jnp.where(has, d[1], 0.0), jnp.where(has, d[0], 1.0))
    return jnp.stack([safe_norm(d), wrap_angle(bearing - s[2])])


def inverse(s, z, params=None):
    """Landmark position from pose ``s`` and measurement ``z = (r, β)``."""
    del params
    s, z = _vec(s, 3, "s", exact=False), _vec(z, 2, "z")
    a = s[2] + z[1]
    return jnp.stack([s[0] + z[0] * jnp.cos(a), s[1] + z[0] * jnp.sin(a)])


def residual(z, zhat):
    """``z − ẑ`` with the bearing wrapped to [−π, π)."""
    z, zhat = _vec(z, 2, "z"), _vec(zhat, 2, "zhat")
    return jnp.stack([z[0] - zhat[0], wrap_angle(z[1] - zhat[1])])
