"""Scenario ``fastslam-helix`` and the whole-flight filter of paper 001 on short, reduced runs.

Default tests: one 2 s truth flight (scenario generator), the dynamics filter on it with
N = 40 (finite, bounded errors, counters sane); bad input; the gradient of a LiDAR frame
w.r.t. log R^S with soft resampling against central differences.  Slow tests (compiling a
whole-flight filter costs 20-60 s each on 2 cores): the kinematics baseline on the same
flight; ``step`` driven in a Python loop equals ``run``; the gradient of a whole short run
w.r.t. log Q and log R against finite differences.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import special

from jaxslam.errors import InputError
from jaxslam.sim.scenarios import fastslam as sc
from jaxslam.sim.scenarios import registry
from jaxslam.systems import fastslam_001 as fs1

N = 40
DUR = 2.0


def _opts(**kw):
    o = {opt.name: opt.default for opt in sc.OPTIONS}
    o.update(particles=N, duration=DUR, bias=0.005)
    o.update(kw)
    return o


@pytest.fixture(scope="module")
def flight():
    setup = sc.truth_setup(0.005, jnp.float64)
    nf = int(round(DUR / (sc.DT * sc.LIDAR_EVERY)))
    fl = jax.jit(lambda k: sc.fly(setup, k, nf))(jax.random.PRNGKey(11))
    return setup, fl


_RESULTS = {}


def _result(flight, model):
    """Run ``model`` once per module (compiling a whole-flight filter costs ~20-30 s)."""
    if model not in _RESULTS:
        setup, fl = flight
        ids = jnp.arange(4, dtype=jnp.int32)
        cfg, prm = sc.make_filter(_opts(model=model), jnp.float64)

        @jax.jit
        def go(key, fl):
            log = fs1.Log(x0=fl.truth[0], rotor_w=fl.rotor, imu=fl.imu, z=fl.z, ids=ids, mask=fl.mask)
            res = fs1.run(log, cfg, prm, key=key)  # cfg.n_particles = N
            return res, sc.evaluate(fl, res, setup.landmarks, 0.005)

        _RESULTS[model] = go(jax.random.PRNGKey(3), fl)
    return _RESULTS[model]


def test_truth_flight_tracks_helix(flight):
    setup, fl = flight
    T = fl.imu.shape[0]
    assert fl.truth.shape == (T + 1, 12) and fl.rotor.shape == (T, 4)
    assert fl.z.shape == (T // sc.LIDAR_EVERY, 4, 3)
    assert np.all(np.isfinite(np.asarray(fl.truth)))
    # Started on the helix: the true position stays within a few cm of the reference (NED).
    ned = np.asarray(jax.jit(jax.vmap(sc.rotor.state_to_ned))(fl.truth))
    assert np.max(np.linalg.norm(ned[:, 0:3] - np.asarray(fl.ref)[:, 0:3], axis=1)) < 0.05
    # IMU offset: constant bias 0.005 on every axis plus a small drift.
    off = np.asarray(fl.offset)
    np.testing.assert_allclose(off[:, 0:6], 0.005, atol=0)
    assert np.max(np.abs(off[:, 6:12])) < 0.005


@pytest.mark.parametrize("model", ["dynamics",
                                   pytest.param("kinematics", marks=pytest.mark.slow)])
def test_reduced_run_is_finite_and_bounded(flight, model):
    res, (m, c) = _result(flight, model)
    m = {k: float(v) for k, v in m.items()}
    assert int(c["non_finite"]) == 0 and int(c["overflow"]) == 0
    assert np.all(np.isfinite(np.asarray(res.steps.pose_mean)))
    assert m["pos_rmse_m"] < 0.15, m
    assert m["att_rmse_deg"] < 3.0, m
    assert m["landmark_rmse_m"] < 0.3, m
    assert 1.0 <= m["neff_min"] <= N
    p = res.final.particles
    # the normalisation in NumPy/SciPy (eager jax.scipy compiled a program per operation)
    np.testing.assert_allclose(float(special.logsumexp(np.asarray(p.log_w))), 0.0, atol=1e-12)
    assert bool(np.all(np.asarray(p.active)))  # all four poles mapped in every particle
    if model == "kinematics":
        # The baseline does not calibrate: its offset estimate stays 0.
        np.testing.assert_array_equal(np.asarray(res.steps.bias_mean), 0.0)
    else:
        assert m["accel_bias_err"] < 0.01 and m["gyro_bias_err"] < 0.01


def test_registered_and_bad_input():
    sc_ = registry.get("fastslam-helix")
    assert {o.name for o in sc_.options} >= {"model", "bias", "particles", "inertia_mismatch",
                                              "weights", "resampling", "duration"}
    for bad in (0, -3):
        with pytest.raises(InputError, match="particles"):
            sc.build(_opts(particles=bad), jnp.float64)
    log0 = fs1.Log(x0=jnp.zeros(12), rotor_w=None, imu=None, z=None, ids=None, mask=None)
    with pytest.raises(InputError, match="n_particles"):
        fs1.init(log0, fs1.Config(n_particles=0), fs1.default_params(), key=jax.random.PRNGKey(0))
    with pytest.raises(InputError, match="key"):
        fs1.init(log0, fs1.Config(), fs1.default_params(), key=None)
    log1 = fs1.Log(x0=np.zeros(12), rotor_w=np.zeros((20, 4)), imu=np.zeros((20, 5)),
                   z=np.zeros((2, 4, 3)), ids=np.arange(4), mask=np.ones((2, 4), bool))
    with pytest.raises(InputError, match=r"log\.imu: expected shape \(T, 6\)"):
        fs1.run(log1, fs1.Config(), fs1.default_params(), key=jax.random.PRNGKey(0))
    with pytest.raises(InputError, match=r"log\.mask"):
        fs1.run(log1._replace(imu=np.zeros((20, 6)), mask=np.ones((3, 4), bool)), fs1.Config(),
                fs1.default_params(), key=jax.random.PRNGKey(0))
    with pytest.raises(InputError, match="duration"):
        sc.build(_opts(duration=0.0), jnp.float64)
    with pytest.raises(InputError, match="model"):
        fs1.validate_config(fs1.Config(model="odometry"))
    with pytest.raises(InputError, match="proposal_var"):
        fs1.validate_params_001(fs1.default_params()._replace(proposal_var=-jnp.ones(12)))


def _lidar_loss_setup(flight):
    """Loss of one LiDAR frame (update of a mapped landmark set, soft resampling, stage 2)."""
    setup, fl = flight
    n = 8
    cfg = fs1.Config(n_particles=n, resampling="soft")
    prm = fs1.default_params("dynamics", dtype=jnp.float64)._replace(resample_threshold=None, soft_alpha=0.5)
    ids = jnp.arange(4, dtype=jnp.int32)

    def state():
        log = fs1.Log(x0=fl.truth[10], rotor_w=None, imu=None, z=None, ids=None, mask=None)
        st = fs1.init(log, cfg, prm, key=jax.random.PRNGKey(1))
        off = 0.05 * jax.random.normal(jax.random.PRNGKey(5), (n, 4, 3), jnp.float64)
        p = st.particles._replace(
            lm_mean=setup.landmarks[None] + off,
            lm_cov=jnp.broadcast_to(jnp.eye(3) * 4e-3, (n, 4, 3, 3)),
            active=jnp.ones((n, 4), bool),
            ids=jnp.broadcast_to(jnp.arange(4, dtype=jnp.int32), (n, 4)))
        return st._replace(particles=p)

    def loss(log_r):
        # the state is built in the caller's compiled program, not by eager dispatch
        st, truth_pos = state(), fl.truth[10, 0:3]
        p2 = fs1.with_log_noise(prm, log_r=log_r)
        s, _ = fs1.lidar_stage(st, fl.z[0], ids, fl.mask[0], jax.random.PRNGKey(2), cfg, p2)
        mean, _ = fs1.estimate(s)
        return jnp.sum((mean[0:3] - truth_pos) ** 2) + 1e-3 * jnp.sum(s.particles.lm_mean ** 2)

    return loss, jnp.log(prm.lidar_var)


def test_lidar_frame_derivative_matches_finite_differences(flight):
    """Directional derivative (forward mode, cheaper to compile than ``grad``; the reverse
    mode over a whole run is the slow test below) against central differences."""
    loss, x0 = _lidar_loss_setup(flight)
    d = jnp.asarray([0.6, -0.3, 0.74])
    # One compiled function: its primal output at ±h gives the finite difference.
    jvp = jax.jit(lambda t: jax.jvp(lambda u: loss(x0 + u * d), (t,), (jnp.ones_like(t),)))
    val, dval = jvp(jnp.zeros(()))
    assert np.isfinite(float(dval)) and float(dval) != 0.0
    h = 1e-5
    # float64 like the zeros above: a weakly typed Python-float argument would recompile
    fd = (jvp(jnp.asarray(h, jnp.float64))[0] - jvp(jnp.asarray(-h, jnp.float64))[0]) / (2 * h)
    np.testing.assert_allclose(float(dval), float(fd), rtol=1e-4, atol=1e-9)


@pytest.mark.slow
def test_step_loop_equals_run(flight):
    setup, fl = flight
    cfg, prm = sc.make_filter(_opts(particles=16), jnp.float64)
    ids = jnp.arange(4, dtype=jnp.int32)
    E, F = sc.LIDAR_EVERY, 3
    T = E * F
    key = jax.random.PRNGKey(4)
    log = fs1.Log(x0=fl.truth[0], rotor_w=fl.rotor[:T], imu=fl.imu[:T], z=fl.z[:F], ids=ids,
                  mask=fl.mask[:F])
    res = jax.jit(lambda k: fs1.run(log, cfg, prm, key=k))(key)
    k_init, k_run = jax.random.split(key)
    st = fs1.init(log, cfg, prm, key=k_init)
    step = jax.jit(lambda s, i, k: fs1.step(s, i, cfg, prm, key=k))
    keys = jax.random.split(k_run, T)
    no = jnp.zeros((4,), bool)
    for k in range(T):
        f = k // E
        last = (k + 1) % E == 0
        inp = fs1.Event(fl.rotor[k], fl.imu[k], fl.z[f], ids, fl.mask[f] if last else no)
        st, out = step(st, inp, keys[k])
        np.testing.assert_allclose(np.asarray(out.pose_mean), np.asarray(res.steps.pose_mean[k]),
                                   rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(st.particles.pose),
                               np.asarray(res.final.particles.pose), atol=1e-12)
    np.testing.assert_allclose(np.asarray(st.particles.lm_mean),
                               np.asarray(res.final.particles.lm_mean), atol=1e-12)


@pytest.mark.slow
def test_whole_run_gradient_wrt_log_q_and_log_r(flight):
    setup, fl = flight
    cfg, prm = sc.make_filter(_opts(resampling="soft", resample_threshold=1.0, particles=8),
                              jnp.float64)
    ids = jnp.arange(4, dtype=jnp.int32)
    E, F = sc.LIDAR_EVERY, 2
    T = E * F

    def loss(theta):
        p2 = fs1.with_log_noise(prm, theta[:12], theta[12:])
        log = fs1.Log(x0=fl.truth[0], rotor_w=fl.rotor[:T], imu=fl.imu[:T], z=fl.z[:F], ids=ids,
                      mask=fl.mask[:F])
        res = fs1.run(log, cfg, p2, key=jax.random.PRNGKey(9))
        e = res.steps.pose_mean[:, 0:3] - fl.truth[1:T + 1, 0:3]
        return jnp.mean(jnp.sum(e * e, axis=1))

    x0 = jnp.concatenate([jnp.log(prm.proposal_var), jnp.log(prm.lidar_var)])
    g = jax.jit(jax.grad(loss))(x0)
    assert np.all(np.isfinite(np.asarray(g)))
    f = jax.jit(loss)
    d = jax.random.normal(jax.random.PRNGKey(0), (15,), jnp.float64)
    h = 1e-5
    fd = (f(x0 + h * d) - f(x0 - h * d)) / (2 * h)
    np.testing.assert_allclose(float(jnp.dot(g, d)), float(fd), rtol=1e-3, atol=1e-12)


def test_run_json_keeps_a_threshold_of_none_as_none():
    # --resample-threshold 1 (resample at every update) is resample_threshold None; the run
    # JSON's config wrote it as NaN (null), which reads as "no threshold given"
    import json

    _, prm = sc.make_filter(_opts(resample_threshold=1.0), jnp.float64)
    assert prm.resample_threshold is None
    doc = json.loads(json.dumps(sc._params_json(prm)))
    assert doc["resample_threshold"] is None and "quad" not in doc
    np.testing.assert_allclose(doc["lidar_var"], np.asarray(prm.lidar_var))
    _, prm = sc.make_filter(_opts(resample_threshold=0.5), jnp.float64)
    assert sc._params_json(prm)["resample_threshold"] == 0.5
