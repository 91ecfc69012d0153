"""NumPy twin of paper 004's line-feature EKF-SLAM (jaxslam.systems.line_slam_004).

An independent implementation of the filter equations with hand-derived
Jacobians and the textbook dense Joseph form, used two ways:

* as a test oracle: :func:`replay` consumes the EKF inputs a jaxslam run
  recorded (``Config(record_inputs=True)``: odometry, matched line
  measurements with their covariances and gate decisions, registered new lines)
  and must reproduce the robot mean/covariance and the map at every step;
* as the NumPy reference for ``jaxslam bench lines``.

The scan processing (RANSAC, matching) is not replayed here: its decisions are
inputs.  Model (thesis eq. 4.10): s = [p_x, p_y, V_x, V_y, ψ, r]; lines [ρ, θ].
"""

from __future__ import annotations

import numpy as np

NR = 6


def wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


def motion(s, dt):
    c, sn = np.cos(s[4]), np.sin(s[4])
    out = s.copy()
    out[0] += (c * s[2] - sn * s[3]) * dt
    out[1] += (sn * s[2] + c * s[3]) * dt
    out[4] += s[5] * dt
    return out


def motion_jac(s, dt):
    """∂f/∂s by hand (thesis eq. 4.11 in real form)."""
    c, sn = np.cos(s[4]), np.sin(s[4])
    F = np.eye(NR)
    F[0, 2], F[0, 3] = c * dt, -sn * dt
    F[1, 2], F[1, 3] = sn * dt, c * dt
    F[0, 4] = (-sn * s[2] - c * s[3]) * dt
    F[1, 4] = (c * s[2] - sn * s[3]) * dt
    F[4, 5] = dt
    return F


def observe(s, l):
    return np.array([l[0] - (s[0] * np.cos(l[1]) + s[1] * np.sin(l[1])), l[1] - s[4]])


def observe_jac(s, l):
    """(H_s (2, 6), H_l (2, 2)) by hand."""
    c, sn = np.cos(l[1]), np.sin(l[1])
    Hs = np.zeros((2, NR))
    Hs[0, 0], Hs[0, 1] = -c, -sn
    Hs[1, 4] = -1.0
    Hl = np.array([[1.0, s[0] * sn - s[1] * c], [0.0, 1.0]])
    return Hs, Hl


def residual(z, zh):
    d1 = np.array([z[0] - zh[0], wrap(z[1] - zh[1])])
    d2 = np.array([-z[0] - zh[0], wrap(z[1] + np.pi - zh[1])])
    return d2 if abs(d2[1]) < abs(d1[1]) else d1


def inverse(s, z):
    """Map line of a sensor line, its Jacobians G_s (2, 6), G_z (2, 2), ρ ≥ 0."""
    th = z[1] + s[4]
    c, sn = np.cos(th), np.sin(th)
    rho = z[0] + s[0] * c + s[1] * sn
    drho_dth = -s[0] * sn + s[1] * c
    Gs = np.zeros((2, NR))
    Gs[0, 0], Gs[0, 1], Gs[0, 4] = c, sn, drho_dth
    Gs[1, 4] = 1.0
    Gz = np.array([[1.0, drho_dth], [0.0, 1.0]])
    if rho < 0:
        rho, th = -rho, th + np.pi
        Gs[0] *= -1
        Gz[0] *= -1
    return np.array([rho, wrap(th)]), Gs, Gz


def joseph(x, P, H, nu, R):
    S = H @ P @ H.T + R
    K = np.linalg.solve(S, H @ P).T
    IKH = np.eye(len(x)) - K @ H
    return x + K @ nu, IKH @ P @ IKH.T + K @ R @ K.T


class Filter:
    """Dense EKF-SLAM state with ``cap`` line slots."""

    def __init__(self, s0, P0, cap):
        n = NR + 2 * cap
        self.x = np.zeros(n)
        self.x[:NR] = s0
        self.P = np.zeros((n, n))
        self.P[:NR, :NR] = P0
        self.active = np.zeros(cap, bool)
        self.cap = cap

    def predict(self, Q, dt):
        s = self.x[:NR]
        F = np.eye(len(self.x))
        F[:NR, :NR] = motion_jac(s, dt)
        self.x[:NR] = motion(s, dt)
        Qf = np.zeros_like(self.P)
        Qf[:NR, :NR] = Q
        self.P = F @ self.P @ F.T + Qf

    def update_odometry(self, flow, gyro, R):
        H = np.zeros((3, len(self.x)))
        H[0, 2] = H[1, 3] = H[2, 5] = 1.0
        z = np.array([flow[0], flow[1], gyro])
        self.x, self.P = joseph(self.x, self.P, H, z - H @ self.x, R)

    def update_lines(self, z, R, used):
        idx = np.flatnonzero(used)
        if idx.size == 0:
            return
        n = len(self.x)
        s = self.x[:NR]
        H = np.zeros((2 * idx.size, n))
        nu = np.zeros(2 * idx.size)
        Rb = np.zeros((2 * idx.size, 2 * idx.size))
        for r, j in enumerate(idx):
            l = self.x[NR + 2 * j: NR + 2 * j + 2]
            Hs, Hl = observe_jac(s, l)
            H[2 * r: 2 * r + 2, :NR] = Hs
            H[2 * r: 2 * r + 2, NR + 2 * j: NR + 2 * j + 2] = Hl
            nu[2 * r: 2 * r + 2] = residual(z[j], observe(s, l))
            Rb[2 * r: 2 * r + 2, 2 * r: 2 * r + 2] = R[j]
        self.x, self.P = joseph(self.x, self.P, H, nu, Rb)

    def register(self, z, R, reg):
        for k in np.flatnonzero(reg):
            free = np.flatnonzero(~self.active)
            if free.size == 0:
                continue
            j = free[0]
            s = self.x[:NR]
            l, Gs, Gz = inverse(s, z[k])
            i0 = NR + 2 * j
            Pll = Gs @ self.P[:NR, :NR] @ Gs.T + Gz @ R[k] @ Gz.T
            Plx = Gs @ self.P[:NR, :]
            self.x[i0:i0 + 2] = l
            self.P[i0:i0 + 2, :] = Plx
            self.P[:, i0:i0 + 2] = Plx.T
            self.P[i0:i0 + 2, i0:i0 + 2] = Pll
            self.active[j] = True


def replay(s0, flow, gyro, inputs, Q, R_odo, P0, dt, cap):
    """Run the twin over T steps with recorded inputs; returns per-step (means (T, 6),
    covs (T, 6, 6), lines (T, cap, 2), active (T, cap)) and the final dense (x, P)."""
    f = Filter(np.asarray(s0, float), np.asarray(P0, float), cap)
    T = len(gyro)
    means, covs, lines, act = [], [], [], []
    for k in range(T):
        f.predict(np.asarray(Q, float), dt)
        f.update_odometry(flow[k], gyro[k], np.asarray(R_odo, float))
        f.update_lines(inputs.z_match[k], inputs.R_match[k], inputs.used[k])
        f.register(inputs.z_new[k], inputs.R_new[k], inputs.reg[k])
        means.append(f.x[:NR].copy())
        covs.append(f.P[:NR, :NR].copy())
        lines.append(f.x[NR:].reshape(cap, 2).copy())
        act.append(f.active.copy())
    return (np.array(means), np.array(covs), np.array(lines), np.array(act)), (f.x, f.P)
