"""Process settings for entry points — the CLI, scripts, notebooks and the tests.

Nothing here runs on import: :func:`configure_process` is called by an entry point before JAX
creates its CPU backend (and, for OpenBLAS, before NumPy loads).  A library user calls it
the same way, first thing in a script, or sets the two variables in the shell.

* ``OPENBLAS_NUM_THREADS=1`` (unless already set): jaxlib's CPU LAPACK kernels (Cholesky,
  triangular solves) run on SciPy's OpenBLAS; threaded, small calls stalled for milliseconds
  on 2 cores (README, "Performance notes").
* ``XLA_FLAGS += --xla_cpu_enable_concurrency_optimized_scheduler=false`` (unless the flag is
  already given): with jax/jaxlib 0.10.2 on CPU, some vmapped programs — the EKF-SLAM tuning
  step over 4 logs, a single 1000-run Monte Carlo call — compiled, then hung on their first
  execution forever, every thread idle (gdb: the caller in ``BlockUntilReady``, XLA's worker
  pools waiting for work).  The same programs with this scheduler switched off ran (measured:
  value+grad of the innovation NLL over 4 logs of 10 s, 2.3 s per call; hung at 4 × 1 s
  without the flag, ran at 2 logs either way).  Passing the option per compilation
  (``compiler_options``) did not help; it must be in ``XLA_FLAGS`` before the backend starts.
"""

from __future__ import annotations

import os
import sys
import warnings

__all__ = ["XLA_WORKAROUND_FLAGS", "configure_process"]

XLA_WORKAROUND_FLAGS = ("--xla_cpu_enable_concurrency_optimized_scheduler=false",)


def _backend_started() -> bool:
    if "jax" not in sys.modules:
        return False
    try:
        from jax._src import xla_bridge

        return bool(xla_bridge.backends_are_initialized())
    except Exception:  # private API moved: assume not started
        return False


def configure_process() -> dict:
    """Set ``OPENBLAS_NUM_THREADS`` and the XLA workaround flags (see the module docstring).

    Leaves a user's own choices alone (an existing ``OPENBLAS_NUM_THREADS``, or the flag
    given with another value in ``XLA_FLAGS``).  Warns when JAX's backend has already
    started, since XLA then ignores new flags.  Returns the two variables' values.
    """
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    flags = os.environ.get("XLA_FLAGS", "")
    missing = [f for f in XLA_WORKAROUND_FLAGS if f.split("=")[0] not in flags]
    if missing:
        if _backend_started():
            warnings.warn("jaxslam.runtime.configure_process: JAX's backend has already started, so "
                          f"XLA_FLAGS {' '.join(missing)} cannot take effect in this process; call it "
                          "before the first JAX computation", RuntimeWarning, stacklevel=2)
        os.environ["XLA_FLAGS"] = " ".join([flags.strip(), *missing]).strip()
    return {"OPENBLAS_NUM_THREADS": os.environ["OPENBLAS_NUM_THREADS"], "XLA_FLAGS": os.environ["XLA_FLAGS"]}
