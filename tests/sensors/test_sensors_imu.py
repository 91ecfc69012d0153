"""Tests for jaxslam.sensors.imu (paper 000 eq. 2, 25, Table 5; paper 001 eq. 5-12)."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

import sensors_oracle_np as ref
from jaxslam.errors import InputError
from jaxslam.sensors import imu
from jaxslam.sensors.imu import PAPER000_IMU, PAPER001_IMU, BiasDriftState, ImuSpec

G = 9.81
RNG = np.random.default_rng(7)

_SF = jax.jit(jax.vmap(imu.specific_force, in_axes=(0, 0, None)))
_SF_JAC = jax.jit(jax.vmap(jax.jacfwd(imu.specific_force, argnums=(0, 1)), in_axes=(0, 0, None)))
_IDEAL = jax.jit(imu.imu_ideal, static_argnames="mode")


def random_state(rng, n):
    x = np.column_stack([rng.uniform(-10, 10, (n, 3)), rng.normal(0, 3, (n, 3)),
                         rng.uniform(-1.2, 1.2, (n, 2)), rng.uniform(-3, 3, (n, 1)),
                         rng.normal(0, 1, (n, 3))])
    xdot = rng.normal(0, 2, (n, 12))
    return x, xdot


# --- ideal readings ---------------------------------------------------------------------------

@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_hover_specific_force_is_minus_g_along_body_z(dtype):
    n = 16
    x = np.zeros((n, 12))
    x[:, 0:3] = RNG.uniform(-5, 5, (n, 3))
    x[:, 8] = RNG.uniform(-math.pi, math.pi, n)  # any yaw
    f = _SF(jnp.asarray(x, dtype), jnp.zeros((n, 12), dtype), G)
    assert f.dtype == dtype
    np.testing.assert_allclose(np.asarray(f, np.float64), np.tile([0.0, 0.0, -G], (n, 1)),
                               rtol=0, atol=1e-6 if dtype == jnp.float32 else 1e-14)
    z = imu.imu_ideal(jnp.asarray(x[0], dtype), jnp.zeros(12, dtype), G, mode="kinematic")
    np.testing.assert_array_equal(np.asarray(z), 0.0)


def test_specific_force_matches_numpy_and_time_derivative_of_position():
    x, xdot = random_state(RNG, 30)
    # Make Λ̇ consistent with ω (paper 000 eq. 3) so the state path is a real motion.
    for i in range(30):
        xdot[i, 6:9] = ref.euler_rate_matrix(x[i, 6:9]) @ x[i, 9:12]
    got = np.asarray(_SF(jnp.asarray(x), jnp.asarray(xdot), G))
    for i in range(30):
        np.testing.assert_allclose(got[i], ref.specific_force(x[i], xdot[i], G), atol=1e-12)
        # Independent oracle: a_N = d/dt [C(Λ(t)) v_B(t)] by central differences in time.
        h = 1e-5

        def rho_dot(t):
            return ref.dcm(x[i, 6:9] + t * xdot[i, 6:9]) @ (x[i, 3:6] + t * xdot[i, 3:6])

        a_n = (rho_dot(h) - rho_dot(-h)) / (2 * h)
        C = ref.dcm(x[i, 6:9])
        f_fd = C.T @ (a_n - G * np.array([0.0, 0.0, 1.0]))
        np.testing.assert_allclose(got[i], f_fd, atol=1e-7)


def test_specific_force_jacobian_matches_hand_derivation():
    x, xdot = random_state(RNG, 40)
    Jx, Jxd = _SF_JAC(jnp.asarray(x), jnp.asarray(xdot), G)
    Jxd_ref = np.zeros((3, 12))
    Jxd_ref[:, 3:6] = np.eye(3)
    for i in range(40):
        np.testing.assert_allclose(np.asarray(Jx[i]), ref.specific_force_jac_x(x[i], xdot[i], G),
                                   rtol=0, atol=1e-9)
        np.testing.assert_allclose(np.asarray(Jxd[i]), Jxd_ref, rtol=0, atol=1e-12)


def test_paper000_eq25_is_third_component_for_rigid_drag_free_model():
    # Eq. 2: v̇ = −ω×v + (C_NBᵀ m g n̂3 − f_T b̂3)/m  ⇒  f_B = [0, 0, −f_T/m].
    m, f_t = 1.56, 17.3
    x, _ = random_state(RNG, 1)
    x = x[0]
    C = ref.dcm(x[6:9])
    # Gravity force m g n̂3 (eq. 2 prints g n̂3 for the force; the /m needs m g).
    vdot = -np.cross(x[9:12], x[3:6]) + (C.T @ np.array([0, 0, m * G]) + np.array([0, 0, -f_t])) / m
    xdot = np.zeros(12)
    xdot[3:6] = vdot
    f = np.asarray(imu.specific_force(jnp.asarray(x), jnp.asarray(xdot), G))
    np.testing.assert_allclose(f, [0.0, 0.0, -f_t / m], atol=1e-12)


def test_imu_ideal_layout_and_modes():
    x, xdot = random_state(RNG, 1)
    x, xdot = x[0], xdot[0]
    z = np.asarray(_IDEAL(jnp.asarray(x), jnp.asarray(xdot), G))
    np.testing.assert_allclose(z[:3], ref.specific_force(x, xdot, G), atol=1e-12)
    np.testing.assert_array_equal(z[3:], x[9:12])
    zk = np.asarray(_IDEAL(jnp.asarray(x), jnp.asarray(xdot), G, mode="kinematic"))
    # paper 001 eq. 7: R_bᵂᵀ a_w with a_w the kinematic acceleration.
    a_n = ref.dcm(x[6:9]) @ (xdot[3:6] + np.cross(x[9:12], x[3:6]))
    np.testing.assert_allclose(zk[:3], ref.dcm(x[6:9]).T @ a_n, atol=1e-12)
    np.testing.assert_allclose(zk[:3] - z[:3], G * ref.dcm(x[6:9]).T[:, 2], atol=1e-12)
    with pytest.raises(InputError, match="mode"):
        imu.imu_ideal(jnp.asarray(x), jnp.asarray(xdot), G, mode="az_only")


def test_shape_validation():
    with pytest.raises(InputError, match="x"):
        imu.specific_force(jnp.zeros(9), jnp.zeros(12), G)
    with pytest.raises(InputError, match="xdot"):
        imu.kinematic_accel(jnp.zeros(12), jnp.zeros(3))


# --- white noise ------------------------------------------------------------------------------

def test_paper000_white_noise_sigma():
    sa, sg = imu.white_noise_sigma(PAPER000_IMU)
    # 300 µg/√Hz · √10 Hz and 0.01 °/s/√Hz · √10 Hz.
    np.testing.assert_allclose(np.asarray(sa), 300e-6 * 9.81 * math.sqrt(10.0) * np.ones(3),
                               rtol=1e-12)
    np.testing.assert_allclose(np.asarray(sg), 0.01 * math.pi / 180 * math.sqrt(10.0) * np.ones(3),
                               rtol=1e-12)
    R = np.asarray(imu.white_noise_cov(PAPER000_IMU, jnp.float64))
    np.testing.assert_allclose(np.diag(R), np.r_[np.asarray(sa) ** 2, np.asarray(sg) ** 2],
                               rtol=1e-12)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_sample_white_noise_std(dtype):
    n = 50_000  # 3·10⁵ draws, the size the LiDAR noise tests draw (shared compile)
    # rbg keys compile faster here; the library is key-implementation agnostic.
    v = imu.sample_white_noise(jax.random.key(11, impl="rbg"), PAPER000_IMU, (n,), dtype)
    assert v.shape == (n, 6) and v.dtype == dtype
    want = np.r_[np.full(3, 300e-6 * 9.81), np.full(3, 0.01 * math.pi / 180)] * math.sqrt(10)
    v = np.asarray(v, np.float64)
    np.testing.assert_allclose(v.std(axis=0), want, rtol=0.02)
    assert np.all(np.abs(v.mean(axis=0)) <= 5 * want / math.sqrt(n))


# --- bias + drift -----------------------------------------------------------------------------

def test_paper001_presets():
    for b in (0.0005, 0.005):
        s = PAPER001_IMU(b)
        assert s.rate == 100.0  # T = 0.01 s
        st = imu.bias_drift_init(jax.random.key(0), s, jnp.float64, stationary=False)
        np.testing.assert_array_equal(np.asarray(st.bias), np.full(6, b))
        np.testing.assert_array_equal(np.asarray(st.drift), 0.0)
        np.testing.assert_allclose(np.asarray(imu.drift_stationary_sigma(s, jnp.float64)),
                                   np.full(6, 0.1 * b), rtol=1e-12)
        assert imu.check_imu_spec(s) is s
    with pytest.raises(InputError, match="bias"):
        PAPER001_IMU(float("nan"))
    with pytest.raises(InputError, match="drift_tau"):
        PAPER001_IMU(0.005, drift_tau=0.0)
    with pytest.raises(InputError, match="^drift_fraction: expected a non-negative"):
        PAPER001_IMU(0.005, drift_fraction=-0.1)
    with pytest.raises(InputError, match="^accel_noise_density: expected a non-negative"):
        PAPER001_IMU(0.005, accel_noise_density="3e-3")  # a string is not read as a number
    assert PAPER001_IMU(0.005, drift_tau=float("inf")).drift_density == 0.0  # no drift


def test_check_imu_spec_rejects_bad_fields():
    assert imu.check_imu_spec(PAPER000_IMU) is PAPER000_IMU
    with pytest.raises(InputError, match="accel_noise_density"):
        imu.check_imu_spec(ImuSpec(accel_noise_density=-1.0))
    with pytest.raises(InputError, match="rate"):
        imu.check_imu_spec(ImuSpec(rate=0.0))
    with pytest.raises(InputError, match="bias"):
        imu.check_imu_spec(ImuSpec(bias=np.zeros(5)))
    with pytest.raises(InputError, match="drift_tau"):
        imu.check_imu_spec(ImuSpec(drift_tau=-3.0))
    with pytest.raises(InputError, match="spec"):
        imu.check_imu_spec((1.0, 2.0))


def test_drift_transition_exact_matches_van_loan_and_euler_matches_eq11():
    tau = np.array([0.5, 2.0, 10.0, 100.0, 1e3, np.inf])
    dens = np.array([0.3, 0.01, 1.0, 2e-3, 5e-4, 0.02])
    spec = ImuSpec(drift_tau=tau, drift_density=dens)
    dt = 0.1
    a, q = (np.asarray(v) for v in imu.drift_transition(spec, jnp.float64(dt)))
    for i in range(6):
        # Van Loan: expm([[−F, G Qc Gᵀ], [0, Fᵀ]] dt) for the scalar SDE ḃ = −b/τ + w.
        F = -1.0 / tau[i] if np.isfinite(tau[i]) else 0.0
        M = scipy.linalg.expm(np.array([[-F, dens[i] ** 2], [0.0, F]]) * dt)
        phi = M[1, 1]  # = e^{F dt}
        qd = phi * M[0, 1]
        np.testing.assert_allclose(a[i], phi, rtol=1e-13)
        np.testing.assert_allclose(q[i], qd, rtol=1e-12)
    ae, qe = (np.asarray(v) for v in imu.drift_transition(spec, dt, method="euler",
                                                          dtype=jnp.float64))
    np.testing.assert_allclose(ae, 1.0 - dt / tau, rtol=1e-15)  # paper 001 eq. 11 A^b block
    np.testing.assert_allclose(qe, dens ** 2 * dt, rtol=1e-15)
    with pytest.raises(InputError, match="method"):
        imu.drift_transition(spec, dt, method="rk4")


_ROLL = jax.jit(imu.bias_drift_rollout, static_argnums=4)
N_CHAINS, N_STEPS, DT = 8000, 41, 0.05


def _gm_spec(tau, dens):
    return ImuSpec(drift_tau=np.broadcast_to(np.asarray(tau, float), (6,)),
                   drift_density=np.broadcast_to(np.asarray(dens, float), (6,)))


def _paths(spec, drift0, seed):
    """(steps, chains, 6) drift paths with Δt = DT from the (chains, 6) start ``drift0``."""
    st = BiasDriftState(bias=jnp.zeros((N_CHAINS, 6)), drift=jnp.asarray(drift0))
    # rbg keys compile faster here; the library is key-implementation agnostic.
    return np.asarray(_ROLL(jax.random.key(seed, impl="rbg"), st, spec, DT, N_STEPS).drift)


def test_gauss_markov_stationary_variance_and_autocorrelation():
    tau, dens = 0.5, 0.2
    spec = _gm_spec(tau, dens)
    var_ss = dens ** 2 * tau / 2
    st0 = imu.bias_drift_init(jax.random.key(2, impl="rbg"), spec, jnp.float64,
                              shape_prefix=(N_CHAINS,))
    d = _paths(spec, st0.drift, seed=3)
    # Stationary: the variance stays σ_w² τ/2 at every step (6 axes × 8000 chains pooled).
    var_t = (d ** 2).mean(axis=(1, 2))
    np.testing.assert_allclose(var_t[[0, 10, 20, 40]], var_ss, rtol=0.03)
    # Autocorrelation E[b(t) b(t+kΔt)] = σ² e^{−kΔt/τ}.
    for k in (1, 5, 10, 20, 40):
        rho_k = (d[0] * d[k]).mean() / var_ss
        assert rho_k == pytest.approx(math.exp(-k * DT / tau), abs=0.02), k


def test_gauss_markov_from_zero_and_random_walk_variance_growth():
    tau, dens = 0.5, 0.2
    spec = _gm_spec(np.r_[np.full(3, tau), np.full(3, np.inf)], dens)
    d = _paths(spec, np.zeros((N_CHAINS, 6)), seed=5)
    k = np.arange(N_STEPS)
    var_gm = (d[:, :, :3] ** 2).mean(axis=(1, 2))
    var_rw = (d[:, :, 3:] ** 2).mean(axis=(1, 2))
    want_gm = dens ** 2 * tau / 2 * (1 - np.exp(-2 * k * DT / tau))
    want_rw = dens ** 2 * k * DT
    np.testing.assert_array_equal(var_gm[0], 0.0)
    np.testing.assert_allclose(var_gm[5:], want_gm[5:], rtol=0.04)
    np.testing.assert_allclose(var_rw[5:], want_rw[5:], rtol=0.04)


@pytest.mark.slow
def test_gauss_markov_long_single_chain_autocorrelation():
    tau, dens, dt = 0.2, 1.0, 0.02
    spec = ImuSpec(drift_tau=tau, drift_density=dens)
    st = imu.bias_drift_init(jax.random.key(1), spec, jnp.float64)
    d = np.asarray(imu.bias_drift_rollout(jax.random.key(2), st, spec, dt, 200_000).drift)
    var_ss = dens ** 2 * tau / 2
    np.testing.assert_allclose(d.var(axis=0), var_ss, rtol=0.05)
    for k in (1, 10, 20):
        r = (d[:-k] * d[k:]).mean() / var_ss
        assert r == pytest.approx(math.exp(-k * dt / tau), abs=0.03)


def test_bias_init_turn_on_sigma_and_constant_bias():
    spec = ImuSpec(bias=np.arange(6) * 0.01, bias_sigma=np.r_[np.full(3, 0.02), np.full(3, 0.001)])
    st = imu.bias_drift_init(jax.random.key(9, impl="rbg"), spec, jnp.float64,
                             shape_prefix=(50_000,))
    b = np.asarray(st.bias)
    assert st.drift.shape == (50_000, 6)
    np.testing.assert_allclose(b.mean(axis=0), np.arange(6) * 0.01, atol=5 * 0.02 / math.sqrt(5e4))
    np.testing.assert_allclose(b.std(axis=0), spec.bias_sigma, rtol=0.03)
    # b0 never changes under the drift dynamics (eq. 8, 10: ḃ0 = 0).
    one = BiasDriftState(bias=jnp.asarray(b[0]), drift=jnp.zeros(6))
    seq = imu.bias_drift_rollout(jax.random.key(1), one, PAPER001_IMU(0.005), 0.01, 5)
    np.testing.assert_array_equal(np.asarray(seq.bias), np.tile(b[0], (5, 1)))
    assert seq.drift.shape == (5, 6)
    np.testing.assert_array_equal(np.asarray(seq.drift[0]), 0.0)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_bias_drift_follows_dtype_and_corrupt_adds_terms(dtype):
    spec = PAPER001_IMU(0.005)

    def chain(key):
        k0, k1, k2 = jax.random.split(key, 3)
        st = imu.bias_drift_init(k0, spec, dtype)
        st2 = imu.bias_drift_step(k1, st, spec, 0.01)
        white = imu.sample_white_noise(k2, spec, (), dtype)
        ideal = jnp.arange(6, dtype=dtype)
        return st, st2, white, imu.corrupt(ideal, st2, white)

    st, st2, white, z = chain(jax.random.key(0, impl="rbg"))
    assert st.bias.dtype == st.drift.dtype == st2.drift.dtype == white.dtype == z.dtype == dtype
    np.testing.assert_allclose(np.asarray(z, np.float64),
                               np.arange(6) + np.asarray(st2.bias, np.float64)
                               + np.asarray(st2.drift, np.float64) + np.asarray(white, np.float64),
                               rtol=1e-6)
    with pytest.raises(InputError, match="n_steps"):
        imu.bias_drift_rollout(jax.random.key(0), st, spec, 0.01, 0)


def test_bias_drift_step_is_exact_decay_without_driving_noise():
    spec = ImuSpec(bias=0.3, drift_tau=np.array([2.0, 2.0, 2.0, 0.5, 0.5, np.inf]),
                   drift_density=0.0)
    st = BiasDriftState(bias=jnp.full(6, 0.3), drift=jnp.ones(6))
    st2 = imu.bias_drift_step(jax.random.key(0), st, spec, 0.1)
    np.testing.assert_allclose(np.asarray(st2.drift),
                               np.exp(-0.1 / np.array([2.0, 2.0, 2.0, 0.5, 0.5, np.inf])),
                               rtol=1e-15)
    np.testing.assert_array_equal(np.asarray(st2.bias), 0.3)
