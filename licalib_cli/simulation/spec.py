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
``t = [0.3, 0.15, 0.05]`` m and ``rpy = [1, 2, 5]`` deg (the forward-looking avia: yaw 95 deg,
:data:`AVIA_RPY_DEG`), 10 s, random intrinsics.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from enum import Enum
from pathlib import Path

import numpy as np

from licalib_cli.errors import ConfigError
from licalib_cli.io.writer import BagFormat
from licalib_cli.simulation.effects import EFFECT_SIZES, Effect, parse_effects

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
    """Simulated LiDAR: two Velodyne (unorganised clouds, a ``time`` field relative to the
    stamp), three Ouster (organised clouds, a ``t`` field in ns from the sweep start) beam
    counts, and two Livox-like non-repetitive scanners, the Mid-360 (360 deg around) and the
    forward-looking Avia (a rosette) (unorganised clouds, a ``line`` field grouping points of
    many elevations, an absolute ``timestamp`` field in ns)."""

    VLP16 = "vlp16"
    HDL32 = "hdl-32"
    OS1_32 = "os1-32"
    OS1_64 = "os1-64"
    OS1_128 = "os1-128"
    MID360 = "mid360"
    AVIA = "avia"

    @property
    def is_velodyne(self) -> bool:
        """A Velodyne (cycle-based firing, unorganised ``PointXYZIRT`` clouds)."""
        return self in (LidarKind.VLP16, LidarKind.HDL32)

    @property
    def is_ouster(self) -> bool:
        """An Ouster OS1 (column-based firing, organised clouds)."""
        return self in (LidarKind.OS1_32, LidarKind.OS1_64, LidarKind.OS1_128)

    @property
    def is_non_repetitive(self) -> bool:
        """A scanner without fixed beams (Livox): each ray has its own elevation and
        successive sweeps cover different directions, so there are no per-beam intrinsics."""
        return self in (LidarKind.MID360, LidarKind.AVIA)

    @property
    def display_name(self) -> str:
        """The sensor's name as its maker writes it."""
        return {
            LidarKind.VLP16: "VLP-16",
            LidarKind.HDL32: "HDL-32E",
            LidarKind.OS1_32: "OS1-32",
            LidarKind.OS1_64: "OS1-64",
            LidarKind.OS1_128: "OS1-128",
            LidarKind.MID360: "Mid-360",
            LidarKind.AVIA: "Avia",
        }[self]


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


DEFAULT_G_SENSITIVITY_DPS_PER_G = EFFECT_SIZES[Effect.G_SENSITIVITY].size
"""Std of each g-sensitivity entry with the ``g_sensitivity`` effect, deg/s per g."""
EFFECT_BIAS_WALK_SCALE = EFFECT_SIZES[Effect.GYRO_BIAS_WALK].size
"""Bias random-walk strength of the bias-walk effects, times the MTi-100 densities."""
EFFECT_IMU_CLOCK_DRIFT_PPM = EFFECT_SIZES[Effect.IMU_CLOCK_DRIFT].size
"""IMU clock drift of the ``imu_clock_drift`` effect, ppm (IMU stamps run fast)."""
EFFECT_POINT_TIME_ERROR = EFFECT_SIZES[Effect.LIDAR_POINT_TIME].size
"""Per-point time error of the ``lidar_point_time`` effect (fraction of the time in the sweep)."""
MAX_TILT_DEG = 60.0
"""Largest ``tilt_deg`` (the rig stays upright enough for the room's floor and walls)."""
MAX_RECORD_DELAY_MS = 20.0
"""Largest ``record_delay_ms`` (a recorder further behind would reorder the topics' messages)."""
RANDOM_TIME_OFFSET_MAX_S = 0.05
"""``random_time_offset`` draws the time offset uniformly in +-this, s."""
LIVOX_RANGE_NOISE_M = 0.02
"""Default range noise of the Livox scanners, m (Mid-360 datasheet: range precision <= 2 cm
at 10 m; Avia: 2 cm)."""
LIVOX_MIN_RATE_HZ = 5.0
LIVOX_MAX_RATE_HZ = 50.0
"""Publish rates of the Livox scanners (``livox_ros_driver2`` ``publish_freq``) the simulator
takes."""


Vec3 = tuple[float, float, float]

DEFAULT_RPY_DEG: Vec3 = (1.0, 2.0, 5.0)
"""Rotation of ``T_imu_lidar`` by default (the paper's), deg."""
AVIA_RPY_DEG: Vec3 = (1.0, 2.0, 95.0)
"""The avia's default rotation: the paper's plus a quarter turn in yaw, so its forward-looking
70 x 77 deg field of view looks along the IMU's +y. Along +x it would face the x = 8.5 m wall
from 1.5 m at the sinusoid's start (97 % of a sweep on that one plane, too little for the
odometry); along +y at least 70 % of every sweep's points lie beyond 3 m in each scenario."""


@dataclass(frozen=True)
class SimulationSpec:
    """All options of a simulation; the same spec and seed give identical bag content.

    Attributes:
        scenario: trajectory of the IMU.
        lidar: LiDAR model.
        fmt: bag container format.
        duration_s: seconds of data; None for the scenario's default (10 s, walk 120 s).
        seed: seed of every random draw (trajectory, extrinsic, intrinsics, noise).
        noise_seed: seed of the sensor noise alone (IMU white noise and bias walks, LiDAR range
            noise and dropouts); None: ``seed``. Another noise seed with the same ``seed`` draws
            new noise for the same motion, mounting and intrinsics (a Monte Carlo over noise).
        mounting: figure-8 mounting case (ignored by the other scenarios).
        tilt_deg: shake only: a slow tilt of this amplitude added about each horizontal axis
            (one sinusoid per axis at 0.1-0.2 Hz, drawn from the seed), deg; 0 for none. The
            accelerometer then sees gravity from attitudes tens of degrees apart.
        imu_rate_hz: IMU sample rate.
        lidar_rate_hz: sweeps per second.
        translation: ``t`` of ``T_imu_lidar`` (LiDAR origin in the IMU frame), m.
        rpy_deg: rotation of ``T_imu_lidar``, ``R = Rz(yaw) Ry(pitch) Rx(roll)``, deg; None
            for the default (:data:`DEFAULT_RPY_DEG`, the avia's :data:`AVIA_RPY_DEG`).
        random_extrinsic: draw the extrinsic instead (any rotation, translation within 0.5 m).
        time_offset_s: ``t_imu = t_lidar + time_offset_s`` (stored rounded to ns).
        random_time_offset: draw ``time_offset_s`` uniformly within +-50 ms from the seed
            instead (``time_offset_s`` must then stay 0).
        lidar_clock_offset_s: whole-bag shift of the LiDAR clock (LiDAR minus IMU), s.
        record_delay_ms: mean transport delay of the messages, ms: each message's record time
            is its true time (the end of its sweep for a cloud) plus an exponential delay of
            this mean, in order per topic (no message overtakes the one before; a cloud's
            delay at most half the sweep period); 0: recorded at the true time.
        intrinsics: ideal sensors or random intrinsics.
        intrinsics_scale: multiplies every standard deviation of the random intrinsics.
        intrinsics_file: result/truth YAML whose ``imu_intrinsics``/``lidar_intrinsics`` are used.
        gyro_bias: constant gyro bias (rad/s), overrides the drawn one.
        accel_bias: constant accelerometer bias (m/s^2), overrides the drawn one.
        range_noise_m: range noise sigma; None for the model's default (0.01 m Velodyne,
            0.015 m Ouster, 0.02 m Mid-360 and Avia).
        azimuth_resolution_deg: thin the sweep to about this azimuth step; None for native.
        lidar_stamp: Velodyne header stamp at the first or the last firing (the Ouster and
            the Livox stamp the first).
        dropout: probability that a ray returns nothing.
        noise_free: zero IMU white noise, bias random walk and range noise.
        bias_walk_scale: multiplies both bias random-walk densities (0 disables the walk);
            None for 1, or the effect's strength with ``gyro_bias_walk`` / ``accel_bias_walk``.
        effects: effects to hide (:class:`~licalib_cli.simulation.effects.Effect`, names or
            members; the earlier names ``g-sensitivity``, ``imu-clock-drift`` and
            ``bias-random-walk`` (both walks) are accepted), each at its reference size
            (:data:`~licalib_cli.simulation.effects.EFFECT_SIZES`) times ``effect_scale``.
            Drawn intrinsic effects replace what ``intrinsics`` drew for that block.
        effect_scale: multiplies the reference size of every named effect.
        g_sensitivity_dps_per_g: sigma of each g-sensitivity entry, deg/s per g (with the
            ``g_sensitivity`` effect); None for its size times ``effect_scale``.
        imu_clock_drift_ppm: IMU stamps run at ``1 + ppm 1e-6`` times the true rate; None for
            0, or its size times ``effect_scale`` with the ``imu_clock_drift`` effect.
        point_time_error: ``k``: each point's published time within its sweep is the true one
            divided by ``1 - k``; None for 0, or its size times ``effect_scale`` with the
            ``lidar_point_time`` effect.
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
    noise_seed: int | None = None
    mounting: Mounting = Mounting.A
    tilt_deg: float = 0.0
    imu_rate_hz: float = 400.0
    lidar_rate_hz: float = 10.0
    translation: Vec3 = (0.3, 0.15, 0.05)
    rpy_deg: Vec3 | None = None
    random_extrinsic: bool = False
    time_offset_s: float = 0.0
    random_time_offset: bool = False
    lidar_clock_offset_s: float = 0.0
    record_delay_ms: float = 0.0
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
    effects: tuple[Effect, ...] = field(default_factory=tuple)
    effect_scale: float = 1.0
    g_sensitivity_dps_per_g: float | None = None
    imu_clock_drift_ppm: float | None = None
    point_time_error: float | None = None
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
            effects = parse_effects(tuple(self.effects))
        except ValueError as err:
            raise ConfigError(str(err)) from err
        object.__setattr__(self, "effects", effects)
        self._validate()

    def _validate(self) -> None:
        checks: list[tuple[bool, str]] = [
            (
                self.seed >= 0 and (self.noise_seed is None or self.noise_seed >= 0),
                f"--seed and --noise-seed must not be negative, got {self.seed} and "
                f"{self.noise_seed}; pass e.g. --seed 0.",
            ),
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
                0.0 <= self.effect_scale <= 100.0,
                f"--effect-scale {self.effect_scale} must be in [0, 100]; the benchmark "
                "uses 1 to 5.",
            ),
            (
                abs(self.resolved_point_time_error) < 0.5,
                "--point-time-error must be below 0.5 in magnitude (a fraction of the time "
                "within the sweep, e.g. 0.01).",
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
            (
                0.0 <= self.record_delay_ms <= MAX_RECORD_DELAY_MS,
                f"--record-delay-ms {self.record_delay_ms} must be in [0, "
                f"{MAX_RECORD_DELAY_MS:g}] ms.",
            ),
            (self.gravity > 0, "gravity must be positive."),
            (
                0.0 <= self.tilt_deg <= MAX_TILT_DEG,
                f"--tilt-deg {self.tilt_deg} must be in [0, {MAX_TILT_DEG:g}] degrees.",
            ),
            (
                self.tilt_deg == 0.0 or self.scenario is Scenario.SHAKE,
                f"--tilt-deg adds a tilt to the shake; the {self.scenario.value} has its own "
                "attitude: drop --tilt-deg or pass --scenario shake.",
            ),
        ]
        name = self.lidar.display_name
        if self.lidar.is_velodyne:
            checks.append(
                (
                    5.0 <= self.lidar_rate_hz <= 20.0,
                    f"--lidar-rate {self.lidar_rate_hz} Hz: the {name} spins at 5-20 Hz.",
                )
            )
        elif self.lidar.is_non_repetitive:
            per_beam = [e.value for e in self.effects if e.per_beam]
            checks += [
                (
                    LIVOX_MIN_RATE_HZ <= self.lidar_rate_hz <= LIVOX_MAX_RATE_HZ,
                    f"--lidar-rate {self.lidar_rate_hz} Hz: the {name} driver publishes at "
                    f"{LIVOX_MIN_RATE_HZ:g}-{LIVOX_MAX_RATE_HZ:g} Hz.",
                ),
                (
                    not per_beam,
                    f"--effect {(per_beam or [''])[0]} is a per-beam LiDAR effect and the {name} "
                    "has no fixed beams; drop it (lidar_point_time and the IMU effects apply) or "
                    "choose a spinning --lidar.",
                ),
            ]
        else:
            checks.append(
                (
                    self.lidar_rate_hz in (10.0, 20.0),
                    f"--lidar-rate {self.lidar_rate_hz} Hz: the {name} runs at 10 or 20 Hz.",
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
    def resolved_rpy_deg(self) -> Vec3:
        """Rotation of ``T_imu_lidar`` actually used (unless ``random_extrinsic``), deg."""
        if self.rpy_deg is not None:
            return self.rpy_deg
        return AVIA_RPY_DEG if self.lidar is LidarKind.AVIA else DEFAULT_RPY_DEG

    @property
    def resolved_lidar_topic(self) -> str:
        if self.lidar_topic:
            return self.lidar_topic
        if self.lidar.is_non_repetitive:
            return "/livox/lidar"
        return "/points_raw" if self.lidar.is_velodyne else "/ouster/points"

    @property
    def resolved_lidar_frame(self) -> str:
        if self.lidar_frame:
            return self.lidar_frame
        if self.lidar.is_non_repetitive:
            return "livox_frame"
        return "velodyne" if self.lidar.is_velodyne else "os_sensor"

    @property
    def accel_unit(self) -> str:
        """Unit of the published ``linear_acceleration``: ``g`` for the Livox built-in IMU (as
        ``livox_ros_driver2`` publishes it), ``m/s^2`` otherwise."""
        return "g" if self.lidar.is_non_repetitive else "m/s^2"

    def _strength(self, effect: Effect) -> float:
        """The named effect's reference size times ``effect_scale``; 0 when not named."""
        if effect not in self.effects:
            return 0.0
        return EFFECT_SIZES[effect].size * float(self.effect_scale)

    def effect_size(self, effect: Effect) -> float:
        """The 1-sigma (or value) an effect is injected with, in its unit of
        :data:`~licalib_cli.simulation.effects.EFFECT_SIZES` (0 when not in force)."""
        if effect is Effect.G_SENSITIVITY:
            return self.resolved_g_sensitivity_dps_per_g
        if effect is Effect.IMU_CLOCK_DRIFT:
            return self.resolved_imu_clock_drift_ppm
        if effect is Effect.LIDAR_POINT_TIME:
            return self.resolved_point_time_error
        if effect is Effect.GYRO_BIAS_WALK:
            return self.resolved_gyro_bias_walk_scale
        if effect is Effect.ACCEL_BIAS_WALK:
            return self.resolved_accel_bias_walk_scale
        return self._strength(effect)

    @property
    def resolved_gyro_bias_walk_scale(self) -> float:
        """Multiplier of the MTi-100 gyro bias random-walk density actually used."""
        if self.bias_walk_scale is not None:
            return float(self.bias_walk_scale)
        return self._strength(Effect.GYRO_BIAS_WALK) or 1.0

    @property
    def resolved_accel_bias_walk_scale(self) -> float:
        """Multiplier of the MTi-100 accelerometer bias random-walk density actually used."""
        if self.bias_walk_scale is not None:
            return float(self.bias_walk_scale)
        return self._strength(Effect.ACCEL_BIAS_WALK) or 1.0

    @property
    def resolved_bias_walk_scale(self) -> float:
        """The larger of the two bias-walk multipliers."""
        return max(self.resolved_gyro_bias_walk_scale, self.resolved_accel_bias_walk_scale)

    @property
    def resolved_g_sensitivity_dps_per_g(self) -> float:
        """Std of each g-sensitivity entry actually used, deg/s per g (0: none)."""
        if Effect.G_SENSITIVITY not in self.effects:
            return 0.0
        if self.g_sensitivity_dps_per_g is not None:
            return float(self.g_sensitivity_dps_per_g)
        return self._strength(Effect.G_SENSITIVITY)

    @property
    def resolved_imu_clock_drift_ppm(self) -> float:
        """IMU clock drift actually used, ppm."""
        if self.imu_clock_drift_ppm is not None:
            return float(self.imu_clock_drift_ppm)
        return self._strength(Effect.IMU_CLOCK_DRIFT)

    @property
    def resolved_point_time_error(self) -> float:
        """Per-point time error ``k`` actually used (fraction of the time within the sweep)."""
        if self.point_time_error is not None:
            return float(self.point_time_error)
        return self._strength(Effect.LIDAR_POINT_TIME)

    @property
    def active_effects(self) -> tuple[Effect, ...]:
        """Effects in force: those named, plus those the numeric options imply.

        ``imu_clock_drift`` when a drift is set, ``lidar_point_time`` when a point time error
        is set, a bias walk when it is stronger than the MTi-100's (multiplier above 1).
        Ordered as :class:`~licalib_cli.simulation.effects.Effect`.
        """
        out = set(self.effects)
        if self.resolved_imu_clock_drift_ppm != 0.0:
            out.add(Effect.IMU_CLOCK_DRIFT)
        if self.resolved_point_time_error != 0.0:
            out.add(Effect.LIDAR_POINT_TIME)
        if self.resolved_gyro_bias_walk_scale > 1.0:
            out.add(Effect.GYRO_BIAS_WALK)
        if self.resolved_accel_bias_walk_scale > 1.0:
            out.add(Effect.ACCEL_BIAS_WALK)
        return tuple(e for e in Effect if e in out)

    @property
    def resolved_noise_seed(self) -> int:
        """The seed of the sensor noise draws."""
        return self.seed if self.noise_seed is None else int(self.noise_seed)

    @property
    def resolved_range_noise_m(self) -> float:
        if self.noise_free:
            return 0.0
        if self.range_noise_m is not None:
            return float(self.range_noise_m)
        if self.lidar.is_non_repetitive:
            return LIVOX_RANGE_NOISE_M
        return 0.01 if self.lidar.is_velodyne else 0.015

    @property
    def gravity_w(self) -> np.ndarray:
        """``g_W``, (3,) m/s^2."""
        return np.array([0.0, 0.0, -self.gravity])

    def with_(self, **changes: object) -> SimulationSpec:
        """Copy with some fields replaced."""
        return replace(self, **changes)  # type: ignore[arg-type]
