"""Read stage: the trajectory splines' knot spacing, chosen from the IMU's signals.

The splines must follow the motion: the gyro reads the first derivative of the rotation
spline and the accelerometer the second of the position spline, so a spacing too coarse for
the motion leaves part of the signal unexplained and biases the fit. A spacing finer than the
motion needs only adds coordinates: the banded systems of every round grow with the knots.

Each IMU axis is fitted on its own with the functions a spline of a candidate spacing can
produce for it (:func:`licalib_cli.consistency.imu_noise`, the fit the noise is measured with).
What the fit leaves is the sensor noise plus what the spacing cannot follow. The spacing kept is
the coarsest candidate, from ``spline.min_knot_spacing_s`` up to ``spline.max_knot_spacing_s``,
whose residual variance on every axis of both sensors stays within :data:`EXCESS` of the finest
candidate's: a smooth sinusoid or a slow walk gets the coarsest, a hand-held shake keeps the
finest. Ovren and Forssen ("Spline Error Weighting for Robust Visual-Inertial Fusion", CVPR
2018) choose a spline's knot spacing from its signal's spectrum with the same aim.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from licalib_cli.config import CalibConfig
from licalib_cli.consistency import imu_noise
from licalib_cli.measurements import ImuSamples

__all__ = ["EXCESS", "STEP", "KnotSpacing", "choose_knot_spacing", "with_knot_spacing"]

logger = logging.getLogger(__name__)

EXCESS = 0.05
"""Largest relative increase of an IMU axis's residual variance, against the finest spacing,
that a coarser spacing may cost (a twentieth of the noise variance: the part of the motion it
cannot follow stays below a quarter of the noise's standard deviation)."""

STEP = 1.25
"""Ratio between consecutive candidate spacings."""


@dataclass(frozen=True)
class KnotSpacing:
    """The knot spacing of a segment and how it was chosen.

    Attributes:
        spacing_s: the spacing the splines use, s.
        chosen: whether the data chose it (``spline.knot_spacing_s`` unset) or the config
            gave it.
        candidates_s: the spacings tried, finest first (empty when the config gave one).
        excess: per candidate, the largest relative increase of an axis's residual variance
            over the finest candidate's (gyro and accelerometer together).
    """

    spacing_s: float
    chosen: bool
    candidates_s: tuple[float, ...] = ()
    excess: tuple[float, ...] = ()

    def describe(self) -> str:
        """One sentence for the log."""
        if not self.chosen:
            return f"Trajectory knots every {self.spacing_s:g} s (spline.knot_spacing_s)."
        tried = ", ".join(
            f"{1e3 * c:.0f} ms +{100 * e:.1f} %"
            for c, e in zip(self.candidates_s, self.excess, strict=True)
        )
        return (
            f"Trajectory knots every {1e3 * self.spacing_s:.0f} ms: the coarsest spacing whose "
            f"splines follow the IMU's readings within {100 * EXCESS:.0f} % of the finest's "
            f"residual variance ({tried})."
        )


def candidate_spacings(finest_s: float, coarsest_s: float) -> tuple[float, ...]:
    """Spacings from ``finest_s`` up by factors of :data:`STEP`, ending at ``coarsest_s``."""
    out = [finest_s]
    while out[-1] * STEP < coarsest_s * (1 - 1e-9):
        out.append(out[-1] * STEP)
    if coarsest_s > out[-1] * (1 + 1e-9):
        # the coarsest itself, in place of a finer candidate it would follow too closely
        if len(out) > 1 and coarsest_s < out[-1] * STEP**0.5:
            out[-1] = coarsest_s
        else:
            out.append(coarsest_s)
    return tuple(out)


def choose_knot_spacing(imu: ImuSamples, cfg: CalibConfig) -> KnotSpacing:
    """The knot spacing of the segment whose IMU samples are ``imu``.

    The config's ``spline.knot_spacing_s`` when given; else the coarsest candidate within
    :data:`EXCESS` (module docstring); on a segment too short to compare them, the finest.
    The reader has checked that the IMU rate allows the finest (``spline.spacing_s``).
    """
    spline = cfg.spline
    if spline.knot_spacing_s is not None:
        return KnotSpacing(spline.knot_spacing_s, chosen=False)
    t_s = np.asarray((imu.t_ns - imu.t_ns[0]) * 1e-9, dtype=np.float64)
    finest, coarsest = spline.min_knot_spacing_s, spline.max_knot_spacing_s
    candidates = candidate_spacings(finest, coarsest)
    if len(candidates) == 1 or t_s.shape[0] < 20 or t_s[-1] < 4 * coarsest:
        return KnotSpacing(finest, chosen=True, candidates_s=(finest,), excess=(0.0,))

    def variances(spacing: float) -> np.ndarray:
        gyro = imu_noise(t_s, imu.gyro, spacing, 1).sigma
        accel = imu_noise(t_s, imu.accel, spacing, 2).sigma
        return np.concatenate([gyro, accel]) ** 2

    reference = variances(candidates[0])
    ok = np.isfinite(reference) & (reference > 0)
    kept, tried, excess = candidates[0], [candidates[0]], [0.0]
    for spacing in candidates[1:]:  # a handful of spacings, each one sparse fit per axis
        rise = float(np.max(variances(spacing)[ok] / reference[ok] - 1.0)) if ok.any() else 0.0
        tried.append(spacing)
        excess.append(rise)
        if not rise <= EXCESS:  # a NaN stops the search too
            break
        kept = spacing
    return KnotSpacing(kept, chosen=True, candidates_s=tuple(tried), excess=tuple(excess))


def with_knot_spacing(cfg: CalibConfig, spacing_s: float) -> CalibConfig:
    """``cfg`` with ``spline.knot_spacing_s`` the segment's (what every fit of it uses and the
    resolved config gives); ``cfg`` itself when it already says so."""
    if cfg.spline.knot_spacing_s == spacing_s:
        return cfg
    spline = cfg.spline.model_copy(update={"knot_spacing_s": spacing_s})
    return cfg.model_copy(update={"spline": spline})
