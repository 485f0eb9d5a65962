"""The true quantities of a run: trajectory, extrinsic, IMU and LiDAR intrinsics.

Every random draw comes from its own stream ``SeedSequence([seed, stream])`` so that, for
example, changing the duration or the LiDAR model does not change the drawn extrinsic.

Random intrinsics follow the paper's Table (sensor_intrinsic_setting), with its "(%)" entries
read as percent (std of ``s - 1`` = value / 100) and angles in degrees:

=========================  ===========  ==========================  ===========
LiDAR elevation ``dphi``   0.1 deg      vertical offset ``V``       0.005 m
LiDAR azimuth ``dtheta``   0.05 deg     horizontal offset ``H``     0.005 m
range scale ``s``          0.005 %      range offset ``drho``       0.01 m
gyro scale                 0.01 %       accel scale                 0.1 %
gyro non-orthogonality     0.05 deg     accel non-orthogonality     0.05 deg
=========================  ===========  ==========================  ===========

plus the gyro-to-IMU rotation ``R_wI`` (0.5 deg per Euler angle, the size of the paper's IMU
intrinsics table), constant biases (gyro 0.2 deg/s, accel 0.03 m/s^2 per axis) and, with the
``g_sensitivity`` effect, ``A_w`` entries of ``g_sensitivity_dps_per_g`` deg/s per g.
With ``random_time_offset`` the time offset is drawn uniformly within +-50 ms.
``intrinsics_scale`` multiplies all of these. An intrinsic effect named in ``spec.effects``
(:mod:`~licalib_cli.simulation.effects`) replaces its block with a draw of its own size times
``effect_scale``, from its own stream (so naming one effect changes nothing else). Beam 0 gets
zero ``dphi, dtheta, V, H``: the calibration fixes them as the gauge (method.md section 4), so
the truth uses the same gauge. A non-repetitive LiDAR (``mid360``, ``avia``) has no per-beam
intrinsics: its LiDAR intrinsics stay nominal while the IMU's are drawn as usual.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from enum import IntEnum
from pathlib import Path

import numpy as np
import numpy.typing as npt

from licalib_cli.errors import ConfigError
from licalib_cli.models.intrinsics import ImuIntrinsics, LidarIntrinsics
from licalib_cli.results import CalibrationResult, Extrinsic, matrix_from_rpy_deg
from licalib_cli.simulation.effects import Effect
from licalib_cli.simulation.lidar_models import LidarModel, lidar_model
from licalib_cli.simulation.scenarios import ScenarioMotion, make_motion
from licalib_cli.simulation.spec import (
    RANDOM_TIME_OFFSET_MAX_S,
    STANDARD_GRAVITY,
    IntrinsicsMode,
    SimulationSpec,
)
from licalib_cli.simulation.trajectories import EulerTrajectory
from licalib_cli.simulation.world import World, default_world

F64 = npt.NDArray[np.float64]

# Standard deviations of the random intrinsics (see the module docstring).
LIDAR_ELEVATION_STD_DEG = 0.1
LIDAR_AZIMUTH_STD_DEG = 0.05
LIDAR_VERTICAL_STD_M = 0.005
LIDAR_HORIZONTAL_STD_M = 0.005
LIDAR_RANGE_SCALE_STD = 0.005 / 100.0
LIDAR_RANGE_OFFSET_STD_M = 0.01
GYRO_SCALE_STD = 0.01 / 100.0
ACCEL_SCALE_STD = 0.1 / 100.0
GYRO_MISALIGNMENT_STD_DEG = 0.05
ACCEL_MISALIGNMENT_STD_DEG = 0.05
GYRO_ROTATION_STD_DEG = 0.5
GYRO_BIAS_STD = float(np.radians(0.2))  # rad/s
ACCEL_BIAS_STD = 0.03  # m/s^2
RANDOM_TRANSLATION_MAX_M = 0.5


class Stream(IntEnum):
    """Independent random streams of a run."""

    EXTRINSIC = 1
    IMU_INTRINSICS = 2
    LIDAR_INTRINSICS = 3
    TRAJECTORY = 4
    IMU_NOISE = 5
    LIDAR_NOISE = 6
    EFFECTS = 7
    RECORD_DELAY = 8


def rng_for(seed: int, stream: Stream, *extra: int) -> np.random.Generator:
    """The generator of one stream (``extra`` e.g. a scan index)."""
    return np.random.default_rng(np.random.SeedSequence([int(seed), int(stream), *extra]))


@dataclass(frozen=True)
class SimulationSetup:
    """Resolved truth of a run.

    Attributes:
        spec: the options.
        world: the room.
        motion: trajectory of the IMU and scenario annotations.
        extrinsic: ``T_imu_lidar`` and ``time_offset_s`` (rounded to ns).
        imu_intrinsics: IMU model incl. constant biases (the biases at ``t = 0``).
        lidar_intrinsics: per-beam model, beams indexed by ring.
        lidar_model: the LiDAR's firing pattern and layout.
    """

    spec: SimulationSpec
    world: World
    motion: ScenarioMotion
    extrinsic: Extrinsic
    imu_intrinsics: ImuIntrinsics
    lidar_intrinsics: LidarIntrinsics
    lidar_model: LidarModel

    @property
    def trajectory(self) -> EulerTrajectory:
        return self.motion.trajectory

    @property
    def time_offset_ns(self) -> int:
        return round(self.extrinsic.time_offset_s * 1e9)

    @property
    def lidar_clock_offset_ns(self) -> int:
        return round(self.spec.lidar_clock_offset_s * 1e9)

    def lidar_pose_at(self, t: npt.ArrayLike) -> tuple[F64, F64]:
        """``T_W_L(t) = T_W_I(t) T_I_L`` at true times ``t`` (N,) s: ``(R (N,3,3), p (N,3))``."""
        r_wi, p_wi = self.trajectory.pose_at(t)
        r_wl = r_wi @ self.extrinsic.rotation
        p_wl = p_wi + r_wi @ self.extrinsic.translation
        return r_wl, p_wl


def draw_time_offset(spec: SimulationSpec) -> float:
    """``time_offset_s`` from the options, or drawn uniformly within +-50 ms; rounded to ns.

    The draw comes from the extrinsic stream's sub-stream ``SeedSequence([seed, EXTRINSIC, 1])``,
    so it is the same for a seed whether or not the extrinsic is drawn too, and it leaves every
    other draw of the run unchanged.
    """
    if not spec.random_time_offset:
        return round(spec.time_offset_s * 1e9) / 1e9
    rng = rng_for(spec.seed, Stream.EXTRINSIC, 1)
    drawn = rng.uniform(-RANDOM_TIME_OFFSET_MAX_S, RANDOM_TIME_OFFSET_MAX_S)
    return round(drawn * 1e9) / 1e9


def draw_extrinsic(spec: SimulationSpec) -> Extrinsic:
    """The extrinsic from the options, or a random one (any rotation, |t| <= 0.5 m).

    The time offset comes from :func:`draw_time_offset`.
    """
    from scipy.spatial.transform import Rotation

    offset = draw_time_offset(spec)
    if not spec.random_extrinsic:
        return Extrinsic(
            rotation=matrix_from_rpy_deg(spec.resolved_rpy_deg),
            translation=np.asarray(spec.translation, dtype=np.float64),
            time_offset_s=offset,
        )
    rng = rng_for(spec.seed, Stream.EXTRINSIC)
    if rng.uniform() < 0.5:
        # One of the 24 axis-aligned mountings (90/180 deg flips) with a small perturbation.
        cube = Rotation.create_group("O")[int(rng.integers(24))]
        small = Rotation.from_rotvec(np.radians(rng.normal(0.0, 5.0, 3)))
        rot = (cube * small).as_matrix()
    else:
        rot = Rotation.random(random_state=rng).as_matrix()
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    radius = RANDOM_TRANSLATION_MAX_M * rng.uniform() ** (1.0 / 3.0)
    return Extrinsic(rotation=rot, translation=direction * radius, time_offset_s=offset)


def _load_intrinsics_file(path: Path) -> CalibrationResult:
    return CalibrationResult.load(Path(path))


def draw_imu_intrinsics(spec: SimulationSpec) -> ImuIntrinsics:
    """IMU intrinsics from a file, the paper's Table (random) or identity; biases included."""
    from scipy.spatial.transform import Rotation

    rng = rng_for(spec.seed, Stream.IMU_INTRINSICS)
    k = spec.intrinsics_scale
    # Always draw in the same order so every field is reproducible on its own.
    d_gs = rng.normal(0.0, GYRO_SCALE_STD, 3)
    d_as = rng.normal(0.0, ACCEL_SCALE_STD, 3)
    m_g = rng.normal(0.0, np.radians(GYRO_MISALIGNMENT_STD_DEG), 3)
    m_a = rng.normal(0.0, np.radians(ACCEL_MISALIGNMENT_STD_DEG), 3)
    r_g = rng.normal(0.0, GYRO_ROTATION_STD_DEG, 3)
    b_g = rng.normal(0.0, GYRO_BIAS_STD, 3)
    b_a = rng.normal(0.0, ACCEL_BIAS_STD, 3)
    a_w = rng.normal(0.0, 1.0, (3, 3))
    if spec.intrinsics_file is not None:
        base = _load_intrinsics_file(spec.intrinsics_file).imu_intrinsics
    elif spec.intrinsics is IntrinsicsMode.RANDOM:
        q = Rotation.from_euler("ZYX", k * r_g[::-1], degrees=True).as_quat()
        base = ImuIntrinsics(
            gyro_scale=1.0 + k * d_gs,
            gyro_misalignment=k * m_g,
            gyro_rotation=q,
            accel_scale=1.0 + k * d_as,
            accel_misalignment=k * m_a,
            gyro_bias=k * b_g,
            accel_bias=k * b_a,
        )
    else:
        base = ImuIntrinsics()
    if Effect.G_SENSITIVITY in spec.effects:
        sigma = np.radians(spec.resolved_g_sensitivity_dps_per_g) / STANDARD_GRAVITY
        base = base.with_(gyro_g_sensitivity=sigma * a_w)
    base = _named_imu_effects(spec, base)
    if spec.gyro_bias is not None:
        base = base.with_(gyro_bias=np.asarray(spec.gyro_bias, dtype=np.float64))
    if spec.accel_bias is not None:
        base = base.with_(accel_bias=np.asarray(spec.accel_bias, dtype=np.float64))
    return base


def draw_lidar_intrinsics(spec: SimulationSpec, model: LidarModel) -> LidarIntrinsics:
    """Per-beam intrinsics from a file, the paper's Table (random) or nominal.

    A non-repetitive scanner has no fixed beams and so no per-beam intrinsics: always nominal
    (zero corrections for each of its lines), whatever ``intrinsics`` or the file say.
    """
    b = model.num_beams
    if not model.repeats:
        return LidarIntrinsics.nominal(model.nominal_elevation)
    if spec.intrinsics_file is not None:
        loaded = _load_intrinsics_file(spec.intrinsics_file).lidar_intrinsics
        if loaded is None or loaded.num_beams != b:
            got = "none" if loaded is None else f"{loaded.num_beams} beams"
            msg = (
                f"{spec.intrinsics_file} has lidar_intrinsics for {got}, but the "
                f"{model.kind.value} has {b} beams; use a file written for this LiDAR."
            )
            raise ConfigError(msg)
        return loaded.with_(nominal_elevation=model.nominal_elevation.copy())
    nominal = LidarIntrinsics.nominal(model.nominal_elevation)
    if spec.intrinsics is IntrinsicsMode.NONE:
        return nominal
    rng = rng_for(spec.seed, Stream.LIDAR_INTRINSICS)
    k = spec.intrinsics_scale
    d_phi = np.radians(rng.normal(0.0, LIDAR_ELEVATION_STD_DEG, b)) * k
    d_theta = np.radians(rng.normal(0.0, LIDAR_AZIMUTH_STD_DEG, b)) * k
    v = rng.normal(0.0, LIDAR_VERTICAL_STD_M, b) * k
    h = rng.normal(0.0, LIDAR_HORIZONTAL_STD_M, b) * k
    s = 1.0 + rng.normal(0.0, LIDAR_RANGE_SCALE_STD, b) * k
    d_rho = rng.normal(0.0, LIDAR_RANGE_OFFSET_STD_M, b) * k
    for arr in (d_phi, d_theta, v, h):
        arr[0] = 0.0  # gauge: beam 0 keeps its angles and offsets
    return nominal.with_(
        elevation_correction=d_phi,
        azimuth_correction=d_theta,
        vertical_offset=v,
        horizontal_offset=h,
        range_scale=s,
        range_offset=d_rho,
    )


def _effect_rng(spec: SimulationSpec, effect: Effect) -> np.random.Generator:
    return rng_for(spec.seed, Stream.EFFECTS, list(Effect).index(effect))


def _named_imu_effects(spec: SimulationSpec, base: ImuIntrinsics) -> ImuIntrinsics:
    """``base`` with each named IMU intrinsic effect drawn at its size times the scale."""
    from scipy.spatial.transform import Rotation

    for effect in spec.effects:
        if effect not in _IMU_DRAWN:
            continue
        rng = _effect_rng(spec, effect)
        size = spec.effect_size(effect)
        draw = rng.normal(0.0, 1.0, 3) * size
        if effect is Effect.GYRO_SCALE:
            base = base.with_(gyro_scale=1.0 + draw)
        elif effect is Effect.ACCEL_SCALE:
            base = base.with_(accel_scale=1.0 + draw)
        elif effect is Effect.GYRO_MISALIGNMENT:
            base = base.with_(gyro_misalignment=np.radians(draw))
        elif effect is Effect.ACCEL_MISALIGNMENT:
            base = base.with_(accel_misalignment=np.radians(draw))
        else:  # gyro rotation: Z-Y-X Euler angles as the random intrinsics
            q = Rotation.from_euler("ZYX", draw[::-1], degrees=True).as_quat()
            base = base.with_(gyro_rotation=q)
    return base


_IMU_DRAWN = (
    Effect.GYRO_SCALE,
    Effect.GYRO_MISALIGNMENT,
    Effect.GYRO_ROTATION,
    Effect.ACCEL_SCALE,
    Effect.ACCEL_MISALIGNMENT,
)
_LIDAR_DRAWN = {
    Effect.LIDAR_ELEVATION: ("elevation_correction", True, True),
    Effect.LIDAR_AZIMUTH: ("azimuth_correction", True, True),
    Effect.LIDAR_VERTICAL_OFFSET: ("vertical_offset", False, True),
    Effect.LIDAR_HORIZONTAL_OFFSET: ("horizontal_offset", False, True),
    Effect.LIDAR_RANGE_SCALE: ("range_scale", False, False),
    Effect.LIDAR_RANGE_OFFSET: ("range_offset", False, False),
}
"""LiDAR effect -> (intrinsics field, size in degrees, beam 0 is the gauge)."""


def _named_lidar_effects(
    spec: SimulationSpec, base: LidarIntrinsics, num_beams: int
) -> LidarIntrinsics:
    """``base`` with each named per-beam effect drawn at its size times the scale."""
    for effect in spec.effects:
        if effect not in _LIDAR_DRAWN:
            continue
        name, degrees, gauge = _LIDAR_DRAWN[effect]
        draw = _effect_rng(spec, effect).normal(0.0, 1.0, num_beams) * spec.effect_size(effect)
        if degrees:
            draw = np.radians(draw)
        if gauge:
            draw[0] = 0.0
        if effect is Effect.LIDAR_RANGE_SCALE:
            draw = 1.0 + draw
        base = base.with_(**{name: draw})
    return base


ROOM_MARGIN_M = 0.2
"""The IMU and the LiDAR stay at least this far from every surface of the room."""


FREE_SPACE_SEARCH_M = 1.0
"""Farthest a motion is moved to keep the rig clear of the room's objects."""
_FREE_SPACE_STEP_M = 0.1
_FREE_SPACE_RATE_HZ = 100.0
_FREE_SPACE_POINTS = 20_000


def in_free_space(
    motion: ScenarioMotion, extrinsic: Extrinsic, world: World, duration_s: float
) -> ScenarioMotion:
    """``motion`` moved as a whole, by the least translation that keeps both the IMU and the
    LiDAR :data:`ROOM_MARGIN_M` from every surface over ``duration_s``: inside the room's walls,
    floor and ceiling, and outside its boxes, pillars and panels; unchanged when they are.

    A long lever arm pointing down put the LiDAR under the floor for most of a shake (the
    benchmark's seed 9642: 1.5 m below an IMU held at 1.5 m), and it scanned the room from
    outside, which no rig does: the odometry lost it and the calibration failed on a recording
    that could not exist (15 of the 180 trust benchmark bags of seeds 7400-8229 came within
    the margin of a wall, 9 went through one). A LiDAR 1.8 m from the IMU of a walking rig
    passed through floor boxes and wall clutter for a tenth of the walk, scanning the inside of
    a box, and the calibration named a LiDAR effect that was not there. The motion's shape, and
    so everything the calibration sees of it, is kept; only where in the room it happens
    changes. The walls give the least move exactly; the objects a search over moves on a
    :data:`_FREE_SPACE_STEP_M` grid up to :data:`FREE_SPACE_SEARCH_M` further, the shortest
    clear one taken (sampled at :data:`_FREE_SPACE_RATE_HZ`).

    Raises:
        ConfigError: the motion with this lever arm does not fit in the room at all, or
            passes through an object wherever it is moved within the search.
    """
    traj = motion.trajectory
    t = np.linspace(0.0, duration_s, max(int(duration_s * _FREE_SPACE_RATE_HZ), 2) + 1)
    r_wi, p_wi = traj.pose_at(t)
    p_wl = p_wi + r_wi @ extrinsic.translation
    both = np.concatenate([p_wi, p_wl])
    lo, hi = world.room_min + ROOM_MARGIN_M, world.room_max - ROOM_MARGIN_M
    low, high = both.min(axis=0), both.max(axis=0)
    lever = np.round(extrinsic.translation, 3).tolist()
    if np.any(high - low > hi - lo):
        msg = (
            f"The rig's motion with the lever arm {lever} m does not fit in the simulated room; "
            "use a shorter lever arm (--translation)."
        )
        raise ConfigError(msg)
    walls = np.maximum(lo - low, 0.0) - np.maximum(high - hi, 0.0)
    shift = _clear_of_objects(both, world, walls, lo - low, hi - high)
    if shift is None:
        msg = (
            f"The rig's motion with the lever arm {lever} m passes through the simulated room's "
            f"objects wherever it is moved within {FREE_SPACE_SEARCH_M:g} m; use a shorter "
            "lever arm (--translation) or another seed."
        )
        raise ConfigError(msg)
    if not np.any(shift):
        return motion
    px, py, pz = (
        replace(sig, offset=sig.offset + float(d))
        for sig, d in zip(traj.position, shift, strict=True)
    )
    return replace(motion, trajectory=replace(traj, position=(px, py, pz)))


def _clear_of_objects(
    points: F64, world: World, start: F64, lowest: F64, highest: F64
) -> F64 | None:
    """The shortest move of ``points``, ``start`` or ``start`` plus a grid step within the
    search and between ``lowest`` and ``highest`` per axis, that keeps them
    :data:`ROOM_MARGIN_M` from the room's objects; None when none does.

    A distance changes by at most as much as the points move, so a move ``d`` from ``start``
    is tested only on the points nearer an object than the margin plus ``|d|``, first every
    sixteenth of them (which rejects most moves), then all.
    """
    gap = world.clearance(points + start, room=False)
    if not gap.shape[0] or gap.min() >= ROOM_MARGIN_M:
        return start
    n = round(FREE_SPACE_SEARCH_M / _FREE_SPACE_STEP_M)
    g = np.arange(-n, n + 1) * _FREE_SPACE_STEP_M
    grid = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)
    moves = start + grid[np.linalg.norm(grid, axis=1) <= FREE_SPACE_SEARCH_M + 1e-9]
    moves = moves[np.all((moves >= lowest - 1e-9) & (moves <= highest + 1e-9), axis=1)]
    moves = moves[np.argsort(np.linalg.norm(moves, axis=1), kind="stable")]

    def least(pts: F64, m: F64) -> F64:
        moved = (pts[None] + m[:, None]).reshape(-1, 3)
        return np.asarray(world.clearance(moved, room=False).reshape(m.shape[0], -1).min(axis=1))

    away = np.linalg.norm(moves - start, axis=1)
    i = 0
    while i < moves.shape[0]:
        # the batch's moves reach at most as far as the next few grid shells
        span = away[i : i + 64].max()
        near = points[gap < ROOM_MARGIN_M + span]
        batch = min(max(_FREE_SPACE_POINTS // max(near[::16].shape[0], 1), 1), 64)
        m = moves[i : i + batch]
        for j in np.flatnonzero(least(near[::16], m) >= ROOM_MARGIN_M):
            if least(near, m[j : j + 1])[0] >= ROOM_MARGIN_M:
                return np.asarray(m[j], dtype=np.float64)
        i += batch
    return None


def build_setup(spec: SimulationSpec) -> SimulationSetup:
    """Resolve every true quantity of a run (deterministic in ``spec``); the motion is moved
    to keep the rig in the room's free space (:func:`in_free_space`)."""
    model = lidar_model(spec.lidar)
    world = default_world()
    extrinsic = draw_extrinsic(spec)
    motion = in_free_space(
        make_motion(spec, rng_for(spec.seed, Stream.TRAJECTORY)),
        extrinsic,
        world,
        spec.resolved_duration_s,
    )
    return SimulationSetup(
        spec=spec,
        world=world,
        motion=motion,
        extrinsic=extrinsic,
        imu_intrinsics=draw_imu_intrinsics(spec),
        lidar_intrinsics=_named_lidar_effects(
            spec, draw_lidar_intrinsics(spec, model), model.num_beams
        ),
        lidar_model=model,
    )
