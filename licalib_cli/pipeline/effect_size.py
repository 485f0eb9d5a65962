"""An effect's expected size, when its score test puts it far above the built-in one.

The truncated SVD holds at nominal every direction of a block that the recording determines
worse than the block's characteristic scale (:data:`~licalib_cli.estimation.CALIBRATION_SCALES`):
the scale says how large the block is expected to be, and a direction known worse than that is
better left at nominal than estimated from noise. An effect far larger than expected breaks the
premise: on a 10 s OS1-64 shake whose gyro bias walked at a hundred times the MTi-100's rate,
the score test showed the walk at 256 on 3 degrees of freedom (its one-step drift up to 2.9e-4
rad/s^2 per axis), but the drift's sigma (2.2e-5 rad/s^2) was above its scale (1e-5), so the
refit held it at zero, gained nothing, and the walk was not added.

When a refit held coordinates of an effect whose score test is significant, and the test's
one-step estimate puts them beyond :data:`SIZE_SIGMAS` of their sigmas and above the scale
they were held at, the effect is refitted expecting that size (``model.expected_size``: the
estimate's largest coordinate, rounded up to 1, 2 or 5 times a power of ten). The BIC decides on
the refit as on any other. Each rival refitted at a step is sized so before the rivals are
compared (:func:`with_sizes_of`): on the second 10 s of a 20 s OS1-64 sinusoid with a gyro walk,
the walk held at its scale did not pay, its rival the gyro scale did (BIC -71), and the walk was
named a gyro scale; sized, the walk pays (BIC -247, -299 in 4 pieces) and wins. The per-beam
LiDAR intrinsics are not sized so: their prior across beams is ``model.lidar_spread``.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterable
from dataclasses import replace

import numpy as np

from licalib_cli.config import SIZED_BLOCKS, CalibConfig
from licalib_cli.consistency.score import EffectScore
from licalib_cli.pipeline.diagnosis_step import CANDIDATES, DiagnosisStep
from licalib_cli.pipeline.fitcheck import EFFECT_P_VALUE
from licalib_cli.pipeline.settings import expected_size

__all__ = [
    "SIZE_SIGMAS",
    "round_up",
    "size_worth_trying",
    "sized_refit",
    "with_expected_size",
    "with_sizes_of",
]

logger = logging.getLogger(__name__)

SIZE_SIGMAS = 3.0
"""Only coordinates the score test puts beyond this many of their sigmas set the size."""


def round_up(x: float) -> float:
    """The smallest of 1, 2 or 5 times a power of ten that is at least ``x`` (> 0)."""
    exponent = math.floor(math.log10(x))
    for mantissa in (1.0, 2.0, 5.0, 10.0):
        value = float(f"{mantissa}e{exponent}")
        if value >= x * (1.0 - 1e-12):
            return value
    raise AssertionError("unreachable")  # pragma: no cover - 10 * 10^e > x always


def with_expected_size(cfg: CalibConfig, block: str, size: float) -> CalibConfig:
    """``cfg`` whose ``model.expected_size`` gives ``model:`` block ``block`` the size
    ``size``."""
    sizes: dict[str, float] = {str(k): v for k, v in cfg.model.expected_size.items()}
    sizes[block] = size
    return cfg.model_copy(update={"model": cfg.model.model_copy(update={"expected_size": sizes})})


def with_sizes_of(cfg: CalibConfig, others: Iterable[CalibConfig]) -> CalibConfig:
    """``cfg`` with every ``model.expected_size`` of ``others`` too (theirs where both set
    one): the configuration to compare rival refits in, each sized as it was refitted (a size
    only matters while its block is free)."""
    out = cfg
    for other in others:
        for block, size in other.model.expected_size.items():
            out = with_expected_size(out, block, size)
    return out


def size_worth_trying(
    score: EffectScore, block: str, held: bool, significant: bool, cfg: CalibConfig
) -> float | None:
    """The size to refit an effect with (see the module), or None.

    Args:
        score: the effect's score test on the fit it was tested on.
        block: its ``model:`` block (``gyro_bias_walk``; per-beam LiDAR blocks are never sized).
        held: whether its refit held some of its coordinates.
        significant: whether its score test is significant.
        cfg: the configuration of the refit.
    """
    if not (held and significant) or block not in SIZED_BLOCKS:
        return None
    estimate = np.abs(np.asarray(score.estimate, dtype=np.float64))
    sigma = np.asarray(score.sigma, dtype=np.float64)
    seen = np.isfinite(sigma) & (estimate > SIZE_SIGMAS * sigma)
    if not np.any(seen):
        return None
    size = round_up(float(np.max(estimate[seen])))
    # size >= the estimate > SIZE_SIGMAS sigmas: the sized refit determines what set it
    return size if size > expected_size(cfg, block) else None


def sized_refit(
    step: DiagnosisStep,
    score: EffectScore,
    try_with: Callable[[CalibConfig], DiagnosisStep],
    cfg: CalibConfig,
) -> tuple[DiagnosisStep, CalibConfig]:
    """An effect whose refit held coordinates its score test puts far above their scale,
    refitted expecting the size the test shows (:mod:`licalib_cli.pipeline.effect_size`).

    Args:
        step: the effect's step at the built-in scale (not kept).
        score: its score test.
        try_with: config -> the effect's step refitted with that config.
        cfg: the configuration of the step.

    Returns:
        The sized refit's step when it pays (``expected_size``, ``held_delta_bic`` and
        ``sized_delta_bic`` set) and its configuration; else ``step`` with those three set when
        the sized refit was tried, and ``cfg``.
    """
    block = CANDIDATES[step.effect][1]
    size = size_worth_trying(score, block, bool(step.held), step.p_value < EFFECT_P_VALUE, cfg)
    if size is None or step.kept:
        return step, cfg
    logger.info(
        "Diagnose: the refit held %s at its characteristic scale although its score test shows "
        "it larger; refitting it expecting %.3g per coordinate (model.expected_size).",
        step.effect,
        size,
    )
    sized_cfg = with_expected_size(cfg, block, size)
    sized = try_with(sized_cfg)
    out, out_cfg = step, cfg
    if sized.kept:
        out = replace(
            sized, not_told_apart=step.not_told_apart, rival_delta_bic=step.rival_delta_bic
        )
        out_cfg = sized_cfg
    out = replace(
        out, expected_size=size, held_delta_bic=step.delta_bic, sized_delta_bic=sized.delta_bic
    )
    return out, out_cfg
