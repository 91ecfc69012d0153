"""Feature extraction from 2D laser scans: RANSAC line features in Hesse normal form (paper 004,
ch. 4.1, Algorithm 1, eq. 4.1) and prior-guided matching of predicted lines ("Feature matching").
"""

from . import lines
from .lines import (
    DEFAULT_RANSAC,
    Lines,
    RansacConfig,
    check_ransac_config,
    extract_guided,
    extract_lines,
    fit_line,
    fit_line_cov,
    hesse_normalize,
    line_through,
    match_predicted,
    n_hypotheses,
    point_line_distance,
    segment_endpoints,
)

__all__ = [
    "lines",
    "Lines",
    "RansacConfig",
    "DEFAULT_RANSAC",
    "check_ransac_config",
    "hesse_normalize",
    "line_through",
    "fit_line",
    "fit_line_cov",
    "point_line_distance",
    "segment_endpoints",
    "n_hypotheses",
    "extract_lines",
    "match_predicted",
    "extract_guided",
]
