"""Closed-loop flight scan, Monte Carlo runner and the tracking scenarios."""

import json
import os
import subprocess
import sys
import textwrap

import numpy as np
import jax
import jax.numpy as jnp
import pytest

from jaxslam.errors import InputError
from jaxslam.progress import Progress
from jaxslam.sim import monte_carlo
from jaxslam.sim.scenarios import registry


def _run(name, runs=2, dtype=np.float64, **opts):
    sc = registry.get(name)
    options = {o.name: o.default for o in sc.options}
    options.update(opts)
    return sc.run(runs=runs, seed=0, dtype=np.dtype(dtype), options=options,
                  progress=Progress.null())


@pytest.fixture(scope="module")
def figure8():
    return _run("track-figure8", runs=2)


def test_track_figure8_converges_from_the_origin(figure8):
    m = figure8.metrics
    # acceptance: settled (t > 10 s) tracking RMSE below 5 cm
    assert np.all(m["track_pos_rmse_settled_m"] < 0.05), m["track_pos_rmse_settled_m"]
    assert np.all(m["settle_time_s"] < 20.0)
    assert np.all(m["max_tilt_deg"] < 30.0)
    assert figure8.flags["non_finite"] == 0
    # the whole-flight RMSE includes the climb from the origin to the figure-8
    assert np.all(m["track_pos_rmse_m"] > m["track_pos_rmse_settled_m"])


def test_track_helix_converges():
    r = _run("track-helix", runs=1)
    assert r.metrics["track_pos_rmse_settled_m"][0] < 0.05, r.metrics


def test_float32_flight_runs_and_agrees(figure8):
    r32 = _run("track-figure8", runs=2, dtype=np.float32)
    for k in ("track_pos_rmse_settled_m", "max_tilt_deg"):
        assert np.all(np.isfinite(r32.metrics[k]))
        np.testing.assert_allclose(r32.metrics[k], figure8.metrics[k], rtol=0.05)


def test_bad_duration_is_an_input_error():
    with pytest.raises(InputError, match="--duration"):
        _run("track-figure8", runs=1, duration=-1.0)


@pytest.mark.parametrize("change, n_frame, lidar_every, extra, needle", [
    ({}, 0, 10, {}, "^n_frame: expected an int >= 1"),
    ({}, 2.0, 10, {}, "^n_frame: expected an int >= 1"),
    ({}, 2, 0, {}, "^lidar_every: expected an int >= 1"),
    ({"dt": 0.0}, 2, 10, {}, "^setup.dt: expected a positive"),
    ({"dt": -0.01}, 2, 10, {}, "^setup.dt: expected a positive"),
    ({"dt": 0.02}, 2, 10, {}, "^setup.imu.rate: must equal 1/setup.dt = 50 Hz"),
    ({"x0": np.full(12, np.nan)}, 2, 10, {}, "^setup.x0: holds a NaN"),
    ({"x0": np.zeros(13)}, 2, 10, {}, r"^setup.x0: expected shape \(12\)"),
    ({"x0": np.zeros(12, np.int32)}, 2, 10, {}, "^setup.x0: expected a floating-point"),
    ({"landmarks": np.zeros((4, 2))}, 2, 10, {}, r"^setup.landmarks: expected shape \(\*, 3\)"),
    ({"landmarks": np.array([[0.0, np.inf, 1.0]])}, 2, 10, {}, "^setup.landmarks: holds a NaN"),
    ({}, 2, 10, {"K": np.zeros((4, 6))}, r"^K: expected shape \(4, 7\)"),
    ({}, 2, 10, {"refs": "short"}, "^refs: expected reference_grid"),
])
def test_simulate_names_a_bad_setup_before_tracing(change, n_frame, lidar_every, extra, needle):
    from jaxslam.sim.scenarios.tracking import make_setup, paper000_figure8
    from jaxslam.sim.simulate import reference_grid, simulate
    setup = make_setup(paper000_figure8(2.0, 0.0), jnp.float32)._replace(**change)
    if extra.get("refs") == "short":  # a grid for fewer steps than the flight flies
        extra = {"refs": reference_grid(setup, 5)}
    with pytest.raises(InputError, match=needle):
        simulate(setup, jax.random.PRNGKey(0), n_frame, lidar_every, **extra)


def test_monte_carlo_is_independent_of_chunking():
    def fn(key):
        x = jax.random.normal(key, (3,))
        return {"s": jnp.sum(x ** 2), "v": x}

    a = monte_carlo.run(fn, seed=5, runs=7, chunk=7)
    b = monte_carlo.run(fn, seed=5, runs=7, chunk=3)
    c = monte_carlo.run(fn, seed=5, runs=7, cpu_batching="loop")
    # The same keys give the same draws; programs compiled for different batch sizes may round
    # the normal's inverse-erf polynomial differently in the last bit (seen: 1 ulp at -O0).
    ulp = 4 * np.finfo(np.float64).eps
    for other in (b, c):
        np.testing.assert_allclose(a.out["s"], other.out["s"], rtol=ulp, atol=0)
        np.testing.assert_allclose(a.out["v"], other.out["v"], rtol=ulp, atol=0)
    assert a.out["v"].shape == (7, 3) and c.chunk == 1
    # run i uses fold_in(PRNGKey(seed), i): reproducible one by one
    k3 = jax.random.fold_in(jax.random.PRNGKey(5), 3)
    np.testing.assert_allclose(a.out["v"][3], np.asarray(jax.random.normal(k3, (3,))), rtol=ulp, atol=0)


def test_monte_carlo_loop_threads_give_the_same_runs_in_order():
    # each run is the same compiled program on its own key, whichever thread calls it
    def fn(key):
        x = jax.random.normal(key, (8,))
        return {"s": jnp.sum(jnp.sin(x) ** 2), "v": x}

    one = monte_carlo.run(fn, seed=4, runs=9, cpu_batching="loop", threads=1)
    three = monte_carlo.run(fn, seed=4, runs=9, cpu_batching="loop", threads=3)
    assert (one.threads, three.threads, three.runs, three.interrupted) == (1, 3, 9, False)
    np.testing.assert_array_equal(one.out["v"], three.out["v"])
    np.testing.assert_array_equal(one.out["s"], three.out["s"])
    vm = monte_carlo.run(fn, seed=4, runs=9, threads=3)  # threads only serve "loop" batching
    assert vm.threads == 1


def test_monte_carlo_thread_errors_reach_the_caller(monkeypatch):
    # run 0's output is checked inside a worker thread; the error is raised by run() itself
    with pytest.raises(InputError, match="detail=True"):
        monte_carlo.run(lambda k: {"x": jax.random.normal(k, (2,))}, seed=0, runs=4, cpu_batching="loop",
                        detail=True, threads=2)
    with pytest.raises(InputError, match="threads"):
        monte_carlo.run(lambda k: k, seed=0, runs=2, cpu_batching="loop", threads=0)
    monkeypatch.setenv("JAXSLAM_MC_THREADS", "two")
    with pytest.raises(InputError, match="JAXSLAM_MC_THREADS"):
        monte_carlo.run(lambda k: k, seed=0, runs=2, cpu_batching="loop")
    monkeypatch.setenv("JAXSLAM_MC_THREADS", "3")
    assert monte_carlo.default_threads() == 3


@pytest.mark.parametrize("batching", ["vmap", "loop"])
def test_monte_carlo_compiles_a_function_once(batching):
    # a second run() of the same fn (new seed, the same chunk) neither traces nor compiles
    traces = []

    def fn(key):
        traces.append(1)
        return jnp.sum(jax.random.normal(key, (3,)) ** 2)

    a = monte_carlo.run(fn, seed=1, runs=4, chunk=2, cpu_batching=batching)
    b = monte_carlo.run(fn, seed=2, runs=4, chunk=2, cpu_batching=batching)
    assert len(traces) == 1, len(traces)
    assert b.compile_s < a.compile_s
    fresh = monte_carlo.run(lambda k: fn(k), seed=2, runs=4, chunk=2, cpu_batching=batching)
    np.testing.assert_array_equal(b.out, fresh.out)
    assert len(traces) == 2  # another function object: its own program
    monte_carlo.clear_programs()  # with JAX's own caches (which hold the loop's jit(fn) trace)
    jax.clear_caches()
    monte_carlo.run(fn, seed=3, runs=4, chunk=2, cpu_batching=batching)
    assert len(traces) == 3


def test_sharded_monte_carlo_equals_single_device(tmp_path):
    """Two forced host devices (subprocess) give the same results as one device."""
    code = textwrap.dedent("""
        import json, sys
        import jax, jax.numpy as jnp
        jax.config.update("jax_enable_x64", True)
        from jaxslam.sim import monte_carlo
        def fn(key):
            x = jax.random.normal(key, (4,))
            return jnp.cumsum(x) @ x
        r = monte_carlo.run(fn, seed=2, runs=6, chunk=3)
        print(json.dumps({"n": r.n_devices, "out": [float(v) for v in r.out]}))
    """)
    outs = []
    for n in (1, 2):
        env = dict(os.environ, XLA_FLAGS=f"--xla_force_host_platform_device_count={n}",
                   JAX_PLATFORMS="cpu")
        p = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                           timeout=300)
        assert p.returncode == 0, p.stderr
        outs.append(json.loads(p.stdout.strip().splitlines()[-1]))
    assert outs[0]["n"] == 1 and outs[1]["n"] == 2
    np.testing.assert_allclose(outs[0]["out"], outs[1]["out"], rtol=0, atol=1e-13)


def test_sharded_monte_carlo_sends_nothing_between_devices():
    """Runs are independent, so the sharded program holds no cross-device collective, even when
    the run reduces over the batch (the active-block engine's shared loop bound, here a
    custom_vmap batch maximum inside a scan), and its results equal one device's."""
    code = textwrap.dedent("""
        import json, re
        import jax, jax.numpy as jnp, numpy as np
        jax.config.update("jax_enable_x64", True)
        from jaxslam.filters import ekf_slam
        from jaxslam.sim import monte_carlo
        def fn(key):
            n = jax.random.randint(key, (), 1, 9)
            def body(c, i):
                hi = ekf_slam._batch_max(n + i)  # the engine's batch-wide loop bound
                own = jax.lax.fori_loop(0, hi, lambda j, a: a + jnp.where(j < n + i, 1.0, 0.0),
                                        jnp.zeros(()))  # depends on the run's n only
                return c + own, None
            c, _ = jax.lax.scan(body, jnp.zeros(()), jnp.arange(5))
            return c
        devs = jax.local_devices()
        keys = jax.device_put(monte_carlo.keys_for(0, 8), None)
        _, jitted, shard = monte_carlo._program(fn, devs, False, {})
        hlo = jitted.lower(jax.device_put(keys, shard)).compile().as_text()
        coll = re.findall(r"(all-reduce|all-gather|collective-permute|all-to-all|reduce-scatter)\\(", hlo)
        two = monte_carlo.run(fn, seed=0, runs=8)
        one = monte_carlo.run(fn, seed=0, runs=8, devices=devs[:1])
        print(json.dumps({"n": len(devs), "coll": coll, "two": [float(v) for v in two.out],
                          "one": [float(v) for v in one.out]}))
    """)
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2",
               JAX_PLATFORMS="cpu")
    p = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                       timeout=300)
    assert p.returncode == 0, p.stderr[-3000:]
    res = json.loads(p.stdout.strip().splitlines()[-1])
    assert res["n"] == 2 and res["coll"] == [], res
    # Per-device bound vs one device's bound over all 8: the loop extent differs, the values not.
    np.testing.assert_allclose(res["two"], res["one"], rtol=0, atol=0)


def test_simulate_refuses_a_nan_gain_and_a_bad_key():
    """Review of 2026-12-07: a NaN gain K made every state of the flight NaN without a word, and
    an int key was JAX's bare 'invalid PRNG key data' TypeError."""
    from jaxslam.errors import InputError
    from jaxslam.sim import simulate as S
    from jaxslam.sim.scenarios import tracking as T

    setup = T.make_setup(T.paper000_figure8(), jnp.float64, landmarks=jnp.array([[5.0, 0, -1]]))
    with pytest.raises(InputError, match=r"^K: contains NaN or Inf"):
        S.simulate(setup, jax.random.PRNGKey(3), 2, 4, K=jnp.full((4, 7), jnp.nan))
    with pytest.raises(InputError, match=r"^key: expected a PRNG key"):
        S.simulate(setup, 3, 2, 4)
