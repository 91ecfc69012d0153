"""Process settings: what the library does on import, and what entry points add.

**On import** (``import jaxslam``), one thing, because without it the library is an order of
magnitude slower and can hang: :func:`pin_lapack_threads` limits the OpenBLAS thread pool
*that jaxlib's CPU LAPACK kernels use* to one thread, at run time (no environment variable,
no restart).  Measured on the 2-core CPU this project is developed on:

* jaxlib calls LAPACK (Cholesky, triangular solves, eigh) through SciPy's bundled OpenBLAS
  (``scipy.linalg.cython_lapack``).  Threaded, a 48×48 triangular solve took 2-17 ms inside
  an XLA program against 0.04 ms on one thread, and the README's library snippet ran 12×
  slower than the same work through the CLI (629 s for 100 runs).
* Some vmapped programs (the EKF-SLAM tuning step over 4 logs, a 1000-run Monte Carlo call)
  compiled and then hung on their first execution: XLA runs independent LAPACK calls on
  several of its own threads at once, and each of them woke the threaded OpenBLAS pool.
  With the pool pinned to one thread they run (``tests/test_runtime.py`` starts a fresh
  interpreter that never calls :func:`configure_process` and runs such a program).

The effect is process-wide but narrow: it touches only SciPy's OpenBLAS (``scipy.linalg``
calls in the same process run on one thread); NumPy links its own OpenBLAS, which is left
alone, and XLA's own thread pools are untouched.  A user's explicit ``OPENBLAS_NUM_THREADS``
is respected, and ``JAXSLAM_LAPACK_THREADS=N`` chooses another limit (``0``: leave the pool
as it is).  jaxslam never enables x64, changes matmul precision or XLA flags on import.

**Entry points** (the ``jaxslam`` command, the scripts, the notebook, the tests) call
:func:`configure_process` first thing.  It adds, before JAX's backend starts:

* ``OPENBLAS_NUM_THREADS=1`` (unless already set), so every OpenBLAS the process loads
  starts single-threaded;
* XLA flags for the CPU backend: ``--xla_cpu_use_fusion_emitters=false``
  (:data:`CPU_COMPILER_OPTIONS`; measured on the main job: compile 18.3 → 9.6 s and run
  6.3 → 3.4 s for 4 vmapped runs) and ``--xla_cpu_enable_concurrency_optimized_scheduler=
  false`` (kept as a second guard against the hang above);
* the persistent compilation cache (:mod:`jaxslam.compilation`).

The library's own runners pass :data:`CPU_COMPILER_OPTIONS` per program
(:func:`compiler_options`), so a script that never calls :func:`configure_process` gets the
same compiled programs as the CLI.
"""

from __future__ import annotations

import ctypes
import glob
import os
import sys
import warnings

__all__ = [
    "XLA_WORKAROUND_FLAGS",
    "CPU_COMPILER_OPTIONS",
    "LAPACK_THREADS_ENV",
    "configure_process",
    "compiler_options",
    "pin_lapack_threads",
    "lapack_threads",
]

# Per-program options of the library's runners on the CPU backend (see the module docstring).
CPU_COMPILER_OPTIONS = {"xla_cpu_use_fusion_emitters": False}

XLA_WORKAROUND_FLAGS = ("--xla_cpu_enable_concurrency_optimized_scheduler=false",) + tuple(
    f"--{k}={str(v).lower()}" for k, v in CPU_COMPILER_OPTIONS.items())

LAPACK_THREADS_ENV = "JAXSLAM_LAPACK_THREADS"

# Symbols of the thread-count setters, newest SciPy wheels first (scipy-openblas32 prefixes
# its symbols; older wheels export the plain OpenBLAS names).
_SET = ("scipy_openblas_set_num_threads", "openblas_set_num_threads")
_GET = ("scipy_openblas_get_num_threads", "openblas_get_num_threads")
_pinned: dict = {}
_found: dict = {}


def _scipy_openblas():
    """ctypes handle of the OpenBLAS bundled with SciPy (what jaxlib's LAPACK runs on), or None.

    Loaded by path without importing SciPy (0.5 s); the dynamic loader hands SciPy the same
    library object when ``scipy.linalg`` loads it later, so the thread limit carries over.
    """
    if "lib" in _found:
        return _found["lib"]
    lib = None
    try:
        import importlib.util

        spec = importlib.util.find_spec("scipy")
    except Exception:  # SciPy absent or broken: jaxlib then has no LAPACK either
        spec = None
    if spec is not None and spec.origin:
        pkg = os.path.dirname(spec.origin)
        candidates = sorted(glob.glob(os.path.join(os.path.dirname(pkg), "scipy.libs", "*openblas*")))
        candidates += sorted(glob.glob(os.path.join(pkg, ".dylibs", "*openblas*")))
        for path in candidates:
            try:
                handle = ctypes.CDLL(path)
            except OSError:
                continue
            if any(hasattr(handle, s) for s in _SET):
                lib = handle
                break
    _found["lib"] = lib
    return lib


def lapack_threads() -> int | None:
    """Threads of the OpenBLAS pool jaxlib's LAPACK uses (None if it cannot be found)."""
    lib = _scipy_openblas()
    for name in _GET:
        fn = getattr(lib, name, None) if lib is not None else None
        if fn is not None:
            fn.restype = ctypes.c_int
            return int(fn())
    return None


def pin_lapack_threads(n: int | None = None) -> int | None:
    """Limit the OpenBLAS pool behind jaxlib's CPU LAPACK kernels to ``n`` threads (default 1).

    Called on ``import jaxslam`` (module docstring).  Does nothing when the user set
    ``OPENBLAS_NUM_THREADS`` (their choice stands), when ``$JAXSLAM_LAPACK_THREADS`` is 0, or
    when SciPy's OpenBLAS cannot be found (then nothing is slow either: another LAPACK is in
    use).  Returns the limit set, or None.  An explicit ``n`` must be an int >= 1, else
    :class:`~jaxslam.errors.InputError` naming ``n`` (OpenBLAS reads 0 or less as "all cores",
    and a float was truncated, while the call returned it as if applied).
    """
    if n is not None:
        from .errors import check_int

        n = check_int(n, "n")  # (the OpenBLAS pool size)
    if n is None:
        if "OPENBLAS_NUM_THREADS" in os.environ:
            return None
        env = os.environ.get(LAPACK_THREADS_ENV, "").strip()
        try:
            n = int(env) if env else 1
        except ValueError:
            warnings.warn(f"jaxslam: {LAPACK_THREADS_ENV}={env!r} is not an integer; using 1",
                          RuntimeWarning, stacklevel=2)
            n = 1
        if n <= 0:
            return None
    if _pinned.get("n") == n:
        return n
    lib = _scipy_openblas()
    for name in _SET:
        fn = getattr(lib, name, None) if lib is not None else None
        if fn is not None:
            fn.argtypes = [ctypes.c_int]
            fn(int(n))
            _pinned["n"] = n
            return n
    return None


def compiler_options() -> dict | None:
    """Compiler options of the library's jitted runners for the current default backend."""
    import jax

    return dict(CPU_COMPILER_OPTIONS) if jax.default_backend() == "cpu" else None


def _backend_started() -> bool:
    if "jax" not in sys.modules:
        return False
    try:
        from jax._src import xla_bridge

        return bool(xla_bridge.backends_are_initialized())
    except Exception:  # private API moved: assume not started
        return False


def configure_process(cache: bool = True) -> dict:
    """Entry-point settings (module docstring): OpenBLAS threads, XLA flags, compilation cache.

    Leaves a user's own choices alone (an existing ``OPENBLAS_NUM_THREADS``, or a flag given
    with another value in ``XLA_FLAGS``).  Warns when JAX's backend has already started, since
    XLA then ignores new flags.  ``cache=False`` skips the persistent cache.  Returns the
    settings made: ``{"OPENBLAS_NUM_THREADS", "XLA_FLAGS", "cache_dir"}``.  ``cache`` is True or
    False (NumPy's too), else :class:`~jaxslam.errors.InputError` naming ``cache``, before any
    setting is made (a string "no" is truthy and switched the cache on).
    """
    # (checked without importing jaxslam.errors, which imports NumPy: NumPy's OpenBLAS must start
    # after OPENBLAS_NUM_THREADS is set; NumPy's bool is recognised by its type's module and name)
    if not (cache is True or cache is False
            or (type(cache).__module__ == "numpy" and type(cache).__name__ in ("bool", "bool_"))):
        from .errors import InputError

        raise InputError(f"cache: expected True or False, got {cache!r}"[:300])
    cache = bool(cache)
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    flags = os.environ.get("XLA_FLAGS", "")
    missing = [f for f in XLA_WORKAROUND_FLAGS if f.split("=")[0] not in flags]
    if missing:
        if _backend_started():
            warnings.warn("jaxslam.runtime.configure_process: JAX's backend has already started, so "
                          f"XLA_FLAGS {' '.join(missing)} cannot take effect in this process; call it "
                          "before the first JAX computation", RuntimeWarning, stacklevel=2)
        os.environ["XLA_FLAGS"] = " ".join([flags.strip(), *missing]).strip()
    folder = None
    if cache:
        from . import compilation

        folder = compilation.enable_cache()
    return {"OPENBLAS_NUM_THREADS": os.environ["OPENBLAS_NUM_THREADS"], "XLA_FLAGS": os.environ["XLA_FLAGS"],
            "cache_dir": None if folder is None else str(folder)}
