"""``licalib calibrate``: parse options, load the config, run the pipeline, render the result."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import typer
from rich.table import Table

from licalib_cli.commands.render import console, console_err
from licalib_cli.config import dump_config, load_config
from licalib_cli.results import prepare_output, write_text_atomic

_IO = "Input"
VERDICT_FAIL_EXIT_CODE = 9
"""Exit code when the calibration ran but its verdict is ``fail``."""
_OUT = "Output"


class RichProgress:
    """Stage progress on standard error (only when it is a terminal)."""

    def __init__(self) -> None:
        from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

        self._enabled = console_err().is_terminal
        self._progress = Progress(
            TextColumn("{task.description:<16}"),
            BarColumn(),
            TextColumn("{task.completed}/{task.total}"),
            TimeElapsedColumn(),
            console=console_err(),
            transient=True,
        )
        self._task: int | None = None
        if self._enabled:
            self._progress.start()

    def stage(self, name: str, total: int | None = None) -> None:
        if self._enabled:
            if self._task is not None:
                self._progress.update(self._task, visible=False)
            self._task = self._progress.add_task(name, total=total)

    def advance(self, done: int, total: int | None = None) -> None:
        if self._enabled and self._task is not None:
            self._progress.update(self._task, completed=done, total=total)

    def note(self, text: str) -> None:
        return None

    def close(self) -> None:
        if self._enabled:
            self._progress.stop()


def calibrate_command(
    bag: Path = typer.Argument(
        ...,
        metavar="BAG",
        help="ROS1 .bag (or folder of split bags), ROS2 bag folder, .db3 or .mcap.",
    ),
    config: Path | None = typer.Option(
        None, "--config", "-c", help="YAML config.", rich_help_panel=_IO
    ),
    imu_topic: str | None = typer.Option(
        None, "--imu-topic", help="sensor_msgs/Imu topic.", rich_help_panel=_IO
    ),
    lidar_topic: str | None = typer.Option(
        None, "--lidar-topic", help="sensor_msgs/PointCloud2 topic.", rich_help_panel=_IO
    ),
    start: float | None = typer.Option(
        None, "--start", help="Seconds after the bag start.", rich_help_panel=_IO
    ),
    duration: float | None = typer.Option(
        None, "--duration", help="Seconds of data to use.", rich_help_panel=_IO
    ),
    out: Path = typer.Option(
        Path("calibration.yaml"),
        "--out",
        "-o",
        help="Result file (schema v1).",
        rich_help_panel=_OUT,
    ),
    truth: Path | None = typer.Option(
        None, "--truth", help="A truth.yaml to compare with (simulated bags).", rich_help_panel=_OUT
    ),
    plots: Path | None = typer.Option(
        None,
        "--plots",
        metavar="DIR",
        help="Write figures (fit, observability) as PNG files into this folder.",
        rich_help_panel=_OUT,
    ),
) -> None:
    """Calibrate T_imu_lidar and the time offset from a bag; write the result file."""
    from licalib_cli.pipeline import calibrate

    cfg = load_config(
        config,
        {
            "imu.topic": imu_topic,
            "lidar.topic": lidar_topic,
            "bag.start_s": start,
            "bag.duration_s": duration,
        },
    )
    prepare_output(out)
    if plots is not None:
        from licalib_cli.plots import prepare_plots

        prepare_plots(plots)
    progress = RichProgress()
    try:
        run = calibrate(bag, cfg, progress)
    finally:
        progress.close()
    run.result.save(out)
    config_out = out.with_name(out.stem + ".config.yaml")
    write_text_atomic(config_out, dump_config(cfg))
    render_run(run, truth)
    console().print(f"Result: {out}  (resolved config: {config_out})")
    if plots is not None:
        from licalib_cli.plots import save_plots

        files = save_plots(run, plots)
        console().print("Plots: " + ", ".join(str(f) for f in files))
    if run.verdict.status == "fail":
        # The result is written for inspection, but scripts must not take it.
        raise typer.Exit(code=VERDICT_FAIL_EXIT_CODE)


def _fmt(v: float, unit: str, scale: float = 1.0, digits: int = 4) -> str:
    if not np.isfinite(v):
        return "unobservable"
    return f"{v * scale:.{digits}f} {unit}"


def render_run(run: object, truth_path: Path | None) -> None:
    """Print the result table, the observability findings, the verdict and the stage timings."""
    from licalib_cli.results import CalibrationResult

    r = run.result  # type: ignore[attr-defined]
    ext = r.extrinsic
    unc = r.extra["uncertainty"]
    shift = float(r.extra.get("recording", {}).get("lidar_clock_shift_s", 0.0))
    truth = None
    if truth_path is not None:
        true = CalibrationResult.load(truth_path)
        clock = true.extra.get("simulation", {}).get("clock", {})
        truth = true.extrinsic.on_shifted_clock(
            float(clock.get("lidar_clock_offset_s", 0.0)), shift
        )
    table = Table(
        title="T_imu_lidar (p_imu = R p_lidar + t) and time offset (t_imu = t_lidar + dt)"
    )
    table.add_column("parameter")
    table.add_column("estimate", justify="right")
    table.add_column("1-sigma", justify="right")
    if truth is not None:
        table.add_column("truth", justify="right")
        table.add_column("error", justify="right")
    rpy = r.to_dict()["extrinsic"]["rotation_rpy_deg"]
    truth_rpy = (
        CalibrationResult.load(truth_path).to_dict()["extrinsic"]["rotation_rpy_deg"]
        if truth_path
        else None
    )
    for i, axis in enumerate("xyz"):
        row = [
            f"t_{axis}",
            f"{ext.translation[i]:+.4f} m",
            _fmt(unc["translation_std_m"][i], "mm", 1e3, 2),
        ]
        if truth is not None:
            row += [
                f"{truth.translation[i]:+.4f} m",
                f"{1e3 * (ext.translation[i] - truth.translation[i]):+.2f} mm",
            ]
        table.add_row(*row)
    for i, name in enumerate(("roll", "pitch", "yaw")):
        row = [name, f"{rpy[i]:+.4f} deg", _fmt(unc["rotation_std_deg"][i], "deg", 1.0, 4)]
        if truth_rpy is not None:
            row += [f"{truth_rpy[i]:+.4f} deg", f"{rpy[i] - truth_rpy[i]:+.4f} deg"]
        table.add_row(*row)
    row = [
        "time offset",
        f"{1e3 * ext.time_offset_s:+.3f} ms",
        _fmt(unc["time_offset_std_s"], "ms", 1e3, 3),
    ]
    if truth is not None:
        row += [
            f"{1e3 * truth.time_offset_s:+.3f} ms",
            f"{1e3 * (ext.time_offset_s - truth.time_offset_s):+.3f} ms",
        ]
    table.add_row(*row)
    out = console()
    out.print(table)
    if shift:
        out.print(
            f"The LiDAR clock was {-shift:+.9f} s off the IMU clock and was shifted before "
            f"calibrating: t_imu = t_lidar + ({shift:+.9f} s) + time offset"
            + ("; the truth is shown on the same footing." if truth is not None else ".")
        )
    if truth is not None:
        err = ext.error_to(truth)
        out.print(
            f"Error against truth: translation {1e3 * err['translation_m']:.2f} mm, rotation "
            f"{err['rotation_deg']:.4f} deg, time offset {1e3 * err['time_offset_s']:.3f} ms"
        )
    obs = r.extra["observability"]
    for text in obs["unobservable"]:
        out.print(f"[yellow]Not observable:[/] {text}")
    verdict = run.verdict  # type: ignore[attr-defined]
    colour = {"pass": "green", "warn": "yellow", "fail": "red"}[verdict.status]
    out.print(f"Verdict: [bold {colour}]{verdict.status.upper()}[/]")
    for reason in verdict.reasons:
        out.print(f"  - {reason}")
    timings = run.timings  # type: ignore[attr-defined]
    total = sum(timings.values())
    out.print(
        "Stages: "
        + ", ".join(f"{k} {v:.1f} s" for k, v in timings.items())
        + f" (total {total:.1f} s)"
    )
