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

The map is computed a group of sweeps at a time (about :data:`CHUNK_POINTS` points) so that
long recordings need neither a copy of every point nor the rotation of every point in memory.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from licalib_cli.config import CalibConfig
from licalib_cli.estimation import CalibrationState
from licalib_cli.geometry.vectors import norms
from licalib_cli.measurements import LidarScan, Recording
from licalib_cli.models.lidar import nominal_point
from licalib_cli.pipeline.points import PointSample, points_in_global, query_times
from licalib_cli.pipeline.settings import spline_margin_s

__all__ = ["CHUNK_POINTS", "MapChunk", "map_chunks", "map_points", "thinning_for"]

CHUNK_POINTS = 200_000
"""Points mapped per vectorised chunk."""


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


def _scan_sample(
    scan: LidarScan, phi: npt.NDArray[np.float64], cfg: CalibConfig, every: int
) -> tuple[PointSample, npt.NDArray[np.float32]]:
    """The points of one sweep within the range limits (every ``every``-th), as raw
    measurements like :func:`~licalib_cli.pipeline.points.sample_points` keeps them, and their
    intensity."""
    rho = norms(scan.xyz)
    idx = np.flatnonzero((rho >= cfg.lidar.min_range_m) & (rho <= cfg.lidar.max_range_m))
    idx = idx[:: max(int(every), 1)]
    assert scan.ring is not None
    beam = scan.ring[idx].astype(np.int64)
    xyz, r = scan.xyz[idx], rho[idx]
    theta = np.arctan2(xyz[:, 1], xyz[:, 0])
    start = np.full(idx.size, int(scan.t_ns.min()), dtype=np.int64)
    sample = PointSample(
        scan.t_ns[idx], start, beam, r, theta, xyz - nominal_point(r, theta, phi[beam])
    )
    value = scan.intensity if scan.intensity is not None else np.zeros(len(scan), np.float32)
    return sample, np.asarray(value, dtype=np.float32)[idx]


def _inside(state: CalibrationState, sample: PointSample, margin_s: float) -> npt.NDArray[np.bool_]:
    t = query_times(state, sample)
    return (t >= state.knots.t0_s + margin_s) & (t <= state.knots.t_end_s - margin_s)


def thinning_for(rec: Recording, at_most: int) -> int:
    """The ``every`` that keeps at most about ``at_most`` points of the segment."""
    total = sum(len(s) for s in rec.scans)
    return max(1, -(-total // max(int(at_most), 1)))


def map_chunks(
    rec: Recording, state: CalibrationState, cfg: CalibConfig, every: int = 1
) -> tuple[int, Iterator[MapChunk]]:
    """The map of the segment under ``state``, a group of sweeps at a time.

    Args:
        rec: the segment.
        state: the calibration and trajectory to map the points with.
        cfg: the configuration (range limits, spline margin).
        every: keep every ``every``-th point of each sweep only (a uniform thinning, the same
            points for any state).

    Returns:
        The number of points the chunks hold in total, and the chunks.
    """
    phi = state.lidar_intrinsics.nominal_elevation
    margin = spline_margin_s(cfg.spline.time_offset_padding_s, state.knots)
    count = 0
    for scan in _mappable(rec):  # sweeps, not points: the count goes into a file header first
        sample, _ = _scan_sample(scan, phi, cfg, every)
        count += int(np.count_nonzero(_inside(state, sample, margin)))
    return count, _chunks(rec, state, cfg, every)


def _mappable(rec: Recording) -> list[LidarScan]:
    return [s for s in rec.scans if s.ring is not None and len(s) > 0]


def _chunks(
    rec: Recording, state: CalibrationState, cfg: CalibConfig, every: int
) -> Iterator[MapChunk]:
    """The chunks of :func:`map_chunks` (without counting their points first)."""
    phi = state.lidar_intrinsics.nominal_elevation
    margin = spline_margin_s(cfg.spline.time_offset_padding_s, state.knots)
    scans = _mappable(rec)
    group: list[tuple[PointSample, npt.NDArray[np.float32]]] = []
    size = 0
    for k, scan in enumerate(scans):
        sample, intensity = _scan_sample(scan, phi, cfg, every)
        keep = _inside(state, sample, margin)
        group.append((sample.subset(keep), intensity[keep]))
        size += int(np.count_nonzero(keep))
        if size >= CHUNK_POINTS or k == len(scans) - 1:
            yield _mapped(state, group)
            group, size = [], 0


def _mapped(
    state: CalibrationState, group: list[tuple[PointSample, npt.NDArray[np.float32]]]
) -> MapChunk:
    parts = [g[0] for g in group]
    sample = PointSample(*(np.concatenate([getattr(p, f) for p in parts]) for f in _SAMPLE_FIELDS))
    return MapChunk(
        xyz=points_in_global(state, sample),
        beam=sample.beam.astype(np.uint16),
        time_s=query_times(state, sample),
        intensity=np.concatenate([g[1] for g in group]),
    )


_SAMPLE_FIELDS = ("t_ns", "sweep_start_ns", "beam", "rho", "theta", "model_gap")


def map_points(
    rec: Recording, state: CalibrationState, cfg: CalibConfig, every: int = 1
) -> MapChunk:
    """The whole map of the segment under ``state`` in one chunk (see :func:`map_chunks`)."""
    parts = list(_chunks(rec, state, cfg, every))
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
