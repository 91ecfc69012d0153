"""Quadcopter dynamics models, parameters and integrators.

* :mod:`.euler_ned`  paper 000 eq. 1-3: 12-state NED rigid body, input
  [f_T, τ].
* :mod:`.rotor`      paper 001 eq. 1-4: z-up world frame, rotor gyroscopic
  term, rotor-speed mixer, converters to the paper-000 layout.
* :mod:`.quaternion_quad` paper 004 eq. 3.10-3.16: 13-state quaternion model
  (NED, same input as euler_ned), RK4 + renormalisation step.
* :mod:`.params`     parameter containers and paper presets.
* :mod:`.integrators` RK4 step, ``lax.scan`` rollout, jacfwd linearisation, the RK4
  step's exact Jacobian from the field's (``rk4_linearized``).

Both models have the signature ``f(x, u, params) -> ẋ`` so they plug into
:func:`rk4_step`, :func:`rollout` and :func:`linearize` unchanged.
"""

from . import euler_ned, integrators, params, quaternion_quad, rotor
from .integrators import check_dt, linearize, rk4_field, rk4_linearized, rk4_step, rollout
from .params import (
    PAPER000,
    PAPER001,
    PAPER001_MISMATCH,
    QuadParams,
    RotorQuadParams,
    as_arrays,
    validate_params,
)

__all__ = [
    "euler_ned",
    "quaternion_quad",
    "rotor",
    "params",
    "integrators",
    "QuadParams",
    "RotorQuadParams",
    "PAPER000",
    "PAPER001",
    "PAPER001_MISMATCH",
    "as_arrays",
    "validate_params",
    "rk4_step",
    "rk4_field",
    "rk4_linearized",
    "rollout",
    "linearize",
    "check_dt",
]
