"""Test configuration: tests run with x64 available so float64 oracles are exact.

x64 is enabled here (the test entry point), never by the library on import.
float32 paths are exercised by passing float32 arrays explicitly.
"""

import jax

jax.config.update("jax_enable_x64", True)
