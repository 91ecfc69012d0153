"""Study (issue 20): batch / smoothed estimation on jaxslam's own CMU Plaza range-only model.

Usage: .venv/bin/python scripts/study_plaza_smoothing.py [--data DIR] [--robot 1 2]
       [--all | --configs NAME ...] [--cv] [--em] [--json FILE]

Smoothing on jaxslam's own CMU Plaza model, run as a batch over the whole log: Levenberg–Marquardt
on an iterated EKS, with IRLS robust kernels. Results are scored by the CLI's SE(2) ATE.

Default run: the six configurations in ``QUICK`` (about 3.5 min on 2 CPU cores).
``--all`` runs every configuration in ``CONFIGS`` (about 8 min). ``--cv`` adds the
blocked cross-validation over the σ_d scale (about 10 min per log) and ``--em`` the EM
noise fit.

Method
------
* **State.** There is one state per event of ``pr.plaza_events``: Plaza 1 has 13 183
  events (3529 of them ranges) and Plaza 2 has 5906 (1816 ranges). Each state is
  z = [x, y, θ, b, s_d, s_θ, l_1 … l_4] (14). The four beacons are static states from
  t = 0, so every range is used, including the 232/230 that reach the EKF before it has
  mapped their beacon. s_d and s_θ are odometry scales, fixed at 1 unless ``calib`` is set.
* **Models.** The motion model is jaxslam's (ODO), but θ is *unwrapped*; see ``f_aug``.
  Q_k is ``odo_process_noise`` (rank 2 in the pose: no sideways slip) plus q_b Δt. The
  GTSAM-style alternative is R(θ) diag(σ_f², σ_l²) R(θ)ᵀ ⊕ σ_h² on DR rows only. The
  range model is (R1), z = ‖p − l‖ + b, with R = σ_r²/w (w the IRLS weight).
* **One iteration** is one damped IEKS pass. The filter is linearised about the nominal
  path (Joseph form; K ≤ 2 scalar updates per event); then the RTS pass runs. The step
  is then retracted onto the dynamics: the positions are rebuilt from each step's forward
  part, because the covariance-form pass satisfies the no-slip constraint only to first
  order. The step is accepted if the full robust negative log posterior decreases.
  Damping is a pseudo-measurement of [x, y, θ, b] at every step and of the whole state
  at the prior, with variance 1/λ; λ is divided by 10 after an accepted step and
  multiplied by 10 after a rejected one.
* **Checks.** An undamped pass equals one dense Gauss–Newton step: they agree to 2e-9 on
  the first 300 events of Plaza 2, with a regularised Q. ``gn_step`` is the step an
  undamped pass would still take at the solution. Where it is 1e-2 to 1e-1, the
  remaining motion is along a nearly flat direction that LM cannot use: the full step
  raises the cost quadratically. ATE does not move at the mm level.

Constants and where each comes from (ground truth is used only to score the finished
estimates)
-----------------------------------------------------------------------------------------
* **Odometry noise.** ``plaza_range.PARAMS``: α_d 0.05, σ_d0 0.01 m/√s, α_θ 0.05, β_θ 0.002
  rad/m, σ_θ0 0.003 rad/√s.
* **Range noise and bias.** σ_r = 1.2 m; bias prior 0 ± 5 m; q_b = 1e-4 m²/s. All from
  ``plaza_range.PARAMS``. The start pose is GT₀ ± (0.1 m, 0.02 rad) (``p0_pos``, ``p0_th``);
  for Plaza 2 the heading gets + π (``start_pose``).
* **Beacon prior.** Mean = the jaxslam EKF SLAM run's final beacons, σ = 1000 m per axis.
  The 1000 m is GTSAM's ``looseNoise``. With so wide a prior the mean only picks the
  basin. TL (the surveyed positions) is never used.
* **Robust kernels.** Huber k = 1.345 and Tukey c = 4.685, in units of σ (the textbook
  95 %-efficiency constants). The hard gate is 2.576σ, the EKF's χ²(1) gate of 6.63.
* **GTSAM model.** From RangeISAMExample_plaza2.cpp: odometry (0.05, 0.01, 0.1) per DR
  row, σ_r = 100, Tukey 15, start prior (1, 1, π), no bias.
  RangeISAMExample_plaza.m (Plaza 1 branch) uses σ_θ = 0.2 instead.
  ``gtsam-huber+bias`` keeps GTSAM's odometry-to-range ratios at σ_r = 1.2, i.e. its
  odometry σ's × 1.2/100.
* **huber-mad.** σ_r = 1.4826·MAD of the *other* log's ``huber`` residuals: 0.729 m
  (Plaza 1) applied to Plaza 2, 1.032 m (Plaza 2) applied to Plaza 1.
* **huber-kd0.01.** σ_d × 0.01 is the value that blocked cross-validation picks on
  Plaza 2 (the smallest CV MAE on the grid). The CV uses 30 s time blocks dealt round-robin into 5 folds and scores the
  mean absolute error of the held-out ranges; no ground truth. The σ_d grid was
  1, 0.3, 0.1, 0.03, 0.01:
  * Plaza 2 CV MAE [m]: 1.5613 1.5246 1.5206 1.5201 1.5200. It is flat below 0.1, and
    the minimum is at 0.01.
  * Plaza 1 CV MAE [m]: 0.733 0.760 0.768 0.770 0.770, so Plaza 1's own CV picks × 1.
  So the cross-log rule ("fit on one log, apply to the other") gives × 1 on Plaza 2
  (0.793) and × 0.01 on Plaza 1 (1.148). With σ_θ scaled as well (σ_d, σ_θ × κ):
  * Plaza 2, κ = 1, 0.3, 0.1, 0.03, 0.01: CV MAE 1.561 1.545 3.07 6.78 7.25; ATE 0.79
    0.55 4.6 14.6 15.8.
  * Plaza 1: CV MAE 0.733 0.752 0.859 0.982 1.086.
  In that sweep CV and ATE agree on both logs.
* **EM (``--em``).** A Laplace E-step at the MAP fits κ_d, κ_θ, q_b and σ_r. On Plaza 2
  it drifts without converging: after 25 steps κ_d ≈ 3.5 and still rising, σ_r → 0.57.
  The ATE gets worse (1.92). The range errors are time-correlated (lag-one
  autocorrelation per beacon 0.4–0.75 on Plaza 2 and 0.26–0.57 on Plaza 1), so a white
  noise likelihood explains them with trajectory wiggles. Not used.

Results (this script, float64, 2 CPU cores; ATE = the CLI's SE(2)-aligned ATE; beacon
errors in m: "beac" in the ATE frame, "beacS" by their own rigid fit; s = wall time of
the solve, including the first-call compile; it = accepted LM steps, pas = IEKS passes)
----------------------------------------------------------------------------------------
========================  ===============================  ===============================
config                    Plaza 1 ATE / beac / b / it / s  Plaza 2 ATE / beac / b / it / s
========================  ===============================  ===============================
EKF (CLI, baseline)       0.876 / 3.36 / −0.54 / – / 2.6    1.875 / 3.24 / +0.89 / – / 0.4
gn-plain (undamped IEKS)  1.135 / 3.69 / −0.87 / 40 (F)     8.06 (oscillates, 20–40 m steps)
lm-gauss (from EKF)       1.135 / 3.69 / −0.87 / 23 / 18    0.830 / 1.93 / +1.00 / 10 / 3.3
lm-gauss-eks              1.135 (same optimum) / 118 / 88   0.830 (same) / 54 / 15
huber 1.345σ              1.134 / 3.68 / −0.86 / 9 / 5.6    0.793 / 1.95 / +1.03 / 17 / 4.7
tukey 4.685σ              1.129 / 3.69 / −0.87 / 9 / 5.7    0.766 / 1.93 / +1.06 / 17 / 4.4
gate 2.57σ                1.135 / 3.69 / −0.87 / 8 / 5.8    0.821 / 1.94 / +1.01 / 9 / 3.2
huber, bias constant      1.130 / 3.57 / −0.74              0.793 / 1.94 / +1.14
huber, no bias            1.116 / 2.78 / 0                  0.997 / 2.92 / 0
huber, σ_r = other MAD    1.146 (σ_r 1.032)                 1.094 (σ_r 0.729)
huber + s_d, s_θ states   1.471 (s_d 1.064)                 2.132 (s_d 1.064, s_θ 0.964)
huber, σ_d × 0.01         1.148 / 3.78 / −0.99              0.451 / 1.76 / +1.41
gtsam-model               1.346 / 2.90 / 0 / 190 / 59       0.398 / 3.11 / 0 / 231 / 46
gtsam-matlab (σ_θ 0.2)    1.201 / 2.85 / 0                  0.534 / 3.08 / 0
gtsam+bias                1.347 / 2.92 / −0.03              0.331 / 2.32 / +0.86
gtsam-huber+bias          1.370 / 3.05 / −0.47 / 12 / 4.0   0.310 / 1.69 / +1.55 / 19 / 3.4
========================  ===============================  ===============================

Findings
--------
* **Plain Gauss–Newton needs care.**
  * Wrapping θ inside the motion model breaks the batch solve; keep it unwrapped.
  * Undamped, the IEKS converges linearly on Plaza 1 (about 0.69 per iteration; 40 its
    reach 3e-6) but oscillates forever on Plaza 2.
  * LM damping with cost-checked acceptance and a retraction converges on both logs.
* **With the filter's own noise, smoothing does not help Plaza 1.** The EKF gives 0.876;
  every smoother gives 1.12–1.15. On Plaza 2 smoothing takes 1.875 to 0.77–0.83, and the
  robust kernels change little: Tukey −0.06 m, Huber −0.04 m.
* **The odometry-to-range weighting matters most.** GTSAM's weights trust the distance
  odometry about 35× more relative to the ranges, with about the same heading noise, a
  small sideways slip and noise per DR row. They give Plaza 2 0.33–0.40 and 0.31 with
  the bias state and Huber, but Plaza 1 only 1.20–1.37. GTSAM's own iSAM2 reports
  0.397 / 1.13–1.35.
* **The ranges do not select that weighting.**
  * White-noise EM pushes the other way; blocked CV agrees with it only on Plaza 2.
  * Tighter σ_r from MAD hurts both logs.
  * An odometry scale state fits the ranges much better (residual MAD 0.73 → 0.54 and
    1.03 → 0.58) but makes ATE much worse. s_d = 1.064 on both logs trades off against
    the range bias (b → 0; the README's +2.8 m is about 6 % of the 40–50 m ranges). The
    data fix only the ratio of range scale to odometry scale.
* **Targets.** Plaza 2 ≤ 0.40 is reached only with the GTSAM example's constants
  (0.398 as is, 0.31–0.33 with jaxslam's bias). Plaza 1 ≤ 0.80 is reached by no batch
  MAP tried here; the best is 1.116 (Huber, no bias).
"""

from __future__ import annotations

import json
import sys
import time
from typing import NamedTuple

from jaxslam import runtime

runtime.configure_process()
from jaxslam.cli.common import ScriptParser, path_arg  # noqa: E402
import numpy as np  # noqa: E402

from jaxslam.data.plaza import load_plaza  # noqa: E402
from jaxslam.errors import InputError  # noqa: E402

NB = 4  # beacons
IB, ISD, IST, IL = 3, 4, 5, 6  # bias, distance scale, heading scale, first beacon
NX = IL + 2 * NB  # [x, y, θ, b, s_d, s_θ, l_1 (2), ..., l_4 (2)] = 14
GATE_K = float(np.sqrt(6.63))  # the EKF's χ²(1) 99 % gate (plaza_range.Params default), in σ
HUBER_K = 1.345  # Huber's 95 %-efficiency constant (σ units)
TUKEY_C = 4.685  # Tukey's 95 %-efficiency constant (σ units)


# ---------------------------------------------------------------------------
# Model: jaxslam's Plaza model (``systems.plaza_range``), beacons in the state from t = 0
# ---------------------------------------------------------------------------

class Noise(NamedTuple):
    """Noise of one configuration (a pytree of floats).

    alpha_d … sigma_th0, q_bias: as ``plaza_range.Params`` (input noise σ_d = α_d|d| + σ_d0√Δt,
    σ_θ = α_θ|dθ| + β_θ|d| + σ_θ0√Δt; bias walk q_b [m²/s]).  gsig: GTSAM-style Between
    sigmas (forward, lateral, heading) per DR row, used when qkind == "gtsam"."""

    alpha_d: float
    sigma_d0: float
    alpha_th: float
    beta_th: float
    sigma_th0: float
    q_bias: float
    gsig: tuple


def noise_from(p: pr.Params, kd=1.0, kt=1.0, q_bias=None, gsig=(1.0, 1.0, 1.0)) -> Noise:
    """``plaza_range.Params`` odometry noise, σ_d scaled by kd and σ_θ by kt."""
    return Noise(p.alpha_d * kd, p.sigma_d0 * kd, p.alpha_th * kt, p.beta_th * kt,
                 p.sigma_th0 * kt, p.q_bias if q_bias is None else q_bias, tuple(gsig))


def f_aug(z, u):
    """(ODO) pose ∘ Pose2(s_d d, 0, s_θ dθ); bias, scales, beacons unchanged.

    With s_d = s_θ = 1 this is ``pr.odo_motion`` except that the heading is **not wrapped**
    (``planar.compose`` wraps θ to (−π, π]; a smoother that forms x_k − f(x_{k−1}) or
    linearises f(x̄) + F(x − x̄) across a wrap sees 2π jumps — that alone made the first
    Gauss–Newton runs blow up).  The state carries an unwrapped θ."""
    x, y, th, sd, st = z[0], z[1], z[2], z[ISD], z[IST]
    d, dth = u[0], u[1]
    rob = jnp.stack([x + sd * d * jnp.cos(th), y + sd * d * jnp.sin(th), th + st * dth])
    return jnp.concatenate([rob, z[3:]])


def h_range(z, j):
    """(R1) z = ‖p − l_j‖ + b for beacon slot j (traced int); ``pr.range_observe``."""
    l = jax.lax.dynamic_slice(z, (IL + 2 * j,), (2,))
    return pr.range_observe(jnp.stack([z[0], z[1], z[2], z[IB]]), l)[0]


def input_sigmas(u, dt, nz: Noise):
    """σ_d, σ_θ of the EKF's input noise (``odo_process_noise``), per step (vectorised)."""
    uu = jnp.abs(u)
    sq = jnp.sqrt(jnp.maximum(dt, 0.0))
    sd = nz.alpha_d * uu[..., 0] + nz.sigma_d0 * sq
    sth = nz.alpha_th * uu[..., 1] + nz.beta_th * uu[..., 0] + nz.sigma_th0 * sq
    return sd, sth


def q_step(z, u, dt, nz: Noise, qkind):
    """Per-step process covariance Q_k (NX, NX) at the linearisation point z.

    "jaxslam": G_u diag(σ_d², σ_θ²) G_uᵀ ⊕ q_b Δt (``pr.odo_process_noise``; rank 2 in the
    pose: no sideways slip).  "gtsam": R(θ) diag(σ_f², σ_l²) R(θ)ᵀ ⊕ σ_h² on DR rows (u ≠ 0),
    zero pose noise on range-only events; bias walk as above.  Static states: zero."""
    if qkind == "gtsam":
        th = z[2]
        c, s = jnp.cos(th), jnp.sin(th)
        Rm = jnp.array([[c, -s], [s, c]])
        g = jnp.asarray(nz.gsig, z.dtype)
        on = jnp.any(u != 0.0).astype(z.dtype)
        Q = jnp.zeros((NX, NX), z.dtype)
        Q = Q.at[:2, :2].set(on * Rm @ jnp.diag(g[:2] ** 2) @ Rm.T).at[2, 2].set(on * g[2] ** 2)
    else:
        sd, sth = input_sigmas(u, dt, nz)
        G = jax.jacfwd(f_aug, argnums=1)(z, u)
        Q = G @ jnp.diag(jnp.stack([sd * sd, sth * sth])) @ G.T
    return Q.at[IB, IB].add(nz.q_bias * dt)


# ---------------------------------------------------------------------------
# Iterated extended Kalman smoother = Gauss–Newton over the whole trajectory
# ---------------------------------------------------------------------------

def _damp(m, P, target, lam, idx):
    """Levenberg–Marquardt pseudo-measurement  x[idx] = target[idx] + N(0, I/λ)  (λ = 0: none)."""
    n = len(idx)
    idx = jnp.asarray(idx)
    on = lam > 0
    lam_e = jnp.where(on, lam, 1.0)
    S = P[jnp.ix_(idx, idx)] + jnp.eye(n, dtype=P.dtype) / lam_e
    Kg = jnp.linalg.solve(S, P[idx, :]).T
    mn = m + Kg @ (target[idx] - m[idx])
    Pn = P - Kg @ P[idx, :]
    return jnp.where(on, mn, m), jnp.where(on, 0.5 * (Pn + Pn.T), P)


def _ieks_pass(zbar, m0, P0, frozen, dt, u, zr, slot, use, rvar, nz, lam, qkind, ekf_lin=False):
    """One (damped) Gauss–Newton step: a Kalman filter linearised about the nominal ``zbar``
    (T+1, NX), then an RTS pass — equal to one dense Gauss–Newton step of the batch problem
    (checked against a dense normal-equation solve on the first 300 events of Plaza 2 with a
    regularised Q: 2e-9 agreement).

    zr, slot, use, rvar: (T, K) ranges, beacon slots, use mask, per-range variance σ²/w
    (IRLS weight w).  frozen: (NX,) states with zero prior variance and no process noise
    (their rows of P stay exactly 0; the RTS solve adds 1 on their diagonal so that the
    singular P_{k+1|k} is inverted on the other states only).  lam: LM damping (pseudo-measurement of [x, y, θ, b] at every step and
    of the whole state at the prior, variance 1/λ; 0 = pure GN).  ekf_lin: linearise about
    the running filter estimate instead (plain EKF + RTS, i.e. the EKS; first pass only).
    Returns smoothed means (T+1, NX) and (covariances (T+1, NX, NX), lag-one
    cross-covariances Cov(x_k, x_{k+1}) (T, NX, NX)).
    """
    I = jnp.eye(NX, dtype=zbar.dtype)
    K = zr.shape[1]
    if not ekf_lin:
        m0, P0 = _damp(m0, P0, zbar[0], lam, list(range(NX)))

    def fwd(carry, inp):
        m, P = carry
        zb_prev, zb, uk, dtk, zk, sk, vk, rk = inp
        if ekf_lin:
            zb_prev = m
        F = jax.jacfwd(f_aug)(zb_prev, uk)
        mp = f_aug(zb_prev, uk) + F @ (m - zb_prev)
        Pp = F @ P @ F.T + q_step(zb_prev, uk, dtk, nz, qkind)
        Pp = 0.5 * (Pp + Pp.T)
        m, P = mp, Pp
        for k in range(K):  # static, K ≤ 2 (Plaza 1 has pairs of ranges at one time)
            if ekf_lin:
                zb = m
            H = jax.grad(h_range)(zb, sk[k])
            nu = zk[k] - h_range(zb, sk[k]) - H @ (m - zb)
            S = H @ P @ H + rk[k]
            Kg = P @ H / S
            A = I - jnp.outer(Kg, H)
            Pn = A @ P @ A.T + rk[k] * jnp.outer(Kg, Kg)  # Joseph form
            m = jnp.where(vk[k], m + Kg * nu, m)
            P = jnp.where(vk[k], 0.5 * (Pn + Pn.T), P)
        if not ekf_lin:
            m, P = _damp(m, P, zb, lam, [0, 1, 2, 3])
        return (m, P), (mp, Pp, m, P, F)

    xs = (zbar[:-1], zbar[1:], u, dt, zr, slot, use, rvar)
    _, (mps, Pps, mfs, Pfs, Fs) = jax.lax.scan(fwd, (m0, P0), xs)
    mfs = jnp.concatenate([m0[None], mfs])
    Pfs = jnp.concatenate([P0[None], Pfs])

    def bwd(carry, inp):
        ms, Ps = carry
        mf, Pf, mp, Pp, F = inp
        Pr = Pp + jnp.diag(frozen.astype(Pp.dtype))
        C = jnp.linalg.solve(Pr, F @ Pf).T  # Pf Fᵀ Pp⁻¹ (Pp symmetric, PD off the frozen)
        ms_k = mf + C @ (ms - mp)
        Ps_k = Pf + C @ (Ps - Pp) @ C.T
        return (ms_k, 0.5 * (Ps_k + Ps_k.T)), (ms_k, Ps_k, C @ Ps)

    _, (mss, Pss, Pcr) = jax.lax.scan(bwd, (mfs[-1], Pfs[-1]),
                                      (mfs[:-1], Pfs[:-1], mps, Pps, Fs), reverse=True)
    mss = jnp.concatenate([mss, mfs[-1][None]])
    Pss = jnp.concatenate([Pss, Pfs[-1][None]])
    return mss, (Pss, Pcr)


# _ieks_pass_jit: jitted by _import_jax


def _project(z, m0, frozen, static, u, dt, nz, qkind):
    """Retraction onto the dynamics' feasible set after a linearised step.

    "jaxslam" Q has no sideways slip: keep θ_k, rebuild p_k = p_{k−1} + fwd_k (cos θ_{k−1},
    sin θ_{k−1}) from the step's forward component (the sideways part a linearised step
    leaves is second order); where σ_d = 0 (σ_θ = 0) the step is the odometry's.  "gtsam":
    the pose is frozen on range-only events only.  Static states (Q = 0: scales, beacons,
    a constant bias) take row 0's value; frozen ones (prior variance 0) the prior mean."""
    sd, sth = input_sigmas(u, dt, nz)
    on = jnp.any(u != 0.0, axis=1)
    row0 = jnp.where(frozen, m0, z[0])
    z = jnp.where(static[None, :], row0[None, :], z)

    def step(prev, inp):
        zk, zraw_prev, uk, sdk, sthk, onk = inp
        th = prev[2]
        c, s = jnp.cos(th), jnp.sin(th)
        e = zk[:2] - zraw_prev[:2]
        if qkind == "gtsam":
            pos = jnp.where(onk, prev[:2] + e, prev[:2])
            thk = jnp.where(onk, zk[2], prev[2])
        else:
            fwd = jnp.where(sdk > 0, c * e[0] + s * e[1], prev[ISD] * uk[0])
            pos = prev[:2] + fwd * jnp.stack([c, s])
            thk = jnp.where(sthk > 0, zk[2], prev[2] + prev[IST] * uk[1])
        new = jnp.concatenate([pos, thk[None], zk[3:]])
        return new, new

    _, rest = jax.lax.scan(step, z[0], (z[1:], z[:-1], u, sd, sth, on))
    return jnp.concatenate([z[:1], rest])


# _project_jit: jitted by _import_jax


def _residuals(zs, zr, slot):
    """(T, K) range residuals z − h(z_k) at the states z_1..z_T."""
    hv = jax.vmap(jax.vmap(h_range, in_axes=(None, 0)), in_axes=(0, 0))
    return zr - hv(zs[1:], slot)


# _residuals_jit: jitted by _import_jax


def weights(a, kernel, c):
    """IRLS weight ψ(a)/a of the standardised residual a = r/σ."""
    a = np.abs(a)
    if kernel == "gauss":
        return np.ones_like(a)
    if kernel == "huber":
        return np.where(a <= c, 1.0, c / np.maximum(a, 1e-300))
    if kernel == "tukey":
        return np.where(a < c, (1.0 - np.minimum(a / c, 1.0) ** 2) ** 2, 0.0)
    if kernel == "gate":  # hard 0/1: the EKF's χ² gate applied to the smoother's residuals
        return (a <= c).astype(float)
    raise ValueError(kernel)


def rho(a, kernel, c):
    """Robust cost ρ(a) of a = r/σ (½ a² for the Gaussian)."""
    a = np.abs(a)
    if kernel == "gauss":
        return 0.5 * a * a
    if kernel == "huber":
        return np.where(a <= c, 0.5 * a * a, c * a - 0.5 * c * c)
    if kernel == "tukey":
        return np.where(a < c, c * c / 6 * (1 - (1 - np.minimum(a / c, 1.0) ** 2) ** 3), c * c / 6)
    if kernel == "gate":
        return np.where(a <= c, 0.5 * a * a, 0.5 * c * c)
    raise ValueError(kernel)


def _process_cost_impl(zs, m0, P0i, dt, u, nz, qkind):
    """½ (prior + process) Mahalanobis terms of a feasible trajectory, and the largest
    violation of the exact constraints (sideways slip / frozen pose / constant bias)."""
    e = zs[1:] - jax.vmap(f_aug)(zs[:-1], u)
    d0 = zs[0] - m0
    c_prior = 0.5 * d0 @ P0i @ d0
    th = zs[:-1, 2]
    c, s = jnp.cos(th), jnp.sin(th)
    fwd = c * e[:, 0] + s * e[:, 1]
    lat = -s * e[:, 0] + c * e[:, 1]
    if qkind == "gtsam":
        on = jnp.any(u != 0, axis=1)
        sf, sl, sh = nz.gsig
        cp = jnp.where(on, (fwd / sf) ** 2 + (lat / sl) ** 2 + (e[:, 2] / sh) ** 2, 0.0)
        viol = jnp.max(jnp.where(on, 0.0, jnp.abs(e[:, 0]) + jnp.abs(e[:, 1]) + jnp.abs(e[:, 2])))
    else:
        sd, sth = input_sigmas(u, dt, nz)
        wd = fwd / zs[:-1, ISD]
        wt = e[:, 2] / zs[:-1, IST]
        cp = jnp.where(sd > 0, (wd / jnp.where(sd > 0, sd, 1)) ** 2, 0.0) + \
            jnp.where(sth > 0, (wt / jnp.where(sth > 0, sth, 1)) ** 2, 0.0)
        viol = jnp.max(jnp.abs(lat))
    qb = nz.q_bias * dt
    cb = jnp.where(qb > 0, e[:, IB] ** 2 / jnp.where(qb > 0, qb, 1), 0.0)
    viol = jnp.maximum(viol, jnp.max(jnp.where(qb > 0, 0.0, jnp.abs(e[:, IB]))))
    return c_prior + 0.5 * jnp.sum(cp) + 0.5 * jnp.sum(cb), viol


# _process_cost: jitted by _import_jax


class Problem(NamedTuple):
    """One log's smoothing problem (arrays) and its prior."""

    dt: jax.Array
    u: jax.Array
    zr: jax.Array
    slot: jax.Array
    valid: np.ndarray
    m0: jax.Array
    P0: jax.Array
    P0i: jax.Array  # pseudo-inverse over the non-frozen states
    frozen: jax.Array  # (NX,) bool: prior variance 0
    static: jax.Array  # (NX,) bool: Q = 0 (scales, beacons, bias if q_b = 0)


def objective(z, pb: Problem, nz, sig, kernel, c, qkind):
    """Full robust negative log posterior (up to constants) of a feasible trajectory."""
    pc, viol = _process_cost(z, pb.m0, pb.P0i, pb.dt, pb.u, nz, qkind)
    r = np.asarray(_residuals_jit(z, pb.zr, pb.slot))
    mc = float(np.sum(np.where(pb.valid, rho(r / sig, kernel, c), 0.0)))
    return float(pc) + mc, float(viol), r


def solve(pb: Problem, z_init, nz: Noise, sig, kernel="gauss", c=None, qkind="jaxslam",
          damped=True, max_iter=300, tol=1e-10, lam0=1.0, verbose=False):
    """Levenberg–Marquardt IEKS with IRLS weights, to convergence (``damped=False``: the
    textbook undamped IEKS / Gauss–Newton, every step taken, no retraction).

    Iteration: weights w = ψ(r/σ)/(r/σ) at the nominal; one damped IEKS pass; retraction
    (:func:`_project`); accepted if the full robust objective does not increase (λ ← λ/10,
    floor 1e-7), else λ ← 10λ and retry.  Stops when an accepted step changes the objective
    by < ``tol`` (relative) and the states by < 1e-4 (m, rad), or when no step with
    λ ≤ 1e12 decreases it.  Reports the step an undamped pass would still take (gn_step).
    """
    sig = float(sig)
    z = jnp.asarray(z_init)
    if damped:
        z = _project_jit(z, pb.m0, pb.frozen, pb.static, pb.u, pb.dt, nz, qkind)
    J, viol, r = objective(z, pb, nz, sig, kernel, c, qkind)
    lam = lam0 if damped else 0.0
    hist = [J]
    conv, n_pass, it = False, 0, 0
    t0 = time.perf_counter()
    for it in range(1, max_iter + 1):
        w = np.where(pb.valid, weights(r / sig, kernel, c), 0.0)
        use = pb.valid & (w > 0)
        rvar = jnp.asarray(np.where(use, sig * sig / np.where(w > 0, w, 1.0), 1.0))
        use = jnp.asarray(use)
        while True:
            zs, _ = _ieks_pass_jit(z, pb.m0, pb.P0, pb.frozen, pb.dt, pb.u, pb.zr, pb.slot, use, rvar, nz,
                                   lam, qkind)
            n_pass += 1
            if damped:
                zs = _project_jit(zs, pb.m0, pb.frozen, pb.static, pb.u, pb.dt, nz, qkind)
            Jn, viol_n, rn = objective(zs, pb, nz, sig, kernel, c, qkind)
            step = float(jnp.max(jnp.abs(zs - z)))
            if not damped or (np.isfinite(Jn) and Jn <= J) or lam > 1e12:
                break
            lam *= 10.0
        if damped and not Jn <= J:
            conv = True  # no decrease even with heavy damping: a minimum to round-off
            break
        dec = (J - Jn) / max(abs(J), 1e-300)
        z, J, r, viol = zs, Jn, rn, viol_n
        hist.append(J)
        if verbose:
            print(f"    it {it:3d} cost {J:.6f} step {step:.2e} lam {lam:.0e} viol {viol:.1e}")
        if damped:
            lam = max(lam / 10.0, 1e-7)
        if not np.isfinite(J) or step > 1e6:
            break
        if abs(dec) < tol and step < 1e-4:
            conv = True
            break
    w = np.where(pb.valid, weights(r / sig, kernel, c), 0.0)
    use = pb.valid & (w > 0)
    rvar = np.where(use, sig * sig / np.where(w > 0, w, 1.0), 1.0)
    zc, (Ps, Pcr) = _ieks_pass_jit(z, pb.m0, pb.P0, pb.frozen, pb.dt, pb.u, pb.zr, pb.slot,
                                   jnp.asarray(use), jnp.asarray(rvar), nz, 0.0, qkind)
    run_s = time.perf_counter() - t0
    return {"zs": np.asarray(z), "Ps": np.asarray(Ps), "Pcross": np.asarray(Pcr), "iters": it,
            "passes": n_pass, "converged": conv, "cost_hist": hist, "w": w, "sigma": sig,
            "run_s": run_s, "cost": J, "viol": viol, "resid": r,
            "gn_step": float(jnp.max(jnp.abs(zc - z)))}


# ---------------------------------------------------------------------------
# EM of the noise scales (a likelihood criterion; no ground truth)
# ---------------------------------------------------------------------------

def _em_stats_impl(zs, Ps, Pcr, dt, u, zr, slot, valid, w, nz):
    """E-step (Laplace, linearised at the MAP): mean E[w_d²]/σ_d², mean E[w_θ²]/σ_θ²,
    mean E[Δb²]/Δt, and Σ w E[r²] / Σ w (E[r²] = r̂² + H P Hᵀ)."""
    F = jax.vmap(jax.jacfwd(f_aug))(zs[:-1], u)
    e = zs[1:] - jax.vmap(f_aug)(zs[:-1], u)
    FP = jnp.einsum("kij,kjl->kil", F, Pcr)
    Ce = Ps[1:] - FP - jnp.swapaxes(FP, 1, 2) + jnp.einsum("kij,kjl,kml->kim", F, Ps[:-1], F)
    th = zs[:-1, 2]
    a = jnp.zeros_like(e).at[:, 0].set(jnp.cos(th)).at[:, 1].set(jnp.sin(th))
    Ewd = (jnp.sum(a * e, 1) ** 2 + jnp.einsum("ki,kij,kj->k", a, Ce, a)) / zs[:-1, ISD] ** 2
    Ewt = (e[:, 2] ** 2 + Ce[:, 2, 2]) / zs[:-1, IST] ** 2
    Ewb = e[:, IB] ** 2 + Ce[:, IB, IB]
    sd, sth = input_sigmas(u, dt, nz)
    kd = jnp.sum(jnp.where(sd > 0, Ewd / jnp.where(sd > 0, sd, 1) ** 2, 0)) / jnp.sum(sd > 0)
    kt = jnp.sum(jnp.where(sth > 0, Ewt / jnp.where(sth > 0, sth, 1) ** 2, 0)) / jnp.sum(sth > 0)
    qb = jnp.sum(jnp.where(dt > 0, Ewb / jnp.where(dt > 0, dt, 1), 0)) / jnp.sum(dt > 0)
    hv = jax.vmap(jax.vmap(h_range, in_axes=(None, 0)), in_axes=(0, 0))
    Hs = jax.vmap(jax.vmap(jax.grad(h_range), in_axes=(None, 0)), in_axes=(0, 0))(zs[1:], slot)
    Er2 = (zr - hv(zs[1:], slot)) ** 2 + jnp.einsum("tki,tij,tkj->tk", Hs, Ps[1:], Hs)
    ww = jnp.where(valid, w, 0.0)
    return kd, kt, qb, jnp.sum(ww * Er2) / jnp.sum(ww)


# _em_stats: jitted by _import_jax


def em_fit(pb, z_start, nz0: Noise, sig0, n_em=12, verbose=False):
    """EM of κ_d, κ_θ (scales of the odometry σ's), q_b and σ_r on one log, Gaussian ranges.

    MAP solve with the current noise (warm start) → E-step → M-step, ``n_em`` times.
    Returns (noise, σ_r, last solve, history)."""
    kd = kt = 1.0
    qb, sig = nz0.q_bias, float(sig0)
    z, hist, out = z_start, [], None
    for i in range(n_em):
        nz = nz0._replace(alpha_d=nz0.alpha_d * kd, sigma_d0=nz0.sigma_d0 * kd,
                          alpha_th=nz0.alpha_th * kt, beta_th=nz0.beta_th * kt,
                          sigma_th0=nz0.sigma_th0 * kt, q_bias=qb)
        out = solve(pb, z, nz, sig, "gauss", max_iter=100)
        z = out["zs"]
        md, mt, qn, s2 = [float(v) for v in _em_stats(
            jnp.asarray(z), jnp.asarray(out["Ps"]), jnp.asarray(out["Pcross"]), pb.dt, pb.u,
            pb.zr, pb.slot, jnp.asarray(pb.valid), jnp.asarray(out["w"]), nz)]
        kd, kt = kd * np.sqrt(md), kt * np.sqrt(mt)
        qb = qn if qb > 0 else 0.0
        sig = float(np.sqrt(s2))
        hist.append({"kd": kd, "kt": kt, "q_bias": qb, "sigma_r": sig})
        if verbose:
            print(f"    EM {i:2d}: κ_d {kd:.3f} κ_θ {kt:.3f} q_b {qb:.2e} σ_r {sig:.3f} "
                  f"(MAP {out['iters']} it)")
    return nz, sig, out, hist


# ---------------------------------------------------------------------------
# Data, EKF start, evaluation
# ---------------------------------------------------------------------------

def prepare(data_dir, which):
    """Load one log, run jaxslam's EKF SLAM (the CLI's run), build the smoother's arrays and
    the first nominal trajectory (the EKF's per-event estimate, its final beacons)."""
    _import_jax()
    d = load_plaza(data_dir, which)
    log = pr.plaza_events(d.dr_t, d.dr, d.td_t, d.td_node, d.td_range)
    pose0 = np.asarray(d.start_pose(), np.float64)
    bid = np.asarray(d.node_id)
    t0 = time.perf_counter()
    res = pr.run(pr.log_from_events(log, pose0, bid, dtype=jnp.float64))
    jax.block_until_ready(res.pos)
    ekf_s = time.perf_counter() - t0
    ids = np.asarray(log.ids)
    eq = ids[..., None] == bid[None, None, :]
    valid = np.asarray(log.mask) & np.isfinite(np.asarray(log.z)[..., 0]) & eq.any(-1)
    slot = np.argmax(eq, -1).astype(np.int32)
    zr = np.where(valid, np.asarray(log.z)[..., 0], 0.0)
    lid, act = np.asarray(res.landmark_ids), np.asarray(res.active)
    L = np.asarray(res.landmarks, np.float64)
    missing = [int(b) for b in bid if not np.any((lid == b) & act)]
    if missing:  # the smoother starts from the EKF's final beacons: there is none (an IndexError before)
        raise InputError(f"Plaza {which}: the EKF never initialised beacon(s) {', '.join(map(str, missing))} "
                         "(too few ranges in this log): the smoother has no starting beacons")
    beac = np.stack([L[np.nonzero((lid == b) & act)[0][0]] for b in bid])
    rob = np.concatenate([np.asarray(res.pos), np.asarray(res.heading)[:, None],
                          np.asarray(res.bias)[:, None]], 1)
    rob = np.concatenate([np.concatenate([pose0, [pr.PARAMS.bias0]])[None], rob])
    rob[:, 2] = np.unwrap(rob[:, 2])
    T1 = rob.shape[0]
    z_init = np.concatenate([rob, np.ones((T1, 2)), np.tile(beac.reshape(-1), (T1, 1))], 1)
    return {"d": d, "log": log, "pose0": pose0, "bid": bid, "ekf": res, "ekf_s": ekf_s,
            "dt": jnp.asarray(log.dt, jnp.float64), "u": jnp.asarray(log.u, jnp.float64),
            "zr": jnp.asarray(zr), "slot": jnp.asarray(slot), "valid": valid,
            "z_init": z_init, "ekf_beacons": beac}


def problem(prep, nz: Noise, start_sig=None, bias="rw", sigma_bias0=None, calib=0.0, sigma_l=1000.0):
    """Prior and bookkeeping.  Start pose GT₀ (Plaza 2 heading + π) ± start_sig; bias 0 ±
    sigma_bias0 ("rw": random walk q_b, "const": q_b = 0, "none": b ≡ 0); scales 1 ± calib
    (0: fixed at 1); beacons: mean = the EKF's final beacons, σ = sigma_l per axis (diffuse:
    the mean only picks the basin).  start_sig, sigma_bias0: default ``pr.PARAMS``' (p0_pos,
    p0_th) and sigma_bias0."""
    sp, sth = (pr.PARAMS.p0_pos, pr.PARAMS.p0_th) if start_sig is None else start_sig
    sigma_bias0 = pr.PARAMS.sigma_bias0 if sigma_bias0 is None else sigma_bias0
    var_b = 0.0 if bias == "none" else sigma_bias0 ** 2
    m0 = np.concatenate([prep["pose0"], [0.0, 1.0, 1.0], prep["ekf_beacons"].reshape(-1)])
    pv = np.concatenate([[sp ** 2, sp ** 2, sth ** 2, var_b, calib ** 2, calib ** 2],
                         np.full(2 * NB, sigma_l ** 2)])
    frozen = pv == 0
    P0i = np.diag(np.where(frozen, 0.0, 1.0 / np.where(frozen, 1.0, pv)))
    static = np.zeros(NX, bool)
    static[ISD:] = True
    if bias != "rw" or nz.q_bias == 0:
        static[IB] = True
    return Problem(prep["dt"], prep["u"], prep["zr"], prep["slot"], prep["valid"],
                   jnp.asarray(m0), jnp.asarray(np.diag(pv)), jnp.asarray(P0i),
                   jnp.asarray(frozen), jnp.asarray(static))


def nz_for(nz, bias):
    return nz._replace(q_bias=0.0) if bias != "rw" else nz


def eks_start(prep, pb, nz, sig, qkind="jaxslam"):
    """EKF with all beacons in the state from t = 0 (prior mean = jaxslam EKF's final
    beacons), linearised about its own running estimate, + RTS: the first smoothed path."""
    rvar = jnp.full(pb.valid.shape, sig ** 2)
    z0 = jnp.asarray(prep["z_init"]).at[:, IB].set(0.0) if bool(pb.frozen[IB]) else \
        jnp.asarray(prep["z_init"])
    zs, _ = _ieks_pass_jit(z0, pb.m0, pb.P0, pb.frozen, pb.dt, pb.u, pb.zr, pb.slot,
                           jnp.asarray(pb.valid), rvar, nz, 0.0, qkind, ekf_lin=True)
    return np.asarray(zs)


def evaluate(prep, zs, Ps=None):
    """The CLI's evaluation (``evaluate_planar``: SE(2) ATE at the event times, beacons in
    the trajectory's ATE frame) plus beacons by their own rigid fit; GT used only here."""
    d = prep["d"]
    gt = np.asarray(d.gt, np.float64).copy()
    gt[:, 2] = gt[:, 2] + d.heading_offset
    beac = zs[-1, IL:].reshape(NB, 2)
    m, _ = evaluate_planar(prep["log"].t, zs[1:, :3], d.gt_t, gt, lm=beac, lm_ids=prep["bid"],
                           lm_true=d.node_xy, lm_true_ids=prep["bid"])
    me = metrics.map_error(beac, prep["bid"], d.node_xy, prep["bid"])
    out = {"ate": m["ate_m"], "beacon_err": m["map_err_m"], "beacon_err_self": me.rmse,
           "bias_end": float(zs[-1, IB]), "bias_start": float(zs[0, IB]),
           "s_d": float(zs[0, ISD]), "s_th": float(zs[0, IST])}
    if Ps is not None:
        out["bias_sigma"] = float(np.sqrt(max(Ps[-1, IB, IB], 0.0)))
    return out


# ---------------------------------------------------------------------------
# Configurations
# ---------------------------------------------------------------------------

GTSAM_GSIG = (0.05, 0.01, 0.1)  # RangeISAMExample_plaza2.cpp odoSigmas (x, y, θ) per DR row
GTSAM_SIGMA_R = 100.0  # its sigmaR
GTSAM_TUKEY = 15.0  # its Tukey::Create(15) (in σ units: a cut at 1500 m, i.e. Gaussian here)
# the names of CONFIGS (built by _import_jax from plaza_range.PARAMS), for the parser: --help
# and an unknown --configs answer before JAX loads
CONFIG_NAMES = ("gn-plain", "lm-gauss", "lm-gauss-eks", "huber", "tukey", "gate", "huber-bconst", "huber-nobias",
                "huber-mad", "huber-calib", "huber-kd0.01", "gtsam-model", "gtsam-matlab", "gtsam+bias",
                "gtsam-huber+bias")
QUICK = ["lm-gauss", "huber", "tukey", "gtsam-model", "gtsam+bias", "gtsam-huber+bias"]


def _import_jax():
    """JAX, the modules that load it, the jitted passes and the configuration table (``P``,
    ``NZ``, ``Cfg``, ``GSIG_SCALED``, ``GTSAM``, ``CONFIGS``, ``CFG``: they are built from
    ``plaza_range.PARAMS``), set as module globals.  Called by main once the arguments are read
    (--help and a usage error exit before JAX loads) and by prepare; once is enough."""
    global jax, jnp, metrics, evaluate_planar, pr
    global _ieks_pass_jit, _project_jit, _residuals_jit, _process_cost, _em_stats
    global P, NZ, Cfg, GSIG_SCALED, GTSAM, CONFIGS, CFG
    if "CFG" in globals():
        return
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    from jaxslam import metrics
    from jaxslam.data.runners import evaluate_planar
    from jaxslam.systems import plaza_range as pr

    _ieks_pass_jit = jax.jit(_ieks_pass, static_argnames=("qkind", "ekf_lin"))
    _project_jit = jax.jit(_project, static_argnames=("qkind",))
    _residuals_jit = jax.jit(_residuals)
    _process_cost = jax.jit(_process_cost_impl, static_argnames=("qkind",))
    _em_stats = jax.jit(_em_stats_impl)

    P = pr.PARAMS
    NZ = noise_from(P)

    class Cfg(NamedTuple):
        name: str
        what: str
        kernel: str = "gauss"
        c: float | None = None
        sigma_r: object = P.sigma_r  # float, or "mad-other": 1.4826·MAD of the other log's residuals
        qkind: str = "jaxslam"
        nz: Noise = NZ
        bias: str = "rw"
        calib: float = 0.0
        start: str = "eks"  # "eks", "ekf" (projected EKF estimate), or a config name (warm start)
        start_sig: tuple = (P.p0_pos, P.p0_th)
        damped: bool = True
        max_iter: int = 300

    GSIG_SCALED = tuple(float(g) * P.sigma_r / GTSAM_SIGMA_R for g in GTSAM_GSIG)  # same ratios at σ_r 1.2
    GTSAM = dict(qkind="gtsam", nz=noise_from(P, gsig=GTSAM_GSIG), sigma_r=GTSAM_SIGMA_R,
                 kernel="tukey", c=GTSAM_TUKEY, bias="none", start_sig=(1.0, np.pi))

    CONFIGS = [
        Cfg("gn-plain", "undamped IEKS (textbook GN) from the EKF estimate, Gaussian", start="ekf",
            damped=False, max_iter=40),
        Cfg("lm-gauss", "LM-IEKS from the (projected) EKF estimate, Gaussian σ_r 1.2, plaza_range.PARAMS, "
            "bias random walk", start="ekf"),
        Cfg("lm-gauss-eks", "as lm-gauss, started from the EKS pass instead"),
        Cfg("huber", "Huber k 1.345σ (IRLS)", "huber", HUBER_K, start="lm-gauss"),
        Cfg("tukey", "Tukey c 4.685σ (IRLS), warm start from huber", "tukey", TUKEY_C, start="huber"),
        Cfg("gate", "hard 0/1 gate at the EKF's χ²(1) 6.63 (2.57σ)", "gate", GATE_K, start="huber"),
        Cfg("huber-bconst", "Huber, bias constant (q_b = 0)", "huber", HUBER_K, bias="const",
            start="huber"),
        Cfg("huber-nobias", "Huber, no bias state (b ≡ 0, as GTSAM)", "huber", HUBER_K, bias="none",
            start="huber"),
        Cfg("huber-mad", "Huber, σ_r = 1.4826·MAD of the other log's huber residuals", "huber",
            HUBER_K, sigma_r="mad-other", start="huber"),
        Cfg("huber-calib", "Huber + odometry scale states s_d, s_θ (prior 1 ± 0.1)", "huber",
            HUBER_K, calib=0.1, start="huber"),
        Cfg("huber-kd0.01", "Huber, odometry σ_d × 0.01 (blocked-CV choice on Plaza 2; CV on "
            "Plaza 1 picks × 1)", "huber", HUBER_K, nz=noise_from(P, kd=0.01), start="huber"),
        Cfg("gtsam-model", "GTSAM example's model: Between σ (0.05, 0.01, 0.1)/DR row, σ_r 100, "
            "Tukey 15, no bias, start prior (1, 1, π)", **GTSAM),
        Cfg("gtsam-matlab", "as gtsam-model with the MATLAB example's σ_θ 0.2", **{
            **GTSAM, "nz": noise_from(P, gsig=(0.05, 0.01, 0.2)), "start": "gtsam-model"}),
        Cfg("gtsam+bias", "gtsam-model + jaxslam's bias random walk (0 ± 5 m, q_b 1e-4)",
            **{**GTSAM, "bias": "rw", "start": "gtsam-model"}),
        Cfg("gtsam-huber+bias", "GTSAM odometry σ × 1.2/100 (its ratios at σ_r 1.2), Huber 1.345σ, "
            "bias random walk, jaxslam start prior", "huber", HUBER_K, qkind="gtsam",
            nz=noise_from(P, gsig=GSIG_SCALED), start="gtsam+bias"),
    ]
    CFG = {c.name: c for c in CONFIGS}
    assert tuple(CFG) == CONFIG_NAMES, "CONFIG_NAMES must list CONFIGS' names, in order"


def run_config(prep, cfg: Cfg, done: dict, mad_other=None):
    """Run one configuration on one log; ``done``: results of earlier configs (warm starts)."""
    nz = nz_for(cfg.nz, cfg.bias)
    pb = problem(prep, nz, start_sig=cfg.start_sig, bias=cfg.bias, calib=cfg.calib)
    sig = mad_other if cfg.sigma_r == "mad-other" else float(cfg.sigma_r)
    t0 = time.perf_counter()
    if cfg.start == "eks":
        z0 = eks_start(prep, pb, nz, sig, cfg.qkind)
    elif cfg.start == "ekf":
        z0 = prep["z_init"]
    else:
        z0 = done[cfg.start]["zs"]
    z0 = np.asarray(z0).copy()
    if cfg.bias == "none":
        z0[:, IB] = 0.0
    if cfg.calib == 0.0:
        z0[:, ISD:IL] = 1.0
    start_s = time.perf_counter() - t0
    out = solve(pb, z0, nz, sig, cfg.kernel, cfg.c, cfg.qkind, damped=cfg.damped,
                max_iter=cfg.max_iter)
    zs = out["zs"]
    ok = bool(np.all(np.isfinite(zs)) and np.max(np.abs(zs)) < 1e5)
    ev = evaluate(prep, zs, out["Ps"]) if ok else {"ate": float("nan")}
    n_valid = int(pb.valid.sum())
    w = out["w"]
    ev.update({"iters": out["iters"], "passes": out["passes"], "converged": out["converged"],
               "run_s": out["run_s"] + start_s, "cost": out["cost"], "viol": out["viol"],
               "gn_step": out["gn_step"], "sigma_r": sig, "n_ranges": n_valid,
               "n_zero_w": int(np.sum(pb.valid & (w == 0))),
               "n_downweighted": int(np.sum(pb.valid & (w < 1))),
               "resid_mad": float(1.4826 * np.median(np.abs(out["resid"][pb.valid] - np.median(
                   out["resid"][pb.valid])))), "zs": zs})
    return ev


CV_KD = (1.0, 0.3, 0.1, 0.03, 0.01)  # σ_d scales tried by the blocked CV (half-decades)


def cv_folds(prep, block_s=30.0, n_folds=5):
    """(T, K) fold index of every range: contiguous time blocks of ``block_s`` seconds dealt
    round-robin to ``n_folds`` folds (blocked, because the range errors are correlated in
    time: lag-one autocorrelation 0.3–0.75 per beacon)."""
    t = np.asarray(prep["log"].t)
    blk = np.floor((t - t[0]) / block_s).astype(int)
    return np.broadcast_to((blk % n_folds)[:, None], prep["valid"].shape)


def cv_score(prep, cfg: Cfg, z_full, folds, verbose=False):
    """Blocked cross-validation of one configuration (no ground truth): for every fold,
    solve without its ranges (warm start ``z_full``) and predict them; returns the mean and
    median absolute prediction error [m] of the held-out ranges and the per-fold solves' time."""
    nz = nz_for(cfg.nz, cfg.bias)
    pb = problem(prep, nz, start_sig=cfg.start_sig, bias=cfg.bias, calib=cfg.calib)
    sig = float(cfg.sigma_r)
    errs, t0 = [], time.perf_counter()
    for f in range(int(folds.max()) + 1):
        held = pb.valid & (folds == f)
        pf = pb._replace(valid=pb.valid & ~held)
        out = solve(pf, z_full, nz, sig, cfg.kernel, cfg.c, cfg.qkind, max_iter=cfg.max_iter)
        r = out["resid"][held]
        errs.append(r)
        if verbose:
            print(f"      fold {f}: {held.sum()} held out, MAE {np.mean(np.abs(r)):.3f} "
                  f"({out['iters']} it)")
    e = np.concatenate(errs)
    return {"cv_mae": float(np.mean(np.abs(e))), "cv_medae": float(np.median(np.abs(e))),
            "cv_rmse": float(np.sqrt(np.mean(e ** 2))), "cv_s": time.perf_counter() - t0}


def fmt_row(which, name, r):
    if not np.isfinite(r.get("ate", np.nan)):
        return (f"P{which} {name:16s} {'diverged':>7s}  {'':29s} it {r['iters']:3d}  "
                f"{r['run_s']:5.1f}s")
    bs = r.get("bias_sigma", np.nan)
    return (f"P{which} {name:16s} {r['ate']:7.3f} {r['beacon_err']:6.2f} {r['beacon_err_self']:6.2f}"
            f" {r['bias_end']:+6.2f}±{bs:4.2f} {r['s_d']:6.4f} {r['s_th']:6.4f}"
            f" {r['iters']:4d} {r['passes']:4d} {str(r['converged'])[0]:>2s} {r['gn_step']:8.1e}"
            f" {r['n_zero_w']:4d}/{r['n_downweighted']:4d} {r['sigma_r']:6.3f} {r['resid_mad']:5.3f}"
            f" {r['run_s']:6.1f}")


HEADER = ("log name                ATE  beac  beacS  bias(end)±σ   s_d    s_θ    it  pas cv  gn_step"
          "  w0/w<1   σ_r   rMAD    s\n" + "-" * 122)


def main(argv=None):
    ap = ScriptParser(prog="study_plaza_smoothing.py", description=__doc__.split("\n")[0])
    ap.add_argument("--data", default=__import__("os").environ.get("JAXSLAM_DATA_DIR"), type=path_arg,
                    help="folder holding gtsam/ (default: $JAXSLAM_DATA_DIR)")
    ap.add_argument("--robot", type=int, nargs="*", default=[1, 2], help="1 and/or 2 (Plaza 1, Plaza 2)")
    ap.add_argument("--configs", nargs="*", default=None, help=f"subset of {list(CONFIG_NAMES)}")
    ap.add_argument("--all", action="store_true", help="every configuration (default: QUICK)")
    ap.add_argument("--em", action="store_true", help="also run the EM noise fit (slow)")
    ap.add_argument("--cv", action="store_true",
                    help="also run the blocked cross-validation over the σ_d scale (slow)")
    ap.add_argument("--json", default=None, type=path_arg)
    a = ap.parse_args(argv)
    if not a.robot or set(a.robot) - {1, 2} or len(set(a.robot)) < len(a.robot):
        ap.error(f"--robot: expected 1 and/or 2 (Plaza 1, Plaza 2), each once, got {' '.join(map(str, a.robot))}")
    unknown = [n for n in a.configs or () if n not in CONFIG_NAMES]
    if unknown:  # (a KeyError traceback after the EKF runs)
        ap.error(f"--configs: unknown configuration(s) {', '.join(unknown)}; choose from {', '.join(CONFIG_NAMES)}")
    if a.json:
        ap.output_file("--json", a.json)  # an unusable path (a folder, under a file) before the smoothers
    _import_jax()  # (CFG: the warm starts below; still before any compute)
    names = a.configs or (list(CFG) if a.all else QUICK)
    # warm starts need their source configs
    need = []
    for n in names:
        chain = [n]
        while CFG[chain[-1]].start not in ("eks", "ekf"):
            chain.append(CFG[chain[-1]].start)
        for m in reversed(chain):
            if m not in need:
                need.append(m)
    if "huber-mad" in need and len(a.robot) < 2:
        ap.error("--configs: huber-mad needs both logs (--robot 1 2)")
    preps = {}
    for w in a.robot:
        try:
            preps[w] = prepare(a.data, w)
        except InputError as e:  # (a beacon the EKF never initialised: one line, exit 1, nothing written)
            print(f"study_plaza_smoothing.py: error: --robot {w}: {e}", file=sys.stderr)
            return 1
    results = {w: {} for w in a.robot}
    print(HEADER)
    for w in a.robot:
        prep = preps[w]
        ekf = prep["ekf"]
        ev = evaluate(prep, prep["z_init"])
        results[w]["ekf"] = {"ate": ev["ate"], "beacon_err": ev["beacon_err"],
                             "beacon_err_self": ev["beacon_err_self"],
                             "bias_end": float(ekf.bias_final), "bias_sigma": float(ekf.bias_sigma),
                             "run_s": prep["ekf_s"]}
        print(f"P{w} {'ekf (CLI)':16s} {ev['ate']:7.3f} {ev['beacon_err']:6.2f} "
              f"{ev['beacon_err_self']:6.2f} {float(ekf.bias_final):+6.2f}±{float(ekf.bias_sigma):4.2f}")
    deferred = [n for n in need if n == "huber-mad"]
    for n in [n for n in need if n not in deferred] + deferred:
        for w in a.robot:
            mad = None
            if n == "huber-mad":
                other = 3 - w
                mad = results[other]["huber"]["resid_mad"]
            r = run_config(preps[w], CFG[n], results[w], mad)
            results[w][n] = r
            print(fmt_row(w, n, r), flush=True)
    if a.em:
        for w in a.robot:
            prep = preps[w]
            pb = problem(prep, NZ)
            _, sig, out, hist = em_fit(pb, results[w]["lm-gauss"]["zs"], NZ, P.sigma_r,
                                        verbose=True)
            ev = evaluate(prep, out["zs"], out["Ps"])
            ev.update({"iters": out["iters"], "passes": out["passes"], "converged": out["converged"],
                       "run_s": out["run_s"], "cost": out["cost"], "gn_step": out["gn_step"],
                       "sigma_r": sig, "n_zero_w": 0, "n_downweighted": 0,
                       "resid_mad": float(np.nan), "em": hist[-1], "zs": out["zs"]})
            results[w]["em-gauss"] = ev
            print(fmt_row(w, "em-gauss", ev) + f"  κ_d {hist[-1]['kd']:.2f} κ_θ {hist[-1]['kt']:.2f}")
    if a.cv:
        for w in a.robot:
            prep = preps[w]
            folds = cv_folds(prep)
            prev = results[w].get("huber", {}).get("zs")
            for kd in CV_KD:
                cfg = Cfg(f"cv-kd{kd}", "", "huber", HUBER_K, nz=noise_from(P, kd=kd),
                          start="_prev")
                r = run_config(prep, cfg, {"_prev": {"zs": prev if prev is not None else
                                                     prep["z_init"]}})
                prev = r["zs"]
                r.update(cv_score(prep, cfg, r["zs"], folds))
                results[w][cfg.name] = r
                print(fmt_row(w, cfg.name, r) + f"  CV MAE {r['cv_mae']:.4f} "
                      f"MedAE {r['cv_medae']:.4f}", flush=True)
    if a.json:
        clean = {str(w): {n: {k: v for k, v in r.items() if k != "zs"} for n, r in rs.items()}
                 for w, rs in results.items()}
        with open(a.json, "w") as f:
            json.dump(clean, f, indent=1, default=float)
        print(f"wrote {a.json}")
    return results


if __name__ == "__main__":
    raise SystemExit(main())
