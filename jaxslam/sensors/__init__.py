"""Sensor models: IMU (specific force, bias + drift), body-frame 3D LiDAR, world-frame
range/bearing, UWB ranges, the 2D scanning laser of paper 004, and the landmark sets of the
paper scenarios.

Modules share function names (``measure``, ``inverse``, ``sample_noise``), so those are reached
through their module: ``jaxslam.sensors.lidar3d.measure``,
``jaxslam.sensors.range_bearing3d.measure``.  Parameter containers, presets and the landmark
generators are also exported here.
"""

from . import imu, landmarks, laser2d, lidar3d, range_bearing3d, uwb
from .imu import PAPER000_IMU, PAPER001_IMU, BiasDriftState, ImuSpec
from .landmarks import generate_landmarks, pole_landmarks
from .laser2d import URG04LX, LaserSpec
from .lidar3d import PAPER000_LIDAR, LidarSpec
from .range_bearing3d import PAPER001_RANGE_BEARING, RangeBearingSpec

__all__ = [
    "imu",
    "lidar3d",
    "range_bearing3d",
    "landmarks",
    "laser2d",
    "uwb",
    "ImuSpec",
    "PAPER000_IMU",
    "PAPER001_IMU",
    "BiasDriftState",
    "LidarSpec",
    "PAPER000_LIDAR",
    "RangeBearingSpec",
    "PAPER001_RANGE_BEARING",
    "LaserSpec",
    "URG04LX",
    "generate_landmarks",
    "pole_landmarks",
]
