"""Read a time segment of a bag into IMU samples and LiDAR scans, with validation.

Entry points:

* :func:`read_segment` -> :class:`Recording` (IMU samples + all scans of the segment);
* :func:`iter_scans` streams the scans one by one (constant memory on long bags);
* :func:`read_imu` reads only the IMU samples.

Time conventions: int64 ns everywhere. The segment ``[bag.start_s, bag.start_s +
bag.duration_s)`` is measured from the bag's first record time. Messages are read by record
time (with a 1 s margin) and then selected by ``header.stamp``: each topic's median
``stamp - record`` offset maps the window into that topic's clock, so that IMU and LiDAR
windows cover the same recorder interval even when the sensors use different clocks.

Clock offset: ``clock_offset_ns = offset_imu - offset_lidar`` is the coarse difference
``t_imu - t_lidar`` of the two clocks (same sign as ``time_offset_s``), where the LiDAR offset
is taken at the last point of each sweep (a cloud is published after its sweep ends), so the
estimate is good to the publication latency (milliseconds). When it is 1 s or
more (e.g. LiDAR on UNIX time, IMU on boot time) the LiDAR times of the recording are shifted
into the IMU clock (``Recording.lidar_shift_ns``) and a warning says so; smaller offsets are
left to the calibration.

Validation (fatal = raises; otherwise a warning in ``Recording.warnings``):

===============================================  =========================================
IMU stamps going backwards                       fatal (TimestampError)
IMU duplicated stamps with different values      fatal (TimestampError)
IMU exact duplicate messages                     dropped, warning
IMU gap longer than 5x the nominal period        fatal (TimestampError)
fewer than 10 IMU samples in the segment         fatal (DataError)
LiDAR stamps going backwards or duplicated       fatal (TimestampError)
LiDAR gap longer than 2.5x the scan period       warning
empty / all-NaN-or-zero / out-of-range cloud     skipped, warning; fatal (DataError) when
                                                 more than half of the clouds are skipped
time field with zero span in a cloud             skipped, warning; fatal (TimestampError)
                                                 when it is so in the clouds used to detect
                                                 the layout or in more than half the clouds
===============================================  =========================================
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

from licalib_cli.config import CalibConfig
from licalib_cli.errors import ConfigError, DataError, LicalibError, TimestampError
from licalib_cli.io.bag import (
    CLOUD_TYPE,
    IMU_TYPE,
    BagHandle,
    RawMessage,
    open_bag,
    select_topic,
)
from licalib_cli.io.imu_units import ImuUnits, convert_imu, detect_imu_units
from licalib_cli.io.pointcloud2 import (
    POINTFIELD_DTYPES,
    DecodedCloud,
    decode_cloud,
    field_names,
    valid_mask,
)
from licalib_cli.io.timestamps import (
    BeamTable,
    TimeLayout,
    assign_beams,
    classify_time_field,
    detect_beams,
    estimate_times,
    find_ring_field,
    find_time_field,
    time_values_to_ns,
)
from licalib_cli.measurements import ImuSamples, LidarScan

__all__ = [
    "IMU_GAP_FACTOR",
    "LIDAR_GAP_FACTOR",
    "CloudLayout",
    "Problem",
    "RawImu",
    "Recording",
    "ScanTally",
    "SegmentWindow",
    "StampStats",
    "detect_layout",
    "exact_duplicates",
    "imu_problems",
    "iter_scans",
    "lidar_stamp_problems",
    "make_scan",
    "read_imu",
    "read_raw_imu",
    "read_segment",
    "segment_window",
    "stamp_record_offset",
    "stamp_stats",
    "window_messages",
]

logger = logging.getLogger(__name__)

_NS = 1_000_000_000
_MARGIN_NS = _NS
IMU_GAP_FACTOR = 5.0
LIDAR_GAP_FACTOR = 2.5
_LAYOUT_CLOUDS = 5
_SKIP_FATAL_FRACTION = 0.5
_DEFAULT_PERIOD_NS = 100_000_000


# --------------------------------------------------------------------------------------------
# Problems and stamp statistics (shared with ``licalib info``)


def _count(n: int, noun: str, plural: str | None = None) -> str:
    """``"1 gap"``, ``"3 gaps"``: a number with its noun in agreement."""
    return f"{n} {noun if n == 1 else (plural or noun + 's')}"


def _times(n: int) -> str:
    """``"once"``, ``"twice"``, ``"3 times"``."""
    return {1: "once", 2: "twice"}.get(n, f"{n} times")


def _first(n: int) -> str:
    """``"first "`` before the position of the first of several events, else nothing."""
    return "first " if n > 1 else ""


def _verb(n: int, singular: str, plural: str) -> str:
    """The verb form agreeing with a count."""
    return singular if n == 1 else plural


@dataclass(frozen=True)
class Problem:
    """A finding about the data.

    Attributes:
        message: one sentence naming the problem and the fix.
        fatal: True when the data cannot be used as is.
        error: the :class:`LicalibError` subclass raised for it (gives the exit code).
    """

    message: str
    fatal: bool
    error: type[LicalibError] = DataError

    @property
    def exit_code(self) -> int:
        """Exit code of the error class (0 for warnings)."""
        return self.error.exit_code if self.fatal else 0

    def exception(self) -> LicalibError:
        """The exception to raise for this problem."""
        return self.error(self.message)


@dataclass(frozen=True)
class StampStats:
    """Statistics of one topic's header stamps.

    Attributes:
        count: number of stamps.
        first_ns: first stamp, ns (0 when empty).
        last_ns: last stamp, ns (0 when empty).
        period_ns: median positive stamp difference, ns (0 when unknown).
        backwards: number of times a stamp is smaller than the previous one.
        first_backwards_s: seconds after ``first_ns`` of the first backwards step.
        duplicates: number of stamps equal to the previous one.
        first_duplicate_s: seconds after ``first_ns`` of the first duplicate.
        gaps: number of differences longer than the gap factor times the period.
        max_gap_s: largest stamp difference, seconds.
        max_gap_at_s: seconds after ``first_ns`` where the largest difference starts.
    """

    count: int
    first_ns: int
    last_ns: int
    period_ns: int
    backwards: int
    first_backwards_s: float
    duplicates: int
    first_duplicate_s: float
    gaps: int
    max_gap_s: float
    max_gap_at_s: float

    @property
    def rate_hz(self) -> float:
        """Nominal rate from the median period, Hz (0 when unknown)."""
        return _NS / self.period_ns if self.period_ns > 0 else 0.0

    @property
    def duration_s(self) -> float:
        """Last minus first stamp, seconds."""
        return (self.last_ns - self.first_ns) / _NS


def stamp_stats(t_ns: npt.NDArray[np.int64], gap_factor: float) -> StampStats:
    """Order, duplicates, rate and gaps of a stamp sequence (in arrival order).

    Args:
        t_ns: (N,) stamps in the order they were recorded, ns.
        gap_factor: a difference longer than ``gap_factor * period`` counts as a gap.

    Returns:
        The statistics.
    """
    t = np.asarray(t_ns, dtype=np.int64)
    if t.size == 0:
        return StampStats(0, 0, 0, 0, 0, 0.0, 0, 0.0, 0, 0.0, 0.0)
    d = np.diff(t)
    pos = d[d > 0]
    period = int(np.median(pos)) if pos.size else 0
    t0 = int(t[0])
    back = np.flatnonzero(d < 0)
    dup = np.flatnonzero(d == 0)
    gaps = int(np.count_nonzero(d > gap_factor * period)) if period else 0
    imax = int(np.argmax(d)) if d.size else 0
    return StampStats(
        count=int(t.size),
        first_ns=t0,
        last_ns=int(t[-1]),
        period_ns=period,
        backwards=int(back.size),
        first_backwards_s=float((t[back[0] + 1] - t0) / _NS) if back.size else 0.0,
        duplicates=int(dup.size),
        first_duplicate_s=float((t[dup[0] + 1] - t0) / _NS) if dup.size else 0.0,
        gaps=gaps,
        max_gap_s=float(d[imax] / _NS) if d.size else 0.0,
        max_gap_at_s=float((t[imax] - t0) / _NS) if d.size else 0.0,
    )


def imu_problems(stats: StampStats, exact_duplicates: int = 0) -> list[Problem]:
    """Problems of the IMU stamps (see the module table).

    Args:
        stats: IMU stamp statistics.
        exact_duplicates: how many duplicates are exact copies of the previous message
            (they are dropped and only warned about).
    """
    out: list[Problem] = []
    if stats.count < 10:
        out.append(
            Problem(
                f"Only {_count(stats.count, 'IMU sample')} in the segment; choose a longer "
                "segment with --start/--duration or check the IMU topic.",
                True,
                DataError,
            )
        )
        return out
    if stats.backwards:
        out.append(
            Problem(
                f"IMU stamps go backwards {_times(stats.backwards)} "
                f"({_first(stats.backwards)}at {stats.first_backwards_s:.3f} s); re-record, or "
                "rewrite the bag in stamp order (e.g. with `rosbags-convert` and a script), or "
                "pick a segment without it with --start/--duration.",
                True,
                TimestampError,
            )
        )
    real_dups = stats.duplicates - exact_duplicates
    if real_dups > 0:
        out.append(
            Problem(
                f"IMU stamps are duplicated {_times(real_dups)} with different values "
                f"({_first(real_dups)}at {stats.first_duplicate_s:.3f} s); the IMU driver "
                "stamps messages wrongly, fix its time stamping and re-record.",
                True,
                TimestampError,
            )
        )
    if exact_duplicates > 0:
        out.append(
            Problem(
                f"{_count(exact_duplicates, 'IMU message')} "
                f"{'was' if exact_duplicates == 1 else 'were'} recorded twice; the copies are "
                "dropped.",
                False,
                TimestampError,
            )
        )
    if stats.gaps:
        out.append(
            Problem(
                f"The IMU stream has {_count(stats.gaps, 'gap')} longer than "
                f"{IMU_GAP_FACTOR:g}x its period of {stats.period_ns / 1e6:.2f} ms (largest "
                f"{stats.max_gap_s:.3f} s at {stats.max_gap_at_s:.3f} s); choose a segment "
                "without gaps with --start/--duration.",
                True,
                TimestampError,
            )
        )
    return out


def lidar_stamp_problems(stats: StampStats) -> list[Problem]:
    """Problems of the LiDAR header stamps (see the module table)."""
    out: list[Problem] = []
    if stats.count == 0:
        out.append(
            Problem(
                "No LiDAR clouds in the segment; choose another segment with --start/--duration.",
                True,
                DataError,
            )
        )
        return out
    if stats.backwards:
        out.append(
            Problem(
                f"LiDAR stamps go backwards {_times(stats.backwards)} "
                f"({_first(stats.backwards)}at {stats.first_backwards_s:.3f} s); re-record, or "
                "pick a segment without it with --start/--duration.",
                True,
                TimestampError,
            )
        )
    if stats.duplicates:
        out.append(
            Problem(
                f"LiDAR stamps are duplicated {_times(stats.duplicates)} "
                f"({_first(stats.duplicates)}at {stats.first_duplicate_s:.3f} s); the driver "
                "stamps clouds wrongly, fix it and re-record, or pick another segment with "
                "--start/--duration.",
                True,
                TimestampError,
            )
        )
    if stats.gaps:
        out.append(
            Problem(
                f"The LiDAR stream has {_count(stats.gaps, 'gap')} longer than "
                f"{LIDAR_GAP_FACTOR:g}x "
                f"its period (largest {stats.max_gap_s:.3f} s at {stats.max_gap_at_s:.3f} s); "
                "clouds were dropped while recording.",
                False,
                TimestampError,
            )
        )
    return out


# --------------------------------------------------------------------------------------------
# Segment window and clocks


@dataclass(frozen=True)
class SegmentWindow:
    """The record-time window of a segment.

    Attributes:
        start_ns: first record time of the segment, ns.
        stop_ns: record time the segment ends before, ns (None: end of the bag).
    """

    start_ns: int
    stop_ns: int | None

    def read_range(self) -> tuple[int, int | None]:
        """Record-time range to read, with the margin for stamp/record jitter."""
        stop = None if self.stop_ns is None else self.stop_ns + _MARGIN_NS
        return max(self.start_ns - _MARGIN_NS, 0), stop

    def contains(self, record_equiv_ns: int) -> bool:
        """Whether a stamp mapped to record time lies in the window."""
        return record_equiv_ns >= self.start_ns and (
            self.stop_ns is None or record_equiv_ns < self.stop_ns
        )


def segment_window(bag: BagHandle, cfg: CalibConfig, *, cap: bool = False) -> SegmentWindow:
    """Record-time window of ``cfg.bag`` (start and duration after the first message).

    With ``cap`` and no ``bag.duration_s``, the window ends ``bag.max_duration_s`` after its
    start (when the bag is longer).

    Raises:
        ConfigError: the start lies after the end of the bag (an invalid option).
    """
    start = bag.start_ns + round(cfg.bag.start_s * _NS)
    if start >= bag.end_ns:
        msg = (
            f"The segment starts at {cfg.bag.start_s:g} s but the bag lasts only "
            f"{(bag.end_ns - bag.start_ns) / _NS:.3f} s; choose a smaller --start "
            "(`bag.start_s`)."
        )
        raise ConfigError(msg)
    stop = None
    if cfg.bag.duration_s is not None:
        stop = start + round(cfg.bag.duration_s * _NS)
    elif cap and bag.end_ns - start > round(cfg.bag.max_duration_s * _NS):
        stop = start + round(cfg.bag.max_duration_s * _NS)
    return SegmentWindow(start, stop)


def stamp_record_offset(bag: BagHandle, topic: str, window: SegmentWindow, n: int = 25) -> int:
    """Median ``header.stamp - record time`` of the first messages of ``topic``, ns."""
    lo, _ = window.read_range()
    diffs = []
    for m in bag.messages([topic], lo, None):
        if m.stamp_ns is not None:
            diffs.append(m.stamp_ns - m.record_ns)
        if len(diffs) >= n:
            break
    return int(np.median(diffs)) if diffs else 0


def window_messages(
    bag: BagHandle, topic: str, window: SegmentWindow, offset_ns: int
) -> Iterator[RawMessage]:
    """Messages of ``topic`` whose header stamp, mapped to record time, is in the window.

    Args:
        bag: open bag.
        topic: topic name.
        window: record-time window.
        offset_ns: the topic's ``stamp - record`` offset (:func:`stamp_record_offset`).
    """
    lo, hi = window.read_range()
    for m in bag.messages([topic], lo, hi):
        stamp = m.stamp_ns if m.stamp_ns is not None else m.record_ns + offset_ns
        if window.contains(stamp - offset_ns):
            yield m


# --------------------------------------------------------------------------------------------
# IMU


@dataclass(frozen=True)
class RawImu:
    """IMU messages as recorded (raw units), in arrival order: t_ns (N,), gyro/accel (N, 3)."""

    t_ns: npt.NDArray[np.int64]
    gyro: npt.NDArray[np.float64]
    accel: npt.NDArray[np.float64]


def read_raw_imu(bag: BagHandle, topic: str, window: SegmentWindow, offset_ns: int) -> RawImu:
    """IMU messages of the window, deserialised one by one (memory grows with the window)."""
    t: list[int] = []
    vals: list[tuple[float, float, float, float, float, float]] = []
    for m in window_messages(bag, topic, window, offset_ns):
        msg = bag.deserialize(m)
        st = msg.header.stamp
        t.append(int(st.sec) * _NS + int(st.nanosec))
        av, la = msg.angular_velocity, msg.linear_acceleration
        vals.append((av.x, av.y, av.z, la.x, la.y, la.z))
    arr = np.asarray(vals, dtype=np.float64).reshape(-1, 6)
    return RawImu(np.asarray(t, dtype=np.int64), arr[:, :3].copy(), arr[:, 3:].copy())


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


def _imu_from_raw(raw: RawImu, cfg: CalibConfig) -> tuple[ImuSamples, ImuUnits, list[Problem]]:
    dup = exact_duplicates(raw)
    stats = stamp_stats(raw.t_ns, IMU_GAP_FACTOR)
    problems = imu_problems(stats, int(dup.sum()))
    keep = ~dup
    units = detect_imu_units(
        raw.gyro[keep], raw.accel[keep], cfg.imu.gyro_unit, cfg.imu.accel_unit, raw.t_ns[keep]
    )
    problems += [Problem(w, False, DataError) for w in units.warnings()]
    gyro, accel = convert_imu(raw.gyro[keep], raw.accel[keep], units)
    return ImuSamples(raw.t_ns[keep].copy(), gyro, accel), units, problems


def read_imu(path: Path, cfg: CalibConfig) -> tuple[ImuSamples, ImuUnits, tuple[str, ...]]:
    """Read and validate the IMU samples of the segment.

    Args:
        path: the bag (any supported form).
        cfg: configuration (``bag``, ``imu`` sections).

    Returns:
        ``(samples in rad/s and m/s^2, units, warnings)``.

    Raises:
        BagError, TopicError, DataError, TimestampError: see the module table.
        ConfigError: the segment starts after the end of the bag.
    """
    with open_bag(path) as bag:
        topic = select_topic(bag, IMU_TYPE, cfg.imu.topic, "--imu-topic", "imu.topic")
        window = segment_window(bag, cfg)
        off = stamp_record_offset(bag, topic.name, window)
        imu, units, problems = _imu_from_raw(read_raw_imu(bag, topic.name, window, off), cfg)
    _raise_fatal(problems)
    return imu, units, tuple(p.message for p in problems) + tuple(units.messages())


# --------------------------------------------------------------------------------------------
# LiDAR layout


@dataclass(frozen=True)
class CloudLayout:
    """The detected point layout of a LiDAR topic.

    Attributes:
        topic: topic name.
        fields: ``name:type`` of every field, e.g. ``("x:f4", ..., "t:u4")``.
        point_step: bytes per point.
        is_bigendian: byte order of the data.
        height: rows of the first checked cloud (1 = unorganised).
        width: points per row of the first checked cloud.
        time: how per-point times are obtained.
        ring_field: beam field name, or None when beams are recovered from elevation.
        beams: number of beams (distinct ring values, or recovered), 0 if unknown.
        beam_table: recovered beam elevations when there is no ring field.
        points_per_scan: median number of points per message (including invalid ones).
        valid_points_per_scan: median number of valid points per checked cloud.
        sweep_end_offset_ns: median ``max(point time) - header stamp`` of the checked clouds,
            ns (about one period when the stamp marks the sweep start). A cloud cannot be
            recorded before its last point, so the clock offset is measured from there.
    """

    topic: str
    fields: tuple[str, ...]
    point_step: int
    is_bigendian: bool
    height: int
    width: int
    time: TimeLayout
    ring_field: str | None
    beams: int
    beam_table: BeamTable | None = field(default=None, repr=False)
    points_per_scan: int = 0
    valid_points_per_scan: int = 0
    sweep_end_offset_ns: int = 0


def _field_desc(msg: Any) -> tuple[str, ...]:
    out = []
    for f in msg.fields:
        typ = POINTFIELD_DTYPES.get(int(f.datatype), f"?{f.datatype}")
        out.append(f"{f.name}:{typ}" + (f"x{f.count}" if int(f.count) > 1 else ""))
    return tuple(out)


def _cloud_period_ns(
    bag: BagHandle, topic: str, window: SegmentWindow, off: int, cfg: CalibConfig
) -> int:
    if cfg.lidar.scan_period_s is not None:
        return round(cfg.lidar.scan_period_s * _NS)
    stamps = []
    for m in window_messages(bag, topic, window, off):
        if m.stamp_ns is not None:
            stamps.append(m.stamp_ns)
        if len(stamps) >= 50:
            break
    d = np.diff(np.asarray(stamps, np.int64))
    d = d[d > 0]
    return int(np.median(d)) if d.size else _DEFAULT_PERIOD_NS


def _skip_reason(decoded: DecodedCloud, mask: npt.NDArray[np.bool_]) -> str | None:
    if len(decoded) == 0:
        return "empty"
    if not mask.any():
        finite = np.isfinite(decoded.xyz).all(axis=1) & np.any(decoded.xyz != 0, axis=1)
        return "invalid" if not finite.any() else "out of range"
    return None


def detect_layout(
    bag: BagHandle, topic: str, window: SegmentWindow, off: int, cfg: CalibConfig
) -> CloudLayout:
    """Detect fields, time field (unit, reference, stamp position) and beams of a topic.

    Uses the first :data:`_LAYOUT_CLOUDS` clouds of the segment that have valid points.

    Raises:
        DataError: no cloud of the segment has valid points.
        TimestampError: the time field has zero span in the clouds checked.
        ConfigError: the configured time or ring field is not in the clouds.
    """
    lo = cfg.lidar
    period = _cloud_period_ns(bag, topic, window, off, cfg)
    samples: list[tuple[int, np.ndarray]] = []
    xyzs: list[npt.NDArray[np.float64]] = []
    rings: list[np.ndarray] = []
    counts: list[int] = []
    valid_counts: list[int] = []
    first: Any = None
    time_field: str | None = None
    ring_field: str | None = None
    reasons = {"empty": 0, "invalid": 0, "out of range": 0}
    seen = 0
    for m in window_messages(bag, topic, window, off):
        msg = bag.deserialize(m)
        seen += 1
        if first is None:
            first = msg
            names = field_names(msg)
            time_field = find_time_field(names, lo.time_field)
            ring_field = find_ring_field(names, lo.ring_field)
        stamp = m.stamp_ns if m.stamp_ns is not None else m.record_ns
        dec = decode_cloud(msg, stamp, time_field, ring_field)
        counts.append(len(dec))
        mask = valid_mask(dec.xyz, lo.min_range_m, lo.max_range_m)
        reason = _skip_reason(dec, mask)
        if reason is not None:
            reasons[reason] += 1
            continue
        valid_counts.append(int(mask.sum()))
        xyzs.append(dec.xyz[mask])
        if dec.time_raw is not None:
            samples.append((stamp, dec.time_raw[mask]))
        if dec.ring is not None:
            rings.append(dec.ring[mask])
        if len(xyzs) >= _LAYOUT_CLOUDS:
            break
    if first is None:
        msg_ = "No LiDAR clouds in the segment; choose another segment with --start/--duration."
        raise DataError(msg_)
    if not xyzs:
        msg_ = _all_skipped_message(seen, reasons)
        raise DataError(msg_)
    if time_field is not None:
        tl = classify_time_field(
            time_field, samples, period, unit=lo.time_unit, reference=lo.time_reference
        )
    else:
        position = lo.stamp_position or "start"
        notes = (
            ()
            if lo.stamp_position
            else ("no time field: stamp assumed at the sweep start (set `lidar.stamp_position`)",)
        )
        _, method, cw = estimate_times(xyzs[0], 0, period, position, lo.clockwise)
        tl = TimeLayout(None, None, "estimated", position, period, method, cw, notes)
    table = None
    if ring_field is not None:
        beams = int(np.unique(np.concatenate(rings)).size)
    else:
        table = detect_beams(xyzs, lo.num_beams)
        beams = table.num_beams
    if tl.field is not None:
        ends = [int(time_values_to_ns(v, st, tl).max()) - st for st, v in samples if v.size]
        end_offset = int(np.median(ends)) if ends else 0
        if abs(end_offset) > 2 * tl.scan_period_ns:  # implausible layout: do not trust it
            end_offset = 0
    else:
        end_offset = tl.scan_period_ns if tl.stamp_position != "end" else 0
    return CloudLayout(
        topic=topic,
        fields=_field_desc(first),
        point_step=int(first.point_step),
        is_bigendian=bool(first.is_bigendian),
        height=int(first.height),
        width=int(first.width),
        time=tl,
        ring_field=ring_field,
        beams=beams,
        beam_table=table,
        points_per_scan=int(np.median(counts)),
        valid_points_per_scan=int(np.median(valid_counts)),
        sweep_end_offset_ns=end_offset,
    )


def _all_skipped_message(total: int, reasons: dict[str, int]) -> str:
    every = "The only LiDAR cloud" if total == 1 else f"All {total} LiDAR clouds"
    if reasons["empty"] == total:
        return (
            f"{every} of the segment {'is' if total == 1 else 'are'} empty; check the LiDAR "
            "driver and topic, or choose another segment with --start/--duration."
        )
    if reasons["invalid"] + reasons["empty"] == total:
        return (
            f"{every} of the segment {'has' if total == 1 else 'have'} only NaN or zero "
            "points; check the LiDAR driver (or its return mode) and re-record."
        )
    return (
        f"No point of the {_count(total, 'LiDAR cloud')} of the segment lies between "
        "`lidar.min_range_m` and `lidar.max_range_m`; widen that range in the config."
    )


# --------------------------------------------------------------------------------------------
# Scans


def make_scan(
    dec: DecodedCloud, layout: CloudLayout, cfg: CalibConfig, shift_ns: int
) -> LidarScan | str:
    """A LidarScan from a decoded cloud, or the reason it is skipped."""
    mask = valid_mask(dec.xyz, cfg.lidar.min_range_m, cfg.lidar.max_range_m)
    reason = _skip_reason(dec, mask)
    if reason is not None:
        return reason
    xyz = dec.xyz[mask]
    tl = layout.time
    if tl.field is not None:
        if dec.time_raw is None:
            return "no time field"
        v = dec.time_raw[mask]
        if v.size > 1 and np.ptp(v) == 0:
            return "zero span"
        t_ns = time_values_to_ns(v, dec.stamp_ns, tl)
    else:
        position: Literal["start", "end"] = "end" if tl.stamp_position == "end" else "start"
        cw = tl.clockwise if tl.clockwise is not None else cfg.lidar.clockwise
        t_ns, _, _ = estimate_times(xyz, dec.stamp_ns, tl.scan_period_ns, position, cw)
    if dec.ring is not None:
        ring = dec.ring[mask]
    elif layout.beam_table is not None:
        ring = assign_beams(xyz, layout.beam_table)
    else:
        ring = None
    inten = dec.intensity[mask] if dec.intensity is not None else None
    return LidarScan(
        stamp_ns=dec.stamp_ns + shift_ns,
        xyz=xyz,
        t_ns=t_ns + shift_ns,
        ring=ring,
        intensity=inten,
    )


@dataclass
class ScanTally:
    """Counts of clouds seen and skipped (by reason) while streaming, and their stamps."""

    total: int = 0
    skipped: dict[str, int] = field(
        default_factory=lambda: {
            "empty": 0,
            "invalid": 0,
            "out of range": 0,
            "zero span": 0,
            "no time field": 0,
        }
    )
    stamps: list[int] = field(default_factory=list)

    def problems(self) -> list[Problem]:
        out: list[Problem] = []
        n_skip = sum(self.skipped.values())
        if self.total == 0:
            return out
        fatal = n_skip > _SKIP_FATAL_FRACTION * self.total
        if n_skip == self.total and self.skipped["zero span"] == 0:
            out.append(Problem(_all_skipped_message(self.total, self.skipped), True, DataError))
            return out
        if self.skipped["zero span"] and (fatal or self.skipped["zero span"] == self.total):
            out.append(
                Problem(
                    f"{self.skipped['zero span']} of {_count(self.total, 'LiDAR cloud')} "
                    f"{_verb(self.skipped['zero span'], 'has', 'have')} a per-point "
                    "time field with zero span; set `lidar.time_field: none` to estimate times "
                    "from the azimuth instead.",
                    True,
                    TimestampError,
                )
            )
            return out
        for reason, n in self.skipped.items():
            if n == 0:
                continue
            what = {
                "empty": _verb(n, "is", "are") + " empty",
                "invalid": _verb(n, "has", "have") + " only NaN or zero points",
                "out of range": _verb(n, "has", "have") + " no point within the range limits",
                "zero span": _verb(n, "has", "have") + " a time field with zero span",
                "no time field": _verb(n, "lacks", "lack") + " the time field",
            }[reason]
            out.append(
                Problem(
                    f"{n} of {_count(self.total, 'LiDAR cloud')} {what} and "
                    f"{_verb(n, 'was', 'were')} skipped"
                    + ("; check the LiDAR driver and re-record." if fatal else "."),
                    fatal,
                    DataError,
                )
            )
        return out


def _scan_stream(
    bag: BagHandle,
    topic: str,
    window: SegmentWindow,
    off: int,
    layout: CloudLayout,
    cfg: CalibConfig,
    shift_ns: int,
    tally: ScanTally,
) -> Iterator[LidarScan]:
    for m in window_messages(bag, topic, window, off):
        msg = bag.deserialize(m)
        stamp = m.stamp_ns if m.stamp_ns is not None else m.record_ns
        tally.total += 1
        tally.stamps.append(stamp)
        names = field_names(msg)
        tf = layout.time.field if layout.time.field in names else None
        rf = layout.ring_field if layout.ring_field in names else None
        dec = decode_cloud(msg, stamp, tf, rf)
        if layout.time.field is not None and tf is None:
            tally.skipped["no time field"] += 1
            continue
        scan = make_scan(dec, layout, cfg, shift_ns)
        if isinstance(scan, str):
            tally.skipped[scan] += 1
            logger.debug("cloud at %d skipped: %s", stamp, scan)
            continue
        yield scan


# --------------------------------------------------------------------------------------------
# Public readers


@dataclass(frozen=True)
class Recording:
    """One segment of a bag, validated and converted.

    Attributes:
        imu: IMU samples (rad/s, m/s^2), IMU clock.
        scans: LiDAR scans of the segment in stamp order; their times are in the IMU clock
            when ``lidar_shift_ns != 0``.
        imu_topic: IMU topic read.
        lidar_topic: LiDAR topic read.
        layout: detected point layout.
        imu_units: units of the raw IMU messages.
        clock_offset_ns: coarse ``t_imu - t_lidar`` clock difference, ns.
        lidar_shift_ns: shift applied to every LiDAR time (``clock_offset_ns`` when it is
            1 s or more, else 0), ns.
        start_ns: segment start in the IMU clock, ns.
        end_ns: segment end in the IMU clock, ns (exclusive).
        warnings: non-fatal findings, one sentence each.
    """

    imu: ImuSamples
    scans: tuple[LidarScan, ...]
    imu_topic: str
    lidar_topic: str
    layout: CloudLayout
    imu_units: ImuUnits
    clock_offset_ns: int
    lidar_shift_ns: int
    start_ns: int
    end_ns: int
    warnings: tuple[str, ...] = ()

    @property
    def clock_offset_s(self) -> float:
        """Coarse clock difference ``t_imu - t_lidar``, seconds."""
        return self.clock_offset_ns / _NS


def _raise_fatal(problems: list[Problem]) -> None:
    for p in problems:
        if p.fatal:
            raise p.exception()


def _clock_shift(clock_offset_ns: int) -> int:
    return clock_offset_ns if abs(clock_offset_ns) >= _NS else 0


def read_segment(path: Path, cfg: CalibConfig) -> Recording:
    """Read, convert and validate the IMU samples and LiDAR scans of one segment.

    Args:
        path: a ROS1 ``.bag`` (or folder of split ``.bag`` files), a ROS2 bag folder, or a bare
            ``.db3``/``.mcap`` file.
        cfg: configuration (``bag``, ``imu`` and ``lidar`` sections).

    Returns:
        The recording. All scans of the segment are held in memory; use :func:`iter_scans`
        to stream them instead.

    Raises:
        BagError: missing, unreadable, corrupt or truncated bag.
        TopicError: missing, ambiguous or wrongly typed topics.
        DataError: unusable clouds or too little data.
        TimestampError: unsorted or duplicated stamps, IMU gaps, zero-span time fields.
        ConfigError: the segment starts after the end of the bag, or a configured time or
            ring field is not in the clouds.
    """
    with open_bag(path) as bag:
        imu_t = select_topic(bag, IMU_TYPE, cfg.imu.topic, "--imu-topic", "imu.topic")
        lid_t = select_topic(bag, CLOUD_TYPE, cfg.lidar.topic, "--lidar-topic", "lidar.topic")
        window = segment_window(bag, cfg, cap=True)
        bag_start, bag_end = bag.start_ns, bag.end_ns
        off_imu = stamp_record_offset(bag, imu_t.name, window)
        off_lid = stamp_record_offset(bag, lid_t.name, window)
        imu, units, problems = _imu_from_raw(read_raw_imu(bag, imu_t.name, window, off_imu), cfg)
        _raise_fatal(problems)
        layout = detect_layout(bag, lid_t.name, window, off_lid, cfg)
        clock_offset = off_imu - (off_lid + layout.sweep_end_offset_ns)
        shift = _clock_shift(clock_offset)
        tally = ScanTally()
        scans = tuple(_scan_stream(bag, lid_t.name, window, off_lid, layout, cfg, shift, tally))
    lstats = stamp_stats(np.asarray(tally.stamps, np.int64), LIDAR_GAP_FACTOR)
    problems += lidar_stamp_problems(lstats) + tally.problems()
    _raise_fatal(problems)
    warnings = (
        [p.message for p in problems]
        + list(layout.time.warnings)
        + units.messages()
        + list(layout.time.notes)
    )
    if cfg.bag.duration_s is None and window.stop_ns is not None:
        warnings.append(
            f"The bag lasts {(bag_end - bag_start) / _NS:.0f} s; only {cfg.bag.max_duration_s:g} "
            f"s from {cfg.bag.start_s:g} s are used. Choose the part with the most varied motion "
            "with --start/--duration (or raise bag.max_duration_s)."
        )
    if shift:
        warnings.append(
            f"The LiDAR and IMU clocks differ by {clock_offset / _NS:+.3f} s; LiDAR times were "
            "shifted into the IMU clock."
        )
    for w in warnings:
        logger.warning(w)
    if window.stop_ns is not None:
        end_ns = window.stop_ns + off_imu
    else:
        end_ns = int(imu.t_ns[-1]) + 1
    return Recording(
        imu=imu,
        scans=scans,
        imu_topic=imu_t.name,
        lidar_topic=lid_t.name,
        layout=layout,
        imu_units=units,
        clock_offset_ns=clock_offset,
        lidar_shift_ns=shift,
        start_ns=window.start_ns + off_imu,
        end_ns=end_ns,
        warnings=tuple(warnings),
    )


def iter_scans(
    path: Path, cfg: CalibConfig, shift_ns: int = 0, warnings: list[str] | None = None
) -> Iterator[LidarScan]:
    """Stream the LiDAR scans of the segment one at a time (constant memory).

    Skipped clouds and stamp problems are checked as they come: a stamp going backwards or
    repeating raises at once; skip counts are appended to ``warnings`` at the end and raise
    when more than half of the clouds were skipped.

    Args:
        path: the bag.
        cfg: configuration (``bag`` and ``lidar`` sections).
        shift_ns: added to every LiDAR time (e.g. ``Recording.lidar_shift_ns``).
        warnings: list that receives non-fatal findings, or None.

    Yields:
        :class:`LidarScan` in stamp order.

    Raises:
        BagError, TopicError, DataError, TimestampError, ConfigError: as :func:`read_segment`.
    """
    with open_bag(path) as bag:
        lid_t = select_topic(bag, CLOUD_TYPE, cfg.lidar.topic, "--lidar-topic", "lidar.topic")
        window = segment_window(bag, cfg)
        off = stamp_record_offset(bag, lid_t.name, window)
        layout = detect_layout(bag, lid_t.name, window, off, cfg)
        tally = ScanTally()
        last: int | None = None
        for scan in _scan_stream(bag, lid_t.name, window, off, layout, cfg, shift_ns, tally):
            if last is not None and scan.stamp_ns <= last:
                what = "go backwards" if scan.stamp_ns < last else "are duplicated"
                at = (scan.stamp_ns - shift_ns - tally.stamps[0]) / _NS
                msg = (
                    f"LiDAR stamps {what} at {at:.3f} s; re-record, or pick a segment without "
                    "it with --start/--duration."
                )
                raise TimestampError(msg)
            last = scan.stamp_ns
            yield scan
    problems = tally.problems()
    _raise_fatal(problems)
    if warnings is not None:
        warnings.extend(p.message for p in problems)
