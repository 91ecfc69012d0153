"""The benchmarks' shared helpers (benchmarks/timing.py) and the fixes that came with them.

* ``timing.wrap_seed`` / ``timing.prng_key``: the one seed -> key conversion of bench fastslam
  (was ``% 2**63``), bench lines (was two's complement), bench tuning (refused ``--seed
  2**63 - 1`` when its memory case runs), bench ekfslam and bench sim.  Every seed + offset
  < 2**63 keeps its key; at the top of the CLI's range, ``2**63 - 1 + k`` is the 64-bit two's
  complement ``-2**63 + k - 1`` (the library's ``monte_carlo.seed_key`` reading).
* ``timing.lidar_frames``: the duration -> whole LiDAR frames of bench fastslam (three copies)
  and bench ekfslam (two), with one error naming the option.
* bench fastslam's ``run`` left ``--mc-runs`` (and the defaults) written into the caller's
  namespace.
* bench sim's ``run`` checks ``--duration`` against the option's declared bounds.
"""

import argparse
import math
import pathlib
import sys

import jax
import numpy as np
import pytest

from jaxslam.errors import InputError

BENCH = pathlib.Path(__file__).resolve().parents[2] / "benchmarks"
sys.path.insert(0, str(BENCH))
sys.path.insert(0, str(BENCH.parent / "tests" / "oracles"))

import bench_ekfslam  # noqa: E402
import bench_fastslam  # noqa: E402
import bench_sim  # noqa: E402
import bench_tuning  # noqa: E402
import timing  # noqa: E402

x64 = pytest.mark.skipif(not jax.config.jax_enable_x64, reason="keys of seeds >= 2**32 need x64")
threefry = pytest.mark.skipif(str(jax.config.jax_default_prng_impl) != "threefry2x32",
                              reason="hand values are threefry2x32 keys: [high word, low word]")


class _Reached(Exception):
    """The benchmark got past its option checks to its first piece of work."""


def _reached(*a, **k):
    raise _Reached


def _words(v):
    """Hand layout of a threefry2x32 key of the 64-bit value ``v``: [high word, low word]."""
    return np.array([v >> 32, v & 0xFFFFFFFF], np.uint32)


# ------------------------------------------------------------------ seed -> key


@x64
@threefry
@pytest.mark.parametrize("seed", [0, 1, 12345, 2**62])
@pytest.mark.parametrize("offset", [0, 1, 2, 3, 7])
def test_prng_key_is_the_key_every_bench_made_before(seed, offset):
    # all three old conversions were PRNGKey(seed + offset) below 2**63
    key = np.asarray(timing.prng_key(seed, offset))
    np.testing.assert_array_equal(key, np.asarray(jax.random.PRNGKey(seed + offset)))
    np.testing.assert_array_equal(key, _words(seed + offset))
    assert timing.wrap_seed(seed, offset) == seed + offset


@x64
@threefry
@pytest.mark.parametrize("offset", [0, 1, 2, 3, 7])
def test_largest_seed_wraps_as_64_bits(offset):
    # --seed 2**63 - 1 (the CLI's largest) + offset: the two's complement of 2**63 + offset - 1
    seed = 2**63 - 1
    assert timing.wrap_seed(seed, offset) == (seed if offset == 0 else -2**63 + offset - 1)
    np.testing.assert_array_equal(np.asarray(timing.prng_key(seed, offset)),
                                  _words(2**63 - 1 + offset))
    # the library reads a seed the same way (monte_carlo.seed_key: bench tuning's memory log)
    from jaxslam.sim import monte_carlo

    np.testing.assert_array_equal(monte_carlo.seed_key(timing.wrap_seed(seed, offset)),
                                  _words(2**63 - 1 + offset))


@pytest.mark.parametrize("seed,offset,name", [(1.5, 0, "seed"), (True, 0, "seed"), ("3", 0, "seed"),
                                              (-2**63 - 1, 0, "seed"), (0, -1, "offset"),
                                              (0, 1.0, "offset")])
def test_wrap_seed_names_a_bad_argument(seed, offset, name):
    with pytest.raises(InputError, match=f"^{name}:"):
        timing.wrap_seed(seed, offset)
    with pytest.raises(InputError, match=f"^{name}:"):
        timing.prng_key(seed, offset)


@x64
@threefry
def test_fastslam_largest_seed_mc_keys_are_its_own():
    """bench fastslam's Monte Carlo keys at ``--seed 2**63 - 1``: ``seed + 7`` wrapped as 64 bits.
    They were PRNGKey((2**63 - 1 + 7) % 2**63) = PRNGKey(6), seed 6's stream."""
    import jax.numpy as jnp
    from bench_inputs import fastslam_mc_jobs

    M = 2
    _, (keys, _), _, _ = fastslam_mc_jobs(bench_fastslam, 2**63 - 1, M=M)
    base = _words(2**63 - 1 + 7)  # [0x80000000, 6]
    assert base.tolist() == [0x80000000, 6]
    np.testing.assert_array_equal(np.asarray(keys), np.asarray(jax.random.split(jnp.asarray(base), M)))
    assert not np.array_equal(np.asarray(keys), np.asarray(jax.random.split(jax.random.PRNGKey(6), M)))


def _tuning_args(**kw):
    base = dict(steps=500, runs=2, repeats=5, ratio_blocks=7, memory_steps=2000, no_lqr=False, seed=0)
    return argparse.Namespace(**{**base, **kw})


def test_tuning_largest_seed_runs_with_the_memory_case(monkeypatch):
    """``--seed 2**63 - 1`` with the memory case (SEED + 1) was an InputError; its memory log is
    now seeded ``wrap_seed(SEED, 1)`` = -2**63, which ``make_slam_logs`` takes."""
    from jaxslam import compilation
    from jaxslam.tuning.targets import ekfslam3d as T

    seeds = []

    def first_logs(seed, *a, **k):
        seeds.append(seed)
        raise _Reached

    monkeypatch.setattr(T, "make_slam_logs", first_logs)
    monkeypatch.setattr(compilation, "disable_cache", lambda: None)
    with pytest.raises(_Reached):
        bench_tuning.run(_tuning_args(seed=2**63 - 1))
    assert seeds == [2**63 - 1]
    assert timing.wrap_seed(2**63 - 1, 1) == -2**63


# ------------------------------------------------------------------ duration -> LiDAR frames


@pytest.mark.parametrize("duration,frames", [(0.1, 1), (0.5, 5), (1.0, 10), (2.0, 20), (50.0, 500),
                                             (3, 30), (np.float64(0.2), 2)])
def test_lidar_frames_counts_whole_frames(duration, frames):
    assert timing.lidar_frames(duration, "--mc-duration") == frames


def test_lidar_frames_other_step():
    assert timing.lidar_frames(1.0, "duration", dt=0.02, lidar_every=5) == 10  # 0.1 s frames
    assert timing.lidar_frames(1.0, "duration", dt=0.01, lidar_every=20) == 5  # 0.2 s frames


@pytest.mark.parametrize("duration", [0, 0.0, 0.04, -1.0, math.nan, math.inf, -math.inf, True, None,
                                      "x", [1.0]])
def test_lidar_frames_names_the_option(duration):
    with pytest.raises(InputError, match=r"^--mc-duration: must hold at least one LiDAR frame \(0.1 s\)"):
        timing.lidar_frames(duration, "--mc-duration")


def test_synthetic_log_of_no_frame_is_an_input_error():
    # bench ekfslam's hand-made log: round(0.04 / 0.1) = 0 frames went on into the simulation
    with pytest.raises(InputError, match="^duration:"):
        bench_ekfslam.synthetic_log(0.04, 0)


@pytest.mark.parametrize("value", [math.nan, math.inf])
def test_fastslam_nonfinite_mc_duration_named(monkeypatch, value):
    # a namespace made without the CLI's finite-float check: round(nan) was a ValueError
    for name in ("_run_here", "_spawn"):
        monkeypatch.setattr(bench_fastslam, name, _reached)
    args = argparse.Namespace(**{k: None for k in bench_fastslam._OPTION_DESTS})
    args.parts, args.quick, args.seed, args.warmup, args.mc_duration = "mc", True, 0, 20, value
    with pytest.raises(InputError, match="^--mc-duration:"):
        bench_fastslam.run(args)


@pytest.mark.parametrize("value", [math.nan, math.inf])
def test_ekfslam_nonfinite_duration_named(monkeypatch, value):
    for name in ("_run_parts", "_spawn", "run_full", "run_mc"):
        monkeypatch.setattr(bench_ekfslam, name, _reached)
    p = argparse.ArgumentParser()
    bench_ekfslam.add_arguments(p)
    args = p.parse_args(["--parts", "full"])
    args.duration = value
    with pytest.raises(InputError, match="^--duration:"):
        bench_ekfslam.run(args)


# ------------------------------------------------------------------ bench fastslam: caller's args


def test_fastslam_run_leaves_the_callers_namespace(monkeypatch):
    """``run`` wrote ``--mc-runs 8`` back as "1,8" (M = 1 added for the sequential reference),
    and the defaults, into the namespace it was given; only in this process (the child
    process's copy was changed there), so the JSON's options differed with the path."""
    monkeypatch.setenv("OPENBLAS_NUM_THREADS", "1")  # in this process: _run_here
    monkeypatch.setattr(bench_fastslam, "_setup", _reached)  # the flight, its first work
    p = argparse.ArgumentParser()
    bench_fastslam.add_arguments(p)
    args = p.parse_args(["--parts", "mc", "--mc-runs", "8,32", "--mc-duration", "0.5"])
    before = dict(vars(args))
    with pytest.raises(_Reached):
        bench_fastslam.run(args)
    assert vars(args) == before


def test_fastslam_mc_runs_puts_the_single_run_first():
    ns = argparse.Namespace(mc_runs="8,32")
    assert bench_fastslam._mc_runs(ns) == [1, 8, 32] and ns.mc_runs == "8,32"
    assert bench_fastslam._mc_runs(argparse.Namespace(mc_runs="32,1,8")) == [32, 1, 8]


# ------------------------------------------------------------------ bench sim --duration


def _sim_args(**kw):
    base = dict(duration=50.0, batches="", repeats=1, numpy_repeats=1, numpy_batch_max=1,
                x0_spread=0.5, seed=0, no_feedforward=False, openblas_check=False, profile=False)
    return argparse.Namespace(**{**base, **kw})


@pytest.fixture
def sim_no_compute(monkeypatch):
    if not jax.config.jax_enable_x64:
        pytest.skip("bench sim needs x64 (tests/conftest.py enables it)")
    monkeypatch.setattr(bench_sim, "make_setup", _reached)


@pytest.mark.parametrize("value", [5000.0, 3600.5, 1e12, 0.04, 0.0999, 0.0, -1.0, math.nan, math.inf, True])
def test_sim_run_checks_the_declared_duration_bounds(sim_no_compute, value):
    # the parser refuses these ([0.1, 3600] s); run() on a namespace flew 5000 s, and 0.04 s
    # stopped in the library naming "duration", not the option
    with pytest.raises(InputError, match="^--duration:"):
        bench_sim.run(_sim_args(duration=value))


@pytest.mark.parametrize("value", [0.1, 50.0, 3600.0, 3600])
def test_sim_run_accepts_the_declared_bounds(sim_no_compute, value):
    with pytest.raises(_Reached):
        bench_sim.run(_sim_args(duration=value))


def test_sim_parser_and_run_agree(sim_no_compute):
    p = argparse.ArgumentParser()
    bench_sim.add_arguments(p)
    for text in ("0.1", "3600"):
        with pytest.raises(_Reached):
            bench_sim.run(_sim_args(duration=p.parse_args(["--duration", text]).duration))
    for text in ("0.05", "3601"):
        with pytest.raises(SystemExit):
            p.parse_args(["--duration", text])
        with pytest.raises(InputError, match="^--duration:"):
            bench_sim.run(_sim_args(duration=float(text)))
