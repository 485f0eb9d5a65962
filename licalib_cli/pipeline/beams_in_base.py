"""The base model when it cannot hold a map (``licalib diagnose``, step 1).

A spinning LiDAR whose beams disagree by centimetres (per-beam range offsets from an old or
generic beam table) blurs the map from the first round on; the base model, which holds the beams
at nominal, then loses its planes (:class:`~licalib_cli.errors.MapLost`), or ends on the few
points left on a few of them (:func:`~licalib_cli.pipeline.lost_map.collapsed_map`), and leaves
no fit whose residuals a score test could read. The beams' intrinsics then join the base model
all at once
(``calibrate --intrinsics lidar`` with the candidates allowed), and the check backwards decides
which of them the data need: each block in turn is reset to nominal on the fit's data and the
rest re-solved (:func:`~licalib_cli.pipeline.backward.deltas_without`); the block whose removal
lowers the BIC most is dropped and the model refitted without it, until no removal pays or the
fit without a block loses its map again, either way (that block is needed). What is left is
named as found, with its BIC change, before the forward selection tests the other candidates on
that fit.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace

from licalib_cli.config import CalibConfig
from licalib_cli.errors import ExcitationError
from licalib_cli.pipeline import CalibrationRun, Prepared, Timer, fit_and_check
from licalib_cli.pipeline.backward import deltas_without
from licalib_cli.pipeline.effect_models import with_effects, without_effect
from licalib_cli.pipeline.lost_map import collapsed_map
from licalib_cli.progress import Progress

__all__ = ["BeamsInBase", "base_with_beams"]

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class BeamsInBase:
    """The beams' intrinsics that joined a base model which lost its map.

    Attributes:
        reason: how the base fit lost its map (its error, or how far the map collapsed).
        freed: the per-beam candidates freed with the base model.
        kept: those the data need, in the order freed.
        delta_bic: per block freed, the BIC with it minus without it on the data of the fit it
            was tested on (negative: it pays; a dropped block's is its positive change).
        lost_without: a block whose removal lost the map again (kept without a BIC; empty if
            none).
    """

    reason: str
    freed: tuple[str, ...]
    kept: tuple[str, ...]
    delta_bic: dict[str, float]
    lost_without: str = ""

    @property
    def dropped(self) -> tuple[str, ...]:
        """The blocks freed that the data do not need."""
        return tuple(e for e in self.freed if e not in self.kept)


def base_with_beams(
    prepared: Prepared,
    cfg: CalibConfig,
    beams: tuple[str, ...],
    lost: str,
    progress: Progress,
    timer: Timer,
) -> tuple[CalibrationRun, BeamsInBase]:
    """Fit the base model with the beams' intrinsics ``beams`` and keep those the data need.

    Args:
        prepared: the segment, noise and initial guess (its state holds the beams at nominal).
        cfg: the base model's configuration.
        beams: the per-beam candidates allowed (at least one).
        lost: how the base fit lost its map (its error, or
            :func:`~licalib_cli.pipeline.lost_map.collapsed_map`'s sentence); its part before the
            first colon says where.
        progress: progress sink.
        timer: stage timer.

    Returns:
        The fit with the blocks kept, and what was freed, kept and dropped.

    Raises:
        ExcitationError: the map is lost with the beams free too.
    """
    logger.warning(
        "Diagnose: the base model lost its map (%s); the beams' intrinsics (%s) join it, and "
        "each is kept only if the data need it.",
        lost.split(":")[0],
        ", ".join(beams),
    )
    nominal = prepared.guess.state
    run = fit_and_check(
        prepared, prepared.guess, with_effects(cfg, beams), progress, timer, rivals=True
    )
    kept, lost_without = beams, ""
    deltas: dict[str, float] = {}
    while kept:
        tested = deltas_without(run, kept, kept, nominal, cfg)
        deltas.update(tested)
        effect = max(tested, key=lambda e: tested[e])
        if not tested[effect] > 0.0:
            break
        rest = tuple(e for e in kept if e != effect)
        logger.info(
            "Diagnose: the base model does not need %s (BIC %+.1f without it); refit without it.",
            effect,
            -tested[effect],
        )
        start = replace(prepared.guess, state=without_effect(run.state, effect, nominal))
        try:
            refit: CalibrationRun | None = fit_and_check(
                prepared, start, with_effects(cfg, rest), progress, timer, warm=True, rivals=True
            )
        except ExcitationError:
            refit = None
        if refit is None or collapsed_map(refit.rounds) is not None:
            logger.info("Diagnose: without %s the map is lost again: it is kept.", effect)
            lost_without = effect
            break
        run, kept = refit, rest
    return run, BeamsInBase(
        reason=lost,
        freed=beams,
        kept=kept,
        delta_bic={e: deltas[e] for e in beams if e in deltas},
        lost_without=lost_without,
    )
