"""The result file (schema v1): extrinsic, time offset, IMU and LiDAR intrinsics.

The same keys are used for a calibration result and for a simulator's ``truth.yaml``::

    schema_version: 1
    extrinsic:                 # T_imu_lidar: p_imu = R p_lidar + t
      translation: [x, y, z]   # metres
      rotation_quaternion: [x, y, z, w]
      rotation_rpy_deg: [roll, pitch, yaw]   # R = Rz(yaw) Ry(pitch) Rx(roll)
      time_offset_s: 0.005     # t_imu = t_lidar + time_offset_s
    imu_intrinsics: {...}
    lidar_intrinsics: {...}

A calibration adds ``gravity_G`` and the typed sections of :mod:`licalib_cli.sections`
(``uncertainty``, ``observability``, ``verdict``, ``consistency``, ``initialization``, ``fit``,
``recording``, ``provenance``). A simulator's ``truth.yaml`` adds ``scenario``, ``seed`` and
``simulation``, read with :class:`licalib_cli.truth.Truth`; :class:`CalibrationResult` reads
such a file's true values and leaves those sections aside.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import yaml

from licalib_cli.config import read_yaml
from licalib_cli.errors import ConfigError
from licalib_cli.filetypes import FileValueError, number, numbers, typed, wrong
from licalib_cli.geometry import so3
from licalib_cli.models.intrinsics import ImuIntrinsics, LidarIntrinsics
from licalib_cli.sections import (
    Consistency,
    ExtraTerms,
    FactoryExtrinsicSection,
    FitSection,
    InitializationSection,
    IntrinsicsUncertainty,
    ModelInfo,
    Observability,
    Provenance,
    RecordingSection,
    Section,
    SegmentsSection,
    Uncertainty,
    VerdictSection,
)

SCHEMA_VERSION = 1
F64 = npt.NDArray[np.float64]


def _list(a: npt.ArrayLike, digits: int = 9) -> list[float]:
    return [round(float(x), digits) for x in np.asarray(a, dtype=np.float64).reshape(-1)]


def vec3(values: Any) -> tuple[float, float, float]:
    """Three numbers (an array, a sequence or an iterable) as a tuple of floats."""
    x, y, z = (float(v) for v in values)
    return (x, y, z)


def rpy_deg_from_matrix(rot: F64) -> F64:
    """``[roll, pitch, yaw]`` in degrees with ``R = Rz(yaw) Ry(pitch) Rx(roll)``."""
    return np.degrees(so3.matrix_to_rpy(rot)) + 0.0  # + 0.0: no -0.0 in the file


def matrix_from_rpy_deg(rpy_deg: npt.ArrayLike) -> F64:
    """Inverse of :func:`rpy_deg_from_matrix`."""
    return so3.rpy_to_matrix(np.radians(np.asarray(rpy_deg, dtype=np.float64)))


@dataclass(frozen=True)
class Extrinsic:
    """``T_imu_lidar`` and the time offset.

    Attributes:
        rotation: (3, 3) ``R`` with ``p_imu = R p_lidar + t``.
        translation: (3,) ``t``, metres (the LiDAR origin in the IMU frame).
        time_offset_s: ``t_imu = t_lidar + time_offset_s``.
    """

    rotation: F64 = field(default_factory=lambda: np.eye(3))
    translation: F64 = field(default_factory=lambda: np.zeros(3))
    time_offset_s: float = 0.0

    @property
    def quaternion(self) -> F64:
        """``[x, y, z, w]`` with ``w >= 0``."""
        return so3.matrix_to_quat(self.rotation) + 0.0

    def matrix(self) -> F64:
        """(4, 4) homogeneous ``T_imu_lidar``."""
        out = np.eye(4)
        out[:3, :3], out[:3, 3] = self.rotation, self.translation
        return out

    def to_dict(self) -> dict[str, Any]:
        return {
            "translation": _list(self.translation),
            "rotation_quaternion": _list(self.quaternion, 12),
            "rotation_rpy_deg": _list(rpy_deg_from_matrix(self.rotation)),
            "time_offset_s": round(float(self.time_offset_s), 12),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any], key: str = "extrinsic") -> Extrinsic:
        """Read ``translation``, a rotation (``rotation_quaternion``, else ``rotation_rpy_deg``)
        and ``time_offset_s``; an absent one is zero.

        Raises:
            FileValueError: a value is not of its kind (3 numbers, a unit quaternion, a
                number).
        """
        q, rpy = rotation_keys(d, key, "rotation")
        if q is not None:
            rot = so3.quat_to_matrix(q)
        else:
            rot = np.eye(3) if rpy is None else matrix_from_rpy_deg(rpy)
        return cls(
            rotation=rot,
            translation=numbers(d.get("translation", [0.0] * 3), f"{key}.translation", 3, True),
            time_offset_s=number(d.get("time_offset_s", 0.0), f"{key}.time_offset_s", finite=True),
        )

    def factory_difference(
        self, factory: Extrinsic, source: str, sensor: str, cloud_frame: str
    ) -> FactoryExtrinsicSection:
        """The factory extrinsic ``factory`` and this calibration's difference from it (see
        :class:`~licalib_cli.sections.FactoryExtrinsicSection`)."""
        d_rot = so3.log(factory.rotation.T @ self.rotation)
        d_t = self.translation - factory.translation
        qx, qy, qz, qw = _list(factory.quaternion, 12)
        return FactoryExtrinsicSection(
            source=source,
            sensor=sensor,
            cloud_frame=cloud_frame,
            translation=vec3(_list(factory.translation)),
            rotation_quaternion=(qx, qy, qz, qw),
            rotation_rpy_deg=vec3(_list(rpy_deg_from_matrix(factory.rotation))),
            difference_translation_m=vec3(_list(d_t)),
            difference_translation_norm_m=round(float(np.linalg.norm(d_t)), 9),
            difference_rotation_deg=round(float(np.degrees(np.linalg.norm(d_rot))), 9),
            difference_rotation_vector_deg=vec3(_list(np.degrees(d_rot))),
        )

    def moved_to(self, other: Extrinsic) -> F64:
        """(7,) how ``other`` differs from this one: translation (m, IMU frame), rotation (rad,
        about the LiDAR axes: ``log(R_self^T R_other)``), time offset (s)."""
        return np.concatenate(
            [
                np.asarray(other.translation, dtype=np.float64)
                - np.asarray(self.translation, dtype=np.float64),
                so3.log(np.asarray(self.rotation).T @ np.asarray(other.rotation)),
                [other.time_offset_s - self.time_offset_s],
            ]
        )

    def error_to(self, other: Extrinsic) -> dict[str, float]:
        """Errors against a reference: translation (m), rotation angle (deg), time offset (s)."""
        d = self.moved_to(other)
        return {
            "translation_m": float(np.linalg.norm(d[:3])),
            "rotation_deg": float(np.degrees(np.linalg.norm(d[3:6]))),
            "time_offset_s": float(abs(d[6])),
        }

    def on_shifted_clock(self, lidar_clock_offset_s: float, applied_shift_s: float) -> Extrinsic:
        """This (true) extrinsic with its time offset expressed on a calibration's clock.

        A simulated LiDAR clock may run ``lidar_clock_offset_s`` ahead of the IMU clock
        (``t_imu = t_lidar - lidar_clock_offset_s + time_offset_s``); a calibration that shifted
        the LiDAR times by ``applied_shift_s`` (``recording.lidar_clock_shift_s``) reports the
        time offset on top of that shift. Both splits of the same total are arbitrary; this
        gives the true offset in the calibration's split so that the two compare.
        """
        total = self.time_offset_s - lidar_clock_offset_s
        return replace(self, time_offset_s=total - applied_shift_s)


def imu_intrinsics_to_dict(k: ImuIntrinsics) -> dict[str, Any]:
    """YAML mapping of the IMU model of method.md section 3."""
    q = np.asarray(k.gyro_rotation, dtype=np.float64)
    q = -q if q[3] < 0 else q
    return {
        "gyro_scale": _list(k.gyro_scale),  # diag(S_w)
        "gyro_misalignment": _list(k.gyro_misalignment),  # M_w = [[1,m0,m1],[0,1,m2],[0,0,1]]
        "gyro_rotation_quaternion": _list(q, 12),  # R_wI: IMU frame -> gyro frame
        "gyro_rotation_rpy_deg": _list(rpy_deg_from_matrix(so3.quat_to_matrix(q))),
        "accel_scale": _list(k.accel_scale),  # diag(S_a)
        "accel_misalignment": _list(k.accel_misalignment),  # M_a
        "gyro_g_sensitivity": [_list(row) for row in np.asarray(k.gyro_g_sensitivity)],  # A_w
        "gyro_bias": _list(k.gyro_bias),  # rad/s
        "accel_bias": _list(k.accel_bias),  # m/s^2
    }


def quaternion(value: Any, key: str) -> F64:
    """A unit quaternion ``[x, y, z, w]`` read from a file (normalised).

    Raises:
        FileValueError: not four finite numbers of norm 1 (within 1e-3).
    """
    q = numbers(value, key, 4, finite=True)
    norm = float(np.linalg.norm(q))
    if abs(norm - 1.0) > 1e-3:
        raise wrong(key, value, "a unit quaternion [x, y, z, w]")
    return q / norm


def rotation_keys(d: dict[str, Any], key: str, prefix: str) -> tuple[F64 | None, F64 | None]:
    """A rotation's two keys, ``<prefix>_quaternion`` (a unit quaternion) and its readable twin
    ``<prefix>_rpy_deg`` (3 finite numbers), each checked when present and None when absent.

    Raises:
        FileValueError: a present one is not of its kind.
    """
    quat, rpy = f"{prefix}_quaternion", f"{prefix}_rpy_deg"
    return (
        quaternion(d[quat], f"{key}.{quat}") if quat in d else None,
        numbers(d[rpy], f"{key}.{rpy}", 3, finite=True) if rpy in d else None,
    )


def imu_intrinsics_from_dict(d: dict[str, Any], key: str = "imu_intrinsics") -> ImuIntrinsics:
    """Read the IMU model (an absent key: its default).

    Raises:
        FileValueError: a value is not of its size (3 numbers, a unit quaternion, 3 x 3).
    """
    default = ImuIntrinsics()
    q, rpy = rotation_keys(d, key, "gyro_rotation")
    if q is None:
        q = default.gyro_rotation if rpy is None else so3.matrix_to_quat(matrix_from_rpy_deg(rpy))

    def arr(name: str, fallback: F64) -> F64:
        return numbers(d[name], f"{key}.{name}", 3, True) if name in d else fallback

    sensitivity = default.gyro_g_sensitivity
    if "gyro_g_sensitivity" in d:
        rows = d["gyro_g_sensitivity"]
        where = f"{key}.gyro_g_sensitivity"
        if not isinstance(rows, list) or len(rows) != 3:
            raise wrong(where, rows, "3 rows of 3 numbers")
        sensitivity = np.stack([numbers(r, f"{where}.{i}", 3, True) for i, r in enumerate(rows)])
    return ImuIntrinsics(
        gyro_scale=arr("gyro_scale", default.gyro_scale),
        gyro_misalignment=arr("gyro_misalignment", default.gyro_misalignment),
        gyro_rotation=q,
        accel_scale=arr("accel_scale", default.accel_scale),
        accel_misalignment=arr("accel_misalignment", default.accel_misalignment),
        gyro_g_sensitivity=sensitivity,
        gyro_bias=arr("gyro_bias", default.gyro_bias),
        accel_bias=arr("accel_bias", default.accel_bias),
    )


def lidar_intrinsics_to_dict(k: LidarIntrinsics) -> dict[str, Any]:
    """YAML mapping of the per-beam model of method.md section 4 (angles in degrees)."""
    return {
        "num_beams": k.num_beams,
        "nominal_elevation_deg": _list(np.degrees(k.nominal_elevation)),  # phi_i
        "elevation_correction_deg": _list(np.degrees(k.elevation_correction)),  # dphi_i
        "azimuth_correction_deg": _list(np.degrees(k.azimuth_correction)),  # dtheta_i
        "vertical_offset_m": _list(k.vertical_offset),  # V_i
        "horizontal_offset_m": _list(k.horizontal_offset),  # H_i
        "range_scale": _list(k.range_scale),  # s_i
        "range_offset_m": _list(k.range_offset),  # drho_i
    }


_LIDAR_KEYS = (
    "nominal_elevation_deg",
    "elevation_correction_deg",
    "azimuth_correction_deg",
    "vertical_offset_m",
    "horizontal_offset_m",
    "range_scale",
    "range_offset_m",
)


def lidar_intrinsics_from_dict(d: dict[str, Any], key: str = "lidar_intrinsics") -> LidarIntrinsics:
    """Read the per-beam model: seven lists of one number per beam.

    Raises:
        FileValueError: a key is missing, or a list is not of finite numbers or not as long as
            the first one.
    """
    missing = [name for name in _LIDAR_KEYS if name not in d]
    if missing:
        raise FileValueError(f"{key}.{missing[0]}", "is missing")
    beams = d[_LIDAR_KEYS[0]]
    size = len(beams) if isinstance(beams, list) and beams else None
    arr = {name: numbers(d[name], f"{key}.{name}", size, True) for name in _LIDAR_KEYS}
    if size is None:
        raise wrong(f"{key}.{_LIDAR_KEYS[0]}", beams, "a list of one number per beam")
    return LidarIntrinsics(
        nominal_elevation=np.radians(arr["nominal_elevation_deg"]),
        elevation_correction=np.radians(arr["elevation_correction_deg"]),
        azimuth_correction=np.radians(arr["azimuth_correction_deg"]),
        vertical_offset=arr["vertical_offset_m"],
        horizontal_offset=arr["horizontal_offset_m"],
        range_scale=arr["range_scale"],
        range_offset=arr["range_offset_m"],
    )


_SECTIONS: tuple[tuple[str, type[Section]], ...] = (
    ("model", ModelInfo),
    ("uncertainty", Uncertainty),
    ("intrinsics_uncertainty", IntrinsicsUncertainty),
    ("observability", Observability),
    ("verdict", VerdictSection),
    ("consistency", Consistency),
    ("initialization", InitializationSection),
    ("fit", FitSection),
    ("recording", RecordingSection),
    ("factory_extrinsic", FactoryExtrinsicSection),
    ("provenance", Provenance),
    ("segments", SegmentsSection),
    ("extra_terms", ExtraTerms),
)


@dataclass(frozen=True)
class CalibrationResult:
    """A calibration (or a simulator's ground truth) in schema v1.

    Attributes:
        extrinsic: ``T_imu_lidar`` and the time offset.
        imu_intrinsics: the IMU model's parameters (biases included).
        lidar_intrinsics: per-beam LiDAR intrinsics, or None when not part of the file.
        gravity_G: (3,) gravity in the first IMU frame, m/s^2, or None.
        model, uncertainty, intrinsics_uncertainty, observability, verdict, consistency,
            initialization, fit, recording, factory_extrinsic, provenance, segments,
            extra_terms: the typed
            sections ``calibrate`` writes (:mod:`licalib_cli.sections`), None when the file
            has none.
    """

    extrinsic: Extrinsic = field(default_factory=Extrinsic)
    imu_intrinsics: ImuIntrinsics = field(default_factory=ImuIntrinsics)
    lidar_intrinsics: LidarIntrinsics | None = None
    gravity_G: tuple[float, float, float] | None = None
    model: ModelInfo | None = None
    uncertainty: Uncertainty | None = None
    intrinsics_uncertainty: IntrinsicsUncertainty | None = None
    observability: Observability | None = None
    verdict: VerdictSection | None = None
    consistency: Consistency | None = None
    initialization: InitializationSection | None = None
    fit: FitSection | None = None
    recording: RecordingSection | None = None
    factory_extrinsic: FactoryExtrinsicSection | None = None
    provenance: Provenance | None = None
    segments: SegmentsSection | None = None
    extra_terms: ExtraTerms | None = None

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"schema_version": SCHEMA_VERSION}
        out["extrinsic"] = self.extrinsic.to_dict()
        out["imu_intrinsics"] = imu_intrinsics_to_dict(self.imu_intrinsics)
        if self.lidar_intrinsics is not None:
            out["lidar_intrinsics"] = lidar_intrinsics_to_dict(self.lidar_intrinsics)
        if self.gravity_G is not None:
            out["gravity_G"] = _list(self.gravity_G, 6)
        for name, _ in _SECTIONS:
            section = getattr(self, name)
            if section is not None:
                out[name] = section.to_dict()
        return out

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> CalibrationResult:
        """Read a result (or the true values of a ``truth.yaml``; other top-level keys are
        left aside).

        Raises:
            ConfigError: another schema version; FileValueError: a key is missing or a value
                is not of its type.
        """
        version = d.get("schema_version")
        if version != SCHEMA_VERSION or isinstance(version, bool):
            msg = (
                f"The result file has schema_version {version!r}, but this licalib reads "
                f"version {SCHEMA_VERSION}; regenerate it with this version."
            )
            raise ConfigError(msg)
        parts = {name: d.get(name) for name in ("extrinsic", "imu_intrinsics", "lidar_intrinsics")}
        for name, value in parts.items():
            if value is not None and not isinstance(value, dict):
                raise wrong(name, value, "a mapping")
        sections: dict[str, Any] = {}
        for name, kind in _SECTIONS:
            if d.get(name) is not None:
                sections[name] = typed(d[name], kind, name)
        gravity = d.get("gravity_G")
        lidar = parts["lidar_intrinsics"]
        return cls(
            extrinsic=Extrinsic.from_dict(parts["extrinsic"] or {}),
            imu_intrinsics=imu_intrinsics_from_dict(parts["imu_intrinsics"] or {}),
            lidar_intrinsics=lidar_intrinsics_from_dict(lidar) if lidar else None,
            gravity_G=None if gravity is None else vec3(numbers(gravity, "gravity_G", 3, True)),
            **sections,
        )

    def to_yaml(self) -> str:
        return dump_yaml(self.to_dict())

    def save(self, path: Path) -> None:
        """Write the YAML atomically."""
        write_text_atomic(Path(path), self.to_yaml())

    @classmethod
    def load(cls, path: Path) -> CalibrationResult:
        path = Path(path)
        data = read_yaml(path, "The result file")
        if not isinstance(data, dict):
            msg = f"The result file {path} is not a YAML mapping; regenerate it."
            raise ConfigError(msg)
        try:
            return cls.from_dict(data)
        except FileValueError as err:
            raise err.in_file(f"the result file {path}") from err


class _Dumper(yaml.SafeDumper):
    pass


def _represent_list(dumper: yaml.SafeDumper, data: list[Any]) -> yaml.Node:
    flow = all(not isinstance(x, (dict, list)) for x in data)
    return dumper.represent_sequence("tag:yaml.org,2002:seq", data, flow_style=flow)


_Dumper.add_representer(list, _represent_list)


def estimate_rows(
    result: CalibrationResult,
    truth: Extrinsic | None = None,
    initial: tuple[Sequence[float], Sequence[float], float] | None = None,
    unobservable: str = "unobservable",
    true_clock_drift: float | None = None,
) -> list[list[str]]:
    """The estimate table's rows, as the console and the report show them.

    Columns: parameter, estimate, 1-sigma, then the initial guess (``initial``: translation m,
    roll/pitch/yaw deg, time offset s) and the truth and error (``truth``) when given. The
    rotation rows' 1-sigma and error are about the LiDAR x, y and z axes
    (``log(R_true^T R_est)``), not differences of Euler angles: those come apart near a pitch
    of 90 deg, where a tiny rotation moves roll and yaw by large and opposite amounts.

    Args:
        result: the result.
        truth: the true extrinsic on the result's clock footing, or None.
        initial: the initial guess, or None.
        unobservable: the sigma cell of a direction that is not observable.
        true_clock_drift: the true IMU clock drift (s/s) for the clock drift's row, when the
            model estimates one and ``truth`` is given.
    """
    ext = result.extrinsic
    unc = result.uncertainty
    nan3 = (float("nan"),) * 3
    t_std = unc.translation_std_m if unc else nan3
    r_std = unc.rotation_std_deg if unc else nan3
    c_std = unc.time_offset_std_s if unc else float("nan")

    def sigma(v: float, scale: float, unit: str, digits: int) -> str:
        return f"{v * scale:.{digits}f} {unit}" if np.isfinite(v) else unobservable

    rpy = rpy_deg_from_matrix(ext.rotation)
    t_rpy = rpy_deg_from_matrix(truth.rotation) if truth is not None else None
    r_err = np.degrees(truth.moved_to(ext)[3:6]) if truth is not None else None
    rows = []
    for i, axis in enumerate("xyz"):
        row = [f"t_{axis}", f"{ext.translation[i]:+.4f} m", sigma(t_std[i], 1e3, "mm", 2)]
        if initial is not None:
            row.append(f"{initial[0][i]:+.4f} m")
        if truth is not None:
            row += [
                f"{truth.translation[i]:+.4f} m",
                f"{1e3 * (ext.translation[i] - truth.translation[i]):+.2f} mm",
            ]
        rows.append(row)
    for i, name in enumerate(("roll", "pitch", "yaw")):
        row = [name, f"{rpy[i]:+.4f} deg", sigma(r_std[i], 1.0, "deg", 4)]
        if initial is not None:
            row.append(f"{initial[1][i]:+.4f} deg")
        if t_rpy is not None and r_err is not None:
            row += [f"{t_rpy[i]:+.4f} deg", f"{r_err[i]:+.4f} deg"]
        rows.append(row)
    extra = result.extra_terms
    drifting = extra is not None and extra.clock_drift is not None
    label = "time offset (mid)" if drifting else "time offset"
    row = [label, f"{1e3 * ext.time_offset_s:+.3f} ms", sigma(c_std, 1e3, "ms", 3)]
    if initial is not None:
        row.append(f"{1e3 * initial[2]:+.3f} ms")
    if truth is not None:
        row += [
            f"{1e3 * truth.time_offset_s:+.3f} ms",
            f"{1e3 * (ext.time_offset_s - truth.time_offset_s):+.3f} ms",
        ]
    rows.append(row)
    if drifting:
        assert extra is not None and extra.clock_drift is not None
        stds = result.intrinsics_uncertainty.values if result.intrinsics_uncertainty else {}
        std = (stds.get("clock_drift") or (None,))[0]
        row = ["clock drift", f"{1e6 * extra.clock_drift:+.2f} ppm"]
        row.append(sigma(std, 1e6, "ppm", 2) if std is not None else unobservable)
        row += [""] * (initial is not None)
        if truth is not None:
            k = true_clock_drift
            row += (
                ["", ""]
                if k is None
                else [
                    f"{1e6 * k:+.2f} ppm",
                    f"{1e6 * (extra.clock_drift - k):+.2f} ppm",
                ]
            )
        rows.append(row)
    return rows


def dump_yaml(data: dict[str, Any]) -> str:
    """YAML with short lists on one line and keys in insertion order."""
    return yaml.dump(data, Dumper=_Dumper, sort_keys=False, default_flow_style=False, width=120)


def create_folder(folder: Path, label: str, fix: str) -> None:
    """Create ``folder`` (and its parents) or raise one clear sentence.

    Args:
        folder: the folder.
        label: how the message names it, e.g. ``"The output folder"``.
        fix: what the user should do, e.g. ``"give another output path"``.

    Raises:
        ConfigError: ``folder`` or a folder above it is a file, or it cannot be created.
    """
    try:
        Path(folder).mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError) as err:
        msg = f"{label} {folder} (or a folder above it) is a file; {fix}."
        raise ConfigError(msg) from err
    except OSError as err:
        msg = f"{label} {folder} cannot be created ({err.strerror}); {fix}."
        raise ConfigError(msg) from err


def _same_file(a: Path, b: Path) -> bool:
    """Whether two paths name the same file (also through links), or would."""
    try:
        if a.exists() and b.exists():
            return os.path.samefile(a, b)
    except OSError:
        pass
    return a.resolve() == b.resolve()


def input_files(path: Path) -> list[Path]:
    """The files an input consists of: itself, or every file in it when it is a folder."""
    if path.is_dir():
        return [p for p in sorted(path.rglob("*")) if p.is_file()]
    return [path]


def check_not_an_input(
    path: Path, inputs: Sequence[tuple[str, Path | None]], label: str | None = None
) -> None:
    """Refuse an output path that is, or would overwrite, an input.

    Args:
        path: the file about to be written.
        inputs: ``(what, path)`` of every input, e.g. ``("the input bag", bag)``; a folder (a
            ROS2 bag, split ROS1 bags) stands for every file in it; None entries are skipped.
        label: how the message names the output (default ``"The output <path>"``).

    Raises:
        ConfigError: ``path`` is one of the inputs or a file of an input folder.
    """
    path = Path(path)
    for what, given in inputs:
        if given is None:
            continue
        given = Path(given)
        for file in input_files(given):
            if _same_file(path, file):
                which = what if file == given else f"a file of {what} {given}"
                msg = (
                    f"{label or f'The output {path}'} is {which} ({file}); writing it would "
                    "destroy that input, give another output path with -o."
                )
                raise ConfigError(msg)


def prepare_output(
    path: Path, inputs: Sequence[tuple[str, Path | None]] = (), example: str = "calib.yaml"
) -> None:
    """Check, before a long run, that a result file can be written at ``path`` without
    overwriting an input (its folder is created if needed).

    Args:
        path: the file to be written.
        inputs: the inputs it must not overwrite (see :func:`check_not_an_input`).
        example: a file name the message suggests when ``path`` is a folder.

    Raises:
        ConfigError: ``path`` is an input or a file of an input folder, a folder, or its folder
            is a file, cannot be created or is not writable.
    """
    path = Path(path)
    check_not_an_input(path, inputs)
    if path.is_dir():
        msg = f"The output {path} is a folder; give a file name such as {path / example}."
        raise ConfigError(msg)
    create_folder(path.parent, "The output folder", "give another output path")
    if not os.access(path.parent, os.W_OK):
        msg = f"The output folder {path.parent} is not writable; give another output path."
        raise ConfigError(msg)


def write_text_atomic(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` through a temporary file and a rename."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as f:
            f.write(text)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp creates 0600; give the usual file mode
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
