"""Paper 001 proposals and stage 2: dynamics (eq. 1-4, Table 2 Step 1), kinematics baseline,
inverse-sensor regeneration (Step 8, eq. 9, 15, 32-34), IMU model h^d (eq. 12) and the
world/body LiDAR models (eq. 13-15).  Oracles: NumPy re-implementations written from the
papers (tests/oracles/dyn_oracles_np.py, tests/oracles/sensors_oracle_np.py), the NED IMU
model of jaxslam.sensors.imu (an independent code path), sample moments.
"""


import jax
import jax.numpy as jnp
import numpy as np
import pytest

import dyn_oracles_np as dyn  # noqa: E402
import sensors_oracle_np as sen  # noqa: E402

from jaxslam.dynamics import rotor  # noqa: E402
from jaxslam.dynamics.params import PAPER001, PAPER001_MISMATCH  # noqa: E402
from jaxslam.sensors import imu as imu_mod  # noqa: E402
from jaxslam.systems import fastslam_001 as fs1  # noqa: E402

DT = 0.01
X = np.array([0.3, -0.2, 1.1, 0.4, -0.3, 0.1, 0.05, -0.08, 0.7, 0.2, -0.1, 0.3])
W = np.array([480.0, 500.0, 495.0, 488.0])


def _np_f(x, w, q):
    return dyn.f001(x, w, q.mass, np.array(q.inertia), q.g, q.rotor_inertia, q.arm_length,
                    q.k_thrust, q.k_drag)


def _np_rk4(f, x, h):
    k1 = f(x)
    k2 = f(x + 0.5 * h * k1)
    k3 = f(x + 0.5 * h * k2)
    k4 = f(x + h * k3)
    return x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)


@pytest.mark.parametrize("quad", [PAPER001, PAPER001_MISMATCH])
def test_dynamics_sample_noise_free_is_rk4_of_eq1_4(quad):
    prm = fs1.default_params("dynamics", quad=quad, dtype=jnp.float64)
    prm = prm._replace(proposal_var=jnp.zeros(12))
    a = jnp.asarray([1.0] * 6 + [0.9] * 6)
    aux = jnp.arange(12.0)
    x1, aux1 = fs1.dynamics_sample(jnp.asarray(X), aux, jax.random.PRNGKey(0), jnp.asarray(W),
                                   prm, DT, a)
    ref = _np_rk4(lambda x: _np_f(x, W, quad), X, DT)
    np.testing.assert_allclose(np.asarray(x1), ref, rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(aux1), np.arange(12.0) * np.r_[[1.0] * 6, [0.9] * 6],
                               atol=1e-15)


def test_dynamics_sample_noise_statistics():
    sig = np.array([1e-3, 2e-3, 3e-3, 1e-2, 2e-2, 3e-2, 1e-4, 2e-4, 3e-4, 1e-3, 2e-3, 3e-3])
    prm = fs1.default_params("dynamics", dtype=jnp.float64)._replace(proposal_var=jnp.asarray(sig ** 2))
    a = jnp.ones(12)
    n = 4000
    keys = jax.random.split(jax.random.PRNGKey(5), n)
    xs, _ = jax.jit(jax.vmap(lambda k: fs1.dynamics_sample(jnp.asarray(X), jnp.zeros(12), k,
                                                           jnp.asarray(W), prm, DT, a)))(keys)
    mean = _np_rk4(lambda x: _np_f(x, W, PAPER001), X, DT)
    e = (np.asarray(xs) - mean) / sig
    # Standardised residuals: mean 0 (5 standard errors) and unit variance (±10 %).
    assert np.all(np.abs(e.mean(0)) < 5 / np.sqrt(n))
    np.testing.assert_allclose(e.var(0), 1.0, atol=0.1)


def _np_kin(x, u, g, accel_mode):
    R = dyn.dcm(x[6:9])
    a = R @ u[0:3] - (g * dyn.E3 if accel_mode == "specific_force" else 0.0)
    return np.concatenate([x[3:6], a, dyn.D(x[6:9]) @ u[3:6], np.zeros(3)])


@pytest.mark.parametrize("accel_mode", ["specific_force", "kinematic"])
def test_kinematics_sample_noise_free(accel_mode):
    prm = fs1.default_params("kinematics", dtype=jnp.float64)._replace(proposal_var=jnp.zeros(12))
    u0 = np.array([0.1, -0.2, 9.7, 0.02, -0.03, 0.05])
    u1 = np.array([0.3, 0.1, 9.9, -0.01, 0.04, 0.02])
    x1, _ = fs1.kinematics_sample(jnp.asarray(X), (), jax.random.PRNGKey(0), jnp.asarray(u0),
                                  jnp.asarray(u1), prm, DT, accel_mode)
    g = PAPER001.g
    um = 0.5 * (u0 + u1)
    k1 = _np_kin(X, u0, g, accel_mode)
    k2 = _np_kin(X + 0.5 * DT * k1, um, g, accel_mode)
    k3 = _np_kin(X + 0.5 * DT * k2, um, g, accel_mode)
    k4 = _np_kin(X + DT * k3, u1, g, accel_mode)
    ref = X + DT / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    ref[9:12] = u1[3:6]
    np.testing.assert_allclose(np.asarray(x1), ref, rtol=0, atol=1e-13)


def test_h_imu_against_ned_imu_model():
    """h^d (z-up body, FLU) equals jaxslam.sensors.imu on the paper-000 NED layout, relabelled."""
    x = jnp.asarray(X)
    w = jnp.asarray(W)
    xdot = rotor.f(x, w, PAPER001)
    T = np.array([1.0, -1.0, -1.0])
    x_ned = rotor.state_to_ned(x)
    xdot_ned = jax.jvp(rotor.state_to_ned, (x,), (xdot,))[1]
    for mode in ("specific_force", "kinematic"):
        ours = np.asarray(fs1.h_imu(x, w, PAPER001, mode))
        ned = np.asarray(imu_mod.imu_ideal(x_ned, xdot_ned, PAPER001.g, mode))
        np.testing.assert_allclose(ours, np.r_[T * ned[0:3], T * ned[3:6]], atol=1e-12)
    # Specific force of the drag-free model is thrust/mass along body z (errata).
    u = dyn.mixer_matrix(PAPER001.arm_length, PAPER001.k_thrust, PAPER001.k_drag) @ W ** 2
    np.testing.assert_allclose(np.asarray(fs1.h_imu(x, w, PAPER001))[0:3],
                               [0, 0, u[0] / PAPER001.mass], atol=1e-12)


def test_landmark_models_world_and_body():
    pose = jnp.asarray(X)
    lm = jnp.asarray([2.0, -2.0, -1.0])
    for name in ("world", "body"):
        m = fs1.landmark_model(name)
        y = np.asarray(m.observe(pose, lm, None))
        if name == "world":
            # eq. 13 in paper order [β, α, r] -> jaxslam order [α, β, r]
            ref = sen.rb_measure_paper_order(X[0:3], np.asarray(lm))[[1, 0, 2]]
        else:
            ref = sen.lidar_measure(X[0:3], X[6:9], np.asarray(lm))
        np.testing.assert_allclose(y, ref, atol=1e-12)
        np.testing.assert_allclose(np.asarray(m.inverse(pose, jnp.asarray(y), None)), lm,
                                   atol=1e-12)


def test_regenerate_rates_moments():
    b = jnp.asarray([0, 0, 0, 0.01, -0.02, 0.03, 0, 0, 0, 0.001, 0.002, -0.003])
    gyro = jnp.asarray([0.1, 0.2, -0.3])
    C = np.array([[4e-6, 1e-6, 0], [1e-6, 3e-6, 0], [0, 0, 2e-6]])
    x = fs1.regenerate_rates(jnp.asarray(X), b, None, gyro, jnp.asarray(C))
    mean = np.asarray(gyro) - np.asarray(b)[3:6] - np.asarray(b)[9:12]
    np.testing.assert_allclose(np.asarray(x[9:12]), mean, atol=1e-15)
    np.testing.assert_allclose(np.asarray(x[0:9]), X[0:9], atol=0)
    n = 20000
    keys = jax.random.split(jax.random.PRNGKey(2), n)
    xs = jax.jit(jax.vmap(lambda k: fs1.regenerate_rates(jnp.asarray(X), b, k, gyro,
                                                         jnp.asarray(C))))(keys)
    w = np.asarray(xs[:, 9:12])
    assert np.all(np.abs(w.mean(0) - mean) < 5 * np.sqrt(np.diag(C) / n))
    np.testing.assert_allclose(np.cov(w.T), C, atol=0.05 * C.max())


def _inverse_moments(lidar, exact, n=20000):
    lms = np.array([[2.0, 2.0, -1.0], [-2.0, 2.0, -1.0], [-2.0, -2.0, -1.0]])
    covs = np.stack([np.diag([1e-4, 2e-4, 3e-4]), np.diag([3e-4, 1e-4, 1e-4]),
                     np.diag([1e-4, 1e-4, 1e-4])])
    R = np.diag([1e-4, 2e-4, 1e-2])
    z = np.array([sen.rb_measure_paper_order(X[0:3] + [0.01, -0.02, 0.005], l)[[1, 0, 2]]
                  if lidar == "world" else sen.lidar_measure(X[0:3] + [0.01, -0.02, 0.005],
                                                             X[6:9], l) for l in lms])
    ids = np.array([0, 2, 3])  # id 3 is not mapped: ignored
    mask = np.array([True, True, True])
    mean_l = np.zeros((4, 3))
    cov_l = np.zeros((4, 3, 3))
    active = np.array([True, False, True, False])
    mean_l[0], mean_l[2] = lms[0], lms[1]
    cov_l[0], cov_l[2] = covs[0], covs[1]
    z_used = z[[0, 1]]
    # NumPy oracle: p_j = μ_j − C ϱ(z_j), C_j = J R Jᵀ (+ Σ_j), information fusion.
    Rot = sen.dcm(X[6:9]) if lidar == "body" else np.eye(3)
    info = np.zeros((3, 3))
    eta = np.zeros(3)
    for mu, Sig, zz in zip([lms[0], lms[1]], [covs[0], covs[1]], z_used):
        p = mu - Rot @ sen.rho(zz)
        J = -Rot @ sen.drho_dy(zz)
        Cj = J @ R @ J.T + (Sig if exact else 0)
        Ci = np.linalg.inv(Cj)
        info += Ci
        eta += Ci @ p
    P = np.linalg.inv(info)
    m = P @ eta

    args = (jnp.asarray(mean_l), jnp.asarray(cov_l), jnp.asarray(active), jnp.asarray(z),
            jnp.asarray(ids, jnp.int32), jnp.asarray(mask))
    keys = jax.random.split(jax.random.PRNGKey(7), n)
    xs = jax.jit(jax.vmap(lambda k: fs1.regenerate_position(
        jnp.asarray(X), *args, k, jnp.asarray(R), lidar, exact)))(keys)
    return np.asarray(xs), m, P


@pytest.mark.parametrize("lidar,exact", [("world", True), ("body", False)])
def test_regenerate_position_fuses_inverse_models(lidar, exact):
    xs, m, P = _inverse_moments(lidar, exact)
    n = xs.shape[0]
    np.testing.assert_allclose(xs[:, 3:12], np.broadcast_to(X[3:12], (n, 9)), atol=0)
    assert np.all(np.abs(xs[:, 0:3].mean(0) - m) < 5 * np.sqrt(np.diag(P) / n))
    np.testing.assert_allclose(np.cov(xs[:, 0:3].T), P, atol=0.06 * np.abs(P).max())


def test_regenerate_position_without_mapped_landmark_keeps_pose():
    z = jnp.zeros((2, 3))
    out = jax.jit(fs1.regenerate_position)(
        jnp.asarray(X), jnp.zeros((4, 3)), jnp.zeros((4, 3, 3)), jnp.zeros(4, bool), z,
        jnp.asarray([0, 1], jnp.int32), jnp.asarray([True, True]), jax.random.PRNGKey(0),
        jnp.eye(3) * 1e-4)
    np.testing.assert_array_equal(np.asarray(out), X)
