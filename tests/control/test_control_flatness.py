"""Flatness: linear model (eq. 6), references (eq. 4-5), inverse map (eq. 15-19), feedforward."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam.control.flatness import (
    body_rates_from_euler_rates,
    feedforward,
    inverse_map,
    linear_model,
    reference,
)
from jaxslam.control.trajectories import Figure8, Helix, flat_output
from jaxslam.dynamics import euler_ned
from jaxslam.dynamics.integrators import rk4_step
from jaxslam.dynamics.params import PAPER000


def _dcm_np(phi, theta, psi):
    """C_NB = C3(ψ) C2(θ) C1(φ), paper 000 eq. 1, written out in NumPy."""
    c, s = math.cos, math.sin
    C1 = np.array([[1, 0, 0], [0, c(phi), -s(phi)], [0, s(phi), c(phi)]])
    C2 = np.array([[c(theta), 0, s(theta)], [0, 1, 0], [-s(theta), 0, c(theta)]])
    C3 = np.array([[c(psi), -s(psi), 0], [s(psi), c(psi), 0], [0, 0, 1]])
    return C3 @ C2 @ C1


def _D_np(phi, theta):
    """D of paper 000 eq. 3."""
    c, s = math.cos, math.sin
    return np.array([[c(theta), s(phi) * s(theta), c(phi) * s(theta)],
                     [0, c(phi) * c(theta), -s(phi) * c(theta)],
                     [0, s(phi), c(phi)]]) / c(theta)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_linear_model_eq6(dtype):
    A, B, b = linear_model(dtype)
    assert A.shape == (7, 7) and B.shape == (7, 4) and b.shape == (7,)
    assert A.dtype == B.dtype == b.dtype == dtype
    rng = np.random.default_rng(0)
    r, u, g = rng.normal(size=7), rng.normal(size=4), 9.81
    rdot = np.asarray(A, np.float64) @ r + np.asarray(B, np.float64) @ u + np.asarray(b) * g
    # ρ̇ = velocity, ρ̈ = u_p + g n̂3, ψ̇ = u_ψ.
    np.testing.assert_allclose(rdot, np.r_[r[3:6], u[0:3] + [0, 0, g], u[3]], rtol=1e-6)


def test_reference_helix_closed_form():
    tr = Helix(radius=1.2, period=15.0, climb_rate=0.05, yaw_rate=0.02, psi0=0.1)
    w = 2 * math.pi / 15.0
    t, g = 3.7, 9.81
    r_d, u_d = jax.jit(reference)(tr, t, g)
    c, s = math.cos(w * t), math.sin(w * t)
    rho = [1.2 * c, 1.2 * s, -0.5 - 0.05 * t]
    vel = [-1.2 * w * s, 1.2 * w * c, -0.05]
    acc = [-1.2 * w * w * c, -1.2 * w * w * s, 0.0]
    np.testing.assert_allclose(r_d, rho + vel + [0.1 + 0.02 * t], rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(u_d, [acc[0], acc[1], acc[2] - g, 0.02], rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_inverse_map_reconstructs_up(dtype):
    rng = np.random.default_rng(1)
    m = 1.56
    f = jax.jit(jax.vmap(inverse_map, in_axes=(0, 0, None)))
    n = 200
    up = rng.normal(size=(n, 3)) * 3.0 + np.array([0, 0, -9.81])
    up[:20, 2] = rng.uniform(1.0, 5.0, size=20)  # downward thrust acceleration: z3 < 0
    u = np.c_[up, rng.normal(size=n)]
    psi = rng.uniform(-math.pi, math.pi, size=n)
    outs = f(jnp.asarray(u, dtype), jnp.asarray(psi, dtype), m)
    fT, phi, theta, r = (np.asarray(a, np.float64) for a in outs)
    tol = 1e-5 if dtype == jnp.float32 else 1e-12
    for i in range(n):
        C = _dcm_np(phi[i], theta[i], psi[i])
        np.testing.assert_allclose(C @ np.array([0, 0, -fT[i]]) / m, up[i], rtol=tol, atol=tol * 10)
        np.testing.assert_allclose(fT[i], m * np.linalg.norm(up[i]), rtol=tol)
        # Corrected eq. 18 with q = 0: ψ̇ = r cos φ / cos θ must equal u_ψ.
        np.testing.assert_allclose(r[i] * math.cos(phi[i]) / math.cos(theta[i]), u[i, 3],
                                   rtol=tol * 10, atol=tol)
        if up[i, 2] < 0:  # normal flight: the paper's eq. 17 (asin, atan) agree
            z = -(_dcm_np(0, 0, psi[i]).T @ up[i]) / np.linalg.norm(up[i])
            paper = [math.asin(-z[1]), math.atan(z[0] / z[2])]
            np.testing.assert_allclose([phi[i], theta[i]], paper, rtol=tol, atol=tol)


def test_inverse_map_zero_thrust_is_finite():
    f = jax.jit(inverse_map)
    out = f(jnp.zeros(4), 0.3, 1.56)
    np.testing.assert_allclose([float(o) for o in out], [0.0, 0.0, 0.0, 0.0], atol=0)
    out = f(jnp.array([1e-9, 0.0, 0.0, 0.1]), 0.0, 1.56)
    assert all(np.isfinite(np.asarray(o)) for o in out)
    np.testing.assert_allclose(float(out[1]), 0.0, atol=1e-12)  # tiny command: levelled
    for u in ([0.3, -0.2, -9.0, 0.1], [0.0, 0.0, 0.0, 0.1]):
        g = jax.jit(jax.grad(lambda u: sum(inverse_map(u, 0.2, 1.56))))(jnp.array(u))
        assert np.all(np.isfinite(g))


def test_body_rates_inverse_of_eq3():
    rng = np.random.default_rng(2)
    for _ in range(20):
        lam = rng.uniform(-1.2, 1.2, size=3)
        w = rng.normal(size=3)
        lam_dot = _D_np(lam[0], lam[1]) @ w
        w_got = body_rates_from_euler_rates(jnp.asarray(lam), jnp.asarray(lam_dot))
        np.testing.assert_allclose(w_got, w, rtol=1e-12, atol=1e-12)


_FF = jax.jit(feedforward)


def test_feedforward_satisfies_dynamics():
    """f(x_d, u_ff) equals dx_d/dt by central differences of x_d (eq. 2 solved exactly)."""
    tr = Figure8(heading_along_path=1.0, psi0=0.2)
    h = 1e-4
    for t in [0.5, 4.0, 13.0]:
        x, u = _FF(tr, t, PAPER000)
        xdot_fd = (_FF(tr, t + h, PAPER000)[0] - _FF(tr, t - h, PAPER000)[0]) / (2 * h)
        np.testing.assert_allclose(euler_ned.f(x, u, PAPER000), xdot_fd, rtol=1e-6, atol=1e-7)
        # x_d holds the flat output's position and yaw; thrust = m ‖ρ̈ − g n̂3‖.
        r_d, u_d = jax.jit(reference)(tr, t, PAPER000.g)
        np.testing.assert_allclose(x[0:3], r_d[0:3], atol=1e-14)
        np.testing.assert_allclose(x[8], r_d[6], atol=1e-14)
        np.testing.assert_allclose(u[0], PAPER000.mass * np.linalg.norm(u_d[0:3]), rtol=1e-13)
        np.testing.assert_allclose(_dcm_np(*np.asarray(x[6:9])) @ np.asarray(x[3:6]), r_d[3:6],
                                   atol=1e-13)


def _open_loop(traj, dt, T, dtype=jnp.float64):
    """x0 = x_d(0); u = u_ff(t_k + dt/2) held over each RK4 step; no feedback."""
    n = int(round(T / dt))

    @jax.jit
    def go():
        x0 = feedforward(traj, jnp.asarray(0.0, dtype), PAPER000)[0]

        def body(x, k):
            u = feedforward(traj, (k + 0.5) * dt, PAPER000)[1]
            xn = rk4_step(euler_ned.f, x, u, dt, PAPER000)
            return xn, xn[0:3]

        ks = jnp.arange(n, dtype=dtype)
        pos = jax.lax.scan(body, x0, ks)[1]
        ref = jax.vmap(lambda t: flat_output(traj, t)[0:3])((ks + 1) * dt)
        return jnp.linalg.norm(pos - ref, axis=1)

    return np.asarray(go())


def test_feedforward_open_loop_reproduces_figure8():
    """Open-loop flatness feedforward through eq. 2 over 10 s: measured 5e-6 m at dt = 5 ms."""
    err = _open_loop(Figure8(), 0.005, 10.0)
    assert err.max() < 1e-3, err.max()
    assert err.max() < 2e-5  # second-order sampling: (dt/2)² scaling of the 2e-5 m at dt = 10 ms


def test_feedforward_float32():
    x, u = _FF(Figure8(), jnp.float32(3.0), PAPER000)
    assert x.dtype == u.dtype == jnp.float32
    x64, u64 = _FF(Figure8(), 3.0, PAPER000)
    np.testing.assert_allclose(x, x64, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(u, u64, rtol=1e-4, atol=1e-4)
