"""Generic filters (they never name a paper).

* :mod:`jaxslam.filters.ekf` — EKF core: predict / masked, gated update / whole-sequence scan.
* :mod:`jaxslam.filters.ekf_slam` — EKF-SLAM engine on a fixed-capacity padded map.
* :mod:`jaxslam.filters.fastslam` — FastSLAM 1.0 core: vmapped particles, padded landmark EKFs.
* :mod:`jaxslam.filters.resampling` — log-weight normalisation, ESS, resampling schemes, soft.
"""

from . import ekf, ekf_slam
from . import fastslam, resampling
from .ekf import (
    Gaussian,
    Posterior,
    UpdateInfo,
    angle_residual,
    chi2_gate,
    filter_scan,
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
    "angle_residual",
    "chi2_gate",
    "validate_gaussian",
    "validate_noise_cov",
]
