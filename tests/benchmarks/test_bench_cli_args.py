"""Argument checks of ``jaxslam bench`` (jaxslam/cli/bench.py) and of benchmarks/bench_fastslam.py,
bench_compile.py, bench_tuning.py, bench_sim.py, bench_filters.py, bench_bad_inputs.py: a bad option
is the CLI's exit 2 with a message naming it, before any compute; ``--json`` creates no folder when
the run stops at its options; help says what the code does."""

import argparse
import json
import pathlib
import sys
import time

import jax
import pytest

from jaxslam import cli
from jaxslam.cli.bench import _CheckedOptions, _format_bench_table
from jaxslam.cli.common import Parser
from jaxslam.errors import InputError

BENCH = pathlib.Path(__file__).resolve().parents[2] / "benchmarks"
sys.path.insert(0, str(BENCH))
sys.path.insert(0, str(BENCH.parent / "tests" / "oracles"))

import bench_compile  # noqa: E402
import bench_fastslam  # noqa: E402
import bench_filters  # noqa: E402
import bench_tuning  # noqa: E402


def _bench(capsys, name, *opts):
    rc = cli.main(["bench", name, "--dir", str(BENCH), *opts])
    out = capsys.readouterr()
    return rc, out.err, out.out


def _exit_2_naming(capsys, flag, name, *opts, not_in_err=()):
    t0 = time.perf_counter()
    rc, err, _ = _bench(capsys, name, *opts)
    assert rc == 2, err
    assert flag in err, err
    assert "internal error" not in err
    for text in not_in_err:  # the progress line of the first piece of work
        assert text not in err
    assert time.perf_counter() - t0 < 10  # nothing simulated or compiled


# ------------------------------------------------------------------ items 2, 6: bench fastslam


@pytest.mark.parametrize("parts", [",", " , "])
def test_fastslam_empty_parts_is_exit_2(capsys, parts):
    _exit_2_naming(capsys, "--parts", "fastslam", "--parts", parts, not_in_err=("simulating",))


@pytest.mark.parametrize("opts,flag", [
    (("--parts", "step", "--particles", "0"), "--particles"),
    (("--parts", "step", "--particles", "x"), "--particles"),
    (("--parts", "mc", "--mc-runs", "0"), "--mc-runs"),
    (("--parts", "mc", "--mc-runs", "1,x"), "--mc-runs"),
])
def test_fastslam_lists_checked_before_the_flight(capsys, monkeypatch, opts, flag):
    # with OPENBLAS_NUM_THREADS != 1 the run goes to a child process: the parent checks first
    monkeypatch.setenv("OPENBLAS_NUM_THREADS", "2")
    _exit_2_naming(capsys, flag, "fastslam", *opts, not_in_err=("simulating", "fresh process"))


def test_fastslam_child_input_error_is_an_input_error(tmp_path):
    """A bad input the child process finds comes back as an InputError with its message (exit 2),
    not a CalledProcessError (exit 1)."""
    args = argparse.Namespace(**{k: None for k in bench_fastslam._OPTION_DESTS})
    args.parts, args.quick, args.seed, args.warmup = "step", True, 0, 5  # 5: not a multiple of 10
    with pytest.raises(InputError, match="--warmup"):
        bench_fastslam._spawn(args, {"step"})


def test_fastslam_help_says_what_the_code_does(capsys):
    assert cli.main(["bench", "fastslam", "--dir", str(BENCH), "--help"]) == 0
    out = " ".join(capsys.readouterr().out.split())
    assert "0.5 s" in out and bench_fastslam._QUICK["mc_duration"] == 0.5
    assert "min(REPEATS, 2)" in out and "max(5, 3 * REPEATS)" in out


# ------------------------------------------------------------------ items 3, 9: bench compile


def test_compile_data_and_only_checked(capsys, tmp_path):
    _exit_2_naming(capsys, "--data", "compile", "--data", str(tmp_path / "absent"),
                   not_in_err=("[bench compile]",))
    rc, err, out = _bench(capsys, "compile", "--only", "zzzz")
    assert rc == 2 and "--only" in err and "zzzz" in err and "[bench compile]" not in out


@pytest.mark.parametrize("value", ["0", "-1"])
def test_compile_timeout_positive(capsys, value):
    _exit_2_naming(capsys, "--timeout", "compile", "--timeout", value)


def test_compile_timeout_is_a_row_error(tmp_path):
    (tmp_path / "out").mkdir()
    row = bench_compile._one(["--help"], tmp_path / "cache", tmp_path / "out", 0.001)
    assert "timed out" in row["error"] and "--timeout" in row["error"]


# ------------------------------------------------------------------ items 8, 10: bench tuning


def _parser(module):
    p = Parser(prog="t")
    module.add_arguments(_CheckedOptions(p))
    return p


def test_tuning_memory_steps_0_skips():
    assert _parser(bench_tuning).parse_args(["--memory-steps", "0"]).memory_steps == 0


def test_tuning_steps_and_memory_steps_named(capsys):
    _exit_2_naming(capsys, "--steps", "tuning", "--steps", "5")
    _exit_2_naming(capsys, "--memory-steps", "tuning", "--memory-steps", "5")
    _exit_2_naming(capsys, "--memory-steps", "tuning", "--memory-steps", "-1")


# ------------------------------------------------------------------ items 10, 11: bench sim


@pytest.mark.parametrize("value", ["0", "-3", "1e12", "3601"])
def test_sim_duration_named_and_bounded(capsys, value):
    _exit_2_naming(capsys, "--duration", "sim", "--duration", value)


def test_sim_batch_memory_bound(capsys):
    _exit_2_naming(capsys, "--batches", "sim", "--duration", "100", "--batches", "1000")


def test_sim_help_documents_the_bounds(capsys):
    assert cli.main(["bench", "sim", "--dir", str(BENCH), "--help"]) == 0
    out = " ".join(capsys.readouterr().out.split())
    assert "3600" in out and "50000" in out


# ------------------------------------------------------------------ items 10, 12, 13: bench filters


@pytest.mark.parametrize("opts,flag,other", [(("--steps", "1"), "--steps", "--repeats")])
def test_filters_message_names_one_flag(capsys, opts, flag, other):
    rc, err, _ = _bench(capsys, "filters", *opts)
    assert rc == 2 and flag in err and other not in err


def test_filters_numpy_warmup_and_reference_named(monkeypatch):
    if not jax.config.jax_enable_x64:
        pytest.skip("needs x64")
    calls = {"numpy": 0, "numpy_before_its_timing": None}
    real_np, real_median = bench_filters._numpy_ekf, bench_filters.median_s

    def counted(*a):
        calls["numpy"] += 1
        return real_np(*a)

    def median(fn, repeats):
        calls["numpy_before_its_timing"] = calls["numpy"]  # the last call is the NumPy loop's
        return real_median(fn, repeats)

    monkeypatch.setattr(bench_filters, "_numpy_ekf", counted)
    monkeypatch.setattr(bench_filters, "median_s", median)
    # the sizes of test_bench_filters.py's run, so its programs come from the suite's cache
    out = bench_filters.run(argparse.Namespace(steps=30, repeats=1, lag=5, iters=2, eager="none"))
    assert calls["numpy_before_its_timing"] == 1  # one untimed warm-up call
    rows = {r["case"]: r for r in out["results"]}
    assert rows["numpy_ekf_loop"]["speedup_vs"] == "numpy" and "NumPy" in rows["numpy_ekf_loop"]["reference"]
    assert all(r["speedup_vs"] == "ekf" and "not NumPy" in r["reference"]
               for c, r in rows.items() if c != "numpy_ekf_loop")
    for key in ("reference", "reference_s", "speedup", "ratio_to_ekf", "us_per_step"):  # kept
        assert key in rows["ukf"]


def test_table_marks_each_rows_reference():
    res = {"benchmark": "x", "results": [
        {"case": "a", "jaxslam_s": 1.0, "reference": "own ekf", "reference_s": 2.0, "speedup": 2.0},
        {"case": "b", "jaxslam_s": 1.0, "reference": "NumPy loop", "reference_s": 3.0, "speedup": 3.0}]}
    text = _format_bench_table(res)
    lines = text.splitlines()
    assert lines[1].split()[-1] == "vs"
    assert lines[3].endswith("[2]") and lines[4].endswith("[1]")  # refs sorted: NumPy loop, own ekf
    assert "[1] NumPy loop" in text and "[2] own ekf" in text
    one = _format_bench_table({"benchmark": "x", "results": res["results"][:1]})
    assert "vs" not in one.splitlines()[1] and one.endswith("reference: own ekf")


# ------------------------------------------------------------------ item 4: --json folders


def test_json_folder_not_created_on_help_or_bad_option(capsys, tmp_path):
    assert cli.main(["bench", "fastslam", "--dir", str(BENCH), "--help", "--json",
                     str(tmp_path / "helpdir" / "x.json")]) == 0
    capsys.readouterr()
    _exit_2_naming(capsys, "--parts", "fastslam", "--json", str(tmp_path / "nodir" / "x.json"),
                   "--parts", "bogus")
    _exit_2_naming(capsys, "--timeout", "compile", "--json", str(tmp_path / "argdir" / "x.json"),
                   "--timeout", "0")
    assert not any((tmp_path / d).exists() for d in ("helpdir", "nodir", "argdir"))


def test_json_checked_before_compute(capsys, tmp_path):
    (tmp_path / "afile").write_text("")
    _exit_2_naming(capsys, "--json", "fastslam", "--json", str(tmp_path / "afile" / "x.json"))
    _exit_2_naming(capsys, "--json", "fastslam", "--json", str(tmp_path))


def test_json_folder_created_when_the_run_finishes(capsys, tmp_path):
    d = tmp_path / "b"
    d.mkdir()
    (d / "bench_tiny.py").write_text(
        "DESCRIPTION = 'tiny'\n\ndef add_arguments(p):\n    pass\n\n"
        "def run(args):\n    return {'results': [{'case': 'x', 'jaxslam_s': 1.0}]}\n")
    out = tmp_path / "new" / "deeper" / "r.json"
    assert cli.main(["bench", "tiny", "--dir", str(d), "--json", str(out)]) == 0
    assert json.loads(out.read_text())["benchmark"] == "tiny"


# ------------------------------------------------------------------ item 14: bench bad_inputs


def test_bad_inputs_says_cases_are_timed_cold(capsys):
    import bench_bad_inputs

    doc = " ".join(bench_bad_inputs.__doc__.split())
    assert "No warm-up, on purpose" in doc
    assert cli.main(["bench", "bad_inputs", "--dir", str(BENCH), "--help"]) == 0
    assert "no warm-up on purpose" in " ".join(capsys.readouterr().out.split())

