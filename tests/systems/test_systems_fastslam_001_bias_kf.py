"""Paper 001 Table 4: the per-particle bias/drift KF of the dynamics filter equals a NumPy KF.

Setup where h^d is known in closed form: every particle hovers level (rotor speeds of hover,
so u1 = m g and the specific force is g e3) with its own constant yaw rate r_i (ω = (0, 0, r_i)
is an equilibrium of eq. 1 with u4 = 0), no proposal noise, stage 2 off, resampling disabled.
Then z̄_i = z^I − [0, 0, g, 0, 0, r_i] and the bias KF is linear: x_{k+1} = A x_k + w,
z̄ = H x + v.  The oracle is written from eq. 11-12 and Table 4 (minimum-norm least-squares
re-initialisation per the errata), in NumPy float64; it also gives the IMU log-likelihoods
whose sums are the particles' log-weight differences (exact and paper weights).
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam import errors
from jaxslam.dynamics import rotor
from jaxslam.dynamics.params import PAPER001
from jaxslam.systems import fastslam_001 as fs1

G = PAPER001.g
RATES = np.array([0.0, 0.01, -0.02])
K_STEPS = 40
A_DRIFT = 0.98
Q_DRIFT = 2e-6
IMU_VAR = np.array([1e-4] * 3 + [4e-6] * 3)
P0 = 1e-2


def _params(dtype):
    base = fs1.default_params("dynamics", dtype=dtype)
    return base._replace(
        proposal_var=jnp.zeros((12,), dtype),
        imu_var=jnp.asarray(IMU_VAR, dtype),
        drift_a=jnp.full((6,), A_DRIFT, dtype),
        drift_q=jnp.full((6,), Q_DRIFT, dtype),
        bias_p0=jnp.full((12,), P0, dtype),
        pose0_var=jnp.zeros((12,), dtype),
    )


def _imu_samples(seed=3):
    rng = np.random.default_rng(seed)
    b0 = np.array([0.02, -0.01, 0.03, 0.004, -0.002, 0.003])
    drift = np.zeros(6)
    zs = []
    for _ in range(K_STEPS):
        drift = A_DRIFT * drift + math.sqrt(Q_DRIFT) * rng.standard_normal(6)
        zs.append(np.r_[0, 0, G, 0, 0, 0] + b0 + drift + np.sqrt(IMU_VAR) * rng.standard_normal(6))
    return np.array(zs)


def _oracle(zs, weights, skip=()):
    """NumPy KF per particle; returns means (K, N, 12), covs (K, 12, 12), loglik sums (N,).
    Samples ``skip`` are missing: prediction only, no update, no likelihood."""
    I3, Z3 = np.eye(3), np.zeros((3, 3))
    H = np.block([[I3, Z3, I3, Z3], [Z3, I3, Z3, I3]])
    A = np.diag([1.0] * 6 + [A_DRIFT] * 6)
    Q = np.diag([0.0] * 6 + [Q_DRIFT] * 6)
    R = np.diag(IMU_VAR)
    N = len(RATES)
    x = np.zeros((N, 12))
    P = P0 * np.eye(12)
    means, covs = [], []
    ll = np.zeros(N)
    for k, z in enumerate(zs):
        xp = x @ A.T
        Pp = A @ P @ A.T + Q
        if k in skip:
            x, P = xp, Pp
            means.append(x.copy())
            covs.append(P.copy())
            continue
        S = H @ Pp @ H.T + R
        K = Pp @ H.T @ np.linalg.inv(S)
        P = (np.eye(12) - K @ H) @ Pp @ (np.eye(12) - K @ H).T + K @ R @ K.T
        for i, r in enumerate(RATES):
            zb = z - np.r_[0, 0, G, 0, 0, r]
            if k == 0:
                # Table 4 re-initialisation, minimum-norm least squares (errata).
                x[i] = np.linalg.lstsq(H, zb, rcond=None)[0]
            else:
                nu = zb - H @ xp[i]
                C = S if weights == "exact" else R
                ll[i] += -0.5 * (nu @ np.linalg.solve(C, nu) + np.linalg.slogdet(2 * np.pi * C)[1])
                x[i] = xp[i] + K @ nu
        means.append(x.copy())
        covs.append(P.copy())
    return np.array(means), np.array(covs), ll


CASES = ((jnp.float64, "exact"), (jnp.float64, "paper"), (jnp.float32, "exact"))


def _bias_kf_run(zs, dtype, weights):
    """The IMU stage alone over ``zs``, from the set-up of the module docstring (traced)."""
    cfg = fs1.Config(n_particles=3, stage2="none", weights=weights)
    prm = _params(dtype)._replace(resample_threshold=1e-9)
    x0 = np.zeros((3, 12))
    x0[:, 2] = 0.5
    x0[:, 11] = RATES
    w = rotor.hover_rotor_speeds(PAPER001, dtype)
    log = fs1.Log(x0=jnp.zeros(12, dtype), rotor_w=None, imu=None, z=None, ids=None, mask=None)
    st = fs1.init(log, cfg, prm, key=jax.random.PRNGKey(0))
    st = st._replace(particles=st.particles._replace(pose=jnp.asarray(x0, dtype)))

    def body(s, x):
        z, k = x
        s, _ = fs1.imu_stage(s, w, z, k, cfg, prm)
        return s, (s.particles.aux, s.bias_cov)

    keys = jax.random.split(jax.random.PRNGKey(1), zs.shape[0])
    return jax.lax.scan(body, st, (zs.astype(dtype), keys))


@pytest.fixture(scope="module")
def runs():
    zs = _imu_samples()
    # The three cases in one compiled program (set-up included: no eager dispatch).
    go = jax.jit(lambda zs: [_bias_kf_run(zs, dtype, weights) for dtype, weights in CASES])
    out = {}
    for (dtype, weights), (final, (means, covs)) in zip(CASES, go(jnp.asarray(zs))):
        out[(jnp.dtype(dtype).name, weights)] = (final, np.asarray(means), np.asarray(covs))
    return zs, out


@pytest.mark.parametrize("dtype,tol", [("float64", 1e-10), ("float32", 2e-3)])
def test_bias_kf_matches_numpy_kf(runs, dtype, tol):
    zs, out = runs
    final, means, covs = out[(dtype, "exact")]
    m_ref, P_ref, _ = _oracle(zs, "exact")
    assert means.dtype == np.dtype(dtype)
    scale = np.max(np.abs(m_ref))
    np.testing.assert_allclose(means, m_ref, atol=tol * scale, rtol=0)
    np.testing.assert_allclose(covs, P_ref, atol=tol * P0, rtol=0)


def test_reinitialisation_is_minimum_norm(runs):
    zs, out = runs
    _, means, _ = out[("float64", "exact")]
    zb = zs[0] - np.r_[0, 0, G, 0, 0, RATES[1]]
    # Minimum-norm solution of [I I] x = z̄ per sensor: b0 = b1 = z̄ / 2.
    np.testing.assert_allclose(means[0, 1, 0:6], zb / 2, atol=1e-12)
    np.testing.assert_allclose(means[0, 1, 6:12], zb / 2, atol=1e-12)


@pytest.mark.parametrize("weights", ["exact", "paper"])
def test_imu_weights(runs, weights):
    zs, out = runs
    final, _, _ = out[("float64", weights)]
    _, _, ll = _oracle(zs, weights)
    lw = np.asarray(final.particles.log_w)
    # The run never resamples (threshold ~0), so log-weight differences are the summed IMU
    # log-likelihood differences (the first sample carries no weight).
    assert int(final.particles.resamples) == 0
    np.testing.assert_allclose(lw - lw[0], ll - ll[0], rtol=1e-8, atol=1e-6)
    np.testing.assert_allclose(np.log(np.sum(np.exp(lw))), 0.0, atol=1e-12)


def test_non_finite_imu_samples_are_skipped_and_flagged():
    # Samples 10-12 NaN (a dropped-out IMU): the KF predicts through them (the oracle's
    # prediction-only steps), the weights take no likelihood from them, MASKED_INPUT is set.
    zs = _imu_samples()
    bad = zs.copy()
    bad[10:13] = np.nan
    final, (means, covs) = jax.jit(lambda z: _bias_kf_run(z, jnp.float64, "exact"))(jnp.asarray(bad))
    m_ref, P_ref, ll = _oracle(zs, "exact", skip={10, 11, 12})
    np.testing.assert_allclose(np.asarray(means), m_ref, atol=1e-10 * np.max(np.abs(m_ref)), rtol=0)
    np.testing.assert_allclose(np.asarray(covs), P_ref, atol=1e-10 * P0, rtol=0)
    lw = np.asarray(final.particles.log_w)
    np.testing.assert_allclose(lw - lw[0], ll - ll[0], rtol=1e-8, atol=1e-6)
    assert "masked_input" in errors.decode(final.particles.status)
    assert np.all(np.isfinite(np.asarray(final.particles.pose)))
