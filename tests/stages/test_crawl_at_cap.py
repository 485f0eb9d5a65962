"""Rounds that run out while crawling one way have not converged (``pipeline.crawl``).

A change below the sigmas at the round cap is a jitter the sigmas can absorb only when the rounds
scatter about a point. Rounds that each move the estimate a little further the same way are
still on their way: on a 20 s VLP-16 shake with the LiDAR intrinsics estimated, the last four
moved t_x by 12.7 mm, each by less than its 8.8 mm sigma, and the result WARNed 36.6 mm off.
"""

from __future__ import annotations

import numpy as np
import pytest

from licalib_cli.geometry import so3
from licalib_cli.pipeline.crawl import CRAWL_WINDOW, crawl_at_cap
from licalib_cli.results import Extrinsic

SIGMA = np.array([8.8e-3, 28.7e-3, 10.2e-3, 0.028, 0.0069, 0.0035, 6.2e-5])
"""The WARN's sigmas (m, rad, s)."""


def rounds(x_mm: list[float], roll_deg: list[float] | None = None) -> list[Extrinsic]:
    """Estimates whose t_x (and roll) take the given values, the rest fixed."""
    roll = roll_deg or [0.0] * len(x_mm)
    base = so3.exp(np.radians([83.5, 66.1, -90.9]))
    return [
        Extrinsic(
            base @ so3.exp([np.radians(r), 0.0, 0.0]),
            np.array([0.95 + 1e-3 * x, -0.48, -1.49]),
            -0.0233,
        )
        for x, r in zip(x_mm, roll, strict=True)
    ]


def test_the_rounds_of_the_warn_crawl_along_t_x() -> None:
    # t_x of its last five rounds (the dense final round last), mm
    crawl = crawl_at_cap(rounds([-49.3, -50.7, -44.8, -42.4, -36.5]), SIGMA)
    assert crawl is not None and crawl.coordinate == 0 and crawl.rounds == CRAWL_WINDOW
    assert crawl.net == pytest.approx(12.8e-3)
    assert crawl.describe() == "t_x by +12.8 mm (its sigma 8.8 mm)"


@pytest.mark.parametrize(
    "x_mm",
    [
        [0.0, 6.0, -1.0, 7.0, 1.0],  # scatter about a point, each step within the sigma
        [0.0, 2.0, 4.0, 6.0, 8.0],  # one way, but 8 mm in all: within the 8.8 mm sigma
        [0.0, 8.0, 3.0, 11.0, 10.0],  # net 10 mm, but 25 mm travelled back and forth
    ],
)
def test_scatter_or_a_move_within_the_sigma_is_not_a_crawl(x_mm: list[float]) -> None:
    assert crawl_at_cap(rounds(x_mm), SIGMA) is None


def test_only_the_last_changes_count_and_too_few_rounds_say_nothing() -> None:
    # crawled early, then scattered about where it ended
    x = [-80.0, -60.0, -40.0, -38.0, -41.0, -39.0, -40.5, -39.5]
    assert crawl_at_cap(rounds(x), SIGMA) is None
    assert crawl_at_cap(rounds(x[:3]), SIGMA) is None
    assert crawl_at_cap(rounds(x[:5]), SIGMA) is not None


def test_a_rotation_crawls_about_the_lidar_axes() -> None:
    crawl = crawl_at_cap(rounds([0.0] * 5, [0.0, 0.5, 1.0, 1.6, 2.0]), SIGMA)
    assert crawl is not None and crawl.coordinate == 3
    assert crawl.net == pytest.approx(np.radians(2.0))
    assert crawl.describe().startswith("roll by +2 deg")
    # the sigma that is not finite (an undetermined coordinate) does not count
    sigma = SIGMA.copy()
    sigma[3] = np.inf
    assert crawl_at_cap(rounds([0.0] * 5, [0.0, 0.5, 1.0, 1.6, 2.0]), sigma) is None
