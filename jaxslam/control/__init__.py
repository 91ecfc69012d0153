"""Trajectories and control: flat outputs, differential flatness, LQR, PD attitude, DF-LQR.

Paper 000 Sec. 2.2 (eq. 4-20): :mod:`.trajectories` (figure-8, helix, circle, square flat
outputs and their autodiff derivatives), :mod:`.flatness` (linear model eq. 6, references
eq. 4-5, inverse map eq. 15-19, full feedforward), :mod:`.lqr` (differentiable CARE, eq. 12-13),
:mod:`.attitude_pd` (eq. 20) and :mod:`.dflqr` (the whole controller of Fig. 2).  Paper 004
ch. 3.3: :mod:`.smc` (quaternion sliding-mode attitude law, eq. 3.18/3.20, Theorem 3.1).
"""

from . import attitude_pd, dflqr, flatness, lqr, smc, trajectories
from .attitude_pd import PDGains, gains_from_bandwidth, pd_torque
from .dflqr import ControlInfo, DFLQRParams, control, gain, paper000_params
from .flatness import (
    body_rates_from_euler_rates,
    feedforward,
    inverse_map,
    linear_model,
    reference,
)
from .lqr import care, lqr_gain, lyapunov, validate_weights
from .trajectories import Circle, Figure8, Helix, Square, flat_derivatives, flat_output

__all__ = [
    "trajectories",
    "flatness",
    "lqr",
    "attitude_pd",
    "dflqr",
    "smc",
    "Figure8",
    "Helix",
    "Circle",
    "Square",
    "flat_output",
    "flat_derivatives",
    "linear_model",
    "reference",
    "inverse_map",
    "body_rates_from_euler_rates",
    "feedforward",
    "care",
    "lqr_gain",
    "lyapunov",
    "validate_weights",
    "PDGains",
    "gains_from_bandwidth",
    "pd_torque",
    "DFLQRParams",
    "ControlInfo",
    "paper000_params",
    "gain",
    "control",
]
