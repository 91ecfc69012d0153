"""jaxslam: differentiable JAX toolkit for quadcopter estimation and control.

Importing jaxslam has no configuration side effects: it never enables x64 or
changes matmul precision.  Entry points (the CLI, scenarios) and tests choose
the dtype; every library function follows the dtype of its inputs.
"""

__version__ = "0.1.0"

__all__ = ["__version__"]
