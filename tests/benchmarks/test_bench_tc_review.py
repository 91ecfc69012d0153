"""Review of bench_tuning.py, bench_compile.py, bench_bad_inputs.py: options checked before any
compute, the compile benchmark's rows and targets.  Nothing here simulates, compiles or times a
filter: the first piece of work each benchmark would do is replaced by a sentinel."""

import argparse
import json
import pathlib
import subprocess
import sys

import pytest

from jaxslam import cli
from jaxslam.errors import InputError

BENCH = pathlib.Path(__file__).resolve().parents[2] / "benchmarks"
sys.path.insert(0, str(BENCH))
sys.path.insert(0, str(BENCH.parent / "tests" / "oracles"))

import bench_compile  # noqa: E402
import bench_tuning  # noqa: E402


class _Reached(Exception):
    """The benchmark got past its option checks to its first simulation."""


@pytest.fixture
def no_compute(monkeypatch):
    """bench tuning's first work (the logs' simulation) raises _Reached; the process keeps its
    persistent compilation cache (run() would switch it off)."""
    from jaxslam import compilation
    from jaxslam.tuning.targets import ekfslam3d as T

    def reached(*a, **k):
        raise _Reached

    monkeypatch.setattr(T, "make_slam_logs", reached)
    monkeypatch.setattr(compilation, "disable_cache", lambda: None)


def _tuning_args(**kw):
    base = dict(steps=500, runs=2, repeats=5, ratio_blocks=7, memory_steps=2000, no_lqr=False, seed=0)
    return argparse.Namespace(**{**base, **kw})


# ------------------------------------------------------------------ bench tuning: whole frames


@pytest.mark.parametrize("flag,kw", [("--steps", {"steps": 25}), ("--steps", {"steps": 57}),
                                     ("--steps", {"steps": 14}), ("--memory-steps", {"memory_steps": 25}),
                                     ("--memory-steps", {"memory_steps": 2005})])
def test_tuning_steps_not_whole_frames_refused(no_compute, flag, kw):
    # the logs hold whole 10-step LiDAR frames: round(25 / 10) = 2 frames = 20 steps (57 -> 60,
    # 14 -> 10) were run while the JSON said 25 / 57 / 14 imu_steps
    with pytest.raises(InputError, match=flag):
        bench_tuning.run(_tuning_args(**kw))


@pytest.mark.parametrize("kw", [{}, {"steps": 10, "memory_steps": 0}, {"steps": 20, "memory_steps": 10}])
def test_tuning_whole_frames_accepted(no_compute, kw):
    with pytest.raises(_Reached):  # past the checks: the defaults (500, 2000) run as before
        bench_tuning.run(_tuning_args(**kw))


def test_tuning_steps_not_whole_frames_is_exit_2(no_compute, capsys):
    rc = cli.main(["bench", "tuning", "--dir", str(BENCH), "--steps", "25"])
    err = capsys.readouterr().err
    assert rc == 2 and "--steps" in err and "internal error" not in err and len(err.strip().splitlines()) == 1


def test_tuning_largest_seed_passes_the_checks(no_compute):
    # the memory case's log is seeded timing.wrap_seed(SEED, 1): 2**63 - 1 + 1 wraps to -2**63
    with pytest.raises(_Reached):
        bench_tuning.run(_tuning_args(seed=2**63 - 1))
    with pytest.raises(_Reached):  # without the memory case the largest seed is fine
        bench_tuning.run(_tuning_args(seed=2**63 - 1, memory_steps=0))
    with pytest.raises(_Reached):
        bench_tuning.run(_tuning_args(seed=2**63 - 2))


def test_tuning_help_says_multiple_of_10(capsys):
    assert cli.main(["bench", "tuning", "--dir", str(BENCH), "--help"]) == 0
    out = " ".join(capsys.readouterr().out.split())
    assert out.count("multiple of 10") == 2 and "SEED + 1" in out


# ------------------------------------------------------------------ bench compile


def test_compile_exit_0_without_json_is_a_row_error(tmp_path):
    # `jaxslam --help` exits 0 and writes no JSON: a FileNotFoundError ended the whole benchmark
    (tmp_path / "out").mkdir()
    row = bench_compile._one(["--help"], tmp_path / "cache", tmp_path / "out", 120.0)
    assert "error" in row and "--json" in row["error"] and row["wall_s"] > 0


def test_compile_unreadable_json_is_a_row_error(tmp_path, monkeypatch):
    out = tmp_path / "out"
    out.mkdir()

    def fake_run(cmd, **kw):
        (out / "out.json").write_text("{not json")
        return subprocess.CompletedProcess(cmd, 0, "", "")

    monkeypatch.setattr(bench_compile.subprocess, "run", fake_run)
    row = bench_compile._one(["run", "x", "--json", "{json}"], tmp_path / "cache", out, 10.0)
    assert "error" in row and "JSONDecodeError" in row["error"]


def test_compile_data_folder_with_braces(tmp_path, monkeypatch):
    data = tmp_path / "data{1}"
    out = tmp_path / "out"
    data.mkdir(), out.mkdir()
    seen = []

    def fake_run(cmd, **kw):
        seen.append(cmd)
        (out / "out.json").write_text(json.dumps({"timing": {"compile_s": 1.5}}))
        return subprocess.CompletedProcess(cmd, 0, "", "")

    monkeypatch.setattr(bench_compile.subprocess, "run", fake_run)
    argv = dict(bench_compile._cases(data))["dataset plaza"]
    row = bench_compile._one(argv, tmp_path / "cache", out, 10.0)
    assert row["compile_s"] == 1.5
    assert seen[0][3:] == ["dataset", "plaza", "--data", str(data), "--quiet", "--json", str(out / "out.json")]
    main = dict(bench_compile._cases(data))["run ekfslam3d-unknown (README main job)"]
    bench_compile._one(main, tmp_path / "cache", out, 10.0)
    assert seen[1][3:] == ["run", "ekfslam3d-unknown", "--runs", "4", "--plots", f"{out}/plots",
                           "--json", str(out / "out.json")]


def test_compile_zero_seconds_meets_the_target(monkeypatch):
    monkeypatch.setattr(bench_compile, "_one", lambda argv, cache, out, timeout: {"compile_s": 0.0})
    res = bench_compile.run(argparse.Namespace(data=None, only="README main job", timeout=1.0))
    assert [t["value"] for t in res["targets"]] == [0.0, 0.0]
    assert [t["met"] for t in res["targets"]] == [True, True]  # 0.0 <= 8 and 0.0 <= 1.5
    monkeypatch.setattr(bench_compile, "_one", lambda argv, cache, out, timeout: {"error": "x"})
    res = bench_compile.run(argparse.Namespace(data=None, only="README main job", timeout=1.0))
    assert [t["met"] for t in res["targets"]] == [False, False]  # no figure: not met


@pytest.mark.parametrize("value", ["", "  "])
def test_compile_empty_data_is_exit_2(capsys, monkeypatch, value):
    # '' fell back to tests/data and ran every case (path_arg, as --dir and the dataset commands)
    def reached(*a, **k):
        raise _Reached

    monkeypatch.setattr(subprocess, "run", reached)
    rc = cli.main(["bench", "compile", "--dir", str(BENCH), "--data", value])
    err = capsys.readouterr().err
    assert rc == 2 and "--data" in err and "internal error" not in err


# ------------------------------------------------------------------ bench bad_inputs


def test_bad_inputs_missing_catalogue_is_exit_2(capsys, tmp_path, monkeypatch):
    # a benchmarks folder with no tests/ beside it: FileNotFoundError, an internal error (exit 1)
    d = tmp_path / "benchmarks"
    d.mkdir()
    (d / "bench_bad_inputs.py").write_text((BENCH / "bench_bad_inputs.py").read_text())

    def reached(*a, **k):
        raise _Reached

    monkeypatch.setattr(subprocess, "run", reached)
    rc = cli.main(["bench", "bad_inputs", "--dir", str(d)])
    err = capsys.readouterr().err
    assert rc == 2 and "test_cli_bad_inputs.py" in err and "internal error" not in err
    assert len(err.strip().splitlines()) == 1


def test_tuning_numpy_twin_timed_after_a_warm_up(monkeypatch):
    """The NumPy reference is timed after one untimed twin run (the JAX side after its warm-up
    call): 1 + reps * (2p + 1) twin runs, reps = max(1, repeats // 2), p = 9."""
    import collections

    import jax.numpy as jnp
    import numpy as np
    import numpy_ekfslam3d as tw

    calls = []

    def fake_run_log(noise, s0, imu, y, ids, visible, every, **kw):
        calls.append(1)
        return None, np.zeros((4, 9)) + float(np.sum(np.diag(noise.Qc)))

    monkeypatch.setattr(tw, "run_log", fake_run_log)
    Log = collections.namedtuple("Log", "s0 imu y ids visible truth")
    log = Log(jnp.zeros(9), jnp.zeros((5, 6)), jnp.zeros((1, 2, 3)), jnp.zeros(2), jnp.zeros((1, 2)),
              jnp.zeros((5, 9)))
    ref = collections.namedtuple("Noise", "Qc")(jnp.eye(9))
    cfg = collections.namedtuple("Cfg", "capacity max_obs dt g")(4, 2, 0.01, 9.81)
    theta = {"Qc": jnp.full(9, 0.1)}
    for repeats, reps in ((4, 2), (1, 1)):
        calls.clear()
        row = bench_tuning._numpy_fd_row(argparse.Namespace(repeats=repeats, steps=40),
                                         lambda th, lg: jnp.sum(th["Qc"] ** 2), theta, log, ref, cfg)
        assert len(calls) == 1 + reps * 19
        assert row["params"]["numpy_runs"] == 19
