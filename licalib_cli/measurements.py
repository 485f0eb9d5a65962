"""Measurement containers: what the bag layer hands to the rest of the pipeline.

All times are int64 nanoseconds. IMU data is in SI units (rad/s, m/s^2) in the IMU frame;
LiDAR points are metres in the LiDAR frame, one absolute time per point.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt


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
