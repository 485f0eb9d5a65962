"""LiDAR clouds of a segment as scans: decoded, validated, per-point times in the IMU's clock
(``clock_offset``, ``clock_shift``), skipped clouds tallied."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import Literal

import numpy as np

from licalib_cli.config import CalibConfig
from licalib_cli.errors import ConfigError, DataError, TimestampError
from licalib_cli.io.bag import BagHandle
from licalib_cli.io.cloud_layout import (
    CloudLayout,
    ScanTally,
    Skip,
    bad_ring,
    content_skip,
    detect_layout,
)
from licalib_cli.io.findings import (
    LIDAR_GAP_FACTOR,
    Finding,
    StampStats,
    lidar_stamp_problems,
    loss_findings,
    stamp_stats,
)
from licalib_cli.io.pointcloud2 import (
    CloudError,
    DecodedCloud,
    decode_cloud,
    field_names,
    valid_mask,
)
from licalib_cli.io.timestamps import UNIT_TO_NS, assign_beams, estimate_times, time_values_to_ns
from licalib_cli.io.window import SegmentWindow, absence_finding, topic_clock, window_messages
from licalib_cli.measurements import LidarScan

__all__ = [
    "LidarRead",
    "clock_offset",
    "clock_shift",
    "make_scan",
    "read_lidar_stream",
    "stream_scans",
]

_NS = 1_000_000_000
_MAX_TIME_NS = 4e18  # per-point times must fit int64 ns (NaN and beyond are corrupt)


def clock_offset(imu_offset_ns: int, lidar_offset_ns: int, layout: CloudLayout) -> int:
    """Coarse ``t_imu - t_lidar`` of the two clocks, ns, with the LiDAR taken at the last
    point of each sweep (a cloud is recorded after its sweep ends)."""
    return imu_offset_ns - (lidar_offset_ns + layout.sweep_end_offset_ns)


def clock_shift(clock_offset_ns: int) -> int:
    """The shift applied to LiDAR times: the clock offset when it is 1 s or more, else 0."""
    return clock_offset_ns if abs(clock_offset_ns) >= _NS else 0


def make_scan(
    dec: DecodedCloud, layout: CloudLayout, cfg: CalibConfig, shift_ns: int
) -> LidarScan | Skip:
    """A LidarScan from a decoded cloud, or why it is skipped."""
    mask = valid_mask(dec.xyz, cfg.lidar.min_range_m, cfg.lidar.max_range_m)
    skip = content_skip(dec, mask, dec.ring)
    if skip is not None:
        return skip
    xyz = dec.xyz[mask]
    ring = None
    if dec.ring is not None:
        ring32 = dec.ring[mask]
        bad = bad_ring(ring32, layout.ring_field)
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


def stream_scans(
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
            findings = [absence_finding(bag, window, topic, imu_topic, "LiDAR", findings[0])]
        else:
            findings.append(Finding(str(err), True, type(err)))
        findings += loss_findings(topic, "LiDAR", lost)
        return LidarRead(topic, offset, None, stats, tally, (), None, 0, tuple(findings))
    clock = None if imu_offset_ns is None else clock_offset(imu_offset_ns, offset, layout)
    shift = 0 if clock is None else clock_shift(clock)
    stream = stream_scans(bag, topic, window, offset, layout, cfg, shift, tally, every)
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
    findings += loss_findings(topic, "LiDAR", lost)
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
