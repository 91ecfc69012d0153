"""Tests for jaxslam.sensors.range_bearing3d (paper 001 eq. 13-15)."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import sensors_oracle_np as ref
from jaxslam.errors import InputError
from jaxslam.sensors import lidar3d
from jaxslam.sensors import range_bearing3d as rb

RNG = np.random.default_rng(1313)

_MEAS = jax.jit(jax.vmap(rb.measure))
_INV = jax.jit(jax.vmap(rb.inverse))
_JAC_M = jax.jit(jax.vmap(jax.jacfwd(rb.measure, argnums=(0, 1))))
_JAC_I = jax.jit(jax.vmap(jax.jacfwd(rb.inverse, argnums=(0, 1))))


def points(n):
    p = RNG.uniform(-10, 10, (n, 3))
    return p, p + RNG.uniform(-15, 15, (n, 3))


def test_measure_matches_paper_eq13_as_printed():
    p, m = points(40)
    y = np.asarray(_MEAS(jnp.asarray(p), jnp.asarray(m)))
    for i in range(40):
        z_paper = ref.rb_measure_paper_order(p[i], m[i])  # [β, α, r] with arcsin
        np.testing.assert_allclose(y[i][list(rb.PAPER001_ORDER)], z_paper, rtol=0, atol=1e-12)
        np.testing.assert_allclose(y[i], z_paper[list(rb.PAPER001_ORDER)], rtol=0, atol=1e-12)


def test_elevation_sign_follows_z_coordinate():
    p, m = np.zeros((40, 3)), np.tile([3.0, 4.0, 5.0], (40, 1))
    y = np.asarray(_MEAS(jnp.asarray(p), jnp.asarray(m)))[0]
    np.testing.assert_allclose(y, [math.atan2(4, 3), math.asin(5 / math.sqrt(50)), math.sqrt(50)],
                               atol=1e-14)
    assert y[1] > 0  # larger z ⇒ positive β (above in paper 001's z-up frame)


def test_equals_body_frame_lidar_at_zero_attitude():
    p, m = points(40)
    y_rb = _MEAS(jnp.asarray(p), jnp.asarray(m))
    y_l = jax.jit(jax.vmap(lidar3d.measure))(jnp.asarray(p), jnp.zeros((40, 3)), jnp.asarray(m))
    np.testing.assert_allclose(np.asarray(y_rb), np.asarray(y_l), atol=1e-12)


def test_measure_jacobians_match_hand_derivation():
    p, m = points(40)
    Jp, Jm = _JAC_M(jnp.asarray(p), jnp.asarray(m))
    for i in range(40):
        J = ref.dsph_dc(m[i] - p[i])
        np.testing.assert_allclose(np.asarray(Jm[i]), J, rtol=0, atol=1e-9)
        np.testing.assert_allclose(np.asarray(Jp[i]), -J, rtol=0, atol=1e-9)


def test_inverse_matches_eq15_and_jacobians():
    p, _ = points(40)
    y = np.column_stack([RNG.uniform(-3.1, 3.1, 40), RNG.uniform(-1.5, 1.5, 40),
                         RNG.uniform(0.2, 50, 40)])
    m = np.asarray(_INV(jnp.asarray(p), jnp.asarray(y)))
    Jp, Jy = _JAC_I(jnp.asarray(p), jnp.asarray(y))
    for i in range(40):
        np.testing.assert_allclose(m[i], ref.rb_inverse(p[i], y[i]), rtol=0, atol=1e-12)
        np.testing.assert_allclose(np.asarray(Jp[i]), np.eye(3), rtol=0, atol=1e-12)
        np.testing.assert_allclose(np.asarray(Jy[i]), ref.drho_dy(y[i]), rtol=0, atol=1e-9)
    # round trip measure ∘ inverse
    np.testing.assert_allclose(np.asarray(_MEAS(jnp.asarray(p), jnp.asarray(m))), y, atol=1e-10)


def test_round_trip_inverse_of_measure_and_batched_landmarks():
    p, m = points(1)
    lms = p[0] + RNG.uniform(-20, 20, (25, 3))
    y, back = jax.jit(lambda pp, ll: (rb.measure(pp, ll), rb.inverse(pp, rb.measure(pp, ll))))(
        jnp.asarray(p[0]), jnp.asarray(lms))
    assert y.shape == (25, 3)
    np.testing.assert_allclose(np.asarray(back), lms, rtol=0, atol=1e-11)


def test_near_vertical_elevation_stays_accurate_and_finite():
    p = jnp.zeros(3)
    m = jnp.array([1e-6, -2e-6, 4.0])
    y, J = jax.jit(lambda pp, mm: (rb.measure(pp, mm), jax.jacfwd(rb.measure, argnums=1)(pp, mm)))(
        p, m)
    y, J = np.asarray(y), np.asarray(J)
    assert y[1] == pytest.approx(math.atan2(4.0, math.hypot(1e-6, 2e-6)), abs=1e-15)
    assert np.all(np.isfinite(J))
    np.testing.assert_allclose(J[2], [0.25e-6, -0.5e-6, 1.0], atol=1e-12)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_sample_noise_and_cov(dtype):
    n = 100_000
    spec = rb.PAPER001_RANGE_BEARING
    # rbg keys compile faster here; the library is key-implementation agnostic.
    z = rb.sample_noise(jax.random.key(3, impl="rbg"), spec, (n,), dtype)
    assert z.shape == (n, 3) and z.dtype == dtype
    want = np.array([0.33 * math.pi / 180, 0.3 * math.pi / 180, 0.1])
    np.testing.assert_allclose(np.asarray(z, np.float64).std(axis=0), want, rtol=0.02)
    np.testing.assert_allclose(np.asarray(rb.measurement_cov(spec, dtype)), np.diag(want ** 2),
                               rtol=1e-6)
    p, m = points(40)
    y = _MEAS(jnp.asarray(p, dtype), jnp.asarray(m, dtype))
    assert y.dtype == dtype
    np.testing.assert_allclose(np.asarray(y, np.float64),
                               np.asarray(_MEAS(jnp.asarray(p), jnp.asarray(m))),
                               rtol=1e-5 if dtype == jnp.float32 else 1e-15, atol=1e-5)


def test_validation():
    with pytest.raises(InputError, match="pos"):
        rb.measure(jnp.zeros(4), jnp.zeros(3))
    with pytest.raises(InputError, match="landmark"):
        rb.measure(jnp.zeros(3), jnp.zeros((2, 4)))
    with pytest.raises(InputError, match="y"):
        rb.inverse(jnp.zeros(3), jnp.zeros(2))
    assert rb.check_range_bearing_spec(rb.PAPER001_RANGE_BEARING) is rb.PAPER001_RANGE_BEARING
    with pytest.raises(InputError, match="sigma_el"):
        rb.check_range_bearing_spec(rb.RangeBearingSpec(sigma_el=-1.0))
