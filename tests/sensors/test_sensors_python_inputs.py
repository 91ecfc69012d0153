"""Sensor models called from plain Python: integer and list inputs, complex values, specs that
skipped validation, empty wall sets and float32 extremes.

Each case used to give a plausible wrong reading, a NaN gradient or a bare error; the expected
values come from closed forms written here in NumPy (or finite differences), never from the
code under test."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam.errors import InputError
from jaxslam.linalg import safe_norm
from jaxslam.sensors import imu, laser2d, lidar3d, range_bearing2d as rb2, range_bearing3d as rb3, uwb

KEY = jax.random.PRNGKey(0)


# ---------------------------------------------------------------------------
# IMU: gravity, integer states, spec helpers, drift gradient
# ---------------------------------------------------------------------------

def _f_b(euler, vdot, g):
    """Closed form f_B = v̇_B − g·(third row of the 3-2-1 C_NB) at rest (ω = v = 0)."""
    phi, theta, _ = euler
    row3 = np.array([-math.sin(theta), math.cos(theta) * math.sin(phi), math.cos(theta) * math.cos(phi)])
    return np.asarray(vdot, float) - g * row3


def test_specific_force_of_an_integer_state_keeps_gravity_a_float():
    x = jnp.zeros(12, int)
    xdot = jnp.zeros(12, int).at[3:6].set(jnp.array([1, 2, 3]))
    f = imu.specific_force(x, xdot, 9.81)  # g used to be cast to the state's int: 9
    assert jnp.issubdtype(f.dtype, jnp.floating)
    np.testing.assert_allclose(np.asarray(f), _f_b((0, 0, 0), [1, 2, 3], 9.81), rtol=0, atol=1e-12)
    reading = imu.imu_ideal([0.0] * 12, [0.0] * 12, 9.81)  # lists are read as arrays
    np.testing.assert_allclose(np.asarray(reading), [0, 0, -9.81, 0, 0, 0], rtol=0, atol=1e-12)


def test_specific_force_refuses_a_gravity_vector_and_non_numbers():
    x = jnp.zeros(12).at[6:9].set(jnp.array([0.3, 0.2, 0.1]))
    np.testing.assert_allclose(np.asarray(imu.specific_force(x, jnp.zeros(12), 9.81)),
                               _f_b((0.3, 0.2, 0.1), [0, 0, 0], 9.81), rtol=1e-13, atol=1e-13)
    # a (3,) g was applied elementwise to C_NB's third row: [0, 0, -9.185] instead of the above
    with pytest.raises(InputError, match="^g: expected a scalar"):
        imu.specific_force(x, jnp.zeros(12), jnp.array([0.0, 0.0, 9.81]))
    with pytest.raises(InputError, match="^g: expected a finite gravity"):
        imu.specific_force(x, jnp.zeros(12), float("nan"))
    with pytest.raises(InputError, match="^g: expected numbers"):
        imu.imu_ideal(x, jnp.zeros(12), "9.81")
    with pytest.raises(InputError, match="^x: expected a real array"):
        imu.specific_force(x + 0j, jnp.zeros(12), 9.81)
    # traced g: no value check under jit
    jit_f = jax.jit(lambda g: imu.specific_force(x, jnp.zeros(12), g))
    np.testing.assert_allclose(np.asarray(jit_f(9.81)), _f_b((0.3, 0.2, 0.1), [0, 0, 0], 9.81), rtol=1e-13)


@pytest.mark.parametrize("call, needle", [
    (lambda: imu.drift_stationary_sigma(imu.ImuSpec(drift_tau=-5.0, drift_density=0.1)), "^spec.drift_tau: invalid"),
    (lambda: imu.bias_drift_init(KEY, imu.ImuSpec(drift_tau=-5.0, drift_density=0.1)), "^spec.drift_tau: invalid"),
    (lambda: imu.bias_drift_init(KEY, imu.ImuSpec(bias=float("nan"))), "^spec.bias: invalid"),
    (lambda: imu.bias_drift_init(KEY, imu.ImuSpec(bias=np.ones(7))), r"^spec.bias: shape \(7,\) does not broadcast"),
    (lambda: imu.white_noise_cov(imu.PAPER000_IMU, dtype=jnp.int32), "^dtype: expected a floating dtype"),
    (lambda: imu.sample_white_noise(KEY, imu.PAPER000_IMU, (2,), dtype=jnp.int32), "^dtype: expected a floating dtype"),
    (lambda: imu.bias_drift_step(KEY, imu.BiasDriftState(jnp.zeros(5), jnp.zeros(5)), imu.PAPER000_IMU, 0.1),
     r"^state.bias: expected shape \(\.\.\., 6\)"),
    (lambda: imu.corrupt(jnp.zeros(6) + 0j, imu.BiasDriftState(jnp.zeros(6), jnp.zeros(6)), jnp.zeros(6)),
     "^ideal: expected a real array"),
], ids=["stationary-tau", "init-tau", "init-nan-bias", "init-bias-7", "cov-int", "noise-int", "step-5", "corrupt-complex"])
def test_imu_spec_helpers_validate(call, needle):
    with pytest.raises(InputError, match=needle):
        call()


def test_imu_drift_gradient_in_the_density_at_zero_is_finite():
    """√q had an infinite derivative at q = 0: grad w.r.t. the default density 0 was NaN.  The
    drift is linear in the density (ξ fixed by the key), so the one-sided difference is exact."""
    dt = 0.01
    st = imu.BiasDriftState(jnp.zeros(6), jnp.linspace(-0.1, 0.1, 6))

    def step(d):
        return jnp.sum(imu.bias_drift_step(jax.random.PRNGKey(1), st, imu.ImuSpec(drift_tau=10.0, drift_density=d), dt).drift)

    def roll(d):
        return jnp.sum(imu.bias_drift_rollout(jax.random.PRNGKey(2), st, imu.ImuSpec(drift_tau=10.0, drift_density=d),
                                              dt, 6).drift)

    for f in (step, roll):
        g = float(jax.grad(f)(0.0))
        h = 1e-3
        fd = (float(f(h)) - float(f(0.0))) / h
        assert math.isfinite(g) and g != 0.0
        np.testing.assert_allclose(g, fd, rtol=1e-8)
    # the state with a list is converted as well
    out = imu.bias_drift_step(KEY, imu.BiasDriftState([0.0] * 6, [0.0] * 6), imu.PAPER000_IMU, 0.1)
    np.testing.assert_array_equal(np.asarray(out.drift), np.zeros(6))


# ---------------------------------------------------------------------------
# UWB
# ---------------------------------------------------------------------------

def test_uwb_integer_inputs_are_read_as_floats():
    v = uwb.measurement_variance(2, 0.04, "range")  # the variance was cast to int: 0
    np.testing.assert_allclose(np.asarray(v), 0.04, rtol=1e-15)
    np.testing.assert_allclose(np.asarray(uwb.measurement_variance(jnp.array([1, 2]), 0.04, "range")), [0.04, 0.04])
    p, l = jnp.array([0, 0], jnp.int32), jnp.array([40000, 40000], jnp.int32)
    # int32 overflow: -1094967296 and NaN
    np.testing.assert_allclose(float(uwb.squared_range(p, l)), 3.2e9, rtol=1e-15)
    np.testing.assert_allclose(float(uwb.plain_range(p, l)), 40000 * math.sqrt(2), rtol=1e-15)
    np.testing.assert_allclose(np.asarray(uwb.ranges_to([0.0, 0.0], [[3.0, 4.0], [6.0, 8.0]])), [5.0, 10.0])


@pytest.mark.parametrize("call, needle", [
    (lambda: uwb.measurement_variance(2.0, -0.04, "range"), "^range_var: must be >= 0"),
    (lambda: uwb.measurement_variance(2.0, float("nan"), "range"), "^range_var: must be >= 0"),
    (lambda: uwb.plain_range(jnp.zeros(2) + 1j, jnp.ones(2)), "^p: expected a real array"),
    (lambda: uwb.valid_ranges(jnp.array([1.0 + 1j])), "^z: expected a real array"),
], ids=["neg-var", "nan-var", "complex-p", "complex-z"])
def test_uwb_bad_values(call, needle):
    with pytest.raises(InputError, match=needle):
        call()


# ---------------------------------------------------------------------------
# 2D laser
# ---------------------------------------------------------------------------

ROOM = laser2d.walls_from_polygon([[-2.0, -2.0], [2.0, -2.0], [2.0, 2.0], [-2.0, 2.0]])


def test_laser_range_sigma_of_integer_ranges():
    s = laser2d.range_sigma(jnp.array([0, 1, 2]), laser2d.URG04LX)  # sigma_near was cast to int: 0
    np.testing.assert_allclose(np.asarray(s), [0.01, 0.01, 0.02], rtol=1e-15)


def test_laser_cast_without_walls_returns_nothing():
    spec = laser2d.URG04LX
    r, v, w = laser2d.cast(jnp.zeros(3), jnp.zeros((0, 2, 2)), jnp.zeros(0, bool), spec)  # argmin of empty
    assert r.shape == (spec.n_beams,) and bool(jnp.all(jnp.isnan(r)))
    assert not bool(jnp.any(v)) and bool(jnp.all(w == -1)) and w.dtype == jnp.int32
    r, v, w = laser2d.scan(KEY, jnp.zeros(3), jnp.zeros((0, 2, 2)), jnp.zeros(0, bool), spec,
                           tilt=jnp.array([0.1, 0.0]), outlier_prob=0.2)
    assert not bool(jnp.any(v)) and bool(jnp.all(jnp.isnan(r))) and bool(jnp.all(w == -1))


@pytest.mark.parametrize("call, needle", [
    (lambda: laser2d.cast(jnp.zeros(3), ROOM, jnp.full(4, 0.1), laser2d.URG04LX), "^wall_mask: expected a bool mask"),
    (lambda: laser2d.cast(jnp.zeros(3), ROOM, jnp.full(4, np.nan), laser2d.URG04LX), "^wall_mask: expected a bool mask"),
    (lambda: laser2d.cast(jnp.array([1j, 0, 0]), ROOM, jnp.ones(4, bool), laser2d.URG04LX), "^pose: expected a real array"),
    (lambda: laser2d.cast(jnp.zeros(3), ROOM + 0j, jnp.ones(4, bool), laser2d.URG04LX), "^walls: expected a real array"),
    (lambda: laser2d.range_sigma(jnp.array([1.0 + 0j]), laser2d.URG04LX), "^ranges: expected a real array"),
], ids=["mask-float", "mask-nan", "pose-complex", "walls-complex", "sigma-complex"])
def test_laser_bad_values(call, needle):
    with pytest.raises(InputError, match=needle):
        call()


# ---------------------------------------------------------------------------
# 2D range-bearing: Jacobian at the landmark
# ---------------------------------------------------------------------------

def test_range_bearing2d_jacobian_is_finite_at_the_landmark():
    s, l = jnp.array([1.0, 2.0, 0.3]), jnp.array([1.0, 2.0])
    Js, Jl = jax.jacfwd(rb2.observe, argnums=(0, 1))(s, l)  # the bearing row was NaN
    np.testing.assert_array_equal(np.asarray(Js), [[0, 0, 0], [0, 0, -1]])
    np.testing.assert_array_equal(np.asarray(Jl), np.zeros((2, 2)))
    np.testing.assert_allclose(np.asarray(rb2.observe(s, l)), [0.0, -0.3], rtol=0, atol=1e-15)
    # away from it: the closed form of the bearing Jacobian
    s, l = jnp.array([1.0, 2.0, 0.3]), jnp.array([4.0, -2.0])
    dx, dy = 3.0, -4.0
    r2 = dx * dx + dy * dy
    z = rb2.observe(s, l)
    np.testing.assert_allclose(np.asarray(z), [5.0, math.atan2(dy, dx) - 0.3], rtol=1e-15)
    Js, _ = jax.jacfwd(rb2.observe, argnums=(0, 1))(s, l)
    np.testing.assert_allclose(np.asarray(Js), [[-dx / 5, -dy / 5, 0], [dy / r2, -dx / r2, -1]], rtol=1e-14)
    with pytest.raises(InputError, match="^l: expected a real array"):
        rb2.observe(s, l + 0j)


# ---------------------------------------------------------------------------
# 3D LiDAR / range-bearing: lists, specs, float32 extremes
# ---------------------------------------------------------------------------

def test_lidar_and_range_bearing3d_accept_lists():
    s = [0.0] * 9
    want = np.array([0.0, 0.0, 1.0])  # a landmark 1 m ahead on the boresight
    for got in (lidar3d.measure([0, 0, 0], [0, 0, 0], [1, 0, 0]), lidar3d.measure_state(s, [1, 0, 0]),
                lidar3d.measure_state_and_jacobians(s, [1.0, 0, 0])[0], lidar3d.measure_all([0, 0, 0], [0, 0, 0], [[1, 0, 0]])[0][0],
                rb3.measure([0, 0, 0], [1, 0, 0])):
        np.testing.assert_allclose(np.asarray(got), want, atol=1e-15)
    for got in (lidar3d.inverse([0, 0, 0], [0, 0, 0], [0, 0, 1.0]), lidar3d.inverse_state_and_jacobians(s, [0.0, 0, 1])[0],
                rb3.inverse([0, 0, 0], [0, 0, 1.0])):
        np.testing.assert_allclose(np.asarray(got), [1.0, 0.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(np.asarray(lidar3d.innovation([3.0, 0, 1], [-3.0, 0, 1])), [6 - 2 * math.pi, 0, 0],
                               atol=1e-15)
    with pytest.raises(InputError, match=r"^y: expected shape \(\.\.\., 3\)"):
        lidar3d.innovation(jnp.array([3.0, 1.0]), jnp.array([-3.0, 1.0]))
    with pytest.raises(InputError, match="^landmark: expected a real array"):
        lidar3d.measure(jnp.zeros(3), jnp.zeros(3), jnp.array([1.0 + 1j, 0, 0]))


@pytest.mark.parametrize("spec, needle", [
    (rb3.RangeBearingSpec(sigma_az=-1.0), "^spec.sigma_az: expected a finite scalar >= 0"),
    (rb3.RangeBearingSpec(sigma_el=float("nan")), "^spec.sigma_el: expected a finite scalar >= 0"),
    (rb3.RangeBearingSpec(sigma_range="a"), "^spec.sigma_range: expected numbers"),
], ids=["negative", "nan", "string"])
def test_range_bearing3d_noise_validates_its_spec(spec, needle):
    with pytest.raises(InputError, match=needle):
        rb3.measurement_cov(spec)
    with pytest.raises(InputError, match=needle):
        rb3.sample_noise(KEY, spec, (2,))


def test_range_bearing3d_traced_sigma_is_not_checked():
    R = jax.jit(lambda s: rb3.measurement_cov(rb3.RangeBearingSpec(sigma_range=s)))(0.5)
    np.testing.assert_allclose(np.asarray(R)[2, 2], 0.25)


def _sph_oracle(c):
    c = np.asarray(c, np.float64)
    h = math.hypot(c[0], c[1])
    return np.array([math.atan2(c[1], c[0]), math.atan2(c[2], h), math.hypot(h, c[2])])


def _sph_jacobian_oracle(c):
    """Closed-form ∂[α, β, δ]/∂c (float64)."""
    c = np.asarray(c, np.float64)
    h2 = c[0] ** 2 + c[1] ** 2  # float64: no underflow for the cases here
    r2 = h2 + c[2] ** 2
    h = math.sqrt(h2)
    return np.array([[-c[1] / h2, c[0] / h2, 0.0],
                     [-c[0] * c[2] / (h * r2), -c[1] * c[2] / (h * r2), h / r2],
                     c / math.sqrt(r2)])


@pytest.mark.parametrize("c", [[1e20, 0, 0], [3e19, 4e19, 1e19], [1e-25, 2e-25, -3e-25], [0, 1e-25, 0],
                               [0, 0, 1e-25], [3e19, 4e19, 0], [-2e-30, 1e-30, 3e-30], [1e37, -2e37, 1e37]])
def test_spherical_float32_extremes(c):
    """Squares of float32 overflow above ~1.8e19 and underflow below ~1e-19: the range read inf or
    0 and the azimuth 0.  The oracle is float64 on the float32-rounded input."""
    c32 = np.asarray(c, np.float32)
    y = np.asarray(lidar3d.spherical_from_cartesian(jnp.asarray(c32)), np.float64)
    want = _sph_oracle(c32)
    np.testing.assert_allclose(y[2], want[2], rtol=4e-7)
    np.testing.assert_allclose(y[:2], want[:2], rtol=0, atol=4e-7)
    for jac in (jax.jacfwd, jax.jacrev):
        J = np.asarray(jac(lidar3d.spherical_from_cartesian)(jnp.asarray(c32)), np.float64)
        assert np.all(np.isfinite(J))
        np.testing.assert_allclose(J[2], c32.astype(np.float64) / want[2], rtol=0, atol=4e-7)  # ∂δ/∂c = c/δ
        if np.max(np.abs(c32)) < 1e30 and math.hypot(c32[0], c32[1]) > 0:  # partials (~1/δ) representable
            O = _sph_jacobian_oracle(c32)
            scale = np.abs(O).max(axis=1, keepdims=True)
            np.testing.assert_allclose(J / scale, O / scale, rtol=0, atol=1e-6)


def test_spherical_keeps_ordinary_values_and_degenerate_gradients():
    """Ordinary float64 inputs: bit-equal to the plain safe_norm form; at 0 and straight
    above the sensor the guarded partials stay finite (zero for the undefined angle)."""
    c = jnp.asarray(np.random.default_rng(3).normal(size=(64, 3)) * 10.0 ** np.arange(-4, 4, 0.125)[:, None])
    y = lidar3d.spherical_from_cartesian(c)
    h, r = safe_norm(c[:, :2]), safe_norm(c)
    np.testing.assert_array_equal(np.asarray(y[:, 2]), np.asarray(r))
    np.testing.assert_array_equal(np.asarray(y[:, 0]), np.asarray(jnp.arctan2(c[:, 1], c[:, 0])))
    np.testing.assert_array_equal(np.asarray(y[:, 1]), np.asarray(jnp.arctan2(c[:, 2], h)))
    for dt in (jnp.float32, jnp.float64):
        J0 = jax.jacfwd(lidar3d.spherical_from_cartesian)(jnp.zeros(3, dt))
        np.testing.assert_array_equal(np.asarray(J0), np.zeros((3, 3)))
        Jz = jax.jacrev(lidar3d.spherical_from_cartesian)(jnp.array([0.0, 0.0, -2.0], dt))
        np.testing.assert_array_equal(np.asarray(Jz), [[0, 0, 0], [0, 0, 0], [0, 0, -1]])
    assert math.isnan(float(lidar3d.spherical_from_cartesian(jnp.array([np.nan, 1.0, 2.0]))[2]))
    assert float(lidar3d.spherical_from_cartesian(jnp.array([np.inf, 1.0, 2.0]))[2]) == math.inf


def test_spherical_angles_stay_right_where_the_float32_range_overflows():
    """‖c‖ beyond float32's largest number reads inf, but the angles are scale-free: the
    elevation was atan2 of an overflowed horizontal norm (0 against 35.26°)."""
    for c in ([3e38, 3e38, 3e38], [-3e38, 1e38, -2e38]):
        c32 = np.asarray(c, np.float32)
        y = np.asarray(lidar3d.spherical_from_cartesian(jnp.asarray(c32)), np.float64)
        want = _sph_oracle(c32)  # float64: finite
        assert y[2] == math.inf
        np.testing.assert_allclose(y[:2], want[:2], rtol=0, atol=4e-7)
