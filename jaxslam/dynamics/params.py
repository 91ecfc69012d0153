"""Physical parameters of the quadcopter models, with paper presets.

Presets hold plain Python floats/tuples, so importing this module creates no
JAX array and fixes no dtype; the dynamics cast every field to the dtype of
the state they are called with.  ``as_arrays(params, dtype)`` turns a preset
into arrays (e.g. to differentiate with respect to the parameters).

Paper 000 (Table 1): m = 1.56 kg, J = diag(0.1147, 0.0576, 0.1712) kg m².
Paper 001 (Sec. IV): m = 1.477 kg, Ixx = Iyy = 0.01152, Izz = 0.0218 kg m²;
the inertia-mismatch test raises them by 150 % (0.0288, 0.0288, 0.0545) in
the filter only.  g = 9.81 m/s² in both (neither paper prints g).

Paper 001 gives no rotor data (arm length, thrust and drag coefficients,
rotor inertia I_r).  jaxslam chooses values typical of a 1.5 kg, 10-inch
propeller quadcopter (the Hector quadrotor class the paper simulates):

* arm_length 0.215 m (rotor hub to centre of mass),
* k_thrust 1.5e-5 N s²/rad² -> hover at ω ≈ 491 rad/s (≈ 4700 rpm),
* k_drag 3.0e-7 N m s²/rad² (k_drag / k_thrust = 0.02 m, a usual ratio),
* rotor_inertia 6.0e-5 kg m² (propeller + motor bell about its spin axis).

They only scale the rotor-speed input mapping and the gyroscopic term; the
paper's results do not depend on them.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from ..errors import InputError
from ._checks import real_numbers

__all__ = [
    "QuadParams",
    "RotorQuadParams",
    "PAPER000",
    "PAPER001",
    "PAPER001_MISMATCH",
    "as_arrays",
    "validate_params",
]


class QuadParams(NamedTuple):
    """Rigid-body quadcopter of paper 000 eq. 2 (no rotor effects).

    mass:    scalar, kg.
    inertia: (3,) diagonal of J in body axes [Jxx, Jyy, Jzz], kg m².
    g:       scalar, gravitational acceleration, m/s² (acts along +n̂3, NED).
    """

    mass: float
    inertia: tuple
    g: float = 9.81


class RotorQuadParams(NamedTuple):
    """Quadcopter with rotors, paper 001 eq. 1-3 (plus rotor mixing).

    mass:          scalar, kg.
    inertia:       (3,) [Ixx, Iyy, Izz], kg m².
    g:             scalar, m/s².
    arm_length:    scalar, rotor hub to centre of mass, m.
    k_thrust:      scalar, rotor thrust f_i = k_thrust ω_i², N s²/rad².
    k_drag:        scalar, rotor reaction torque k_drag ω_i², N m s²/rad².
    rotor_inertia: scalar I_r of one rotor about its axis, kg m² (0 removes
                   the gyroscopic term).
    """

    mass: float
    inertia: tuple
    g: float = 9.81
    arm_length: float = 0.215
    k_thrust: float = 1.5e-5
    k_drag: float = 3.0e-7
    rotor_inertia: float = 6.0e-5


PAPER000 = QuadParams(1.56, (0.1147, 0.0576, 0.1712), 9.81)
"""Paper 000, Table 1."""

PAPER001 = RotorQuadParams(1.477, (0.01152, 0.01152, 0.0218), 9.81)
"""Paper 001, Sec. IV (rotor data chosen by jaxslam, see module docstring)."""

PAPER001_MISMATCH = RotorQuadParams(1.477, (0.0288, 0.0288, 0.0545), 9.81)
"""Paper 001, Sec. IV robustness test: inertia +150 % (filter model only)."""


def as_arrays(params, dtype=None):
    """Same container with every field a JAX array of ``dtype``.

    ``dtype`` defaults to JAX's default float (float32 unless x64 is on).
    Works for :class:`QuadParams` and :class:`RotorQuadParams`.
    """
    if dtype is None:
        dtype = jnp.result_type(float)
    return type(params)(*(jnp.asarray(v, dtype=dtype) for v in params))


_POSITIVE_SCALARS = ("mass", "g", "arm_length", "k_thrust", "k_drag")


def validate_params(p):
    """Host-side check of a parameter container; returns it unchanged.

    Raises :class:`jaxslam.errors.InputError` naming the field when a scalar
    field is not a finite scalar, ``inertia`` is not shape (3,), or mass,
    inertia, g, arm_length, k_thrust, k_drag are not positive
    (rotor_inertia must be >= 0).  Not for use under ``jit``.
    """
    if not isinstance(p, (QuadParams, RotorQuadParams)):
        raise InputError(f"params: expected QuadParams or RotorQuadParams, got {type(p).__name__}")
    for name in p._fields:
        val = real_numbers(getattr(p, name), f"params.{name}")  # a bool or complex field too
        want = (3,) if name == "inertia" else ()
        if val.shape != want:
            raise InputError(f"params.{name}: expected shape {want}, got {val.shape}")
        if not np.all(np.isfinite(val)):
            raise InputError(f"params.{name}: contains NaN or Inf")
        if name == "rotor_inertia":
            if val < 0:
                raise InputError(f"params.{name}: must be >= 0, got {float(val)}")
        elif name == "inertia" or name in _POSITIVE_SCALARS:
            if np.any(val <= 0):
                raise InputError(f"params.{name}: must be positive, got {val.tolist()}")
    return p


def _cast(params, dtype):
    """Fields of ``params`` as arrays of ``dtype`` (traced values pass through)."""
    return type(params)(*(jnp.asarray(v, dtype=dtype) for v in params))
