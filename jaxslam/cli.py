"""The ``jaxslam`` command: ``list | run | bench | tune | dataset``.

    jaxslam list [--dir DIR] [--data DIR]
    jaxslam run SCENARIO [--runs N] [--seed S] [--float32] [--json PATH] [--plots DIR]
                         [--quiet] [--params FILE] [scenario options]
    jaxslam bench NAME [--dir DIR] [--json PATH] [benchmark options]
    jaxslam tune SCENARIO [--target noise|lqr] [--loss LOSS] [--steps K] ...  (jaxslam.tuning.cli)
    jaxslam dataset NAME --data DIR ...   (real logs: mrclam, victoria-park, util-uwb, plaza)
    jaxslam cache info|clear [--dir DIR] [--json]

Exit codes: 0 success; 2 usage or input error (one line on stderr, no
traceback); 1 internal failure (one line plus a hint; ``--debug`` or the
environment variable ``JAXSLAM_DEBUG=1`` prints the traceback).

Decisions
- This is the one place where ``jax_enable_x64`` is switched on: ``run`` and
  ``bench`` enable it before any scenario or benchmark module is imported, so
  module-level constants get the right dtype.  ``run --float32`` leaves the
  setting as it is (off in a fresh process) and passes ``float32`` to the scenario.
- ``--quiet`` silences stdout and the progress bar entirely (no table, no list of
  written files); errors still go to stderr.
- JAX, NumPy and the scenario modules are imported only by the commands that use
  them, so ``jaxslam --help`` and ``--version`` return at once.
- Each scenario gets its own argument parser built from ``Scenario.options``, so
  ``jaxslam run NAME --help`` lists that scenario's options with their defaults.
- Benchmarks live outside the package, in ``benchmarks/bench_<name>.py`` (module
  attributes ``DESCRIPTION``, ``add_arguments(parser)``, ``run(args) -> dict``).
  The folder is ``--dir DIR``, else ``./benchmarks``, else the ``benchmarks/``
  folder beside the package source (editable installs); the first of the last
  two that holds a ``bench_*.py`` wins.  The folder is put on ``sys.path`` while a
  benchmark runs so that it can import its NumPy twins from the same folder.
  ``jaxslam list`` reads ``DESCRIPTION`` without importing the module.
- ``bench`` fills in ``"benchmark"`` and ``"machine"`` in the JSON when the
  benchmark's ``run`` leaves them out.
"""

from __future__ import annotations

import argparse
import ast
import importlib.util
import math
import os

from jaxslam import runtime

# The command is an entry point: it pins OpenBLAS to one thread (threaded, a 48×48 triangular
# solve measured 9 ms vs 0.04 ms pinned on 2 cores) and sets the XLA workaround flags, before
# NumPy/SciPy load and before JAX starts its backend (see jaxslam.runtime, README "Performance").
runtime.configure_process()
import pathlib
import sys

from jaxslam import __version__, files
from jaxslam.errors import InputError

__all__ = ["main", "find_benchmarks_dir", "list_benchmarks"]

PROG = "jaxslam"
_DEBUG_ENV = "JAXSLAM_DEBUG"

_TOP_EPILOG = """\
commands:
  list      scenarios, benchmarks and datasets with a one-line description
  run       run a scenario (Monte Carlo), print metrics, write JSON and plots
  bench     run a benchmark from the benchmarks/ folder
  tune      tune noise covariances (Q, R) or LQR weights by gradient descent,
            with a held-out before/after comparison
  dataset   run EKF-SLAM / FastSLAM on a real log (MRCLAM, Victoria Park, UTIL UWB,
            CMU Plaza) and report ATE/RPE/map error against ground truth
  cache     info / clear the persistent compilation cache (a second call of any
            command loads its compiled programs from there)

'jaxslam COMMAND --help' shows the options of a command;
'jaxslam run SCENARIO --help' also shows that scenario's own options.

exit codes: 0 success, 2 usage or input error, 1 internal failure
(--debug or JAXSLAM_DEBUG=1 prints the traceback of an internal failure)."""


class UsageError(Exception):
    """A command-line usage error (exit code 2)."""


class _Parser(argparse.ArgumentParser):
    """An ArgumentParser whose errors become one-line :class:`UsageError` s."""

    def error(self, message):  # noqa: D401 - argparse API
        raise UsageError(f"{self.prog}: {message} (see '{self.prog} --help')")


def int_at_least(lo: int):
    """argparse type: an int >= ``lo`` (shared by ``jaxslam tune``)."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"invalid int value: {text!r}") from None
        if value < lo:
            raise argparse.ArgumentTypeError(f"must be >= {lo}, got {value}")
        return value

    return parse


def positive_float(text: str) -> float:
    """argparse type: a finite float > 0 (shared by ``jaxslam tune``)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"invalid float value: {text!r}") from None
    if not (value > 0 and math.isfinite(value)):
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text}")
    return value


_positive_int = int_at_least(1)


def _seed(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"invalid int value: {text!r}") from None
    if not 0 <= value < 2**63:
        raise argparse.ArgumentTypeError(f"must be in [0, 2**63), got {value}")
    return value


def _out(text: str = "") -> None:
    print(text, file=sys.stdout, flush=True)


# ----------------------------------------------------------------------------- top level


def _top_parser() -> _Parser:
    p = _Parser(
        prog=PROG,
        usage=f"{PROG} [--version] [--debug] COMMAND [ARGS ...]",
        description="jaxslam: differentiable JAX toolkit for quadcopter estimation and control.",
        epilog=_TOP_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--version", action="version", version=f"{PROG} {__version__}")
    p.add_argument("--debug", action="store_true",
                   help="print tracebacks of internal failures (also JAXSLAM_DEBUG=1)")
    return p


def _dispatch(argv: list[str]) -> int:
    # The command is the first word that is not an option; what precedes it is global options.
    idx = next((i for i, a in enumerate(argv) if not a.startswith("-")), len(argv))
    top = _top_parser()
    top.parse_args(argv[:idx])  # --help / --version exit here; unknown options are errors
    if idx == len(argv):
        raise UsageError(f"{PROG}: missing COMMAND (one of list, run, bench, tune, dataset, cache; "
                         f"see '{PROG} --help')")
    command, rest = argv[idx], argv[idx + 1:]
    if command == "list":
        return _cmd_list(rest)
    if command == "run":
        return _cmd_run(rest)
    if command == "bench":
        return _cmd_bench(rest)
    if command == "tune":
        from jaxslam.tuning.cli import main as tune_main

        return tune_main(rest)
    if command == "dataset":
        from jaxslam.data.cli import main as dataset_main

        return dataset_main(rest)
    if command == "cache":
        return _cmd_cache(rest)
    raise UsageError(f"{PROG}: unknown command {command!r} (choose from list, run, bench, tune, "
                     f"dataset, cache; see '{PROG} --help')")


# ----------------------------------------------------------------------------- cache


def _cmd_cache(rest: list[str]) -> int:
    from jaxslam import compilation

    p = _Parser(prog=f"{PROG} cache",
                description="The persistent XLA compilation cache every jaxslam command uses "
                            f"(folder: ${compilation.CACHE_DIR_ENV}, else $XDG_CACHE_HOME/jaxslam/xla, "
                            f"else ~/.cache/jaxslam/xla; {compilation.CACHE_ENV}=0 switches it off).")
    p.add_argument("action", choices=("info", "clear"), help="info: folder, entries, size; clear: delete the entries")
    p.add_argument("--dir", metavar="DIR", help="the cache folder (default: as above)")
    p.add_argument("--json", action="store_true", help="print the information as JSON")
    p.add_argument("--debug", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args(rest)
    if args.action == "info":
        info = compilation.cache_info(args.dir)
    else:
        info = compilation.clear_cache(args.dir)
        info = {**info, "removed_entries": info.pop("entries"), "removed_bytes": info.pop("bytes")}
    if args.json:
        import json

        _out(json.dumps(info, indent=2))
        return 0
    state = "on" if info["enabled"] else f"off ({compilation.CACHE_ENV}=0)"
    if args.action == "info":
        _out(f"compilation cache: {info['dir']} ({state})")
        _out(f"  {info['entries']} entries, {info['bytes'] / 2**20:.1f} MiB"
             + ("" if info["exists"] else " (folder not created yet)"))
    else:
        _out(f"cleared {info['dir']}: {info['removed_entries']} entries, "
             f"{info['removed_bytes'] / 2**20:.1f} MiB removed")
    return 0


# ----------------------------------------------------------------------------- list


def _cmd_list(rest: list[str]) -> int:
    p = _Parser(prog=f"{PROG} list", description="List scenarios, benchmarks and datasets.")
    p.add_argument("--dir", metavar="DIR", help="benchmarks folder (default: see 'jaxslam bench --help')")
    p.add_argument("--data", metavar="DIR",
                   help="data folder whose datasets to show as found / not found (default: $JAXSLAM_DATA_DIR)")
    p.add_argument("--debug", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args(rest)
    from jaxslam.data import catalogue

    root = None  # checked first: a bad --data costs no JAX import
    if args.data:
        root = catalogue.data_root(args.data)
    elif os.environ.get(catalogue.DATA_ENV, "").strip():
        try:  # a stale variable does not stop the listing
            root = catalogue.data_root(None)
        except InputError as e:
            root = f"{e}, so found / not found is not shown"

    from jaxslam.sim.scenarios import registry

    scenarios = registry.all_scenarios()
    _out(f"Scenarios ({PROG} run NAME):")
    if scenarios:
        w = max(len(s.name) for s in scenarios)
        for s in scenarios:
            _out(f"  {s.name.ljust(w)}  {s.description.strip()}")
    else:
        _out("  (none registered)")

    _out()
    try:
        bench_dir = find_benchmarks_dir(args.dir)
    except InputError as e:
        if args.dir:
            raise
        bench_dir, note = None, str(e)
    benches = list_benchmarks(bench_dir) if bench_dir is not None else {}
    _out(f"Benchmarks ({PROG} bench NAME)" + (f", in {bench_dir}:" if bench_dir else ":"))
    if benches:
        w = max(len(n) for n in benches)
        for name, desc in benches.items():
            _out(f"  {name.ljust(w)}  {desc}")
    else:
        _out(f"  (none: {note})" if bench_dir is None else "  (none)")

    _out()
    _list_datasets(root)
    return 0


def _list_datasets(root) -> None:
    """The datasets of ``jaxslam dataset`` and, when a data folder is known, which it holds."""
    from jaxslam.data import catalogue

    if isinstance(root, str):  # the environment's folder is not usable: say so, list the rest
        _out(f"Datasets ({PROG} dataset NAME --data DIR; {root}):")
        w = max(len(d.name) for d in catalogue.DATASETS)
        for d in catalogue.DATASETS:
            _out(f"  {d.name.ljust(w)}  {d.description}")
        return
    where = f"in {root}" if root is not None else f"give --data DIR or set {catalogue.DATA_ENV} to see which are present"
    _out(f"Datasets ({PROG} dataset NAME --data DIR; {where}):")
    w = max(len(d.name) for d in catalogue.DATASETS)
    for d in catalogue.DATASETS:
        state = ""
        if root is not None:
            folder = catalogue.find(d.name, root)
            robots = catalogue.robots_found(d.name, root)
            state = ("  [not found]" if folder is None else
                     f"  [found: {folder}" + (f", --robot {', '.join(map(str, robots))}" if robots else "") + "]")
        _out(f"  {d.name.ljust(w)}  {d.description}{state}")


# ----------------------------------------------------------------------------- run


def _add_run_common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--runs", type=_positive_int, default=1, metavar="N",
                   help="number of Monte Carlo runs (default: 1)")
    p.add_argument("--seed", type=_seed, default=0, metavar="S",
                   help="seed of the first PRNG key; runs are split from it (default: 0)")
    p.add_argument("--float32", action="store_true",
                   help="compute in float32 (default: float64, with jax_enable_x64 switched on)")
    p.add_argument("--json", metavar="PATH", help="write the run JSON here (parent folders are created)")
    p.add_argument("--plots", metavar="DIR", help="write the scenario's PNG figures into DIR")
    p.add_argument("--quiet", action="store_true",
                   help="print nothing on stdout and no progress bar (errors still go to stderr)")
    p.add_argument("--params", metavar="FILE",
                   help="JSON file of parameter overrides ('jaxslam tune' writes them); its keys "
                        "are checked before the run and listed by 'jaxslam run SCENARIO --help'")
    p.add_argument("--debug", action="store_true",
                   help="print the traceback of an internal failure (also JAXSLAM_DEBUG=1)")


def _scenario_list_text() -> str:
    from jaxslam.sim.scenarios import registry

    return ", ".join(registry.names()) or "(none registered)"


def _escape(text: str) -> str:
    return text.replace("%", "%%")


def _add_option(group, opt) -> None:
    flags = [opt.flag] + ([f"--{opt.name}"] if "_" in opt.name else [])
    help_text = _escape(opt.help.strip())
    if opt.type is bool:
        if opt.default:
            group.add_argument(*flags, dest=opt.name, action=argparse.BooleanOptionalAction,
                               default=True, help=help_text + " (default: on)")
        else:
            group.add_argument(*flags, dest=opt.name, action="store_true", default=False,
                               help=help_text)
        return
    # An option whose help already states its default (e.g. "default: all") is not told twice.
    shown = "" if "default:" in help_text else " (default: %(default)s)"
    kw = dict(dest=opt.name, type=opt.type, default=opt.default, help=help_text + shown)
    if opt.choices is not None:
        kw["choices"] = opt.choices
    else:
        kw["metavar"] = opt.name.upper()
    group.add_argument(*flags, **kw)


def _run_parser(scenario=None, help_params: bool = False) -> _Parser:
    if scenario is None:
        p = _Parser(
            prog=f"{PROG} run",
            usage=f"{PROG} run SCENARIO [options] [scenario options]",
            description="Run a scenario: simulate, filter, report metrics over Monte Carlo runs.",
            epilog=f"scenarios: {_scenario_list_text()}\n"
                   f"'{PROG} run SCENARIO --help' lists the options of that scenario.",
            formatter_class=argparse.RawDescriptionHelpFormatter,
        )
    else:
        epilog = None
        if help_params:  # built only for --help: the schema comes from the scenario's defaults
            import numpy as np

            from jaxslam import paramfile
            from jaxslam.sim.scenarios import registry

            if scenario.params is None:
                epilog = f"--params FILE: {scenario.name} takes no --params file."
            else:
                schema = scenario.params(registry.default_options(scenario), np.dtype(np.float64))
                epilog = ("--params FILE: a JSON object with these sections and keys (matrices as\n"
                          "nested lists or their diagonals; every key optional; 'jaxslam tune'\n"
                          "writes such files):\n" + paramfile.describe(schema))
        p = _Parser(prog=f"{PROG} run {scenario.name}", description=scenario.description,
                    usage=f"{PROG} run {scenario.name} [options] [scenario options]", epilog=epilog,
                    formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scenario", metavar="SCENARIO", help="scenario name (see 'jaxslam list')")
    _add_run_common(p)
    if scenario is not None and scenario.options:
        group = p.add_argument_group(f"options of scenario {scenario.name}")
        for opt in scenario.options:
            _add_option(group, opt)
    return p


def _cmd_run(rest: list[str]) -> int:
    base = _Parser(prog=f"{PROG} run", add_help=False)
    base.add_argument("scenario", nargs="?")
    base.add_argument("-h", "--help", action="store_true")
    _add_run_common(base)
    pre, _ = base.parse_known_args(rest)
    from jaxslam import paramfile

    # What needs no scenario is checked before JAX is imported (a second, not three): the
    # --params file's JSON, then every output path (its folder created, a probe written).
    raw_params = json_path = plots_dir = None
    if pre.scenario is not None and not pre.help:
        raw_params = paramfile.load(pre.params) if pre.params else None
        json_path = files.prepare_file("--json", pre.json) if pre.json else None
        plots_dir = files.prepare_dir("--plots", pre.plots) if pre.plots else None

    # x64 before any scenario module is imported (module-level constants take its dtype).
    import jax
    import numpy as np

    if not pre.float32:
        jax.config.update("jax_enable_x64", True)

    from jaxslam import io
    from jaxslam.progress import Progress
    from jaxslam.sim.scenarios import registry

    if pre.scenario is None:
        if pre.help:
            _run_parser().print_help()
            return 0
        raise UsageError(f"{PROG} run: missing SCENARIO; valid scenarios: {_scenario_list_text()}")
    scenario = registry.get(pre.scenario)
    args = _run_parser(scenario, help_params=pre.help).parse_args(rest)
    options = {opt.name: getattr(args, opt.name) for opt in scenario.options}
    dtype = np.dtype(np.float32 if args.float32 else np.float64)

    # The --params keys against the scenario's own parameters, before anything compiles.
    params = registry.check_params(scenario, raw_params, options, dtype) if raw_params is not None else None

    from jaxslam import compilation

    progress = Progress(args.runs, label=scenario.name, enabled=not args.quiet)
    with compilation.account() as acct:
        try:
            kw = {"plots": plots_dir is not None} if _accepts(scenario.run, "plots") else {}
            result = scenario.run(runs=args.runs, seed=args.seed, dtype=dtype, options=options,
                                  progress=progress, params=params, **kw)
        finally:
            progress.close()
    if not isinstance(result, registry.ScenarioResult):
        raise TypeError(f"scenario {scenario.name!r} returned {type(result).__name__}, "
                        "expected ScenarioResult")

    report = io.run_json(scenario.name, args.runs, args.seed, dtype, result)
    report["timing"]["main_program_compile_s"] = report["timing"]["compile_s"]
    report["timing"].update(compile_timing(acct.result))
    notes = _run_notes(result, report["runs"])
    if notes:
        report["notes"] = notes
    if not args.quiet:
        _out(_format_run_report(report))
        for note in notes:
            _out(f"note: {note}")
    written = []
    if json_path is not None:
        written.append(io.write_json(json_path, report))
    if result.interrupted:  # keep what finished, skip the plots, exit as interrupted
        where = f"; wrote them to {json_path}" if json_path is not None else " (no --json: not saved)"
        print(f"{PROG} run: interrupted after {report['runs']} of {args.runs} runs; the table covers "
              f"the finished runs{where}" + (" (marked \"interrupted\": true)" if json_path else "")
              + ("; plots skipped" if plots_dir is not None else ""), file=sys.stderr, flush=True)
        return 130
    if plots_dir is not None:
        if result.plot is None:
            print(f"{PROG} run: scenario {scenario.name!r} has no plots; --plots ignored", file=sys.stderr)
        else:
            import time

            import matplotlib

            matplotlib.use("Agg")  # files only; never open a window
            t0 = time.perf_counter()
            pngs = [pathlib.Path(p) for p in (result.plot(plots_dir) or [])]
            report["timing"]["plots_s"] = time.perf_counter() - t0
            written.extend(pngs)
            if json_path is not None:  # again, now with the plotting time
                io.write_json(json_path, report)
            if not args.quiet:
                _out(f"plots: {len(pngs)} file(s) in {report['timing']['plots_s']:.1f} s")
    if not args.quiet:
        for path in written:
            _out(f"wrote {path}")
    return 0


def _run_notes(result, runs: int) -> list:
    """Notes for the run report: runs that are identical (the scenario draws no noise)."""
    import numpy as np

    if runs < 2 or not result.metrics:
        return []
    if not any(np.isfinite(np.asarray(m, float)).any() for m in result.metrics.values()):
        return []  # every run diverged: equal NaNs say nothing about random draws
    same = all(np.array_equal(v, np.broadcast_to(np.asarray(v).reshape(-1)[:1], np.shape(v)), equal_nan=True)
               for v in (np.asarray(m) for m in result.metrics.values()))
    if not same:
        return []
    return [f"all {runs} runs gave identical metrics: this scenario has no random draw under these "
            "options (every run flies the same flight), so the statistics describe one flight"]


def _accepts(fn, name: str) -> bool:
    """Whether ``fn`` takes the keyword ``name`` (scenarios registered before ``plots`` existed
    do not; they plot by themselves)."""
    import inspect

    try:
        params = inspect.signature(fn).parameters.values()
    except (TypeError, ValueError):
        return False
    return any(p.name == name or p.kind is p.VAR_KEYWORD for p in params)


def compile_timing(acct) -> dict:
    """The compile part of a command's timing JSON, from a :class:`jaxslam.compilation.CompileAccount`.

    ``compile_s`` = trace + lower + XLA compile of every program the command built (cache loads
    included); ``cache`` says whether the persistent cache was on and how often it served.
    """
    from jaxslam import compilation

    folder = compilation.enabled_dir()
    return {
        "compile_s": acct.total_s,
        "trace_s": acct.trace_s,
        "lower_s": acct.lower_s,
        "backend_compile_s": acct.compile_s,
        "programs": acct.programs,
        "cache": {"dir": None if folder is None else str(folder), "hits": acct.cache_hits,
                  "misses": acct.cache_misses},
    }


def _fmt(x) -> str:
    from jaxslam.io import _fmt_num

    return _fmt_num(float("nan") if x is None else float(x))


def _consistency_lines(cons: dict) -> list:
    """One line per statistic of the run JSON's ``consistency``: what it covers (``S_block``,
    ``S_dim``; docs/cli.md), its value against its bounds, and what an OUTSIDE verdict means.

    A statistic ``key`` (a number) finds its companions as ``key_bounds`` / ``key_block`` /
    ``key_dim`` or under its stem (``nis_mean`` -> ``nis_bounds``); reports written before the
    ``_block`` entries existed print without them.
    """
    from jaxslam.metrics import consistency_verdict

    out = []
    for key, value in cons.items():
        if key.endswith(("_bounds", "_block", "_dim")) or isinstance(value, (str, bool, list, dict)):
            continue
        stem = key.removesuffix("_mean")

        def part(suffix, key=key, stem=stem):
            return cons.get(f"{key}{suffix}", cons.get(f"{stem}{suffix}"))

        bounds, block, dim = part("_bounds"), part("_block"), part("_dim")
        kind = "nis" if stem.startswith("nis") else "nees" if "nees" in stem else None
        if block is not None:
            if kind == "nis":
                label = f"mean NIS of {block}" + (f", expected {_fmt_dim(dim)}" if dim is not None else "")
            else:
                label = f"{'ANEES' if kind == 'nees' else key} of {block}"
                if dim is not None:
                    label += f", {_fmt_dim(dim)} state{'' if dim == 1 else 's'}"
            text = f"{label} [{key}]: {_fmt(value)}"
        else:
            text = f"{key} {_fmt(value)}"
        if bounds is not None and len(bounds) == 2:
            lo, hi = (float("nan") if b is None else float(b) for b in bounds)
            v = float("nan") if value is None else float(value)
            text += f" in [{_fmt(lo)}, {_fmt(hi)}] "
            word = consistency_verdict(v, (lo, hi), kind)
            text += "undefined (no value or no bounds)" if word == "undefined" else word
        out.append(text)
    return out


def _fmt_dim(dim) -> str:
    return str(int(dim)) if float(dim).is_integer() else _fmt(dim)


def _format_run_report(report: dict) -> str:
    from jaxslam.io import format_table

    lines = [
        (f"scenario {report['scenario']}: {report['runs']} run(s), seed {report['seed']}, "
         f"{report['dtype']}"),
        "",
        format_table(report["metrics"]),
    ]
    cons = report.get("consistency")
    if cons:
        lines += ["", "consistency (two-sided 95 % chi-square bounds):"]
        lines += ["  " + line for line in _consistency_lines(cons)]
    if report.get("flags"):
        lines.append("flags: " + ", ".join(f"{k}={v}" for k, v in report["flags"].items()))
    t = report["timing"]
    cache = t.get("cache") or {}
    served = (f" ({cache.get('hits', 0)} of {cache.get('hits', 0) + cache.get('misses', 0)} programs "
              "from the compilation cache)") if cache.get("dir") else " (compilation cache off)"
    lines.append(f"timing: compile {_fmt(t['compile_s'])} s{served if 'cache' in t else ''}, "
                 f"run {_fmt(t['run_s'])} s, {_fmt(t['runs_per_s'])} runs/s")
    return "\n".join(lines)


# ----------------------------------------------------------------------------- bench


def find_benchmarks_dir(explicit=None) -> pathlib.Path:
    """The benchmarks folder: ``explicit``, else ``./benchmarks``, else the one beside the package.

    Raises:
      InputError: ``explicit`` is not a folder, or no candidate holds a ``bench_*.py``.
    """
    if explicit:
        p = pathlib.Path(explicit)
        if not p.is_dir():
            raise InputError(f"--dir: {str(p)!r} is not a folder")
        return p
    import jaxslam

    candidates = [pathlib.Path.cwd() / "benchmarks",
                  pathlib.Path(jaxslam.__file__).resolve().parents[1] / "benchmarks"]
    for c in candidates:
        if c.is_dir() and any(c.glob("bench_*.py")):
            return c
    looked = " and ".join(repr(str(c)) for c in dict.fromkeys(candidates))
    raise InputError(f"no benchmarks folder with bench_*.py files found (looked in {looked}); "
                     "pass --dir DIR")


def _description_of(path: pathlib.Path) -> str:
    """``DESCRIPTION`` of a benchmark file, read with ``ast`` (the module is not run)."""
    try:
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    except (OSError, SyntaxError, UnicodeDecodeError, ValueError):
        return "(cannot read DESCRIPTION)"
    for node in tree.body:
        targets = node.targets if isinstance(node, ast.Assign) else (
            [node.target] if isinstance(node, ast.AnnAssign) and node.value is not None else [])
        if any(isinstance(t, ast.Name) and t.id == "DESCRIPTION" for t in targets):
            try:
                value = ast.literal_eval(node.value)
            except ValueError:
                break
            if isinstance(value, str):
                return " ".join(value.split())
    return "(no DESCRIPTION)"


def list_benchmarks(bench_dir) -> dict[str, str]:
    """``{name: description}`` for the ``bench_<name>.py`` files of ``bench_dir``, sorted."""
    bench_dir = pathlib.Path(bench_dir)
    return {p.stem[len("bench_"):]: _description_of(p)
            for p in sorted(bench_dir.glob("bench_*.py")) if p.stem != "bench_"}


def _load_bench_module(path: pathlib.Path):
    mod_name = f"_jaxslam_bench_{path.stem[len('bench_'):]}"
    spec = importlib.util.spec_from_file_location(mod_name, path)
    if spec is None or spec.loader is None:
        raise InputError(f"cannot load benchmark file {str(path)!r}")
    module = importlib.util.module_from_spec(spec)
    sys.modules[mod_name] = module  # dataclasses and pickling look modules up here
    try:
        spec.loader.exec_module(module)
    except BaseException:
        sys.modules.pop(mod_name, None)
        raise
    missing = [a for a in ("DESCRIPTION", "add_arguments", "run") if not hasattr(module, a)]
    if missing:
        raise InputError(f"benchmark {str(path)!r} lacks {', '.join(missing)} "
                         "(needs DESCRIPTION, add_arguments(parser), run(args))")
    return module


def _bench_common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--dir", metavar="DIR",
                   help="benchmarks folder (default: ./benchmarks, else the one beside the "
                        "jaxslam source)")
    p.add_argument("--json", metavar="PATH", help="write the bench JSON here")
    p.add_argument("--debug", action="store_true",
                   help="print the traceback of an internal failure (also JAXSLAM_DEBUG=1)")


def _cmd_bench(rest: list[str]) -> int:
    base = _Parser(prog=f"{PROG} bench", add_help=False)
    base.add_argument("name", nargs="?")
    base.add_argument("-h", "--help", action="store_true")
    _bench_common(base)
    pre, _ = base.parse_known_args(rest)

    if pre.name is None:
        try:
            bench_dir = find_benchmarks_dir(pre.dir)
            names = ", ".join(list_benchmarks(bench_dir)) or "(none)"
        except InputError as e:
            if not pre.help:
                raise
            names = f"(none: {e})"
        if pre.help:
            p = _Parser(prog=f"{PROG} bench", usage=f"{PROG} bench NAME [options] [benchmark options]",
                        description="Run a benchmark (benchmarks/bench_NAME.py) and write its JSON.",
                        epilog=f"benchmarks: {names}\n'{PROG} bench NAME --help' lists its options.",
                        formatter_class=argparse.RawDescriptionHelpFormatter)
            p.add_argument("name", metavar="NAME", help="benchmark name")
            _bench_common(p)
            p.print_help()
            return 0
        raise UsageError(f"{PROG} bench: missing NAME; available benchmarks: {names}")

    name = pre.name
    name = name[: -len(".py")] if name.endswith(".py") else name
    name = name[len("bench_"):] if name.startswith("bench_") else name
    bench_dir = find_benchmarks_dir(pre.dir)
    available = list_benchmarks(bench_dir)
    if name not in available:
        raise InputError(f"unknown benchmark {pre.name!r} in {str(bench_dir)!r}; available: "
                         f"{', '.join(available) or '(none)'}")

    json_path = files.prepare_file("--json", pre.json) if pre.json else None  # before anything runs
    import jax

    jax.config.update("jax_enable_x64", True)  # benchmarks choose float32 by passing float32 arrays
    from jaxslam import io

    path = bench_dir / f"bench_{name}.py"
    added = str(bench_dir.resolve())
    sys.path.insert(0, added)  # lets a benchmark import its NumPy twins from the same folder
    try:
        module = _load_bench_module(path)
        p = _Parser(prog=f"{PROG} bench {name}", description=str(module.DESCRIPTION))
        p.add_argument("name", metavar="NAME", help="benchmark name")
        _bench_common(p)
        module.add_arguments(p)
        args = p.parse_args(rest)
        result = module.run(args)
    finally:
        try:
            sys.path.remove(added)
        except ValueError:
            pass
    if not isinstance(result, dict) or not isinstance(result.get("results"), list):
        raise TypeError(f"benchmark {name!r}: run(args) must return a dict with a 'results' list")
    result = {"benchmark": name, **result}
    result.setdefault("machine", io.machine_info())

    _out(_format_bench_table(result))
    if json_path is not None:
        path = io.write_json(json_path, result)
        _out(f"wrote {path}")
    return 0


def _format_bench_table(result: dict) -> str:
    header = ("case", "jaxslam_s", "reference_s", "speedup")

    def cell(row, key):
        v = row.get(key)
        if v is None:
            return "-"
        if key == "case":
            return str(v)
        try:
            v = float(v)
        except (TypeError, ValueError):
            return str(v)
        return f"{v:.2f}x" if key == "speedup" else f"{v:.4g}"

    rows = [header] + [tuple(cell(r, k) for k in header) for r in result["results"] if isinstance(r, dict)]
    widths = [max(len(r[i]) for r in rows) for i in range(len(header))]
    lines = [f"benchmark {result.get('benchmark')}"]
    for j, r in enumerate(rows):
        lines.append("  ".join([r[0].ljust(widths[0])] + [c.rjust(w) for c, w in zip(r[1:], widths[1:])]))
        if j == 0:
            lines.append("  ".join("-" * w for w in widths))
    refs = sorted({str(r["reference"]) for r in result["results"] if isinstance(r, dict) and r.get("reference")})
    if refs:
        lines.append("reference: " + ", ".join(refs))
    return "\n".join(lines)


# ----------------------------------------------------------------------------- main


def _one_line(text: str, limit: int = 400) -> str:
    first = next((ln.strip() for ln in str(text).splitlines() if ln.strip()), "")
    return first if len(first) <= limit else first[: limit - 3] + "..."


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``jaxslam`` console script and ``python -m jaxslam``.

    Returns:
      The exit code: 0 success, 2 usage or input error, 1 internal failure.
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    debug = "--debug" in argv or os.environ.get(_DEBUG_ENV, "").strip().lower() in ("1", "true", "yes", "on")
    try:
        return _dispatch(argv)
    except SystemExit as e:  # argparse --help / --version
        if e.code is None or isinstance(e.code, int):
            return int(e.code or 0)
        print(_one_line(e.code), file=sys.stderr)
        return 1
    except (UsageError, InputError) as e:
        if debug:
            import traceback

            traceback.print_exc()
        msg = _one_line(str(e))
        print(msg if msg.startswith(PROG) else f"{PROG}: error: {msg}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # `jaxslam list | head`: the reader left; not our failure
        try:
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
        except (OSError, ValueError, AttributeError):
            pass
        return 0
    except Exception as e:  # noqa: BLE001 - the last line of defence: one line, no traceback
        if debug:
            import traceback

            traceback.print_exc()
        print(f"{PROG}: internal error: {type(e).__name__}: {_one_line(str(e))}"
              + ("" if debug else f" (run again with --debug or {_DEBUG_ENV}=1 for the traceback)"),
              file=sys.stderr)
        return 1
