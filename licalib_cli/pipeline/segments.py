"""Segment selection (``licalib select-segments``): which windows of a long bag inform the
calibration most (method.md section 8, the paper's Sec. V-A).

The bag (or ``bag.start_s`` / ``bag.duration_s`` of it) is cut into windows of ``length_s``
seconds, ``step_s`` apart. For every window the information of the calibration parameters
(extrinsic rotation and translation, time offset) is computed at one common estimate: the
Schur complement of the linearised problem of that window, scaled by the characteristic sizes
(translation 1 cm, rotation 1 mrad, time offset 1 ms; README "How far to trust the result"),
with its minimum singular value (the paper's metric), trace and log-determinant, and its weak
directions in words. The metric compares windows of one bag; it is not an absolute figure.

With IMU intrinsics in the model (``model.imu``: scales, misalignments, gyro rotation,
g-sensitivity) the window's problem estimates them too, and the metric is the information of
the extrinsic and time offset with them unknown to their characteristic sizes
(:func:`~licalib_cli.solver.observability.marginal_information`): a window whose motion leaves
the extrinsic rotation trading with the accelerometer's misalignment or the gyro's rotation (no
tilt) ranks low. Directions mostly on the intrinsics that the window leaves undetermined are
listed after the extrinsic's. LiDAR intrinsics and the drift effects are not part of it: a
window's planes are each sweep's own, which would take up what the beams' intrinsics do.

How it stays cheap (no window is calibrated):

1. **IMU pass.** All IMU samples of the range are read (56 bytes a sample: 13 MB for ten
   minutes at 400 Hz); they give the excitation of every window and of the whole bag.
2. **Common estimate.** The initialisation of ``calibrate`` (odometry, hand-eye rotation,
   coarse time offset, lever arm) runs once, on the :data:`ESTIMATE_S` seconds whose rotation
   about the least-excited axis is largest; with the extrinsic and time offset all given in the
   config (``initialization``), only that part's noise is measured.
3. **LiDAR pass.** The clouds are streamed (every ``every``-th one decoded, by default every
   third); each decoded cloud is reduced at once to a few hundred points on planes of its own
   (surfels of that single sweep, in the LiDAR frame), so memory holds one window of such
   points.
4. **Per window.** The trajectory is the gyro's rotation and the accelerometer's motion
   (gravity from the window's mean specific force, velocity with its linear drift removed);
   every point gets the plane through itself with its sweep's normal, so every residual is zero
   at this estimate and only the Jacobians matter. The planes are fixed, as within a round of
   the calibration, so the Schur complement has the form the solver's observability uses.

Times: windows are given in seconds after the bag's first message (as ``--start``); the
IMU clock is the reference (LiDAR times shifted by the reader's whole-bag clock shift and
evaluated at ``tau + time_offset_s``).
"""

from __future__ import annotations

import logging
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import numpy.typing as npt
from scipy.integrate import cumulative_trapezoid

from licalib_cli.config import CalibConfig
from licalib_cli.errors import ConfigError, ExcitationError
from licalib_cli.estimation import (
    CalibrationState,
    FreeParameters,
    ImuData,
    Planes,
    build_problem,
)
from licalib_cli.geometry.vectors import norms
from licalib_cli.initialization.rotation import GyroIntegrator
from licalib_cli.io.bag import IMU_TYPE, open_bag, select_topic
from licalib_cli.io.findings import first_fatal
from licalib_cli.io.imu_stream import read_imu_stream
from licalib_cli.io.reader import iter_scans
from licalib_cli.io.window import MIN_SEGMENT_S, segment_window
from licalib_cli.measurements import ImuSamples, LidarScan
from licalib_cli.models.intrinsics import LidarIntrinsics
from licalib_cli.models.lidar import nominal_point
from licalib_cli.pipeline.initialise import initialise, lidar_odometry
from licalib_cli.pipeline.points import PointSample, points_in_global, solver_points
from licalib_cli.pipeline.read import read
from licalib_cli.pipeline.settings import (
    IMU_INTRINSIC_NAMES,
    NoiseLevels,
    association_distance,
    free_parameters,
    noise_model,
    spline_margin_s,
    surfel_config,
)
from licalib_cli.residuals import EXT_ROTATION, EXT_TRANSLATION, TIME_OFFSET
from licalib_cli.results import matrix_from_rpy_deg
from licalib_cli.solver.observability import (
    InformationSummary,
    calibration_information,
    marginal_information,
    summed_information,
)
from licalib_cli.spline import R3Spline, SO3Spline, UniformKnots
from licalib_cli.surfels import SurfelConfig, associate_points, build_surfels

__all__ = [
    "ESTIMATE_S",
    "CommonEstimate",
    "Excitation",
    "Selection",
    "WindowInformation",
    "WindowScore",
    "choose",
    "common_estimate",
    "joint_information",
    "plan_windows",
    "select_segments",
    "window_free",
    "window_information",
]

logger = logging.getLogger(__name__)

F64 = npt.NDArray[np.float64]
_NS = 1_000_000_000

ESTIMATE_S = 6.0
"""Seconds of the bag the common estimate is initialised on (at most the window length)."""

POINTS_PER_SCAN = 300
"""Points on planes kept per decoded sweep."""

_SURFEL_POINTS = 5000
"""Points of a sweep its planes are extracted from."""

_BIN_S = 0.1
"""Bin of the excitation trace of the whole bag (the plot), s."""

_PAD_S = 0.2
"""IMU seconds read beyond a window's ends (room for the time offset and the spline)."""

GRAVITY_NORM = 9.81

_END_TOLERANCE_S = 0.5
"""A window that would end less than this (or 5 % of its length) after the range is cut at
the range's end rather than followed by a window aligned to the end."""


# ----------------------------------------------------------------------------- window plan


def plan_windows(
    start_s: float, end_s: float, length_s: float, step_s: float
) -> list[tuple[float, float]]:
    """Windows ``[a, a + length_s]`` over ``[start_s, end_s]``, ``step_s`` apart.

    The first starts at ``start_s``; a window reaching past ``end_s`` by less than
    :data:`_END_TOLERANCE_S` (or 5 % of its length) is cut there; when the last regular window
    ends before ``end_s``, one more window ``[end_s - length_s, end_s]`` covers the rest. A
    range shorter than ``length_s`` is one window, the whole range.

    Raises:
        ConfigError: a non-positive length or step, or a range under :data:`MIN_SEGMENT_S`.
    """
    if not (length_s > 0 and np.isfinite(length_s)):
        msg = f"Invalid value {length_s:g} for --length: give a positive number of seconds."
        raise ConfigError(msg)
    if not (step_s > 0 and np.isfinite(step_s)):
        msg = f"Invalid value {step_s:g} for --step: give a positive number of seconds."
        raise ConfigError(msg)
    span = end_s - start_s
    if span < MIN_SEGMENT_S:
        msg = (
            f"The range to rank lasts only {span:.2f} s, too little for a window; give at "
            f"least {MIN_SEGMENT_S:g} s (a longer --duration or an earlier --start)."
        )
        raise ExcitationError(msg)
    if length_s < MIN_SEGMENT_S:
        msg = (
            f"Invalid value {length_s:g} for --length: a window needs at least "
            f"{MIN_SEGMENT_S:g} s (10-20 s is typical)."
        )
        raise ConfigError(msg)
    if span <= length_s + 1e-9:
        return [(start_s, end_s)]
    out: list[tuple[float, float]] = []
    a = start_s
    eps = min(_END_TOLERANCE_S, 0.05 * length_s)
    while a + length_s <= end_s + eps:
        out.append((a, min(a + length_s, end_s)))
        a = start_s + len(out) * step_s
    if out[-1][1] < end_s - 1e-6:
        out.append((end_s - length_s, end_s))
    return out


# ------------------------------------------------------------------------------ excitation


@dataclass(frozen=True)
class Excitation:
    """The motion of the whole range, binned (the sparse summary behind the plot).

    Attributes:
        t_s: (K,) bin centres, seconds after the bag start.
        angular_rate: (K,) largest ``|w|`` in the bin, rad/s.
        acceleration: (K,) largest ``| |a_m| - g |`` in the bin, m/s^2 (specific force minus
            gravity, in magnitude).
    """

    t_s: F64
    angular_rate: F64
    acceleration: F64


def _binned_max(t_s: F64, value: F64, start_s: float, end_s: float) -> tuple[F64, F64]:
    n = max(1, int(np.ceil((end_s - start_s) / _BIN_S)))
    idx = np.clip(((t_s - start_s) / _BIN_S).astype(np.int64), 0, n - 1)
    out = np.zeros(n)
    np.maximum.at(out, idx, value)
    return start_s + (np.arange(n, dtype=np.float64) + 0.5) * _BIN_S, out


def excitation_of(imu: ImuSamples, bag_start_ns: int, span: tuple[float, float]) -> Excitation:
    """The binned angular rate and acceleration of the IMU samples."""
    t = np.asarray((imu.t_ns - bag_start_ns) * 1e-9, dtype=np.float64)
    w = np.linalg.norm(imu.gyro, axis=1)
    a = np.abs(np.linalg.norm(imu.accel, axis=1) - GRAVITY_NORM)
    tc, wb = _binned_max(t, w, *span)
    _, ab = _binned_max(t, a, *span)
    return Excitation(tc, wb, ab)


def _window_motion(imu: ImuSamples) -> tuple[float, float, float]:
    """RMS angular rate (rad/s), RMS of the specific force about its mean (m/s^2), and the
    RMS angular rate about the least-rotated axis (rad/s)."""
    if len(imu.t_ns) < 2:
        return 0.0, 0.0, 0.0
    w = float(np.sqrt(np.mean(np.sum(imu.gyro**2, axis=1))))
    f = imu.accel - imu.accel.mean(axis=0)
    a = float(np.sqrt(np.mean(np.sum(f**2, axis=1))))
    eig = np.linalg.eigvalsh(imu.gyro.T @ imu.gyro / len(imu.t_ns))
    return w, a, float(np.sqrt(max(eig[0], 0.0)))


def window_tilt_deg(imu: ImuSamples) -> float:
    """RMS angle of gravity's direction in the IMU frame from its mean direction over the
    samples, deg: how far the rig tilted. The attitude is the gyro's, gravity the mean specific
    force in the first sample's frame (the rig's own accelerations average out). The
    accelerometer's frame (``gyro_rotation``, ``accel_misalignment``) is told apart from the
    extrinsic rotation by gravity seen at attitudes tens of degrees apart; hand-held shaking
    without tilting gave 7-13 deg on the simulator's shakes."""
    if len(imu.t_ns) < 2:
        return 0.0
    rot = GyroIntegrator.from_imu(imu)(imu.t_ns).as_matrix()
    g = -np.einsum("nij,nj->ni", rot, imu.accel).mean(axis=0)
    up = np.einsum("nji,j->ni", rot, g / max(float(np.linalg.norm(g)), 1e-12))
    mean = up.mean(axis=0)
    mean /= max(float(np.linalg.norm(mean)), 1e-12)
    angle = np.arccos(np.clip(up @ mean, -1.0, 1.0))
    return float(np.degrees(np.sqrt(np.mean(angle**2))))


def _slice(imu: ImuSamples, lo_ns: int, hi_ns: int) -> ImuSamples:
    i0, i1 = np.searchsorted(imu.t_ns, [lo_ns, hi_ns])
    return ImuSamples(imu.t_ns[i0:i1], imu.gyro[i0:i1], imu.accel[i0:i1])


# ------------------------------------------------------------------------ common estimate


@dataclass(frozen=True)
class CommonEstimate:
    """The estimate every window is linearised at.

    Attributes:
        R_imu_lidar: (3, 3) extrinsic rotation.
        t_imu_lidar: (3,) translation, m.
        time_offset_s: ``t_imu = t_lidar + time_offset_s``.
        nominal_elevation: (B,) beam elevations, rad.
        noise: the noise the windows' residuals are weighted with.
        lidar_shift_ns: whole-bag shift of the LiDAR clock into the IMU clock, ns.
        source: where it came from (e.g. ``"initialisation on 31.0-39.0 s"``).
    """

    R_imu_lidar: F64
    t_imu_lidar: F64
    time_offset_s: float
    nominal_elevation: F64
    noise: NoiseLevels
    lidar_shift_ns: int
    source: str


def _with_range(cfg: CalibConfig, start_s: float, duration_s: float) -> CalibConfig:
    bag = cfg.bag.model_copy(update={"start_s": start_s, "duration_s": duration_s})
    return cfg.model_copy(update={"bag": bag})


def common_estimate(
    bag: Path, cfg: CalibConfig, start_s: float, duration_s: float
) -> CommonEstimate:
    """Initialise on ``[start_s, start_s + duration_s]`` (or take the config's values).

    Raises:
        ExcitationError: the part does not determine the rotation (the message says to give
            ``initialization.rotation_rpy_deg``).
    """
    part = _with_range(cfg, start_s, duration_s)
    seg = read(bag, part)
    rec = seg.recording
    ini = cfg.initialization
    where = f"{start_s:.1f}-{start_s + duration_s:.1f} s"
    if ini.rotation_rpy_deg is not None and ini.time_offset_s is not None:
        R = matrix_from_rpy_deg(np.asarray(ini.rotation_rpy_deg, dtype=np.float64))
        t = np.asarray(ini.translation_m or [0.0, 0.0, 0.0], dtype=np.float64)
        return CommonEstimate(
            R,
            t,
            float(ini.time_offset_s),
            seg.nominal_elevation,
            seg.noise,
            rec.lidar_shift_ns,
            "config",
        )
    try:
        odo = lidar_odometry(rec, part)
        guess = initialise(rec, odo, seg.nominal_elevation, seg.noise, part)
    except ExcitationError as err:
        msg = (
            f"The common estimate of the windows could not be initialised on the most rotated "
            f"part of the bag ({where}): {err} Give initialization.rotation_rpy_deg and "
            "time_offset_s in the config instead."
        )
        raise ExcitationError(msg) from err
    return CommonEstimate(
        guess.R_imu_lidar,
        np.asarray(guess.t_imu_lidar, dtype=np.float64),
        guess.time_offset_s,
        seg.nominal_elevation,
        seg.noise,
        rec.lidar_shift_ns,
        f"initialisation on {where}",
    )


# ---------------------------------------------------------------------- points on planes


@dataclass(frozen=True)
class SweepPlanes:
    """Points of one sweep that lie on planes of that sweep.

    Attributes:
        stamp_ns: the sweep's stamp (IMU clock after the shift), ns.
        sample: the points' raw measurements and times.
        normal_lidar: (N, 3) unit normal of each point's plane in the LiDAR frame.
    """

    stamp_ns: int
    sample: PointSample
    normal_lidar: F64


def sweep_planes(
    scan: LidarScan,
    phi: F64,
    cfg: CalibConfig,
    scfg: SurfelConfig,
    rng: np.random.Generator,
    per_scan: int = POINTS_PER_SCAN,
) -> SweepPlanes | None:
    """Reduce a sweep to at most ``per_scan`` points on its own planes (None: none found).

    The planes are surfels of the sweep alone, in the LiDAR frame: a sweep is short enough
    (0.1 s) for a cell of it to be one surface seen at one instant.
    """
    if scan.ring is None or len(scan) == 0:
        return None
    rho = norms(scan.xyz)
    idx = np.flatnonzero((rho >= cfg.lidar.min_range_m) & (rho <= cfg.lidar.max_range_m))
    if idx.size > _SURFEL_POINTS:
        idx = np.sort(rng.choice(idx, _SURFEL_POINTS, replace=False))
    if idx.size < 3 * scfg.min_points:
        return None
    xyz = scan.xyz[idx]
    surf = build_surfels(xyz, scfg)
    if len(surf) == 0:
        return None
    assoc = associate_points(xyz, surf, scfg)
    if len(assoc) == 0:
        return None
    keep = np.arange(len(assoc))
    if keep.size > per_scan:
        keep = np.sort(rng.choice(keep, per_scan, replace=False))
    pi, si = assoc.point_index[keep], assoc.surfel_index[keep]
    sel = idx[pi]
    beam = scan.ring[sel].astype(np.int64)
    beam = np.minimum(beam, phi.shape[0] - 1)
    r = rho[sel]
    pts = scan.xyz[sel]
    theta = np.arctan2(pts[:, 1], pts[:, 0])
    gap = pts - nominal_point(r, theta, phi[beam])
    start = np.full(sel.size, int(scan.t_ns.min()), dtype=np.int64)
    sample = PointSample(scan.t_ns[sel].astype(np.int64), start, beam, r, theta, gap)
    return SweepPlanes(int(scan.stamp_ns), sample, surf.normal[si])


def _concat(parts: Sequence[SweepPlanes]) -> tuple[PointSample, F64]:
    s = [p.sample for p in parts]
    sample = PointSample(
        np.concatenate([x.t_ns for x in s]),
        np.concatenate([x.sweep_start_ns for x in s]),
        np.concatenate([x.beam for x in s]),
        np.concatenate([x.rho for x in s]),
        np.concatenate([x.theta for x in s]),
        np.concatenate([x.model_gap for x in s]),
    )
    return sample, np.concatenate([p.normal_lidar for p in parts])


# --------------------------------------------------------------------- window information


def _window_state(imu: ImuSamples, est: CommonEstimate, cfg: CalibConfig) -> CalibrationState:
    """The window's trajectory from the IMU alone (see the module docstring)."""
    t0 = int(imu.t_ns[0])
    t = (imu.t_ns - t0) * 1e-9
    knots = UniformKnots.for_interval(0.0, float(t[-1]), cfg.spline.spacing_s)
    rot = GyroIntegrator.from_imu(imu)(imu.t_ns).as_matrix()
    so3 = SO3Spline.from_rotations(knots, t, rot)
    r_gi = so3.rotation(t)
    f_g = np.einsum("nij,nj->ni", r_gi, imu.accel)  # p_ddot - g
    g = -f_g.mean(axis=0)
    g = GRAVITY_NORM * g / max(float(np.linalg.norm(g)), 1e-9)
    acc = f_g + g
    vel = cumulative_trapezoid(acc, t, axis=0, initial=0.0)
    design = np.stack([np.ones_like(t), t], axis=1)
    coef, *_ = np.linalg.lstsq(design, vel, rcond=None)
    vel = vel - design @ coef
    pos = cumulative_trapezoid(vel, t, axis=0, initial=0.0)
    r3 = R3Spline.fit(knots, t, pos, smoothing=1e-6)
    return CalibrationState(
        so3_spline=so3,
        r3_spline=r3,
        gyro_bias=np.zeros(3),
        accel_bias=np.zeros(3),
        gravity_G=g,
        R_imu_lidar=est.R_imu_lidar,
        t_imu_lidar=est.t_imu_lidar,
        time_offset_s=est.time_offset_s,
        lidar_intrinsics=LidarIntrinsics.nominal(est.nominal_elevation),
        t0_ns=t0,
        t_ref_s=0.5 * float(t[-1]),
    )


def window_free(cfg: CalibConfig) -> FreeParameters:
    """What a window's problem estimates: the extrinsic, time offset, trajectory, biases and
    gravity, and the IMU intrinsic blocks of the config's ``model:`` section (g-sensitivity
    included); LiDAR intrinsics and the drift effects are left out (see the module
    docstring)."""
    model = free_parameters(cfg, intrinsics=True)
    return FreeParameters(imu_blocks=model.imu_blocks, g_sensitivity=model.g_sensitivity)


@dataclass(frozen=True)
class WindowInformation:
    """What one window's data determine.

    Attributes:
        extrinsic: scaled information of the extrinsic and time offset, the model's IMU
            intrinsics (if any) marginalised (:func:`marginal_information`): the metric.
        full: scaled information of every estimated calibration coordinate.
    """

    extrinsic: InformationSummary
    full: InformationSummary


def window_information(
    imu: ImuSamples, parts: Sequence[SweepPlanes], est: CommonEstimate, cfg: CalibConfig
) -> WindowInformation | None:
    """Scaled information of the extrinsic and time offset from one window's data (None:
    too little data in it).

    Args:
        imu: the window's IMU samples (with :data:`_PAD_S` beyond its ends).
        parts: its sweeps reduced to points on planes.
        est: the common estimate.
        cfg: configuration (knot spacing, noise, huber, the model's IMU blocks).
    """
    if len(imu.t_ns) < 10 or not parts:
        return None
    state = _window_state(imu, est, cfg)
    sample, normal_l = _concat(parts)
    tq = (sample.t_ns - state.t0_ns) * 1e-9 + state.time_offset_s
    margin = spline_margin_s(cfg.spline.time_offset_padding_s, state.knots)
    inside = (tq >= state.knots.t0_s + margin) & (tq <= state.knots.t_end_s - margin)
    if np.count_nonzero(inside) < 50:
        return None
    sample, normal_l, tq = sample.subset(inside), normal_l[inside], tq[inside]
    p_g = points_in_global(state, sample)
    r_gi = state.so3_spline.rotation(tq)
    n_g = np.einsum("nij,nj->ni", r_gi, normal_l @ state.R_imu_lidar.T)
    d = -np.einsum("ij,ij->i", n_g, p_g)
    lidar = solver_points(state, sample, np.arange(len(sample)))
    problem = build_problem(
        state,
        ImuData.from_samples(imu, state.t0_ns),
        lidar,
        Planes(normal=n_g, d=d),
        noise_model(cfg, est.noise),
        window_free(cfg),
    )
    full = calibration_information(problem)
    return WindowInformation(marginal_information(full, _EXTRINSIC_BLOCKS), full)


_EXTRINSIC_BLOCKS = frozenset((EXT_ROTATION, EXT_TRANSLATION, TIME_OFFSET))

_WINDOW_IMU_BLOCKS = frozenset((*IMU_INTRINSIC_NAMES, "g_sensitivity"))
"""``model.imu`` names a window's problem estimates (:func:`window_free`)."""

_TIME_OFFSET_ELIMINATION = 1e-9
"""Scaled information added to a window's time offset when it is eliminated (its own)."""


def joint_information(infos: Sequence[InformationSummary]) -> InformationSummary | None:
    """What windows calibrated together (``calibrate --segments``) determine of the extrinsic:
    they share it and the model's intrinsics, and each keeps its own trajectory and time
    offset. Each window's time offset is eliminated, the rest summed, and the intrinsics
    marginalised as in one window's metric. None without windows.

    Args:
        infos: the windows' full information (:attr:`WindowInformation.full`), one model.
    """
    if not infos:
        return None
    shared = [
        marginal_information(i, set(i.owners) - {TIME_OFFSET}, prior=_TIME_OFFSET_ELIMINATION)
        for i in infos
    ]
    summed = summed_information(shared)
    return marginal_information(summed, _EXTRINSIC_BLOCKS)


# ------------------------------------------------------------------------------ selection


@dataclass(frozen=True)
class WindowScore:
    """One window and the information its data carry.

    Attributes:
        start_s: start, seconds after the bag start.
        end_s: end, seconds after the bag start.
        min_singular_value: smallest singular value of the scaled information (the paper's
            metric; 0 when the window has too little data).
        trace: trace of the scaled information.
        logdet: its log-determinant (``-inf`` when singular).
        singular_values: (7,) all of them, descending (empty without data).
        weak_directions: the weakest direction and any other below the solver's threshold
            (``solver.tsvd_threshold``), in words.
        angular_rate: RMS angular rate, rad/s.
        acceleration: RMS specific force about its mean, m/s^2.
        scans: sweeps that contributed.
        points: points that contributed.
        selected: chosen by ``--top`` / ``--threshold``.
        rank: 1 for the most informative window.
        tilt_deg: RMS angle of gravity's direction in the IMU frame from its mean, deg
            (:func:`window_tilt_deg`; not part of the metric).
        information: the window's scaled information of every estimated calibration
            coordinate (None without data; not in the JSON).
    """

    start_s: float
    end_s: float
    min_singular_value: float
    trace: float
    logdet: float
    singular_values: tuple[float, ...]
    weak_directions: tuple[str, ...]
    angular_rate: float
    acceleration: float
    scans: int
    points: int
    selected: bool = False
    rank: int = 0
    tilt_deg: float = 0.0
    information: InformationSummary | None = field(default=None, compare=False, repr=False)

    def overlaps(self, other: WindowScore) -> bool:
        """Whether the two windows share more than an instant."""
        return self.start_s < other.end_s - 1e-6 and other.start_s < self.end_s - 1e-6

    def to_dict(self) -> dict[str, object]:
        """The JSON form."""

        def num(x: float) -> float | None:
            return float(x) if np.isfinite(x) else None

        return {
            "start_s": round(self.start_s, 3),
            "end_s": round(self.end_s, 3),
            "rank": self.rank,
            "min_singular_value": num(self.min_singular_value),
            "trace": num(self.trace),
            "logdet": num(self.logdet),
            "singular_values": [float(s) for s in self.singular_values],
            "weak_directions": list(self.weak_directions),
            "angular_rate_rad_s": self.angular_rate,
            "acceleration_m_s2": self.acceleration,
            "tilt_deg": self.tilt_deg,
            "scans": self.scans,
            "points": self.points,
            "selected": self.selected,
        }


@dataclass(frozen=True)
class Selection:
    """What ``select-segments`` produces.

    Attributes:
        windows: every window, in time order, with its rank and whether it is selected.
        estimate: the common estimate.
        excitation: the whole range's motion, binned.
        length_s: window length, s.
        step_s: window step, s.
        top: ``--top`` used (None: not given).
        threshold: ``--threshold`` used (None: not given).
        scaling: statement of the scaling of the information.
        timings: wall seconds per stage.
        every: every how many clouds one was decoded.
        intrinsics: the model's IMU intrinsics the metric counts as unknown
            (:func:`window_free`), as ``imu.<model.imu name>``.
        not_ranked: the model's blocks the metric leaves out (LiDAR intrinsics, drifts), as
            ``imu.<name>`` / ``lidar.<name>``.
        together: what the selected windows determine of the extrinsic together
            (:func:`joint_information`; None when none is selected).
    """

    windows: tuple[WindowScore, ...]
    estimate: CommonEstimate
    excitation: Excitation
    length_s: float
    step_s: float
    top: int | None
    threshold: float | None
    scaling: str
    timings: dict[str, float] = field(default_factory=dict)
    every: int = 1
    intrinsics: tuple[str, ...] = ()
    not_ranked: tuple[str, ...] = ()
    together: InformationSummary | None = None

    @property
    def ranked(self) -> tuple[WindowScore, ...]:
        """The windows, most informative first."""
        return tuple(sorted(self.windows, key=lambda w: w.rank))

    @property
    def selected(self) -> tuple[WindowScore, ...]:
        """The selected windows in time order."""
        return tuple(w for w in self.windows if w.selected)

    def to_dict(self) -> dict[str, object]:
        """The JSON form: ``{"segments": [...], ...}`` (segments in rank order)."""
        return {
            "segments": [w.to_dict() for w in self.ranked],
            "metric": "min_singular_value",
            "scaling": self.scaling,
            "intrinsics_unknown": list(self.intrinsics),
            "model_not_ranked": list(self.not_ranked),
            "selected_together": None
            if self.together is None
            else {
                "min_singular_value": self.together.min_singular_value,
                "singular_values": [float(x) for x in self.together.singular_values],
                "weakest_direction": self.together.describe(-1, verdict="").text,
            },
            "length_s": self.length_s,
            "step_s": self.step_s,
            "top": self.top,
            "threshold": self.threshold,
            "estimate": {
                "source": self.estimate.source,
                "rotation_matrix": self.estimate.R_imu_lidar.tolist(),
                "translation": self.estimate.t_imu_lidar.tolist(),
                "time_offset_s": self.estimate.time_offset_s,
            },
            "timings_s": {k: round(v, 3) for k, v in self.timings.items()},
        }


DEFAULT_TOP = 3
"""Windows selected when neither ``--top`` nor ``--threshold`` is given."""


def _rank_key(w: WindowScore) -> tuple[float, float]:
    logdet = w.logdet if np.isfinite(w.logdet) else -np.inf
    return (-w.min_singular_value, -logdet)


def choose(
    windows: Sequence[WindowScore], top: int | None, threshold: float | None
) -> tuple[WindowScore, ...]:
    """Rank the windows and mark the selected ones; time order is kept.

    The candidates are the windows with data whose metric is at least ``threshold``; at most
    ``top`` are taken (default :data:`DEFAULT_TOP` without a threshold), none overlapping
    another. The first is the best ranked; each next one, when the windows carry their
    information, the candidate that adds most to what the windows taken so far determine
    together (the smallest singular value of :func:`joint_information`, ties to the better
    rank), so that windows weak in the same direction do not crowd out one that is strong
    there; without it, the next in rank.
    """
    order = sorted(range(len(windows)), key=lambda i: _rank_key(windows[i]))
    rank = {i: r + 1 for r, i in enumerate(order)}
    limit = top if top is not None else (None if threshold is not None else DEFAULT_TOP)
    candidates = [
        i
        for i in order
        if windows[i].min_singular_value > 0
        and (threshold is None or windows[i].min_singular_value >= threshold)
    ]
    known = {i: x for i in candidates if (x := windows[i].information) is not None}
    greedy = limit is not None and len(known) == len(candidates)
    taken: list[int] = []

    def together(i: int) -> float:
        joint = joint_information([known[t] for t in (*taken, i)])
        return joint.min_singular_value if joint is not None else 0.0

    while candidates and (limit is None or len(taken) < limit):
        free = [i for i in candidates if not any(windows[i].overlaps(windows[t]) for t in taken)]
        if not free:
            break
        pick = max(free, key=lambda i: (together(i), -rank[i])) if greedy and taken else free[0]
        taken.append(pick)
        candidates.remove(pick)
    chosen = set(taken)
    return tuple(replace(w, rank=rank[i], selected=i in chosen) for i, w in enumerate(windows))


def _weak(info: InformationSummary, threshold: float) -> list[str]:
    s = info.singular_values
    if s.size == 0:
        return []
    out = []
    for i in range(s.size - 1, -1, -1):
        if i != s.size - 1 and s[i] >= threshold:
            break
        out.append(f"{info.describe(i).text} (singular value {s[i]:.3g})")
    return out


def _weak_intrinsics(info: InformationSummary, threshold: float) -> list[str]:
    """Directions of the full information below ``threshold`` that lie mostly (over half
    their squared norm) on the IMU intrinsics: what the window's reduced problem leaves
    undetermined there (an indication; the calibration's own check decides)."""
    out = []
    s = info.singular_values
    for i in range(s.size - 1, -1, -1):
        if s[i] >= threshold:
            break
        blocks = info.describe(i).blocks
        if sum(share for b, share in blocks if b not in _EXTRINSIC_BLOCKS) > 0.5:
            out.append(f"{info.describe(i).text} (singular value {s[i]:.3g})")
    return out


def _score(
    window: tuple[float, float],
    imu: ImuSamples,
    parts: Sequence[SweepPlanes],
    est: CommonEstimate,
    cfg: CalibConfig,
) -> tuple[WindowScore, str]:
    rate, accel, _ = _window_motion(imu)
    tilt = window_tilt_deg(imu)
    info = window_information(imu, parts, est, cfg)
    points = sum(len(p.sample) for p in parts)
    if info is None:
        return WindowScore(
            window[0],
            window[1],
            0.0,
            0.0,
            -np.inf,
            (),
            ("too little data",),
            rate,
            accel,
            len(parts),
            points,
            tilt_deg=tilt,
        ), ""
    ext, thr = info.extrinsic, cfg.solver.tsvd_threshold
    return WindowScore(
        window[0],
        window[1],
        ext.min_singular_value,
        ext.trace,
        ext.log_determinant,
        tuple(float(x) for x in ext.singular_values),
        tuple(_weak(ext, thr) + _weak_intrinsics(info.full, thr)),
        rate,
        accel,
        len(parts),
        points,
        tilt_deg=tilt,
        information=info.full,
    ), ext.scaling


@dataclass(frozen=True)
class _Range:
    bag_start_ns: int
    start_s: float
    end_s: float
    imu: ImuSamples


def _read_range(bag: Path, cfg: CalibConfig) -> _Range:
    """All IMU samples of the configured range, and the range on the IMU clock."""
    with open_bag(bag) as handle:
        topic = select_topic(handle, IMU_TYPE, cfg.imu.topic, "--imu-topic", "imu.topic")
        window = segment_window(handle, cfg)
        imu = read_imu_stream(handle, topic.name, window, cfg)
        bag_start = handle.start_ns + imu.offset_ns
    fatal = first_fatal(list(imu.findings))
    if fatal is not None:
        raise fatal.exception()
    t = imu.samples.t_ns
    start_s = max(cfg.bag.start_s, (int(t[0]) - bag_start) / _NS)
    end_s = (int(t[-1]) - bag_start) / _NS
    if cfg.bag.duration_s is not None:
        end_s = min(end_s, cfg.bag.start_s + cfg.bag.duration_s)
    return _Range(bag_start, start_s, end_s, imu.samples)


def _best_part(rng: _Range, length_s: float) -> tuple[float, float]:
    """The :data:`ESTIMATE_S` seconds with the most rotation about the least-rotated axis."""
    span = rng.end_s - rng.start_s
    dur = min(ESTIMATE_S, length_s, span)
    best, best_at = -1.0, rng.start_s
    for a in np.arange(rng.start_s, rng.end_s - dur + 1e-9, max(dur / 4, 0.5)):
        lo = rng.bag_start_ns + round(a * _NS)
        part = _slice(rng.imu, lo, lo + round(dur * _NS))
        score = _window_motion(part)[2]
        if score > best:
            best, best_at = score, float(a)
    return best_at, dur


def select_segments(
    bag: Path,
    cfg: CalibConfig,
    length_s: float = 15.0,
    step_s: float | None = None,
    top: int | None = None,
    threshold: float | None = None,
    every: int = 3,
    progress: Callable[[int, int], None] | None = None,
) -> Selection:
    """Rank the windows of a bag by the information they carry about the calibration.

    Args:
        bag: the bag (any supported form); only read.
        cfg: configuration; ``bag.start_s`` / ``bag.duration_s`` restrict the range
            (``bag.max_duration_s`` does not apply).
        length_s: window length, s.
        step_s: window step, s (default: ``length_s``, windows side by side).
        top: select ``top`` windows that do not overlap (:func:`choose`).
        threshold: select windows whose metric is at least this.
        every: decode every ``every``-th cloud (3: a third of them).
        progress: called as ``progress(done, total)`` after each window.

    Returns:
        The selection.

    Raises:
        BagError, TopicError, DataError, TimestampError: unreadable or unusable input.
        ConfigError: invalid options.
        ExcitationError: the range is too short, or the common estimate cannot be found.
    """
    step_s = length_s if step_s is None else step_s
    if top is not None and top < 1:
        msg = f"Invalid value {top} for --top: select at least one window."
        raise ConfigError(msg)
    if threshold is not None and not (threshold >= 0 and np.isfinite(threshold)):
        msg = f"Invalid value {threshold:g} for --threshold: give a non-negative number."
        raise ConfigError(msg)
    timings: dict[str, float] = {}
    clock = time.perf_counter()
    rng = _read_range(bag, cfg)
    windows = plan_windows(rng.start_s, rng.end_s, length_s, step_s)
    excitation = excitation_of(rng.imu, rng.bag_start_ns, (rng.start_s, rng.end_s))
    timings["imu"] = time.perf_counter() - clock

    clock = time.perf_counter()
    a, dur = _best_part(rng, length_s)
    est = common_estimate(bag, cfg, a, dur)
    timings["common estimate"] = time.perf_counter() - clock
    logger.info(
        "Common estimate (%s): translation [%.3f %.3f %.3f] m, time offset %+.4f s.",
        est.source,
        *est.t_imu_lidar,
        est.time_offset_s,
    )

    clock = time.perf_counter()
    scfg = surfel_config(cfg, est.noise, 3.0 * association_distance(cfg, est.noise))
    gen = np.random.default_rng(0)
    pending: deque[SweepPlanes] = deque()
    scores: list[WindowScore] = []
    scaling = ""
    next_w = 0
    pad = round(_PAD_S * _NS)

    def finish(index: int) -> None:
        nonlocal scaling
        w0, w1 = windows[index]
        lo = rng.bag_start_ns + round(w0 * _NS)
        hi = rng.bag_start_ns + round(w1 * _NS)
        parts = [p for p in pending if lo <= p.stamp_ns < hi]
        shift = round(est.time_offset_s * _NS)
        imu = _slice(rng.imu, lo + shift - pad, hi + shift + pad)
        score, text = _score((w0, w1), imu, parts, est, cfg)
        scaling = scaling or text
        scores.append(score)
        if progress is not None:
            progress(len(scores), len(windows))

    warnings: list[str] = []
    for scan in iter_scans(bag, cfg, est.lidar_shift_ns, warnings, every=every):
        while next_w < len(windows):
            end_ns = rng.bag_start_ns + round(windows[next_w][1] * _NS)
            if scan.stamp_ns < end_ns:
                break
            finish(next_w)
            next_w += 1
            keep_from = (
                rng.bag_start_ns + round(windows[next_w][0] * _NS)
                if next_w < len(windows)
                else None
            )
            while pending and keep_from is not None and pending[0].stamp_ns < keep_from:
                pending.popleft()
        if next_w >= len(windows):
            break
        planes = sweep_planes(scan, est.nominal_elevation, cfg, scfg, gen)
        if planes is not None:
            pending.append(planes)
    while next_w < len(windows):
        finish(next_w)
        next_w += 1
    for w in warnings:
        logger.warning(w)
    timings["windows"] = time.perf_counter() - clock
    ranked = choose(scores, top, threshold)
    chosen = [w.information for w in ranked if w.selected and w.information is not None]
    return Selection(
        windows=ranked,
        estimate=est,
        excitation=excitation,
        length_s=length_s,
        step_s=step_s,
        top=top,
        threshold=threshold,
        scaling=scaling,
        timings=timings,
        every=every,
        intrinsics=tuple(f"imu.{n}" for n in cfg.model.imu if n in _WINDOW_IMU_BLOCKS),
        not_ranked=(
            *(f"imu.{n}" for n in cfg.model.imu if n not in _WINDOW_IMU_BLOCKS),
            *(f"lidar.{n}" for n in cfg.model.lidar),
        ),
        together=joint_information(chosen),
    )
