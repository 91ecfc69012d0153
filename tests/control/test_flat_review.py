"""Review of the flatness / DF-LQR / planar-trajectory / dynamics helpers: each test compares
with a hand-computed value or checks that bad input is an early InputError naming it."""

import math

import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam.control import dflqr
from jaxslam.control.attitude_pd import PDGains
from jaxslam.control.flatness import body_rates_from_euler_rates, feedforward, inverse_map
from jaxslam.control.trajectories import Circle
from jaxslam.control.trajectories_2d import CirclePath, PolylinePath, RateProfile, planar_state
from jaxslam.dynamics import euler_ned
from jaxslam.dynamics.params import PAPER000, QuadParams
from jaxslam.errors import InputError

_PTS = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 5.0]])
_TIMES = np.array([0.0, 10.0, 20.0])


def test_hover_input_integer_mass_array_is_not_truncated():
    """An integer mass array used to set the dtype: g = 9.81 became 9, m g = 18 instead of 19.62."""
    for mass in (jnp.array(2), np.int64(2)):
        u = euler_ned.hover_input(QuadParams(mass, (1.0, 1.0, 1.0), 9.81))
        assert jnp.issubdtype(u.dtype, jnp.floating)
        np.testing.assert_allclose(np.asarray(u), [2 * 9.81, 0.0, 0.0, 0.0], rtol=1e-12)
    # a float32 array mass still sets the dtype (unchanged behaviour)
    assert euler_ned.hover_input(QuadParams(jnp.float32(1.5), (1.0, 1.0, 1.0))).dtype == jnp.float32


def test_dflqr_validate_pd_names_the_field():
    p = dflqr.paper000_params()
    with pytest.raises(InputError, match=r"params\.pd: expected PDGains"):
        dflqr.validate(p._replace(pd=None))  # was AttributeError: 'NoneType' ... 'kp'
    with pytest.raises(InputError, match=r"params\.pd\.kd"):
        dflqr.validate(p._replace(pd=PDGains(kd=("a", "b", "c"))))  # was a bare ValueError
    assert dflqr.validate(p) is p


def test_body_rates_refuses_wrong_shapes():
    """A (2,) euler_dot read euler_dot[2] clamped to euler_dot[1] with no error."""
    with pytest.raises(InputError, match="euler_dot"):
        body_rates_from_euler_rates(jnp.zeros(3), jnp.array([0.1, 0.2]))
    with pytest.raises(InputError, match="euler"):
        body_rates_from_euler_rates(jnp.zeros(2), jnp.zeros(3))
    # hand value at Λ = 0: ω = Λ̇
    np.testing.assert_allclose(body_rates_from_euler_rates(jnp.zeros(3), jnp.array([0.1, 0.2, 0.3])),
                               [0.1, 0.2, 0.3], atol=1e-15)


def test_inverse_map_scalar_arguments_checked():
    u = jnp.array([0.0, 0.0, -9.81, 0.0])
    with pytest.raises(InputError, match="mass"):
        inverse_map(u, 0.0, "1.56")
    with pytest.raises(InputError, match="psi_d"):
        inverse_map(u, jnp.zeros(2), 1.56)
    f_T, phi, theta, r = inverse_map(u, 0.0, 1.56)  # hover: f_T = m g, level, no yaw rate
    np.testing.assert_allclose([f_T, phi, theta, r], [1.56 * 9.81, 0.0, 0.0, 0.0], atol=1e-12)


def test_feedforward_string_time_is_an_input_error():
    with pytest.raises(InputError, match="t:"):
        feedforward(Circle(), "1.0", PAPER000)  # was TypeError: data type '.0' not understood


@pytest.mark.parametrize("kw,field", [
    (dict(times=np.array([10.0, 0.0, 20.0])), "PolylinePath.times"),
    (dict(times=np.zeros(0), points=np.zeros((0, 2))), "PolylinePath.times"),
    (dict(points=np.zeros((2, 2))), "PolylinePath.points"),
    (dict(wiggle_period=0.0), "PolylinePath.wiggle_period"),
    (dict(wiggle_amp=float("nan")), "PolylinePath.wiggle_amp"),
])
def test_polyline_bad_fields_name_the_field(kw, field):
    """Unsorted times were interpolated silently wrong; wiggle_period = 0 gave NaN at t = 0 even
    with wiggle_amp = 0; mismatched shapes raised bare NumPy/JAX errors."""
    path = PolylinePath(**{"times": _TIMES, "points": _PTS, **kw})
    with pytest.raises(InputError, match=field):
        path.position(jnp.asarray(0.0))


def test_polyline_integer_time_and_dtypes():
    path = PolylinePath(times=_TIMES, points=_PTS)
    np.testing.assert_allclose(path.position(5), [5.0, 0.0])  # int t failed inside jax.jvp
    np.testing.assert_allclose(path.position(15), [10.0, 2.5])
    assert path.position(jnp.float32(5.0)).dtype == jnp.float32
    s = planar_state(path, RateProfile(np.zeros(1), np.zeros(1), np.zeros((1, 3)), np.zeros(3),
                                       np.zeros(3)), 15.0)
    np.testing.assert_allclose(s[:4], [10.0, 2.5, 0.0, 0.5], atol=1e-12)


def test_rate_profile_integer_time_not_truncated():
    """An integer t cast every rate to int: 0.5 rad/s read 0, and the angles 0."""
    prof = RateProfile(np.array([0.0]), np.array([10.0]), np.array([[0.5, 0.0, 0.25]]),
                       np.array([0.0, 0.1, 0.0]), np.array([0.0, 0.2, 0.0]))
    np.testing.assert_allclose(prof.rates(5), [0.5, 0.1 * math.sin(1.0), 0.25], rtol=1e-12)
    np.testing.assert_allclose(prof.angles(5), [2.5, 0.1 * (1 - math.cos(1.0)) / 0.2, 1.25],
                               rtol=1e-12)
    assert prof.rates(jnp.float32(5.0)).dtype == jnp.float32


def test_rate_profile_bad_fields_name_the_field():
    ok = dict(t0=np.array([3.0]), t1=np.array([5.0]), r=np.array([[1.0, 0, 0]]),
              sin_amp=np.zeros(3), sin_omega=np.zeros(3))
    with pytest.raises(InputError, match="RateProfile.t1"):  # angles were −2 rad for zero rates
        RateProfile(**{**ok, "t1": np.array([1.0])}).angles(jnp.asarray(5.0))
    with pytest.raises(InputError, match="RateProfile.r"):
        RateProfile(**{**ok, "r": np.array([1.0, 0, 0])}).rates(jnp.asarray(5.0))
    with pytest.raises(InputError, match="RateProfile.sin_omega"):
        RateProfile(**{**ok, "sin_omega": np.array([0.0, np.inf, 0.0])}).rates(jnp.asarray(5.0))
    np.testing.assert_allclose(RateProfile(**ok).angles(jnp.asarray(4.0)), [1.0, 0.0, 0.0])


def test_circle_path_rates_integer_time():
    np.testing.assert_allclose(CirclePath().rates(3), [0.0, 0.0, 0.2 * math.sin(0.3)], rtol=1e-12)


def test_specific_force_batched_rotor_speeds():
    """mixer takes (..., 4); specific_force took [0] of the batch for the thrust and crashed."""
    from jaxslam.dynamics import rotor
    from jaxslam.dynamics.params import PAPER001

    W = np.array([[400.0, 450.0, 500.0, 520.0], [300.0, 300.0, 300.0, 300.0]])
    want = np.zeros((2, 3))
    want[:, 2] = 1.5e-5 * np.sum(W ** 2, axis=1) / 1.477  # k_thrust Σω² / m
    np.testing.assert_allclose(rotor.specific_force(W, PAPER001), want, rtol=1e-12)
    np.testing.assert_allclose(rotor.specific_force(W[1], PAPER001), want[1], rtol=1e-12)
    assert rotor.specific_force(W, PAPER001, jnp.float32).dtype == jnp.float32


def test_gain_integer_dtype_is_named():
    """int32 truncated Q̃ = 0.01 to 0 and R̃ to 0: the error blamed R, not the dtype."""
    with pytest.raises(InputError, match="dtype: expected a floating dtype"):
        dflqr.gain(dflqr.paper000_params(), jnp.int32)


def test_control_ref_checks_reference_shapes():
    p = dflqr.paper000_params()
    K = np.zeros((4, 7))
    bad = dflqr.Reference(jnp.zeros(6), jnp.zeros(4), jnp.zeros(3), jnp.zeros(3))
    with pytest.raises(InputError, match=r"ref\.r_d"):
        dflqr.control_ref(jnp.zeros(12), bad, K, p)
    # K = 0, x = r_d = 0, u_d = -g n̂3: hover thrust m g, level attitude, zero torque
    ok = dflqr.Reference(jnp.zeros(7), jnp.array([0.0, 0.0, -9.81, 0.0]), jnp.zeros(3), jnp.zeros(3))
    u, _ = dflqr.control_ref(jnp.zeros(12), ok, K, p)
    np.testing.assert_allclose(u, [1.56 * 9.81, 0.0, 0.0, 0.0], atol=1e-12)


def test_rotor_model_refuses_paper000_params():
    """A QuadParams (no rotor data) raised a bare AttributeError deep inside the mixer."""
    from jaxslam.dynamics import rotor
    from jaxslam.dynamics.params import PAPER001

    w = jnp.full((4,), 300.0)
    for call in (lambda p: rotor.mixer(w, p), lambda p: rotor.f(jnp.zeros(12), w, p),
                 lambda p: rotor.rotor_speeds_from_input(jnp.ones(4), p),
                 lambda p: rotor.mixer_matrix(p)):
        with pytest.raises(InputError, match="params: expected RotorQuadParams"):
            call(PAPER000)
    # hand value: u1 = 4 k ω² with k = 1.5e-5
    np.testing.assert_allclose(rotor.mixer(w, PAPER001), [4 * 1.5e-5 * 9e4, 0, 0, 0], atol=1e-15)
