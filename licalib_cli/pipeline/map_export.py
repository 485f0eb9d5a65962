"""The undistorted map of a segment: every point mapped into ``{G}`` with a calibration.

Each LiDAR point is corrected with the state's LiDAR intrinsics, moved into the IMU frame with
its extrinsic and placed on the trajectory at the point's own time plus the time offset, exactly
as the rounds map the points they sample (:func:`licalib_cli.pipeline.points.points_in_global`),
but for every point of every sweep. With the final estimate that is the calibrated map; with the
initial guess (:attr:`InitialGuess.state`) the map the rounds started from.

Frame and time: points are in ``{G}``, the IMU frame at the first IMU sample of the segment
(metres); ``time`` is the IMU-clock time the point was placed at (its LiDAR stamp plus the
time offset), seconds since the segment start ``t0_ns``. Points whose time falls outside the
trajectory (the first and last few milliseconds) are left out.

The map is computed in chunks of :data:`CHUNK_POINTS` points so that long recordings do not need
the rotation of every point in memory at once.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from licalib_cli.config import CalibConfig
from licalib_cli.estimation import CalibrationState
from licalib_cli.measurements import Recording
from licalib_cli.pipeline.points import (
    PointSample,
    points_in_global,
    query_times,
    sample_points,
)
from licalib_cli.pipeline.settings import spline_margin_s

__all__ = ["CHUNK_POINTS", "MapChunk", "MapPoints", "map_chunks", "map_points", "segment_points"]

CHUNK_POINTS = 200_000
"""Points mapped per vectorised chunk."""

_ALL = 1 << 40


@dataclass(frozen=True)
class MapChunk:
    """Part of a map.

    Attributes:
        xyz: (N, 3) float64 points in ``{G}``, m.
        beam: (N,) uint16 beam index.
        time_s: (N,) float64 IMU-clock time of each point, seconds since the segment start.
        intensity: (N,) float32 intensity (zero when the clouds carry none).
    """

    xyz: npt.NDArray[np.float64]
    beam: npt.NDArray[np.uint16]
    time_s: npt.NDArray[np.float64]
    intensity: npt.NDArray[np.float32]

    def __len__(self) -> int:
        return int(self.xyz.shape[0])


@dataclass(frozen=True)
class MapPoints:
    """The raw points of a segment, ready to be mapped with any calibration.

    Attributes:
        sample: raw measurements (beam, range, azimuth, times) of every point kept.
        intensity: (N,) float32 intensity per point.
    """

    sample: PointSample
    intensity: npt.NDArray[np.float32]

    def __len__(self) -> int:
        return len(self.sample)


def segment_points(rec: Recording, state: CalibrationState, cfg: CalibConfig) -> MapPoints:
    """Every point of the segment's sweeps within the configured range limits.

    Args:
        rec: the segment.
        state: any estimate of the segment (its nominal beam elevations are used).
        cfg: the configuration (range limits).
    """
    phi = state.lidar_intrinsics.nominal_elevation
    sample = sample_points(rec.scans, phi, _ALL, cfg)
    parts = []
    for scan in rec.scans:  # loop over sweeps, not points; same selection as sample_points
        if scan.ring is None or len(scan) == 0:
            continue
        rho = np.linalg.norm(scan.xyz, axis=1)
        ok = (rho >= cfg.lidar.min_range_m) & (rho <= cfg.lidar.max_range_m)
        value = scan.intensity if scan.intensity is not None else np.zeros(len(scan), np.float32)
        parts.append(np.asarray(value, dtype=np.float32)[ok])
    intensity = np.concatenate(parts) if parts else np.zeros(0, np.float32)
    return MapPoints(sample, intensity)


def _inside(state: CalibrationState, sample: PointSample, margin_s: float) -> npt.NDArray[np.bool_]:
    t = query_times(state, sample)
    return (t >= state.knots.t0_s + margin_s) & (t <= state.knots.t_end_s - margin_s)


def map_chunks(
    points: MapPoints,
    state: CalibrationState,
    cfg: CalibConfig,
    every: int = 1,
) -> tuple[int, Iterator[MapChunk]]:
    """The map of ``points`` under ``state``, chunk by chunk.

    Args:
        points: the segment's points.
        state: the calibration and trajectory to map them with.
        cfg: the configuration (the spline margin).
        every: keep every ``every``-th point only (a uniform thinning, same points for any
            state).

    Returns:
        The number of points the chunks hold in total, and the chunks.
    """
    index = np.arange(0, len(points), max(int(every), 1))
    keep = index[_inside(state, points.sample.subset(index), spline_margin_s(cfg))]

    def chunks() -> Iterator[MapChunk]:
        for start in range(0, keep.size, CHUNK_POINTS):
            sel = keep[start : start + CHUNK_POINTS]
            sub = points.sample.subset(sel)
            yield MapChunk(
                xyz=points_in_global(state, sub),
                beam=sub.beam.astype(np.uint16),
                time_s=query_times(state, sub),
                intensity=points.intensity[sel],
            )

    return int(keep.size), chunks()


def map_points(
    points: MapPoints, state: CalibrationState, cfg: CalibConfig, every: int = 1
) -> MapChunk:
    """The whole map of ``points`` under ``state`` in one chunk (see :func:`map_chunks`)."""
    _, chunks = map_chunks(points, state, cfg, every)
    parts = list(chunks)
    if not parts:
        return MapChunk(
            np.zeros((0, 3)), np.zeros(0, np.uint16), np.zeros(0), np.zeros(0, np.float32)
        )
    return MapChunk(
        np.concatenate([p.xyz for p in parts]),
        np.concatenate([p.beam for p in parts]),
        np.concatenate([p.time_s for p in parts]),
        np.concatenate([p.intensity for p in parts]),
    )
