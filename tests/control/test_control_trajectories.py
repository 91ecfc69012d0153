"""Trajectories: autodiff derivatives against closed forms written here (NumPy)."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam.errors import InputError
from jaxslam.control.trajectories import (
    Circle,
    Figure8,
    Helix,
    Square,
    flat_derivatives,
    flat_output,
)

TS = [0.0, 0.7, 3.3, 12.9, 31.4]

# One compiled function per container type (numeric fields and t are traced).
_FD = jax.jit(flat_derivatives, static_argnums=2)


def FD(traj, t):
    return np.asarray(_FD(traj, jnp.asarray(t, jnp.float64), 4))


def _sin_derivs(A, w, t, phase=0.0, order=4):
    """d^k/dt^k A sin(w t + phase) = A w^k sin(w t + phase + kπ/2)."""
    return np.array([A * w ** k * math.sin(w * t + phase + k * math.pi / 2)
                     for k in range(order + 1)])


def _fig8_closed(tr, t, order=4):
    w = 2 * math.pi / tr.period
    out = np.zeros((order + 1, 4))
    out[:, 0] = _sin_derivs(tr.a_x, w, t, order=order)
    out[:, 1] = _sin_derivs(tr.a_y, 2 * w, t, order=order)
    out[0, :3] += np.array(tr.center)
    out[0, 3] = tr.psi0
    return out


def test_figure8_no_ramp_closed_form():
    tr = Figure8(center=(1.0, -2.0, -4.0), a_x=3.0, a_y=1.5, period=17.0, psi0=0.3, ramp_time=0.0)
    for t in TS:
        np.testing.assert_allclose(FD(tr, t), _fig8_closed(tr, t),
                                   rtol=1e-11, atol=1e-11)


def test_figure8_after_ramp_is_the_path_and_starts_at_rest():
    tr = Figure8()
    for t in [8.0, 9.5, 30.0]:
        np.testing.assert_allclose(FD(tr, t), _fig8_closed(tr, t),
                                   rtol=1e-10, atol=1e-10)
    Y0 = FD(tr, 0.0)
    np.testing.assert_allclose(Y0[0, :3], tr.start, atol=1e-14)
    np.testing.assert_allclose(Y0[1:, :3], 0.0, atol=1e-12)


def test_figure8_during_ramp_leibniz():
    """p = s0 + s(t/T)(q − s0): Leibniz rule with the smoothstep polynomial's derivatives."""
    tr = Figure8(start=(0.5, 0.2, -0.1), ramp_time=6.0)
    poly = np.polynomial.Polynomial([0, 0, 0, 0, 0, 126, -420, 540, -315, 70])
    T = tr.ramp_time
    start = np.array(tr.start)
    for t in [0.4, 2.0, 3.0, 5.7]:
        q = _fig8_closed(tr._replace(ramp_time=0.0), t)[:, :3]
        s = np.array([poly.deriv(j)(t / T) / T ** j if j else poly(t / T) for j in range(5)])
        expect = np.zeros((5, 3))
        for k in range(5):
            for j in range(k + 1):
                qk = q[k - j] - (start if k - j == 0 else 0.0)
                expect[k] += math.comb(k, j) * s[j] * qk
        expect[0] += start
        got = FD(tr, t)
        np.testing.assert_allclose(got[:, :3], expect, rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(got[:, 3], [tr.psi0, 0, 0, 0, 0], atol=1e-14)


def test_figure8_heading_along_path():
    tr = Figure8(heading_along_path=1.0, psi0=0.1, ramp_time=0.0)
    h = 1e-4

    def closed(t):
        Y = _fig8_closed(tr, t, 2)
        xd, yd, xdd, ydd = Y[1, 0], Y[1, 1], Y[2, 0], Y[2, 1]
        return 0.1 + math.atan2(yd, xd), (xd * ydd - yd * xdd) / (xd ** 2 + yd ** 2)

    for t in [0.3, 5.0, 11.0, 20.0]:
        got = FD(tr, t)[:3, 3]
        psi, psidot = closed(t)
        psiddot = (closed(t + h)[1] - closed(t - h)[1]) / (2 * h)
        np.testing.assert_allclose(got[0], psi, atol=1e-12)
        np.testing.assert_allclose(got[1], psidot, rtol=1e-10)
        np.testing.assert_allclose(got[2], psiddot, rtol=1e-6, atol=1e-8)


def test_helix_closed_form():
    tr = Helix(center=(0.3, -0.2, -0.5), radius=1.2, period=15.0, climb_rate=0.05, psi0=0.4,
               yaw_rate=0.02)
    w = 2 * math.pi / tr.period
    for t in TS:
        e = np.zeros((5, 4))
        e[:, 0] = _sin_derivs(tr.radius, w, t, phase=math.pi / 2)
        e[:, 1] = _sin_derivs(tr.radius, w, t)
        e[0, :3] += np.array(tr.center)
        e[0, 2] -= tr.climb_rate * t
        e[1, 2] = -tr.climb_rate
        e[0, 3] = tr.psi0 + tr.yaw_rate * t
        e[1, 3] = tr.yaw_rate
        np.testing.assert_allclose(FD(tr, t), e, rtol=1e-11, atol=1e-12)


def test_circle_paper003_closed_form():
    tr = Circle()  # paper 003 scenario I: [1.5 cos 0.1t, 1.5 sin 0.1t], ψ̇ = 0.2 sin 0.1t
    for t in TS:
        Y = FD(tr, t)
        np.testing.assert_allclose(Y[0, :2], [1.5 * math.cos(0.1 * t), 1.5 * math.sin(0.1 * t)],
                                   atol=1e-13)
        np.testing.assert_allclose(Y[:, 0], _sin_derivs(1.5, 0.1, t, phase=math.pi / 2), atol=1e-13)
        np.testing.assert_allclose(Y[:, 1], _sin_derivs(1.5, 0.1, t), atol=1e-13)
        np.testing.assert_allclose(Y[0, 2], -1.0)
        np.testing.assert_allclose(Y[0, 3], 2.0 * (1 - math.cos(0.1 * t)), atol=1e-13)
        np.testing.assert_allclose(Y[1:, 3], _sin_derivs(0.2, 0.1, t, order=3), atol=1e-13)


def test_circle_zero_yaw_frequency_is_finite():
    tr = Circle(yaw_omega=0.0, yaw_amp=0.3)
    Y = FD(tr, 2.0)
    assert np.all(np.isfinite(Y))
    np.testing.assert_allclose(Y[:, 3], 0.0, atol=1e-15)  # ψ̇ = a sin(0·t) = 0


def _square_closed(tr, t):
    """x = S tanh(k cos θ), y = S tanh(k sin θ), θ = Ω t; orders 0-2 by hand."""
    S = tr.half_side / math.tanh(tr.sharpness)
    k = tr.sharpness
    W = 2 * math.pi / tr.period
    th = W * t
    out = np.zeros((3, 2))
    for i, (u, du, ddu) in enumerate([
        (k * math.cos(th), -k * math.sin(th) * W, -k * math.cos(th) * W ** 2),
        (k * math.sin(th), k * math.cos(th) * W, -k * math.sin(th) * W ** 2),
    ]):
        th_u = math.tanh(u)
        sech2 = 1 - th_u ** 2
        out[0, i] = S * th_u
        out[1, i] = S * sech2 * du
        out[2, i] = S * (-2 * sech2 * th_u * du ** 2 + sech2 * ddu)
    return out


def test_square_closed_form_and_shape():
    tr = Square(center=(0.0, 0.0, -1.0), psi0=0.2, yaw_rate=0.01)
    h = 1e-3
    for t in [0.0, 4.0, 7.5, 22.0, 41.0]:
        Y = FD(tr, t)
        np.testing.assert_allclose(Y[:3, :2], _square_closed(tr, t), rtol=1e-11, atol=1e-12)
        third = (_square_closed(tr, t + h)[2] - _square_closed(tr, t - h)[2]) / (2 * h)
        fourth = (_square_closed(tr, t + h)[2] - 2 * _square_closed(tr, t)[2]
                  + _square_closed(tr, t - h)[2]) / h ** 2
        np.testing.assert_allclose(Y[3, :2], third, rtol=1e-4, atol=1e-7)
        np.testing.assert_allclose(Y[4, :2], fourth, rtol=1e-3, atol=1e-6)
        np.testing.assert_allclose(Y[:, 3], [0.2 + 0.01 * t, 0.01, 0, 0, 0], atol=1e-14)
    # Corner at θ = π/4 lies within 3 % of the sharp corner (documented rounding).
    c = np.asarray(flat_output(tr, tr.period / 8))[:2]
    assert np.all(np.abs(c) > 0.97 * tr.half_side) and np.all(np.abs(c) <= tr.half_side)


@pytest.mark.parametrize("traj", [Figure8(), Helix(), Circle(), Square(),
                                  Figure8(heading_along_path=1.0)])
@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_dtype_jit_vmap(traj, dtype):
    t = jnp.asarray(13.0, dtype)
    if dtype == jnp.float64:
        Y = _FD(traj, t, 4)
    else:
        Y = jax.jit(flat_derivatives, static_argnums=2)(traj, t, 1)
    assert Y.shape == ((5, 4) if dtype == jnp.float64 else (2, 4)) and Y.dtype == dtype
    np.testing.assert_allclose(np.asarray(Y, np.float64), FD(traj, 13.0)[: Y.shape[0]],
                               rtol=1e-4 if dtype == jnp.float32 else 1e-12, atol=1e-5)
    Ys = jax.vmap(lambda tt: flat_output(traj, tt))(jnp.linspace(0, 5, 7, dtype=dtype))
    assert Ys.shape == (7, 4) and Ys.dtype == dtype


def test_jit_and_grad_in_container_fields():
    f = jax.jit(lambda r, t: flat_output(Circle(radius=r), t)[0])
    np.testing.assert_allclose(f(2.0, 3.0), 2.0 * math.cos(0.3))
    np.testing.assert_allclose(jax.grad(f)(2.0, 3.0), math.cos(0.3))
    # The container itself is a jit argument (numeric leaves are traced, no recompilation).
    g = jax.jit(flat_output)
    np.testing.assert_allclose(g(Figure8(period=20.0), 1.0), flat_output(Figure8(period=20.0), 1.0))
    np.testing.assert_allclose(g(Figure8(period=30.0), 1.0), flat_output(Figure8(period=30.0), 1.0))


def test_bad_arguments():
    with pytest.raises(TypeError, match="traj"):
        flat_output((1.0, 2.0), 0.0)
    with pytest.raises(TypeError, match="traj"):
        flat_derivatives((1.0, 2.0), 0.0, 1)
    with pytest.raises(InputError, match="order"):
        flat_derivatives(Figure8(), 0.0, -1)
    with pytest.raises(InputError, match="order"):
        flat_derivatives(Figure8(), 0.0, 2.5)  # a float order used to be truncated to 2
    assert flat_derivatives(Figure8(), 1.0, 0).shape == (1, 4)
    # concrete fields are checked: a zero period made every reference NaN, a NaN centre too
    with pytest.raises(InputError, match=r"Figure8\.period: must be > 0"):
        flat_output(Figure8(period=0.0), 1.0)
    with pytest.raises(InputError, match=r"Square\.sharpness: must be > 0"):
        flat_derivatives(Square(sharpness=-1.0), 1.0, 2)
    with pytest.raises(InputError, match=r"Helix\.center: must be finite"):
        flat_output(Helix(center=(0.0, float("nan"), -1.0)), 1.0)
    with pytest.raises(InputError, match=r"Circle\.radius: expected a number"):
        flat_output(Circle(radius=(1.0, 2.0)), 1.0)
    # traced fields are not checked (a tuned period under jit stays differentiable)
    assert jnp.isfinite(jax.jit(lambda p: flat_output(Figure8(period=p), 1.0))(25.0)).all()
