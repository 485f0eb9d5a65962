"""``licalib calibrate``: one call from a bag to a calibration, stage by stage.

Data flow (method.md sections 5-8)::

    bag --read_segment--> Recording (IMU samples, LiDAR scans; int64 ns)
        --run_odometry--> LiDAR poses (kiss-icp, stamped at each sweep's latest point)
        --initialise----> coarse time offset (|w| cross-correlation), hand-eye rotation,
                          rotation spline from the gyro, position spline from odometry, gravity
        --rounds--------> surfel map in {G} + point-to-plane associations, then a
                          Levenberg-Marquardt round (Schur complement + truncated SVD), repeated
                          with the map rebuilt from the latest estimate until it settles
        --> CalibrationRun (result file content, uncertainties, observability, verdict)

Frames and time: ``{G}`` is the IMU frame at the first IMU sample of the segment (``t0_ns``),
the splines carry ``T_G_I(t)`` on the IMU clock in seconds since ``t0_ns``, and a point stamped
``tau`` on the LiDAR clock is evaluated at ``tau + time_offset_s``.
"""

from __future__ import annotations

import hashlib
import logging
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from licalib_cli import __version__
from licalib_cli.config import CalibConfig
from licalib_cli.errors import ExcitationError, SolverError
from licalib_cli.estimation import (
    CalibrationState,
    FreeParameters,
    ImuData,
    LidarPoints,
    NoiseModel,
    Planes,
    build_problem,
    state_from_problem,
)
from licalib_cli.geometry import so3
from licalib_cli.initialization.rotation import (
    GyroIntegrator,
    HandEyeConfig,
    HandEyeRotation,
    estimate_rotation_extrinsic,
    lidar_rotation_at,
)
from licalib_cli.initialization.rotation_search import search_rotation_extrinsic
from licalib_cli.initialization.single_axis import rotation_axes, single_axis_rotation
from licalib_cli.initialization.time_offset import (
    TimeOffsetConfig,
    TimeOffsetEstimate,
    estimate_time_offset,
    estimate_time_offset_aligned,
    estimate_time_offset_joint,
)
from licalib_cli.io.reader import Recording, read_segment
from licalib_cli.measurements import LidarScan
from licalib_cli.models.intrinsics import LidarIntrinsics, lidar_point, nominal_point
from licalib_cli.odometry import OdometryConfig, PoseSeries, refine_odometry, run_odometry
from licalib_cli.progress import NullProgress, Progress
from licalib_cli.results import CalibrationResult, Extrinsic, matrix_from_rpy_deg
from licalib_cli.solver.lm import LMParams, SolverReport, solve
from licalib_cli.spline import R3Spline, SO3Spline, UniformKnots
from licalib_cli.surfels import SurfelConfig, associate_points, build_surfels

logger = logging.getLogger(__name__)

F64 = npt.NDArray[np.float64]
F32 = npt.NDArray[np.float32]
_NS = 1_000_000_000
GRAVITY_NORM = 9.81

__all__ = ["CalibrationRun", "InitialGuess", "RoundSummary", "Verdict", "calibrate"]


# ------------------------------------------------------------------------------ data types


@dataclass(frozen=True)
class InitialGuess:
    """What initialisation found before any optimisation.

    Attributes:
        R_imu_lidar: (3, 3) initial extrinsic rotation.
        t_imu_lidar: (3,) initial translation, m.
        time_offset_s: initial ``t_imu = t_lidar + time_offset_s``.
        rotation_source: ``"hand-eye"`` or ``"config"``.
        time_offset_source: ``"cross-correlation"`` or ``"config"``.
        correlation: peak normalised correlation of the angular speeds (NaN when not used).
        hand_eye: the hand-eye solution with its conditioning, or None.
        gravity_G: (3,) initial gravity in ``{G}``, m/s^2.
    """

    R_imu_lidar: F64
    t_imu_lidar: F64
    time_offset_s: float
    rotation_source: str
    time_offset_source: str
    correlation: float
    hand_eye: HandEyeRotation | None
    gravity_G: F64


@dataclass(frozen=True)
class RoundSummary:
    """One refinement round (map rebuild + LM).

    Attributes:
        index: 1-based round number.
        free: names of the parameter groups estimated.
        points: associated points used.
        surfels: surfels in the map.
        associated_fraction: share of sampled points associated with a surfel.
        rms_m: RMS point-to-plane distance after the round, m.
        cost_start: cost before the round.
        cost_end: cost after the round.
        iterations: LM iterations.
        extrinsic: estimate after the round.
        seconds: wall time of the round.
        distances_before_m: (P,) float32 signed point-to-plane distances of the associated points
            at the start of the round (their own map), m.
        distances_after_m: (P,) float32 the same after the round (same map), m.
    """

    index: int
    free: tuple[str, ...]
    points: int
    surfels: int
    associated_fraction: float
    rms_m: float
    cost_start: float
    cost_end: float
    iterations: int
    extrinsic: Extrinsic
    seconds: float
    distances_before_m: F32 = field(default_factory=lambda: np.zeros(0, np.float32), repr=False)
    distances_after_m: F32 = field(default_factory=lambda: np.zeros(0, np.float32), repr=False)


@dataclass(frozen=True)
class Verdict:
    """Whether the result can be trusted.

    Attributes:
        status: ``"pass"``, ``"warn"`` or ``"fail"``.
        reasons: one sentence per finding (empty for a clean pass).
    """

    status: str
    reasons: tuple[str, ...] = ()


@dataclass(frozen=True)
class CalibrationRun:
    """Everything ``calibrate`` produces.

    Attributes:
        result: the result file content (schema v1 plus uncertainty, observability, provenance).
        state: the final estimate of every parameter (splines included).
        initial: the initial guess.
        rounds: one summary per refinement round.
        solver: the last round's solver report (covariance and spectrum at the final estimate).
        verdict: pass / warn / fail with reasons.
        timings: wall seconds per stage, in order.
        recording: summary of the data used (topics, counts, duration, clock offset).
        warnings: non-fatal findings.
    """

    result: CalibrationResult
    state: CalibrationState
    initial: InitialGuess
    rounds: tuple[RoundSummary, ...]
    solver: SolverReport
    verdict: Verdict
    timings: dict[str, float]
    recording: dict[str, Any]
    warnings: tuple[str, ...] = ()


@dataclass(frozen=True)
class PointSample:
    """Points kept for the optimisation, with their raw measurements.

    Attributes:
        t_ns: (N,) LiDAR-clock time of each point, ns.
        beam: (N,) beam index.
        rho: (N,) raw range, m.
        theta: (N,) raw azimuth, rad.
        offset: (N, 3) published point minus the nominal model point, m (zero for an ideal
            driver conversion); kept so that nominal intrinsics reproduce the published cloud.
    """

    t_ns: npt.NDArray[np.int64]
    beam: npt.NDArray[np.int64]
    rho: F64
    theta: F64
    offset: F64

    def __len__(self) -> int:
        return int(self.t_ns.shape[0])

    def subset(self, mask: npt.NDArray[np.bool_]) -> PointSample:
        return PointSample(
            self.t_ns[mask], self.beam[mask], self.rho[mask], self.theta[mask], self.offset[mask]
        )


class _Timer:
    def __init__(self) -> None:
        self.timings: dict[str, float] = {}

    @contextmanager
    def stage(self, name: str, progress: Progress, total: int | None = None) -> Iterator[None]:
        progress.stage(name, total)
        start = time.perf_counter()
        try:
            yield
        finally:
            self.timings[name] = self.timings.get(name, 0.0) + time.perf_counter() - start


# ------------------------------------------------------------------------------ stages


def odometry_config(cfg: CalibConfig) -> OdometryConfig:
    """kiss-icp settings from the config tree."""
    o = cfg.odometry
    return OdometryConfig(
        voxel_size=o.voxel_size_m,
        max_range=o.max_range_m,
        min_range=o.min_range_m,
        deskew=o.deskew,
        max_points_per_voxel=o.max_points_per_voxel,
    )


def nominal_elevations(scans: tuple[LidarScan, ...], cfg: CalibConfig) -> F64:
    """Nominal elevation ``phi_i`` of each beam, rad: the config's table or the data's median."""
    rings = [s.ring for s in scans if s.ring is not None and len(s) > 0]
    if not rings:
        msg = "The LiDAR clouds carry no beam index; set lidar.ring_field or lidar.num_beams."
        raise ExcitationError(msg)
    n_beams = int(max(int(r.max()) for r in rings)) + 1
    if cfg.lidar.nominal_elevation_deg is not None:
        table = np.radians(np.asarray(cfg.lidar.nominal_elevation_deg, dtype=np.float64))
        if table.shape[0] < n_beams:
            msg = (
                f"lidar.nominal_elevation_deg lists {table.shape[0]} beams but the data has "
                f"ring numbers up to {n_beams - 1}; list one elevation per ring."
            )
            raise ExcitationError(msg)
        return table
    step = max(1, len(scans) // 20)
    xyz = np.concatenate([s.xyz for s in scans[::step] if s.ring is not None])
    ring = np.concatenate([s.ring for s in scans[::step] if s.ring is not None]).astype(np.int64)
    elev = np.arcsin(np.clip(xyz[:, 2] / np.maximum(np.linalg.norm(xyz, axis=1), 1e-9), -1, 1))
    order = np.argsort(ring, kind="stable")
    ring, elev = ring[order], elev[order]
    bounds = np.searchsorted(ring, np.arange(n_beams + 1))
    out = np.zeros(n_beams)
    for b in range(n_beams):  # loop over beams (at most a few hundred), not points
        seg = elev[bounds[b] : bounds[b + 1]]
        out[b] = float(np.median(seg)) if seg.size else 0.0
    return out


def points_per_scan(cfg: CalibConfig, num_scans: int, wanted: int | None = None) -> int:
    """Points kept per scan: ``wanted`` (default ``surfels.points_per_scan``), lowered so that
    all scans together keep at most ``surfels.max_points``."""
    per_scan = cfg.surfels.points_per_scan if wanted is None else wanted
    return max(1, min(per_scan, cfg.surfels.max_points // max(num_scans, 1)))


def sample_points(
    scans: tuple[LidarScan, ...], phi: F64, per_scan: int, cfg: CalibConfig, seed: int = 0
) -> PointSample:
    """Keep up to ``per_scan`` points of each sweep, spread uniformly over the sweep."""
    rng = np.random.default_rng(seed)
    parts: list[tuple[Any, ...]] = []
    for scan in scans:
        if scan.ring is None or len(scan) == 0:
            continue
        rho = np.linalg.norm(scan.xyz, axis=1)
        ok = (rho >= cfg.lidar.min_range_m) & (rho <= cfg.lidar.max_range_m)
        idx = np.flatnonzero(ok)
        if idx.size > per_scan:
            idx = np.sort(rng.choice(idx, per_scan, replace=False))
        parts.append((scan.t_ns[idx], scan.ring[idx].astype(np.int64), scan.xyz[idx], rho[idx]))
    t_ns = np.concatenate([p[0] for p in parts])
    beam = np.concatenate([p[1] for p in parts])
    xyz = np.concatenate([p[2] for p in parts])
    rho = np.concatenate([p[3] for p in parts])
    theta = np.arctan2(xyz[:, 1], xyz[:, 0])
    offset = xyz - nominal_point(rho, theta, phi[beam])
    return PointSample(t_ns, beam, rho, theta, offset)


def _hand_eye_config(cfg: CalibConfig) -> HandEyeConfig:
    ini = cfg.initialization
    return HandEyeConfig(
        min_angle_deg=ini.min_rotation_deg,
        max_singular_ratio=ini.max_singular_ratio,
        min_axis_ratio=ini.min_axis_ratio,
    )


def _with_rotation_hint(err: ExcitationError) -> ExcitationError:
    msg = (
        f"{str(err).rstrip('.')}, or give initialization.rotation_rpy_deg in the config to "
        "start from a known rotation."
    )
    return ExcitationError(msg)


def searched_rotation(
    rec: Recording,
    kiss: PoseSeries,
    ocfg: OdometryConfig,
    gyro: GyroIntegrator,
    t_c: float,
    cfg: CalibConfig,
    max_rounds: int = 4,
) -> tuple[F64, PoseSeries, HandEyeRotation]:
    """Rotation extrinsic when the LiDAR-only odometry cannot follow the motion.

    A global search over SO(3) by map sharpness (:mod:`rotation_search`) gives a rotation within
    a few degrees without any odometry; then rounds of gyro-aided odometry (deskew and seed
    rotations from the gyro through the current rotation) and hand-eye bring it to the accuracy
    of hand-eye on good odometry.

    Returns:
        ``(R_imu_lidar, poses, hand_eye)``.

    Raises:
        ExcitationError: the search is ambiguous (rotation about one axis only) or hand-eye on the
            gyro-aided odometry is still refused.
    """
    found = search_rotation_extrinsic(rec.scans, gyro, t_c)
    if found.ambiguity < 1.02:
        msg = (
            "Rotation excitation is too weak: the LiDAR odometry did not follow the motion and "
            "no rotation extrinsic makes the map clearly sharper than others (the rig turned "
            "about one axis only); rotate the rig about at least two axes during the recording"
        )
        raise ExcitationError(msg)
    rot = found.R_imu_lidar
    hand_eye: HandEyeRotation | None = None
    poses = kiss
    for _ in range(max_rounds):
        poses = refine_odometry(
            rec.scans, kiss, ocfg, rotation_at=lidar_rotation_at(gyro, rot, t_c)
        )
        new = estimate_rotation_extrinsic(gyro, poses, time_offset_s=t_c, cfg=_hand_eye_config(cfg))
        step = float(np.degrees(np.abs(so3.log(rot.T @ new.R_imu_lidar)).max()))
        rot, hand_eye = new.R_imu_lidar, new
        logger.info("Gyro-aided hand-eye round after the search: rotation moved %.3f deg.", step)
        if step < 0.5:  # the rounds at the coarse time offset that follow do the rest
            break
    assert hand_eye is not None
    return rot, poses, hand_eye


SINGLE_AXIS = "single axis + accelerations"


def initial_rotation(
    rec: Recording,
    kiss: PoseSeries,
    poses: PoseSeries,
    ocfg: OdometryConfig,
    gyro: GyroIntegrator,
    t_c: float,
    cfg: CalibConfig,
) -> tuple[F64, PoseSeries, HandEyeRotation | None, str]:
    """Hand-eye rotation on the LiDAR-only odometry, or another way when that fails.

    Hand-eye is trusted when it is well conditioned and its residual is below
    ``initialization.max_hand_eye_residual_deg``. Otherwise: when the rig turned about one axis
    only (planar, vehicle-like motion) the axis and the accelerations in the plane give the
    rotation (:func:`single_axis_rotation`); else the LiDAR-only odometry did not follow a
    violent motion and :func:`searched_rotation` takes over, the better-fitting of the two being
    kept when both succeed.

    Returns:
        ``(R_imu_lidar, poses, hand_eye, source)`` with ``source`` ``"hand-eye"``,
        ``"search + gyro-aided hand-eye"`` or :data:`SINGLE_AXIS` (``hand_eye`` None then);
        ``poses`` are the odometry the rotation rests on.

    Raises:
        ExcitationError: no way determines the rotation.
    """
    ini = cfg.initialization
    first: HandEyeRotation | None = None
    failure: ExcitationError | None = None
    try:
        first = estimate_rotation_extrinsic(
            gyro, poses, time_offset_s=t_c, cfg=_hand_eye_config(cfg)
        )
    except ExcitationError as err:
        failure = err
        logger.info("Hand-eye on the LiDAR-only odometry refused: %s", err)
    else:
        if first.residual_rms_deg <= ini.max_hand_eye_residual_deg or not ini.rotation_search:
            return first.R_imu_lidar, poses, first, "hand-eye"
        logger.info(
            "Hand-eye residual %.2f deg: the LiDAR-only odometry may not follow the motion.",
            first.residual_rms_deg,
        )
    t_imu = poses.t_ns + np.int64(round(t_c * 1e9))
    t_imu = t_imu[(t_imu >= gyro.t_ns[0]) & (t_imu <= gyro.t_ns[-1])]
    if first is None and rotation_axes(gyro, t_imu).second_to_first < ini.min_axis_ratio:
        found = single_axis_rotation(rec.imu, gyro, poses, t_c, ini.min_rotation_deg)
        return found.R_imu_lidar, poses, None, SINGLE_AXIS
    if not ini.rotation_search:
        assert failure is not None
        raise _with_rotation_hint(failure)
    try:
        rot, searched_poses, hand_eye = searched_rotation(rec, kiss, ocfg, gyro, t_c, cfg)
    except ExcitationError as err:
        if first is not None:
            return first.R_imu_lidar, poses, first, "hand-eye"
        assert failure is not None
        raise _with_rotation_hint(failure) from err
    if first is not None and first.residual_rms_deg <= hand_eye.residual_rms_deg:
        return first.R_imu_lidar, poses, first, "hand-eye"
    return rot, searched_poses, hand_eye, "search + gyro-aided hand-eye"


def initialise(
    rec: Recording,
    kiss: PoseSeries,
    poses: PoseSeries,
    ocfg: OdometryConfig,
    cfg: CalibConfig,
    gyro: GyroIntegrator,
) -> tuple[F64, float, str, str, float, HandEyeRotation | None, PoseSeries]:
    """Initial extrinsic rotation and time offset (method.md 5.3-5.4).

    Order: the rotation with a zero offset (hand-eye, robust to offsets of tens of ms, or the
    sharpness search when the LiDAR-only odometry cannot follow the motion), then the time
    offset by cross-correlating the angular-velocity vectors (the LiDAR's rotated into the IMU
    frame; the angular speed alone when that fails), then hand-eye again at that offset.

    Returns:
        ``(R_imu_lidar, time_offset_s, rotation_source, time_offset_source, correlation,
        hand_eye, poses)``.
    """
    ini = cfg.initialization
    he_cfg = _hand_eye_config(cfg)
    hand_eye: HandEyeRotation | None = None
    t_guess = 0.0 if ini.time_offset_s is None else float(ini.time_offset_s)
    if ini.rotation_rpy_deg is not None:
        rot, r_source = matrix_from_rpy_deg(ini.rotation_rpy_deg), "config"
    else:
        rot, poses, hand_eye, r_source = initial_rotation(
            rec, kiss, poses, ocfg, gyro, t_guess, cfg
        )

    correlation = float("nan")
    if ini.time_offset_s is not None:
        t_c, t_source = float(ini.time_offset_s), "config"
    else:
        toc = TimeOffsetConfig(
            max_lag_s=ini.time_offset_max_lag_s, min_peak_correlation=ini.min_peak_correlation
        )
        est = coarse_time_offset(rec, poses, rot, toc)
        if est is not None and est.ok:
            t_c, t_source = float(est.time_offset_s), "cross-correlation"
            correlation = float(est.peak_correlation)
        else:
            reason = est.reason if est is not None else "the angular rate hardly varies"
            logger.warning("Coarse time offset not found (%s); starting from 0 s.", reason)
            t_c, t_source = 0.0, "zero"
        if r_source == SINGLE_AXIS and t_c != 0.0:
            rot = single_axis_rotation(rec.imu, gyro, poses, t_c, ini.min_rotation_deg).R_imu_lidar
        if hand_eye is not None and t_c != 0.0:
            try:
                hand_eye = estimate_rotation_extrinsic(gyro, poses, time_offset_s=t_c, cfg=he_cfg)
            except ExcitationError as err:
                raise _with_rotation_hint(err) from err
            rot = hand_eye.R_imu_lidar
    return rot, t_c, r_source, t_source, correlation, hand_eye, poses


MIN_SEGMENT_S = 2.0
"""Shorter segments are refused: a few scans cannot determine the extrinsic."""

THICKNESS_PER_RANGE_SIGMA = 1.5
"""Default ``surfels.max_thickness_m`` in units of ``noise.range_sigma_m``: range noise alone
gives an RMS of at most one sigma off a plane; a cell much thicker than that straddles
surfaces."""

_AGREEING_HAND_EYE_DEG = 0.25
"""Hand-eye RMS residual (deg) under which the LiDAR-only odometry is taken to follow the motion
(no gyro-aided re-registration; the optimisation absorbs the rest)."""


def coarse_time_offset(
    rec: Recording, poses: PoseSeries, rot: F64, toc: TimeOffsetConfig
) -> TimeOffsetEstimate | None:
    """Coarse time offset from the angular rates: jointly with the rotation (robust to a
    rotation that absorbed part of the offset), else with ``rot`` fixed, else from the angular
    speed alone. Returns the first estimate that is ok, else the last one (None when none was
    possible)."""
    est: TimeOffsetEstimate | None = None
    attempts: tuple[Callable[[], TimeOffsetEstimate], ...] = (
        lambda: estimate_time_offset_joint(rec.imu, poses, toc)[0],
        lambda: estimate_time_offset_aligned(rec.imu, poses, rot, toc),
        lambda: estimate_time_offset(rec.imu, poses, toc),
    )
    for attempt in attempts:
        try:
            est = attempt()
        except ExcitationError as err:
            logger.info("Time-offset correlation not possible: %s", err)
            continue
        if est.ok:
            break
    return est


def gyro_aided_rotation(
    rec: Recording,
    kiss: PoseSeries,
    lidar_only: PoseSeries,
    ocfg: OdometryConfig,
    gyro: GyroIntegrator,
    rot: F64,
    t_c: float,
    hand_eye: HandEyeRotation | None,
    cfg: CalibConfig,
    reestimate_offset: bool = False,
    max_rounds: int = 3,
) -> tuple[F64, float, PoseSeries, HandEyeRotation | None]:
    """Re-run the odometry with scans deskewed by the gyro, alternating with hand-eye.

    A LiDAR-only odometry cannot deskew violent motion (the rotation rate changes a lot within a
    sweep); once a rotation extrinsic is known, the gyro can. When the odometry given
    (``lidar_only``) already agrees with the gyro (hand-eye residual under
    ``_AGREEING_HAND_EYE_DEG``) it is kept.
    Otherwise each round deskews with the current rotation and time offset, re-registers (seeded
    by kiss-icp and the gyro), re-estimates the coarse time offset when ``reestimate_offset``
    (the gyro's timing leaks into odometry it deskews, pulling the correlation towards the
    offset assumed, so it is iterated), and re-solves hand-eye, until the odometry agrees with
    the gyro (hand-eye residual under ``_AGREEING_HAND_EYE_DEG``) or the rotation moves less than
    0.05 deg and the offset less than 0.5 ms. With a rotation from the config the rounds
    start from it.

    Returns:
        ``(R_imu_lidar, time_offset_s, poses, hand_eye)`` after the last round.
    """
    ini = cfg.initialization
    he_cfg = _hand_eye_config(cfg)
    toc = TimeOffsetConfig(
        max_lag_s=ini.time_offset_max_lag_s, min_peak_correlation=ini.min_peak_correlation
    )
    poses = lidar_only
    if hand_eye is None and ini.rotation_rpy_deg is None:
        return rot, t_c, lidar_only, hand_eye  # single-axis motion: hand-eye cannot help
    if hand_eye is not None and hand_eye.residual_rms_deg < _AGREEING_HAND_EYE_DEG:
        return rot, t_c, lidar_only, hand_eye  # the odometry already agrees with the gyro
    for _ in range(max_rounds):
        poses = refine_odometry(
            rec.scans, kiss, ocfg, rotation_at=lidar_rotation_at(gyro, rot, t_c)
        )
        if ini.rotation_rpy_deg is not None:
            return rot, t_c, poses, hand_eye
        t_step = 0.0
        if reestimate_offset:
            est = coarse_time_offset(rec, poses, rot, toc)
            if est is not None and est.ok:
                t_step = abs(est.time_offset_s - t_c)
                t_c = float(est.time_offset_s)
        try:
            new = estimate_rotation_extrinsic(gyro, poses, time_offset_s=t_c, cfg=he_cfg)
        except ExcitationError:
            break
        step = float(np.degrees(np.abs(so3.log(rot.T @ new.R_imu_lidar)).max()))
        rot, hand_eye = new.R_imu_lidar, new
        logger.info(
            "Gyro-aided hand-eye round: rotation moved %.3f deg, time offset %+.4f s.", step, t_c
        )
        if new.residual_rms_deg < _AGREEING_HAND_EYE_DEG or (step < 0.05 and t_step < 5e-4):
            break  # the odometry now agrees with the gyro; the optimisation does the rest
    return rot, t_c, poses, hand_eye


def initial_state(
    rec: Recording,
    poses: PoseSeries,
    gyro: GyroIntegrator,
    R_imu_lidar: F64,
    t_imu_lidar: F64,
    time_offset_s: float,
    phi: F64,
    cfg: CalibConfig,
) -> CalibrationState:
    """Splines, gravity and biases from the gyro and the odometry (method.md 5.1, 5.5).

    Rotation: the integrated gyro, ``R_G_I(t0) = I``. Position: the odometry poses mapped into
    ``{G}`` through the initial extrinsic, fitted with a smoothing spline. Gravity: the mean of
    ``p_ddot - R a_m`` over the segment, scaled to ``GRAVITY_NORM``.
    """
    t0 = int(rec.imu.t_ns[0])
    t_imu = (rec.imu.t_ns - t0) * 1e-9
    knots = UniformKnots.for_interval(0.0, float(t_imu[-1]), cfg.spline.knot_spacing_s)
    rot_imu = gyro(rec.imu.t_ns).as_matrix()
    so3_spline = SO3Spline.from_rotations(knots, t_imu, rot_imu)

    # Poses on the IMU clock; keep those inside the spline.
    t_pose = (poses.t_ns - t0) * 1e-9 + time_offset_s
    inside = knots.contains(t_pose)
    if np.count_nonzero(inside) < 4:
        msg = (
            "Fewer than 4 LiDAR poses overlap the IMU data in time; check the topics, the "
            "segment and the clock offset between the sensors."
        )
        raise ExcitationError(msg)
    t_pose = t_pose[inside]
    T_ml = poses.T_map_lidar[inside]
    R_gi = so3_spline.rotation(t_pose)
    # T_G_M from the first pose: R_G_M = R_G_I(t_first) R_IL R_M_L(first)^T, p_G_M = 0.
    R_gm = R_gi[0] @ R_imu_lidar @ T_ml[0, :3, :3].T
    p_gl = T_ml[:, :3, 3] @ R_gm.T
    p_gi = p_gl - R_gi @ t_imu_lidar
    span = float(t_pose[-1] - t_pose[0])
    spacing = span / max(len(t_pose) - 1, 1)
    r3 = R3Spline.fit(knots, t_pose, p_gi, smoothing=1e-3 * spacing)
    acc = r3.acceleration(t_imu)
    use = (t_imu >= t_pose[0]) & (t_imu <= t_pose[-1])
    g = np.mean(acc[use] - np.einsum("nij,nj->ni", rot_imu[use], rec.imu.accel[use]), axis=0)
    if not np.all(np.isfinite(g)) or np.linalg.norm(g) < 1e-6:
        g = -np.mean(np.einsum("nij,nj->ni", rot_imu, rec.imu.accel), axis=0)
    g = GRAVITY_NORM * g / np.linalg.norm(g)
    return CalibrationState(
        so3_spline=so3_spline,
        r3_spline=r3,
        gyro_bias=np.zeros(3),
        accel_bias=np.zeros(3),
        gravity_G=g,
        R_imu_lidar=R_imu_lidar,
        t_imu_lidar=t_imu_lidar,
        time_offset_s=time_offset_s,
        lidar_intrinsics=LidarIntrinsics.nominal(phi),
        t0_ns=t0,
    )


def points_in_global(state: CalibrationState, sample: PointSample) -> F64:
    """(N, 3) sampled points mapped into ``{G}`` with the state's trajectory and calibration."""
    t = (sample.t_ns - state.t0_ns) * 1e-9 + state.time_offset_s
    p_l = lidar_point(state.lidar_intrinsics, sample.beam, sample.rho, sample.theta)
    p_i = (p_l + sample.offset) @ state.R_imu_lidar.T + state.t_imu_lidar
    rot = state.so3_spline.rotation(t)
    return np.einsum("nij,nj->ni", rot, p_i) + state.r3_spline.position(t)


def usable_points(state: CalibrationState, sample: PointSample, margin_s: float) -> PointSample:
    """Points whose trajectory time ``tau + t_c`` stays inside the spline with a margin."""
    t = (sample.t_ns - state.t0_ns) * 1e-9 + state.time_offset_s
    knots = state.knots
    lo = knots.t0_s + margin_s
    hi = knots.t_end_s - margin_s
    return sample.subset((t >= lo) & (t <= hi))


def _free_for_round(index: int, cfg: CalibConfig) -> FreeParameters:
    sch = cfg.schedule
    imu_on = sch.imu_intrinsics_from_round > 0 and index >= sch.imu_intrinsics_from_round
    lidar_on = sch.lidar_intrinsics_from_round > 0 and index >= sch.lidar_intrinsics_from_round
    return FreeParameters(imu_intrinsics=imu_on, lidar_intrinsics=lidar_on)


def _free_names(free: FreeParameters) -> tuple[str, ...]:
    names = ["trajectory", "biases", "gravity", "extrinsic", "time offset"]
    if free.imu_intrinsics:
        names.append("IMU intrinsics")
    if free.lidar_intrinsics:
        names.append("LiDAR intrinsics")
    return tuple(names)


def _extrinsic(state: CalibrationState) -> Extrinsic:
    return Extrinsic(state.R_imu_lidar.copy(), state.t_imu_lidar.copy(), state.time_offset_s)


def _change(a: Extrinsic, b: Extrinsic) -> tuple[float, float, float]:
    err = a.error_to(b)
    return err["translation_m"], err["rotation_deg"], err["time_offset_s"]


def surfel_thickness(cfg: CalibConfig) -> float:
    """``surfels.max_thickness_m``, or its default from the range noise."""
    s = cfg.surfels
    if s.max_thickness_m is not None:
        return s.max_thickness_m
    return THICKNESS_PER_RANGE_SIGMA * cfg.noise.range_sigma_m


def run_round(
    state: CalibrationState,
    sample: PointSample,
    imu: ImuData,
    cfg: CalibConfig,
    index: int,
    max_distance_m: float,
) -> tuple[CalibrationState, RoundSummary, SolverReport]:
    """Rebuild surfels and associations from ``state``, then one LM round."""
    start = time.perf_counter()
    margin = max(cfg.spline.time_offset_padding_s, 2 * cfg.spline.knot_spacing_s)
    pts = usable_points(state, sample, margin)
    p_g = points_in_global(state, pts)
    s = cfg.surfels
    scfg = SurfelConfig(
        cell_sizes=tuple(s.cell_sizes_m),
        min_points=s.min_points,
        min_planarity=s.min_planarity,
        # as loose as the association (the first map is blurred by the initial guess)
        max_thickness_m=surfel_thickness(cfg) * max_distance_m / s.max_distance_m,
        max_distance_m=max_distance_m,
    )
    surfels = build_surfels(p_g, scfg)
    if len(surfels.d) == 0:
        msg = (
            "No planar surfaces were found in the LiDAR map; calibrate in a structured scene "
            "(walls, floor) or raise surfels.cell_sizes_m."
        )
        raise ExcitationError(msg)
    assoc = associate_points(p_g, surfels, scfg)
    if assoc.point_index.size < 100:
        msg = (
            f"Only {assoc.point_index.size} LiDAR points lie on planar surfaces; calibrate in a "
            "structured scene or raise surfels.max_distance_m."
        )
        raise ExcitationError(msg)
    used = pts.subset(np.isin(np.arange(len(pts)), assoc.point_index))
    order = np.argsort(assoc.point_index)
    plane_of = assoc.surfel_index[order]
    lidar = LidarPoints(
        t_s=(used.t_ns - state.t0_ns) * 1e-9,
        beam=used.beam,
        rho=used.rho,
        theta=used.theta,
        plane=plane_of,
    )
    planes = Planes(normal=surfels.normal, offset=surfels.d, thickness=surfels.thickness)
    rate = (len(imu) - 1) / float(imu.t_s[-1] - imu.t_s[0])
    noise = NoiseModel.from_densities(
        cfg.noise.gyro_noise_density,
        cfg.noise.accel_noise_density,
        rate,
        range_sigma=cfg.noise.range_sigma_m,
        huber_threshold=cfg.noise.huber_sigmas,
    )
    free = _free_for_round(index, cfg)
    problem = build_problem(state, imu, lidar, planes, noise, free)
    params = LMParams(
        max_iterations=cfg.schedule.iterations_per_round,
        initial_lambda=1e-6,
        min_decrease=0.1,
        use_tsvd=cfg.solver.use_tsvd,
        tsvd_threshold=cfg.solver.tsvd_threshold,
    )
    report = solve(problem, params)
    if report.status == "failed":
        msg = f"The optimisation failed in round {index}: {report.reason}."
        raise SolverError(msg)
    new_state = state_from_problem(state, problem)
    p_after = points_in_global(new_state, used)
    dist = np.einsum("ij,ij->i", surfels.normal[plane_of], p_after) + surfels.d[plane_of]
    p_before = p_g[np.sort(assoc.point_index)]
    dist0 = np.einsum("ij,ij->i", surfels.normal[plane_of], p_before) + surfels.d[plane_of]
    summary = RoundSummary(
        index=index,
        free=_free_names(free),
        points=len(used),
        surfels=len(surfels.d),
        associated_fraction=len(used) / max(len(pts), 1),
        rms_m=float(np.sqrt(np.mean(dist**2))),
        cost_start=float(report.initial_cost),
        cost_end=float(report.final_cost),
        iterations=int(report.iterations),
        extrinsic=_extrinsic(new_state),
        seconds=time.perf_counter() - start,
        distances_before_m=dist0.astype(np.float32),
        distances_after_m=dist.astype(np.float32),
    )
    return new_state, summary, report


# ------------------------------------------------------------------------------ results


def _std(report: SolverReport, names: list[str]) -> F64:
    out = []
    for n in names:
        try:
            out.append(report.std_of(n))
        except KeyError:
            out.append(float("nan"))
    return np.asarray(out, dtype=np.float64)


def uncertainty(report: SolverReport) -> dict[str, Any]:
    """One-sigma uncertainties of the extrinsic (inf where not observable)."""
    t_std = _std(report, [f"ext.translation.{a}" for a in "xyz"])
    r_std = _std(report, [f"ext.rotation.r{a}" for a in "xyz"])
    c_std = _std(report, ["ext.time_offset"])
    return {
        "translation_std_m": [float(x) for x in t_std],
        "rotation_std_deg": [float(np.degrees(x)) for x in r_std],
        "time_offset_std_s": float(c_std[0]),
    }


def observability(report: SolverReport) -> dict[str, Any]:
    """Spectrum of the scaled calibration information and the truncated directions."""
    return {
        "scaling": report.scaling,
        "threshold": float(report.tsvd_threshold),
        "singular_values": [float(f"{s:.6g}") for s in report.singular_values],
        "unobservable": [d.text for d in report.truncated],
    }


def judge(
    report: SolverReport,
    rounds: tuple[RoundSummary, ...],
    unc: dict[str, Any],
    cfg: CalibConfig,
    notes: tuple[str, ...] = (),
) -> Verdict:
    """Pass / warn / fail from observability, uncertainty, convergence and fit quality.

    ``notes`` are findings of earlier stages that make the result less trustworthy (a warning
    each).
    """
    reasons: list[str] = list(notes)
    status = "warn" if notes else "pass"
    ext_truncated = [
        d.text for d in report.truncated if any(b.startswith("ext.") for b, _ in d.blocks)
    ]
    if ext_truncated:
        status = "warn"
        reasons.extend(f"Not observable from this data: {t}" for t in ext_truncated)
        reasons.append(
            "Record with rotation about more axes, or set what is not observable from a "
            "measurement (initialization.translation_m, rotation_rpy_deg, time_offset_s)."
        )
    t_std = np.asarray(unc["translation_std_m"])
    r_std = np.asarray(unc["rotation_std_deg"])
    c_std = float(unc["time_offset_std_s"])
    finite_t = t_std[np.isfinite(t_std)]
    if finite_t.size and finite_t.max() > 0.01:
        status = "warn"
        reasons.append(
            f"Translation is uncertain (1-sigma up to {100 * finite_t.max():.1f} cm); record "
            "with more rotation about all axes."
        )
    finite_r = r_std[np.isfinite(r_std)]
    if finite_r.size and finite_r.max() > 0.1:
        status = "warn"
        reasons.append(f"Rotation is uncertain (1-sigma up to {finite_r.max():.2f} deg).")
    if np.isfinite(c_std) and c_std > 0.002:
        status = "warn"
        reasons.append(f"Time offset is uncertain (1-sigma {1e3 * c_std:.1f} ms).")
    last = rounds[-1]
    if last.rms_m > 3 * cfg.noise.range_sigma_m:
        status = "warn"
        reasons.append(
            f"Point-to-plane residuals are large (RMS {100 * last.rms_m:.1f} cm against "
            f"{100 * cfg.noise.range_sigma_m:.1f} cm expected); check noise.range_sigma_m and "
            "the scene."
        )
    if last.associated_fraction < 0.2:
        status = "warn"
        reasons.append(
            f"Only {100 * last.associated_fraction:.0f} % of the points lie on planar "
            "surfaces; the map may be poor."
        )
    if report.status not in ("converged",) and len(rounds) >= cfg.schedule.max_rounds:
        reasons.append(f"The last round stopped on: {report.reason}.")
    ext = [i for i, n in enumerate(report.calibration_names) if n.startswith("ext.")]
    n_observable = int(np.count_nonzero(report.observable[ext])) if ext else 0
    if ext and n_observable < (len(ext) + 1) // 2:
        status = "fail"
        reasons.insert(
            0,
            f"The data determine only {n_observable} of the {len(ext)} extrinsic coordinates; "
            "the result is mostly the initial guess. Record 10-60 s with rotation about all "
            "three axes.",
        )
    if report.variance_factor > 25:
        status = "fail"
        reasons.append(
            f"The fit is poor (residuals {np.sqrt(report.variance_factor):.0f}x their expected "
            "size); the model does not explain the data."
        )
    return Verdict(status, tuple(reasons))


def bag_fingerprint(path: Path) -> str:
    """A quick content fingerprint: sha256 of the sizes and first/last MiB of the bag files."""
    files = sorted(p for p in (path.rglob("*") if path.is_dir() else [path]) if p.is_file())
    h = hashlib.sha256()
    for f in files:
        size = f.stat().st_size
        h.update(f"{f.name}:{size}".encode())
        with f.open("rb") as fh:
            h.update(fh.read(1 << 20))
            if size > 2 << 20:
                fh.seek(-(1 << 20), 2)
                h.update(fh.read())
    return h.hexdigest()[:16]


# ------------------------------------------------------------------------------ entry point


def calibrate(bag: Path, cfg: CalibConfig, progress: Progress | None = None) -> CalibrationRun:
    """Calibrate ``T_imu_lidar`` and the time offset from one segment of a bag.

    Args:
        bag: a ROS1 ``.bag`` (or folder of split bags), a ROS2 bag folder, or a bare ``.db3`` /
            ``.mcap`` file. It is only read.
        cfg: the configuration tree.
        progress: where stage progress goes (nothing by default).

    Returns:
        The run: result, uncertainties, observability, verdict, per-round and per-stage figures.

    Raises:
        BagError, TopicError, DataError, TimestampError: unreadable or unusable input.
        ExcitationError: the motion or the scene does not support a calibration.
        SolverError: the optimisation failed.
    """
    progress = progress or NullProgress()
    timer = _Timer()
    bag = Path(bag)
    warnings: list[str] = []

    with timer.stage("read", progress):
        rec = read_segment(bag, cfg)
    warnings.extend(rec.warnings)
    logger.info(
        "Read %d IMU samples and %d scans (%.1f s).",
        len(rec.imu),
        len(rec.scans),
        (rec.end_ns - rec.start_ns) / _NS,
    )
    span_s = float(rec.imu.t_ns[-1] - rec.imu.t_ns[0]) / _NS
    if span_s < MIN_SEGMENT_S:
        msg = (
            f"The segment holds only {span_s:.1f} s of data, too little to calibrate; use "
            "10-60 s with rotation about all three axes (--start/--duration)."
        )
        raise ExcitationError(msg)

    ocfg = odometry_config(cfg)
    with timer.stage("odometry", progress, total=len(rec.scans)):
        kiss = run_odometry(rec.scans, ocfg, progress=lambda d, n: progress.advance(d, n))
        poses = refine_odometry(rec.scans, kiss, ocfg)

    with timer.stage("initialisation", progress):
        gyro = GyroIntegrator.from_imu(rec.imu)
        rot, t_c, r_src, t_src, corr, hand_eye, poses = initialise(
            rec, kiss, poses, ocfg, cfg, gyro
        )
        rot, t_c, poses, hand_eye = gyro_aided_rotation(
            rec,
            kiss,
            poses,
            ocfg,
            gyro,
            rot,
            t_c,
            hand_eye,
            cfg,
            reestimate_offset=t_src == "cross-correlation",
        )
        ini = cfg.initialization
        t_init = np.asarray(ini.translation_m if ini.translation_m else [0.0, 0.0, 0.0], float)
        phi = nominal_elevations(rec.scans, cfg)
        state = initial_state(rec, poses, gyro, rot, t_init, t_c, phi, cfg)
        sample = sample_points(rec.scans, phi, points_per_scan(cfg, len(rec.scans)), cfg)
        imu = ImuData.from_samples(rec.imu, state.t0_ns)
    initial = InitialGuess(
        R_imu_lidar=rot,
        t_imu_lidar=t_init,
        time_offset_s=t_c,
        rotation_source=r_src,
        time_offset_source=t_src,
        correlation=corr,
        hand_eye=hand_eye,
        gravity_G=state.gravity_G,
    )
    logger.info("Initial guess: rotation from %s, time offset %+.4f s from %s.", r_src, t_c, t_src)

    rounds: list[RoundSummary] = []
    report: SolverReport | None = None
    sch = cfg.schedule
    with timer.stage("optimisation", progress, total=sch.max_rounds):
        for index in range(1, sch.max_rounds + 1):
            # The first map is blurred by the initial guess: associate generously, then tighten.
            max_dist = cfg.surfels.max_distance_m * (3.0 if index == 1 else 1.0)
            before = _extrinsic(state)
            state, summary, report = run_round(state, sample, imu, cfg, index, max_dist)
            rounds.append(summary)
            progress.advance(index, sch.max_rounds)
            dt, dr, dc = _change(before, summary.extrinsic)
            logger.info(
                "Round %d: %d points on %d surfels, RMS %.2f cm, change %.2f mm / %.4f deg / "
                "%.3f ms.",
                index,
                summary.points,
                summary.surfels,
                100 * summary.rms_m,
                1e3 * dt,
                dr,
                1e3 * dc,
            )
            settled = (
                dt < sch.translation_tolerance_m
                and dr < sch.rotation_tolerance_deg
                and dc < sch.time_offset_tolerance_s
            )
            intrinsics_pending = any(
                0 < k and index < k
                for k in (sch.imu_intrinsics_from_round, sch.lidar_intrinsics_from_round)
            )
            if index >= 2 and settled and not intrinsics_pending:
                break
        final = cfg.surfels.final_points_per_scan
        if final is not None:
            final = points_per_scan(cfg, len(rec.scans), final)
        if final is not None and final > points_per_scan(cfg, len(rec.scans)):
            # One more round on a denser sample from the settled estimate: the uncertainty of
            # the time offset and the translation shrinks with the number of points.
            dense = sample_points(rec.scans, phi, final, cfg, seed=1)
            index = len(rounds) + 1
            state, summary, report = run_round(
                state, dense, imu, cfg, index, cfg.surfels.max_distance_m
            )
            rounds.append(summary)
            dt, dr, dc = _change(rounds[-2].extrinsic, summary.extrinsic)
            logger.info(
                "Final round: %d points on %d surfels, RMS %.2f cm, change %.2f mm / %.4f deg / "
                "%.3f ms.",
                summary.points,
                summary.surfels,
                100 * summary.rms_m,
                1e3 * dt,
                dr,
                1e3 * dc,
            )
    assert report is not None

    unc = uncertainty(report)
    obs = observability(report)
    notes = []
    if r_src == SINGLE_AXIS:
        notes.append(
            "The rig turned about one axis only; the rotation about it rests on the "
            "accelerations, and the translation along it is not observable."
        )
    verdict = judge(report, tuple(rounds), unc, cfg, tuple(notes))
    recording = {
        "bag": str(bag),
        "imu_topic": rec.imu_topic,
        "lidar_topic": rec.lidar_topic,
        "imu_samples": len(rec.imu),
        "scans": len(rec.scans),
        "duration_s": round((rec.end_ns - rec.start_ns) / _NS, 6),
        "start_ns": int(rec.start_ns),
        "clock_offset_s": round(rec.clock_offset_s, 9),
        "lidar_clock_shift_s": round(rec.lidar_shift_ns / _NS, 9),
    }
    extra: dict[str, Any] = {
        "gravity_G": [round(float(x), 6) for x in state.gravity_G],
        "uncertainty": unc,
        "observability": obs,
        "verdict": {"status": verdict.status, "reasons": list(verdict.reasons)},
        "initialization": {
            "rotation_source": r_src,
            "time_offset_source": t_src,
            "coarse_time_offset_s": round(t_c, 9),
            "angular_speed_correlation": None if np.isnan(corr) else round(corr, 4),
            "hand_eye_conditioning": None
            if hand_eye is None
            else float(f"{hand_eye.conditioning:.4g}"),
        },
        "fit": {
            "rounds": len(rounds),
            "points": rounds[-1].points,
            "surfels": rounds[-1].surfels,
            "point_rms_m": round(rounds[-1].rms_m, 6),
            "variance_factor": float(f"{report.variance_factor:.4g}"),
        },
        "recording": recording,
        "provenance": {
            "licalib_version": __version__,
            "bag_fingerprint": bag_fingerprint(bag),
            "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        },
    }
    result = CalibrationResult(
        extrinsic=_extrinsic(state),
        imu_intrinsics=state.imu_intrinsics,
        lidar_intrinsics=state.lidar_intrinsics if _lidar_estimated(cfg) else None,
        extra=extra,
    )
    progress.close()
    return CalibrationRun(
        result=result,
        state=state,
        initial=initial,
        rounds=tuple(rounds),
        solver=report,
        verdict=verdict,
        timings=dict(timer.timings),
        recording=recording,
        warnings=tuple(warnings),
    )


def _lidar_estimated(cfg: CalibConfig) -> bool:
    return cfg.schedule.lidar_intrinsics_from_round > 0


def with_overrides(cfg: CalibConfig, **sections: dict[str, Any]) -> CalibConfig:
    """Copy of ``cfg`` with some fields of some sections replaced (for scripts and tests)."""
    data = cfg.model_dump()
    for name, values in sections.items():
        data[name].update(values)
    return CalibConfig.model_validate(data)
