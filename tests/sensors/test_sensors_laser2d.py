"""Tests for jaxslam.sensors.laser2d (paper 004 Table 5.1; ray casting, tilt, ground projection).

Speed: a few jitted wrappers shared by the module (static spec closed over).
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam.errors import InputError
from jaxslam.sensors import laser2d as L

SPEC = L.URG04LX
ROOM = L.walls_from_polygon([[0.0, 0.0], [4.0, 0.0], [4.0, 3.0], [0.0, 3.0]])
MASK = np.ones(4, bool)

_CAST = jax.jit(lambda pose, walls, mask: L.cast(pose, walls, mask, SPEC))
_CAST_TILT = jax.jit(lambda pose, walls, mask, tilt: L.cast(pose, walls, mask, SPEC, tilt))
_POINTS_TILT = jax.jit(lambda r, v, tilt: L.scan_points(r, v, SPEC, tilt))
_SCAN = jax.jit(lambda k, pose, walls, mask, q: L.scan(k, pose, walls, mask, SPEC, outlier_prob=q))
_SCAN_V = jax.jit(jax.vmap(lambda k, pose, walls, mask, q: L.scan(k, pose, walls, mask, SPEC, outlier_prob=q),
                           in_axes=(0, None, None, None, None)))


def test_urg04lx_preset_matches_table_5_1():
    step = 2 * math.pi / 1024
    assert SPEC.n_beams == 682 and SPEC.angle_step == pytest.approx(step, abs=1e-15)
    assert math.degrees(SPEC.angle_step) == pytest.approx(0.3516, abs=1e-4)
    assert math.degrees(SPEC.n_beams * SPEC.angle_step) == pytest.approx(239.8, abs=0.05)
    assert (SPEC.range_min, SPEC.range_max) == (0.02, 4.0)
    # ±30 mm ≤ 1 m and ±3 % beyond read as 3σ.
    s = np.asarray(L.range_sigma(jnp.array([0.5, 1.0, 2.0, 4.0]), SPEC))
    np.testing.assert_allclose(s, [0.01, 0.01, 0.02, 0.04], rtol=1e-12)


def test_beam_geometry_symmetric_and_dtype():
    a = np.asarray(L.beam_angles(SPEC, jnp.float64))
    assert a.shape == (682,)
    np.testing.assert_allclose(a[0], -a[-1], atol=1e-14)
    np.testing.assert_allclose(np.diff(a), SPEC.angle_step, atol=1e-13)
    assert L.beam_angles(SPEC, jnp.float32).dtype == jnp.float32


def test_cast_matches_closed_form_for_a_room():
    pose = np.array([1.0, 1.2, 0.3])
    r, v, w = map(np.asarray, _CAST(jnp.asarray(pose), jnp.asarray(ROOM), jnp.asarray(MASK)))
    a = np.asarray(L.beam_angles(SPEC, jnp.float64)) + pose[2]
    c, s = np.cos(a), np.sin(a)
    with np.errstate(divide="ignore", invalid="ignore"):
        cand = np.stack([np.where(s < 0, -pose[1] / s, np.inf),           # y = 0
                         np.where(c > 0, (4 - pose[0]) / c, np.inf),      # x = 4
                         np.where(s > 0, (3 - pose[1]) / s, np.inf),      # y = 3
                         np.where(c < 0, -pose[0] / c, np.inf)], 1)       # x = 0
    expect = cand.min(1)
    ok = expect <= SPEC.range_max
    np.testing.assert_array_equal(v, ok)
    np.testing.assert_allclose(r[ok], expect[ok], rtol=1e-12)
    np.testing.assert_array_equal(w[ok], cand.argmin(1)[ok])
    assert np.all(np.isnan(r[~ok])) and np.all(w[~ok] == -1)


def test_validity_at_range_limits_and_masked_walls():
    wall = np.array([[[2.0, -10.0], [2.0, 10.0]]])
    for x, expect in ((2.0 - 3.99, True), (2.0 - 4.01, False), (2.0 - 0.021, True), (2.0 - 0.019, False)):
        r, v, _ = _CAST(jnp.array([x, 0.0, 0.0]), jnp.asarray(wall), jnp.ones(1, bool))
        assert bool(v[341]) is expect  # the centre beams look along +x
    r, v, w = _CAST(jnp.array([1.0, 0.0, 0.0]), jnp.asarray(wall), jnp.zeros(1, bool))
    assert not np.any(np.asarray(v)) and np.all(np.asarray(w) == -1)


def test_tilt_projection_puts_points_on_walls():
    pose = jnp.array([1.5, 1.4, -0.7])
    tilt = jnp.array([0.15, -0.2])
    r, v, w = map(np.asarray, _CAST_TILT(pose, jnp.asarray(ROOM), jnp.asarray(MASK), tilt))
    r0, _, _ = _CAST(pose, jnp.asarray(ROOM), jnp.asarray(MASK))
    assert v.sum() > 300
    assert np.nanmax(r) > 0 and np.nanmean(r[v] - np.asarray(r0)[v]) > 0  # slant ranges are longer
    p, m = map(np.asarray, _POINTS_TILT(jnp.asarray(r), jnp.asarray(v), tilt))
    c, s = np.cos(-0.7), np.sin(-0.7)
    world = p @ np.array([[c, s], [-s, c]]) + np.array([1.5, 1.4])
    coord = np.where(np.isin(w, [0, 2]), world[:, 1], world[:, 0])
    target = np.choose(np.maximum(w, 0), [0.0, 4.0, 3.0, 0.0])
    np.testing.assert_allclose(coord[m], target[m], atol=1e-10)
    # Level tilt reproduces the untilted scan.
    r1, _, _ = _CAST_TILT(pose, jnp.asarray(ROOM), jnp.asarray(MASK), jnp.zeros(2))
    np.testing.assert_allclose(np.asarray(r1), np.asarray(r0), rtol=1e-12, equal_nan=True)


def test_noise_statistics_and_outliers():
    wall = np.array([[[2.0, -10.0], [2.0, 10.0]], [[-3.0, -10.0], [-3.0, 10.0]]])
    keys = jax.random.split(jax.random.PRNGKey(0), 400)
    r, v, w = map(np.asarray, _SCAN_V(keys, jnp.array([0.0, 0.0, 0.0]), jnp.asarray(wall), jnp.ones(2, bool), 0.0))
    r0, v0, _ = map(np.asarray, _CAST(jnp.array([0.0, 0.0, 0.0]), jnp.asarray(wall), jnp.ones(2, bool)))
    z = (r - r0) / np.asarray(L.range_sigma(jnp.asarray(np.where(v0, r0, 1.0)), SPEC))
    z = z[:, v0 & (np.nan_to_num(r0) < 3.5)]  # away from range_max, where noise can invalidate
    assert abs(z.mean()) < 0.02 and abs(z.std() - 1.0) < 0.02
    r, v, w = map(np.asarray, _SCAN_V(keys, jnp.array([0.0, 0.0, 0.0]), jnp.asarray(wall), jnp.ones(2, bool), 0.3))
    out = v & (w == -1)
    assert abs(out.sum() / v.sum() - 0.3) < 0.01
    assert np.all(r[out] <= np.broadcast_to(r0, r.shape)[out] + 1e-12) and np.all(r[out] >= SPEC.range_min)


def test_check_scan():
    with pytest.raises(InputError, match="expected 682 ranges.*got 681"):
        L.check_scan(np.ones(681), SPEC)
    with pytest.raises(InputError, match="numbers"):
        L.check_scan(np.array(["a"] * 682), SPEC)
    r = np.full(682, 1.0)
    r[:3] = [np.nan, 0.0, 5.0]
    m = L.check_scan(r, SPEC)
    assert m.dtype == bool and m.sum() == 679 and not m[:3].any()


def test_walls_from_polygon_validation():
    assert L.walls_from_polygon([[0, 0], [1, 0], [1, 1]]).shape == (3, 2, 2)
    assert L.walls_from_polygon([[0, 0], [1, 0], [1, 1]], closed=False).shape == (2, 2, 2)
    with pytest.raises(InputError):
        L.walls_from_polygon([[0, 0], [1, 0]])
    with pytest.raises(InputError, match="zero-length"):
        L.walls_from_polygon([[0, 0], [0, 0], [1, 1]])
    with pytest.raises(InputError, match="NaN"):
        L.walls_from_polygon([[0, 0], [np.nan, 0], [1, 1]])


def test_no_walls_in_view_and_all_invalid_give_clean_masks():
    far = np.array([[[10.0, -1.0], [10.0, 1.0]]])
    r, v, w = _SCAN(jax.random.PRNGKey(1), jnp.array([0.0, 0.0, 0.0]), jnp.asarray(far), jnp.ones(1, bool), 0.3)
    assert not np.any(np.asarray(v)) and np.all(np.asarray(w) == -1)
    p, m = L.scan_points(r, v, SPEC)
    assert not np.any(np.asarray(m)) and np.all(np.asarray(p) == 0.0)


def test_float32_and_vmap_over_poses():
    poses = jnp.asarray([[1.0, 1.0, 0.0], [2.0, 1.5, 1.0], [3.0, 2.0, -2.0]], jnp.float32)
    f = jax.jit(jax.vmap(lambda p: L.cast(p, jnp.asarray(ROOM, jnp.float32), jnp.asarray(MASK), SPEC)))
    r32, v32, w32 = f(poses)
    assert r32.dtype == jnp.float32 and r32.shape == (3, 682)
    for i in range(3):
        r64, v64, w64 = _CAST(jnp.asarray(poses[i], jnp.float64), jnp.asarray(ROOM), jnp.asarray(MASK))
        both = np.asarray(v32[i]) & np.asarray(v64)
        assert both.sum() > 600
        np.testing.assert_allclose(np.asarray(r32[i])[both], np.asarray(r64)[both], rtol=1e-4, atol=1e-5)
