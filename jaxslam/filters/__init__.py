"""Generic filters (they never name a paper).

* :mod:`jaxslam.filters.gaussian` — what every Gaussian filter shares: beliefs, the masked
  correction, ``GaussianFilter(predict, update)`` and one runner (``run``).
* :mod:`jaxslam.filters.ekf` — EKF core: predict / masked, gated (optionally iterated) update /
  whole-sequence scan.
* :mod:`jaxslam.filters.ukf` — sigma-point filter (unscented, cubature), the EKF's signatures.
* :mod:`jaxslam.filters.sqrt_ekf` — square-root (Cholesky-factor) EKF for float32 runs.
* :mod:`jaxslam.filters.sqrt_ukf` — square-root sigma-point filter (same rules as ``ukf``).
* :mod:`jaxslam.filters.smoother` — RTS, fixed-lag and iterated (Gauss–Newton) smoothers.
* :mod:`jaxslam.filters.ekf_slam` — EKF-SLAM engine on a fixed-capacity padded map.
* :mod:`jaxslam.filters.fastslam` — FastSLAM 1.0 core: vmapped particles, padded landmark EKFs.
* :mod:`jaxslam.filters.trilateration` — least-squares trilateration (ranges to known points).
* :mod:`jaxslam.filters.delayed_init` — landmarks from buffered ranges (range-only SLAM).
* :mod:`jaxslam.filters.resampling` — log-weight normalisation, ESS, resampling schemes, soft.
"""

from . import ekf, ekf_slam, gaussian, smoother, sqrt_ekf, sqrt_ukf, ukf
from . import fastslam, resampling
from .ekf import (
    Gaussian,
    Posterior,
    UpdateInfo,
    angle_residual,
    chi2_gate,
    filter_scan,
    make_filter,
    predict,
    predict_additive,
    update,
    update_batch,
    validate_gaussian,
    validate_noise_cov,
)

__all__ = [
    "ekf",
    "ekf_slam",
    "gaussian",
    "ukf",
    "sqrt_ekf",
    "sqrt_ukf",
    "smoother",
    "fastslam",
    "resampling",
    "Gaussian",
    "UpdateInfo",
    "Posterior",
    "predict",
    "predict_additive",
    "update",
    "update_batch",
    "filter_scan",
    "make_filter",
    "angle_residual",
    "chi2_gate",
    "validate_gaussian",
    "validate_noise_cov",
]
