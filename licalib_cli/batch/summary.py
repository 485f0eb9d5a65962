"""The fleet summary: one row per bag, and per rig the spread of its calibrations and the bags
that disagree with the rig's others beyond their sigmas (a sensor that moved or came loose).

Comparison within a rig. Each usable calibration (verdict ``pass`` or ``warn``) is a 7-vector
``x = [t (m), r (deg), dt (s)]``: the translation, the rotation as the rotation vector
``log(R_ref^T R)`` about the LiDAR axes (``R_ref`` the rig's first calibration; the axes of
``uncertainty.rotation_std_deg``) and the time offset, with its 1-sigma ``s`` from
``uncertainty``. Bag ``i`` is compared with the inverse-variance weighted mean ``m`` (sigma
``s_m``) of the rig's other reference bags: ``z = (x_i - m) / sqrt(s_i^2 + s_m^2)`` per
coordinate and ``chi2 = sum z^2`` over the coordinates both determine (finite sigmas). The bag
with the smallest p-value leaves the reference while that p-value is below :data:`DIFFER_P`
(the split-halves check's threshold), so that one moved sensor does not pull the reference
towards it; the bags left out differ. Of two bags that disagree, both differ.
"""

from __future__ import annotations

import csv
import io
import math
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from licalib_cli.consistency.distributions import chi2_sf
from licalib_cli.geometry import so3
from licalib_cli.results import CalibrationResult, rpy_deg_from_matrix, write_text_atomic
from licalib_cli.sections import p_is

__all__ = [
    "DIFFER_P",
    "BagRow",
    "RigRow",
    "compare_within_rig",
    "find_differing",
    "rig_rows",
    "summary_csv",
]

F64 = npt.NDArray[np.float64]

DIFFER_P = 1e-3
"""p-value below which a calibration differs from the rig's others."""

COORDINATES = ("t_x", "t_y", "t_z", "rot_x", "rot_y", "rot_z", "time_offset")
_UNITS = (("mm", 1e3),) * 3 + (("deg", 1.0),) * 3 + (("ms", 1e3),)


@dataclass(frozen=True)
class BagRow:
    """One bag of the batch (a row of ``summary.csv``).

    Attributes:
        rig: the rig's id.
        bag: the bag's stem.
        status: ``calibrated`` (this run), ``up to date`` (an earlier run's result, kept),
            ``failed`` or ``not run`` (interrupted).
        verdict: ``pass``, ``warn`` or ``fail``; empty without a result.
        recorded_utc: first stamp of the calibrated segment (IMU clock) as ISO 8601 UTC.
        t_x_m, t_y_m, t_z_m: translation of ``T_imu_lidar``, m.
        roll_deg, pitch_deg, yaw_deg: its rotation, ``R = Rz(yaw) Ry(pitch) Rx(roll)``.
        time_offset_s: ``t_imu = t_lidar + time_offset_s`` (on top of ``lidar_clock_shift_s``).
        t_x_std_m, t_y_std_m, t_z_std_m: 1-sigma of the translation (``inf``: unobservable).
        rot_x_std_deg, rot_y_std_deg, rot_z_std_deg: 1-sigma of the rotation about the LiDAR
            axes.
        time_offset_std_s: 1-sigma of the time offset.
        lidar_clock_shift_s: whole-recording LiDAR clock shift applied before calibrating.
        clock_rate_ppm: how fast the IMU's stamps ran against the LiDAR's, from the bag's
            stamps against its record times (``recording.clock_rate_ppm``; away from zero where
            the sensors' clocks are not synchronised).
        added_effects: the effects calibrate estimated beyond the config's model because the
            data showed them beyond doubt (``model.added``), joined by ``+``; a rig whose bags
            keep showing one has a sensor to look at.
        calibration_s: wall seconds of the calibration (of the run that made the result).
        attempts: tries this run (0 when the result was up to date).
        differs: whether it disagrees with the rig's other bags beyond their sigmas.
        difference: the largest disagreement in words, e.g. ``t_z +12.0 mm (9.5 sigma)``.
        error: the sentence of the failure.
        exit_code: the exit code ``licalib calibrate`` gives that failure.
        result: the result file, relative to the output folder.
        path: the bag.
    """

    rig: str
    bag: str
    status: str
    verdict: str = ""
    recorded_utc: str = ""
    t_x_m: float = math.nan
    t_y_m: float = math.nan
    t_z_m: float = math.nan
    roll_deg: float = math.nan
    pitch_deg: float = math.nan
    yaw_deg: float = math.nan
    time_offset_s: float = math.nan
    t_x_std_m: float = math.nan
    t_y_std_m: float = math.nan
    t_z_std_m: float = math.nan
    rot_x_std_deg: float = math.nan
    rot_y_std_deg: float = math.nan
    rot_z_std_deg: float = math.nan
    time_offset_std_s: float = math.nan
    lidar_clock_shift_s: float = math.nan
    clock_rate_ppm: float = math.nan
    added_effects: str = ""
    calibration_s: float = math.nan
    attempts: int = 0
    differs: bool = False
    difference: str = ""
    error: str = ""
    exit_code: int = 0
    result: str = ""
    path: str = ""

    @property
    def usable(self) -> bool:
        """A result whose verdict is ``pass`` or ``warn``."""
        return self.verdict in ("pass", "warn")

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def bag_row(
    rig: str,
    stem: str,
    status: str,
    calibration: CalibrationResult | None,
    **extra: Any,
) -> BagRow:
    """A summary row from a calibration (or none, for a failure); ``extra``: the other
    fields."""
    if calibration is None:
        return BagRow(rig=rig, bag=stem, status=status, **extra)
    ext = calibration.extrinsic
    rpy = rpy_deg_from_matrix(ext.rotation)
    unc = calibration.uncertainty
    t_std = unc.translation_std_m if unc else (math.nan,) * 3
    r_std = unc.rotation_std_deg if unc else (math.nan,) * 3
    rec = calibration.recording
    return BagRow(
        rig=rig,
        bag=stem,
        status=status,
        verdict=calibration.verdict.status if calibration.verdict else "",
        recorded_utc=_utc(rec.start_ns) if rec else "",
        t_x_m=float(ext.translation[0]),
        t_y_m=float(ext.translation[1]),
        t_z_m=float(ext.translation[2]),
        roll_deg=float(rpy[0]),
        pitch_deg=float(rpy[1]),
        yaw_deg=float(rpy[2]),
        time_offset_s=float(ext.time_offset_s),
        t_x_std_m=float(t_std[0]),
        t_y_std_m=float(t_std[1]),
        t_z_std_m=float(t_std[2]),
        rot_x_std_deg=float(r_std[0]),
        rot_y_std_deg=float(r_std[1]),
        rot_z_std_deg=float(r_std[2]),
        time_offset_std_s=float(unc.time_offset_std_s) if unc else math.nan,
        lidar_clock_shift_s=float(rec.lidar_clock_shift_s) if rec else math.nan,
        clock_rate_ppm=_or_nan(rec.clock_rate_ppm if rec else None),
        added_effects="+".join(a.effect for a in calibration.model.added)
        if calibration.model
        else "",
        **extra,
    )


def _or_nan(value: float | None) -> float:
    return math.nan if value is None else float(value)


def _utc(stamp_ns: int) -> str:
    seconds, ns = divmod(int(stamp_ns), 1_000_000_000)
    return time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(seconds)) + f".{ns // 1_000_000:03d}Z"


@dataclass(frozen=True)
class RigRow:
    """One rig (a row of ``rigs.csv``).

    Attributes:
        rig: the rig's id.
        bags: bags of the rig in the batch.
        usable: bags with a usable result (verdict ``pass`` or ``warn``), the ones compared.
        failed: bags that failed (no result) or whose verdict is ``fail``.
        first_recorded_utc, last_recorded_utc: the span of the usable recordings.
        spread_t_x_mm, spread_t_y_mm, spread_t_z_mm: max - min of the translation over the
            usable bags, mm.
        spread_rot_x_deg, spread_rot_y_deg, spread_rot_z_deg: max - min of the rotation vector
            about the LiDAR axes (relative to the rig's first calibration), deg.
        spread_time_offset_ms: max - min of the time offset, ms.
        differing: the bags that differ from the rig's others beyond their sigmas.
    """

    rig: str
    bags: int
    usable: int
    failed: int
    first_recorded_utc: str = ""
    last_recorded_utc: str = ""
    spread_t_x_mm: float = math.nan
    spread_t_y_mm: float = math.nan
    spread_t_z_mm: float = math.nan
    spread_rot_x_deg: float = math.nan
    spread_rot_y_deg: float = math.nan
    spread_rot_z_deg: float = math.nan
    spread_time_offset_ms: float = math.nan
    differing: tuple[str, ...] = ()

    def to_dict(self) -> dict[str, Any]:
        out = asdict(self)
        out["differing"] = list(self.differing)
        return out


def compare_within_rig(
    x: F64, sigma: F64, reference: npt.NDArray[np.bool_] | None = None
) -> tuple[F64, F64, F64, F64, F64]:
    """Each calibration against the weighted mean of the reference ones but itself.

    Args:
        x: (n, k) estimates, one row per calibration.
        sigma: (n, k) their 1-sigma; ``inf``, NaN or 0 leave the coordinate out.
        reference: (n,) which rows make the reference (default: all).

    Returns:
        ``(z, difference, chi2, dof, p)``: (n, k) normalised differences and differences
        ``x - mean`` (0 where left out), and per calibration the chi-square, its degrees of
        freedom and its p-value (1 when ``dof`` is 0).
    """
    x = np.asarray(x, dtype=np.float64)
    sigma = np.asarray(sigma, dtype=np.float64)
    ref = np.ones(len(x), dtype=bool) if reference is None else np.asarray(reference, bool)
    ok = np.isfinite(sigma) & (sigma > 0) & np.isfinite(x)
    w = np.where(ok, 1.0 / np.where(ok, sigma, 1.0) ** 2, 0.0)
    w_ref = w * ref[:, None]
    wx_ref = np.where(ok, w_ref * np.where(ok, x, 0.0), 0.0)
    w_others = w_ref.sum(axis=0) - w_ref
    valid = ok & (w_others > 0)
    safe_w = np.where(valid, w_others, 1.0)
    mean_others = (wx_ref.sum(axis=0) - wx_ref) / safe_w
    diff = np.where(valid, np.where(ok, x, 0.0) - mean_others, 0.0)
    var = np.where(valid, np.where(ok, sigma, 0.0) ** 2 + 1.0 / safe_w, 1.0)
    z = diff / np.sqrt(var)
    chi2 = (z**2).sum(axis=1)
    dof = valid.sum(axis=1).astype(np.float64)
    p = np.where(dof > 0, chi2_sf(chi2, np.maximum(dof, 1.0)), 1.0)
    return z, diff, chi2, dof, p


def find_differing(x: F64, sigma: F64) -> tuple[npt.NDArray[np.bool_], F64, F64, F64]:
    """The calibrations that differ from their rig's others (module docstring).

    The most discrepant calibration (smallest p-value against the others) leaves the
    reference while its p-value is below :data:`DIFFER_P` and more than two remain, so that
    one moved sensor does not drag the reference towards itself and make the others look
    moved too; each calibration is then compared with the final reference. Of the last two,
    when they disagree, neither can be preferred: both differ.

    Args:
        x: (n, k) estimates.
        sigma: (n, k) their 1-sigma.

    Returns:
        ``(differs, z, difference, p)``: (n,) flags, (n, k) normalised differences and
        differences from the reference's mean, (n,) p-values.
    """
    ref = np.ones(len(x), dtype=bool)
    while ref.sum() > 2:
        p = compare_within_rig(x, sigma, ref)[4]
        candidates = np.flatnonzero(ref)
        worst = candidates[np.argmin(p[candidates])]
        if p[worst] >= DIFFER_P:
            break
        ref[worst] = False
    z, diff, _chi2, _dof, p = compare_within_rig(x, sigma, ref)
    differs = ~ref
    if ref.sum() == 2 and np.all(p[ref] < DIFFER_P):
        differs = np.ones(len(x), dtype=bool)
    return differs, z, diff, p


def _vectors(rows: Sequence[BagRow]) -> tuple[F64, F64]:
    """(n, 7) estimates and sigmas of usable rows (module docstring)."""
    rot = so3.rpy_to_matrix(np.radians([[r.roll_deg, r.pitch_deg, r.yaw_deg] for r in rows]))
    rel = np.degrees(so3.log(np.einsum("ji,njk->nik", rot[0], rot)))
    x = np.column_stack(
        [
            [[r.t_x_m, r.t_y_m, r.t_z_m] for r in rows],
            rel,
            [r.time_offset_s for r in rows],
        ]
    )
    sigma = np.array(
        [
            [
                r.t_x_std_m,
                r.t_y_std_m,
                r.t_z_std_m,
                r.rot_x_std_deg,
                r.rot_y_std_deg,
                r.rot_z_std_deg,
                r.time_offset_std_s,
            ]
            for r in rows
        ],
        dtype=np.float64,
    )
    return x, sigma


def rig_rows(rows: Sequence[BagRow]) -> tuple[list[BagRow], list[RigRow]]:
    """Per rig: the spread of its usable calibrations and the bags that differ.

    Args:
        rows: one per bag.

    Returns:
        The rows with ``differs``/``difference`` filled in (same order), and one row per rig
        (in order of first appearance).
    """
    out = list(rows)
    rigs: list[RigRow] = []
    for rig in dict.fromkeys(r.rig for r in rows):
        index = [i for i, r in enumerate(rows) if r.rig == rig]
        usable = [i for i in index if rows[i].usable]
        failed = sum(1 for i in index if rows[i].status == "failed" or rows[i].verdict == "fail")
        if not usable:
            rigs.append(RigRow(rig, len(index), 0, failed))
            continue
        x, sigma = _vectors([rows[i] for i in usable])
        spread = x.max(axis=0) - x.min(axis=0)
        stamps = sorted(rows[i].recorded_utc for i in usable if rows[i].recorded_utc)
        differing: list[str] = []
        if len(usable) >= 2:
            flags, z, diff, p = find_differing(x, sigma)
            for k in np.flatnonzero(flags):
                i = usable[k]
                j = int(np.argmax(np.abs(z[k])))
                unit, scale = _UNITS[j]
                text = (
                    f"{COORDINATES[j]} {diff[k, j] * scale:+.3g} {unit} from the others "
                    f"({abs(z[k, j]):.1f} sigma, {p_is(p[k], 1)})"
                )
                out[i] = replace(out[i], differs=True, difference=text)
                differing.append(rows[i].bag)
        scaled = spread * np.array([s for _, s in _UNITS])
        rigs.append(
            RigRow(
                rig=rig,
                bags=len(index),
                usable=len(usable),
                failed=failed,
                first_recorded_utc=stamps[0] if stamps else "",
                last_recorded_utc=stamps[-1] if stamps else "",
                spread_t_x_mm=float(scaled[0]),
                spread_t_y_mm=float(scaled[1]),
                spread_t_z_mm=float(scaled[2]),
                spread_rot_x_deg=float(scaled[3]),
                spread_rot_y_deg=float(scaled[4]),
                spread_rot_z_deg=float(scaled[5]),
                spread_time_offset_ms=float(scaled[6]),
                differing=tuple(differing),
            )
        )
    return out, rigs


def _cell(value: Any) -> str:
    if isinstance(value, bool):
        return "yes" if value else ""
    if isinstance(value, float):
        if math.isnan(value):
            return ""
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        return f"{value:.9g}"
    if isinstance(value, tuple | list):
        return ";".join(str(v) for v in value)
    return str(value)


def summary_csv(rows: Sequence[BagRow] | Sequence[RigRow], kind: type) -> str:
    """CSV text with a header of the row type's field names (empty cell: no value)."""
    buffer = io.StringIO(newline="")
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow([f.name for f in fields(kind)])
    for row in rows:
        writer.writerow([_cell(getattr(row, f.name)) for f in fields(kind)])
    return buffer.getvalue()


def write_summaries(out_dir: Path, bags: Sequence[BagRow], rigs: Sequence[RigRow]) -> None:
    """``summary.csv`` (per bag) and ``rigs.csv`` (per rig), each written atomically."""
    write_text_atomic(Path(out_dir) / "summary.csv", summary_csv(bags, BagRow))
    write_text_atomic(Path(out_dir) / "rigs.csv", summary_csv(rigs, RigRow))


def earlier_seconds(out_dir: Path) -> dict[str, float]:
    """``calibration_s`` per result file of an earlier ``summary.csv`` (empty if none)."""
    path = Path(out_dir) / "summary.csv"
    try:
        reader = csv.DictReader(io.StringIO(path.read_text()))
        out = {}
        for row in reader:
            try:
                out[row["result"]] = float(row["calibration_s"])
            except (KeyError, TypeError, ValueError):
                continue
        return out
    except (OSError, UnicodeDecodeError, csv.Error):
        return {}
