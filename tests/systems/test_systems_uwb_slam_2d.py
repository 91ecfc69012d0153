"""Paper 003 models: UWB range rows (eq. 16-18), gyro rows (eq. 19), motion (eq. 12, 15), Q (eq. 27).

Oracles: the hand Jacobians of eq. 18 and of the plain range (∂d/∂p = (p − l)/d),
the F of eq. 15 written out in the paper's state order (eq. 14), closed-form
noise moments, Monte Carlo moments drawn with NumPy.
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam.errors import InputError
from jaxslam.sensors import uwb
from jaxslam.systems import uwb_slam_2d as U

DTYPES = [jnp.float32, jnp.float64]


def _tol(dtype):
    return 1e-5 if dtype == jnp.float32 else 1e-12


@pytest.mark.parametrize("dtype", DTYPES)
def test_squared_range_matches_eq18(dtype):
    rng = np.random.default_rng(0)
    model = U.make_model("squared")
    for _ in range(5):
        s = jnp.asarray(rng.normal(size=10), dtype)
        l = jnp.asarray(rng.normal(size=2) * 3, dtype)
        z = model.observe(s, l, None)
        Hs, Hl = jax.jacfwd(model.observe, argnums=(0, 1))(s, l, None)
        x, y = float(s[0]), float(s[1])
        lx, ly = float(l[0]), float(l[1])
        assert z.dtype == dtype and z.shape == (1,)
        np.testing.assert_allclose(float(z[0]), (lx - x) ** 2 + (ly - y) ** 2, rtol=_tol(dtype))
        Hs_hand = np.zeros(10)
        Hs_hand[0], Hs_hand[1] = 2 * (x - lx), 2 * (y - ly)  # eq. 18, robot part
        Hl_hand = np.array([2 * (lx - x), 2 * (ly - y)])  # eq. 18, landmark part
        np.testing.assert_allclose(np.asarray(Hs[0]), Hs_hand, atol=10 * _tol(dtype))
        np.testing.assert_allclose(np.asarray(Hl[0]), Hl_hand, atol=10 * _tol(dtype))


@pytest.mark.parametrize("dtype", DTYPES)
def test_plain_range_matches_hand_jacobian(dtype):
    rng = np.random.default_rng(1)
    model = U.make_model("range")
    for _ in range(5):
        s = jnp.asarray(rng.normal(size=10), dtype)
        l = jnp.asarray(rng.normal(size=2) * 3 + 1, dtype)
        z = model.observe(s, l, None)
        Hs, Hl = jax.jacfwd(model.observe, argnums=(0, 1))(s, l, None)
        p = np.asarray(s[:2], float)
        ll = np.asarray(l, float)
        d = np.linalg.norm(p - ll)
        np.testing.assert_allclose(float(z[0]), d, rtol=_tol(dtype))
        Hs_hand = np.zeros(10)
        Hs_hand[:2] = (p - ll) / d
        np.testing.assert_allclose(np.asarray(Hs[0]), Hs_hand, atol=10 * _tol(dtype))
        np.testing.assert_allclose(np.asarray(Hl[0]), (ll - p) / d, atol=10 * _tol(dtype))


def test_plain_range_jacobian_at_anchor_is_zero_not_nan():
    model = U.make_model("range")
    s = jnp.zeros(10).at[:2].set(jnp.array([1.0, 2.0]))
    Hs, Hl = jax.jacfwd(model.observe, argnums=(0, 1))(s, jnp.array([1.0, 2.0]), None)
    assert np.all(np.isfinite(Hs)) and np.all(np.isfinite(Hl))
    assert float(model.observe(s, jnp.array([1.0, 2.0]), None)[0]) == 0.0


def test_gyro_rows_select_the_rates():
    gm = U.make_gyro_model()
    s = jnp.arange(10.0)
    z = gm.observe(s, jnp.array([5.0, 5.0]), None)
    np.testing.assert_array_equal(np.asarray(z), [7.0, 8.0, 9.0])
    Hs, Hl = jax.jacfwd(gm.observe, argnums=(0, 1))(s, jnp.zeros(2), None)
    H = np.zeros((3, 10))
    H[0, 7] = H[1, 8] = H[2, 9] = 1.0  # eq. 19: Ω = w
    np.testing.assert_array_equal(np.asarray(Hs), H)
    np.testing.assert_array_equal(np.asarray(Hl), np.zeros((3, 2)))


@pytest.mark.parametrize("dt", [1.0, 0.1])
def test_motion_is_eq15_in_paper_order(dt):
    N = 3
    s = jnp.asarray(np.random.default_rng(2).normal(size=10))
    F_r = np.asarray(jax.jacfwd(lambda x: U.motion(x, None, dt))(s))
    # Full engine-order F (landmarks static), permuted to the order of eq. 14.
    n = 10 + 2 * N
    F = np.eye(n)
    F[:10, :10] = F_r
    perm = U.paper_permutation(N)
    Fp = F[np.ix_(perm, perm)]
    # Eq. 15 written out: x += v_x, y += v_y, α += w_α, β += w_β, θ += w_θ (times Δt).
    F15 = np.eye(n)
    F15[0, 2] = F15[1, 3] = dt
    a = 4 + 2 * N
    for i in range(3):
        F15[a + i, a + 3 + i] = dt
    np.testing.assert_allclose(Fp, F15, atol=1e-15)
    np.testing.assert_allclose(np.asarray(U.motion(s, None, dt)), F_r @ np.asarray(s), atol=1e-14)


def test_paper_permutation_roundtrip():
    perm = U.paper_permutation(2)
    np.testing.assert_array_equal(perm, [0, 1, 2, 3, 10, 11, 12, 13, 4, 5, 6, 7, 8, 9])
    x = jnp.arange(14.0)
    P = jnp.diag(x)
    xp, Pp = U.to_paper_order(x, P, 2)
    np.testing.assert_array_equal(np.asarray(xp), perm.astype(float))
    np.testing.assert_array_equal(np.diag(np.asarray(Pp)), perm.astype(float))


def test_paper_Q_is_eq27():
    Q = np.asarray(U.paper_process_noise(1.0))
    eq27 = [0.01, 0.01, 0.1, 0.1] + [0.0] * 6 + [math.pi / 15] * 3 + [1.0] * 3  # 3 landmarks
    perm = U.paper_permutation(3)
    Qfull = np.zeros((16, 16))
    Qfull[:10, :10] = Q
    np.testing.assert_allclose(np.diag(Qfull[np.ix_(perm, perm)]), eq27, atol=1e-15)
    np.testing.assert_allclose(np.asarray(U.paper_process_noise(0.5)), 0.5 * Q, atol=1e-15)


def test_ncv_Q_closed_form():
    dt, qa, qw = 0.5, 2e-3, 3e-4
    Q = np.asarray(U.ncv_process_noise(dt, qa, qw))
    blk = np.array([[dt ** 3 / 3, dt ** 2 / 2], [dt ** 2 / 2, dt]])
    np.testing.assert_allclose(Q[np.ix_([0, 2], [0, 2])], qa * blk, atol=1e-15)
    np.testing.assert_allclose(Q[np.ix_([6, 9], [6, 9])], qw * blk, atol=1e-15)
    assert Q[0, 1] == 0 and Q[0, 3] == 0 and Q[2, 7] == 0
    assert np.all(np.linalg.eigvalsh(Q) > 0)


@pytest.mark.parametrize("dist", ["uniform", "gaussian"])
def test_noise_moments(dist):
    a = 0.2
    x = np.asarray(uwb.sample_noise(jax.random.PRNGKey(0), (200000,), a, dist))
    var = a * a / 3
    assert abs(x.mean()) < 4 * math.sqrt(var / x.size)
    assert abs(x.var() / var - 1) < 0.02
    if dist == "uniform":
        assert np.max(np.abs(x)) <= a
        assert np.max(np.abs(x)) > 0.99 * a


def test_noise_follows_dtype_and_rejects_unknown():
    x = uwb.sample_noise(jax.random.PRNGKey(1), (3,), 0.2, "uniform", jnp.float32)
    assert x.dtype == jnp.float32
    with pytest.raises(InputError, match="noise"):
        uwb.sample_noise(jax.random.PRNGKey(1), (3,), 0.2, "laplace")
    with pytest.raises(InputError, match="model"):
        U.make_model("cubed")


def test_squared_range_variance_against_monte_carlo():
    rng = np.random.default_rng(3)
    s2 = 0.04 / 3
    for d in (0.3, 1.0, 3.0):
        delta = rng.normal(0, math.sqrt(s2), 400000)
        y = (d + delta) ** 2
        assert abs(y.mean() - (d * d + s2)) < 5 * y.std() / math.sqrt(y.size)  # the debias offset
        np.testing.assert_allclose(y.var(), float(uwb.squared_range_variance(d, s2)), rtol=0.02)


def test_valid_ranges():
    z = jnp.array([1.0, 0.0, -0.1, jnp.nan, jnp.inf, 2.0])
    np.testing.assert_array_equal(np.asarray(uwb.valid_ranges(z)), [True, False, False, False, False, True])
