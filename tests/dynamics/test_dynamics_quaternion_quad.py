"""Quaternion quadcopter model of paper 004 (eq. 3.10-3.16) against the Euler NED model."""

import numpy as np
import jax
import jax.numpy as jnp
import pytest

from jaxslam.dynamics import euler_ned, quaternion_quad as qq
from jaxslam.dynamics.integrators import rk4_step
from jaxslam.dynamics.params import QuadParams
from jaxslam.errors import InputError
from jaxslam.geometry.quaternion import qexp, qlog, qmul

PARAMS = QuadParams(1.3, (0.0119, 0.0131, 0.0219), 9.81)
DT = 1e-3
STEPS = 2000


def _inputs(dtype=jnp.float64):
    """Time-varying thrust and torques (s, N, N m): tilts up to ~35°, turns, no gimbal lock."""
    t = jnp.arange(STEPS, dtype=dtype) * DT
    f_T = PARAMS.mass * PARAMS.g * (1.0 + 0.2 * jnp.sin(2.0 * t))
    tau = jnp.stack([0.004 * jnp.sin(3.0 * t), 0.003 * jnp.cos(2.0 * t) - 0.001,
                     0.002 * jnp.sin(1.3 * t + 0.4)], axis=1)
    return jnp.concatenate([f_T[:, None], tau], axis=1)


@pytest.fixture(scope="module")
def both_models():
    x0e = jnp.array([1.0, -2.0, -3.0, 0.5, -0.3, 0.2, 0.2, -0.3, 1.0, 0.3, -0.2, 0.5])
    x0q = qq.from_euler_ned(x0e)
    us = _inputs()

    @jax.jit
    def run(x0e, x0q, us):
        def body(c, u):
            xe, xq = c
            xe = rk4_step(euler_ned.f, xe, u, DT, PARAMS)
            xq = qq.step(qq.f, xq, u, DT, PARAMS)
            return (xe, xq), (xe, xq)

        _, (xes, xqs) = jax.lax.scan(body, (x0e, x0q), us)
        return xes, xqs

    return run(x0e, x0q, us)


def test_quaternion_model_matches_euler_model(both_models):
    xes, xqs = both_models
    conv = jax.vmap(qq.to_euler_ned)(xqs)
    xes, conv = np.asarray(xes), np.asarray(conv)
    # the run is non-trivial: it tilts, turns and moves
    assert np.max(np.abs(np.degrees(xes[:, 6:8]))) > 15.0
    assert np.ptp(xes[:, 8]) > 0.2 and np.ptp(xes[:, 2]) > 0.5
    assert np.max(np.abs(xes[:, 7])) < np.radians(60.0)  # away from gimbal lock
    d = conv - xes
    d[:, 6:9] = (d[:, 6:9] + np.pi) % (2 * np.pi) - np.pi
    np.testing.assert_array_less(np.max(np.abs(d), axis=0), 1e-8)
    # the inertial velocity of the quaternion model is C_NB v_B of the Euler model
    back = jax.vmap(qq.from_euler_ned)(jnp.asarray(xes))
    np.testing.assert_allclose(np.asarray(back[:, qq.VEL]), np.asarray(xqs[:, qq.VEL]), atol=1e-8)


def test_converters_round_trip():
    x = jnp.array([1.0, 2.0, 3.0, 0.4, -0.5, 0.6, 0.3, -0.7, 2.5, 0.1, 0.2, -0.3])
    np.testing.assert_allclose(np.asarray(qq.to_euler_ned(qq.from_euler_ned(x))), np.asarray(x),
                               atol=1e-14)


def test_hover_is_an_equilibrium():
    x = qq.hover_state((1.0, 2.0, -3.0))
    u = jnp.array([PARAMS.mass * PARAMS.g, 0.0, 0.0, 0.0])
    np.testing.assert_allclose(np.asarray(qq.f(x, u, PARAMS)), 0.0, atol=1e-15)


def test_norm_stays_unit_over_1e5_steps():
    J = jnp.array([0.0119, 0.0131, 0.0219])
    xa0 = jnp.concatenate([qexp(jnp.array([0.3, -1.0, 2.0])), jnp.array([3.0, -2.0, 5.0])])
    tau = jnp.array([1e-3, -2e-3, 5e-4])
    dt = 1e-3

    @jax.jit
    def run(xa0):
        def body(xa, _):
            xn = qq.step(qq.f_att, xa, tau, dt, J)
            return xn, jnp.abs(jnp.linalg.norm(xn[:4]) - 1.0)

        def raw(xa, _):
            xn = rk4_step(qq.f_att, xa, tau, dt, J)
            return xn, None

        xf, dev = jax.lax.scan(body, xa0, None, length=100_000)
        xr, _ = jax.lax.scan(raw, xa0, None, length=100_000)
        return jnp.max(dev), jnp.abs(jnp.linalg.norm(xr[:4]) - 1.0), xf

    dev, raw_dev, xf = run(xa0)
    assert float(dev) < 1e-12
    # without the renormalisation RK4 drifts (at these rates) — the step is what fixes it
    assert float(raw_dev) > 10 * float(dev)
    assert np.all(np.isfinite(np.asarray(xf)))


@pytest.mark.parametrize("angle", [0.0, 1e-9, 1e-5, 0.3, 2.0, np.pi - 1e-6, np.pi - 1e-9])
def test_qlog_qexp_round_trip(angle):
    axis = np.array([1.0, -7.0, 3.0]) / np.sqrt(59.0)
    r = jnp.asarray(angle * axis)
    q = qexp(r)
    np.testing.assert_allclose(np.linalg.norm(np.asarray(q)), 1.0, atol=1e-15)
    np.testing.assert_allclose(np.asarray(qlog(q)), np.asarray(r), atol=1e-12)
    # shortest rotation: −q gives the same vector
    np.testing.assert_allclose(np.asarray(qlog(-q)), np.asarray(r), atol=1e-12)
    # exp(log q) = ±q
    q2 = np.asarray(qexp(qlog(q)))
    assert min(np.max(np.abs(q2 - np.asarray(q))), np.max(np.abs(q2 + np.asarray(q)))) < 1e-12


def test_qlog_beyond_pi_wraps_to_shortest():
    axis = jnp.array([0.0, 0.0, 1.0])
    q = qexp((np.pi + 0.2) * axis)  # q0 < 0
    np.testing.assert_allclose(np.asarray(qlog(q)), np.asarray(-(np.pi - 0.2) * axis), atol=1e-12)


def test_f_att_matches_hand_derived_oracle():
    rng = np.random.default_rng(3)
    J = np.array([0.0119, 0.0131, 0.0219])
    for _ in range(5):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        w, tau, xi = rng.normal(size=3), rng.normal(size=3) * 0.01, rng.normal(size=3)
        q0, q1, q2, q3 = q
        S = np.array([[-q1, -q2, -q3], [q0, -q3, q2], [q3, q0, -q1], [-q2, q1, q0]])  # eq. 3.12
        Jm = np.diag(J)
        wdot = np.linalg.solve(Jm, tau - np.cross(w, Jm @ w)) + xi  # eq. 3.13 + ξ (eq. 3.17)
        want = np.concatenate([0.5 * S @ w, wdot])
        got = qq.f_att(jnp.asarray(np.concatenate([q, w])), jnp.asarray(tau), jnp.asarray(J),
                       jnp.asarray(xi))
        np.testing.assert_allclose(np.asarray(got), want, rtol=1e-13, atol=1e-13)
        np.testing.assert_allclose(np.asarray(qq.s_matrix(jnp.asarray(q))), S)
        # thrust rotated by q ⊗ F ⊗ q* (eq. 3.16), gravity +z NED
        x = jnp.concatenate([jnp.zeros(6), jnp.asarray(q), jnp.asarray(w)])
        acc = np.asarray(qq.f(x, jnp.array([10.0, *tau]), PARAMS))[3:6]
        F = np.asarray(qmul(qmul(jnp.asarray(q), jnp.array([0.0, 0.0, 0.0, -10.0 / PARAMS.mass])),
                            jnp.asarray(q * [1, -1, -1, -1])))[1:]
        np.testing.assert_allclose(acc, F + [0.0, 0.0, PARAMS.g], atol=1e-12)


def test_float32_path_runs():
    x = qq.from_euler_ned(jnp.asarray(np.r_[np.zeros(6), 0.2, -0.1, 0.5, 0.1, 0.0, -0.2], np.float32))
    assert x.dtype == jnp.float32
    u = jnp.asarray([12.0, 1e-3, 0.0, -1e-3], jnp.float32)
    xn = qq.step(qq.f, x, u, 1e-3, PARAMS)
    assert xn.dtype == jnp.float32 and np.all(np.isfinite(np.asarray(xn)))
    xa = qq.step(qq.f_att, x[6:], u[1:], 1e-3, jnp.asarray(PARAMS.inertia, jnp.float32))
    assert xa.dtype == jnp.float32
    assert abs(float(jnp.linalg.norm(xa[:4])) - 1.0) < 1e-6
    assert qq.to_euler_ned(xn).dtype == jnp.float32


def test_bad_inputs_raise():
    with pytest.raises(InputError, match="xa"):
        qq.check_att_state(np.zeros(6))
    with pytest.raises(InputError, match="unit norm"):
        qq.check_att_state(np.r_[2.0, 0, 0, 0, 0, 0, 0])
    with pytest.raises(InputError, match="NaN"):
        qq.check_state(np.r_[np.zeros(6), 1.0, 0, 0, 0, np.nan, 0, 0])
    with pytest.raises(InputError, match="positive"):
        qq.check_inertia([0.01, 0.0, 0.02])
    with pytest.raises(InputError, match="quaternion"):
        qq.step(qq.f_att, jnp.zeros(5), jnp.zeros(3), 1e-3, jnp.ones(3))
    qq.check_state(np.asarray(qq.hover_state()))
    # the dynamics themselves name a wrong shape (a (12,) Euler state was sliced silently)
    with pytest.raises(InputError, match=r"^x: expected shape \(13\)"):
        qq.f(jnp.zeros(12), jnp.zeros(4), QuadParams(1.0, (0.01, 0.01, 0.02), 9.81))
    with pytest.raises(InputError, match=r"^tau: expected shape \(3\)"):
        qq.f_att(jnp.r_[1.0, jnp.zeros(6)], jnp.zeros(4), jnp.ones(3))
    with pytest.raises(InputError, match=r"^xi: expected shape \(3\)"):
        qq.f_att(jnp.r_[1.0, jnp.zeros(6)], jnp.zeros(3), jnp.ones(3), xi=jnp.zeros(2))


def test_quaternion_step_names_the_state():
    from jaxslam.dynamics import quaternion_quad as qq
    from jaxslam.errors import InputError

    with pytest.raises(InputError, match=r"^x: step cannot locate the quaternion in a state of size 5"):
        qq.step(lambda x, u: x, jnp.zeros(5), jnp.zeros(4), 0.1)
