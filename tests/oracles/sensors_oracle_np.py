"""Independent float64 NumPy references for the sensor tests (no jaxslam imports).

Hand-derived Jacobians are written out element by element from the paper equations; they
are the oracles for the library's ``jax.jacfwd`` Jacobians.
"""

import numpy as np


# --- 3-2-1 DCM (paper 000 eq. 1) and its partial derivatives -------------------------------

def c1(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]], dtype=np.float64)


def c2(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]], dtype=np.float64)


def c3(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]], dtype=np.float64)


def dc1(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[0, 0, 0], [0, -s, -c], [0, c, -s]], dtype=np.float64)


def dc2(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[-s, 0, c], [0, 0, 0], [-c, 0, -s]], dtype=np.float64)


def dc3(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[-s, -c, 0], [c, -s, 0], [0, 0, 0]], dtype=np.float64)


def dcm(e):
    phi, th, psi = e
    return c3(psi) @ c2(th) @ c1(phi)


def ddcm(e):
    """[∂C/∂φ, ∂C/∂θ, ∂C/∂ψ]."""
    phi, th, psi = e
    return [c3(psi) @ c2(th) @ dc1(phi),
            c3(psi) @ dc2(th) @ c1(phi),
            dc3(psi) @ c2(th) @ c1(phi)]


def euler_rate_matrix(e):
    """D of paper 000 eq. 3 (Λ̇ = D ω)."""
    phi, th, _ = e
    ct, st = np.cos(th), np.sin(th)
    cf, sf = np.cos(phi), np.sin(phi)
    return np.array([[ct, sf * st, cf * st], [0, cf * ct, -sf * ct], [0, sf, cf]]) / ct


def skew(w):
    return np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]], dtype=np.float64)


# --- spherical coordinates (paper 000 eq. 31 per errata, eq. 45) ---------------------------

def sph(c):
    c = np.asarray(c, np.float64)
    return np.array([np.arctan2(c[1], c[0]),
                     np.arctan2(c[2], np.hypot(c[0], c[1])),
                     np.sqrt(c @ c)])


def dsph_dc(c):
    c1_, c2_, c3_ = c
    h2 = c1_ ** 2 + c2_ ** 2
    h = np.sqrt(h2)
    d2 = h2 + c3_ ** 2
    d = np.sqrt(d2)
    return np.array([
        [-c2_ / h2, c1_ / h2, 0.0],
        [-c1_ * c3_ / (h * d2), -c2_ * c3_ / (h * d2), h / d2],
        [c1_ / d, c2_ / d, c3_ / d],
    ])


def rho(y):
    a, b, r = y
    return np.array([r * np.cos(b) * np.cos(a), r * np.cos(b) * np.sin(a), r * np.sin(b)])


def drho_dy(y):
    a, b, r = y
    ca, sa, cb, sb = np.cos(a), np.sin(a), np.cos(b), np.sin(b)
    return np.array([
        [-r * cb * sa, -r * sb * ca, cb * ca],
        [r * cb * ca, -r * sb * sa, cb * sa],
        [0.0, r * cb, sb],
    ])


# --- LiDAR (paper 000) ----------------------------------------------------------------------

def lidar_measure(p, e, l):
    return sph(dcm(e).T @ (np.asarray(l) - np.asarray(p)))


def lidar_H(s, l):
    """(∂h/∂s (3×9), ∂h/∂l (3×3)) for s = [ρ, v, Λ]."""
    p, e = s[0:3], s[6:9]
    d = np.asarray(l) - p
    C = dcm(e)
    c = C.T @ d
    J = dsph_dc(c)
    dc_dl = C.T
    dc_de = np.stack([dC.T @ d for dC in ddcm(e)], axis=1)
    Hs = np.zeros((3, 9))
    Hs[:, 0:3] = -J @ dc_dl
    Hs[:, 6:9] = J @ dc_de
    return Hs, J @ dc_dl


def lidar_inverse(p, e, y):
    return np.asarray(p) + dcm(e) @ rho(y)


def lidar_G(s, y):
    """(G_s (3×9), G_l (3×3)) of paper 000 eq. 49."""
    e = s[6:9]
    r = rho(y)
    Gs = np.zeros((3, 9))
    Gs[:, 0:3] = np.eye(3)
    Gs[:, 6:9] = np.stack([dC @ r for dC in ddcm(e)], axis=1)
    return Gs, dcm(e) @ drho_dy(y)


# --- world-frame range/bearing (paper 001 eq. 13-15, written with arcsin as printed) --------

def rb_measure_paper_order(p, m):
    """z^S = [β, α, r] exactly as paper 001 eq. 13 prints it."""
    dx, dy, dz = np.asarray(m, np.float64) - np.asarray(p, np.float64)
    r = np.sqrt(dx * dx + dy * dy + dz * dz)
    return np.array([np.arcsin(dz / r), np.arctan2(dy, dx), r])


def rb_inverse(p, y):
    """Eq. 15 with y = [α, β, r]."""
    a, b, r = y
    x, yy, z = p
    return np.array([x + r * np.cos(b) * np.cos(a), yy + r * np.cos(b) * np.sin(a),
                     z + r * np.sin(b)])


# --- IMU (paper 000 eq. 2) --------------------------------------------------------------------

def specific_force(x, xdot, g):
    """C_NBᵀ(a_N − g n̂3) with a_N = C_NB(v̇ + ω × v)."""
    v, e, w = x[3:6], x[6:9], x[9:12]
    C = dcm(e)
    a_n = C @ (xdot[3:6] + np.cross(w, v))
    return C.T @ (a_n - g * np.array([0.0, 0.0, 1.0]))


def specific_force_jac_x(x, xdot, g):
    """∂f/∂x (3×12): f = v̇ + ω×v − g [−sθ, cθ sφ, cθ cφ]."""
    v, e, w = x[3:6], x[6:9], x[9:12]
    phi, th = e[0], e[1]
    cf, sf, ct, st = np.cos(phi), np.sin(phi), np.cos(th), np.sin(th)
    J = np.zeros((3, 12))
    J[:, 3:6] = skew(w)            # ∂(ω×v)/∂v
    J[:, 6] = -g * np.array([0.0, ct * cf, -ct * sf])
    J[:, 7] = -g * np.array([-ct, -st * sf, -st * cf])
    J[:, 9:12] = -skew(v)          # ∂(ω×v)/∂ω
    return J
