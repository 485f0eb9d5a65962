"""IMU priors a recording cannot check.

The sigmas of the extrinsic include the spread of every IMU intrinsic the model holds fixed,
known to within its prior (``model.imu_prior``: the residual error of the IMU's factory
calibration). They cover the error while the IMU is within that prior; whether it is, the data
can tell only for an effect large enough to show in the score test. When the recording would
name an effect only at several times its prior, it cannot check the prior, and a worse IMU
moves the extrinsic beyond its sigma unseen: a 10 s OS1-64 shake with accelerometer scale
errors of -4400 / -2900 / +700 ppm (the default prior 1000 ppm; this bag names the effect from
6600 ppm) passed 3.2 of its sigmas off in t_z. The checks say so beside the sigmas.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from licalib_cli.consistency.distributions import chi2_isf
from licalib_cli.consistency.power import detectable_rms, display_size
from licalib_cli.pipeline.fitcheck import EFFECT_P_VALUE, EffectEvidence

__all__ = [
    "HIDDEN_SHIFT",
    "UNCHECKED_FACTOR",
    "UncheckedPrior",
    "combined_unchecked_priors",
    "unchecked_priors",
    "unchecked_text",
]

F64 = npt.NDArray[np.float64]

logger = logging.getLogger(__name__)

UNCHECKED_FACTOR = 3.0
"""A prior is unchecked when the recording names its effect only from more than this many times
the prior's sigma (RMS per coordinate, along the direction it determines worst)."""

HIDDEN_SHIFT = 1.0
"""Only priors whose effect, at the size the recording names it from, would move some
coordinate of the extrinsic or time offset by at least this many of its reported sigmas are
listed (the others cannot hide an error that matters)."""


@dataclass(frozen=True)
class UncheckedPrior:
    """An IMU effect held fixed whose prior this recording cannot check.

    Attributes:
        effect: its name (``accel_scale``, ...).
        prior: the prior's sigma per coordinate, solver units.
        detectable: the RMS per coordinate from which the recording names the effect nine times
            in ten along the direction it determines worst, solver units; ``inf`` when some
            direction of it is not determined at all.
        hidden_shift: how far an effect of that size would move the extrinsic or time offset,
            in their reported sigmas (the largest over the coordinates; ``inf`` with
            ``detectable``).
    """

    effect: str
    prior: float
    detectable: float
    hidden_shift: float


def unchecked_priors(held: Sequence[EffectEvidence], sigma: F64) -> list[UncheckedPrior]:
    """The priors among ``held`` (IMU effects held fixed and not covered by their shift) that
    the recording cannot check (:data:`UNCHECKED_FACTOR`) and that could hide an error beyond
    the reported ``sigma`` (:data:`HIDDEN_SHIFT`), the one that could hide most first.

    An effect held at zero moves the estimate by its full shift map: one drawn from the prior
    by ``prior_reach``, one as large as the recording
    can hide by about that times ``detectable / prior``. The prior's spread in the sigmas
    (``prior_std``, the posterior's of data and prior) is smaller where the data carry some
    information: on a 10 s VLP-16 shake with the gyro-to-IMU rotation estimated, an
    accelerometer misalignment the recording names from 3.3 times its prior had a posterior
    spread of two thirds of its reach (0.53 against 0.78 of a sigma per prior sigma), and the
    hidden shift it gave (1.74 sigmas) fell short of what a misalignment of 1.5 times the prior
    did (2.1 sigmas; the diagnose benchmark's seed 4144).
    """
    out = []
    for e in held:
        u = _unchecked(
            e.score.name,
            e.prior_sigma,
            e.prior_reach,
            e.score.information,
            int(e.score.estimate.size),
            int(e.score.rank),
            sigma,
        )
        if u is not None:
            out.append(u)
    return sorted(out, key=lambda u: -u.hidden_shift)


def combined_unchecked_priors(
    segments: Sequence[Sequence[EffectEvidence]], sigma: F64, relative_rank: float = 1e-8
) -> list[UncheckedPrior]:
    """:func:`unchecked_priors` for several segments of one recording calibrated together, with
    ``sigma`` the joint sigmas: an effect of the rig shows in their information summed (as the
    combined score test, :func:`~licalib_cli.consistency.score.combined_score`), and its prior
    moves the joint estimate as much as in the best-determined segment (the smallest
    ``prior_std``). ``segments`` holds each segment's held effects that its sigmas do not cover
    by their shift; an effect missing from one is left out."""
    by_name: dict[str, list[EffectEvidence]] = {}
    for held in segments:
        for e in held:
            by_name.setdefault(e.score.name, []).append(e)
    out = []
    for name, effects in by_name.items():
        sizes = {e.score.profiled_information.shape for e in effects}
        if len(effects) != len(segments) or len(sizes) != 1 or 0 in next(iter(sizes)):
            continue
        info = np.sum([e.score.profiled_information for e in effects], axis=0)
        vals = np.linalg.eigvalsh(0.5 * (info + info.T))
        kept = vals[vals > relative_rank * max(float(vals.max(initial=0.0)), 1e-300)]
        u = _unchecked(
            name,
            min(e.prior_sigma for e in effects),
            np.min([e.prior_reach for e in effects], axis=0),
            kept,
            int(info.shape[0]),
            int(kept.size),
            sigma,
        )
        if u is not None:
            out.append(u)
    return sorted(out, key=lambda u: -u.hidden_shift)


def _unchecked(
    name: str,
    prior_sigma: float,
    reach: F64,
    information: npt.ArrayLike,
    coordinates: int,
    rank: int,
    sigma: F64,
) -> UncheckedPrior | None:
    finite = np.isfinite(sigma) & (sigma > 0.0)
    if prior_sigma <= 0.0 or not np.any(finite):
        return None
    if rank < coordinates:
        detectable = float("inf")
    else:
        threshold = chi2_isf(EFFECT_P_VALUE, max(rank, 1))
        detectable, _ = detectable_rms(threshold, coordinates, information)
    share = float(np.max(np.asarray(reach)[finite] / sigma[finite]))
    hidden = share * detectable / prior_sigma if share > 0.0 else 0.0
    logger.debug(
        "prior of %s: %.3g, named from %.3g, reach %.2f of a sigma, hidden shift %.2f",
        name,
        prior_sigma,
        detectable,
        share,
        hidden,
    )
    if detectable > UNCHECKED_FACTOR * prior_sigma and hidden >= HIDDEN_SHIFT:
        return UncheckedPrior(name, prior_sigma, detectable, hidden)
    return None


def unchecked_text(items: Sequence[UncheckedPrior]) -> str:
    """``, which this recording cannot check: ...`` for the sigmas' reason; empty without any."""
    if not items:
        return ""
    parts = []
    for u in items:
        prior, unit = display_size(u.effect, u.prior)
        if np.isfinite(u.detectable):
            size, _ = display_size(u.effect, u.detectable)
            parts.append(f"{u.effect} only from {size:.2g} {unit} RMS (prior {prior:.2g})")
        else:
            parts.append(f"{u.effect} not in every direction (prior {prior:.2g} {unit})")
    listed = parts[0] if len(parts) == 1 else ", ".join(parts[:-1]) + " and " + parts[-1]
    return (
        f", which this recording cannot check: it would show {listed}; the sigmas hold while "
        "the IMU is within those priors"
    )
