"""Every public runner compiles once: a second call with new numbers neither traces nor compiles.

* Scenario runners (``jaxslam run``): the Monte Carlo program and the controller/reference
  program are kept by :func:`jaxslam.compilation.compile_program`; a second ``run`` with
  another seed traces nothing (checked with the compile account, which counts JAX's own
  trace and compile events).
* Real-log runners (``jaxslam dataset``): the jitted system scans take every number as a
  traced argument; their jit caches hold one entry after calls with other noise values.
"""

import pathlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam import compilation
from jaxslam.data.mrclam import load_mrclam
from jaxslam.progress import Progress
from jaxslam.sim.scenarios import registry

DATA = pathlib.Path(__file__).resolve().parent / "data"

SCENARIOS = {  # short flights: one program each (the seed changes the noise, not the program)
    "ekfslam3d-known": {"duration": 0.5},  # (ekfslam3d-unknown flies in tests/sim, tests/tuning)
    "uwb-circle": {"duration": 20.0},
    "attitude-smc": {"duration": 0.2, "perturbation": "random"},
    "lineslam-room": {"duration": 2.0},
}


@pytest.mark.parametrize("name", sorted(SCENARIOS))
def test_scenario_second_call_with_new_seed_traces_nothing(name):
    sc = registry.get(name)
    opts = {o.name: o.default for o in sc.options}
    opts.update(SCENARIOS[name])
    kw = dict(runs=2, dtype=np.dtype(np.float64), options=opts, progress=Progress.null())
    first = sc.run(seed=0, **kw)
    with compilation.account() as acc:
        second = sc.run(seed=1, **kw)
    a = acc.result
    assert a.trace_s == 0.0 and a.programs == 0, a
    some = next(iter(first.metrics))
    assert not np.array_equal(first.metrics[some], second.metrics[some])  # new numbers did run


def _mrclam_log():
    from jaxslam.data import presets

    log, pose0 = presets.mrclam_raw_log(load_mrclam(DATA, 1), K=8)
    return log, jnp.asarray(pose0)


def test_planar_ekf_slam_compiles_once_for_new_noise():
    from jaxslam.data import presets
    from jaxslam.systems import planar_ekf_slam as pe

    log, pose0 = _mrclam_log()
    cfg = presets.mrclam_config(association="known")
    prm = presets.mrclam_params(1, dtype=np.float64)
    n0 = pe._run._cache_size()
    a = pe.run(pe.log_from_events(log, pose0), cfg, prm)
    b = pe.run(pe.log_from_events(log, pose0), cfg, prm._replace(R=prm.R * 1.7, M_c=prm.M_c * 0.5))
    assert pe._run._cache_size() == n0 + 1
    assert not np.allclose(np.asarray(a.pose), np.asarray(b.pose))


def test_planar_fastslam_compiles_once_for_new_noise_and_key():
    from jaxslam.data import runners
    from jaxslam.systems import planar_fastslam as pf

    from jaxslam.data import presets

    log, pose0 = _mrclam_log()
    subjects = presets.mrclam_subjects(load_mrclam(DATA, 1))
    cfg, prm, id_map, _ = runners._mrclam_fastslam(1, 16, "known", subjects, 8)
    log = log._replace(ids=runners._known_slots(log.ids, log.mask, id_map))
    prm = jax.tree_util.tree_map(lambda v: jnp.asarray(v, jnp.float64), prm)
    n0 = pf._run._cache_size()
    pf.run(pf.log_from_events(log, pose0), cfg, prm, key=jax.random.PRNGKey(0))
    scaled = prm._replace(**{f: getattr(prm, f) * 1.3 for f in prm._fields[:1]})
    pf.run(pf.log_from_events(log, pose0), cfg, scaled, key=jax.random.PRNGKey(1))
    assert pf._run._cache_size() == n0 + 1


def test_range_only_runners_compile_once():
    from jaxslam.data.util_uwb import load_util
    from jaxslam.systems import util_range as ur

    d = load_util(DATA, "twr_obs_log1")
    log = ur.util_events(d.twr_t, d.twr_anchor, d.twr_range)
    aid = np.asarray(d.anchor_id)
    n0 = ur._run._cache_size()
    ur.run(ur.log_from_events(log, aid, anchors=d.anchor_p))
    p = ur.PARAMS
    other = p._replace(**{f: np.asarray(getattr(p, f)) * 1.5 for f in p._fields
                          if np.asarray(getattr(p, f)).dtype.kind == "f"})
    # other numbers (anchors, noise): the same program
    ur.run(ur.log_from_events(log, aid, anchors=np.asarray(d.anchor_p) + 0.05), ur.Config(), other)
    assert ur._run._cache_size() == n0 + 1


def test_plaza_range_runner_compiles_once():
    from jaxslam.data.plaza import load_plaza
    from jaxslam.systems import plaza_range as pr

    d = load_plaza(DATA, 1)
    events = pr.plaza_events(d.dr_t, d.dr, d.td_t, d.td_node, d.td_range)
    bid = np.asarray(d.node_id)
    log = pr.log_from_events(events, np.asarray(d.start_pose()), bid, beacons=np.asarray(d.node_xy),
                             dtype=jnp.float64)
    n0 = pr._run._cache_size()
    a = pr.run(log, pr.Config(), pr.PARAMS)
    b = pr.run(log._replace(pose0=log.pose0 + 0.1), pr.Config(), pr.PARAMS._replace(sigma_r=pr.PARAMS.sigma_r * 2))
    assert pr._run._cache_size() == n0 + 1
    assert not np.allclose(np.asarray(a.pos), np.asarray(b.pos))


def test_ekf_slam_3d_runner_compiles_once():
    from jaxslam.sensors import imu as imu_mod
    from jaxslam.sim.scenarios import tracking
    from jaxslam.sim.simulate import simulate
    from jaxslam.sensors import landmarks as lm_mod
    from jaxslam.systems import ekf_slam_3d as s3

    lms = lm_mod.generate_landmarks(jax.random.PRNGKey(3), 12, center=(0.0, 0.0, -3.0), dtype=jnp.float64)
    setup = tracking.make_setup(tracking.paper000_figure8(), jnp.float64, landmarks=lms)
    fl = jax.jit(lambda k: simulate(setup, k, 20, 10))(jax.random.PRNGKey(1))
    imu = jnp.concatenate([jnp.array([[0.0, 0.0, -9.81, 0.0, 0.0, 0.0]]), fl.imu])
    log = s3.Log(s0=fl.truth[0, :9], imu=imu, y=fl.lidar_y, visible=fl.lidar_mask, ids=jnp.arange(12))
    noise = s3.imu_noise(imu_mod.PAPER000_IMU)
    cfg = s3.Config(mode="unknown", capacity=12, max_obs=12)
    n0 = s3._run._cache_size()
    a = s3.run(log, cfg, noise)
    b = s3.run(log._replace(y=log.y + 0.01), cfg, jax.tree_util.tree_map(lambda v: v * 1.5, noise))
    assert s3._run._cache_size() == n0 + 1
    assert not np.allclose(np.asarray(a.means), np.asarray(b.means))


def test_uwb_slam_2d_runner_compiles_once():
    from jaxslam.sim.scenarios import uwb as S
    from jaxslam.systems import uwb_slam_2d as U

    setup = S.make_setup("circle", duration=10.0)
    log = jax.jit(lambda k: S.simulate(k, setup, jnp.float64).log)(jax.random.PRNGKey(0))
    cfg = U.Config(mode="localization", model="range")
    fp = U.matched_params("range")
    n0 = U._run._cache_size()
    a = U.run(log._replace(anchors=jnp.asarray(setup.anchors)), cfg, fp)
    b = U.run(log._replace(anchors=jnp.asarray(setup.anchors) + 0.05, ranges=log.ranges + 0.01), cfg,
              fp._replace(r_range=fp.r_range * 1.5, Q=fp.Q * 2.0))
    assert U._run._cache_size() == n0 + 1
    assert not np.allclose(np.asarray(a.steps.mean), np.asarray(b.steps.mean))


def test_generic_ekf_slam_runner_under_the_callers_jit_compiles_once():
    """The generic runner leaves jit to the caller: new noise and new data reuse the program."""
    from jaxslam.filters import ekf_slam as es

    model = es.SlamModel(robot_dim=2, lm_dim=2, meas_dim=2, motion=lambda s, u, p=None: s + u,
                         observe=lambda s, l, p=None: l - s, inverse=lambda s, z, p=None: s + z)
    T, K = 20, 3
    rng = np.random.default_rng(0)
    log = es.SlamLog(u=jnp.asarray(rng.normal(size=(T, 2)) * 0.1), z=jnp.asarray(rng.normal(size=(T, K, 2))),
                     ids=jnp.tile(jnp.arange(K), (T, 1)), mask=jnp.ones((T, K), bool))
    run = jax.jit(lambda log, q, r: es.run(model, es.init(jnp.zeros(2), jnp.eye(2), 4, 2), log,
                                           q * jnp.eye(2), r * jnp.eye(2)).robot)
    a = run(log, 0.01, 0.1)
    b = run(log._replace(z=log.z * 1.1), 0.02, 0.3)
    assert run._cache_size() == 1
    assert not np.allclose(np.asarray(a), np.asarray(b))


# Thresholds and gates are Params fields (traced): a new value reuses the program, and the value
# is really used (the second run differs), so the tests cannot pass vacuously.

def test_uwb_slam_2d_new_thresholds_neither_retrace_nor_recompile():
    from jaxslam.sim.scenarios import uwb as S
    from jaxslam.systems import uwb_slam_2d as U

    setup = S.make_setup("circle", duration=10.0)
    log = jax.jit(lambda k: S.simulate(k, setup, jnp.float64).log)(jax.random.PRNGKey(0))
    log = log._replace(anchors=jnp.asarray(setup.anchors))
    cfg = U.Config(mode="localization", model="range")
    fp = U.matched_params("range")._replace(gate=9.0)
    a = U.run(log, cfg, fp)
    n1 = U._run._cache_size()  # (an earlier test may have compiled the same program)
    tight = fp._replace(gate=0.05, near_gate=40.0, init_speed_bound=2.0, min_spread=0.1,
                        startup_min_points=4, delayed_min_points=3)
    with compilation.account() as acc:
        b = U.run(log, cfg, tight)
    assert acc.result.trace_s == 0.0 and acc.result.programs == 0, acc.result
    assert U._run._cache_size() == n1
    # the much tighter χ² gate and near-anchor gate drop range rows: fewer update dofs, more skipped
    assert int(np.sum(b.steps.dof)) < int(np.sum(a.steps.dof))
    assert int(b.final.near) > int(a.final.near)
    assert not np.allclose(np.asarray(a.steps.mean), np.asarray(b.steps.mean))


def test_util_range_new_gate_neither_retraces_nor_recompiles():
    from jaxslam.data.util_uwb import load_util
    from jaxslam.systems import util_range as ur

    d = load_util(DATA, "twr_obs_log1")
    log = ur.log_from_events(ur.util_events(d.twr_t, d.twr_anchor, d.twr_range), np.asarray(d.anchor_id),
                             anchors=d.anchor_p, dtype=jnp.float64)
    a = ur.run(log, ur.Config(), ur.PARAMS)
    n1 = ur._run._cache_size()
    with compilation.account() as acc:
        b = ur.run(log, ur.Config(), ur.PARAMS._replace(gate=0.5))
    assert acc.result.trace_s == 0.0 and acc.result.programs == 0, acc.result
    assert ur._run._cache_size() == n1
    assert int(b.n_gated) > int(a.n_gated) and int(b.n_used) < int(a.n_used)


def test_plaza_range_new_gate_and_init_thresholds_neither_retrace_nor_recompile():
    from jaxslam.data.plaza import load_plaza
    from jaxslam.systems import plaza_range as pr

    d = load_plaza(DATA, 2)
    events = pr.plaza_events(d.dr_t, d.dr, d.td_t, d.td_node, d.td_range)
    log = pr.log_from_events(events, np.asarray(d.start_pose()), np.asarray(d.node_id), dtype=jnp.float64)
    a = pr.run(log, pr.Config(), pr.PARAMS)  # SLAM: the excerpt is too short for the defaults
    n1 = pr._run._cache_size()
    with compilation.account() as acc:
        b = pr.run(log, pr.Config(), pr.PARAMS._replace(min_points=5, min_spread=0.5))
        c = pr.run(log, pr.Config(), pr.PARAMS._replace(min_points=5, min_spread=0.5, gate=1e-4))
    assert acc.result.trace_s == 0.0 and acc.result.programs == 0, acc.result
    assert pr._run._cache_size() == n1
    # looser delayed-init thresholds map beacons the defaults leave unmapped; a tight gate gates ranges
    assert int(a.n_registered) == 0 and int(b.n_registered) > 0 and int(b.n_used) > 0
    assert int(c.n_gated) > int(b.n_gated)


def test_planar_ekf_slam_new_gates_and_limits_neither_retrace_nor_recompile():
    from jaxslam.data import presets
    from jaxslam.systems import planar_ekf_slam as pe

    log, pose0 = _mrclam_log()
    cfg = presets.mrclam_config(association="nn")  # ids hidden: the gate and new_threshold are read
    prm = presets.mrclam_params(1, dtype=np.float64)._replace(range_max=100.0)
    a = pe.run(pe.log_from_events(log, pose0), cfg, prm)
    n1 = pe._run._cache_size()
    tight = prm._replace(gate=0.5, new_threshold=60.0, range_max=1.7)
    with compilation.account() as acc:
        b = pe.run(pe.log_from_events(log, pose0), cfg, tight)
    assert acc.result.trace_s == 0.0 and acc.result.programs == 0, acc.result
    assert pe._run._cache_size() == n1
    # the shorter range limit masks rows; the much tighter gate (with a higher new-landmark
    # threshold) leaves more sightings ambiguous: fewer used, more rejected
    assert int(np.sum(b.n_limited)) > int(np.sum(a.n_limited))
    assert int(np.sum(b.n_used)) < int(np.sum(a.n_used))
    assert int(np.sum(b.n_rejected)) > int(np.sum(a.n_rejected))
    assert not np.allclose(np.asarray(a.pose), np.asarray(b.pose))


def test_planar_fastslam_new_gate_and_thresholds_neither_retrace_nor_recompile():
    from jaxslam.data import presets
    from jaxslam.systems import planar_fastslam as pf

    log, pose0 = _mrclam_log()
    cfg, prm = presets.mrclam_fastslam_setup(1, n_particles=16, association="ml")
    prm = jax.tree_util.tree_map(lambda v: jnp.asarray(v, jnp.float64), prm._replace(gate=9.21))
    key = jax.random.PRNGKey(0)
    a = pf.run(pf.log_from_events(log, pose0), cfg, prm, key=key)
    n1 = pf._run._cache_size()
    with compilation.account() as acc:
        b = pf.run(pf.log_from_events(log, pose0), cfg, prm._replace(gate=0.05, new_threshold=200.0), key=key)
        c = pf.run(pf.log_from_events(log, pose0), cfg, prm._replace(resample_threshold=0.99), key=key)
    assert acc.result.trace_s == 0.0 and acc.result.programs == 0, acc.result
    assert pf._run._cache_size() == n1
    # same key, other thresholds: more detections fall between the gate and the new-landmark
    # threshold (ignored, counted as gated) and fewer start landmarks; a higher resampling
    # threshold resamples more often
    assert float(b.gated) > float(a.gated)
    assert float(b.registered) < float(a.registered)
    assert int(c.resamples) > int(a.resamples)


def test_ekf_slam_3d_new_gate_and_association_thresholds_neither_retrace_nor_recompile():
    from jaxslam.sensors import imu as imu_mod
    from jaxslam.sensors import landmarks as lm_mod
    from jaxslam.sim.scenarios import tracking
    from jaxslam.sim.simulate import simulate
    from jaxslam.systems import ekf_slam_3d as s3

    lms = lm_mod.generate_landmarks(jax.random.PRNGKey(3), 12, center=(0.0, 0.0, -3.0), dtype=jnp.float64)
    setup = tracking.make_setup(tracking.paper000_figure8(), jnp.float64, landmarks=lms)
    fl = jax.jit(lambda k: simulate(setup, k, 20, 10))(jax.random.PRNGKey(1))
    imu = jnp.concatenate([jnp.array([[0.0, 0.0, -9.81, 0.0, 0.0, 0.0]]), fl.imu])
    log = s3.Log(s0=fl.truth[0, :9], imu=imu, y=fl.lidar_y, visible=fl.lidar_mask, ids=jnp.arange(12))
    cfg = s3.Config(mode="unknown", association="nn", capacity=24, max_obs=12)
    loose = s3.imu_noise(imu_mod.PAPER000_IMU)._replace(gate=16.27)
    a = s3.run(log, cfg, loose)
    n1 = s3._run._cache_size()
    with compilation.account() as acc:
        b = s3.run(log, cfg, loose._replace(gate=0.05, nn_gate=0.5, nn_new=1.0))
    assert acc.result.trace_s == 0.0 and acc.result.programs == 0, acc.result
    assert s3._run._cache_size() == n1
    # the new numbers did act: a tight gate uses fewer rows, a low new-landmark threshold maps more
    assert int(np.sum(b.frames.dof)) < int(np.sum(a.frames.dof))
    assert int(b.frames.n_active[-1]) > int(a.frames.n_active[-1])


def test_line_slam_004_new_gates_and_thresholds_neither_retrace_nor_recompile():
    from jaxslam.sim.scenarios import lineslam as sc
    from jaxslam.systems import line_slam_004 as LS

    setup = sc.make_setup(duration=3.0)
    cfg = LS.Config()
    log = jax.jit(lambda k: sc.simulate(k, setup, cfg.spec, jnp.float64))(jax.random.PRNGKey(3))
    fp = LS.default_params()
    key = jax.random.PRNGKey(5)
    a = LS.run(log, cfg, fp, key=key)
    n1 = LS._run._cache_size()
    with compilation.account() as acc:
        b = LS.run(log, cfg, fp._replace(nis_gate=0.01, new_threshold=1e6, min_update_inliers=5.0), key=key)
    assert acc.result.trace_s == 0.0 and acc.result.programs == 0, acc.result
    assert LS._run._cache_size() == n1
    # the new numbers did act: the tight gate gates matched lines, the huge threshold maps none
    assert int(np.sum(b.steps.n_gated)) > int(np.sum(a.steps.n_gated))
    assert int(np.sum(b.steps.n_new)) < int(np.sum(a.steps.n_new))


def test_fastslam_001_new_resampling_numbers_neither_retrace_nor_recompile():
    from jaxslam.sim.scenarios import fastslam as sc
    from jaxslam.systems import fastslam_001 as fs1

    opts = {o.name: o.default for o in sc.OPTIONS}
    opts["particles"] = 16
    cfg, prm = sc.make_filter(opts, jnp.float64)
    setup = sc.truth_setup(float(opts["bias"]), jnp.float64)
    fl = jax.jit(lambda k: sc.fly(setup, k, 3, sc.LIDAR_EVERY, cfg.lidar, cfg.accel_mode))(jax.random.PRNGKey(1))
    log = fs1.Log(x0=fl.truth[0], rotor_w=fl.rotor, imu=fl.imu, z=fl.z, ids=jnp.arange(4, dtype=jnp.int32),
                  mask=fl.mask)
    key = jax.random.PRNGKey(2)
    a = fs1.run(log, cfg, prm._replace(resample_threshold=0.1), key=key)
    n1 = fs1._run._cache_size()
    with compilation.account() as acc:
        b = fs1.run(log, cfg, prm._replace(resample_threshold=1.0), key=key)
    assert acc.result.trace_s == 0.0 and acc.result.programs == 0, acc.result
    assert fs1._run._cache_size() == n1
    assert not np.allclose(np.asarray(a.steps.pose_mean), np.asarray(b.steps.pose_mean))  # the new threshold acted
