"""Independent NumPy (float64) oracles for the dynamics tests.

Everything here is written from the papers' printed equations, component by
component, without importing jaxslam: elementary DCMs of paper 000 eq. 1 and
their derivatives, D of eq. 3 and its partials, the right-hand sides of
paper 000 eq. 2 and paper 001 eq. 1-3 with the plus-layout mixer, and their
hand-derived Jacobians.
"""

import numpy as np

E3 = np.array([0.0, 0.0, 1.0])


def skew(a):
    return np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])


def c1(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]], dtype=float)


def c2(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]], dtype=float)


def c3(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]], dtype=float)


def dc1(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[0, 0, 0], [0, -s, -c], [0, c, -s]], dtype=float)


def dc2(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[-s, 0, c], [0, 0, 0], [-c, 0, -s]], dtype=float)


def dc3(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[-s, -c, 0], [c, -s, 0], [0, 0, 0]], dtype=float)


def dcm(lam):
    f, t, p = lam
    return c3(p) @ c2(t) @ c1(f)


def dcm_partials(lam):
    """[∂C/∂φ, ∂C/∂θ, ∂C/∂ψ] by the product rule on eq. 1."""
    f, t, p = lam
    return [c3(p) @ c2(t) @ dc1(f), c3(p) @ dc2(t) @ c1(f), dc3(p) @ c2(t) @ c1(f)]


def D(lam):
    """Eq. 3 exactly as printed: (1/cos θ) [[cθ, sφ sθ, cφ sθ], [0, cφ cθ, −sφ cθ], [0, sφ, cφ]]."""
    f, t = lam[0], lam[1]
    cf, sf, ct, st = np.cos(f), np.sin(f), np.cos(t), np.sin(t)
    return np.array([[ct, sf * st, cf * st], [0, cf * ct, -sf * ct], [0, sf, cf]]) / ct


def D_partials(lam):
    """[∂D/∂φ, ∂D/∂θ] of D = [[1, sφ tθ, cφ tθ], [0, cφ, −sφ], [0, sφ/cθ, cφ/cθ]]."""
    f, t = lam[0], lam[1]
    cf, sf, ct, st = np.cos(f), np.sin(f), np.cos(t), np.sin(t)
    tt, sec2 = st / ct, 1.0 / ct**2
    d_phi = np.array([[0, cf * tt, -sf * tt], [0, -sf, -cf], [0, cf / ct, -sf / ct]])
    d_theta = np.array([[0, sf * sec2, cf * sec2], [0, 0, 0], [0, sf * st * sec2, cf * st * sec2]])
    return d_phi, d_theta


# ----------------------------------------------------------------- paper 000
def f000(x, u, m, J, g):
    v, lam, w = x[3:6], x[6:9], x[9:12]
    C = dcm(lam)
    fT, tau = u[0], u[1:]
    Jx, Jy, Jz = J
    p, q, r = w
    rho_dot = C @ v
    v_dot = -np.cross(w, v) + C.T @ (g * E3) + np.array([0, 0, -fT]) / m
    lam_dot = D(lam) @ w
    w_dot = np.array(
        [
            ((Jy - Jz) * q * r + tau[0]) / Jx,
            ((Jz - Jx) * p * r + tau[1]) / Jy,
            ((Jx - Jy) * p * q + tau[2]) / Jz,
        ]
    )
    return np.concatenate([rho_dot, v_dot, lam_dot, w_dot])


def jac000(x, u, m, J, g):
    v, lam, w = x[3:6], x[6:9], x[9:12]
    C = dcm(lam)
    dC = dcm_partials(lam)
    dDf, dDt = D_partials(lam)
    Jx, Jy, Jz = J
    p, q, r = w
    A = np.zeros((12, 12))
    B = np.zeros((12, 4))
    A[0:3, 3:6] = C
    for i in range(3):
        A[0:3, 6 + i] = dC[i] @ v
        A[3:6, 6 + i] = g * dC[i].T @ E3
    A[3:6, 3:6] = -skew(w)
    A[3:6, 9:12] = skew(v)  # −ω×v = v×ω
    A[6:9, 6] = dDf @ w
    A[6:9, 7] = dDt @ w
    A[6:9, 9:12] = D(lam)
    A[9:12, 9:12] = np.array(
        [
            [0, (Jy - Jz) * r / Jx, (Jy - Jz) * q / Jx],
            [(Jz - Jx) * r / Jy, 0, (Jz - Jx) * p / Jy],
            [(Jx - Jy) * q / Jz, (Jx - Jy) * p / Jz, 0],
        ]
    )
    B[5, 0] = -1.0 / m
    B[9:12, 1:4] = np.diag([1 / Jx, 1 / Jy, 1 / Jz])
    return A, B


# ----------------------------------------------------------------- paper 001
SPIN = np.array([1.0, -1.0, 1.0, -1.0])


def mixer_matrix(l, k, d):
    """u = M ω² for the plus layout (1 front, 2 left, 3 back, 4 right, z up)."""
    return np.array(
        [
            [k, k, k, k],
            [0, l * k, 0, -l * k],  # roll: left rotor up-thrust minus right
            [-l * k, 0, l * k, 0],  # pitch (about +y = left): back minus front
            [-d, d, -d, d],  # reaction torque opposes each rotor's spin
        ]
    )


def f001_wrench(x, u, Om, m, J, g, Ir):
    vel, lam, w = x[3:6], x[6:9], x[9:12]
    R = dcm(lam)
    Ixx, Iyy, Izz = J
    p, q, r = w
    acc = u[0] / m * R[:, 2] - g * E3
    lam_dot = D(lam) @ w
    w_dot = np.array(
        [
            (Iyy - Izz) / Ixx * q * r - Ir * Om * q / Ixx + u[1] / Ixx,
            (Izz - Ixx) / Iyy * p * r + Ir * Om * p / Iyy + u[2] / Iyy,
            (Ixx - Iyy) / Izz * p * q + u[3] / Izz,
        ]
    )
    return np.concatenate([vel, acc, lam_dot, w_dot])


def f001(x, ws, m, J, g, Ir, l, k, d):
    u = mixer_matrix(l, k, d) @ (ws**2)
    return f001_wrench(x, u, SPIN @ ws, m, J, g, Ir)


def jac001(x, ws, m, J, g, Ir, l, k, d):
    """(A, B) of f001 with respect to the state and the rotor speeds."""
    lam, w = x[6:9], x[9:12]
    M = mixer_matrix(l, k, d)
    u = M @ ws**2
    Om = SPIN @ ws
    R = dcm(lam)
    dC = dcm_partials(lam)
    dDf, dDt = D_partials(lam)
    Ixx, Iyy, Izz = J
    a1, a2, a3 = (Iyy - Izz) / Ixx, (Izz - Ixx) / Iyy, (Ixx - Iyy) / Izz
    p, q, r = w
    A = np.zeros((12, 12))
    B = np.zeros((12, 4))
    A[0:3, 3:6] = np.eye(3)
    for i in range(3):
        A[3:6, 6 + i] = u[0] / m * dC[i][:, 2]
    A[6:9, 6] = dDf @ w
    A[6:9, 7] = dDt @ w
    A[6:9, 9:12] = D(lam)
    A[9:12, 9:12] = np.array(
        [
            [0, a1 * r - Ir * Om / Ixx, a1 * q],
            [a2 * r + Ir * Om / Iyy, 0, a2 * p],
            [a3 * q, a3 * p, 0],
        ]
    )
    du_dw = M * (2.0 * ws)[None, :]
    B[3:6, :] = np.outer(R[:, 2] / m, du_dw[0])
    B[9, :] = -Ir * q * SPIN / Ixx + du_dw[1] / Ixx
    B[10, :] = Ir * p * SPIN / Iyy + du_dw[2] / Iyy
    B[11, :] = du_dw[3] / Izz
    return A, B


def jac001_input(x, u, m, J, g, Ir, l, k, d):
    """(A, B) of the paper-001 model driven by u, Ω_r from the inverse mixer."""
    M = mixer_matrix(l, k, d)
    S = np.linalg.solve(M, u)
    ws = np.sqrt(S)
    A, Bw = jac001(x, ws, m, J, g, Ir, l, k, d)
    dw_du = np.linalg.solve(M, np.eye(4)) / (2.0 * ws)[:, None]
    lam_w = x[9:12]
    Ixx, Iyy, _ = J
    p, q = lam_w[0], lam_w[1]
    B = np.zeros((12, 4))
    R = dcm(x[6:9])
    B[3:6, 0] = R[:, 2] / m
    B[9:12, 1:4] = np.diag(1.0 / np.asarray(J))
    dOm_du = SPIN @ dw_du
    B[9, :] += -Ir * q * dOm_du / Ixx
    B[10, :] += Ir * p * dOm_du / Iyy
    return A, B
