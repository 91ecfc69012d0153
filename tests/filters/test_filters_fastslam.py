"""Tests of the generic FastSLAM core (jaxslam.filters.fastslam).

A toy planar robot (x, y, yaw) with a 2D range-bearing landmark model is
written here.  Oracles: an independent NumPy EKF with hand-derived Jacobians
and SciPy Gaussian log-densities, ``jaxslam.filters.ekf.update`` applied
directly, per-particle Python loops of the same jitted single-particle call,
and NumPy weighted means.
"""

import functools

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import special, stats

from jaxslam import errors
from jaxslam.errors import InputError
from jaxslam.filters import ekf
from jaxslam.filters import fastslam as fs
from jaxslam.filters import resampling as rs
from jaxslam.linalg import wrap_angle

# ---------------------------------------------------------------------------
# Toy model (JAX) and its NumPy oracle with hand Jacobians
# ---------------------------------------------------------------------------


def observe(pose, l, params):
    d = l - pose[:2]
    return jnp.stack([jnp.sqrt(d @ d), wrap_angle(jnp.arctan2(d[1], d[0]) - pose[2])])


def inverse(pose, z, params):
    a = z[1] + pose[2]
    return pose[:2] + z[0] * jnp.stack([jnp.cos(a), jnp.sin(a)])


RESID = ekf.angle_residual([False, True])
MODEL = fs.LandmarkModel(2, 2, observe, inverse, RESID)
LMS = np.array([[2.0, 1.0], [-1.0, 3.0], [4.0, -2.0], [0.5, -3.0]])
R_NP = np.array([[0.02, 0.001], [0.001, 0.003]])


def np_wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


def np_h(pose, l):
    d = l - pose[:2]
    return np.array([np.hypot(*d), np_wrap(np.arctan2(d[1], d[0]) - pose[2])])


def np_H(pose, l):
    dx, dy = l - pose[:2]
    q = dx * dx + dy * dy
    r = np.sqrt(q)
    return np.array([[dx / r, dy / r], [-dy / q, dx / q]])


def np_register(pose, z, R):
    a = z[1] + pose[2]
    l = pose[:2] + z[0] * np.array([np.cos(a), np.sin(a)])
    Gi = np.linalg.inv(np_H(pose, l))
    return l, Gi @ R @ Gi.T


def np_ekf(m, P, z, pose, R):
    """(m⁺, P⁺, ν, S) of one landmark EKF update, Joseph form."""
    H = np_H(pose, m)
    nu = z - np_h(pose, m)
    nu[1] = np_wrap(nu[1])
    S = H @ P @ H.T + R
    K = P @ H.T @ np.linalg.inv(S)
    A = np.eye(2) - K @ H
    return m + K @ nu, A @ P @ A.T + K @ R @ K.T, nu, S


def poses_path(T):
    t = np.arange(T) * 0.2
    return np.stack([1.5 * np.cos(t) - 1.0, 1.5 * np.sin(t), t + np.pi / 2], axis=1)


def measure(pose, rng, sigma=(0.1, 0.03)):
    z = np.stack([np_h(pose, l) for l in LMS])
    return z + rng.normal(size=z.shape) * np.asarray(sigma)


def one(p, i):
    """Particle i of p as a one-particle set (same counters)."""
    take = lambda x: x[i:i + 1]  # noqa: E731
    return p._replace(pose=take(p.pose), aux=jax.tree_util.tree_map(take, p.aux),
                      lm_mean=take(p.lm_mean), lm_cov=take(p.lm_cov), active=take(p.active),
                      ids=take(p.ids), log_w=jnp.zeros((1,), p.log_w.dtype))


@functools.lru_cache(maxsize=None)
def _obs_jit(weights, solver, slot_by_id):
    # The gate is a traced threshold (inf = no gate) so that gating needs no
    # extra compilation; the no-gate path (gate=None) runs in the scan test.
    return jax.jit(lambda p, z, ids, mask, R, gate: fs.observe_update(
        p, MODEL, z, ids, mask, R, None, weights=weights, gate=gate, slot_by_id=slot_by_id,
        solver=solver))


def obs_fn(weights="exact", solver="closed", slot_by_id=False, gate=np.inf):
    f = _obs_jit(weights, solver, slot_by_id)
    return lambda p, z, ids, mask, R: f(p, z, ids, mask, R, gate)


N_SET = 8  # one particle count for most tests: fewer compilations


@jax.jit
def core_update(g, z, pose):
    return ekf.update(g, z, lambda l: observe(pose, l, None), R_NP, residual=RESID)[0]


def logpdf(nu, S):
    return stats.multivariate_normal(mean=np.zeros(len(nu)), cov=S).logpdf(nu)


# ---------------------------------------------------------------------------
# One particle, known pose: landmark EKFs = ekf.update = NumPy EKF
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("solver,dtype", [("closed", np.float64), ("closed", np.float32),
                                          ("ekf", np.float64)])
def test_single_particle_equals_ekf_core_and_numpy(solver, dtype):
    T, K = 12, 4
    rng = np.random.default_rng(0)
    poses = poses_path(T)
    f = obs_fn("exact", solver)
    p = fs.init(poses[0].astype(dtype), 1, 6, 2)
    np_maps, core_maps = {}, {}
    tol = dict(rtol=1e-12, atol=1e-12) if dtype == np.float64 else dict(rtol=2e-4, atol=2e-5)
    for t in range(T):
        z = measure(poses[t], rng)
        mask = np.ones(K, bool)
        mask[(t + 1) % K] = t % 3 != 0  # some steps miss a landmark
        ll_np = 0.0
        for k in range(K):
            if not mask[k]:
                continue
            if k not in np_maps:
                np_maps[k] = np_register(poses[t], z[k], R_NP)
                core_maps[k] = ekf.Gaussian(jnp.asarray(np_maps[k][0]), jnp.asarray(np_maps[k][1]))
            else:
                m, P, nu, S = np_ekf(*np_maps[k], z[k], poses[t], R_NP)
                np_maps[k] = (m, P)
                ll_np += logpdf(nu, S)
                core_maps[k] = core_update(core_maps[k], z[k], poses[t])
        p = p._replace(pose=jnp.asarray(poses[t][None], dtype))
        zt = np.where(mask[:, None], z, np.nan).astype(dtype)
        p, info = f(p, zt, np.arange(K), mask, R_NP.astype(dtype))
        assert p.lm_mean.dtype == dtype and info.loglik.dtype == dtype
        np.testing.assert_allclose(float(info.loglik[0]), ll_np, **tol)
        for k, (m, P) in np_maps.items():
            slot = int(np.flatnonzero(np.asarray(p.ids[0]) == k)[0])
            np.testing.assert_allclose(np.asarray(p.lm_mean[0, slot], float), m, **tol)
            np.testing.assert_allclose(np.asarray(p.lm_cov[0, slot], float), P, **tol)
            if dtype == np.float64:
                np.testing.assert_allclose(np.asarray(p.lm_mean[0, slot]),
                                           np.asarray(core_maps[k].mean), rtol=1e-12, atol=1e-13)
                np.testing.assert_allclose(np.asarray(p.lm_cov[0, slot]),
                                           np.asarray(core_maps[k].cov), rtol=1e-12, atol=1e-13)
    assert int(p.status) == 0 and int(p.overflow) == 0
    assert set(np.asarray(p.ids[0])[np.asarray(p.active[0])]) == set(range(K))


def test_small_closed_forms_match_numpy():
    rng = np.random.default_rng(12)
    for d in (1, 2, 3):
        A = rng.normal(size=(d, d))
        S = A @ A.T + 0.1 * np.eye(d)
        inv, logdet, ok = jax.jit(fs._spd_inv_logdet)(jnp.asarray(S))
        np.testing.assert_allclose(np.asarray(inv), np.linalg.inv(S), rtol=1e-12, atol=1e-12)
        assert float(logdet) == pytest.approx(np.linalg.slogdet(S)[1], rel=1e-12)
        assert bool(ok)
        _, _, ok_bad = jax.jit(fs._spd_inv_logdet)(jnp.asarray(-S))
        assert not bool(ok_bad)


# A 3D range / azimuth / elevation model (pose = x, y, z, yaw) for the 3×3 closed forms.
def observe3(pose, l, params):
    d = l - pose[:3]
    rho = jnp.sqrt(d[0] ** 2 + d[1] ** 2)
    return jnp.stack([jnp.sqrt(d @ d), wrap_angle(jnp.arctan2(d[1], d[0]) - pose[3]),
                      jnp.arctan2(d[2], rho)])


def inverse3(pose, z, params):
    r, az, el = z[0], z[1] + pose[3], z[2]
    return pose[:3] + r * jnp.stack([jnp.cos(el) * jnp.cos(az), jnp.cos(el) * jnp.sin(az),
                                     jnp.sin(el)])


MODEL3 = fs.LandmarkModel(3, 3, observe3, inverse3, ekf.angle_residual([False, True, False]))


def np_H3(pose, l):
    dx, dy, dz = l - pose[:3]
    rho2 = dx * dx + dy * dy
    rho, r2 = np.sqrt(rho2), rho2 + dz * dz
    r = np.sqrt(r2)
    return np.array([[dx / r, dy / r, dz / r], [-dy / rho2, dx / rho2, 0.0],
                     [-dx * dz / (r2 * rho), -dy * dz / (r2 * rho), rho / r2]])


def np_h3(pose, l):
    d = l - pose[:3]
    return np.array([np.linalg.norm(d), np_wrap(np.arctan2(d[1], d[0]) - pose[3]),
                     np.arctan2(d[2], np.hypot(d[0], d[1]))])


def test_3d_landmarks_closed_and_ekf_solvers_match_numpy():
    """d = 3: registration G⁻¹RG⁻ᵀ and one update, both solvers, one compilation."""
    rng = np.random.default_rng(13)
    lms = np.array([[2.0, 1.0, -1.0], [-1.5, 2.0, 0.5], [0.5, -3.0, -0.8]])
    pose0, pose1 = np.array([0.1, -0.2, 0.3, 0.4]), np.array([0.3, 0.0, 0.25, 0.5])
    R = np.diag([0.02, 0.003, 0.004])
    z0 = np.stack([np_h3(pose0, l) for l in lms]) + rng.normal(size=(3, 3)) * 0.02
    z1 = np.stack([np_h3(pose1, l) for l in lms]) + rng.normal(size=(3, 3)) * 0.02

    @jax.jit
    def run(z0, z1):
        out = []
        for solver in ("closed", "ekf"):
            p = fs.init(jnp.asarray(pose0), 1, 4, 3)
            p, _ = fs.observe_update(p, MODEL3, z0, jnp.arange(3), jnp.ones(3, bool), R,
                                     solver=solver)
            p0 = p
            p = p._replace(pose=jnp.asarray(pose1)[None])
            p, info = fs.observe_update(p, MODEL3, z1, jnp.arange(3), jnp.ones(3, bool), R,
                                        solver=solver)
            out.append((p0, p, info.loglik))
        return out

    for p0, p, ll in run(z0, z1):
        ll_ref = 0.0
        for k in range(3):
            a = z0[k, 1] + pose0[3]
            l = pose0[:3] + z0[k, 0] * np.array([np.cos(z0[k, 2]) * np.cos(a),
                                                 np.cos(z0[k, 2]) * np.sin(a), np.sin(z0[k, 2])])
            Gi = np.linalg.inv(np_H3(pose0, l))
            P = Gi @ R @ Gi.T
            np.testing.assert_allclose(np.asarray(p0.lm_mean[0, k]), l, rtol=1e-12)
            np.testing.assert_allclose(np.asarray(p0.lm_cov[0, k]), P, rtol=1e-10, atol=1e-14)
            H = np_H3(pose1, l)
            nu = z1[k] - np_h3(pose1, l)
            nu[1] = np_wrap(nu[1])
            S = H @ P @ H.T + R
            K = P @ H.T @ np.linalg.inv(S)
            A = np.eye(3) - K @ H
            np.testing.assert_allclose(np.asarray(p.lm_mean[0, k]), l + K @ nu, rtol=1e-12)
            np.testing.assert_allclose(np.asarray(p.lm_cov[0, k]), A @ P @ A.T + K @ R @ K.T,
                                       rtol=1e-10, atol=1e-14)
            ll_ref += logpdf(nu, S)
        assert float(ll[0]) == pytest.approx(ll_ref, rel=1e-12)


# ---------------------------------------------------------------------------
# vmap over particles = per-particle loop of the same jitted call
# ---------------------------------------------------------------------------

def _spread_particles(n=N_SET, T=4, seed=1, dtype=np.float64):
    """n particles with different poses and maps after T registration/update steps."""
    rng = np.random.default_rng(seed)
    poses = poses_path(T)
    p = fs.init(poses[0].astype(dtype), n, 6, 2)
    f = obs_fn()
    for t in range(T):
        jit_pose = poses[t] + rng.normal(size=(n, 3)) * [0.05, 0.05, 0.02]
        p = p._replace(pose=jnp.asarray(jit_pose, dtype))
        p, _ = f(p, measure(poses[t], rng).astype(dtype), np.arange(4), np.ones(4, bool),
                 R_NP.astype(dtype))
    return p, rng


def test_vmapped_update_equals_per_particle_loop():
    p, rng = _spread_particles()
    z = measure(poses_path(5)[4], rng)
    mask = np.array([True, True, False, True])
    f = obs_fn()
    pv, info = f(p, z, np.arange(4), mask, R_NP)
    for i in range(p.pose.shape[0]):
        pi, ii = f(one(p, i), z, np.arange(4), mask, R_NP)
        for a, b in [(pv.lm_mean[i], pi.lm_mean[0]), (pv.lm_cov[i], pi.lm_cov[0]),
                     (info.loglik[i], ii.loglik[0]), (info.nis[i], ii.nis[0])]:
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-12, atol=1e-14)
        np.testing.assert_array_equal(np.asarray(pv.ids[i]), np.asarray(pi.ids[0]))
    # Chunked processing (lax.map over chunks of 3, remainder 2) gives the same.
    pc, ic = jax.jit(lambda p: fs.observe_update(p, MODEL, z, np.arange(4), mask, R_NP,
                                                 chunk=3))(p)
    for a, b in [(pc.lm_mean, pv.lm_mean), (pc.lm_cov, pv.lm_cov), (pc.log_w, pv.log_w),
                 (ic.loglik, info.loglik)]:
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-13, atol=1e-15)
    # Weights: log_w + loglik renormalised.
    ref = np.asarray(p.log_w) + np.asarray(info.loglik)
    np.testing.assert_allclose(np.asarray(pv.log_w), ref - special.logsumexp(ref), rtol=1e-12)


def sample_fn(pose, aux, key, u, sq):
    v, w = u
    mean = pose + 0.1 * jnp.stack([v * jnp.cos(pose[2]), v * jnp.sin(pose[2]), w])
    return mean + sq * jax.random.normal(key, (3,), pose.dtype), aux + 1.0


def test_propagate_vmapped_equals_loop():
    p = fs.init(np.zeros(3), 5, 3, 2, aux=jnp.zeros(2))
    p = p._replace(pose=jnp.asarray(np.random.default_rng(2).normal(size=(5, 3))))
    key = jax.random.PRNGKey(3)
    prop = jax.jit(lambda p, k: fs.propagate(p, k, sample_fn, (1.0, 0.3), 0.05))
    q = prop(p, key)
    single = jax.jit(sample_fn)
    keys = jax.random.split(key, 5)
    for i in range(5):
        pose_i, aux_i = single(p.pose[i], p.aux[i], keys[i], (1.0, 0.3), 0.05)
        np.testing.assert_allclose(np.asarray(q.pose[i]), np.asarray(pose_i), rtol=1e-12)
        np.testing.assert_allclose(np.asarray(q.aux[i]), np.asarray(aux_i), rtol=1e-12)
    assert q.aux.shape == (5, 2)


# ---------------------------------------------------------------------------
# Weights: exact vs mean
# ---------------------------------------------------------------------------

def test_exact_and_mean_weights_match_their_densities():
    rng = np.random.default_rng(4)
    pose = poses_path(2)
    z0, z1 = measure(pose[0], rng), measure(pose[1], rng, sigma=(0.3, 0.1))
    lls = {}
    for w in ("exact", "mean"):
        f = obs_fn(w)
        p = fs.init(pose[0], 1, 4, 2)
        p, _ = f(p, z0, np.arange(4), np.ones(4, bool), R_NP)
        p = p._replace(pose=jnp.asarray(pose[1][None]))
        p1, info = f(p, z1, np.arange(4), np.ones(4, bool), R_NP)
        lls[w] = float(info.loglik[0])
        # The landmark posteriors do not depend on the weighting.
        lls[w + "_map"] = np.asarray(p1.lm_mean)
    ref_exact = ref_mean = 0.0
    for k in range(4):
        l, P = np_register(pose[0], z0[k], R_NP)
        _, _, nu, S = np_ekf(l, P, z1[k], pose[1], R_NP)
        ref_exact += logpdf(nu, S)
        ref_mean += logpdf(nu, R_NP)
    assert lls["exact"] == pytest.approx(ref_exact, rel=1e-12)
    assert lls["mean"] == pytest.approx(ref_mean, rel=1e-12)
    assert abs(lls["exact"] - lls["mean"]) > 1.0
    np.testing.assert_array_equal(lls["exact_map"], lls["mean_map"])


def test_paper_weights_alias_is_mean():
    p = fs.init(np.zeros(3), 2, 3, 2)
    args = (p, MODEL, np.zeros((4, 2)), np.arange(4), np.ones(4, bool), R_NP)
    jx = [str(jax.make_jaxpr(lambda *a: fs.observe_update(*a[:1], MODEL, *a[1:], weights=w))(
        p, *args[2:])) for w in ("paper", "mean", "exact")]
    assert jx[0] == jx[1] != jx[2]


# ---------------------------------------------------------------------------
# Flags and counters
# ---------------------------------------------------------------------------

def test_capacity_overflow_flagged_and_counted():
    rng = np.random.default_rng(5)
    pose = poses_path(1)[0]
    f = obs_fn()
    p = fs.init(pose, 1, 6, 2)
    z = measure(pose, rng)
    # Ten distinct ids (the measurements repeat: only the ids matter) into 6 slots.
    for ids in ([0, 1, 2, 3], [4, 5, 6, 7], [8, 9, 0, 1]):
        p, info = f(p, z, np.array(ids), np.ones(4, bool), R_NP)
    assert int(p.overflow) == 4  # ids 6, 7, 8, 9: counted per measurement
    assert int(info.status) & errors.CAPACITY_OVERFLOW
    assert "capacity_overflow" in errors.decode(p.status)
    np.testing.assert_array_equal(np.asarray(p.ids), [[0, 1, 2, 3, 4, 5]])
    np.testing.assert_array_equal(np.asarray(info.used), [[False, False, True, True]])
    # slot_by_id: an id >= capacity overflows, the others land in their own slot.
    g = obs_fn(slot_by_id=True)
    q = fs.init(pose, 1, 6, 2)
    q, _ = g(q, z, np.array([2, 0, 7, -1]), np.ones(4, bool), R_NP)
    assert int(q.overflow) == 1 and int(q.status) & errors.CAPACITY_OVERFLOW
    np.testing.assert_array_equal(np.asarray(q.ids), [[0, -1, 2, -1, -1, -1]])


def test_weight_underflow_recovered_and_counted():
    pose = poses_path(2)
    rng = np.random.default_rng(6)
    p, _ = _spread_particles(T=1)
    lw_before = np.asarray(p.log_w)
    # A measurement 50 m off with a tight R: every likelihood is ~ exp(-1e6).
    z = measure(pose[1], rng)
    z[:, 0] += 50.0
    p2, info = obs_fn()(p, z, np.arange(4), np.ones(4, bool), R_NP * 1e-2)
    ll = np.asarray(info.loglik)
    assert np.all(ll < -1e4) and np.all(np.exp(lw_before + ll) == 0.0)
    assert int(p2.underflow) == 1 and not int(p2.status) & errors.DEGENERATE
    lw = np.asarray(p2.log_w)
    assert np.all(np.isfinite(lw))
    np.testing.assert_allclose(np.exp(lw), special.softmax(lw_before + ll), rtol=1e-9)
    # No finite weight at all: uniform reset, counted, DEGENERATE set.
    p3 = jax.jit(fs.reweight)(p, jnp.full((N_SET,), -jnp.inf))
    np.testing.assert_allclose(np.asarray(p3.log_w), -np.log(N_SET), rtol=1e-14)
    assert int(p3.underflow) == 1 and int(p3.status) & errors.DEGENERATE


def test_masked_and_bad_measurements_do_nothing():
    p, rng = _spread_particles(T=2)
    z = measure(poses_path(3)[2], rng)
    f = obs_fn()
    z_nan = np.full_like(z, np.nan)
    # mask False, negative ids: nothing changes, no flag.
    for ids, mask in [(np.arange(4), np.zeros(4, bool)), (-np.ones(4, int), np.ones(4, bool))]:
        q, info = f(p, z_nan, ids, mask, R_NP)
        for a, b in [(q.lm_mean, p.lm_mean), (q.lm_cov, p.lm_cov), (q.log_w, p.log_w)]:
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
        assert int(q.status) == 0 and int(info.n_used) == 0
    # mask True but NaN: skipped and flagged MASKED_INPUT.
    q, info = f(p, z_nan, np.arange(4), np.ones(4, bool), R_NP)
    np.testing.assert_array_equal(np.asarray(q.lm_mean), np.asarray(p.lm_mean))
    assert int(q.status) & errors.MASKED_INPUT and int(info.n_used) == 0


def test_gate_rejects_outlier():
    p, rng = _spread_particles(T=2)
    z = measure(poses_path(3)[2], rng)
    z[1, 0] += 20.0  # an outlier on landmark 1 only: NIS ~ 2e4, the others < 200
    q, info = obs_fn(gate=500.0)(p, z, np.arange(4), np.ones(4, bool), R_NP)
    g = np.asarray(info.gated)
    assert g[:, 1].all() and not g[:, [0, 2, 3]].any()
    assert int(q.status) & errors.GATED
    slot1 = np.asarray(p.ids) == 1
    np.testing.assert_array_equal(np.asarray(q.lm_mean)[slot1], np.asarray(p.lm_mean)[slot1])
    assert np.all(np.asarray(info.used)[:, [0, 2, 3]])


def test_register_then_update_within_one_step():
    """Two observations of a new landmark in one step: register, then update."""
    pose = poses_path(1)[0]
    rng = np.random.default_rng(7)
    z = measure(pose, rng)
    z2 = np.stack([z[0], z[0] + [0.05, -0.01], z[1], z[2]])
    p = fs.init(pose, 1, 6, 2)
    q, info = obs_fn()(p, z2, np.array([0, 0, -1, -1]), np.ones(4, bool), R_NP)
    l, P = np_register(pose, z2[0], R_NP)
    m, P2, nu, S = np_ekf(l, P, z2[1], pose, R_NP)
    np.testing.assert_allclose(np.asarray(q.lm_mean[0, 0]), m, rtol=1e-12)
    np.testing.assert_allclose(np.asarray(q.lm_cov[0, 0]), P2, rtol=1e-12, atol=1e-15)
    np.testing.assert_array_equal(np.asarray(info.registered[0]), [True, False, False, False])
    np.testing.assert_array_equal(np.asarray(info.used[0]), [False, True, False, False])


def test_bad_inputs_raise():
    for kw, match in [(dict(n_particles=0), "n_particles"), (dict(n_particles=-3), "n_particles"),
                      (dict(capacity=0), "capacity"), (dict(lm_dim=0), "lm_dim")]:
        args = dict(pose0=np.zeros(3), n_particles=4, capacity=3, lm_dim=2)
        args.update(kw)
        with pytest.raises(InputError, match=match):
            fs.init(**args)
    with pytest.raises(InputError, match="pose0"):
        fs.init(np.zeros((5, 3)), 4, 3, 2)
    with pytest.raises(InputError, match="pose0"):
        fs.init(np.array([0.0, np.nan, 0.0]), 4, 3, 2)
    with pytest.raises(InputError, match="aux"):
        fs.init(np.zeros(3), 4, 3, 2, aux=np.zeros((3, 2)), aux_per_particle=True)
    p = fs.init(np.zeros(3), 2, 3, 2)
    with pytest.raises(InputError, match="z"):
        fs.observe_update(p, MODEL, np.zeros((4, 3)), np.arange(4), np.ones(4, bool), R_NP)
    with pytest.raises(InputError, match="weights"):
        fs.observe_update(p, MODEL, np.zeros((4, 2)), np.arange(4), np.ones(4, bool), R_NP,
                          weights="bogus")
    with pytest.raises(InputError, match="R"):
        fs.observe_update(p, MODEL, np.zeros((4, 2)), np.arange(4), np.ones(4, bool),
                          np.eye(3))


def test_init_shapes_and_aux_broadcast():
    g = ekf.Gaussian(np.zeros(4), np.eye(4))
    p = fs.init(np.zeros(3, np.float32), 5, 7, 3, aux=g)
    assert p.aux.mean.shape == (5, 4) and p.aux.cov.shape == (5, 4, 4)
    assert p.lm_mean.shape == (5, 7, 3) and p.lm_cov.shape == (5, 7, 3, 3)
    assert p.lm_mean.dtype == jnp.float32 and p.log_w.dtype == jnp.float32
    assert p.ids.dtype == jnp.int32 and bool(jnp.all(p.ids == -1))
    np.testing.assert_allclose(np.asarray(p.log_w), -np.log(5), rtol=1e-6)
    q = fs.init(np.zeros((5, 3)), 5, 2, 2, aux=np.arange(5.0))
    np.testing.assert_array_equal(np.asarray(q.aux), np.arange(5.0))


# ---------------------------------------------------------------------------
# Resampling of the particle set
# ---------------------------------------------------------------------------

def test_maybe_resample_moves_every_leaf_together():
    n = N_SET
    p, _ = _spread_particles(T=2)
    p = p._replace(aux=jnp.arange(float(n)))
    rng = np.random.default_rng(8)
    key = jax.random.PRNGKey(9)
    res = jax.jit(lambda p, k, thr: fs.maybe_resample(p, k, thr))
    # Mild weights: N_eff above 0.5 N, nothing happens.
    mild = jnp.asarray(special.log_softmax(rng.normal(size=n) * 0.1))
    q = res(p._replace(log_w=mild), key, 0.5)
    np.testing.assert_array_equal(np.asarray(q.pose), np.asarray(p.pose))
    assert int(q.resamples) == 0
    # Peaked weights: resampled by the systematic indices of the same key.
    peaked = jnp.asarray(special.log_softmax(rng.normal(size=n) * 3.0))
    assert 1.0 / np.sum(np.exp(2 * np.asarray(peaked))) < n / 2
    q = res(p._replace(log_w=peaked), key, 0.5)
    idx = np.asarray(jax.jit(rs.systematic)(key, peaked))
    assert int(q.resamples) == 1
    np.testing.assert_allclose(np.asarray(q.log_w), -np.log(n), rtol=1e-14)
    np.testing.assert_array_equal(np.asarray(q.aux), idx.astype(float))
    for a, b in [(q.pose, p.pose), (q.lm_mean, p.lm_mean), (q.lm_cov, p.lm_cov),
                 (q.ids, p.ids), (q.active, p.active)]:
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b)[idx])
    # threshold=None always resamples; soft resampling keeps w/q weights.
    always = jax.jit(lambda p, k: fs.maybe_resample(p, k, None))
    assert int(always(p._replace(log_w=mild), key).resamples) == 1
    s = jax.jit(fs.resample_soft)(p._replace(log_w=peaked), key, 0.5)
    sidx, slw = jax.jit(rs.soft)(key, peaked, 0.5)
    np.testing.assert_array_equal(np.asarray(s.aux), np.asarray(sidx).astype(float))
    np.testing.assert_allclose(np.asarray(s.log_w), np.asarray(slw), rtol=1e-14)
    assert int(s.resamples) == 1


# ---------------------------------------------------------------------------
# Estimates
# ---------------------------------------------------------------------------

def test_estimate_best_and_mean_map():
    rng = np.random.default_rng(10)
    n = 9
    pose = rng.normal(size=(n, 3))
    pose[:, 2] = np.pi - 0.1 + rng.normal(size=n) * 0.05  # straddles ±π
    w = special.softmax(rng.normal(size=n))
    lw = jnp.asarray(np.log(w))
    p = fs.init(pose, n, 3, 2)._replace(pose=jnp.asarray(np_wrap(pose)), log_w=lw)
    mu, _ = jax.jit(fs.estimate)(p)
    np.testing.assert_allclose(np.asarray(mu), w @ np_wrap(pose), rtol=1e-12)
    mu_a, cov_a = jax.jit(lambda p: fs.estimate(p, angle_mask=[False, False, True]))(p)
    th = np.arctan2(w @ np.sin(pose[:, 2]), w @ np.cos(pose[:, 2]))
    ref_mu = np.r_[w @ pose[:, :2], th]
    np.testing.assert_allclose(np.asarray(mu_a), ref_mu, rtol=1e-12)
    dev = np_wrap(pose) - ref_mu
    dev[:, 2] = np_wrap(dev[:, 2])
    np.testing.assert_allclose(np.asarray(cov_a), (dev * w[:, None]).T @ dev, rtol=1e-12,
                               atol=1e-15)
    assert float(cov_a[2, 2]) < 0.01  # the wrapped yaw spread stays small
    # Maps aligned by id (slot_by_id): weighted mean and total covariance per slot.
    means = rng.normal(size=(n, 3, 2))
    covs = np.broadcast_to(np.eye(2) * 0.1, (n, 3, 2, 2)) * rng.uniform(1, 2, (n, 3, 1, 1))
    active = np.ones((n, 3), bool)
    active[:4, 2] = False
    p = p._replace(lm_mean=jnp.asarray(means), lm_cov=jnp.asarray(covs),
                   active=jnp.asarray(active), ids=jnp.asarray(np.tile(np.arange(3), (n, 1))))
    mm = jax.jit(fs.map_mean)(p)
    for s in range(3):
        ws = w * active[:, s]
        ws = ws / ws.sum()
        m = ws @ means[:, s]
        d = means[:, s] - m
        C = np.einsum("n,nij->ij", ws, covs[:, s]) + (d * ws[:, None]).T @ d
        np.testing.assert_allclose(np.asarray(mm.mean[s]), m, rtol=1e-12)
        np.testing.assert_allclose(np.asarray(mm.cov[s]), C, rtol=1e-12)
    b = jax.jit(fs.best_map)(p)
    i = int(np.argmax(w))
    np.testing.assert_array_equal(np.asarray(b.mean), means[i])
    assert bool(jnp.all(b.active == active[i]))


# ---------------------------------------------------------------------------
# dtype; a whole filter in one scan (slow: one more full compilation per dtype)
# ---------------------------------------------------------------------------

def test_float32_stays_float32():
    """propagate → reweight → maybe_resample → estimates keep float32 (one jit)."""
    p = fs.init(np.zeros(3, np.float32), N_SET, 3, 2, aux=np.zeros(2, np.float32))

    @jax.jit
    def run(p, key):
        k1, k2 = jax.random.split(key)
        p = fs.propagate(p, k1, sample_fn, (jnp.float32(1.0), jnp.float32(0.3)),
                         jnp.float32(0.05))
        p = fs.reweight(p, -jnp.arange(N_SET, dtype=jnp.float32) ** 2)
        p = fs.maybe_resample(p, k2, 0.5)
        return p, fs.estimate(p), fs.map_mean(p), fs.neff(p)

    out = run(p, jax.random.PRNGKey(0))
    for leaf in jax.tree_util.tree_leaves(out):
        if jnp.issubdtype(leaf.dtype, jnp.floating):
            assert leaf.dtype == jnp.float32, leaf.dtype
    assert int(out[0].resamples) == 1


@pytest.mark.slow
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_scanned_run_tracks_and_keeps_dtype(dtype):
    T, N = 40, 64
    rng = np.random.default_rng(11)
    truth = poses_path(T + 1)
    u = np.diff(truth, axis=0)
    zs = np.stack([measure(truth[t + 1], rng, sigma=(0.05, 0.01)) for t in range(T)])

    def sample(pose, aux, key, du):
        return pose + du + jax.random.normal(key, (3,), pose.dtype) * jnp.asarray(
            [0.02, 0.02, 0.005], pose.dtype), aux

    R = np.diag([0.05**2, 0.01**2]).astype(dtype)

    @jax.jit
    def run(p, key):
        def body(p, x):
            k, du, z = x
            p, info = fs.step(p, k, sample, (du,), MODEL, z, jnp.arange(4), jnp.ones(4, bool),
                              R, slot_by_id=True)
            return p, (fs.estimate(p, angle_mask=[False, False, True])[0], fs.neff(p))
        return jax.lax.scan(body, p, (jax.random.split(key, T), u.astype(dtype),
                                      zs.astype(dtype)))

    p0 = fs.init(truth[0].astype(dtype), N, 4, 2)
    p, (est, ne) = run(p0, jax.random.PRNGKey(0))
    for leaf in (p.pose, p.lm_mean, p.lm_cov, p.log_w, est, ne):
        assert leaf.dtype == dtype
    err = np.linalg.norm(np.asarray(est, float)[:, :2] - truth[1:, :2], axis=1)
    assert err.max() < 0.1, err.max()
    lm = np.asarray(fs.map_mean(p).mean, float)
    assert np.max(np.linalg.norm(lm - LMS, axis=1)) < 0.1
    assert int(p.status) == 0 and int(p.resamples) > 0
    chex.assert_tree_all_finite(p)


# ---------------------------------------------------------------------------
# The generic runner: fs.run is a scan of fs.step
# ---------------------------------------------------------------------------

@jax.jit
def _pose_estimate(p):
    """fs.estimate's mean with the yaw wrapped, one program per particle set shape (the loops
    below called it eagerly: a program per operation)."""
    return fs.estimate(p, angle_mask=[False, False, True])[0]


def _run_case(T=8, N=16, seed=12):
    rng = np.random.default_rng(seed)
    truth = poses_path(T + 1)
    u = np.diff(truth, axis=0)
    zs = np.stack([measure(truth[t + 1], rng, sigma=(0.05, 0.01)) for t in range(T)])
    masks = rng.random((T, 4)) > 0.2

    def sample(pose, aux, key, du):
        return pose + du + jax.random.normal(key, (3,), pose.dtype) * jnp.asarray([0.02, 0.02, 0.005],
                                                                                 pose.dtype), aux

    R = np.diag([0.05**2, 0.01**2])
    return truth, u, zs, masks, sample, R, fs.init(truth[0], N, 4, 2)


def test_generic_run_equals_a_loop_of_step():
    truth, u, zs, masks, sample, R, p0 = _run_case()
    key = jax.random.PRNGKey(4)
    out = jax.jit(lambda p, k: fs.run(p, k, sample, (u,), MODEL, zs, np.arange(4), masks, R,
                                      angle_mask=[False, False, True], slot_by_id=True, threshold=0.7))(p0, key)
    step = jax.jit(lambda p, k, du, z, m: fs.step(p, k, sample, (du,), MODEL, z, jnp.arange(4), m, R,
                                                   slot_by_id=True, threshold=0.7))
    p = p0
    for t, k in enumerate(jax.random.split(key, len(u))):
        p, info = step(p, k, u[t], zs[t], masks[t])
        np.testing.assert_allclose(np.asarray(out.pose_mean[t]),
                                   np.asarray(_pose_estimate(p)), rtol=1e-12)
        assert float(out.log_marginal[t]) == pytest.approx(float(info.log_marginal), rel=1e-12)
        assert int(out.n_used[t]) == int(info.n_used) and int(out.n_gated[t]) == int(np.sum(info.gated))
    np.testing.assert_allclose(np.asarray(out.final.pose), np.asarray(p.pose), rtol=1e-12)
    np.testing.assert_allclose(np.asarray(out.final.lm_mean), np.asarray(p.lm_mean), rtol=1e-12)
    assert int(out.final.resamples) == int(p.resamples) > 0
    assert np.all(np.asarray(out.neff) <= 16.0 + 1e-9) and out.pose_mean.shape == (len(u), 3)


def test_generic_run_names_the_bad_argument():
    truth, u, zs, masks, sample, R, p0 = _run_case(T=3)
    key = jax.random.PRNGKey(0)
    with pytest.raises(InputError, match=r"zs: expected shape \(T, K, d_z\)"):
        fs.run(p0, key, sample, (u,), MODEL, zs[0], np.arange(4), masks, R)
    with pytest.raises(InputError, match="masks"):
        fs.run(p0, key, sample, (u,), MODEL, zs, np.arange(4), masks[:2], R)
    with pytest.raises(InputError, match="lm_ids"):
        fs.run(p0, key, sample, (u,), MODEL, zs, np.arange(3), masks, R)
    with pytest.raises(InputError, match=r"inputs\[0\]"):
        fs.run(p0, key, sample, (u[:2],), MODEL, zs, np.arange(4), masks, R)
    with pytest.raises(InputError, match="R: expected shape"):
        fs.run(p0, key, sample, (u,), MODEL, zs, np.arange(4), masks, np.eye(3))
    # a fractional id used to be truncated onto another landmark; a concrete R that is not a
    # covariance used to surface only as a run-time flag
    with pytest.raises(InputError, match="lm_ids: expected whole-number"):
        fs.run(p0, key, sample, (u,), MODEL, zs, np.array([0.0, 1.5, 2.0, 3.0]), masks, R)
    # whole floats: fine (checked and traced through the whole run; eval_shape compiles nothing,
    # running it compiled a run of its own for this check)
    jax.eval_shape(lambda: fs.run(p0, key, sample, (u,), MODEL, zs, np.array([0.0, 1.0, 2.0, 3.0]), masks, R))
    with pytest.raises(InputError, match="^R"):
        fs.run(p0, key, sample, (u,), MODEL, zs, np.arange(4), masks, np.asarray(R) * np.array([[1.0, 0.0], [0.0, -1.0]]))
    with pytest.raises(InputError, match="^R"):
        fs.run(p0, key, sample, (u,), MODEL, zs, np.arange(4), masks, np.full((2, 2), np.nan))

    def bad_moments(pose, aux, cov, du):
        return pose + du, aux, cov[:2, :2]

    with pytest.raises(InputError, match="moment_fn: expected"):
        fs.run(p0, key, None, (u,), MODEL, zs, np.arange(4), masks, R, proposal="optimal", moment_fn=bad_moments)


def test_propagate_additive_is_the_mean_plus_one_draw_and_keeps_bad_particles():
    """Oracle: the mean function called per particle plus σ ⊙ ε with ε = normal(key, (N, 3))
    (one draw for the set); a factor L gives L ε; a non-finite mean keeps the old pose."""
    def mean_fn(pose, aux, u):
        v, w = u
        return pose + 0.1 * jnp.stack([v * jnp.cos(pose[2]), v * jnp.sin(pose[2]), w]), aux + 1.0

    p = fs.init(np.zeros(3), 5, 3, 2, aux=jnp.zeros(2))
    p = p._replace(pose=jnp.asarray(np.random.default_rng(2).normal(size=(5, 3))))
    key = jax.random.PRNGKey(3)
    sig = jnp.asarray([0.05, 0.02, 0.01])
    # one program per std shape (called eagerly, each call compiled its operations one by one)
    prop = jax.jit(lambda p, k, std: fs.propagate_additive(p, k, mean_fn, std, (1.0, 0.3)))
    q = prop(p, key, sig)
    eps = np.asarray(jax.random.normal(key, (5, 3), p.pose.dtype))
    mean_j = jax.jit(mean_fn)  # the mean function per particle, one program
    pose_np, aux_np = np.asarray(p.pose), np.asarray(p.aux)
    for i in range(5):
        m, a = mean_j(pose_np[i], aux_np[i], (1.0, 0.3))
        np.testing.assert_allclose(np.asarray(q.pose[i]), np.asarray(m) + np.asarray(sig) * eps[i],
                                   rtol=1e-12)
        np.testing.assert_allclose(np.asarray(q.aux[i]), np.asarray(a), rtol=1e-12)
    L = jnp.asarray([[0.05, 0.0, 0.0], [0.01, 0.02, 0.0], [0.0, 0.005, 0.01]])
    qL = prop(p, key, L)
    m0, _ = mean_j(pose_np[0], aux_np[0], (1.0, 0.3))
    np.testing.assert_allclose(np.asarray(qL.pose[0]), np.asarray(m0) + np.asarray(L) @ eps[0],
                               rtol=1e-12)
    bad = p._replace(pose=p.pose.at[2, 0].set(jnp.inf))
    qb = prop(bad, key, sig)
    np.testing.assert_array_equal(np.asarray(qb.pose[2]), np.asarray(bad.pose[2]))
    np.testing.assert_array_equal(np.asarray(qb.aux[2]), np.asarray(bad.aux[2]))
    assert int(qb.status) & errors.NON_FINITE and not int(q.status) & errors.NON_FINITE
    with pytest.raises(InputError, match=r"std: expected shape \(3,\)"):
        fs.propagate_additive(p, key, mean_fn, jnp.ones(2), (1.0, 0.3))


def test_estimate_var_is_the_diagonal_of_estimate():
    rng = np.random.default_rng(11)
    n = 9
    pose = rng.normal(size=(n, 3))
    pose[:, 2] = np.pi - 0.1 + rng.normal(size=n) * 0.05  # straddles ±π
    lw = jnp.asarray(np.log(special.softmax(rng.normal(size=n))))
    p = fs.init(pose, n, 3, 2)._replace(pose=jnp.asarray(np_wrap(pose)), log_w=lw)
    for am in (None, [False, False, True]):
        # both in one program per mask (eagerly, every operation compiled a program of its own)
        (mu, cov), (mu2, var) = jax.jit(lambda p: (fs.estimate(p, am), fs.estimate_var(p, am)))(p)
        np.testing.assert_allclose(np.asarray(mu2), np.asarray(mu), rtol=1e-14)
        np.testing.assert_allclose(np.asarray(var), np.diagonal(np.asarray(cov)), rtol=1e-12)


def test_robust_update_and_weight_match_numpy_student_t():
    """``robust=ν``: each landmark update divides R by the EM weight min((ν + 2)/(ν + d²), 1) of
    its prior NIS and the weight is the Student-t density with scale S ("exact") or R ("mean").
    Oracle: the update written out in NumPy and SciPy's multivariate_t; ν → ∞ is the Gaussian."""
    rng = np.random.default_rng(7)
    pose = poses_path(2)
    z0, z1 = measure(pose[0], rng), measure(pose[1], rng)
    z1[1, 0] += 3.0  # an outlier on landmark 1: its weight w ≪ 1
    nu_t = 5.0
    obs = jax.jit(lambda p, z, R, nu, weights: fs.observe_update(
        p, MODEL, z, jnp.arange(4), jnp.ones(4, bool), R, None, weights=weights, robust=nu),
        static_argnames="weights")
    for weights in ("exact", "mean"):
        p = fs.init(pose[0], 1, 4, 2)
        p, _ = obs(p, z0, R_NP, nu_t, weights)
        p = p._replace(pose=jnp.asarray(pose[1][None]))
        q, info = obs(p, z1, R_NP, nu_t, weights)
        ll_ref, ws = 0.0, []
        for k in range(4):
            l, P = np_register(pose[0], z0[k], R_NP)
            H = np_H(pose[1], l)
            nu = z1[k] - np_h(pose[1], l)
            nu[1] = np_wrap(nu[1])
            S = H @ P @ H.T + R_NP
            d2 = nu @ np.linalg.solve(S, nu)
            w = min((nu_t + 2) / (nu_t + d2), 1.0)
            ws.append(w)
            Rw = R_NP / w
            K = P @ H.T @ np.linalg.inv(H @ P @ H.T + Rw)
            A = np.eye(2) - K @ H
            np.testing.assert_allclose(np.asarray(q.lm_mean)[0, k], l + K @ nu, rtol=1e-12, atol=1e-14)
            np.testing.assert_allclose(np.asarray(q.lm_cov)[0, k], A @ P @ A.T + K @ Rw @ K.T, rtol=1e-10,
                                       atol=1e-16)
            scale = S if weights == "exact" else R_NP
            ll_ref += stats.multivariate_t(loc=np.zeros(2), shape=scale, df=nu_t).logpdf(nu)
        assert float(info.loglik[0]) == pytest.approx(ll_ref, rel=1e-12)
        assert ws[1] < 0.1 and min(ws[0], ws[2], ws[3]) > 0.5  # the outlier is the one down-weighted
        # ν → ∞ (1e8, without the outlier: the terms left are O(d⁴/ν), and the log-gamma terms
        # of the density cancel to ~1e-8): the Gaussian update and weight
        z1c = z1.copy()
        z1c[1, 0] -= 3.0
        qg, ig = obs(p, z1c, R_NP, 1e8, weights)
        # the Gaussian update (no gate: an infinite one), the program of
        # test_exact_and_mean_weights_match_their_densities (one particle, four slots)
        qn, in_ = obs_fn(weights)(p, z1c, np.arange(4), np.ones(4, bool), R_NP)
        np.testing.assert_allclose(np.asarray(qg.lm_mean), np.asarray(qn.lm_mean), rtol=1e-8)
        np.testing.assert_allclose(np.asarray(qg.lm_cov), np.asarray(qn.lm_cov), rtol=1e-7)
        assert float(ig.loglik[0]) == pytest.approx(float(in_.loglik[0]), rel=1e-7)
    with pytest.raises(InputError, match="robust"):
        fs.observe_update(p, MODEL, z1, jnp.arange(4), jnp.ones(4, bool), R_NP, None, solver="ekf", robust=5.0)


def np_Hs(pose, l):
    """∂h/∂s of the range-bearing toy model at pose s = (x, y, θ), by hand."""
    dx, dy = l - pose[:2]
    q = dx * dx + dy * dy
    r = np.sqrt(q)
    return np.array([[-dx / r, -dy / r, 0.0], [dy / q, -dx / q, -1.0]])


def test_optimal_proposal_matches_numpy():
    """FastSLAM 2.0's proposal (``propose_optimal``): per particle, a sequential EKF update of
    the pose (mean, covariance) with each mapped row, noise Z = R + G_l Σ_l G_lᵀ, the weight the
    sum of the rows' predictive log-densities, then one draw s̄ + chol(Σ) ε.  Oracle: the same
    written in NumPy with hand Jacobians (∂h/∂s, ∂h/∂l), SciPy's normal log-density, and the
    core's own ε (one normal(N·3) draw of the key).  A masked row, a row of an unmapped
    landmark and (with a gate) a gross outlier inform nothing."""
    rng = np.random.default_rng(11)
    N = 3
    pose = poses_path(2)
    p = fs.init(np.asarray(pose[0])[None] + 0.05 * rng.normal(size=(N, 3)), N, 6, 2)
    z0 = measure(pose[0], rng)
    p, _ = fs.observe_update(p, MODEL, z0[:3], np.arange(3), np.ones(3, bool), R_NP)  # landmarks 0-2
    p = p._replace(pose=jnp.asarray(np.asarray(pose[1])[None] + 0.05 * rng.normal(size=(N, 3))))
    A = rng.normal(size=(N, 3, 3)) * 0.05
    P0 = A @ np.transpose(A, (0, 2, 1)) + np.diag([1e-3, 1e-3, 1e-4])
    z1 = measure(pose[1], rng)
    mask = np.array([True, True, False, True])  # row 2 masked; row 3: landmark 3 is not mapped
    key = jax.random.PRNGKey(21)
    for gate in (None, 100.0):
        z = z1.copy()
        skipped = 0
        if gate is not None:
            z[1, 0] += 50.0  # a gross outlier on row 1, beyond the gate in every particle
        q, ll, log_marg, st = fs.propose_optimal(p, MODEL, z, np.arange(4), mask, R_NP, P0, key, gate=gate,
                                                angle_mask=(False, False, True))
        eps = np.asarray(jax.random.normal(key, (N, 3), jnp.float64))
        lm_mean, lm_cov, poses = np.asarray(p.lm_mean), np.asarray(p.lm_cov), np.asarray(p.pose)
        ll_ref, draws = [], []
        for i in range(N):
            s, P, lli = poses[i].copy(), P0[i].copy(), 0.0
            for k in range(4):
                if not mask[k] or k == 3:
                    continue
                l, Sl = lm_mean[i, k], lm_cov[i, k]
                Gs, Gl = np_Hs(s, l), np_H(s, l)
                Z = R_NP + Gl @ Sl @ Gl.T
                nu = z[k] - np_h(s, l)
                nu[1] = np_wrap(nu[1])
                S = Gs @ P @ Gs.T + Z
                if gate is not None and nu @ np.linalg.solve(S, nu) > gate:
                    skipped += 1
                    continue
                K = P @ Gs.T @ np.linalg.inv(S)
                IKG = np.eye(3) - K @ Gs
                s = s + K @ nu
                s[2] = np_wrap(s[2])
                P = IKG @ P @ IKG.T + K @ Z @ K.T
                lli += logpdf(nu, S)
            jit = np.finfo(np.float64).eps * (1.0 + np.trace(P))
            d = s + np.linalg.cholesky(P + jit * np.eye(3)) @ eps[i]
            d[2] = np_wrap(d[2])
            ll_ref.append(lli)
            draws.append(d)
        np.testing.assert_allclose(np.asarray(ll), ll_ref, rtol=1e-10)
        np.testing.assert_allclose(np.asarray(q.pose), draws, rtol=0, atol=1e-10)
        assert float(log_marg) == pytest.approx(float(special.logsumexp(np.asarray(p.log_w) + ll_ref)), rel=1e-12)
        assert int(st) == 0
        np.testing.assert_array_equal(np.asarray(q.log_w), np.asarray(p.log_w))  # weights untouched
        assert skipped == (0 if gate is None else N)
    # ids per particle (an association made per particle): the shared row tiled gives the same
    # draws; dropping a row for particle 0 only changes particle 0
    q1, ll1, _, _ = fs.propose_optimal(p, MODEL, z1, np.arange(4), mask, R_NP, P0, key)
    ids = np.tile(np.arange(4), (N, 1))
    q2, ll2, _, _ = fs.propose_optimal(p, MODEL, z1, ids, mask, R_NP, P0, key)
    np.testing.assert_array_equal(np.asarray(q2.pose), np.asarray(q1.pose))
    ids[0, 0] = -1
    q3, ll3, _, _ = fs.propose_optimal(p, MODEL, z1, ids, mask, R_NP, P0, key)
    assert not np.allclose(np.asarray(q3.pose)[0], np.asarray(q1.pose)[0])
    np.testing.assert_array_equal(np.asarray(q3.pose)[1:], np.asarray(q1.pose)[1:])
    np.testing.assert_array_equal(np.asarray(ll3)[1:], np.asarray(ll1)[1:])
    with pytest.raises(InputError, match="pose_cov"):
        fs.propose_optimal(p, MODEL, z1, np.arange(4), mask, R_NP, P0[:2], key)
    with pytest.raises(InputError, match="lm_ids"):
        fs.propose_optimal(p, MODEL, z1, ids[:2], mask, R_NP, P0, key)


def test_robust_optimal_proposal_matches_numpy():
    """``propose_optimal(robust=ν)``: the pose update of each mapped row uses
    Z_w = (R + G_l Σ_l G_lᵀ) / w with the EM weight w = min((ν + 2)/(ν + d²), 1) of the row's NIS
    under S = G_s Σ_s G_sᵀ + R + G_l Σ_l G_lᵀ (the whole row's noise scaled, the docstring's
    choice), and the row's weight is the Student-t density with scale S.
    Oracle: written out in NumPy with hand Jacobians and SciPy's multivariate_t; an outlier
    row must be the one down-weighted."""
    rng = np.random.default_rng(5)
    N, nu_t = 2, 5.0
    pose = poses_path(2)
    p = fs.init(np.asarray(pose[0])[None] + 0.05 * rng.normal(size=(N, 3)), N, 4, 2)
    p, _ = fs.observe_update(p, MODEL, measure(pose[0], rng), np.arange(4), np.ones(4, bool), R_NP)
    p = p._replace(pose=jnp.asarray(np.asarray(pose[1])[None] + 0.05 * rng.normal(size=(N, 3))))
    A = rng.normal(size=(N, 3, 3)) * 0.05
    P0 = A @ np.transpose(A, (0, 2, 1)) + np.diag([1e-3, 1e-3, 1e-4])
    z = measure(pose[1], rng)
    z[2, 0] += 2.0  # an outlier on row 2
    key = jax.random.PRNGKey(4)
    q, ll, _, st = fs.propose_optimal(p, MODEL, z, np.arange(4), np.ones(4, bool), R_NP, P0, key,
                                      robust=nu_t, angle_mask=(False, False, True))
    eps = np.asarray(jax.random.normal(key, (N, 3), jnp.float64))
    lm_mean, lm_cov, poses = np.asarray(p.lm_mean), np.asarray(p.lm_cov), np.asarray(p.pose)
    for i in range(N):
        s, P, lli, ws = poses[i].copy(), P0[i].copy(), 0.0, []
        for k in range(4):
            l, Sl = lm_mean[i, k], lm_cov[i, k]
            Gs, Gl = np_Hs(s, l), np_H(s, l)
            nu = z[k] - np_h(s, l)
            nu[1] = np_wrap(nu[1])
            S = Gs @ P @ Gs.T + R_NP + Gl @ Sl @ Gl.T
            d2 = nu @ np.linalg.solve(S, nu)
            w = min((nu_t + 2) / (nu_t + d2), 1.0)
            ws.append(w)
            Zw = (R_NP + Gl @ Sl @ Gl.T) / w
            K = P @ Gs.T @ np.linalg.inv(Gs @ P @ Gs.T + Zw)
            IKG = np.eye(3) - K @ Gs
            s = s + K @ nu
            s[2] = np_wrap(s[2])
            P = IKG @ P @ IKG.T + K @ Zw @ K.T
            lli += stats.multivariate_t(loc=np.zeros(2), shape=S, df=nu_t).logpdf(nu)
        jit = np.finfo(np.float64).eps * (1.0 + np.trace(P))
        d = s + np.linalg.cholesky(P + jit * np.eye(3)) @ eps[i]
        d[2] = np_wrap(d[2])
        assert float(ll[i]) == pytest.approx(lli, rel=1e-10)
        np.testing.assert_allclose(np.asarray(q.pose)[i], d, rtol=0, atol=1e-10)
        assert ws[2] < 0.1 and min(ws[0], ws[1], ws[3]) > 0.3, ws
    assert int(st) == 0


def test_observe_update_weights_none_updates_maps_only():
    rng = np.random.default_rng(3)
    pose = poses_path(2)
    p = fs.init(pose[0], 2, 4, 2)
    p, _ = fs.observe_update(p, MODEL, measure(pose[0], rng), np.arange(4), np.ones(4, bool), R_NP)
    z1 = measure(pose[1], rng)
    p = p._replace(pose=jnp.asarray(np.tile(pose[1], (2, 1))))
    qe, ie = fs.observe_update(p, MODEL, z1, np.arange(4), np.ones(4, bool), R_NP)
    qn, in_ = fs.observe_update(p, MODEL, z1, np.arange(4), np.ones(4, bool), R_NP, weights="none")
    np.testing.assert_array_equal(np.asarray(qn.lm_mean), np.asarray(qe.lm_mean))
    np.testing.assert_array_equal(np.asarray(qn.lm_cov), np.asarray(qe.lm_cov))
    assert np.all(np.asarray(in_.loglik) == 0.0) and np.all(np.asarray(ie.loglik) != 0.0)


def test_generic_run_optimal_proposal_tracks_with_four_particles():
    """``run(..., proposal="optimal", moment_fn=...)``: the toy model's Gaussian pose moved by
    ``moment_fn`` (mean + Δ, covariance + Q) and drawn at events with rows.  With 4 particles it
    tracks the truth (as the motion proposal does with 64 in the test above); an event whose
    rows are all masked draws nothing (the covariance keeps growing), which the loop written
    here checks against the runner's own output step by step."""
    T, N = 40, 4
    rng = np.random.default_rng(11)
    truth = poses_path(T + 1)
    u = np.diff(truth, axis=0)
    zs = np.stack([measure(truth[t + 1], rng, sigma=(0.05, 0.01)) for t in range(T)])
    masks = np.ones((T, 4), bool)
    masks[5:9] = False  # four events without rows
    Q = np.diag([0.02, 0.02, 0.005]) ** 2
    R = np.diag([0.05**2, 0.01**2])
    ang = [False, False, True]

    def moments(pose, aux, cov, du):
        return pose + du, aux, cov + jnp.asarray(Q, pose.dtype)

    p0 = fs.init(truth[0], N, 4, 2)
    key = jax.random.PRNGKey(2)
    out = jax.jit(lambda p, k: fs.run(p, k, None, (u,), MODEL, zs, np.arange(4), masks, R, angle_mask=ang,
                                      slot_by_id=True, proposal="optimal", moment_fn=moments))(p0, key)
    err = np.linalg.norm(np.asarray(out.pose_mean)[:, :2] - truth[1:, :2], axis=1)
    assert err.max() < 0.1, err.max()
    assert int(out.final.status) == 0
    # the same events by hand: moments, then (rows only) draw, landmark updates, weights, resampling
    @jax.jit
    def draw_update(p, cov, k_prop, z, m):
        p, ll, _, _ = fs.propose_optimal(p, MODEL, z, np.arange(4), m, R, cov, k_prop, slot_by_id=True,
                                         angle_mask=ang)
        p, _ = fs.observe_update(p, MODEL, z, np.arange(4), m, R, weights="none", slot_by_id=True)
        return fs.reweight(p, ll)

    resample = jax.jit(lambda p, k: fs.maybe_resample(p, k, 0.5))
    p, cov = p0, np.zeros((N, 3, 3))
    for t, k in enumerate(jax.random.split(key, T)):
        k_prop, k_res = jax.random.split(k)
        p = p._replace(pose=p.pose + u[t])
        cov = cov + Q
        if masks[t].any():
            p = draw_update(p, cov, k_prop, zs[t], masks[t])
            cov = np.zeros_like(cov)
        p = resample(p, k_res)
        np.testing.assert_allclose(np.asarray(out.pose_mean[t]), np.asarray(_pose_estimate(p)),
                                   rtol=1e-10, atol=1e-12)
    with pytest.raises(InputError, match="moment_fn"):
        fs.run(p0, key, None, (u,), MODEL, zs, np.arange(4), masks, R, proposal="optimal")
    with pytest.raises(InputError, match="proposal"):
        fs.run(p0, key, None, (u,), MODEL, zs, np.arange(4), masks, R, proposal="fastslam2")


def test_optimal_proposal_gradient_finite_with_a_free_slot_at_the_pose():
    """A row of an unmapped landmark (free slot, mean 0) with the particle at the origin: the
    unused row's Jacobian is infinite, and must not reach the gradient (0·inf).  Oracle: central
    differences of the same loss.  Also: a non-finite or non-positive ν is refused by name."""
    p = fs.init(np.zeros(3), 2, 4, 2)
    z0 = np.array([[2.0, 0.3], [1.5, -0.4]])
    p, _ = fs.observe_update(p, MODEL, z0[1:], np.array([1]), np.ones(1, bool), R_NP)  # slot 1 mapped
    p = p._replace(pose=jnp.asarray([[0.0, 0.0, 0.0], [0.1, 0.0, 0.05]]))
    z = np.array([[2.0, 0.3], [1.52, -0.38]])  # row 0: landmark 0, not mapped

    def loss(q):
        cov = jnp.broadcast_to(q * jnp.eye(3), (2, 3, 3))
        _, ll, lm, _ = fs.propose_optimal(p, MODEL, z, np.array([0, 1]), np.ones(2, bool), R_NP, cov,
                                           jax.random.PRNGKey(0))
        return lm

    loss_j, grad_j = jax.jit(loss), jax.jit(jax.grad(loss))  # one program each, not one per operation
    g = float(grad_j(0.01))
    h = 1e-6
    fd = (float(loss_j(0.01 + h)) - float(loss_j(0.01 - h))) / (2 * h)
    assert np.isfinite(g) and g == pytest.approx(fd, rel=1e-5)
    for bad in (np.inf, 0.0, -1.0):
        with pytest.raises(InputError, match="robust"):
            fs.propose_optimal(p, MODEL, z, np.array([0, 1]), np.ones(2, bool), R_NP, np.zeros((2, 3, 3)),
                               jax.random.PRNGKey(0), robust=bad)
        with pytest.raises(InputError, match="robust"):
            fs.observe_update(p, MODEL, z, np.array([0, 1]), np.ones(2, bool), R_NP, robust=bad)


def test_propose_optimal_checks_mask_and_pose_cov_and_flags_a_nan_row():
    """Review of 2026-12-07: propose_optimal read a 0.5 mask as True and took a negative or NaN
    pose_cov (every particle then kept its prior, only NON_FINITE said so), and a present NaN
    row was dropped without the MASKED_INPUT that observe_update sets."""
    from jaxslam.errors import InputError

    N = 3
    p = fs.init(np.zeros(3), N, 4, 2)
    z = np.array([[1.0, 0.2]])
    P0 = np.broadcast_to(0.01 * np.eye(3), (N, 3, 3))
    key = jax.random.PRNGKey(0)
    with pytest.raises(InputError, match=r"^mask: expected a bool mask"):
        fs.propose_optimal(p, MODEL, z, np.array([0]), np.array([0.5]), R_NP, P0, key)
    with pytest.raises(InputError, match=r"^pose_cov\[0\]: not positive semi-definite"):
        fs.propose_optimal(p, MODEL, z, np.array([0]), np.array([True]), R_NP, -P0, key)
    with pytest.raises(InputError, match=r"^pose_cov\[0\]: contains NaN"):
        fs.propose_optimal(p, MODEL, z, np.array([0]), np.array([True]), R_NP, np.full((N, 3, 3), np.nan), key)
    _, _, _, st = fs.propose_optimal(p, MODEL, np.array([[np.nan, 0.2]]), np.array([0]), np.array([True]), R_NP,
                                     P0, key)
    assert int(st) & errors.MASKED_INPUT
    _, _, _, st = fs.propose_optimal(p, MODEL, np.array([[np.nan, 0.2]]), np.array([0]), np.array([False]), R_NP,
                                     P0, key)
    assert not int(st) & errors.MASKED_INPUT  # a masked-off NaN row is nobody's business
