"""Quadcopter with rotor gyroscopic coupling and rotor-speed inputs.

Paper 001, Sec. II-A, eq. 1-4.  The paper writes the state in a z-up world
frame with world-frame velocity, and jaxslam keeps that layout here:

    x = [x, y, z, ẋ, ẏ, ż, φ, θ, ψ, p, q, r]                 (12,)  (eq. 4)
        position and velocity in the world frame W (z up), m and m/s
        φ, θ, ψ   3-2-1 Euler angles of R_b^w = C3(ψ) C2(θ) C1(φ), rad
        p, q, r   body angular velocity in body axes (z up), rad/s
    u = [u1, u2, u3, u4]                                       (4,)
        u1 total thrust along +b̂3 (up), N; u2..u4 body torques, N m

    ṗ = (Iyy − Izz)/Ixx q r − I_r Ω_r q / Ixx + u2 / Ixx     (eq. 1)
    q̇ = (Izz − Ixx)/Iyy p r + I_r Ω_r p / Iyy + u3 / Iyy
    ṙ = (Ixx − Iyy)/Izz p q + u4 / Izz
    Λ̇ = D(φ, θ) ω                                             (eq. 2)
    ẍ = u1/m R[:, 2],   R = R_b^w,   z̈ += −g                 (eq. 3)

Ω_r = ω1 − ω2 + ω3 − ω4 is the net rotor spin along +b̂3; eq. 1's terms are
−ω × (I_r Ω_r b̂3), the rotor angular momentum coupling.

Decisions (paper 001 is silent or misprinted):

* Eq. 2 prints θ̇ = cos(θ) q − sin(φ) r; the correct form (and D of paper 000
  eq. 3, used here) is θ̇ = cos(φ) q − sin(φ) r.
* Eq. 6's R_b^w has a misprinted (1,3) entry; eq. 3 and this module use
  C3(ψ) C2(θ) C1(φ) (:func:`jaxslam.geometry.euler.dcm_from_euler`).
* Rotor layout ("plus" configuration, not given by the paper): rotor i sits
  at angle (i − 1)·90° about +b̂3 from +b̂1 at distance ``arm_length``
  (1 front, 2 left, 3 back, 4 right in the z-up body frame) and spins with
  sign s = (+1, −1, +1, −1) about +b̂3, consistent with Ω_r above.  With
  f_i = k_thrust ω_i² and reaction torque −s_i k_drag ω_i² b̂3 on the body:
      u1 = k Σ ω_i²,  u2 = l k (ω2² − ω4²),  u3 = l k (ω3² − ω1²),
      u4 = k_drag (−ω1² + ω2² − ω3² + ω4²).
* The rotor-acceleration reaction torque I_r Ω̇_r about b̂3 is neglected, as
  in eq. 1 (rotor speeds are inputs, held over a step).
* ``rotor_speeds_from_input`` inverts the mixer; an input that would need a
  negative squared speed (a thrust/torque combination outside what the
  rotors can produce) is clipped to ω_i = 0, so the mixer of the result no
  longer reproduces that input.
* World frame: the paper only says z is up.  For conversion to the paper-000
  layout jaxslam reads W as North-West-Up and the body as
  Front-Left-Up, so W→NED and FLU→FRD are both T = diag(1, −1, −1).  Then
  ρ_N = T p_W, Λ_NED = (φ, −θ, −ψ), ω_FRD = T ω, v_B = C_NBᵀ T v_W and the
  paper-000 input is [u1, u2, −u3, −u4] (``state_to_ned`` and friends).

``f`` and ``f_input`` are jit/vmap/grad-safe and follow the dtype of ``x``.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from ..errors import InputError
from ..geometry.euler import dcm_from_euler, euler_rates
from ..linalg import check_shape
from ._checks import check_last_dim, real_float
from .euler_ned import _state_and_input
from .params import _cast

__all__ = [
    "POS",
    "VEL",
    "ATT",
    "RATE",
    "ROTOR_SPIN",
    "mixer",
    "mixer_matrix",
    "rotor_speeds_from_input",
    "net_rotor_speed",
    "f",
    "f_wrench",
    "f_input",
    "specific_force",
    "hover_input",
    "hover_rotor_speeds",
    "state_to_ned",
    "state_from_ned",
    "input_to_ned",
    "input_from_ned",
    "check_rotor_speeds",
]

POS = slice(0, 3)  # world position (z up), m
VEL = slice(3, 6)  # world velocity, m/s (paper-000 layout uses body velocity)
ATT = slice(6, 9)
RATE = slice(9, 12)

ROTOR_SPIN = (1.0, -1.0, 1.0, -1.0)
"""Spin direction of rotors 1-4 about +b̂3 (Ω_r = Σ s_i ω_i)."""

_T = (1.0, -1.0, -1.0)  # diag of the z-up (NWU/FLU) <-> NED/FRD relabelling


def _rotor_params(params):
    """``params`` unchanged, or :class:`InputError` when it lacks the rotor fields (a paper-000
    :class:`~jaxslam.dynamics.params.QuadParams` gave a bare ``AttributeError: k_thrust``).
    Static (attribute names only): free under ``jit``."""
    missing = [n for n in ("arm_length", "k_thrust", "k_drag", "rotor_inertia") if not hasattr(params, n)]
    if missing:
        raise InputError(f"params: expected RotorQuadParams (rotor fields {missing} missing), "
                         f"got {type(params).__name__}")
    return params


def mixer_matrix(params, dtype=None):
    """(4, 4) matrix M with u = M [ω1², ω2², ω3², ω4²] (see module docstring).

    ``dtype`` defaults to JAX's default float.
    """
    if dtype is None:
        dtype = jnp.result_type(float)
    p = _cast(_rotor_params(params), dtype)
    k, lk, d = p.k_thrust, p.arm_length * p.k_thrust, p.k_drag
    z = jnp.zeros((), dtype)
    return jnp.stack(
        [
            jnp.stack([k, k, k, k]),
            jnp.stack([z, lk, z, -lk]),
            jnp.stack([-lk, z, lk, z]),
            jnp.stack([-d, d, -d, d]),
        ]
    )


def mixer(rotor_speeds, params):
    """Thrust and torques from rotor speeds, paper 001 u = [u1, u2, u3, u4].

    ``rotor_speeds``: (4,) ω_i in rad/s (rotors 1-4, plus layout).
    Returns (4,) [u1 (N), u2, u3, u4 (N m)] in the dtype of the speeds.
    """
    w = check_last_dim(real_float(rotor_speeds, "rotor_speeds"), 4, "rotor_speeds")
    p = _cast(_rotor_params(params), w.dtype)
    s = w * w
    lk = p.arm_length * p.k_thrust
    # Differences before scaling, so symmetric speeds give exactly zero torque
    # (a matmul with FMA leaves an O(eps) residual).
    return jnp.stack(
        [
            p.k_thrust * jnp.sum(s, axis=-1),
            lk * (s[..., 1] - s[..., 3]),
            lk * (s[..., 2] - s[..., 0]),
            p.k_drag * ((s[..., 1] + s[..., 3]) - (s[..., 0] + s[..., 2])),
        ],
        axis=-1,
    )


def rotor_speeds_from_input(u, params):
    """Inverse of :func:`mixer`: rotor speeds (4,) rad/s for u = [u1..u4].

    Squared speeds below 0 (inputs the rotors cannot produce) are clipped to
    0 before the square root (gradient 0 there, never NaN).  Closed form:
    with a = u1/k, b = u2/(l k), c = u3/(l k), e = u4/k_drag,
    ω1² = (a − e − 2c)/4, ω2² = (a + e + 2b)/4, ω3² = (a − e + 2c)/4,
    ω4² = (a + e − 2b)/4.
    """
    u = check_last_dim(real_float(u, "u"), 4, "u")
    p = _cast(_rotor_params(params), u.dtype)
    a = u[..., 0] / p.k_thrust
    b = u[..., 1] / (p.arm_length * p.k_thrust)
    c = u[..., 2] / (p.arm_length * p.k_thrust)
    e = u[..., 3] / p.k_drag
    s = 0.25 * jnp.stack([a - e - 2 * c, a + e + 2 * b, a - e + 2 * c, a + e - 2 * b], axis=-1)
    pos = s > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, s, 1.0)), 0.0)


def net_rotor_speed(rotor_speeds):
    """Ω_r = ω1 − ω2 + ω3 − ω4 (rad/s), paper 001 eq. 1."""
    w = check_last_dim(real_float(rotor_speeds, "rotor_speeds"), 4, "rotor_speeds")
    return w[..., 0] - w[..., 1] + w[..., 2] - w[..., 3]


def f_wrench(x, u, omega_r, params):
    """Paper 001 eq. 1-3 given thrust/torques ``u`` (4,) and Ω_r (scalar).

    ``x``: (12,) paper-001 state (see module docstring); ``params``:
    :class:`~jaxslam.dynamics.params.RotorQuadParams`.  Returns ẋ (12,) in
    the dtype of ``x``.
    """
    x, u = _state_and_input(x, u, 12, 4)
    dt = x.dtype
    omega_r = real_float(omega_r, "omega_r", ()).astype(dt)
    p = _cast(_rotor_params(params), dt)
    vel, lam, w = x[VEL], x[ATT], x[RATE]
    R = dcm_from_euler(lam)
    J = p.inertia
    zero = jnp.zeros((), dt)
    acc = u[0] / p.mass * R[:, 2] - jnp.stack([zero, zero, p.g])
    lam_dot = euler_rates(lam, w)
    # Rotor angular momentum I_r Ω_r b̂3 adds −ω × h: eq. 1's ∓I_r Ω_r q, p terms.
    h = jnp.stack([zero, zero, p.rotor_inertia * omega_r])
    w_dot = (-jnp.cross(w, J * w + h) + u[1:]) / J
    return jnp.concatenate([vel, acc, lam_dot, w_dot])


def f(x, rotor_speeds, params):
    """Paper 001 eq. 1-4 driven by rotor speeds (4,) rad/s.

    u = :func:`mixer` (ω) and Ω_r = ω1 − ω2 + ω3 − ω4 enter
    :func:`f_wrench`.  ``x``: (12,) paper-001 state.  Returns ẋ (12,).
    """
    x, w = _state_and_input(x, rotor_speeds, 12, 4, ("x", "rotor_speeds"))
    return f_wrench(x, mixer(w, params), net_rotor_speed(w), params)


def specific_force(rotor_speeds, params, dtype=None):
    """What an accelerometer reads in body axes: the non-gravitational force per unit mass
    of eq. 3, [0, 0, u1/m] (3,) m/s² with u1 = :func:`mixer` (ω)[0] (z up).

    Equal to R_b^wᵀ(ẍ + g e3) for :func:`f` (the model has no drag), without the rotation:
    it does not depend on the state.  Batched speeds (..., 4) give (..., 3), like :func:`mixer`
    (they raised a bare stacking error: the first row was taken for the thrust).
    """
    w = check_last_dim(real_float(rotor_speeds, "rotor_speeds"), 4, "rotor_speeds")
    w = w if dtype is None else w.astype(dtype)
    p = _cast(params, w.dtype)
    a = mixer(w, params)[..., 0] / p.mass
    zero = jnp.zeros_like(a)
    return jnp.stack([zero, zero, a], axis=-1)


def f_input(x, u, params):
    """Paper 001 eq. 1-4 driven by u = [u1..u4] (the paper's input, eq. 4).

    Ω_r for the gyroscopic term comes from :func:`rotor_speeds_from_input`
    (exact while no squared speed is clipped).  Returns ẋ (12,).
    """
    x, u = _state_and_input(x, u, 12, 4)
    return f_wrench(x, u, net_rotor_speed(rotor_speeds_from_input(u, params)), params)


def hover_input(params, dtype=None):
    """u = [m g, 0, 0, 0] (4,) that holds a level hover in paper 001's model."""
    if dtype is None:
        dtype = jnp.result_type(float)
    p = _cast(params, dtype)
    z = jnp.zeros((), dtype)
    return jnp.stack([p.mass * p.g, z, z, z])


def hover_rotor_speeds(params, dtype=None):
    """Equal rotor speeds sqrt(m g / (4 k_thrust)) (4,) rad/s for hover."""
    return rotor_speeds_from_input(hover_input(params, dtype), params)


def _tdiag(dtype):
    return jnp.asarray(_T, dtype=dtype)


def state_to_ned(x):
    """Paper-001 state (z-up world, world velocity) -> paper-000 layout.

    Returns (12,) [ρ_N, v_B (FRD body axes), Λ_NED, ω_FRD] (see module
    docstring: ρ_N = T p, Λ = (φ, −θ, −ψ), ω = T ω, v_B = C_NBᵀ T v_W).
    Batched inputs: use ``jax.vmap``.
    """
    x = real_float(x, "x", (12,))
    T = _tdiag(x.dtype)
    lam = x[ATT] * T
    C = dcm_from_euler(lam)
    v_b = C.T @ (T * x[VEL])
    return jnp.concatenate([T * x[POS], v_b, lam, T * x[RATE]])


def state_from_ned(x_ned):
    """Inverse of :func:`state_to_ned`: paper-000 layout -> paper-001 state."""
    x = real_float(x_ned, "x_ned", (12,))
    T = _tdiag(x.dtype)
    lam = x[6:9]
    C = dcm_from_euler(lam)
    v_w = T * (C @ x[3:6])
    return jnp.concatenate([T * x[0:3], v_w, T * lam, T * x[9:12]])


def input_to_ned(u):
    """Paper-001 input [u1, u2, u3, u4] -> paper-000 input [f_T, τ_FRD].

    Thrust magnitude is unchanged; torques are relabelled FLU -> FRD
    ([u2, −u3, −u4]).
    """
    u = check_last_dim(real_float(u, "u"), 4, "u")
    return u * jnp.asarray((1.0, *_T), dtype=u.dtype)


def input_from_ned(u_ned):
    """Inverse of :func:`input_to_ned` (the relabelling is its own inverse)."""
    return input_to_ned(u_ned)


def check_rotor_speeds(rotor_speeds, name="rotor_speeds"):
    """Host-side check: finite real (4,) array of rotor speeds; returns it."""
    check_shape(rotor_speeds, (4,), name)
    arr = np.asarray(rotor_speeds)
    if not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
        raise InputError(f"{name}: expected a real numeric array, got dtype {arr.dtype}")
    if not np.all(np.isfinite(arr)):
        raise InputError(f"{name}: contains NaN or Inf")
    return rotor_speeds
