"""Rounds still moving at the cap: a failure unless the move is within the reported sigmas (and
the rounds do not crawl one way beyond them)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from licalib_cli.config import CalibConfig
from licalib_cli.pipeline.checks import _convergence, within_sigmas
from licalib_cli.pipeline.crawl import Crawl
from licalib_cli.pipeline.schedule import Change

# 1 mm, 0.5 deg and 0.2 ms of reported 1-sigma (translation, rotation, time offset)
SIGMA = np.array([1e-3, 0.4e-3, 0.6e-3, *np.radians([0.5, 0.3, 0.2]), 2e-4])


def _at_cap(change: Change, final_rounds: int = 0, final_jump: float = 0.0) -> SimpleNamespace:
    """A fit whose regular rounds ran out still moving by ``change``, with ``final_rounds``
    denser final rounds after them, the last moving it ``final_jump`` of its sigmas."""
    return SimpleNamespace(
        converged=False,
        final_unsettled=False,
        jitter=False,
        last_change=change,
        extra_rounds=0,
        final_rounds=final_rounds,
        final_jump=final_jump,
    )


def test_a_change_below_every_reported_sigma_is_within_them() -> None:
    assert within_sigmas(Change(0.4e-3, 0.035, 0.03e-3), SIGMA)  # the trust benchmark's 1300
    assert not within_sigmas(Change(1.2e-3, 0.035, 0.03e-3), SIGMA)  # translation beyond
    assert not within_sigmas(Change(0.4e-3, 0.6, 0.03e-3), SIGMA)  # rotation beyond
    assert not within_sigmas(Change(0.4e-3, 0.035, 0.3e-3), SIGMA)  # time offset beyond
    assert not within_sigmas(Change(0.4e-3, 0.035, 0.03e-3), np.full(7, np.nan))


def test_rounds_moving_at_the_cap_fail_unless_within_the_sigmas() -> None:
    fit = _at_cap(Change(4e-4, 0.035, 3e-5), final_rounds=1, final_jump=0.3)
    cfg = CalibConfig()
    (failed,) = _convergence(fit, cfg)  # type: ignore[arg-type]
    assert failed.severity == "fail" and "did not converge" in failed.text
    assert "after schedule.max_rounds = 12 rounds the estimate" in failed.text
    fit.extra_rounds = 2  # two rounds beyond the cap checked a planes-free step
    (failed,) = _convergence(fit, cfg)  # type: ignore[arg-type]
    assert (
        "after schedule.max_rounds = 12 rounds (and 2 more that checked a planes-free step) the "
        "estimate still moved" in failed.text
    )
    fit.extra_rounds = 0
    (noted,) = _convergence(fit, cfg, settled_in_sigmas=True)  # type: ignore[arg-type]
    assert noted.severity == "note" and "less than its reported sigmas" in noted.text
    # dense final rounds that jump stay a failure whatever the sigmas
    fit.final_unsettled = True
    (jumped,) = _convergence(fit, cfg, settled_in_sigmas=True)  # type: ignore[arg-type]
    assert jumped.severity == "fail"


def test_rounds_that_crawl_at_the_cap_fail_and_say_which_coordinate() -> None:
    fit = _at_cap(Change(5.1e-3, 0.03, 1e-5))
    crawl = Crawl(coordinate=0, net=12.7e-3, sigma=7.15e-3, rounds=4)
    (failed,) = _convergence(fit, CalibConfig(), crawl=crawl)  # type: ignore[arg-type]
    assert failed.severity == "fail" and "did not converge" in failed.text
    assert "its last 4 rounds moved t_x by +12.7 mm (its sigma 7.15 mm) the same way" in failed.text


def test_rounds_moving_at_the_cap_warn_when_the_dense_rounds_after_them_came_to_rest() -> None:
    """The regular rounds ran out still moving; the dense rounds after them moved the estimate
    by many of its sigmas, then by at most one (a 10 s Avia sinusoid with the IMU intrinsics
    estimated: 62.7, 10.8 and 0.5 sigmas)."""
    fit = _at_cap(Change(8.5e-3, 0.031, 2.0e-4), final_rounds=3, final_jump=0.5)
    crawl = Crawl(coordinate=5, net=np.radians(-0.784), sigma=np.radians(0.0196), rounds=4)
    (warned,) = _convergence(fit, CalibConfig(), crawl=crawl)  # type: ignore[arg-type]
    assert warned.severity == "warn"
    assert warned.text.startswith(
        "After schedule.max_rounds = 12 rounds the estimate still moved 8.5 mm / 0.031 deg / "
        "0.20 ms per round; the 3 denser final rounds after them came to rest (the last moved "
        "it 0.5 of its sigmas)"
    )
    # not at rest: the last dense round moved more than one sigma, or only one dense round ran
    # (nothing checked where it went), or they never settled
    for rounds, jump, unsettled in ((3, 1.5, False), (1, 0.5, False), (6, 0.5, True)):
        fit.final_rounds, fit.final_jump, fit.final_unsettled = rounds, jump, unsettled
        (failed,) = _convergence(fit, CalibConfig(), crawl=crawl)  # type: ignore[arg-type]
        assert failed.severity == "fail" and "did not converge" in failed.text
