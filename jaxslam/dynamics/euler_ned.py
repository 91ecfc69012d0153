"""12-state rigid-body quadcopter in NED with 3-2-1 Euler angles.

Paper 000, Sec. 2.1, eq. 1-3.  State and input layout:

    x = [ρ_N (3), v_B (3), Λ (3), ω_B (3)]          (12,)
        ρ_N  position in the NED inertial frame, m
        v_B  velocity expressed in body axes, m/s
        Λ    [φ, θ, ψ] 3-2-1 Euler angles, rad
        ω_B  [p, q, r] body angular velocity, rad/s
    u = [f_T, τ_φ, τ_θ, τ_ψ]                         (4,)
        f_T  thrust magnitude, N (acts along −b̂3, i.e. upwards at hover)
        τ    body torques, N m

    ρ̇ = C_NB v_B
    v̇ = −ω × v + (C_NBᵀ g n̂3 − f_T b̂3) / m
    Λ̇ = D(φ, θ) ω                                    (eq. 3)
    ω̇ = J⁻¹ (−ω × J ω + τ),  J = diag(inertia)

Rotor aerodynamics and gyroscopic effects are ignored, as the paper states;
:mod:`jaxslam.dynamics.rotor` adds them (paper 001).  The index slices
``POS``, ``VEL``, ``ATT``, ``RATE`` address the four blocks.

``f`` is a pure function of arrays (jit/vmap/grad-safe, parameters may be
traced arrays for gradients with respect to them).  It follows the dtype of
``x``: parameters and ``u`` are cast to it.  Validation lives in the
host-side ``check_state`` / ``check_input`` (call them before ``jit``).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from ..errors import InputError
from ..geometry.euler import dcm_from_euler, euler_rates
from ..linalg import check_scalar, check_shape, is_concrete
from ._checks import real_float, real_numbers
from .params import _cast

__all__ = [
    "POS",
    "VEL",
    "ATT",
    "RATE",
    "STATE_DIM",
    "INPUT_DIM",
    "f",
    "hover_input",
    "hover_state",
    "check_state",
    "check_input",
]

POS = slice(0, 3)
VEL = slice(3, 6)
ATT = slice(6, 9)
RATE = slice(9, 12)
STATE_DIM = 12
INPUT_DIM = 4


def _state_and_input(x, u, nx: int, nu: int, names=("x", "u")):
    """``x`` (nx,) and ``u`` (nu,) as arrays of one float dtype (``x``'s; an integer state is
    promoted to JAX's default float): a wrong shape is an :class:`InputError` naming the
    argument (checked at trace time, free under ``jit``; a (13,) state was sliced silently and an
    integer state truncated the thrust).  Batches go through ``jax.vmap``."""
    x = real_float(x, names[0], (nx,))
    u = real_float(u, names[1], (nu,))
    return x, u.astype(x.dtype)


def f(x, u, params):
    """Continuous-time dynamics ẋ = f(x, u), paper 000 eq. 2 (D of eq. 3).

    ``x``: (12,) state [ρ_N, v_B, Λ, ω_B]; ``u``: (4,) [f_T (N), τ (N m)];
    ``params``: :class:`~jaxslam.dynamics.params.QuadParams` (floats or
    arrays).  Returns ẋ (12,) in the dtype of ``x``.  Gravity is +g n̂3 (NED
    down) and thrust −f_T b̂3.  Use ``jax.vmap`` for batches.
    """
    x, u = _state_and_input(x, u, STATE_DIM, INPUT_DIM)
    dt = x.dtype
    p = _cast(params, dt)
    v, lam, w = x[VEL], x[ATT], x[RATE]
    C = dcm_from_euler(lam)
    J = p.inertia
    f_T, tau = u[0], u[1:]
    zero = jnp.zeros((), dt)
    # C_NBᵀ n̂3 is the third row of C_NB; thrust only has a b̂3 component.
    accel = -jnp.cross(w, v) + p.g * C[2, :] - jnp.stack([zero, zero, f_T / p.mass])
    rho_dot = C @ v
    lam_dot = euler_rates(lam, w)
    w_dot = (-jnp.cross(w, J * w) + tau) / J
    return jnp.concatenate([rho_dot, accel, lam_dot, w_dot])


def hover_input(params, dtype=None):
    """Input that holds a level hover: u = [m g, 0, 0, 0], shape (4,).

    ``dtype`` defaults to the dtype of ``params.mass`` if it is a floating array,
    else JAX's default float (an integer mass array no longer truncates g to an integer).
    With :func:`hover_state`, f(x, u) = 0.
    """
    if dtype is None:
        dtype = getattr(params.mass, "dtype", None)
        if dtype is not None and not jnp.issubdtype(dtype, jnp.floating):
            dtype = None
    if dtype is None:
        dtype = jnp.result_type(float)
    m = jnp.asarray(params.mass, dtype=dtype)
    g = jnp.asarray(params.g, dtype=dtype)
    return jnp.stack([m * g, *([jnp.zeros((), dtype)] * 3)])


def hover_state(position=(0.0, 0.0, 0.0), yaw=0.0, dtype=None):
    """Level hover state at ``position`` (NED, m) with heading ``yaw`` (rad).

    Returns (12,): zero velocity, φ = θ = 0, ψ = yaw, zero rates.
    """
    if dtype is None:
        dtype = jnp.result_type(float)
    if is_concrete(position, yaw):  # the usual case: built on the host, no program to compile
        x = np.zeros(STATE_DIM)
        x[POS] = _check_vector(real_numbers(position, "position"), 3, "position")
        x[8] = check_scalar(yaw, "yaw")
        return jnp.asarray(x, dtype)
    x = jnp.zeros(STATE_DIM, dtype)
    x = x.at[POS].set(jnp.asarray(position, dtype=dtype))
    return x.at[8].set(jnp.asarray(yaw, dtype=dtype))


def _check_vector(a, n, name):
    check_shape(a, (n,), name)
    arr = np.asarray(a)
    if not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
        raise InputError(f"{name}: expected a real numeric array, got dtype {arr.dtype}")
    if not np.all(np.isfinite(arr)):
        raise InputError(f"{name}: contains NaN or Inf")
    return a


def check_state(x, name="x"):
    """Host-side check that ``x`` is a finite real (12,) state; returns it.

    Raises :class:`~jaxslam.errors.InputError` naming ``name``.
    """
    return _check_vector(x, STATE_DIM, name)


def check_input(u, name="u"):
    """Host-side check that ``u`` is a finite real (4,) input; returns it.

    Raises :class:`~jaxslam.errors.InputError` naming ``name``.
    """
    return _check_vector(u, INPUT_DIM, name)
