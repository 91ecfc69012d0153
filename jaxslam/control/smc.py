"""Quaternion sliding-mode attitude control of paper 004 (eq. 3.15, 3.17-3.20, Theorem 3.1).

The attitude error is the shortest rotation vector of the error quaternion,

    q_e = q ⊗ q_d*,   θ_e = 2 ln q_e = qlog(q_e)   (eq. 3.6; ch. 6.1 defines q_e),
    x = [θ_e, ω − ω_d]                              (6,)  (eq. 3.18, 3.20)

and the law is

    u = −K1 x − K2 tanh(x / ε)                      (eq. 3.18/3.20; ε = 1 is the thesis' TANH,
                                                     ``switching="sign"`` the discontinuous SIGN)
    τ = J u + ω × J ω   (``torque="exact"``, eq. 3.15: u is an angular acceleration)
    τ = u               (``torque="direct"``, the code of app. B line 67: u is a torque)
    τ ← clip(τ, ±τ_max) (app. B line 69: τ_max = 0.6·0.3 = 0.18 N m; None: no limit)

Decisions (where the thesis is silent or inconsistent):

* Shortest rotation (errata): ``qlog`` canonicalises q_e to q_e0 ≥ 0 before the log, so
  the control is the same for q and −q and does not jump when the vehicle quaternion's
  q0 crosses 0 (it only jumps where the error itself is a rotation by π, which is
  inherent to any continuous-time law on the double cover, ch. 7).
* 2 ln q, not ln q: eq. 3.6 and eq. 3.18 define θ = 2 ln q (the full rotation angle, so
  that θ̇ = ω as eq. 3.15 assumes); app. B line 65 feeds its ``log_q`` (presumably ln q,
  the half angle) to the same gains, which halves the effective proportional gain.
  jaxslam uses 2 ln q (``qlog``), consistent with eq. 3.15 and with the LQR design.
* The error q ⊗ q_d* (ch. 6.1, app. B) is a rotation expressed in the inertial frame,
  while ω is in body axes; θ̇_e = C_NB(q) ω, not ω, away from q = I.  The thesis'
  linear model (3.15) neglects this; jaxslam keeps the thesis' definition.
* Torque model: the law functions default to ``"exact"`` (eq. 3.15, the law the theory is
  about; u is in rad/s²).  ``"direct"`` reproduces app. B, where the same gains act as N m
  per rad (stiff: J⁻¹K1 ~ 8400 s⁻², riding the saturation at the start); it is the code
  behind the thesis' Figs. 3.2-3.7, so the scenario ``attitude-smc`` defaults to it.
* Sampling: in :func:`closed_loop` the control and ξ are computed once per step and
  held over it (a 1 kHz digital controller); app. B evaluates both continuously inside
  ``odeint``.  At dt = 1 ms the fastest closed-loop pole of the exact law (≈ 31 s⁻¹) is
  far below the sampling rate.
* Perturbations (app. B lines 71-76), functions of ``(key, t, x_err, bounds)`` with
  ``bounds = (L1, L2)``; magnitude ‖ξ‖ = (L2 + L1‖x‖)(1 − 1e-10), i.e. just inside the
  quasi-Lipschitz bound ‖ξ‖ < L2 + L1‖x‖ of eq. 3.17.  App. B's code writes
  (L1 + L2‖x‖)/(1 + 1e-10): it swaps L1 and L2 relative to eq. 3.17 and Theorem 3.1;
  jaxslam follows the equation.  ``random`` draws a uniform direction and a magnitude
  uniform in [0, bound] (bounded, so the theorem's assumption holds; app. B draws
  ``np.random.normal`` with that scale, which is unbounded).  ``constant``: direction
  ones/√3; ``sinusoidal``: direction cos([0.3t, 0.5t, t]) normalised.
* L1, L2 default to the admissible maxima of Theorem 3.1 in app. B's form (NumPy's
  default Frobenius norms, line 38-40), see :func:`theorem31`, times a ``scale``.

Units: θ in rad, ω in rad/s, u in rad/s² (exact) or N m (direct), τ in N m, J in kg m²
(diagonal, (3,)).  All law functions are pure, jit/vmap-safe and follow the dtype of
their first array argument.  Host-side validation: :func:`validate`.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np

from ..dynamics import quaternion_quad as qq
from ..dynamics._checks import real_float, real_numbers
from ..dynamics.params import QuadParams
from ..errors import InputError
from ..geometry.quaternion import qconj, qlog, qmul, qnormalize
from ..linalg import check_real, check_shape, is_concrete, safe_norm
from .lqr import is_hurwitz, lqr_gain, lyapunov, validate_weights

__all__ = [
    "SMCGains",
    "LQRDesign",
    "Theorem31",
    "Rollout",
    "THESIS_SIM",
    "PROTOTYPE",
    "APPB_WEIGHTS",
    "PAPER004_APPB",
    "TAU_MAX_APPB",
    "Q0_CH34",
    "QD_CH34",
    "QD_APPB",
    "DURATION_S",
    "DT_S",
    "PERTURBATIONS",
    "att_matrices",
    "state_error",
    "law",
    "torque",
    "control",
    "lqr_gains",
    "theorem31",
    "perturbation",
    "perturbation_constant",
    "perturbation_sinusoidal",
    "perturbation_random",
    "perturbation_none",
    "perturbation_bounds",
    "initial_state",
    "closed_loop",
    "validate",
]


class SMCGains(NamedTuple):
    """Gains of the sliding-mode law eq. 3.18: u = −K1 x − K2 tanh(x/ε).

    K1: (3, 6) linear gain on x = [θ_e, ω − ω_d].
    K2: (3, 6) switching gain.
    """

    K1: tuple
    K2: tuple


def _blockdiag_gain(a, b, az=None, bz=None):
    az = a if az is None else az
    bz = b if bz is None else bz
    return ((a, 0.0, 0.0, b, 0.0, 0.0), (0.0, a, 0.0, 0.0, b, 0.0), (0.0, 0.0, az, 0.0, 0.0, bz))


THESIS_SIM = SMCGains(
    K1=_blockdiag_gain(100.0, 34.6410162, 31.6227766, 32.6074463),
    K2=_blockdiag_gain(0.316227766, 0.855836160),
)
"""Paper 004 ch. 3.4, gains exactly as printed (LQR of app. B lines 34-35)."""

PROTOTYPE = SMCGains(
    K1=_blockdiag_gain(0.35, 0.08, 0.2, 0.2),
    K2=_blockdiag_gain(0.01868069, 0.04637922, 0.0, 0.0),
)
"""Paper 004 eq. 6.1, the gains of the prototype flights (K2 has no yaw row)."""

APPB_WEIGHTS = (
    tuple(1e3 * w for w in (10.0, 10.0, 1.0, 1.0, 1.0, 1.0)),  # Q1 diagonal
    (1.0, 1.0, 1.0),  # R1 diagonal
    (0.1,) * 6,  # Q2 diagonal
    (1.0, 1.0, 1.0),  # R2 diagonal
)
"""App. B lines 34-35: K1 = lqr(A, B, diag([10,10,1,1,1,1])·1e3, I), K2 = lqr(A, B, 0.1·I, I)."""

_SP = 2.0 * (1.3 - 4 * 0.065) * 0.06 ** 2 / 5.0
_ARMXY = 4 * 0.065 * 0.2 ** 2
_ARMZ = 4 * 0.065 * 0.28 ** 2
PAPER004_APPB = QuadParams(mass=1.3, inertia=(_SP + _ARMXY, _SP + _ARMXY, _SP + _ARMZ), g=9.81)
"""App. B lines 16-22: m = 1.3 kg, J = diag(sp + armxy, sp + armxy, sp + armz) with
sp = 2(1.3 − 4·0.065)·0.06²/5, armxy = 4·0.065·0.2², armz = 4·0.065·0.28²
(J ≈ diag(0.0118976, 0.0118976, 0.0218816) kg m²)."""

TAU_MAX_APPB = 0.6 * 0.3
"""App. B line 24: torque limit per axis, N m."""

_E0 = np.array([1.0, -7.0, 3.0]) / math.sqrt(59.0)
Q0_CH34 = (math.cos(math.pi / 4),) + tuple(float(v) for v in _E0 * math.sin(math.pi / 4))
"""Ch. 3.4 initial attitude: 90° about [1, −7, 3]/‖·‖ (q0 ≥ 0), zero rates."""

QD_CH34 = (math.cos(math.pi / 12), 0.0, 0.0, math.sin(math.pi / 12))
"""Ch. 3.4 desired attitude: 30° about ẑ.  (App. B line 55 writes [cos 30°, 0, 0, sin 30°],
i.e. 60° about ẑ; the printed ch. 3.4 values are used.)"""

QD_APPB = (math.cos(math.pi / 6), 0.0, 0.0, math.sin(math.pi / 6))
"""App. B line 54-55 desired attitude as coded (60° about ẑ), for comparison only."""

DURATION_S = 25.0
"""App. B line 12: 25 s."""
DT_S = 1e-3
"""App. B line 13: 1 ms resolution."""


# ---------------------------------------------------------------------------
# The law
# ---------------------------------------------------------------------------

def att_matrices(dtype=None):
    """(A, B) of the linear attitude model eq. 3.15/3.17: A (6, 6), B (6, 3)."""
    if dtype is None:
        dtype = jnp.result_type(float)
    A = jnp.zeros((6, 6), dtype).at[:3, 3:].set(jnp.eye(3, dtype=dtype))
    B = jnp.zeros((6, 3), dtype).at[3:, :].set(jnp.eye(3, dtype=dtype))
    return A, B


def state_error(q, omega, q_d, omega_d=None):
    """x = [θ_e, ω − ω_d] of eq. 3.18/3.20 with θ_e = qlog(q ⊗ q_d*) (shortest rotation).

    ``q``, ``q_d``: (4,) unit quaternions (either sign); ``omega``, ``omega_d``: (3,)
    rad/s (``omega_d`` defaults to 0).  Returns (6,) in the dtype of ``q``; identical
    for ±q and ±q_d.
    """
    q = real_float(q, "q", (4,))  # an integer q truncated q_d to integers (NaN error)
    dt = q.dtype
    for v, nm, n in ((q_d, "q_d", 4), (omega, "omega", 3), (omega_d, "omega_d", 3)):
        if v is not None:
            check_real(v, nm)
            check_shape(v, (n,), nm)
    for v, nm in ((q, "q"), (q_d, "q_d")):
        if is_concrete(v):  # a zero quaternion has no log: NaN torque
            a = real_numbers(v, nm)
            if not (np.all(np.isfinite(a)) and np.linalg.norm(a) > 0):
                raise InputError(f"{nm}: expected a finite nonzero quaternion, got {a.tolist()}")
    theta = qlog(qmul(q, qconj(jnp.asarray(q_d, dt))))
    w_err = jnp.asarray(omega, dt)
    if omega_d is not None:
        w_err = w_err - jnp.asarray(omega_d, dt)
    return jnp.concatenate([theta, w_err])


def law(x, gains, eps=1.0, switching="tanh"):
    """u = −K1 x − K2 s(x), eq. 3.18/3.20; s = tanh(x/ε) or sign(x).

    ``x``: (6,) state error; ``gains``: :class:`SMCGains`; ``eps``: smoothing width of
    the tanh (1 = the thesis' TANH, same units as x); ``switching``: ``"tanh"`` or
    ``"sign"`` (Python string, static).  Returns u (3,).
    """
    x = real_float(x, "x", (6,))  # an integer x truncated the gains to 0
    # eps = 0 gave NaN (tanh only); NaN gains a NaN torque, (3, 3) ones a bare TypeError
    _validate_known(eps=eps if switching == "tanh" else None, gains=gains)
    dt = x.dtype
    K1 = jnp.asarray(gains.K1, dt)
    K2 = jnp.asarray(gains.K2, dt)
    if switching == "tanh":
        s = jnp.tanh(x / jnp.asarray(eps, dt))
    elif switching == "sign":
        s = jnp.sign(x)
    else:
        raise InputError(f"switching: expected 'tanh' or 'sign', got {switching!r}")
    return -K1 @ x - K2 @ s


def torque(u, omega, inertia, model="exact", tau_max=None):
    """Body torque from the law's output u; eq. 3.15 or app. B, then saturation.

    ``u``: (3,); ``omega``: (3,) rad/s; ``inertia``: (3,) J diagonal, kg m²;
    ``model``: ``"exact"`` τ = J u + ω × J ω (eq. 3.15) or ``"direct"`` τ = u (app. B);
    ``tau_max``: per-axis limit in N m (scalar, may be traced) or None.  Returns τ (3,).
    """
    u = real_float(u, "u", (3,))
    _validate_known(tau_max=tau_max, model=model,  # a negative limit flipped the clip
                    inertia=inertia if model == "exact" else None)
    dt = u.dtype
    if model == "exact":
        w = real_float(omega, "omega", (3,)).astype(dt)  # a (3, 3) ω broadcast to a (3, 3) τ
        J = jnp.asarray(inertia, dt)
        tau = J * u + jnp.cross(w, J * w)
    elif model == "direct":
        tau = u
    else:
        raise InputError(f"torque model: expected 'exact' or 'direct', got {model!r}")
    if tau_max is not None:
        lim = jnp.asarray(tau_max, dt)
        tau = jnp.clip(tau, -lim, lim)
    return tau


def control(q, omega, q_d, gains, inertia, omega_d=None, *, eps=1.0, switching="tanh",
            model="exact", tau_max=None):
    """Attitude torque of the sliding-mode law (eq. 3.20 with eq. 3.15), N m, (3,).

    Composition of :func:`state_error`, :func:`law` and :func:`torque`; see those for
    the arguments.  Continuous in q across q0 = 0 and identical for q and −q.
    """
    _validate_known(eps=eps, tau_max=tau_max, switching=switching, model=model,
                    inertia=inertia if model == "exact" else None)
    x = state_error(q, omega, q_d, omega_d)
    return torque(law(x, gains, eps, switching), omega, inertia, model, tau_max)


def _validate_known(**kw):
    """:func:`validate` on the arguments whose values are known now (an eager call; traced
    ones pass, and the strings are always known): a zero ``eps`` used to give a NaN torque."""
    validate(**{k: v for k, v in kw.items() if v is not None and (isinstance(v, str) or is_concrete(v))})


# ---------------------------------------------------------------------------
# Design and analysis
# ---------------------------------------------------------------------------

class LQRDesign(NamedTuple):
    """Result of :func:`lqr_gains`: K1, K2 (3, 6) and their Riccati matrices P1, P2 (6, 6)."""

    K1: jax.Array
    K2: jax.Array
    P1: jax.Array
    P2: jax.Array

    @property
    def gains(self) -> SMCGains:
        return SMCGains(self.K1, self.K2)


def _as_weight(W):
    W = jnp.asarray(W)
    return jnp.diag(W) if W.ndim == 1 else W


def lqr_gains(Q1=APPB_WEIGHTS[0], R1=APPB_WEIGHTS[1], Q2=APPB_WEIGHTS[2], R2=APPB_WEIGHTS[3]):
    """K1 and K2 by LQR on the double integrator (A, B) of eq. 3.15 (app. B lines 34-35).

    ``Q1``, ``Q2``: (6, 6) PSD or (6,) diagonal; ``R1``, ``R2``: (3, 3) PD or (3,)
    diagonal.  Defaults: app. B's weights (:data:`APPB_WEIGHTS`), which reproduce the
    printed ch. 3.4 gains.  Uses the foundation's CARE (:func:`jaxslam.control.lqr.care`).
    Returns :class:`LQRDesign` in the common dtype of the weights (float64 defaults
    follow JAX's default float).  Validated on the host when called with concrete arrays.
    """
    Ws = [_as_weight(W) for W in (Q1, R1, Q2, R2)]
    if is_concrete(*Ws):
        validate_weights(Ws[0], Ws[1], 6, 3, names=("Q1", "R1"))
        validate_weights(Ws[2], Ws[3], 6, 3, names=("Q2", "R2"))
    dtype = jnp.result_type(*Ws)
    if not jnp.issubdtype(dtype, jnp.floating):
        dtype = jnp.result_type(float)
    A, B = att_matrices(dtype)
    K1, P1 = lqr_gain(A, B, Ws[0].astype(dtype), Ws[1].astype(dtype))
    K2, P2 = lqr_gain(A, B, Ws[2].astype(dtype), Ws[3].astype(dtype))
    return LQRDesign(K1, K2, P1, P2)


class Theorem31(NamedTuple):
    """Theorem 3.1 checked numerically (see :func:`theorem31`).  All fields are arrays.

    As printed (app. B lines 38-40, NumPy's default Frobenius norms ‖·‖_F):
      L1_max:  ‖Q‖_F / (2 ‖P‖_F ‖B‖_F)
      L2_max:  ‖K2‖_F
      cond1 / cond2 / holds: L1_max > L1, L2_max > L2, both (holds also needs A − B K1
        Hurwitz and Q positive definite; a concrete non-Hurwitz K1 is an InputError).
    Rigorous form (spectral norms ‖·‖₂, λ_min):
      L1_max_rigorous:     λ_min(Q) / (2 ‖P B‖₂) — with L1 below it, V̇ < 0 for every
                           ‖x‖ > ball_radius (uniform ultimate boundedness); no
                           condition on L2 gives V̇ < 0 near 0.
      L1_max_conservative: λ_min(Q) / (2 ‖P‖₂ ‖B‖₂) (the proof's grouping, spectral).
      ball_radius:         2‖PB‖₂ (L2 + √6 ‖K2‖₂) / (λ_min(Q) − 2‖PB‖₂ L1), inf if
                           L1 ≥ L1_max_rigorous.
      lambda_min_Q, norm2_P, norm2_PB, norm2_K2: the pieces.
    Sampled check (worst-case ξ, SIGN law): frac_negative (fraction of sampled states
    with V̇ < 0), max_norm_violating (largest ‖x‖ with V̇ ≥ 0; 0 if none), r_min / r_max
    (range of ‖x‖ sampled).  NaN when no key was given.
    """

    L1_max: jax.Array
    L2_max: jax.Array
    cond1: jax.Array
    cond2: jax.Array
    holds: jax.Array
    L1_max_rigorous: jax.Array
    L1_max_conservative: jax.Array
    ball_radius: jax.Array
    lambda_min_Q: jax.Array
    norm2_P: jax.Array
    norm2_PB: jax.Array
    norm2_K2: jax.Array
    frac_negative: jax.Array
    max_norm_violating: jax.Array
    r_min: jax.Array
    r_max: jax.Array
    Q: jax.Array
    P: jax.Array


def _check_gain_matrix(K, name):
    check_shape(K, (3, 6), name)
    if not np.all(np.isfinite(np.asarray(K, dtype=np.float64))):
        raise InputError(f"{name}: contains NaN or Inf")


def theorem31(K1, K2, L1, L2, P=None, *, key=None, n_samples=4096, r_min=1e-3, r_max=10.0,
              switching="sign"):
    """Check Theorem 3.1 of paper 004 numerically for gains (K1, K2) and bounds (L1, L2).

    Q = −[(A − BK1)ᵀP + P(A − BK1)] with (A, B) of eq. 3.15.  ``P``: (6, 6) SPD, e.g.
    the LQR Riccati matrix of K1 (``lqr_gains().P1``); when None, P solves the
    Lyapunov equation (A − BK1)ᵀP + P(A − BK1) = −I (so Q = I).  ``K1``, ``K2``:
    (3, 6); ``L1``, ``L2``: scalars.

    The printed inequalities use unstated norms; app. B evaluates them with NumPy's
    default (Frobenius) norm, reproduced in ``L1_max``/``L2_max``.  The proof's step
    −2xᵀPBK2 SIGN(x) ≤ −2‖PB‖‖K2‖‖x‖ does not hold in general, so the rigorous
    fields report what does: V̇ < 0 outside a ball when L1 < ``L1_max_rigorous``.
    With ``key``, ``n_samples`` states x (uniform directions, ‖x‖ log-uniform in
    [r_min, r_max]) are checked with the worst-case admissible ξ
    (‖ξ‖ = L2 + L1‖x‖ along BᵀPx): V̇ = 2xᵀP[(A − BK1)x − BK2 s(x) + Bξ].
    Returns :class:`Theorem31`.
    """
    if is_concrete(K1, K2, L1, L2, P):
        _check_gain_matrix(K1, "K1")
        _check_gain_matrix(K2, "K2")
        for v, nm in ((L1, "L1"), (L2, "L2")):
            a = np.asarray(v, dtype=np.float64)
            if a.shape != () or not np.isfinite(a) or a < 0:
                raise InputError(f"{nm}: expected a finite scalar >= 0, got {v!r}")
        if P is not None:
            check_shape(P, (6, 6), "P")
            Pn = np.asarray(P, dtype=np.float64)
            if not np.all(np.isfinite(Pn)) or np.linalg.eigvalsh(0.5 * (Pn + Pn.T))[0] <= 0:
                raise InputError("P: must be a finite symmetric positive-definite matrix")
    K1, K2 = jnp.asarray(K1), jnp.asarray(K2)
    dtype = jnp.result_type(K1, K2) if P is None else jnp.result_type(K1, K2, jnp.asarray(P))
    if not jnp.issubdtype(dtype, jnp.floating):
        dtype = jnp.result_type(float)
    K1 = jnp.asarray(K1, dtype)
    K2 = jnp.asarray(K2, dtype)
    L1 = jnp.asarray(L1, dtype)
    L2 = jnp.asarray(L2, dtype)
    A, B = att_matrices(dtype)
    Acl = A - B @ K1
    hurwitz = is_hurwitz(Acl)  # traced: holds is False for a destabilising K1
    if is_concrete(hurwitz) and not bool(hurwitz):  # the bounds would mean nothing
        ev = np.linalg.eigvals(np.asarray(Acl, np.float64))
        raise InputError(f"K1: A − B K1 is not Hurwitz (largest eigenvalue real part "
                         f"{np.max(ev.real):.3g}); Theorem 3.1 needs a stabilising K1")
    if P is None:
        P = lyapunov(Acl, jnp.eye(6, dtype=dtype))
    P = 0.5 * (jnp.asarray(P, dtype) + jnp.asarray(P, dtype).T)
    Q = -(Acl.T @ P + P @ Acl)
    Q = 0.5 * (Q + Q.T)
    fro = jnp.linalg.norm
    L1_max = fro(Q) / (2.0 * fro(P) * fro(B))
    L2_max = fro(K2)
    lam_min = jnp.linalg.eigvalsh(Q)[0]
    n2P = jnp.linalg.norm(P, 2)
    PB = P @ B
    n2PB = jnp.linalg.norm(PB, 2)
    n2K2 = jnp.linalg.norm(K2, 2)
    L1_rig = lam_min / (2.0 * n2PB)
    L1_cons = lam_min / (2.0 * n2P * jnp.linalg.norm(B, 2))
    margin = lam_min - 2.0 * n2PB * L1
    radius = jnp.where(margin > 0, 2.0 * n2PB * (L2 + jnp.sqrt(6.0) * n2K2) / margin, jnp.inf)

    nan = jnp.asarray(jnp.nan, dtype)
    frac, worst = nan, nan
    if key is not None:
        kd, kr = jax.random.split(key)
        d = jax.random.normal(kd, (n_samples, 6), dtype)
        d = d / jnp.linalg.norm(d, axis=1, keepdims=True)
        lo, hi = math.log(r_min), math.log(r_max)
        r = jnp.exp(jax.random.uniform(kr, (n_samples,), dtype, lo, hi))
        xs = d * r[:, None]

        def vdot(x):
            s = jnp.sign(x) if switching == "sign" else jnp.tanh(x)
            g = B.T @ (P @ x)
            ng = jnp.linalg.norm(g)
            mag = (L2 + L1 * jnp.linalg.norm(x)) * (1.0 - 1e-10)
            xi = jnp.where(ng > 0, g / jnp.where(ng > 0, ng, 1.0), 0.0) * mag
            return 2.0 * x @ (P @ (Acl @ x - B @ (K2 @ s) + B @ xi))

        vd = jax.vmap(vdot)(xs)
        bad = vd >= 0
        frac = jnp.mean(~bad).astype(dtype)
        worst = jnp.max(jnp.where(bad, r, 0.0))
    return Theorem31(
        L1_max=L1_max, L2_max=L2_max, cond1=L1_max > L1, cond2=L2_max > L2,
        holds=(L1_max > L1) & (L2_max > L2) & hurwitz & (lam_min > 0), L1_max_rigorous=L1_rig,
        L1_max_conservative=L1_cons, ball_radius=radius, lambda_min_Q=lam_min, norm2_P=n2P,
        norm2_PB=n2PB, norm2_K2=n2K2, frac_negative=frac, max_norm_violating=worst,
        r_min=jnp.asarray(r_min, dtype), r_max=jnp.asarray(r_max, dtype), Q=Q, P=P)


# ---------------------------------------------------------------------------
# Perturbations (app. B lines 71-76, with eq. 3.17's bound)
# ---------------------------------------------------------------------------

def _magnitude(x_err, bounds):
    L1, L2 = bounds
    # safe_norm: a finite gradient at x_err = 0 (jnp.linalg.norm's is NaN there)
    return (L2 + L1 * safe_norm(x_err)) * (1.0 - 1e-10)


def _unit(v):
    return v / jnp.linalg.norm(v)  # (v never depends on the error: no gradient at 0 to guard)


def perturbation_constant(key, t, x_err, bounds):
    """ξ along ones/√3 with ‖ξ‖ = (L2 + L1‖x‖)(1 − 1e-10) (app. B line 73, eq. 3.17)."""
    del key, t
    return _unit(jnp.ones(3, x_err.dtype)) * _magnitude(x_err, bounds)


def perturbation_sinusoidal(key, t, x_err, bounds):
    """ξ along cos([0.3t, 0.5t, t]) normalised, bounded like the constant one (app. B line 72)."""
    del key
    t = jnp.asarray(t, x_err.dtype)
    return _unit(jnp.cos(jnp.stack([0.3 * t, 0.5 * t, t]))) * _magnitude(x_err, bounds)


def perturbation_random(key, t, x_err, bounds):
    """Uniform random direction, magnitude uniform in [0, (L2 + L1‖x‖)(1 − 1e-10)].

    Bounded (app. B line 76 draws a Gaussian of that scale, which can exceed the bound
    of eq. 3.17).  ``key`` must differ per step (:func:`closed_loop` folds in the step).
    """
    del t
    kd, km = jax.random.split(key)
    d = _unit(jax.random.normal(kd, (3,), x_err.dtype))
    return d * jax.random.uniform(km, (), x_err.dtype) * _magnitude(x_err, bounds)


def perturbation_none(key, t, x_err, bounds):
    """ξ = 0."""
    del key, t, bounds
    return jnp.zeros(3, x_err.dtype)


PERTURBATIONS = {
    "none": perturbation_none,
    "constant": perturbation_constant,
    "sinusoidal": perturbation_sinusoidal,
    "random": perturbation_random,
}


def perturbation(name):
    """The perturbation function ``(key, t, x_err, bounds) -> ξ (3,)`` called ``name``."""
    try:
        return PERTURBATIONS[name]
    except KeyError:
        raise InputError(f"perturbation: expected one of {sorted(PERTURBATIONS)}, got {name!r}") from None


def perturbation_bounds(gains, P=None, scale=1.0):
    """(L1, L2) = scale × the admissible maxima of Theorem 3.1 in app. B's (Frobenius) form.

    ``P``: Riccati/Lyapunov matrix for K1 (None: Lyapunov with Q = I, see
    :func:`theorem31`).  Returns two Python floats (host side).
    """
    try:
        rep = theorem31(real_numbers(gains.K1, "gains.K1"), real_numbers(gains.K2, "gains.K2"), 0.0, 0.0,
                        None if P is None else real_numbers(P, "P"))
    except InputError as e:
        msg = str(e)
        raise InputError("gains." + msg if msg.startswith(("K1:", "K2:")) else msg) from None
    return float(scale) * float(rep.L1_max), float(scale) * float(rep.L2_max)


# ---------------------------------------------------------------------------
# Closed loop
# ---------------------------------------------------------------------------

class Rollout(NamedTuple):
    """Output of :func:`closed_loop`.

    xa_final: (7,) final [q, ω].
    norms:    (T, 3) per step: ‖θ_e‖ (rad), ‖ω − ω_d‖ (rad/s), max_i |τ_i| (N m), at the
              start of each step (t_k = k dt).
    xa:       (T + 1, 7) states, or None unless ``record=True``.
    x_err:    (T, 6) state errors, or None.
    tau:      (T, 3) applied torques (after saturation), N m, or None.
    xi:       (T, 3) applied perturbations, rad/s², or None.
    """

    xa_final: jax.Array
    norms: jax.Array
    xa: Optional[jax.Array] = None
    x_err: Optional[jax.Array] = None
    tau: Optional[jax.Array] = None
    xi: Optional[jax.Array] = None


def closed_loop(xa0, q_d, gains, inertia, dt, steps, key, bounds, *, perturbation_name="constant",
                eps=1.0, switching="tanh", model="exact", tau_max=None, omega_d=None,
                record=False):
    """Simulate the attitude model eq. 3.13 (+ ξ, eq. 3.17) under the law eq. 3.20.

    ``xa0``: (7,) [q, ω]; ``q_d``: (4,) constant desired attitude; ``omega_d``: (3,) or
    None (0); ``gains``: :class:`SMCGains`; ``inertia``: (3,) kg m²; ``dt``: s;
    ``steps``: number of steps T (static); ``key``: PRNG key (random perturbation;
    step k uses fold_in(key, k)); ``bounds``: (L1, L2) of eq. 3.17 (traced);
    ``perturbation_name``: a key of :data:`PERTURBATIONS`; ``eps``, ``switching``,
    ``model``, ``tau_max``: as in :func:`control` (``tau_max`` None: no limit; traced
    otherwise).  The control and ξ are held over each step; each step is
    :func:`jaxslam.dynamics.quaternion_quad.step` (RK4 + renormalisation), all in one
    ``lax.scan``.  Returns :class:`Rollout`.  The arguments whose values are known now (an
    eager call) are validated here, before the jitted core (inside it every value was a tracer:
    eps = 0 ran to NaN, a negative dt or inertia ran silently); traced ones pass.
    """
    _validate_known(inertia=inertia, dt=dt, eps=eps if switching == "tanh" else None, tau_max=tau_max,
                    switching=switching, model=model,
                    perturbation_name=perturbation_name, gains=gains, xa0=xa0, q_d=q_d)
    check_real(xa0, "xa0")
    check_shape(xa0, (7,), "xa0")
    # (a zero q_d or xa0 quaternion, NaN gains, bounds or omega_d ran to an all-NaN rollout)
    if is_concrete(bounds):
        b = np.asarray([np.asarray(v, np.float64) for v in bounds]) if len(bounds) == 2 else None
        if b is None or b.shape != (2,) or not np.all(np.isfinite(b) & (b >= 0)):
            raise InputError(f"bounds: expected (L1, L2), two finite numbers >= 0, got {bounds!r}"[:300])
    if omega_d is not None and is_concrete(omega_d):
        check_shape(omega_d, (3,), "omega_d")
        if not np.all(np.isfinite(np.asarray(omega_d, np.float64))):
            raise InputError(f"omega_d: expected finite rates, got {omega_d!r}"[:300])
    if not isinstance(steps, (int, np.integer)) or isinstance(steps, bool) or steps < 0:
        raise InputError(f"steps: expected an int >= 0 (static), got {steps!r}")
    return _closed_loop(xa0, q_d, gains, inertia, dt, steps, key, bounds,
                        perturbation_name=perturbation_name, eps=eps, switching=switching, model=model,
                        tau_max=tau_max, omega_d=omega_d, record=record)


@functools.partial(jax.jit, static_argnames=("steps", "perturbation_name", "switching", "model",
                                             "record"))
def _closed_loop(xa0, q_d, gains, inertia, dt, steps, key, bounds, *, perturbation_name="constant",
                 eps=1.0, switching="tanh", model="exact", tau_max=None, omega_d=None,
                 record=False):
    """The jitted core of :func:`closed_loop` (compiled once per static options, shapes, dtypes)."""
    xa0 = real_float(xa0, "xa0")
    dtp = xa0.dtype
    q_d = jnp.asarray(q_d, dtp)
    J = jnp.asarray(inertia, dtp)
    h = jnp.asarray(dt, dtp)
    bounds = (jnp.asarray(bounds[0], dtp), jnp.asarray(bounds[1], dtp))
    lim = None if tau_max is None else jnp.asarray(tau_max, dtp)
    w_d = None if omega_d is None else jnp.asarray(omega_d, dtp)
    pert = PERTURBATIONS[perturbation_name]

    def body(xa, k):
        t = k.astype(dtp) * h
        x = state_error(xa[:4], xa[4:], q_d, w_d)
        tau = torque(law(x, gains, eps, switching), xa[4:], J, model, lim)
        xi = pert(jax.random.fold_in(key, k), t, x, bounds)
        xn = qq.step(qq.f_att, xa, tau, h, J, xi)
        norms = jnp.stack([safe_norm(x[:3]), safe_norm(x[3:]), jnp.max(jnp.abs(tau))])
        out = (norms, xn, x, tau, xi) if record else (norms,)
        return xn, out

    xa_f, outs = jax.lax.scan(body, xa0, jnp.arange(steps))
    if record:
        norms, xs, xe, taus, xis = outs
        return Rollout(xa_f, norms, jnp.concatenate([xa0[None], xs]), xe, taus, xis)
    return Rollout(xa_f, outs[0])


# the compiled core's cache, seen through the wrapper (a new value must reuse the program)
closed_loop._cache_size = _closed_loop._cache_size
closed_loop.clear_cache = _closed_loop.clear_cache


def validate(gains=None, inertia=None, *, xa0=None, q_d=None, dt=None, eps=None, tau_max=None,
             switching=None, model=None, perturbation_name=None):
    """Host-side checks of the law's inputs; raises :class:`~jaxslam.errors.InputError`.

    Checks what is given: gains (3, 6) finite, inertia (3,) positive finite, xa0 (7,)
    finite with unit quaternion, q_d (4,) finite unit, dt / eps positive finite,
    tau_max positive finite or None, and the string options.
    """
    if gains is not None:
        if not isinstance(gains, SMCGains):
            raise InputError(f"gains: expected SMCGains, got {type(gains).__name__}")
        _check_gain_matrix(gains.K1, "gains.K1")
        _check_gain_matrix(gains.K2, "gains.K2")
    if inertia is not None:
        qq.check_inertia(inertia, "inertia")
    if xa0 is not None:
        qq.check_att_state(xa0, "xa0")
    if q_d is not None:
        check_shape(q_d, (4,), "q_d")
        a = np.asarray(q_d, dtype=np.float64)
        if not np.all(np.isfinite(a)) or abs(np.linalg.norm(a) - 1.0) > 1e-6:
            raise InputError(f"q_d: expected a finite unit quaternion, got {a.tolist()}")
    for v, nm in ((dt, "dt"), (eps, "eps"), (tau_max, "tau_max")):
        if v is None:
            continue
        a = np.asarray(v, dtype=np.float64)
        if a.shape != () or not np.isfinite(a) or a <= 0:
            raise InputError(f"{nm}: expected a finite positive scalar, got {v!r}")
    if switching is not None and switching not in ("tanh", "sign"):
        raise InputError(f"switching: expected 'tanh' or 'sign', got {switching!r}")
    if model is not None and model not in ("exact", "direct"):
        raise InputError(f"torque model: expected 'exact' or 'direct', got {model!r}")
    if perturbation_name is not None and perturbation_name not in PERTURBATIONS:
        raise InputError(f"perturbation: expected one of {sorted(PERTURBATIONS)}, "
                         f"got {perturbation_name!r}")


def initial_state(dtype=None):
    """Ch. 3.4 initial attitude state [q0 (90° about [1, −7, 3]), ω = 0], (7,)."""
    if dtype is None:
        dtype = jnp.result_type(float)
    return jnp.concatenate([qnormalize(jnp.asarray(Q0_CH34, dtype)), jnp.zeros(3, dtype)])

