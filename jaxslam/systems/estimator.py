"""The estimator interface of the closed loop: what a system hands to :func:`jaxslam.sim.simulate.simulate`.

When the estimator is in the loop (paper 000: the DF-LQR acts on the EKF-SLAM estimate), the
simulation scan calls the system's filter at every control step and every sensor frame; a
system builds this container of pure functions (e.g. :func:`jaxslam.systems.ekf_slam_3d.make_estimator`).
It lives at the systems level so that systems never import the simulation.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

__all__ = ["Estimator"]


class Estimator(NamedTuple):
    """An estimator plugged into the closed loop (all pure functions).

    init(key, x0_true) -> est
    propagate(est, imu_prev (6,), imu_now (6,)) -> est            every step
    correct(est, y (L, 3), ids (L,), visible (L,), x_true (12,)) -> (est, frame_out)
                                                     every LiDAR frame (x_true for metrics only)
    ctrl_state(est, imu_now) -> (12,) state the controller sees
    step_out(est, x_true (12,)) -> pytree saved at every step (e.g. mean, NEES)
    """

    init: Callable
    propagate: Callable
    correct: Callable
    ctrl_state: Callable
    step_out: Callable
