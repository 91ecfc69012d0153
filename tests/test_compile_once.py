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
    "ekfslam3d-unknown": {"duration": 0.5},
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
    from jaxslam.systems import planar_ekf_slam as pe

    log, pose0 = pe.mrclam_raw_log(load_mrclam(DATA, 1), K=8)
    return log, jnp.asarray(pose0)


def test_planar_ekf_slam_compiles_once_for_new_noise():
    from jaxslam.systems import planar_ekf_slam as pe

    log, pose0 = _mrclam_log()
    cfg = pe.mrclam_config(association="known")
    prm = pe.mrclam_params(1, dtype=np.float64)
    n0 = pe._run._cache_size()
    a = pe.run(pe.log_from_events(log, pose0), cfg, prm)
    b = pe.run(pe.log_from_events(log, pose0), cfg, prm._replace(R=prm.R * 1.7, M_c=prm.M_c * 0.5))
    assert pe._run._cache_size() == n0 + 1
    assert not np.allclose(np.asarray(a.pose), np.asarray(b.pose))


def test_planar_fastslam_compiles_once_for_new_noise_and_key():
    from jaxslam.data import runners
    from jaxslam.systems import planar_fastslam as pf

    log, pose0 = _mrclam_log()
    cfg, prm, id_offset, _ = runners._mrclam_fastslam(1, 16, "known")
    if id_offset:
        log = log._replace(ids=np.where(log.mask, log.ids - id_offset, -1).astype(np.int32))
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
