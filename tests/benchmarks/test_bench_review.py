"""Review fixes of benchmarks/timing.py, bench_ekfslam.py, bench_fastslam.py and bench_sim.py:
bad options stop before any compute with an InputError naming them, a large --seed does not
overflow the PRNG key, and bench sim's pinned-OpenBLAS check flies the same loop as the timed
case (--no-feedforward)."""

import argparse
import pathlib
import sys

import jax
import pytest

from jaxslam.errors import InputError

BENCH = pathlib.Path(__file__).resolve().parents[2] / "benchmarks"
sys.path.insert(0, str(BENCH))
sys.path.insert(0, str(BENCH.parent / "tests" / "oracles"))

import bench_ekfslam  # noqa: E402
import bench_fastslam  # noqa: E402
import timing  # noqa: E402


def _args(module, *opts):
    p = argparse.ArgumentParser()
    module.add_arguments(p)
    return p.parse_args(list(opts))


def _no_compute(monkeypatch, module, *names):
    def boom(*a, **k):
        raise AssertionError("the run started before the options were checked")

    for name in names:
        monkeypatch.setattr(module, name, boom)


# ------------------------------------------------------------------ timing.median_s


@pytest.mark.parametrize("repeats", [0, -2])
def test_median_s_rejects_no_repeats(repeats):
    calls = []
    with pytest.raises(InputError, match="repeats"):
        timing.median_s(lambda: calls.append(1), repeats)
    assert calls == []


def test_median_s_is_the_median_of_the_calls(monkeypatch):
    ticks = iter([0.0, 1.0, 10.0, 13.0, 20.0, 22.0])  # durations 1, 3, 2 -> median 2
    monkeypatch.setattr(timing.time, "perf_counter", lambda: next(ticks))
    assert timing.median_s(lambda: None, 3) == 2.0


# ------------------------------------------------------------------ bench ekfslam durations


@pytest.mark.parametrize("opts,flag", [
    (("--parts", "full", "--duration", "0"), "--duration"),
    (("--parts", "full", "--duration", "-1"), "--duration"),
    (("--parts", "full", "--duration", "0.04"), "--duration"),  # rounds to 0 LiDAR frames
    (("--parts", "mc", "--mc-duration", "0"), "--mc-duration"),
    (("--parts", "mc", "--mc-duration", "-2"), "--mc-duration"),
])
def test_ekfslam_durations_checked_before_compute(monkeypatch, opts, flag):
    _no_compute(monkeypatch, bench_ekfslam, "_run_parts", "_spawn", "run_full", "run_mc")
    with pytest.raises(InputError, match=flag):
        bench_ekfslam.run(_args(bench_ekfslam, *opts))


def test_ekfslam_duration_of_an_unrun_part_is_not_checked(monkeypatch):
    seen = []
    monkeypatch.setattr(bench_ekfslam, "_run_parts", lambda a, p, lbl: seen.append(p) or ([], {"targets": []}))
    monkeypatch.setenv("OPENBLAS_NUM_THREADS", "1")
    bench_ekfslam.run(_args(bench_ekfslam, "--parts", "mc", "--duration", "0", "--mc-duration", "0.1"))
    assert seen == [{"mc"}]


# ------------------------------------------------------------------ bench fastslam


@pytest.mark.parametrize("value", ["0", "-1", "0.04"])
def test_fastslam_mc_duration_checked_before_compute(monkeypatch, value):
    _no_compute(monkeypatch, bench_fastslam, "_run_here", "_spawn")
    with pytest.raises(InputError, match="--mc-duration"):
        bench_fastslam.run(_args(bench_fastslam, "--parts", "mc", "--mc-duration", value))


def test_fastslam_largest_seed_does_not_overflow_the_key():
    import numpy as np
    from bench_inputs import fastslam_mc_jobs

    seed, M = 2**63 - 1, 2  # the largest --seed the CLI accepts
    jobs, (keys, _), N, F_out = fastslam_mc_jobs(bench_fastslam, seed, M=M)
    # seed + 7 as 64 bits (timing.prng_key, two's complement): 2**63 - 1 + 7 -> -2**63 + 6
    expected = jax.random.split(jax.random.PRNGKey(-2**63 + 6), M)
    assert np.array_equal(np.asarray(keys), np.asarray(expected))
    assert (N, F_out) == (3, 1) and [name for name, _ in jobs] == ["mc batch=1", "mc batch=2"]


# (bench sim --openblas-check: tests/benchmarks/test_bench_s36.py, the child flies the timed flight bit for bit)
