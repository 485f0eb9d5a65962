"""The point layout of a LiDAR topic (time field, unit, beams, sweep period) detected from
its first clouds, and why a cloud is skipped."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from licalib_cli.config import CalibConfig
from licalib_cli.errors import ConfigError, DataError, TimestampError
from licalib_cli.geometry.vectors import elevations
from licalib_cli.io.bag import BagHandle
from licalib_cli.io.beam_spread import elevation_spread_deg
from licalib_cli.io.findings import Finding, count_noun, stamp_text, verb_for
from licalib_cli.io.pointcloud2 import (
    POINTFIELD_DTYPES,
    CloudError,
    DecodedCloud,
    decode_cloud,
    field_names,
    valid_mask,
)
from licalib_cli.io.timestamps import (
    BeamTable,
    TimeLayout,
    classify_time_field,
    detect_beams,
    estimate_times,
    find_ring_field,
    find_time_field,
    time_values_to_ns,
)
from licalib_cli.io.window import SegmentWindow, window_messages

__all__ = [
    "MIN_CLOUD_POINTS",
    "SKIP_REASONS",
    "CloudLayout",
    "ScanTally",
    "Skip",
    "bad_ring",
    "content_skip",
    "detect_layout",
]

logger = logging.getLogger(__name__)

_NS = 1_000_000_000
MIN_CLOUD_POINTS = 100
"""Clouds with fewer valid points are skipped: no LiDAR odometry works on them."""
_MAX_RING = 512
_LAYOUT_CLOUDS = 5
_DEFAULT_PERIOD_NS = 100_000_000
_ONE_BEAM_RAD = np.deg2rad(0.5)  # elevation spread of a single beam's points


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
        elevation_spread_deg: how far a beam's points spread in elevation (median over the
            beams, :func:`~licalib_cli.io.beam_spread.elevation_spread_deg`): hundredths of a
            degree for rings, tens for a non-repetitive scanner's lines; NaN without a ring
            field.
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
    elevation_spread_deg: float = float("nan")

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


def content_skip(
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
        one = float(np.ptp(elevations(dec.xyz[mask]))) < _ONE_BEAM_RAD
    return Skip("one beam") if one else None


def bad_ring(ring: npt.NDArray[np.int32], name: str | None) -> Skip | None:
    if ring.size and (int(ring.min()) < 0 or int(ring.max()) >= _MAX_RING):
        return Skip("corrupt", f"field '{name}' holds beam numbers outside 0-{_MAX_RING - 1}")
    return None


def _finite_times(values: np.ndarray) -> np.ndarray:
    """The finite values of a per-point time array (all of them for an integer field)."""
    return values[np.isfinite(values)] if values.dtype.kind == "f" else values


def _cloud_label(index: int, stamp_ns: int, topic: str) -> str:
    """``cloud 18 of /points in the segment, stamp 1700000001.700000000``."""
    where = f" of {topic}" if topic else ""
    return f"cloud {index}{where} in the segment, stamp {stamp_text(stamp_ns)}"


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
        skip = content_skip(dec, mask, dec.ring)
        if skip is None and dec.ring is not None:
            skip = bad_ring(dec.ring[mask], ring_field)
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
    spread = float("nan")
    if ring_field is not None:
        all_rings = np.concatenate(rings)
        beams = int(np.unique(all_rings).size)
        top = int(all_rings.max()) + 1
        spread = elevation_spread_deg(xyzs, rings)
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
        elevation_spread_deg=spread,
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
                f"No point of the {count_noun(total, 'LiDAR cloud')} of the segment lies "
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
                    f"{zero} of {count_noun(self.total, 'LiDAR cloud')} "
                    f"{verb_for(zero, 'has', 'have')} a per-point "
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
                f"{n} of {count_noun(self.total, 'LiDAR cloud')} {verb_for(n, singular, plural)} "
                f"{what} and {verb_for(n, 'was', 'were')} skipped{self._example(reason, n)}"
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
