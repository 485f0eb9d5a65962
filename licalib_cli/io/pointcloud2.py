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

__all__ = [
    "POINTFIELD_DTYPES",
    "DecodedCloud",
    "decode_cloud",
    "field_names",
    "pointcloud2_dtype",
    "to_structured",
    "valid_mask",
]

POINTFIELD_DTYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
"""``sensor_msgs/PointField`` datatype code -> numpy type (without byte order)."""


def field_names(msg: Any) -> tuple[str, ...]:
    """Names of the fields of a PointCloud2 message, in message order."""
    return tuple(str(f.name) for f in msg.fields)


def pointcloud2_dtype(msg: Any) -> np.dtype:
    """Structured dtype of one point: field names, offsets, byte order and ``point_step``.

    Raises:
        DataError: unknown datatype code or a field that does not fit in ``point_step``.
    """
    order = ">" if msg.is_bigendian else "<"
    names: list[str] = []
    formats: list[Any] = []
    offsets: list[int] = []
    step = int(msg.point_step)
    for f in msg.fields:
        code = int(f.datatype)
        if code not in POINTFIELD_DTYPES:
            msg_ = (
                f"PointCloud2 field '{f.name}' has unknown datatype {code}; the cloud is corrupt."
            )
            raise DataError(msg_)
        base = np.dtype(order + POINTFIELD_DTYPES[code])
        count = max(int(f.count), 1)
        if int(f.offset) + base.itemsize * count > step:
            msg_ = (
                f"PointCloud2 field '{f.name}' (offset {f.offset}) does not fit in point_step "
                f"{step}; the cloud is corrupt."
            )
            raise DataError(msg_)
        if f.name in names:  # duplicated names (seen in some drivers): keep the first
            continue
        names.append(str(f.name))
        formats.append(base if count == 1 else (base, (count,)))
        offsets.append(int(f.offset))
    return np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": step})


def to_structured(msg: Any) -> npt.NDArray[np.void]:
    """Zero-copy structured view of all points, shape (height * width,).

    Honours ``row_step`` padding and byte order; does not copy the data unless the cloud is
    organised with row padding (then ``reshape`` copies).

    Raises:
        DataError: the sizes in the message disagree with its data.
    """
    dtype = pointcloud2_dtype(msg)
    height, width = int(msg.height), int(msg.width)
    point_step, row_step = int(msg.point_step), int(msg.row_step)
    data = np.asarray(msg.data, dtype=np.uint8)
    if height * width == 0:
        return np.empty(0, dtype=dtype)
    if point_step <= 0 or row_step < width * point_step:
        msg_ = (
            f"PointCloud2 has row_step {row_step} < width {width} x point_step {point_step}; "
            "the cloud is corrupt."
        )
        raise DataError(msg_)
    needed = (height - 1) * row_step + width * point_step
    if data.size < needed:
        msg_ = (
            f"PointCloud2 data has {data.size} bytes but its header announces {needed}; the "
            "cloud is truncated."
        )
        raise DataError(msg_)
    rows = np.ndarray((height, width), dtype=dtype, buffer=data, strides=(row_step, point_step))
    return rows.reshape(-1)


@dataclass(frozen=True)
class DecodedCloud:
    """All points of one cloud, before any filtering.

    Attributes:
        stamp_ns: header stamp, ns.
        xyz: (N, 3) float64 points in the LiDAR frame, metres (may hold NaN / zeros).
        time_raw: (N,) raw values of the per-point time field in its own dtype, or None.
        ring: (N,) int16 beam index from the ``ring``/``line`` field, or None.
        intensity: (N,) float32, or None.
        height: rows of the message (1 for unorganised clouds).
        width: points per row.
    """

    stamp_ns: int
    xyz: npt.NDArray[np.float64]
    time_raw: np.ndarray | None
    ring: npt.NDArray[np.int16] | None
    intensity: npt.NDArray[np.float32] | None
    height: int
    width: int

    def __len__(self) -> int:
        return int(self.xyz.shape[0])


def decode_cloud(
    msg: Any,
    stamp_ns: int,
    time_field: str | None,
    ring_field: str | None,
    intensity_field: str | None = "intensity",
) -> DecodedCloud:
    """Decode one PointCloud2 message into arrays.

    Args:
        msg: a deserialised ``sensor_msgs/PointCloud2``.
        stamp_ns: its header stamp, ns.
        time_field: name of the per-point time field to extract, or None.
        ring_field: name of the beam field (``ring``/``line``), or None.
        intensity_field: name of the intensity field, or None.

    Returns:
        The decoded cloud (xyz, raw time values, ring, intensity).

    Raises:
        DataError: the cloud has no x/y/z or a named field is missing or corrupt.
    """
    pts = to_structured(msg)
    names = pts.dtype.names or ()
    missing = [n for n in ("x", "y", "z") if n not in names]
    if missing:
        msg_ = (
            f"PointCloud2 has no {'/'.join(missing)} field (fields: {', '.join(names)}); "
            "licalib needs Cartesian x, y, z."
        )
        raise DataError(msg_)
    xyz = np.empty((pts.shape[0], 3), dtype=np.float64)
    xyz[:, 0] = pts["x"]
    xyz[:, 1] = pts["y"]
    xyz[:, 2] = pts["z"]
    time_raw = None
    if time_field is not None:
        if time_field not in names:
            msg_ = (
                f"PointCloud2 has no time field '{time_field}' (fields: {', '.join(names)}); "
                "fix `lidar.time_field` in the config."
            )
            raise DataError(msg_)
        time_raw = np.asarray(pts[time_field])
        if time_raw.ndim != 1:
            time_raw = time_raw.reshape(time_raw.shape[0], -1)[:, 0]
    ring = None
    if ring_field is not None and ring_field in names:
        ring = np.asarray(pts[ring_field]).astype(np.int16)
    intensity = None
    if intensity_field is not None and intensity_field in names:
        intensity = np.asarray(pts[intensity_field]).astype(np.float32)
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
    finite = np.isfinite(xyz).all(axis=1)
    safe = np.where(finite[:, None], xyz, 0.0)
    rng = np.sqrt(np.einsum("ij,ij->i", safe, safe))
    return finite & (rng > 0.0) & (rng >= min_range_m) & (rng <= max_range_m)
