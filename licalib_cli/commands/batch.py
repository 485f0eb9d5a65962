"""``licalib batch``: parse the inputs, one call to :func:`licalib_cli.batch.run_batch`, render
the fleet summary (rich tables, or one JSON object with ``--json``)."""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

import typer
from rich.console import Console
from rich.table import Table

from licalib_cli.commands.options import SetOption, settings_of
from licalib_cli.commands.render import VERDICT_COLOURS, console, console_err
from licalib_cli.errors import BatchIncomplete

if TYPE_CHECKING:
    from rich.progress import TaskID

_IO = "Input"
_OUT = "Output"
_CLUSTER = "Cluster"
_FILE_WIDTH = 180
"""Width of the tables when standard output is not a terminal (a log file, a pipe)."""


class BatchProgress:
    """Bags done of those to calibrate, with ``N running, N failed``, on standard error (only
    when it is a terminal); the log lines of finished bags print above it."""

    def __init__(self) -> None:
        from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

        self._enabled = console_err().is_terminal
        self._progress = Progress(
            TextColumn("{task.description:<12}"),
            BarColumn(),
            TextColumn("{task.completed}/{task.total} done,"),
            TextColumn("{task.fields[note]}"),
            TimeElapsedColumn(),
            console=console_err(),
            transient=True,
        )
        self._task: TaskID | None = None
        self._started = False

    def stage(self, name: str, total: int | None = None) -> None:
        if not self._enabled:
            return
        if not self._started:
            self._progress.start()
            self._started = True
        self._task = self._progress.add_task(name, total=total, note="")

    def advance(self, done: int, total: int | None = None) -> None:
        if self._enabled and self._task is not None:
            self._progress.update(self._task, completed=done, total=total)

    def note(self, text: str) -> None:
        if self._enabled and self._task is not None:
            self._progress.update(self._task, note=text)

    def close(self) -> None:
        if self._started:
            self._progress.stop()
            self._started = False


def _num(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def _plain(row: Any) -> dict[str, Any]:
    return {k: _num(v) if isinstance(v, float) else v for k, v in row.to_dict().items()}


def report_dict(report: Any) -> dict[str, Any]:
    """The report as plain data (the ``--json`` output; NaN and inf as null)."""
    return {
        "out_dir": str(report.out_dir),
        "summary": str(report.out_dir / "summary.csv"),
        "counts": {
            "bags": len(report.bags),
            "calibrated": report.count("calibrated"),
            "up_to_date": report.count("up to date"),
            "failed": report.count("failed"),
            "verdict_fail": report.verdict_fail,
        },
        "workers": report.workers,
        "wall_s": round(report.wall_s, 2),
        "bags": [_plain(b) for b in report.bags],
        "rigs": [_plain(r) for r in report.rigs],
    }


def _vec(values: tuple[float, ...], scale: float, digits: int, sign: bool = True) -> str:
    fmt = f"{{:{'+' if sign else ''}.{digits}f}}"
    return " ".join("-" if math.isinf(v) else fmt.format(v * scale) for v in values)


def _bags_table(report: Any) -> Table:
    table = Table(title="Bags: T_imu_lidar (p_imu = R p_lidar + t), time offset, 1-sigma")
    for name in ("rig", "bag", "recorded (UTC)", "result"):
        table.add_column(name)
    for name in ("t (mm)", "1-sigma (mm)", "rpy (deg)", "1-sigma (deg)", "dt (ms)", "time (s)"):
        table.add_column(name, justify="right", no_wrap=True)
    colour = VERDICT_COLOURS
    for b in report.bags:
        if b.verdict:
            status = f"[{colour[b.verdict]}]{b.verdict.upper()}[/]"
            if b.status == "up to date":
                status += " (kept)"
            if b.differs:
                status += " [red]differs[/]"
            t = (b.t_x_m, b.t_y_m, b.t_z_m)
            ts = (b.t_x_std_m, b.t_y_std_m, b.t_z_std_m)
            r = (b.roll_deg, b.pitch_deg, b.yaw_deg)
            rs = (b.rot_x_std_deg, b.rot_y_std_deg, b.rot_z_std_deg)
            dt = f"{1e3 * b.time_offset_s:+.2f}"
            if math.isfinite(b.time_offset_std_s):
                dt += f" ± {1e3 * b.time_offset_std_s:.2f}"
            cells = [
                _vec(t, 1e3, 1),
                _vec(ts, 1e3, 1, sign=False),
                _vec(r, 1.0, 3),
                _vec(rs, 1.0, 3, sign=False),
                dt,
            ]
        else:
            status = "[red]failed[/]" if b.status == "failed" else b.status
            cells = ["", "", "", "", ""]
        seconds = "" if math.isnan(b.calibration_s) else f"{b.calibration_s:.1f}"
        recorded = b.recorded_utc.replace("T", " ")[:16]
        table.add_row(b.rig, b.bag, recorded, status, *cells, seconds)
    return table


def _rigs_table(report: Any) -> Table:
    table = Table(title="Rigs: spread of the usable calibrations (max - min) and bags that differ")
    table.add_column("rig")
    table.add_column("bags", justify="right")
    table.add_column("recorded (UTC)")
    for name in ("t (mm)", "rotation (deg)", "dt (ms)"):
        table.add_column(name, justify="right", no_wrap=True)
    table.add_column("differ beyond their sigmas")
    for r in report.rigs:
        counts = f"{r.usable} of {r.bags}"
        if r.usable == 0:
            table.add_row(r.rig, counts, "", "", "", "", "")
            continue
        span = r.first_recorded_utc[:10]
        if r.last_recorded_utc[:10] != span:
            span += " .. " + r.last_recorded_utc[:10]
        t = (r.spread_t_x_mm, r.spread_t_y_mm, r.spread_t_z_mm)
        rot = (r.spread_rot_x_deg, r.spread_rot_y_deg, r.spread_rot_z_deg)
        differing = ", ".join(r.differing) if r.differing else ("none" if r.usable > 1 else "")
        table.add_row(
            r.rig,
            counts,
            span,
            _vec(t, 1.0, 1, sign=False),
            _vec(rot, 1.0, 3, sign=False),
            f"{r.spread_time_offset_ms:.2f}",
            f"[red]{differing}[/]" if r.differing else differing,
        )
    return table


def render_report(report: Any) -> None:
    """The bags and rigs tables, each failure's sentence and each difference, the totals."""
    out = console()
    if not out.is_terminal:  # a log file or a pipe: no need to wrap at 80 columns
        out = Console(width=_FILE_WIDTH, highlight=False)
    out.print(_bags_table(report))
    out.print(_rigs_table(report))
    for b in report.bags:
        if b.status == "failed":
            out.print(f"[red]Failed[/] {b.rig}/{b.bag}: {b.error}")
        if b.differs:
            out.print(f"[red]Differs[/] {b.rig}/{b.bag}: {b.difference}")
    out.print(
        f"{len(report.bags)} bags: {report.count('calibrated')} calibrated, "
        f"{report.count('up to date')} up to date (kept), {report.count('failed')} failed, "
        f"{report.verdict_fail} with verdict FAIL; {report.wall_s:.1f} s"
        + (f" on {report.workers} workers" if report.workers else "")
        + f". Summary: {report.out_dir / 'summary.csv'}, {report.out_dir / 'rigs.csv'}"
    )


def batch_command(
    inputs: list[str] = typer.Argument(
        ...,
        metavar="MANIFEST_OR_GLOB",
        help="Bags (files or bag folders), glob patterns such as 'fleet/*/*.bag' (quoted), or "
        "manifests (.csv or .yaml: path, rig, config, start, duration, imu_topic, lidar_topic, "
        "segments).",
        show_default=False,
    ),
    out: Path = typer.Option(
        ...,
        "--out",
        "-o",
        help="Output folder: OUT/<rig>/<bag-stem>.yaml per bag, OUT/summary.csv, OUT/rigs.csv.",
        rich_help_panel=_OUT,
    ),
    config: Path | None = typer.Option(
        None,
        "--config",
        "-c",
        help="YAML config of every bag whose manifest row names none.",
        rich_help_panel=_IO,
    ),
    settings: SetOption = None,
    segments: str | None = typer.Option(
        None,
        "--segments",
        help="Calibrate every bag whose manifest row gives no segments over several segments "
        "in one problem, as calibrate --segments: auto (the best windows) or START-END,... in "
        "seconds.",
        rich_help_panel=_IO,
    ),
    scheduler: str | None = typer.Option(
        None,
        "--scheduler",
        metavar="ADDRESS",
        help="A running Dask scheduler, e.g. tcp://10.0.0.5:8786 (its workers must see the "
        "bags at the same paths); default: a local cluster.",
        rich_help_panel=_CLUSTER,
    ),
    workers: int | None = typer.Option(
        None,
        "--workers",
        help="Worker processes of the local cluster (default: one per core).",
        rich_help_panel=_CLUSTER,
    ),
    retries: int = typer.Option(
        2,
        "--retries",
        help="How often a bag whose task raised or whose worker died is tried again.",
        rich_help_panel=_CLUSTER,
    ),
    as_json: bool = typer.Option(
        False, "--json", help="Print one JSON object for scripts.", rich_help_panel=_OUT
    ),
) -> None:
    """Calibrate many bags on Dask (locally or on a cluster), resumably; summarise the fleet."""
    from licalib_cli.batch import read_inputs, run_batch

    jobs = read_inputs(inputs, config, segments)
    report = run_batch(
        jobs,
        out,
        scheduler=scheduler,
        workers=workers,
        retries=retries,
        progress=BatchProgress(),
        quiet_dask=not logging.getLogger("licalib_cli").isEnabledFor(logging.DEBUG),
        settings=settings_of(settings),
    )
    if as_json:
        typer.echo(json.dumps(report_dict(report), indent=2))
    else:
        render_report(report)
    if not report.complete:
        raise BatchIncomplete(_incomplete(report))


def _incomplete(report: Any) -> str:
    """One sentence: how many bags have no usable result, and where to read why."""
    n, failed, fail = len(report.bags), report.count("failed"), report.verdict_fail
    if failed:
        text = f"{failed} of {n} bags failed"
        if fail:
            text += f" and {fail} got the verdict FAIL (written for inspection only)"
    else:
        text = f"{fail} of {n} bags got the verdict FAIL (written for inspection only)"
    return (
        f"{text}; every other result is written and {report.out_dir / 'summary.csv'} gives "
        "each failure's sentence (run the same command again to retry the failed bags)."
    )
