"""What an Ouster recording carries besides clouds and IMU messages: its metadata and packets.

The ouster-ros driver publishes the sensor's metadata as a JSON string (``std_msgs/String``,
topic ``/ouster/metadata`` or ``/<node>/metadata``). It holds the factory transforms
``lidar_to_sensor_transform`` and ``imu_to_sensor_transform``: row-major 4x4 matrices, in mm,
mapping the ``os_lidar`` and ``os_imu`` frames into the ``os_sensor`` frame (top level in the
legacy metadata format; under ``lidar_intrinsics`` / ``imu_intrinsics`` in the newer one).
In licalib's convention (``p_imu = R p_lidar + t``) the factory extrinsic of a cloud in
``os_lidar`` is::

    T_imu_lidar = inv(T_sensor_imu) * T_sensor_lidar      (mm converted to m)

and of a cloud published in ``os_sensor`` (the driver's ``point_cloud_frame``), ``T_imu_sensor
= inv(T_sensor_imu)``. Which applies is read from the cloud's ``header.frame_id``.

A bag recorded in the driver's packet mode holds ``ouster_ros/PacketMsg`` (or
``ouster_sensor_msgs/PacketMsg``) topics instead of clouds and IMU messages:
:func:`packet_topics` finds them so that the reader can say what to do.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from licalib_cli.io.bag import BagHandle, TopicInfo

__all__ = [
    "METADATA_TYPE",
    "PACKET_TYPES",
    "FactoryExtrinsic",
    "cloud_frame",
    "factory_extrinsic",
    "metadata_transforms",
    "packet_topics",
    "read_factory_extrinsic",
]

logger = logging.getLogger(__name__)

METADATA_TYPE = "std_msgs/msg/String"
PACKET_TYPES = ("ouster_ros/msg/PacketMsg", "ouster_sensor_msgs/msg/PacketMsg")
"""Message types of the ouster-ros driver's raw packets (ROS1 and ROS2 names)."""


@dataclass(frozen=True)
class FactoryExtrinsic:
    """The factory IMU-LiDAR extrinsic of an Ouster sensor, in licalib's convention.

    Attributes:
        rotation: (3, 3) ``R`` of ``p_imu = R p_cloud + t``.
        translation: (3,) ``t``, m (the cloud frame's origin in the IMU frame).
        cloud_frame: ``os_lidar`` or ``os_sensor``: the frame the clouds are in, which the
            extrinsic maps from.
        topic: the metadata topic it was read from.
        sensor: product line and serial number, e.g. ``OS-1-128 sn 122201000998`` (what the
            metadata names; may be empty).
    """

    rotation: npt.NDArray[np.float64]
    translation: npt.NDArray[np.float64]
    cloud_frame: str
    topic: str
    sensor: str = ""

    def quaternion_xyzw(self) -> npt.NDArray[np.float64]:
        """The rotation as a unit quaternion ``[x, y, z, w]`` (w >= 0)."""
        from scipy.spatial.transform import Rotation

        q = Rotation.from_matrix(self.rotation).as_quat()
        return q if q[3] >= 0 else -q


def _matrix(values: Any) -> npt.NDArray[np.float64] | None:
    """A 4x4 matrix from 16 row-major numbers, or None when it is not one."""
    try:
        m = np.asarray(values, dtype=np.float64).reshape(4, 4)
    except (TypeError, ValueError):
        return None
    return m if np.all(np.isfinite(m)) else None


def metadata_transforms(
    metadata: dict[str, Any],
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]] | None:
    """``(T_sensor_lidar, T_sensor_imu)`` in mm from Ouster metadata (legacy or nested
    format), or None when it does not carry both."""
    lidar = metadata.get("lidar_to_sensor_transform")
    imu = metadata.get("imu_to_sensor_transform")
    if lidar is None and isinstance(metadata.get("lidar_intrinsics"), dict):
        lidar = metadata["lidar_intrinsics"].get("lidar_to_sensor_transform")
    if imu is None and isinstance(metadata.get("imu_intrinsics"), dict):
        imu = metadata["imu_intrinsics"].get("imu_to_sensor_transform")
    t_lidar, t_imu = _matrix(lidar), _matrix(imu)
    if t_lidar is None or t_imu is None:
        return None
    return t_lidar, t_imu


def _sensor_name(metadata: dict[str, Any]) -> str:
    sensor_info = metadata.get("sensor_info")
    info: dict[str, Any] = sensor_info if isinstance(sensor_info, dict) else {}
    line = metadata.get("prod_line") or info.get("prod_line") or ""
    serial = metadata.get("prod_sn") or info.get("prod_sn") or ""
    return " ".join(x for x in (str(line), f"sn {serial}" if serial else "") if x)


def factory_extrinsic(
    metadata: dict[str, Any], cloud_frame: str = "os_lidar", topic: str = ""
) -> FactoryExtrinsic | None:
    """The factory ``T_imu_<cloud frame>`` from Ouster metadata, or None without transforms.

    Args:
        metadata: the parsed metadata JSON.
        cloud_frame: ``os_sensor`` when the clouds are published in the sensor frame,
            anything else for ``os_lidar`` (the driver's default).
        topic: where the metadata came from (kept in the result).
    """
    transforms = metadata_transforms(metadata)
    if transforms is None:
        return None
    t_sensor_lidar, t_sensor_imu = transforms
    frame = "os_sensor" if cloud_frame.endswith("sensor") else "os_lidar"
    t_cloud = np.eye(4) if frame == "os_sensor" else t_sensor_lidar
    t_imu_cloud = np.linalg.inv(t_sensor_imu) @ t_cloud
    rotation = t_imu_cloud[:3, :3]
    u, _, vt = np.linalg.svd(rotation)  # the metadata's numbers are rounded: re-orthonormalise
    rotation = u @ np.diag([1.0, 1.0, float(np.linalg.det(u @ vt))]) @ vt
    return FactoryExtrinsic(
        rotation=rotation,
        translation=t_imu_cloud[:3, 3] / 1000.0,
        cloud_frame=frame,
        topic=topic,
        sensor=_sensor_name(metadata),
    )


def _metadata_topics(topics: Sequence[TopicInfo]) -> list[TopicInfo]:
    return [t for t in topics if t.msgtype == METADATA_TYPE and t.name.endswith("metadata")]


def read_factory_extrinsic(
    bag: BagHandle, cloud_frame: str = "os_lidar"
) -> FactoryExtrinsic | None:
    """The factory extrinsic from the first Ouster metadata message of the bag (a
    ``std_msgs/String`` topic named ``.../metadata`` holding the sensor's JSON), or None when
    the bag has none or it carries no transforms."""
    for topic in _metadata_topics(bag.topics):
        for raw in bag.messages([topic.name]):
            msg = bag.decode(raw)
            if msg is None:
                continue
            try:
                metadata = json.loads(msg.data)
            except (TypeError, ValueError):
                logger.debug("%s does not hold JSON", topic.name)
                break
            if isinstance(metadata, dict):
                found = factory_extrinsic(metadata, cloud_frame, topic.name)
                if found is not None:
                    return found
            break
    return None


def cloud_frame(bag: BagHandle, topic: str) -> str:
    """``header.frame_id`` of the first cloud of ``topic`` that decodes (``""``: none)."""
    for raw in bag.messages([topic]):
        msg = bag.decode(raw)
        if msg is not None:
            return str(msg.header.frame_id)
    return ""


def packet_topics(topics: Sequence[TopicInfo]) -> list[TopicInfo]:
    """The topics of raw Ouster packets (the driver's packet mode)."""
    return [t for t in topics if t.msgtype in PACKET_TYPES]
