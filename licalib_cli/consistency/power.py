"""How large an effect must be for a recording to show it: the power of the score test.

The score statistic of an effect ``d`` held fixed is non-central chi-square with ``rank``
degrees of freedom and non-centrality ``d^T I d``, ``I`` the effect's information with
everything estimated profiled out (:class:`~licalib_cli.consistency.score.EffectScore`). Below
the size :func:`detectable_rms` returns, an effect may hide in the recording.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt
from scipy import optimize

from licalib_cli.consistency.distributions import ncx2_sf

__all__ = [
    "DETECTION_POWER",
    "DISPLAY_UNITS",
    "detectable_noncentrality",
    "detectable_rms",
    "display_size",
]

DISPLAY_UNITS: dict[str, tuple[float, str]] = {
    "gyro_scale": (1e6, "ppm"),
    "gyro_misalignment": (math.degrees(1.0), "deg"),
    "gyro_rotation": (math.degrees(1.0), "deg"),
    "accel_scale": (1e6, "ppm"),
    "accel_misalignment": (math.degrees(1.0), "deg"),
    "g_sensitivity": (math.degrees(1.0) * 9.80665, "deg/s per g"),
    "gyro_bias_walk": (math.degrees(1.0), "deg/s^2"),
    "accel_bias_walk": (1.0, "m/s^3"),
    "imu_clock_drift": (1e6, "ppm"),
    "lidar_range_offset": (1e3, "mm"),
    "lidar_range_scale": (1e6, "ppm"),
    "lidar_elevation": (math.degrees(1.0), "deg"),
    "lidar_azimuth": (math.degrees(1.0), "deg"),
    "lidar_vertical_offset": (1e3, "mm"),
    "lidar_horizontal_offset": (1e3, "mm"),
    "lidar_point_time": (100.0, "% of the sweep time"),
}
"""Effect -> (factor from its solver coordinates, unit) for printing sizes."""


DETECTION_POWER = 0.9
"""``not_shown`` sizes are those an effect needs to be named at least this often."""


def detectable_noncentrality(
    statistic_threshold: float, rank: int, power: float = DETECTION_POWER
) -> float:
    """The non-centrality ``d^T I d`` at which the score statistic (``rank`` degrees of
    freedom) exceeds ``statistic_threshold`` with probability ``power``: an effect ``d`` inside
    that ellipsoid may hide in the recording."""

    def shortfall(nc: float) -> float:
        return ncx2_sf(statistic_threshold, rank, nc) - power

    if shortfall(0.0) >= 0.0:
        return 0.0
    hi = max(statistic_threshold, 1.0)
    while shortfall(hi) < 0.0:
        hi *= 2.0
    return float(optimize.brentq(shortfall, 0.0, hi))


def detectable_rms(
    statistic_threshold: float,
    coordinates: int,
    information: npt.ArrayLike,
    power: float = DETECTION_POWER,
) -> tuple[float, float]:
    """RMS per coordinate of an effect whose score statistic exceeds ``statistic_threshold``
    with probability ``power``: ``(along the weakest determined direction, along the
    strongest)``.

    The statistic of an effect ``d`` is non-central chi-square with ``rank`` degrees of freedom
    and non-centrality ``d^T I d``; ``d`` has ``coordinates`` entries, ``information`` holds the
    eigenvalues of ``I`` along the directions the data determine (``inf`` without any).
    """
    info = np.asarray(information, dtype=np.float64)
    info = info[info > 0.0]
    if coordinates <= 0 or info.size == 0:
        return float("inf"), float("inf")
    needed = detectable_noncentrality(statistic_threshold, info.size, power)
    per_coordinate = needed / coordinates
    return math.sqrt(per_coordinate / float(info.min())), math.sqrt(
        per_coordinate / float(info.max())
    )


def display_size(effect: str, value: float) -> tuple[float, str]:
    """``value`` in solver coordinates of ``effect`` as printed: (number, unit)."""
    factor, unit = DISPLAY_UNITS[effect]
    return value * factor, unit
