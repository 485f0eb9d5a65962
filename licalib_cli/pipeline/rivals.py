"""Close rivals: effects that can stand in for each other.

A candidate that explains most of the leading candidate's score when freed with it can stand in
for it (:func:`rivals_of`); both are refitted and compared on the same data
(:func:`rival_delta_bic`, :func:`same_data_bic`, :func:`pick_rival`), and a pair that neither
score test separates is reported as not told apart (:func:`not_told_apart`,
:func:`refits_alike`). ``diagnose``'s forward selection (:mod:`licalib_cli.pipeline.diagnose`)
weighs its rivals so at every step, and offers a rival that lost to an effect kept once more
while the data still show it given the winner (:class:`CandidatePool`); ``calibrate``'s evident
effects (:mod:`licalib_cli.pipeline.evident`) weigh each refit's close rival."""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

from licalib_cli.config import CalibConfig
from licalib_cli.pipeline import CalibrationRun
from licalib_cli.pipeline.diagnosis_step import CANDIDATES, DiagnosisStep
from licalib_cli.pipeline.effect_models import sensor_samples, sum_of_squares, with_effects
from licalib_cli.pipeline.fitcheck import EFFECT_P_VALUE, EffectEvidence

__all__ = [
    "MAX_RIVALS",
    "RIVAL_FRACTION",
    "RIVAL_SHARE",
    "CandidatePool",
    "alike",
    "compare_rivals",
    "not_told_apart",
    "pick_rival",
    "refits_alike",
    "rival_delta_bic",
    "rivals_of",
    "same_data_bic",
    "stand_in_share",
    "weigh_refits",
]

logger = logging.getLogger(__name__)


def rival_delta_bic(
    a: DiagnosisStep, b: DiagnosisStep, kept: tuple[str, ...], cfg: CalibConfig, samples: int
) -> float:
    """BIC of ``b``'s model minus ``a``'s, both on the same data (:func:`same_data_bic`)."""
    assert a.after is not None and b.after is not None
    return same_data_bic(
        (a.effect, a.after, with_effects(cfg, (*kept, a.effect))),
        (b.effect, b.after, with_effects(cfg, (*kept, b.effect))),
        samples,
    )


def same_data_bic(
    a: tuple[str, CalibrationRun, CalibConfig],
    b: tuple[str, CalibrationRun, CalibConfig],
    samples: int,
) -> float:
    """BIC of the model of ``b`` minus that of ``a``, both on the same data; each given as
    ``(label, refit, its configuration)``.

    Each refit ends on its own data: its final association of points to surfels and its map
    (the planes estimated with the effect). Between two refits these differ by a few hundred
    points and by planes adapted to each effect, and the base model re-solved on them leaves
    sums of squares that differ by far more than the rivals do: on a shaking OS1-64 bag with
    150 ppm per-beam range scales, the base left 239 more on the range offset's data than on
    the range scale's, which alone made the offset's BIC change 234 lower, while on either
    refit's data the two effects left sums of squares within 12 of each other. Each model is
    therefore re-solved on the other's data (a few iterations from its own estimate, as the
    base model is) and the differences on the two data sets are averaged, so that neither
    keeps the advantage of the map that was built with it.
    """
    (name_a, run_a, cfg_a), (name_b, run_b, cfg_b) = a, b
    ss_a, _, k_a = sum_of_squares(run_a, cfg_a, refit=False)
    ss_b, _, k_b = sum_of_squares(run_b, cfg_b, refit=False)
    ss_b_on_a, _, _ = sum_of_squares(replace(run_a, state=run_b.state), cfg_b, refit=True)
    ss_a_on_b, _, _ = sum_of_squares(replace(run_b, state=run_a.state), cfg_a, refit=True)
    logger.info(
        "%s against %s on the same data: sum of squares %+.1f on the data of %s, "
        "%+.1f on those of %s.",
        name_b,
        name_a,
        ss_b_on_a - ss_a,
        name_a,
        ss_b - ss_a_on_b,
        name_b,
    )
    return 0.5 * ((ss_b_on_a - ss_a) + (ss_b - ss_a_on_b)) + (k_b - k_a) * math.log(max(samples, 2))


def weigh_refits(
    base: CalibrationRun,
    a: tuple[str, CalibrationRun, CalibConfig],
    b: tuple[str, CalibrationRun, CalibConfig],
) -> tuple[float, bool]:
    """A refit against its close rival's, each ``(effect, refit with it, its configuration)``,
    both refitted from ``base``: the BIC of ``b``'s model minus ``a``'s on the same data
    (:func:`same_data_bic`, the penalty at the larger of the two effects' sensors' sample counts
    in ``base``) and whether the recording does not tell them apart (:func:`refits_alike`)."""
    samples = max(sensor_samples(base, CANDIDATES[name][2]) for name in (a[0], b[0]))
    return same_data_bic(a, b, samples), refits_alike(a[:2], b[:2])


def not_told_apart(a: DiagnosisStep, b: DiagnosisStep) -> bool:
    """Whether the data show nothing that one of two refitted rivals explains and the other
    does not (:func:`refits_alike`)."""
    return refits_alike((a.effect, a.after), (b.effect, b.after))


def refits_alike(
    a: tuple[str, CalibrationRun | None], b: tuple[str, CalibrationRun | None]
) -> bool:
    """Whether two refits, each ``(effect, refit with it)``, leave nothing that one of the
    effects explains and the other does not: the score test of each on the refit with the
    other is not significant.

    Such a pair is one effect as far as the bag can tell (a per-beam range scale and a range
    offset in a room seen at ranges spread by a few tens of percent around their mean: a scale
    of 150 ppm differs from an offset by 0.1 mm over that spread), and naming one of them would
    state more than the data do. A pair missing either test counts as told apart.
    """

    def conditional_p(fit: CalibrationRun | None, name: str) -> float:
        if fit is None:
            return 0.0
        return next((float(e.score.p_value) for e in fit.effects if e.score.name == name), 0.0)

    (name_a, fit_a), (name_b, fit_b) = a, b
    return (
        conditional_p(fit_a, name_b) >= EFFECT_P_VALUE
        and conditional_p(fit_b, name_a) >= EFFECT_P_VALUE
    )


def compare_rivals(
    trials: list[DiagnosisStep], kept: tuple[str, ...], cfg: CalibConfig, samples: int
) -> list[DiagnosisStep]:
    """The trials of one step with :attr:`DiagnosisStep.rival_delta_bic` (each one's BIC minus
    the lowest of the others', on the same data, through the first) and
    :attr:`DiagnosisStep.not_told_apart` filled in; a single trial unchanged."""
    if len(trials) < 2:
        return trials
    relative = [0.0] + [rival_delta_bic(trials[0], t, kept, cfg, samples) for t in trials[1:]]
    out = []
    for i, t in enumerate(trials):
        others = [r for j, r in enumerate(relative) if j != i]
        apart = tuple(u.effect for u in trials if u is not t and not_told_apart(t, u))
        out.append(replace(t, rival_delta_bic=relative[i] - min(others), not_told_apart=apart))
    return out


def pick_rival(delta_bic: Sequence[float], rival_bic: Sequence[float]) -> int:
    """Index of the trial to name among rivals refitted at one step.

    ``delta_bic``: each trial's BIC change against the model without it (on its own data);
    ``rival_bic``: each trial's BIC on the same data relative to the others'
    (:attr:`DiagnosisStep.rival_delta_bic`). Among the trials that pay, the one with the
    lowest BIC on the same data; when none pays, the same among all (it is then not kept). The
    BIC changes against the base model decide whether an effect of the kind is worth adding,
    the comparison on the same data which one: the former differ between the rivals mostly
    through their data (see :func:`rival_delta_bic`).
    """
    paying = [i for i, d in enumerate(delta_bic) if d < 0.0] or list(range(len(delta_bic)))
    return min(paying, key=lambda i: rival_bic[i])


RIVAL_FRACTION = 0.3
"""A rival candidate (:func:`alike`) whose score per degree of freedom is at least this fraction
of the strongest one's is refitted as well; among those that pay, the lower BIC on the same data
wins (:func:`pick_rival`)."""

RIVAL_SHARE = 0.5
"""A candidate that explains at least this fraction of what a stand-in would explain of the
leading one's score, when freed with it (:attr:`~licalib_cli.pipeline.fitcheck.EffectEvidence.
explained_by`, :func:`stand_in_share`), can stand in for it and is its rival, whatever sensor it
belongs to. A candidate of the same sensor that explains little of it (an accelerometer scale,
0.14 of a misalignment's score on bag 1837 of ``bench_diagnose.py --first-seed 1800``) cannot be
what the leader stands for, whereas one of the other sensor can: there the gyro rotation
explained 0.83 of the accelerometer misalignment's score (3060 on 3 degrees of freedom, after
the elevations); with the extrinsic rotation re-estimated, a gyro triad rotated against the
accelerometer's looks like an accelerometer triad rotated against the gyro's."""

MAX_RIVALS = 1


def stand_in_share(best: EffectEvidence) -> float:
    """The share of ``best``'s score that the effect in the data would explain were ``best``
    only its echo: all but what noise leaves, about ``best``'s degrees of freedom, so
    ``1 - dof / statistic`` (0.88 for three coordinates at the significance level of
    :data:`EFFECT_P_VALUE`, 0.48 for 64 per-beam coordinates there, near 1 for a strong
    effect); 1 without a statistic."""
    statistic = float(best.statistic_alone)
    if not statistic > 0.0:
        return 1.0
    return min(max(1.0 - max(best.score.rank, 1) / statistic, 0.0), 1.0)


def alike(best: EffectEvidence, other: EffectEvidence) -> bool:
    """Whether ``other`` is a rival of ``best`` at a step: it explains at least
    :data:`RIVAL_SHARE` of what a stand-in would explain of ``best``'s score
    (:func:`stand_in_share`), whatever sensor it belongs to."""
    return best.explained_by.get(other.score.name, 0.0) >= RIVAL_SHARE * stand_in_share(best)


def rivals_of(best: EffectEvidence, options: Sequence[EffectEvidence]) -> list[EffectEvidence]:
    """The rivals refitted with ``best`` at a step: at most :data:`MAX_RIVALS` of ``options``
    :func:`alike` it with a score per degree of freedom (each on its own) at least
    :data:`RIVAL_FRACTION` of its, the one that explains most of ``best``'s score first."""
    per_dof = best.statistic_alone / max(best.score.rank, 1)
    rivals = [
        e
        for e in options
        if e is not best
        and alike(best, e)
        and e.statistic_alone / max(e.score.rank, 1) >= RIVAL_FRACTION * per_dof
    ]
    return sorted(
        rivals, key=lambda e: (-best.explained_by.get(e.score.name, 0.0), -e.statistic_alone)
    )[:MAX_RIVALS]


@dataclass
class CandidatePool:
    """Which candidates a step of the forward selection may try.

    A candidate is tried once; a rival that lost to an effect kept (:func:`pick_rival`) gets
    one more chance. It was compared with the model without that effect; once that is in, the
    question is a different one: whether the rival is there as well. On the paper's case
    (every intrinsic of both sensors off; a 15 s VLP-16 sinusoid) the elevations won against
    the vertical offsets and the azimuths against the horizontal offsets, the offsets were
    never tried again, and with everything else in their score tests were still 1748 and 4299
    on 15 degrees of freedom (the verdict WARN, 12.7 mm of translation sigma from the effects
    held). Such a rival stays on offer while its test, now conditional on the winner, is
    significant: a rival that only echoed the winner is not, and leaves the pool.

    Attributes:
        allowed: the candidates considered at all.
        tried: those refitted so far.
        second_chance: rivals that lost to an effect kept, each with that effect.
        retried: rivals given a second chance (at most one each).
    """

    allowed: tuple[str, ...]
    tried: set[str] = field(default_factory=set)
    second_chance: dict[str, str] = field(default_factory=dict)
    retried: set[str] = field(default_factory=set)

    def offered(
        self, effects: Sequence[EffectEvidence], p_value: float = EFFECT_P_VALUE
    ) -> tuple[list[EffectEvidence], list[EffectEvidence]]:
        """The candidates of a fit's ``effects`` a step may try (allowed, determined by the
        data, not tried or given a second chance) and those of them significant at
        ``p_value``. A rival given a second chance that is not significant leaves the pool."""
        options = [
            e
            for e in effects
            if e.score.name in self.allowed
            and e.score.rank > 0
            and (e.score.name not in self.tried or e.score.name in self.second_chance)
        ]
        significant = [e for e in options if e.score.p_value < p_value]
        shown = {e.score.name for e in significant}
        for name in [n for n in self.second_chance if n not in shown]:
            del self.second_chance[name]  # with its winner in, the data no longer show it
        return options, significant

    def refitting(self, name: str) -> str | None:
        """Record that ``name`` is refitted; the effect it lost to when this is its second
        chance, else None."""
        self.tried.add(name)
        return self.second_chance.pop(name, None)

    def decided(self, losers: Sequence[str], winner: str, kept: bool) -> None:
        """A step's rivals ``losers`` lost to ``winner``; when it was kept, each not retried
        before gets a second chance."""
        if not kept:
            return
        for name in losers:
            if name not in self.retried:
                self.second_chance[name] = winner
                self.retried.add(name)
