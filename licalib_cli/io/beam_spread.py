"""How far the points of one beam spread in elevation: rings of a spinning LiDAR or lines of a
non-repetitive scanner.

A spinning LiDAR's ``ring`` numbers beams of fixed elevation: a ring's points spread a few
hundredths of a degree in elevation (its intrinsics, its offset from the sensor's origin). A
non-repetitive scanner (a Livox) numbers its lasers in a ``line`` field, and each line traces a
curve over much of the field of view: its points spread tens of degrees. ``info`` reports the
spread and ``calibrate`` takes the beams for lines above :data:`SPREAD_DEG`
(:mod:`licalib_cli.pipeline.scan_pattern`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from licalib_cli.geometry.vectors import elevations, norms

__all__ = ["FAR_SHARE", "MIN_RANGE_M", "NEAR_RANGE_M", "SPREAD_DEG", "elevation_spread_deg"]

SPREAD_DEG = 3.0
"""Beams whose elevations spread more than this (:func:`elevation_spread_deg`) are a
non-repetitive scanner's lines."""

MIN_RANGE_M = 3.0
"""Points nearer than this do not enter the spread: a beam's offset from the sensor's origin (a
few centimetres) turns its elevation seen from the origin by a degree at a metre."""

NEAR_RANGE_M = 1.0
"""When fewer than :data:`FAR_SHARE` of the points beyond this range lie beyond
:data:`MIN_RANGE_M` (a forward-looking scanner facing a wall), all points from this range on
are taken instead."""

FAR_SHARE = 0.25
"""See :data:`NEAR_RANGE_M`."""

_MIN_BEAM_POINTS = 50
"""A beam enters the spread with at least this many points beyond :data:`MIN_RANGE_M`."""

_MAD_TO_SIGMA = 1.4826


def elevation_spread_deg(
    xyz: Sequence[npt.NDArray[np.float64]], ring: Sequence[npt.ArrayLike]
) -> float:
    """The median over the beams of their elevations' robust spread (1.4826 times the median
    absolute deviation), deg.

    Args:
        xyz: (N_k, 3) points of some clouds, m.
        ring: (N_k,) their beam index.

    Returns:
        The spread over the points beyond :data:`MIN_RANGE_M` (or :data:`NEAR_RANGE_M`); NaN
        when no beam has 50 such points.
    """
    if not xyz:
        return float("nan")
    p = np.concatenate([np.asarray(x, dtype=np.float64).reshape(-1, 3) for x in xyz])
    b = np.concatenate([np.asarray(r, dtype=np.int64).reshape(-1) for r in ring])
    r = norms(p)
    far, near = r >= MIN_RANGE_M, r >= NEAR_RANGE_M
    # a few far points of a scanner facing a wall lie in one patch, whatever its lines do
    keep = far if np.count_nonzero(far) >= FAR_SHARE * np.count_nonzero(near) else near
    elev = np.degrees(elevations(p[keep]))
    beam = b[keep]
    order = np.argsort(beam, kind="stable")
    elev, beam = elev[order], beam[order]
    spreads = [
        _MAD_TO_SIGMA * float(np.median(np.abs(seg - np.median(seg))))
        for seg in np.split(elev, np.flatnonzero(np.diff(beam)) + 1)  # per beam (a few hundred)
        if seg.size >= _MIN_BEAM_POINTS
    ]
    return float(np.median(spreads)) if spreads else float("nan")
