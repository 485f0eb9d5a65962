"""IMU messages of a segment: read in chunks, validated (non-finite readings, duplicates,
gaps, units, gravity) and converted to rad/s and m/s^2."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from licalib_cli.config import CalibConfig
from licalib_cli.errors import ConfigError, DataError
from licalib_cli.io.bag import CLOUD_TYPE, BagHandle, MessageLosses, imu_vectors_from_raw
from licalib_cli.io.findings import (
    IMU_GAP_FACTOR,
    MIN_IMU_SAMPLES,
    Finding,
    StampStats,
    count_noun,
    first_fatal,
    imu_problems,
    loss_findings,
    stamp_stats,
    verb_for,
)
from licalib_cli.io.imu_units import GRAVITY, ImuUnits, convert_imu, detect_imu_units
from licalib_cli.io.window import SegmentWindow, absence_finding, topic_clock, window_messages
from licalib_cli.measurements import ImuSamples

__all__ = [
    "ImuRead",
    "RawImu",
    "exact_duplicates",
    "read_imu_stream",
    "read_raw_imu",
    "validate_imu",
]

_NS = 1_000_000_000
_MAX_BAD_IMU_FRACTION = 0.01
_MAX_BAD_IMU_RUN = 3  # dropping a run of 3 leaves a 4-period hole, under the gap factor
_NO_GRAVITY_M_S2 = 3.0
_MAX_IMU_READING = 1e6  # rad/s, deg/s, g or m/s^2: beyond this a reading is garbage


@dataclass(frozen=True)
class RawImu:
    """IMU messages as recorded (raw units), in arrival order: t_ns (N,), gyro/accel (N, 3),
    and their record times (N,)."""

    t_ns: npt.NDArray[np.int64]
    gyro: npt.NDArray[np.float64]
    accel: npt.NDArray[np.float64]
    record_ns: npt.NDArray[np.int64] | None = None

    def take(self, keep: npt.NDArray[np.bool_]) -> RawImu:
        """The samples where ``keep`` is True."""
        rec = None if self.record_ns is None else self.record_ns[keep]
        return RawImu(self.t_ns[keep], self.gyro[keep], self.accel[keep], rec)


_I64 = npt.NDArray[np.int64]
_IMU_CHUNK = 65_536
"""IMU samples gathered in Python lists before they are packed into arrays."""


def read_raw_imu(bag: BagHandle, topic: str, window: SegmentWindow, offset_ns: int) -> RawImu:
    """IMU messages of the window (memory grows with the window: 64 bytes a sample). The
    vectors are read at their fixed offsets (:func:`~licalib_cli.io.bag.imu_vectors_from_raw`)
    once the first message read so agrees with its full decode; a message of another size is
    deserialised. Messages that do not decode are skipped (and counted in ``bag.losses``)."""
    acc = _ImuChunks()
    fast: bool | None = None  # reading at fixed offsets, once checked against a full decode
    for m in window_messages(bag, topic, window, offset_ns):
        quick = imu_vectors_from_raw(m.raw, bag.ros1) if fast is not False else None
        if fast and quick is not None and m.stamp_ns is not None:
            acc.add(m.stamp_ns, m.record_ns, quick)
            continue
        msg = bag.decode(m)
        if msg is None:
            continue
        st = msg.header.stamp
        av, la = msg.angular_velocity, msg.linear_acceleration
        stamp = int(st.sec) * _NS + int(st.nanosec)
        vec = (av.x, av.y, av.z, la.x, la.y, la.z)
        acc.add(stamp, m.record_ns, vec)
        if fast is None:
            fast = quick == vec and m.stamp_ns == stamp
    return acc.result()


class _ImuChunks:
    """IMU samples gathered in Python lists of at most :data:`_IMU_CHUNK` samples, each full
    list packed into arrays: an hour at 400 Hz stays about 90 MB instead of the lists' 500."""

    def __init__(self) -> None:
        self._t: list[int] = []
        self._rec: list[int] = []
        self._vals: list[tuple[float, ...]] = []
        self._packed: list[tuple[_I64, _I64, npt.NDArray[np.float64]]] = []

    def add(self, stamp_ns: int, record_ns: int, vec: tuple[float, ...]) -> None:
        self._t.append(stamp_ns)
        self._rec.append(record_ns)
        self._vals.append(vec)
        if len(self._t) >= _IMU_CHUNK:
            self._pack()

    def _pack(self) -> None:
        if self._t:
            self._packed.append(
                (
                    np.asarray(self._t, dtype=np.int64),
                    np.asarray(self._rec, dtype=np.int64),
                    np.asarray(self._vals, dtype=np.float64).reshape(-1, 6),
                )
            )
            self._t, self._rec, self._vals = [], [], []

    def result(self) -> RawImu:
        self._pack()
        if not self._packed:
            empty = np.zeros(0, dtype=np.int64)
            return RawImu(empty, np.zeros((0, 3)), np.zeros((0, 3)), empty.copy())
        t = np.concatenate([c[0] for c in self._packed])
        rec = np.concatenate([c[1] for c in self._packed])
        arr = np.concatenate([c[2] for c in self._packed])
        self._packed = []
        return RawImu(t, arr[:, :3].copy(), arr[:, 3:].copy(), rec)


def exact_duplicates(raw: RawImu) -> npt.NDArray[np.bool_]:
    """(N,) True for samples identical (stamp and values) to the previous one."""
    same = np.zeros(raw.t_ns.shape[0], dtype=bool)
    if raw.t_ns.size > 1:
        same[1:] = (
            (np.diff(raw.t_ns) == 0)
            & np.all(raw.gyro[1:] == raw.gyro[:-1], axis=1)
            & np.all(raw.accel[1:] == raw.accel[:-1], axis=1)
        )
    return same


def _longest_run(mask: npt.NDArray[np.bool_]) -> int:
    """Length of the longest run of True in a boolean array."""
    if not mask.any():
        return 0
    edges = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return int(np.max(np.flatnonzero(edges == -1) - np.flatnonzero(edges == 1)))


def _nonfinite_findings(raw: RawImu, topic: str) -> tuple[npt.NDArray[np.bool_], list[Finding]]:
    """Samples holding NaN, inf or absurd values (beyond 1e6 in any unit an IMU uses):
    ``(bad mask, findings)``. Isolated ones (at most 1 % of the samples, in runs of at most 3)
    are dropped with a warning; otherwise the IMU is unusable."""
    with np.errstate(invalid="ignore"):  # NaN compares False: bad
        fine = np.all(np.abs(raw.gyro) < _MAX_IMU_READING, axis=1) & np.all(
            np.abs(raw.accel) < _MAX_IMU_READING, axis=1
        )
    bad = ~fine
    n_bad = int(bad.sum())
    if n_bad == 0:
        return bad, []
    n = int(bad.size)
    t0 = int(raw.t_ns.min())
    where = np.flatnonzero(bad)
    a, b = (raw.t_ns[where[0]] - t0) / _NS, (raw.t_ns[where[-1]] - t0) / _NS
    span = f"at {a:.3f} s" if n_bad == 1 else f"between {a:.3f} s and {b:.3f} s"
    isolated = n_bad <= _MAX_BAD_IMU_FRACTION * n and _longest_run(bad) <= _MAX_BAD_IMU_RUN
    if isolated and n - n_bad >= MIN_IMU_SAMPLES:
        msg = (
            f"{count_noun(n_bad, 'IMU sample')} of {n} on {topic} "
            f"{verb_for(n_bad, 'holds', 'hold')} NaN or infinite values ({span}) and "
            f"{verb_for(n_bad, 'is', 'are')} dropped."
        )
        return bad, [Finding(msg, False, DataError)]
    every = "All" if n_bad == n else f"{n_bad} of"
    msg = (
        f"{every} {n} IMU samples on {topic} hold NaN or infinite values ({span}); the IMU "
        "driver published invalid readings, choose a segment without them with "
        "--start/--duration, or fix the driver and re-record."
    )
    return bad, [Finding(msg, True, DataError)]


def _gravity_and_rate(
    accel_m_s2: npt.NDArray[np.float64], stats: StampStats, topic: str, cfg: CalibConfig
) -> list[Finding]:
    """The accelerometer must read gravity, and the IMU must give at least one sample per
    spline knot (the trajectory model of the motion)."""
    out: list[Finding] = []
    median = float(np.median(np.linalg.norm(accel_m_s2, axis=1))) if len(accel_m_s2) else 0.0
    if median < _NO_GRAVITY_M_S2:
        out.append(
            Finding(
                f"The accelerometer on {topic} reads no gravity (median |a| {median:.3g} m/s^2, "
                f"about {GRAVITY:.2f} expected); the topic carries zeros or gravity-free "
                "acceleration, record the IMU's raw data (specific force including gravity) "
                "or set `imu.accel_unit` if the unit is wrong.",
                True,
                DataError,
            )
        )
    # the configured spacing, or the finest the data may choose (pipeline/knot_spacing.py)
    knot = cfg.spline.spacing_s
    needed = 1.0 / knot
    if 0 < stats.rate_hz < 0.95 * needed:
        out.append(
            Finding(
                f"The IMU on {topic} publishes at {stats.rate_hz:.1f} Hz, too slow for the "
                f"motion model (a trajectory knot every {knot:g} s needs at least "
                f"{needed:.0f} Hz, and 100-400 Hz is usual); record the IMU at a higher rate, "
                f"or for slow motion raise `spline.knot_spacing_s` to "
                f"{min(0.2, 1.0 / stats.rate_hz):.2g}.",
                True,
                DataError,
            )
        )
    return out


@dataclass(frozen=True)
class ImuRead:
    """The IMU stream of a segment, validated (what both ``info`` and the reader use).

    Attributes:
        topic: the topic.
        offset_ns: its ``stamp - record`` offset, ns.
        samples: the usable samples (finite, without exact copies), rad/s and m/s^2.
        raw: the usable samples in the raw units.
        units: the decided units (None when the stream could not be read).
        stats: statistics of the stamps of the usable samples.
        dropped: samples dropped for NaN or inf values.
        duplicates: exact copies dropped.
        record_span_ns: first and last record time of the samples, ns (None: none).
        findings: in the order of the module table.
    """

    topic: str
    offset_ns: int
    samples: ImuSamples
    raw: RawImu
    units: ImuUnits | None
    stats: StampStats
    dropped: int
    duplicates: int
    record_span_ns: tuple[int, int] | None
    findings: tuple[Finding, ...]


def _empty_imu(
    topic: str, offset: int, findings: list[Finding], stats: StampStats | None = None
) -> ImuRead:
    z3 = np.zeros((0, 3))
    zt = np.zeros(0, np.int64)
    return ImuRead(
        topic,
        offset,
        ImuSamples(zt, z3, z3.copy()),
        RawImu(zt, z3, z3.copy(), zt),
        None,
        stats if stats is not None else stamp_stats(zt, IMU_GAP_FACTOR),
        0,
        0,
        None,
        tuple(findings),
    )


def validate_imu(
    raw: RawImu,
    topic: str,
    cfg: CalibConfig,
    lost: MessageLosses | None = None,
    offset_ns: int = 0,
    absence: Callable[[Finding], Finding] | None = None,
    livox: bool = False,
) -> ImuRead:
    """Validate and convert raw IMU samples (the checks of the module table, in its order).

    Args:
        raw: the samples as read, in arrival order.
        topic: their topic (for messages).
        cfg: configuration (``imu`` units, ``spline.knot_spacing_s``).
        lost: the topic's unreadable messages, to explain gaps.
        offset_ns: the topic's ``stamp - record`` offset, kept in the result.
        absence: replaces the finding of too few samples with a better diagnosis.
        livox: the LiDAR is a Livox (:func:`livox_clouds`): its IMU's g pairs with rad/s.

    Returns:
        The stream; its findings say whether it is usable. Only :class:`LicalibError`
        findings come out of any input: nothing raises, nothing warns.
    """
    bad, findings = _nonfinite_findings(raw, topic)
    if first_fatal(findings) is not None:
        return _empty_imu(topic, offset_ns, findings, stamp_stats(raw.t_ns, IMU_GAP_FACTOR))
    raw = raw.take(~bad)
    dup = exact_duplicates(raw)
    stats = stamp_stats(raw.t_ns, IMU_GAP_FACTOR)
    stamp_findings = imu_problems(stats, int(dup.sum()), lost)
    if stats.count < MIN_IMU_SAMPLES and absence is not None:
        stamp_findings = [absence(stamp_findings[0])]
    findings += stamp_findings
    raw = raw.take(~dup)
    units = detect_imu_units(
        raw.gyro, raw.accel, cfg.imu.gyro_unit, cfg.imu.accel_unit, raw.t_ns, livox=livox
    )
    gyro, accel = convert_imu(raw.gyro, raw.accel, units)
    if units.contradiction is not None:
        findings.append(Finding(units.contradiction, True, ConfigError))
    findings += [Finding(w, False, DataError) for w in units.warnings()]
    if stats.count >= MIN_IMU_SAMPLES:
        findings += _gravity_and_rate(accel, stats, topic, cfg)
    if lost is not None:
        findings += loss_findings(topic, "IMU", lost)
    rec = raw.record_ns
    span = (int(rec.min()), int(rec.max())) if rec is not None and rec.size else None
    return ImuRead(
        topic=topic,
        offset_ns=offset_ns,
        samples=ImuSamples(raw.t_ns.copy(), gyro, accel),
        raw=raw,
        units=units,
        stats=stats,
        dropped=int(bad.sum()),
        duplicates=int(dup.sum()),
        record_span_ns=span,
        findings=tuple(findings),
    )


def read_imu_stream(
    bag: BagHandle,
    topic: str,
    window: SegmentWindow,
    cfg: CalibConfig,
    lidar_topic: str | None = None,
) -> ImuRead:
    """Read and validate the IMU samples of the window (see the module table).

    Args:
        bag: the open bag.
        topic: the IMU topic.
        window: the segment.
        cfg: configuration (``imu`` units, ``spline.knot_spacing_s``).
        lidar_topic: the LiDAR topic, to tell why the segment holds no IMU samples and whether
            the IMU is a Livox's (:func:`livox_clouds`); None: the configured one or the bag's
            only cloud topic, for the latter.

    Returns:
        The stream; its findings say whether it is usable.
    """
    offset, findings = topic_clock(bag, topic, window, "IMU")
    if findings:
        return _empty_imu(topic, offset, findings)
    raw = read_raw_imu(bag, topic, window, offset)

    def absence(default: Finding) -> Finding:
        return absence_finding(bag, window, topic, lidar_topic, "IMU", default)

    clouds = lidar_topic if lidar_topic is not None else _cloud_topic(bag, cfg)
    livox = clouds is not None and livox_clouds(bag, clouds, window)
    return validate_imu(raw, topic, cfg, bag.loss(topic), offset, absence, livox)


def _cloud_topic(bag: BagHandle, cfg: CalibConfig) -> str | None:
    """The configured LiDAR topic, or the bag's only cloud topic (None when there are several
    or none): whose clouds tell whether the IMU is a Livox's."""
    if cfg.lidar.topic is not None:
        return cfg.lidar.topic
    topics = bag.topics_of_type(CLOUD_TYPE)
    return topics[0].name if len(topics) == 1 else None


LIVOX_FIELDS = frozenset({"tag", "line"})
"""Fields every Livox driver's clouds carry (``livox_ros_driver`` and ``livox_ros_driver2``
PointCloud2, and ``CustomMsg`` converted to PointCloud2) and no spinning LiDAR's driver does."""


def livox_clouds(bag: BagHandle, topic: str, window: SegmentWindow) -> bool:
    """Whether the first cloud of ``topic`` in the window carries :data:`LIVOX_FIELDS` (a Livox
    driver's: its IMU publishes acceleration in g and angular velocity in rad/s)."""
    for message in bag.messages([topic], start_ns=window.start_ns):
        msg = bag.decode(message)
        fields = getattr(msg, "fields", None)
        return fields is not None and LIVOX_FIELDS <= {str(f.name) for f in fields}
    return False
