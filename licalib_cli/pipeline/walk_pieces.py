"""A bias walk estimated in pieces: once its one linear drift paid, diagnose refits it as a bias
linear over each of 2, 4 and 8 equal pieces of the segment, each kept while the BIC falls
further (``model.bias_walk_piece_s``)."""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import replace

from licalib_cli.config import CalibConfig
from licalib_cli.pipeline.diagnosis_step import DiagnosisStep

__all__ = ["MIN_WALK_PIECE_S", "WALKS", "WALK_PIECES", "finer_walk", "with_walk_pieces"]

logger = logging.getLogger(__name__)

WALKS = ("gyro_bias_walk", "accel_bias_walk")
"""The effects a bias walk can be estimated for in pieces (:func:`finer_walk`)."""

WALK_PIECES = (2, 4, 8)
"""Pieces tried, in turn, for a bias walk once its linear drift paid: each finer model is kept
while it lowers the BIC further."""

MIN_WALK_PIECE_S = 1.0
"""No piece shorter than this: the trajectory spline's knots (0.02 s) and a bias both explain
the gyro's slow residuals, and a piece of a second still holds some 10^2-10^3 IMU samples."""


def with_walk_pieces(cfg: CalibConfig, piece_s: float | None) -> CalibConfig:
    """``cfg`` whose bias walks are piecewise linear over pieces of ``piece_s`` (None: one
    linear drift)."""
    return cfg.model_copy(
        update={"model": cfg.model.model_copy(update={"bias_walk_piece_s": piece_s})}
    )


def finer_walk(
    step: DiagnosisStep,
    try_with: Callable[[CalibConfig], DiagnosisStep],
    cfg: CalibConfig,
) -> tuple[DiagnosisStep, CalibConfig]:
    """A kept bias walk refitted in finer pieces (:data:`WALK_PIECES`), each kept while its BIC
    (against the same model without the walk) is lower than the coarser one's.

    A random walk is far from a line over a 20 s bag: on one such gyro walk the linear drift
    closed 23 % of the gyro's gap. A continuous piecewise-linear bias follows it the closer the
    shorter its pieces, and each piece's three drifts pay ``ln n`` each like any coordinate.

    Args:
        step: the walk's step with one linear drift (kept).
        try_with: config -> the walk's step refitted with that config.
        cfg: the configuration of the step.

    Returns:
        The step to keep (``pieces`` and ``linear_delta_bic`` set when pieces won) and its
        configuration.
    """
    assert step.after is not None
    span = 2.0 * step.after.state.t_ref_s
    best, best_cfg = step, cfg
    for pieces in WALK_PIECES:
        if span / pieces < MIN_WALK_PIECE_S:
            break
        piece_cfg = with_walk_pieces(cfg, span / pieces)
        finer = try_with(piece_cfg)
        logger.info(
            "Diagnose: %s in %d pieces of %.1f s: BIC %+.1f (%s %+.1f).",
            step.effect,
            pieces,
            span / pieces,
            finer.delta_bic,
            "one drift" if best is step else f"{best.pieces} pieces",
            best.delta_bic,
        )
        if not (finer.kept and finer.delta_bic < best.delta_bic):
            break
        best = replace(
            finer,
            pieces=pieces,
            linear_delta_bic=step.delta_bic,
            expected_size=step.expected_size,  # the size the pieces were refitted at, if any
            held_delta_bic=step.held_delta_bic,
            sized_delta_bic=step.sized_delta_bic,
        )
        best_cfg = piece_cfg
    return best, best_cfg
