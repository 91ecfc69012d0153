"""The bad-input catalogue: every case exits 2 with one line naming the argument, before any compile.

All cases run in ONE fresh interpreter (a driver script below), one after another, as
``jaxslam.cli.main(argv)`` with stdout/stderr captured; the first case therefore pays the
imports a user's first call pays.  For each case the driver records the exit code, stderr,
wall time and the programs JAX traced, compiled or loaded from the persistent cache
(:func:`jaxslam.compilation.totals`).  The assertions, per case:

* exit code 2, exactly one non-empty line on stderr, no traceback;
* the line contains the case's needle: the option or key it is about (``--json``,
  ``controller.R``, ...), stated here from the design, not copied from the output;
* nothing compiled and nothing loaded from the compilation cache (the check happened
  before any compile, so a bad argument costs no compile time);
* wall time under :data:`HANG_GUARD_S` — a guard against a case that starts real work, not
  a speed test (speed is ``benchmarks/``'s job; the closing figures quote the times this
  driver records).
"""

from __future__ import annotations

import json
import os
import pathlib
import subprocess
import sys

import pytest

REPO = pathlib.Path(__file__).resolve().parents[1]
DATA = REPO / "tests" / "data"
BENCH = REPO / "benchmarks"
HANG_GUARD_S = 20.0

# A folder nobody can write into, root included (Linux's sysfs); its cases run only where it
# exists and a probe file cannot be created in it (chmod alone does not stop root).
_RO = pathlib.Path("/sys")


def _files(tmp: pathlib.Path) -> None:
    """The files the cases point at (created in ``tmp``)."""
    (tmp / "afile").write_text("not a folder\n")
    (tmp / "folder").mkdir()
    docs = {
        "notjson": "{not json",
        "list": "[1, 2]",
        "section": {"noise": {}},
        "key": {"controller": {"Qx": 1}},
        "shape": {"controller": {"Q": [1, 2]}},
        "rshape": {"controller": {"R": [[1, 2], [2, 1], [0, 0], [0, 0]]}},
        "notpsd": {"controller": {"R": [1, -1, 1, 1]}},
        "asym": {"controller": {"R": [[1, 0.5, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}},
        "other": {"scenario": "uwb-circle", "filter": {}},
        "dsfile": {"dataset": "mrclam", "noise": {}},
        "dsother": {"dataset": "victoria-park", "noise": {}},
        "scenfile": {"scenario": "track-figure8", "controller": {}},
        "rscaled": {"filter": {"r_scaled": 1}},
        "qc": {"noise": {"Qc": [1, 2, 3]}},
        "strings": {"controller": {"kp": ["a", "b", "c"]}},
        "dskey": {"dataset": "mrclam", "noise": {"sigma_nope": 1}},
        "inverted": {"dataset": "mrclam", "noise": {"range_min": 5, "range_max": 1}},
        "prunefrac": {"dataset": "mrclam", "noise": {"prune_window_s": 2, "prune_min_obs": 2.5}},
        "dsnotpd": {"dataset": "mrclam", "noise": {"R": [-1, 1]}},
        "dsread": {"dataset": "mrclam", "noise": {}},
        "uwbok": {"filter": {"r_scaled": True}},
    }
    for name, doc in docs.items():
        (tmp / f"{name}.json").write_text(doc if isinstance(doc, str) else json.dumps(doc))
    (tmp / "nan.json").write_text('{"controller": {"kp": [NaN, 1, 1]}}')  # Python's json reads NaN
    # A key given twice: JSON parsers keep the last value, so an edit above it would be lost
    (tmp / "dupkey.json").write_text('{"controller": {"kp": [1, 1, 1], "kp": [2, 2, 2]}}')
    (tmp / "dsdupkey.json").write_text('{"dataset": "mrclam", "noise": {}, "noise": {"R": [1, 1]}}')


def _cases(t: pathlib.Path) -> list:
    """(argv, needle, env) of every case; ``t`` is the folder of :func:`_files`."""
    d, bad = str(DATA), DATA / "bad"
    p = lambda name: str(t / f"{name}.json")  # noqa: E731
    run8 = ["run", "track-figure8"]
    cases = [
        # usage: commands, options, values
        ([], "COMMAND", None),
        (["frobnicate"], "frobnicate", None),
        (["--nope", "list"], "--nope", None),
        (["run"], "SCENARIO", None),
        (["run", "no-such-scenario"], "no-such-scenario", None),
        (["run", "--anchors", "4", "uwb-circle"], "SCENARIO comes first", None),  # it said: unknown scenario '4'
        (run8 + ["--runs", "0"], "--runs", None),
        (run8 + ["--runs", "x"], "--runs", None),
        (run8 + ["--seed", "-1"], "--seed", None),
        (["run", "ekfslam3d-known", "--threads", "0"], "--threads", None),
        (run8 + ["--bogus"], "--bogus", None),
        (run8 + ["--duration", "-1"], "--duration", None),
        (run8 + ["--duration", "nan"], "--duration", None),
        (["run", "lineslam-room", "--capacity", "0"], "--capacity", None),
        (["run", "uwb-circle", "--model", "cubic"], "--model", None),
        (run8 + ["--altitude", "nan"], "--altitude", None),  # every float option is finite
        (["run", "ekfslam3d-unknown", "--max-obs", "0"], "--max-obs", None),
        (["run", "uwb-circle", "--chunk", "0"], "--chunk", None),
        (run8 + ["--json", ""], "--json", None),  # an empty path is not "no file"
        (["cache", "clear", "--dir", ""], "--dir", None),  # it cleared the current folder
        (["list", "--data", ""], "--data", None),  # '' fell back to $JAXSLAM_DATA_DIR
        (["list", "--dir", ""], "--dir", None),
        (["dataset", "mrclam", "--data", ""], "--data", None),
        (["bench", "filters", "--dir", ""], "--dir", None),
        (run8 + ["--processe", "2"], "--processe", None),  # abbreviations: read by one parser only
        # output paths, checked before the run
        (run8 + ["--json", str(t / "afile" / "x.json")], "--json", None),
        (run8 + ["--json", str(t / "folder")], "--json", None),
        (run8 + ["--plots", str(t / "afile")], "--plots", None),
        (run8 + ["--plots", str(t / "afile" / "sub")], "--plots", None),
        # --params files
        (run8 + ["--params", str(t / "absent.json")], "--params", None),
        (run8 + ["--params", str(t / "folder")], "--params", None),
        (run8 + ["--params", p("notjson")], "--params", None),
        (run8 + ["--params", p("list")], "--params", None),
        (run8 + ["--params", p("section")], "'noise'", None),
        (run8 + ["--params", p("key")], "Qx", None),
        (run8 + ["--params", p("shape")], "controller.Q", None),
        (run8 + ["--params", p("rshape")], "controller.R", None),
        (run8 + ["--params", p("notpsd")], "controller.R", None),
        (run8 + ["--params", p("asym")], "controller.R", None),
        (run8 + ["--params", p("nan")], "controller.kp", None),
        (run8 + ["--params", p("strings")], "controller.kp", None),
        (run8 + ["--params", p("dupkey")], "'kp' twice", None),
        (run8 + ["--params", p("other")], "'scenario'", None),
        (run8 + ["--params", p("dsfile")], "dataset", None),
        (["run", "attitude-smc", "--params", p("key")], "--params", None),
        (["run", "fastslam-helix", "--params", p("key")], "--params", None),
        (["run", "uwb-circle", "--params", p("rscaled")], "filter.r_scaled", None),
        (["run", "uwb-circle", "--dt", "-1", "--params", p("uwbok")], "--dt", None),  # it named params.Q
        (["run", "ekfslam3d-known", "--params", p("qc")], "noise.Qc", None),
        # dataset
        (["dataset", "x", "--data", d], "NAME", None),
        (["dataset", "mrclam"], "--data", {"JAXSLAM_DATA_DIR": ""}),
        (["dataset", "mrclam"], "$JAXSLAM_DATA_DIR", {"JAXSLAM_DATA_DIR": "/no/such/folder"}),
        (["dataset", "mrclam", "--data", "/no/such/folder"], "--data", None),
        (["dataset", "mrclam", "--data", d, "--robot", "7"], "--robot", None),
        (["dataset", "mrclam", "--data", d, "--robot", "0"], "--robot", None),
        (["dataset", "plaza", "--data", d, "--robot", "3"], "--robot", None),
        (["dataset", "mrclam", "--data", d, "--json", str(t / "afile" / "x.json")], "--json", None),
        (["dataset", "mrclam", "--data", d, "--tum", str(t / "folder")], "--tum", None),
        (["dataset", "mrclam", "--data", d, "--plots", str(t / "afile")], "--plots", None),
        (["dataset", "victoria-park", "--data", d, "--ids", "hidden"], "--ids", None),
        (["dataset", "util-uwb", "--data", d, "--filter", "fastslam"], "--filter", None),
        (["dataset", "mrclam", "--data", d, "--particles", "5"], "--particles", None),
        (["dataset", "mrclam", "--data", d, "--params", p("dsother")], "dataset", None),
        (["dataset", "mrclam", "--data", d, "--params", p("scenfile")], "--params", None),
        (["dataset", "mrclam", "--data", d, "--params", p("dskey")], "sigma_nope", None),
        (["dataset", "mrclam", "--data", d, "--params", p("dsdupkey")], "'noise' twice", None),
        # an output on another output's path or on the file the command reads
        (["dataset", "mrclam", "--data", d, "--json", str(t / "o1"), "--plots", str(t / "o1")], "--plots", None),
        (["dataset", "mrclam", "--data", d, "--params", p("dsread"), "--tum", p("dsread")], "--tum", None),
        (["tune", "track-figure8", "--json", str(t / "o2"), "--plots", str(t / "o2" / "s")], "--plots", None),
        (["dataset", "mrclam", "--data", d, "--params", p("inverted")], "range_min", None),
        (["dataset", "mrclam", "--data", d, "--params", p("prunefrac")], "prune_min_obs", None),
        (["dataset", "mrclam", "--data", d, "--params", p("dsnotpd")], "--params: noise.R", None),
        (["dataset", "util-uwb", "--data", d, "--json", str(t / "same.out"), "--tum", str(t / "same.out")],
         "--tum", None),  # two outputs on one file: the later would replace the earlier
        (["dataset", "mrclam", "--data", d, "--filter", "fastslam", "--params", p("dsfile")], "--params", None),
        (["dataset", "mrclam", "--data", str(bad / "mrclam_truncated")], "Robot1_", None),
        (["dataset", "victoria-park", "--data", str(bad / "victoria_park_columns")], ".dat:", None),
        (["dataset", "plaza", "--data", str(bad / "plaza_backwards")], "Plaza", None),
        (["dataset", "util-uwb", "--data", str(bad / "util_nonnumeric")], ".csv:", None),
        # tune
        (["tune", "no-such-scenario"], "no-such-scenario", None),
        (["tune", "track-figure8", "--steps", "0"], "--steps", None),
        (["tune", "track-figure8", "--lr", "-1"], "--lr", None),
        (["tune", "track-figure8", "--b2", "2"], "--b2", None),  # before the build, not after compiling
        (["tune", "track-figure8", "--batch-size", "5", "--train-runs", "2"], "--batch-size", None),
        (["bench", "sim", "--dir", str(BENCH), "--duration", "nan"], "--duration", None),
        (["bench", "sim", "--dir", str(BENCH), "--x0-spread", "-5"], "--x0-spread", None),
        (["tune", "track-figure8", "--json", str(t / "afile" / "y.json")], "--json", None),
        (["tune", "track-figure8", "--params-out", str(t / "folder")], "--params-out", None),
        (["tune", "track-figure8", "--data", d], "--data", None),
        (["tune", "mrclam", "--data", d, "--robots", "1,9"], "--robots", None),
        (["tune", "mrclam"], "--data", {"JAXSLAM_DATA_DIR": ""}),
        (["tune", "util-uwb", "--data", d, "--train-runs", "3"], "--train-runs", None),  # simulation only
        # bench, cache, list
        (["bench", "no-such-bench", "--dir", str(BENCH)], "no-such-bench", None),
        (["bench", "ekfslam", "--dir", "/no/such/folder"], "--dir", None),
        (["bench", "ekfslam", "--dir", str(BENCH), "--json", str(t / "afile" / "z.json")], "--json", None),
        (["cache", "explode"], "action", None),
        (["cache", "info", "--dir", str(t / "afile")], "cache folder", None),
        (["list", "--data", "/no/such/folder"], "--data", None),
    ]
    if _RO.is_dir() and not _can_create_in(_RO):  # a truly read-only folder (root cannot write either)
        cases += [(run8 + ["--json", str(_RO / "x.json")], "--json", None),
                  (run8 + ["--plots", str(_RO / "plots")], "--plots", None),
                  (["dataset", "mrclam", "--data", d, "--json", str(_RO / "x.json")], "--json", None)]
    return cases


def _can_create_in(folder: pathlib.Path) -> bool:
    try:
        (folder / ".jaxslam-write-probe").touch()
    except OSError:
        return False
    (folder / ".jaxslam-write-probe").unlink()
    return True


_DRIVER = r"""
import contextlib, io, json, os, sys, time
from jaxslam import cli, compilation  # cli first: it configures the process before NumPy loads
cases = json.loads(sys.argv[1])
out = []
for argv, env in cases:
    saved = {k: os.environ.get(k) for k in (env or {})}
    os.environ.update(env or {})
    before = compilation.totals()
    err, std = io.StringIO(), io.StringIO()
    t0 = time.perf_counter()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(std):
        rc = cli.main(argv)
    wall = time.perf_counter() - t0
    acc = compilation.totals() - before
    for k, v in saved.items():
        if v is None:
            os.environ.pop(k, None)
        else:
            os.environ[k] = v
    out.append({"rc": rc, "err": err.getvalue(), "wall_s": wall, "programs": acc.programs,
                "cache_hits": acc.cache_hits, "trace_s": acc.trace_s})
print(json.dumps(out))
"""


@pytest.fixture(scope="module")
def catalogue(tmp_path_factory):
    t = tmp_path_factory.mktemp("bad_inputs")
    _files(t)
    cases = _cases(t)
    env = {k: v for k, v in os.environ.items() if k != "JAXSLAM_DATA_DIR"}
    proc = subprocess.run([sys.executable, "-c", _DRIVER, json.dumps([[a, e] for a, _, e in cases])],
                          capture_output=True, text=True, env=env, cwd=str(t), timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    results = json.loads(proc.stdout.strip().splitlines()[-1])
    return list(zip(cases, results))


def test_catalogue_has_at_least_40_cases(catalogue):
    assert len(catalogue) >= 40


def test_every_case_exits_2_with_one_line_naming_the_argument(catalogue):
    failures = []
    for (argv, needle, _), r in catalogue:
        lines = [ln for ln in r["err"].splitlines() if ln.strip()]
        ok = (r["rc"] == 2 and len(lines) == 1 and "Traceback" not in r["err"] and needle in lines[0])
        if not ok:
            failures.append(f"{' '.join(argv)} -> rc {r['rc']}, stderr {r['err']!r} (wanted {needle!r})")
    assert not failures, "\n".join(failures)


def test_no_case_compiles_or_loads_a_program(catalogue):
    compiled = [f"{' '.join(argv)}: {r['programs']} compiled, {r['cache_hits']} from the cache"
                for (argv, _, _), r in catalogue if r["programs"] or r["cache_hits"]]
    assert not compiled, "\n".join(compiled)


def test_no_case_starts_real_work(catalogue):
    slow = [f"{' '.join(argv)}: {r['wall_s']:.1f} s" for (argv, _, _), r in catalogue
            if r["wall_s"] > HANG_GUARD_S]
    assert not slow, "\n".join(slow)
