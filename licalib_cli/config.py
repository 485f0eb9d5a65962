"""One typed configuration tree (pydantic v2, unknown keys rejected).

A YAML config mirrors :class:`CalibConfig`; every section is optional. Command-line options
override the file. ``licalib config dump`` prints the resolved tree.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from licalib_cli.errors import ConfigError


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_assignment=True)


class ImuInputConfig(_Section):
    """How to read the IMU messages."""

    topic: str | None = None
    """``sensor_msgs/Imu`` topic; found automatically when the bag has exactly one."""
    gyro_unit: Literal["rad/s", "deg/s"] | None = None
    """Unit of ``angular_velocity``; detected from the data when unset."""
    accel_unit: Literal["m/s^2", "g"] | None = None
    """Unit of ``linear_acceleration``; detected from the data when unset."""


class LidarInputConfig(_Section):
    """How to read the PointCloud2 messages."""

    topic: str | None = None
    """``sensor_msgs/PointCloud2`` topic; found automatically when the bag has exactly one."""
    time_field: str | None = None
    """Per-point time field name (``t``, ``time``, ``timestamp``, ``offset_time``, ...); detected."""
    time_unit: Literal["s", "ms", "us", "ns"] | None = None
    """Unit of the per-point time field; detected from the data when unset."""
    time_reference: Literal["relative", "absolute"] | None = None
    """Whether the per-point times are relative to the header stamp or absolute; detected."""
    stamp_position: Literal["start", "end"] | None = None
    """Whether the header stamp marks the sweep start or end (used when times are estimated)."""
    ring_field: str | None = None
    """Beam index field (``ring`` or ``line``); detected. Recovered from elevation if absent."""
    num_beams: int | None = Field(default=None, ge=1, le=512)
    """Number of beams, needed only when there is no ring field and elevations are ambiguous."""
    scan_period_s: float | None = Field(default=None, gt=0.0, le=1.0)
    """Sweep period used to estimate per-point times from azimuth; detected from stamps."""
    clockwise: bool = False
    """Spin direction used when per-point times are estimated from azimuth."""
    min_range_m: float = Field(default=0.5, ge=0.0)
    max_range_m: float = Field(default=100.0, gt=0.0)


class BagConfig(_Section):
    """Which part of the bag to use."""

    start_s: float = Field(default=0.0, ge=0.0)
    """Seconds after the first message at which the segment starts."""
    duration_s: float | None = Field(default=None, gt=0.0)
    """Length of the segment; the whole bag when unset."""


class CalibConfig(_Section):
    """The whole configuration."""

    bag: BagConfig = BagConfig()
    imu: ImuInputConfig = ImuInputConfig()
    lidar: LidarInputConfig = LidarInputConfig()


def yaml_error_summary(err: yaml.YAMLError) -> str:
    """One-line description of a YAML parse error with its line and column."""
    problem = getattr(err, "problem", None) or type(err).__name__
    mark = getattr(err, "problem_mark", None)
    where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
    return f"{problem}{where}"


def load_config(path: Path | None, overrides: dict[str, Any] | None = None) -> CalibConfig:
    """Read a YAML config (or defaults) and apply dotted overrides such as ``{"imu.topic": "/x"}``.

    Raises:
        ConfigError: the file is missing, not YAML, or has unknown keys or bad values.
    """
    data: dict[str, Any] = {}
    if path is not None:
        path = Path(path)
        try:
            loaded = yaml.safe_load(path.read_text())
        except FileNotFoundError as err:
            msg = f"The config file {path} does not exist; check the path."
            raise ConfigError(msg) from err
        except yaml.YAMLError as err:
            msg = f"The config file {path} is not valid YAML ({yaml_error_summary(err)}); fix the syntax."
            raise ConfigError(msg) from err
        if loaded is not None and not isinstance(loaded, dict):
            msg = f"The config file {path} must be a YAML mapping of sections."
            raise ConfigError(msg)
        data = loaded or {}
    for dotted, value in (overrides or {}).items():
        if value is None:
            continue
        node = data
        *parents, leaf = dotted.split(".")
        for key in parents:
            node = node.setdefault(key, {})
        node[leaf] = value
    try:
        return CalibConfig.model_validate(data)
    except ValidationError as err:
        first = err.errors()[0]
        where = ".".join(str(x) for x in first["loc"])
        source = f"config file {path}" if path else "options"
        msg = f"Invalid setting '{where}' in the {source}: {first['msg']}."
        raise ConfigError(msg) from err


def dump_config(cfg: CalibConfig) -> str:
    """The resolved configuration as YAML."""
    return yaml.safe_dump(cfg.model_dump(mode="json"), sort_keys=False)
