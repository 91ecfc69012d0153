"""Planar ground-vehicle motion models for the real-data systems (issue 9).

Pose ``s = (x, y, φ)`` in metres and radians (φ counter-clockwise from +x).
Every model is a pure function ``f(s, u, dt, ...) -> s'``; Jacobians come from
``jax.jacfwd`` in the filters (the hand forms are oracles in the tests only).

* :func:`unicycle` — odometry velocities ``u = (v, ω)`` held over ``dt``
  (UTIAS MRCLAM: iRobot Create odometry, data README §1).  Exact arc
  integration: x' = x + v/ω (sin(φ+ωΔt) − sin φ), y' = y − v/ω (cos(φ+ωΔt) − cos φ),
  φ' = φ + ωΔt, written with sinc-type functions so it is smooth (and
  differentiable) through ω = 0.  The data README's reference dead reckoning uses
  Euler steps (RMS 2.729 m for robot 1); exact arcs give 2.722 m.
* :func:`ackermann` — the Victoria Park Ute (data README §2, from RFS-SLAM's
  ``ProcessModel_Ackerman2D`` after ACFR's model notes): the state is the
  **laser's** position with the vehicle heading; inputs are the rear-left
  encoder speed v_e and the steering angle α::

      v_c = v_e / (1 − tan(α)·H/L)
      ẋ = v_c cos φ − (v_c/L) tan α (a sin φ + b cos φ)
      ẏ = v_c sin φ + (v_c/L) tan α (a cos φ − b sin φ)
      φ̇ = (v_c/L) tan α

  integrated with one Euler step per held input (as RFS-SLAM does).
* :func:`odometry_increment` — a pose increment ``u = (d, dθ)`` composed as
  ``s ∘ Pose2(d, 0, dθ)``: move forward d, then turn dθ (CMU Plaza ``DR``,
  as gtsam composes it).

Process noise (:func:`input_noise_cov`): the inputs carry white noise, and the
discrete covariance is ``Q = J_u M J_uᵀ`` with ``J_u = ∂f/∂u`` by autodiff.
For held *rates* the input-noise is a density (units (m/s)²·s, (rad/s)²·s):
over a step of length Δt the averaged input has variance M_c/Δt, so
``M = M_c / Δt`` and Q scales with Δt (splitting an interval at a measurement
time leaves the total noise unchanged; Δt = 0 gives Q = 0).  For increments M
is per increment.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import InputError
from ..linalg import is_concrete, wrap_angle
from ._checks import real_numbers

__all__ = [
    "AckermannGeometry",
    "VICTORIA_PARK",
    "unicycle",
    "ackermann",
    "odometry_increment",
    "compose",
    "input_noise_cov",
    "step_input_cov",
    "MOTIONS",
    "motion_model",
]


class AckermannGeometry(NamedTuple):
    """Car geometry [m]: wheelbase L, encoder lateral offset H, laser offsets a (forward), b (lateral)."""

    L: float = 2.83
    H: float = 0.76
    a: float = 3.78
    b: float = 0.50


#: The Victoria Park Ute (data README §2; RFS-SLAM cfg).
VICTORIA_PARK = AckermannGeometry()


def _sinc_terms(w):
    """(sin w / w, (1 − cos w) / w), smooth through w = 0 (Taylor branch).

    (1 − cos w)/w is evaluated as 2 sin²(w/2)/w, which has no cancellation: in float32 the
    direct form lost every digit just above the Taylor branch (0 at w = 2e-4, 4.6 % off at 1e-3).
    float32 switches at 0.1 (with two more Taylor terms: error ~3e-14 there), where the autodiff
    derivative of sin w / w is within ~4e-5 (above 1e-4 it cancelled: 23× off at w = 1.01e-4,
    0.2 % at 1e-2); float64 at 1e-4.
    """
    w = jnp.asarray(w)
    f32 = jnp.finfo(jnp.result_type(w, float)).bits < 64
    small = jnp.abs(w) < (0.1 if f32 else 1e-4)
    ws = jnp.where(small, 1.0, w)
    w2 = w * w
    s_taylor = 1.0 - w2 / 6.0 + w2 * w2 / 120.0
    c_taylor = w / 2.0 - w * w2 / 24.0
    if f32:  # (float64 keeps its form, and its runs their bits)
        s_taylor = s_taylor - w2 * w2 * w2 / 5040.0
        c_taylor = c_taylor + w * w2 * w2 / 720.0
    sh = jnp.sin(0.5 * ws)
    return jnp.where(small, s_taylor, jnp.sin(ws) / ws), jnp.where(small, c_taylor, 2.0 * sh * sh / ws)


def _check_step(s, u, fn: str):
    """Static shapes of a planar step (free under ``jit``): an index past the end was clamped, so
    a (2,) pose read y as its heading and a (1,) input v as its turn rate."""
    if np.shape(s) != (3,):
        raise InputError(f"s: {fn} expects a pose (x, y, φ) of shape (3,), got {np.shape(s)}")
    if np.shape(u) != (2,):
        raise InputError(f"u: {fn} expects an input of shape (2,), got {np.shape(u)}")


def unicycle(s, u, dt):
    """Exact-arc unicycle step with ``u = (v, ω)`` held over ``dt``."""
    _check_step(s, u, "unicycle")
    x, y, phi = s[0], s[1], s[2]
    v, om = u[0], u[1]
    th = om * dt
    sw, cw = _sinc_terms(th)
    d = v * dt
    # forward/lateral displacement in the body frame at the start of the step
    fx = d * sw
    fy = d * cw
    c, sn = jnp.cos(phi), jnp.sin(phi)
    return jnp.stack([x + c * fx - sn * fy, y + sn * fx + c * fy, wrap_angle(phi + th)])


def ackermann(s, u, dt, geom: AckermannGeometry = VICTORIA_PARK):
    """One Euler step of the Victoria Park Ackermann model (laser-centred state)."""
    _check_step(s, u, "ackermann")
    x, y, phi = s[0], s[1], s[2]
    ve, alpha = u[0], u[1]
    L, H, a, b = geom.L, geom.H, geom.a, geom.b
    ta = jnp.tan(alpha)
    vc = ve / (1.0 - ta * H / L)
    c, sn = jnp.cos(phi), jnp.sin(phi)
    k = vc / L * ta
    return jnp.stack([
        x + dt * (vc * c - k * (a * sn + b * c)),
        y + dt * (vc * sn + k * (a * c - b * sn)),
        wrap_angle(phi + dt * k),
    ])


def compose(s, d):
    """SE(2) composition ``s ∘ d`` of two poses (x, y, φ)."""
    c, sn = jnp.cos(s[2]), jnp.sin(s[2])
    return jnp.stack([s[0] + c * d[0] - sn * d[1], s[1] + sn * d[0] + c * d[1], wrap_angle(s[2] + d[2])])


def odometry_increment(s, u, dt=None):
    """``s ∘ Pose2(d, 0, dθ)`` for ``u = (d, dθ)`` (``dt`` unused; same signature as the others)."""
    del dt
    return compose(s, jnp.stack([u[0], jnp.zeros_like(u[0]), u[1]]))


def input_noise_cov(f, s, u, dt, M):
    """Discrete process noise ``J_u M J_uᵀ`` of motion ``f(s, u, dt)`` (J_u by ``jacfwd``).

    ``M`` (d_u, d_u) is the input covariance of this step (for held rates pass
    ``M_c / Δt``, see the module docstring).  A concrete negative ``dt`` is an
    :class:`~jaxslam.errors.InputError`.
    """
    _check_dt(dt)
    Ju = jax.jacfwd(lambda u_: f(s, u_, dt))(u)
    return Ju @ M @ Ju.T


def _check_dt(dt):
    """A concrete step ``dt`` must be finite and >= 0 (0 is an empty step); traced values pass."""
    if dt is None or not is_concrete(dt):
        return
    a = real_numbers(dt, "dt")
    if not np.all(np.isfinite(a)) or np.any(a < 0):
        raise InputError(f"dt: expected a finite step >= 0 s, got {dt!r}")


def step_input_cov(M, dt, input_mode: str = "rate"):
    """Input covariance of one step: ``M / Δt`` for held rates (M a density), ``M`` for increments.

    ``Δt`` is floored at 1e-9 s; with Δt = 0 the rate Jacobian is 0, so Q = 0.  A concrete
    negative or non-finite ``dt`` (held rates) is an :class:`~jaxslam.errors.InputError` (it was floored to
    1e-9 s: Q ~ 1e9 M).
    """
    if input_mode not in ("rate", "increment"):
        raise InputError(f"input_mode: expected 'rate' or 'increment', got {input_mode!r}")
    if input_mode == "rate":
        _check_dt(dt)
        return M / jnp.maximum(dt, 1e-9)
    return M


#: Names accepted by :func:`motion_model` (and the systems' ``config.motion``).
MOTIONS = ("unicycle", "ackermann", "increment")


def motion_model(name: str, geometry: AckermannGeometry = VICTORIA_PARK):
    """The motion function ``f(s, u, dt)`` called ``name`` (one of :data:`MOTIONS`)."""
    if name == "unicycle":
        return unicycle
    if name == "ackermann":
        return lambda s, u, dt: ackermann(s, u, dt, geometry)
    if name == "increment":
        return odometry_increment
    raise InputError(f"name: expected a motion model, one of {MOTIONS}, got {name!r}")
