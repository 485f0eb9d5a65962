"""Read a time segment of a bag into IMU samples and LiDAR scans, with validation.

Entry points:

* :func:`read_segment` -> :class:`~licalib_cli.measurements.Recording` (IMU samples + all scans
  of the segment);
* :func:`iter_scans` streams the scans one by one (constant memory on long bags);
* :func:`read_imu` reads only the IMU samples.

``licalib info`` (:mod:`licalib_cli.inspection`) reads through the same functions
(:func:`read_imu_stream`, :func:`read_lidar_stream`, :func:`segment_findings`), so that it
reaches the same diagnosis, with the same exit code, as the commands that calibrate.

Time conventions: int64 ns everywhere. The segment ``[bag.start_s, bag.start_s +
bag.duration_s)`` is measured from the bag's first record time. Messages are read by record
time (with a 1 s margin) and then selected by ``header.stamp``: each topic's median
``stamp - record`` offset maps the window into that topic's clock, so that IMU and LiDAR
windows cover the same recorder interval even when the sensors use different clocks. A
message whose stamp lies more than the margin off its topic's offset (e.g. a zero stamp in a
stamped stream) is skipped and counted as unreadable.

Clock offset: ``clock_offset_ns = offset_imu - offset_lidar`` is the coarse difference
``t_imu - t_lidar`` of the two clocks (same sign as ``time_offset_s``), where the LiDAR offset
is taken at the last point of each sweep (a cloud is published after its sweep ends), so the
estimate is good to the publication latency (milliseconds). When it is 1 s or
more (e.g. LiDAR on UNIX time, IMU on boot time) the LiDAR times of the recording are shifted
into the IMU clock (``Recording.lidar_shift_ns``) and a warning says so; smaller offsets are
left to the calibration.

Validation, in this order (fatal = raises, with the error's exit code; otherwise a warning in
``Recording.warnings``):

===============================================  =========================================
segment shorter than 2 s (options or bag)        fatal (ExcitationError)
header stamps unset (zero) on a topic            fatal (TimestampError)
IMU samples with NaN or inf                      isolated ones dropped, warning; fatal
                                                 (DataError) above 1 % or in runs
IMU stamps going backwards                       fatal (TimestampError)
IMU duplicated stamps with different values      fatal (TimestampError)
IMU exact duplicate messages                     dropped, warning
IMU gap longer than 5x the nominal period        fatal (TimestampError); says so when
                                                 unreadable messages explain it
fewer than 10 IMU samples in the segment         fatal: TimestampError when the sensors were
                                                 recorded at different times, else DataError
accelerometer without gravity (median < 3 m/s^2) fatal (DataError)
IMU rate under one sample per spline knot        fatal (DataError)
undecodable or far-off-stamped messages          skipped, counted, warning
LiDAR stamps going backwards or duplicated       fatal (TimestampError)
LiDAR gap longer than 2.5x the scan period       warning
empty / all-NaN-or-zero / out-of-range cloud,    skipped, warning naming the first one;
fewer than 100 valid points, one beam only,      fatal (DataError) when more than
corrupt (truncated, bad sizes or values)         ``lidar.max_skipped_fraction`` (half) of the
                                                 clouds are skipped
time field with zero span in a cloud             skipped, warning; fatal (TimestampError)
                                                 when it is so in the clouds used to detect
                                                 the layout or past that fraction
IMU and LiDAR stamps that do not overlap         fatal (TimestampError): recorded at
                                                 different times, or clocks not synchronised
less than 2 s covered by both sensors            fatal (ExcitationError)
===============================================  =========================================
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

from licalib_cli.config import CalibConfig
from licalib_cli.errors import (
    ConfigError,
    DataError,
    ExcitationError,
    LicalibError,
    TimestampError,
    TopicError,
)
from licalib_cli.io.bag import (
    CLOUD_TYPE,
    IMU_TYPE,
    BagHandle,
    MessageLosses,
    RawMessage,
    imu_vectors_from_raw,
    open_bag,
    select_topic,
)
from licalib_cli.io.imu_units import GRAVITY, ImuUnits, convert_imu, detect_imu_units
from licalib_cli.io.ouster import cloud_frame, read_factory_extrinsic
from licalib_cli.io.pointcloud2 import (
    POINTFIELD_DTYPES,
    CloudError,
    DecodedCloud,
    decode_cloud,
    field_names,
    valid_mask,
)
from licalib_cli.io.timestamps import (
    UNIT_TO_NS,
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
from licalib_cli.measurements import ImuSamples, LidarScan, Recording

__all__ = [
    "IMU_GAP_FACTOR",
    "LIDAR_GAP_FACTOR",
    "MIN_CLOUD_POINTS",
    "MIN_SEGMENT_S",
    "CloudLayout",
    "Finding",
    "ImuRead",
    "LidarRead",
    "RawImu",
    "Recording",
    "ScanTally",
    "SegmentWindow",
    "Skip",
    "StampStats",
    "clock_offset",
    "clock_shift",
    "detect_layout",
    "exact_duplicates",
    "imu_problems",
    "iter_scans",
    "lidar_stamp_problems",
    "make_scan",
    "read_imu",
    "read_imu_stream",
    "read_lidar_stream",
    "read_raw_imu",
    "read_segment",
    "segment_findings",
    "segment_window",
    "stamp_record_offset",
    "stamp_stats",
    "validate_imu",
    "window_findings",
    "window_messages",
]

logger = logging.getLogger(__name__)

_NS = 1_000_000_000
_MARGIN_NS = _NS
_MS = 1_000_000  # slack of comparisons of durations built from rounded stamps
IMU_GAP_FACTOR = 5.0
LIDAR_GAP_FACTOR = 2.5
MIN_SEGMENT_S = 2.0
"""Shorter segments are refused: a few scans cannot determine the extrinsic."""
MIN_CLOUD_POINTS = 100
"""Clouds with fewer valid points are skipped: no LiDAR odometry works on them."""
_MIN_IMU_SAMPLES = 10
_MAX_RING = 512
_MAX_BAD_IMU_FRACTION = 0.01
_MAX_BAD_IMU_RUN = 3  # dropping a run of 3 leaves a 4-period hole, under the gap factor
_NO_GRAVITY_M_S2 = 3.0
_MAX_IMU_READING = 1e6  # rad/s, deg/s, g or m/s^2: beyond this a reading is garbage
_LAYOUT_CLOUDS = 5
_DEFAULT_PERIOD_NS = 100_000_000
_ONE_BEAM_RAD = np.deg2rad(0.5)  # elevation spread of a single beam's points
_MAX_TIME_NS = 4e18  # per-point times must fit int64 ns (NaN and beyond are corrupt)
_MAX_SPAN_S = 1e9  # durations beyond 31 years are "to the end" (keeps the ns in int64)


# --------------------------------------------------------------------------------------------
# Findings and stamp statistics (shared with ``licalib info``)


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


def _stamp_text(stamp_ns: int) -> str:
    """A header stamp as ``sec.nanosec``, as ROS tools print it."""
    sec, nsec = divmod(int(stamp_ns), _NS)
    return f"{sec}.{nsec:09d}"


@dataclass(frozen=True)
class Finding:
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
        """The exception to raise for this finding."""
        return self.error(self.message)


def first_fatal(findings: list[Finding]) -> Finding | None:
    """The first fatal finding, or None."""
    return next((f for f in findings if f.fatal), None)


def _raise_fatal(findings: list[Finding]) -> None:
    fatal = first_fatal(findings)
    if fatal is not None:
        raise fatal.exception()


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
        missing_in_gaps: periods missing in the gaps, about the messages they lack.
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
    missing_in_gaps: int = 0

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
    long = d[d > gap_factor * period] if period else d[:0]
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
        gaps=int(long.size),
        max_gap_s=float(d[imax] / _NS) if d.size else 0.0,
        max_gap_at_s=float((t[imax] - t0) / _NS) if d.size else 0.0,
        missing_in_gaps=int(np.sum(np.round(long / period) - 1)) if long.size else 0,
    )


def _losses_explain(stats: StampStats, lost: MessageLosses | None) -> bool:
    """Whether unreadable messages account for the gaps (at least 80 % of what they lack)."""
    return lost is not None and lost.total > 0 and lost.total >= 0.8 * stats.missing_in_gaps


def imu_problems(
    stats: StampStats, exact_duplicates: int = 0, lost: MessageLosses | None = None
) -> list[Finding]:
    """Findings on the IMU stamps (see the module table).

    Args:
        stats: IMU stamp statistics.
        exact_duplicates: how many duplicates are exact copies of the previous message
            (they are dropped and only warned about).
        lost: the topic's unreadable messages, to tell a damaged bag from a sensor that
            stopped publishing.
    """
    out: list[Finding] = []
    if stats.count < _MIN_IMU_SAMPLES:
        out.append(
            Finding(
                f"Only {_count(stats.count, 'IMU sample')} in the segment; choose a longer "
                "segment with --start/--duration or check the IMU topic.",
                True,
                DataError,
            )
        )
        return out
    if stats.backwards:
        out.append(
            Finding(
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
            Finding(
                f"IMU stamps are duplicated {_times(real_dups)} with different values "
                f"({_first(real_dups)}at {stats.first_duplicate_s:.3f} s); the IMU driver "
                "stamps messages wrongly, fix its time stamping and re-record.",
                True,
                TimestampError,
            )
        )
    if exact_duplicates > 0:
        out.append(
            Finding(
                f"{_count(exact_duplicates, 'IMU message')} "
                f"{'was' if exact_duplicates == 1 else 'were'} recorded twice; the copies are "
                "dropped.",
                False,
                TimestampError,
            )
        )
    if stats.gaps:
        gap = (
            f"The IMU stream has {_count(stats.gaps, 'gap')} longer than "
            f"{IMU_GAP_FACTOR:g}x its period of {stats.period_ns / 1e6:.2f} ms (largest "
            f"{stats.max_gap_s:.3f} s at {stats.max_gap_at_s:.3f} s)"
        )
        if lost is not None and _losses_explain(stats, lost):
            n = lost.total
            gap += (
                f", caused by {_count(n, 'IMU message')} of the bag that cannot be read "
                f"({lost.describe()}); repair the bag or choose a segment without "
                f"{_verb(n, 'it', 'them')} with --start/--duration."
            )
        else:
            gap += "; choose a segment without gaps with --start/--duration."
        out.append(Finding(gap, True, TimestampError))
    return out


def lidar_stamp_problems(stats: StampStats, lost: MessageLosses | None = None) -> list[Finding]:
    """Findings on the LiDAR header stamps (see the module table)."""
    out: list[Finding] = []
    if stats.count == 0:
        out.append(
            Finding(
                "No LiDAR clouds in the segment; choose another segment with --start/--duration.",
                True,
                DataError,
            )
        )
        return out
    if stats.backwards:
        out.append(
            Finding(
                f"LiDAR stamps go backwards {_times(stats.backwards)} "
                f"({_first(stats.backwards)}at {stats.first_backwards_s:.3f} s); re-record, or "
                "pick a segment without it with --start/--duration.",
                True,
                TimestampError,
            )
        )
    if stats.duplicates:
        out.append(
            Finding(
                f"LiDAR stamps are duplicated {_times(stats.duplicates)} "
                f"({_first(stats.duplicates)}at {stats.first_duplicate_s:.3f} s); the driver "
                "stamps clouds wrongly, fix it and re-record, or pick another segment with "
                "--start/--duration.",
                True,
                TimestampError,
            )
        )
    if stats.gaps:
        gap = (
            f"The LiDAR stream has {_count(stats.gaps, 'gap')} longer than "
            f"{LIDAR_GAP_FACTOR:g}x "
            f"its period (largest {stats.max_gap_s:.3f} s at {stats.max_gap_at_s:.3f} s)"
        )
        if lost is not None and _losses_explain(stats, lost):
            gap += (
                f", caused by {_count(lost.total, 'cloud')} of the bag that cannot be read "
                f"({lost.describe()}); repair the bag to use them."
            )
        else:
            gap += "; clouds were dropped while recording."
        out.append(Finding(gap, False, TimestampError))
    return out


def _loss_findings(topic: str, what: str, lost: MessageLosses) -> list[Finding]:
    """A warning on the messages of ``topic`` that could not be used, if any."""
    if lost.total == 0:
        return []
    n = lost.total
    return [
        Finding(
            f"{_count(n, what + ' message')} on {topic} cannot be read ({lost.describe()}) "
            f"and {_verb(n, 'is', 'are')} skipped; the bag is damaged, repair or re-record it "
            "if the data there is needed.",
            False,
            DataError,
        )
    ]


# --------------------------------------------------------------------------------------------
# Segment window and clocks


@dataclass(frozen=True)
class SegmentWindow:
    """The record-time window of a segment.

    Attributes:
        start_ns: first record time of the segment, ns.
        stop_ns: record time the segment ends before, ns (None: end of the bag).
        from_bag_start: the segment starts at the bag's first message: nothing before
            ``start_ns`` is cut (a stamp mapped to record time with its topic's median offset
            may land a little before the bag's first record time, e.g. the first IMU message
            recorded with less latency than the others).
    """

    start_ns: int
    stop_ns: int | None
    from_bag_start: bool = False

    def read_range(self) -> tuple[int, int | None]:
        """Record-time range to read, with the margin for stamp/record jitter."""
        stop = None if self.stop_ns is None else self.stop_ns + _MARGIN_NS
        return max(self.start_ns - _MARGIN_NS, 0), stop

    def contains(self, record_equiv_ns: int) -> bool:
        """Whether a stamp mapped to record time lies in the window."""
        return (self.from_bag_start or record_equiv_ns >= self.start_ns) and (
            self.stop_ns is None or record_equiv_ns < self.stop_ns
        )


def segment_window(bag: BagHandle, cfg: CalibConfig, *, cap: bool = False) -> SegmentWindow:
    """Record-time window of ``cfg.bag`` (start and duration after the first message).

    With ``cap`` and no ``bag.duration_s``, the window ends ``bag.max_duration_s`` after its
    start (when the bag is longer). Any finite start and duration are accepted (a duration
    longer than the bag reads to its end).

    Raises:
        ConfigError: the start lies after the end of the bag (an invalid option).
    """
    bag_s = (bag.end_ns - bag.start_ns) / _NS
    if cfg.bag.start_s >= bag_s:
        msg = (
            f"The segment starts at {cfg.bag.start_s:g} s but the bag lasts only "
            f"{bag_s:.3f} s; choose a smaller --start (`bag.start_s`)."
        )
        raise ConfigError(msg)
    start = bag.start_ns + round(cfg.bag.start_s * _NS)
    stop = None
    if cfg.bag.duration_s is not None:
        stop = start + round(min(cfg.bag.duration_s, _MAX_SPAN_S) * _NS)
    elif cap:
        limit = round(min(cfg.bag.max_duration_s, _MAX_SPAN_S) * _NS)
        if bag.end_ns - start > limit:
            stop = start + limit
    return SegmentWindow(start, stop, from_bag_start=cfg.bag.start_s <= 0)


def window_findings(
    bag: BagHandle, window: SegmentWindow, cfg: CalibConfig, min_span_s: float = MIN_SEGMENT_S
) -> list[Finding]:
    """The segment is shorter than ``min_span_s``, too short to calibrate, from its window
    alone (before reading)."""
    end = bag.end_ns if window.stop_ns is None else min(window.stop_ns, bag.end_ns)
    length_s = (end - window.start_ns) / _NS
    if length_s >= min_span_s:
        return []
    bag_s = (bag.end_ns - bag.start_ns) / _NS
    if bag_s < min_span_s:
        msg = (
            f"The bag lasts only {bag_s:.2f} s, too little to calibrate; record 10-60 s of "
            "motion with rotation about all three axes."
        )
    elif cfg.bag.duration_s is not None and cfg.bag.duration_s < min_span_s:
        msg = (
            f"The segment is {cfg.bag.duration_s:g} s long (--duration), too short to "
            f"calibrate; give at least {min_span_s:g} s (10-60 s of varied motion is best)."
        )
    else:
        msg = (
            f"The segment from {cfg.bag.start_s:g} s to the end of the bag ({bag_s:.3f} s) "
            f"lasts only {length_s:.2f} s, too little to calibrate; choose an earlier --start "
            f"(at least {min_span_s:g} s before the end, 10-60 s of varied motion is best)."
        )
    return [Finding(msg, True, ExcitationError)]


def _clock_samples(bag: BagHandle, topic: str, window: SegmentWindow, n: int) -> list[RawMessage]:
    """The first ``n`` messages of ``topic`` from the start of the window's reading range."""
    lo, _ = window.read_range()
    out: list[RawMessage] = []
    for m in bag.messages([topic], lo, None):
        out.append(m)
        if len(out) >= n:
            break
    return out


def _median_offset(messages: list[RawMessage]) -> int:
    diffs = [m.stamp_ns - m.record_ns for m in messages if m.stamp_ns]
    return int(np.median(diffs)) if diffs else 0


def stamp_record_offset(bag: BagHandle, topic: str, window: SegmentWindow, n: int = 25) -> int:
    """Median ``header.stamp - record time`` of the first messages of ``topic``, ns (messages
    with an unset, zero stamp are left out; 0 when all are)."""
    return _median_offset(_clock_samples(bag, topic, window, n))


def topic_clock(
    bag: BagHandle, topic: str, window: SegmentWindow, what: str
) -> tuple[int, list[Finding]]:
    """The topic's ``stamp - record`` offset (:func:`stamp_record_offset`), and a fatal
    finding when its first messages carry no header stamp (all zero)."""
    first = _clock_samples(bag, topic, window, 25)
    if first and not any(m.stamp_ns for m in first):
        unset = Finding(
            f"The {what} messages on {topic} have unset header stamps (all zero); the driver "
            "does not stamp them, fix its time stamping (header.stamp) and re-record.",
            True,
            TimestampError,
        )
        return 0, [unset]
    return _median_offset(first), []


def window_messages(
    bag: BagHandle, topic: str, window: SegmentWindow, offset_ns: int
) -> Iterator[RawMessage]:
    """Messages of ``topic`` whose header stamp, mapped to record time, is in the window.

    A message of the window whose stamp lies more than the reading margin (1 s) off the
    topic's offset (e.g. a zero stamp among stamped messages) is skipped and counted in
    ``bag.losses`` as mis-stamped.

    Args:
        bag: open bag.
        topic: topic name.
        window: record-time window.
        offset_ns: the topic's ``stamp - record`` offset (:func:`stamp_record_offset`).
    """
    lo, hi = window.read_range()
    for m in bag.messages([topic], lo, hi):
        if m.stamp_ns is None:
            if window.contains(m.record_ns):
                yield m
            continue
        if abs(m.stamp_ns - m.record_ns - offset_ns) > _MARGIN_NS:
            if window.contains(m.record_ns):
                bag.loss(topic).misstamped.add(m.record_ns)
            continue
        if window.contains(m.stamp_ns - offset_ns):
            yield m


def clock_offset(imu_offset_ns: int, lidar_offset_ns: int, layout: CloudLayout) -> int:
    """Coarse ``t_imu - t_lidar`` of the two clocks, ns, with the LiDAR taken at the last
    point of each sweep (a cloud is recorded after its sweep ends)."""
    return imu_offset_ns - (lidar_offset_ns + layout.sweep_end_offset_ns)


def clock_shift(clock_offset_ns: int) -> int:
    """The shift applied to LiDAR times: the clock offset when it is 1 s or more, else 0."""
    return clock_offset_ns if abs(clock_offset_ns) >= _NS else 0


def _record_spans(bag: BagHandle, topics: list[str]) -> dict[str, tuple[int, int, int]]:
    """``(first, last, count)`` record times of each topic over the whole bag (a full pass
    over their messages, without decoding them)."""
    spans: dict[str, tuple[int, int, int]] = {}
    for m in bag.messages(topics):
        first, _, n = spans.get(m.topic, (m.record_ns, m.record_ns, 0))
        spans[m.topic] = (first, m.record_ns, n + 1)
    return spans


def _different_times(
    bag_start_ns: int, first: tuple[str, int, int], second: tuple[str, int, int]
) -> Finding:
    """The two sensors' messages were recorded at different times: ``(name, first record,
    last record)`` of each, ns."""
    t0 = bag_start_ns

    def span(a: int, b: int) -> str:
        return f"{(a - t0) / _NS:.1f}-{(b - t0) / _NS:.1f} s"

    return Finding(
        f"The {first[0]} messages (recorded {span(first[1], first[2])} after the bag start) "
        f"and the {second[0]} messages ({span(second[1], second[2])}) were recorded at "
        "different times; the bag holds no time with both sensors, record them together (or "
        "pass bags of the same session).",
        True,
        TimestampError,
    )


def _absence_finding(
    bag: BagHandle,
    window: SegmentWindow,
    topic: str,
    other: str | None,
    what: str,
    default: Finding,
) -> Finding:
    """Why the segment holds (almost) no ``what`` messages: the topic is empty, the two
    sensors were recorded at different times, or the segment misses the time both were
    recorded; ``default`` when none of these."""
    spans = _record_spans(bag, [topic] if other is None else [topic, other])
    if topic not in spans:
        return Finding(
            f"The bag has no readable message on {topic}; record the {what}, or pass the "
            "right topic.",
            True,
            TopicError,
        )
    if other is None or other not in spans:
        return default
    t0 = bag.start_ns
    a0, a1, _ = spans[topic]
    b0, b1, _ = spans[other]
    if a1 < b0 or b1 < a0:
        mine, theirs = (what, a0, a1), ("LiDAR" if what == "IMU" else "IMU", b0, b1)
        return _different_times(t0, *((mine, theirs) if what == "IMU" else (theirs, mine)))
    o0, o1 = max(a0, b0), min(a1, b1)
    w1 = bag.end_ns if window.stop_ns is None else window.stop_ns
    inside = min(o1, w1) - max(o0, window.start_ns)
    if inside >= MIN_SEGMENT_S * _NS:
        return default
    return Finding(
        f"{default.message.split(';')[0]}: both sensors were recorded together only from "
        f"{(o0 - t0) / _NS:.1f} s to {(o1 - t0) / _NS:.1f} s after the bag start; choose a "
        "segment there with --start/--duration.",
        True,
        DataError,
    )


# --------------------------------------------------------------------------------------------
# IMU


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
    if isolated and n - n_bad >= _MIN_IMU_SAMPLES:
        msg = (
            f"{_count(n_bad, 'IMU sample')} of {n} on {topic} "
            f"{_verb(n_bad, 'holds', 'hold')} NaN or infinite values ({span}) and "
            f"{_verb(n_bad, 'is', 'are')} dropped."
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
    knot = cfg.spline.knot_spacing_s
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
) -> ImuRead:
    """Validate and convert raw IMU samples (the checks of the module table, in its order).

    Args:
        raw: the samples as read, in arrival order.
        topic: their topic (for messages).
        cfg: configuration (``imu`` units, ``spline.knot_spacing_s``).
        lost: the topic's unreadable messages, to explain gaps.
        offset_ns: the topic's ``stamp - record`` offset, kept in the result.
        absence: replaces the finding of too few samples with a better diagnosis.

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
    if stats.count < _MIN_IMU_SAMPLES and absence is not None:
        stamp_findings = [absence(stamp_findings[0])]
    findings += stamp_findings
    raw = raw.take(~dup)
    units = detect_imu_units(raw.gyro, raw.accel, cfg.imu.gyro_unit, cfg.imu.accel_unit, raw.t_ns)
    gyro, accel = convert_imu(raw.gyro, raw.accel, units)
    findings += [Finding(w, False, DataError) for w in units.warnings()]
    if stats.count >= _MIN_IMU_SAMPLES:
        findings += _gravity_and_rate(accel, stats, topic, cfg)
    if lost is not None:
        findings += _loss_findings(topic, "IMU", lost)
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
        lidar_topic: the LiDAR topic, to tell why the segment holds no IMU samples.

    Returns:
        The stream; its findings say whether it is usable.
    """
    offset, findings = topic_clock(bag, topic, window, "IMU")
    if findings:
        return _empty_imu(topic, offset, findings)
    raw = read_raw_imu(bag, topic, window, offset)

    def absence(default: Finding) -> Finding:
        return _absence_finding(bag, window, topic, lidar_topic, "IMU", default)

    return validate_imu(raw, topic, cfg, bag.loss(topic), offset, absence)


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
        imu = read_imu_stream(bag, topic.name, window, cfg)
    findings = list(imu.findings)
    _raise_fatal(findings)
    assert imu.units is not None
    return imu.samples, imu.units, tuple(f.message for f in findings) + tuple(imu.units.messages())


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
        sweep_start_offset_ns: median ``min(point time) - header stamp`` of the checked
            clouds, ns (0 when the stamp marks the sweep start, about minus one period when it
            marks the end). With ``sweep_end_offset_ns`` it gives the time a cloud covers,
            which is what the sensors' overlap is measured with (one cloud covers a sweep).
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
    sweep_start_offset_ns: int = 0

    def sweep_span_ns(self, stamp_ns: int) -> tuple[int, int]:
        """The time a cloud stamped ``stamp_ns`` stands for, ns: its sweep, at least one scan
        period long (consecutive clouds then tile the time, so 20 clouds at 10 Hz cover 2 s)."""
        start = stamp_ns + self.sweep_start_offset_ns
        sweep = self.sweep_end_offset_ns - self.sweep_start_offset_ns
        length = max(sweep, self.time.scan_period_ns)
        return start, start + length


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


SKIP_REASONS = (
    "empty",
    "invalid",
    "out of range",
    "too few points",
    "one beam",
    "corrupt",
    "zero span",
    "no time field",
)
"""Why a cloud is skipped, in the order the checks run."""


@dataclass(frozen=True)
class Skip:
    """Why one cloud is skipped: a reason of :data:`SKIP_REASONS` and what exactly is wrong."""

    reason: str
    detail: str = ""


def _elevation(xyz: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    return np.arctan2(xyz[:, 2], np.hypot(xyz[:, 0], xyz[:, 1]))


def _content_skip(
    dec: DecodedCloud, mask: npt.NDArray[np.bool_], ring: npt.NDArray[np.int32] | None
) -> Skip | None:
    """Whether the points of a cloud are usable: some, valid, enough, on several beams."""
    if len(dec) == 0:
        return Skip("empty")
    if not mask.any():
        finite = np.isfinite(dec.xyz).all(axis=1) & np.any(dec.xyz != 0, axis=1)
        return Skip("invalid" if not finite.any() else "out of range")
    valid = int(mask.sum())
    if valid < MIN_CLOUD_POINTS:
        return Skip("too few points", f"{valid} valid")
    if ring is not None:
        kept = ring[mask]
        one = int(kept.min()) == int(kept.max())  # fewer than two distinct beams
    elif dec.height > 1 and dec.height * dec.width == len(dec):
        one = int(np.count_nonzero(mask.reshape(dec.height, dec.width).any(axis=1))) < 2
    else:
        one = float(np.ptp(_elevation(dec.xyz[mask]))) < _ONE_BEAM_RAD
    return Skip("one beam") if one else None


def _bad_ring(ring: npt.NDArray[np.int32], name: str | None) -> Skip | None:
    if ring.size and (int(ring.min()) < 0 or int(ring.max()) >= _MAX_RING):
        return Skip("corrupt", f"field '{name}' holds beam numbers outside 0-{_MAX_RING - 1}")
    return None


def _finite_times(values: np.ndarray) -> np.ndarray:
    """The finite values of a per-point time array (all of them for an integer field)."""
    return values[np.isfinite(values)] if values.dtype.kind == "f" else values


def _cloud_label(index: int, stamp_ns: int, topic: str) -> str:
    """``cloud 18 of /points in the segment, stamp 1700000001.700000000``."""
    where = f" of {topic}" if topic else ""
    return f"cloud {index}{where} in the segment, stamp {_stamp_text(stamp_ns)}"


def detect_layout(
    bag: BagHandle, topic: str, window: SegmentWindow, off: int, cfg: CalibConfig
) -> CloudLayout:
    """Detect fields, time field (unit, reference, stamp position) and beams of a topic.

    Uses the first :data:`_LAYOUT_CLOUDS` clouds of the segment that have valid points (clouds
    that are corrupt or unusable are passed over, as :func:`make_scan` would skip them).

    Raises:
        DataError: no cloud of the segment is usable (the message says why).
        TimestampError: the time field has zero span in the clouds checked.
        ConfigError: the configured time or ring field is not in the clouds, or the
            configured beam table lists fewer beams than the clouds have.
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
    tally = ScanTally(topic=topic)
    for m in window_messages(bag, topic, window, off):
        stamp = m.stamp_ns if m.stamp_ns is not None else m.record_ns
        tally.total += 1
        tally.stamps.append(stamp)
        msg = bag.decode(m)
        if msg is None:
            tally.skip(Skip("corrupt", "the message does not decode"), stamp)
            continue
        names = field_names(msg)
        if first is None:
            tf = find_time_field(names, lo.time_field)
            rf = find_ring_field(names, lo.ring_field)
        else:
            tf = time_field if time_field in names else None
            rf = ring_field if ring_field in names else None
        try:
            dec = decode_cloud(msg, stamp, tf, rf)
        except CloudError as err:
            tally.skip(Skip("corrupt", err.reason), stamp)
            continue
        if first is None:
            first, time_field, ring_field = msg, tf, rf
        counts.append(len(dec))
        mask = valid_mask(dec.xyz, lo.min_range_m, lo.max_range_m)
        skip = _content_skip(dec, mask, dec.ring)
        if skip is None and dec.ring is not None:
            skip = _bad_ring(dec.ring[mask], ring_field)
        if skip is not None:
            tally.skip(skip, stamp)
            continue
        valid_counts.append(int(mask.sum()))
        xyzs.append(dec.xyz[mask])
        if dec.time_raw is not None:
            samples.append((stamp, _finite_times(dec.time_raw[mask])))
        if dec.ring is not None:
            rings.append(dec.ring[mask])
        if len(xyzs) >= _LAYOUT_CLOUDS:
            break
    if tally.total == 0:
        msg_ = "No LiDAR clouds in the segment; choose another segment with --start/--duration."
        raise DataError(msg_)
    if not xyzs:
        raise DataError(tally.all_skipped_message())
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
        all_rings = np.concatenate(rings)
        beams = int(np.unique(all_rings).size)
        top = int(all_rings.max()) + 1
    else:
        table = detect_beams(xyzs, lo.num_beams)
        beams = top = table.num_beams
    if lo.nominal_elevation_deg is not None and len(lo.nominal_elevation_deg) < top:
        msg_ = (
            f"lidar.nominal_elevation_deg lists {len(lo.nominal_elevation_deg)} beams but the "
            f"clouds on {topic} have {top}; list one elevation per beam (ring 0 first)."
        )
        raise ConfigError(msg_)
    if tl.field is not None:
        converted = [time_values_to_ns(v, st, tl) - st for st, v in samples if v.size]
        end_offset = int(np.median([int(c.max()) for c in converted])) if converted else 0
        start_offset = int(np.median([int(c.min()) for c in converted])) if converted else 0
        if max(abs(end_offset), abs(start_offset)) > 2 * tl.scan_period_ns:  # implausible
            end_offset = start_offset = 0  # layout: do not trust it
    else:
        end_offset = tl.scan_period_ns if tl.stamp_position != "end" else 0
        start_offset = end_offset - tl.scan_period_ns
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
        sweep_start_offset_ns=start_offset,
    )


# --------------------------------------------------------------------------------------------
# Scans


def make_scan(
    dec: DecodedCloud, layout: CloudLayout, cfg: CalibConfig, shift_ns: int
) -> LidarScan | Skip:
    """A LidarScan from a decoded cloud, or why it is skipped."""
    mask = valid_mask(dec.xyz, cfg.lidar.min_range_m, cfg.lidar.max_range_m)
    skip = _content_skip(dec, mask, dec.ring)
    if skip is not None:
        return skip
    xyz = dec.xyz[mask]
    ring = None
    if dec.ring is not None:
        ring32 = dec.ring[mask]
        bad = _bad_ring(ring32, layout.ring_field)
        if bad is not None:
            return bad
        ring = ring32.astype(np.int16)
    tl = layout.time
    if tl.field is not None:
        if dec.time_raw is None:
            return Skip("no time field")
        v = dec.time_raw[mask]
        assert tl.unit is not None
        with np.errstate(over="ignore", invalid="ignore"):
            scaled = np.abs(v.astype(np.float64) * UNIT_TO_NS[tl.unit])
        if not np.all(scaled < _MAX_TIME_NS):  # also catches NaN
            return Skip("corrupt", f"per-point times ('{tl.field}') hold NaN or absurd values")
        if v.size > 1 and np.ptp(v) == 0:
            return Skip("zero span")
        t_ns = time_values_to_ns(v, dec.stamp_ns, tl)
    else:
        position: Literal["start", "end"] = "end" if tl.stamp_position == "end" else "start"
        cw = tl.clockwise if tl.clockwise is not None else cfg.lidar.clockwise
        t_ns, _, _ = estimate_times(xyz, dec.stamp_ns, tl.scan_period_ns, position, cw)
    if ring is None and layout.beam_table is not None:
        ring = assign_beams(xyz, layout.beam_table)
    inten = dec.intensity[mask] if dec.intensity is not None else None
    return LidarScan(
        stamp_ns=dec.stamp_ns + shift_ns,
        xyz=xyz,
        t_ns=t_ns + shift_ns,
        ring=ring,
        intensity=inten,
    )


_SKIP_WHAT = {
    "empty": ("is", "are", "empty"),
    "invalid": ("has", "have", "only NaN or zero points"),
    "out of range": ("has", "have", "no point within the range limits"),
    "too few points": ("has", "have", f"fewer than {MIN_CLOUD_POINTS} valid points"),
    "one beam": ("has", "have", "valid points on one beam or row only"),
    "corrupt": ("is", "are", "corrupt"),
    "zero span": ("has", "have", "a time field with zero span"),
    "no time field": ("lacks", "lack", "the time field"),
}

_SKIP_FIX = {
    "empty": "check the LiDAR driver and topic",
    "invalid": "check the LiDAR driver (or its return mode) and re-record",
    "out of range": "widen `lidar.min_range_m`/`lidar.max_range_m` in the config",
    "too few points": (
        "licalib needs 3D scans of thousands of points, check the driver's filters and "
        "downsampling (or the topic) and re-record"
    ),
    "one beam": (
        "licalib needs a multi-beam 3D LiDAR, check the driver's row or beam filters and re-record"
    ),
    "corrupt": "the bag is damaged, repair or re-record it",
    "no time field": "check the LiDAR driver and re-record",
}


@dataclass
class ScanTally:
    """Counts of clouds checked and skipped (by reason) while streaming, and their stamps.

    Attributes:
        total: clouds checked (decoded or attempted).
        skipped: skipped clouds per reason (:data:`SKIP_REASONS`).
        stamps: header stamps of every cloud of the segment, checked or not.
        records: their record times, ns.
        examples: for each reason, the first skipped cloud: ``(index in the segment, stamp,
            detail)``.
        topic: the LiDAR topic (for messages).
    """

    total: int = 0
    skipped: dict[str, int] = field(default_factory=lambda: dict.fromkeys(SKIP_REASONS, 0))
    stamps: list[int] = field(default_factory=list)
    records: list[int] = field(default_factory=list)
    examples: dict[str, tuple[int, int, str]] = field(default_factory=dict)
    topic: str = ""

    def skip(self, why: Skip, stamp_ns: int) -> None:
        """Count a skipped cloud (the last one of :attr:`stamps`)."""
        self.skipped[why.reason] += 1
        self.examples.setdefault(why.reason, (len(self.stamps), stamp_ns, why.detail))
        logger.debug("cloud at %d skipped: %s %s", stamp_ns, why.reason, why.detail)

    def _example(self, reason: str, n: int) -> str:
        """Which cloud was corrupt and how (the other reasons need no example)."""
        if reason != "corrupt" or reason not in self.examples:
            return ""
        index, stamp, detail = self.examples[reason]
        first = "the first: " if n > 1 else ""
        return (
            f" ({first}{_cloud_label(index, stamp, self.topic)}{': ' + detail if detail else ''})"
        )

    def all_skipped_message(self) -> str:
        """The sentence for a segment whose every checked cloud was skipped."""
        total = self.total
        every = "The only LiDAR cloud" if total == 1 else f"All {total} LiDAR clouds"
        reason = max(self.skipped, key=lambda r: self.skipped[r])
        if self.skipped["invalid"] + self.skipped["empty"] == total and reason == "empty":
            reason = "empty" if self.skipped["empty"] == total else "invalid"
        singular, plural, what = _SKIP_WHAT[reason]
        verb = singular if total == 1 else plural
        fix = _SKIP_FIX.get(reason, "check the LiDAR driver and re-record")
        if reason == "empty":
            fix = (
                "check the LiDAR driver and topic, or choose another segment with "
                "--start/--duration"
            )
        if reason == "out of range":
            return (
                f"No point of the {_count(total, 'LiDAR cloud')} of the segment lies "
                "between `lidar.min_range_m` and `lidar.max_range_m`; widen that range in the "
                "config."
            )
        mixed = "" if self.skipped[reason] == total else " or otherwise unusable"
        return (
            f"{every} of the segment {verb} {what}{mixed}"
            f"{self._example(reason, self.skipped[reason])}; {fix}."
        )

    def problems(self, max_fraction: float = 0.5) -> list[Finding]:
        """Findings on the skipped clouds: warnings, or fatal past ``max_fraction``."""
        out: list[Finding] = []
        n_skip = sum(self.skipped.values())
        if self.total == 0 or n_skip == 0:
            return out
        fatal = n_skip > max_fraction * self.total
        if n_skip == self.total and self.skipped["zero span"] == 0:
            return [Finding(self.all_skipped_message(), True, DataError)]
        zero = self.skipped["zero span"]
        if zero and (fatal or zero == self.total):
            out.append(
                Finding(
                    f"{zero} of {_count(self.total, 'LiDAR cloud')} "
                    f"{_verb(zero, 'has', 'have')} a per-point "
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
            singular, plural, what = _SKIP_WHAT[reason]
            text = (
                f"{n} of {_count(self.total, 'LiDAR cloud')} {_verb(n, singular, plural)} "
                f"{what} and {_verb(n, 'was', 'were')} skipped{self._example(reason, n)}"
            )
            if fatal:
                fix = _SKIP_FIX.get(reason, "check the LiDAR driver and re-record")
                text += (
                    f"; that is more than `lidar.max_skipped_fraction` ({max_fraction:g}) of "
                    f"the clouds, {fix}."
                )
            else:
                text += "."
            out.append(Finding(text, fatal, DataError))
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
    every: int = 1,
) -> Iterator[LidarScan]:
    """The usable scans of the window; every cloud's stamp goes to ``tally``, and every
    ``every``-th cloud is decoded and checked (the others are only counted)."""
    for m in window_messages(bag, topic, window, off):
        stamp = m.stamp_ns if m.stamp_ns is not None else m.record_ns
        tally.stamps.append(stamp)
        tally.records.append(m.record_ns)
        if (len(tally.stamps) - 1) % every:
            continue
        tally.total += 1
        msg = bag.decode(m)
        if msg is None:
            tally.skip(Skip("corrupt", "the message does not decode"), stamp)
            continue
        names = field_names(msg)
        tf = layout.time.field if layout.time.field in names else None
        rf = layout.ring_field if layout.ring_field in names else None
        if layout.time.field is not None and tf is None:
            tally.skip(Skip("no time field"), stamp)
            continue
        try:
            dec = decode_cloud(msg, stamp, tf, rf)
        except CloudError as err:
            tally.skip(Skip("corrupt", err.reason), stamp)
            continue
        scan = make_scan(dec, layout, cfg, shift_ns)
        if isinstance(scan, Skip):
            tally.skip(scan, stamp)
            continue
        yield scan


@dataclass(frozen=True)
class LidarRead:
    """The LiDAR stream of a segment, validated (what both ``info`` and the reader use).

    Attributes:
        topic: the topic.
        offset_ns: its ``stamp - record`` offset, ns.
        layout: the detected point layout (None when it could not be detected).
        stats: statistics of the header stamps of every cloud of the segment.
        tally: the clouds checked and skipped.
        scans: the usable scans (empty unless kept), LiDAR times shifted by ``shift_ns``.
        clock_offset_ns: coarse ``t_imu - t_lidar``, ns (None: unknown).
        shift_ns: shift applied to the LiDAR times (the clock offset when 1 s or more).
        findings: in the order of the module table.
    """

    topic: str
    offset_ns: int
    layout: CloudLayout | None
    stats: StampStats
    tally: ScanTally
    scans: tuple[LidarScan, ...]
    clock_offset_ns: int | None
    shift_ns: int
    findings: tuple[Finding, ...]

    @property
    def record_span_ns(self) -> tuple[int, int] | None:
        """First and last record time of the clouds, ns (None: none)."""
        rec = self.tally.records
        return (min(rec), max(rec)) if rec else None


def read_lidar_stream(
    bag: BagHandle,
    topic: str,
    window: SegmentWindow,
    cfg: CalibConfig,
    imu_offset_ns: int | None,
    *,
    keep: bool = True,
    every: int = 1,
    imu_topic: str | None = None,
) -> LidarRead:
    """Read and validate the LiDAR clouds of the window (see the module table).

    Args:
        bag: the open bag.
        topic: the LiDAR topic.
        window: the segment.
        cfg: configuration (``lidar`` section).
        imu_offset_ns: the IMU topic's ``stamp - record`` offset, for the clock difference
            (None: unknown, no shift).
        keep: keep the scans (False: only check them).
        every: decode and check every ``every``-th cloud only (all stamps are checked).
        imu_topic: the IMU topic, to tell why the segment holds no clouds.

    Returns:
        The stream; its findings say whether it is usable.
    """
    offset, findings = topic_clock(bag, topic, window, "LiDAR")
    tally = ScanTally(topic=topic)
    empty = stamp_stats(np.zeros(0, np.int64), LIDAR_GAP_FACTOR)
    if findings:
        return LidarRead(topic, offset, None, empty, tally, (), None, 0, tuple(findings))
    lost = bag.loss(topic)
    try:
        layout = detect_layout(bag, topic, window, offset, cfg)
    except (DataError, ConfigError) as err:
        for m in window_messages(bag, topic, window, offset):
            tally.stamps.append(m.stamp_ns if m.stamp_ns is not None else m.record_ns)
            tally.records.append(m.record_ns)
        stats = stamp_stats(np.asarray(tally.stamps, np.int64), LIDAR_GAP_FACTOR)
        findings = lidar_stamp_problems(stats, lost)
        if stats.count == 0:
            findings = [_absence_finding(bag, window, topic, imu_topic, "LiDAR", findings[0])]
        else:
            findings.append(Finding(str(err), True, type(err)))
        findings += _loss_findings(topic, "LiDAR", lost)
        return LidarRead(topic, offset, None, stats, tally, (), None, 0, tuple(findings))
    clock = None if imu_offset_ns is None else clock_offset(imu_offset_ns, offset, layout)
    shift = 0 if clock is None else clock_shift(clock)
    stream = _scan_stream(bag, topic, window, offset, layout, cfg, shift, tally, every)
    if keep:
        scans = tuple(stream)
    else:
        scans = ()
        for _ in stream:
            pass
    stats = stamp_stats(np.asarray(tally.stamps, np.int64), LIDAR_GAP_FACTOR)
    findings = lidar_stamp_problems(stats, lost)
    findings += tally.problems(cfg.lidar.max_skipped_fraction)
    findings += [Finding(w, False, ConfigError) for w in layout.time.warnings]
    findings += _loss_findings(topic, "LiDAR", lost)
    if shift and clock is not None:
        findings.append(
            Finding(
                f"The IMU and LiDAR stamps use different clocks ({clock / _NS:+.3f} s apart); "
                "licalib shifts the LiDAR times into the IMU clock, check the drivers' time "
                "synchronisation.",
                False,
                TimestampError,
            )
        )
    return LidarRead(topic, offset, layout, stats, tally, scans, clock, shift, tuple(findings))


# --------------------------------------------------------------------------------------------
# The segment as a whole


def segment_findings(
    imu: ImuRead, lidar: LidarRead, bag_start_ns: int, min_span_s: float = MIN_SEGMENT_S
) -> list[Finding]:
    """Whether the IMU and LiDAR data of the segment cover the same time, at least
    ``min_span_s`` (``bag_start_ns``: the bag's first record time, for the message).

    Stamps that do not overlap come from sensors recorded at different times (their record
    times do not overlap either) or from clocks that are not synchronised.
    """
    if imu.samples.t_ns.size == 0 or not lidar.tally.stamps or lidar.layout is None:
        return []
    # each sample or sweep stands for its period: a 2 s window holds 2 s of data; the LiDAR
    # covers its sweeps (from the per-point times), not last minus first stamp (0 for one cloud)
    i0, i1 = int(imu.samples.t_ns.min()), int(imu.samples.t_ns.max()) + imu.stats.period_ns
    l0 = lidar.layout.sweep_span_ns(min(lidar.tally.stamps) + lidar.shift_ns)[0]
    l1 = lidar.layout.sweep_span_ns(max(lidar.tally.stamps) + lidar.shift_ns)[1]
    overlap = min(i1, l1) - max(i0, l0)
    if overlap <= 0:
        ri, rl = imu.record_span_ns, lidar.record_span_ns
        if ri is not None and rl is not None and (ri[1] < rl[0] or rl[1] < ri[0]):
            return [_different_times(bag_start_ns, ("IMU", *ri), ("LiDAR", *rl))]
        msg = (
            "The IMU and LiDAR stamps do not overlap in time; the sensors' clocks are not "
            "synchronised, fix the drivers' time stamping and re-record."
        )
        return [Finding(msg, True, TimestampError)]
    # a record-time window selects clouds by when they were recorded (after their sweep), so
    # its edge can cut up to one sweep off the LiDAR's share: that much is not held against it
    if overlap + lidar.layout.time.scan_period_ns + _MS < min_span_s * _NS:
        return [
            Finding(
                f"The IMU and LiDAR data of the segment overlap for only {overlap / _NS:.2f} s, "
                "too little to calibrate; choose a segment where both sensors record 10-60 s "
                "with --start/--duration.",
                True,
                ExcitationError,
            )
        ]
    return []


# --------------------------------------------------------------------------------------------
# Public readers


def read_segment(path: Path, cfg: CalibConfig, *, min_span_s: float = MIN_SEGMENT_S) -> Recording:
    """Read, convert and validate the IMU samples and LiDAR scans of one segment.

    Args:
        path: a ROS1 ``.bag`` (or folder of split ``.bag`` files), a ROS2 bag folder, or a bare
            ``.db3``/``.mcap`` file.
        cfg: configuration (``bag``, ``imu``, ``lidar`` and ``spline`` sections).
        min_span_s: the least time both sensors must cover (a calibration needs
            :data:`MIN_SEGMENT_S`; 0 reads any segment, e.g. to check a short bag's decoding).

    Returns:
        The recording. All scans of the segment are held in memory; use :func:`iter_scans`
        to stream them instead.

    Raises:
        BagError: missing, unreadable, corrupt or truncated bag.
        TopicError: missing, ambiguous or wrongly typed topics.
        DataError: unusable IMU data or clouds, or too little data.
        TimestampError: unset, unsorted or duplicated stamps, IMU gaps, zero-span time
            fields, sensors recorded at different times or on unsynchronised clocks.
        ExcitationError: the segment (or the time both sensors cover) is under
            ``min_span_s``.
        ConfigError: the segment starts after the end of the bag, or a configured time or
            ring field or beam table does not match the clouds.
    """
    with open_bag(path) as bag:
        imu_t = select_topic(bag, IMU_TYPE, cfg.imu.topic, "--imu-topic", "imu.topic")
        lid_t = select_topic(bag, CLOUD_TYPE, cfg.lidar.topic, "--lidar-topic", "lidar.topic")
        window = segment_window(bag, cfg, cap=True)
        findings = window_findings(bag, window, cfg, min_span_s)
        _raise_fatal(findings)
        imu = read_imu_stream(bag, imu_t.name, window, cfg, lid_t.name)
        findings += imu.findings
        _raise_fatal(findings)
        lidar = read_lidar_stream(bag, lid_t.name, window, cfg, imu.offset_ns, imu_topic=imu_t.name)
        findings += lidar.findings
        _raise_fatal(findings)
        findings += segment_findings(imu, lidar, bag.start_ns, min_span_s)
        _raise_fatal(findings)
        factory = read_factory_extrinsic(bag, cloud_frame(bag, lid_t.name))
        bag_start, bag_end = bag.start_ns, bag.end_ns
        imu_lost, lidar_lost = bag.loss(imu_t.name).total, bag.loss(lid_t.name).total
    layout, units = lidar.layout, imu.units
    assert layout is not None and units is not None and lidar.clock_offset_ns is not None
    warnings = [f.message for f in findings] + units.messages() + list(layout.time.notes)
    if cfg.bag.duration_s is None and window.stop_ns is not None:
        warnings.append(
            f"The bag lasts {(bag_end - bag_start) / _NS:.0f} s; only {cfg.bag.max_duration_s:g} "
            f"s from {cfg.bag.start_s:g} s are used. Let --segments auto calibrate on its most "
            "informative windows together (licalib select-segments ranks them), or choose a "
            "part with --start/--duration (or raise bag.max_duration_s)."
        )
    for w in warnings:
        logger.warning(w)
    if window.stop_ns is not None:
        end_ns = window.stop_ns + imu.offset_ns
    else:
        end_ns = int(imu.samples.t_ns[-1]) + 1
    return Recording(
        imu=imu.samples,
        scans=lidar.scans,
        imu_topic=imu_t.name,
        lidar_topic=lid_t.name,
        layout=layout,
        imu_units=units,
        clock_offset_ns=lidar.clock_offset_ns,
        lidar_shift_ns=lidar.shift_ns,
        start_ns=min(window.start_ns + imu.offset_ns, int(imu.samples.t_ns[0]))
        if window.from_bag_start
        else window.start_ns + imu.offset_ns,
        end_ns=end_ns,
        warnings=tuple(warnings),
        imu_unreadable=imu_lost,
        lidar_unreadable=lidar_lost,
        imu_samples_dropped=imu.dropped,
        scans_skipped=sum(lidar.tally.skipped.values()),
        factory_extrinsic=factory,
    )


def iter_scans(
    path: Path,
    cfg: CalibConfig,
    shift_ns: int = 0,
    warnings: list[str] | None = None,
    every: int = 1,
) -> Iterator[LidarScan]:
    """Stream the LiDAR scans of the segment one at a time (constant memory).

    Skipped clouds and stamp problems are checked as they come: a stamp going backwards or
    repeating raises at once; skip counts are appended to ``warnings`` at the end and raise
    when more than ``lidar.max_skipped_fraction`` of the clouds were skipped.

    Args:
        path: the bag.
        cfg: configuration (``bag`` and ``lidar`` sections).
        shift_ns: added to every LiDAR time (e.g. ``Recording.lidar_shift_ns``).
        warnings: list that receives non-fatal findings, or None.
        every: decode only every ``every``-th cloud (the others are only counted).

    Yields:
        :class:`LidarScan` in stamp order.

    Raises:
        BagError, TopicError, DataError, TimestampError, ConfigError: as :func:`read_segment`.
    """
    with open_bag(path) as bag:
        lid_t = select_topic(bag, CLOUD_TYPE, cfg.lidar.topic, "--lidar-topic", "lidar.topic")
        window = segment_window(bag, cfg)
        off, findings = topic_clock(bag, lid_t.name, window, "LiDAR")
        _raise_fatal(findings)
        layout = detect_layout(bag, lid_t.name, window, off, cfg)
        tally = ScanTally(topic=lid_t.name)
        last: int | None = None
        stream = _scan_stream(bag, lid_t.name, window, off, layout, cfg, shift_ns, tally, every)
        for scan in stream:
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
    problems = tally.problems(cfg.lidar.max_skipped_fraction)
    _raise_fatal(problems)
    if warnings is not None:
        warnings.extend(p.message for p in problems)
