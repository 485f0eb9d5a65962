"""Whether rounds that ran out still crawl in one direction (the checks' view of the rounds).

When the rounds reach ``schedule.max_rounds`` still moving, the checks call the last change a
jitter of the rounds and add it to the sigmas if it is below them. That holds for rounds that
scatter about a point; it does not for rounds that crawl, each moving the estimate a little
further the same way (every round holds its map's planes fixed, and a map built at the estimate
pulls the next round back towards it). On a 20 s VLP-16 shake with a 1.85 m lever arm and the
LiDAR intrinsics estimated, the last four of twelve rounds moved t_x by 12.8 mm, always the same
way, each by less than its 8.8 mm sigma: the result WARNed 36.6 mm off in t_x, 4.2 of its
sigmas, with the last change (5.1 mm) in the sigmas.

:func:`crawl_at_cap` measures the last :data:`CRAWL_WINDOW` changes of the regular rounds per
coordinate (translation in the IMU frame, rotation about the LiDAR axes from the first of them,
time offset): a coordinate whose net move exceeds its reported sigma and makes up more than
:data:`CRAWL_CONSISTENCY` of the distance it travelled crawls, and the rounds have not converged.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from licalib_cli.results import Extrinsic

__all__ = ["COORDINATES", "CRAWL_CONSISTENCY", "CRAWL_WINDOW", "Crawl", "crawl_at_cap"]

F64 = npt.NDArray[np.float64]

CRAWL_WINDOW = 4
"""Round-to-round changes looked at (the last regular rounds')."""

CRAWL_CONSISTENCY = 0.75
"""A coordinate crawls when its net move over the window is more than this fraction of the sum
of its moves (steps of random sign give about half; four steps of one sign give 1)."""

COORDINATES = ("t_x", "t_y", "t_z", "roll", "pitch", "yaw", "time offset")
"""Names of the seven coordinates, in the sigmas' order."""


@dataclass(frozen=True)
class Crawl:
    """The coordinate that crawls most, in its sigmas.

    Attributes:
        coordinate: index into the seven (:data:`COORDINATES`).
        net: its net move over the window (m, rad about the LiDAR axis, or s).
        sigma: its reported sigma.
        rounds: the number of changes looked at.
    """

    coordinate: int
    net: float
    sigma: float
    rounds: int

    def describe(self) -> str:
        """E.g. ``t_x by +12.8 mm (its sigma 8.8 mm)``."""
        k = self.coordinate
        if k < 3:
            unit, scale = "mm", 1e3
        elif k < 6:
            unit, scale = "deg", float(np.degrees(1.0))
        else:
            unit, scale = "ms", 1e3
        return (
            f"{COORDINATES[k]} by {scale * self.net:+.3g} {unit} (its sigma "
            f"{scale * self.sigma:.3g} {unit})"
        )


def crawl_at_cap(
    extrinsics: Sequence[Extrinsic], sigma: F64, window: int = CRAWL_WINDOW
) -> Crawl | None:
    """The coordinate the last ``window`` changes of ``extrinsics`` (the regular rounds'
    estimates, in order) moved consistently one way by more than its ``sigma`` (7,); the one
    furthest in its sigmas, or None when none did (or there are too few rounds)."""
    if len(extrinsics) < window + 1:
        return None
    last = extrinsics[-(window + 1) :]
    x = np.stack([last[0].moved_to(e) for e in last])  # (window + 1, 7) from the first
    net = x[-1] - x[0]
    path = np.sum(np.abs(np.diff(x, axis=0)), axis=0)
    sigma = np.asarray(sigma, dtype=np.float64)
    ok = np.isfinite(sigma) & (sigma > 0.0)
    ratio = np.where(ok, np.abs(net) / np.where(ok, sigma, 1.0), 0.0)
    crawls = ok & (ratio > 1.0) & (np.abs(net) > CRAWL_CONSISTENCY * path)
    if not np.any(crawls):
        return None
    k = int(np.argmax(np.where(crawls, ratio, -1.0)))
    return Crawl(k, float(net[k]), float(sigma[k]), window)
