"""What a report needs beyond the result file, kept by ``calibrate`` in a sidecar file.

The result YAML holds the verdict, the estimate with its sigmas, the singular values and the
unobservable directions in words, the checks, the fit summary and the provenance. The figures
need arrays that do not belong in a YAML file; ``calibrate`` writes them next to the result as
``<stem>.report-data.npz`` (numpy's zip of arrays, no pickles, written atomically), so that
``licalib report RESULT`` can draw the whole report later without the bag:

======================================  ========================================================
key                                     content
======================================  ========================================================
``report_data_version``                 1
``result_created_utc``                  the result's ``provenance.created_utc`` (ties the pair)
``command_line``, ``config_text``       how ``calibrate`` was called, the resolved config
``truth_matrix``, ``truth_time_offset``  the ``--truth`` extrinsic on the result's clock (empty
                                        without ``--truth``)
``calibration_names``                   (Nc,) free calibration coordinates
``singular_labels``                     (Nc,) the dominant coordinate of each singular vector
``truncated_vectors``                   (k, Nc) the unobservable directions, scaled coordinates
``distances_before_m/after_m``          point-to-plane distances of round 1 before its solve
                                        and of the final round after it (thinned)
``imu_t_s``, ``gyro_residual``,         IMU residuals (prediction minus reading) against time,
``accel_residual``                      rad/s and m/s^2 (thinned)
``round_*``                             one entry per round: association distance, points,
                                        surfels, RMS, map entropy, iterations, seconds, the
                                        extrinsic after it (``round_translation_m``,
                                        ``round_rpy_deg``, ``round_time_offset_s``), ``round_free``
``motion_t_s``, ``angular_rate``,       the gyro and accelerometer readings over the recording
``specific_force``, ``segments_s``      read (thinned), seconds since ``motion_t0_ns``, and the
                                        segment(s) calibrated as ``[start, end]`` rows
``map_*``                               the map with the initial (``before``) and the final
                                        (``after``) calibration in the level frame (z up against
                                        gravity, origin at the first IMU position, x along the
                                        first IMU x axis): a horizontal slab (``top``, x/y), a
                                        vertical slab (``side``, x/z) of the same region, every
                                        point of the horizontal slab in a 1 m square on the
                                        densest wall (``zoom``), the slabs' definitions and the
                                        mean map entropy of both maps
======================================  ========================================================

A result of ``calibrate --segments`` has one more sidecar per window,
``<stem>.segK.report-data.npz``: the same arrays for window K calibrated alone (the joint problem
spans several windows, each with its own trajectory and map, so its figures are each window's);
``<stem>.report-data.npz`` then holds only the command line, the config and the truth.

A report drawn from a result without its sidecar shows what the YAML holds and says which
figures are missing.
"""

from __future__ import annotations

import os
import tempfile
import zipfile
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from licalib_cli.errors import ConfigError, DataError
from licalib_cli.parallel.threads import map_blocks
from licalib_cli.results import Extrinsic

if TYPE_CHECKING:
    from licalib_cli.config import CalibConfig
    from licalib_cli.measurements import Recording
    from licalib_cli.pipeline import CalibrationRun

__all__ = [
    "REPORT_DATA_VERSION",
    "MapSlices",
    "ReportData",
    "build_report_data",
    "report_data_path",
    "window_report_data_path",
]

REPORT_DATA_VERSION = 1

F32 = npt.NDArray[np.float32]
F64 = npt.NDArray[np.float64]

_MAX_DISTANCES = 60_000
_MAX_IMU = 4_000
_MAX_MOTION = 6_000
_MAP_POINTS = 600_000
"""Points of each map mapped for the slices (every k-th point of the segment)."""
_ENTROPY_POINTS = 100_000
"""Points of each map the report's entropy is taken over (every k-th of the mapped points).
The neighbourhoods keep their 0.3 m, so a thinner map changes the entropies by their sampling
scatter (0.02-0.05 on a 12 s shake, the difference between the two maps by less) at a third of
the time (0.4 s instead of 1.2-1.5 s per map)."""
_ENTROPY_QUERIES = 4_000
_MAX_SLICE = 150_000
TOP_SLAB_M = 0.3
"""Thickness of the horizontal slab of the top view, m (centred on the first IMU position)."""
SIDE_SLAB_M = 0.2
"""Thickness of the vertical slab of the side view, m (through the first IMU position)."""
_REGION_M = 40.0
ZOOM_M = 1.0
"""Side of the zoomed top view, m."""


def report_data_path(result_path: Path) -> Path:
    """``<stem>.report-data.npz`` next to the result file."""
    result_path = Path(result_path)
    return result_path.with_name(result_path.stem + ".report-data.npz")


def window_report_data_path(result_path: Path, index: int) -> Path:
    """``<stem>.seg<index>.report-data.npz`` next to a result of ``calibrate --segments``: the
    report data of window ``index`` (1-based, ``segK`` as in the result) calibrated alone."""
    result_path = Path(result_path)
    return result_path.with_name(f"{result_path.stem}.seg{index}.report-data.npz")


def _thin(n: int, at_most: int) -> npt.NDArray[np.intp]:
    return np.arange(0, n, max(1, -(-n // at_most))) if n else np.zeros(0, np.intp)


@dataclass(frozen=True)
class MapSlices:
    """Two views of one map in the level frame.

    Attributes:
        top_xy: (n, 2) points of the horizontal slab, m.
        side_xz: (m, 2) points of the vertical slab, m.
        zoom_xy: (k, 2) every point of the horizontal slab within the zoom window, m.
        entropy: mean map entropy of the map, nats (NaN when too sparse).
    """

    top_xy: F32
    side_xz: F32
    zoom_xy: F32
    entropy: float


@dataclass(frozen=True)
class ReportData:
    """The arrays of a report (see the module docstring for their meaning)."""

    result_created_utc: str = ""
    command_line: str = ""
    config_text: str = ""
    truth_matrix: F64 = field(default_factory=lambda: np.zeros((0, 4)))
    truth_time_offset: F64 = field(default_factory=lambda: np.zeros(0))
    calibration_names: npt.NDArray[np.str_] = field(default_factory=lambda: np.zeros(0, "U1"))
    singular_labels: npt.NDArray[np.str_] = field(default_factory=lambda: np.zeros(0, "U1"))
    truncated_vectors: F64 = field(default_factory=lambda: np.zeros((0, 0)))
    distances_before_m: F32 = field(default_factory=lambda: np.zeros(0, np.float32))
    distances_after_m: F32 = field(default_factory=lambda: np.zeros(0, np.float32))
    imu_t_s: F32 = field(default_factory=lambda: np.zeros(0, np.float32))
    gyro_residual: F32 = field(default_factory=lambda: np.zeros((0, 3), np.float32))
    accel_residual: F32 = field(default_factory=lambda: np.zeros((0, 3), np.float32))
    round_index: npt.NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    round_max_distance_m: F64 = field(default_factory=lambda: np.zeros(0))
    round_points: npt.NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    round_surfels: npt.NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    round_rms_m: F64 = field(default_factory=lambda: np.zeros(0))
    round_map_entropy: F64 = field(default_factory=lambda: np.zeros(0))
    round_iterations: npt.NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    round_seconds: F64 = field(default_factory=lambda: np.zeros(0))
    round_translation_m: F64 = field(default_factory=lambda: np.zeros((0, 3)))
    round_rpy_deg: F64 = field(default_factory=lambda: np.zeros((0, 3)))
    round_time_offset_s: F64 = field(default_factory=lambda: np.zeros(0))
    round_free: npt.NDArray[np.str_] = field(default_factory=lambda: np.zeros(0, "U1"))
    initial_translation_m: F64 = field(default_factory=lambda: np.zeros(0))
    initial_rpy_deg: F64 = field(default_factory=lambda: np.zeros(0))
    initial_time_offset_s: F64 = field(default_factory=lambda: np.zeros(0))
    motion_t0_ns: int = 0
    motion_t_s: F32 = field(default_factory=lambda: np.zeros(0, np.float32))
    angular_rate: F32 = field(default_factory=lambda: np.zeros((0, 3), np.float32))
    specific_force: F32 = field(default_factory=lambda: np.zeros((0, 3), np.float32))
    segments_s: F64 = field(default_factory=lambda: np.zeros((0, 2)))
    map_before_top_xy: F32 = field(default_factory=lambda: np.zeros((0, 2), np.float32))
    map_before_side_xz: F32 = field(default_factory=lambda: np.zeros((0, 2), np.float32))
    map_after_top_xy: F32 = field(default_factory=lambda: np.zeros((0, 2), np.float32))
    map_after_side_xz: F32 = field(default_factory=lambda: np.zeros((0, 2), np.float32))
    map_before_zoom_xy: F32 = field(default_factory=lambda: np.zeros((0, 2), np.float32))
    map_after_zoom_xy: F32 = field(default_factory=lambda: np.zeros((0, 2), np.float32))
    map_zoom_m: F64 = field(default_factory=lambda: np.zeros(0))
    """``[x_min, x_max, y_min, y_max]`` of the zoomed top view, level frame, m."""
    map_entropy_before: float = float("nan")
    map_entropy_after: float = float("nan")
    map_region_m: F64 = field(default_factory=lambda: np.zeros(0))
    """``[x_min, x_max, y_min, y_max, z_min, z_max]`` of the views, level frame, m."""
    map_top_slab_m: float = TOP_SLAB_M
    map_side_slab_m: float = SIDE_SLAB_M

    @property
    def truth(self) -> Extrinsic | None:
        """The ``--truth`` extrinsic on the result's clock, or None."""
        if self.truth_matrix.shape != (4, 4) or self.truth_time_offset.size != 1:
            return None
        m = np.asarray(self.truth_matrix, dtype=np.float64)
        return Extrinsic(m[:3, :3].copy(), m[:3, 3].copy(), float(self.truth_time_offset[0]))

    @property
    def has_map(self) -> bool:
        """Whether the map views were kept."""
        return bool(self.map_after_top_xy.shape[0] or self.map_after_side_xz.shape[0])

    def save(self, path: Path) -> None:
        """Write the arrays as a compressed ``.npz`` atomically (temporary file, rename)."""
        path = Path(path)
        arrays = {"report_data_version": np.asarray(REPORT_DATA_VERSION)}
        for f in fields(self):
            value = getattr(self, f.name)
            arrays[f.name] = np.asarray(value)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
        try:
            with os.fdopen(fd, "wb") as fh:
                np.savez_compressed(fh, **arrays)  # type: ignore[arg-type]
            umask = os.umask(0)
            os.umask(umask)
            os.chmod(tmp, 0o666 & ~umask)
            os.replace(tmp, path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise

    @classmethod
    def load(cls, path: Path) -> ReportData:
        """Read a sidecar written by :meth:`save`.

        Raises:
            ConfigError: the file is not such a sidecar or of another version.
        """
        path = Path(path)
        try:
            with np.load(path, allow_pickle=False) as z:
                arrays = {k: z[k] for k in z.files}
        except (OSError, ValueError, zipfile.BadZipFile, EOFError) as err:
            msg = (
                f"{path} is not a licalib report-data file ({err}); delete it or calibrate "
                "again to rewrite it."
            )
            raise ConfigError(msg) from err
        version = arrays.pop("report_data_version", None)
        if version is None or int(version) != REPORT_DATA_VERSION:
            msg = (
                f"{path} is report data of version {version}, but this licalib reads version "
                f"{REPORT_DATA_VERSION}; calibrate again to rewrite it."
            )
            raise ConfigError(msg)
        kwargs: dict[str, Any] = {}
        for f in fields(cls):
            if f.name not in arrays:
                continue
            value = arrays[f.name]
            if f.type in ("str",):
                kwargs[f.name] = str(value)
            elif f.type in ("float",):
                kwargs[f.name] = float(value)
            elif f.type in ("int",):
                kwargs[f.name] = int(value)
            else:
                kwargs[f.name] = value
        return cls(**kwargs)


# ------------------------------------------------------------------------------ building it


def level_frame(gravity_G: F64) -> F64:
    """(3, 3) rotation from ``{G}`` into the level frame: z against gravity, x along the
    horizontal part of ``{G}``'s x axis (its y axis when x is vertical)."""
    g = np.asarray(gravity_G, dtype=np.float64)
    up = -g / max(float(np.linalg.norm(g)), 1e-12)
    x = np.array([1.0, 0.0, 0.0]) - up * up[0]
    if np.linalg.norm(x) < 1e-6:
        x = np.array([0.0, 1.0, 0.0]) - up * up[1]
    x /= np.linalg.norm(x)
    y = np.cross(up, x)
    return np.stack([x, y, up])


def _entropy(xyz: F64) -> float:
    from licalib_cli.map_quality import mean_map_entropy

    idx = _thin(xyz.shape[0], _ENTROPY_POINTS)
    try:
        return float(mean_map_entropy(xyz[idx], max_query_points=_ENTROPY_QUERIES).mean)
    except DataError:
        return float("nan")


def _region(level_xyz: F64) -> F64:
    """The views' region: the central 99 % of the final map horizontally (at most
    :data:`_REGION_M` across), its 0.5-99.5 % in height."""
    if level_xyz.shape[0] == 0:
        return np.array([-1.0, 1.0, -1.0, 1.0, -1.0, 1.0])
    lo = np.percentile(level_xyz, 0.5, axis=0)
    hi = np.percentile(level_xyz, 99.5, axis=0)
    zlo, zhi = lo[2], hi[2]
    half = _REGION_M / 2
    x0, x1 = max(lo[0], -half), min(hi[0], half)
    y0, y1 = max(lo[1], -half), min(hi[1], half)
    pad = 0.3
    return np.array([x0 - pad, x1 + pad, y0 - pad, y1 + pad, zlo - pad, zhi + pad])


def _zoom(level_xyz: F64) -> F64:
    """A :data:`ZOOM_M` square of the horizontal slab on the densest stretch of surface at
    least 1 m from the start (where a doubled or thick wall shows best)."""
    x, y, z = level_xyz[:, 0], level_xyz[:, 1], level_xyz[:, 2]
    slab = (np.abs(z) <= TOP_SLAB_M / 2) & (np.hypot(x, y) > 1.0)
    if not np.any(slab):
        return np.array([-ZOOM_M / 2, ZOOM_M / 2, -ZOOM_M / 2, ZOOM_M / 2])
    cell = np.floor(np.stack([x[slab], y[slab]], axis=1) / ZOOM_M).astype(np.int64)
    keys, counts = np.unique(cell, axis=0, return_counts=True)
    cx, cy = keys[int(np.argmax(counts))]
    inside = slab.copy()
    inside[slab] = (cell[:, 0] == cx) & (cell[:, 1] == cy)
    mx, my = float(np.median(x[inside])), float(np.median(y[inside]))
    h = ZOOM_M / 2
    return np.array([mx - h, mx + h, my - h, my + h])


def _slices(level_xyz: F64, region: F64, zoom: F64, entropy: float) -> MapSlices:
    x, y, z = level_xyz[:, 0], level_xyz[:, 1], level_xyz[:, 2]
    inside = (x >= region[0]) & (x <= region[1]) & (y >= region[2]) & (y <= region[3])
    top = inside & (np.abs(z) <= TOP_SLAB_M / 2)
    in_zoom = (
        (np.abs(z) <= TOP_SLAB_M / 2)
        & (x >= zoom[0])
        & (x <= zoom[1])
        & (y >= zoom[2])
        & (y <= zoom[3])
    )
    side = (
        (x >= region[0])
        & (x <= region[1])
        & (z >= region[4])
        & (z <= region[5])
        & (np.abs(y) <= SIDE_SLAB_M / 2)
    )
    t_idx = np.flatnonzero(top)
    s_idx = np.flatnonzero(side)
    t_idx = t_idx[_thin(t_idx.size, _MAX_SLICE)]
    s_idx = s_idx[_thin(s_idx.size, _MAX_SLICE)]
    return MapSlices(
        level_xyz[t_idx][:, :2].astype(np.float32),
        level_xyz[s_idx][:, [0, 2]].astype(np.float32),
        level_xyz[in_zoom][:, :2].astype(np.float32),
        entropy,
    )


def imu_residuals(run: CalibrationRun) -> tuple[F64, F64, F64]:
    """``(t_s, gyro, accel)``: the IMU residuals (prediction minus reading) of the final fit,
    rad/s and m/s^2, without evaluating the LiDAR points."""
    from licalib_cli.estimation import build_problem
    from licalib_cli.residuals import AccelResidual, GyroResidual

    inputs = run.fit.inputs
    problem = build_problem(
        run.state, inputs.imu, None, None, inputs.noise, inputs.free, fix_gauge=False
    )
    params = problem.values()
    gyro = next(b for b in problem.residual_blocks if isinstance(b, GyroResidual))
    accel = next(b for b in problem.residual_blocks if isinstance(b, AccelResidual))
    r_g = gyro.evaluate(params, jacobians=False).residuals / gyro.inv_sigma
    r_a = accel.evaluate(params, jacobians=False).residuals / accel.inv_sigma
    return np.asarray(gyro.t_s), np.reshape(r_g, (-1, 3)), np.reshape(r_a, (-1, 3))


def build_report_data(
    run: CalibrationRun,
    rec: Recording,
    cfg: CalibConfig,
    *,
    truth: Extrinsic | None = None,
    command_line: str = "",
    config_text: str = "",
    with_map: bool = True,
) -> ReportData:
    """Collect the report's arrays from a finished run.

    Args:
        run: the calibration.
        rec: the segment it was computed from.
        cfg: its configuration.
        truth: the true extrinsic on the result's clock (``--truth``), if any.
        command_line: how ``calibrate`` was called.
        config_text: the resolved configuration as YAML.
        with_map: map the segment with both calibrations for the map views.
    """
    from licalib_cli.pipeline.map_export import map_points, thinning_for
    from licalib_cli.plots import dominant_labels
    from licalib_cli.results import rpy_deg_from_matrix

    result = run.result
    report = run.solver
    info = report.information
    rounds = run.rounds
    first, last = rounds[0].distances_before_m, rounds[-1].distances_after_m
    t_res, r_gyro, r_accel = imu_residuals(run)
    imu_idx = _thin(t_res.shape[0], _MAX_IMU)
    t_imu = rec.imu.t_ns
    m_idx = _thin(t_imu.shape[0], _MAX_MOTION)
    t0 = int(t_imu[0]) if t_imu.size else int(rec.start_ns)
    segments = np.array([[(rec.start_ns - t0) * 1e-9, (rec.end_ns - t0) * 1e-9]])
    truncated = (
        np.stack([d.vector for d in report.truncated])
        if report.truncated
        else np.zeros((0, len(info.names)))
    )
    ini = run.initial
    data: dict[str, Any] = {
        "result_created_utc": result.provenance.created_utc if result.provenance else "",
        "command_line": command_line,
        "config_text": config_text,
        "calibration_names": np.asarray(info.names, dtype=str),
        "singular_labels": np.asarray(
            dominant_labels(info.singular_vectors, info.names) if len(info.names) else [],
            dtype=str,
        ),
        "truncated_vectors": truncated,
        "distances_before_m": np.asarray(first[_thin(first.size, _MAX_DISTANCES)], np.float32),
        "distances_after_m": np.asarray(last[_thin(last.size, _MAX_DISTANCES)], np.float32),
        "imu_t_s": t_res[imu_idx].astype(np.float32),
        "gyro_residual": r_gyro[imu_idx].astype(np.float32),
        "accel_residual": r_accel[imu_idx].astype(np.float32),
        "round_index": np.array([r.index for r in rounds], np.int64),
        "round_max_distance_m": np.array([r.max_distance_m for r in rounds]),
        "round_points": np.array([r.points for r in rounds], np.int64),
        "round_surfels": np.array([r.surfels for r in rounds], np.int64),
        "round_rms_m": np.array([r.rms_m for r in rounds]),
        "round_map_entropy": np.array([r.map_entropy for r in rounds]),
        "round_iterations": np.array([r.iterations for r in rounds], np.int64),
        "round_seconds": np.array([r.seconds for r in rounds]),
        "round_translation_m": np.array([r.extrinsic.translation for r in rounds]),
        "round_rpy_deg": np.array([rpy_deg_from_matrix(r.extrinsic.rotation) for r in rounds]),
        "round_time_offset_s": np.array([r.extrinsic.time_offset_s for r in rounds]),
        "round_free": np.asarray([", ".join(r.free) for r in rounds], dtype=str),
        "initial_translation_m": np.asarray(ini.t_imu_lidar, np.float64),
        "initial_rpy_deg": rpy_deg_from_matrix(np.asarray(ini.R_imu_lidar)),
        "initial_time_offset_s": np.array([ini.time_offset_s]),
        "motion_t0_ns": t0,
        "motion_t_s": ((t_imu[m_idx] - t0) * 1e-9).astype(np.float32),
        "angular_rate": rec.imu.gyro[m_idx].astype(np.float32),
        "specific_force": rec.imu.accel[m_idx].astype(np.float32),
        "segments_s": segments,
    }
    if truth is not None:
        data["truth_matrix"] = truth.matrix()
        data["truth_time_offset"] = np.array([truth.time_offset_s])
    if with_map:
        every = thinning_for(rec, _MAP_POINTS)
        level = level_frame(run.state.gravity_G)
        states = (run.state, ini.state)

        def leveled_map(i: int) -> tuple[F64, float]:
            xyz = map_points(rec, states[i], cfg, every).xyz @ level.T
            return xyz, _entropy(xyz)

        # the final and the initial map, one per block thread
        (after, entropy_after), (before, entropy_before) = map_blocks(leveled_map, 2)
        region = _region(after)
        zoom = _zoom(after)
        s_after = _slices(after, region, zoom, entropy_after)
        s_before = _slices(before, region, zoom, entropy_before)
        data.update(
            map_before_top_xy=s_before.top_xy,
            map_before_side_xz=s_before.side_xz,
            map_after_top_xy=s_after.top_xy,
            map_after_side_xz=s_after.side_xz,
            map_before_zoom_xy=s_before.zoom_xy,
            map_after_zoom_xy=s_after.zoom_xy,
            map_zoom_m=zoom,
            map_entropy_before=s_before.entropy,
            map_entropy_after=s_after.entropy,
            map_region_m=region,
        )
    return ReportData(**data)
