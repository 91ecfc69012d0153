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
