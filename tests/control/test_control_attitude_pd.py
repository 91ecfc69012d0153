"""PD attitude law of paper 000 eq. 20."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam.control.attitude_pd import PDGains, gains_from_bandwidth, pd_torque

J000 = np.array([0.1147, 0.0576, 0.1712])


def test_default_gains_are_documented_bandwidth():
    g = PDGains()
    np.testing.assert_allclose(g.kp, J000 * 25.0 ** 2, rtol=1e-15)
    np.testing.assert_allclose(g.kd, 2 * 0.8 * 25.0 * J000, rtol=1e-15)
    g2 = gains_from_bandwidth(J000, 25.0, 0.8)
    np.testing.assert_allclose(g2.kp, g.kp)
    np.testing.assert_allclose(g2.kd, g.kd)
    # Closed loop of J ë = −kp e − kd ė: roots of J s² + kd s + kp have |s| = ω_n, ζ = 0.8.
    for i in range(3):
        s = np.roots([J000[i], g.kd[i], g.kp[i]])
        np.testing.assert_allclose(np.abs(s), 25.0, rtol=1e-12)
        np.testing.assert_allclose(-s.real / np.abs(s), 0.8, rtol=1e-12)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_eq20_closed_form(dtype):
    rng = np.random.default_rng(0)
    kp, kd = rng.uniform(1, 5, 3), rng.uniform(0.1, 1, 3)
    lam, lam_d = rng.uniform(-0.5, 0.5, 3), rng.uniform(-0.5, 0.5, 3)
    w, w_d = rng.normal(size=3), rng.normal(size=3)
    a = lambda x: jnp.asarray(x, dtype)  # noqa: E731
    tau = jax.jit(pd_torque)(a(lam), a(w), a(lam_d), a(w_d), PDGains(a(kp), a(kd)))
    assert tau.dtype == dtype
    expect = [-kp[i] * (lam[i] - lam_d[i]) - kd[i] * (w[i] - w_d[i]) for i in range(3)]
    np.testing.assert_allclose(tau, expect, rtol=1e-5 if dtype == jnp.float32 else 1e-13)
    tau_ff = rng.normal(size=3)
    tau2 = pd_torque(a(lam), a(w), a(lam_d), a(w_d), PDGains(a(kp), a(kd)), a(tau_ff))
    np.testing.assert_allclose(tau2, np.array(expect) + tau_ff,
                               rtol=1e-5 if dtype == jnp.float32 else 1e-13)


def test_yaw_error_is_wrapped():
    g = PDGains(kp=(1.0, 1.0, 2.0), kd=(0.0, 0.0, 0.0))
    tau = pd_torque(jnp.array([0.0, 0.0, 3.1]), jnp.zeros(3), jnp.array([0.0, 0.0, -3.1]),
                    jnp.zeros(3), g)
    # ψ − ψ_d = 6.2 rad wraps to 6.2 − 2π = −0.0832 rad: turn the short way (positive torque).
    np.testing.assert_allclose(tau[2], -2.0 * (6.2 - 2 * math.pi), rtol=1e-12)
    # Roll is not wrapped (documented).
    tau = pd_torque(jnp.array([0.2, 0.0, 0.0]), jnp.zeros(3), jnp.zeros(3), jnp.zeros(3), g)
    np.testing.assert_allclose(tau[0], -0.2)


def test_pd_shapes_and_values_are_checked():
    """Review of 2026-12-07: a (2,) inertia gave (2,) gains; NaN gains a NaN torque; a (2,)
    tau_ff a bare TypeError."""
    from jaxslam.errors import InputError

    with pytest.raises(InputError, match=r"^inertia: expected finite and > 0 \(a scalar or \(3,\)\)"):
        gains_from_bandwidth([0.1, 0.2], 10.0, 0.7)
    with pytest.raises(InputError, match=r"^omega_n: expected finite and >= 0"):
        gains_from_bandwidth([0.1, 0.2, 0.3], np.ones(5), 0.7)
    z = np.zeros(3)
    with pytest.raises(InputError, match=r"^gains\.kp: expected finite numbers"):
        pd_torque(z, z, z, z, PDGains(kp=(np.nan, 1.0, 1.0), kd=(1.0, 1.0, 1.0)))
    with pytest.raises(InputError, match=r"^tau_ff: expected shape \(3\), got \(2,\)"):
        pd_torque(z, z, z, z, PDGains(), tau_ff=np.zeros(2))
    tau = pd_torque(np.array([0.1, 0.0, 0.0]), z, z, z, PDGains(kp=(2.0, 1.0, 1.0), kd=(1.0, 1.0, 1.0)),
                    tau_ff=np.ones(3))
    np.testing.assert_allclose(np.asarray(tau), [-0.2 + 1.0, 1.0, 1.0])
