"""Options several commands share, declared once so their names, help and panels agree.

Each is an ``Annotated`` alias: a command writes ``config: ConfigOption = None``. Typer copies
the option's description for every command that uses it.
"""

from __future__ import annotations

from collections.abc import Sequence
from enum import Enum
from pathlib import Path
from typing import Annotated, Any

import typer
import yaml

from licalib_cli.config import INTRINSIC_PRESETS
from licalib_cli.errors import ConfigError

__all__ = [
    "INPUT_PANEL",
    "BagArgument",
    "ConfigOption",
    "DurationOption",
    "ImuTopicOption",
    "Intrinsics",
    "LidarTopicOption",
    "SetOption",
    "StartOption",
    "input_overrides",
    "intrinsics_overrides",
    "settings_of",
]

INPUT_PANEL = "Input"
"""The help panel of the options that say what to read."""

BagArgument = Annotated[
    Path,
    typer.Argument(
        metavar="BAG",
        help="ROS1 .bag (or folder of split bags), ROS2 bag folder, .db3 or .mcap.",
        show_default=False,
    ),
]
ConfigOption = Annotated[
    Path | None,
    typer.Option("--config", "-c", help="YAML config.", rich_help_panel=INPUT_PANEL),
]
SetOption = Annotated[
    list[str] | None,
    typer.Option(
        "--set",
        metavar="KEY=VALUE",
        help="Change one setting of the config, e.g. surfels.final_points_per_scan=15000 "
        "(repeatable; the value is read as YAML, null unsets an optional setting; `licalib "
        "config dump` prints them all).",
        rich_help_panel=INPUT_PANEL,
        show_default=False,
    ),
]
ImuTopicOption = Annotated[
    str | None,
    typer.Option("--imu-topic", help="sensor_msgs/Imu topic.", rich_help_panel=INPUT_PANEL),
]
LidarTopicOption = Annotated[
    str | None,
    typer.Option(
        "--lidar-topic", help="sensor_msgs/PointCloud2 topic.", rich_help_panel=INPUT_PANEL
    ),
]
StartOption = Annotated[
    float | None,
    typer.Option("--start", help="Seconds after the bag start.", rich_help_panel=INPUT_PANEL),
]
DurationOption = Annotated[
    float | None,
    typer.Option("--duration", help="Seconds of data to use.", rich_help_panel=INPUT_PANEL),
]


def input_overrides(
    imu_topic: str | None, lidar_topic: str | None, start: float | None, duration: float | None
) -> dict[str, object]:
    """The config keys the input options set (None: the config's or the default value)."""
    return {
        "imu.topic": imu_topic,
        "lidar.topic": lidar_topic,
        "bag.start_s": start,
        "bag.duration_s": duration,
    }


class Intrinsics(str, Enum):
    """``--intrinsics`` choices."""

    NONE = "none"
    IMU = "imu"
    LIDAR = "lidar"
    ALL = "all"


def intrinsics_overrides(choice: Intrinsics | None) -> dict[str, list[str] | None]:
    """Config overrides of ``--intrinsics`` (none: the config's ``model:`` section)."""
    if choice is None:
        return {}
    imu, lidar = INTRINSIC_PRESETS[choice.value]
    return {"model.imu": list(imu), "model.lidar": list(lidar)}


def settings_of(values: Sequence[str] | None) -> dict[str, Any]:
    """The ``--set KEY=VALUE`` settings by dotted key, each value read as YAML (a later one of
    the same key wins).

    Raises:
        ConfigError: a value without ``=``, an empty key or value, or a value that is not YAML.
    """
    settings: dict[str, Any] = {}
    for item in values or ():
        key, sep, text = item.partition("=")
        key = key.strip()
        if not sep or not key or any(not part for part in key.split(".")):
            msg = (
                f"--set takes KEY=VALUE, such as surfels.final_points_per_scan=15000; got {item!r}."
            )
            raise ConfigError(msg)
        if not text.strip():
            msg = f"--set {key}= gives no value; write {key}=null to unset it."
            raise ConfigError(msg)
        try:
            settings[key] = yaml.safe_load(text)
        except yaml.YAMLError as err:
            msg = f"The value of --set {key} is not valid YAML ({text!r}); quote it or fix it."
            raise ConfigError(msg) from err
    return settings
