"""How fast the IMU's clock runs against the LiDAR's, from the bag alone.

Every message carries two times: its header stamp, on the sensor's (or its driver's) clock, and
its record time, on the recorder's. Over a recording, ``stamp - record`` of one topic is a
constant (the clocks' difference) plus the message's transport delay, and grows by the clock's
rate against the recorder's: a clock that runs ``k`` fast adds ``k`` seconds per second. The
IMU's rate minus the LiDAR's is the rate of ``t_imu - t_lidar``, the clock drift the model's
``clock_drift`` estimates, measured before any fit and without the recorder's own rate (which
both share).

The delays vary from message to message (a burst queued behind a cloud, a busy disk): each
topic's ``stamp - record`` is reduced to its :data:`QUANTILE` quantile in :data:`BINS` equal
spans of record time (the messages that came through fastest: a delay's spread is one-sided;
with exponential delays this quantile's rate erred 8 ppm RMS where the median's erred 12, over
30 s with a 10 Hz LiDAR, and for symmetric jitter it is nearly as precise as the median), and
the rate is the slope of the line through those values, with the 1-sigma their scatter about
it gives.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

if TYPE_CHECKING:
    from licalib_cli.config import CalibConfig
    from licalib_cli.io.imu_stream import ImuRead
    from licalib_cli.io.scan_stream import LidarRead

__all__ = [
    "BINS",
    "MATERIAL_MOVE_S",
    "MIN_PER_BIN",
    "QUANTILE",
    "SIGNIFICANT_SIGMAS",
    "ClockRate",
    "clock_rate",
    "rate_warning",
    "stamp_rate",
    "streams_clock_rate",
]

BINS = 10
"""Spans of record time each topic's ``stamp - record`` is reduced to (one value in each)."""

QUANTILE = 0.75
"""The quantile of ``stamp - record`` taken in each span: the quarter of the messages with the
shortest delays lie above it."""

MIN_PER_BIN = 3
"""Messages a span needs for its value to count; at least four spans must count."""

SIGNIFICANT_SIGMAS = 5.0
"""A rate is told (a warning) only when it is this many of its sigmas from zero..."""

MATERIAL_MOVE_S = 1e-4
"""...and moves ``t_imu - t_lidar`` by at least this much over the segment (0.1 ms: the time
offset's tolerance of the benchmarks; a smaller drift is left to the fit's own checks)."""

_NS = 1_000_000_000


@dataclass(frozen=True)
class ClockRate:
    """The IMU clock's rate against the LiDAR's, from stamps against record times.

    Attributes:
        rate: ``d(t_imu - t_lidar) / dt``, s/s (``1e-6`` = 1 ppm; positive: the IMU's stamps
            run fast against the LiDAR's, as the model's ``clock_drift``).
        sigma: its 1-sigma, s/s.
        span_s: the record time the two topics cover together, s.
    """

    rate: float
    sigma: float
    span_s: float

    @property
    def moves_s(self) -> float:
        """How far ``t_imu - t_lidar`` moves over the span at this rate, s."""
        return abs(self.rate) * self.span_s

    @property
    def material(self) -> bool:
        """Significant (:data:`SIGNIFICANT_SIGMAS`) and moving the offset by at least
        :data:`MATERIAL_MOVE_S` over the span."""
        return abs(self.rate) > SIGNIFICANT_SIGMAS * self.sigma and self.moves_s >= MATERIAL_MOVE_S

    def text(self, estimated: bool) -> str:
        """One sentence for a user: the rate, what it does over the segment and what to do
        (``estimated``: the model's ``clock_drift`` is free)."""
        head = (
            f"The IMU's stamps run {1e6 * self.rate:+.1f} +/- {1e6 * self.sigma:.1f} ppm against "
            "the LiDAR's (each topic's stamps against the recorder's record times): over this "
            f"{self.span_s:.0f} s segment t_imu - t_lidar moves by {1e3 * self.moves_s:.2f} ms"
        )
        if estimated:
            return (
                head + "; the model estimates it (model.imu: clock_drift), with this rate as "
                "its prior."
            )
        return (
            head + ", which one time offset cannot follow. Add clock_drift to model.imu (licalib "
            "diagnose tests for it), or synchronise the sensors' clocks (PTP, the driver's time "
            "synchronisation) and re-record."
        )


def stamp_rate(
    stamps_ns: npt.ArrayLike, records_ns: npt.ArrayLike, span_ns: tuple[int, int]
) -> tuple[float, float] | None:
    """The rate of a topic's clock against the recorder's, s/s, and its 1-sigma.

    Args:
        stamps_ns: (N,) header stamps, ns.
        records_ns: (N,) their record times, ns.
        span_ns: the record-time span ``[first, last]`` cut into :data:`BINS` equal spans.

    Returns:
        ``(rate, sigma)``, or None when fewer than four spans hold :data:`MIN_PER_BIN`
        messages.
    """
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    records = np.asarray(records_ns, dtype=np.int64)
    lo, hi = span_ns
    if stamps.shape != records.shape or hi <= lo:
        return None
    inside = (records >= lo) & (records <= hi)
    rel = (records[inside] - lo).astype(np.float64) / _NS  # s since the span's start
    diff = (stamps[inside] - records[inside]).astype(np.float64) / _NS
    edges = np.linspace(0.0, (hi - lo) / _NS, BINS + 1)
    which = np.clip(np.searchsorted(edges, rel, side="right") - 1, 0, BINS - 1)
    order = np.argsort(which, kind="stable")
    counts = np.bincount(which, minlength=BINS)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    full = np.flatnonzero(counts >= MIN_PER_BIN)
    if full.size < 4:
        return None
    # one value per span (a handful of spans: the loop is over spans, not messages)
    x = np.array([np.median(rel[order[starts[b] : starts[b] + counts[b]]]) for b in full])
    y = np.array(
        [np.quantile(diff[order[starts[b] : starts[b] + counts[b]]], QUANTILE) for b in full]
    )
    xc = x - x.mean()
    sxx = float(xc @ xc)
    if sxx <= 0.0:
        return None
    slope = float(xc @ (y - y.mean())) / sxx
    resid = y - y.mean() - slope * xc
    dof = x.size - 2
    sigma = float(np.sqrt(float(resid @ resid) / dof / sxx))
    return slope, sigma


def clock_rate(
    imu_stamps_ns: npt.ArrayLike,
    imu_records_ns: npt.ArrayLike,
    lidar_stamps_ns: npt.ArrayLike,
    lidar_records_ns: npt.ArrayLike,
) -> ClockRate | None:
    """The IMU clock's rate against the LiDAR's over the record time both topics cover (see the
    module's description); None when either topic has too few messages there, or when every
    record time of both topics is its message's stamp (a bag rewritten with the stamps as record
    times: they tell nothing about the clocks)."""
    ir = np.asarray(imu_records_ns, dtype=np.int64)
    lr = np.asarray(lidar_records_ns, dtype=np.int64)
    if ir.size == 0 or lr.size == 0:
        return None
    copied = [
        np.array_equal(np.asarray(st, dtype=np.int64), rec)
        for st, rec in ((imu_stamps_ns, ir), (lidar_stamps_ns, lr))
    ]
    if all(copied):
        return None
    span = (max(int(ir.min()), int(lr.min())), min(int(ir.max()), int(lr.max())))
    imu = stamp_rate(imu_stamps_ns, ir, span)
    lidar = stamp_rate(lidar_stamps_ns, lr, span)
    if imu is None or lidar is None:
        return None
    return ClockRate(
        rate=imu[0] - lidar[0],
        sigma=float(np.hypot(imu[1], lidar[1])),
        span_s=(span[1] - span[0]) / _NS,
    )


def streams_clock_rate(imu: ImuRead, lidar: LidarRead) -> ClockRate | None:
    """:func:`clock_rate` of a segment's IMU and LiDAR streams as read (the IMU's usable
    samples; every cloud of the segment, decoded or not)."""
    if imu.raw.record_ns is None:
        return None
    return clock_rate(imu.raw.t_ns, imu.raw.record_ns, lidar.tally.stamps, lidar.tally.records)


def rate_warning(rate: ClockRate | None, cfg: CalibConfig) -> str | None:
    """The sentence ``licalib info`` and the reader tell about a material rate (its advice
    depending on whether ``model.imu`` estimates ``clock_drift``); None otherwise."""
    if rate is None or not rate.material:
        return None
    return rate.text("clock_drift" in cfg.model.imu)
