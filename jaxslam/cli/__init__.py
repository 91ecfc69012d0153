"""The ``jaxslam`` command: ``list | run | bench | tune | dataset | cache``.

One module per command (``run``, ``bench``, ``tune``, ``dataset``, ``listing``, ``cache``;
``common`` holds what they share); :func:`main` dispatches.  Importing the package has no side
effect: :func:`main` configures the process (:func:`jaxslam.runtime.configure_process`) when it
is called.

    jaxslam list [--dir DIR] [--data DIR]
    jaxslam run SCENARIO [--runs N] [--seed S] [--float32] [--json PATH] [--plots DIR]
                         [--quiet] [--params FILE] [scenario options]
    jaxslam bench NAME [--dir DIR] [--json PATH] [benchmark options]
    jaxslam tune SCENARIO [--target noise|lqr] [--loss LOSS] [--steps K] ...
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
import contextlib
import os
import sys

from jaxslam import __version__, runtime
from jaxslam.errors import InputError

from .common import (DEBUG_ENV, PROG, Parser, UsageError, counting_interrupts, one_line, reader_gone_safe_stdout,
                     silence_stdout)

__all__ = ["main", "find_benchmarks_dir", "list_benchmarks"]

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

exit codes: 0 success, 2 usage or input error, 1 internal failure, 130 interrupted (Ctrl-C)
(--debug or JAXSLAM_DEBUG=1 prints the traceback of an internal failure)."""



def _top_parser() -> Parser:
    p = Parser(
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
        from . import listing

        return listing.command(rest)
    if command == "run":
        from . import run

        return run.command(rest)
    if command == "bench":
        from . import bench

        return bench.command(rest)
    if command == "tune":
        from . import tune

        return tune.main(rest)
    if command == "dataset":
        from . import dataset

        return dataset.main(rest)
    if command == "cache":
        from . import cache

        return cache.command(rest)
    raise UsageError(f"{PROG}: unknown command {command!r} (choose from list, run, bench, tune, "
                     f"dataset, cache; see '{PROG} --help')")


@contextlib.contextmanager
def _one_line_warnings():
    """While a command runs, jaxslam's own warnings (their text starts with ``jaxslam:``, e.g. an
    unwritable cache folder) print as one ``jaxslam: warning: ...`` line on stderr, not as
    Python's file:line header plus a source line; other warnings keep Python's format.  The
    previous handler is restored afterwards (``main`` may be called in-process)."""
    import warnings

    default = warnings.showwarning

    def show(message, category, filename, lineno, file=None, line=None):
        text = str(message)
        if not text.startswith(PROG + ":"):
            return default(message, category, filename, lineno, file, line)
        print(f"{PROG}: warning:{text[len(PROG) + 1:]}", file=sys.stderr if file is None else file)

    warnings.showwarning = show
    try:
        yield
    finally:
        if warnings.showwarning is show:
            warnings.showwarning = default


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``jaxslam`` console script and ``python -m jaxslam``.

    Returns:
      The exit code: 0 success, 2 usage or input error, 1 internal failure, 130 interrupted.
    """
    with _one_line_warnings(), counting_interrupts(), reader_gone_safe_stdout():
        return _main(argv)


def _main(argv):
    # An entry point configures the process (OpenBLAS pinned, XLA workaround flags, the persistent
    # compilation cache) before NumPy/SciPy load and JAX starts its backend; importing this package
    # does nothing of the kind (see jaxslam.runtime, README "Performance").
    # (inside the handlers below: a Ctrl-C while it runs is the one line and 130, not a traceback)
    argv = list(sys.argv[1:] if argv is None else argv)
    debug = "--debug" in argv or os.environ.get(DEBUG_ENV, "").strip().lower() in ("1", "true", "yes", "on")
    try:
        runtime.configure_process()
        return _dispatch(argv)
    except SystemExit as e:  # argparse --help / --version
        if e.code is None or isinstance(e.code, int):
            return int(e.code or 0)
        print(one_line(e.code), file=sys.stderr)
        return 1
    except (UsageError, InputError) as e:
        if debug:
            import traceback

            traceback.print_exc()
        msg = one_line(str(e))
        print(msg if msg.startswith(PROG) else f"{PROG}: error: {msg}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # `jaxslam list | head`: the reader left; not our failure
        try:
            silence_stdout(sys.stdout.fileno())
        except (OSError, ValueError, AttributeError):
            pass
        return 0
    except Exception as e:  # noqa: BLE001 - the last line of defence: one line, no traceback
        if debug:
            import traceback

            traceback.print_exc()
        print(f"{PROG}: internal error: {type(e).__name__}: {one_line(str(e))}"
              + ("" if debug else f" (run again with --debug or {DEBUG_ENV}=1 for the traceback)"),
              file=sys.stderr)
        return 1


def __getattr__(name):  # PEP 562: the benchmark helpers without importing them at start-up
    if name in ("find_benchmarks_dir", "list_benchmarks"):
        from . import bench

        return getattr(bench, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
