"""Attitude geometry: 3-2-1 Euler angles in NED (paper 000 eq. 1, 3) and
Hamilton unit quaternions (paper 004 ch. 3.1, app. A).

A rotation here always means the body-to-NED map C_NB; Euler angles are
Λ = [φ, θ, ψ]; quaternions are scalar first.
"""

from . import euler, quaternion
from .euler import C1, C2, C3, dcm_from_euler, euler_from_dcm, euler_rate_matrix, euler_rates
from .quaternion import (
    dcm_from_quat,
    euler_from_quat,
    qcanonical,
    qconj,
    qexp,
    qlog,
    qmul,
    qnormalize,
    qrotate,
    quat_from_dcm,
    quat_from_euler,
)

__all__ = [
    "euler",
    "quaternion",
    "C1",
    "C2",
    "C3",
    "dcm_from_euler",
    "euler_from_dcm",
    "euler_rate_matrix",
    "euler_rates",
    "qmul",
    "qconj",
    "qnormalize",
    "qrotate",
    "qcanonical",
    "quat_from_euler",
    "euler_from_quat",
    "dcm_from_quat",
    "quat_from_dcm",
    "qexp",
    "qlog",
]
