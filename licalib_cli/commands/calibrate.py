"""``licalib calibrate``: parse options, load the config, run the pipeline, render the result."""

from __future__ import annotations

from enum import Enum
from pathlib import Path
from typing import TYPE_CHECKING

import typer

from licalib_cli.commands.options import (
    INPUT_PANEL,
    BagArgument,
    ConfigOption,
    DurationOption,
    ImuTopicOption,
    Intrinsics,
    LidarTopicOption,
    SetOption,
    StartOption,
    input_overrides,
    intrinsics_overrides,
    settings_of,
)
from licalib_cli.commands.render import console, console_err, render_run
from licalib_cli.config import dump_config, load_config
from licalib_cli.errors import ConfigError, NotConverged, VerdictFailure
from licalib_cli.report.data import report_data_path
from licalib_cli.results import check_not_an_input, prepare_output, write_text_atomic
from licalib_cli.truth import Truth

if TYPE_CHECKING:
    from rich.progress import TaskID

    from licalib_cli.config import CalibConfig
    from licalib_cli.pipeline import CalibrationRun

_IO = INPUT_PANEL
_OUT = "Output"
_MODEL = "Model"


class ModelChoice(str, Enum):
    """``--model`` choices."""

    EVIDENT = "evident"
    CONFIG = "config"
    AUTO = "auto"


def evident_override(model: ModelChoice | None) -> dict[str, bool]:
    """Config override of ``--model`` (none: the config's ``model.add_evident_effects``)."""
    if model is ModelChoice.EVIDENT:
        return {"model.add_evident_effects": True}
    if model is ModelChoice.CONFIG:
        return {"model.add_evident_effects": False}
    return {}


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
        self._task: TaskID | None = None
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


def _check_extra_outputs(
    extra: dict[str, Path | None],
    inputs: list[tuple[str, Path | None]],
    written: dict[str, Path],
) -> None:
    """Refuse, before the run, a report or map path that is an input, another output or a
    map without a point-cloud suffix."""
    from licalib_cli.io.map_writer import check_map_suffix

    taken = dict(written)
    for option, path in extra.items():
        if path is None:
            continue
        if option.startswith("--map"):
            check_map_suffix(path, option)
        example = "report.html" if option == "--report" else "map.ply"
        prepare_output(path, inputs, example)
        for what, other in taken.items():
            if path.resolve() == other.resolve():
                msg = f"{option} {path} is also the output of {what}; give another path."
                raise ConfigError(msg)
        taken[option] = path
    if extra.get("--report") is not None:
        from licalib_cli.plots import pyplot

        pyplot()


def _write_report_outputs(
    run: CalibrationRun,
    cfg: CalibConfig,
    out: Path,
    data_out: Path,
    report: Path | None,
    reference: Truth | None,
    config_text: str,
    map_file: Path | None,
    map_before: Path | None,
) -> None:
    """The report data beside the result, and the report and map files asked for."""
    from licalib_cli.cli import command_line
    from licalib_cli.report import build_report_data, write_report

    assert run.segment is not None
    truth = reference.extrinsic_for(run.result) if reference is not None else None
    data = build_report_data(
        run,
        run.segment,
        cfg,
        truth=truth,
        command_line=command_line(),
        config_text=config_text,
    )
    data.save(data_out)
    console().print(f"Report data: {data_out}")
    if report is not None:
        write_report(report, run.result, data, str(out))
        console().print(f"Report: {report}")
    for path, state, which in (
        (map_file, run.state, "final"),
        (map_before, run.initial.state, "initial"),
    ):
        if path is None:
            continue
        from licalib_cli.io.map_writer import write_map
        from licalib_cli.pipeline.map_export import map_chunks

        count, chunks = map_chunks(run.segment, state, cfg)
        write_map(path, count, chunks)
        console().print(f"Map with the {which} calibration: {path} ({count} points)")


def calibrate_command(
    bag: BagArgument,
    config: ConfigOption = None,
    settings: SetOption = None,
    imu_topic: ImuTopicOption = None,
    lidar_topic: LidarTopicOption = None,
    start: StartOption = None,
    duration: DurationOption = None,
    segments: str | None = typer.Option(
        None,
        "--segments",
        help="Calibrate over several segments in one problem: auto (the best windows by "
        "`licalib select-segments`) or START-END,... in seconds, e.g. 60-75,105-120.",
        rich_help_panel=_IO,
    ),
    model: ModelChoice | None = typer.Option(
        None,
        "--model",
        help="evident (the default, model.add_evident_effects): the config's model section (or "
        "--intrinsics), plus any effect the data show beyond doubt; config: exactly that "
        "section; auto: start from the base model and add the effects the data show (as "
        "`licalib diagnose`; with --segments, what any window shows).",
        rich_help_panel=_MODEL,
    ),
    intrinsics: Intrinsics | None = typer.Option(
        None,
        "--intrinsics",
        help="Also estimate intrinsics: imu (scale, misalignment, gyro rotation), lidar (six "
        "per beam) or all; default: the config's model section (none).",
        rich_help_panel=_MODEL,
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
    report: Path | None = typer.Option(
        None,
        "--report",
        metavar="FILE",
        help="Write the calibration report: one self-contained HTML page (verdict, estimate, "
        "observability, fit, motion, map, provenance).",
        rich_help_panel=_OUT,
    ),
    map_file: Path | None = typer.Option(
        None,
        "--map",
        metavar="FILE",
        help="Write the undistorted map with the final calibration (.ply or .pcd, with "
        "intensity, beam and time per point).",
        rich_help_panel=_OUT,
    ),
    map_before: Path | None = typer.Option(
        None,
        "--map-before",
        metavar="FILE",
        help="Write the map with the initial calibration too (.ply or .pcd).",
        rich_help_panel=_OUT,
    ),
) -> None:
    """Calibrate T_imu_lidar and the time offset from a bag; write the result file."""
    from licalib_cli.pipeline import calibrate

    # Nothing is read or computed before the outputs are known not to overwrite an input.
    config_out = out.with_name(out.stem + ".config.yaml")
    inputs = [("the input bag", bag), ("the config file", config), ("the truth file", truth)]
    prepare_output(out, inputs)
    label = f"The resolved config that calibrate writes next to the result, {config_out},"
    check_not_an_input(config_out, inputs, label)
    data_out = report_data_path(out)
    label = f"The report data that calibrate writes next to the result, {data_out},"
    check_not_an_input(data_out, inputs, label)
    _check_extra_outputs(
        {"--report": report, "--map": map_file, "--map-before": map_before},
        inputs,
        {"-o": out, "the resolved config": config_out, "the report data": data_out},
    )
    if segments is not None:
        from licalib_cli.commands.segments_render import check_window_outputs

        check_window_outputs(out, inputs)
    reference = Truth.load(truth) if truth is not None else None
    cfg = load_config(
        config,
        {
            **input_overrides(imu_topic, lidar_topic, start, duration),
            **intrinsics_overrides(intrinsics),
            **evident_override(model),
        },
        settings_of(settings),
    )
    if model is ModelChoice.AUTO and intrinsics is not None:
        msg = "--model auto chooses the intrinsics itself; drop --intrinsics or use --model config."
        raise ConfigError(msg)
    if segments is not None and (start is not None or duration is not None):
        msg = (
            "--segments chooses the data itself; drop --start/--duration "
            "(select-segments --start/--duration restricts the search)."
        )
        raise ConfigError(msg)
    if plots is not None:
        from licalib_cli.plots import prepare_plots

        prepare_plots(plots)
    if segments is not None:
        from licalib_cli.commands.segments_render import SegmentOutputs, run_segments

        outputs = SegmentOutputs(
            out, config_out, map_file, map_before, report, plots, inputs=tuple(inputs)
        )
        run_segments(bag, cfg, segments, outputs, reference, model is ModelChoice.AUTO)
        return
    progress = RichProgress()
    diagnosis = None
    try:
        if model is ModelChoice.AUTO:
            from licalib_cli.pipeline.diagnose import diagnose

            diagnosis = diagnose(bag, cfg, progress=progress)
            run = diagnosis.final
        else:
            run = calibrate(bag, cfg, progress)
    finally:
        progress.close()
    if diagnosis is not None:
        from licalib_cli.commands.diagnose import render_diagnosis

        render_diagnosis(diagnosis)
    run.result.save(out)
    # With --model auto, the model the diagnosis arrived at: calibrating with it estimates it.
    # With effects added because the data showed them, the model they arrived at.
    config_text = dump_config(
        diagnosis.config
        if diagnosis is not None and diagnosis.config is not None
        else run.config or cfg
    )
    write_text_atomic(config_out, config_text)
    render_run(run, reference)
    console().print(f"Result: {out}  (resolved config: {config_out})")
    _write_report_outputs(
        run, cfg, out, data_out, report, reference, config_text, map_file, map_before
    )
    if plots is not None:
        from licalib_cli.plots import save_plots

        files = save_plots(run, plots)
        console().print("Plots: " + ", ".join(str(f) for f in files))
    # The result is written for inspection, but scripts must not take a failed one.
    if run.checks.exit_status == "not converged":
        msg = f"The calibration did not converge; the result in {out} is not trustworthy."
        raise NotConverged(msg)
    if run.checks.exit_status == "fail":
        msg = f"The verdict is FAIL; the result in {out} is for inspection only."
        raise VerdictFailure(msg)
