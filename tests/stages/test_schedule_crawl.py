"""The planes-free steps between crawling rounds (``licalib_cli.pipeline.schedule``).

With LiDAR intrinsics free, each round holds its map's planes fixed, so the common mode of the
range offsets and scales moves by a nearly constant fraction per round. The schedule then takes
a planes-free step between two rounds. These tests pin the rule (:func:`crawls`) and its wiring
in :func:`run_schedule`: the step happens after a crawling round only, the next round starts
from the stepped estimate with nothing kept from the round before, and at most
:data:`MAX_CRAWL_STEPS` times. The rounds themselves are stand-ins whose changes are given.
"""

from __future__ import annotations

from dataclasses import dataclass
from types import SimpleNamespace
from typing import Any

import pytest

from licalib_cli.config import CalibConfig
from licalib_cli.pipeline import schedule
from licalib_cli.pipeline.schedule import CRAWL_RATIO, MAX_CRAWL_STEPS, Change, crawls
from licalib_cli.progress import NullProgress


def _mm(x: float) -> Change:
    return Change(1e-3 * x, 0.0, 0.0)


def test_crawls_on_a_slowly_shrinking_step_only() -> None:
    on = {"lidar_intrinsics_free": True, "at_base_distance": True, "steps_taken": 0}
    assert crawls(_mm(2.1), _mm(2.3), **on)
    # a settling estimate shrinks its steps faster than the ratio
    assert not crawls(_mm(1.0), _mm(2.3), **on)
    assert not crawls(_mm(CRAWL_RATIO * 2.0 - 1e-6), _mm(2.0), **on)
    assert crawls(_mm(CRAWL_RATIO * 2.0 + 1e-6), _mm(2.0), **on)
    # nothing to compare with on the first round
    assert not crawls(_mm(5.0), None, **on)


@pytest.mark.parametrize(
    ("free", "at_base", "steps"),
    [(False, True, 0), (True, False, 0), (True, True, MAX_CRAWL_STEPS)],
)
def test_no_step_without_lidar_intrinsics_before_the_base_distance_or_past_the_cap(
    free: bool, at_base: bool, steps: int
) -> None:
    assert not crawls(
        _mm(2.1),
        _mm(2.3),
        lidar_intrinsics_free=free,
        at_base_distance=at_base,
        steps_taken=steps,
    )


@dataclass(frozen=True)
class _State:
    """A stand-in estimate: which round (or step) produced it and its translation, mm."""

    label: str
    x_mm: float
    t0_ns: int = 0


def _wired_schedule(
    monkeypatch: pytest.MonkeyPatch, steps_mm: list[float], refine_mm: float
) -> tuple[list[tuple[str, str, bool]], list[str]]:
    """Run :func:`run_schedule` with rounds that move the translation by ``steps_mm``.

    Returns the rounds' calls (round label, starting state, whether a mapped sample was passed
    in) and the states the planes-free steps started from.
    """
    rounds: list[tuple[str, str, bool]] = []
    refined_from: list[str] = []

    def run_round(state, sample, imu, settings, index, mapped=None):  # type: ignore[no-untyped-def]
        rounds.append((f"round {index}", state.label, mapped is not None))
        step = steps_mm[min(index - 1, len(steps_mm) - 1)]
        new = _State(f"round {index}", state.x_mm + step)
        free = SimpleNamespace(any_lidar_intrinsics=True)
        return SimpleNamespace(
            state=new,
            summary=SimpleNamespace(points=1, surfels=1, rms_m=0.01, map_entropy=0.0),
            report=SimpleNamespace(calibration_names=(), std=()),
            inputs=SimpleNamespace(free=free),
            solved=object(),
            mapped=object(),
        )

    def refine(state, inputs, lm):  # type: ignore[no-untyped-def]
        refined_from.append(state.label)
        return SimpleNamespace(
            state=_State(f"step after {state.label}", state.x_mm + refine_mm),
            report=None,
            inputs=inputs,
            steps=1,
            cost_start=1.0,
            cost_end=0.5,
            seconds=0.0,
        )

    def change(before: Any, after: Any) -> Change:
        return _mm(abs(after.x_mm - before.x_mm))

    monkeypatch.setattr(schedule, "run_round", run_round)
    monkeypatch.setattr(schedule, "refine_with_planes", refine)
    monkeypatch.setattr(schedule, "_change", change)
    monkeypatch.setattr(schedule, "map_movement", lambda before, after, probe: 0.0)
    monkeypatch.setattr(schedule, "intrinsic_change", lambda before, after, report: 0.0)

    class _Sample(list):  # type: ignore[type-arg]
        def subset(self, index: Any) -> _Sample:
            return self

    monkeypatch.setattr(schedule, "sample_points", lambda *a, **k: _Sample())
    monkeypatch.setattr(schedule, "points_per_scan", lambda *a, **k: 100)
    monkeypatch.setattr(schedule, "round_settings", lambda *a, **k: SimpleNamespace(solver=None))
    monkeypatch.setattr(schedule, "ImuData", SimpleNamespace(from_samples=lambda *a: None))
    cfg = CalibConfig.model_validate(
        {
            "schedule": {"max_rounds": 12, "translation_tolerance_m": 1e-4},
            "surfels": {"final_points_per_scan": None},
            "model": {"lidar": ["range_offset"]},
        }
    )
    rec = SimpleNamespace(scans=(), imu=None)
    guess = SimpleNamespace(state=_State("guess", 0.0), nominal_elevation=None)
    fit = schedule.run_schedule(rec, guess, None, cfg, NullProgress(), warm=True)  # type: ignore[arg-type]
    # the refinement after the last round always runs with LiDAR intrinsics free
    assert refined_from[-1] == rounds[-1][0]
    assert fit.state.label == f"step after {rounds[-1][0]}"
    return rounds, refined_from[:-1]


def test_a_crawl_takes_a_planes_free_step_before_the_next_round(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # 3.0, 2.4, 1.9, ... mm: each round covers 80 % of the one before (crawling)
    steps = [3.0 * 0.8**k for k in range(12)]
    rounds, refined_from = _wired_schedule(monkeypatch, steps, refine_mm=5.0)
    # the first round has nothing to compare with; from the second on each crawls
    assert refined_from == ["round 2", "round 3", "round 4"]
    assert len(refined_from) == MAX_CRAWL_STEPS
    starts = {label: (start, kept) for label, start, kept in rounds}
    # the round after a step starts from the stepped estimate, with no mapped sample kept
    for k in (3, 4, 5):
        assert starts[f"round {k}"] == (f"step after round {k - 1}", False)
    # past the cap the rounds go on as before: each from the one before, its map kept
    assert starts["round 6"] == ("round 5", True)


def test_no_planes_free_step_while_the_rounds_settle(monkeypatch: pytest.MonkeyPatch) -> None:
    # each round moves a third of the one before: converging, not crawling
    steps = [3.0 / 3.0**k for k in range(12)]
    rounds, refined_from = _wired_schedule(monkeypatch, steps, refine_mm=5.0)
    assert refined_from == []
    assert all(kept for label, _, kept in rounds if label != "round 1")
