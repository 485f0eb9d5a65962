"""Read stage: the segment of the bag as measurements, the beams' nominal elevations and the
sensors' noise."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import numpy.typing as npt

from licalib_cli.config import CalibConfig
from licalib_cli.consistency import imu_noise, line_range_noise, range_noise
from licalib_cli.geometry.vectors import norms
from licalib_cli.inspection import (
    ACCELEROMETER_FRAME_MODEL,
    GRAVITY_TURN_FOR_IMU_DEG,
    gravity_turn_deg,
    tilt_advice,
)
from licalib_cli.io.reader import read_segment
from licalib_cli.io.window import MIN_SEGMENT_S
from licalib_cli.measurements import ImuSamples, Recording
from licalib_cli.pipeline.knot_spacing import KnotSpacing, choose_knot_spacing, with_knot_spacing
from licalib_cli.pipeline.points import nominal_elevations
from licalib_cli.pipeline.scan_pattern import (
    SPINNING,
    ScanPattern,
    check_model,
    elevation_beams,
    scan_pattern,
)
from licalib_cli.pipeline.settings import NoiseLevels

__all__ = [
    "MIN_SEGMENT_S",
    "Segment",
    "measure_noise",
    "read",
    "read_recording",
    "tilt_warning",
]

logger = logging.getLogger(__name__)

_NS = 1_000_000_000

_NOISE_SCANS = 20
"""Scans used to measure the range noise (spread over the segment)."""


@dataclass(frozen=True)
class Segment:
    """What the read stage produces.

    Attributes:
        recording: the segment's IMU samples and scans on one clock.
        nominal_elevation: (B,) nominal elevation of each beam, rad.
        noise: the noise the fit is weighted with.
        pattern: what the clouds' beam field means (a non-repetitive scanner's points carry
            elevation bins as their beams: :func:`.scan_pattern.elevation_beams`).
        knots: the trajectory splines' knot spacing (the config's, or chosen from the IMU's
            signals: :mod:`.knot_spacing`); None: the config's as it stands.
    """

    recording: Recording
    nominal_elevation: npt.NDArray[np.float64]
    noise: NoiseLevels
    pattern: ScanPattern = SPINNING
    knots: KnotSpacing | None = None


def read(bag: Path, cfg: CalibConfig) -> Segment:
    """The configured segment of ``bag``, its beam table and its noise.

    Raises:
        BagError, TopicError, DataError, TimestampError: unreadable or unusable input.
        ConfigError: the configured beam table does not cover the data's beams, or the model
            estimates per-beam intrinsics of a non-repetitive scanner.
        ExcitationError: the segment is shorter than :data:`MIN_SEGMENT_S`.
    """
    rec = read_recording(bag, cfg)
    warning = tilt_warning(rec.imu, cfg.model.imu)
    if warning:
        logger.warning(warning)
    knots = choose_knot_spacing(rec.imu, cfg)
    (logger.info if knots.chosen else logger.debug)(knots.describe())
    # the IMU noise is measured with the splines' spacing
    cfg = with_knot_spacing(cfg, knots.spacing_s)
    pattern = scan_pattern(rec.layout.elevation_spread_deg, cfg)
    if not pattern.non_repetitive:
        phi = nominal_elevations(rec.scans, cfg)
        return Segment(rec, phi, measure_noise(rec, cfg, phi.shape[0]), pattern, knots)
    check_model(cfg, pattern)
    lines = 1 + max(
        (int(s.ring.max()) for s in rec.scans if s.ring is not None and len(s)), default=0
    )
    noise = measure_noise(rec, cfg, lines, along_lines=True)
    scans, phi = elevation_beams(rec.scans)
    binned = replace(rec, scans=scans)
    logger.info(
        "The LiDAR is a non-repetitive scanner (%s): its points are grouped into %d elevation "
        "bins as beams, and it has no per-beam intrinsics.",
        pattern.evidence(),
        phi.shape[0],
    )
    per_bin = np.full(phi.shape[0], noise.range_measured_m)
    return Segment(binned, phi, replace(noise, range_sigma_per_beam=per_bin), pattern, knots)


def tilt_warning(imu: ImuSamples, model_imu: Sequence[str]) -> str | None:
    """A warning before the fit when the model estimates the accelerometer's frame
    (``gyro_rotation``, ``accel_misalignment``) and gravity turned less than
    :data:`~licalib_cli.inspection.GRAVITY_TURN_FOR_IMU_DEG` in the IMU frame over the segment
    (:func:`~licalib_cli.inspection.gravity_turn_deg`); None otherwise. The checks after the fit
    say whether the frame was in fact left undetermined."""
    blocks = [b for b in ACCELEROMETER_FRAME_MODEL if b in model_imu]
    if not blocks:
        return None
    turn = gravity_turn_deg(imu.t_ns, imu.accel)
    if turn is None or turn >= GRAVITY_TURN_FOR_IMU_DEG:
        return None
    return (
        f"Gravity turned only {turn:.0f} deg RMS in the IMU frame over this segment: with "
        f"{' and '.join(blocks)} estimated, the accelerometer's frame may trade off with the "
        f"extrinsic rotation (the checks after the fit say whether it did); {tilt_advice(blocks)}."
    )


def read_recording(bag: Path, cfg: CalibConfig) -> Recording:
    """The configured segment of ``bag`` (IMU samples and scans on one clock).

    Raises:
        BagError, TopicError, DataError, TimestampError: unreadable or unusable input.
        ExcitationError: the segment (or the time both sensors cover) is shorter than
            :data:`MIN_SEGMENT_S` (the reader's rule, shared with ``licalib info``).
    """
    rec = read_segment(Path(bag), cfg)
    logger.info(
        "Read %d IMU samples and %d scans (%.1f s).",
        len(rec.imu),
        len(rec.scans),
        (rec.end_ns - rec.start_ns) / _NS,
    )
    return rec


def measure_noise(
    rec: Recording, cfg: CalibConfig, num_beams: int, *, along_lines: bool = False
) -> NoiseLevels:
    """The noise the fit is weighted with: the config's where given, else measured.

    The IMU noise is what a free spline with the calibration's knot spacing leaves of each axis
    (:func:`licalib_cli.consistency.imu_noise`); the range noise comes from second differences
    along each beam (:func:`licalib_cli.consistency.range_noise`), or with ``along_lines``
    along each line's point order (a non-repetitive scanner's lines:
    :func:`licalib_cli.consistency.line_range_noise`). Both are measured even when the config
    gives values (the checks report them side by side).
    """
    t_s = (rec.imu.t_ns - rec.imu.t_ns[0]) * 1e-9
    rate = (len(rec.imu) - 1) / max(float(t_s[-1]), 1e-9)
    dt = cfg.spline.spacing_s
    gyro_data = imu_noise(t_s, rec.imu.gyro, dt, 1).sigma
    accel_data = imu_noise(t_s, rec.imu.accel, dt, 2).sigma
    step = max(1, len(rec.scans) // _NOISE_SCANS)
    scans = [s for s in rec.scans[::step] if s.ring is not None and len(s)]
    if scans:
        xyz = np.concatenate([s.xyz for s in scans])
        index = np.concatenate([np.full(len(s), i) for i, s in enumerate(scans)])
        beam = np.concatenate([np.asarray(s.ring, dtype=np.int64) for s in scans])
        if along_lines:
            t_ns = np.concatenate([s.t_ns for s in scans])
            rn = line_range_noise(index, beam, t_ns, xyz, num_beams).sigma
        else:
            azimuth = np.arctan2(xyz[:, 1], xyz[:, 0])
            rn = range_noise(index, beam, azimuth, norms(xyz), num_beams).sigma
    else:
        rn = np.full(num_beams, np.nan)
    range_data = float(np.nanmedian(rn)) if np.any(np.isfinite(rn)) else float("nan")

    n = cfg.noise
    root = float(np.sqrt(rate))
    if n.gyro_noise_density is not None:
        gyro, g_src = np.full(3, n.gyro_noise_density * root), "config"
    else:
        gyro, g_src = gyro_data, "data"
    if n.accel_noise_density is not None:
        accel, a_src = np.full(3, n.accel_noise_density * root), "config"
    else:
        accel, a_src = accel_data, "data"
    if n.range_sigma_m is not None:
        rng, r_src = float(n.range_sigma_m), "config"
    elif np.isfinite(range_data):
        rng, r_src = range_data, "data"
    else:
        rng, r_src = 0.02, "default"
    # A measured noise can be zero only for noise-free (simulated) data: keep a floor so that
    # the weights stay finite.
    gyro = np.maximum(np.nan_to_num(gyro, nan=1e-3), 1e-6)
    accel = np.maximum(np.nan_to_num(accel, nan=1e-2), 1e-5)
    rng = max(rng, 1e-4)
    logger.info(
        "Noise: gyro %s rad/s (%s), accelerometer %s m/s^2 (%s), range %.4f m (%s; measured "
        "%.4f m).",
        np.array2string(gyro, precision=5),
        g_src,
        np.array2string(accel, precision=4),
        a_src,
        rng,
        r_src,
        range_data,
    )
    return NoiseLevels(
        gyro_sigma=gyro,
        accel_sigma=accel,
        range_sigma_m=rng,
        gyro_source=g_src,
        accel_source=a_src,
        range_source=r_src,
        range_sigma_per_beam=rn,
        gyro_measured=gyro_data,
        accel_measured=accel_data,
        range_measured_m=range_data,
    )
