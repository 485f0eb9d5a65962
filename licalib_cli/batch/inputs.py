"""What ``licalib batch`` calibrates: bag paths, glob patterns and manifests, as jobs.

A manifest is a CSV file with a header row, or a YAML file holding a list (or ``bags:`` with a
list) of mappings or plain paths; one row per bag (or per pattern)::

    path,rig,config,start,duration
    robot7/2026-05-01.bag,robot7,,10,30
    robot9/*.bag,robot9,configs/os1-64.yaml,,

Columns (YAML keys): ``path`` (required; a bag, a bag folder or a glob pattern), ``rig`` (the
folder of the results; default: the name of the folder holding the bag), ``config`` (default:
``-c``), ``start`` and ``duration`` (seconds, as ``calibrate --start/--duration``),
``imu_topic`` and ``lidar_topic``, ``segments`` (``auto`` or ``START-END,...`` in seconds, as
``calibrate --segments``: the bag is calibrated over several segments in one problem; not with
``start``/``duration``). Relative paths are read from the manifest's folder. An empty cell is not
given.
"""

from __future__ import annotations

import csv
import glob
import io
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from licalib_cli.config import parse_yaml, read_text
from licalib_cli.errors import ConfigError, LicalibError, ManifestError

__all__ = ["COLUMNS", "BatchJob", "normalise_segments", "read_inputs"]

COLUMNS = ("path", "rig", "config", "start", "duration", "imu_topic", "lidar_topic", "segments")
"""The columns (YAML keys) a manifest may have, ``path`` required."""

MANIFEST_SUFFIXES = (".csv", ".yaml", ".yml")
_GLOB_CHARS = frozenset("*?[")
_RIG_CHARS = frozenset("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789._-")

_FIX = {
    "path": "give the bag's path",
    "rig": "give a folder name of letters, digits, '.', '_' or '-'",
    "config": "give the config file's path",
    "start": "give seconds after the bag start (0 or more)",
    "duration": "give seconds of data (more than 0)",
    "imu_topic": "give the topic's name",
    "lidar_topic": "give the topic's name",
    "segments": "give auto or START-END,... in seconds",
}


@dataclass(frozen=True)
class BatchJob:
    """One bag to calibrate, with where its settings come from.

    Attributes:
        bag: the bag (file or folder), absolute.
        rig: the rig's id: the folder of its results under the output folder.
        config: the config file, or None for the defaults.
        start_s: ``bag.start_s`` override, s; None: the config's.
        duration_s: ``bag.duration_s`` override, s; None: the config's.
        imu_topic: ``imu.topic`` override.
        lidar_topic: ``lidar.topic`` override.
        segments: ``"auto"`` or windows ``"60-75,105-120"`` (normalised): calibrate over
            several segments in one problem (``calibrate --segments``); None: one segment.
        source: where the job was given, for messages (``"manifest m.csv, line 3"``).
    """

    bag: Path
    rig: str
    config: Path | None = None
    start_s: float | None = None
    duration_s: float | None = None
    imu_topic: str | None = None
    lidar_topic: str | None = None
    segments: str | None = None
    source: str = ""

    @property
    def stem(self) -> str:
        """The result's file name without ``.yaml``: the bag's stem (a folder's name)."""
        return self.bag.name if self.bag.is_dir() else self.bag.stem

    @property
    def label(self) -> str:
        """``rig/stem``, how the bag is named in progress and tables."""
        return f"{self.rig}/{self.stem}"

    def overrides(self) -> dict[str, Any]:
        """Dotted config overrides (None entries are not applied)."""
        return {
            "imu.topic": self.imu_topic,
            "lidar.topic": self.lidar_topic,
            "bag.start_s": self.start_s,
            "bag.duration_s": self.duration_s,
        }


class _Row(BaseModel):
    """One manifest row, validated."""

    model_config = ConfigDict(
        extra="forbid", allow_inf_nan=False, str_strip_whitespace=True, coerce_numbers_to_str=True
    )

    path: str = Field(min_length=1)
    rig: str | None = None
    config: str | None = None
    start: float | None = Field(default=None, ge=0.0)
    duration: float | None = Field(default=None, gt=0.0)
    imu_topic: str | None = None
    lidar_topic: str | None = None
    segments: str | None = None

    @field_validator("rig")
    @classmethod
    def _folder_name(cls, value: str | None) -> str | None:
        if value is not None and not _is_folder_name(value):
            msg = "not a folder name"
            raise ValueError(msg)
        return value


def normalise_segments(text: str) -> str:
    """A segments choice as ``calibrate --segments`` takes it, normalised: ``"auto"``, or the
    windows in time order (``"60-75,105-120"``), so that equal choices compare equal.

    Checked as ``calibrate --segments`` checks it, with the same sentences, except the bag's
    length (the task checks that when it reads the bag).

    Raises:
        ConfigError, ExcitationError: a malformed, reversed, too short or overlapping window.
    """
    from licalib_cli.pipeline.joint import parse_segments

    if text.strip().lower() == "auto":
        return "auto"
    windows = parse_segments(text, math.inf)
    return ",".join(f"{a:.15g}-{b:.15g}" for a, b in windows)


def _is_folder_name(name: str) -> bool:
    return bool(name) and not name.startswith(".") and set(name) <= _RIG_CHARS


def _default_rig(bag: Path) -> str:
    """The name of the folder holding the bag, made a safe folder name."""
    name = bag.parent.name
    safe = "".join(c if c in _RIG_CHARS else "_" for c in name).lstrip(".")
    return safe or "default"


def _is_pattern(text: str) -> bool:
    return any(c in _GLOB_CHARS for c in text)


def _expand(text: str, base: Path | None) -> list[Path]:
    """The paths a bag argument names: itself, or the sorted matches of a pattern."""
    path = Path(text).expanduser()
    if base is not None and not path.is_absolute():
        path = base / path
    if not _is_pattern(text):
        return [path.absolute()]
    return [Path(p).absolute() for p in sorted(glob.glob(str(path), recursive=True))]


def _is_manifest(text: str) -> bool:
    return Path(text).suffix.lower() in MANIFEST_SUFFIXES and not _is_pattern(text)


def read_inputs(
    args: Sequence[str], config: Path | None = None, segments: str | None = None
) -> list[BatchJob]:
    """The jobs named on the command line: bags, glob patterns and manifests, in order.

    Args:
        args: bag paths (files or bag folders), glob patterns (``fleet/**/*.bag``) and
            manifests (``.csv``, ``.yaml``, ``.yml``).
        config: the config of every bag whose manifest row names none.
        segments: ``batch --segments``: the segments choice (``"auto"`` or ``START-END,...``)
            of every bag whose manifest row gives none; such a row may not give start or
            duration.

    Returns:
        One job per bag; a bag named twice with the same settings once.

    Raises:
        ManifestError: no input, a manifest that cannot be read or has an unknown column or a
            bad value (segments with start or duration), a bag that does not exist, a pattern
            that matches nothing.
        ConfigError, ExcitationError: a bad ``segments`` (``calibrate --segments``'s sentence).
    """
    default_segments = None if segments is None else normalise_segments(segments)
    if not args:
        msg = "No bags given; pass bag paths, glob patterns or a manifest (.csv or .yaml)."
        raise ManifestError(msg)
    jobs: list[BatchJob] = []
    for arg in args:
        if _is_manifest(arg):
            jobs.extend(_read_manifest(Path(arg), config, default_segments))
            continue
        paths = _expand(arg, None)
        if not paths:
            msg = (
                f"No file matches {arg}; check the pattern (quote it so that the shell passes "
                "it on unexpanded)."
            )
            raise ManifestError(msg)
        if not _is_pattern(arg) and not paths[0].exists():
            msg = f"The bag {arg} does not exist; check the path."
            raise ManifestError(msg)
        jobs.extend(
            BatchJob(
                bag=p,
                rig=_default_rig(p),
                config=config,
                segments=default_segments,
                source=f"argument {arg}",
            )
            for p in paths
        )
    return _unique(jobs)


def _unique(jobs: Iterable[BatchJob]) -> list[BatchJob]:
    """Drop a job that repeats an earlier one (same bag and settings)."""
    seen: set[tuple[Any, ...]] = set()
    out = []
    for job in jobs:
        key = (job.bag.resolve(), job.rig, job.config, job.segments, *job.overrides().values())
        if key not in seen:
            seen.add(key)
            out.append(job)
    return out


def _read_manifest(path: Path, config: Path | None, default_segments: str | None) -> list[BatchJob]:
    if path.suffix.lower() == ".csv":
        rows = _csv_rows(path)
        what = "column"
    else:
        rows = _yaml_rows(path)
        what = "key"
    base = path.parent.absolute()
    jobs: list[BatchJob] = []
    for where, raw in rows:
        row = _validate(path, where, what, raw)
        segments = _row_segments(path, where, row, default_segments)
        source = f"manifest {path}, {where}"
        bags = _expand(row.path, base)
        if not bags:
            msg = (
                f"The manifest {path} names in {where} the pattern {row.path}, which matches "
                "no file (relative paths are read from the manifest's folder); fix the pattern."
            )
            raise ManifestError(msg)
        if not _is_pattern(row.path) and not bags[0].exists():
            msg = (
                f"The manifest {path} names in {where} the bag {row.path}, which does not exist "
                f"({bags[0]}; relative paths are read from the manifest's folder); fix the path."
            )
            raise ManifestError(msg)
        row_config = config
        if row.config is not None:
            given = Path(row.config).expanduser()
            row_config = given if given.is_absolute() else base / given
        for bag in bags:
            jobs.append(
                BatchJob(
                    bag=bag,
                    rig=row.rig or _default_rig(bag),
                    config=row_config,
                    start_s=row.start,
                    duration_s=row.duration,
                    imu_topic=row.imu_topic,
                    lidar_topic=row.lidar_topic,
                    segments=segments,
                    source=source,
                )
            )
    if not jobs:
        msg = f"The manifest {path} lists no bags; add one row per bag (column {COLUMNS[0]!r})."
        raise ManifestError(msg)
    return jobs


def _row_segments(path: Path, where: str, row: _Row, default: str | None) -> str | None:
    """The row's segments choice, normalised (the default when it gives none), checked as
    ``calibrate --segments`` checks it; refused with ``start``/``duration`` as there."""
    if row.segments is None and default is None:
        return None
    ranged = [c for c in ("start", "duration") if getattr(row, c) is not None]
    if row.segments is None:
        if ranged:
            msg = (
                f"The manifest {path} gives {' and '.join(ranged)} in {where}, but --segments "
                f"{default} chooses the data of every bag without its own segments; drop "
                f"{' and '.join(ranged)} from that row, or give it segments, or drop --segments."
            )
            raise ManifestError(msg)
        return default
    if ranged:
        msg = (
            f"The manifest {path} gives segments and {' and '.join(ranged)} in {where}; "
            f"segments chooses the data itself, drop {' and '.join(ranged)} (as with "
            "calibrate --segments)."
        )
        raise ManifestError(msg)
    try:
        return normalise_segments(row.segments)
    except LicalibError as err:
        text = str(err)
        msg = (
            f"The manifest {path} has bad segments in {where}: {row.segments!r}; "
            f"{text[0].lower() + text[1:]}"
        )
        raise ManifestError(msg) from err


def _validate(path: Path, where: str, what: str, raw: dict[str, Any]) -> _Row:
    """One row as a :class:`_Row`, or one sentence naming the column and the fix."""
    given = {k: v for k, v in raw.items() if v is not None and v != ""}
    try:
        return _Row.model_validate(given)
    except ValidationError as err:
        first = err.errors()[0]
        column = str(first["loc"][0]) if first["loc"] else "path"
        if first["type"] == "extra_forbidden":
            msg = (
                f"The manifest {path} has an unknown {what} {column!r} ({where}); the "
                f"{what}s are {', '.join(COLUMNS)}."
            )
        elif first["type"] == "missing":
            msg = f"The manifest {path} gives no {column} in {where}; {_FIX[column]}."
        else:
            reason = first["msg"].replace("Value error, ", "")
            msg = (
                f"The manifest {path} has a bad {column} in {where}: {given.get(column)!r} "
                f"({reason[0].lower() + reason[1:]}); {_FIX.get(column, 'fix it')}."
            )
        raise ManifestError(msg) from err


def _read_text(path: Path) -> str:
    return read_text(path, "The manifest", "a CSV or YAML file", ManifestError)


def _csv_rows(path: Path) -> list[tuple[str, dict[str, Any]]]:
    text = _read_text(path)
    try:
        reader = csv.reader(io.StringIO(text, newline=""), strict=True)
        lines = [(reader.line_num, cells) for cells in reader]
    except csv.Error as err:
        msg = f"The manifest {path} is not valid CSV ({err}); fix the quoting."
        raise ManifestError(msg) from err
    lines = [(n, cells) for n, cells in lines if any(c.strip() for c in cells)]
    if not lines:
        msg = f"The manifest {path} is empty; give a header row (path,rig,...) and one row per bag."
        raise ManifestError(msg)
    header = [c.strip() for c in lines[0][1]]
    unknown = [c for c in header if c not in COLUMNS]
    if unknown:
        msg = (
            f"The manifest {path} has an unknown column {unknown[0]!r} (line {lines[0][0]}); "
            f"the columns are {', '.join(COLUMNS)}."
        )
        raise ManifestError(msg)
    if "path" not in header:
        msg = (
            f"The manifest {path} has no 'path' column in its header (line {lines[0][0]}); add it."
        )
        raise ManifestError(msg)
    if len(set(header)) != len(header):
        twice = next(c for c in header if header.count(c) > 1)
        msg = f"The manifest {path} names the column {twice!r} twice; keep one of them."
        raise ManifestError(msg)
    rows = []
    for n, cells in lines[1:]:
        if len(cells) > len(header):
            msg = (
                f"The manifest {path} has {len(cells)} cells on line {n} but {len(header)} "
                "columns in its header; remove the extra cells or quote a value with a comma."
            )
            raise ManifestError(msg)
        rows.append((f"line {n}", dict(zip(header, cells, strict=False))))
    return rows


def _yaml_rows(path: Path) -> list[tuple[str, dict[str, Any]]]:
    text = _read_text(path)  # the manifest's own sentences for a missing or binary file
    try:
        data = parse_yaml(text, path, "The manifest")
    except ConfigError as err:
        raise ManifestError(str(err)) from err
    if isinstance(data, dict):
        extra = sorted(set(data) - {"bags"})
        if extra:
            msg = (
                f"The manifest {path} has an unknown top-level key {extra[0]!r}; give a list of "
                "bags, or 'bags:' with that list."
            )
            raise ManifestError(msg)
        data = data.get("bags")
    if not isinstance(data, list):
        msg = (
            f"The manifest {path} is not a list of bags; give one entry per bag, a path or a "
            "mapping with 'path' and optional rig, config, start, duration, segments."
        )
        raise ManifestError(msg)
    rows = []
    for i, entry in enumerate(data, start=1):
        if isinstance(entry, str):
            entry = {"path": entry}
        if not isinstance(entry, dict):
            msg = (
                f"The manifest {path} has entry {i} that is neither a path nor a mapping; give "
                "a mapping with 'path' and optional rig, config, start, duration, segments."
            )
            raise ManifestError(msg)
        rows.append((f"entry {i}", {str(k): v for k, v in entry.items()}))
    return rows
