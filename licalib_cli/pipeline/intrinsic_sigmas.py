"""The reported 1-sigma of every intrinsic the model estimates (the result's
``intrinsics_uncertainty``), under the result's keys."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from licalib_cli.config import CalibConfig
from licalib_cli.pipeline.map_uncertainty import MapUncertainty
from licalib_cli.pipeline.settings import calibration_block
from licalib_cli.sections import IntrinsicsUncertainty
from licalib_cli.solver.lm import SolverReport

__all__ = ["LIDAR_UNCERTAINTY_KEYS", "intrinsics_uncertainty"]

_IMU_SUFFIXES = {
    "gyro_scale": ("x", "y", "z"),
    "gyro_misalignment": ("xy", "xz", "yz"),
    "gyro_rotation": ("rx", "ry", "rz"),
    "accel_scale": ("x", "y", "z"),
    "accel_misalignment": ("xy", "xz", "yz"),
    "g_sensitivity": tuple(f"{a}{b}" for a in "xyz" for b in "xyz"),
}
_DRIFT_SUFFIXES: dict[str, tuple[str, ...]] = {
    "gyro_bias_walk": ("x", "y", "z"),
    "accel_bias_walk": ("x", "y", "z"),
    "clock_drift": (),
}
LIDAR_UNCERTAINTY_KEYS: Mapping[str, tuple[str, str, bool]] = {
    "elevation": ("dphi", "elevation_deg", True),
    "azimuth": ("dtheta", "azimuth_deg", True),
    "vertical_offset": ("V", "vertical_offset_m", False),
    "horizontal_offset": ("H", "horizontal_offset_m", False),
    "range_scale": ("s", "range_scale", False),
    "range_offset": ("drho", "range_offset_m", False),
}
"""Each ``model.lidar`` block: its column in the solver's ``lidar.intrinsics[b].<column>``
names, its key in the result's ``intrinsics_uncertainty``, and whether that key is in degrees
(the solver's coordinate in radians)."""


def intrinsics_uncertainty(
    report: SolverReport,
    cfg: CalibConfig,
    factor: float,
    num_beams: int,
    planes: MapUncertainty | None = None,
) -> IntrinsicsUncertainty | None:
    """1-sigma of every intrinsic the model estimates (``None`` for held or unobservable ones),
    enlarged by ``factor`` (the root of the largest chi-square per sample) and, with ``planes``,
    by each coordinate's factor for the map planes' own uncertainty."""
    if not (cfg.model.imu or cfg.model.lidar):
        return None
    std = dict(zip(report.calibration_names, report.std, strict=True))
    weight = dict(zip(report.calibration_names, report.truncated_weight, strict=True))

    def get(name: str, degrees: bool = False) -> float | None:
        v = std.get(name)
        if v is None or not np.isfinite(v) or weight.get(name, 0.0) > 0.5:
            return None  # held, or not determined by the data (kept near nominal)
        grow = factor * (planes.of(name) if planes is not None else 1.0)
        return float(np.degrees(v) if degrees else v) * grow

    values: dict[str, tuple[float | None, ...]] = {}
    for block in cfg.model.imu:
        prefix = calibration_block(block)
        if block in _DRIFT_SUFFIXES:  # drifts (diagnose's bias walks, clock drift)
            suffixes = _DRIFT_SUFFIXES[block]
            names = [f"{prefix}.{s}" for s in suffixes] if suffixes else [prefix]
            pieces = [n for n in report.calibration_names if n.startswith(f"{prefix}.")]
            if suffixes and len(pieces) > len(names):  # a walk in pieces: x_1, y_1, z_1, x_2 ...
                names = pieces
            values[block] = tuple(get(n) for n in names)
            continue
        key: str = "gyro_rotation_deg" if block == "gyro_rotation" else block
        values[key] = tuple(
            get(f"{prefix}.{s}", block == "gyro_rotation") for s in _IMU_SUFFIXES[block]
        )
    for name in cfg.model.lidar:
        if name == "point_time":  # one number for the whole LiDAR
            values[name] = (get(calibration_block(name)),)
            continue
        col, key, degrees = LIDAR_UNCERTAINTY_KEYS[name]
        values[key] = tuple(get(f"lidar.intrinsics[{b}].{col}", degrees) for b in range(num_beams))
    return IntrinsicsUncertainty(values)
