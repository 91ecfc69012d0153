"""Tests for jaxslam.sensors.lidar3d (paper 000 eq. 30-31 per errata, 44-45, Table 4).

Speed: every model call goes through a few jitted, vmapped wrappers used with one batch size
N, so the file compiles a handful of executables instead of hundreds of eager primitives.
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import sensors_oracle_np as ref
from jaxslam.errors import InputError
from jaxslam.sensors import lidar3d
from jaxslam.sensors.lidar3d import PAPER000_LIDAR, LidarSpec

N = 40
RNG = np.random.default_rng(20240501)

_MEAS = jax.jit(jax.vmap(lidar3d.measure))
_INV = jax.jit(jax.vmap(lidar3d.inverse))
_JAC_H = jax.jit(jax.vmap(jax.jacfwd(lidar3d.measure_state, argnums=(0, 1))))
_JAC_G = jax.jit(jax.vmap(jax.jacfwd(lidar3d.inverse_state, argnums=(0, 1))))
_MEAS_ALL = jax.jit(lidar3d.measure_all, static_argnums=3)
_IN_FOV = jax.jit(lidar3d.in_fov, static_argnums=1)


def random_pose(rng, n=N):
    pos = rng.uniform(-20, 20, (n, 3))
    euler = np.column_stack([rng.uniform(-1.2, 1.2, n), rng.uniform(-1.2, 1.2, n),
                             rng.uniform(-3.1, 3.1, n)])
    return pos, euler


def random_points(rng, n=N):
    pos, euler = random_pose(rng, n)
    return pos, euler, pos + rng.uniform(-30, 30, (n, 3))


def j(*arrays, dtype=jnp.float64):
    return tuple(jnp.asarray(a, dtype) for a in arrays)


def test_spec_is_table4_in_si_units():
    s = PAPER000_LIDAR
    assert s.az_min == pytest.approx(-45 * math.pi / 180, abs=1e-15)
    assert s.az_max == pytest.approx(45 * math.pi / 180, abs=1e-15)
    assert s.el_min == pytest.approx(-30 * math.pi / 180, abs=1e-15)
    assert s.el_max == pytest.approx(30 * math.pi / 180, abs=1e-15)
    assert (s.range_min, s.range_max, s.sigma_range, s.rate) == (0.0, 100.0, 0.1, 10.0)
    assert s.sigma_az == pytest.approx(0.33 * math.pi / 180, abs=1e-15)
    assert s.sigma_el == pytest.approx(0.3 * math.pi / 180, abs=1e-15)


def test_measure_matches_numpy_scipy_and_sign_conventions():
    pos, euler, lm = random_points(RNG)
    # Two hand-made cases: level facing north, landmark ahead-right-below (α > 0, β > 0 in
    # NED); yaw +90° (facing east), landmark due east straight ahead.
    pos[:2] = 0.0
    euler[0], euler[1] = 0.0, [0.0, 0.0, math.pi / 2]
    lm[0], lm[1] = [10.0, 10.0, 5.0], [0.0, 7.0, 0.0]
    ys = np.asarray(_MEAS(*j(pos, euler, lm)))
    assert ys[0][0] == pytest.approx(math.pi / 4, abs=1e-15)
    assert ys[0][1] == pytest.approx(math.atan2(5.0, math.hypot(10.0, 10.0)), abs=1e-15)
    assert ys[0][1] > 0 and ys[0][2] == pytest.approx(15.0, abs=1e-13)
    np.testing.assert_allclose(ys[1], [0.0, 0.0, 7.0], atol=1e-12)
    for p, e, l, got in zip(pos, euler, lm, ys):
        np.testing.assert_allclose(got, ref.lidar_measure(p, e, l), rtol=0, atol=1e-12)
        # A second independent rotation: SciPy's intrinsic Z-Y-X = C3(ψ) C2(θ) C1(φ).
        C = Rotation.from_euler("ZYX", [e[2], e[1], e[0]]).as_matrix()
        np.testing.assert_allclose(got, ref.sph(C.T @ (l - p)), rtol=0, atol=1e-10)


def test_measure_state_jacobians_match_hand_derivation():
    # The (12,) state of eq. 2 is passed, so the same call also checks ∂h/∂v = ∂h/∂ω = 0.
    rng = np.random.default_rng(100)
    pos, euler, lm = random_points(rng)
    x = np.column_stack([pos, rng.normal(size=(N, 3)), euler, rng.normal(size=(N, 3))])
    Hx, Hl = (np.asarray(a) for a in _JAC_H(*j(x, lm)))
    assert Hx.shape == (N, 3, 12) and Hl.shape == (N, 3, 3)
    np.testing.assert_array_equal(Hx[:, :, 3:6], 0.0)
    np.testing.assert_array_equal(Hx[:, :, 9:12], 0.0)
    for i in range(N):
        Hs_ref, Hl_ref = ref.lidar_H(x[i, :9], lm[i])
        np.testing.assert_allclose(Hx[i, :, :9], Hs_ref, rtol=0, atol=1e-9)
        np.testing.assert_allclose(Hl[i], Hl_ref, rtol=0, atol=1e-9)
    # The (9,) EKF state of eq. 24 reads the same ρ and Λ.
    y9 = jax.jit(jax.vmap(lidar3d.measure_state))(*j(x[:, :9], lm))
    np.testing.assert_allclose(np.asarray(y9), np.asarray(_MEAS(*j(pos, euler, lm))), atol=1e-13)


def test_inverse_state_jacobians_match_hand_derivation():
    rng = np.random.default_rng(200)
    pos, euler = random_pose(rng)
    s = np.column_stack([pos, rng.normal(size=(N, 3)), euler])
    y = np.column_stack([rng.uniform(-math.pi, math.pi, N), rng.uniform(-1.4, 1.4, N),
                         rng.uniform(0.5, 90, N)])
    Gs, Gl = _JAC_G(*j(s, y))
    lm = np.asarray(_INV(*j(pos, euler, y)))
    for i in range(N):
        Gs_ref, Gl_ref = ref.lidar_G(s[i], y[i])
        np.testing.assert_allclose(np.asarray(Gs[i]), Gs_ref, rtol=0, atol=1e-9)
        np.testing.assert_allclose(np.asarray(Gl[i]), Gl_ref, rtol=0, atol=1e-9)
        np.testing.assert_allclose(lm[i], ref.lidar_inverse(pos[i], euler[i], y[i]),
                                   rtol=0, atol=1e-11)


def test_degenerate_points_stay_finite():
    # Row 0: landmark straight below a level sensor (c1 = c2 = 0): the azimuth is undefined,
    # but the range and its gradient must stay right and every entry finite.
    rng = np.random.default_rng(300)
    pos, euler, lm = random_points(rng)
    x = np.column_stack([pos, np.zeros((N, 3)), euler, np.zeros((N, 3))])
    x[0, :] = 0.0
    lm[0] = [0.0, 0.0, 5.0]
    y = np.asarray(_MEAS(*j(x[:, :3], x[:, 6:9], lm)))
    Hx, Hl = (np.asarray(a) for a in _JAC_H(*j(x, lm)))
    np.testing.assert_allclose(y[0], [0.0, math.pi / 2, 5.0], atol=1e-15)
    assert np.all(np.isfinite(Hx)) and np.all(np.isfinite(Hl))
    np.testing.assert_allclose(Hl[0, 2], [0.0, 0.0, 1.0], atol=1e-15)
    np.testing.assert_allclose(Hx[0, 2, :3], [0.0, 0.0, -1.0], atol=1e-15)


def test_round_trips():
    pos, euler, lm = random_points(RNG)
    # inverse ∘ measure = identity on landmarks
    back = _INV(*j(pos, euler), _MEAS(*j(pos, euler, lm)))
    np.testing.assert_allclose(np.asarray(back), lm, rtol=0, atol=1e-11)
    # measure ∘ inverse = identity on measurements in the principal domain
    ys = np.column_stack([RNG.uniform(-3.1, 3.1, N), RNG.uniform(-1.5, 1.5, N),
                          RNG.uniform(0.1, 100, N)])
    y2 = _MEAS(*j(pos, euler), _INV(*j(pos, euler, ys)))
    np.testing.assert_allclose(np.asarray(y2), ys, rtol=0, atol=1e-10)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_measure_all_vectorised_visibility_and_dtype(dtype):
    p, e = (a[0] for a in random_pose(RNG, 1))
    lms = p + RNG.uniform(-40, 40, (N, 3))
    y, vis = _MEAS_ALL(*j(p, e, lms, dtype=dtype), PAPER000_LIDAR)
    assert y.shape == (N, 3) and vis.shape == (N,)
    assert y.dtype == dtype and vis.dtype == jnp.bool_
    yr = np.stack([ref.lidar_measure(p, e, l) for l in lms])
    tol = 1e-12 if dtype == jnp.float64 else 2e-4
    np.testing.assert_allclose(np.asarray(y, np.float64), yr, rtol=tol, atol=tol)
    vr = ((yr[:, 0] >= -math.pi / 4) & (yr[:, 0] <= math.pi / 4)
          & (yr[:, 1] >= -math.pi / 6) & (yr[:, 1] <= math.pi / 6) & (yr[:, 2] <= 100))
    assert vr.any() and (~vr).any()
    np.testing.assert_array_equal(np.asarray(vis), vr)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_fov_boundaries_inclusive_in_measurement_space(dtype):
    s = PAPER000_LIDAR
    inf = np.array(np.inf, dtype)
    tiny = np.finfo(dtype).tiny

    def step(v, direction):
        # One ulp outwards/inwards, but never into subnormals (XLA on CPU flushes them to 0).
        w = np.nextafter(dtype(v), direction)
        return w if abs(w) >= tiny or w == 0 else dtype(np.sign(w) * tiny)

    cases = []
    for col, lo, hi in ((0, s.az_min, s.az_max), (1, s.el_min, s.el_max),
                        (2, s.range_min, s.range_max)):
        lo, hi = dtype(lo), dtype(hi)
        for v, inside in ((lo, True), (hi, True), (step(lo, inf), True), (step(hi, -inf), True),
                          (step(lo, -inf), False), (step(hi, inf), False)):
            yy = np.array([0.0, 0.0, 50.0], dtype)
            yy[col] = v
            cases.append((yy, inside))
    ys = np.stack([c[0] for c in cases]).reshape(3, 6, 3)  # batched leading shape
    got = np.asarray(_IN_FOV(jnp.asarray(ys), s))
    assert got.shape == (3, 6)
    np.testing.assert_array_equal(got.ravel(), [c[1] for c in cases])


def test_fov_geometry_just_inside_and_outside():
    pos = np.array([3.0, -2.0, -10.0])
    euler = np.array([0.05, -0.1, 2.0])
    eps = 1e-7
    ys = []
    want = []
    for col, bound in ((0, math.pi / 4), (0, -math.pi / 4), (1, math.pi / 6), (1, -math.pi / 6),
                       (2, 100.0)):
        for sgn, inside in ((-1, True), (1, False)):
            yy = np.array([0.1, -0.1, 30.0])
            yy[col] = bound + sgn * eps * math.copysign(1, bound)
            ys.append(yy)
            want.append(inside)
    ys = np.array(ys + [ys[0]] * (N - len(ys)))  # pad to the shared batch size
    want = np.array(want + [want[0]] * (N - len(want)))
    lms = np.stack([ref.lidar_inverse(pos, euler, yy) for yy in ys])
    _, vis = _MEAS_ALL(*j(pos, euler, lms), PAPER000_LIDAR)
    np.testing.assert_array_equal(np.asarray(vis), want)


def test_innovation_wraps_azimuth_only():
    r = np.asarray(lidar3d.innovation(jnp.array([3.1, 0.2, 10.0]), jnp.array([-3.1, 0.1, 9.0])))
    np.testing.assert_allclose(r, [6.2 - 2 * math.pi, 0.1, 1.0], atol=1e-12)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_sample_noise_sigma_and_cov(dtype):
    n = 100_000
    # rbg keys compile faster here; the library is key-implementation agnostic.
    z = lidar3d.sample_noise(jax.random.key(7, impl="rbg"), PAPER000_LIDAR, (n,), dtype)
    assert z.shape == (n, 3) and z.dtype == dtype
    want = np.array([0.33 * math.pi / 180, 0.3 * math.pi / 180, 0.1])
    z = np.asarray(z, np.float64)
    np.testing.assert_allclose(z.std(axis=0), want, rtol=0.02)
    assert np.all(np.abs(z.mean(axis=0)) <= 5 * want / math.sqrt(n))
    R = np.asarray(lidar3d.measurement_cov(PAPER000_LIDAR, dtype))
    assert R.dtype == dtype
    np.testing.assert_allclose(R, np.diag(want ** 2), rtol=1e-6)
    # default threefry keys and a scalar prefix work too
    assert lidar3d.sample_noise(jax.random.key(0), PAPER000_LIDAR, (), dtype).shape == (3,)


def test_float32_in_float32_out_and_close_to_float64():
    pos, euler, lm = random_points(RNG)
    s = np.column_stack([pos, np.zeros((N, 3)), euler, np.zeros((N, 3))])
    y32 = _MEAS(*j(pos, euler, lm, dtype=jnp.float32))
    l32 = _INV(*j(pos, euler, dtype=jnp.float32), y32)
    Hs, Hl = _JAC_H(*j(s, lm, dtype=jnp.float32))
    assert y32.dtype == l32.dtype == Hs.dtype == Hl.dtype == jnp.float32
    for i in range(N):
        np.testing.assert_allclose(np.asarray(y32[i], np.float64),
                                   ref.lidar_measure(pos[i], euler[i], lm[i]), rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(np.asarray(l32[i], np.float64), lm[i], rtol=1e-5, atol=1e-4)
        np.testing.assert_allclose(np.asarray(Hs[i, :, :9], np.float64),
                                   ref.lidar_H(s[i, :9], lm[i])[0], rtol=1e-3, atol=1e-4)


def test_shape_validation():
    z3 = np.zeros(3)
    with pytest.raises(InputError, match="pos"):
        lidar3d.measure(np.zeros(2), z3, z3)
    with pytest.raises(InputError, match="euler"):
        lidar3d.measure(z3, np.zeros(4), z3)
    with pytest.raises(InputError, match="landmark"):
        lidar3d.measure(z3, z3, np.zeros((2, 2)))
    with pytest.raises(InputError, match="s:"):
        lidar3d.measure_state(np.zeros(8), z3)
    with pytest.raises(InputError, match="y"):
        lidar3d.inverse_state(np.zeros(9), np.zeros(2))
    with pytest.raises(InputError, match="landmarks"):
        lidar3d.measure_all(z3, z3, z3)
    with pytest.raises(InputError, match="y"):
        lidar3d.in_fov(np.zeros(4))


def test_check_lidar_spec():
    assert lidar3d.check_lidar_spec(PAPER000_LIDAR) is PAPER000_LIDAR
    with pytest.raises(InputError, match="az_min"):
        lidar3d.check_lidar_spec(LidarSpec(az_min=1.0, az_max=0.5))
    with pytest.raises(InputError, match="sigma_range"):
        lidar3d.check_lidar_spec(LidarSpec(sigma_range=-0.1))
    with pytest.raises(InputError, match="rate"):
        lidar3d.check_lidar_spec(LidarSpec(rate=0.0))
    with pytest.raises(InputError, match="range_max"):
        lidar3d.check_lidar_spec(LidarSpec(range_max=float("nan")))
    with pytest.raises(InputError, match="spec"):
        lidar3d.check_lidar_spec((1, 2, 3))


# Closed-form H (eq. 40) and G_s, G_y (eq. 49) against the hand-derived NumPy twin and autodiff
import numpy_ekfslam3d as np3d  # noqa: E402


def _states(n, seed):
    rng = np.random.default_rng(seed)
    return [(rng.normal(size=9) * np.array([3, 3, 3, 1, 1, 1, 0.5, 0.5, 3]), rng.normal(size=3) * 10)
            for _ in range(n)]


def test_measure_state_and_jacobians_match_twin_and_autodiff():
    W = jnp.asarray(np.random.default_rng(1).normal(size=(3, 9)))
    # Each function jitted once (eager op-by-op dispatch, second derivatives included, compiled
    # hundreds of one-operation programs)
    closed = jax.jit(lidar3d.measure_state_and_jacobians)
    value = jax.jit(lidar3d.measure_state)
    auto = jax.jit(jax.jacfwd(lidar3d.measure_state, argnums=(0, 1)))
    # second derivatives, as a gradient through the filter takes them
    d_closed = jax.jit(jax.grad(lambda x, l: jnp.sum(W * lidar3d.measure_state_and_jacobians(x, l)[1])))
    d_auto = jax.jit(jax.grad(lambda x, l: jnp.sum(W * jax.jacfwd(lidar3d.measure_state)(x, l))))
    for s, l in _states(5, 0):
        sj, lj = jnp.asarray(s), jnp.asarray(l)
        y, Hs, Hl = closed(sj, lj)
        np.testing.assert_array_equal(np.asarray(y), np.asarray(value(sj, lj)))
        yo, Hso, Hlo = np3d.observe(s, l[None])
        np.testing.assert_allclose(np.asarray(Hs), Hso[0], rtol=1e-11, atol=1e-13)
        np.testing.assert_allclose(np.asarray(Hl), Hlo[0], rtol=1e-11, atol=1e-13)
        Hs0, Hl0 = auto(sj, lj)
        np.testing.assert_allclose(np.asarray(Hs), np.asarray(Hs0), rtol=1e-11, atol=1e-13)
        g1, g0 = d_closed(sj, lj), d_auto(sj, lj)
        np.testing.assert_allclose(np.asarray(g1), np.asarray(g0), rtol=1e-10, atol=1e-12)
    # (12,) states: ω does not enter
    s12 = jnp.concatenate([jnp.asarray(s), jnp.ones(3)])
    _, H12, _ = closed(s12, jnp.asarray(l))
    np.testing.assert_allclose(np.asarray(H12), np.asarray(auto(s12, jnp.asarray(l))[0]),
                               rtol=1e-11, atol=1e-13)


def test_measurement_jacobians_where_angles_are_undefined():
    # landmark at the sensor (r = 0) and straight above it (h = 0): rows of undefined angles are
    # zero, as autodiff of the guarded model gives, never NaN (also in their derivatives)
    s = jnp.zeros(9)
    closed = jax.jit(lidar3d.measure_state_and_jacobians)  # jitted once: one program, not one per operation
    auto = jax.jit(jax.jacfwd(lidar3d.measure_state, argnums=(0, 1)))
    grad = jax.jit(jax.grad(lambda x, l: jnp.sum(lidar3d.measure_state_and_jacobians(x, l)[1])))
    for l in (jnp.zeros(3), jnp.asarray([0.0, 0.0, 2.0])):
        y, Hs, Hl = closed(s, l)
        Hs0, Hl0 = auto(s, l)
        np.testing.assert_allclose(np.asarray(Hs), np.asarray(Hs0), atol=1e-15)
        np.testing.assert_allclose(np.asarray(Hl), np.asarray(Hl0), atol=1e-15)
        g = grad(s, l)
        assert np.all(np.isfinite(np.asarray(g)))


def test_inverse_state_and_jacobians_match_twin_and_autodiff():
    rng = np.random.default_rng(4)
    closed = jax.jit(lidar3d.inverse_state_and_jacobians)  # jitted once: one program, not one per operation
    value = jax.jit(lidar3d.inverse_state)
    auto = jax.jit(jax.jacfwd(lidar3d.inverse_state, argnums=(0, 1)))
    for s, _ in _states(4, 2):
        y = rng.normal(size=3) * np.array([1.0, 0.4, 8.0])
        sj, yj = jnp.asarray(s), jnp.asarray(y)
        l, Gs, Gy = closed(sj, yj)
        np.testing.assert_array_equal(np.asarray(l), np.asarray(value(sj, yj)))
        lo, Gso, Gyo = np3d.inverse(s, y)
        np.testing.assert_allclose(np.asarray(Gs), Gso, rtol=1e-11, atol=1e-13)
        np.testing.assert_allclose(np.asarray(Gy), Gyo, rtol=1e-11, atol=1e-13)
        Gs0, Gy0 = auto(sj, yj)
        np.testing.assert_allclose(np.asarray(Gs), np.asarray(Gs0), rtol=1e-11, atol=1e-13)
        np.testing.assert_allclose(np.asarray(Gy), np.asarray(Gy0), rtol=1e-11, atol=1e-13)
    l32, Gs32, Gy32 = closed(jnp.asarray(s, jnp.float32), jnp.asarray(y, jnp.float32))
    assert l32.dtype == Gs32.dtype == Gy32.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(Gy32), Gyo, rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("scale", [1e-20, 1e-18, 1.0, 1e18, 1e20])
def test_closed_form_jacobians_hold_at_any_magnitude_in_float32(scale):
    """The closed-form J was built from the raw squares of c: in float32 at |c| ~ 1e20 the range
    row read [0 0 0], at 1e-20 it read 1e-21 (review 2026-12-07).  J from c scaled by a power of
    two: the range row is the unit vector at every magnitude (oracle: c/|c| in float64), the
    angle rows scale as 1/|c|, and autodiff agrees."""
    s = jnp.zeros(9, jnp.float32)
    c = np.array([0.6, 0.3, -0.2]) * scale
    y, Hs, Hl = lidar3d.measure_state_and_jacobians(s, jnp.asarray(c, jnp.float32))
    np.testing.assert_allclose(np.asarray(Hl[2], np.float64), c / np.linalg.norm(c), rtol=1e-5)
    h2 = c[0] ** 2 + c[1] ** 2
    np.testing.assert_allclose(np.asarray(Hl[0, :2], np.float64) * scale, np.array([-c[1], c[0]]) / h2 * scale,
                               rtol=1e-5)
    Hs0, Hl0 = jax.jacfwd(lidar3d.measure_state, argnums=(0, 1))(s, jnp.asarray(c, jnp.float32))
    np.testing.assert_allclose(np.asarray(Hl) * scale, np.asarray(Hl0) * scale, rtol=1e-5, atol=1e-6)
