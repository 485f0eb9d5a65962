"""Options several commands share, declared once so their names, help and panels agree.

Each is an ``Annotated`` alias: a command writes ``config: ConfigOption = None``. Typer copies
the option's description for every command that uses it.
"""

from __future__ import annotations

from enum import Enum
from pathlib import Path
from typing import Annotated

import typer

from licalib_cli.config import INTRINSIC_PRESETS

__all__ = [
    "INPUT_PANEL",
    "BagArgument",
    "ConfigOption",
    "DurationOption",
    "ImuTopicOption",
    "Intrinsics",
    "LidarTopicOption",
    "StartOption",
    "input_overrides",
    "intrinsics_overrides",
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
