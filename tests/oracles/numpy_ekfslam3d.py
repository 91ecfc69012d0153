"""Vectorised NumPy twin of paper 000's EKF-SLAM (the reference of ``bench_ekfslam``).

It runs exactly the filter of :func:`jaxslam.systems.ekf_slam_3d.run`
(engine :mod:`jaxslam.filters.ekf_slam`; ``joseph`` as ``Config.joseph``), written the way a careful NumPy
programmer would, with **hand-derived Jacobians** (no autodiff anywhere), so
that it is both the timing reference and an independent oracle of the JAX
filter (``tests/benchmarks/test_bench_twin.py`` checks agreement to 1e-8).

Model (paper 000 eq. 1-3, 24-53, errata of docs/papers.md):

* state s = [ρ (3, NED m), v_B (3, m/s), Λ = (φ, θ, ψ) (3, rad)], IMU input
  λ = [f_B (3, m/s²), ω_B (3, rad/s)];
  ṡ = f(s, λ) = [C v,  v × ω + g C₃,:ᵀ + f_B,  D(Λ) ω]  (C = C_NB of eq. 1, D of eq. 3);
* one RK4 step per IMU interval with a first-order hold of the IMU
  (λ(τ) = a + τ (b − a)); φ and ψ wrapped after the step, θ not (as the JAX model);
* F = ∂s⁺/∂s chained through the RK4 stages from the continuous Jacobian
  A(s, λ) = ∂f/∂s:  dk₁ = A₁, dk₂ = A₂ (I + Δt/2 dk₁), dk₃ = A₃ (I + Δt/2 dk₂),
  dk₄ = A₄ (I + Δt dk₃),  F = I + Δt/6 (dk₁ + 2 dk₂ + 2 dk₃ + dk₄)
  (wrapping has derivative 1);
* Q_d = (Q_c + G Q_imu Gᵀ) Δt with G = ∂f/∂λ at the pre-step mean and the MEAN
  of the two IMU samples;
* prediction touches only P_rr and P_rl (P_ll untouched);
* LiDAR y = [α, β, δ] of c = C_NBᵀ (l − ρ) (α = atan2(c₂, c₁),
  β = atan2(c₃, √(c₁² + c₂²)), δ = ‖c‖), residual with α wrapped;
* per LiDAR frame: the first ``max_obs`` visible, usable measurements (in landmark
  order — the stable compaction of the JAX ``correct``), known-id association,
  ONE joint update of the mapped ones from the gathered columns of P with
  paper 000's eq. 43, P − K S Kᵀ = P − (K L)(K L)ᵀ (S = L Lᵀ; the system's default), or with
  ``joseph=True`` the factored Joseph form A − (A Hᵀ) Kᵀ + K R Kᵀ, A = P − K (P Hᵀ)ᵀ, symmetrised,
  then sequential registration (eq. 44-53) of the unmapped ones into the first
  free slot: l = C ϱ(y) + ρ, P_ll = G_s P_ss G_sᵀ + G_y R G_yᵀ, P_lx = G_s P_s,: ;
  measurements outside the Table 4 FOV widened by 5σ (before the compaction)
  are dropped, as the estimator's ``fov_check`` does (``fov=None`` turns it off).

The padded layout is the JAX one (n = 9 + 3·capacity, inactive slots zero), so
costs are comparable; blocks are written in place.  ``active_block=True`` makes
the update work on the leading block that holds every active slot (exact, since
slots fill first-free and inactive ones have zero covariance): the NumPy side of an
active-block engine, for a like-for-like comparison.  NumPy's natural advantage
is kept: it processes only the measurements actually present (no static
padding), and the Joseph form is grouped as A − (A Hᵀ − K R) Kᵀ (one n²·m
product fewer, same algebra).  (``joseph`` defaults to False, the system's default.)  Numerical guards mirror the JAX engine: a
non-finite prediction or update keeps the prior; non-finite measurements are
skipped; a landmark with no free slot is counted in ``overflow``.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.linalg import cho_factor, cho_solve

__all__ = [
    "dcm_and_partials",
    "euler_rate_and_partials",
    "f_cont",
    "jac_state",
    "jac_input",
    "rk4_step",
    "observe",
    "inverse",
    "NumpyEkfSlam3D",
    "run_log",
]

NX = 9
_TWO_PI = 2.0 * math.pi


def _wrap(a):
    """Wrap to [−π, π) with the floor-mod convention of ``jaxslam.linalg.wrap_angle``."""
    return np.mod(a + math.pi, _TWO_PI) - math.pi


def _skew(a):
    return np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])


# ---------------------------------------------------------------------------
# Geometry with hand-derived partials (paper 000 eq. 1, 3)
# ---------------------------------------------------------------------------

def dcm_and_partials(e):
    """C_NB = C3(ψ) C2(θ) C1(φ) and ∂C/∂φ, ∂C/∂θ, ∂C/∂ψ, each (3, 3)."""
    cf, sf = math.cos(e[0]), math.sin(e[0])
    ct, st = math.cos(e[1]), math.sin(e[1])
    cp, sp = math.cos(e[2]), math.sin(e[2])
    C = np.array([
        [cp * ct, cp * st * sf - sp * cf, cp * st * cf + sp * sf],
        [sp * ct, sp * st * sf + cp * cf, sp * st * cf - cp * sf],
        [-st, ct * sf, ct * cf],
    ])
    dphi = np.array([
        [0.0, cp * st * cf + sp * sf, -cp * st * sf + sp * cf],
        [0.0, sp * st * cf - cp * sf, -sp * st * sf - cp * cf],
        [0.0, ct * cf, -ct * sf],
    ])
    dtheta = np.array([
        [-cp * st, cp * ct * sf, cp * ct * cf],
        [-sp * st, sp * ct * sf, sp * ct * cf],
        [-ct, -st * sf, -st * cf],
    ])
    dpsi = np.array([
        [-sp * ct, -sp * st * sf - cp * cf, -sp * st * cf + cp * sf],
        [cp * ct, cp * st * sf - sp * cf, cp * st * cf + sp * sf],
        [0.0, 0.0, 0.0],
    ])
    return C, dphi, dtheta, dpsi


def euler_rate_and_partials(e):
    """D(φ, θ) of eq. 3 (Λ̇ = D ω) and ∂D/∂φ, ∂D/∂θ (D does not depend on ψ)."""
    cf, sf = math.cos(e[0]), math.sin(e[0])
    ct, st = math.cos(e[1]), math.sin(e[1])
    tt = st / ct
    ict = 1.0 / ct
    ict2 = ict * ict
    D = np.array([[1.0, sf * tt, cf * tt], [0.0, cf, -sf], [0.0, sf * ict, cf * ict]])
    dphi = np.array([[0.0, cf * tt, -sf * tt], [0.0, -sf, -cf], [0.0, cf * ict, -sf * ict]])
    dtheta = np.array([[0.0, sf * ict2, cf * ict2], [0.0, 0.0, 0.0],
                       [0.0, sf * st * ict2, cf * st * ict2]])
    return D, dphi, dtheta


# ---------------------------------------------------------------------------
# Continuous model and its Jacobians (paper 000 eq. 24 with the IMU as input)
# ---------------------------------------------------------------------------

def _fb(imu, accel_mode):
    if accel_mode == "az":
        return np.array([0.0, 0.0, imu[2]])
    return imu[0:3]


def f_cont(s, imu, g, accel_mode="3axis"):
    """ṡ (9,) of s (9,), imu (6,)."""
    v, e, w = s[3:6], s[6:9], imu[3:6]
    C, _, _, _ = dcm_and_partials(e)
    D, _, _ = euler_rate_and_partials(e)
    return np.concatenate([C @ v, np.cross(v, w) + g * C[2] + _fb(imu, accel_mode), D @ w])


def _f_and_A(s, imu, g, accel_mode):
    """ṡ and A = ∂f/∂s (9, 9), hand-derived."""
    v, e, w = s[3:6], s[6:9], imu[3:6]
    C, Cf, Ct, Cp = dcm_and_partials(e)
    D, Df, Dt = euler_rate_and_partials(e)
    f = np.concatenate([C @ v, np.cross(v, w) + g * C[2] + _fb(imu, accel_mode), D @ w])
    A = np.zeros((9, 9))
    A[0:3, 3:6] = C
    A[0:3, 6] = Cf @ v
    A[0:3, 7] = Ct @ v
    A[0:3, 8] = Cp @ v
    # ∂(v × ω)/∂v = −[ω×]
    A[3:6, 3:6] = -_skew(w)
    A[3:6, 6] = g * Cf[2]
    A[3:6, 7] = g * Ct[2]
    A[6:9, 6] = Df @ w
    A[6:9, 7] = Dt @ w
    return f, A


def jac_state(s, imu, g, accel_mode="3axis"):
    """A = ∂f/∂s (9, 9) at (s, imu)."""
    return _f_and_A(s, imu, g, accel_mode)[1]


def jac_input(s, imu, accel_mode="3axis"):
    """G = ∂f/∂λ (9, 6): ∂v̇/∂f_B = I (az mode: e₃e₃ᵀ), ∂v̇/∂ω = [v×], ∂Λ̇/∂ω = D."""
    v, e = s[3:6], s[6:9]
    D, _, _ = euler_rate_and_partials(e)
    G = np.zeros((9, 6))
    if accel_mode == "az":
        G[5, 2] = 1.0
    else:
        G[3, 0] = G[4, 1] = G[5, 2] = 1.0
    G[3:6, 3:6] = _skew(v)
    G[6:9, 3:6] = D
    return G


_I9 = np.eye(9)


def rk4_step(s, a, b, dt, g, accel_mode="3axis"):
    """One RK4 step with a first-order hold of the IMU: (s⁺ (9,), F (9, 9))."""
    m = a + (b - a) * 0.5  # λ(τ = 1/2), formed as the JAX model does
    h = 0.5 * dt
    k1, A1 = _f_and_A(s, a, g, accel_mode)
    k2, A2 = _f_and_A(s + h * k1, m, g, accel_mode)
    k3, A3 = _f_and_A(s + h * k2, m, g, accel_mode)
    k4, A4 = _f_and_A(s + dt * k3, b, g, accel_mode)
    d1 = A1
    d2 = A2 @ (_I9 + h * d1)
    d3 = A3 @ (_I9 + h * d2)
    d4 = A4 @ (_I9 + dt * d3)
    s_new = s + dt / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
    s_new[6] = _wrap(s_new[6])
    s_new[8] = _wrap(s_new[8])
    F = _I9 + dt / 6.0 * (d1 + 2.0 * d2 + 2.0 * d3 + d4)
    return s_new, F


# ---------------------------------------------------------------------------
# LiDAR model and inverse (paper 000 eq. 30-31 per errata, 44-49)
# ---------------------------------------------------------------------------

def observe(s, L):
    """ŷ (k, 3), H_s (k, 3, 9), H_l (k, 3, 3) for landmark means L (k, 3)."""
    C, Cf, Ct, Cp = dcm_and_partials(s[6:9])
    d = L - s[0:3]
    c = d @ C  # rows cᵢ = Cᵀ dᵢ
    c1, c2, c3 = c[:, 0], c[:, 1], c[:, 2]
    h2 = c1 * c1 + c2 * c2
    h = np.sqrt(h2)
    r2 = h2 + c3 * c3
    r = np.sqrt(r2)
    k = L.shape[0]
    y = np.stack([np.arctan2(c2, c1), np.arctan2(c3, h), r], axis=1)
    Jc = np.empty((k, 3, 3))  # ∂y/∂c
    Jc[:, 0, 0] = -c2 / h2
    Jc[:, 0, 1] = c1 / h2
    Jc[:, 0, 2] = 0.0
    t = c3 / (h * r2)
    Jc[:, 1, 0] = -c1 * t
    Jc[:, 1, 1] = -c2 * t
    Jc[:, 1, 2] = h / r2
    Jc[:, 2, :] = c / r[:, None]
    Hl = Jc @ C.T  # ∂c/∂l = Cᵀ
    Hs = np.zeros((k, 3, 9))
    Hs[:, :, 0:3] = -Hl  # ∂c/∂ρ = −Cᵀ
    # ∂c/∂φ = (∂C/∂φ)ᵀ d, i.e. rows d @ ∂C/∂φ
    Hs[:, :, 6] = np.einsum("kij,kj->ki", Jc, d @ Cf)
    Hs[:, :, 7] = np.einsum("kij,kj->ki", Jc, d @ Ct)
    Hs[:, :, 8] = np.einsum("kij,kj->ki", Jc, d @ Cp)
    return y, Hs, Hl


def inverse(s, y):
    """l = C ϱ(y) + ρ (3,), G_s = ∂l/∂s (3, 9), G_y = ∂l/∂y (3, 3) for one measurement."""
    C, Cf, Ct, Cp = dcm_and_partials(s[6:9])
    al, be, de = y
    ca, sa = math.cos(al), math.sin(al)
    cb, sb = math.cos(be), math.sin(be)
    u = np.array([cb * ca, cb * sa, sb])
    rho = de * u
    l = C @ rho + s[0:3]
    Gs = np.zeros((3, 9))
    Gs[0, 0] = Gs[1, 1] = Gs[2, 2] = 1.0
    Gs[:, 6] = Cf @ rho
    Gs[:, 7] = Ct @ rho
    Gs[:, 8] = Cp @ rho
    Jr = np.array([[-de * cb * sa, -de * sb * ca, cb * ca],
                   [de * cb * ca, -de * sb * sa, cb * sa],
                   [0.0, de * cb, sb]])
    return l, Gs, C @ Jr


# ---------------------------------------------------------------------------
# Field of view (paper 000 Table 4), widened by 5σ as the JAX estimator's check
# ---------------------------------------------------------------------------

def fov_with_tolerance(az=math.pi / 4, el=math.pi / 6, rng=(0.0, 100.0),
                       sigma=(math.radians(0.33), math.radians(0.3), 0.1), n_sigma=5.0):
    """((α_lo, α_hi), (β_lo, β_hi), (δ_lo, δ_hi)) of a symmetric FOV widened by n_sigma·σ."""
    return ((-az - n_sigma * sigma[0], az + n_sigma * sigma[0]),
            (-el - n_sigma * sigma[1], el + n_sigma * sigma[1]),
            (rng[0] - n_sigma * sigma[2], rng[1] + n_sigma * sigma[2]))


PAPER000_FOV = fov_with_tolerance()


def _within_fov(y, fov):
    ok = np.ones(y.shape[0], bool)
    for j, (lo, hi) in enumerate(fov):
        ok &= (y[:, j] >= lo) & (y[:, j] <= hi)
    return ok


# ---------------------------------------------------------------------------
# The filter
# ---------------------------------------------------------------------------

class NumpyEkfSlam3D:
    """Padded-capacity EKF-SLAM state (x (n,), P (n, n), active, ids) with in-place steps.

    noise: anything with P0 (9, 9), Qc (9, 9), Qimu (6, 6), R (3, 3) (e.g.
    ``jaxslam.systems.ekf_slam_3d.Params``; converted to float64 NumPy).
    """

    def __init__(self, noise, s0, capacity, *, max_obs=16, dt=0.01, g=9.81,
                 accel_mode="3axis", mode="unknown", landmarks_true=None, fov=PAPER000_FOV,
                 active_block=False, joseph=False):
        self.capacity = int(capacity)
        self.joseph = bool(joseph)
        self.fov = fov
        self.active_block = bool(active_block)
        self.max_obs = int(max_obs)
        self.dt = float(dt)
        self.g = float(g)
        self.accel_mode = accel_mode
        self.mode = mode
        self.Qc = np.asarray(noise.Qc, float)
        self.Qimu = np.asarray(noise.Qimu, float)
        self.R = np.asarray(noise.R, float)
        n = NX + 3 * self.capacity
        self.x = np.zeros(n)
        self.x[:NX] = np.asarray(s0, float)
        self.P = np.zeros((n, n))
        self.P[:NX, :NX] = np.asarray(noise.P0, float)
        self.active = np.zeros(self.capacity, bool)
        self.ids = np.full(self.capacity, -1, np.int64)
        self.overflow = 0
        if mode == "known":
            L = np.asarray(landmarks_true, float)
            self.x[NX:NX + L.size] = L.reshape(-1)
            self.active[:L.shape[0]] = True
            self.ids[:L.shape[0]] = np.arange(L.shape[0])
        self._slot_of = {int(i): j for j, i in enumerate(self.ids) if self.active[j]}

    def set_state(self, x, P, active, ids):
        """Overwrite the posterior (copies): x (n,), P (n, n), active (cap,), ids (cap,)."""
        self.x = np.array(x, float)
        self.P = np.array(P, float)
        self.active = np.array(active, bool)
        self.ids = np.array(ids, np.int64)
        self._slot_of = {int(i): j for j, i in enumerate(self.ids) if self.active[j]}
        return self

    def copy(self):
        """An independent copy (arrays copied)."""
        new = object.__new__(NumpyEkfSlam3D)
        new.__dict__.update(self.__dict__)
        new.x, new.P = self.x.copy(), self.P.copy()
        new.active, new.ids = self.active.copy(), self.ids.copy()
        new._slot_of = dict(self._slot_of)
        return new

    # -- prediction --------------------------------------------------------
    def predict(self, imu_prev, imu_now):
        """One IMU step: s ← RK4(s), P_rr ← F P_rr Fᵀ + Q_d, P_rl ← F P_rl."""
        s = self.x[:NX]
        s_new, F = rk4_step(s, imu_prev, imu_now, self.dt, self.g, self.accel_mode)
        G = jac_input(s, 0.5 * (imu_prev + imu_now), self.accel_mode)
        Q = (self.Qc + G @ self.Qimu @ G.T) * self.dt
        P = self.P
        Prr = F @ P[:NX, :NX] @ F.T + Q
        Prr = 0.5 * (Prr + Prr.T)
        Prl = F @ P[:NX, NX:]
        if not (np.all(np.isfinite(s_new)) and np.all(np.isfinite(Prr))):
            return
        P[:NX, :NX] = Prr
        P[:NX, NX:] = Prl
        P[NX:, :NX] = Prl.T
        self.x[:NX] = s_new

    # -- update ------------------------------------------------------------
    def update(self, z, slots):
        """Joint update with measurements z (k, 3) of the mapped slots (k,)."""
        k = len(slots)
        if k == 0:
            return
        m = 3 * k
        x, P = self.x, self.P
        if self.active_block:
            # Slots fill first-free, inactive ones have zero covariance: the update of
            # the leading block holding every active slot is exact (views, in place).
            top = int(np.flatnonzero(self.active)[-1]) + 1
            na = NX + 3 * top
            x, P = x[:na], P[:na, :na]
        idx = (NX + 3 * np.asarray(slots)[:, None] + np.arange(3)).reshape(-1)  # (m,)
        L = x[idx].reshape(k, 3)
        zh, Hs, Hl = observe(x[:NX], L)
        nu = z - zh
        nu[:, 0] = _wrap(nu[:, 0])
        nu = nu.reshape(m)
        Hs2 = Hs.reshape(m, NX)
        HlT = np.ascontiguousarray(Hl.transpose(0, 2, 1))  # (k, 3, 3)

        def gather_ht(M):
            # M Hᵀ from the columns H touches: (n, m)
            out = M[:, :NX] @ Hs2.T
            Ml = M[:, idx].reshape(-1, k, 3).transpose(1, 0, 2)  # (k, n, 3)
            out += (Ml @ HlT).transpose(1, 0, 2).reshape(-1, m)
            return out

        PHt = gather_ht(P)
        rows = PHt[idx].reshape(k, 3, m)
        HPHt = Hs2 @ PHt[:NX] + (Hl @ rows).reshape(m, m)
        S = HPHt
        for j in range(k):
            S[3 * j:3 * j + 3, 3 * j:3 * j + 3] += self.R
        S = 0.5 * (S + S.T)
        try:
            cf = cho_factor(S, lower=True, check_finite=False)
        except np.linalg.LinAlgError:
            return
        Kg = cho_solve(cf, PHt.T, check_finite=False).T  # (n, m) = P Hᵀ S⁻¹
        x_new = x + Kg @ nu
        if self.joseph:
            A = P - Kg @ PHt.T  # (I − K H) P
            AHt = gather_ht(A)  # (I − K H) P Hᵀ
            KR = (Kg.reshape(-1, k, 3) @ self.R).reshape(-1, m)
            A -= (AHt - KR) @ Kg.T  # A − (A Hᵀ) Kᵀ + K R Kᵀ
        else:
            U = Kg @ np.tril(cf[0])  # K L, S = L Lᵀ
            A = P - U @ U.T  # eq. 43: P − K S Kᵀ (one n²·m product)
        if not (np.all(np.isfinite(x_new)) and np.all(np.isfinite(A))):
            return
        np.add(A, A.T, out=P)  # P may be a view of the leading block: written in place
        P *= 0.5
        x[:] = x_new

    # -- registration --------------------------------------------------------
    def register(self, z, lm_ids):
        """Sequential registration (eq. 44-53) of unmapped measurements z (k, 3)."""
        x, P = self.x, self.P
        for zk, idk in zip(z, lm_ids):
            if not np.all(np.isfinite(zk)):
                continue
            free = np.flatnonzero(~self.active)
            if free.size == 0:
                self.overflow += 1
                continue
            slot = int(free[0])
            s = x[:NX]
            l, Gs, Gy = inverse(s, zk)
            Pll = Gs @ P[:NX, :NX] @ Gs.T + Gy @ self.R @ Gy.T
            Pll = 0.5 * (Pll + Pll.T)
            if not (np.all(np.isfinite(l)) and np.all(np.isfinite(Pll))):
                continue
            row = Gs @ P[:NX, :]  # P_lx (3, n)
            a = NX + 3 * slot
            row[:, a:a + 3] = Pll
            P[a:a + 3, :] = row
            P[:, a:a + 3] = row.T
            x[a:a + 3] = l
            self.active[slot] = True
            self.ids[slot] = int(idk)
            self._slot_of[int(idk)] = slot

    # -- one LiDAR frame -----------------------------------------------------
    def correct(self, y, ids, visible):
        """Mask non-finite/out-of-FOV rows, compact the visible rest to max_obs, associate by id,
        update mapped, register new."""
        usable = np.all(np.isfinite(y), axis=1)
        if self.fov is not None:
            # before the compaction, as the JAX correct(): a measurement beyond the FOV
            # (widened by 5σ) is impossible and is neither used nor registered, nor takes a slot
            usable &= _within_fov(np.where(np.isfinite(y), y, 0.0), self.fov)
        sel = np.flatnonzero(np.asarray(visible, bool) & usable)[: self.max_obs]
        ys, idsel = y[sel], ids[sel]
        slots = np.array([self._slot_of.get(int(i), -1) for i in idsel], dtype=np.int64)
        mapped = slots >= 0
        self.update(ys[mapped], slots[mapped])
        if self.mode == "unknown":
            self.register(ys[~mapped], idsel[~mapped])

def run_log(noise, s0, imu, y, ids, visible, lidar_every, *, capacity, max_obs=16, dt=0.01,
            g=9.81, accel_mode="3axis", mode="unknown", landmarks_true=None, fov=PAPER000_FOV,
            active_block=False, joseph=False):
    """Run the twin over a log with the layout of :class:`jaxslam.systems.ekf_slam_3d.Log`.

    imu: (T + 1, 6); y: (F, L, 3); ids: (L,) or (F, L); visible: (F, L); T = F·lidar_every.
    Returns (filter, means (T, 9)).
    """
    imu = np.asarray(imu, float)
    y = np.asarray(y, float)
    visible = np.asarray(visible, bool)
    F, L = visible.shape
    ids = np.broadcast_to(np.asarray(ids), (F, L))
    flt = NumpyEkfSlam3D(noise, s0, capacity, max_obs=max_obs, dt=dt, g=g, accel_mode=accel_mode,
                         mode=mode, landmarks_true=landmarks_true, fov=fov, active_block=active_block,
                         joseph=joseph)
    means = np.empty((F * lidar_every, NX))
    t = 0
    for f in range(F):
        for _ in range(lidar_every):
            flt.predict(imu[t], imu[t + 1])
            means[t] = flt.x[:NX]
            t += 1
        flt.correct(y[f], ids[f], visible[f])
    return flt, means
