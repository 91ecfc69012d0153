"""Differential flatness of the paper-000 quadcopter: linear model, references, inverse map.

Paper 000, Sec. 2.2.1-2.2.3, eq. 4-9 and 15-19.  Frames: N is NED (n̂3 down, gravity
+g n̂3), B the body frame (b̂3 down, thrust −f_T b̂3).  The flat output is
y_d = [ρ_d (3,), ψ_d]; the LQR state is r = [ρ (3,), ρ̇ (3,), ψ] (eq. 7) and its input
u = [u_p (3,), u_ψ] with u_p = C_NB f_T_B / m (thrust acceleration, inertial frame) and
u_ψ = ψ̇ (eq. 9), so that ṙ = A r + B u + b g (eq. 6/8) is exact, not a linearisation.

Decisions (papers silent or wrong):

* Eq. 17 writes θ_d = atan(z1/z3) and φ_d = asin(−z2).  jaxslam uses
  φ_d = atan2(−z2, ‖(z1, z3)‖) and θ_d = atan2(z1, z3).  Both equal the paper's formulas for
  ‖z‖ = 1 and z3 > 0 (thrust pointing up, normal flight), but atan2 keeps the correct quadrant
  when z3 ≤ 0 (commanded downward acceleration above g: the exact inverse then has |θ_d| > 90°)
  and both stay differentiable where asin(±1) and z3 = 0 are not.
* Eq. 16 divides by f_T.  jaxslam never divides: φ_d and θ_d (atan2 form) depend only on the
  direction of z, so z = −C3(ψ_d)ᵀ u_p is used unnormalised.  When the commanded thrust
  acceleration ‖u_p‖ falls below ``min_accel`` (default 1e-3 m/s², a commanded free fall) the
  direction is blended continuously toward level, z += (min_accel − ‖u_p‖) b̂3, so u_p = 0 gives
  φ_d = θ_d = 0 with finite gradients; f_T = m ‖u_p‖ (eq. 15) is returned unclipped.
* Eq. 18 misprints the ψ̇ row of eq. 3; the right one is ψ̇ = (q sin φ + r cos φ)/cos θ.  With
  q_d = 0 it gives eq. 19, r_d = u_ψ cos θ_d / cos φ_d, which jaxslam uses.  cos φ_d is
  ‖(z1, z3)‖ ≥ 0 and is clipped below at 1e-6 (only reached for horizontal thrust).
* :func:`feedforward` (not in the paper) gives the full flatness reference of the 12-state model:
  attitude Λ_d from eq. 16-17 along y_d(t), body rates ω_d = D(Λ_d)⁻¹ Λ̇_d (inverse of eq. 3),
  Λ̇_d and ω̇_d by forward-mode autodiff (``jax.jvp``) in t, torques τ = J ω̇_d + ω_d × J ω_d
  (eq. 2 solved for τ), and the body velocity v_B = C_NBᵀ ρ̇_d.  Fed open loop through eq. 2
  (RK4) it reproduces ρ_d: the input must be sampled at the step midpoint t_k + dt/2 (or
  evaluated inside the RK4 stages); holding u_ff(t_k) over the step is only first order and
  the open-loop attitude integrates that half-step delay (1.1 cm over 10 s at dt = 0.01 s on
  the figure-8, against 2e-5 m at the midpoint and 1e-8 m inside the stages).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ..dynamics._checks import as_scalar, real_float
from ..geometry.euler import C3, dcm_from_euler
from ..linalg import safe_norm
from .trajectories import _float_dtype, flat_derivatives

__all__ = [
    "linear_model",
    "reference",
    "inverse_map",
    "body_rates_from_euler_rates",
    "feedforward",
]


def linear_model(dtype=None):
    """Matrices of the flat linear model ṙ = A r + B u + b g, paper 000 eq. 6 and 8.

    ``dtype``: floating dtype of the result (default: JAX's default float).
    Returns ``(A (7, 7), B (7, 4), b (7,))`` with A = [[0, I3, 0], [0_{4×7}]] (ρ̇ block),
    B = [0_{3×4}; I4] and b = e6 (gravity enters the down velocity).
    """
    dtype = jnp.result_type(float) if dtype is None else jnp.dtype(dtype)
    A = jnp.zeros((7, 7), dtype).at[0:3, 3:6].set(jnp.eye(3, dtype=dtype))
    B = jnp.zeros((7, 4), dtype).at[3:7, :].set(jnp.eye(4, dtype=dtype))
    b = jnp.zeros((7,), dtype).at[5].set(1.0)
    return A, B, b


def reference(traj, t, g):
    """Desired LQR state and input from the flat output, paper 000 eq. 4-5.

    ``traj``: a trajectory container (:mod:`jaxslam.control.trajectories`); ``t``: s;
    ``g``: gravitational acceleration in m/s² (scalar).
    Returns ``(r_d (7,), u_d (4,))`` with r_d = [ρ_d, ρ̇_d, ψ_d] (m, m/s, rad; NED) and
    u_d = [ρ̈_d − g n̂3, ψ̇_d] (m/s², rad/s).
    """
    Y = flat_derivatives(traj, t, 2)
    g = jnp.asarray(g, Y.dtype)
    r_d = jnp.concatenate([Y[0, 0:3], Y[1, 0:3], Y[0, 3:4]])
    u_d = jnp.concatenate([Y[2, 0:3] - jnp.stack([0.0 * g, 0.0 * g, g]), Y[1, 3:4]])
    return r_d, u_d


def inverse_map(u, psi_d, mass, min_accel=1e-3):
    """Inverse mapping of the LQR output to thrust, attitude and yaw rate; paper 000 eq. 15-19.

    ``u``: (4,) = [u_p (3,) thrust acceleration in N (m/s²), u_ψ = ψ̇ (rad/s)];
    ``psi_d``: desired yaw (rad); ``mass``: kg; ``min_accel``: m/s², below this ‖u_p‖ the
    attitude is blended toward level (module docstring).
    Returns ``(f_T, phi_d, theta_d, r_d)``: thrust magnitude in N (eq. 15), desired roll and
    pitch in rad (eq. 16-17, atan2 form), desired body yaw rate in rad/s (eq. 19, with the
    eq. 18 erratum).  All scalars.
    """
    u = real_float(u, "u", (4,))  # an integer u truncated the mass; a (3,) u read u[3] clamped
    dtype = u.dtype
    # A string mass ("1.56") was parsed by JAX; an array psi_d broadcast the angles.
    psi_d = as_scalar(psi_d, dtype, "psi_d")
    mass = as_scalar(mass, dtype, "mass")
    min_accel = as_scalar(min_accel, dtype, "min_accel")
    up = u[0:3]
    acc = safe_norm(up)
    f_T = mass * acc
    # z ∝ −(m/f_T) C3(ψ_d)ᵀ u_p (eq. 16); the angles below are scale invariant, so no division.
    # Below min_accel the direction is blended continuously toward level (z = b̂3).
    lift = jnp.maximum(min_accel - acc, 0.0)
    z = -(C3(psi_d).T @ up) + jnp.stack([0.0 * lift, 0.0 * lift, lift])
    cphi = safe_norm(z[jnp.array([0, 2])])
    phi_d = jnp.arctan2(-z[1], cphi)
    theta_d = jnp.arctan2(z[0], z[2])
    cos_phi = jnp.cos(phi_d)
    r_d = u[3] * jnp.cos(theta_d) / jnp.maximum(cos_phi, jnp.asarray(1e-6, dtype))
    return f_T, phi_d, theta_d, r_d


def body_rates_from_euler_rates(euler, euler_dot):
    """Body angular velocity ω = D(Λ)⁻¹ Λ̇, the inverse of paper 000 eq. 3.

    ``euler``: (3,) [φ, θ, ψ] rad; ``euler_dot``: (3,) rad/s.  Returns (3,) [p, q, r] rad/s:
    p = φ̇ − ψ̇ sθ, q = θ̇ cφ + ψ̇ cθ sφ, r = −θ̇ sφ + ψ̇ cθ cφ (no division: valid at any pitch).
    A shape other than (3,) is an :class:`InputError` naming the argument (JAX clamped
    ``euler_dot[2]`` of a (2,) array to its last entry).
    """
    euler = real_float(euler, "euler", (3,))
    euler_dot = real_float(euler_dot, "euler_dot", (3,))
    phi, theta = euler[0], euler[1]
    dphi, dtheta, dpsi = euler_dot[0], euler_dot[1], euler_dot[2]
    cf, sf = jnp.cos(phi), jnp.sin(phi)
    ct, st = jnp.cos(theta), jnp.sin(theta)
    return jnp.stack([dphi - dpsi * st,
                      dtheta * cf + dpsi * ct * sf,
                      -dtheta * sf + dpsi * ct * cf])


def _attitude_thrust(traj, t, mass, g):
    """Nominal Λ_d (3,) and f_T along the trajectory (eq. 5, 15-17 with ũ = 0)."""
    r_d, u_d = reference(traj, t, g)
    f_T, phi_d, theta_d, _ = inverse_map(u_d, r_d[6], mass)
    return jnp.stack([phi_d, theta_d, r_d[6]]), f_T


def feedforward(traj, t, params):
    """Full flatness feedforward state and input of the 12-state model (paper 000 eq. 2-5, 15-17).

    ``traj``: trajectory container; ``t``: s;
    ``params``: :class:`jaxslam.dynamics.params.QuadParams` (mass kg, inertia (3,) kg·m² diagonal, g m/s²).
    Returns ``(x_d (12,), u_ff (4,))`` with x_d = [ρ_d (N, m), v_B = C_NBᵀ ρ̇_d (m/s),
    Λ_d = [φ_d, θ_d, ψ_d] (rad), ω_d (rad/s, body)] and u_ff = [f_T (N), τ (3,) (N·m, body)],
    τ = J ω̇_d + ω_d × J ω_d.  Λ̇_d and ω̇_d come from forward-mode autodiff in t, so the
    trajectory must be C⁴ (all containers are).  Fed open loop through eq. 2 it reproduces ρ_d(t).
    """
    as_scalar(t, None, "t")  # check only: "1.0" gave "data type '.0' not understood"
    dtype = _float_dtype(traj, t)
    t = jnp.asarray(t, dtype)
    mass = jnp.asarray(params.mass, dtype)
    g = jnp.asarray(params.g, dtype)
    J = jnp.asarray(params.inertia, dtype)

    def att(tt):
        return _attitude_thrust(traj, tt, mass, g)[0]

    def rates(tt):
        lam, lam_dot = jax.jvp(att, (tt,), (jnp.ones_like(tt),))
        return body_rates_from_euler_rates(lam, lam_dot)

    omega, omega_dot = jax.jvp(rates, (t,), (jnp.ones_like(t),))
    lam, f_T = _attitude_thrust(traj, t, mass, g)
    tau = J * omega_dot + jnp.cross(omega, J * omega)
    Y = flat_derivatives(traj, t, 1)
    v_B = dcm_from_euler(lam).T @ Y[1, 0:3]
    x_d = jnp.concatenate([Y[0, 0:3], v_B, lam, omega])
    u_ff = jnp.concatenate([f_T[None], tau])
    return x_d, u_ff
