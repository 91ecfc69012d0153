"""benchmarks/ review (s36): bench sim's pinned-OpenBLAS child calls the NumPy oracle explicitly on
the timed case's own inputs (no patched ``numpy_flight.simulate``) and flies that flight bit for
bit; bench sim records the duration flown (whole LiDAR frames), not the one asked for."""

import argparse
import hashlib
import pathlib
import sys

import jax
import numpy as np
import pytest

BENCH = pathlib.Path(__file__).resolve().parents[2] / "benchmarks"
sys.path.insert(0, str(BENCH))
sys.path.insert(0, str(BENCH.parent / "tests" / "oracles"))

import bench_sim  # noqa: E402
import numpy_flight  # noqa: E402


def _needs_x64():
    if not jax.config.jax_enable_x64:
        pytest.skip("bench sim needs x64 (tests/conftest.py enables it)")


def _sha(flight):  # written out here, not bench_sim.flight_digest: truth then IMU, float64 bytes
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(flight["truth"], np.float64).tobytes())
    h.update(np.ascontiguousarray(flight["imu"], np.float64).tobytes())
    return h.hexdigest()


# ------------------------------------------------------------------ 1. pinned child, no patching


def test_pinned_child_flies_the_timed_flight_with_the_asked_feedforward():
    """The child ran ``numpy_flight._main`` with ``simulate`` patched (functools.partial) to set
    the feedforward, on its own inputs (rng(0) noise); it now calls ``simulate`` itself on the
    timed case's inputs, so its flight is the in-process one, bit for bit, per feedforward."""
    _needs_x64()
    traj, ctrl, sigma, dt = bench_sim.numpy_inputs(bench_sim.make_setup())
    n = 40
    x0 = np.zeros(12)
    noise = np.random.default_rng(3).standard_normal((n, 6))
    digests = {}
    for ff in (False, True):
        ref = numpy_flight.simulate(traj, ctrl, x0, dt, n, sigma, noise, feedforward_on=ff)
        digests[ff] = _sha(ref)
        assert bench_sim.flight_digest(ref) == digests[ff]
        res = bench_sim._openblas1_numpy(traj, ctrl, x0, dt, n, sigma, noise, 2, ff)
        assert "error" not in res, res
        assert res["flight_sha256"] == digests[ff], ff
        assert res["feedforward"] is ff and res["steps"] == n
        assert res["openblas_num_threads"] == "1" and len(res["times_s"]) == 2
    assert digests[False] != digests[True]  # the feedforward changes the flight: the check can tell


def test_pinned_child_reports_its_error():
    _needs_x64()
    traj, ctrl, sigma, dt = bench_sim.numpy_inputs(bench_sim.make_setup())
    res = bench_sim._openblas1_numpy(traj, ctrl, np.zeros(12), dt, 5, sigma, np.zeros((2, 6)), 1)
    assert list(res) == ["error"] and "IndexError" in res["error"][0]  # 5 steps, 2 rows of noise


# ------------------------------------------------------------------ 2. duration flown


def test_sim_records_the_duration_flown():
    """0.14 s is one LiDAR frame (10 steps of 0.01 s): the JSON said ``duration_s: 0.14``."""
    _needs_x64()
    args = argparse.Namespace(duration=0.14, batches="1", repeats=1, numpy_repeats=1,
                              numpy_batch_max=1, x0_spread=0.5, seed=0, no_feedforward=False,
                              openblas_check=True, profile=False)
    out = bench_sim.run(args)
    rows = {r["case"]: r for r in out["results"]}
    assert set(rows) == {"single", "batch-1"}
    for row in rows.values():
        assert row["params"]["steps"] == 10
        assert row["params"]["duration_s"] == 0.1
        assert row["params"]["duration_asked_s"] == 0.14
    pinned = rows["single"]["reference_openblas1"]
    assert pinned["steps"] == 10 and pinned["same_flight_as_timed"] is True, pinned
