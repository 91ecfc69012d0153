"""Sensor models: IMU (specific force, bias + drift), body-frame 3D LiDAR, world-frame
range/bearing, and the landmark sets of the paper scenarios.

Modules share function names (``measure``, ``inverse``, ``sample_noise``), so those are reached
through their module: ``jaxslam.sensors.lidar3d.measure``,
``jaxslam.sensors.range_bearing3d.measure``.  Parameter containers, presets and the landmark
generators are also exported here.
"""

from . import imu, landmarks, lidar3d, range_bearing3d
from .imu import PAPER000_IMU, PAPER001_IMU, BiasDriftState, ImuSpec
from .landmarks import generate_landmarks, pole_landmarks
from .lidar3d import PAPER000_LIDAR, LidarSpec
from .range_bearing3d import PAPER001_RANGE_BEARING, RangeBearingSpec

__all__ = [
    "imu",
    "lidar3d",
    "range_bearing3d",
    "landmarks",
    "ImuSpec",
    "PAPER000_IMU",
    "PAPER001_IMU",
    "BiasDriftState",
    "LidarSpec",
    "PAPER000_LIDAR",
    "RangeBearingSpec",
    "PAPER001_RANGE_BEARING",
    "generate_landmarks",
    "pole_landmarks",
]
