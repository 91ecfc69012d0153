"""Test configuration.

x64 is enabled here (the test entry point), never by the library on import;
float32 paths are exercised by passing float32 arrays explicitly.

Compilation dominates this suite's run time (XLA backend compile was 672 of 853 s of a
one-core profile), so:

* the persistent compilation cache lives in a test-local folder (``.pytest_cache/jaxslam-xla``
  beside this checkout, or ``$JAXSLAM_TEST_CACHE_DIR``), shared by the xdist workers and kept
  between runs; ``JAXSLAM_TEST_NO_CACHE=1`` runs uncached;
* JAX's in-memory caches are cleared after a test module once the worker passes 800 MB, and
  after any test once it passes 1.2 GB, which bounds each worker's memory (compiled programs
  otherwise accumulate: 5.5 GB over the suite);
* programs are compiled with LLVM's optimisation off (``--xla_backend_optimization_level=0``,
  also for the CLI subprocesses the tests start): measured on the main job's program, compile
  6.6 → 4.0 s, run 1.0 → 2.3 s, results equal to 1e-14.  The tests check numbers, not
  speed (speed is ``benchmarks/``'s job).  ``JAXSLAM_TEST_OPT=1`` compiles as users do;
* the lowered programs carry each operation's own source line, not the whole call stack
  (``JAX_INCLUDE_FULL_TRACEBACKS_IN_LOCATIONS=0``, ``JAX_TRACEBACK_IN_LOCATIONS_LIMIT=0``
  unless set; JAX's defaults are on and 100 frames, and under pytest every operation's stack
  is deep): whole suite, empty cache, same machine, 2026-12-07: 602.9 s (1112 s user) → 578.9
  s (1061 s user); two filter test files without the cache, one worker: lowering 21.1 → 19.4 s,
  XLA compile 41.6 → 38.6 s (smaller modules).  Python's own tracebacks are unchanged.  Tried
  and not kept the same day: ``--xla_cpu_parallel_codegen_split_count=1`` (six mid-size files
  93-99 → 84-89 s, the whole suite 602.9 → 671.6 s).

Where the time goes (whole suite, empty cache, ``JAX_LOG_COMPILES`` read by a logging
plugin, 2026-12-07, 605 s wall, 1180 s in the two workers): XLA compilation 546 s, lowering
(jaxpr → MLIR) 198 s, tracing 196 s — 80 % of the workers' time.  14 439 programs compiled;
13 176 of them one-operation programs of eager code (test bodies and the library's eager
paths; 100 s of XLA time and 97 s of lowering, ~15-18 ms each in all, of which ~3.4 ms is
JAX making a new MLIR context per program); 232 programs over 0.5 s take 284 s.  JAX 0.10
compiles an identity program (``jit(stage)``) for every ``jnp.asarray`` of a NumPy array of a
new shape (776 in the suite): the library converts NumPy inputs with ``linalg.to_jax``.
"""

import collections
import os
import pathlib

_cache = pathlib.Path(os.environ.get("JAXSLAM_TEST_CACHE_DIR", "")
                      or pathlib.Path(__file__).resolve().parents[1] / ".pytest_cache" / "jaxslam-xla")
if os.environ.get("JAXSLAM_TEST_NO_CACHE") == "1":
    os.environ["JAXSLAM_CACHE"] = "0"
else:
    os.environ["JAXSLAM_CACHE_DIR"] = str(_cache)  # subprocesses of the tests (the CLI) use it too

os.environ.setdefault("JAX_INCLUDE_FULL_TRACEBACKS_IN_LOCATIONS", "0")
os.environ.setdefault("JAX_TRACEBACK_IN_LOCATIONS_LIMIT", "0")

if os.environ.get("JAXSLAM_TEST_OPT") != "1" and "xla_backend_optimization_level" not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_backend_optimization_level=0").strip()

# OpenBLAS pinned, the XLA flags before JAX's backend starts, the persistent cache (jaxslam.runtime).
from jaxslam import runtime  # noqa: E402

runtime.configure_process()

import jax  # noqa: E402
import pytest  # noqa: E402

jax.config.update("jax_enable_x64", True)


try:
    import ctypes

    _malloc_trim = ctypes.CDLL("libc.so.6").malloc_trim
except (OSError, AttributeError):  # not glibc
    _malloc_trim = None


_RSS_LIMIT_MB = 1200  # per worker: two workers and the controller stay under 3 GB
# After a module, caches are kept while the worker is below this: the one-operation programs of
# test bodies (run outside jit, ~10 ms to compile each) then serve the next modules too
# (measured: 10444 -> 9973 compiles over the suite; largest worker 1.33 GB).
_MODULE_RSS_MB = 800


def _rss_mb() -> int:
    try:
        with open("/proc/self/status") as f:
            return next(int(line.split()[1]) for line in f if line.startswith("VmRSS")) // 1024
    except (OSError, StopIteration):
        return 0


def _release():
    jax.clear_caches()
    from jaxslam import compilation
    from jaxslam.sim import monte_carlo

    compilation.clear_programs()
    monte_carlo.clear_programs()
    if _malloc_trim is not None:  # hand the freed compiler memory back (glibc keeps it otherwise)
        _malloc_trim(0)


@pytest.fixture(autouse=True, scope="module")
def _clear_jax_caches_after_module():
    yield
    if _rss_mb() > _MODULE_RSS_MB:
        _release()


@pytest.fixture(autouse=True)
def _bound_memory_within_module():
    # A module that compiles many programs (tests/filters/test_filters_ekf_slam.py reached
    # 2.2 GB) is cleared between its tests once the worker passes the limit.
    yield
    if _rss_mb() > _RSS_LIMIT_MB:
        _release()


if os.environ.get("JAXSLAM_TEST_RSS_LOG"):  # development aid: resident memory after every test
    def pytest_runtest_teardown(item):
        with open("/proc/self/status") as f:
            rss = next(int(line.split()[1]) for line in f if line.startswith("VmRSS"))
        with open(os.environ["JAXSLAM_TEST_RSS_LOG"] + f".{os.getpid()}", "a") as f:
            f.write(f"{rss // 1024} {item.nodeid}\n")


# The files that take longest (fresh cache, 2026-12-04 --durations: 30-90 s each) go first.
# xdist hands whole files (--dist loadfile) to the two workers in order; one of these started
# last would leave the other core idle at the end (a simulation of the measured durations gave
# 499 s for xdist's own order, most tests first, and 490 s for this one).  The rest keep
# xdist's order, most tests first (``--no-loadscope-reorder`` in pyproject.toml hands the
# ordering to this hook).
_LONGEST_FIRST = (
    "tests/tuning/test_tuning_loop.py",
    "tests/filters/test_filters_ekf_slam.py",
    "tests/test_compile_once.py",
    "tests/tuning/test_real_logs_plaza.py",
    "tests/systems/test_systems_ekf_slam_3d.py",
    "tests/tuning/test_tuning_cli.py",
    "tests/systems/test_planar_ekf_slam.py",
    "tests/faults/test_faults_datasets.py",
    "tests/tuning/test_real_logs_victoria_park.py",
    "tests/test_readme.py",
)


def pytest_collection_modifyitems(config, items):
    rank = {f: i for i, f in enumerate(_LONGEST_FIRST)}
    files = [it.nodeid.split("::")[0] for it in items]
    count = collections.Counter(files)
    order = {id(it): (rank.get(f, len(rank)), -count[f], f) for it, f in zip(items, files)}
    items.sort(key=lambda it: order[id(it)])  # stable: a file's own order is kept


@pytest.fixture
def run_cli(capsys):
    """``run_cli(argv) -> (exit code, stdout, stderr)`` of ``jaxslam`` called in this process."""
    from jaxslam import cli

    def run(argv):
        rc = cli.main(argv)
        out = capsys.readouterr()
        return rc, out.out, out.err

    return run
