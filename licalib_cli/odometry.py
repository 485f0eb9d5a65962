"""LiDAR odometry with kiss-icp: scans in, one pose per scan out.

Conventions:
    - ``T_map_lidar[k]`` maps points of scan ``k`` (LiDAR frame at time ``t_ns[k]``) into the map
      frame ``{M}`` = the LiDAR frame of the first scan, so ``T_map_lidar[0]`` is the identity.
    - kiss-icp (>= 1.2.2) deskews every scan to its latest point time, so a pose refers to the
      absolute time of the latest point of its scan; licalib stamps it with that time itself.
      Without deskewing (``deskew=False`` or a scan whose points all share one time) the cloud is
      registered as a rigid snapshot and the pose is stamped with the mean point time instead.
    - Per-point times are handed to kiss-icp as float seconds relative to the first point of the
      scan. A scan whose points all share one time is passed with an empty time array, because a
      zero time span makes kiss-icp divide 0/0 and abort the process.
    - The kiss-icp configuration is built field by field, so ``kiss_icp_*`` environment variables
      cannot change it.
    - Optional rotation pre-deskew: given the LiDAR orientation ``R_w_lidar(t)`` in any fixed frame
      (for example from the gyro and the rotation extrinsic), every point is rotated into the LiDAR
      frame at the latest point time before registration, and kiss-icp's own constant-velocity
      deskew is switched off for that run. Translation during the sweep is compensated with the
      constant velocity of the two previous poses (none for the first two scans).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation

from licalib_cli.errors import ConfigError, DataError
from licalib_cli.measurements import LidarScan

if TYPE_CHECKING:
    from kiss_icp.config import KISSConfig

__all__ = [
    "OdometryConfig",
    "PoseSeries",
    "ProgressFn",
    "RotationAt",
    "kiss_icp_config",
    "run_odometry",
]

logger = logging.getLogger(__name__)

RotationAt = Callable[[npt.NDArray[np.int64]], Rotation]
"""Orientation of the LiDAR frame in a fixed frame, ``R_w_lidar(t)``, at absolute times (ns)."""

ProgressFn = Callable[[int, int], None]
"""Called as ``progress(done, total)`` after each scan."""


@dataclass(frozen=True)
class OdometryConfig:
    """Settings of the kiss-icp odometry.

    Attributes:
        voxel_size: map voxel size, metres; None gives ``max_range / 100`` (kiss-icp's rule).
        max_range: points farther than this from the sensor are dropped, metres.
        min_range: points closer than this are dropped, metres.
        deskew: motion-compensate each scan with kiss-icp's constant-velocity model.
        max_points_per_voxel: kiss-icp local-map density.
        max_threads: threads kiss-icp may use; 0 lets it decide.
    """

    voxel_size: float | None = None
    max_range: float = 100.0
    min_range: float = 0.5
    deskew: bool = True
    max_points_per_voxel: int = 20
    max_threads: int = 0


@dataclass(frozen=True)
class PoseSeries:
    """LiDAR poses from odometry.

    Attributes:
        t_ns: (K,) int64 absolute time each pose refers to, nanoseconds (see module docstring).
        T_map_lidar: (K, 4, 4) float64 pose of the LiDAR in the map frame; the first is identity.
        n_points: (K,) int64 points of each scan left after the range filter.
        n_keypoints: (K,) int64 downsampled points used for registration.
        threshold_m: (K,) float64 kiss-icp adaptive correspondence threshold used, metres.
        deviation_m: (K,) float64 translation between the constant-velocity prediction and the
            registered pose, metres (large jumps flag registration failures).
        deviation_deg: (K,) float64 rotation between prediction and registered pose, degrees.
    """

    t_ns: npt.NDArray[np.int64]
    T_map_lidar: npt.NDArray[np.float64]
    n_points: npt.NDArray[np.int64]
    n_keypoints: npt.NDArray[np.int64]
    threshold_m: npt.NDArray[np.float64]
    deviation_m: npt.NDArray[np.float64]
    deviation_deg: npt.NDArray[np.float64]

    def __len__(self) -> int:
        return int(self.t_ns.shape[0])

    @property
    def rotations(self) -> Rotation:
        """``R_map_lidar`` of every pose as one scipy Rotation of length K."""
        return Rotation.from_matrix(self.T_map_lidar[:, :3, :3])

    @property
    def positions(self) -> npt.NDArray[np.float64]:
        """(K, 3) LiDAR origin in the map frame, metres."""
        return self.T_map_lidar[:, :3, 3]


def kiss_icp_config(cfg: OdometryConfig) -> KISSConfig:
    """Build a kiss-icp ``KISSConfig`` from ``cfg`` without reading environment variables.

    Every field is given explicitly and the pydantic-settings sources are bypassed
    (``model_construct``), so ``kiss_icp_*`` variables in the environment have no effect.

    Returns:
        The ``kiss_icp.config.KISSConfig`` instance.

    Raises:
        ConfigError: ``min_range``/``max_range`` are inconsistent.
    """
    from kiss_icp.config import KISSConfig
    from kiss_icp.config.config import (
        AdaptiveThresholdConfig,
        DataConfig,
        MappingConfig,
        RegistrationConfig,
    )

    max_range = float(cfg.max_range)
    min_range = float(cfg.min_range)
    if not 0.0 <= min_range < max_range:
        msg = (
            f"Odometry range limits are inconsistent (min_range {min_range} m, max_range "
            f"{max_range} m); set 0 <= min_range < max_range."
        )
        raise ConfigError(msg)
    voxel = float(cfg.voxel_size) if cfg.voxel_size is not None else max_range / 100.0
    return KISSConfig.model_construct(
        out_dir="results",
        data=DataConfig(max_range=max_range, min_range=min_range, deskew=bool(cfg.deskew)),
        registration=RegistrationConfig(
            max_num_iterations=500, convergence_criterion=1e-4, max_num_threads=cfg.max_threads
        ),
        mapping=MappingConfig(voxel_size=voxel, max_points_per_voxel=cfg.max_points_per_voxel),
        adaptive_threshold=AdaptiveThresholdConfig(
            fixed_threshold=None, initial_threshold=2.0, min_motion_th=0.1
        ),
    )


def _rotation_deskew(
    scan: LidarScan,
    rotation_at: RotationAt,
    velocity_lidar: npt.NDArray[np.float64],
) -> npt.NDArray[np.float64]:
    """Move every point of ``scan`` into the LiDAR frame at the scan's latest point time.

    ``p_end = R_w_lidar(t_end)^T R_w_lidar(t) p + v (t - t_end)``, with the rotation from
    ``rotation_at`` and ``v`` (3,) the LiDAR velocity expressed in the end frame, m/s.

    Returns:
        (N, 3) float64 points.
    """
    t_end = scan.t_ns.max()
    r_pts = rotation_at(scan.t_ns)
    r_end = rotation_at(np.array([t_end], dtype=np.int64))
    dt = (scan.t_ns - t_end).astype(np.float64) * 1e-9
    moved = (r_end.inv() * r_pts).apply(scan.xyz) + dt[:, None] * velocity_lidar[None, :]
    return np.asarray(moved, dtype=np.float64)


def run_odometry(
    scans: Sequence[LidarScan],
    cfg: OdometryConfig,
    progress: ProgressFn | None = None,
    *,
    rotation_at: RotationAt | None = None,
) -> PoseSeries:
    """Register the scans one after the other with kiss-icp.

    Args:
        scans: K scans in time order, points in the LiDAR frame with absolute per-point times.
        cfg: odometry settings.
        progress: optional ``progress(done, total)`` callback, called after each scan.
        rotation_at: optional ``R_w_lidar(t)`` used to rotation-deskew each scan before
            registration (kiss-icp's own deskew is then off); see the module docstring.

    Returns:
        One pose per scan, stamped with the time it refers to.

    Raises:
        DataError: no scans, a scan without points, or scans out of time order.
        ConfigError: inconsistent range limits.
    """
    if len(scans) == 0:
        msg = "No LiDAR scans to run odometry on; check the LiDAR topic and the time window."
        raise DataError(msg)
    from kiss_icp.kiss_icp import KissICP

    kcfg = kiss_icp_config(cfg)
    odom = KissICP(config=kcfg)
    k = len(scans)
    t_out = np.empty(k, dtype=np.int64)
    poses = np.empty((k, 4, 4), dtype=np.float64)
    n_points = np.zeros(k, dtype=np.int64)
    n_keys = np.zeros(k, dtype=np.int64)
    thresholds = np.zeros(k, dtype=np.float64)
    dev_m = np.zeros(k, dtype=np.float64)
    dev_deg = np.zeros(k, dtype=np.float64)
    empty = np.zeros(0, dtype=np.float64)
    for i, scan in enumerate(scans):
        if len(scan) == 0:
            msg = (
                f"LiDAR scan {i} (stamp {scan.stamp_ns} ns) has no points; "
                "drop empty scans before odometry."
            )
            raise DataError(msg)
        rng = np.linalg.norm(scan.xyz, axis=1)
        if not np.any((rng >= kcfg.data.min_range) & (rng <= kcfg.data.max_range)):
            msg = (
                f"LiDAR scan {i} (stamp {scan.stamp_ns} ns) has no point between "
                f"{kcfg.data.min_range:g} m and {kcfg.data.max_range:g} m; check the range "
                "limits of the odometry and the point units."
            )
            raise DataError(msg)
        t_min = int(scan.t_ns.min())
        t_max = int(scan.t_ns.max())
        span = t_max - t_min
        if rotation_at is not None and span > 0:
            # Translation during the sweep from the constant velocity of the last two poses,
            # expressed in the predicted end frame.
            velocity = np.zeros(3)
            if i >= 2:
                dt_prev = float(t_out[i - 1] - t_out[i - 2]) * 1e-9
                v_map = (poses[i - 1, :3, 3] - poses[i - 2, :3, 3]) / dt_prev
                r_pred = (odom.last_pose @ odom.last_delta)[:3, :3]
                velocity = r_pred.T @ v_map
            xyz = _rotation_deskew(scan, rotation_at, velocity)
            times = empty
            t_ref = t_max
        elif cfg.deskew and span > 0:
            xyz = np.ascontiguousarray(scan.xyz, dtype=np.float64)
            times = (scan.t_ns - t_min).astype(np.float64) * 1e-9
            t_ref = t_max
        else:
            xyz = np.ascontiguousarray(scan.xyz, dtype=np.float64)
            times = empty
            t_ref = t_min + int(np.mean(scan.t_ns - t_min))
        if i > 0 and t_ref <= t_out[i - 1]:
            msg = (
                f"LiDAR scan {i} refers to time {t_ref} ns, not after scan {i - 1} "
                f"({t_out[i - 1]} ns); sort the scans by time and drop duplicates."
            )
            raise DataError(msg)
        sigma = float(odom.adaptive_threshold.get_threshold())
        prediction = odom.last_pose @ odom.last_delta
        frame, source = odom.register_frame(xyz, times)
        deviation = np.linalg.inv(prediction) @ odom.last_pose
        t_out[i] = t_ref
        poses[i] = odom.last_pose
        n_points[i] = frame.shape[0]
        n_keys[i] = source.shape[0]
        thresholds[i] = sigma
        dev_m[i] = float(np.linalg.norm(deviation[:3, 3]))
        dev_deg[i] = float(np.degrees(Rotation.from_matrix(deviation[:3, :3]).magnitude()))
        if progress is not None:
            progress(i + 1, k)
    # kiss-icp starts at identity already; re-anchor anyway so the contract holds exactly.
    poses = np.linalg.inv(poses[0]) @ poses
    logger.info(
        "odometry: %d scans, %.1f m path, max prediction deviation %.3f m / %.2f deg",
        k,
        float(np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1).sum()),
        float(dev_m.max()),
        float(dev_deg.max()),
    )
    return PoseSeries(
        t_ns=t_out,
        T_map_lidar=poses,
        n_points=n_points,
        n_keypoints=n_keys,
        threshold_m=thresholds,
        deviation_m=dev_m,
        deviation_deg=dev_deg,
    )
