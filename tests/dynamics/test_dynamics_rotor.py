"""Paper 001 eq. 1-4 model with rotor gyroscopic term, mixer and converters."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import dyn_oracles_np as orc
from jaxslam.dynamics import PAPER000, PAPER001, QuadParams, RotorQuadParams, linearize
from jaxslam.dynamics import euler_ned as en
from jaxslam.dynamics import rotor as ro
from jaxslam.errors import InputError

# Paper 001 Sec. IV values typed here; rotor data are the documented jaxslam choices.
M, J, G = 1.477, (0.01152, 0.01152, 0.0218), 9.81
IR, L, K, DRAG = 6.0e-5, 0.215, 1.5e-5, 3.0e-7
ORC = (M, J, G, IR, L, K, DRAG)

f_j = jax.jit(ro.f)
f_input_j = jax.jit(ro.f_input)
lin_j = jax.jit(linearize, static_argnums=0)
mixer_j = jax.jit(ro.mixer)
inv_j = jax.jit(ro.rotor_speeds_from_input)


def random_state(rng):
    x = rng.normal(size=12)
    x[6:9] = rng.uniform([-1.2, -1.3, -3.0], [1.2, 1.3, 3.0])
    x[9:12] *= 2.0
    return x


def random_speeds(rng):
    return rng.uniform(350.0, 650.0, size=4)


def test_mixer_matches_geometry():
    rng = np.random.default_rng(0)
    ws = random_speeds(rng)
    u = np.asarray(mixer_j(ws, PAPER001))
    f = K * ws**2
    # Thrust sum, roll from left(2)/right(4), pitch from back(3)/front(1), yaw from drag.
    np.testing.assert_allclose(u[0], f.sum(), rtol=1e-13)
    np.testing.assert_allclose(u[1], L * (f[1] - f[3]), rtol=1e-12)
    np.testing.assert_allclose(u[2], L * (f[2] - f[0]), rtol=1e-12)
    np.testing.assert_allclose(u[3], DRAG * (-ws[0] ** 2 + ws[1] ** 2 - ws[2] ** 2 + ws[3] ** 2), rtol=1e-12)
    # Moments of the thrust vectors r_i × (f_i ẑ) about the centre, computed directly.
    pos = L * np.array([[1, 0, 0], [0, 1, 0], [-1, 0, 0], [0, -1, 0]], dtype=float)
    tau = sum(np.cross(pos[i], [0, 0, f[i]]) for i in range(4))
    np.testing.assert_allclose(u[1:3], tau[:2], rtol=1e-12)
    np.testing.assert_allclose(jax.jit(ro.net_rotor_speed)(ws), ws[0] - ws[1] + ws[2] - ws[3])
    Mj = np.asarray(jax.jit(ro.mixer_matrix, static_argnums=1)(PAPER001, np.float64))
    np.testing.assert_allclose(Mj, orc.mixer_matrix(L, K, DRAG), rtol=1e-15)
    np.testing.assert_allclose(Mj @ ws**2, u, rtol=1e-12, atol=1e-14)


def test_inverse_mixer_round_trip_and_clipping():
    rng = np.random.default_rng(1)
    for _ in range(5):
        ws = random_speeds(rng)
        u = orc.mixer_matrix(L, K, DRAG) @ ws**2
        np.testing.assert_allclose(inv_j(u, PAPER001), ws, rtol=1e-12)
    # A pure roll torque with no thrust needs ω4² < 0: clipped to 0, finite gradient.
    u = np.array([0.0, 0.5, 0.0, 0.0])
    w = np.asarray(inv_j(u, PAPER001))
    np.testing.assert_allclose(w, [0.0, np.sqrt(2 * 0.5 / (L * K) / 4), 0.0, 0.0], rtol=1e-12)
    g = jax.jit(jax.jacfwd(ro.rotor_speeds_from_input))(u, PAPER001)
    assert np.all(np.isfinite(g))
    assert np.all(np.asarray(g)[[0, 2, 3]] == 0.0)


def test_f_matches_oracle_and_eq1():
    rng = np.random.default_rng(2)
    for _ in range(8):
        x, ws = random_state(rng), random_speeds(rng)
        np.testing.assert_allclose(f_j(x, ws, PAPER001), orc.f001(x, ws, *ORC), rtol=1e-11, atol=1e-11)
    # f_input reproduces f through the inverse mixer.
    u = orc.mixer_matrix(L, K, DRAG) @ ws**2
    np.testing.assert_allclose(f_input_j(x, u, PAPER001), orc.f001(x, ws, *ORC), rtol=1e-10, atol=1e-10)


def test_gyroscopic_term_isolated():
    """Only the I_r Ω_r terms of eq. 1 change when I_r changes."""
    x = np.zeros(12)
    x[9:12] = [0.3, -0.7, 0.2]
    ws = np.array([500.0, 480.0, 510.0, 470.0])
    p0 = PAPER001._replace(rotor_inertia=0.0)
    d = np.asarray(f_j(x, ws, PAPER001)) - np.asarray(f_j(x, ws, p0))
    Om = 500 - 480 + 510 - 470
    expect = np.zeros(12)
    expect[9] = -IR * Om * x[10] / J[0]
    expect[10] = IR * Om * x[9] / J[1]
    np.testing.assert_allclose(d, expect, atol=1e-13)


def test_hand_jacobians_match_linearize():
    rng = np.random.default_rng(3)
    for _ in range(8):
        x, ws = random_state(rng), random_speeds(rng)
        A, B = lin_j(ro.f, x, ws, PAPER001)
        A0, B0 = orc.jac001(x, ws, *ORC)
        np.testing.assert_allclose(A, A0, rtol=0, atol=1e-9)
        np.testing.assert_allclose(B, B0, rtol=0, atol=1e-9)
        u = orc.mixer_matrix(L, K, DRAG) @ ws**2
        Au, Bu = lin_j(ro.f_input, x, u, PAPER001)
        A1, B1 = orc.jac001_input(x, u, *ORC)
        np.testing.assert_allclose(Au, A1, rtol=0, atol=1e-9)
        np.testing.assert_allclose(Bu, B1, rtol=0, atol=1e-9)
    h = 1e-3  # rotor speeds ~500 rad/s
    Bfd = np.stack([(orc.f001(x, ws + h * e, *ORC) - orc.f001(x, ws - h * e, *ORC)) / (2 * h) for e in np.eye(4)], 1)
    np.testing.assert_allclose(B0, Bfd, atol=1e-8)
    h = 1e-6
    Afd = np.stack([(orc.f001(x + h * e, ws, *ORC) - orc.f001(x - h * e, ws, *ORC)) / (2 * h) for e in np.eye(12)], 1)
    np.testing.assert_allclose(A0, Afd, atol=1e-6)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_hover_is_equilibrium(dtype):
    x = np.zeros(12, dtype)
    x[0:3] = [1.0, -2.0, 3.0]
    x[8] = 0.9

    @jax.jit
    def run(x):
        w = ro.hover_rotor_speeds(PAPER001, dtype)
        return w, ro.f(x, w, PAPER001), ro.f_input(x, ro.hover_input(PAPER001, dtype), PAPER001)

    w, xd, xd2 = run(x)
    assert w.dtype == dtype and xd.dtype == dtype and xd2.dtype == dtype
    np.testing.assert_allclose(np.asarray(w), np.sqrt(M * G / (4 * K)), rtol=1e-6)
    np.testing.assert_allclose(np.asarray(xd), 0.0, atol=2e-5 if dtype == np.float32 else 1e-12)
    np.testing.assert_allclose(np.asarray(xd2), 0.0, atol=2e-5 if dtype == np.float32 else 1e-12)


T = np.diag([1.0, -1.0, -1.0])


def ned_oracle(x):
    """Hand conversion z-up (NWU world, FLU body) -> NED/FRD, written from rotations."""
    R = orc.dcm(x[6:9])  # R_b^w
    C = T @ R @ T  # C_NB between FRD and NED
    lam = np.array([x[6], -x[7], -x[8]])
    np.testing.assert_allclose(orc.dcm(lam), C, atol=1e-14)  # Euler relabelling is exact
    return np.concatenate([T @ x[0:3], C.T @ T @ x[3:6], lam, T @ x[9:12]])


def test_converters():
    rng = np.random.default_rng(4)
    to_j, from_j = jax.jit(ro.state_to_ned), jax.jit(ro.state_from_ned)
    for _ in range(5):
        x = random_state(rng)
        xn = to_j(x)
        np.testing.assert_allclose(xn, ned_oracle(x), atol=1e-13)
        np.testing.assert_allclose(from_j(xn), x, atol=1e-13)
    u = rng.normal(size=4)
    un, ub = jax.jit(lambda u: (ro.input_to_ned(u), ro.input_from_ned(ro.input_to_ned(u))))(u)
    np.testing.assert_allclose(un, [u[0], u[1], -u[2], -u[3]])
    np.testing.assert_allclose(ub, u)


def test_models_agree_without_rotor_inertia():
    """With I_r = 0, paper 001's model is paper 000's model in another frame:
    f000(T(x), T(u)) = dT/dx · f001(x, u)."""
    rng = np.random.default_rng(5)
    p1 = RotorQuadParams(1.56, (0.1147, 0.0576, 0.1712), 9.81, rotor_inertia=0.0)
    p0 = QuadParams(1.56, (0.1147, 0.0576, 0.1712), 9.81)

    @jax.jit
    def both(x, u):
        xd1 = ro.f_wrench(x, u, 0.0, p1)
        _, xd_conv = jax.jvp(ro.state_to_ned, (x,), (xd1,))
        return xd_conv, en.f(ro.state_to_ned(x), ro.input_to_ned(u), p0)

    for _ in range(5):
        x = random_state(rng)
        u = np.r_[rng.uniform(5, 25), rng.normal(scale=0.3, size=3)]
        a, b = both(x, u)
        np.testing.assert_allclose(a, b, rtol=1e-11, atol=1e-11)
        # and the paper-000 side equals its own NumPy oracle
        np.testing.assert_allclose(b, orc.f000(ned_oracle(x), u * [1, 1, -1, -1], *PAPER000[:2], 9.81), atol=1e-11)


def test_bad_rotor_speeds_raise():
    with pytest.raises(InputError, match="^rotor_speeds:"):
        ro.check_rotor_speeds(np.zeros(3))
    with pytest.raises(InputError, match="^w:"):
        ro.check_rotor_speeds(np.array([1.0, np.inf, 1.0, 1.0]), name="w")


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_specific_force_equals_rotated_acceleration_plus_gravity(dtype):
    """Oracle: R_b^wᵀ (ẍ + g e3) from f's own acceleration, for random attitudes."""
    from jaxslam.geometry.euler import dcm_from_euler

    rng = np.random.default_rng(5)
    w = jnp.asarray(380.0 + 30.0 * rng.random(4), dtype)
    tol = 1e-10 if dtype == np.float64 else 1e-4
    for _ in range(4):
        x = jnp.asarray(np.r_[rng.normal(size=6), rng.uniform(-1, 1, 3), rng.normal(size=3)],
                        dtype)
        xd = ro.f(x, w, PAPER001)
        ref = np.asarray(dcm_from_euler(x[6:9])).T @ (np.asarray(xd[3:6], float)
                                                      + np.r_[0, 0, PAPER001.g])
        sf = ro.specific_force(w, PAPER001)
        assert sf.dtype == dtype
        np.testing.assert_allclose(np.asarray(sf, float), ref, rtol=tol, atol=tol)
