"""Everything a simulation run depends on, as one frozen dataclass.

Clocks and time (all stamps int64 ns):

* True time ``t`` (float s inside the math) starts at 0 at ``base_time_ns``. IMU samples are taken
  at their stamps: IMU stamp = ``base_time_ns + t`` (with ``imu_clock_drift_ppm``: stamps run at
  ``1 + ppm 1e-6`` times the true rate, ``stamp - base = t (1 + ppm 1e-6)``).
* LiDAR stamps ``tau = t - time_offset_s + lidar_clock_offset_s`` (on top of ``base_time_ns``),
  so ``t_imu = t_lidar + time_offset_s`` holds after the coarse shift ``lidar_clock_offset_s``
  (LiDAR clock minus IMU clock) is removed.
* Bag record times are the true arrival times: an IMU sample when taken, a scan at its last ray.

Defaults follow the paper's simulation (Sec. VI): 400 Hz IMU, 10 Hz VLP-16, ``T_imu_lidar`` with
``t = [0.3, 0.15, 0.05]`` m and ``rpy = [1, 2, 5]`` deg, 10 s, random intrinsics.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from enum import Enum
from pathlib import Path

import numpy as np

from licalib_cli.errors import ConfigError
from licalib_cli.io.writer import BagFormat

# Xsens MTi 100-series datasheet (MTi-100/200/300 share the inertial sensors):
# gyro noise density 0.01 deg/s/sqrt(Hz), in-run bias stability 10 deg/h;
# accelerometer noise density 60 ug/sqrt(Hz), in-run bias stability 15 ug.
STANDARD_GRAVITY = 9.80665
GYRO_NOISE_DENSITY = float(np.radians(0.01))  # rad/s/sqrt(Hz)
ACCEL_NOISE_DENSITY = 60e-6 * STANDARD_GRAVITY  # m/s^2/sqrt(Hz)
GYRO_BIAS_STABILITY = float(np.radians(10.0 / 3600.0))  # rad/s
ACCEL_BIAS_STABILITY = 15e-6 * STANDARD_GRAVITY  # m/s^2
# Bias random-walk densities: chosen so that the 1-sigma drift over 100 s equals the in-run
# bias stability (sigma_walk = stability / sqrt(100 s)).
BIAS_WALK_HORIZON_S = 100.0
_SQRT_HORIZON = float(np.sqrt(BIAS_WALK_HORIZON_S))
GYRO_BIAS_WALK_DENSITY = GYRO_BIAS_STABILITY / _SQRT_HORIZON  # rad/s^2/sqrt(Hz)
ACCEL_BIAS_WALK_DENSITY = ACCEL_BIAS_STABILITY / _SQRT_HORIZON  # m/s^3/sqrt(Hz)

DEFAULT_BASE_TIME_NS = 1_700_000_000_000_000_000
DEFAULT_DURATION_S = 10.0
DEFAULT_WALK_DURATION_S = 120.0


class Scenario(str, Enum):
    """Motion of the rig."""

    SINUSOID = "sinusoid"
    FIGURE8 = "figure8"
    SHAKE = "shake"
    WALK = "walk"
    TRANSLATION = "translation"


class LidarKind(str, Enum):
    """Simulated LiDAR."""

    VLP16 = "vlp16"
    OS1_64 = "os1-64"


class Mounting(str, Enum):
    """Figure-8 mounting cases of the paper (robot vertical expressed in the IMU frame)."""

    A = "A"
    B = "B"
    C = "C"


class IntrinsicsMode(str, Enum):
    """Ideal sensors, or intrinsics drawn from the paper's Table (sensor_intrinsic_setting)."""

    NONE = "none"
    RANDOM = "random"


class LidarStamp(str, Enum):
    """Header stamp of a Velodyne scan: its first firing (times >= 0) or its last (times <= 0)."""

    START = "start"
    END = "end"


class ImuEffect(str, Enum):
    """Optional IMU effects beyond the MTi-100 model of method.md section 3.

    * ``g-sensitivity``: gyro g-sensitivity ``A_w``, entries with std
      ``g_sensitivity_dps_per_g`` (default :data:`DEFAULT_G_SENSITIVITY_DPS_PER_G`).
    * ``bias-random-walk``: a stronger bias random walk, the MTi-100 densities times
      ``bias_walk_scale`` (default :data:`EFFECT_BIAS_WALK_SCALE`, a consumer-grade MEMS IMU);
      without the effect the walk is the MTi-100's (scale 1).
    * ``imu-clock-drift``: the IMU clock runs fast by ``imu_clock_drift_ppm`` (default
      :data:`EFFECT_IMU_CLOCK_DRIFT_PPM`, a typical uncompensated crystal); without the effect
      there is no drift unless ``imu_clock_drift_ppm`` is set.
    """

    G_SENSITIVITY = "g-sensitivity"
    BIAS_RANDOM_WALK = "bias-random-walk"
    IMU_CLOCK_DRIFT = "imu-clock-drift"


DEFAULT_G_SENSITIVITY_DPS_PER_G = 0.1
"""Std of each g-sensitivity entry with the ``g-sensitivity`` effect, deg/s per g."""
EFFECT_BIAS_WALK_SCALE = 10.0
"""Bias random-walk strength of the ``bias-random-walk`` effect, times the MTi-100 densities."""
EFFECT_IMU_CLOCK_DRIFT_PPM = 50.0
"""IMU clock drift of the ``imu-clock-drift`` effect, ppm (IMU stamps run fast)."""
RANDOM_TIME_OFFSET_MAX_S = 0.05
"""``random_time_offset`` draws the time offset uniformly in +-this, s."""


Vec3 = tuple[float, float, float]


@dataclass(frozen=True)
class SimulationSpec:
    """All options of a simulation; the same spec and seed give identical bag content.

    Attributes:
        scenario: trajectory of the IMU.
        lidar: LiDAR model.
        fmt: bag container format.
        duration_s: seconds of data; None for the scenario's default (10 s, walk 120 s).
        seed: seed of every random draw (trajectory, extrinsic, intrinsics, noise).
        mounting: figure-8 mounting case (ignored by the other scenarios).
        imu_rate_hz: IMU sample rate.
        lidar_rate_hz: sweeps per second.
        translation: ``t`` of ``T_imu_lidar`` (LiDAR origin in the IMU frame), m.
        rpy_deg: rotation of ``T_imu_lidar``, ``R = Rz(yaw) Ry(pitch) Rx(roll)``, deg.
        random_extrinsic: draw the extrinsic instead (any rotation, translation within 0.5 m).
        time_offset_s: ``t_imu = t_lidar + time_offset_s`` (stored rounded to ns).
        random_time_offset: draw ``time_offset_s`` uniformly within +-50 ms from the seed
            instead (``time_offset_s`` must then stay 0).
        lidar_clock_offset_s: whole-bag shift of the LiDAR clock (LiDAR minus IMU), s.
        intrinsics: ideal sensors or random intrinsics.
        intrinsics_scale: multiplies every standard deviation of the random intrinsics.
        intrinsics_file: result/truth YAML whose ``imu_intrinsics``/``lidar_intrinsics`` are used.
        gyro_bias: constant gyro bias (rad/s), overrides the drawn one.
        accel_bias: constant accelerometer bias (m/s^2), overrides the drawn one.
        range_noise_m: range noise sigma; None for the model's default.
        azimuth_resolution_deg: thin the sweep to about this azimuth step; None for native.
        lidar_stamp: Velodyne header stamp at the first or the last firing.
        dropout: probability that a ray returns nothing.
        noise_free: zero IMU white noise, bias random walk and range noise.
        bias_walk_scale: multiplies the bias random-walk densities (0 disables the walk); None
            for 1, or :data:`EFFECT_BIAS_WALK_SCALE` with the ``bias-random-walk`` effect.
        effects: optional IMU effects (:class:`ImuEffect`, names or members).
        g_sensitivity_dps_per_g: sigma of each g-sensitivity entry, deg/s per g (used with the
            ``g-sensitivity`` effect).
        imu_clock_drift_ppm: IMU stamps run at ``1 + ppm 1e-6`` times the true rate; None for
            0, or :data:`EFFECT_IMU_CLOCK_DRIFT_PPM` with the ``imu-clock-drift`` effect.
        gyro_noise_density: rad/s/sqrt(Hz).
        accel_noise_density: m/s^2/sqrt(Hz).
        gyro_bias_walk_density: rad/s^2/sqrt(Hz).
        accel_bias_walk_density: m/s^3/sqrt(Hz).
        imu_topic: topic of the Imu messages.
        lidar_topic: topic of the clouds; None for the model's default.
        imu_frame: frame_id of the Imu messages.
        lidar_frame: frame_id of the clouds; None for the model's default.
        base_time_ns: absolute time of ``t = 0``.
        gravity: magnitude of gravity, m/s^2 (``g_W = [0, 0, -gravity]``).
        command_line: the command that produced the run, recorded in ``truth.yaml``.
    """

    scenario: Scenario = Scenario.SINUSOID
    lidar: LidarKind = LidarKind.VLP16
    fmt: BagFormat = BagFormat.ROS1
    duration_s: float | None = None
    seed: int = 0
    mounting: Mounting = Mounting.A
    imu_rate_hz: float = 400.0
    lidar_rate_hz: float = 10.0
    translation: Vec3 = (0.3, 0.15, 0.05)
    rpy_deg: Vec3 = (1.0, 2.0, 5.0)
    random_extrinsic: bool = False
    time_offset_s: float = 0.0
    random_time_offset: bool = False
    lidar_clock_offset_s: float = 0.0
    intrinsics: IntrinsicsMode = IntrinsicsMode.RANDOM
    intrinsics_scale: float = 1.0
    intrinsics_file: Path | None = None
    gyro_bias: Vec3 | None = None
    accel_bias: Vec3 | None = None
    range_noise_m: float | None = None
    azimuth_resolution_deg: float | None = None
    lidar_stamp: LidarStamp = LidarStamp.START
    dropout: float = 0.001
    noise_free: bool = False
    bias_walk_scale: float | None = None
    effects: tuple[ImuEffect, ...] = field(default_factory=tuple)
    g_sensitivity_dps_per_g: float = DEFAULT_G_SENSITIVITY_DPS_PER_G
    imu_clock_drift_ppm: float | None = None
    gyro_noise_density: float = GYRO_NOISE_DENSITY
    accel_noise_density: float = ACCEL_NOISE_DENSITY
    gyro_bias_walk_density: float = GYRO_BIAS_WALK_DENSITY
    accel_bias_walk_density: float = ACCEL_BIAS_WALK_DENSITY
    imu_topic: str = "/imu/data"
    lidar_topic: str | None = None
    imu_frame: str = "imu_link"
    lidar_frame: str | None = None
    base_time_ns: int = DEFAULT_BASE_TIME_NS
    gravity: float = 9.81
    command_line: str | None = None

    def __post_init__(self) -> None:
        # Accept plain strings for the enum fields (library callers, YAML).
        for name, enum in (
            ("scenario", Scenario),
            ("lidar", LidarKind),
            ("fmt", BagFormat),
            ("mounting", Mounting),
            ("intrinsics", IntrinsicsMode),
            ("lidar_stamp", LidarStamp),
        ):
            value = getattr(self, name)
            try:
                object.__setattr__(self, name, enum(value))
            except ValueError as err:
                choices = ", ".join(e.value for e in enum)
                msg = f"Unknown {name} {value!r}; choose one of {choices}."
                raise ConfigError(msg) from err
        try:
            effects = tuple(ImuEffect(e) for e in self.effects)
        except ValueError as err:
            choices = ", ".join(e.value for e in ImuEffect)
            msg = f"Unknown IMU effect in {list(self.effects)}; choose from {choices}."
            raise ConfigError(msg) from err
        object.__setattr__(self, "effects", tuple(dict.fromkeys(effects)))
        self._validate()

    def _validate(self) -> None:
        checks: list[tuple[bool, str]] = [
            (
                self.duration_s is None or self.duration_s > 0,
                f"--duration must be positive, got {self.duration_s}; pass e.g. --duration 10.",
            ),
            (
                50.0 <= self.imu_rate_hz <= 2000.0,
                f"--imu-rate {self.imu_rate_hz} Hz is outside 50-2000 Hz; use e.g. 400.",
            ),
            (
                self.intrinsics_scale >= 0 and self.resolved_bias_walk_scale >= 0,
                "--intrinsics-scale and --bias-walk-scale must not be negative.",
            ),
            (
                not (self.random_time_offset and self.time_offset_s != 0.0),
                "--random-time-offset draws the time offset, so do not also pass "
                "--time-offset; drop one of them.",
            ),
            (
                self.range_noise_m is None or self.range_noise_m >= 0,
                "--range-noise must not be negative.",
            ),
            (
                0.0 <= self.dropout < 1.0,
                f"--dropout {self.dropout} must be in [0, 1).",
            ),
            (
                self.azimuth_resolution_deg is None or 0 < self.azimuth_resolution_deg <= 10,
                "--azimuth-resolution-deg must be in (0, 10] degrees.",
            ),
            (
                abs(self.resolved_imu_clock_drift_ppm) < 1e4,
                "--imu-clock-drift-ppm must be below 10000 in magnitude.",
            ),
            (self.gravity > 0, "gravity must be positive."),
        ]
        if self.lidar is LidarKind.VLP16:
            checks.append(
                (
                    5.0 <= self.lidar_rate_hz <= 20.0,
                    f"--lidar-rate {self.lidar_rate_hz} Hz: the VLP-16 spins at 5-20 Hz.",
                )
            )
        else:
            checks.append(
                (
                    self.lidar_rate_hz in (10.0, 20.0),
                    f"--lidar-rate {self.lidar_rate_hz} Hz: the OS1-64 runs at 10 or 20 Hz.",
                )
            )
        for ok, msg in checks:
            if not ok:
                raise ConfigError(msg)

    @property
    def resolved_duration_s(self) -> float:
        if self.duration_s is not None:
            return float(self.duration_s)
        return DEFAULT_WALK_DURATION_S if self.scenario is Scenario.WALK else DEFAULT_DURATION_S

    @property
    def resolved_lidar_topic(self) -> str:
        if self.lidar_topic:
            return self.lidar_topic
        return "/points_raw" if self.lidar is LidarKind.VLP16 else "/ouster/points"

    @property
    def resolved_lidar_frame(self) -> str:
        if self.lidar_frame:
            return self.lidar_frame
        return "velodyne" if self.lidar is LidarKind.VLP16 else "os_sensor"

    @property
    def resolved_bias_walk_scale(self) -> float:
        """Multiplier of the MTi-100 bias random-walk densities actually used."""
        if self.bias_walk_scale is not None:
            return float(self.bias_walk_scale)
        return EFFECT_BIAS_WALK_SCALE if ImuEffect.BIAS_RANDOM_WALK in self.effects else 1.0

    @property
    def resolved_imu_clock_drift_ppm(self) -> float:
        """IMU clock drift actually used, ppm."""
        if self.imu_clock_drift_ppm is not None:
            return float(self.imu_clock_drift_ppm)
        return EFFECT_IMU_CLOCK_DRIFT_PPM if ImuEffect.IMU_CLOCK_DRIFT in self.effects else 0.0

    @property
    def active_effects(self) -> tuple[ImuEffect, ...]:
        """Effects in force: those named, plus those the numeric options imply.

        ``imu-clock-drift`` when a drift is set, ``bias-random-walk`` when the walk is stronger
        than the MTi-100's (scale above 1). Ordered as :class:`ImuEffect`.
        """
        out = set(self.effects)
        if self.resolved_imu_clock_drift_ppm != 0.0:
            out.add(ImuEffect.IMU_CLOCK_DRIFT)
        if self.resolved_bias_walk_scale > 1.0:
            out.add(ImuEffect.BIAS_RANDOM_WALK)
        return tuple(e for e in ImuEffect if e in out)

    @property
    def resolved_range_noise_m(self) -> float:
        if self.noise_free:
            return 0.0
        if self.range_noise_m is not None:
            return float(self.range_noise_m)
        return 0.01 if self.lidar is LidarKind.VLP16 else 0.015

    @property
    def gravity_w(self) -> np.ndarray:
        """``g_W``, (3,) m/s^2."""
        return np.array([0.0, 0.0, -self.gravity])

    def with_(self, **changes: object) -> SimulationSpec:
        """Copy with some fields replaced."""
        return replace(self, **changes)  # type: ignore[arg-type]
