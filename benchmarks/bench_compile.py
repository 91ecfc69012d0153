"""Compile-time benchmark: trace, lower and XLA-compile seconds of every public runner, cold and warm.

Run with ``jaxslam bench compile [--json PATH] [--only SUBSTRING] [--data DIR]``.  Each case is
one ``jaxslam`` command run as a user runs it, in a fresh process:

* **cold**: a new, empty compilation cache (``JAXSLAM_CACHE_DIR`` set to a temporary folder), so
  every program is traced, lowered and compiled — what a user pays on a fresh machine;
* **warm**: the same command again in a second process on that cache — what every later call
  pays (stored programs are loaded, tracing is skipped where a runner keeps its traced program).

The figures come from the command's own JSON (``timing``: ``compile_s`` = trace + lower + XLA
compile over every program the command built, ``trace_s``, ``lower_s``, ``backend_compile_s``,
``programs``, ``cache.hits``), plus the process's wall time.  Cases: every scenario of
``jaxslam run`` (one run; the README's main job as the README gives it), every ``jaxslam
dataset`` runner on the excerpts in ``tests/data`` (or ``--data``), and the tuning steps of
``jaxslam tune`` (one step).  ``jaxslam_s`` is the warm compile, ``reference_s`` the cold one.

Timings are wall clock on a shared machine: compare cases within one run of the benchmark, and
``load_average`` says how busy the machine was.
"""

from __future__ import annotations

import json
import os
import pathlib
import shutil
import subprocess
import sys
import tempfile
import time

from jaxslam.cli.common import path_arg, positive_float
from jaxslam.errors import InputError

DESCRIPTION = ("Compile time (trace / lower / XLA compile) of every public runner: each run scenario, "
               "each dataset runner, the tuning steps; cold (empty cache) and warm, in fresh processes")

TARGETS = {"main_job_cold_s": 8.0, "main_job_warm_s": 1.5, "tune_step_cold_s": 10.0}
# (label, case name prefix, cold|warm, timing field, TARGETS key).  The tuning step is the jitted
# value_and_grad + Adam step alone (``timing.step_compile_s`` of ``jaxslam tune``), the figure the
# target was set on; the command's whole compile (log simulation, evaluation) is the row's compile_s.
_TARGET_ROWS = (
    ("README main job, compile cold", "run ekfslam3d-unknown (README", "cold", "compile_s", "main_job_cold_s"),
    ("README main job, compile warm (second call)", "run ekfslam3d-unknown (README", "warm", "compile_s",
     "main_job_warm_s"),
    ("tuning step (value_and_grad + Adam), compile cold", "tune ekfslam3d", "cold", "step_compile_s",
     "tune_step_cold_s"),
)

_HERE = pathlib.Path(__file__).resolve().parent


def add_arguments(parser):
    parser.add_argument("--only", metavar="TEXT", default=None,
                        help="run only the cases whose name contains TEXT")
    parser.add_argument("--data", metavar="DIR", default=None, type=path_arg,  # '' fell back to tests/data
                        help="dataset folder for the dataset cases (default: the excerpts in tests/data)")
    parser.add_argument("--timeout", type=positive_float, default=900.0,
                        help="seconds per command, > 0 (default 900); a command that runs longer is "
                             "stopped and its row records the timeout as its error")


def _cases(data: pathlib.Path):
    # (name, argv after "jaxslam", note)
    main = ["run", "ekfslam3d-unknown", "--runs", "4", "--plots", "{out}/plots", "--json", "{json}"]
    cases = [("run ekfslam3d-unknown (README main job)", main)]
    for sc in ("ekfslam3d-known", "track-figure8", "track-helix", "fastslam-helix", "uwb-circle",
               "uwb-square", "uwb-rough", "attitude-smc", "lineslam-room"):
        cases.append((f"run {sc}", ["run", sc, "--runs", "1", "--quiet", "--json", "{json}"]))
    d = str(data)
    cases += [
        ("dataset mrclam (EKF, known ids)", ["dataset", "mrclam", "--data", d, "--quiet", "--json", "{json}"]),
        ("dataset mrclam (EKF, ids hidden)", ["dataset", "mrclam", "--data", d, "--ids", "hidden", "--quiet",
                                              "--json", "{json}"]),
        ("dataset mrclam (FastSLAM)", ["dataset", "mrclam", "--data", d, "--filter", "fastslam", "--quiet",
                                       "--json", "{json}"]),
        ("dataset victoria-park", ["dataset", "victoria-park", "--data", d, "--float32", "--quiet",
                                   "--json", "{json}"]),
        ("dataset util-uwb", ["dataset", "util-uwb", "--data", d, "--quiet", "--json", "{json}"]),
        ("dataset plaza", ["dataset", "plaza", "--data", d, "--quiet", "--json", "{json}"]),
        ("tune ekfslam3d-unknown (nll, one step)", ["tune", "ekfslam3d-unknown", "--loss", "nll", "--steps", "1",
                                                    "--train-runs", "2", "--test-runs", "1", "--quiet",
                                                    "--json", "{json}"]),
        ("tune uwb-circle (mse, one step)", ["tune", "uwb-circle", "--loss", "mse", "--steps", "1",
                                             "--train-runs", "2", "--test-runs", "1", "--quiet", "--json", "{json}"]),
        ("tune track-figure8 (lqr, one step)", ["tune", "track-figure8", "--target", "lqr", "--steps", "1",
                                                "--train-runs", "1", "--test-runs", "1", "--quiet",
                                                "--json", "{json}"]),
    ]
    return cases


def _timing(doc: dict) -> dict:
    t = doc.get("timing") or {}
    step = {"step_compile_s": t["step_compile_s"]} if "step_compile_s" in t else {}  # jaxslam tune only
    return {k: t.get(k) for k in ("compile_s", "trace_s", "lower_s", "backend_compile_s", "programs")} | step | {
        "cache_hits": (t.get("cache") or {}).get("hits"), "run_s": t.get("run_s", t.get("step_s"))}


def _one(argv, cache: pathlib.Path, out: pathlib.Path, timeout: float) -> dict:
    js = out / "out.json"
    if js.exists():
        js.unlink()
    # only the placeholders are filled in: str.format on every argument failed on a --data
    # folder whose name holds a brace ("KeyError" from inside the benchmark)
    cmd = [sys.executable, "-m", "jaxslam"] + [a.replace("{out}", str(out)).replace("{json}", str(js))
                                               if a.startswith(("{out}", "{json}")) else a for a in argv]
    env = {**os.environ, "JAXSLAM_CACHE_DIR": str(cache)}
    env.pop("JAXSLAM_CACHE", None)
    t0 = time.perf_counter()
    try:
        p = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=timeout)
    except subprocess.TimeoutExpired:
        return {"error": f"timed out after {timeout:g} s (--timeout)", "wall_s": time.perf_counter() - t0}
    wall = time.perf_counter() - t0
    if p.returncode != 0:
        return {"error": (p.stderr.strip().splitlines() or ["?"])[-1], "wall_s": wall}
    try:  # a command that exits 0 without its JSON is this row's error, not the end of the run
        doc = json.loads(js.read_text())
    except (OSError, ValueError) as e:
        return {"error": f"exit 0 but no readable --json output ({type(e).__name__}: {e})"[:300], "wall_s": wall}
    if not isinstance(doc, dict):
        return {"error": "exit 0 but the --json output is not a JSON object", "wall_s": wall}
    return {**_timing(doc), "wall_s": wall}


def run(args):
    data = pathlib.Path(args.data) if args.data else _HERE.parent / "tests" / "data"
    if args.data is not None and not data.is_dir():
        raise InputError(f"--data: {str(data)!r} is not a folder")
    names = [name for name, _ in _cases(data)]
    if args.only is not None and not any(args.only in name for name in names):
        raise InputError(f"--only: no case name contains {args.only!r}; cases: {', '.join(names)}")
    results, targets = [], []
    load0 = list(os.getloadavg())
    for name, argv in _cases(data):
        if args.only and args.only not in name:
            continue
        root = pathlib.Path(tempfile.mkdtemp(prefix="jaxslam-bench-compile-"))
        try:
            cache, out = root / "cache", root / "out"
            out.mkdir()
            print(f"[bench compile] {name}: cold", flush=True)
            cold = _one(argv, cache, out, args.timeout)
            print(f"[bench compile] {name}: warm", flush=True)
            warm = _one(argv, cache, out, args.timeout) if "error" not in cold else {}
        finally:
            shutil.rmtree(root, ignore_errors=True)
        row = {"case": name, "params": {"argv": argv}, "jaxslam_s": warm.get("compile_s"),
               "reference": "cold (empty compilation cache)", "reference_s": cold.get("compile_s"),
               "speedup": (cold["compile_s"] / warm["compile_s"]) if cold.get("compile_s") and warm.get("compile_s")
               else None, "cold": cold, "warm": warm}
        results.append(row)
        for label, case_prefix, which, field, key in _TARGET_ROWS:
            if name.startswith(case_prefix):
                v = (cold if which == "cold" else warm).get(field)
                targets.append({"name": label, "target": f"<= {TARGETS[key]:g} s", "value": v,
                                "met": v is not None and v <= TARGETS[key]})  # 0.0 s meets it
    for t in targets:
        v = t["value"]
        print(f"  [{'met' if t['met'] else 'MISSED'}] {t['name']}: "
              f"{'n/a' if v is None else f'{v:.2f} s'} (target {t['target']})")
    return {"results": results, "targets": targets,
            "load_average": {"before": load0, "after": list(os.getloadavg())}}
