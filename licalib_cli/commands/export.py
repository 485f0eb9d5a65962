"""``licalib export``: a result file as FAST-LIO, LIO-SAM, URDF, tf2, Kalibr or JSON text.

Thin wiring: read the result, check its verdict, one call to :func:`licalib_cli.export.export`,
then standard output or an atomically written file.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import typer

from licalib_cli.errors import ConfigError
from licalib_cli.export import (
    FRAME_TARGETS,
    ExportTarget,
    ParentSensor,
    export,
    exportable,
    load_result,
    resolve_frames,
)
from licalib_cli.results import prepare_output, write_text_atomic

logger = logging.getLogger(__name__)

_FRAMES = "Frames (urdf, tf2)"


def _same_file(a: Path, b: Path) -> bool:
    try:
        return a.exists() and b.exists() and os.path.samefile(a, b)
    except OSError:
        return a.resolve() == b.resolve()


def _check_not_an_input(out: Path, result_path: Path, bag: str | None) -> None:
    """Refuse an output path that is the result file, its resolved config or the bag."""
    inputs = [
        ("the result file being exported", result_path),
        ("the result's resolved config", result_path.with_name(result_path.stem + ".config.yaml")),
    ]
    if bag:
        inputs.append(("the calibrated bag", Path(bag)))
    for what, path in inputs:
        if _same_file(out, path) or out.resolve() == path.resolve():
            msg = f"The output {out} is {what}; give another output path."
            raise ConfigError(msg)


def export_command(
    result_path: Path = typer.Argument(
        ..., metavar="RESULT", help="A result file written by `licalib calibrate`."
    ),
    to: ExportTarget = typer.Option(..., "--to", help="Target format."),
    out: Path | None = typer.Option(
        None, "--out", "-o", help="Write to this file (atomically) instead of standard output."
    ),
    force: bool = typer.Option(
        False, "--force", help="Export even a result whose verdict is fail."
    ),
    ros2: bool = typer.Option(
        False,
        "--ros2",
        help="fast-lio, lio-sam: the ROS 2 parameter-file form (/**: ros__parameters:); for "
        "lio-sam also its ros2 branch's extrinsicRPY.",
    ),
    parent: str | None = typer.Option(
        None,
        "--parent",
        help="Parent frame name (default: the recorded frame id of the parent sensor).",
        rich_help_panel=_FRAMES,
    ),
    child: str | None = typer.Option(
        None,
        "--child",
        help="Child frame name (default: the recorded frame id of the other sensor).",
        rich_help_panel=_FRAMES,
    ),
    parent_sensor: ParentSensor | None = typer.Option(
        None,
        "--parent-sensor",
        help="Which sensor's frame is the parent (default imu; the child's pose in the parent "
        "is written).",
        rich_help_panel=_FRAMES,
    ),
) -> None:
    """Write a result as FAST-LIO, LIO-SAM, URDF, tf2, Kalibr or JSON parameters."""
    frame_options = (parent, child, parent_sensor)
    if to not in FRAME_TARGETS and any(o is not None for o in frame_options):
        msg = (
            f"--parent, --child and --parent-sensor apply to urdf and tf2 only, not "
            f"{to.value}; drop them."
        )
        raise ConfigError(msg)
    result = load_result(result_path)
    warnings = exportable(result, force=force)
    frames = resolve_frames(result, parent, child, parent_sensor) if to in FRAME_TARGETS else None
    text = export(result, to, frames=frames, ros2=ros2)
    for warning in warnings:
        logger.warning(warning)
    if out is None:
        typer.echo(text, nl=False)
        return
    _check_not_an_input(out, result_path, result.recording.bag if result.recording else None)
    prepare_output(out)
    write_text_atomic(out, text)
    logger.info("Wrote %s (%s).", out, to.value)
