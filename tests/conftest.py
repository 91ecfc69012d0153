"""Test configuration.

x64 is enabled here (the test entry point), never by the library on import;
float32 paths are exercised by passing float32 arrays explicitly.

Compilation dominates this suite's run time, so a persistent XLA compilation
cache (in pytest's cache folder) lets identical programs compiled by different
tests — and by later runs — be reused.
"""

import os
import pathlib

# OpenBLAS pinned to one thread before it loads, and the XLA workaround flags before JAX's
# backend starts (jaxslam.runtime: small LAPACK calls stall when threaded; a CPU scheduler hang).
from jaxslam import runtime  # noqa: E402

runtime.configure_process()

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

_cache = pathlib.Path(__file__).resolve().parents[1] / ".pytest_cache" / "jax_compilation"
if os.environ.get("JAXSLAM_TEST_NO_CACHE") != "1":
    _cache.mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", str(_cache))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
