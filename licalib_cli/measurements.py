"""Measurement containers: what the bag layer hands to the rest of the pipeline.

All times are int64 nanoseconds. IMU data is in SI units (rad/s, m/s^2) in the IMU frame;
LiDAR points are metres in the LiDAR frame, one absolute time per point.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

if TYPE_CHECKING:
    from licalib_cli.io.clock_rate import ClockRate
    from licalib_cli.io.cloud_layout import CloudLayout
    from licalib_cli.io.imu_units import ImuUnits
    from licalib_cli.io.ouster import FactoryExtrinsic

_NS = 1_000_000_000


@dataclass(frozen=True)
class ImuSamples:
    """A run of IMU samples.

    Attributes:
        t_ns: (N,) int64 header stamps, nanoseconds.
        gyro: (N, 3) float64 angular rate, rad/s, IMU (gyro) frame.
        accel: (N, 3) float64 specific force, m/s^2, IMU frame.
    """

    t_ns: npt.NDArray[np.int64]
    gyro: npt.NDArray[np.float64]
    accel: npt.NDArray[np.float64]

    def __post_init__(self) -> None:
        n = self.t_ns.shape[0]
        if self.t_ns.ndim != 1 or self.gyro.shape != (n, 3) or self.accel.shape != (n, 3):
            msg = (
                f"ImuSamples shapes disagree: t_ns {self.t_ns.shape}, gyro {self.gyro.shape}, "
                f"accel {self.accel.shape}"
            )
            raise ValueError(msg)

    def __len__(self) -> int:
        return int(self.t_ns.shape[0])

    def slice_time(self, start_ns: int, end_ns: int) -> ImuSamples:
        """Samples with ``start_ns <= t_ns < end_ns``."""
        i0, i1 = np.searchsorted(self.t_ns, [start_ns, end_ns])
        return ImuSamples(self.t_ns[i0:i1], self.gyro[i0:i1], self.accel[i0:i1])


@dataclass(frozen=True)
class LidarScan:
    """One LiDAR sweep, finite points only.

    Attributes:
        stamp_ns: header stamp of the message, nanoseconds.
        xyz: (N, 3) float64 points in the LiDAR frame, metres.
        t_ns: (N,) int64 absolute time of each point, nanoseconds.
        ring: (N,) int16 beam index per point as the driver numbers it (``ring``/``line``),
            or recovered from elevation; None when unknown.
        intensity: (N,) float32 or None.
    """

    stamp_ns: int
    xyz: npt.NDArray[np.float64]
    t_ns: npt.NDArray[np.int64]
    ring: npt.NDArray[np.int16] | None = None
    intensity: npt.NDArray[np.float32] | None = field(default=None, repr=False)

    def __len__(self) -> int:
        return int(self.xyz.shape[0])


@dataclass(frozen=True)
class Recording:
    """One segment of a bag, validated and converted (what the reader hands on).

    Attributes:
        imu: IMU samples (rad/s, m/s^2), IMU clock.
        scans: LiDAR scans of the segment in stamp order; their times are in the IMU clock
            when ``lidar_shift_ns != 0``.
        imu_topic: IMU topic read.
        lidar_topic: LiDAR topic read.
        layout: detected point layout.
        imu_units: units of the raw IMU messages.
        clock_offset_ns: coarse ``t_imu - t_lidar`` clock difference, ns.
        lidar_shift_ns: shift applied to every LiDAR time (``clock_offset_ns`` when it is
            1 s or more, else 0), ns.
        start_ns: segment start in the IMU clock, ns.
        end_ns: segment end in the IMU clock, ns (exclusive).
        warnings: non-fatal findings, one sentence each.
        imu_unreadable: IMU messages of the segment that could not be read (undecodable, a
            stamp far from their record time, or lost in a damaged chunk).
        lidar_unreadable: the same for the LiDAR messages.
        imu_samples_dropped: IMU samples dropped for NaN or infinite values.
        scans_skipped: clouds of the segment skipped as unusable (empty, corrupt, ...).
        factory_extrinsic: the sensor's factory extrinsic when the bag carries one (Ouster
            metadata), for the frame the clouds are in; None otherwise.
        clock_rate: how fast the IMU's stamps run against the LiDAR's, from each topic's
            stamps against the record times (:mod:`licalib_cli.io.clock_rate`); None when a
            topic has too few messages or no record times.
    """

    imu: ImuSamples
    scans: tuple[LidarScan, ...]
    imu_topic: str
    lidar_topic: str
    layout: CloudLayout
    imu_units: ImuUnits
    clock_offset_ns: int
    lidar_shift_ns: int
    start_ns: int
    end_ns: int
    warnings: tuple[str, ...] = ()
    imu_unreadable: int = 0
    lidar_unreadable: int = 0
    imu_samples_dropped: int = 0
    scans_skipped: int = 0
    factory_extrinsic: FactoryExtrinsic | None = None
    clock_rate: ClockRate | None = None

    @property
    def clock_offset_s(self) -> float:
        """Coarse clock difference ``t_imu - t_lidar``, seconds."""
        return self.clock_offset_ns / _NS
