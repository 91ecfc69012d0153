"""Systems: each paper's (or dataset's) model on the generic engines, one module per system.

Every system module follows one convention, so a script written for one runs another:

* ``Config`` — static choices (sizes and switches; hashable, a change recompiles);
* ``Params`` — the numbers (noise, initial spreads; traced, so a change never recompiles and
  ``jax.grad`` reaches them);
* ``Log`` — one run's recorded inputs (a batch adds a leading axis); ``Event`` — one slice of it;
* ``State`` — the posterior between events; ``StepOut`` — what one event reports;
  ``Result`` — a whole run;
* ``init(log, config, params, *, key=None) -> State``,
  ``step(state, event, config, params, *, key=None) -> (State, StepOut)``,
  ``run(log, config, params, *, key=None) -> Result``.  ``run`` checks concrete inputs
  (:class:`jaxslam.errors.InputError` naming the argument), jits itself with ``config``
  static, and also works inside an outer ``jax.jit`` / ``jax.vmap``.  Particle filters and
  systems that draw random numbers (RANSAC) require ``key``.

=======================  ====================================================================
module                   system
=======================  ====================================================================
``ekf_slam_3d``          paper 000: 3D LiDAR + IMU EKF-SLAM (also the closed-loop estimator)
``fastslam_001``         paper 001: two-stage dynamics-based FastSLAM with IMU bias and drift
``uwb_slam_2d``          paper 003: 2D range-only UWB EKF-SLAM with trilateration start-up
``line_slam_004``        paper 004: RANSAC line features, line-feature EKF-SLAM
``planar_ekf_slam``      planar range-bearing EKF-SLAM (MRCLAM, Victoria Park)
``planar_fastslam``      planar range-bearing FastSLAM 1.0 and 2.0 (MRCLAM, Victoria Park)
``util_range``           UTIL UWB TWR: 3D range-only tag tracking / SLAM with a range bias
``plaza_range``          Plaza: 2D range-only SLAM with a range bias and delayed initialisation
=======================  ====================================================================

``biased_range`` holds the range model the last two share; ``estimator`` the interface of an
estimator in the closed-loop simulation.  Submodules load on first use
(``jaxslam.systems.util_range`` or ``from jaxslam.systems import util_range``), so importing
this package costs nothing.
"""

from __future__ import annotations

import importlib

SYSTEMS = ("ekf_slam_3d", "fastslam_001", "uwb_slam_2d", "line_slam_004", "planar_ekf_slam",
           "planar_fastslam", "util_range", "plaza_range")

__all__ = list(SYSTEMS) + ["biased_range", "estimator", "SYSTEMS"]


def __getattr__(name):
    if name in __all__:
        return importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(__all__))
