"""``licalib select-segments``: rank the windows of a long bag by the information they carry
about the calibration; print the ranking, optionally as JSON and as a figure."""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import typer
from rich.table import Table

from licalib_cli.commands.options import (
    INPUT_PANEL,
    BagArgument,
    ConfigOption,
    ImuTopicOption,
    Intrinsics,
    LidarTopicOption,
    SetOption,
    input_overrides,
    intrinsics_overrides,
    settings_of,
)
from licalib_cli.commands.render import console
from licalib_cli.config import load_config
from licalib_cli.results import prepare_output

if TYPE_CHECKING:
    from licalib_cli.pipeline.segments import Selection

_IO = INPUT_PANEL
_WIN = "Windows"
_OUT = "Output"


def short_direction(text: str) -> str:
    """A weak direction in a few words: ``rotation [0.23, -0.02, 0.97] (LiDAR)``."""
    text = text.split(" (singular value")[0]
    for long, short in (
        ("ext.", ""),
        (" along ", " "),
        (" in the LiDAR frame", " (LiDAR)"),
        (" in the IMU frame", " (IMU)"),
        ("time_offset", "time offset"),
    ):
        text = text.replace(long, short)
    return text


def render_selection(sel: Selection, limit: int | None = None) -> Table:
    """The ranked table: window, metric, weakest direction, excitation, selected."""
    table = Table(
        title=f"Windows of {sel.length_s:g} s by the information they carry (min singular "
        "value of the scaled calibration information; RMS angular rate and acceleration; "
        "tilt: RMS turn of gravity in the IMU frame, deg)"
    )
    for col, just in (
        ("#", "right"),
        ("window s", "left"),
        ("min sv", "right"),
        ("weakest direction", "left"),
        ("deg/s", "right"),
        ("m/s^2", "right"),
        ("tilt", "right"),
        ("sel.", "center"),
    ):
        table.add_column(col, justify=just)  # type: ignore[arg-type]
    rows = sel.ranked if limit is None else sel.ranked[:limit]
    for w in rows:
        weak = short_direction(w.weak_directions[0]) if w.weak_directions else ""
        table.add_row(
            str(w.rank),
            f"{w.start_s:.1f}-{w.end_s:.1f}",
            f"{w.min_singular_value:.3g}",
            weak,
            f"{np.degrees(w.angular_rate):.0f}",
            f"{w.acceleration:.2f}",
            f"{w.tilt_deg:.0f}",
            "yes" if w.selected else "",
        )
    return table


def save_selection_plot(sel: Selection, path: Path) -> Path:
    """The paper's figure: the metric per window over the angular rate and acceleration of
    the whole bag (selected windows shaded)."""
    from licalib_cli.plots import pyplot

    plt = pyplot()
    fig, (ax_m, ax_w, ax_a) = plt.subplots(3, 1, figsize=(10, 7), sharex=True)
    for w in sel.windows:
        colour = "tab:green" if w.selected else "tab:blue"
        ax_m.hlines(max(w.min_singular_value, 1e-6), w.start_s, w.end_s, colors=colour, lw=3)
        if w.selected:
            for ax in (ax_m, ax_w, ax_a):
                ax.axvspan(w.start_s, w.end_s, color="tab:green", alpha=0.12, lw=0)
    ax_m.set_yscale("log")
    ax_m.set_ylabel("min singular value")
    ax_m.set_title("Information per window (selected in green)")
    ex = sel.excitation
    ax_w.plot(ex.t_s, np.degrees(ex.angular_rate), lw=0.7, color="tab:orange")
    ax_w.set_ylabel("|angular rate| deg/s")
    ax_a.plot(ex.t_s, ex.acceleration, lw=0.7, color="tab:purple")
    ax_a.set_ylabel("| |a| - g | m/s^2")
    ax_a.set_xlabel("seconds after the bag start")
    fig.tight_layout()
    tmp = path.with_name(f".{path.name}.tmp")
    fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
    tmp.replace(path)
    return path


def select_segments_command(
    bag: BagArgument,
    config: ConfigOption = None,
    settings: SetOption = None,
    imu_topic: ImuTopicOption = None,
    lidar_topic: LidarTopicOption = None,
    start: float | None = typer.Option(
        None,
        "--start",
        help="Rank from this many seconds after the bag start.",
        rich_help_panel=_IO,
    ),
    duration: float | None = typer.Option(
        None,
        "--duration",
        help="Rank only this many seconds (default: to the end).",
        rich_help_panel=_IO,
    ),
    intrinsics: Intrinsics | None = typer.Option(
        None,
        "--intrinsics",
        help="The intrinsics the calibration will estimate (as calibrate --intrinsics; default: "
        "the config's model section): the IMU blocks among them count as unknown in the metric.",
        rich_help_panel=_WIN,
    ),
    length: float = typer.Option(15.0, "--length", help="Window length, s.", rich_help_panel=_WIN),
    step: float | None = typer.Option(
        None,
        "--step",
        help="Window step, s (default: the length; shorter overlaps).",
        rich_help_panel=_WIN,
    ),
    top: int | None = typer.Option(
        None,
        "--top",
        help="Select K windows that do not overlap: the best, then each adding most to those "
        "taken (default 3).",
        rich_help_panel=_WIN,
    ),
    threshold: float | None = typer.Option(
        None,
        "--threshold",
        help="Select the windows whose min singular value is at least this.",
        rich_help_panel=_WIN,
    ),
    every: int = typer.Option(
        3,
        "--every",
        min=1,
        help="Decode every N-th cloud (1: all; faster when larger).",
        rich_help_panel=_WIN,
    ),
    as_json: bool = typer.Option(
        False, "--json", help="Print one JSON object instead of the table.", rich_help_panel=_OUT
    ),
    plot: Path | None = typer.Option(
        None,
        "--plot",
        metavar="FILE",
        help="Write the figure (metric per window over the bag's motion) as PNG.",
        rich_help_panel=_OUT,
    ),
) -> None:
    """Rank windows of a bag by how well they determine the calibration; select the best."""
    from licalib_cli.pipeline.segments import select_segments

    if plot is not None:
        from licalib_cli.plots import pyplot

        pyplot()
        prepare_output(plot, [("the input bag", bag), ("the config file", config)])
    cfg = load_config(
        config,
        {
            **input_overrides(imu_topic, lidar_topic, start, duration),
            **intrinsics_overrides(intrinsics),
        },
        settings_of(settings),
    )
    from licalib_cli.commands.calibrate import RichProgress

    progress = RichProgress()
    progress.stage("windows")
    try:
        sel = select_segments(bag, cfg, length, step, top, threshold, every, progress.advance)
    finally:
        progress.close()
    if as_json:
        typer.echo(json.dumps(_jsonable(sel.to_dict()), indent=2))
    else:
        out = console()
        out.print(render_selection(sel))
        chosen = ",".join(f"{w.start_s:g}-{w.end_s:g}" for w in sel.selected)
        out.print(f"Common estimate: {sel.estimate.source}.")
        if sel.intrinsics:
            out.print(
                f"Metric with the model's {', '.join(sel.intrinsics)} unknown (to their "
                "characteristic sizes)."
            )
        if sel.not_ranked:
            out.print(f"Not part of the metric: {', '.join(sel.not_ranked)}.")
        if chosen:
            out.print(f"Selected: {chosen}  (licalib calibrate BAG --segments {chosen})")
            if len(sel.selected) > 1 and sel.together is not None:
                weak = short_direction(sel.together.describe(-1, verdict="").text)
                out.print(
                    f"Together: min sv {sel.together.min_singular_value:.3g} (the extrinsic, "
                    f"each window with its own time offset), weakest {weak}"
                )
        else:
            out.print("Selected: none (no window reaches --threshold).")
        stages = ", ".join(f"{k} {v:.1f} s" for k, v in sel.timings.items())
        out.print(f"Stages: {stages}")
    if plot is not None:
        save_selection_plot(sel, plot)
        if not as_json:
            console().print(f"Plot: {plot}")


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {k: _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    return obj
