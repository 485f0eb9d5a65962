"""Inflation stage: the sigmas to report, the solver's enlarged to cover what the checks found.

The solver's sigmas (times each coordinate's factor for the map planes' own uncertainty) are
enlarged by the root of the largest chi-square per sample of the sensors, by half the
disagreement of the two halves of the segment beyond its expected spread
(:func:`split_floor`), by the shift a fixed effect would cause and the spread its estimate
would add (a material one, or one the data hint at: :data:`COVER_P_VALUE`), by what the IMU
intrinsics held to their priors add (:func:`prior_variance`), and by the last round's change
when the rounds settled only to within their jitter. :mod:`licalib_cli.pipeline.checks` turns
the findings into the verdict and says which of these applied.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from licalib_cli.pipeline.fitcheck import EFFECT_P_VALUE, EffectEvidence
from licalib_cli.pipeline.schedule import Change, Fit
from licalib_cli.pipeline.split import SplitResult
from licalib_cli.pipeline.unchecked_priors import prior_owner, unchecked_priors, unchecked_text
from licalib_cli.sections import SensorCheck, p_is

__all__ = [
    "COVER_P_VALUE",
    "effect_is_material",
    "effect_to_cover",
    "inflate",
    "largest_prior",
    "moves_extrinsic",
    "prior_variance",
    "split_floor",
    "uncovered",
    "with_change",
]

F64 = npt.NDArray[np.float64]

COVER_P_VALUE = 1e-3
"""The sigmas also cover the shift of a fixed effect the data hint at: one with a score test
below this p-value, though not significant at :data:`~licalib_cli.pipeline.fitcheck.
EFFECT_P_VALUE` (the stricter level that names an effect; a sigma enlarged by a false alarm costs
less than a misnamed effect). On clean data about one run in 60 enlarges a sigma this way
(16 effects tested)."""


def effect_is_material(e: EffectEvidence, raw_sigma: F64) -> bool:
    """Selected (significant beyond the stronger effects), or measured apart from the fit
    (:attr:`~licalib_cli.pipeline.fitcheck.EffectEvidence.measured`), and moving some extrinsic
    coordinate by more than its sigma."""
    shown = e.measured or (e.selected and e.score.p_value < EFFECT_P_VALUE)
    return shown and moves_extrinsic(e, raw_sigma)


def effect_to_cover(e: EffectEvidence, raw_sigma: F64) -> bool:
    """Hinted at (p below :data:`COVER_P_VALUE`, which every material effect is) or measured
    apart from the fit, and moving some extrinsic coordinate by more than its sigma: the sigmas
    cover its shift."""
    return (e.measured or e.score.p_value < COVER_P_VALUE) and moves_extrinsic(e, raw_sigma)


def uncovered(effects: Sequence[EffectEvidence], raw_sigma: F64) -> list[EffectEvidence]:
    """The ``effects`` whose shift the sigmas do not cover (:func:`effect_to_cover`): held
    fixed, known only to within their priors, or taken as exact."""
    return [e for e in effects if not effect_to_cover(e, raw_sigma)]


def largest_prior(effects: Sequence[EffectEvidence], raw_sigma: F64) -> str | None:
    """The block whose prior (``model.imu_prior``, ``model.lidar_prior``) adds most to the
    sigmas; None when no prior adds anything."""
    held = uncovered(effects, raw_sigma)
    finite = np.isfinite(raw_sigma) & (raw_sigma > 0.0)
    size = [float(np.max(np.where(finite, e.prior_std / raw_sigma, 0.0))) for e in held]
    if not size or max(size) <= 0.0:
        return None
    return held[int(np.argmax(size))].score.name


def prior_variance(effects: Sequence[EffectEvidence], raw_sigma: F64) -> F64:
    """(7,) variance the priors add to the sigmas (``model.imu_prior``, ``model.lidar_prior``):
    an effect the data do not show is still only known to within its prior (a sensor's factory
    calibration; the clock drift, the rate of the stamps against the record times), and its
    posterior spread moves the estimate too; a covered effect adds its shift instead.

    Per coordinate, the larger of the blocks' spreads summed one by one and what they add held
    at zero all together (:attr:`~licalib_cli.pipeline.fitcheck.EffectEvidence.
    joint_prior_var`) plus the square of the move to their joint posterior mean: held at zero,
    the blocks bias the estimate by their true size carried into it, which given the data lies
    about that move away, within that spread. Each alone moved the roll of a sinusoid with the
    simulator's random IMU intrinsics (each 1-2 times its prior) by at most 0.02 deg, together
    by 0.048 deg (joint score 225 on 15), three of its sigmas. The move counts whatever the
    blocks' joint score test says: left out below significance, the sigmas covered the error
    of a linear problem whose held block is drawn from its prior only as a standard deviation
    1.1 to 1.75 times too small (the more so the better the data determine the block beside its
    prior); with it, to within 2 %."""
    out = np.zeros(7)
    joint = np.zeros(7)
    for e in effects:
        held = np.asarray(e.joint_prior_var, dtype=np.float64)
        held = held + np.asarray(e.joint_prior_shift, dtype=np.float64) ** 2
        joint = np.maximum(joint, held)
        if not effect_to_cover(e, raw_sigma):
            out += e.prior_std**2
    return np.maximum(out, joint)


def moves_extrinsic(e: EffectEvidence, raw_sigma: F64) -> bool:
    """Estimating the effect would move some extrinsic coordinate by more than its sigma."""
    ratio = np.abs(e.shift) / np.where(np.isfinite(raw_sigma), raw_sigma, np.inf)
    return bool(np.nanmax(ratio) > 1.0)


def inflate(
    raw: F64,
    sensors: tuple[SensorCheck, ...],
    effects: list[EffectEvidence],
    split: SplitResult,
    fit: Fit,
) -> tuple[F64, tuple[str, ...]]:
    """The sigmas to report: the solver's, enlarged to cover what the checks found.

    Returns:
        ``(sigma (7,), reasons)`` with one sentence per enlargement applied (none for a
        chi-square factor that would print as 1.00).
    """
    sigma = raw.copy()
    why: list[str] = []
    chi = max((s.chi2_per_sample for s in sensors), default=1.0)
    if chi > 1.0:
        sigma = sigma * np.sqrt(chi)
        worst = max(sensors, key=lambda s: s.chi2_per_sample)
        shown = f"{np.sqrt(chi):.2f}"
        if shown != "1.00":  # a factor that prints as 1.00 is not worth a line
            why.append(
                f"times {shown}, the root of the {worst.sensor} residuals' chi-square per sample"
            )
    if split.ran:
        grown = np.maximum(sigma, split_floor(split))
        if np.any(grown > sigma * (1 + 1e-9)):
            why.append(
                "to at least half the difference between the two halves of the segment beyond "
                "its expected spread"
            )
        sigma = grown
    for e in effects:
        # Held fixed, the effect biases the estimate by about its shift; freed, the estimate
        # would move by the shift and its sigma grow by shift_std. Both are added, so that
        # sigma covers the estimate either way (3 sigma covers |shift| + 3 times the sigma the
        # estimate would have with the effect free, once |shift| is at least 0.75 of it).
        if effect_to_cover(e, raw):
            sigma = np.sqrt(sigma**2 + e.shift**2 + e.shift_std**2)
            hint = (
                ""
                if effect_is_material(e, raw)
                else f", which the data hint at ({p_is(e.score.p_value, 1)})"
            )
            if e.refitted:
                why.append(f"by the move of a refit with {e.score.name} estimated")
            elif e.measured:
                why.append(f"by the shift of {e.score.name} held at zero, at its measured size")
            else:
                why.append(f"by the shift estimating {e.score.name} would cause{hint}")
    prior_var = prior_variance(effects, raw)
    if np.any(prior_var > 0.0):
        grown = np.sqrt(sigma**2 + prior_var)
        finite = np.isfinite(sigma) & (sigma > 0.0)
        factor = float(np.max(grown[finite] / sigma[finite])) if np.any(finite) else 1.0
        most = largest_prior(effects, raw)
        known = (
            ", known to within the rate of its stamps against the record times"
            if most == "imu_clock_drift"
            else ""
        )
        what, where = prior_owner([e.score.name for e in effects if e.prior_sigma > 0.0])
        why.append(
            f"by the {what} held fixed, each known to within {where} "
            f"(times up to {factor:.2f}; most from {most}{known})"
            + unchecked_text(unchecked_priors(uncovered(effects, raw), grown))
        )
        sigma = grown
    if fit.jitter:
        sigma = with_change(sigma, fit.last_change)
        why.append("by the last round's change (the rounds settled only to within it)")
    return sigma, tuple(why)


def split_floor(split: SplitResult) -> F64:
    """(7,) the least sigma the two halves' difference ``d`` supports: half its excess over
    the spread ``sigma_d`` it has without any change between the halves,
    ``0.5 sqrt(max(d^2 - sigma_d^2, 0))``; zero where the halves do not both determine the
    coordinate.

    Each half's estimate errs by a common part (the whole segment's error) and its own; a
    difference within its expected spread says nothing the solver's sigma does not already
    hold, while one beyond it is a change over the recording the whole estimate averages, of
    which half stays as its error. :func:`inflate` applies it whether or not the halves disagree
    as a whole (``p < SPLIT_HALF_P``): halves that agree can still differ beyond their spread in
    one coordinate, and that excess is what covers an effect the model lacks and the data do
    not show (an accelerometer scale below what a shake shows moved t_z 3.4 sigma with it
    left out).
    """
    d, sd = np.asarray(split.difference), np.asarray(split.sigma)
    known = np.isfinite(sd)
    excess = np.where(known, d**2 - np.where(known, sd, 0.0) ** 2, 0.0)
    return 0.5 * np.sqrt(np.maximum(excess, 0.0))


def with_change(sigma: F64, c: Change) -> F64:
    """The (7,) sigmas with a round's change of the extrinsic added in quadrature."""
    jitter = np.array([c.translation_m] * 3 + [np.radians(c.rotation_deg)] * 3 + [c.time_offset_s])
    return np.sqrt(sigma**2 + jitter**2)
