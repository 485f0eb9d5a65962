"""Zero-copy decoding of ``sensor_msgs/PointCloud2`` into numpy arrays.

The message's byte buffer is viewed through a structured dtype built from its ``fields``,
with the byte order in the dtype (``is_bigendian``), ``itemsize = point_step`` (driver padding)
and a row stride of ``row_step`` (row padding). Nothing is byte-swapped in place (the buffer
is read-only). Organised clouds (``height > 1``) are flattened row by row.

Points are metres in the LiDAR frame. Invalid points (NaN or exactly (0, 0, 0), which
organised drivers such as Ouster publish for missing returns) are removed together with their
times, rings and intensities by one shared mask (:func:`valid_mask`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from licalib_cli.errors import DataError
from licalib_cli.geometry.vectors import norms

__all__ = [
    "MAX_POINT_STEP",
    "POINTFIELD_DTYPES",
    "CloudError",
    "DecodedCloud",
    "decode_cloud",
    "field_names",
    "pointcloud2_dtype",
    "to_structured",
    "valid_mask",
]

POINTFIELD_DTYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
"""``sensor_msgs/PointField`` datatype code -> numpy type (without byte order)."""

MAX_POINT_STEP = 1 << 16
"""Largest ``point_step`` accepted, bytes (drivers use 16 to 64; more means a corrupt header)."""


class CloudError(DataError):
    """A PointCloud2 message that cannot be decoded.

    Attributes:
        reason: what is wrong, a clause without a final full stop (e.g. ``field 'x' holds 3
            values per point instead of one``).
        field: the field at fault, or None when the sizes of the message are.
    """

    def __init__(self, reason: str, field: str | None = None, fix: str = "the cloud is corrupt"):
        super().__init__(f"PointCloud2 {reason}; {fix}.")
        self.reason = reason
        self.field = field


def field_names(msg: Any) -> tuple[str, ...]:
    """Names of the fields of a PointCloud2 message, in message order."""
    return tuple(str(f.name) for f in msg.fields)


def pointcloud2_dtype(msg: Any) -> np.dtype:
    """Structured dtype of one point: field names, offsets, byte order and ``point_step``.

    Raises:
        CloudError: ``point_step`` is implausibly large, a datatype code is unknown, or a field
            does not fit in ``point_step``.
    """
    order = ">" if msg.is_bigendian else "<"
    names: list[str] = []
    formats: list[Any] = []
    offsets: list[int] = []
    step = int(msg.point_step)
    if step > MAX_POINT_STEP:
        reason = f"has point_step {step}, more than {MAX_POINT_STEP} bytes per point"
        raise CloudError(reason)
    for f in msg.fields:
        name, code = str(f.name), int(f.datatype)
        if code not in POINTFIELD_DTYPES:
            raise CloudError(f"field '{name}' has unknown datatype {code}", name)
        base = np.dtype(order + POINTFIELD_DTYPES[code])
        count = max(int(f.count), 1)
        if int(f.offset) + base.itemsize * count > step:
            reason = (
                f"field '{name}' (offset {f.offset}, {count} x {base.itemsize} bytes) does not "
                f"fit in point_step {step}"
            )
            raise CloudError(reason, name)
        if name in names:  # duplicated names (seen in some drivers): keep the first
            continue
        names.append(name)
        formats.append(base if count == 1 else (base, (count,)))
        offsets.append(int(f.offset))
    return np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": step})


def to_structured(msg: Any) -> npt.NDArray[np.void]:
    """Zero-copy structured view of all points, shape (height * width,).

    Honours ``row_step`` padding and byte order; does not copy the data unless the cloud is
    organised with row padding (then ``reshape`` copies).

    Raises:
        CloudError: the sizes in the message disagree with its data.
    """
    dtype = pointcloud2_dtype(msg)
    height, width = int(msg.height), int(msg.width)
    point_step, row_step = int(msg.point_step), int(msg.row_step)
    raw = msg.data
    data = raw if isinstance(raw, np.ndarray) else np.frombuffer(bytes(raw), dtype=np.uint8)
    data = data.reshape(-1).view(np.uint8)
    if height * width == 0:
        return np.empty(0, dtype=dtype)
    if point_step <= 0 or row_step < width * point_step:
        reason = f"has row_step {row_step} < width {width} x point_step {point_step}"
        raise CloudError(reason)
    needed = (height - 1) * row_step + width * point_step
    if data.size < needed:
        reason = f"data has {data.size} bytes but its header announces {needed}"
        raise CloudError(reason, fix="the cloud is truncated")
    rows = np.ndarray((height, width), dtype=dtype, buffer=data, strides=(row_step, point_step))
    return rows.reshape(-1)


@dataclass(frozen=True)
class DecodedCloud:
    """All points of one cloud, before any filtering.

    Attributes:
        stamp_ns: header stamp, ns.
        xyz: (N, 3) float64 points in the LiDAR frame, metres (may hold NaN / zeros).
        time_raw: (N,) raw values of the per-point time field in its own dtype, or None.
        ring: (N,) int32 beam index from the ``ring``/``line`` field (-1 where a float field
            holds no number), or None.
        intensity: (N,) float32, or None.
        height: rows of the message (1 for unorganised clouds).
        width: points per row.
    """

    stamp_ns: int
    xyz: npt.NDArray[np.float64]
    time_raw: np.ndarray | None
    ring: npt.NDArray[np.int32] | None
    intensity: npt.NDArray[np.float32] | None
    height: int
    width: int

    def __len__(self) -> int:
        return int(self.xyz.shape[0])


def _first_value(values: np.ndarray) -> np.ndarray:
    """(N,) the first value of each point of a field that may hold several (``count > 1``)."""
    values = np.asarray(values)
    return values[(slice(None),) + (0,) * (values.ndim - 1)]


def _as_ring(values: np.ndarray) -> npt.NDArray[np.int32]:
    v = _first_value(values)
    if v.dtype.kind == "f":
        finite = np.isfinite(v)
        safe = np.where(finite, v, -1.0).clip(-1, np.iinfo(np.int32).max)
        return safe.astype(np.int32)
    return v.astype(np.int64).clip(-1, np.iinfo(np.int32).max).astype(np.int32)


def decode_cloud(
    msg: Any,
    stamp_ns: int,
    time_field: str | None,
    ring_field: str | None,
    intensity_field: str | None = "intensity",
) -> DecodedCloud:
    """Decode one PointCloud2 message into arrays.

    A field that holds several values per point (``count > 1``) contributes its first value
    for time, ring and intensity; x, y and z must hold one.

    Args:
        msg: a deserialised ``sensor_msgs/PointCloud2``.
        stamp_ns: its header stamp, ns.
        time_field: name of the per-point time field to extract, or None.
        ring_field: name of the beam field (``ring``/``line``), or None.
        intensity_field: name of the intensity field, or None.

    Returns:
        The decoded cloud (xyz, raw time values, ring, intensity).

    Raises:
        CloudError: the cloud has no x/y/z, a named field is missing, or the message is
            corrupt (its sizes, a datatype, a field's place or count).
    """
    pts = to_structured(msg)
    names = pts.dtype.names or ()
    missing = [n for n in ("x", "y", "z") if n not in names]
    if missing:
        reason = f"has no {'/'.join(missing)} field (fields: {', '.join(names)})"
        raise CloudError(reason, missing[0], fix="licalib needs Cartesian x, y, z")
    xyz = np.empty((pts.shape[0], 3), dtype=np.float64)
    for k, axis in enumerate(("x", "y", "z")):
        values = pts[axis]
        if values.ndim != 1:
            count = int(np.prod(values.shape[1:]))
            reason = f"field '{axis}' holds {count} values per point instead of one"
            raise CloudError(reason, axis)
        xyz[:, k] = values
    time_raw = None
    if time_field is not None:
        if time_field not in names:
            reason = f"has no time field '{time_field}' (fields: {', '.join(names)})"
            raise CloudError(reason, time_field, fix="fix `lidar.time_field` in the config")
        time_raw = _first_value(pts[time_field])
    ring = None
    with np.errstate(invalid="ignore", over="ignore"):
        if ring_field is not None and ring_field in names:
            ring = _as_ring(pts[ring_field])
        intensity = None
        if intensity_field is not None and intensity_field in names:
            intensity = _first_value(pts[intensity_field]).astype(np.float32)
    return DecodedCloud(
        stamp_ns=int(stamp_ns),
        xyz=xyz,
        time_raw=time_raw,
        ring=ring,
        intensity=intensity,
        height=int(msg.height),
        width=int(msg.width),
    )


def valid_mask(
    xyz: npt.NDArray[np.float64], min_range_m: float = 0.0, max_range_m: float = np.inf
) -> npt.NDArray[np.bool_]:
    """Points to keep: finite, not (0, 0, 0), range within ``[min_range_m, max_range_m]``.

    Args:
        xyz: (N, 3) points, metres.
        min_range_m: minimum range, metres.
        max_range_m: maximum range, metres.

    Returns:
        (N,) boolean mask to apply to xyz and to every per-point array alike.
    """
    with np.errstate(over="ignore", invalid="ignore"):
        # ranges beyond 1e154 m overflow to inf: out of range (as are NaN and inf points)
        rng = norms(xyz)
        if not np.all(np.isfinite(rng)):
            finite = np.all(np.isfinite(xyz), axis=1)
            rng = np.where(finite, norms(np.where(finite[:, None], xyz, 0.0)), np.nan)
    return (rng > 0.0) & (rng >= min_range_m) & (rng <= max_range_m)
