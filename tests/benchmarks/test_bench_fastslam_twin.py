"""The NumPy twin of paper 001's FastSLAM step (tests/oracles/numpy_fastslam.py) runs the same filter.

The twin is the reference of ``jaxslam bench fastslam``; a speed comparison means
something only if both do the same work.  Oracle: the twin is written
independently in NumPy with hand-derived Jacobians (spherical map and its
inverse), closed-form 3×3 inverses and Cholesky factors, and the rotor dynamics
written out component by component.  Both filters get the same random numbers:
the test reproduces jaxslam's key splitting (``step`` → IMU / LiDAR keys →
proposal, resampling and regeneration keys, one draw per set) to extract the
proposal noise, the systematic-resampling uniforms and the regeneration noise,
and injects them into the twin.  Over 30 steps (three LiDAR frames: landmark
registration, then updates; the bias re-initialisation at k = 0; resampling
at some steps and not at others; an azimuth crossing ±π) every particle's pose,
bias mean, landmark means and covariances, log-weight, the shared bias
covariance and the step outputs must agree to 1e-9 (measured: ~1e-15).

The jaxslam step is compiled with XLA's cheap optimisation level (the numbers
are the same function's; only compile time changes) to keep the file fast.
Not a timing test.
"""

import pathlib
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam.dynamics import rotor
from jaxslam.dynamics.params import PAPER001
from jaxslam.sensors import lidar3d
from jaxslam.systems import fastslam_001 as fs1

BENCH = pathlib.Path(__file__).resolve().parents[2] / "benchmarks"
sys.path.insert(0, str(BENCH))
import numpy_fastslam as tw  # noqa: E402

TOL = 1e-9
N = 16
T = 30
FAST_COMPILE = {"xla_backend_optimization_level": 0, "xla_llvm_disable_expensive_passes": True}
LANDMARKS = np.array([[2.0, 2.0, -1.0], [-2.0, 2.0, -1.0], [-2.0, -2.0, -1.0], [2.0, -2.0, -1.0]])


def _inputs(rng, prm):
    """Near-hover rotor speeds (±1 % wobble), IMU = hover specific force + noise + bias, LiDAR
    of the four poles from x0 + noise.  x0 puts pole 2 straight behind (azimuth ±π)."""
    x0 = np.zeros(12)
    x0[0:3] = [1.0, 2.0, 0.5]
    w_h = np.sqrt(PAPER001.mass * PAPER001.g / (4 * PAPER001.k_thrust))
    t = np.arange(T) * 0.01
    rot = w_h * (1 + 0.01 * np.sin(2 * np.pi * np.outer(t, [1.0, 1.3, 0.7, 1.1])))
    imu = np.zeros((T, 6))
    imu[:, 2] = PAPER001.g
    imu += 0.002 + np.sqrt(np.asarray(prm.imu_var)) * rng.standard_normal((T, 6))
    d = LANDMARKS - x0[0:3]
    y = np.stack([np.arctan2(d[:, 1], d[:, 0]), np.arctan2(d[:, 2], np.hypot(d[:, 0], d[:, 1])),
                  np.linalg.norm(d, axis=1)], 1)
    z = np.zeros((T, 4, 3))
    mask = np.zeros((T, 4), bool)
    for k in range(9, T, 10):
        zz = y + np.sqrt(np.asarray(prm.lidar_var)) * rng.standard_normal((4, 3))
        zz[:, 0] = (zz[:, 0] + np.pi) % (2 * np.pi) - np.pi
        z[k], mask[k] = zz, True
    return x0, rot, imu, z, mask


def _draws(key, n):
    """jaxslam's random numbers of one ``fastslam_001.step`` call with key ``key`` (its key
    splitting reproduced: step → IMU/LiDAR keys → proposal, resampling, regeneration; each
    noise is one draw for the whole set)."""
    k_imu, k_lid = jax.random.split(key)
    k_prop, k_res, k_s2 = jax.random.split(k_imu, 3)
    k_res2, k_s22 = jax.random.split(k_lid)

    def normals(k, m):
        return jax.random.normal(k, (n, m), jnp.float64)

    return (normals(k_prop, 12), jax.random.uniform(k_res, (), jnp.float64),
            normals(k_s2, 3), jax.random.uniform(k_res2, (), jnp.float64), normals(k_s22, 3))


# the filter's parameters from one small compiled program shared by the tests (eager, every
# primitive of their construction is compiled)
_default_params = jax.jit(lambda: fs1.default_params("dynamics", dtype=jnp.float64))


def _maxdiff(a, b):
    return float(np.max(np.abs(np.asarray(a, float) - np.asarray(b, float))))


@pytest.fixture(scope="module")
def runs():
    cfg = fs1.Config(n_particles=N)
    prm = _default_params()
    rng = np.random.default_rng(4)
    x0, rot, imu, z, mask = _inputs(rng, prm)
    ids = np.arange(4, dtype=np.int32)
    # the initial state from one small program (eager, every primitive is compiled)
    def init(k, x):  # init reads only log.x0
        log = fs1.Log(x0=x, rotor_w=None, imu=None, z=None, ids=None, mask=None)
        return fs1.init(log, cfg, prm, key=k)

    st = jax.jit(init)(jax.random.PRNGKey(3), jnp.asarray(x0))
    inp0 = fs1.Event(jnp.asarray(rot[0]), jnp.asarray(imu[0]), jnp.asarray(z[0]),
                     jnp.asarray(ids), jnp.asarray(mask[0]))
    # One compiled program: the step and the draws it makes from its key.
    step = jax.jit(lambda s, i, k: (fs1.step(s, i, cfg, prm, key=k), _draws(k, N)),
                   compiler_options=FAST_COMPILE)
    P = tw.params_from(prm, cfg.dt, prm.resample_threshold)
    ts = tw.state_from(st)
    worst, resampled, seen = {}, [], []
    states = []
    for k in range(T):
        key = jax.random.fold_in(jax.random.PRNGKey(11), k)
        inp = inp0._replace(rotor=jnp.asarray(rot[k]), imu=jnp.asarray(imu[k]),
                            z=jnp.asarray(z[k]), mask=jnp.asarray(mask[k]))
        before = int(st.particles.resamples)
        (st, out), d = step(st, inp, key)
        ts_prev = ts
        ts, tout = tw.step(ts, rot[k], imu[k], z[k], ids, mask[k],
                           tw.Draws(*(np.asarray(a) for a in d)), P)
        states.append((ts_prev, k))
        p = st.particles
        pairs = {"pose": (p.pose, ts.pose), "bias_mean": (p.aux, ts.aux),
                 "lm_mean": (p.lm_mean, ts.lm_mean), "lm_cov": (p.lm_cov, ts.lm_cov),
                 "log_w": (p.log_w, ts.log_w), "bias_cov": (st.bias_cov, ts.bias_cov),
                 "neff_min": (st.neff_min, ts.neff_min)}
        pairs.update({f"out.{f}": (getattr(out, f), getattr(tout, f)) for f in out._fields})
        for name, (a, b) in pairs.items():
            worst[name] = max(worst.get(name, 0.0), _maxdiff(a, b))
        seen.append((np.array_equal(np.asarray(p.active), ts.active),
                     np.array_equal(np.asarray(p.ids), ts.ids),
                     int(p.resamples) == ts.resamples, int(st.k) == ts.k))
        resampled.append(int(p.resamples) - before)
    return {"worst": worst, "seen": seen, "resampled": resampled, "final": (st, ts),
            "inputs": (rot, imu, z, mask, ids), "P": P, "states": states}


def test_twin_equals_jaxslam_step_on_the_same_draws(runs):
    worst = runs["worst"]
    print("max |jaxslam − twin| over 30 steps:",
          ", ".join(f"{k} {v:.1e}" for k, v in worst.items()))
    bad = {k: v for k, v in worst.items() if not v < TOL}
    assert not bad, f"twin disagrees with jaxslam: {bad}"
    for k, (act, ids, res, kk) in enumerate(runs["seen"]):
        assert act and ids and res and kk, f"step {k}: maps/ids/resamples/k differ"


def test_the_run_exercised_every_branch(runs):
    st, ts = runs["final"]
    res = runs["resampled"]
    # both resampling outcomes, three LiDAR frames (registration then updates), all slots mapped
    assert 0 < sum(r > 0 for r in res) < T, res
    assert np.all(ts.active) and np.all(np.asarray(st.particles.active))
    # landmark covariances shrank below their registration value (updates happened)
    assert np.all(np.trace(ts.lm_cov, axis1=-2, axis2=-1) < 0.05)
    assert np.isfinite(ts.log_w).all()


def test_per_particle_loop_equals_vectorised_twin(runs):
    rot, imu, z, mask, ids = runs["inputs"]
    P = runs["P"]
    rng = np.random.default_rng(1)
    for ts0, k in runs["states"]:
        if k not in (0, 19, 25):  # the re-initialisation, a LiDAR step, an IMU-only step
            continue
        d = tw.draw(rng, N)
        a, oa = tw.step(ts0, rot[k], imu[k], z[k], ids, mask[k], d, P)
        b, ob = tw.step_loop(ts0, rot[k], imu[k], z[k], ids, mask[k], d, P)
        for f in ("pose", "aux", "lm_mean", "lm_cov", "log_w", "bias_cov"):
            assert _maxdiff(getattr(a, f), getattr(b, f)) < 1e-13, (k, f)
        assert np.array_equal(a.active, b.active)
        assert _maxdiff(oa.pose_mean, ob.pose_mean) < 1e-13


def test_hand_jacobians_and_models_match_the_package():
    rng = np.random.default_rng(2)
    c = rng.normal(size=(5, 3)) * 3
    y = np.stack([rng.uniform(-3, 3, 5), rng.uniform(-1.2, 1.2, 5), rng.uniform(1, 9, 5)], 1)
    prm = _default_params()
    x = np.r_[rng.normal(size=6), rng.uniform(-0.5, 0.5, 3), rng.normal(size=3)]
    w = 380.0 + 20 * rng.random(4)

    @jax.jit
    def ref(c, y, x, w, quad):
        sph, cart = lidar3d.spherical_from_cartesian, lidar3d.cartesian_from_spherical
        return (sph(c), jax.vmap(jax.jacfwd(sph))(c), cart(y), jax.vmap(jax.jacfwd(cart))(y),
                rotor.f(x, w, quad), fs1.h_imu(x, w, quad))

    s_ref, Js_ref, c_ref, Jc_ref, f_ref, h_ref = ref(c, y, x, w, prm.quad)
    val, J = tw._spherical(c)
    assert _maxdiff(val, s_ref) < 1e-14 and _maxdiff(J, Js_ref) < 1e-12
    val, J = tw._cartesian(y)
    assert _maxdiff(val, c_ref) < 1e-12 and _maxdiff(J, Jc_ref) < 1e-12
    P = tw.params_from(prm, 0.01)
    u, om = tw._mixer(w, P)
    assert _maxdiff(tw._f(x, u, om, P), f_ref) < 1e-11
    assert _maxdiff(tw._h_imu(x, u, P), h_ref) < 1e-12
    A = rng.normal(size=(3, 3))
    S = A @ A.T + np.eye(3)
    assert _maxdiff(tw._inv3(S)[0], np.linalg.inv(S)) < 1e-12
    assert _maxdiff(tw._chol3(S), np.linalg.cholesky(S)) < 1e-12
