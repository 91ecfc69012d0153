"""Figures (matplotlib, Agg): one module per family, each function writes PNG files atomically.

``flight`` (trajectories, errors, ±3σ), ``slam3d`` (paper 000 maps), ``fastslam`` (paper 001),
``uwb`` (paper 003), ``lines`` and ``attitude`` (paper 004), ``dataset`` (real logs), ``tuning``
(loss curves and fitted parameters).
"""
