"""13-state quadcopter with a unit-quaternion attitude (paper 004, eq. 3.10-3.16).

State and input layout (paper 004 eq. 3.10):

    x = [p (3), ṗ (3), q (4), ω (3)]                 (13,)
        p   position in the NED inertial frame, m
        ṗ   velocity in the NED inertial frame, m/s (not body axes: compare
            :mod:`jaxslam.dynamics.euler_ned`, whose velocity is v_B)
        q   unit quaternion [q0, q1, q2, q3], Hamilton, scalar first, body → NED
            (C_NB = dcm_from_quat(q), as in :mod:`jaxslam.geometry.quaternion`)
        ω   body angular velocity [ω_x, ω_y, ω_z], rad/s
    u = [f_T, τ (3)]                                  (4,)
        f_T thrust magnitude, N, along −b̂3 (upwards at hover, same convention as
            ``euler_ned`` so the two models are comparable)
        τ   body torques, N m

    ṗ  = ṗ
    p̈  = q ⊗ [0, 0, 0, −f_T/m] ⊗ q* + g n̂3          (eq. 3.16, gravity +z in NED)
    q̇  = ½ q ⊗ [0, ω] = ½ S(q) ω                      (eq. 3.12)
    ω̇  = J⁻¹ (τ − ω × J ω) (+ ξ)                      (eq. 3.13; ξ of eq. 3.17)

The attitude-only subsystem x_qatt = [q, ω] (7,) of eq. 3.13 is :func:`f_att`; it
takes an optional additive angular-acceleration perturbation ξ (rad/s², eq. 3.17:
external torques, model error and noise, after J⁻¹).

Decisions:

* The thesis' rotation matrix eq. 3.3 has a typo in its (2, 3) entry:
  2(q2q3 + q0q1) must be 2(q2q3 − q0q1) for the matrix to be orthonormal (its
  (3, 2) entry already is 2(q0q1 + q2q3)).  jaxslam uses the foundation's
  :func:`~jaxslam.geometry.quaternion.dcm_from_quat` / ``qrotate``, which are
  correct; eq. 3.3 is not transcribed.
* ``J`` is the diagonal of the inertia matrix, (3,) (the thesis assumes J diagonal,
  eq. 3.13).
* Integration: :func:`step` is one RK4 step (zero-order hold on u) followed by a
  renormalisation of the quaternion.  RK4 does not preserve ‖q‖ = 1 (its local
  error drifts the norm by O(dt⁵) per step, and round-off accumulates); the
  renormalisation projects back onto the unit sphere after every step, which is what
  keeps ‖q‖ within 1e-12 of 1 over 1e5 steps in float64 (tested).  The sign of q
  is never changed (q and −q are the same attitude; the controller must not care,
  see :mod:`jaxslam.control.smc`).
* The model functions accept slightly non-unit q inside an RK4 step (the rotation of
  the thrust uses ``qrotate``, exact for unit q; for q scaled by 1 + ε it rotates by
  v + (1 + ε)²(Rv − v), an error first order in the norm drift — ~1e-12 relative in
  float64 with the renormalisation after every step).

Converters :func:`to_euler_ned` / :func:`from_euler_ned` map to and from the
12-state layout of :mod:`jaxslam.dynamics.euler_ned` (v_B = C_NBᵀ ṗ).

Everything is pure and jit/vmap/grad-safe, and follows the dtype of ``x``
(parameters and inputs are cast to it).  Host-side validation: :func:`check_state`,
:func:`check_att_state`, :func:`check_inertia`.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from ..errors import InputError
from ..geometry.quaternion import (
    dcm_from_quat,
    euler_from_quat,
    qmul,
    qnormalize,
    qrotate,
    quat_from_euler,
)
from ..linalg import check_real, check_shape, is_concrete
from . import euler_ned
from ._checks import real_float, real_numbers
from .integrators import rk4_step
from .params import _cast

__all__ = [
    "POS",
    "VEL",
    "QUAT",
    "RATE",
    "STATE_DIM",
    "ATT_DIM",
    "INPUT_DIM",
    "f",
    "f_att",
    "step",
    "s_matrix",
    "to_euler_ned",
    "from_euler_ned",
    "hover_state",
    "check_state",
    "check_att_state",
    "check_inertia",
]

POS = slice(0, 3)
VEL = slice(3, 6)
QUAT = slice(6, 10)
RATE = slice(10, 13)
STATE_DIM = 13
ATT_DIM = 7
INPUT_DIM = 4


def s_matrix(q):
    """S(q) of paper 004 eq. 3.12, (4, 3): q̇ = ½ S(q) ω = ½ q ⊗ [0, ω].

    ``q``: (4,).  Used by the tests as a hand-derived oracle; the model itself uses
    the Hamilton product.
    """
    q0, q1, q2, q3 = q[0], q[1], q[2], q[3]
    return jnp.stack(
        [
            jnp.stack([-q1, -q2, -q3]),
            jnp.stack([q0, -q3, q2]),
            jnp.stack([q3, q0, -q1]),
            jnp.stack([-q2, q1, q0]),
        ]
    )


def _rigid_body(q, w, tau, J):
    """(q̇, ω̇) of eq. 3.13 (diagonal J)."""
    zero = jnp.zeros((1,), q.dtype)
    q_dot = 0.5 * qmul(q, jnp.concatenate([zero, w]))
    w_dot = (tau - jnp.cross(w, J * w)) / J
    return q_dot, w_dot


def f_att(xa, tau, J, xi=None):
    """Attitude dynamics ẋ_qatt, paper 004 eq. 3.13, with the perturbation of eq. 3.17.

    ``xa``: (7,) [q (4), ω (3)]; ``tau``: (3,) body torque, N m; ``J``: (3,)
    diagonal inertia, kg m²; ``xi``: optional (3,) additive angular acceleration,
    rad/s² (ω̇ = J⁻¹(τ − ω×Jω) + ξ).  Returns (7,) in the dtype of ``xa``.
    """
    xa, tau = euler_ned._state_and_input(xa, tau, 7, 3, ("xa", "tau"))
    dt = xa.dtype
    q, w = xa[:4], xa[4:]
    J = jnp.asarray(J, dt)
    check_shape(J, (3,), "J")
    q_dot, w_dot = _rigid_body(q, w, tau, J)
    if xi is not None:
        xi = jnp.asarray(xi, dt)
        check_shape(xi, (3,), "xi")
        w_dot = w_dot + xi
    return jnp.concatenate([q_dot, w_dot])


def f(x, u, params):
    """Continuous-time dynamics ẋ = f(x, u), paper 004 eq. 3.12, 3.13 and 3.16.

    ``x``: (13,) [p, ṗ, q, ω] (NED, inertial velocity, body→NED quaternion, body
    rates); ``u``: (4,) [f_T (N), τ (N m)]; ``params``:
    :class:`~jaxslam.dynamics.params.QuadParams` (mass, inertia (3,), g).  Returns
    ẋ (13,) in the dtype of ``x``.  Thrust −f_T b̂3, gravity +g n̂3.
    """
    x, u = euler_ned._state_and_input(x, u, STATE_DIM, INPUT_DIM)
    dt = x.dtype
    p = _cast(params, dt)
    v, q, w = x[VEL], x[QUAT], x[RATE]
    f_T, tau = u[0], u[1:]
    zero = jnp.zeros((), dt)
    thrust_b = jnp.stack([zero, zero, -f_T / p.mass])
    accel = qrotate(q, thrust_b) + jnp.stack([zero, zero, p.g])
    q_dot, w_dot = _rigid_body(q, w, tau, p.inertia)
    return jnp.concatenate([v, accel, q_dot, w_dot])


def step(fn, x, u, dt, *args, quat=None):
    """One RK4 step of ẋ = fn(x, u, *args) followed by quaternion renormalisation.

    ``fn``: :func:`f` (13 states) or :func:`f_att` (7 states), or any model with a
    quaternion block; ``x``: (n,); ``u``: input held over the step; ``dt``: s;
    ``quat``: slice of the quaternion in ``x`` (default: ``QUAT`` for 13 states,
    ``slice(0, 4)`` for 7).  The renormalisation is what keeps ‖q‖ = 1 to within
    1e-12 over 1e5 steps (RK4 alone drifts); the sign of q is kept.  Returns (n,).
    """
    x = real_float(x, "x")
    if quat is None:
        n = x.shape[-1]
        if n == STATE_DIM:
            quat = QUAT
        elif n == ATT_DIM:
            quat = slice(0, 4)
        else:
            raise InputError(f"x: step cannot locate the quaternion in a state of size {n}; pass quat=")
    xn = rk4_step(fn, x, u, dt, *args)
    return xn.at[quat].set(qnormalize(xn[quat]))


def to_euler_ned(x):
    """13-state [p, ṗ, q, ω] -> 12-state paper-000 layout [p, v_B, Λ, ω].

    v_B = C_NBᵀ ṗ, Λ = 3-2-1 Euler angles of q (gimbal-lock convention of
    :func:`~jaxslam.geometry.quaternion.euler_from_quat`).  ``x``: (13,) -> (12,).
    """
    x = real_float(x, "x", (STATE_DIM,))
    q = qnormalize(x[QUAT])
    C = dcm_from_quat(q)
    return jnp.concatenate([x[POS], C.T @ x[VEL], euler_from_quat(q), x[RATE]])


def from_euler_ned(x):
    """12-state [p, v_B, Λ, ω] (paper 000) -> 13-state [p, ṗ, q, ω] (paper 004).

    q = quat_from_euler(Λ) (smooth closed form, sign not canonicalised),
    ṗ = C_NB v_B.  ``x``: (12,) -> (13,).
    """
    x = real_float(x, "x", (euler_ned.STATE_DIM,))
    q = quat_from_euler(x[euler_ned.ATT])
    return jnp.concatenate([x[euler_ned.POS], qrotate(q, x[euler_ned.VEL]), q, x[euler_ned.RATE]])


def hover_state(position=(0.0, 0.0, 0.0), q=(1.0, 0.0, 0.0, 0.0), dtype=None):
    """State at rest at ``position`` (NED, m) with attitude ``q`` (normalised).  (13,)."""
    if dtype is None:
        dtype = jnp.result_type(float)
    check_real(position, "position")
    check_real(q, "q")
    if is_concrete(position):
        euler_ned._check_vector(real_numbers(position, "position"), 3, "position")
    if is_concrete(q):  # a zero quaternion normalised to NaN
        qa = euler_ned._check_vector(real_numbers(q, "q"), 4, "q")
        if not np.linalg.norm(qa) > 0:
            raise InputError(f"q: expected a nonzero quaternion, got {qa.tolist()}")
    x = jnp.zeros(STATE_DIM, dtype)
    x = x.at[POS].set(jnp.asarray(position, dtype))
    return x.at[QUAT].set(qnormalize(jnp.asarray(q, dtype)))


def _check_finite_vector(a, n, name):
    check_shape(a, (n,), name)
    arr = np.asarray(a)
    if not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
        raise InputError(f"{name}: expected a real numeric array, got dtype {arr.dtype}")
    if not np.all(np.isfinite(arr)):
        raise InputError(f"{name}: contains NaN or Inf")
    return arr


def _check_unit(qa, name, tol):
    nq = float(np.linalg.norm(qa))
    if abs(nq - 1.0) > tol:
        raise InputError(f"{name}: quaternion block must have unit norm (|q| = {nq:.6g})")


def check_state(x, name="x", tol=1e-6):
    """Host-side check of a finite (13,) state whose quaternion has unit norm (±tol)."""
    arr = _check_finite_vector(x, STATE_DIM, name)
    _check_unit(arr[QUAT], name, tol)
    return x


def check_att_state(xa, name="xa", tol=1e-6):
    """Host-side check of a finite (7,) attitude state [q, ω] with ‖q‖ = 1 (±tol)."""
    arr = _check_finite_vector(xa, ATT_DIM, name)
    _check_unit(arr[:4], name, tol)
    return xa


def check_inertia(J, name="J"):
    """Host-side check that ``J`` is a finite positive (3,) inertia diagonal, kg m²."""
    arr = _check_finite_vector(J, 3, name)
    if np.any(arr <= 0):
        raise InputError(f"{name}: inertia must be positive, got {arr.tolist()}")
    return J
