"""Tests of the CLI, the run JSON, the scenario registry and the progress bar.

A dummy scenario defined here (a tiny jnp computation whose per-run metric values
follow a closed form, ``expected_pos``) stands in for the real scenarios; the
expected summary statistics are computed with NumPy from that closed form.
Cases that depend on the process-wide x64 switch run the CLI in a subprocess.
"""

from __future__ import annotations

import dataclasses
import inspect
import io as _io
import json
import math
import os
import pathlib
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam import cli
from jaxslam import io as jio
from jaxslam.errors import InputError
from jaxslam.progress import Progress
from jaxslam.sim.scenarios import registry
from jaxslam.sim.scenarios.registry import Option, Scenario, ScenarioResult

REPO = pathlib.Path(__file__).resolve().parents[1]
TESTS_DIR = pathlib.Path(__file__).resolve().parent
RUN_KEYS = ["scenario", "runs", "seed", "dtype", "config", "metrics", "consistency", "flags",
            "timing", "versions"]
STAT_KEYS = {"mean", "median", "p95", "max", "per_run"}
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"

CALLS: list[dict] = []  # what the dummy scenario received, newest last


def expected_pos(runs: int, seed: int, gain: float) -> np.ndarray:
    """Closed form of the dummy's per-run position metric (the test oracle)."""
    return 0.5 * gain * (np.arange(runs) + 1.0) + 0.01 * seed


def _dummy_plot(directory: pathlib.Path) -> list[pathlib.Path]:
    from matplotlib.figure import Figure

    fig = Figure(figsize=(2, 2))
    fig.add_subplot().plot([0, 1], [1, 0])
    path = pathlib.Path(directory) / "dummy_pos.png"
    fig.savefig(path)
    return [path]


def _dummy_run(*, runs, seed, dtype, options, progress, params):
    CALLS.append(dict(runs=runs, seed=seed, dtype=dtype, options=dict(options), params=params))
    if options["explode"]:
        raise RuntimeError("boom\nsecond line of the message")
    if options["bad_input"]:
        raise InputError("argument 'q' must be positive")
    base = jnp.arange(runs, dtype=dtype)
    pos = 0.5 * jnp.asarray(options["gain"], dtype) * (base + 1) + jnp.asarray(0.01 * seed, dtype)
    progress.update(runs)
    pos = np.array(pos)
    vel = np.asarray(jnp.square(base) + 1)
    if options["nan_run"]:
        pos[0] = np.nan
    if options["constant"]:
        pos, vel = np.full(runs, 1.5), np.full(runs, 2.5)
    return ScenarioResult(
        config={"gain": options["gain"], "mode": options["mode"], "noise_scale": options["noise_scale"],
                "x64": bool(jax.config.jax_enable_x64), "array_dtype": str(base.dtype),
                "params": params},
        metrics={"pos_rmse_m": pos, "vel_rmse_mps": vel},
        consistency=None if options["no_filter"] else
        {"anees": np.float64(1.1), "anees_bounds": [0.5, 1.5], "nis_mean": 3.1, "nis_bounds": [2.0, 4.0]},
        flags={"capacity_overflow": np.int64(0), "masked_measurements": 3, "non_finite": 0},
        timing={"compile_s": 0.25, "run_s": 0.5},
        plot=_dummy_plot,
    )


DUMMY = Scenario(
    name="dummy",
    description="Tiny test scenario (closed-form metrics).",
    options=(
        Option("gain", float, 2.0, "scale of the position error (m)"),
        Option("mode", str, "a", "a test choice", choices=("a", "b")),
        Option("noise_scale", float, 1.0, "an option with an underscore"),
        Option("nan_run", bool, False, "make run 0 diverge (NaN)"),
        Option("no_filter", bool, False, "return no consistency section"),
        Option("explode", bool, False, "raise an internal error"),
        Option("bad_input", bool, False, "raise an InputError"),
        Option("constant", bool, False, "every run returns the same metrics"),
    ),
    run=_dummy_run,
    params=lambda options, dtype: {"filter": {"q_scale": 1.0, "r": np.ones(2), "R": np.eye(2)}},
)


def register_dummy() -> None:
    registry.register(DUMMY, replace=True)


@pytest.fixture(autouse=True)
def dummy_scenario():
    register_dummy()
    CALLS.clear()
    yield
    registry.unregister("dummy")


def _stderr_line(err: str) -> str:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert "Traceback" not in err
    return lines[0]


def _strict_json(path) -> dict:
    def bad(const):
        raise AssertionError(f"non-strict JSON constant {const}")

    return json.loads(pathlib.Path(path).read_text(), parse_constant=bad)


# ----------------------------------------------------------------------------- run


def test_list_prints_scenarios_and_benchmarks(tmp_path, capsys):
    (tmp_path / "bench_fake.py").write_text('DESCRIPTION = "Fake one-line description."\n')
    assert cli.main(["list", "--dir", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "dummy" in out and "Tiny test scenario (closed-form metrics)." in out
    assert "fake" in out and "Fake one-line description." in out


def test_run_json_plots_and_summary_stats(tmp_path, capsys):
    runs, seed, gain = 5, 7, 3.0
    out_json = tmp_path / "sub" / "out.json"
    plots = tmp_path / "plots"
    rc = cli.main(["run", "dummy", "--runs", str(runs), "--seed", str(seed), "--gain", str(gain),
                   "--json", str(out_json), "--plots", str(plots)])
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    rep = _strict_json(out_json)
    assert list(rep) == RUN_KEYS
    assert rep["scenario"] == "dummy" and rep["runs"] == runs and rep["seed"] == seed
    assert rep["dtype"] == "float64"
    assert CALLS[-1]["dtype"] == np.float64 and CALLS[-1]["params"] is None
    assert rep["config"]["gain"] == gain and rep["config"]["mode"] == "a"

    want = expected_pos(runs, seed, gain)
    pos = rep["metrics"]["pos_rmse_m"]
    assert set(pos) == STAT_KEYS
    np.testing.assert_allclose(pos["per_run"], want, rtol=1e-12)
    np.testing.assert_allclose(pos["mean"], np.mean(want), rtol=1e-12)
    np.testing.assert_allclose(pos["median"], np.median(want), rtol=1e-12)
    np.testing.assert_allclose(pos["p95"], np.percentile(want, 95), rtol=1e-12)
    np.testing.assert_allclose(pos["max"], want.max(), rtol=1e-12)
    # p95 of 5 runs interpolates between the 4th and 5th value: 0.8 of the way.
    np.testing.assert_allclose(pos["p95"], want[3] + 0.8 * (want[4] - want[3]), rtol=1e-12)
    vel = np.arange(runs) ** 2 + 1.0
    np.testing.assert_allclose(rep["metrics"]["vel_rmse_mps"]["per_run"], vel)

    assert rep["consistency"] == {"anees": 1.1, "anees_bounds": [0.5, 1.5], "nis_mean": 3.1,
                                  "nis_bounds": [2.0, 4.0]}
    assert rep["flags"] == {"capacity_overflow": 0, "masked_measurements": 3, "non_finite": 0}
    t = rep["timing"]
    assert (t["main_program_compile_s"], t["run_s"], t["runs_per_s"]) == (0.25, 0.5, runs / 0.5)
    # compile_s: trace + lower + compile of every program the command built, measured
    np.testing.assert_allclose(t["compile_s"], t["trace_s"] + t["lower_s"] + t["backend_compile_s"])
    assert t["programs"] >= 0 and set(t["cache"]) == {"dir", "hits", "misses"}
    assert t["plots_s"] > 0
    assert rep["versions"] == {"jaxslam": __import__("jaxslam").__version__, "jax": jax.__version__}

    png = plots / "dummy_pos.png"
    assert png.read_bytes()[:8] == PNG_MAGIC
    assert f"wrote {out_json}" in captured.out and f"wrote {png}" in captured.out
    assert "pos_rmse_m" in captured.out and "anees" in captured.out and "runs/s" in captured.out


def test_run_threads_applies_to_its_own_run_only(monkeypatch):
    # --threads set $JAXSLAM_MC_THREADS for the rest of the process: a later in-process run
    # without it ran on one thread too
    from jaxslam.sim import monte_carlo

    seen = []
    registry.register(dataclasses.replace(DUMMY, run=_recording_threads(DUMMY.run, seen, monte_carlo)),
                      replace=True)
    monkeypatch.delenv("JAXSLAM_MC_THREADS", raising=False)
    assert cli.main(["run", "dummy", "--threads", "1", "--quiet"]) == 0
    assert "JAXSLAM_MC_THREADS" not in os.environ
    monkeypatch.setenv("JAXSLAM_MC_THREADS", "3")
    assert cli.main(["run", "dummy", "--threads", "2", "--quiet"]) == 0
    assert os.environ["JAXSLAM_MC_THREADS"] == "3"
    assert seen == [1, 2]


def _recording_threads(run, seen, monte_carlo):
    def wrapped(*a, **kw):
        seen.append(monte_carlo.default_threads())
        return run(*a, **kw)

    wrapped.__signature__ = inspect.signature(run)  # the CLI passes plots= only to a run that takes it
    return wrapped


def test_run_help_starts_no_process_group(monkeypatch, capsys):
    # with --processes P, --help started P processes, each importing JAX, to print the help
    from jaxslam.cli import run as cli_run

    started = []
    monkeypatch.setattr(cli_run, "_launch_local", lambda *a: started.append(a) or 0)
    assert cli.main(["run", "dummy", "--processes", "3", "--help"]) == 0
    assert started == [] and "--processes" in capsys.readouterr().out


class _ReaderLeaves:
    """A stdout whose pipe reader left after the first line (``jaxslam run ... | head -1``)."""

    def __init__(self):
        self.lines = 0

    def write(self, text):
        self.lines += 1
        if self.lines > 1:
            raise BrokenPipeError(32, "Broken pipe")
        return len(text)

    def flush(self):
        if self.lines > 1:
            raise BrokenPipeError(32, "Broken pipe")

    def fileno(self):
        raise ValueError("no descriptor")  # a capture, not a terminal: nothing to redirect


def test_run_writes_its_files_when_the_stdout_reader_leaves(tmp_path, monkeypatch):
    # The first table line used to end the command (BrokenPipeError -> exit 0) before --json
    # and --plots were written.
    out_json, plots = tmp_path / "r.json", tmp_path / "plots"
    gone = _ReaderLeaves()
    monkeypatch.setattr(sys, "stdout", gone)
    assert cli.main(["run", "dummy", "--runs", "2", "--json", str(out_json), "--plots", str(plots)]) == 0
    assert sys.stdout is gone and gone.lines > 1
    assert _strict_json(out_json)["runs"] == 2 and (plots / "dummy_pos.png").read_bytes()[:8] == PNG_MAGIC


@pytest.mark.parametrize("case", ["plots_is_json", "plots_under_json", "json_is_params"])
def test_run_refuses_an_output_on_another_output_or_its_input(tmp_path, capsys, case):
    # Each used to pass the early checks: the first two failed after the compute with nothing
    # written ('path: cannot write JSON'), the third replaced the --params file with the report.
    f = tmp_path / "p.json"
    f.write_text("{}")
    argv, flag = {"plots_is_json": (["--json", str(tmp_path / "o"), "--plots", str(tmp_path / "o")], "--plots"),
                  "plots_under_json": (["--json", str(tmp_path / "o"), "--plots", str(tmp_path / "o" / "s")],
                                       "--plots"),
                  "json_is_params": (["--params", str(f), "--json", str(f)], "--json")}[case]
    assert cli.main(["run", "dummy", *argv]) == 2
    line = _stderr_line(capsys.readouterr().err)
    assert line.startswith(f"jaxslam: error: {flag}:"), line
    assert CALLS == [] and f.read_text() == "{}" and not (tmp_path / "o").exists()


def test_run_float32_passes_float32(tmp_path, capsys):
    out_json = tmp_path / "o.json"
    assert cli.main(["run", "dummy", "--runs", "2", "--float32", "--json", str(out_json), "--quiet"]) == 0
    assert capsys.readouterr().out == ""  # --quiet prints nothing
    rep = _strict_json(out_json)
    assert rep["dtype"] == "float32"
    assert CALLS[-1]["dtype"] == np.float32
    assert rep["config"]["array_dtype"] == "float32"
    np.testing.assert_allclose(rep["metrics"]["pos_rmse_m"]["per_run"], expected_pos(2, 0, 2.0), rtol=1e-6)


@pytest.mark.parametrize("float32", [False, True])
def test_run_x64_switch_in_fresh_process(tmp_path, float32):
    script = tmp_path / "runner.py"
    script.write_text(textwrap.dedent(f"""\
        import sys
        sys.path.insert(0, {str(TESTS_DIR)!r})
        import test_cli
        test_cli.register_dummy()
        from jaxslam.cli import main
        raise SystemExit(main(sys.argv[1:]))
        """))
    out_json = tmp_path / "o.json"
    env = {k: v for k, v in os.environ.items() if k != "JAX_ENABLE_X64"}
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    cmd = [sys.executable, str(script), "run", "dummy", "--runs", "2", "--json", str(out_json), "--quiet"]
    proc = subprocess.run(cmd + (["--float32"] if float32 else []), capture_output=True, text=True,
                          env=env, cwd=tmp_path, timeout=120)
    assert proc.returncode == 0, proc.stderr
    rep = _strict_json(out_json)
    assert rep["dtype"] == ("float32" if float32 else "float64")
    assert rep["config"]["array_dtype"] == rep["dtype"]
    assert rep["config"]["x64"] is (not float32)


def test_unknown_scenario_exit_2_lists_names(capsys):
    assert cli.main(["run", "nosuch"]) == 2
    line = _stderr_line(capsys.readouterr().err)
    assert "nosuch" in line and "dummy" in line


def test_scenario_options_in_help_and_reach_options(capsys):
    assert cli.main(["run", "dummy", "--help"]) == 0
    out = capsys.readouterr().out
    for text in ("--gain", "scale of the position error (m)", "--noise-scale", "--nan-run", "{a,b}",
                 "options of scenario dummy"):
        assert text in out
    assert cli.main(["run", "dummy", "--gain", "2.5", "--mode", "b", "--noise_scale", "0.3",
                     "--no-filter", "--quiet"]) == 0
    assert CALLS[-1]["options"] == {"gain": 2.5, "mode": "b", "noise_scale": 0.3, "nan_run": False,
                                    "no_filter": True, "explode": False, "bad_input": False,
                                    "constant": False}
    assert cli.main(["run", "dummy", "--mode", "c"]) == 2
    assert "invalid choice" in _stderr_line(capsys.readouterr().err)


def test_no_consistency_key_when_none(tmp_path):
    out_json = tmp_path / "o.json"
    assert cli.main(["run", "dummy", "--no-filter", "--json", str(out_json), "--quiet"]) == 0
    rep = _strict_json(out_json)
    assert "consistency" not in rep
    assert list(rep) == [k for k in RUN_KEYS if k != "consistency"]


def test_nan_run_is_reported_not_dropped(tmp_path, capsys):
    out_json = tmp_path / "o.json"
    assert cli.main(["run", "dummy", "--runs", "3", "--nan-run", "--json", str(out_json)]) == 0
    out = capsys.readouterr().out
    pos = _strict_json(out_json)["metrics"]["pos_rmse_m"]
    assert pos["mean"] is None and pos["max"] is None and pos["p95"] is None and pos["median"] is None
    assert pos["per_run"][0] is None
    np.testing.assert_allclose(pos["per_run"][1:], expected_pos(3, 0, 2.0)[1:])
    assert "1 of 3 runs non-finite" in out


@pytest.mark.parametrize("content, needle", [("{not json", "not valid JSON"), ("[1, 2]", "JSON object")])
def test_params_bad_file_exit_2(tmp_path, capsys, content, needle):
    f = tmp_path / "p.json"
    f.write_text(content)
    assert cli.main(["run", "dummy", "--params", str(f)]) == 2
    line = _stderr_line(capsys.readouterr().err)
    assert needle in line and "p.json" in line
    assert CALLS == []  # rejected before the scenario ran


def test_params_missing_file_exit_2(tmp_path, capsys):
    assert cli.main(["run", "dummy", "--params", str(tmp_path / "absent.json")]) == 2
    assert "not found" in _stderr_line(capsys.readouterr().err)


def test_params_reach_scenario(tmp_path):
    f = tmp_path / "p.json"
    f.write_text('{"scenario": "dummy", "filter": {"q_scale": 2.0, "r": [1, 2], "R": [3, 4]}}')
    assert cli.main(["run", "dummy", "--params", str(f), "--quiet"]) == 0
    assert CALLS[-1]["params"] == {"filter": {"q_scale": 2.0, "r": [1, 2], "R": [3, 4]}}


@pytest.mark.parametrize("doc, needle", [
    ({"filtr": {}}, "unknown key(s) ['filtr']"),
    ({"filter": {"q": 1}}, "filter: unknown key(s) ['q']"),
    ({"filter": {"r": [1, 2, 3]}}, "filter.r: expected 2, got shape 3"),
    ({"filter": {"R": [[1, 2], [2, 1]]}}, "filter.R: not positive semi-definite (smallest eigenvalue -1)"),
    ({"filter": {"R": [[1, 0.1], [0, 1]]}}, "filter.R: not symmetric"),
    ({"filter": {"R": [-1, 1]}}, "filter.R: not positive semi-definite"),
    ({"filter": {"q_scale": [1, 2]}}, "filter.q_scale: expected a number"),
    ({"scenario": "other", "filter": {}}, "key 'scenario' is 'other', this run is 'dummy'"),
    ({"dataset": "mrclam", "noise": {}}, "the file is for dataset 'mrclam'"),
])
def test_params_schema_errors_name_the_key(tmp_path, capsys, doc, needle):
    f = tmp_path / "p.json"
    f.write_text(json.dumps(doc))
    assert cli.main(["run", "dummy", "--params", str(f)]) == 2
    assert needle in _stderr_line(capsys.readouterr().err)
    assert CALLS == []  # refused before the scenario ran


def test_params_of_a_tune_report_are_its_sections(tmp_path):
    # A whole `jaxslam tune --json` report is a --params file: its sections are read, the
    # report's own keys are not parameters.
    f = tmp_path / "tune.json"
    f.write_text(json.dumps({"scenario": "dummy", "target": "noise", "before": {}, "after": {},
                             "params_after": {"filter": {"q_scale": 3.0}}, "history": [],
                             "filter": {"q_scale": 3.0}}))
    assert cli.main(["run", "dummy", "--params", str(f), "--quiet"]) == 0
    assert CALLS[-1]["params"] == {"filter": {"q_scale": 3.0}}


def test_run_help_lists_the_params_keys(capsys):
    assert cli.main(["run", "dummy", "--help"]) == 0
    out = capsys.readouterr().out
    assert "--params FILE" in out and "filter: q_scale (a number), r (2), R (2×2 symmetric PSD or 2" in out


def test_identical_runs_are_said_to_be(tmp_path, capsys):
    # The dummy's metrics differ per run (closed form); a scenario whose runs are all equal
    # gets a note, in the console and the JSON.
    out_json = tmp_path / "o.json"
    assert cli.main(["run", "dummy", "--runs", "3", "--json", str(out_json)]) == 0
    assert "note: all" not in capsys.readouterr().out and "notes" not in _strict_json(out_json)
    assert cli.main(["run", "dummy", "--runs", "3", "--constant", "--json", str(out_json)]) == 0
    out = capsys.readouterr().out
    assert "note: all 3 runs gave identical metrics" in out
    assert _strict_json(out_json)["notes"][0].startswith("all 3 runs gave identical metrics")
    assert cli.main(["run", "dummy", "--runs", "1", "--constant", "--json", str(out_json)]) == 0
    assert "note: all" not in capsys.readouterr().out  # one run: nothing to compare



@pytest.mark.parametrize("argv, needle", [
    (["run", "dummy", "--runs", "0"], "--runs"),
    (["run", "dummy", "--runs", "x"], "--runs"),
    (["run", "dummy", "--seed", "-1"], "--seed"),
    (["run", "dummy", "--bogus"], "--bogus"),
    (["run"], "dummy"),
    ([], "COMMAND"),
    (["frobnicate"], "frobnicate"),
    (["--nope", "list"], "--nope"),
    (["tune", "no-such-scenario"], "no-such-scenario"),
    (["dataset", "x", "--data", "."], "invalid choice: 'x'"),
    (["dataset", "mrclam"], "--data"),
    (["dataset", "mrclam", "--data", "/no/such/folder"], "is not a folder"),
])
def test_usage_errors_exit_2_one_line(capsys, monkeypatch, argv, needle):
    monkeypatch.delenv("JAXSLAM_DATA_DIR", raising=False)  # `dataset` would read it for --data
    assert cli.main(argv) == 2
    assert needle in _stderr_line(capsys.readouterr().err)


def test_input_error_inside_scenario_exit_2(capsys):
    assert cli.main(["run", "dummy", "--bad-input"]) == 2
    assert "argument 'q' must be positive" in _stderr_line(capsys.readouterr().err)


def test_internal_error_exit_1_traceback_only_with_debug(capsys, monkeypatch):
    monkeypatch.delenv("JAXSLAM_DEBUG", raising=False)
    assert cli.main(["run", "dummy", "--explode"]) == 1
    line = _stderr_line(capsys.readouterr().err)
    assert "RuntimeError: boom" in line and "--debug" in line and "JAXSLAM_DEBUG=1" in line
    assert cli.main(["run", "dummy", "--explode", "--debug"]) == 1
    assert "Traceback" in capsys.readouterr().err
    monkeypatch.setenv("JAXSLAM_DEBUG", "1")
    assert cli.main(["run", "dummy", "--explode"]) == 1
    assert "Traceback" in capsys.readouterr().err


def test_version(capsys):
    assert cli.main(["--version"]) == 0
    assert capsys.readouterr().out.strip() == f"jaxslam {__import__('jaxslam').__version__}"


def test_python_m_jaxslam_help_is_fast_and_jax_free(tmp_path):
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.run([sys.executable, "-m", "jaxslam", "--help"], capture_output=True,
                          text=True, env=env, cwd=tmp_path, timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert "usage: jaxslam" in proc.stdout and "bench" in proc.stdout
    code = "import sys; from jaxslam.cli import main; main(['--help']); print('JAX', 'jax' in sys.modules)"
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                          cwd=tmp_path, timeout=60)
    assert proc.stdout.strip().endswith("JAX False")


def test_quick_bad_input_exits_do_not_import_jax(tmp_path):
    """An error found from the arguments alone exits without importing JAX (2.2 s on these
    machines): a module-level import of jaxslam.linalg in paramfile once made every `run` and
    `dataset` exit import it (bench bad_inputs: median 0.19 -> 2.48 s)."""
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    (tmp_path / "afile").write_text("not a folder")
    for stem, text in (("section", '{"noise": {}}'), ("other", '{"scenario": "uwb-circle", "controller": {}}'),
                       ("dsfile", '{"dataset": "mrclam", "noise": {}}'), ("ctrl", '{"controller": {}}'),
                       ("dsother", '{"dataset": "plaza", "noise": {}}')):
        (tmp_path / f"{stem}.json").write_text(text)
    cases = [["dataset", "x", "--data", "."], ["dataset", "mrclam", "--data", str(tmp_path / "absent")],
             ["run", "track-figure8", "--json", str(tmp_path / "afile" / "x.json")],
             ["run", "track-figure8", "--params", str(tmp_path / "absent.json")],
             # the scenario's name and options come from its declaration (sim/scenarios/builtin.py):
             # 1.4-2.8 s each before, every one of them importing JAX
             ["run"], ["run", "no-such-scenario"], ["run", "track-figure8", "--bogus"],
             ["run", "track-figure8", "--duration", "nan"], ["run", "uwb-circle", "--model", "cubic"],
             ["run", "uwb-circle", "--max-range", "-1"], ["run", "lineslam-room", "--capacity", "0"],
             ["run", "ekfslam3d-unknown", "--max-obs", "0"],
             ["run", "attitude-smc", "--json", str(tmp_path / "made" / "x.json"), "--gains", "none"],
             # tune's arguments against the declared targets (tuning/targets/__init__.py: DECLARED)
             ["tune", "no-such-scenario"], ["tune", "track-figure8", "--b2", "2"],
             ["tune", "track-figure8", "--data", "."], ["tune", "mrclam", "--data", str(tmp_path / "absent")],
             ["tune", "track-figure8", "--batch-size", "5", "--train-runs", "2"],
             ["tune", "no-such-scenario", "--json", str(tmp_path / "made" / "t.json")],
             # a --params file's top level against the declared sections (paramfile.check_sections)
             *(["run", sc, "--params", str(tmp_path / f"{stem}.json")]
               for sc, stem in (("track-figure8", "section"), ("track-figure8", "other"), ("uwb-circle", "dsfile"),
                                ("attitude-smc", "ctrl"), ("fastslam-helix", "ctrl"))),
             # a dataset --params file's top level (paramfile.check_dataset_sections)
             *(["dataset", "mrclam", "--data", str(REPO / "tests" / "data"), "--params", str(tmp_path / f"{stem}.json")]
               for stem in ("dsother", "ctrl"))]
    code = ("import sys, contextlib, io; from jaxslam.cli import main\n"
            f"for argv in {cases!r}:\n"
            "    with contextlib.redirect_stderr(io.StringIO()):\n"
            "        rc = main(argv)\n"
            "    print(rc, 'jax' in sys.modules)")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                          cwd=tmp_path, timeout=60)
    assert proc.stdout.split() == ["2", "False"] * len(cases), (proc.stdout, proc.stderr)
    assert not (tmp_path / "made").exists()  # a bad option exits before any output folder is made
    # listing the scenarios and the run's own help need no scenario module either
    code = ("import sys, contextlib, io; from jaxslam.cli import main\n"
            "out = io.StringIO()\n"
            "with contextlib.redirect_stdout(out):\n"
            "    rcs = [main(['list', '--dir', '.']), main(['run', '--help'])]\n"
            "print(rcs, 'jax' in sys.modules, 'uwb-rough' in out.getvalue())")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                          cwd=tmp_path, timeout=60)
    assert proc.stdout.split() == ["[0,", "0]", "False", "True"], (proc.stdout, proc.stderr)


# ----------------------------------------------------------------------------- bench

BENCH_SRC = '''\
"""A fake benchmark."""
import helper_twin_cli_test as twin

DESCRIPTION = "Fake benchmark for the CLI tests."


def add_arguments(parser):
    parser.add_argument("--size", type=int, default=3)
    parser.add_argument("--scale", type=float, default=1.0)


def run(args):
    return {"results": [{"case": f"n={args.size}", "params": {"n": args.size},
                         "jaxslam_s": 0.5, "reference": "numpy", "reference_s": twin.REF_S,
                         "speedup": twin.REF_S / 0.5}]}
'''


@pytest.fixture
def bench_dir(tmp_path):
    d = tmp_path / "benchmarks"
    d.mkdir()
    (d / "bench_fake.py").write_text(BENCH_SRC)
    (d / "helper_twin_cli_test.py").write_text("REF_S = 1.5\n")
    yield d
    sys.modules.pop("helper_twin_cli_test", None)


def test_bench_with_dir(bench_dir, tmp_path, capsys):
    out_json = tmp_path / "b.json"
    assert cli.main(["bench", "fake", "--dir", str(bench_dir), "--size", "7", "--json", str(out_json)]) == 0
    out = capsys.readouterr().out
    rep = _strict_json(out_json)
    assert rep["benchmark"] == "fake"
    assert isinstance(rep["machine"], dict) and rep["machine"]["cpu_count"] == os.cpu_count()
    assert rep["results"] == [{"case": "n=7", "params": {"n": 7}, "jaxslam_s": 0.5, "reference": "numpy",
                               "reference_s": 1.5, "speedup": 3.0}]
    assert "n=7" in out and "3.00x" in out and "reference_s" in out
    assert str(bench_dir.resolve()) not in sys.path  # the folder is put on sys.path only while running


def test_a_benchmark_importing_jax_at_its_top_gets_float64_arrays(tmp_path):
    """x64 is on before a benchmark module is loaded, so a module that imports JAX at its top gets
    float64 module-level arrays (in a fresh process, where nothing imported JAX before).  (A
    version that parsed the options before importing JAX and loaded such a module a second time
    after x64 failed this for a helper module's arrays and ran the module's top twice.)"""
    d = tmp_path / "benchmarks"
    d.mkdir()
    (d / "bench_topjax.py").write_text(
        '"""Imports JAX at its top."""\nimport jax.numpy as jnp\n\nX = jnp.ones(2)\n'
        'DESCRIPTION = "x"\n\n\ndef add_arguments(parser):\n    parser.add_argument("--n", type=int, default=1)\n\n\n'
        'def run(args):\n    return {"results": [{"case": str(X.dtype), "jaxslam_s": 1.0}]}\n')
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    out = tmp_path / "b.json"
    proc = subprocess.run([sys.executable, "-m", "jaxslam", "bench", "topjax", "--dir", str(d), "--json", str(out)],
                          capture_output=True, text=True, env=env, cwd=tmp_path, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert _strict_json(out)["results"][0]["case"] == "float64"
    proc = subprocess.run([sys.executable, "-m", "jaxslam", "bench", "topjax", "--dir", str(d), "--n", "x"],
                          capture_output=True, text=True, env=env, cwd=tmp_path, timeout=120)
    assert proc.returncode == 2 and "--n" in proc.stderr


def test_bench_found_in_cwd_and_help(bench_dir, monkeypatch, capsys):
    monkeypatch.chdir(bench_dir.parent)
    assert cli.main(["bench", "fake", "--help"]) == 0
    out = capsys.readouterr().out
    assert "--size" in out and "Fake benchmark for the CLI tests." in out
    assert cli.main(["bench", "bench_fake"]) == 0
    assert "n=3" in capsys.readouterr().out


def test_bench_errors_exit_2(bench_dir, tmp_path, capsys):
    assert cli.main(["bench", "nosuch", "--dir", str(bench_dir)]) == 2
    line = _stderr_line(capsys.readouterr().err)
    assert "nosuch" in line and "fake" in line
    assert cli.main(["bench", "fake", "--dir", str(tmp_path / "absent")]) == 2
    assert "not a folder" in _stderr_line(capsys.readouterr().err)
    # a benchmark's plain int / float options are checked for it: a count >= 1, a finite number
    # (they used to reach the benchmark and come back as internal errors, exit 1)
    for opt, val in (("--size", "0"), ("--scale", "nan"), ("--scale", "inf")):
        assert cli.main(["bench", "fake", "--dir", str(bench_dir), opt, val]) == 2
        assert opt in capsys.readouterr().err
    (bench_dir / "bench_broken.py").write_text("DESCRIPTION = 'x'\n")
    assert cli.main(["bench", "broken", "--dir", str(bench_dir)]) == 2
    assert "add_arguments" in _stderr_line(capsys.readouterr().err)


def test_find_benchmarks_dir_missing(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(__import__("jaxslam"), "__file__", str(tmp_path / "src" / "jaxslam" / "__init__.py"))
    with pytest.raises(InputError, match="--dir"):
        cli.find_benchmarks_dir()


# ----------------------------------------------------------------------------- registry


def _noop_run(**kw):
    raise AssertionError("not run")


@pytest.mark.parametrize("options, needle", [
    ((Option("runs", int, 1, "x"),), "clashes"),
    ((Option("q", float, "a", "x"),), "not of type float"),
    ((Option("m", str, "z", "x", choices=("a", "b")),), "not one of"),
    ((Option("f", bool, 0, "x"),), "bool default"),
    ((Option("bad-name", int, 1, "x"),), "identifier"),
    ((Option("q", float, 1.0, "x"), Option("q", float, 2.0, "y")), "twice"),
    ((Option("c", list, [], "x"),), "type must be"),
])
def test_register_rejects_bad_options(options, needle):
    with pytest.raises(InputError, match=needle):
        registry.register(Scenario("bad", "d", options, _noop_run))
    assert "bad" not in registry.names()


def test_register_duplicate_get_and_names():
    other = Scenario("dummy", "another", (), _noop_run)
    with pytest.raises(InputError, match="already registered"):
        registry.register(other)
    assert registry.register(DUMMY) is DUMMY  # the same object again is fine
    with pytest.raises(InputError, match="valid scenarios: .*dummy"):
        registry.get("nope")
    assert registry.get("dummy") is DUMMY
    assert registry.names() == sorted(registry.names()) and "dummy" in registry.names()
    assert DUMMY in registry.all_scenarios()
    with pytest.raises(InputError, match="lower case"):
        registry.register(Scenario("Bad Name", "d", (), _noop_run))


def test_scenario_run_from_python_checks_and_completes_options():
    """get(name).run(...) from a script checks ``options`` as the command line does: a misspelt
    key was ignored silently, a partial dict failed with a bare KeyError inside the scenario."""
    from jaxslam.progress import Progress

    def call(options):
        return DUMMY.run(runs=2, seed=0, dtype=np.dtype(np.float64), options=options,
                         progress=Progress.null(), params=None)

    res = call({"gain": 4})  # partial: the rest are the defaults; an int for a float option
    assert res.config["gain"] == 4.0 and res.config["mode"] == "a" and res.config["noise_scale"] == 1.0
    assert call(None).config["gain"] == 2.0
    for bad, needle in (({"gian": 1.0}, r"^options: unknown key\(s\) \['gian'\] for scenario 'dummy'"),
                        ({"gain": "2"}, r"^--gain \(options\['gain'\]\): expected float"),
                        ({"gain": True}, r"^--gain \(options\['gain'\]\): expected float"),
                        ({"gain": float("nan")}, r"^--gain \(options\['gain'\]\): expected a finite number"),
                        ({"mode": "c"}, r"^--mode \(options\['mode'\]\): expected one of \['a', 'b'\]"),
                        ({"nan_run": 1}, r"^--nan-run \(options\['nan_run'\]\): expected bool"),
                        ([("gain", 1.0)], r"^options: expected a dict")):
        with pytest.raises(InputError, match=needle):
            call(bad)
    # by position too (a scenario's own run may take them so), and a dataclasses.replace copy
    # checks against its own options
    seen = []
    positional = Scenario("positional", "d", DUMMY.options,
                          lambda runs, seed, dtype, options, progress: seen.append(options))
    positional.run(1, 0, np.dtype(np.float64), {"gain": 1.0}, None)
    assert seen[0]["gain"] == 1.0 and seen[0]["mode"] == "a"
    with pytest.raises(InputError, match=r"^options: unknown key"):
        positional.run(1, 0, np.dtype(np.float64), {"gian": 1.0}, None)
    import dataclasses

    fewer = dataclasses.replace(DUMMY, options=DUMMY.options[1:])
    with pytest.raises(InputError, match=r"^options: unknown key\(s\) \['gain'\]"):
        fewer.run(runs=1, seed=0, dtype=np.dtype(np.float64), options={"gain": 1.0}, progress=Progress.null())
    lower = Scenario("lower", "d", (Option("n", int, 2, "x", lower=1),), _noop_run)
    with pytest.raises(InputError, match=r"^--n \(options\['n'\]\): expected >= 1, got 0"):
        lower.run(runs=1, seed=0, dtype=np.dtype(np.float64), options={"n": 0}, progress=None)


# ----------------------------------------------------------------------------- io


def test_summarize_metrics_against_numpy():
    x = np.array([3.0, 1.0, 4.0, 1.5, 9.0, 2.6])
    s = jio.summarize_metrics({"a_m": x, "b_m": jnp.asarray([2.0], dtype=jnp.float32), "c_m": 5.0})
    assert s["a_m"] == {"mean": np.mean(x), "median": np.median(x), "p95": np.percentile(x, 95),
                        "max": 9.0, "per_run": list(x)}
    assert s["b_m"]["p95"] == 2.0 and s["c_m"]["per_run"] == [5.0]
    s = jio.summarize_metrics({"a_m": [1.0, np.nan]})["a_m"]
    assert all(math.isnan(s[k]) for k in ("mean", "median", "p95", "max"))
    with pytest.raises(InputError, match="a_m"):
        jio.summarize_metrics({"a_m": np.zeros((2, 2))})
    with pytest.raises(InputError, match="a_m"):
        jio.summarize_metrics({"a_m": []})


def test_write_json_converts_numpy_jax_and_nonfinite(tmp_path):
    obj = {"i": np.int32(3), "f": np.float32(0.5), "b": np.bool_(True), "arr": np.arange(3),
           "jarr": jnp.ones((2,)), "jscalar": jnp.asarray(2.0), "nan": float("nan"),
           "inf": np.array([1.0, np.inf]), "t": (1, 2), "p": pathlib.Path("a/b"),
           "dt": np.dtype("float32"), "ty": np.float64}
    path = jio.write_json(tmp_path / "x" / "y.json", obj)
    got = _strict_json(path)
    assert got == {"i": 3, "f": 0.5, "b": True, "arr": [0, 1, 2], "jarr": [1.0, 1.0], "jscalar": 2.0,
                   "nan": None, "inf": [1.0, None], "t": [1, 2], "p": "a/b", "dt": "float32",
                   "ty": "float64"}
    with pytest.raises(TypeError):
        jio.write_json(tmp_path / "z.json", {"o": object()})
    with pytest.raises(InputError, match="cannot write"):
        jio.write_json(path / "under_a_file.json", {})


def test_run_json_rejects_extra_key_clash():
    res = ScenarioResult(config={}, metrics={"a_m": [1.0]}, consistency=None, flags={},
                         timing={"compile_s": 0.0, "run_s": 0.0}, extra={"metrics": 1})
    with pytest.raises(ValueError, match="metrics"):
        jio.run_json("x", 1, 0, np.float64, res)
    res.extra = {"trajectory_rmse": {"x": np.float64(1.0)}}
    rep = jio.run_json("x", 1, 0, np.float64, res)
    assert rep["trajectory_rmse"] == {"x": 1.0} and math.isnan(rep["timing"]["runs_per_s"])


def test_format_table_aligned():
    s = jio.summarize_metrics({"pos_rmse_m": [1.0, 2.0], "a": [np.nan, 1.0]})
    lines = jio.format_table(s).splitlines()
    assert lines[0].split() == ["metric", "mean", "median", "p95", "max"]
    assert len(lines[0]) == len(lines[1]) == len(lines[2]) == len(lines[3])
    assert lines[2].split() == ["pos_rmse_m", "1.5000", "1.5000", "1.9500", "2.0000"]
    assert lines[3].split()[1:] == ["nan"] * 4
    assert lines[4] == "note: a: 1 of 2 runs non-finite"


def test_load_params_ok(tmp_path):
    from jaxslam import paramfile

    f = tmp_path / "p.json"
    f.write_text('{"a": 1}')
    assert paramfile.load(f) == {"a": 1}


def test_load_params_refuses_a_key_given_twice(tmp_path):
    from jaxslam import paramfile
    from jaxslam.errors import InputError

    f = tmp_path / "p.json"
    f.write_text('{"a": {"b": 1, "b": 2}, "c": [{"d": 1}, {"d": 2}]}')
    with pytest.raises(InputError, match="gives the key 'b' twice"):
        paramfile.load(f)
    f.write_text('{"a": {"b": 1}, "c": [{"d": 1}, {"d": 2}]}')  # equal keys in two objects are fine
    assert paramfile.load(f) == {"a": {"b": 1}, "c": [{"d": 1}, {"d": 2}]}


# ----------------------------------------------------------------------------- progress


class _Clock:
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t


def test_progress_silent_before_delay_then_bar_with_eta():
    clock, stream = _Clock(), _io.StringIO()
    p = Progress(10, "mc", True, stream, clock=clock)
    p.update(3)
    clock.t = 0.9
    p.advance(1)
    assert stream.getvalue() == ""  # jobs under ~1 s print nothing
    clock.t = 2.0
    p.update(4)
    text = stream.getvalue()
    # 4 of 10 done in 2 s -> 3 s left.
    assert "mc [" in text and "4/10" in text and "00:02" in text and "ETA 00:03" in text
    clock.t = 2.05
    p.advance(1)  # within the log interval: no new line
    assert stream.getvalue() == text
    clock.t = 4.0
    p.update(10)
    p.close()
    assert stream.getvalue().splitlines()[-1].startswith("mc [" + "#" * 30 + "] 10/10 00:04")
    p.close()  # idempotent


class _TtyStream(_io.StringIO):
    def isatty(self):
        return True


def test_progress_note_is_a_line_of_its_own_and_the_bar_comes_back():
    clock = _Clock()
    pipe, tty = _io.StringIO(), _TtyStream()
    for stream in (pipe, tty):
        p = Progress(10, "tune", True, stream, clock=clock, delay_s=0.0)
        clock.t += 1.0
        p.update(2)
        p.note("  step 2: run 0 left out")
        clock.t += 10.0
        p.update(3)
        p.close()
    assert pipe.getvalue().splitlines()[1] == "  step 2: run 0 left out"
    assert "3/10" in pipe.getvalue().splitlines()[2]
    # on a terminal the bar's line is cleared first, and the bar is redrawn after the note
    text = tty.getvalue()
    assert "\r\x1b[K  step 2: run 0 left out\n" in text
    assert "3/10" in text.split("left out\n", 1)[1]
    Progress(3, "x", False, pipe).note("nothing")  # disabled: prints nothing
    assert "nothing" not in pipe.getvalue()


def test_progress_quick_job_disabled_and_null_print_nothing():
    clock, stream = _Clock(), _io.StringIO()
    p = Progress(5, "x", True, stream, clock=clock)
    p.update(5)
    p.close()
    q = Progress(5, "x", False, stream, clock=clock)
    clock.t = 10.0
    q.update(2)
    q.close()
    n = Progress.null()
    n.advance(3)
    n.close()
    assert stream.getvalue() == ""
    assert q.n_done == 2


def test_list_shows_datasets_and_survives_a_stale_data_variable(capsys, monkeypatch):
    data = str(TESTS_DIR / "data")
    monkeypatch.setenv("JAXSLAM_DATA_DIR", data)
    assert cli.main(["list"]) == 0
    out = capsys.readouterr().out
    assert "mrclam" in out and "[found:" in out and "--robot 1, 2" in out
    monkeypatch.setenv("JAXSLAM_DATA_DIR", "/no/such/folder")
    assert cli.main(["list"]) == 0  # the listing still works; the folder's problem is said
    out = capsys.readouterr().out
    assert "$JAXSLAM_DATA_DIR: '/no/such/folder' is not a folder" in out and "plaza" in out
    assert cli.main(["list", "--data", "/no/such/folder"]) == 2  # an explicit --data must be usable


def test_metrics_that_are_not_finite_are_said_in_the_notes():
    # a flight shorter than the settling window has no *_settled value in any run; the JSON
    # summary is null there, and the notes (console and JSON) say which and why
    from types import SimpleNamespace

    from jaxslam.cli.run import _run_notes

    nan = float("nan")
    res = SimpleNamespace(metrics={"pos_rmse_m": np.array([0.1, 0.2, 0.3]),
                                   "pos_rmse_settled_m": np.array([nan, nan, nan]),
                                   "anees": np.array([3.0, nan, 2.0])})
    notes = _run_notes(res, 3)
    assert notes[0].startswith("not finite in any run (null in the summary): pos_rmse_settled_m")
    assert "settling time" in notes[0]
    assert notes[1] == "not finite in some runs (left out of the summary): anees (1 of 3)"
    assert _run_notes(SimpleNamespace(metrics={"a": np.array([1.0, 2.0])}), 2) == []
