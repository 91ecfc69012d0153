"""Differential-flatness LQR trajectory controller of paper 000 (Fig. 2, eq. 4-20).

One control step: state r = [ρ, ρ̇ = C_NB v_B, ψ] from the (estimated) 12-state x (eq. 7);
reference r_d, u_d from the flat output (eq. 4-5); ũ = −K (r − r_d) (eq. 12, ψ error wrapped);
u = u_d + ũ (eq. 14); inverse map to f_T, φ_d, θ_d, r_d (eq. 15-19); ω_d = [0, 0, r_d] (the
paper's p_d = q_d = 0); PD torque (eq. 20).  The output is the input of
:func:`jaxslam.dynamics.euler_ned.f`: u = [f_T, τ_φ, τ_θ, τ_ψ].

The gain K = R̃⁻¹BᵀP̃ is computed once per run by :func:`gain` (outside any time scan) and
passed to :func:`control`; gradients flow from Q̃ and R̃ through :func:`jaxslam.control.lqr.care`.

Decisions:

* Table 2 prints R̃ = diag(0.2, 0.32, 0.1) for a 4×4 matrix; jaxslam reads
  diag(0.2, 0.2, 0.32, 0.1) (x and y share 0.2).  Q̃ = diag(0.01 ×6, 0.04) as printed.
* The yaw error in r − r_d is wrapped to [−π, π) (the paper is silent).
* ``feedforward=True`` (not in the paper) replaces p_d = q_d = 0 by the flatness feedforward
  body rates of :func:`jaxslam.control.flatness.feedforward`, adds its torque J ω̇_d + ω_d × Jω_d
  to the PD output, and uses r_d = r_ff + ũ_ψ cos θ_d / cos φ_d (the nominal yaw rate plus the
  LQR's yaw-rate correction through eq. 19).  The attitude set point is still eq. 16-17 of the
  LQR output u, so the position feedback is unchanged.
* PD gains: see :mod:`jaxslam.control.attitude_pd` (ω_n = 25 rad/s, ζ = 0.8).
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from ..dynamics._checks import as_scalar, real_float, real_numbers
from ..linalg import check_real, check_scalar, check_shape, wrap_angle
from ..dynamics.params import PAPER000, QuadParams, validate_params
from ..errors import InputError
from ..geometry.euler import dcm_from_euler
from .attitude_pd import PDGains, pd_torque
from .flatness import feedforward as _feedforward
from .flatness import inverse_map, linear_model, reference
from .lqr import lqr_gain, validate_weights

__all__ = [
    "DFLQRParams",
    "ControlInfo",
    "paper000_params",
    "validate",
    "gain",
    "control",
    "Reference",
    "reference_at",
    "control_ref",
]

_Q000 = tuple(tuple(float(v) if i == j else 0.0 for j, v in enumerate((0.01,) * 6 + (0.04,)))
              for i in range(7))
_R000 = tuple(tuple(float(v) if i == j else 0.0 for j, v in enumerate((0.2, 0.2, 0.32, 0.1)))
              for i in range(4))


class DFLQRParams(NamedTuple):
    """Parameters of the DF-LQR controller (paper 000, Table 1-2 as defaults).

    Q: (7, 7) state weight Q̃ on r̃ = [ρ̃ (m), ρ̇̃ (m/s), ψ̃ (rad)], symmetric PSD.
    R: (4, 4) input weight R̃ on ũ = [ũ_p (m/s²), ũ_ψ (rad/s)], symmetric PD.
    pd: :class:`PDGains` of the attitude loop (eq. 20).
    quad: :class:`jaxslam.dynamics.params.QuadParams` (mass kg, inertia (3,) kg·m², g m/s²).
    min_accel: scalar, m/s²; below this ‖u_p‖ the inverse map levels the attitude set point.
    """

    Q: tuple = _Q000
    R: tuple = _R000
    pd: PDGains = PDGains()
    quad: QuadParams = PAPER000
    min_accel: float = 1e-3


class ControlInfo(NamedTuple):
    """Intermediate quantities of one control step (for plotting and diagnostics).

    euler_d: (3,) desired attitude [φ_d, θ_d, ψ_d], rad.
    omega_d: (3,) desired body rates [p_d, q_d, r_d], rad/s.
    thrust: scalar f_T, N.
    r_err: (7,) r − r_d (yaw wrapped): position m, velocity m/s, yaw rad.
    u_lqr: (4,) u = u_d + ũ: thrust acceleration (m/s², NED) and yaw rate (rad/s).
    r_d: (7,) reference state [ρ_d, ρ̇_d, ψ_d].
    """

    euler_d: jnp.ndarray
    omega_d: jnp.ndarray
    thrust: jnp.ndarray
    r_err: jnp.ndarray
    u_lqr: jnp.ndarray
    r_d: jnp.ndarray


def paper000_params() -> DFLQRParams:
    """Paper 000 preset: Table 2 weights (R̃ per errata), Table 1 quadcopter, jaxslam PD gains."""
    return DFLQRParams()


_FIELD_NAMES = {"Q": "params.Q", "R": "params.R", "kp": "params.pd.kp", "kd": "params.pd.kd"}


def validate(params: DFLQRParams, *, names=None) -> DFLQRParams:
    """Host-side check of :class:`DFLQRParams`; raises :class:`InputError` naming the field.

    ``names``: the names the messages give the weights and gains, by field (``"Q"``, ``"R"``,
    ``"kp"``, ``"kd"``; e.g. ``{"Q": "params.controller.Q"}`` for a value read from a file);
    the fields left out keep ``params.Q``, ``params.R``, ``params.pd.kp``, ``params.pd.kd``.
    """
    if names is None:
        names = {}
    if not isinstance(names, dict) or not all(k in _FIELD_NAMES and isinstance(v, str) and v
                                              for k, v in names.items()):
        raise InputError(f"names: expected a dict of names for some of {', '.join(_FIELD_NAMES)}, "
                         f"got {names!r}"[:300])
    nm = {**_FIELD_NAMES, **names}
    if not isinstance(params, DFLQRParams):
        raise InputError(f"params: expected DFLQRParams, got {type(params).__name__}")
    validate_weights(params.Q, params.R, n=7, m=4, names=(nm["Q"], nm["R"]))
    if not isinstance(params.pd, PDGains):  # None or a tuple raised a bare AttributeError
        raise InputError(f"params.pd: expected PDGains, got {type(params.pd).__name__}")
    for field in ("kp", "kd"):
        name = nm[field]
        v = real_numbers(getattr(params.pd, field), name)  # a string: ValueError
        if v.shape != (3,):
            raise InputError(f"{name}: expected shape (3,), got {v.shape}")
        if not np.all(np.isfinite(v)) or np.any(v < 0):
            raise InputError(f"{name}: must be finite and >= 0, got {v.tolist()}")
    try:
        validate_params(params.quad)
    except InputError as e:
        raise InputError(f"params.quad: {e}") from None
    check_scalar(params.min_accel, "params.min_accel", lower=0)  # -1 or NaN was accepted
    return params


def gain(params: DFLQRParams, dtype=None, *, return_status: bool = False):
    """LQR gain K (4, 7) of paper 000 eq. 12-13 on the flat model of eq. 6.

    ``dtype`` defaults to the promoted dtype of ``params.Q`` and ``params.R`` (JAX's default float
    for Python floats and integers: a float32 Q with the default tuple R gives that default).
    Differentiable in ``params.Q`` and ``params.R``.  An integer ``dtype`` is an
    :class:`InputError` (it truncated the weights).  With ``return_status=True`` returns
    ``(K, ok)`` (``ok`` False if the Riccati solver failed).  Call once per run, outside scans.
    """
    if dtype is None:
        dtype = jnp.result_type(jnp.asarray(params.Q), jnp.asarray(params.R))
        if not jnp.issubdtype(dtype, jnp.floating):
            dtype = jnp.result_type(float)
    elif not jnp.issubdtype(jnp.dtype(dtype), jnp.floating):
        # an integer dtype truncated Q̃ = 0.01 I to 0 and R̃ to 0: "R: not positive definite"
        raise InputError(f"dtype: expected a floating dtype, got {jnp.dtype(dtype)}")
    A, B, _ = linear_model(dtype)
    Q = jnp.asarray(params.Q, dtype)
    R = jnp.asarray(params.R, dtype)
    if return_status:
        K, _, ok = lqr_gain(A, B, Q, R, return_status=True)
        return K, ok
    return lqr_gain(A, B, Q, R)[0]


class Reference(NamedTuple):
    """The time-only part of a control step (no state): precompute it along a time grid.

    r_d: (7,) [ρ_d, ρ̇_d, ψ_d] (eq. 4).  u_d: (4,) [ρ̈_d − g n̂3, ψ̇_d] (eq. 5).
    omega_ff: (3,) feedforward body rates; tau_ff: (3,) feedforward torques (zeros unless the
    reference was built with ``feedforward=True``).
    """

    r_d: jnp.ndarray
    u_d: jnp.ndarray
    omega_ff: jnp.ndarray
    tau_ff: jnp.ndarray


def reference_at(t, traj, params: DFLQRParams, *, feedforward: bool = False, dtype=None) -> Reference:
    """:class:`Reference` at time ``t`` (eq. 4-5 and, optionally, the flatness feedforward).

    It depends on time only, so a simulation evaluates it for the whole time grid at once
    (``jax.vmap`` over t, outside the time scan) instead of once per step inside it: the
    nested forward-mode derivatives of the trajectory then run vectorised.
    """
    dtype = jnp.result_type(float) if dtype is None else dtype
    t = as_scalar(t, dtype, "t")  # "1.0" was parsed
    g = jnp.asarray(params.quad.g, dtype)
    r_d, u_d = reference(traj, t, g)
    if feedforward:
        x_ff, u_ff = _feedforward(traj, t, params.quad)
        omega_ff, tau_ff = x_ff[9:12].astype(dtype), u_ff[1:4].astype(dtype)
    else:
        omega_ff = tau_ff = jnp.zeros((3,), dtype)
    return Reference(r_d.astype(dtype), u_d.astype(dtype), omega_ff, tau_ff)


def control_ref(x_est, ref: Reference, K, params: DFLQRParams, *, feedforward: bool = False):
    """The state-feedback part of :func:`control` given a precomputed :class:`Reference`."""
    x = real_float(x_est, "x_est", (12,))  # an integer state truncated the gains; (13,) was sliced
    dtype = x.dtype
    check_real(K, "K")
    K = jnp.asarray(K, dtype)
    check_shape(K, (4, 7), "K")  # Kᵀ (7, 4) gave a bare matmul error
    for name, n in (("r_d", 7), ("u_d", 4), ("omega_ff", 3), ("tau_ff", 3)):
        check_shape(getattr(ref, name), (n,), f"ref.{name}")  # (6,) r_d: a bare broadcast error
    mass = jnp.asarray(params.quad.mass, dtype)
    lam = x[6:9]
    C = dcm_from_euler(lam)
    r = jnp.concatenate([x[0:3], C @ x[3:6], lam[2:3]])
    r_d, u_d = ref.r_d.astype(dtype), ref.u_d.astype(dtype)
    r_err = r - r_d
    r_err = r_err.at[6].set(wrap_angle(r_err[6]))
    u_tilde = -K @ r_err
    u = u_d + u_tilde
    psi_d = r_d[6]
    f_T, phi_d, theta_d, rate_d = inverse_map(u, psi_d, mass, jnp.asarray(params.min_accel, dtype))
    euler_d = jnp.stack([phi_d, theta_d, psi_d])
    if feedforward:
        yaw_fb = u_tilde[3] * jnp.cos(theta_d) / jnp.maximum(jnp.cos(phi_d), 1e-6)
        omega_d = ref.omega_ff.astype(dtype).at[2].add(yaw_fb)
        tau_ff = ref.tau_ff.astype(dtype)
    else:
        omega_d = jnp.stack([jnp.zeros_like(rate_d), jnp.zeros_like(rate_d), rate_d])
        tau_ff = None
    tau = pd_torque(lam, x[9:12], euler_d, omega_d, params.pd, tau_ff)
    u_out = jnp.concatenate([f_T[None], tau])
    info = ControlInfo(euler_d=euler_d, omega_d=omega_d, thrust=f_T, r_err=r_err, u_lqr=u, r_d=r_d)
    return u_out, info


def control(x_est, t, traj, K, params: DFLQRParams, *, feedforward: bool = False):
    """One DF-LQR control step, paper 000 Fig. 2 (eq. 4-5, 7, 12, 14-20).

    ``x_est``: (12,) state [ρ (N, m), v_B (m/s), Λ (rad), ω_B (rad/s)] — the estimate when the
    controller acts on the EKF output; ``t``: time s; ``traj``: trajectory container;
    ``K``: (4, 7) gain from :func:`gain`; ``params``: :class:`DFLQRParams`;
    ``feedforward``: static bool, use the flatness feedforward rates and torques (module
    docstring).  Returns ``(u (4,) = [f_T (N), τ (3,) (N·m)], info: ControlInfo)``.
    Pure and jit-able (``feedforward`` static); dtype of ``x_est``.  Equals
    ``control_ref(x_est, reference_at(t, ...), ...)``.
    """
    x = real_float(x_est, "x_est", (12,))
    ref = reference_at(t, traj, params, feedforward=feedforward, dtype=x.dtype)
    return control_ref(x, ref, K, params, feedforward=feedforward)
