"""A map the rounds lost, and whether the beams may be why.

The rounds lose their map in two ways: its planes vanish (an error,
:class:`~licalib_cli.errors.MapLost`, raised by the schedule), or a few points stay on a few
planes and the rounds go on to a fit that rests on them (:func:`collapsed_map`). Either way a
spinning LiDAR whose beams are held at nominal (:func:`beams_held`) may be the cause: beams that
disagree by centimetres (per-beam range offsets from an old or generic beam table) blur the map
from the first round on. ``diagnose`` then frees the beams (:mod:`.beams_in_base`); ``calibrate``
says to.
"""

from __future__ import annotations

from collections.abc import Sequence

from licalib_cli.config import CalibConfig
from licalib_cli.pipeline.round import RoundSummary

__all__ = ["COLLAPSED_SHARE", "POOR_MAP_FRACTION", "beams_advice", "beams_held", "collapsed_map"]

POOR_MAP_FRACTION = 0.2
"""A last round with fewer of its points on planes than this is a poor map."""

COLLAPSED_SHARE = 0.1
"""A poor last round with less than this share of the best round's fraction of points on planes
is a collapsed map. On a 10 s OS1-64 sinusoid with per-beam range offsets of 5 cm RMS (seed
18014) the rounds went from 45 000 points on 274 surfels (round 3) to 100-200 points on about
ten (rounds 6-12), and the fit ended 59 mm off with sigmas that did not cover it; a poor scene
is poor from round 1 and a clean fit's last (dense) round holds its share."""


def beams_held(cfg: CalibConfig) -> bool:
    """The model holds the beams of a spinning LiDAR at nominal (no ``model.lidar``)."""
    return not cfg.model.lidar and not cfg.lidar.non_repetitive


def beams_advice(detail: str = "") -> str:
    """The advice to estimate beams that may disagree, with ``detail`` (how the map fared) in
    its parenthesis; the lost map's error and the collapsed map's finding end with it."""
    why = (
        "per-beam range offsets or angles from an old or generic beam table blur the map from "
        "the first round on"
    )
    return (
        f"if the LiDAR's beams may disagree ({why}{f'; {detail}' if detail else ''}), estimate "
        "their intrinsics (licalib calibrate --intrinsics lidar, or model.lidar in the config)"
    )


def collapsed_map(rounds: Sequence[RoundSummary]) -> str | None:
    """How the rounds lost the map (``round 12 had 0.3 % of its points on planes (144), round 3
    had 20.1 % (44974)``), or None when the last round's map is not collapsed."""
    if not rounds:
        return None
    last = rounds[-1]
    best = max(rounds, key=lambda r: r.associated_fraction)
    if (
        last.associated_fraction >= POOR_MAP_FRACTION
        or last.associated_fraction >= COLLAPSED_SHARE * best.associated_fraction
    ):
        return None
    return (
        f"round {last.index} had {100 * last.associated_fraction:.1f} % of its points on planes "
        f"({last.points}), round {best.index} had {100 * best.associated_fraction:.1f} % "
        f"({best.points})"
    )
