"""A simulator's ``truth.yaml``: the true values in the result file's form, and the run.

``licalib simulate`` writes the true extrinsic and intrinsics with the keys of a calibration
result (schema v1, :class:`~licalib_cli.results.CalibrationResult`), followed by three sections
of its own::

    scenario:      name, duration, motion bursts (figure-8: mounting, vertical axis)
    seed:          the random seed
    noise_seed:    the seed of the sensor noise, when ``--noise-seed`` gave another one
    simulation:    gravity, initial pose, IMU, LiDAR, clocks, bag and command line, and
                   ``effects``: every effect hidden in the data by name (the candidates of
                   ``licalib diagnose``) with its size and the values injected

:class:`Truth` reads and writes the whole file; a calibration result read as a truth (e.g.
``calibrate --truth previous.yaml``) has no simulation sections (``None``).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from licalib_cli.config import read_yaml
from licalib_cli.errors import ConfigError
from licalib_cli.filetypes import FileValueError, typed
from licalib_cli.models.intrinsics import ImuIntrinsics, LidarIntrinsics
from licalib_cli.results import CalibrationResult, Extrinsic, dump_yaml, write_text_atomic
from licalib_cli.sections import Section

__all__ = [
    "InitialImuPose",
    "InjectedEffect",
    "Scenario",
    "SimulatedBag",
    "SimulatedClock",
    "SimulatedImu",
    "SimulatedLidar",
    "Simulation",
    "Truth",
]

Vec3 = tuple[float, float, float]


@dataclass(frozen=True)
class Scenario(Section):
    """The simulated motion.

    Attributes:
        name: scenario name (``sinusoid``, ``figure8``, ...).
        duration_s: simulated duration, s.
        bursts_s: ``[start, end]`` of each burst of motion, s.
        mounting: figure-8 only: the mounting of the rig on the robot.
        vertical_in_imu: figure-8 only: the robot's vertical in the IMU frame.
        tilt_deg: shake only: the amplitude of the slow tilt added about each horizontal axis,
            deg (absent without one).
    """

    name: str
    duration_s: float
    bursts_s: tuple[tuple[float, ...], ...] = ()
    mounting: str | None = None
    vertical_in_imu: Vec3 | None = None
    tilt_deg: float | None = None

    def to_dict(self) -> dict[str, Any]:
        return {k: v for k, v in super().to_dict().items() if v is not None}


@dataclass(frozen=True)
class InitialImuPose(Section):
    """The IMU's true state at its first sample (world frame)."""

    stamp_ns: int
    position: Vec3
    rotation_quaternion: tuple[float, float, float, float]
    velocity: Vec3
    angular_velocity: Vec3


@dataclass(frozen=True)
class SimulatedImu(Section):
    """The simulated IMU: topic, rate, noise, biases and effects (units as named);
    ``accel_unit`` is the unit of the bag's ``linear_acceleration`` (``g`` for a Livox, the
    only case the file names it)."""

    topic: str
    frame_id: str
    rate_hz: float
    num_samples: int
    model: str
    gyro_noise_density: float
    accel_noise_density: float
    gyro_bias_walk_density: float
    accel_bias_walk_density: float
    gyro_noise_sigma: float
    accel_noise_sigma: float
    noise_free: bool
    bias_walk_scale: float
    effects: tuple[str, ...]
    g_sensitivity_dps_per_g: float
    clock_drift_ppm: float
    gyro_bias_mean: Vec3
    accel_bias_mean: Vec3
    gyro_bias_end: Vec3
    accel_bias_end: Vec3
    gyro_bias_walk_scale: float = 1.0
    accel_bias_walk_scale: float = 1.0
    accel_unit: str = "m/s^2"

    def to_dict(self) -> dict[str, Any]:
        # the key only for an IMU in g (other truth files read as before)
        out = super().to_dict()
        if out.get("accel_unit") == "m/s^2":
            del out["accel_unit"]
        return out


@dataclass(frozen=True)
class SimulatedLidar(Section):
    """The simulated LiDAR: model, topic, firing pattern, noise and intrinsics."""

    model: str
    topic: str
    frame_id: str
    rate_hz: float
    num_beams: int
    rays_per_beam: int
    num_scans: int
    organized: bool
    stamp: str
    range_noise_m: float
    azimuth_resolution_deg: float | None
    dropout: float
    intrinsics: str
    intrinsics_scale: float
    point_time_error: float = 0.0


@dataclass(frozen=True)
class SimulatedClock(Section):
    """The clocks: ``t_imu = t_lidar - lidar_clock_offset_s + time_offset_s``.

    Attributes:
        base_time_ns: stamp of simulated time 0, ns.
        time_offset_s: the true time offset, s.
        time_offset_drawn: whether it was drawn from the seed.
        lidar_clock_offset_s: how far the LiDAR clock runs ahead of the IMU clock, s.
        relation: the relation above, in words.
        record_delay_ms: mean transport delay added to the record times, ms (0: each message
            recorded at its true time).
    """

    base_time_ns: int
    time_offset_s: float
    time_offset_drawn: bool
    lidar_clock_offset_s: float
    relation: str
    record_delay_ms: float = 0.0


@dataclass(frozen=True)
class SimulatedBag(Section):
    """The bag written: ``ros1``, ``ros2-sqlite3`` or ``ros2-mcap`` and its path."""

    format: str
    path: str | None


@dataclass(frozen=True)
class InjectedEffect(Section):
    """One effect hidden in the simulated data (:mod:`licalib_cli.simulation.effects`).

    Attributes:
        name: the effect's name (as ``licalib diagnose`` names it).
        scale: ``--effect-scale``: times the reference size (1 when set by a numeric option).
        size: the size injected, in ``unit`` (a 1-sigma for drawn effects).
        unit: unit of ``size``.
        values: what was injected, in ``values_unit``: per axis (IMU scale ``s - 1``,
            misalignment and rotation angles), the 9 g-sensitivity entries row-major, per beam
            (LiDAR intrinsics, beam 0 first), the drift (ppm) or the per-point time error; for a
            bias walk its least-squares slope over the recording per axis (what a linear bias
            drift would estimate).
        values_unit: unit of ``values``.
    """

    name: str
    scale: float
    size: float
    unit: str
    values: tuple[float, ...]
    values_unit: str


@dataclass(frozen=True)
class Simulation(Section):
    """How the run was simulated."""

    gravity_world: Vec3
    gravity_in_first_imu_frame: Vec3
    initial_imu_pose: InitialImuPose
    imu: SimulatedImu
    lidar: SimulatedLidar
    clock: SimulatedClock
    random_extrinsic: bool
    bag: SimulatedBag
    command_line: str
    licalib_version: str
    effects: tuple[InjectedEffect, ...] = ()

    def effect(self, name: str) -> InjectedEffect | None:
        """The injected effect of that name, or None."""
        return next((e for e in self.effects if e.name == name), None)


@dataclass(frozen=True)
class Truth:
    """A ``truth.yaml``: the true values and, for a simulated run, how it was made.

    Attributes:
        values: the true extrinsic, time offset and intrinsics (the result file's keys).
        scenario: the simulated motion, or None.
        seed: the random seed, or None.
        simulation: the simulation settings, or None.
        noise_seed: the seed of the sensor noise when it is not ``seed``, or None.
    """

    values: CalibrationResult
    scenario: Scenario | None = None
    seed: int | None = None
    simulation: Simulation | None = None
    noise_seed: int | None = None

    @property
    def extrinsic(self) -> Extrinsic:
        """The true ``T_imu_lidar`` and time offset."""
        return self.values.extrinsic

    @property
    def imu_intrinsics(self) -> ImuIntrinsics:
        """The true IMU intrinsics (biases: those at the first sample)."""
        return self.values.imu_intrinsics

    @property
    def lidar_intrinsics(self) -> LidarIntrinsics | None:
        """The true per-beam LiDAR intrinsics."""
        return self.values.lidar_intrinsics

    @property
    def lidar_clock_offset_s(self) -> float:
        """How far the LiDAR clock ran ahead of the IMU clock, s (0 when not simulated)."""
        return self.simulation.clock.lidar_clock_offset_s if self.simulation else 0.0

    def extrinsic_for(self, result: CalibrationResult) -> Extrinsic:
        """The true extrinsic in a calibration's terms, so that the two compare.

        The time offset is put on the calibration's clock split (its
        ``recording.lidar_clock_shift_s``, :meth:`Extrinsic.on_shifted_clock`) and, when the
        simulated IMU clock drifts, taken at the instant the calibration's offset refers to: the
        instant whose LiDAR time is its ``extra_terms.reference_ns`` when it estimated the
        drift (``t_imu = t_lidar + time_offset_s + k (t_lidar - reference)``), else the middle
        of its recording (a constant offset fitted to a drifting clock is the mean offset). The
        truth's ``time_offset_s`` holds at the simulation's first sample.
        """
        shift = result.recording.lidar_clock_shift_s if result.recording else 0.0
        ext = self.extrinsic.on_shifted_clock(self.lidar_clock_offset_s, shift)
        drift = 1e-6 * self.simulation.imu.clock_drift_ppm if self.simulation else 0.0
        if drift == 0.0 or result.recording is None or self.simulation is None:
            return ext
        if result.extra_terms is not None:
            ref_ns = result.extra_terms.reference_ns
        else:
            rec = result.recording
            ref_ns = rec.start_ns + round(0.5e9 * rec.duration_s)
        # IMU stamps run (1 + drift) times true time: the instant whose LiDAR time (on the
        # calibration's axis) is ref_ns came ext.time_offset_s after the first sample, and the
        # offset grows by drift per true second
        t_true = (ref_ns - self.simulation.clock.base_time_ns) * 1e-9 + ext.time_offset_s
        return replace(ext, time_offset_s=ext.time_offset_s + drift * t_true)

    def to_dict(self) -> dict[str, Any]:
        out = self.values.to_dict()
        if self.scenario is not None:
            out["scenario"] = self.scenario.to_dict()
        if self.seed is not None:
            out["seed"] = int(self.seed)
        if self.noise_seed is not None:
            out["noise_seed"] = int(self.noise_seed)
        if self.simulation is not None:
            out["simulation"] = self.simulation.to_dict()
        return out

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Truth:
        """Read a truth (or a calibration result used as one).

        Raises:
            ConfigError: another schema version; FileValueError: a key is missing or a value
                is not of its type.
        """
        values = CalibrationResult.from_dict(d)
        sections: dict[str, Any] = {}
        for name, kind in (("scenario", Scenario), ("simulation", Simulation)):
            if d.get(name) is not None:
                sections[name] = typed(d[name], kind, name)
        seeds = {key: typed(d.get(key), int | None, key) for key in ("seed", "noise_seed")}
        return cls(values, **seeds, **sections)

    def to_yaml(self) -> str:
        return dump_yaml(self.to_dict())

    def save(self, path: Path) -> None:
        """Write the YAML atomically."""
        write_text_atomic(Path(path), self.to_yaml())

    @classmethod
    def load(cls, path: Path) -> Truth:
        """Read a ``truth.yaml``.

        Raises:
            ConfigError: missing, a folder, not text, not YAML, not a mapping or of another
                schema version.
        """
        path = Path(path)
        data = read_yaml(path, "The truth file")
        if not isinstance(data, dict):
            msg = f"The truth file {path} is not a YAML mapping; regenerate it."
            raise ConfigError(msg)
        try:
            return cls.from_dict(data)
        except FileValueError as err:
            raise err.in_file(f"the truth file {path}") from err
