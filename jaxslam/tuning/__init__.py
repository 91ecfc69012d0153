"""Gradient-based tuning of noise covariances and controller weights (issue 7).

* :mod:`.params` — unconstrained parametrisations (log-diagonal, log-Cholesky), always PD.
* :mod:`.losses` — innovation negative log-likelihood (no truth), MSE against the truth,
  NEES consistency loss; the EKF-SLAM joint innovation terms.
* :mod:`.optimize` — optax Adam with warm-up + cosine schedule and gradient clipping,
  ``vmap`` over training runs, held-out loss curve, NaN-safe host loop, memory report.
* :mod:`.targets` — what is tuned on which data, one module per target: paper 000's
  EKF-SLAM noise on recorded logs, the DF-LQR weights on ``track-figure8``, the
  linear-Gaussian oracle, paper 003's UWB noise, the planar EKF-SLAM's noise from MRCLAM logs;
  held-out evaluation on the scenarios themselves.

``jaxslam tune`` is :mod:`jaxslam.cli.tune`.

No paper covers tuning; every decision is recorded in the module docstrings and in
``docs/tuning.md``.  Nothing here changes JAX's configuration on import.
"""

import importlib

# Names are loaded on first use (PEP 562), so importing ``jaxslam.cli.tune`` imports no JAX
# and no target module: ``jaxslam tune`` checks its arguments and output paths first, then
# switches x64 on, then imports the targets (their module constants take that dtype).
_SOURCES = {
    "losses": ("innovation_nll", "mse", "nees_loss", "nll_terms", "slam_innovation_terms"),
    "optimize": ("FitResult", "batch_loss", "fit", "make_optimizer", "memory_report"),
    "params": ("CovSpec", "cov_from_log_chol", "cov_from_log_diag", "cov_from_theta",
               "log_chol_from_cov", "log_diag_from_cov", "pack", "theta_from_cov", "unpack"),
    "targets": ("Target",),
}
_WHERE = {name: mod for mod, names in _SOURCES.items() for name in names}


def __getattr__(name):
    if name in _SOURCES:
        return importlib.import_module(f"{__name__}.{name}")
    if name in _WHERE:
        return getattr(importlib.import_module(f"{__name__}.{_WHERE[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(__all__))


__all__ = [
    "params",
    "losses",
    "optimize",
    "targets",
    "CovSpec",
    "log_diag_from_cov",
    "cov_from_log_diag",
    "log_chol_from_cov",
    "cov_from_log_chol",
    "theta_from_cov",
    "cov_from_theta",
    "pack",
    "unpack",
    "nll_terms",
    "slam_innovation_terms",
    "innovation_nll",
    "mse",
    "nees_loss",
    "FitResult",
    "make_optimizer",
    "batch_loss",
    "fit",
    "memory_report",
    "Target",
]
