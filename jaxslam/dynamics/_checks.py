"""Input rules shared by :mod:`jaxslam.dynamics` and :mod:`jaxslam.control` (one copy each).

* :func:`real_float` — the working-array rule of the models: an integer or bool array becomes
  JAX's default float (an integer state used to truncate every parameter, gain and step cast to
  its dtype), a complex one is refused (casting it dropped the imaginary part with only a
  ``ComplexWarning``), a concrete non-number (a string, None) is refused, and an optional static
  shape is checked (JAX clamps out-of-range indices, so a (13,) state was read silently).
* :func:`real_numbers` — host-side: a concrete value as float64 NumPy, refusing complex and bool
  (a weight or a parameter given as ``True`` was read as 1).
* :func:`as_scalar` — a scalar argument (dt, t) as an array of the working dtype; a concrete
  string ("0.1") or complex number is refused instead of parsed.

Every check is static (dtype, shape) or runs only when the value is concrete
(:func:`jaxslam.linalg.is_concrete`), so nothing is added to a jitted program.  The complex /
bool rule is :func:`jaxslam.linalg.check_real`, the filters' too.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from ..errors import InputError
from ..linalg import check_numbers, check_real, check_shape, float_array, is_concrete

__all__ = ["real_float", "real_numbers", "as_scalar", "check_last_dim"]


def real_float(x, name: str, shape=None):
    """``x`` as a real floating JAX array (integer/bool -> JAX's default float, a float dtype
    kept), optionally of static ``shape`` (``None`` entries match any size); complex, a concrete
    non-number or a wrong shape is an :class:`InputError` naming ``name``."""
    x = float_array(x, name)  # complex refused there
    if shape is not None:
        check_shape(x, shape, name)
    return x


def check_last_dim(x, n: int, name: str):
    """:class:`InputError` unless ``x`` has at least one axis and its last is ``n`` long (static)."""
    s = np.shape(x)
    if len(s) == 0 or s[-1] != n:
        raise InputError(f"{name}: expected shape (..., {n}), got {tuple(s)}")
    return x


def real_numbers(value, name: str) -> np.ndarray:
    """Host-side: ``value`` as a float64 NumPy array; complex, bool or non-numbers are an
    :class:`InputError` naming ``name`` (:func:`jaxslam.linalg.check_numbers` plus the dtype)."""
    check_real(value, name, allow_bool=False)
    return check_numbers(value, name)


def as_scalar(v, dtype, name: str):
    """Scalar argument ``v`` (a time step, a time) as a JAX array of ``dtype``; anything but one
    real number (a string — JAX parsed "0.1" —, a bool, a complex value, an array) is an
    :class:`InputError` naming ``name``.  Static dtype and shape checks; only a concrete
    non-array is converted on the host."""
    check_real(v, name, allow_bool=False)
    dt = getattr(v, "dtype", None)
    if dt is not None:
        if np.dtype(dt).kind not in "iuf":  # a NumPy string array skipped the check
            raise InputError(f"{name}: expected a number, got dtype {np.dtype(dt)}")
    elif is_concrete(v):
        check_numbers(v, name)
    if np.ndim(v) != 0:
        raise InputError(f"{name}: expected a scalar, got shape {np.shape(v)}")
    return jnp.asarray(v, dtype=dtype)
