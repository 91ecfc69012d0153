"""Tests for jaxslam.sensors.landmarks (paper 000 Table 3; paper 001 Sec. IV-B)."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

from jaxslam.errors import InputError
from jaxslam.sensors import landmarks, lidar3d

DEG = math.pi / 180

# One compile per static configuration; center stays traced.
_GEN = jax.jit(landmarks.generate_landmarks,
               static_argnames=("n", "az_range", "el_range", "range_range", "dtype"))


def spherical_np(d):
    """[az, el, r] of offsets d (N, 3) in NED, el positive below the horizon."""
    return np.column_stack([np.arctan2(d[:, 1], d[:, 0]),
                            np.arctan2(d[:, 2], np.hypot(d[:, 0], d[:, 1])),
                            np.linalg.norm(d, axis=1)])


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_table3_region_and_defaults(dtype):
    center = np.array([1.0, -2.0, -5.0])
    lm = _GEN(jax.random.key(0), center=jnp.asarray(center, dtype), dtype=dtype)
    assert lm.shape == (40, 3) and lm.dtype == dtype
    a = spherical_np(np.asarray(lm, np.float64) - center)
    tol = 1e-4 if dtype == jnp.float32 else 1e-12
    assert np.all(np.abs(a[:, 0]) <= math.pi + tol)
    assert np.all(np.abs(a[:, 1]) <= 50 * DEG + tol)
    assert np.all((a[:, 2] >= 8 - tol) & (a[:, 2] <= 20 + tol))


def test_uniform_in_each_box_and_ned_elevation_sign():
    n = 4000
    az, el, rg = (-0.5, 1.0), (10 * DEG, 40 * DEG), (8.0, 20.0)
    lm = np.asarray(_GEN(jax.random.key(42, impl="rbg"), n, center=jnp.zeros(3),
                         az_range=az, el_range=el, range_range=rg, dtype=jnp.float64))
    a = spherical_np(lm)
    # Positive elevation lies below the horizon: NED z (down) is positive.
    assert np.all(lm[:, 2] > 0)
    for col, (lo, hi) in enumerate((az, el, rg)):
        assert a[:, col].min() >= lo - 1e-12 and a[:, col].max() <= hi + 1e-12
        p = stats.kstest(a[:, col], stats.uniform(loc=lo, scale=hi - lo).cdf).pvalue
        assert p > 1e-3, (col, p)


def test_lidar_at_center_level_reads_back_the_drawn_angles():
    center = np.array([0.0, 0.0, -3.0])
    lm = _GEN(jax.random.key(1), 40, center=jnp.asarray(center), dtype=jnp.float64)
    y, _ = jax.jit(lidar3d.measure_all)(jnp.asarray(center), jnp.zeros(3), lm)
    np.testing.assert_allclose(np.asarray(y), spherical_np(np.asarray(lm) - center), atol=1e-12)


def test_keyed_and_reproducible():
    a = _GEN(jax.random.key(5), 40, center=jnp.zeros(3), dtype=jnp.float64)
    b = _GEN(jax.random.key(5), 40, center=jnp.zeros(3), dtype=jnp.float64)
    c = _GEN(jax.random.key(6), 40, center=jnp.zeros(3), dtype=jnp.float64)
    # The eager (non-jitted) call gives the same set.
    np.testing.assert_allclose(
        np.asarray(landmarks.generate_landmarks(jax.random.key(5), dtype=jnp.float64)),
        np.asarray(a), rtol=0, atol=1e-12)
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert not np.allclose(np.asarray(a), np.asarray(c))


def test_validation():
    k = jax.random.key(0)
    with pytest.raises(InputError, match="n"):
        landmarks.generate_landmarks(k, 0)
    with pytest.raises(InputError, match="el_range"):
        landmarks.generate_landmarks(k, el_range=(-2.0, 0.0))
    with pytest.raises(InputError, match="range_range"):
        landmarks.generate_landmarks(k, range_range=(20.0, 8.0))
    with pytest.raises(InputError, match="center"):
        landmarks.generate_landmarks(k, center=(0.0, 0.0))


def test_pole_landmarks_paper001():
    p = np.asarray(landmarks.pole_landmarks(jnp.float64))
    np.testing.assert_array_equal(p, [[2, 2, -1], [-2, 2, -1], [-2, -2, -1], [2, -2, -1]])
    assert landmarks.pole_landmarks(jnp.float32).dtype == jnp.float32
