"""PD attitude controller of paper 000, eq. 20.

τ = −k_p ⊙ (Λ − Λ_d) − k_d ⊙ (ω − ω_d) (+ optional feedforward torque), with Λ = [φ, θ, ψ]
(3-2-1 Euler angles, rad), ω = [p, q, r] body rates (rad/s) and τ in N·m about the body axes.

Decisions (paper 000 gives no gains):

* The yaw error ψ − ψ_d is wrapped to [−π, π) (``jaxslam.linalg.wrap_angle``) so a heading
  that crosses ±π does not make the vehicle turn the long way round.  Roll and pitch errors are
  not wrapped (they stay far from ±π in flight).
* Default gains treat each axis as J_i ë = τ_i (small angles, D ≈ I):
  k_p = J ω_n², k_d = 2 ζ ω_n J with ω_n = 25 rad/s and ζ = 0.8 for paper 000's
  J = diag(0.1147, 0.0576, 0.1712) kg·m²: k_p = (71.6875, 36.0, 107.0) N·m/rad,
  k_d = (4.588, 2.304, 6.848) N·m·s/rad.  Why so stiff: with the paper's p_d = q_d = 0 the
  PD lags a changing tilt by about 2ζ/ω_n, and the slow Table-2 LQR (position bandwidth
  ≈ 0.47 rad/s) cannot remove the resulting acceleration error.  On the default figure-8
  (dt = 0.01 s) the settled (t > 10 s) position RMSE is 0.128 m at ω_n = 10, 0.062 m at 20,
  0.044 m at 25 (ζ = 0.8) and 0.036 m at 30; ω_n = 25 still runs stably with the controller
  at 20 Hz (ω_n = 30 diverges there).  With the flatness feedforward option of
  :func:`jaxslam.control.dflqr.control` the error is 0.2 mm at any of these gains.
  :func:`gains_from_bandwidth` builds gains for other inertias.
"""

from __future__ import annotations

from typing import NamedTuple, Tuple

import jax.numpy as jnp
import numpy as np

from ..dynamics._checks import real_float, real_numbers
from ..linalg import check_real, check_shape, is_concrete, wrap_angle
from ..errors import InputError

__all__ = ["PDGains", "gains_from_bandwidth", "pd_torque"]

_J000 = (0.1147, 0.0576, 0.1712)
_WN, _ZETA = 25.0, 0.8


class PDGains(NamedTuple):
    """Gains of paper 000 eq. 20 (defaults: jaxslam's choice for paper 000's inertia).

    kp: (3,) proportional gains [k_pφ, k_pθ, k_pψ], N·m/rad.
    kd: (3,) derivative gains [k_dφ, k_dθ, k_dψ], N·m·s/rad.
    """

    kp: Tuple[float, float, float] = tuple(j * _WN ** 2 for j in _J000)
    kd: Tuple[float, float, float] = tuple(2.0 * _ZETA * _WN * j for j in _J000)


def gains_from_bandwidth(inertia, omega_n, zeta) -> PDGains:
    """PD gains placing each axis of J ë = τ at natural frequency ω_n (rad/s), damping ζ.

    ``inertia``: (3,) diagonal of J in kg·m²; ``omega_n``, ``zeta``: scalars or (3,).
    Returns :class:`PDGains` with k_p = J ω_n², k_d = 2 ζ ω_n J (arrays, (3,)).
    """
    for v, nm in ((inertia, "inertia"), (omega_n, "omega_n"), (zeta, "zeta")):
        if is_concrete(v):  # (traced: real_float below checks the dtype)  # a negative bandwidth or damping gave negative (destabilising) gains
            a = real_numbers(v, nm)
            if a.shape not in ((), (3,)) or not np.all(np.isfinite(a)) or np.any(a <= 0 if nm == "inertia" else a < 0):
                want = "finite and > 0" if nm == "inertia" else "finite and >= 0"
                raise InputError(f"{nm}: expected {want} (a scalar or (3,)), got {v!r}")
    J = real_float(inertia, "inertia")
    wn = real_float(omega_n, "omega_n")
    return PDGains(kp=J * wn ** 2, kd=2.0 * real_float(zeta, "zeta") * wn * J)


def pd_torque(euler, omega, euler_d, omega_d, gains, tau_ff=None):
    """Attitude PD torque, paper 000 eq. 20 (yaw error wrapped).

    ``euler``, ``euler_d``: (3,) [φ, θ, ψ] rad; ``omega``, ``omega_d``: (3,) body rates rad/s;
    ``gains``: :class:`PDGains`; ``tau_ff``: optional (3,) feedforward torque N·m added to the
    PD output (not in the paper).  Returns τ (3,) in N·m, body axes, dtype of ``euler``.
    """
    euler = real_float(euler, "euler", (3,))  # an integer attitude truncated the gains
    dtype = euler.dtype
    for v, nm in ((omega, "omega"), (euler_d, "euler_d"), (omega_d, "omega_d")):
        check_real(v, nm)
        check_shape(v, (3,), nm)
    for v, nm in ((gains.kp, "gains.kp"), (gains.kd, "gains.kd"), (tau_ff, "tau_ff")):
        if v is not None and is_concrete(v):  # (NaN gains gave a NaN torque, a (2,) tau_ff a TypeError)
            check_real(v, nm)
            check_shape(v, (3,), nm)
            if not np.all(np.isfinite(np.asarray(v, np.float64))):
                raise InputError(f"{nm}: expected finite numbers, got {v!r}"[:300])
    e = euler - jnp.asarray(euler_d, dtype)
    e = e.at[2].set(wrap_angle(e[2]))
    kp = jnp.asarray(gains.kp, dtype)
    kd = jnp.asarray(gains.kd, dtype)
    tau = -kp * e - kd * (jnp.asarray(omega, dtype) - jnp.asarray(omega_d, dtype))
    if tau_ff is not None:
        tau = tau + jnp.asarray(tau_ff, dtype)
    return tau
