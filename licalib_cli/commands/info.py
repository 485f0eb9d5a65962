"""``licalib info BAG``: what is in a bag and whether licalib can use it.

Thin command: parse options -> ``load_config`` -> :func:`licalib_cli.inspection.inspect_bag`
-> render (rich tables, or one JSON object with ``--json``).

Exit codes: 0 when the segment is usable; otherwise the code of the first fatal problem
(2 bag unreadable, 3 topic problem, 4 unusable data, 5 timestamp problem, 6 configuration,
7 segment too short), the same as ``calibrate`` would stop with, and its one-sentence message
on standard error. With ``--json`` one JSON object with ``problems`` is printed to standard
output whatever the outcome (an unreadable bag or an invalid option included).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer
from rich.markup import escape
from rich.table import Table

from licalib_cli.commands.options import SetOption, input_overrides, settings_of
from licalib_cli.commands.render import console
from licalib_cli.config import load_config
from licalib_cli.errors import LicalibError

if TYPE_CHECKING:
    from licalib_cli.inspection import BagReport


def info_command(
    bag: Annotated[
        Path,
        typer.Argument(
            metavar="BAG",
            help="ROS1 .bag (or folder of split .bag files), ROS2 bag folder, or .db3/.mcap.",
        ),
    ],
    imu_topic: Annotated[
        str | None, typer.Option("--imu-topic", help="sensor_msgs/Imu topic.")
    ] = None,
    lidar_topic: Annotated[
        str | None, typer.Option("--lidar-topic", help="sensor_msgs/PointCloud2 topic.")
    ] = None,
    config: Annotated[Path | None, typer.Option("--config", "-c", help="YAML config file.")] = None,
    settings: SetOption = None,
    as_json: Annotated[
        bool, typer.Option("--json", help="Print one JSON object for scripts.")
    ] = False,
    start: Annotated[
        float | None,
        typer.Option("--start", help="Segment start, seconds after the first message."),
    ] = None,
    duration: Annotated[
        float | None, typer.Option("--duration", help="Segment length, seconds.")
    ] = None,
) -> None:
    """Show topics, rates, gaps, point layout, IMU units and clock offsets of a bag."""
    from licalib_cli.inspection import error_report, inspect_bag

    try:
        cfg = load_config(
            config,
            input_overrides(imu_topic, lidar_topic, start, duration),
            settings_of(settings),
        )
        report = inspect_bag(bag, cfg)
    except LicalibError as err:
        if as_json:
            typer.echo(json.dumps(error_report(bag, str(err), err.exit_code), indent=2))
        raise
    if as_json:
        typer.echo(json.dumps(report.to_dict(), indent=2))
    else:
        render_report(report)
    problem = report.error()
    if problem is not None:
        raise problem


def _fmt(value: object, fmt: str = "") -> str:
    if value is None:
        return "-"
    return format(value, fmt) if fmt else str(value)


def _problem_cell(n: int, bad: bool = True) -> str:
    if n == 0:
        return "0"
    return f"[red]{n}[/red]" if bad else f"[yellow]{n}[/yellow]"


def render_report(report: BagReport) -> None:
    """Print the report as rich tables on standard output."""
    out = console()
    seg = f"{report.segment_start_s:g} s"
    seg += f" + {report.segment_duration_s:g} s" if report.segment_duration_s else " to the end"
    out.print(
        f"[bold]{escape(report.path)}[/bold]  {report.format}, {report.duration_s:.3f} s, "
        f"{len(report.topics)} topics; segment: {seg}"
    )
    roles = {}
    unreadable = {}
    for role, stream in (("IMU", report.imu), ("LiDAR", report.lidar)):
        if stream is not None:
            roles[stream.topic] = role
            unreadable[stream.topic] = stream.unreadable
    topics = Table(title="Topics", title_justify="left")
    for col, just in (
        ("topic", "left"),
        ("type", "left"),
        ("count", "right"),
        ("rate (Hz)", "right"),
        ("used as", "left"),
    ):
        topics.add_column(col, justify=just)  # type: ignore[arg-type]
    for t in report.topics:
        count = str(t.count)
        if unreadable.get(t.name):
            count += f" ([yellow]{unreadable[t.name]} unreadable[/yellow])"
        topics.add_row(escape(t.name), t.msgtype, count, f"{t.rate_hz:.1f}", roles.get(t.name, ""))
    out.print(topics)

    if report.imu is not None:
        i = report.imu
        imu = Table(title=f"IMU {escape(i.topic)}", title_justify="left", show_header=False)
        imu.add_column("key")
        imu.add_column("value")
        imu.add_row("samples", f"{i.count} over {i.duration_s:.3f} s")
        imu.add_row("rate", f"{i.rate_hz:.1f} Hz")
        evidence = f"p99 |w| {i.gyro_p99:.3g}"
        if i.gyro_gravity_factor is not None:
            evidence += f", gravity turns at {i.gyro_gravity_factor:.3g} x w"
        if i.gyro_unit_basis is not None:
            evidence += f"; {i.gyro_unit_basis}"
        imu.add_row("gyro unit", f"{i.gyro_unit} ({i.gyro_unit_source}, {evidence})")
        imu.add_row(
            "accel unit",
            f"{i.accel_unit} ({i.accel_unit_source}, median |a| {i.accel_norm_median:.3f})",
        )
        imu.add_row(
            "gaps > 5x period", f"{_problem_cell(i.gaps)} (largest {i.max_gap_s * 1e3:.1f} ms)"
        )
        imu.add_row("stamps going backwards", _problem_cell(i.backwards))
        imu.add_row("duplicated stamps", _problem_cell(i.duplicates))
        if i.unreadable or i.dropped:
            imu.add_row("unreadable messages", _problem_cell(i.unreadable, False))
            imu.add_row("samples with NaN/inf", _problem_cell(i.dropped, False))
        if i.excitation is not None:
            e = i.excitation
            given = f" (gyro unit assumed {i.gyro_unit})" if i.gyro_unit_source == "assumed" else ""
            imu.add_row(
                "rotation RMS x, y, z",
                ", ".join(f"{v:.1f}" for v in e.rotation_rms_deg_s) + " deg/s" + given,
            )
            imu.add_row(
                "rotation axes",
                "principal axes "
                + " : ".join(f"{v:.1f}" for v in e.rotation_axis_strength)
                + " deg/s RMS",
            )
            imu.add_row(
                "accel std x, y, z", ", ".join(f"{v:.2f}" for v in e.accel_std_m_s2) + " m/s^2"
            )
            colour = "green" if e.ok else "yellow"
            imu.add_row("excitation", f"[{colour}]{escape(e.summary)}[/]")
            if e.imu_intrinsics_note:
                colour = "green" if e.gravity_turn_ok else "yellow"
                note = f"[{colour}]{escape(e.imu_intrinsics_note)}[/]"
                imu.add_row("tilt (IMU intrinsics)", note)
        out.print(imu)

    if report.lidar is not None:
        li = report.lidar
        lid = Table(title=f"LiDAR {escape(li.topic)}", title_justify="left", show_header=False)
        lid.add_column("key")
        lid.add_column("value")
        lid.add_row("clouds", f"{li.count} over {li.duration_s:.3f} s")
        lid.add_row("rate", f"{li.rate_hz:.2f} Hz")
        if li.fields:
            order = "big-endian" if li.is_bigendian else "little-endian"
            lid.add_row("fields", escape(", ".join(li.fields)))
            lid.add_row("point step", f"{li.point_step} bytes, {order}")
            shape = f"organised {li.height} x {li.width}" if li.height > 1 else "unorganised"
            lid.add_row(
                "points per scan",
                f"{li.points_per_scan} ({shape}), {li.valid_points_per_scan} valid",
            )
            if li.time_field is not None:
                timing = f"'{li.time_field}' in {li.time_unit}, {li.time_reference}"
            else:
                timing = f"none: estimated from {li.time_estimation}"
            lid.add_row("per-point time", timing)
            lid.add_row("header stamp at sweep", _fmt(li.stamp_position))
            src = f"field '{li.ring_field}'" if li.ring_field else "recovered from elevation"
            lid.add_row("beams", f"{li.beams} ({src})")
            if li.scan_pattern == "non_repetitive":
                lid.add_row(
                    "scan pattern",
                    f"non-repetitive: a beam's points spread {li.elevation_spread_deg:.1f} deg "
                    "in elevation (lines, not rings); no per-beam intrinsics",
                )
            elif li.scan_pattern == "spinning":
                lid.add_row(
                    "scan pattern",
                    f"spinning: a ring's points spread {li.elevation_spread_deg:.2f} deg in "
                    "elevation",
                )
            skipped = sum(li.clouds_skipped.values())
            detail = ", ".join(f"{k}: {v}" for k, v in li.clouds_skipped.items())
            lid.add_row(
                "unusable clouds",
                f"{_problem_cell(skipped, False)} of {li.clouds_checked} checked"
                + (f" ({detail})" if detail else ""),
            )
        lid.add_row(
            "gaps > 2.5x period",
            f"{_problem_cell(li.gaps, False)} (largest {li.max_gap_s * 1e3:.1f} ms)",
        )
        lid.add_row("stamps going backwards", _problem_cell(li.backwards))
        lid.add_row("duplicated stamps", _problem_cell(li.duplicates))
        if li.unreadable:
            lid.add_row("unreadable messages", _problem_cell(li.unreadable, False))
        out.print(lid)

    if report.clock_offset_s is not None:
        out.print(
            f"Clock difference IMU - LiDAR (coarse, from record times): "
            f"{round(report.clock_offset_s, 6) + 0.0:+.6f} s"
        )
    if report.clock_rate is not None:
        r = report.clock_rate
        out.print(
            f"Clock rate IMU - LiDAR (stamps against record times): {1e6 * r.rate:+.1f} +/- "
            f"{1e6 * r.sigma:.1f} ppm, t_imu - t_lidar moving {1e3 * r.moves_s:.3f} ms over "
            f"{r.span_s:.0f} s"
        )
    if report.factory_extrinsic is not None:
        f = report.factory_extrinsic
        from licalib_cli.inspection import factory_extrinsic_dict

        d = factory_extrinsic_dict(f)
        t_text = ", ".join(f"{v:+.6f}" for v in d["translation"])
        rpy = ", ".join(f"{v:.2f}" for v in d["rotation_rpy_deg"])
        q = ", ".join(f"{v:.4f}" for v in d["rotation_quaternion"])
        who = f" of {escape(f.sensor)}" if f.sensor else ""
        out.print(
            f"Factory extrinsic{who} (Ouster metadata on {escape(f.topic)}, clouds in "
            f"{f.cloud_frame}): T_imu_lidar t = ({t_text}) m, rpy = ({rpy}) deg, "
            f"quaternion xyzw = ({q}); p_imu = R p_lidar + t"
        )
    for note in report.notes:
        out.print(f"[cyan]note[/cyan]: {escape(note)}")
    for p in report.problems:
        tag = "[red]error[/red]" if p.fatal else "[yellow]warning[/yellow]"
        out.print(f"{tag}: {escape(p.message)}")
    if report.usable:
        out.print("[green]usable[/green]")
