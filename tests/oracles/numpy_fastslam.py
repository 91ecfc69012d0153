"""NumPy twin of paper 001's FastSLAM step (``jaxslam.systems.fastslam_001.step``).

The reference of ``jaxslam bench fastslam`` and an independent oracle of
``tests/benchmarks/test_bench_fastslam_twin.py``.  It runs the SAME filter step
as the package with ``Config(model="dynamics", lidar="world",
weights="exact", stage2="paper", accel_mode="specific_force",
resampling="systematic")`` and a resampling threshold (default N_eff < 0.5 N,
or ``None`` = every weight update):

IMU sample (paper 001 Table 2, steps 1-4, 6, 8):
  1. x^D ← RK4(f, x^D, ω_rotor) + diag(σ) ε  (eq. 1-4: mixer, gyroscopic Ω_r,
     3-2-1 Euler D(φ, θ), z-up world), bias means ← A^b x̂^B (eq. 11);
  2. shared bias covariance P ← A^b P A^b + Q^b;
  3. z̄ = z^I − h^d(x^D) (eq. 12, specific force R_b^wᵀ(a_w + g e3), ω_b);
     log-weight += log N(z̄ − H_b x̂^B; 0, H_b P H_bᵀ + R^I) (none at k = 0);
  4. bias KF update of every mean with the shared gain (factored Joseph form
     for the shared P); at k = 0 the means are re-initialised by H_b⁺ z̄;
  6. systematic resampling when N_eff < threshold·N;
  8. rates ← ω_m − (b̂0ω + b̂1ω) + chol(R_ω + H_ω P H_ωᵀ) ε.
LiDAR frame (when any measurement is present, after the IMU sample):
  landmark EKF per particle and measurement in order (id j in slot j): update
  with the closed-form 3×3 inverse of S and log N(ν; 0, S), or registration
  μ = p + ϱ(z), Σ = G⁻¹ R G⁻ᵀ; resampling; position regeneration from the
  information fusion of p_j = μ_j − ϱ(z_j), C_j = J R Jᵀ + Σ_j.

Everything is vectorised over particles with hand-written Jacobians (∂[α, β, r]
/∂c of the spherical map, ∂ϱ/∂z of its inverse) and closed-form 3×3 inverses
and Cholesky factors; no JAX.  The kernels broadcast over any leading axes, so
:func:`step_loop` runs the same kernels one particle at a time (the per-particle
Python loop of the benchmark).  Float64.

Random numbers are inputs (:class:`Draws`): the test injects the draws that
jaxslam makes from its keys, the benchmark draws them with NumPy.

Not reproduced (diagnostics only, no effect on the estimate): the status bits,
overflow and underflow counters; the frame output (map mean) that ``step``
discards.  Host-side shortcuts a NumPy programmer would take (and that change
no number): measurements absent from the frame are skipped, and the landmark
update and registration branches are computed only for the particles that
need them (all or none in practice, known data association).
"""

from __future__ import annotations

import math
from typing import NamedTuple, Optional

import numpy as np

__all__ = ["H_B", "Params", "State", "Draws", "StepOut", "params_from", "state_from",
           "draw", "imu_stage", "lidar_stage", "step", "step_loop"]

LOG2PI = math.log(2.0 * math.pi)
H_B = np.block([[np.eye(3), np.zeros((3, 3)), np.eye(3), np.zeros((3, 3))],
                [np.zeros((3, 3)), np.eye(3), np.zeros((3, 3)), np.eye(3)]])
H_B_PINV = np.linalg.pinv(H_B)
ANGLES = slice(6, 9)


class Params(NamedTuple):
    """Numbers of the filter (float64 NumPy).

    mass kg; inertia (3,) kg m²; g m/s²; arm m; k_thrust N s²; k_drag N m s²;
    rotor_inertia kg m²; prop_sd (12,) per-step proposal std; imu_var (6,);
    lidar_var (3,) [rad², rad², m²]; a_b, q_b (12,) diagonals of A^b, Q^b;
    bias_p0 (12,); dt s; threshold: N_eff fraction or None (every update).
    """

    mass: float
    inertia: np.ndarray
    g: float
    arm: float
    k_thrust: float
    k_drag: float
    rotor_inertia: float
    prop_sd: np.ndarray
    imu_var: np.ndarray
    lidar_var: np.ndarray
    a_b: np.ndarray
    q_b: np.ndarray
    dt: float
    threshold: Optional[float] = 0.5


class State(NamedTuple):
    """pose (N, 12), aux (N, 12) bias means, lm_mean (N, cap, 3), lm_cov (N, cap, 3, 3),
    active (N, cap) bool, ids (N, cap) int, log_w (N,), bias_cov (12, 12), k int,
    neff_min float, resamples int."""

    pose: np.ndarray
    aux: np.ndarray
    lm_mean: np.ndarray
    lm_cov: np.ndarray
    active: np.ndarray
    ids: np.ndarray
    log_w: np.ndarray
    bias_cov: np.ndarray
    k: int
    neff_min: float
    resamples: int


class Draws(NamedTuple):
    """Random numbers of one step: prop (N, 12) N(0, 1) proposal noise; u_imu () U(0, 1) of
    the IMU-stage systematic resampling; rate (N, 3) N(0, 1) of the rate regeneration;
    u_lidar () U(0, 1) of the LiDAR-stage resampling; pos (N, 3) N(0, 1) of the position
    regeneration."""

    prop: np.ndarray
    u_imu: float
    rate: np.ndarray
    u_lidar: float
    pos: np.ndarray


class StepOut(NamedTuple):
    """As ``fastslam_001.StepOut``: pose mean/var (12,), bias mean/var (12,), offset var (6,),
    N_eff after the IMU weight."""

    pose_mean: np.ndarray
    pose_var: np.ndarray
    bias_mean: np.ndarray
    bias_var: np.ndarray
    offset_var: np.ndarray
    neff: float


def params_from(fp, dt, threshold=0.5) -> Params:
    """:class:`Params` from a ``fastslam_001.Params`` (any array types)."""
    q = fp.quad
    f = lambda v: float(np.asarray(v))  # noqa: E731
    drift_a = np.asarray(fp.drift_a, np.float64)
    drift_q = np.asarray(fp.drift_q, np.float64)
    return Params(
        mass=f(q.mass), inertia=np.asarray(q.inertia, np.float64), g=f(q.g), arm=f(q.arm_length),
        k_thrust=f(q.k_thrust), k_drag=f(q.k_drag), rotor_inertia=f(q.rotor_inertia),
        prop_sd=np.sqrt(np.asarray(fp.proposal_var, np.float64)),
        imu_var=np.asarray(fp.imu_var, np.float64), lidar_var=np.asarray(fp.lidar_var, np.float64),
        a_b=np.concatenate([np.ones(6), drift_a]), q_b=np.concatenate([np.zeros(6), drift_q]),
        dt=float(dt), threshold=None if threshold is None else float(threshold))


def state_from(fs) -> State:
    """:class:`State` (NumPy copies) from a ``fastslam_001.State``."""
    p = fs.particles
    a = lambda v: np.array(v)  # noqa: E731
    return State(a(p.pose), a(p.aux), a(p.lm_mean), a(p.lm_cov), a(p.active), a(p.ids),
                 a(p.log_w), a(fs.bias_cov), int(fs.k), float(fs.neff_min), int(p.resamples))


def draw(rng: np.random.Generator, n: int) -> Draws:
    """Fresh :class:`Draws` for n particles from a NumPy generator."""
    return Draws(rng.standard_normal((n, 12)), rng.random(), rng.standard_normal((n, 3)),
                 rng.random(), rng.standard_normal((n, 3)))


# ---------------------------------------------------------------------------
# Small kernels (broadcast over leading axes)
# ---------------------------------------------------------------------------

def _wrap(a):
    return (a + np.pi) % (2.0 * np.pi) - np.pi


def _sym(A):
    return 0.5 * (A + np.swapaxes(A, -1, -2))


def _mv(A, x):
    return np.einsum("...ij,...j->...i", A, x)


def _dcm(e):
    """R_b^w = C3(ψ) C2(θ) C1(φ) (..., 3, 3)."""
    cf, sf = np.cos(e[..., 0]), np.sin(e[..., 0])
    ct, st = np.cos(e[..., 1]), np.sin(e[..., 1])
    cp, sp = np.cos(e[..., 2]), np.sin(e[..., 2])
    R = np.empty(e.shape[:-1] + (3, 3))
    R[..., 0, 0] = cp * ct
    R[..., 0, 1] = cp * st * sf - sp * cf
    R[..., 0, 2] = cp * st * cf + sp * sf
    R[..., 1, 0] = sp * ct
    R[..., 1, 1] = sp * st * sf + cp * cf
    R[..., 1, 2] = sp * st * cf - cp * sf
    R[..., 2, 0] = -st
    R[..., 2, 1] = ct * sf
    R[..., 2, 2] = ct * cf
    return R


def _f(x, u, omega_r, P: Params):
    """Paper 001 eq. 1-3 (z-up world velocity, 3-2-1 Euler, gyroscopic term); ẋ (..., 12)."""
    e, w = x[..., 6:9], x[..., 9:12]
    cf, sf = np.cos(e[..., 0]), np.sin(e[..., 0])
    ct, st = np.cos(e[..., 1]), np.sin(e[..., 1])
    cp, sp = np.cos(e[..., 2]), np.sin(e[..., 2])
    a = u[0] / P.mass
    out = np.empty(x.shape)
    out[..., 0:3] = x[..., 3:6]
    out[..., 3] = a * (cp * st * cf + sp * sf)
    out[..., 4] = a * (sp * st * cf - cp * sf)
    out[..., 5] = a * (ct * cf) - P.g
    p, q, r = w[..., 0], w[..., 1], w[..., 2]
    tt = st / ct
    out[..., 6] = p + sf * tt * q + cf * tt * r
    out[..., 7] = cf * q - sf * r
    out[..., 8] = (sf * q + cf * r) / ct
    J = P.inertia
    h = P.rotor_inertia * omega_r
    Jw0, Jw1, Jw2 = J[0] * p, J[1] * q, J[2] * r + h
    # −ω × (J ω + h e3) + τ, divided by J
    out[..., 9] = (-(q * Jw2 - r * Jw1) + u[1]) / J[0]
    out[..., 10] = (-(r * Jw0 - p * Jw2) + u[2]) / J[1]
    out[..., 11] = (-(p * Jw1 - q * Jw0) + u[3]) / J[2]
    return out


def _mixer(wr, P: Params):
    s = wr * wr
    lk = P.arm * P.k_thrust
    u = np.array([P.k_thrust * s.sum(), lk * (s[1] - s[3]), lk * (s[2] - s[0]),
                  P.k_drag * ((s[1] + s[3]) - (s[0] + s[2]))])
    return u, wr[0] - wr[1] + wr[2] - wr[3]


def _h_imu(x, u, P: Params):
    """h^d(x) (..., 6): R_b^wᵀ (a_w + g e3) and ω_b (eq. 12, specific force)."""
    R = _dcm(x[..., 6:9])
    a = u[0] / P.mass
    acc = a * R[..., :, 2]
    acc[..., 2] = acc[..., 2] - P.g + P.g  # same rounding as a_w + g e3 in the package
    out = np.empty(x.shape[:-1] + (6,))
    out[..., 0:3] = np.einsum("...ji,...j->...i", R, acc)
    out[..., 3:6] = x[..., 9:12]
    return out


def _spherical(c):
    """[α, β, r] of c (..., 3) and its Jacobian ∂/∂c (..., 3, 3) (hand-derived)."""
    x, y, z = c[..., 0], c[..., 1], c[..., 2]
    h2 = x * x + y * y
    h = np.sqrt(h2)
    r2 = h2 + z * z
    r = np.sqrt(r2)
    val = np.stack([np.arctan2(y, x), np.arctan2(z, h), r], axis=-1)
    J = np.empty(c.shape + (3,))
    J[..., 0, 0] = -y / h2
    J[..., 0, 1] = x / h2
    J[..., 0, 2] = 0.0
    hr2 = h * r2
    J[..., 1, 0] = -x * z / hr2
    J[..., 1, 1] = -y * z / hr2
    J[..., 1, 2] = h / r2
    J[..., 2, 0] = x / r
    J[..., 2, 1] = y / r
    J[..., 2, 2] = z / r
    return val, J


def _cartesian(zz):
    """ϱ(z) = r [cβ cα, cβ sα, sβ] (..., 3) and ∂ϱ/∂z (..., 3, 3) (hand-derived)."""
    a, b, r = zz[..., 0], zz[..., 1], zz[..., 2]
    ca, sa, cb, sb = np.cos(a), np.sin(a), np.cos(b), np.sin(b)
    val = np.stack([r * cb * ca, r * cb * sa, r * sb], axis=-1)
    J = np.empty(zz.shape + (3,))
    J[..., 0, 0] = -r * cb * sa
    J[..., 1, 0] = r * cb * ca
    J[..., 2, 0] = 0.0
    J[..., 0, 1] = -r * sb * ca
    J[..., 1, 1] = -r * sb * sa
    J[..., 2, 1] = r * cb
    J[..., 0, 2] = cb * ca
    J[..., 1, 2] = cb * sa
    J[..., 2, 2] = sb
    return val, J


def _inv3(A):
    """(A⁻¹, det A) of (..., 3, 3) by the adjugate (det = 0 gives a zero-divided inverse)."""
    a, b, c = A[..., 0, 0], A[..., 0, 1], A[..., 0, 2]
    d, e, f = A[..., 1, 0], A[..., 1, 1], A[..., 1, 2]
    g, h, i = A[..., 2, 0], A[..., 2, 1], A[..., 2, 2]
    c00, c01, c02 = e * i - f * h, -(d * i - f * g), d * h - e * g
    det = a * c00 + b * c01 + c * c02
    adj = np.empty(A.shape)
    adj[..., 0, 0], adj[..., 1, 0], adj[..., 2, 0] = c00, c01, c02
    adj[..., 0, 1] = -(b * i - c * h)
    adj[..., 1, 1] = a * i - c * g
    adj[..., 2, 1] = -(a * h - b * g)
    adj[..., 0, 2] = b * f - c * e
    adj[..., 1, 2] = -(a * f - c * d)
    adj[..., 2, 2] = a * e - b * d
    safe = np.where(det != 0, det, 1.0)
    return adj / safe[..., None, None], det


def _chol3(A):
    """Lower Cholesky factor of SPD (..., 3, 3) in closed form."""
    L = np.zeros(A.shape)
    l00 = np.sqrt(A[..., 0, 0])
    l10 = A[..., 1, 0] / l00
    l20 = A[..., 2, 0] / l00
    l11 = np.sqrt(A[..., 1, 1] - l10 * l10)
    l21 = (A[..., 2, 1] - l20 * l10) / l11
    l22 = np.sqrt(A[..., 2, 2] - l20 * l20 - l21 * l21)
    L[..., 0, 0], L[..., 1, 0], L[..., 2, 0] = l00, l10, l20
    L[..., 1, 1], L[..., 2, 1], L[..., 2, 2] = l11, l21, l22
    return L


def _normalize(lw):
    lw = np.where(np.isnan(lw), -np.inf, lw)
    top = np.max(lw)
    if not np.isfinite(top):
        return np.full_like(lw, -math.log(lw.shape[0]))
    s = lw - top
    return s - math.log(np.sum(np.exp(s)))


def _ess(lw):
    lw = _normalize(lw)
    t = 2.0 * lw
    m = np.max(t)
    return math.exp(-(m + math.log(np.sum(np.exp(t - m)))))


def _systematic(lw, U):
    n = lw.shape[0]
    c = np.cumsum(np.exp(_normalize(lw)))
    c[-1] = 1.0
    u = (np.arange(n) + U) / n
    return np.clip(np.searchsorted(c, u, side="right"), 0, n - 1)


def _maybe_resample(st: State, U, threshold):
    n = st.log_w.shape[0]
    if threshold is not None and not (_ess(st.log_w) < threshold * n):
        return st
    i = _systematic(st.log_w, U)
    return st._replace(pose=st.pose[i], aux=st.aux[i], lm_mean=st.lm_mean[i],
                       lm_cov=st.lm_cov[i], active=st.active[i], ids=st.ids[i],
                       log_w=np.full(n, -math.log(n)), resamples=st.resamples + 1)


# ---------------------------------------------------------------------------
# Per-particle kernels (any leading axes: (12,) one particle, (N, 12) all)
# ---------------------------------------------------------------------------

def _propagate(x, b, eps, u, omega_r, P: Params):
    """Step 1-2: RK4 of eq. 1-4 with the rotor input held, + σ ε; bias mean A^b b."""
    h = P.dt
    k1 = _f(x, u, omega_r, P)
    k2 = _f(x + 0.5 * h * k1, u, omega_r, P)
    k3 = _f(x + 0.5 * h * k2, u, omega_r, P)
    k4 = _f(x + h * k3, u, omega_r, P)
    xn = x + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
    return xn + P.prop_sd * eps, P.a_b * b


def _bias_update(x, b, imu, u, K, Sinv, m_first, P: Params):
    """Steps 3-4 per particle: z̄, innovation ν = z̄ − H_b b, posterior mean, NIS."""
    zbar = imu - _h_imu(x, u, P)
    nu = zbar - (b[..., 0:6] + b[..., 6:12])  # H_b b
    nis = np.einsum("...i,ij,...j->...", nu, Sinv, nu)
    if m_first:
        return zbar @ H_B_PINV.T, nis
    return b + nu @ K.T, nis


def _regen_rates(x, b, eps, gyro, Lg):
    x = x.copy()
    x[..., 9:12] = gyro - b[..., 3:6] - b[..., 9:12] + eps @ Lg.T
    return x


def _lidar_particle(x, mean, cov, active, z, ids, mask, R):
    """One LiDAR frame for particle(s): landmark EKFs and registrations in measurement order
    (Table 3) with the exact log-likelihood log N(ν; 0, S).  Returns (mean, cov, active, loglik)."""
    cap = mean.shape[-2]
    pos = x[..., 0:3]
    ll = np.zeros(x.shape[:-1])
    mean, cov, active = mean.copy(), cov.copy(), active.copy()
    for j in range(z.shape[0]):
        if not mask[j] or ids[j] < 0 or not np.all(np.isfinite(z[j])):
            continue
        i = int(ids[j])
        if i >= cap:
            continue  # capacity overflow: dropped (the package counts it)
        known = active[..., i]
        zj = z[j]
        if np.any(known):
            m, Pl = mean[..., i, :], cov[..., i, :, :]
            zhat, H = _spherical(m - pos)
            nu = zj - zhat
            nu[..., 0] = _wrap(nu[..., 0])
            HP = H @ Pl
            S = _sym(HP @ np.swapaxes(H, -1, -2) + R)
            Si, det = _inv3(S)
            ok = (det > 0) & (S[..., 0, 0] > 0) & (S[..., 0, 0] * S[..., 1, 1] - S[..., 0, 1] * S[..., 1, 0] > 0)
            ok &= np.all(np.isfinite(Si), axis=(-1, -2))
            K = np.swapaxes(HP, -1, -2) @ Si
            nis = np.einsum("...i,...ij,...j->...", nu, Si, nu)
            m_post = m + _mv(K, nu)
            A = Pl - K @ HP
            P_post = _sym(A - (A @ np.swapaxes(H, -1, -2)) @ np.swapaxes(K, -1, -2)
                          + K @ R @ np.swapaxes(K, -1, -2))
            acc = known & ok & np.all(np.isfinite(m_post), -1) & np.all(np.isfinite(P_post), (-1, -2))
            mean[..., i, :] = np.where(acc[..., None], m_post, m)
            cov[..., i, :, :] = np.where(acc[..., None, None], P_post, Pl)
            logdet = np.log(np.where(ok, det, 1.0))
            ll = ll + np.where(acc, -(0.5 * (nis + logdet) + 1.5 * LOG2PI), 0.0)
        if not np.all(known):
            rho, _ = _cartesian(zj)
            l_reg = pos + rho
            _, G = _spherical(l_reg - pos)
            Gi, det = _inv3(G)
            c_reg = _sym(Gi @ R @ np.swapaxes(Gi, -1, -2))
            reg = (~known) & (det != 0) & np.all(np.isfinite(l_reg), -1) & np.all(np.isfinite(c_reg), (-1, -2))
            mean[..., i, :] = np.where(reg[..., None], l_reg, mean[..., i, :])
            cov[..., i, :, :] = np.where(reg[..., None, None], c_reg, cov[..., i, :, :])
            active[..., i] = active[..., i] | reg
    return mean, cov, active, ll


def _regen_position(x, mean, cov, active, z, ids, mask, R, eps):
    """Step 8 (position): fuse p_j = μ_j − ϱ(z_j), C_j = J R Jᵀ + Σ_j over the frame's mapped
    landmarks and draw m + chol(P) ε; unchanged where none is mapped."""
    cap = mean.shape[-2]
    info = np.zeros(x.shape[:-1] + (3, 3))
    eta = np.zeros(x.shape[:-1] + (3,))
    any_ok = np.zeros(x.shape[:-1], bool)
    for j in range(z.shape[0]):
        if not mask[j] or ids[j] < 0 or ids[j] >= cap:
            continue
        i = int(ids[j])
        ok = active[..., i]
        rho, Jc = _cartesian(z[j])
        pj = mean[..., i, :] - rho
        C = _sym(Jc @ R @ Jc.T + cov[..., i, :, :])
        C = np.where(ok[..., None, None], C, np.eye(3))
        Ci, _ = _inv3(C)
        Ci = Ci * ok[..., None, None]
        info = info + Ci
        eta = eta + _mv(Ci, np.where(ok[..., None], pj, 0.0))
        any_ok = any_ok | ok
    info = np.where(any_ok[..., None, None], info, np.eye(3))
    Pp, _ = _inv3(info)
    Pp = _sym(Pp)
    m = _mv(Pp, eta)
    sample = m + _mv(_chol3(Pp), eps)
    x = x.copy()
    x[..., 0:3] = np.where(any_ok[..., None], sample, x[..., 0:3])
    return x


# ---------------------------------------------------------------------------
# Stages and step
# ---------------------------------------------------------------------------

def _shared_bias(st: State, P: Params):
    """Shared KF quantities: predicted P, S = H P Hᵀ + R^I, gain, S⁻¹, log det S, posterior P."""
    Pp = _sym(P.a_b[:, None] * st.bias_cov * P.a_b[None, :] + np.diag(P.q_b))
    HP = H_B @ Pp
    S = _sym(HP @ H_B.T + np.diag(P.imu_var))
    L = np.linalg.cholesky(S)
    Li = np.linalg.inv(L)
    Sinv = Li.T @ Li
    K = HP.T @ Sinv
    A = Pp - K @ HP
    P_post = _sym(A - (A @ H_B.T) @ K.T + K @ np.diag(P.imu_var) @ K.T)
    logdet = 2.0 * np.sum(np.log(np.diag(L)))
    return K, Sinv, logdet, P_post


def _step_out(st: State, neff) -> StepOut:
    w = np.exp(st.log_w)
    x = st.pose
    mu = w @ x
    ang = x[:, ANGLES]
    mu[ANGLES] = np.arctan2(w @ np.sin(ang), w @ np.cos(ang))
    dev = x - mu
    dev[:, ANGLES] = _wrap(dev[:, ANGLES])
    pvar = w @ (dev * dev)
    bm = w @ st.aux
    bvar = np.diag(st.bias_cov) + w @ ((st.aux - bm) ** 2)
    off = st.aux[:, 0:6] + st.aux[:, 6:12]
    ov = np.diag(H_B @ st.bias_cov @ H_B.T) + w @ ((off - (bm[0:6] + bm[6:12])) ** 2)
    return StepOut(mu, pvar, bm, bvar, ov, neff)


def _per_particle(fn, n, *arrays):
    """Apply ``fn`` to particle i's slices of ``arrays`` for i < n; stack the outputs."""
    outs = [fn(*(a[i] for a in arrays)) for i in range(n)]
    if isinstance(outs[0], tuple):
        return tuple(np.stack(o) for o in zip(*outs))
    return np.stack(outs)


def imu_stage(st: State, rotor_w, imu, d: Draws, P: Params, loop: bool = False):
    """One IMU sample (module docstring, steps 1-4, 6, 8).  Returns (State, StepOut)."""
    n = st.pose.shape[0]
    rotor_w = np.asarray(rotor_w, np.float64)
    imu = np.asarray(imu, np.float64)
    u, omega_r = _mixer(rotor_w, P)
    first = st.k == 0
    K, Sinv, logdet, P_post = _shared_bias(st, P)
    if loop:
        def one(x, b, e):
            xn, bn = _propagate(x, b, e, u, omega_r, P)
            return (xn, bn) + _bias_update(xn, bn, imu, u, K, Sinv, first, P)

        pose, _, aux, nis = _per_particle(one, n, st.pose, st.aux, d.prop)
    else:
        pose, aux = _propagate(st.pose, st.aux, d.prop, u, omega_r, P)
        aux, nis = _bias_update(pose, aux, imu, u, K, Sinv, first, P)
    ll = np.zeros(n) if first else -0.5 * (nis + logdet) - 3.0 * LOG2PI
    st = st._replace(pose=pose, aux=aux, log_w=_normalize(st.log_w + ll))
    neff = _ess(st.log_w)
    st = _maybe_resample(st, d.u_imu, P.threshold)
    Hw = H_B[3:6]
    Lg = _chol3(_sym(np.diag(P.imu_var[3:6]) + Hw @ P_post @ Hw.T))
    if loop:
        pose = _per_particle(lambda x, b, e: _regen_rates(x, b, e, imu[3:6], Lg), n,
                             st.pose, st.aux, d.rate)
    else:
        pose = _regen_rates(st.pose, st.aux, d.rate, imu[3:6], Lg)
    st = st._replace(pose=pose, bias_cov=P_post, k=st.k + 1, neff_min=min(st.neff_min, neff))
    return st, _step_out(st, neff)


def lidar_stage(st: State, z, ids, mask, d: Draws, P: Params, loop: bool = False) -> State:
    """One LiDAR frame (landmark EKFs, weights, resampling, position regeneration)."""
    n = st.pose.shape[0]
    z = np.asarray(z, np.float64)
    ids = np.asarray(ids)
    mask = np.asarray(mask, bool)
    R = np.diag(P.lidar_var)
    if loop:
        mean, cov, active, ll = _per_particle(
            lambda x, m, c, a: _lidar_particle(x, m, c, a, z, ids, mask, R), n,
            st.pose, st.lm_mean, st.lm_cov, st.active)
    else:
        mean, cov, active, ll = _lidar_particle(st.pose, st.lm_mean, st.lm_cov, st.active,
                                                z, ids, mask, R)
    st = st._replace(lm_mean=mean, lm_cov=cov, active=active,
                     ids=np.where(active, np.arange(mean.shape[1]), -1).astype(st.ids.dtype),
                     log_w=_normalize(st.log_w + ll))
    neff = _ess(st.log_w)
    st = _maybe_resample(st, d.u_lidar, P.threshold)
    if loop:
        pose = _per_particle(lambda x, m, c, a, e: _regen_position(x, m, c, a, z, ids, mask, R, e),
                             n, st.pose, st.lm_mean, st.lm_cov, st.active, d.pos)
    else:
        pose = _regen_position(st.pose, st.lm_mean, st.lm_cov, st.active, z, ids, mask, R, d.pos)
    return st._replace(pose=pose, neff_min=min(st.neff_min, neff))


def step(st: State, rotor_w, imu, z, ids, mask, d: Draws, P: Params, loop: bool = False):
    """One IMU sample, then the LiDAR frame when ``mask`` has a True entry (as
    ``fastslam_001.step``).  ``loop=True`` runs the per-particle kernels in a Python loop
    over particles (same numbers).  Returns (State, StepOut)."""
    st, out = imu_stage(st, rotor_w, imu, d, P, loop)
    if np.any(mask):
        st = lidar_stage(st, z, ids, mask, d, P, loop)
    return st, out


def step_loop(st: State, rotor_w, imu, z, ids, mask, d: Draws, P: Params):
    """:func:`step` with a Python loop over particles (the benchmark's per-particle baseline)."""
    return step(st, rotor_w, imu, z, ids, mask, d, P, loop=True)
