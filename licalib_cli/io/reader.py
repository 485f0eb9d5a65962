"""Read a time segment of a bag into IMU samples and LiDAR scans, with validation.

Entry points:

* :func:`read_segment` -> :class:`~licalib_cli.measurements.Recording` (IMU samples + all scans
  of the segment);
* :func:`iter_scans` streams the scans one by one (constant memory on long bags);
* :func:`read_imu` reads only the IMU samples.

The stages behind them have a module each: :mod:`~licalib_cli.io.window` (the segment's
record-time window and each topic's clock), :mod:`~licalib_cli.io.imu_stream` (IMU messages
read and validated), :mod:`~licalib_cli.io.cloud_layout` (the point layout and why a cloud is
skipped), :mod:`~licalib_cli.io.scan_stream` (clouds as scans) and
:mod:`~licalib_cli.io.findings` (what the stamps say). ``licalib info``
(:mod:`licalib_cli.inspection`) reads through the same functions
(:func:`~licalib_cli.io.imu_stream.read_imu_stream`,
:func:`~licalib_cli.io.scan_stream.read_lidar_stream`, :func:`segment_findings`), so that it
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
from collections.abc import Iterator
from pathlib import Path

from licalib_cli.config import CalibConfig
from licalib_cli.errors import ExcitationError, TimestampError
from licalib_cli.io.bag import CLOUD_TYPE, IMU_TYPE, open_bag, select_topic
from licalib_cli.io.clock_rate import rate_warning, streams_clock_rate
from licalib_cli.io.cloud_layout import ScanTally, detect_layout
from licalib_cli.io.findings import Finding, raise_fatal
from licalib_cli.io.imu_stream import ImuRead, read_imu_stream
from licalib_cli.io.imu_units import ImuUnits
from licalib_cli.io.ouster import cloud_frame, read_factory_extrinsic
from licalib_cli.io.scan_stream import LidarRead, read_lidar_stream, stream_scans
from licalib_cli.io.window import (
    MIN_SEGMENT_S,
    different_times,
    segment_window,
    topic_clock,
    window_findings,
)
from licalib_cli.measurements import ImuSamples, LidarScan, Recording

__all__ = [
    "iter_scans",
    "read_imu",
    "read_segment",
    "segment_findings",
]

logger = logging.getLogger(__name__)

_NS = 1_000_000_000
_MS = 1_000_000  # slack of comparisons of durations built from rounded stamps


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
            return [different_times(bag_start_ns, ("IMU", *ri), ("LiDAR", *rl))]
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
        raise_fatal(findings)
        imu = read_imu_stream(bag, imu_t.name, window, cfg, lid_t.name)
        findings += imu.findings
        raise_fatal(findings)
        lidar = read_lidar_stream(bag, lid_t.name, window, cfg, imu.offset_ns, imu_topic=imu_t.name)
        findings += lidar.findings
        raise_fatal(findings)
        findings += segment_findings(imu, lidar, bag.start_ns, min_span_s)
        raise_fatal(findings)
        factory = read_factory_extrinsic(bag, cloud_frame(bag, lid_t.name))
        bag_start, bag_end = bag.start_ns, bag.end_ns
        imu_lost, lidar_lost = bag.loss(imu_t.name).total, bag.loss(lid_t.name).total
    layout, units = lidar.layout, imu.units
    assert layout is not None and units is not None and lidar.clock_offset_ns is not None
    warnings = [f.message for f in findings] + units.messages() + list(layout.time.notes)
    rate = streams_clock_rate(imu, lidar)
    told = rate_warning(rate, cfg)
    if told is not None:
        warnings.append(told)
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
        clock_rate=rate,
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
        raise_fatal(findings)
        layout = detect_layout(bag, lid_t.name, window, off, cfg)
        tally = ScanTally(topic=lid_t.name)
        last: int | None = None
        stream = stream_scans(bag, lid_t.name, window, off, layout, cfg, shift_ns, tally, every)
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
    raise_fatal(problems)
    if warnings is not None:
        warnings.extend(p.message for p in problems)


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
    raise_fatal(findings)
    assert imu.units is not None
    return imu.samples, imu.units, tuple(f.message for f in findings) + tuple(imu.units.messages())
