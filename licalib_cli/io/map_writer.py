"""Point-cloud files of a map: binary PLY or PCD with beam and time per point.

Both files hold one record per point with the fields

=============  ========  ============================================================
field          type      meaning
=============  ========  ============================================================
``x y z``      float32   position in ``{G}`` (the IMU frame at the segment start), m
``intensity``  float32   the driver's intensity (0 when the clouds carry none)
``beam``       int32     beam (ring) index
``time``       float64   IMU-clock time of the point, s since the trajectory's start
=============  ========  ============================================================

PLY is ``binary_little_endian 1.0`` with one ``vertex`` element (Open3D, CloudCompare, PCL,
MeshLab); PCD is ``DATA binary`` version 0.7 (PCL, Open3D, CloudCompare). The file is written
through a temporary file in the same folder and renamed, so a reader never sees a partial map.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterable
from pathlib import Path
from typing import Protocol

import numpy as np
import numpy.typing as npt

from licalib_cli.errors import ConfigError

__all__ = ["MAP_SUFFIXES", "POINT_DTYPE", "check_map_suffix", "write_map"]

MAP_SUFFIXES = (".ply", ".pcd")

POINT_DTYPE = np.dtype(
    [
        ("x", "<f4"),
        ("y", "<f4"),
        ("z", "<f4"),
        ("intensity", "<f4"),
        ("beam", "<i4"),
        ("time", "<f8"),
    ]
)
"""One packed little-endian record per point (32 bytes); ``beam`` is int32 because Open3D reads
no 16-bit PLY property."""

_PLY_TYPES = {"<f4": "float", "<i4": "int", "<f8": "double"}
_PCD_TYPES = {"<f4": ("4", "F"), "<i4": ("4", "I"), "<f8": ("8", "F")}


class _Chunk(Protocol):
    @property
    def xyz(self) -> npt.NDArray[np.float64]: ...
    @property
    def beam(self) -> npt.NDArray[np.uint16]: ...
    @property
    def time_s(self) -> npt.NDArray[np.float64]: ...
    @property
    def intensity(self) -> npt.NDArray[np.float32]: ...


def check_map_suffix(path: Path, option: str) -> None:
    """Refuse a map path whose suffix names no format written here.

    Raises:
        ConfigError: the suffix is not ``.ply`` or ``.pcd``.
    """
    if Path(path).suffix.lower() not in MAP_SUFFIXES:
        msg = (
            f"{option} {path} has no known point-cloud suffix; name the file .ply or .pcd "
            "(the format follows the suffix)."
        )
        raise ConfigError(msg)


def _header(fmt: str, count: int) -> bytes:
    names = POINT_DTYPE.names or ()
    kinds = [POINT_DTYPE[n].str for n in names]
    if fmt == ".ply":
        lines = ["ply", "format binary_little_endian 1.0", "comment licalib undistorted map"]
        lines.append(f"element vertex {count}")
        lines += [f"property {_PLY_TYPES[k]} {n}" for n, k in zip(names, kinds, strict=True)]
        lines.append("end_header")
    else:
        lines = [
            "# .PCD v0.7 - licalib undistorted map",
            "VERSION 0.7",
            "FIELDS " + " ".join(names),
            "SIZE " + " ".join(_PCD_TYPES[k][0] for k in kinds),
            "TYPE " + " ".join(_PCD_TYPES[k][1] for k in kinds),
            "COUNT " + " ".join("1" for _ in names),
            f"WIDTH {count}",
            "HEIGHT 1",
            "VIEWPOINT 0 0 0 1 0 0 0",
            f"POINTS {count}",
            "DATA binary",
        ]
    return ("\n".join(lines) + "\n").encode("ascii")


def write_map(path: Path, count: int, chunks: Iterable[_Chunk]) -> int:
    """Write a map atomically as PLY or PCD (by the suffix of ``path``).

    Args:
        path: the file, ``.ply`` or ``.pcd``.
        count: the number of points the chunks hold (written in the header first).
        chunks: the map's parts (``xyz``, ``beam``, ``time_s``, ``intensity``).

    Returns:
        The number of points written.

    Raises:
        ConfigError: an unknown suffix.
        ValueError: the chunks hold another number of points than ``count``.
    """
    path = Path(path)
    fmt = path.suffix.lower()
    check_map_suffix(path, "The map file")
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    written = 0
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(_header(fmt, count))
            for chunk in chunks:
                rec = np.empty(len(chunk.beam), POINT_DTYPE)
                xyz = np.asarray(chunk.xyz, dtype=np.float32)
                rec["x"], rec["y"], rec["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
                rec["intensity"] = chunk.intensity
                rec["beam"] = chunk.beam
                rec["time"] = chunk.time_s
                f.write(rec.tobytes())
                written += rec.shape[0]
        if written != count:
            msg = f"The map announced {count} points but {written} were written."
            raise ValueError(msg)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return written
