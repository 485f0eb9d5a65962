"""Write a simulated bag and its ``truth.yaml``.

``truth.yaml`` is a :class:`~licalib_cli.truth.Truth`: the true values with the keys of a result
file (schema v1: ``extrinsic``, ``imu_intrinsics``, ``lidar_intrinsics``) and these sections::

    scenario: {name, duration_s, mounting, vertical_in_imu, tilt_deg, bursts_s: [[t0, t1], ...]}
    seed: 0
    simulation:
      gravity_world: [0, 0, -9.81]                # g_W, m/s^2
      gravity_in_first_imu_frame: [gx, gy, gz]    # g_G = R_W_I(t_first_imu)^T g_W
      initial_imu_pose: {stamp_ns, position, rotation_quaternion, velocity, angular_velocity}
      imu: {topic, frame_id, rate_hz, num_samples, noise densities and discrete sigmas,
            bias_walk_scale, effects, g_sensitivity_dps_per_g, clock_drift_ppm,
            gyro_bias_mean, accel_bias_mean, ..., gyro_bias_walk_scale, accel_bias_walk_scale,
            accel_unit}                           # g: the bag's unit (mid360, avia only)
      lidar: {model, topic, frame_id, rate_hz, num_beams, num_scans, stamp, range_noise_m, ...,
              point_time_error}
      clock: {base_time_ns, time_offset_s, time_offset_drawn, lidar_clock_offset_s, relation,
              record_delay_ms}
      bag: {format, path}
      command_line: "licalib simulate ..."
      licalib_version: "0.1.0"
      effects:                                    # every effect hidden, by diagnose's names
        - {name: gyro_scale, scale: 3.0, size: 0.0003, unit: "1 (std of s - 1)",
           values: [...], values_unit: "1 (s - 1)"}

Times in ``bursts_s`` are true seconds after ``base_time_ns`` (the IMU clock without drift).
Every value is in SI units; the bag's IMU messages carry ``linear_acceleration`` in
``accel_unit`` (``g`` with the Mid-360 and the Avia, whose built-in IMUs publish g: divided by
9.80665).
"""

from __future__ import annotations

import logging
import shutil
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from licalib_cli import __version__
from licalib_cli import truth as tr
from licalib_cli.errors import ConfigError
from licalib_cli.io.writer import BagWriter, default_bag_path
from licalib_cli.results import CalibrationResult, create_folder, write_text_atomic
from licalib_cli.simulation.effects import EFFECT_SIZES, Effect
from licalib_cli.simulation.ground_truth import SimulationSetup, build_setup
from licalib_cli.simulation.imu import ImuTruth, generate_imu
from licalib_cli.simulation.lidar import generate_scans, num_scans
from licalib_cli.simulation.spec import STANDARD_GRAVITY, Scenario, SimulationSpec

logger = logging.getLogger(__name__)

ProgressCallback = Callable[[int, int], None]
"""Called as ``progress(scans_written, scans_total)``."""


@dataclass(frozen=True)
class SimulationOutput:
    """What :func:`simulate` wrote.

    Attributes:
        bag_path: ``OUT_DIR/bag.bag`` (ROS1) or the ROS2 bag folder ``OUT_DIR/bag``.
        truth_path: ``OUT_DIR/truth.yaml``.
        truth: the ground truth as written.
        num_imu: IMU messages written.
        num_scans: PointCloud2 messages written.
        num_points: valid points over all scans.
        elapsed_s: wall time of the run, s.
    """

    bag_path: Path
    truth_path: Path
    truth: tr.Truth
    num_imu: int
    num_scans: int
    num_points: int
    elapsed_s: float


def _vec(a: Any, digits: int = 9) -> tuple[float, ...]:
    return tuple(round(float(x), digits) for x in np.asarray(a, dtype=np.float64).reshape(-1))


def _vec3(a: Any, digits: int = 9) -> tuple[float, float, float]:
    x, y, z = _vec(a, digits)
    return (x, y, z)


def _walk_slope(t_s: Any, bias: Any) -> tuple[float, ...]:
    """Least-squares slope of each column of ``bias`` (N, 3) over ``t_s`` (N,)."""
    t = np.asarray(t_s, dtype=np.float64)
    dt = t - t.mean()
    b = np.asarray(bias, dtype=np.float64)
    return _vec(dt @ (b - b.mean(axis=0)) / max(float(dt @ dt), 1e-300), 12)


def injected_effects(
    spec: SimulationSpec, setup: SimulationSetup, imu_truth: ImuTruth
) -> tuple[tr.InjectedEffect, ...]:
    """Every effect in force with its size and the values injected (truth ``effects``)."""
    from scipy.spatial.transform import Rotation

    imu = setup.imu_intrinsics
    lid = setup.lidar_intrinsics
    out = []
    for effect in spec.active_effects:
        named = effect in spec.effects
        ref = EFFECT_SIZES[effect]
        size = spec.effect_size(effect)
        if effect is Effect.GYRO_SCALE:
            values, unit = _vec(imu.gyro_scale - 1.0, 12), "1 (s - 1)"
        elif effect is Effect.ACCEL_SCALE:
            values, unit = _vec(imu.accel_scale - 1.0, 12), "1 (s - 1)"
        elif effect is Effect.GYRO_MISALIGNMENT:
            values, unit = _vec(np.degrees(imu.gyro_misalignment), 12), "deg"
        elif effect is Effect.ACCEL_MISALIGNMENT:
            values, unit = _vec(np.degrees(imu.accel_misalignment), 12), "deg"
        elif effect is Effect.GYRO_ROTATION:
            q = np.asarray(imu.gyro_rotation, dtype=np.float64)
            values, unit = _vec(np.degrees(Rotation.from_quat(q).as_rotvec()), 12), "deg"
            unit = "deg (rotation vector of R_wI)"
        elif effect is Effect.G_SENSITIVITY:
            a_w = np.asarray(imu.gyro_g_sensitivity, dtype=np.float64)
            values = _vec(np.degrees(a_w) * STANDARD_GRAVITY, 12)
            unit = "deg/s per g (A_w row-major)"
        elif effect is Effect.GYRO_BIAS_WALK:
            values = _walk_slope(imu_truth.t_true_s, imu_truth.gyro_bias)
            unit = "rad/s^2 (least-squares slope of the gyro bias)"
        elif effect is Effect.ACCEL_BIAS_WALK:
            values = _walk_slope(imu_truth.t_true_s, imu_truth.accel_bias)
            unit = "m/s^3 (least-squares slope of the accelerometer bias)"
        elif effect is Effect.IMU_CLOCK_DRIFT:
            values, unit = (size,), "ppm"
        elif effect is Effect.LIDAR_POINT_TIME:
            values, unit = (size,), "1 (fraction of the time within the sweep)"
        else:
            field, scale, degrees = {
                Effect.LIDAR_RANGE_OFFSET: ("range_offset", 0.0, False),
                Effect.LIDAR_RANGE_SCALE: ("range_scale", 1.0, False),
                Effect.LIDAR_ELEVATION: ("elevation_correction", 0.0, True),
                Effect.LIDAR_AZIMUTH: ("azimuth_correction", 0.0, True),
                Effect.LIDAR_VERTICAL_OFFSET: ("vertical_offset", 0.0, False),
                Effect.LIDAR_HORIZONTAL_OFFSET: ("horizontal_offset", 0.0, False),
            }[effect]
            v = np.asarray(getattr(lid, field), dtype=np.float64) - scale
            values = _vec(np.degrees(v) if degrees else v, 12)
            unit = "deg per beam" if degrees else ("1 (s - 1) per beam" if scale else "m per beam")
        out.append(
            tr.InjectedEffect(
                name=effect.value,
                scale=float(spec.effect_scale) if named else 1.0,
                size=float(f"{size:.12g}"),
                unit=ref.unit,
                values=values,
                values_unit=unit,
            )
        )
    return tuple(out)


def build_truth(
    spec: SimulationSpec,
    setup: SimulationSetup,
    imu_truth: ImuTruth | None = None,
    bag_path: Path | None = None,
) -> tr.Truth:
    """The ground truth of a run: the true values and how they were simulated."""
    from scipy.spatial.transform import Rotation

    imu_truth = imu_truth if imu_truth is not None else generate_imu(spec, setup)[1]
    t_first = float(imu_truth.t_true_s[0])
    state = setup.trajectory.state(np.array([t_first]))
    r0 = state.rotation[0]
    g_g = r0.T @ spec.gravity_w
    q0 = Rotation.from_matrix(r0).as_quat()
    qx, qy, qz, qw = _vec(-q0 if q0[3] < 0 else q0, 12)
    model = setup.lidar_model
    pattern = model.pattern(spec.lidar_rate_hz, spec.azimuth_resolution_deg)
    rate = spec.imu_rate_hz
    scenario = tr.Scenario(
        name=spec.scenario.value,
        duration_s=float(spec.resolved_duration_s),
        bursts_s=tuple(_vec(b, 3) for b in setup.motion.bursts_s),
    )
    if spec.scenario is Scenario.FIGURE8:
        scenario = replace(
            scenario,
            mounting=spec.mounting.value,
            vertical_in_imu=_vec3(setup.motion.vertical_in_imu),
        )
    if spec.tilt_deg > 0.0:
        scenario = replace(scenario, tilt_deg=float(spec.tilt_deg))
    imu = tr.SimulatedImu(
        topic=spec.imu_topic,
        frame_id=spec.imu_frame,
        rate_hz=float(rate),
        num_samples=int(imu_truth.t_true_s.shape[0]),
        model="Xsens MTi-100 (datasheet densities)",
        gyro_noise_density=float(spec.gyro_noise_density),  # rad/s/sqrt(Hz)
        accel_noise_density=float(spec.accel_noise_density),  # m/s^2/sqrt(Hz)
        gyro_bias_walk_density=float(spec.gyro_bias_walk_density),  # rad/s^2/sqrt(Hz)
        accel_bias_walk_density=float(spec.accel_bias_walk_density),  # m/s^3/sqrt(Hz)
        gyro_noise_sigma=imu_truth.gyro_noise_sigma,  # density * sqrt(rate)
        accel_noise_sigma=imu_truth.accel_noise_sigma,
        noise_free=spec.noise_free,
        bias_walk_scale=float(spec.resolved_bias_walk_scale),
        effects=tuple(e.value for e in spec.active_effects if e.sensor == "imu"),
        g_sensitivity_dps_per_g=float(spec.resolved_g_sensitivity_dps_per_g),
        clock_drift_ppm=float(spec.resolved_imu_clock_drift_ppm),
        gyro_bias_mean=_vec3(imu_truth.gyro_bias.mean(axis=0), 12),
        accel_bias_mean=_vec3(imu_truth.accel_bias.mean(axis=0), 12),
        gyro_bias_end=_vec3(imu_truth.gyro_bias[-1], 12),
        accel_bias_end=_vec3(imu_truth.accel_bias[-1], 12),
        gyro_bias_walk_scale=float(spec.resolved_gyro_bias_walk_scale),
        accel_bias_walk_scale=float(spec.resolved_accel_bias_walk_scale),
        accel_unit=spec.accel_unit,
    )
    lidar = tr.SimulatedLidar(
        model=model.kind.value,
        topic=spec.resolved_lidar_topic,
        frame_id=spec.resolved_lidar_frame,
        rate_hz=float(spec.lidar_rate_hz),
        num_beams=model.num_beams,
        rays_per_beam=int(pattern.t_ns.shape[0]),
        num_scans=num_scans(spec),
        organized=model.organized,
        stamp=spec.lidar_stamp.value if spec.lidar.is_velodyne else "start",
        range_noise_m=float(spec.resolved_range_noise_m),
        azimuth_resolution_deg=None
        if spec.azimuth_resolution_deg is None
        else float(spec.azimuth_resolution_deg),
        dropout=float(spec.dropout),
        intrinsics=spec.intrinsics.value
        if spec.intrinsics_file is None
        else str(spec.intrinsics_file),
        intrinsics_scale=float(spec.intrinsics_scale),
        point_time_error=float(spec.resolved_point_time_error),
    )
    simulation = tr.Simulation(
        gravity_world=_vec3(spec.gravity_w),
        gravity_in_first_imu_frame=_vec3(g_g),
        initial_imu_pose=tr.InitialImuPose(
            stamp_ns=int(spec.base_time_ns + round(t_first * 1e9)),
            position=_vec3(state.position[0]),
            rotation_quaternion=(qx, qy, qz, qw),
            velocity=_vec3(state.velocity[0]),
            angular_velocity=_vec3(state.angular_velocity[0]),
        ),
        imu=imu,
        lidar=lidar,
        clock=tr.SimulatedClock(
            base_time_ns=int(spec.base_time_ns),
            time_offset_s=float(setup.time_offset_ns * 1e-9),
            time_offset_drawn=spec.random_time_offset,
            lidar_clock_offset_s=float(setup.lidar_clock_offset_ns * 1e-9),
            relation="t_imu = t_lidar - lidar_clock_offset_s + time_offset_s",
            record_delay_ms=float(spec.record_delay_ms),
        ),
        random_extrinsic=spec.random_extrinsic,
        bag=tr.SimulatedBag(
            format=spec.fmt.value, path=None if bag_path is None else str(bag_path)
        ),
        command_line=spec.command_line or "",
        licalib_version=__version__,
        effects=injected_effects(spec, setup, imu_truth),
    )
    values = CalibrationResult(
        extrinsic=setup.extrinsic,
        imu_intrinsics=setup.imu_intrinsics,
        lidar_intrinsics=setup.lidar_intrinsics,
    )
    noise_seed = None if spec.resolved_noise_seed == spec.seed else spec.resolved_noise_seed
    return tr.Truth(values, scenario, int(spec.seed), simulation, noise_seed)


def _is_bag_like(path: Path) -> bool:
    if path.is_file():
        return path.suffix == ".bag"
    if path.is_dir():
        names = {p.name for p in path.iterdir()}
        return "metadata.yaml" in names and all(
            n == "metadata.yaml" or n.endswith((".db3", ".mcap", ".db3-wal", ".db3-shm"))
            for n in names
        )
    return False


def _check_overwrite(bag_path: Path, force: bool) -> None:
    if not (bag_path.exists() or bag_path.is_symlink()):
        return
    if not force:
        msg = f"{bag_path} already exists; pass --force to overwrite it or choose another OUT_DIR."
        raise ConfigError(msg)
    if not _is_bag_like(bag_path):
        msg = (
            f"{bag_path} exists and does not look like a bag, so --force will not delete it; "
            "remove it yourself or choose another OUT_DIR."
        )
        raise ConfigError(msg)


def _remove_existing(bag_path: Path, force: bool) -> None:
    if not (bag_path.exists() or bag_path.is_symlink()):
        return
    _check_overwrite(bag_path, force)
    if bag_path.is_dir() and not bag_path.is_symlink():
        shutil.rmtree(bag_path)
    else:
        bag_path.unlink()


def simulate(
    spec: SimulationSpec,
    out_dir: Path,
    *,
    force: bool = False,
    progress: ProgressCallback | None = None,
) -> SimulationOutput:
    """Generate the bag and ``truth.yaml`` of a simulation.

    Args:
        spec: all options.
        out_dir: output folder (created if missing).
        force: overwrite an existing bag (only a file or folder that looks like a bag).
        progress: optional ``progress(scans_written, scans_total)`` callback.

    Returns:
        Paths, the ground truth and counts.

    Raises:
        ConfigError: the bag exists and ``force`` is False, or an option is invalid.
    """
    t_start = time.perf_counter()
    out_dir = Path(out_dir)
    bag_path = default_bag_path(out_dir, spec.fmt)
    truth_path = out_dir / "truth.yaml"
    _check_overwrite(bag_path, force)
    setup = build_setup(spec)  # an option it refuses leaves no folder behind
    create_folder(out_dir, "The output", "give a folder path")

    imu, imu_truth = generate_imu(spec, setup)
    truth = build_truth(spec, setup, imu_truth, bag_path)
    truth_text = truth.to_yaml()  # fail early, before any bag is written
    total = num_scans(spec)
    lidar_topic = spec.resolved_lidar_topic
    lidar_frame = spec.resolved_lidar_frame
    n_points = 0
    n_written = 0
    accel = imu.accel / STANDARD_GRAVITY if spec.accel_unit == "g" else imu.accel
    tmp_dir = Path(tempfile.mkdtemp(prefix=".simulate-", dir=out_dir))
    try:
        tmp_bag = tmp_dir / bag_path.name
        with BagWriter(tmp_bag, spec.fmt) as writer:
            i_imu = 0
            n_imu = len(imu)
            for scan in generate_scans(spec, setup):
                # Interleave by record time: IMU messages that arrived before this scan.
                stop = int(np.searchsorted(imu_truth.record_ns, scan.record_ns, side="right"))
                for i in range(i_imu, stop):
                    writer.write_imu(
                        spec.imu_topic,
                        int(imu.t_ns[i]),
                        imu.gyro[i],
                        accel[i],
                        frame_id=spec.imu_frame,
                        record_ns=int(imu_truth.record_ns[i]),
                    )
                i_imu = stop
                writer.write_cloud(
                    lidar_topic,
                    scan.stamp_ns,
                    scan.points,
                    frame_id=lidar_frame,
                    record_ns=scan.record_ns,
                )
                n_points += int(np.count_nonzero(scan.truth.valid))
                n_written += 1
                if progress is not None:
                    progress(n_written, total)
            for i in range(i_imu, n_imu):
                writer.write_imu(
                    spec.imu_topic,
                    int(imu.t_ns[i]),
                    imu.gyro[i],
                    accel[i],
                    frame_id=spec.imu_frame,
                    record_ns=int(imu_truth.record_ns[i]),
                )
        _remove_existing(bag_path, force)
        tmp_bag.rename(bag_path)
    finally:
        shutil.rmtree(tmp_dir, ignore_errors=True)

    write_text_atomic(truth_path, truth_text)
    elapsed = time.perf_counter() - t_start
    logger.debug("simulated %d scans and %d IMU samples in %.1f s", n_written, len(imu), elapsed)
    return SimulationOutput(
        bag_path=bag_path,
        truth_path=truth_path,
        truth=truth,
        num_imu=len(imu),
        num_scans=n_written,
        num_points=n_points,
        elapsed_s=elapsed,
    )
