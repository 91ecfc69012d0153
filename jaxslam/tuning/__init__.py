"""Gradient-based tuning of noise covariances and controller weights (issue 7).

* :mod:`.params` — unconstrained parametrisations (log-diagonal, log-Cholesky), always PD.
* :mod:`.losses` — innovation negative log-likelihood (no truth), MSE against the truth,
  NEES consistency loss; the EKF-SLAM joint innovation terms.
* :mod:`.optimize` — optax Adam with warm-up + cosine schedule and gradient clipping,
  ``vmap`` over training runs, held-out loss curve, NaN-safe host loop, memory report.
* :mod:`.targets` — what is tuned on which data: paper 000's EKF-SLAM noise on recorded
  logs, the DF-LQR weights on ``track-figure8``, the linear-Gaussian oracle, paper 003's
  UWB noise; held-out evaluation on the scenarios themselves.
* :mod:`.cli` — ``jaxslam tune``.

No paper covers tuning; every decision is recorded in the module docstrings and in
``docs/tuning.md``.  Nothing here changes JAX's configuration on import.
"""

from . import losses, optimize, params, targets
from .losses import innovation_nll, mse, nees_loss, nll_terms, slam_innovation_terms
from .optimize import FitResult, batch_loss, fit, make_optimizer, memory_report
from .params import (
    CovSpec,
    cov_from_log_chol,
    cov_from_log_diag,
    cov_from_theta,
    log_chol_from_cov,
    log_diag_from_cov,
    pack,
    theta_from_cov,
    unpack,
)
from .targets import SlamLog, SlamRun, Target, make_slam_logs, run_slam_log, slam_loss

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
    "SlamLog",
    "SlamRun",
    "make_slam_logs",
    "run_slam_log",
    "slam_loss",
]
