"""Review tests: IMU argument checks, landmark-map arguments, 2-D range-bearing inputs and the
status-flag helpers (each against a hand-computed / NumPy expectation)."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam import errors
from jaxslam.errors import InputError
from jaxslam.sensors import imu, landmarks
from jaxslam.sensors import range_bearing2d as rb2

KEY = jax.random.PRNGKey(0)
SPEC = imu.ImuSpec(drift_tau=10.0, drift_density=0.1)


# --- imu: dt of the drift model ------------------------------------------------------------

@pytest.mark.parametrize("dt", [True, np.True_, "0.01", math.inf, np.float64("inf")])
def test_drift_transition_refuses_bool_string_and_infinite_dt(dt):
    # True was a 1 s step, "0.01" was parsed, ∞ gave q = NaN
    with pytest.raises(InputError, match="^dt: "):
        imu.drift_transition(SPEC, dt)


def test_drift_transition_closed_form_still_holds():
    a, q = imu.drift_transition(SPEC, 0.5, dtype=jnp.float32)
    x = 0.5 / 10.0
    np.testing.assert_allclose(np.asarray(a), np.full(6, math.exp(-x)), rtol=1e-6)
    np.testing.assert_allclose(np.asarray(q), np.full(6, 0.01 * 10.0 / 2 * (1 - math.exp(-2 * x))), rtol=1e-5)
    assert a.dtype == jnp.float32


def test_bias_drift_step_refuses_bool_dt():
    st = imu.BiasDriftState(jnp.zeros(6), jnp.zeros(6))
    with pytest.raises(InputError, match="^dt: "):
        imu.bias_drift_step(KEY, st, SPEC, True)


# --- imu: ImuSpec / PAPER001 bools ----------------------------------------------------------

@pytest.mark.parametrize("field", ["rate", "accel_noise_density", "bias", "drift_tau"])
def test_check_imu_spec_refuses_bool_fields(field):
    with pytest.raises(InputError, match=f"^spec.{field}: "):
        imu.check_imu_spec(imu.PAPER000_IMU._replace(**{field: True}))


def test_paper001_preset_refuses_bool_bias():
    with pytest.raises(InputError, match="^bias: "):
        imu.PAPER001_IMU(True)
    with pytest.raises(InputError, match="^rate: "):
        imu.PAPER001_IMU(0.005, rate=True)


# --- imu: shape_prefix ----------------------------------------------------------------------

@pytest.mark.parametrize("prefix", [(2.7,), (-1,), 5, ("3",)])
def test_sample_white_noise_refuses_bad_shape_prefix(prefix):
    with pytest.raises(InputError, match="^shape_prefix: "):
        imu.sample_white_noise(KEY, imu.PAPER000_IMU, prefix)


def test_bias_drift_init_refuses_fractional_shape_prefix():
    with pytest.raises(InputError, match="^shape_prefix: "):
        imu.bias_drift_init(KEY, SPEC, shape_prefix=(1.5,))


def test_shape_prefix_numpy_ints_and_zero_still_work():
    v = imu.sample_white_noise(KEY, imu.PAPER000_IMU, (np.int64(3), 2), jnp.float32)
    assert v.shape == (3, 2, 6) and v.dtype == jnp.float32
    assert imu.sample_white_noise(KEY, imu.PAPER000_IMU, [0]).shape == (0, 6)


# --- imu: corrupt with lists ----------------------------------------------------------------

def test_corrupt_adds_python_lists_elementwise():
    ideal = [1.0, 2.0, 3.0, 4.0, 5.0, 6.0]
    st = imu.BiasDriftState([0.5] * 6, [0.25] * 6)
    white = [0.0, 0.0, 0.0, 0.0, 0.0, -1.0]
    out = np.asarray(imu.corrupt(ideal, st, white))
    np.testing.assert_allclose(out, np.array(ideal) + 0.75 + np.array(white))
    assert out.shape == (6,)


# --- landmarks ------------------------------------------------------------------------------

@pytest.mark.parametrize("n", [float("nan"), math.inf, None])
def test_generate_landmarks_bad_n_is_input_error(n):
    with pytest.raises(InputError, match="^n: expected a positive integer"):
        landmarks.generate_landmarks(KEY, n)


def test_generate_landmarks_refuses_string_and_complex_center():
    with pytest.raises(InputError, match="^center: "):
        landmarks.generate_landmarks(KEY, 2, center=("a", "b", "c"))
    with pytest.raises(InputError, match="^center: "):
        landmarks.generate_landmarks(KEY, 2, center=jnp.array([1j, 0.0, 0.0]))


def test_generate_landmarks_refuses_string_interval_and_int_dtype():
    with pytest.raises(InputError, match="^az_range: "):
        landmarks.generate_landmarks(KEY, 2, az_range="12")
    with pytest.raises(InputError, match="^dtype: "):
        landmarks.generate_landmarks(KEY, 2, dtype=jnp.int32)


def test_generate_landmarks_geometry_against_numpy():
    c = np.array([1.0, -2.0, 3.0])
    L = np.asarray(landmarks.generate_landmarks(jax.random.key(4), 300, center=tuple(c), az_range=(0.1, 0.5),
                                                el_range=(0.2, 0.4), range_range=(8.0, 9.0), dtype=jnp.float64))
    d = L - c
    r = np.linalg.norm(d, axis=1)
    el = np.arcsin(d[:, 2] / r)  # positive elevation = +n3 (down)
    az = np.arctan2(d[:, 1], d[:, 0])
    assert 8.0 <= r.min() and r.max() <= 9.0
    assert 0.2 - 1e-12 <= el.min() and el.max() <= 0.4 + 1e-12
    assert 0.1 - 1e-12 <= az.min() and az.max() <= 0.5 + 1e-12


# --- range-bearing 2-D ----------------------------------------------------------------------

def test_range_bearing2d_refuses_strings_and_bools():
    with pytest.raises(InputError, match="^s: "):
        rb2.observe("abc", [1.0, 2.0])
    with pytest.raises(InputError, match="^s: "):
        rb2.observe(jnp.array([True, False, True]), [1.0, 2.0])
    with pytest.raises(InputError, match="^z: "):
        rb2.inverse([0.0, 0.0, 0.0], np.array(["1", "2"]))


def test_range_bearing2d_against_numpy_and_finite_differences():
    s, lm = np.array([0.3, -1.2, 2.9]), np.array([-2.0, 1.5])
    dx, dy = lm - s[:2]
    beta = (math.atan2(dy, dx) - s[2] + math.pi) % (2 * math.pi) - math.pi
    np.testing.assert_allclose(np.asarray(rb2.observe(s, lm)), [math.hypot(dx, dy), beta], atol=1e-12)
    J = np.asarray(jax.jacfwd(rb2.observe)(jnp.asarray(s), jnp.asarray(lm)))
    r2 = dx * dx + dy * dy
    Jexp = np.array([[-dx / math.sqrt(r2), -dy / math.sqrt(r2), 0.0], [dy / r2, -dx / r2, -1.0]])
    np.testing.assert_allclose(J, Jexp, atol=1e-12)
    # float32 keeps working
    assert rb2.observe(jnp.asarray(s, jnp.float32), jnp.asarray(lm, jnp.float32)).dtype == jnp.float32


# --- status helpers -------------------------------------------------------------------------

def test_decode_ors_an_array_of_status_words():
    words = np.array([errors.GATED, errors.NON_FINITE | errors.GATED, errors.NOT_PSD], np.int32)
    assert errors.decode(words) == ["non_finite", "gated", "not_psd"]
    assert errors.decode(jnp.asarray(words).reshape(3, 1)) == ["non_finite", "gated", "not_psd"]
    assert errors.decode(1 << 7) == ["not_converged"]


def test_status_helpers_refuse_float_words_and_accept_empty():
    with pytest.raises(InputError, match="^status: "):
        errors.decode(2.5)  # was truncated to 2 = non_finite
    with pytest.raises(InputError, match="^status: "):
        errors.check(np.array([2.0]))
    errors.check([])  # no runs: nothing set
    assert errors.decode(np.zeros(0, np.int32)) == []


def test_check_names_unknown_bits():
    with pytest.raises(RuntimeError, match=r"^jaxslam status flags set: unknown bits 0x100$"):
        errors.check(1 << 8)
    with pytest.raises(RuntimeError, match=r"^jaxslam status flags set: non_finite, unknown bits 0x200$"):
        errors.check(np.array([errors.NON_FINITE, 1 << 9], np.int32))
    errors.check(np.array([errors.GATED, errors.MASKED_INPUT], np.int32))  # allowed by default


# --- PRNG keys ------------------------------------------------------------------------------

@pytest.mark.parametrize("call", [
    lambda k: imu.sample_white_noise(k, imu.PAPER000_IMU, (2,)),
    lambda k: imu.bias_drift_init(k, SPEC),
    lambda k: imu.bias_drift_step(k, imu.BiasDriftState(jnp.zeros(6), jnp.zeros(6)), SPEC, 0.1),
    lambda k: imu.bias_drift_rollout(k, imu.BiasDriftState(jnp.zeros(6), jnp.zeros(6)), SPEC, 0.1, 3),
    lambda k: landmarks.generate_landmarks(k, 3),
])
def test_int_seed_instead_of_key_is_input_error(call):
    with pytest.raises(InputError, match="^key: expected a PRNG key"):
        call(0)
