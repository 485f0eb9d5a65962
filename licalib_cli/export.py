"""Exporters: a calibration result as the parameters of LIO stacks, ROS and Kalibr.

One pure function per target turns a :class:`~licalib_cli.results.CalibrationResult` into the
text of that target; :func:`export` picks one. Every written file states, in comments, the
direction and units of each key. licalib's own conventions (README, "Conventions"):
``T_imu_lidar`` maps LiDAR points into the IMU frame, ``p_imu = R p_lidar + t``, and a LiDAR
stamp ``t_lidar`` is the IMU time ``t_imu = t_lidar + lidar_clock_shift_s + time_offset_s``.

The targets' conventions, read from their sources:

``fast-lio``
    ``mapping.extrinsic_T`` / ``mapping.extrinsic_R`` are ``t`` and ``R`` of ``T_imu_lidar``
    (``R`` row-major: FAST-LIO fills an Eigen matrix with the comma initialiser
    ``MAT_FROM_ARRAY``) and points are mapped ``p_imu = extrinsic_R p_lidar + extrinsic_T``.
    ``common.time_offset_lidar_to_imu`` is subtracted from every IMU stamp, which puts the IMU
    on the LiDAR clock: it is the total ``t_imu - t_lidar``. LI-Init writes the same quantities
    ("Rotation/Translation LiDAR to IMU", "Time Lag IMU to LiDAR") and subtracts the lag from the
    IMU stamps the same way.
``lio-sam``
    LIO-SAM works in the LiDAR frame: ``extrinsicRot`` turns IMU readings into it
    (``acc_lidar = extrinsicRot acc_imu``), so it is ``R^T``; ``extrinsicTrans`` is the IMU origin
    in the LiDAR frame (its IMU pose is ``T_world_lidar * Pose3(I, extrinsicTrans)``), so it is
    ``-R^T t``: LIO-SAM's extrinsic is ``T_lidar_imu``, the inverse of ``T_imu_lidar``.
    ``extrinsicRPY`` rotates the IMU's orientation reading: on the ``master`` (ROS 1) branch
    ``q_world_lidar = q_world_imu * inverse(extrinsicRPY)``, so it is ``R^T``; on the ``ros2``
    branch ``q_world_lidar = q_world_imu * extrinsicRPY``, so it is ``R``. LIO-SAM has no time
    offset parameter.
``urdf``
    A fixed joint's ``<origin xyz rpy>`` is the child frame's pose in the parent frame
    (``p_parent = R(rpy) p_child + xyz``), ``rpy`` in radians with ``R = Rz(y) Ry(p) Rx(r)``
    (urdfdom ``Rotation::setFromRPY``).
``tf2``
    ``static_transform_publisher`` publishes ``frame_id -> child_frame_id``: the child frame's
    pose in the parent frame (translation, quaternion ``[x, y, z, w]``), in ROS 2 with named
    arguments, in ROS 1 positionally with a period in milliseconds.
``kalibr``
    Kalibr's ``T_cam_imu`` maps IMU points into the camera frame and ``timeshift_cam_imu`` is
    ``t_imu = t_cam + shift`` (the camera stamp plus the shift is the IMU time). Here
    ``T_imu_lidar`` and ``T_lidar_imu`` (4x4, nested rows) and ``timeshift_lidar_imu`` with
    ``t_imu = t_lidar + shift``.
``json``
    The result file as JSON; ``.inf`` / ``.nan`` (unobservable) become ``null``.
"""

from __future__ import annotations

import json
import math
import re
import shlex
from collections.abc import Sequence
from dataclasses import dataclass
from enum import Enum
from pathlib import Path
from typing import TYPE_CHECKING, Any
from xml.sax.saxutils import quoteattr

import numpy as np
import yaml

from licalib_cli.errors import ConfigError, VerdictFailure
from licalib_cli.geometry import so3
from licalib_cli.results import SCHEMA_VERSION, CalibrationResult

if TYPE_CHECKING:
    import numpy.typing as npt

__all__ = [
    "ExportTarget",
    "Frames",
    "ParentSensor",
    "export",
    "exportable",
    "load_result",
    "resolve_frames",
    "to_fast_lio",
    "to_json",
    "to_kalibr",
    "to_lio_sam",
    "to_tf2",
    "to_urdf",
]

ROS1_TF_PERIOD_MS = 100
"""Republishing period of ROS 1 ``tf static_transform_publisher`` (its last argument)."""


class ExportTarget(str, Enum):
    """What :func:`export` writes."""

    FAST_LIO = "fast-lio"
    LIO_SAM = "lio-sam"
    URDF = "urdf"
    TF2 = "tf2"
    KALIBR = "kalibr"
    JSON = "json"


class ParentSensor(str, Enum):
    """Which sensor's frame is the parent of a URDF joint or tf2 transform."""

    IMU = "imu"
    LIDAR = "lidar"


FRAME_TARGETS = (ExportTarget.URDF, ExportTarget.TF2)
"""Targets that name the two frames."""
ROS2_TARGETS = (ExportTarget.FAST_LIO, ExportTarget.LIO_SAM)
"""Targets with a ROS 2 parameter-file form (``--ros2``)."""


@dataclass(frozen=True)
class Frames:
    """The two frames of a URDF joint or tf2 transform.

    Attributes:
        parent: parent frame name (tf2 ``frame_id``, URDF ``<parent link>``).
        child: child frame name; the exported transform is the child's pose in the parent.
        parent_sensor: which sensor the parent frame belongs to.
    """

    parent: str
    child: str
    parent_sensor: ParentSensor


# --------------------------------------------------------------------------------------------
# The result's sections used here: read in one place
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Sections:
    """What the exporters read from a result besides the extrinsic."""

    verdict: str | None  # "pass", "warn", "fail"; None: the file has no verdict
    reasons: tuple[str, ...]
    imu_topic: str | None
    lidar_topic: str | None
    imu_frame: str | None
    lidar_frame: str | None
    lidar_clock_shift_s: float
    provenance: str


def _sections(result: CalibrationResult) -> _Sections:
    """The verdict, recording and provenance sections of ``result`` (None where absent)."""
    verdict = result.verdict
    rec = result.recording
    prov = result.provenance

    def text(value: Any) -> str | None:
        return str(value) if value not in (None, "") else None

    origin = []
    if prov is not None:
        origin = [f"licalib {prov.licalib_version}", f"created {prov.created_utc}"]
        origin.append(f"bag fingerprint {prov.bag_fingerprint}")
    return _Sections(
        verdict=None if verdict is None else str(verdict.status),
        reasons=() if verdict is None else tuple(verdict.reasons),
        imu_topic=None if rec is None else text(rec.imu_topic),
        lidar_topic=None if rec is None else text(rec.lidar_topic),
        imu_frame=None if rec is None else text(getattr(rec, "imu_frame", None)),
        lidar_frame=None if rec is None else text(getattr(rec, "lidar_frame", None)),
        lidar_clock_shift_s=0.0 if rec is None else float(rec.lidar_clock_shift_s),
        provenance=", ".join(origin),
    )


# --------------------------------------------------------------------------------------------
# Reading and checking a result
# --------------------------------------------------------------------------------------------


def load_result(path: Path, purpose: str = "export") -> CalibrationResult:
    """Read a licalib result file for export (or for a report).

    Args:
        path: the YAML file ``licalib calibrate`` wrote.
        purpose: ``"export"`` or ``"report"``: what the messages say the file is read for.

    Returns:
        The result.

    Raises:
        ConfigError: the file is missing, unreadable or not YAML, is not a licalib result (not
            a mapping, no ``schema_version``, no complete ``extrinsic``), or has another schema
            version.
    """
    path = Path(path)
    fix = "give the file `licalib calibrate -o` wrote"
    raw: Any = _UNREAD
    try:
        raw = yaml.safe_load(path.read_text())
    except FileNotFoundError:
        pass  # CalibrationResult.load says so
    except UnicodeDecodeError as err:
        msg = f"{path} is not a licalib result (not a text file); {fix}."
        raise ConfigError(msg) from err
    except OSError as err:
        msg = f"The result file {path} cannot be read ({err.strerror}); {fix}."
        raise ConfigError(msg) from err
    except yaml.YAMLError:
        pass  # CalibrationResult.load names the line
    if raw is not _UNREAD and not isinstance(raw, dict):
        msg = f"{path} is not a licalib result (not a YAML mapping); {fix}."
        raise ConfigError(msg)
    if isinstance(raw, dict) and "schema_version" not in raw:
        msg = f"{path} is not a licalib result (it has no schema_version); {fix}."
        raise ConfigError(msg)
    if isinstance(raw, dict) and raw["schema_version"] != SCHEMA_VERSION:
        msg = (
            f"{path} is a result of schema version {raw['schema_version']!r}, but this licalib "
            f"{'exports' if purpose == 'export' else 'reads'} version {SCHEMA_VERSION}; "
            f"{purpose} it with the licalib that wrote it or calibrate again."
        )
        raise ConfigError(msg)
    result = CalibrationResult.load(path)
    ext = raw.get("extrinsic") if isinstance(raw, dict) else None
    keys = set(ext) if isinstance(ext, dict) else set()
    if not {"translation", "time_offset_s"} <= keys or not (
        {"rotation_quaternion", "rotation_rpy_deg"} & keys
    ):
        msg = (
            f"{path} is not a complete licalib result (its extrinsic needs translation, "
            f"rotation_quaternion and time_offset_s); {fix}."
        )
        raise ConfigError(msg)
    return result


_SENTENCE_END = re.compile(r"(?<=[a-z0-9)\]])\. (?=[A-Z])")


def _brief_reasons(reasons: Sequence[str]) -> str:
    """The verdict's reasons for a one-line message: the first reason's first sentence and how
    many more there are (the result file's ``verdict.reasons`` and ``licalib report`` list them
    all; an exported file's header keeps them all)."""
    if not reasons:
        return "no reason recorded"
    sentences = _SENTENCE_END.split(reasons[0].strip(), maxsplit=1)
    first = sentences[0].rstrip(".")
    more = len(reasons) - 1
    if more:
        return f"{first}; and {more} more reason{'s' if more > 1 else ''} in the result's verdict"
    if len(sentences) > 1:
        return f"{first}; more in the result's verdict"
    return first


_UNREAD = object()


def exportable(result: CalibrationResult, force: bool = False) -> tuple[str, ...]:
    """Check that ``result`` may be exported; the warnings to show.

    Args:
        result: the result.
        force: export even when the verdict is ``fail``.

    Returns:
        Warnings, one sentence each (a ``warn`` verdict, a forced ``fail``, a LiDAR clock shift
        folded into the time offset, an IMU clock drift the time offset cannot carry).

    Raises:
        VerdictFailure: the verdict is ``fail`` and ``force`` is False.
    """
    s = _sections(result)
    why = _brief_reasons(s.reasons)
    warnings: list[str] = []
    if s.verdict == "fail" and not force:
        msg = (
            f"The result's verdict is fail ({why}), so it is not exported; fix the recording "
            "and calibrate again, or pass --force to export it anyway."
        )
        raise VerdictFailure(msg)
    if s.verdict == "fail":
        warnings.append(f"Exporting a result whose verdict is fail (--force): {why}.")
    elif s.verdict == "warn":
        warnings.append(f"The result's verdict is warn: {why}.")
    if s.lidar_clock_shift_s != 0.0:
        warnings.append(
            f"The time offset includes the whole-recording LiDAR clock shift of "
            f"{s.lidar_clock_shift_s:+.9g} s; it holds only while both clocks keep that relation "
            "(not after a sensor restarts its clock)."
        )
    drift = _clock_drift(result)
    if drift is not None:
        k, reference_ns = drift
        warnings.append(
            f"The IMU clock drifts {1e6 * k:+.3g} ppm against the LiDAR's (extra_terms."
            f"clock_drift): the exported time offset holds at stamp {reference_ns} (the "
            f"calibrated segment's middle) and moves {1e3 * 60.0 * k:+.3g} ms per minute, which a "
            "constant offset cannot follow; sync the clocks (PTP, or the driver's time "
            "synchronisation) or restamp the IMU before using it."
        )
    return tuple(warnings)


def _clock_drift(result: CalibrationResult) -> tuple[float, int] | None:
    """``(k, reference_ns)`` of a clock drift the calibration estimated, else None."""
    extra = result.extra_terms
    if extra is None or extra.clock_drift is None:
        return None
    return float(extra.clock_drift), int(extra.reference_ns)


def resolve_frames(
    result: CalibrationResult,
    parent: str | None = None,
    child: str | None = None,
    parent_sensor: ParentSensor | None = None,
) -> Frames:
    """The two frames of a URDF joint or tf2 transform and which sensor is the parent.

    Names default to the frame ids the result recorded (``recording.imu_frame`` and
    ``recording.lidar_frame``). The parent is the IMU unless ``parent_sensor`` says otherwise or
    ``parent`` / ``child`` name the recorded LiDAR / IMU frame.

    Raises:
        ConfigError: a name is needed but the result records none, the names contradict the
            recorded frames or ``parent_sensor``, or parent and child are the same frame.
    """
    s = _sections(result)
    if parent is not None and parent == child:
        msg = f"The parent and child frames are both {parent!r}; give two different names."
        raise ConfigError(msg)
    recorded = {ParentSensor.IMU: s.imu_frame, ParentSensor.LIDAR: s.lidar_frame}
    other = {ParentSensor.IMU: ParentSensor.LIDAR, ParentSensor.LIDAR: ParentSensor.IMU}
    implied: set[ParentSensor] = set()  # the parent sensor that the names imply
    if s.imu_frame != s.lidar_frame:
        for sensor, name in recorded.items():
            if name is not None and parent == name:
                implied.add(sensor)
            if name is not None and child == name:
                implied.add(other[sensor])
    if parent_sensor is not None and implied and parent_sensor not in implied:
        msg = (
            f"--parent-sensor {parent_sensor.value} contradicts the frame names (the result "
            f"records IMU frame {s.imu_frame} and LiDAR frame {s.lidar_frame}); give the names "
            "of that sensor's frames or drop --parent-sensor."
        )
        raise ConfigError(msg)
    if parent_sensor is None:
        parent_sensor = implied.pop() if implied else ParentSensor.IMU
    parent = parent or recorded[parent_sensor]
    child = child or recorded[other[parent_sensor]]
    if parent is None or child is None:
        msg = (
            "The result records no frame ids of the sensors (recording.imu_frame, "
            "recording.lidar_frame); pass --parent and --child with the frame names (the parent "
            "is the IMU frame unless --parent-sensor lidar)."
        )
        raise ConfigError(msg)
    if parent == child:
        msg = f"The parent and child frames are both {parent!r}; give two different names."
        raise ConfigError(msg)
    return Frames(parent=parent, child=child, parent_sensor=parent_sensor)


# --------------------------------------------------------------------------------------------
# Numbers and the shared transform
# --------------------------------------------------------------------------------------------


def _num(x: float) -> str:
    """A float as YAML/XML/shell text: shortest round-trip form, no exponent, always a dot.

    Rounded to 1e-12 (picoseconds, picometres, 1e-12 of a rotation entry), which removes the
    1e-16 residues of exact flips; ``-0.0`` is written as ``0.0``. A YAML reader takes
    ``1e-05`` as a string, and ROS 2 refuses integers for a double array: both avoided.
    """
    value = round(float(x), 12) + 0.0
    return np.format_float_positional(value, unique=True, trim="0")


def _vec(v: npt.ArrayLike) -> str:
    return "[" + ", ".join(_num(x) for x in np.asarray(v, dtype=np.float64).reshape(-1)) + "]"


def _rows(m: npt.ArrayLike, indent: int) -> str:
    """A 3x3 matrix as a flat YAML list, one row per line (row-major)."""
    rows = np.asarray(m, dtype=np.float64).reshape(3, 3)
    pad = " " * indent
    body = (",\n" + pad).join(", ".join(_num(x) for x in row) for row in rows)
    return "[" + body + "]"


def _transform(
    result: CalibrationResult,
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """``(R, t)`` of ``T_imu_lidar``."""
    ext = result.extrinsic
    R = so3.project_to_so3(np.asarray(ext.rotation, dtype=np.float64))
    return R, np.asarray(ext.translation, dtype=np.float64).reshape(3)


def _time_offset_s(result: CalibrationResult) -> float:
    """Total ``t_imu - t_lidar`` on the recorded stamps: clock shift plus calibrated offset."""
    return float(result.extrinsic.time_offset_s) + _sections(result).lidar_clock_shift_s


def _header(result: CalibrationResult, target: str, marker: str = "#") -> list[str]:
    s = _sections(result)
    lines = [f"{marker} {target} parameters from a licalib calibration"]
    if s.provenance:
        lines.append(f"{marker} ({s.provenance})")
    if s.verdict is not None:
        lines.append(f"{marker} verdict: {s.verdict}" + (", because:" if s.reasons else ""))
        lines.extend(f"{marker}   - {reason}" for reason in s.reasons)
    return lines


def _time_lines(result: CalibrationResult, marker: str = "#") -> list[str]:
    s = _sections(result)
    dt = float(result.extrinsic.time_offset_s)
    total = _time_offset_s(result)
    lines = [
        f"{marker} licalib: t_imu - t_lidar = {_num(total)} s (the IMU stamp of an instant minus "
        "its LiDAR stamp)"
    ]
    if s.lidar_clock_shift_s != 0.0:
        lines.append(
            f"{marker}   = recording.lidar_clock_shift_s {_num(s.lidar_clock_shift_s)} s + "
            f"time_offset_s {_num(dt)} s; the clock shift holds only while both clocks keep "
            "that relation"
        )
    drift = _clock_drift(result)
    if drift is not None:
        k, reference_ns = drift
        lines.append(
            f"{marker}   at LiDAR stamp {reference_ns} ns only: the IMU clock drifts "
            f"(t_imu - t_lidar grows by {_num(k)} s per s, extra_terms.clock_drift)"
        )
    return lines


def _ros2_wrap(body: str) -> str:
    """A parameter block as a ROS 2 parameter file (``/**: ros__parameters:``)."""
    inner = "\n".join(("    " + ln) if ln else ln for ln in body.splitlines())
    return "/**:\n  ros__parameters:\n" + inner + "\n"


# --------------------------------------------------------------------------------------------
# One function per target
# --------------------------------------------------------------------------------------------


def to_fast_lio(result: CalibrationResult, ros2: bool = False) -> str:
    """FAST-LIO (and LI-Init) parameters: ``common`` and ``mapping`` keys of its config.

    Args:
        result: the calibration.
        ros2: write the ROS 2 branch's parameter-file form (same keys under
            ``/**: ros__parameters:``).

    Returns:
        YAML text with comments.
    """
    s = _sections(result)
    R, t = _transform(result)
    head = _header(result, "FAST-LIO / LI-Init")
    head += [
        "# Paste into FAST-LIO's config (config/*.yaml); the other keys stay as they are.",
        *_time_lines(result),
        "# FAST-LIO subtracts time_offset_lidar_to_imu from every IMU stamp (imu_cbk), which puts",
        "# the IMU on the LiDAR clock: time_offset_lidar_to_imu = t_imu - t_lidar, seconds.",
        "# extrinsic_R, extrinsic_T: the LiDAR in the IMU frame (FAST-LIO's Lidar_R_wrt_IMU,",
        "# Lidar_T_wrt_IMU): p_imu = extrinsic_R * p_lidar + extrinsic_T; extrinsic_R row-major,",
        "# extrinsic_T in metres (the LiDAR origin in the IMU frame). Set mapping.extrinsic_est_en",
        "# to false to keep them fixed.",
    ]
    body = ["common:"]
    if s.lidar_topic is not None:
        body.append(f"  lid_topic: {json.dumps(s.lidar_topic)}")
    if s.imu_topic is not None:
        body.append(f"  imu_topic: {json.dumps(s.imu_topic)}")
    body += [
        "  time_sync_en: false  # FAST-LIO's software sync (Livox) off: the offset is calibrated",
        f"  time_offset_lidar_to_imu: {_num(_time_offset_s(result))}  # s, taken off IMU stamps",
        "mapping:",
        f"  extrinsic_T: {_vec(t)}  # m, LiDAR origin in the IMU frame",
        f"  extrinsic_R: {_rows(R, 16)}  # row-major, p_imu = R p_lidar + T",
    ]
    text = "\n".join(body) + "\n"
    return "\n".join(head) + "\n" + (_ros2_wrap(text) if ros2 else text)


def to_lio_sam(result: CalibrationResult, ros2: bool = False) -> str:
    """LIO-SAM parameters ``extrinsicTrans``, ``extrinsicRot``, ``extrinsicRPY``.

    Args:
        result: the calibration.
        ros2: follow LIO-SAM's ``ros2`` branch: ``/**: ros__parameters:`` and ``extrinsicRPY``
            as that branch applies it (``R``, not ``R^T``: it does not invert it).

    Returns:
        YAML text with comments.
    """
    s = _sections(result)
    R, t = _transform(result)
    R_l_i, t_l_i = so3.se3_inverse(R, t)  # T_lidar_imu
    rpy = R if ros2 else R_l_i
    branch = "ros2 branch" if ros2 else "master (ROS 1) branch"
    head = _header(result, f"LIO-SAM ({branch})")
    head += [
        "# Paste into LIO-SAM's config/params.yaml.",
        "# LIO-SAM's extrinsic is T_lidar_imu, the INVERSE of licalib's T_imu_lidar",
        "# (p_imu = R p_lidar + t):",
        "#   extrinsicRot: R^T, row-major; imuConverter turns IMU readings into the LiDAR frame:",
        "#     acc_lidar = extrinsicRot * acc_imu, gyr_lidar = extrinsicRot * gyr_imu",
        "#   extrinsicTrans: -R^T t, metres, the IMU origin in the LiDAR frame; imuPreintegration:",
        "#     T_world_imu = T_world_lidar * Pose3(I, extrinsicTrans)",
    ]
    if ros2:
        head += [
            "#   extrinsicRPY: R, row-major; the ros2 branch's imuConverter: q_world_lidar =",
            "#     q_world_imu * Quaternion(extrinsicRPY) (no inverse, unlike master)",
        ]
    else:
        head += [
            "#   extrinsicRPY: R^T, row-major; imuConverter: q_world_lidar =",
            "#     q_world_imu * Quaternion(extrinsicRPY).inverse()",
        ]
    head += [
        "#   (assumes the IMU's orientation reading uses the axes of its gyro and accelerometer;",
        "#   if not, extrinsicRPY differs by that rotation)",
        "# LIO-SAM has no time offset parameter, so this one is not applied:",
        *_time_lines(result),
    ]
    body = ["lio_sam:"] if not ros2 else []
    pad = "" if ros2 else "  "
    if s.lidar_topic is not None:
        body.append(f"{pad}pointCloudTopic: {json.dumps(s.lidar_topic)}")
    if s.imu_topic is not None:
        body.append(f"{pad}imuTopic: {json.dumps(s.imu_topic)}")
    width = len(pad) + len("extrinsicRot: [")
    body += [
        f"{pad}extrinsicTrans: {_vec(t_l_i)}  # m, IMU origin in the LiDAR frame",
        f"{pad}extrinsicRot: {_rows(R_l_i, width)}  # R_lidar_imu",
        f"{pad}extrinsicRPY: {_rows(rpy, width)}  # {'R_imu_lidar' if ros2 else 'R_lidar_imu'}",
    ]
    text = "\n".join(body) + "\n"
    return "\n".join(head) + "\n" + (_ros2_wrap(text) if ros2 else text)


def _child_in_parent(
    result: CalibrationResult, frames: Frames
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """``(R, t)`` of ``T_parent_child``: ``p_parent = R p_child + t``."""
    R, t = _transform(result)
    if frames.parent_sensor is ParentSensor.IMU:
        return R, t
    return so3.se3_inverse(R, t)


def _direction(frames: Frames) -> str:
    what = "T_imu_lidar" if frames.parent_sensor is ParentSensor.IMU else "T_lidar_imu"
    return (
        f"the pose of {frames.child} in {frames.parent}: p_{frames.parent} = R p_{frames.child} "
        f"+ xyz (licalib's {what})"
    )


def to_urdf(result: CalibrationResult, frames: Frames) -> str:
    """A URDF ``<robot>`` with the two links and the fixed joint between them.

    Args:
        result: the calibration.
        frames: parent and child frame names and which sensor is the parent.

    Returns:
        XML text; the joint's ``<origin xyz rpy>`` is the child's pose in the parent, ``rpy`` in
        radians, fixed-axis roll-pitch-yaw (``R = Rz(yaw) Ry(pitch) Rx(roll)``).
    """
    R, t = _child_in_parent(result, frames)
    rpy = so3.matrix_to_rpy(R)
    comments = [
        *_header(result, "URDF", marker=""),
        f"The joint origin is {_direction(frames)}.",
        "xyz in metres; rpy in radians, fixed axes: R = Rz(yaw) Ry(pitch) Rx(roll).",
    ]
    comment = "\n".join("  " + c.strip() for c in comments).replace("--", "- -")
    parent, child = quoteattr(frames.parent), quoteattr(frames.child)
    joint = quoteattr(f"{frames.parent}_to_{frames.child}")
    xyz = " ".join(_num(x) for x in t)
    rpy_text = " ".join(_num(x) for x in rpy)
    return (
        '<?xml version="1.0"?>\n'
        f"<!--\n{comment}\n-->\n"
        '<robot name="licalib_calibration">\n'
        f"  <link name={parent}/>\n"
        f"  <link name={child}/>\n"
        f'  <joint name={joint} type="fixed">\n'
        f"    <parent link={parent}/>\n"
        f"    <child link={child}/>\n"
        f'    <origin xyz="{xyz}" rpy="{rpy_text}"/>\n'
        "  </joint>\n"
        "</robot>\n"
    )


def to_tf2(result: CalibrationResult, frames: Frames) -> str:
    """``static_transform_publisher`` command lines for ROS 2 (named) and ROS 1 (positional).

    Args:
        result: the calibration.
        frames: parent (``frame_id``) and child (``child_frame_id``) and which sensor is the parent.

    Returns:
        Shell text: comments, the ROS 2 line, the ROS 1 line.
    """
    R, t = _child_in_parent(result, frames)
    q = so3.matrix_to_quat(R)
    x, y, z = (_num(v) for v in t)
    qx, qy, qz, qw = (_num(v) for v in q)
    parent, child = shlex.quote(frames.parent), shlex.quote(frames.child)
    ros2 = (
        f"ros2 run tf2_ros static_transform_publisher --x {x} --y {y} --z {z} "
        f"--qx {qx} --qy {qy} --qz {qz} --qw {qw} --frame-id {parent} --child-frame-id {child}"
    )
    ros1 = (
        f"rosrun tf static_transform_publisher {x} {y} {z} {qx} {qy} {qz} {qw} "
        f"{parent} {child} {ROS1_TF_PERIOD_MS}"
    )
    head = _header(result, "tf2 static transform")
    head += [
        f"# frame_id {frames.parent} (parent) -> child_frame_id {frames.child}:",
        f"# {_direction(frames)};",
        "# translation in metres, quaternion [qx, qy, qz, qw]. ROS 2 (named arguments):",
    ]
    return (
        "\n".join(
            [
                *head,
                ros2,
                "# ROS 1 (positional: x y z qx qy qz qw frame_id child_frame_id period_ms):",
                ros1,
            ]
        )
        + "\n"
    )


def to_kalibr(result: CalibrationResult) -> str:
    """A Kalibr-style YAML (like a camchain-imucam file, for the LiDAR).

    Returns:
        YAML text: ``lidar0`` with ``T_imu_lidar``, ``T_lidar_imu`` (4x4 nested rows),
        ``timeshift_lidar_imu`` (``t_imu = t_lidar + shift``, seconds) and ``rostopic``.
    """
    s = _sections(result)
    R, t = _transform(result)
    T = so3.se3_to_matrix(R, t)
    T_inv = so3.se3_to_matrix(*so3.se3_inverse(R, t))

    def matrix(m: npt.NDArray[np.float64]) -> str:
        return "\n".join("  - " + _vec(row) for row in m)

    head = _header(result, "Kalibr-style")
    head += [
        "# Kalibr names T_a_b the transform mapping points from frame b into frame a (its",
        "# camchain writes T_cam_imu): T_imu_lidar maps LiDAR points into the IMU frame,",
        "# p_imu = T_imu_lidar p_lidar; T_lidar_imu is its inverse. Metres.",
        "# timeshift_lidar_imu as Kalibr's timeshift_cam_imu: t_imu = t_lidar + shift, seconds.",
        *_time_lines(result),
    ]
    body = [
        "lidar0:",
        "  T_imu_lidar:",
        matrix(T),
        "  T_lidar_imu:",
        matrix(T_inv),
        f"  timeshift_lidar_imu: {_num(_time_offset_s(result))}",
    ]
    if s.lidar_topic is not None:
        body.append(f"  rostopic: {json.dumps(s.lidar_topic)}")
    if s.imu_topic is not None:
        body.append(f"  imu_rostopic: {json.dumps(s.imu_topic)}")
    return "\n".join(head + body) + "\n"


def _finite_or_null(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _finite_or_null(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_finite_or_null(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def to_json(result: CalibrationResult) -> str:
    """The result file's content as JSON (``.inf`` / ``.nan`` as ``null``)."""
    return json.dumps(_finite_or_null(result.to_dict()), indent=2, allow_nan=False) + "\n"


def export(
    result: CalibrationResult,
    target: ExportTarget,
    *,
    frames: Frames | None = None,
    ros2: bool = False,
) -> str:
    """The text of ``target`` for ``result``.

    Args:
        result: the calibration.
        target: what to write.
        frames: the two frames (``urdf`` and ``tf2`` only; see :func:`resolve_frames`).
        ros2: ROS 2 parameter-file form (``fast-lio`` and ``lio-sam`` only).

    Raises:
        ConfigError: ``frames`` missing for ``urdf`` / ``tf2``, or an option the target does not
            take.
    """
    target = ExportTarget(target)
    if ros2 and target not in ROS2_TARGETS:
        msg = f"--ros2 applies to fast-lio and lio-sam only, not {target.value}; drop it."
        raise ConfigError(msg)
    if target in FRAME_TARGETS and frames is None:
        msg = f"{target.value} needs the parent and child frames; pass --parent and --child."
        raise ConfigError(msg)
    if target is ExportTarget.FAST_LIO:
        return to_fast_lio(result, ros2=ros2)
    if target is ExportTarget.LIO_SAM:
        return to_lio_sam(result, ros2=ros2)
    if target is ExportTarget.URDF:
        assert frames is not None
        return to_urdf(result, frames)
    if target is ExportTarget.TF2:
        assert frames is not None
        return to_tf2(result, frames)
    if target is ExportTarget.KALIBR:
        return to_kalibr(result)
    return to_json(result)
