"""RK4 order, scan rollout, linearisation and dt validation."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp

import dyn_oracles_np as orc
from jaxslam.dynamics import PAPER000, check_dt, linearize, rk4_step, rollout
from jaxslam.dynamics import rk4_field, rk4_linearized
from jaxslam.dynamics import euler_ned as en
from jaxslam.errors import InputError

M, J, G = 1.56, (0.1147, 0.0576, 0.1712), 9.81

rollout_j = jax.jit(rollout, static_argnums=0)
step_j = jax.jit(rk4_step, static_argnums=0)

X0 = np.array([0.5, -1.0, -2.0, 1.0, 0.3, -0.2, 0.2, -0.3, 0.5, 0.8, -0.6, 0.4])
U = np.array([14.0, 0.02, -0.015, 0.01])  # constant thrust and torques


def reference(t_end):
    sol = solve_ivp(lambda t, x: orc.f000(x, U, M, J, G), (0.0, t_end), X0,
                    method="DOP853", rtol=1e-13, atol=1e-13)
    return sol.y[:, -1]


def test_rk4_fourth_order_on_quadcopter():
    t_end = 1.0
    x_ref = reference(t_end)
    errs = []
    for n in (20, 40, 80):  # one compiled step, dt traced (no recompilation)
        x = X0
        for _ in range(n):
            x = step_j(en.f, x, U, t_end / n, PAPER000)
        errs.append(np.linalg.norm(np.asarray(x) - x_ref))
    ratios = [errs[0] / errs[1], errs[1] / errs[2]]
    assert errs[-1] < 1e-7
    for r in ratios:
        assert 13.0 < r < 19.5, (errs, ratios)


def test_rk4_against_closed_form_linear():
    """ẋ = A x: one RK4 step equals the 4th-order Taylor polynomial of e^{A h}."""
    A = np.array([[0.0, 1.0], [-4.0, -0.3]])
    f = lambda x, u: jnp.asarray(A) @ x + u
    h = 0.1
    x0 = np.array([1.0, -0.5])
    P = np.eye(2) + h * A + (h * A) @ (h * A) / 2 + np.linalg.matrix_power(h * A, 3) / 6 + np.linalg.matrix_power(h * A, 4) / 24
    np.testing.assert_allclose(step_j(f, x0, np.zeros(2), h), P @ x0, rtol=1e-14, atol=1e-14)


def test_rollout_matches_stepping_and_shape():
    rng = np.random.default_rng(0)
    us = np.tile(U, (7, 1)) + 0.01 * rng.normal(size=(7, 4))
    xs = rollout_j(en.f, X0, us, 0.01, PAPER000)
    assert xs.shape == (8, 12)
    np.testing.assert_array_equal(xs[0], X0)
    x = X0
    for k in range(7):
        x = step_j(en.f, x, us[k], 0.01, PAPER000)
        np.testing.assert_allclose(xs[k + 1], x, rtol=1e-14, atol=1e-14)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_rollout_dtype(dtype):
    xs = rollout_j(en.f, X0.astype(dtype), np.tile(U, (10, 1)).astype(dtype), 0.02, PAPER000)
    assert xs.dtype == dtype
    ref = reference(0.2)
    np.testing.assert_allclose(np.asarray(xs[-1], float), ref, atol=2e-5 if dtype == np.float32 else 1e-8)


def test_linearize_linear_system():
    A = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, -2.0, -3.0]])
    B = np.array([[0.0], [0.0], [1.0]])
    f = lambda x, u, s: s * (jnp.asarray(A) @ x + jnp.asarray(B) @ u)
    Aj, Bj = jax.jit(linearize, static_argnums=0)(f, np.ones(3), np.ones(1), 2.0)
    np.testing.assert_array_equal(Aj, 2 * A)
    np.testing.assert_array_equal(Bj, 2 * B)


def test_check_dt():
    assert check_dt(0.01) == 0.01
    for bad in (0.0, -1e-3, np.nan, np.inf):
        with pytest.raises(InputError, match="^dt:"):
            check_dt(bad)
    with pytest.raises(InputError, match="^dt:"):
        check_dt(np.array([0.1, 0.2]))
    with pytest.raises(InputError, match="^step:"):
        check_dt(-1.0, name="step")


def _field(x, c):
    # a kinematic car: position (2) does not enter the field; heading, speed, steering do,
    # with an input that varies over the step through c
    th, v, d = x[2], x[3], x[4]
    return jnp.stack([v * jnp.cos(th), v * jnp.sin(th), v * jnp.tan(d) / 2.5, -0.3 * v + c, jnp.sin(c + d)])


@pytest.mark.parametrize("skip", [0, 2])
def test_rk4_linearized_is_the_exact_jacobian_of_the_step(skip):
    x = jnp.asarray([0.3, -1.2, 0.7, 2.0, 0.2])
    dt = 0.05
    xn, F = jax.jit(lambda y: rk4_linearized(_field, y, dt, skip=skip))(x)
    np.testing.assert_array_equal(np.asarray(xn), np.asarray(rk4_field(_field, x, dt)))
    F_ad = jax.jacfwd(lambda y: rk4_field(_field, y, dt))(x)
    np.testing.assert_allclose(np.asarray(F), np.asarray(F_ad), rtol=1e-13, atol=1e-15)
    # central differences as the independent oracle
    h = 1e-6
    fd = np.stack([(np.asarray(rk4_field(_field, x + h * e, dt)) - np.asarray(rk4_field(_field, x - h * e, dt))) / (2 * h)
                   for e in np.eye(5)], axis=1)
    np.testing.assert_allclose(np.asarray(F), fd, rtol=1e-7, atol=1e-9)
    # its derivative (what a gradient through a filter needs) equals autodiff's
    W = jnp.asarray(np.random.default_rng(0).normal(size=(5, 5)))
    g1 = jax.grad(lambda y: jnp.sum(W * rk4_linearized(_field, y, dt, skip=skip)[1]))(x)
    g0 = jax.grad(lambda y: jnp.sum(W * jax.jacfwd(lambda z: rk4_field(_field, z, dt))(y)))(x)
    np.testing.assert_allclose(np.asarray(g1), np.asarray(g0), rtol=1e-11, atol=1e-13)


def test_rk4_linearized_with_a_given_jacobian_and_float32():
    def jac(y, c):
        return _field(y, c), jax.jacfwd(lambda q: _field(jnp.concatenate([y[:2], q]), c))(y[2:])
    x = jnp.asarray([0.3, -1.2, 0.7, 2.0, 0.2], jnp.float32)
    xn, F = rk4_linearized(_field, x, 0.05, jacobian=jac, skip=2)
    assert xn.dtype == F.dtype == jnp.float32
    F64 = jax.jacfwd(lambda y: rk4_field(_field, y, 0.05))(x.astype(jnp.float64))
    np.testing.assert_allclose(np.asarray(F), np.asarray(F64), rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(np.asarray(rk4_step(lambda y, u: _field(y, u), x, 0.25, 0.05)),
                                  np.asarray(rk4_field(lambda y, c: _field(y, 0.25), x, 0.05)))
    with pytest.raises(InputError, match="skip"):
        rk4_linearized(_field, x, 0.05, skip=5)
