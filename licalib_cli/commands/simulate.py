"""``licalib simulate``: write a synthetic bag and its ground truth ``truth.yaml``.

Thin wiring: options -> :class:`~licalib_cli.simulation.SimulationSpec` ->
:func:`~licalib_cli.simulation.simulate` -> a short summary on stdout whose last line is the
bag's path (so scripts can capture it).
"""

from __future__ import annotations

import shlex
from enum import Enum
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from licalib_cli.io.writer import BagFormat
from licalib_cli.simulation.effects import LEGACY_EFFECT_NAMES, Effect
from licalib_cli.simulation.spec import (
    DEFAULT_G_SENSITIVITY_DPS_PER_G,
    EFFECT_BIAS_WALK_SCALE,
    EFFECT_IMU_CLOCK_DRIFT_PPM,
    EFFECT_POINT_TIME_ERROR,
    IntrinsicsMode,
    LidarKind,
    LidarStamp,
    Mounting,
    Scenario,
    SimulationSpec,
)

if TYPE_CHECKING:
    from licalib_cli.simulation.simulate import SimulationOutput

_SCENE = "Scenario"
_SENSORS = "Sensors"
_CALIB = "Extrinsic, time and intrinsics"
EffectName = Enum(  # type: ignore[misc]
    "EffectName",
    {name: name for name in [*(e.value for e in Effect), *LEGACY_EFFECT_NAMES]},
    type=str,
)
"""``--effect`` choices: every effect by name, and the earlier names."""

_IMU = "IMU noise"
_EFFECTS = "Hidden effects (the candidates of licalib diagnose)"
_OUT = "Output"


def _command_line(ctx: typer.Context) -> str:
    """The options given on the command line, in a canonical order."""
    words = ["licalib", "simulate"]
    for param in ctx.command.params:
        name = param.name or ""
        source = ctx.get_parameter_source(name)
        if getattr(source, "name", None) != "COMMANDLINE":
            continue
        value = ctx.params.get(name)
        if getattr(param, "param_type_name", "") == "argument":
            words.append(str(value))
            continue
        flag = max(param.opts, key=len)
        if getattr(param, "is_flag", False):
            if value:
                words.append(flag)
            continue
        values = value if isinstance(value, (list, tuple)) else [value]
        if getattr(param, "multiple", False):
            for v in values:
                words += [flag, str(getattr(v, "value", v))]
        else:
            words += [flag, *(str(getattr(v, "value", v)) for v in values)]
    return " ".join(shlex.quote(w) for w in words)


def simulate_command(
    ctx: typer.Context,
    out_dir: Annotated[
        Path,
        typer.Argument(metavar="OUT_DIR", help="Output folder for the bag and truth.yaml."),
    ],
    scenario: Annotated[
        Scenario, typer.Option("--scenario", help="Motion of the rig.", rich_help_panel=_SCENE)
    ] = Scenario.SINUSOID,
    duration: Annotated[
        float | None,
        typer.Option(
            "--duration", help="Seconds (default: 10; walk: 120).", rich_help_panel=_SCENE
        ),
    ] = None,
    seed: Annotated[
        int, typer.Option("--seed", help="Seed of every random draw.", rich_help_panel=_SCENE)
    ] = 0,
    noise_seed: Annotated[
        int | None,
        typer.Option(
            "--noise-seed",
            help="Seed of the sensor noise alone (default: --seed): new noise for the same "
            "motion, mounting and intrinsics.",
            rich_help_panel=_SCENE,
        ),
    ] = None,
    mounting: Annotated[
        Mounting, typer.Option("--mounting", help="Figure-8 mounting case.", rich_help_panel=_SCENE)
    ] = Mounting.A,
    tilt_deg: Annotated[
        float,
        typer.Option(
            "--tilt-deg",
            help="Shake only: add a slow tilt of this amplitude about each horizontal axis, deg "
            "(gravity seen from attitudes tens of degrees apart).",
            rich_help_panel=_SCENE,
        ),
    ] = 0.0,
    lidar: Annotated[
        LidarKind,
        typer.Option(
            "--lidar",
            help="LiDAR model; mid360: a non-repetitive Livox Mid-360-like scanner (livox_ros_"
            "driver2 clouds, no per-beam intrinsics, its built-in IMU in g); avia: the same with "
            "a forward-looking Livox Avia-like rosette (70.4 x 77.2 deg).",
            rich_help_panel=_SENSORS,
        ),
    ] = LidarKind.VLP16,
    lidar_rate: Annotated[
        float, typer.Option("--lidar-rate", help="Sweeps per second.", rich_help_panel=_SENSORS)
    ] = 10.0,
    imu_rate: Annotated[
        float, typer.Option("--imu-rate", help="IMU samples per second.", rich_help_panel=_SENSORS)
    ] = 400.0,
    range_noise: Annotated[
        float | None,
        typer.Option(
            "--range-noise",
            help="Range noise sigma, m (default: 0.01 Velodyne, 0.015 Ouster, 0.02 Livox).",
            rich_help_panel=_SENSORS,
        ),
    ] = None,
    azimuth_resolution_deg: Annotated[
        float | None,
        typer.Option(
            "--azimuth-resolution-deg",
            help="Thin the sweep to about this azimuth step (small bags).",
            rich_help_panel=_SENSORS,
        ),
    ] = None,
    lidar_stamp: Annotated[
        LidarStamp,
        typer.Option(
            "--lidar-stamp",
            help="Velodyne header stamp at the first (times >= 0) or last firing (times <= 0).",
            rich_help_panel=_SENSORS,
        ),
    ] = LidarStamp.START,
    dropout: Annotated[
        float,
        typer.Option(
            "--dropout", help="Probability of a ray without return.", rich_help_panel=_SENSORS
        ),
    ] = 0.001,
    translation: Annotated[
        tuple[float, float, float],
        typer.Option(
            "--translation",
            metavar="X Y Z",
            help="t of T_imu_lidar (LiDAR origin in the IMU frame), m, three numbers apart "
            "(--translation 0.3 -0.15 0.05).",
            show_default="0.3 0.15 0.05",
            rich_help_panel=_CALIB,
        ),
    ] = (0.3, 0.15, 0.05),
    rpy_deg: Annotated[
        tuple[float, float, float] | None,
        typer.Option(
            "--rpy-deg",
            metavar="ROLL PITCH YAW",
            help="Rotation of T_imu_lidar, R = Rz(yaw) Ry(pitch) Rx(roll), deg (default: 1 2 5; "
            "avia: 1 2 95, its forward view along the IMU's +y).",
            rich_help_panel=_CALIB,
        ),
    ] = None,
    random_extrinsic: Annotated[
        bool,
        typer.Option(
            "--random-extrinsic",
            help="Draw any rotation (incl. 90/180 deg flips) and |t| <= 0.5 m.",
            rich_help_panel=_CALIB,
        ),
    ] = False,
    time_offset: Annotated[
        float,
        typer.Option(
            "--time-offset", help="t_imu = t_lidar + time_offset, s.", rich_help_panel=_CALIB
        ),
    ] = 0.0,
    random_time_offset: Annotated[
        bool,
        typer.Option(
            "--random-time-offset",
            help="Draw the time offset uniformly within +-50 ms from the seed.",
            rich_help_panel=_CALIB,
        ),
    ] = False,
    lidar_clock_offset: Annotated[
        float,
        typer.Option(
            "--lidar-clock-offset",
            help="Whole-bag shift of the LiDAR clock (LiDAR minus IMU), s.",
            rich_help_panel=_CALIB,
        ),
    ] = 0.0,
    record_delay: Annotated[
        float,
        typer.Option(
            "--record-delay-ms",
            help="Mean transport delay of the messages, ms: record times are the true times "
            "plus exponential delays, in order per topic (default 0: recorded at the true time).",
            rich_help_panel=_CALIB,
        ),
    ] = 0.0,
    intrinsics: Annotated[
        IntrinsicsMode,
        typer.Option(
            "--intrinsics",
            help="Ideal sensors or intrinsics drawn from the paper's table.",
            rich_help_panel=_CALIB,
        ),
    ] = IntrinsicsMode.RANDOM,
    intrinsics_scale: Annotated[
        float,
        typer.Option(
            "--intrinsics-scale",
            help="Multiply every std of the random intrinsics.",
            rich_help_panel=_CALIB,
        ),
    ] = 1.0,
    intrinsics_file: Annotated[
        Path | None,
        typer.Option(
            "--intrinsics-file",
            help="Take imu_intrinsics/lidar_intrinsics from this result or truth YAML.",
            rich_help_panel=_CALIB,
        ),
    ] = None,
    gyro_bias: Annotated[
        tuple[float, float, float] | None,
        typer.Option(
            "--gyro-bias",
            metavar="X Y Z",
            help="Constant gyro bias, rad/s.",
            rich_help_panel=_CALIB,
        ),
    ] = None,
    accel_bias: Annotated[
        tuple[float, float, float] | None,
        typer.Option(
            "--accel-bias",
            metavar="X Y Z",
            help="Constant accelerometer bias, m/s^2.",
            rich_help_panel=_CALIB,
        ),
    ] = None,
    noise_free: Annotated[
        bool,
        typer.Option(
            "--noise-free", help="No IMU noise, bias walk or range noise.", rich_help_panel=_IMU
        ),
    ] = False,
    bias_walk_scale: Annotated[
        float | None,
        typer.Option(
            "--bias-walk-scale",
            help="Multiply both MTi-100 bias random-walk densities (0: constant biases; "
            f"default 1, or {EFFECT_BIAS_WALK_SCALE:g} x --effect-scale for a named walk).",
            rich_help_panel=_IMU,
        ),
    ] = None,
    effect: Annotated[
        list[EffectName] | None,
        typer.Option(
            "--effect",
            metavar="NAME",
            help="Hide this effect (repeatable), at its reference size (the paper's table "
            "where it has one) times --effect-scale: "
            + ", ".join(e.value for e in Effect)
            + ". Intrinsic effects replace what --intrinsics drew for their block; use "
            "--intrinsics none to hide them alone.",
            rich_help_panel=_EFFECTS,
        ),
    ] = None,
    effect_scale: Annotated[
        float,
        typer.Option(
            "--effect-scale",
            help="Times the reference size of every named effect (the benchmark uses 2-5).",
            rich_help_panel=_EFFECTS,
        ),
    ] = 1.0,
    g_sensitivity: Annotated[
        float | None,
        typer.Option(
            "--g-sensitivity",
            help="Std of each g-sensitivity entry, deg/s per g (with --effect g_sensitivity; "
            f"default {DEFAULT_G_SENSITIVITY_DPS_PER_G:g} x --effect-scale).",
            rich_help_panel=_EFFECTS,
        ),
    ] = None,
    imu_clock_drift_ppm: Annotated[
        float | None,
        typer.Option(
            "--imu-clock-drift-ppm",
            help="IMU stamps run at (1 + ppm 1e-6) times the true rate (default 0, or "
            f"{EFFECT_IMU_CLOCK_DRIFT_PPM:g} x --effect-scale with --effect imu_clock_drift).",
            rich_help_panel=_EFFECTS,
        ),
    ] = None,
    point_time_error: Annotated[
        float | None,
        typer.Option(
            "--point-time-error",
            help="Per-point times within a sweep published 1 / (1 - k) fast (default 0, or "
            f"{EFFECT_POINT_TIME_ERROR:g} x --effect-scale with --effect lidar_point_time).",
            rich_help_panel=_EFFECTS,
        ),
    ] = None,
    fmt: Annotated[
        BagFormat, typer.Option("--format", help="Bag format.", rich_help_panel=_OUT)
    ] = BagFormat.ROS1,
    imu_topic: Annotated[str, typer.Option("--imu-topic", rich_help_panel=_OUT)] = "/imu/data",
    lidar_topic: Annotated[
        str | None,
        typer.Option(
            "--lidar-topic",
            help="(default: /points_raw Velodyne, /ouster/points Ouster, /livox/lidar Livox)",
            rich_help_panel=_OUT,
        ),
    ] = None,
    imu_frame: Annotated[str, typer.Option("--imu-frame", rich_help_panel=_OUT)] = "imu_link",
    lidar_frame: Annotated[
        str | None,
        typer.Option(
            "--lidar-frame",
            help="(default: velodyne Velodyne, os_sensor Ouster, livox_frame Livox)",
            rich_help_panel=_OUT,
        ),
    ] = None,
    base_time_ns: Annotated[
        int,
        typer.Option(
            "--base-time-ns",
            help="Absolute time of the first IMU sample, ns.",
            rich_help_panel=_OUT,
        ),
    ] = 1_700_000_000_000_000_000,
    force: Annotated[
        bool,
        typer.Option("--force", help="Overwrite an existing bag in OUT_DIR.", rich_help_panel=_OUT),
    ] = False,
) -> None:
    """Simulate a LiDAR-IMU bag (the paper's Sec. VI room) and write its ground truth."""
    spec = SimulationSpec(
        scenario=scenario,
        lidar=lidar,
        fmt=fmt,
        duration_s=duration,
        seed=seed,
        noise_seed=noise_seed,
        mounting=mounting,
        tilt_deg=tilt_deg,
        imu_rate_hz=imu_rate,
        lidar_rate_hz=lidar_rate,
        translation=tuple(translation),  # type: ignore[arg-type]
        rpy_deg=tuple(rpy_deg) if rpy_deg else None,  # type: ignore[arg-type]
        random_extrinsic=random_extrinsic,
        time_offset_s=time_offset,
        random_time_offset=random_time_offset,
        lidar_clock_offset_s=lidar_clock_offset,
        record_delay_ms=record_delay,
        intrinsics=intrinsics,
        intrinsics_scale=intrinsics_scale,
        intrinsics_file=intrinsics_file,
        gyro_bias=tuple(gyro_bias) if gyro_bias else None,  # type: ignore[arg-type]
        accel_bias=tuple(accel_bias) if accel_bias else None,  # type: ignore[arg-type]
        range_noise_m=range_noise,
        azimuth_resolution_deg=azimuth_resolution_deg,
        lidar_stamp=lidar_stamp,
        dropout=dropout,
        noise_free=noise_free,
        bias_walk_scale=bias_walk_scale,
        effects=tuple(e.value for e in effect or ()),
        effect_scale=effect_scale,
        g_sensitivity_dps_per_g=g_sensitivity,
        imu_clock_drift_ppm=imu_clock_drift_ppm,
        point_time_error=point_time_error,
        imu_topic=imu_topic,
        lidar_topic=lidar_topic,
        imu_frame=imu_frame,
        lidar_frame=lidar_frame,
        base_time_ns=base_time_ns,
        command_line=_command_line(ctx),
    )
    out = _run(spec, out_dir, force)
    ext = out.truth.extrinsic
    rpy = out.truth.to_dict()["extrinsic"]["rotation_rpy_deg"]
    typer.echo(
        f"Simulated {spec.scenario.value} for {spec.resolved_duration_s:g} s: "
        f"{out.num_scans} {spec.lidar.value} scans ({out.num_points:,} points), "
        f"{out.num_imu} IMU samples, in {out.elapsed_s:.1f} s."
    )
    typer.echo(
        f"T_imu_lidar: t = [{', '.join(f'{v:.4f}' for v in ext.translation)}] m, "
        f"rpy = [{', '.join(f'{v:.3f}' for v in rpy)}] deg; "
        f"time_offset_s = {ext.time_offset_s:g}."
    )
    typer.echo(f"Ground truth: {out.truth_path}")
    typer.echo(str(out.bag_path))


def _run(spec: SimulationSpec, out_dir: Path, force: bool) -> SimulationOutput:
    """Call the library, with a progress bar on an interactive stderr."""
    from licalib_cli.commands.render import console_err
    from licalib_cli.simulation.simulate import simulate

    console = console_err()
    if not console.is_terminal:
        return simulate(spec, out_dir, force=force)
    from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

    with Progress(
        TextColumn("simulating"),
        BarColumn(),
        TextColumn("{task.completed}/{task.total} scans"),
        TimeRemainingColumn(),
        console=console,
        transient=True,
    ) as bar:
        task = bar.add_task("scans", total=None)

        def progress(done: int, total: int) -> None:
            bar.update(task, completed=done, total=total)

        return simulate(spec, out_dir, force=force, progress=progress)
