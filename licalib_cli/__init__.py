"""licalib: targetless LiDAR-IMU calibration from ROS1/ROS2 bags.

Conventions used everywhere in the package:

* ``T_imu_lidar`` maps LiDAR points into the IMU frame: ``p_imu = R @ p_lidar + t``.
* Quaternions are ``[x, y, z, w]`` (Hamilton).
* ``time_offset_s``: ``t_imu = t_lidar + time_offset_s``.
* Time is int64 nanoseconds at every boundary; float seconds only inside the math.
"""

from __future__ import annotations

import logging

__version__ = "0.1.0"

logging.getLogger(__name__).addHandler(logging.NullHandler())

__all__ = ["__version__"]
