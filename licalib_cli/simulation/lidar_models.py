"""Firing patterns and PointCloud2 layouts of the simulated LiDARs.

All sensors but the Avia spin clockwise seen from above, so the azimuth ``theta = atan2(y, x)``
of the rays decreases with time: ``theta(t) = theta_start - 2 pi (t - t_sweep) / T_sweep``.

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

Mid-360-like (Livox Mid-360 datasheet: 4 lasers, 200 000 points/s, 360 x 59 deg field of view
from -7 to +52 deg, 0.1-70 m; Livox does not publish the exact pattern, so this is a simplified
one with the same figures): lasers ``line`` 0..3 fire one after another every 5 us (a 20 us
cycle, 50 000 points/s each, 20 000 points a 10 Hz sweep). Each line traces a continuous curve:
its azimuth turns one full turn per sweep (clockwise as above, line ``l`` offset by ``l``
quarter turns: ``theta = -2 pi (t - t_sweep) / T_sweep - l pi / 2``) while its elevation swings
over the field of view, ``phi = 22.5 deg + 29.5 deg sin(2 pi f t + l pi / 2)`` with
``f = 10 (18 + (sqrt(5) - 1) / 2) = 186.18 Hz`` and ``t`` the time since the start of the run.
Consecutive points of a line are 0.7 deg apart at most (0.8 deg at 50 Hz); ``f`` over the sweep
rate is no integer, so each sweep starts at another phase and covers other directions than the
sweeps before it (the golden fraction 0.618 of an oscillation per 10 Hz sweep keeps every phase
far from all the earlier ones): the pattern does not repeat. Points as
``Livox-SDK/livox_ros_driver2`` publishes them with ``xfer_format`` 0 (``lddc.cpp``
``InitPointcloud2MsgHeader``, ``#pragma pack(1) LivoxPointXyzrtlt``): ``x, y, z, intensity``
float32 at 0, 4, 8, 12, ``tag`` uint8 at 16, ``line`` uint8 at 17, ``timestamp`` float64 at 18
(absolute time of the point, ns, on the header stamp's clock), packed, point_step 26,
unorganised, no-returns dropped, in time order; header stamp = the sweep's first point.

Avia-like (Livox Avia datasheet: 6 lasers, 240 000 points/s, a forward-looking 70.4 x 77.2 deg
field of view, 1-190 m, range precision 2 cm; Livox does not publish the exact pattern, so this
is a rosette with the datasheet's figures): lasers ``line`` 0..5 fire one after another every
25/6 us (4167 ns, rounded; a 25 us cycle, 40 000 points/s each, 24 000 points a 10 Hz sweep).
The head does not spin: each line traces a rose curve in the (azimuth, elevation) plane around
the LiDAR's +x axis, ``theta = 35.2 deg r cos(psi)``, ``phi = 38.6 deg r sin(psi)`` (so within
+-35.2 deg of azimuth and +-38.6 deg of elevation), with the radius ``r = cos(3 2 pi f1 t)``
(3 petal pairs per ``1 / f1``) and the angle ``psi = 2 pi f2 t + l pi / 6`` of line ``l``,
``f1 = 10 (14 + (sqrt(5) - 1) / 2) / 3 = 48.73 Hz`` (the radius swings ``3 f1 = 146.18`` times
a second), ``f2 = 10 ((sqrt(5) - 1) / 2) / 6 = 1.03 Hz`` (about a turn a second) and ``t`` the
time since the start of the run. Each line runs through the centre and turns back at the edge
of the field of view, so its azimuth is not monotonic; consecutive points of a line are 0.9 deg
apart at most (at any rate: 25 us apart). The radius takes both signs, so the six lines trace
six chords through the centre, 30 deg apart (``l pi / 3`` would put lines ``l`` and ``l + 3`` on
the same chords); the petals turn with ``psi``, 37 deg a 10 Hz sweep, so each sweep covers the
whole field of view. Per 10 Hz sweep the radius advances the golden fraction 0.618 of a swing
and ``psi`` 37.08 deg, 1.236 chord spacings (0.236 = 0.618^3, a golden fraction too), so
neither repeats sweep to sweep. Points as the Mid-360's (``livox_ros_driver2``, which drives
Livox's HAP, a rosette scanner too; the Avia's own ``livox_ros_driver`` publishes no per-point
time in its PointCloud2), ``line`` 0..5. ``azimuth_resolution_deg`` thins both Livox scanners
alike: every k-th cycle, ``k`` the resolution over ``360 deg x cycle / T_sweep``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

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

LIVOX_DTYPE = np.dtype(
    {
        "names": ["x", "y", "z", "intensity", "tag", "line", "timestamp"],
        "formats": ["<f4", "<f4", "<f4", "<f4", "u1", "u1", "<f8"],
        "offsets": [0, 4, 8, 12, 16, 17, 18],
        "itemsize": 26,
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

MID360_LINES = 4
MID360_FIRING_NS = 5000
MID360_CYCLE_NS = MID360_LINES * MID360_FIRING_NS
MID360_ELEVATION_MIN_DEG = -7.0
MID360_ELEVATION_MAX_DEG = 52.0
MID360_ELEVATION_HZ = 10.0 * (18.0 + (np.sqrt(5.0) - 1.0) / 2.0)
"""Elevation oscillations per second of each line (186.18 Hz, see the module docstring)."""

AVIA_LINES = 6
AVIA_CYCLE_NS = 25_000
AVIA_FIRING_NS = round(AVIA_CYCLE_NS / AVIA_LINES)
AVIA_AZIMUTH_HALF_FOV_DEG = 35.2
AVIA_ELEVATION_HALF_FOV_DEG = 38.6
AVIA_PETAL_PAIRS = 3
AVIA_ROSE_HZ = 10.0 * (14.0 + (np.sqrt(5.0) - 1.0) / 2.0) / AVIA_PETAL_PAIRS
"""``f1`` of the rose's radius ``cos(3 2 pi f1 t)`` (48.73 Hz, see the module docstring)."""
AVIA_TURN_HZ = 10.0 * ((np.sqrt(5.0) - 1.0) / 2.0) / 6.0
"""``f2``: turns per second of the rose's angle (1.03 Hz, see the module docstring)."""


@dataclass(frozen=True)
class FiringPattern:
    """Rays of one sweep, shape (C, B): C firing cycles/columns, B beams (indexed by ring).

    Attributes:
        t_ns: (C, B) int64 firing time relative to the sweep start, ns.
        theta: (C, B) encoder azimuth at firing, rad, in (-pi, pi].
        ring: (C, B) beam index (``ring`` field, ``line`` of a Livox), int.
        period_ns: sweep period, ns.
        elevation: (C, B) nominal elevation of each ray, rad, for a scanner without fixed
            beams; None: every ray of ring ``i`` has the model's ``nominal_elevation[i]``.
    """

    t_ns: npt.NDArray[np.int64]
    theta: F64
    ring: npt.NDArray[np.int64]
    period_ns: int
    elevation: F64 | None = None


class ScanCurve(Protocol):
    """The curve each line of a non-repetitive scanner traces."""

    def rays(self, spin: F64, t_run: F64) -> tuple[F64, F64]:
        """Azimuth and elevation (rad) of the rays of a sweep, (C, B) like its firing times.

        Args:
            spin: (C, B) the azimuth of a head turning once per sweep, ``theta_start - 2 pi
                (t - t_sweep) / T_sweep``, rad (a scanner that does not spin ignores it).
            t_run: (C, B) firing time since the start of the run (not of the sweep), s.
        """
        ...


@dataclass(frozen=True)
class ElevationSweep:
    """A spinning head whose lines swing in elevation (Mid-360):
    ``phi = centre + amplitude sin(2 pi frequency_hz t + line_phase[l])``, ``t`` the time since
    the start of the run (not of the sweep), and the azimuth ``spin - line_azimuth[l]``.

    Attributes:
        centre: middle of the vertical field of view, rad.
        amplitude: half the vertical field of view, rad.
        frequency_hz: oscillations per second.
        line_phase: (B,) phase of each line, rad.
        line_azimuth: (B,) azimuth of each line behind line 0's, rad.
    """

    centre: float
    amplitude: float
    frequency_hz: float
    line_phase: F64
    line_azimuth: F64

    def rays(self, spin: F64, t_run: F64) -> tuple[F64, F64]:
        theta = spin - self.line_azimuth[None, :]
        phase = 2 * np.pi * self.frequency_hz * t_run + self.line_phase[None, :]
        return theta, self.centre + self.amplitude * np.sin(phase)


@dataclass(frozen=True)
class Rosette:
    """A head that does not spin, each line tracing a rose curve around the +x axis (Avia):
    ``theta = azimuth_amplitude r cos(psi)``, ``phi = elevation_amplitude r sin(psi)``,
    ``r = cos(petal_pairs 2 pi frequency_hz t)``, ``psi = 2 pi turn_hz t + line_angle[l]``,
    ``t`` the time since the start of the run (not of the sweep).

    Attributes:
        azimuth_amplitude: half the horizontal field of view, rad.
        elevation_amplitude: half the vertical field of view, rad.
        petal_pairs: swings of the radius (out and back on both sides) per ``1 / frequency_hz``.
        frequency_hz: ``f1`` of the radius.
        turn_hz: turns per second of the angle ``psi``.
        line_angle: (B,) angle ``psi`` of each line at ``t = 0``, rad.
    """

    azimuth_amplitude: float
    elevation_amplitude: float
    petal_pairs: int
    frequency_hz: float
    turn_hz: float
    line_angle: F64

    def rays(self, spin: F64, t_run: F64) -> tuple[F64, F64]:
        radius = np.cos(self.petal_pairs * 2 * np.pi * self.frequency_hz * t_run)
        psi = 2 * np.pi * self.turn_hz * t_run + self.line_angle[None, :]
        return (
            self.azimuth_amplitude * radius * np.cos(psi),
            self.elevation_amplitude * radius * np.sin(psi),
        )


@dataclass(frozen=True)
class LidarModel:
    """A spinning multi-beam LiDAR, or a non-repetitive scanner (``scan_curve``).

    Attributes:
        kind: which sensor.
        nominal_elevation: (B,) elevation of each ring, rad (driver's factory table); of a
            non-repetitive scanner, the middle of its field of view for every line.
        firing_order: (B,) position of each ring within a firing cycle (0 = first).
        firing_step_ns: time between consecutive firings within a cycle, ns.
        organized: publish an organised (B, C) cloud with zero points for no-returns.
        min_range: closest return, m.
        max_range: farthest return, m.
        theta_start: azimuth of the first ray of a sweep, rad.
        native_columns: columns per sweep for column-based sensors (0 for cycle-based).
        cycle_ns: duration of a firing cycle for cycle-based sensors, ns (0 for column-based).
        scan_curve: the azimuth and elevation of each ray of a non-repetitive scanner; None
            for a spinning LiDAR (each ring at its nominal elevation).
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
    scan_curve: ScanCurve | None = None

    @property
    def num_beams(self) -> int:
        return int(self.nominal_elevation.shape[0])

    @property
    def repeats(self) -> bool:
        """Every sweep fires the same rays (a spinning LiDAR): one pattern serves them all."""
        return self.scan_curve is None

    @property
    def dtype(self) -> np.dtype:
        if self.scan_curve is not None:
            return LIVOX_DTYPE
        return OUSTER_DTYPE if self.organized else VLP16_DTYPE

    def native_azimuth_step_deg(self, rate_hz: float) -> float:
        """Azimuth between consecutive cycles/columns at ``rate_hz``, deg."""
        if self.native_columns:
            return 360.0 / self.native_columns
        return 360.0 * self.cycle_ns * 1e-9 * rate_hz

    def pattern(
        self, rate_hz: float, azimuth_resolution_deg: float | None = None, sweep: int = 0
    ) -> FiringPattern:
        """Firing times and azimuths of one sweep, optionally thinned in azimuth.

        ``sweep`` (the sweep number k, starting at ``k / rate_hz`` s into the run) matters only
        to a non-repetitive scanner, whose pattern also gives each ray its elevation; a spinning
        LiDAR fires the same rays in every sweep.
        """
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
        elevation = None
        if self.scan_curve is not None:
            t_run = (int(sweep) * period_ns + t_ns).astype(np.float64) * 1e-9
            theta, elevation = self.scan_curve.rays(theta, t_run)
        theta = np.mod(theta + np.pi, 2 * np.pi) - np.pi
        theta = np.where(theta == -np.pi, np.pi, theta)
        ring = np.broadcast_to(np.arange(self.num_beams), t_ns.shape).copy()
        return FiringPattern(t_ns, theta, ring, period_ns, elevation)


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


def _mid360(kind: LidarKind) -> LidarModel:
    lo, hi = np.radians(MID360_ELEVATION_MIN_DEG), np.radians(MID360_ELEVATION_MAX_DEG)
    quarter_turns = np.arange(MID360_LINES, dtype=np.float64) * (np.pi / 2)
    return LidarModel(
        kind=kind,
        nominal_elevation=np.full(MID360_LINES, (lo + hi) / 2),
        firing_order=np.arange(MID360_LINES, dtype=np.int64),
        firing_step_ns=MID360_FIRING_NS,
        organized=False,
        min_range=0.1,
        max_range=70.0,  # datasheet: 40 m at 10 % reflectivity, 70 m at 80 %
        theta_start=0.0,
        cycle_ns=MID360_CYCLE_NS,
        scan_curve=ElevationSweep(
            centre=float((lo + hi) / 2),
            amplitude=float((hi - lo) / 2),
            frequency_hz=float(MID360_ELEVATION_HZ),
            line_phase=quarter_turns,
            line_azimuth=quarter_turns.copy(),
        ),
    )


def _avia(kind: LidarKind) -> LidarModel:
    return LidarModel(
        kind=kind,
        nominal_elevation=np.zeros(AVIA_LINES),
        firing_order=np.arange(AVIA_LINES, dtype=np.int64),
        firing_step_ns=AVIA_FIRING_NS,
        organized=False,
        min_range=1.0,
        max_range=190.0,  # datasheet: 190 m at 10 % reflectivity
        theta_start=0.0,
        cycle_ns=AVIA_CYCLE_NS,
        scan_curve=Rosette(
            azimuth_amplitude=float(np.radians(AVIA_AZIMUTH_HALF_FOV_DEG)),
            elevation_amplitude=float(np.radians(AVIA_ELEVATION_HALF_FOV_DEG)),
            petal_pairs=AVIA_PETAL_PAIRS,
            frequency_hz=float(AVIA_ROSE_HZ),
            turn_hz=float(AVIA_TURN_HZ),
            line_angle=np.arange(AVIA_LINES, dtype=np.float64) * (np.pi / AVIA_LINES),
        ),
    )


def lidar_model(kind: LidarKind | str) -> LidarModel:
    """The model of a LiDAR kind."""
    kind = LidarKind(kind)
    if kind is LidarKind.MID360:
        return _mid360(kind)
    if kind is LidarKind.AVIA:
        return _avia(kind)
    if kind is LidarKind.VLP16:
        return _velodyne(kind, VLP16_LASER_ELEVATION_DEG, VLP16_FIRING_NS, VLP16_CYCLE_NS, 0.4)
    if kind is LidarKind.HDL32:
        return _velodyne(kind, HDL32_LASER_ELEVATION_DEG, HDL32_FIRING_NS, HDL32_CYCLE_NS, 1.0)
    if kind is LidarKind.OS1_64:
        return _ouster(kind, 64, 16.6)
    beams = {LidarKind.OS1_32: 32, LidarKind.OS1_128: 128}[kind]
    return _ouster(kind, beams, 22.5)
