"""The segment window of a bag and the clocks of its topics: which messages a segment reads.

The segment ``[bag.start_s, bag.start_s + bag.duration_s)`` is measured from the bag's first
record time; each topic's median ``stamp - record`` offset maps it into that topic's clock
(see :mod:`licalib_cli.io.reader`)."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from licalib_cli.config import CalibConfig
from licalib_cli.errors import ConfigError, DataError, ExcitationError, TimestampError, TopicError
from licalib_cli.io.bag import BagHandle, RawMessage
from licalib_cli.io.findings import Finding

__all__ = [
    "MIN_SEGMENT_S",
    "SegmentWindow",
    "absence_finding",
    "different_times",
    "segment_window",
    "stamp_record_offset",
    "topic_clock",
    "window_findings",
    "window_messages",
]

_NS = 1_000_000_000
_MARGIN_NS = _NS
MIN_SEGMENT_S = 2.0
"""Shorter segments are refused: a few scans cannot determine the extrinsic."""
_MAX_SPAN_S = 1e9  # durations beyond 31 years are "to the end" (keeps the ns in int64)


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


def _record_spans(bag: BagHandle, topics: list[str]) -> dict[str, tuple[int, int, int]]:
    """``(first, last, count)`` record times of each topic over the whole bag (a full pass
    over their messages, without decoding them)."""
    spans: dict[str, tuple[int, int, int]] = {}
    for m in bag.messages(topics):
        first, _, n = spans.get(m.topic, (m.record_ns, m.record_ns, 0))
        spans[m.topic] = (first, m.record_ns, n + 1)
    return spans


def different_times(
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


def absence_finding(
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
        return different_times(t0, *((mine, theirs) if what == "IMU" else (theirs, mine)))
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
