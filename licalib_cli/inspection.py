"""The pre-flight report of a bag (``licalib info``) as data.

:func:`inspect_bag` reads a segment (the whole bag by default) and returns a frozen
:class:`BagReport`: topics, IMU and LiDAR rates, gaps, unsorted or duplicated stamps, the
detected point layout, IMU units, unreadable messages and the coarse IMU-LiDAR clock
difference, plus the list of findings. It reads through the reader's own functions
(:func:`licalib_cli.io.imu_stream.read_imu_stream`,
:func:`licalib_cli.io.scan_stream.read_lidar_stream`,
:func:`licalib_cli.io.reader.segment_findings`), so that a bag that ``info`` calls usable can be
read by the other commands, and a bag it refuses is refused by them with the same message and
exit code.

Unlike the reader, topic, segment and data findings do not raise: they are collected so that
the whole report can be shown; :meth:`BagReport.error` gives the exception for the first fatal
one. Only unreadable inputs (missing, not a bag, corrupt) raise :class:`BagError`.
:func:`error_report` gives the JSON form of any error, so that ``info --json`` always prints
one object.

Times: int64 ns in the data; the report's ``*_s`` values are seconds, relative to the first
stamp of the stream concerned unless stated otherwise. ``clock_offset_s`` is the coarse
``t_imu - t_lidar`` difference of the two clocks (same sign as ``time_offset_s``), measured
against the bag's record times at the last point of each sweep (good to the publication
latency, milliseconds).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from licalib_cli.config import CalibConfig
from licalib_cli.errors import ConfigError, ExcitationError, LicalibError, TopicError
from licalib_cli.io.bag import CLOUD_TYPE, IMU_TYPE, open_bag, select_topic
from licalib_cli.io.beam_spread import SPREAD_DEG
from licalib_cli.io.clock_rate import ClockRate, rate_warning, streams_clock_rate
from licalib_cli.io.findings import Finding
from licalib_cli.io.imu_stream import ImuRead, read_imu_stream
from licalib_cli.io.ouster import FactoryExtrinsic, cloud_frame, read_factory_extrinsic
from licalib_cli.io.reader import segment_findings
from licalib_cli.io.scan_stream import LidarRead, read_lidar_stream
from licalib_cli.io.window import MIN_SEGMENT_S, segment_window, window_findings

__all__ = [
    "ACCELEROMETER_FRAME_MODEL",
    "GRAVITY_TURN_FOR_IMU_DEG",
    "BagReport",
    "Excitation",
    "ImuReport",
    "LidarReport",
    "TopicReport",
    "error_report",
    "gravity_turn_deg",
    "inspect_bag",
    "motion_excitation",
    "tilt_advice",
]

logger = logging.getLogger(__name__)

_NS = 1_000_000_000
_MAX_DECODED = 200


def _round(value: float, digits: int) -> float:
    """``round`` for JSON, with ``-0.0`` written as ``0.0``."""
    return round(value, digits) + 0.0


@dataclass(frozen=True)
class TopicReport:
    """One topic of the bag (whole bag, not only the segment).

    Attributes:
        name: topic name.
        msgtype: message type, e.g. ``sensor_msgs/msg/Imu``.
        count: messages in the bag.
        rate_hz: count over the bag's record duration, Hz.
    """

    name: str
    msgtype: str
    count: int
    rate_hz: float


GRAVITY_TURN_FOR_IMU_DEG = 15.0
"""RMS turn of the specific force's direction in the IMU frame (:func:`gravity_turn_deg`)
from which a recording tells the accelerometer's frame from the extrinsic rotation when the IMU
intrinsics are estimated. On the simulator's 10-20 s bags with ``gyro_rotation`` and
``accel_misalignment`` estimated, hand-held shakes at 7-10 deg by this measure left the two
traded off (the extrinsic rotation undetermined); the same shakes tilted slowly by 15-30 deg
(about 17-30 deg by this measure) and the paper's sinusoids (27 deg) determined them."""
ACCELEROMETER_FRAME_MODEL = ("gyro_rotation", "accel_misalignment")
"""The ``model.imu`` blocks that turn the accelerometer's frame against the gyro's and the
LiDAR's: only gravity seen at other attitudes tells them from the extrinsic rotation (the
checks' :data:`~licalib_cli.pipeline.checks.ACCELEROMETER_FRAME_BLOCKS`, by their model
names)."""
GRAVITY_TURN_BIN_S = 0.5
"""The specific force is averaged over bins of this length before its direction is taken: the
rig's own accelerations (shaking, vibration) mostly average out, gravity stays."""
MIN_ROTATION_RMS_DEG_S = 5.0
"""Below this RMS angular rate the recording is too calm to calibrate."""
SINGLE_AXIS_RATIO = 0.1
"""Rotation about a second axis weaker than this fraction of the first counts as one axis."""


@dataclass(frozen=True)
class Excitation:
    """How the IMU moved in the segment (a pre-flight check before calibrating).

    Attributes:
        rotation_rms_deg_s: (3,) RMS angular rate about the IMU's x, y, z axes, deg/s.
        rotation_axis_strength: (3,) RMS angular rate along the principal axes of rotation,
            strongest first, deg/s (square roots of the eigenvalues of ``mean(w w^T)``).
        strongest_axis: (3,) unit principal axis of rotation in the IMU frame.
        accel_std_m_s2: (3,) standard deviation of the specific force per IMU axis, m/s^2.
        summary: one sentence: what the motion lets the calibration determine.
        ok: False when the rotation is too weak or about one axis only.
        gravity_turn_deg: how far gravity turned in the IMU frame, deg RMS
            (:func:`gravity_turn_deg`; None without sample times).
        imu_intrinsics_note: one sentence: whether that turn tells the accelerometer's frame
            from the extrinsic rotation when the IMU intrinsics are estimated ("" without it).
    """

    rotation_rms_deg_s: tuple[float, float, float]
    rotation_axis_strength: tuple[float, float, float]
    strongest_axis: tuple[float, float, float]
    accel_std_m_s2: tuple[float, float, float]
    summary: str
    ok: bool
    gravity_turn_deg: float | None = None
    imu_intrinsics_note: str = ""

    @property
    def gravity_turn_ok(self) -> bool:
        """Whether gravity turned enough for the IMU intrinsics' accelerometer frame (True
        when not known)."""
        turn = self.gravity_turn_deg
        return turn is None or turn >= GRAVITY_TURN_FOR_IMU_DEG


def motion_excitation(
    gyro_rad_s: np.ndarray,
    accel_m_s2: np.ndarray,
    assumption: str | None = None,
    t_ns: np.ndarray | None = None,
) -> Excitation:
    """Per-axis rotation and acceleration of an IMU recording (gyro in rad/s, accel in m/s^2).

    Rotation about all three axes makes the extrinsic fully observable; about one axis only
    (a vehicle on flat ground) the translation along that axis is not; without rotation neither
    the rotation extrinsic nor the lever arm can be found. ``assumption`` (e.g. ``"gyro unit
    assumed deg/s"``) names what the rates rest on when the gyro unit was not told by the data:
    the summary then says so, as its figures are only right if the assumption is. With the
    samples' times ``t_ns`` (int64 ns) the excitation also says how far gravity turned in the
    IMU frame, which the IMU intrinsics need (:attr:`Excitation.imu_intrinsics_note`).
    """
    w = np.degrees(np.asarray(gyro_rad_s, dtype=np.float64))
    a = np.asarray(accel_m_s2, dtype=np.float64)
    rms = np.sqrt(np.mean(w**2, axis=0))
    lam, vec = np.linalg.eigh(w.T @ w / max(w.shape[0], 1))
    strength = np.sqrt(np.clip(lam[::-1], 0.0, None))
    axis = vec[:, -1] * (1.0 if vec[np.argmax(np.abs(vec[:, -1])), -1] >= 0 else -1.0)
    first = max(float(strength[0]), 1e-12)
    total = float(np.sqrt(np.sum(strength**2)))
    given = f", {assumption}" if assumption else ""
    if total < MIN_ROTATION_RMS_DEG_S:
        summary = (
            f"hardly any rotation (RMS {total:.1f} deg/s{given}): the rotation extrinsic and "
            "the lever arm cannot be determined; rotate the rig about all three axes"
        )
        ok = False
    elif strength[1] / first < SINGLE_AXIS_RATIO:
        ax = ", ".join(f"{x:.2f}" for x in np.round(axis, 2) + 0.0)
        summary = (
            f"rotation about one axis only ([{ax}] in the IMU frame, planar motion{given}): "
            "the translation along it will not be observable"
        )
        ok = False
    elif strength[2] / first < SINGLE_AXIS_RATIO:
        summary = (
            f"rotation about two axes only (RMS {total:.1f} deg/s{given}): the extrinsic is "
            "observable but weakly along the third; rotate about all three axes for the best "
            "result"
        )
        ok = True
    else:
        summary = (
            f"rotation about all three axes (RMS {total:.1f} deg/s{given}): the extrinsic is "
            "fully observable"
        )
        ok = True
    std_a = np.std(a, axis=0)
    turn = None if t_ns is None else gravity_turn_deg(t_ns, a)
    return Excitation(
        rotation_rms_deg_s=(float(rms[0]), float(rms[1]), float(rms[2])),
        rotation_axis_strength=(float(strength[0]), float(strength[1]), float(strength[2])),
        strongest_axis=(float(axis[0]), float(axis[1]), float(axis[2])),
        accel_std_m_s2=(float(std_a[0]), float(std_a[1]), float(std_a[2])),
        summary=summary,
        ok=ok,
        gravity_turn_deg=turn,
        imu_intrinsics_note="" if turn is None else _imu_intrinsics_note(turn),
    )


def gravity_turn_deg(
    t_ns: np.ndarray, accel_m_s2: np.ndarray, bin_s: float = GRAVITY_TURN_BIN_S
) -> float | None:
    """How far gravity turned in the IMU frame: the RMS angle of the specific force's direction,
    averaged over ``bin_s`` bins (:data:`GRAVITY_TURN_BIN_S`), from its mean direction, deg.

    The accelerometer alone, so that neither a gyro bias integrated over a long bag nor the
    order of the stamps matters. Fast tilting (shaking at a few Hz) partly averages out within a
    bin and counts less than a slow tilt of the same size (9 deg by the gyro's attitude read 7
    deg on a simulated shake, 31 deg read 30 deg on the same shake tilted slowly): the measure
    leans to saying too little. None without two bins of at least half the usual samples and a
    specific force other than zero.
    """
    t = np.asarray(t_ns, dtype=np.int64)
    a = np.asarray(accel_m_s2, dtype=np.float64)
    if t.size < 2:
        return None
    k = (t - t.min()) // max(int(bin_s * 1e9), 1)
    counts = np.bincount(k)
    full = counts >= max(2.0, 0.5 * float(np.median(counts[counts > 0])))
    if int(full.sum()) < 2:
        return None
    sums = np.stack([np.bincount(k, weights=a[:, j], minlength=counts.size) for j in range(3)], 1)
    mean_force = sums[full] / counts[full, None]
    size = np.linalg.norm(mean_force, axis=1)
    seen = (
        size > 1e-6
    )  # a bin without specific force (an accelerometer reading zeros) has no direction
    if int(seen.sum()) < 2:
        return None
    u = mean_force[seen] / size[seen, None]
    mean = u.mean(axis=0)
    mean /= max(float(np.linalg.norm(mean)), 1e-12)
    angle = np.arccos(np.clip(u @ mean, -1.0, 1.0))
    return float(np.degrees(np.sqrt(np.mean(angle**2))))


def _imu_intrinsics_note(turn_deg: float) -> str:
    if turn_deg >= GRAVITY_TURN_FOR_IMU_DEG:
        return (
            f"gravity turned {turn_deg:.0f} deg RMS in the IMU frame: enough to tell the "
            "accelerometer's frame from the extrinsic rotation when the IMU intrinsics are "
            "estimated (--intrinsics imu)"
        )
    return (
        f"gravity turned only {turn_deg:.0f} deg RMS in the IMU frame: with the IMU intrinsics "
        "estimated (--intrinsics imu) the accelerometer's frame may trade off with the extrinsic "
        f"rotation; {tilt_advice(ACCELEROMETER_FRAME_MODEL)}"
    )


def tilt_advice(blocks: Sequence[str]) -> str:
    """What to do when gravity turned too little for the accelerometer-frame ``blocks``
    (:data:`ACCELEROMETER_FRAME_MODEL` names) the model estimates."""
    them = " and ".join(blocks)
    return (
        "record with the rig tilted by tens of degrees about both horizontal axes, or leave "
        f"{them} out of model.imu when the IMU's own calibration covers "
        f"{'them' if len(blocks) > 1 else 'it'}"
    )


@dataclass(frozen=True)
class ImuReport:
    """The IMU stream of the segment.

    Attributes:
        topic: topic name.
        count: samples in the segment.
        rate_hz: nominal rate from the median stamp difference, Hz.
        duration_s: last minus first stamp, s.
        gyro_unit: unit of the raw gyro data (``rad/s`` or ``deg/s``).
        accel_unit: unit of the raw accelerometer data (``m/s^2`` or ``g``).
        gyro_unit_source: ``detected``, ``assumed`` or ``config``.
        accel_unit_source: ``detected``, ``assumed`` or ``config``.
        gyro_p99: 99th percentile of the raw rate norm.
        gyro_gravity_factor: how fast gravity turns in the IMU frame per raw gyro unit (about 1
            for rad/s, 0.0175 for deg/s), or None when the motion does not tell.
        accel_norm_median: median raw accelerometer norm.
        gaps: stamp differences longer than 5x the period.
        max_gap_s: largest stamp difference, s.
        backwards: stamps smaller than the previous one.
        duplicates: stamps equal to the previous one.
        first_stamp_ns: first stamp, ns.
        excitation: how the IMU moved, or None without samples.
        unreadable: messages of the segment that could not be read (damaged bag).
        dropped: samples dropped for NaN or infinite values.
        gyro_unit_basis: why an assumed gyro unit was chosen (``accelerometer in g``,
            ``Livox driver: g with rad/s`` or ``ROS convention``), with ``too little data to
            tell`` when the samples are too short for the tilting check; None when the unit was
            detected or configured.
    """

    topic: str
    count: int
    rate_hz: float
    duration_s: float
    gyro_unit: str
    accel_unit: str
    gyro_unit_source: str
    accel_unit_source: str
    gyro_p99: float
    accel_norm_median: float
    gaps: int
    max_gap_s: float
    backwards: int
    duplicates: int
    first_stamp_ns: int
    gyro_gravity_factor: float | None = None
    excitation: Excitation | None = None
    unreadable: int = 0
    dropped: int = 0
    gyro_unit_basis: str | None = None


@dataclass(frozen=True)
class LidarReport:
    """The LiDAR stream of the segment and its detected point layout.

    Attributes:
        topic: topic name.
        count: clouds in the segment.
        rate_hz: nominal rate from the median stamp difference, Hz.
        duration_s: last minus first stamp, s.
        fields: ``name:type`` of every PointField.
        point_step: bytes per point.
        is_bigendian: byte order.
        height: rows (1 = unorganised).
        width: points per row.
        time_field: per-point time field, or None when times are estimated.
        time_unit: unit of the time field, or None.
        time_reference: ``relative``, ``absolute`` or ``estimated``.
        stamp_position: header stamp at the sweep ``start``, ``end``, ``middle``, ``unknown``.
        time_estimation: ``azimuth`` or ``index`` when times are estimated, else None.
        ring_field: beam field, or None when beams are recovered from elevation.
        beams: number of beams.
        elevation_spread_deg: how far one beam's points spread in elevation (NaN without a
            ring field): above :data:`~licalib_cli.io.beam_spread.SPREAD_DEG` the beams are a
            non-repetitive scanner's lines.
        points_per_scan: median points per message (including invalid ones).
        valid_points_per_scan: median valid points per cloud.
        clouds_checked: clouds decoded to check their content (a sample on long bags).
        clouds_skipped: how many of those were unusable, by reason.
        gaps: stamp differences longer than 2.5x the period.
        max_gap_s: largest stamp difference, s.
        backwards: stamps smaller than the previous one.
        duplicates: stamps equal to the previous one.
        first_stamp_ns: first stamp, ns.
        unreadable: messages of the segment that could not be read (damaged bag).
    """

    topic: str
    count: int
    rate_hz: float
    duration_s: float
    fields: tuple[str, ...] = ()
    point_step: int = 0
    is_bigendian: bool = False
    height: int = 0
    width: int = 0
    time_field: str | None = None
    time_unit: str | None = None
    time_reference: str | None = None
    stamp_position: str | None = None
    time_estimation: str | None = None
    ring_field: str | None = None
    beams: int = 0
    elevation_spread_deg: float = float("nan")
    points_per_scan: int = 0
    valid_points_per_scan: int = 0
    clouds_checked: int = 0
    clouds_skipped: dict[str, int] = field(default_factory=dict)
    gaps: int = 0
    max_gap_s: float = 0.0
    backwards: int = 0
    duplicates: int = 0
    first_stamp_ns: int = 0
    unreadable: int = 0

    @property
    def scan_pattern(self) -> str | None:
        """``spinning`` (rings of fixed elevation) or ``non_repetitive`` (a Livox's lines), from
        :attr:`elevation_spread_deg`; None when it is not known (no ring field)."""
        if not math.isfinite(self.elevation_spread_deg):
            return None
        return "non_repetitive" if self.elevation_spread_deg > SPREAD_DEG else "spinning"


@dataclass(frozen=True)
class BagReport:
    """Everything ``licalib info`` shows.

    Attributes:
        path: the bag as given.
        format: ``ros1``, ``ros2-db3`` or ``ros2-mcap``.
        start_ns: first record time of the bag, ns.
        end_ns: last record time of the bag, ns.
        segment_start_s: segment start after the first message, s.
        segment_duration_s: segment length, s (None: to the end).
        topics: every topic of the bag.
        imu: the IMU stream, or None when no IMU topic could be chosen.
        lidar: the LiDAR stream, or None when no LiDAR topic could be chosen.
        clock_offset_s: coarse ``t_imu - t_lidar`` clock difference, s (None: unknown).
        clock_rate: how fast the IMU's stamps run against the LiDAR's (None: unknown; see
            :mod:`licalib_cli.io.clock_rate`).
        problems: findings, fatal ones first (in the reader's order).
        notes: informative remarks (detected units, layout overrides).
        factory_extrinsic: the factory ``T_imu_lidar`` of an Ouster sensor, from the
            metadata topic the driver records (None when the bag has none), for the frame the
            clouds are published in.
    """

    path: str
    format: str
    start_ns: int
    end_ns: int
    segment_start_s: float
    segment_duration_s: float | None
    topics: tuple[TopicReport, ...]
    imu: ImuReport | None
    lidar: LidarReport | None
    clock_offset_s: float | None
    problems: tuple[Finding, ...]
    notes: tuple[str, ...] = ()
    factory_extrinsic: FactoryExtrinsic | None = None
    clock_rate: ClockRate | None = None

    @property
    def duration_s(self) -> float:
        """Record duration of the whole bag, s."""
        return (self.end_ns - self.start_ns) / _NS

    @property
    def usable(self) -> bool:
        """True when no problem is fatal."""
        return not any(p.fatal for p in self.problems)

    @property
    def exit_code(self) -> int:
        """0 when usable, else the exit code of the first fatal problem."""
        for p in self.problems:
            if p.fatal:
                return p.exit_code
        return 0

    def error(self) -> LicalibError | None:
        """The exception for the first fatal problem, or None when usable."""
        for p in self.problems:
            if p.fatal:
                return p.exception()
        return None

    def to_dict(self) -> dict[str, Any]:
        """The report as plain JSON-serialisable data (``licalib info --json``)."""
        rate = self.clock_rate
        imu = None
        if self.imu is not None:
            i = self.imu
            imu = {
                "topic": i.topic,
                "count": i.count,
                "rate_hz": _round(i.rate_hz, 3),
                "duration_s": _round(i.duration_s, 6),
                "gyro_unit": i.gyro_unit,
                "accel_unit": i.accel_unit,
                "gyro_unit_source": i.gyro_unit_source,
                "accel_unit_source": i.accel_unit_source,
                "gyro_p99": _round(i.gyro_p99, 6),
                "gyro_gravity_factor": None
                if i.gyro_gravity_factor is None
                else _round(i.gyro_gravity_factor, 6),
                "accel_norm_median": _round(i.accel_norm_median, 6),
                "gaps": i.gaps,
                "max_gap_s": _round(i.max_gap_s, 6),
                "backwards": i.backwards,
                "duplicates": i.duplicates,
                "first_stamp_ns": i.first_stamp_ns,
                "unreadable": i.unreadable,
                "dropped_samples": i.dropped,
                "gyro_unit_basis": i.gyro_unit_basis,
                "excitation": None if i.excitation is None else _excitation_dict(i.excitation),
            }
        lidar = None
        if self.lidar is not None:
            li = self.lidar
            lidar = {
                "topic": li.topic,
                "count": li.count,
                "rate_hz": _round(li.rate_hz, 3),
                "duration_s": _round(li.duration_s, 6),
                "time_field": li.time_field,
                "time_unit": li.time_unit,
                "time_reference": li.time_reference,
                "stamp_position": li.stamp_position,
                "time_estimation": li.time_estimation,
                "beams": li.beams,
                "ring_field": li.ring_field,
                "scan_pattern": li.scan_pattern,
                "elevation_spread_deg": (
                    _round(li.elevation_spread_deg, 3)
                    if math.isfinite(li.elevation_spread_deg)
                    else None
                ),
                "fields": list(li.fields),
                "point_step": li.point_step,
                "is_bigendian": li.is_bigendian,
                "height": li.height,
                "width": li.width,
                "points_per_scan": li.points_per_scan,
                "valid_points_per_scan": li.valid_points_per_scan,
                "clouds_checked": li.clouds_checked,
                "clouds_skipped": dict(li.clouds_skipped),
                "gaps": li.gaps,
                "max_gap_s": _round(li.max_gap_s, 6),
                "backwards": li.backwards,
                "duplicates": li.duplicates,
                "first_stamp_ns": li.first_stamp_ns,
                "unreadable": li.unreadable,
            }
        return {
            "path": self.path,
            "format": self.format,
            "duration_s": _round(self.duration_s, 6),
            "start_ns": self.start_ns,
            "end_ns": self.end_ns,
            "segment": {"start_s": self.segment_start_s, "duration_s": self.segment_duration_s},
            "topics": [
                {
                    "name": t.name,
                    "type": t.msgtype,
                    "count": t.count,
                    "rate_hz": _round(t.rate_hz, 3),
                }
                for t in self.topics
            ],
            "imu": imu,
            "lidar": lidar,
            "clock_offset_s": None
            if self.clock_offset_s is None
            else _round(self.clock_offset_s, 6),
            "clock_rate_ppm": None if rate is None else _round(1e6 * rate.rate, 3),
            "clock_rate_sigma_ppm": None if rate is None else _round(1e6 * rate.sigma, 3),
            "usable": self.usable,
            "exit_code": self.exit_code,
            "problems": [
                {
                    "severity": "error" if p.fatal else "warning",
                    "message": p.message,
                    "exit_code": p.exit_code,
                }
                for p in self.problems
            ],
            "notes": list(self.notes),
            "factory_extrinsic": None
            if self.factory_extrinsic is None
            else factory_extrinsic_dict(self.factory_extrinsic),
        }


def factory_extrinsic_dict(f: FactoryExtrinsic) -> dict[str, Any]:
    """The factory extrinsic in the result file's keys (``p_imu = R p_lidar + t``), with
    where it came from."""
    from licalib_cli.results import Extrinsic

    ext = Extrinsic(rotation=f.rotation, translation=f.translation).to_dict()
    del ext["time_offset_s"]
    return {**ext, "cloud_frame": f.cloud_frame, "topic": f.topic, "sensor": f.sensor}


def _imu_report(imu: ImuRead, unreadable: int, findings: list[Finding]) -> ImuReport:
    excitation = None
    if len(imu.samples) >= 10:
        assumption = imu.units.gyro_assumption if imu.units is not None else None
        excitation = motion_excitation(
            imu.samples.gyro, imu.samples.accel, assumption, t_ns=imu.samples.t_ns
        )
        if not excitation.ok:
            msg = f"The IMU shows {excitation.summary}."
            findings.append(Finding(msg, False, ExcitationError))
    units, stats = imu.units, imu.stats
    basis = None
    if units is not None and units.gyro_source == "assumed":
        if units.gyro_unit == "deg/s":
            basis = "accelerometer in g"
        elif units.livox and units.accel_unit == "g":
            basis = "Livox driver: g with rad/s"
        else:
            basis = "ROS convention"
        if units.too_short:
            basis = f"too little data to tell, {basis}"
    return ImuReport(
        topic=imu.topic,
        count=stats.count,
        rate_hz=stats.rate_hz,
        duration_s=stats.duration_s,
        gyro_unit=units.gyro_unit if units else "-",
        accel_unit=units.accel_unit if units else "-",
        gyro_unit_source=units.gyro_source if units else "-",
        accel_unit_source=units.accel_source if units else "-",
        gyro_p99=units.gyro_p99 if units else 0.0,
        accel_norm_median=units.accel_norm_median if units else 0.0,
        gaps=stats.gaps,
        max_gap_s=stats.max_gap_s,
        backwards=stats.backwards,
        duplicates=stats.duplicates,
        first_stamp_ns=stats.first_ns,
        gyro_gravity_factor=units.gravity_turn_factor if units else None,
        excitation=excitation,
        unreadable=unreadable,
        dropped=imu.dropped,
        gyro_unit_basis=basis,
    )


def _lidar_report(lidar: LidarRead, unreadable: int) -> LidarReport:
    stats, tally, layout = lidar.stats, lidar.tally, lidar.layout
    base = LidarReport(
        topic=lidar.topic,
        count=stats.count,
        rate_hz=stats.rate_hz,
        duration_s=stats.duration_s,
        gaps=stats.gaps,
        max_gap_s=stats.max_gap_s,
        backwards=stats.backwards,
        duplicates=stats.duplicates,
        first_stamp_ns=stats.first_ns,
        unreadable=unreadable,
    )
    if layout is None:
        return base
    tl = layout.time
    return LidarReport(
        topic=lidar.topic,
        count=stats.count,
        rate_hz=stats.rate_hz,
        duration_s=stats.duration_s,
        fields=layout.fields,
        point_step=layout.point_step,
        is_bigendian=layout.is_bigendian,
        height=layout.height,
        width=layout.width,
        time_field=tl.field,
        time_unit=tl.unit,
        time_reference=tl.reference,
        stamp_position=tl.stamp_position,
        time_estimation=tl.method,
        ring_field=layout.ring_field,
        beams=layout.beams,
        elevation_spread_deg=layout.elevation_spread_deg,
        points_per_scan=layout.points_per_scan,
        valid_points_per_scan=layout.valid_points_per_scan,
        clouds_checked=tally.total,
        clouds_skipped={k: v for k, v in tally.skipped.items() if v},
        gaps=stats.gaps,
        max_gap_s=stats.max_gap_s,
        backwards=stats.backwards,
        duplicates=stats.duplicates,
        first_stamp_ns=stats.first_ns,
        unreadable=unreadable,
    )


def _excitation_dict(e: Excitation) -> dict[str, Any]:
    return {
        "rotation_rms_deg_s": [_round(x, 3) for x in e.rotation_rms_deg_s],
        "rotation_axis_strength_deg_s": [_round(x, 3) for x in e.rotation_axis_strength],
        "strongest_axis": [_round(x, 4) for x in e.strongest_axis],
        "accel_std_m_s2": [_round(x, 4) for x in e.accel_std_m_s2],
        "summary": e.summary,
        "ok": e.ok,
        "gravity_turn_deg": None if e.gravity_turn_deg is None else _round(e.gravity_turn_deg, 2),
        "imu_intrinsics": e.imu_intrinsics_note or None,
    }


def inspect_bag(path: Path, cfg: CalibConfig, *, min_span_s: float = MIN_SEGMENT_S) -> BagReport:
    """Inspect a segment of a bag (the whole bag by default) without calibrating.

    Args:
        path: a ROS1 ``.bag`` (or folder of split ``.bag`` files), a ROS2 bag folder, or a bare
            ``.db3``/``.mcap`` file.
        cfg: configuration (``bag``, ``imu``, ``lidar`` sections: topics, segment, overrides;
            ``spline.spacing_s`` for the IMU rate it needs).
        min_span_s: the least time both sensors must cover, as
            :func:`licalib_cli.io.reader.read_segment` (0: judge a short bag's data only).

    Returns:
        The report; topic, segment, stamp and content findings are listed in ``problems``, in
        the order the reader checks them (so the first fatal one is what ``calibrate`` would
        stop on).

    Raises:
        BagError: the path is missing, not a bag, or corrupt/truncated.
    """
    findings: list[Finding] = []
    notes: list[str] = []
    imu_read: ImuRead | None = None
    lidar_read: LidarRead | None = None
    imu = lidar = None
    with open_bag(path) as bag:
        dur = max((bag.end_ns - bag.start_ns) / _NS, 1e-9)
        topics = tuple(
            TopicReport(t.name, t.msgtype, t.count, t.count / dur if t.count > 1 else 0.0)
            for t in bag.topics
        )
        chosen = {}
        for key, msgtype, name, option, config_key in (
            ("imu", IMU_TYPE, cfg.imu.topic, "--imu-topic", "imu.topic"),
            ("lidar", CLOUD_TYPE, cfg.lidar.topic, "--lidar-topic", "lidar.topic"),
        ):
            try:
                chosen[key] = select_topic(bag, msgtype, name, option, config_key).name
            except TopicError as err:
                if all(f.message != str(err) for f in findings):  # e.g. a packet-mode bag
                    findings.append(Finding(str(err), True, TopicError))
        try:
            window = segment_window(bag, cfg)
        except ConfigError as err:
            findings.append(Finding(str(err), True, ConfigError))
            window = None
        if window is not None:
            findings += window_findings(bag, window, cfg, min_span_s)
            if "imu" in chosen:
                imu_read = read_imu_stream(bag, chosen["imu"], window, cfg, chosen.get("lidar"))
                findings += imu_read.findings
            if "lidar" in chosen:
                listed = next(t.count for t in bag.topics if t.name == chosen["lidar"])
                end = bag.end_ns if window.stop_ns is None else min(window.stop_ns, bag.end_ns)
                share = max(0.0, (end - window.start_ns) / _NS / dur)
                every = max(1, int(np.ceil(listed * min(share, 1.0) / _MAX_DECODED)))
                lidar_read = read_lidar_stream(
                    bag,
                    chosen["lidar"],
                    window,
                    cfg,
                    None if imu_read is None else imu_read.offset_ns,
                    keep=False,
                    every=every,
                    imu_topic=chosen.get("imu"),
                )
                findings += lidar_read.findings
            if imu_read is not None and lidar_read is not None:
                both = segment_findings(imu_read, lidar_read, bag.start_ns, min_span_s)
                if any(p.fatal and p.error is ExcitationError for p in findings):
                    # the segment itself is too short: say so once, as calibrate does
                    both = [p for p in both if p.error is not ExcitationError]
                findings += both
        if imu_read is not None:
            imu = _imu_report(imu_read, bag.loss(imu_read.topic).total, findings)
            if imu_read.units is not None:
                notes.extend(imu_read.units.messages())
        if lidar_read is not None:
            lidar = _lidar_report(lidar_read, bag.loss(lidar_read.topic).total)
            if lidar_read.layout is not None:
                notes.extend(lidar_read.layout.time.notes)
        factory = None
        if "lidar" in chosen:
            factory = read_factory_extrinsic(bag, cloud_frame(bag, chosen["lidar"]))
        fmt, start_ns, end_ns = bag.format, bag.start_ns, bag.end_ns
    stamp_rates = {r.topic: r.rate_hz for r in (imu, lidar) if r is not None and r.rate_hz > 0}
    topics = tuple(
        TopicReport(t.name, t.msgtype, t.count, stamp_rates.get(t.name, t.rate_hz)) for t in topics
    )
    clock = None
    if lidar_read is not None and lidar_read.clock_offset_ns is not None:
        clock = lidar_read.clock_offset_ns / _NS
    rate = None
    if imu_read is not None and lidar_read is not None:
        rate = streams_clock_rate(imu_read, lidar_read)
        told = rate_warning(rate, cfg)
        if told is not None:
            findings.append(Finding(told, False))
    findings.sort(key=lambda p: not p.fatal)
    for p in findings:
        logger.debug("finding: %s", p.message)
    return BagReport(
        path=str(path),
        format=fmt,
        start_ns=start_ns,
        end_ns=end_ns,
        segment_start_s=cfg.bag.start_s,
        segment_duration_s=cfg.bag.duration_s,
        topics=topics,
        imu=imu,
        lidar=lidar,
        clock_offset_s=clock,
        clock_rate=rate,
        problems=tuple(findings),
        notes=tuple(notes),
        factory_extrinsic=factory,
    )


def error_report(path: Path | str | None, message: str, exit_code: int) -> dict[str, Any]:
    """The JSON object of ``licalib info --json`` when the bag could not be inspected (it
    could not be opened, an option is invalid, the run was interrupted): the keys of
    :meth:`BagReport.to_dict`, empty, with the error as the one problem."""
    code = int(exit_code)
    return {
        "path": None if path is None else str(path),
        "format": None,
        "duration_s": None,
        "start_ns": None,
        "end_ns": None,
        "segment": None,
        "topics": [],
        "imu": None,
        "lidar": None,
        "clock_offset_s": None,
        "clock_rate_ppm": None,
        "clock_rate_sigma_ppm": None,
        "usable": False,
        "exit_code": code,
        "problems": [{"severity": "error", "message": message, "exit_code": code}],
        "notes": [],
        "factory_extrinsic": None,
    }
