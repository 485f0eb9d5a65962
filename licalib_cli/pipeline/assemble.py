"""Assemble stage: the result file from the estimate, the checks and what the data were."""

from __future__ import annotations

import hashlib
import time
from pathlib import Path

import numpy as np
import numpy.typing as npt

from licalib_cli import __version__
from licalib_cli.config import CalibConfig, config_fingerprint
from licalib_cli.estimation import CalibrationState, beam_point_counts
from licalib_cli.inspection import gravity_turn_deg
from licalib_cli.io.frames import frame_ids
from licalib_cli.measurements import Recording
from licalib_cli.pipeline.checks import Checks
from licalib_cli.pipeline.initialise import InitialGuess
from licalib_cli.pipeline.round import extrinsic_of
from licalib_cli.pipeline.schedule import Fit
from licalib_cli.results import CalibrationResult, Extrinsic, vec3
from licalib_cli.sections import (
    ExtraTerms,
    FactoryExtrinsicSection,
    FitSection,
    InitializationSection,
    ModelInfo,
    Provenance,
    RecordingSection,
)

__all__ = ["assemble", "bag_fingerprint", "extra_terms", "recording_section"]

_NS = 1_000_000_000


def bag_fingerprint(path: Path) -> str:
    """A quick content fingerprint: sha256 of the sizes and first/last MiB of the bag files."""
    files = sorted(p for p in (path.rglob("*") if path.is_dir() else [path]) if p.is_file())
    h = hashlib.sha256()
    for f in files:
        size = f.stat().st_size
        h.update(f"{f.name}:{size}".encode())
        with f.open("rb") as fh:
            h.update(fh.read(1 << 20))
            if size > 2 << 20:
                fh.seek(-(1 << 20), 2)
                h.update(fh.read())
    return h.hexdigest()[:16]


def recording_section(bag: Path, rec: Recording) -> RecordingSection:
    """What data the calibration used (the sensors' frame ids read from the bag)."""
    frames = frame_ids(bag, (rec.imu_topic, rec.lidar_topic))
    rate = rec.clock_rate
    return RecordingSection(
        bag=str(bag),
        imu_topic=rec.imu_topic,
        lidar_topic=rec.lidar_topic,
        imu_samples=len(rec.imu),
        scans=len(rec.scans),
        duration_s=round((rec.end_ns - rec.start_ns) / _NS, 6),
        start_ns=int(rec.start_ns),
        clock_offset_s=round(rec.clock_offset_s, 9),
        lidar_clock_shift_s=round(rec.lidar_shift_ns / _NS, 9),
        imu_unreadable_messages=rec.imu_unreadable,
        lidar_unreadable_messages=rec.lidar_unreadable,
        imu_samples_dropped=rec.imu_samples_dropped,
        scans_skipped=rec.scans_skipped,
        imu_frame=frames.get(rec.imu_topic, ""),
        lidar_frame=frames.get(rec.lidar_topic, ""),
        gravity_turn_deg=_rounded(gravity_turn_deg(rec.imu.t_ns, rec.imu.accel), 3),
        clock_rate_ppm=None if rate is None else round(1e6 * rate.rate, 3),
        clock_rate_sigma_ppm=None if rate is None else round(1e6 * rate.sigma, 3),
    )


def _rounded(value: float | None, digits: int) -> float | None:
    return None if value is None else round(value, digits)


def factory_section(rec: Recording, calibrated: Extrinsic) -> FactoryExtrinsicSection | None:
    """The bag's factory extrinsic and the calibration's difference from it (None: none)."""
    f = rec.factory_extrinsic
    if f is None:
        return None
    factory = Extrinsic(rotation=f.rotation, translation=f.translation)
    return calibrated.factory_difference(
        factory, f"Ouster metadata on {f.topic}", f.sensor, f.cloud_frame
    )


def model_info(fit: Fit, cfg: CalibConfig) -> ModelInfo:
    """Which intrinsics were estimated, the gauge beam and the beams held for lack of points."""
    gauge = -1
    held: tuple[int, ...] = ()
    if cfg.model.lidar:
        counts = beam_point_counts(fit.inputs.lidar, fit.state.lidar_intrinsics.num_beams)
        enough = counts >= cfg.model.min_points_per_beam
        gauge = int(np.argmax(enough)) if np.any(enough) else -1
        held = tuple(int(b) for b in np.flatnonzero(~enough))
    spread = cfg.model.lidar_spread.configured(cfg.model.lidar)
    estimated = {*cfg.model.imu, *cfg.model.lidar}
    sizes = {str(b): float(v) for b, v in cfg.model.expected_size.items() if b in estimated}
    return ModelInfo(
        tuple(cfg.model.imu),
        tuple(cfg.model.lidar),
        gauge,
        held,
        spread,
        dict(sorted(sizes.items())),
    )


def extra_terms(state: CalibrationState, cfg: CalibConfig) -> ExtraTerms | None:
    """The estimates of the model's terms beyond the paper's (None when it holds none)."""
    imu, lidar = set(cfg.model.imu), set(cfg.model.lidar)
    if not ({"clock_drift", "gyro_bias_walk", "accel_bias_walk"} & imu or "point_time" in lidar):
        return None
    walks = [
        np.size(drift) // 3
        for name, drift in (
            ("gyro_bias_walk", state.gyro_bias_drift),
            ("accel_bias_walk", state.accel_bias_drift),
        )
        if name in imu
    ]
    pieces = max(walks, default=1)
    return ExtraTerms(
        reference_ns=state.t0_ns + round(state.t_ref_s * _NS),
        clock_drift=state.time_drift if "clock_drift" in imu else None,
        gyro_bias_walk=_walk(state.gyro_bias_drift) if "gyro_bias_walk" in imu else None,
        accel_bias_walk=_walk(state.accel_bias_drift) if "accel_bias_walk" in imu else None,
        point_time=state.point_time_scale if "point_time" in lidar else None,
        bias_walk_pieces=pieces if pieces > 1 else None,
    )


def _walk(drift: npt.ArrayLike) -> tuple[float, ...]:
    """A bias walk's drifts, piece-major (``x, y, z`` of each piece)."""
    return tuple(float(v) for v in np.asarray(drift, dtype=np.float64).reshape(-1))


def assemble(
    bag: Path,
    rec: Recording,
    guess: InitialGuess,
    fit: Fit,
    checks: Checks,
    cfg: CalibConfig,
) -> CalibrationResult:
    """The result file's content (schema v1 with its typed sections)."""
    state = fit.state
    last = fit.rounds[-1]
    c = fit.last_change
    hand_eye = guess.hand_eye
    return CalibrationResult(
        extrinsic=extrinsic_of(state),
        imu_intrinsics=state.imu_intrinsics,
        lidar_intrinsics=state.lidar_intrinsics if cfg.model.lidar else None,
        model=model_info(fit, cfg),
        intrinsics_uncertainty=checks.intrinsics_uncertainty,
        gravity_G=vec3(round(float(x), 6) for x in state.gravity_G),
        uncertainty=checks.uncertainty,
        observability=checks.observability,
        verdict=checks.verdict,
        consistency=checks.consistency,
        initialization=InitializationSection(
            rotation_source=guess.rotation_source,
            time_offset_source=guess.time_offset_source,
            coarse_time_offset_s=round(guess.time_offset_s, 9),
            angular_speed_correlation=None
            if np.isnan(guess.correlation)
            else round(guess.correlation, 4),
            hand_eye_conditioning=None
            if hand_eye is None
            else float(f"{hand_eye.conditioning:.4g}"),
            translation_source=guess.translation_source,
            initial_translation_m=vec3(round(float(x), 6) for x in guess.t_imu_lidar),
        ),
        fit=FitSection(
            rounds=len(fit.rounds),
            converged=bool(fit.converged),
            last_change_translation_m=float(c.translation_m),
            last_change_rotation_deg=float(c.rotation_deg),
            last_change_time_offset_s=float(c.time_offset_s),
            points=last.points,
            surfels=last.surfels,
            point_rms_m=round(last.rms_m, 6),
            variance_factor=float(f"{fit.report.variance_factor:.4g}"),
        ),
        recording=recording_section(bag, rec),
        factory_extrinsic=factory_section(rec, extrinsic_of(state)),
        extra_terms=extra_terms(state, cfg),
        provenance=Provenance(
            licalib_version=__version__,
            bag_fingerprint=bag_fingerprint(bag),
            created_utc=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
            config_fingerprint=config_fingerprint(cfg),
        ),
    )
