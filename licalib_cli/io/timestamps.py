"""Per-point LiDAR times: find the time field, classify it, convert to absolute int64 ns.

Drivers publish per-point time in different ways (field name, dtype, unit, reference):

* Velodyne (``velodyne_pointcloud``): ``time`` float32, seconds relative to the header stamp;
  negative when the stamp marks the sweep end.
* Ouster (``ouster-ros``): ``t`` uint32, nanoseconds relative to the sweep start.
* Hesai / Robosense: ``timestamp`` float64, absolute seconds (Hesai stamps the first point,
  Robosense by default the last one).
* Livox ``livox_ros_driver2`` PointCloud2: ``timestamp`` float64, absolute nanoseconds.
* No time field (e.g. ``livox_ros_driver`` v1 PointCloud2, many converted clouds): times are
  estimated from the azimuth and the scan period (spinning LiDARs) or from the point order
  (non-repetitive scanners).

The unit comes from the data's own span: a spinning LiDAR's per-point times span about one
sweep period, so the unit is the one that makes the span of a cloud's values closest to the
scan period (within a factor of 30; integer fields are never seconds). Where the header stamp
falls does not decide the unit: an Ouster ``t`` (ns since the stamp) read as ms spans 0-100 s,
which contains any stamp on a sensor clock of under 100 s since power-on. Then the reference
follows rko_lio's rule: the values are *absolute* when the header stamp lies within (or within
10 ms of) the span of the converted values, or when they are epoch-sized although the clock
differs from the stamp; otherwise *relative* to the header stamp. Only when no unit gives a
plausible span (a cropped cloud) does the stamp's position choose the unit. Every decision
can be overridden from the config (``lidar.time_field``, ``time_unit``, ``time_reference``;
``time_field: none`` forces estimation).

Beams: the ``ring``/``line`` field is used when present; otherwise beams are recovered by
clustering the elevation angles ``atan2(z, hypot(x, y))`` (ring 0 = lowest beam).

All outputs are int64 nanoseconds.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
import numpy.typing as npt

from licalib_cli.errors import ConfigError, DataError, TimestampError
from licalib_cli.geometry.vectors import elevations, norms

__all__ = [
    "RING_FIELD_CANDIDATES",
    "TIME_FIELD_CANDIDATES",
    "UNIT_TO_NS",
    "BeamTable",
    "TimeLayout",
    "assign_beams",
    "classify_time_field",
    "detect_beams",
    "estimate_times",
    "find_ring_field",
    "find_time_field",
    "time_values_to_ns",
]

logger = logging.getLogger(__name__)

TIME_FIELD_CANDIDATES = (
    "t",
    "time",
    "timestamp",
    "timestamps",
    "offset_time",
    "time_stamp",
    "time_offset_us",
)
"""Per-point time field names, in order of preference."""

RING_FIELD_CANDIDATES = ("ring", "line")
"""Beam index field names, in order of preference."""

UNIT_TO_NS = {"s": 1e9, "ms": 1e6, "us": 1e3, "ns": 1.0}
"""Nanoseconds per unit of a time field."""

Unit = Literal["s", "ms", "us", "ns"]
_NS = 1_000_000_000
_EPOCH_NS = 1e15  # ~11.6 days: relative per-point offsets are never this large
_ABS_TOL_NS = 10_000_000  # rko_lio: max time within 10 ms of the header stamp
_FAR_FROM_STAMP_NS = 1e9  # per-point times farther than this from the stamp are implausible
_FAR_FROM_STAMP_PERIODS = 10.0  # ... or than this many scan periods
_LONG_SWEEP_PERIODS = 3.0  # a cloud spanning more than this many periods is implausible
_SPAN_PLAUSIBLE = float(np.log(30.0))  # a sweep spans 1/30 to 30 periods in the right unit


@dataclass(frozen=True)
class TimeLayout:
    """How per-point times are obtained for one LiDAR topic.

    Attributes:
        field: time field name, or None when times are estimated.
        unit: unit of the field (``s``, ``ms``, ``us``, ``ns``), or None when estimated.
        reference: ``relative`` (to the header stamp), ``absolute``, or ``estimated``.
        stamp_position: where the header stamp lies in the sweep: ``start``, ``end``,
            ``middle`` or ``unknown``.
        scan_period_ns: sweep period used for estimation and unit detection, ns.
        method: for estimated times, ``azimuth`` or ``index``; None otherwise.
        clockwise: spin direction used by azimuth estimation; None otherwise.
        notes: human-readable remarks (overrides used, clock mismatch, ...).
        warnings: implausible results that usually mean a wrong unit or reference (per-point
            times far from the header stamp, or a sweep much longer than the scan period),
            one sentence each.
    """

    field: str | None
    unit: Unit | None
    reference: Literal["relative", "absolute", "estimated"]
    stamp_position: Literal["start", "end", "middle", "unknown"]
    scan_period_ns: int
    method: Literal["azimuth", "index"] | None = None
    clockwise: bool | None = None
    notes: tuple[str, ...] = ()
    warnings: tuple[str, ...] = ()


def find_time_field(names: Sequence[str], override: str | None) -> str | None:
    """The per-point time field to use.

    Args:
        names: field names of the cloud.
        override: ``lidar.time_field`` from the config; ``"none"`` forces estimation.

    Returns:
        The field name, or None when there is none (times will be estimated).

    Raises:
        ConfigError: the configured field is not in the cloud.
    """
    if override is not None:
        if override.lower() == "none":
            return None
        if override not in names:
            msg = (
                f"The configured time field '{override}' is not in the cloud (fields: "
                f"{', '.join(names)}); fix `lidar.time_field` or remove it to detect the field."
            )
            raise ConfigError(msg)
        return override
    for cand in TIME_FIELD_CANDIDATES:
        if cand in names:
            return cand
    return None


def find_ring_field(names: Sequence[str], override: str | None) -> str | None:
    """The beam index field to use (``ring`` or ``line``), or None.

    Raises:
        ConfigError: the configured field is not in the cloud.
    """
    if override is not None:
        if override.lower() == "none":
            return None
        if override not in names:
            msg = (
                f"The configured ring field '{override}' is not in the cloud (fields: "
                f"{', '.join(names)}); fix `lidar.ring_field` or remove it to detect the field."
            )
            raise ConfigError(msg)
        return override
    for cand in RING_FIELD_CANDIDATES:
        if cand in names:
            return cand
    return None


def _units_for(kind: str) -> tuple[Unit, ...]:
    return ("ns", "us", "ms") if kind in "iu" else ("s", "ms", "us", "ns")


def classify_time_field(
    field_name: str,
    samples: Sequence[tuple[int, np.ndarray]],
    scan_period_ns: int,
    unit: Unit | None = None,
    reference: Literal["relative", "absolute"] | None = None,
) -> TimeLayout:
    """Detect unit, reference and stamp position of a time field from a few clouds.

    Args:
        field_name: name of the time field.
        samples: ``(stamp_ns, values)`` for a few clouds; ``values`` are the raw field values
            of the valid points (any numeric dtype).
        scan_period_ns: expected sweep period, ns (from the stamps or the config).
        unit: forced unit (config), or None to detect.
        reference: forced reference (config), or None to detect.

    Returns:
        The time layout.

    Raises:
        TimestampError: the field has zero span in every sampled cloud.
        ConfigError: the configured unit makes the sweeps a thousand times too short or long
            while another unit fits them.
    """
    samples = [(int(s), np.asarray(v)) for s, v in samples if np.asarray(v).size > 0]
    if not samples:
        msg = "No cloud with valid points to detect the time field from; check the LiDAR data."
        raise DataError(msg)
    kind = samples[0][1].dtype.kind
    stamps = np.array([s for s, _ in samples], dtype=np.int64)
    vmin = np.array([float(np.min(v)) for _, v in samples])
    vmax = np.array([float(np.max(v)) for _, v in samples])
    span = vmax - vmin
    if not np.any(span > 0):
        msg = (
            f"The per-point time field '{field_name}' has the same value for every point of "
            f"the clouds checked (zero span); set `lidar.time_field: none` to estimate times "
            "from the azimuth instead."
        )
        raise TimestampError(msg)
    period = float(max(scan_period_ns, 1))
    notes: list[str] = []
    candidates = (unit,) if unit is not None else _units_for(kind)
    if unit is not None:
        notes.append(f"time unit '{unit}' set in the config")

    def span_score(u: Unit) -> float:
        s = float(np.median(span[span > 0])) * UNIT_TO_NS[u]
        return abs(np.log(s / period))

    def absolute_fit(u: Unit) -> float:
        """Fraction of clouds whose stamp lies within the converted span (+-10 ms)."""
        lo = vmin * UNIT_TO_NS[u] - _ABS_TOL_NS
        hi = vmax * UNIT_TO_NS[u] + _ABS_TOL_NS
        return float(np.mean((stamps >= lo) & (stamps <= hi)))

    if unit is not None and span_score(unit) > _SPAN_PLAUSIBLE:
        fits = [u for u in _units_for(kind) if span_score(u) <= _SPAN_PLAUSIBLE]
        if fits:
            # units are 1000x apart: the configured one makes every sweep 1000x too short or
            # long (ms on times in s: no deskew, a VLP-16 sinusoid 145 mm off, only warning)
            sweep_ms = float(np.median(span[span > 0])) * 1e-6
            msg = (
                f"lidar.time_unit '{unit}' makes the points of a cloud span "
                f"{sweep_ms * UNIT_TO_NS[unit]:.3g} ms of its {period * 1e-6:.3g} ms sweep; read "
                f"in {fits[0]} they span {sweep_ms * UNIT_TO_NS[fits[0]]:.3g} ms: set "
                f"lidar.time_unit: {fits[0]}, or remove it to detect the unit."
            )
            raise ConfigError(msg)
    by_span = min(candidates, key=span_score)
    # A spinning LiDAR's per-point times span about one sweep period: the unit that gives that
    # span is the unit, wherever the header stamp falls. Units are 1000x apart, so at most one
    # gives a plausible span; only when none does (a cropped or odd cloud) does the stamp decide.
    span_fits = [u for u in candidates if span_score(u) <= _SPAN_PLAUSIBLE]
    other_clock = False
    chosen_ref: Literal["relative", "absolute"]
    chosen_unit: Unit
    if reference is not None:
        notes.append(f"time reference '{reference}' set in the config")
        chosen_ref = reference
        if reference == "absolute" and not span_fits:
            fits = [u for u in candidates if absolute_fit(u) >= 0.5]
            chosen_unit = fits[0] if fits else by_span
        else:
            chosen_unit = by_span
    else:
        if span_fits:
            chosen_unit = span_fits[0]
            absolute = absolute_fit(chosen_unit) >= 0.5
        else:
            fits = [u for u in candidates if absolute_fit(u) >= 0.5]
            absolute = bool(fits)
            chosen_unit = fits[0] if fits else by_span
        if absolute:
            chosen_ref = "absolute"
        else:
            magnitude = float(np.median(np.abs(vmax))) * UNIT_TO_NS[chosen_unit]
            if magnitude > _EPOCH_NS:
                other_clock = True
                chosen_ref = "absolute"
                diff_s = (float(np.median(vmin)) * UNIT_TO_NS[chosen_unit] - stamps[0]) / _NS
                notes.append(
                    f"per-point times are absolute but {diff_s:+.3f} s away from the header "
                    "stamps (the driver uses another clock); the per-point times are used"
                )
            else:
                chosen_ref = "relative"
    scale = UNIT_TO_NS[chosen_unit]
    ref = stamps.astype(np.float64) if chosen_ref == "absolute" else 0.0
    first = float(np.median(vmin * scale - ref))
    last = float(np.median(vmax * scale - ref))
    sweep = float(np.median(span)) * scale
    tol = max(1e6, 0.05 * sweep)
    position: Literal["start", "end", "middle", "unknown"]
    if abs(first) <= tol:
        position = "start"
    elif abs(last) <= tol:
        position = "end"
    elif first < 0 < last:
        position = "middle"
    else:
        position = "unknown"
    warnings = _plausibility_warnings(field_name, first, last, sweep, period, other_clock)
    return TimeLayout(
        field=field_name,
        unit=chosen_unit,
        reference=chosen_ref,
        stamp_position=position,
        scan_period_ns=int(period),
        notes=tuple(notes),
        warnings=tuple(warnings),
    )


def _plausibility_warnings(
    field_name: str, first: float, last: float, sweep: float, period: float, other_clock: bool
) -> list[str]:
    """Warnings for converted per-point times that cannot be right for a LiDAR sweep.

    Args:
        field_name: the time field.
        first: median first point time minus header stamp, ns.
        last: median last point time minus header stamp, ns.
        sweep: median time span of a cloud, ns.
        period: scan period, ns.
        other_clock: the times were detected as absolute on another clock than the stamps
            (already explained by a note).
    """
    out = []
    distance = max(first, -last, 0.0)  # 0 when the stamp lies within the sweep
    if not other_clock and distance > max(_FAR_FROM_STAMP_NS, _FAR_FROM_STAMP_PERIODS * period):
        out.append(
            f"Per-point times ('{field_name}') lie {distance / _NS:.4g} s from the header "
            "stamps; check `lidar.time_unit` and `lidar.time_reference` in the config."
        )
    if sweep > _LONG_SWEEP_PERIODS * period:
        out.append(
            f"Per-point times ('{field_name}') span {sweep / _NS:.4g} s per cloud, "
            f"{sweep / period:.3g} times the scan period of {period / _NS:.3g} s; check "
            "`lidar.time_unit` in the config."
        )
    return out


def time_values_to_ns(
    values: np.ndarray, stamp_ns: int, layout: TimeLayout
) -> npt.NDArray[np.int64]:
    """Convert raw time-field values to absolute int64 ns.

    Relative: ``stamp_ns + round(v * scale)``. Absolute: converted around the whole second of
    the stamp, so that float64 epoch seconds keep sub-microsecond precision.

    Args:
        values: (N,) raw field values.
        stamp_ns: header stamp of the cloud, ns.
        layout: a layout with a time field.

    Returns:
        (N,) int64 absolute times, ns.
    """
    assert layout.unit is not None
    scale = UNIT_TO_NS[layout.unit]
    if layout.reference == "relative":
        return stamp_ns + np.round(values.astype(np.float64) * scale).astype(np.int64)
    base_ns = (int(stamp_ns) // _NS) * _NS
    if values.dtype.kind in "iu" and layout.unit == "ns":
        return values.astype(np.int64)
    base_units = base_ns / scale  # exact: whole seconds in any unit
    rel = (values.astype(np.float64) - base_units) * scale
    return base_ns + np.round(rel).astype(np.int64)


def _unwrap_angle(a: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    return (a + np.pi) % (2.0 * np.pi) - np.pi


def estimate_times(
    xyz: npt.NDArray[np.float64],
    stamp_ns: int,
    scan_period_ns: int,
    stamp_position: Literal["start", "end"] = "start",
    clockwise: bool = False,
) -> tuple[npt.NDArray[np.int64], Literal["azimuth", "index"], bool | None]:
    """Estimate per-point times of a cloud that has no time field.

    Spinning LiDARs (points all around the sensor): the time is the azimuth swept since the
    first point, ``t = stamp + (frac - [stamp at end]) * period`` with
    ``frac = (s * (theta - theta_0) mod 2 pi) / 2 pi``. The spin direction ``s`` comes from the
    point order when it is clear (drivers publish points in firing order), otherwise from
    ``clockwise``. Points at the seam are put at the start or end of the sweep according to
    their position in the cloud. Non-spinning LiDARs (less than half of the azimuth covered):
    times are spread uniformly in point order over the period.

    Args:
        xyz: (N, 3) valid points in cloud order, metres.
        stamp_ns: header stamp, ns.
        scan_period_ns: sweep period, ns.
        stamp_position: whether the stamp marks the sweep ``start`` or ``end``.
        clockwise: spin direction seen from above (+z) when the order does not tell.

    Returns:
        ``(t_ns (N,) int64, method, clockwise used or None)``.
    """
    n = xyz.shape[0]
    end_shift = 1.0 if stamp_position == "end" else 0.0
    if n == 0:
        return np.empty(0, np.int64), "azimuth", clockwise
    theta = np.arctan2(xyz[:, 1], xyz[:, 0])
    occupied = np.unique(((theta + np.pi) / (2 * np.pi) * 36).astype(int).clip(0, 35)).size
    if occupied < 18 or n < 3:
        frac = np.arange(n, dtype=np.float64) / max(n - 1, 1)
        t = stamp_ns + np.round((frac - end_shift) * scan_period_ns).astype(np.int64)
        return t, "index", None
    d = _unwrap_angle(np.diff(theta))
    d = d[(np.abs(d) > 0) & (np.abs(d) < 0.2)]
    ordered = False
    cw = clockwise
    if d.size >= 10:
        pos = float(np.mean(d > 0))
        if pos > 0.7 or pos < 0.3:
            ordered = True
            cw = pos < 0.3
    sign = -1.0 if cw else 1.0
    head = max(1, min(50, n // 200))
    theta0 = float(np.angle(np.mean(np.exp(1j * theta[:head])))) if head > 1 else float(theta[0])
    frac = np.mod(sign * (theta - theta0), 2 * np.pi) / (2 * np.pi)
    if ordered:
        idx = np.arange(n) / n
        frac = np.where((idx < 0.1) & (frac > 0.9), frac - 1.0, frac)
        frac = np.where((idx > 0.9) & (frac < 0.1), frac + 1.0, frac)
    t = stamp_ns + np.round((frac - end_shift) * scan_period_ns).astype(np.int64)
    return t, "azimuth", cw


@dataclass(frozen=True)
class BeamTable:
    """Beam elevations recovered from the data (ring 0 = lowest beam).

    Attributes:
        elevation_rad: (B,) ascending beam elevation angles, radians.
    """

    elevation_rad: npt.NDArray[np.float64]

    @property
    def num_beams(self) -> int:
        """Number of beams."""
        return int(self.elevation_rad.shape[0])


def detect_beams(
    clouds: Sequence[npt.NDArray[np.float64]], num_beams: int | None = None
) -> BeamTable:
    """Recover beam elevations by clustering the elevation angles of a few clouds.

    Uses points farther than 3 m when there are enough (beam origin offsets blur near points).
    With ``num_beams`` the clusters are split at the ``num_beams - 1`` largest gaps;
    otherwise at gaps wider than ``max(0.06 deg, 20 x the 90th-percentile gap)``. Clusters
    with fewer than 0.05 % of the points are treated as noise.

    Args:
        clouds: (N_i, 3) valid points of a few clouds, metres.
        num_beams: known number of beams (config ``lidar.num_beams``), or None.

    Returns:
        The beam table.

    Raises:
        DataError: no points to cluster.
    """
    xyz = np.concatenate([np.asarray(c, np.float64).reshape(-1, 3) for c in clouds], axis=0)
    if xyz.shape[0] == 0:
        msg = "No valid LiDAR points to recover the beams from; check the LiDAR data."
        raise DataError(msg)
    far = norms(xyz) > 3.0
    if far.sum() > 1000:
        xyz = xyz[far]
    el = np.sort(elevations(xyz))
    gaps = np.diff(el)
    if gaps.size == 0:
        return BeamTable(np.array([el[0]]))
    if num_beams is not None and num_beams > 1:
        k = min(num_beams - 1, gaps.size)
        cuts = np.sort(np.argpartition(gaps, -k)[-k:])
    else:
        thr = max(np.deg2rad(0.06), 20.0 * float(np.percentile(gaps, 90)))
        cuts = np.flatnonzero(gaps > thr)
    groups = np.split(el, cuts + 1)
    min_size = max(1, int(0.0005 * el.size))
    centers = np.array([float(np.median(g)) for g in groups if g.size >= min_size])
    return BeamTable(np.sort(centers))


def assign_beams(xyz: npt.NDArray[np.float64], table: BeamTable) -> npt.NDArray[np.int16]:
    """Beam index of each point: the nearest beam elevation of ``table``.

    Args:
        xyz: (N, 3) points, metres.
        table: beam elevations.

    Returns:
        (N,) int16 ring indices (0 = lowest beam).
    """
    el = elevations(xyz)
    mids = 0.5 * (table.elevation_rad[1:] + table.elevation_rad[:-1])
    return np.searchsorted(mids, el).astype(np.int16)
