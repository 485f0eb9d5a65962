"""How the rounds end (``licalib_cli.pipeline.schedule``): crawling rounds and the final rounds.

With LiDAR intrinsics free, each round holds its map's planes fixed, so the common mode of the
range offsets and scales moves by a nearly constant fraction per round. The schedule then takes
a planes-free step between two rounds. These tests pin the rule (:func:`crawls`) and its wiring
in :func:`run_schedule`: the step happens after a crawling round only, the next round starts
from the stepped estimate with nothing kept from the round before, and at most
:data:`MAX_CRAWL_STEPS` times.

The denser final round may determine a direction the regular rounds held; when it moves the
estimate by many of its sigmas, another dense round on a map rebuilt at the moved estimate
checks it, and dense rounds that keep jumping are a non-convergence (a FAIL), not a PASS. A
dense round that moved it by more than :data:`FINAL_REFINE_SIGMAS` shows that the regular
rounds crawled whatever the model: the planes-free refinement follows it then, and only then.

The rounds themselves are stand-ins whose changes are given.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from licalib_cli.config import CalibConfig
from licalib_cli.pipeline import checks, free_planes, schedule
from licalib_cli.pipeline.schedule import (
    CRAWL_RATIO,
    FINAL_REFINE_MIN_M,
    FINAL_REFINE_SIGMAS,
    FINAL_SETTLE_SIGMAS,
    MAX_CRAWL_STEPS,
    MAX_FINAL_ROUNDS,
    Change,
    crawls,
    final_jump,
)
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


@dataclass
class _Run:
    rounds: list[tuple[str, str, bool, bool]]  # label, start, mapped kept, dense
    refined_from: list[str]
    max_steps: list[int] = field(default_factory=list)
    solved_given: list[Any] = field(default_factory=list)  # what each refinement was handed
    fit: Any = None


SIGMA_MM = 0.1
"""The stand-in rounds' translation 1-sigma."""


def _schedule(
    monkeypatch: pytest.MonkeyPatch,
    step_mm: Callable[[int, bool], float],
    *,
    lidar: bool = True,
    final_points: int | None = None,
    refine_mm: float = 5.0,
    sigma_mm: float = SIGMA_MM,
) -> _Run:
    """Run :func:`run_schedule` with rounds that move the translation by ``step_mm(index,
    dense)`` mm (``dense``: a round on the final, denser sample), each reporting a translation
    sigma of :data:`SIGMA_MM`, with LiDAR intrinsics free or none."""
    run = _Run([], [])

    def run_round(state, sample, imu, settings, index, mapped=None):  # type: ignore[no-untyped-def]
        dense = sample.dense
        run.rounds.append((f"round {index}", state.label, mapped is not None, dense))
        new = _State(f"round {index}", state.x_mm + step_mm(index, dense))
        names = ("ext.translation.x", "ext.translation.y", "ext.translation.z")
        return SimpleNamespace(
            state=new,
            summary=SimpleNamespace(points=1, surfels=1, rms_m=0.01, map_entropy=0.0),
            report=SimpleNamespace(calibration_names=names, std=(1e-3 * sigma_mm,) * 3),
            inputs=SimpleNamespace(free=SimpleNamespace(any_lidar_intrinsics=lidar)),
            solved=f"solved at round {index}",
            mapped=object(),
        )

    def refine(state, inputs, lm, max_steps=free_planes.MAX_STEPS, solved=None):  # type: ignore[no-untyped-def]
        run.refined_from.append(state.label)
        run.max_steps.append(max_steps)
        run.solved_given.append(solved)
        return SimpleNamespace(
            solved=f"solved after {state.label}",
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

    class _Sample(list):  # type: ignore[type-arg]
        def __init__(self, dense: bool) -> None:
            super().__init__()
            self.dense = dense

        def subset(self, index: Any) -> _Sample:
            return self

    def sample_points(scans, phi, per_scan, cfg, seed=0):  # type: ignore[no-untyped-def]
        return _Sample(per_scan != 100)

    monkeypatch.setattr(schedule, "run_round", run_round)
    monkeypatch.setattr(schedule, "refine_with_planes", refine)
    monkeypatch.setattr(schedule, "_change", change)
    monkeypatch.setattr(schedule, "map_movement", lambda before, after, probe: 0.0)
    monkeypatch.setattr(schedule, "intrinsic_change", lambda before, after, report: 0.0)
    monkeypatch.setattr(schedule, "sample_points", sample_points)
    monkeypatch.setattr(schedule, "points_per_scan", lambda cfg, n, per_scan=None: per_scan or 100)
    monkeypatch.setattr(schedule, "round_settings", lambda *a, **k: SimpleNamespace(solver=None))
    monkeypatch.setattr(schedule, "ImuData", SimpleNamespace(from_samples=lambda *a: None))
    cfg = CalibConfig.model_validate(
        {
            "schedule": {"max_rounds": 12, "translation_tolerance_m": 1e-5},
            "surfels": {"final_points_per_scan": final_points},
            "model": {"lidar": ["range_offset"] if lidar else []},
        }
    )
    rec = SimpleNamespace(scans=(), imu=None)
    guess = SimpleNamespace(state=_State("guess", 0.0), nominal_elevation=None)
    run.fit = schedule.run_schedule(rec, guess, None, cfg, NullProgress(), warm=lidar)  # type: ignore[arg-type]
    if lidar:
        # the refinement after the last round always runs with LiDAR intrinsics free
        assert run.refined_from.pop() == run.rounds[-1][0]
        assert run.fit.state.label == f"step after {run.rounds[-1][0]}"
    return run


def _wired_schedule(
    monkeypatch: pytest.MonkeyPatch, steps_mm: list[float], refine_mm: float
) -> tuple[list[tuple[str, str, bool]], list[str]]:
    """The rounds (label, start, mapped kept) and the planes-free steps' starting states of
    regular rounds that move the translation by ``steps_mm``."""
    run = _schedule(
        monkeypatch, lambda i, dense: steps_mm[min(i - 1, len(steps_mm) - 1)], refine_mm=refine_mm
    )
    return [r[:3] for r in run.rounds], run.refined_from


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


def _settling(index: int) -> float:
    """Regular rounds that settle: 3, 1, 0.33, ... mm."""
    return 3.0 / 3.0 ** (index - 1)


def test_a_final_round_that_jumps_is_checked_by_another_dense_round(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    dense_steps = iter([2.0, 0.05])  # 20 sigmas, then half a sigma

    def step(index: int, dense: bool) -> float:
        return next(dense_steps) if dense else _settling(index)

    run = _schedule(monkeypatch, step, lidar=False, final_points=400)
    dense = [r for r in run.rounds if r[3]]
    assert len(dense) == 2
    # the second dense round starts from the first's estimate, on its mapped sample
    assert dense[1][1] == dense[0][0] and dense[1][2]
    assert run.fit.converged and not run.fit.final_unsettled


def test_a_final_round_within_its_sigmas_runs_once(monkeypatch: pytest.MonkeyPatch) -> None:
    def step(index: int, dense: bool) -> float:
        return (FINAL_SETTLE_SIGMAS - 0.5) * SIGMA_MM if dense else _settling(index)

    run = _schedule(monkeypatch, step, lidar=False, final_points=400)
    assert sum(r[3] for r in run.rounds) == 1
    assert run.fit.converged


@pytest.mark.parametrize(
    ("moved_mm", "sigma_mm", "refined"),
    [
        (1.5, 1.5 / (FINAL_REFINE_SIGMAS + 0.5), True),  # 1.5 mm, 2.5 sigmas
        (1.5, 1.5 / (FINAL_REFINE_SIGMAS - 0.5), False),  # 1.5 mm but 1.5 sigmas
        (0.9, 0.2, False),  # 4.5 sigmas but within FINAL_REFINE_MIN_M
    ],
)
def test_without_lidar_intrinsics_a_dense_round_that_moved_far_is_refined_with_the_planes_free(
    monkeypatch: pytest.MonkeyPatch, moved_mm: float, sigma_mm: float, refined: bool
) -> None:
    dense_steps = iter([moved_mm, 0.0])  # a second dense round (after a jump) settles

    def step(index: int, dense: bool) -> float:
        return next(dense_steps) if dense else _settling(index)

    run = _schedule(monkeypatch, step, lidar=False, final_points=400, sigma_mm=sigma_mm)
    last = [r for r in run.rounds if r[3]][-1]
    if refined:
        assert 1e-3 * moved_mm > FINAL_REFINE_MIN_M
        assert run.refined_from == [last[0]]
        assert run.max_steps == [1]  # without LiDAR intrinsics one step does it
        assert run.fit.state.label == f"step after {last[0]}"
        # the refinement starts from the dense round's linearisation, and the checks get the
        # refinement's own
        assert run.solved_given == [f"solved at {last[0]}"]
        assert run.fit.solved == f"solved after {last[0]}"
    else:
        assert run.refined_from == [] and run.fit.state.label == last[0]
        assert run.fit.solved == f"solved at {last[0]}"
    assert run.fit.converged


def test_dense_rounds_that_keep_jumping_are_a_non_convergence(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    def step(index: int, dense: bool) -> float:
        return 2.0 if dense else _settling(index)

    run = _schedule(monkeypatch, step, lidar=False, final_points=400)
    assert sum(r[3] for r in run.rounds) == MAX_FINAL_ROUNDS
    fit = run.fit
    assert fit.final_unsettled and not fit.converged
    assert fit.last_change.translation_m == pytest.approx(2e-3)
    cfg = CalibConfig()
    (finding,) = checks._convergence(fit, cfg)
    assert finding.severity == "fail"
    assert finding.text.startswith("The calibration did not converge")
    assert "denser final rounds" in finding.text


def test_final_jump_in_sigmas_ignores_what_is_within_tolerance_or_not_observable() -> None:
    cfg = CalibConfig()
    names = (
        "ext.translation.x",
        "ext.translation.y",
        "ext.rotation.x",
        "ext.time_offset",
    )
    report = SimpleNamespace(calibration_names=names, std=(1e-3, 2e-3, np.inf, 1e-4))
    # translation 10 mm over its largest sigma 2 mm
    assert final_jump(Change(0.01, 0.0, 0.0), report, cfg) == pytest.approx(5.0)  # type: ignore[arg-type]
    # a rotation without a finite sigma does not count
    assert final_jump(Change(0.0, 3.0, 0.0), report, cfg) == 0.0  # type: ignore[arg-type]
    # a change within the configured tolerance does not count
    tol = cfg.schedule.time_offset_tolerance_s
    assert final_jump(Change(0.0, 0.0, 0.9 * tol), report, cfg) == 0.0  # type: ignore[arg-type]
    assert final_jump(Change(0.0, 0.0, 1e-3), report, cfg) == pytest.approx(10.0)  # type: ignore[arg-type]


def test_provisional_rounds_stop_early_only_without_intrinsics() -> None:
    """A provisional round may leave its last tenths of a sigma to the next round when only the
    extrinsic is free; with intrinsics it is solved to its optimum (stopped early, the rounds
    moved the range scales too little and settled before those had)."""
    from licalib_cli.pipeline.settings import (
        PROVISIONAL_COST_TOLERANCE,
        NoiseLevels,
        round_settings,
    )

    cfg = CalibConfig.model_validate({"model": {"lidar": ["range_scale", "range_offset"]}})
    gyro, accel = np.full(3, 0.0035), np.full(3, 0.0118)
    noise = NoiseLevels(
        gyro, accel, 0.01, "config", "config", "config", np.full(16, np.nan), gyro, accel, 0.01
    )

    def tolerance(intrinsics: bool, provisional: bool) -> float:
        settings = round_settings(cfg, noise, 0.05, intrinsics, provisional=provisional)
        return settings.solver.cost_tolerance

    assert tolerance(False, True) == PROVISIONAL_COST_TOLERANCE > 0.0
    assert tolerance(True, True) == 0.0
    assert tolerance(False, False) == tolerance(True, False) == 0.0
