"""Plain NumPy twin of jaxslam's closed-loop flight (the reference of ``bench_sim``).

It flies exactly what :func:`jaxslam.sim.simulate.simulate` flies with the DF-LQR on the
true state (no estimator, no landmarks): per control step

1. the figure-8 flat output and its derivatives in **closed form** (no autodiff):
   x = c_x + a_x sin ωt, y = c_y + a_y sin 2ωt, z = c_z, ψ = ψ0 + h·atan2(ẏ, ẋ) with the
   k-th derivative of a sin(νt) = a ν^k sin(νt + kπ/2), and ψ̇, ψ̈ from the quotient rule on
   atan2 (they need ẋ … x⃛, ẏ … y⃛);
2. the DF-LQR of paper 000 (eq. 4-5, 7, 12, 14-20; decisions of
   :mod:`jaxslam.control.dflqr` / :mod:`jaxslam.control.flatness`): r = [ρ, C_NB v_B, ψ],
   ũ = −K (r − r_d) with the ψ error wrapped, u = u_d + ũ, the inverse map (atan2 form,
   min_accel blend, r_d of eq. 19 with cos φ_d clipped at 1e-6) and the PD torque of eq. 20;
   K from SciPy's CARE solver (``scipy.linalg.solve_continuous_are``), once per run;
3. with ``feedforward=True`` the flatness feedforward: nominal attitude Λ_d(t) from eq. 16-17
   with ũ = 0, its first and second time derivatives by **second-order Taylor (jet)
   arithmetic** seeded with (ρ̈, ρ⃛, ρ⁗) and (ψ, ψ̇, ψ̈), ω_d = D(Λ_d)⁻¹ Λ̇_d and ω̇_d by the
   product rule written out by hand, τ_ff = J ω̇_d + ω_d × J ω_d, yaw-rate feedback
   ũ_ψ cos θ_d / cos φ_d added to r_d;
4. one classical RK4 step of paper 000 eq. 2 (input held), and the IMU sample of the new
   state: specific force f_B = v̇_B + ω × v_B − g C_NBᵀ n̂3 and gyro ω_B, plus white noise
   σ·n_k with σ = ND·√rate (Table 5) and n_k the caller's standard normals (so both
   implementations can consume the same draws).

It is written the way a careful NumPy programmer would write a per-step simulation: NumPy
arrays for the 12-state, the 3×3 DCM and the LQR product, Python floats and :mod:`math` for
the scalar trigonometry (NumPy's per-call overhead on 0-d values is 10-50× that of
:mod:`math`), explicit 3-vector cross products (``np.cross`` costs ~10 µs per call).

Only the figure-8 (``Figure8``-like container with ``ramp_time = 0``) is supported: it is
the trajectory of the benchmark.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = [
    "Figure8Params",
    "QuadNp",
    "ControllerNp",
    "lqr_gain",
    "flat_derivatives",
    "feedforward",
    "control",
    "f",
    "rk4_step",
    "imu_ideal",
    "simulate",
]

_TWO_PI = 2.0 * math.pi


class Figure8Params:
    """Figure-8 of :class:`jaxslam.control.trajectories.Figure8` (ramp_time must be 0)."""

    def __init__(self, center=(0.0, 0.0, -5.0), a_x=5.0, a_y=2.5, period=25.0, psi0=0.0,
                 heading_along_path=0.0):
        self.center = np.asarray(center, dtype=np.float64).reshape(3)
        self.a_x = float(a_x)
        self.a_y = float(a_y)
        self.period = float(period)
        self.psi0 = float(psi0)
        self.heading = float(heading_along_path)

    @classmethod
    def from_container(cls, traj):
        """From a jaxslam ``Figure8`` (raises ValueError when it has a take-off blend)."""
        if float(traj.ramp_time) > 0.0:
            raise ValueError("traj.ramp_time: the NumPy twin supports only ramp_time = 0")
        return cls(center=traj.center, a_x=traj.a_x, a_y=traj.a_y, period=traj.period,
                   psi0=traj.psi0, heading_along_path=traj.heading_along_path)


class QuadNp:
    """Rigid-body quadcopter of paper 000 eq. 2: mass kg, inertia (3,) kg·m², g m/s²."""

    def __init__(self, mass, inertia, g):
        self.mass = float(mass)
        self.J = np.asarray(inertia, dtype=np.float64).reshape(3)
        self.g = float(g)


class ControllerNp:
    """DF-LQR weights and PD gains (paper 000 Table 2, eq. 20) as float64 arrays."""

    def __init__(self, Q, R, kp, kd, quad: QuadNp, min_accel=1e-3):
        self.Q = np.asarray(Q, dtype=np.float64)
        self.R = np.asarray(R, dtype=np.float64)
        self.kp = np.asarray(kp, dtype=np.float64).reshape(3)
        self.kd = np.asarray(kd, dtype=np.float64).reshape(3)
        self.quad = quad
        self.min_accel = float(min_accel)

    @classmethod
    def from_params(cls, p):
        """From a :class:`jaxslam.control.dflqr.DFLQRParams`."""
        q = p.quad
        return cls(p.Q, p.R, p.pd.kp, p.pd.kd, QuadNp(q.mass, q.inertia, q.g), p.min_accel)


def lqr_gain(Q, R):
    """K = R⁻¹BᵀP of the flat model ṙ = A r + B u (paper 000 eq. 6, 12-13), via SciPy."""
    from scipy.linalg import solve_continuous_are

    A = np.zeros((7, 7))
    A[0:3, 3:6] = np.eye(3)
    B = np.zeros((7, 4))
    B[3:7, :] = np.eye(4)
    P = solve_continuous_are(A, B, Q, R)
    return np.linalg.solve(R, B.T @ P)


def _wrap(a):
    """[−π, π) with the floor-mod convention of ``jaxslam.linalg.wrap_angle``."""
    return (a + math.pi) % _TWO_PI - math.pi


# ---------------------------------------------------------------------------
# Trajectory (closed form)
# ---------------------------------------------------------------------------

def flat_derivatives(traj: Figure8Params, t: float):
    """Position derivatives P (5, 3) (orders 0-4) and yaw (ψ, ψ̇, ψ̈) of the figure-8 at t."""
    w = _TWO_PI / traj.period
    w2 = 2.0 * w
    P = np.zeros((5, 3))
    sx, cx = math.sin(w * t), math.cos(w * t)
    sy, cy = math.sin(w2 * t), math.cos(w2 * t)
    # d^k/dt^k sin(νt) cycles through sin, cos, −sin, −cos (times ν^k).
    cyc_x = (sx, cx, -sx, -cx, sx)
    cyc_y = (sy, cy, -sy, -cy, sy)
    for k in range(5):
        P[k, 0] = traj.a_x * w ** k * cyc_x[k]
        P[k, 1] = traj.a_y * w2 ** k * cyc_y[k]
    P[0] += traj.center
    h = traj.heading
    a0, a1, a2 = P[1, 0], P[2, 0], P[3, 0]  # ẋ, ẍ, x⃛
    b0, b1, b2 = P[1, 1], P[2, 1], P[3, 1]  # ẏ, ÿ, y⃛
    N = a0 * b1 - b0 * a1
    D = a0 * a0 + b0 * b0
    dN = a0 * b2 - b0 * a2
    dD = 2.0 * (a0 * a1 + b0 * b1)
    psi = traj.psi0 + h * math.atan2(b0, a0)
    dpsi = h * N / D
    ddpsi = h * (dN * D - N * dD) / (D * D)
    return P, (psi, dpsi, ddpsi)


# ---------------------------------------------------------------------------
# Second-order jets (value, d/dt, d²/dt²) of scalars
# ---------------------------------------------------------------------------

def _jmul(a, b):
    return (a[0] * b[0], a[1] * b[0] + a[0] * b[1], a[2] * b[0] + 2.0 * a[1] * b[1] + a[0] * b[2])


def _jadd(a, b):
    return (a[0] + b[0], a[1] + b[1], a[2] + b[2])


def _jneg(a):
    return (-a[0], -a[1], -a[2])


def _jsincos(a):
    s, c = math.sin(a[0]), math.cos(a[0])
    d1sq = a[1] * a[1]
    return (s, c * a[1], -s * d1sq + c * a[2]), (c, -s * a[1], -c * d1sq - s * a[2])


def _jsqrt(a):
    r = math.sqrt(a[0])
    return (r, a[1] / (2.0 * r), a[2] / (2.0 * r) - a[1] * a[1] / (4.0 * r * r * r))


def _jatan2(y, x):
    N = x[0] * y[1] - y[0] * x[1]
    D = x[0] * x[0] + y[0] * y[0]
    dN = x[0] * y[2] - y[0] * x[2]
    dD = 2.0 * (x[0] * x[1] + y[0] * y[1])
    return (math.atan2(y[0], x[0]), N / D, (dN * D - N * dD) / (D * D))


def _inverse_map(up, u_psi, psi_d, mass, min_accel):
    """Eq. 15-19 (atan2 form, min_accel blend): f_T, φ_d, θ_d, r_d."""
    acc = math.sqrt(up[0] * up[0] + up[1] * up[1] + up[2] * up[2])
    f_T = mass * acc
    lift = max(min_accel - acc, 0.0)
    c, s = math.cos(psi_d), math.sin(psi_d)
    # z = −C3(ψ_d)ᵀ u_p + lift n̂3
    z0 = -(c * up[0] + s * up[1])
    z1 = -(-s * up[0] + c * up[1])
    z2 = -up[2] + lift
    phi = math.atan2(-z1, math.sqrt(z0 * z0 + z2 * z2))
    theta = math.atan2(z0, z2)
    r_d = u_psi * math.cos(theta) / max(math.cos(phi), 1e-6)
    return f_T, phi, theta, r_d


def feedforward(P, yaw, quad: QuadNp, min_accel=1e-3):
    """Nominal attitude Λ_d, body rates ω_d and torque τ_ff (3,) of the flat output.

    ``P``: (5, 3) position derivatives, ``yaw``: (ψ, ψ̇, ψ̈).  Λ_d from eq. 16-17 on
    u_p = ρ̈ − g n̂3, differentiated twice by jet arithmetic; ω = D(Λ)⁻¹Λ̇ and its derivative
    by the product rule.  Returns (Λ_d (3,), ω_d (3,), τ_ff (3,)).
    """
    g = quad.g
    ax = (P[2, 0], P[3, 0], P[4, 0])
    ay = (P[2, 1], P[3, 1], P[4, 1])
    az = (P[2, 2] - g, P[3, 2], P[4, 2])
    acc = math.sqrt(ax[0] ** 2 + ay[0] ** 2 + az[0] ** 2)
    if acc < min_accel:  # the blend toward level is not differentiated here (never reached)
        raise ValueError("feedforward: commanded thrust acceleration below min_accel")
    spsi, cpsi = _jsincos(yaw)
    z0 = _jneg(_jadd(_jmul(cpsi, ax), _jmul(spsi, ay)))
    z1 = _jadd(_jmul(spsi, ax), _jneg(_jmul(cpsi, ay)))
    z2 = _jneg(az)
    cphi = _jsqrt(_jadd(_jmul(z0, z0), _jmul(z2, z2)))
    phi = _jatan2(_jneg(z1), cphi)
    theta = _jatan2(z0, z2)
    psi = yaw
    sf, cf = math.sin(phi[0]), math.cos(phi[0])
    st, ct = math.sin(theta[0]), math.cos(theta[0])
    dphi, dth, dpsi = phi[1], theta[1], psi[1]
    ddphi, ddth, ddpsi = phi[2], theta[2], psi[2]
    # ω = D⁻¹Λ̇ (inverse of eq. 3) and ω̇ by the product rule.
    p = dphi - dpsi * st
    q = dth * cf + dpsi * ct * sf
    r = -dth * sf + dpsi * ct * cf
    dp = ddphi - ddpsi * st - dpsi * ct * dth
    dq = (ddth * cf - dth * sf * dphi + ddpsi * ct * sf - dpsi * st * dth * sf
          + dpsi * ct * cf * dphi)
    dr = (-ddth * sf - dth * cf * dphi + ddpsi * ct * cf - dpsi * st * dth * cf
          - dpsi * ct * sf * dphi)
    J = quad.J
    Jw0, Jw1, Jw2 = J[0] * p, J[1] * q, J[2] * r
    tau = np.array([J[0] * dp + (q * Jw2 - r * Jw1),
                    J[1] * dq + (r * Jw0 - p * Jw2),
                    J[2] * dr + (p * Jw1 - q * Jw0)])
    return np.array([phi[0], theta[0], psi[0]]), np.array([p, q, r]), tau


# ---------------------------------------------------------------------------
# Model (paper 000 eq. 1-3) and IMU
# ---------------------------------------------------------------------------

def _dcm(phi, theta, psi):
    cf, sf = math.cos(phi), math.sin(phi)
    ct, st = math.cos(theta), math.sin(theta)
    cp, sp = math.cos(psi), math.sin(psi)
    return np.array([[cp * ct, cp * st * sf - sp * cf, cp * st * cf + sp * sf],
                     [sp * ct, sp * st * sf + cp * cf, sp * st * cf - cp * sf],
                     [-st, ct * sf, ct * cf]])


def _cross(a, b):
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2],
                     a[0] * b[1] - a[1] * b[0]])


def f(x, u, quad: QuadNp):
    """ẋ of paper 000 eq. 2 (12,) for x = [ρ, v_B, Λ, ω_B], u = [f_T, τ]."""
    v, w = x[3:6], x[9:12]
    phi, theta = x[6], x[7]
    C = _dcm(phi, theta, x[8])
    J = quad.J
    accel = -_cross(w, v) + quad.g * C[2]
    accel[2] -= u[0] / quad.mass
    cf, sf = math.cos(phi), math.sin(phi)
    ct, tt = math.cos(theta), math.tan(theta)
    p, q, r = w[0], w[1], w[2]
    lam_dot = np.array([p + sf * tt * q + cf * tt * r, cf * q - sf * r, (sf * q + cf * r) / ct])
    w_dot = (u[1:4] - _cross(w, J * w)) / J
    return np.concatenate([C @ v, accel, lam_dot, w_dot])


def rk4_step(x, u, dt, quad: QuadNp):
    """One classical RK4 step with u held over the step."""
    k1 = f(x, u, quad)
    k2 = f(x + 0.5 * dt * k1, u, quad)
    k3 = f(x + 0.5 * dt * k2, u, quad)
    k4 = f(x + dt * k3, u, quad)
    return x + (dt / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


def imu_ideal(x, xdot, g):
    """[specific force f_B (3,), ω_B (3,)] = [v̇ + ω × v − g C_NBᵀ n̂3, ω]."""
    phi, theta = x[6], x[7]
    c3 = np.array([-math.sin(theta), math.cos(theta) * math.sin(phi),
                   math.cos(theta) * math.cos(phi)])
    acc = xdot[3:6] + _cross(x[9:12], x[3:6]) - g * c3
    return np.concatenate([acc, x[9:12]])


def control(x, t, traj: Figure8Params, K, ctrl: ControllerNp, feedforward_on=True):
    """One DF-LQR step (paper 000 Fig. 2) on the state x at time t: returns (u (4,), ref (4,))."""
    quad = ctrl.quad
    g = quad.g
    P, yaw = flat_derivatives(traj, t)
    lam = x[6:9]
    C = _dcm(lam[0], lam[1], lam[2])
    r_err = np.empty(7)
    r_err[0:3] = x[0:3] - P[0]
    r_err[3:6] = C @ x[3:6] - P[1]
    r_err[6] = _wrap(lam[2] - yaw[0])
    u_t = -(K @ r_err)
    up = (P[2, 0] + u_t[0], P[2, 1] + u_t[1], P[2, 2] - g + u_t[2])
    u_psi = yaw[1] + u_t[3]
    psi_d = yaw[0]
    f_T, phi_d, theta_d, rate_d = _inverse_map(up, u_psi, psi_d, quad.mass, ctrl.min_accel)
    if feedforward_on:
        _, omega_d, tau_ff = feedforward(P, yaw, quad, ctrl.min_accel)
        omega_d[2] += u_t[3] * math.cos(theta_d) / max(math.cos(phi_d), 1e-6)
    else:
        omega_d = np.array([0.0, 0.0, rate_d])
        tau_ff = 0.0
    e = np.array([lam[0] - phi_d, lam[1] - theta_d, _wrap(lam[2] - psi_d)])
    tau = -ctrl.kp * e - ctrl.kd * (x[9:12] - omega_d) + tau_ff
    u = np.empty(4)
    u[0] = f_T
    u[1:4] = tau
    ref = np.array([P[0, 0], P[0, 1], P[0, 2], psi_d])
    return u, ref


def simulate(traj: Figure8Params, ctrl: ControllerNp, x0, dt, n_steps, imu_sigma, noise,
             feedforward_on=True, K=None):
    """Closed-loop flight of ``n_steps`` control steps (a Python loop, one RK4 step each).

    ``x0``: (12,) initial state; ``dt``: s; ``imu_sigma``: (6,) discrete IMU σ
    [m/s² ×3, rad/s ×3]; ``noise``: (n_steps, 6) standard normals (sample k's noise is
    ``imu_sigma * noise[k]``); ``K``: (4, 7) LQR gain, computed with SciPy when None
    (as jaxslam computes it inside its call).
    Returns a dict of arrays: ``t`` (T+1,), ``truth`` (T+1, 12), ``ref`` (T+1, 4),
    ``u`` (T, 4), ``imu`` (T, 6) — the fields of :class:`jaxslam.sim.simulate.Flight`.
    """
    if K is None:
        K = lqr_gain(ctrl.Q, ctrl.R)
    quad = ctrl.quad
    g = quad.g
    imu_sigma = np.asarray(imu_sigma, dtype=np.float64)
    noise = np.asarray(noise, dtype=np.float64)
    truth = np.empty((n_steps + 1, 12))
    ref = np.empty((n_steps + 1, 4))
    us = np.empty((n_steps, 4))
    imus = np.empty((n_steps, 6))
    x = np.array(x0, dtype=np.float64)
    truth[0] = x
    for k in range(n_steps):
        t = k * dt
        u, ref[k] = control(x, t, traj, K, ctrl, feedforward_on)
        x = rk4_step(x, u, dt, quad)
        imus[k] = imu_ideal(x, f(x, u, quad), g) + imu_sigma * noise[k]
        us[k] = u
        truth[k + 1] = x
    P, yaw = flat_derivatives(traj, n_steps * dt)
    ref[n_steps] = (P[0, 0], P[0, 1], P[0, 2], yaw[0])
    return {"t": np.arange(n_steps + 1) * dt, "truth": truth, "ref": ref, "u": us, "imu": imus}
