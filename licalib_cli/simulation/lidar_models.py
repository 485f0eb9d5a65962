"""Firing patterns and PointCloud2 layouts of the simulated LiDARs.

All sensors spin clockwise seen from above, so the azimuth ``theta = atan2(y, x)`` of the rays
decreases with time: ``theta(t) = theta_start - 2 pi (t - t_sweep) / T_sweep``.

VLP-16 (Velodyne VLP-16 manual): lasers 0..15 fire one after another every 2.304 us at
elevations -15, 1, -13, 3, ..., -1, 15 deg (interleaved); a firing cycle of 16 firings and the
recharge lasts 55.296 us, so a 10 Hz sweep has 1808 cycles (azimuth step 0.199 deg). Each
firing gets the azimuth of its own time (as the ROS driver interpolates it). ``ring`` numbers
the beams by elevation (ring 0 = -15 deg). Points as the ROS ``velodyne_pointcloud`` driver's
``PointXYZIRT`` cloud: ``x, y, z, intensity`` float32 at 0, 4, 8, 12, ``ring`` uint16 at 16,
``time`` float32 at 18 (seconds relative to the header stamp), packed,
point_step 22,
unorganised, no-returns dropped, in firing order.

HDL-32E (Velodyne HDL-32E manual): lasers 0..31 fire one after another every 1.152 us at
elevations -30.67, -9.33, -29.33, -8.00, ..., -10.67, 10.67 deg (interleaved, 1.33 deg apart); a
firing cycle lasts 46.08 us (2170 cycles per 10 Hz sweep). Same ``ring`` numbering and cloud
layout as the VLP-16.

OS1-64-like (ouster-ros default ``ouster_ros::Point``): 64 beams evenly from +16.6 deg (ring 0)
to -16.6 deg; OS1-32 and OS1-128 alike with 32 and 128 beams evenly over +-22.5 deg (the
uniform beam spacing of the OS1's later revisions); 1024 columns per sweep; all beams of a
column fire at the column's time (rounded to ns); the first column looks backwards (theta = pi);
thinning keeps 1024 / 2^k columns. Organised B x 1024, ``x, y, z`` float32 at 0, 4, 8,
``intensity`` float32 at 16, ``t`` uint32 ns relative to the sweep start at 20, ``reflectivity``
uint16 at 24, ``ring`` uint16 at 26, ``ambient`` uint16 at 28, ``range`` uint32 (mm) at 32,
point_step 48 (EIGEN_ALIGN16); no-returns are zero points with range 0.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from licalib_cli.simulation.spec import LidarKind

F64 = npt.NDArray[np.float64]

VLP16_DTYPE = np.dtype(
    {
        "names": ["x", "y", "z", "intensity", "ring", "time"],
        "formats": ["<f4", "<f4", "<f4", "<f4", "<u2", "<f4"],
        "offsets": [0, 4, 8, 12, 16, 18],
        "itemsize": 22,
    }
)

OUSTER_DTYPE = np.dtype(
    {
        "names": ["x", "y", "z", "intensity", "t", "reflectivity", "ring", "ambient", "range"],
        "formats": ["<f4", "<f4", "<f4", "<f4", "<u4", "<u2", "<u2", "<u2", "<u4"],
        "offsets": [0, 4, 8, 16, 20, 24, 26, 28, 32],
        "itemsize": 48,
    }
)

VLP16_FIRING_NS = 2304
VLP16_CYCLE_NS = 55296
VLP16_LASER_ELEVATION_DEG = np.array(
    [-15, 1, -13, 3, -11, 5, -9, 7, -7, 9, -5, 11, -3, 13, -1, 15], dtype=np.float64
)

HDL32_FIRING_NS = 1152
HDL32_CYCLE_NS = 46080
HDL32_LASER_ELEVATION_DEG = np.array(
    [
        -30.67, -9.33, -29.33, -8.00, -28.00, -6.67, -26.67, -5.33,
        -25.33, -4.00, -24.00, -2.67, -22.67, -1.33, -21.33, 0.00,
        -20.00, 1.33, -18.67, 2.67, -17.33, 4.00, -16.00, 5.33,
        -14.67, 6.67, -13.33, 8.00, -12.00, 9.33, -10.67, 10.67,
    ],
    dtype=np.float64,
)  # fmt: skip
"""Elevation of laser 0, 1, 2, ... (the manual's firing order), deg."""


@dataclass(frozen=True)
class FiringPattern:
    """Rays of one sweep, shape (C, B): C firing cycles/columns, B beams (indexed by ring).

    Attributes:
        t_ns: (C, B) int64 firing time relative to the sweep start, ns.
        theta: (C, B) encoder azimuth at firing, rad, in (-pi, pi].
        ring: (C, B) beam index (``ring`` field), int.
        period_ns: sweep period, ns.
    """

    t_ns: npt.NDArray[np.int64]
    theta: F64
    ring: npt.NDArray[np.int64]
    period_ns: int


@dataclass(frozen=True)
class LidarModel:
    """A spinning multi-beam LiDAR.

    Attributes:
        kind: which sensor.
        nominal_elevation: (B,) elevation of each ring, rad (driver's factory table).
        firing_order: (B,) position of each ring within a firing cycle (0 = first).
        firing_step_ns: time between consecutive firings within a cycle, ns.
        organized: publish an organised (B, C) cloud with zero points for no-returns.
        min_range: closest return, m.
        max_range: farthest return, m.
        theta_start: azimuth of the first ray of a sweep, rad.
        native_columns: columns per sweep for column-based sensors (0 for cycle-based).
        cycle_ns: duration of a firing cycle for cycle-based sensors, ns (0 for column-based).
    """

    kind: LidarKind
    nominal_elevation: F64
    firing_order: npt.NDArray[np.int64]
    firing_step_ns: int
    organized: bool
    min_range: float
    max_range: float
    theta_start: float
    native_columns: int = 0
    cycle_ns: int = 0

    @property
    def num_beams(self) -> int:
        return int(self.nominal_elevation.shape[0])

    @property
    def dtype(self) -> np.dtype:
        return OUSTER_DTYPE if self.organized else VLP16_DTYPE

    def native_azimuth_step_deg(self, rate_hz: float) -> float:
        """Azimuth between consecutive cycles/columns at ``rate_hz``, deg."""
        if self.native_columns:
            return 360.0 / self.native_columns
        return 360.0 * self.cycle_ns * 1e-9 * rate_hz

    def pattern(self, rate_hz: float, azimuth_resolution_deg: float | None = None) -> FiringPattern:
        """Firing times and azimuths of one sweep, optionally thinned in azimuth."""
        period_ns = round(1e9 / rate_hz)
        step = 1
        if azimuth_resolution_deg is not None:
            ratio = azimuth_resolution_deg / self.native_azimuth_step_deg(rate_hz)
            step = max(1, round(ratio))
            if self.native_columns:  # keep a power-of-two column count (like 512/1024/2048 modes)
                step = int(2 ** np.clip(np.round(np.log2(max(ratio, 1.0))), 0, 6))
        if self.native_columns:
            cols = np.arange(0, self.native_columns, step)
            col_t = np.round(cols * (period_ns / self.native_columns)).astype(np.int64)
        else:
            n_cycles = period_ns // self.cycle_ns
            cols = np.arange(0, n_cycles, step)
            col_t = cols.astype(np.int64) * self.cycle_ns
        t_ns = col_t[:, None] + self.firing_order[None, :].astype(np.int64) * self.firing_step_ns
        theta = self.theta_start - 2 * np.pi * t_ns.astype(np.float64) / period_ns
        theta = np.mod(theta + np.pi, 2 * np.pi) - np.pi
        theta = np.where(theta == -np.pi, np.pi, theta)
        ring = np.broadcast_to(np.arange(self.num_beams), t_ns.shape).copy()
        return FiringPattern(t_ns, theta, ring, period_ns)


def _velodyne(
    kind: LidarKind, laser_elevation_deg: F64, firing_ns: int, cycle_ns: int, min_range: float
) -> LidarModel:
    laser_of_ring = np.argsort(laser_elevation_deg)  # ring 0 = the lowest beam
    return LidarModel(
        kind=kind,
        nominal_elevation=np.radians(laser_elevation_deg[laser_of_ring]),
        firing_order=laser_of_ring.astype(np.int64),
        firing_step_ns=firing_ns,
        organized=False,
        min_range=min_range,
        max_range=100.0,
        theta_start=0.0,
        cycle_ns=cycle_ns,
    )


def _ouster(kind: LidarKind, beams: int, half_fov_deg: float) -> LidarModel:
    return LidarModel(
        kind=kind,
        nominal_elevation=np.radians(np.linspace(half_fov_deg, -half_fov_deg, beams)),
        firing_order=np.zeros(beams, dtype=np.int64),
        firing_step_ns=0,
        organized=True,
        min_range=0.5,
        max_range=120.0,
        theta_start=np.pi,
        native_columns=1024,
    )


def lidar_model(kind: LidarKind | str) -> LidarModel:
    """The model of a LiDAR kind."""
    kind = LidarKind(kind)
    if kind is LidarKind.VLP16:
        return _velodyne(kind, VLP16_LASER_ELEVATION_DEG, VLP16_FIRING_NS, VLP16_CYCLE_NS, 0.4)
    if kind is LidarKind.HDL32:
        return _velodyne(kind, HDL32_LASER_ELEVATION_DEG, HDL32_FIRING_NS, HDL32_CYCLE_NS, 1.0)
    if kind is LidarKind.OS1_64:
        return _ouster(kind, 64, 16.6)
    beams = {LidarKind.OS1_32: 32, LidarKind.OS1_128: 128}[kind]
    return _ouster(kind, beams, 22.5)
