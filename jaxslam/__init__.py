"""jaxslam: differentiable JAX toolkit for quadcopter estimation and control.

Importing jaxslam never enables x64, changes matmul precision or sets XLA flags: entry
points (the CLI, scenarios) and tests choose the dtype, and every library function follows
the dtype of its inputs.  It does one thing to the process: it limits the OpenBLAS pool that
jaxlib's CPU LAPACK kernels run on to one thread (threaded, those small calls stalled for
milliseconds and some programs hung; see :mod:`jaxslam.runtime`, which also says how to opt
out).
"""

from . import runtime as _runtime

__version__ = "0.1.0"

__all__ = ["__version__"]

_runtime.pin_lapack_threads()
