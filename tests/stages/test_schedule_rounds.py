"""How the rounds end (``licalib_cli.pipeline.schedule``): crawling rounds and the final rounds.

With LiDAR intrinsics free, each round holds its map's planes fixed, so the common mode of the
range offsets and scales moves by a nearly constant fraction per round. The schedule then takes
a planes-free step between two rounds. These tests pin the rule (:func:`crawls`) and its wiring
in :func:`run_schedule`: the step happens after a crawling round only, the next round starts
from the stepped estimate with nothing kept from the round before, and at most
:data:`MAX_CRAWL_STEPS` times. A map that stalls (:func:`stalls`: it blurs, or stays blurred with
few points on its planes) takes the same step at any association distance.

The denser final round may determine a direction the regular rounds held; when it moves the
estimate by many of its sigmas, another dense round on a map rebuilt at the moved estimate
checks it, and dense rounds that keep jumping are a non-convergence (a FAIL), not a PASS.
A dense round only builds and linearises its problem, and planes-free steps from that
linearisation move the estimate (the regular rounds, holding their planes fixed, stop short of
the optimum whatever the model): one without LiDAR intrinsics, up to ``MAX_STEPS`` with them.

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
from licalib_cli.geometry import so3
from licalib_cli.pipeline import checks, free_planes, schedule
from licalib_cli.pipeline.schedule import (
    CRAWL_RATIO,
    FINAL_SETTLE_SIGMAS,
    MAX_CRAWL_STEPS,
    MAX_FINAL_ROUNDS,
    STALL_ENTROPY,
    STALL_FRACTION,
    WANDER_SHRINK,
    Change,
    crawls,
    final_jump,
    initial_sd,
    stalls,
    takes_back,
)
from licalib_cli.progress import NullProgress


def _mm(x: float) -> Change:
    return Change(1e-3 * x, 0.0, 0.0)


def test_crawls_on_a_slowly_shrinking_step_only() -> None:
    on = {"at_base_distance": True, "steps_taken": 0}
    assert crawls(_mm(2.1), _mm(2.3), **on)
    # a settling estimate shrinks its steps faster than the ratio
    assert not crawls(_mm(1.0), _mm(2.3), **on)
    assert not crawls(_mm(CRAWL_RATIO * 2.0 - 1e-6), _mm(2.0), **on)
    assert crawls(_mm(CRAWL_RATIO * 2.0 + 1e-6), _mm(2.0), **on)
    # nothing to compare with on the first round
    assert not crawls(_mm(5.0), None, **on)


@pytest.mark.parametrize(("at_base", "steps"), [(False, 0), (True, MAX_CRAWL_STEPS)])
def test_no_step_before_the_base_distance_or_past_the_cap(at_base: bool, steps: int) -> None:
    assert not crawls(_mm(2.1), _mm(2.3), at_base_distance=at_base, steps_taken=steps)


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
    evaluate_only: list[bool] = field(default_factory=list)  # per round: no solver step
    max_steps: list[int] = field(default_factory=list)
    solved_given: list[Any] = field(default_factory=list)  # what each refinement was handed
    distances_m: list[float] = field(default_factory=list)  # per round: association distance
    unsettled: list[str] = field(default_factory=list)  # steps with no solve after them
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
    moved_mm: float = 0.0,
    warm: bool | None = None,
    entropy: Callable[[int], float] = lambda index: -4.0 - 0.3 * index,
    fraction: float = 0.6,
    kept_steps: int = 1,
    sources: tuple[str, str] = ("hand-eye", "odometry + accelerometer"),
) -> _Run:
    """Run :func:`run_schedule` with rounds that move the translation by ``step_mm(index,
    dense)`` mm (``dense``: a round on the final, denser sample), each reporting a translation
    sigma of :data:`SIGMA_MM`, with LiDAR intrinsics free or none. A round that only evaluates
    moves nothing; the planes-free step after it moves the translation by what the round would
    have, and any other planes-free step by ``refine_mm``. Every round moves the map by
    ``moved_mm``; round ``index`` ends with mean map entropy ``entropy(index)`` (by default
    sharpening by 0.3 a round) and ``fraction`` of the sample on its planes. A planes-free step
    keeps ``kept_steps`` steps (0: rejected, the state does not move)."""
    run = _Run([], [])
    names = ("ext.translation.x", "ext.translation.y", "ext.translation.z")
    report = SimpleNamespace(calibration_names=names, std=(1e-3 * sigma_mm,) * 3, truncated=())
    held: dict[str, float] = {}  # an evaluate-only round's label: the step it left

    def run_round(state, sample, imu, settings, index, mapped=None):  # type: ignore[no-untyped-def]
        dense = sample.dense
        run.rounds.append((f"round {index}", state.label, mapped is not None, dense))
        run.evaluate_only.append(settings.evaluate_only)
        run.distances_m.append(settings.max_dist)
        step = step_mm(index, dense)
        if settings.evaluate_only:
            held[f"round {index}"], step = step, 0.0
        return SimpleNamespace(
            state=_State(f"round {index}", state.x_mm + step),
            summary=SimpleNamespace(
                points=1,
                surfels=1,
                rms_m=0.01,
                map_entropy=entropy(index),
                associated_fraction=fraction,
            ),
            report=report,
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
            state=_State(
                f"step after {state.label}",
                state.x_mm + (held.get(state.label, refine_mm) if kept_steps else 0.0),
            ),
            report=report,
            inputs=inputs,
            steps=kept_steps,
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

    def steps_only(state, inputs, lm, max_steps=free_planes.MAX_STEPS, solved=None):  # type: ignore[no-untyped-def]
        run.unsettled.append(state.label)
        return refine(state, inputs, lm, max_steps, solved)

    monkeypatch.setattr(schedule, "refine_with_planes", refine)
    monkeypatch.setattr(schedule, "planes_free_steps_from", steps_only)
    monkeypatch.setattr(schedule, "_change", change)

    def takes_back(step_from: Any, step_to: Any, after: Any) -> bool:
        step = step_to.x_mm - step_from.x_mm
        return step != 0.0 and (after.x_mm - step_to.x_mm) * step <= -0.5 * step**2

    monkeypatch.setattr(schedule, "takes_back", takes_back)
    monkeypatch.setattr(schedule, "map_movement", lambda before, after, probe: 1e-3 * moved_mm)
    monkeypatch.setattr(schedule, "intrinsic_change", lambda before, after, report: 0.0)
    monkeypatch.setattr(schedule, "sample_points", sample_points)

    def round_points(cfg: Any, n: int) -> tuple[int, int | None]:
        final = cfg.surfels.final_points_per_scan  # 100 points a sweep in the regular rounds
        return 100, final if final is not None and final > 100 else None

    monkeypatch.setattr(schedule, "round_points", round_points)
    monkeypatch.setattr(
        schedule,
        "round_settings",
        lambda cfg, noise, max_dist, *a, evaluate_only=False, **k: SimpleNamespace(
            solver=None, evaluate_only=evaluate_only, max_dist=max_dist
        ),
    )
    monkeypatch.setattr(schedule, "refined_summary", lambda summary, refined: summary)
    monkeypatch.setattr(schedule, "ImuData", SimpleNamespace(from_samples=lambda *a: None))
    monkeypatch.setattr(schedule, "association_distance", lambda cfg, noise: 0.03)
    cfg = CalibConfig.model_validate(
        {
            "schedule": {"max_rounds": 12, "translation_tolerance_m": 1e-5},
            "surfels": {"final_points_per_scan": final_points},
            "model": {"lidar": ["range_offset"] if lidar else []},
        }
    )
    rec = SimpleNamespace(scans=(), imu=None, clock_rate=None)
    guess = SimpleNamespace(
        state=_State("guess", 0.0),
        nominal_elevation=None,
        rotation_source=sources[0],
        translation_source=sources[1],
    )
    warm = lidar if warm is None else warm
    run.fit = schedule.run_schedule(rec, guess, None, cfg, NullProgress(), warm=warm)  # type: ignore[arg-type]
    if lidar and warm:
        # the refinement after the last round always runs with LiDAR intrinsics free
        assert run.refined_from.pop() == run.rounds[-1][0]
        assert run.fit.state.label == f"step after {run.rounds[-1][0]}"
    return run


def _wired_schedule(
    monkeypatch: pytest.MonkeyPatch, steps_mm: list[float], refine_mm: float
) -> tuple[list[tuple[str, str, bool]], list[str], list[str]]:
    """The rounds (label, start, mapped kept), the planes-free steps' starting states and those
    of the steps not followed by a solve, of regular rounds that move the translation by
    ``steps_mm``."""
    run = _schedule(
        monkeypatch, lambda i, dense: steps_mm[min(i - 1, len(steps_mm) - 1)], refine_mm=refine_mm
    )
    return [r[:3] for r in run.rounds], run.refined_from, run.unsettled


def test_a_crawl_takes_a_planes_free_step_before_the_next_round(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # 3.0, 2.4, 1.9, ... mm: each round covers 80 % of the one before (crawling)
    steps = [3.0 * 0.8**k for k in range(12)]
    rounds, refined_from, unsettled = _wired_schedule(monkeypatch, steps, refine_mm=5.0)
    # the first round associates at three times the configured distance, the second at it:
    # from the third on each is compared with a round at the same distance, and crawls
    assert refined_from == ["round 3", "round 4", "round 5"]
    # the crawl's steps are not followed by a solve on their planes: the next round solves
    assert unsettled == refined_from
    assert len(refined_from) == MAX_CRAWL_STEPS
    starts = {label: (start, kept) for label, start, kept in rounds}
    # the round after a step starts from the stepped estimate, with no mapped sample kept
    for k in (4, 5, 6):
        assert starts[f"round {k}"] == (f"step after round {k - 1}", False)
    # past the cap the rounds go on as before: each from the one before, its map kept
    assert starts["round 7"] == ("round 6", True)


def test_a_round_that_takes_the_step_back_is_no_crawl_and_ends_the_steps(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    # rounds 1-3 crawl, the step after round 3 moves +5 mm and round 4 takes 4 mm of it back
    # (the rounds and the step disagree): that is not a crawl, and no step follows
    steps = [3.0, 2.4, 1.92, -4.0, 1.0, 0.3, 0.05, 0.005, 0.001, 0.001, 0.001, 0.001]
    with caplog.at_level("INFO", logger=schedule.__name__):
        run = _schedule(monkeypatch, lambda i, dense: steps[i - 1], lidar=False)
    assert run.refined_from == ["round 3"]
    assert "Round 4 took back the planes-free step before it" in caplog.text
    assert run.fit.converged and len(run.rounds) == 8
    # a round that goes on in the step's direction is judged as before: a crawl, another step
    steps[3] = 4.0
    run = _schedule(monkeypatch, lambda i, dense: steps[i - 1], lidar=False)
    assert run.refined_from[:2] == ["round 3", "round 4"]


def test_takes_back_measures_along_the_step_in_characteristic_scales() -> None:
    def at(x_m: float, yaw_mrad: float) -> Any:
        """A state with only the extrinsic: translation along x, m; yaw, mrad."""
        return SimpleNamespace(
            R_imu_lidar=so3.exp(np.array([0.0, 0.0, 1e-3 * yaw_mrad])),
            t_imu_lidar=np.array([x_m, 0.0, 0.0]),
            time_offset_s=0.0,
        )

    a, b = at(0.0, 0.0), at(0.0, 2.0)  # a step of 2 mrad in yaw
    assert takes_back(a, b, at(0.0, 0.9))  # 1.1 of the 2 mrad back
    assert not takes_back(a, b, at(0.0, 1.1))  # 0.9 back: less than half
    assert not takes_back(a, b, at(0.0, 3.0))  # further on
    # 2 mm across the step (0.2 scales) does not count as taking it back
    assert not takes_back(a, b, at(0.002, 1.5))
    assert not takes_back(a, a, at(0.01, 0.0))  # no step, nothing to take back


def test_crawling_rounds_above_the_base_distance_tighten_it_then_step(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # each round covers 80 % of the one before while the map moves 30 mm a round: three times
    # that never tightens the coarse 9 cm, so the crawl tightens it from the third round on
    steps = [3.0 * 0.8**k for k in range(12)]
    run = _schedule(monkeypatch, lambda i, dense: steps[i - 1], lidar=False, moved_mm=30.0)
    base = 0.03
    expected = [3 * base] * 3 + [max(base, 3 * base * WANDER_SHRINK**k) for k in range(1, 9)]
    assert run.distances_m[: len(expected)] == pytest.approx(expected)
    # at the base distance (round 8, after round 7 at 1.23 times it) the crawl takes
    # planes-free steps, without LiDAR intrinsics too; the round after starts from the step
    assert run.refined_from[:MAX_CRAWL_STEPS] == ["round 8", "round 9", "round 10"]
    starts = {label: start for label, start, _, _ in run.rounds}
    assert starts["round 9"] == "step after round 8"


def test_the_round_after_the_intrinsics_join_is_not_judged_a_crawl(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # the intrinsics join after round 3 (the rounds do not settle): round 4's change is theirs,
    # so only round 5, compared with round 4, can tighten the distance for round 6
    steps = [3.0 * 0.8**k for k in range(20)]
    run = _schedule(
        monkeypatch, lambda i, dense: steps[i - 1], lidar=True, moved_mm=30.0, warm=False
    )
    assert run.distances_m[:6] == pytest.approx([0.09] * 5 + [0.09 * WANDER_SHRINK])


def test_no_step_after_a_round_at_a_wider_distance(monkeypatch: pytest.MonkeyPatch) -> None:
    # round 2, the first at the base distance, moves 1.1 mm after round 1's 1.5 mm at three
    # times it (more than 1 / WANDER_SHRINK): not a crawl, its move comes from the tighter
    # association; the rounds at the base distance then settle
    steps = [1.5, 1.1, 0.45, 0.1, 0.03, 0.01, 0.003, 0.001]
    run = _schedule(monkeypatch, lambda i, dense: steps[min(i, 8) - 1], lidar=False)
    assert run.distances_m[:2] == pytest.approx([0.09, 0.03])
    assert run.refined_from == []


def test_settling_rounds_keep_the_distance_the_map_movement_gives(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # each round moves a third of the one before: not crawling, so 3 x 30 mm holds 9 cm
    steps = [3.0 / 3.0**k for k in range(12)]
    run = _schedule(monkeypatch, lambda i, dense: steps[i - 1], lidar=False, moved_mm=30.0)
    assert run.distances_m == pytest.approx([0.09] * len(run.distances_m))
    assert run.refined_from == []


def test_no_planes_free_step_while_the_rounds_settle(monkeypatch: pytest.MonkeyPatch) -> None:
    # each round moves a third of the one before: converging, not crawling
    steps = [3.0 / 3.0**k for k in range(12)]
    rounds, refined_from, _ = _wired_schedule(monkeypatch, steps, refine_mm=5.0)
    assert refined_from == []
    assert all(kept for label, _, kept in rounds if label != "round 1")


def _summary(entropy: float, fraction: float) -> Any:
    return SimpleNamespace(map_entropy=entropy, associated_fraction=fraction)


def test_a_map_stalls_when_it_blurs_or_stays_blurred_with_few_points_on_its_planes() -> None:
    def stalled(entropies: list[float], fraction: float, **kw: Any) -> bool:
        rounds = [_summary(h, fraction) for h in entropies]
        return stalls(rounds, settled=kw.get("settled", False), steps_taken=kw.get("steps", 0))

    # blurrier by more than STALL_ENTROPY over two rounds: stalled whatever the association
    assert stalled([-3.04, -2.94, -3.04 + 1.5 * STALL_ENTROPY], 0.5)
    # sharper by less than STALL_ENTROPY with few points on the planes (the 20 s sinusoid)
    assert stalled([-2.51, -2.54, -2.51 - 0.5 * STALL_ENTROPY], STALL_FRACTION)
    # the same with most points on the planes: a settled map whose estimate still moves
    assert not stalled([-4.27, -4.27, -4.28], 0.6)
    # sharpening: not stalled, however few points associate
    assert not stalled([-3.0, -3.4, -3.0 - 2 * STALL_ENTROPY], 0.03)
    # a map blurrier by less than STALL_ENTROPY with enough points on it is noise
    assert not stalled([-4.0, -4.0, -4.0 + 0.5 * STALL_ENTROPY], 0.6)
    # not before the third round, not once settled, not past the cap, not without an entropy
    assert not stalled([-2.0, -1.0], 0.01)
    assert not stalled([-3.0, -2.0, -1.0], 0.01, settled=True)
    assert not stalled([-3.0, -2.0, -1.0], 0.01, steps=MAX_CRAWL_STEPS)
    assert not stalled([float("nan"), -2.0, -1.0], 0.01)


def test_a_stalled_map_takes_a_planes_free_step_above_the_base_distance(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # rounds that shrink their steps (by 0.45 a round: no crawl) while the map moves 30 mm a
    # round, so the association stays at three times the base distance; the map stays blurred
    # (entropy -2.5, 3 % of the sample on its planes): from the third round on a planes-free
    # step follows each round, up to the cap
    steps = [3.0 * 0.45**k for k in range(12)]
    run = _schedule(
        monkeypatch,
        lambda i, dense: steps[i - 1],
        lidar=False,
        moved_mm=30.0,
        entropy=lambda index: -2.5,
        fraction=0.03,
    )
    assert run.refined_from[:MAX_CRAWL_STEPS] == ["round 3", "round 4", "round 5"]
    assert run.distances_m[2] == pytest.approx(0.09)
    starts = {label: (start, kept) for label, start, kept, _ in run.rounds}
    assert starts["round 4"] == ("step after round 3", False)
    # the same rounds on a map that sharpens take no step
    sharp = _schedule(monkeypatch, lambda i, dense: steps[i - 1], lidar=False, moved_mm=30.0)
    assert sharp.refined_from == []


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
    # the second dense round starts from the first's planes-free step, on a map rebuilt there
    assert dense[1][1] == f"step after {dense[0][0]}" and not dense[1][2]
    assert run.fit.converged and not run.fit.final_unsettled


def test_a_final_round_within_its_sigmas_runs_once(monkeypatch: pytest.MonkeyPatch) -> None:
    def step(index: int, dense: bool) -> float:
        return (FINAL_SETTLE_SIGMAS - 0.5) * SIGMA_MM if dense else _settling(index)

    run = _schedule(monkeypatch, step, lidar=False, final_points=400)
    assert sum(r[3] for r in run.rounds) == 1
    assert run.fit.converged


@pytest.mark.parametrize(
    ("later_mm", "rounds", "rested"), [(0.05, 2, True), (0.12, 3, False), (0.3, 3, False)]
)
def test_after_unsettled_regular_rounds_the_dense_rounds_go_on_to_rest(
    monkeypatch: pytest.MonkeyPatch, later_mm: float, rounds: int, rested: bool
) -> None:
    """Regular rounds still moving 1 mm (10 sigmas) each at the cap, a first dense round 3
    sigmas: the dense rounds go on until the second or a later one moves at most
    DENSE_REST_SIGMAS (half a sigma: at rest after two), within MAX_FINAL_ROUNDS (1.2 sigmas
    or 3 sigmas a round: three, not at rest; within FINAL_SETTLE_SIGMAS, so no non-convergence
    of the dense rounds, the regular rounds' finding stands). Settled regular rounds run one
    (test_a_final_round_within_its_sigmas_runs_once)."""
    moves = iter([0.3] + [later_mm] * 5)

    def step(index: int, dense: bool) -> float:
        return next(moves) if dense else 1.0

    run = _schedule(monkeypatch, step, lidar=False, final_points=400, refine_mm=0.0)
    dense = [r for r in run.rounds if r[3]]
    assert len(dense) == rounds
    assert dense[1][1] == f"step after {dense[0][0]}" and not dense[1][2]
    fit = run.fit
    assert not fit.converged and not fit.final_unsettled and fit.final_rounds == rounds
    assert fit.final_jump == pytest.approx(10.0 * later_mm)
    assert schedule.dense_rounds_rested(fit) is rested
    (finding,) = checks._convergence(fit, CalibConfig())
    assert finding.severity == ("warn" if rested else "fail")


@pytest.mark.parametrize("moved_mm", [0.0, 0.3, 1.5])
def test_without_lidar_intrinsics_the_dense_round_is_one_planes_free_step(
    monkeypatch: pytest.MonkeyPatch, moved_mm: float
) -> None:
    def step(index: int, dense: bool) -> float:
        return moved_mm if dense else _settling(index)

    run = _schedule(monkeypatch, step, lidar=False, final_points=400, sigma_mm=1.0)
    (last,) = [r for r in run.rounds if r[3]]
    # the regular rounds solve; the dense round only builds and linearises its problem
    assert run.evaluate_only == [r[3] for r in run.rounds]
    # one planes-free step from the dense round's linearisation, whatever it then moves, and no
    # refinement after it
    assert run.refined_from == [last[0]]
    assert run.max_steps == [1]
    assert run.solved_given == [f"solved at {last[0]}"]
    assert run.fit.state.label == f"step after {last[0]}"
    regular = len(run.rounds) - 1
    expected = sum(_settling(i) for i in range(1, regular + 1)) + moved_mm
    assert run.fit.state.x_mm == pytest.approx(expected)
    # the checks get the step's own linearisation
    assert run.fit.solved == f"solved after {last[0]}"
    assert run.fit.converged


@pytest.mark.parametrize("final_points", [400, None])
def test_with_lidar_intrinsics_the_last_round_takes_up_to_max_steps_planes_free_steps(
    monkeypatch: pytest.MonkeyPatch, final_points: int | None
) -> None:
    def step(index: int, dense: bool) -> float:
        return 0.05 if dense else _settling(index)

    run = _schedule(monkeypatch, step, lidar=True, final_points=final_points)
    last = run.rounds[-1]
    assert last[3] == (final_points is not None)
    # a dense round only builds and linearises its problem; without one the last regular round
    # solves as the others did
    assert run.evaluate_only == [r[3] for r in run.rounds]
    # (the refinement after the last round is checked and removed by _schedule)
    assert run.max_steps[-1] == free_planes.MAX_STEPS
    assert run.solved_given[-1] == f"solved at {last[0]}"
    assert run.fit.solved == f"solved after {last[0]}"


def test_dense_rounds_that_keep_jumping_are_a_non_convergence(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    def step(index: int, dense: bool) -> float:
        return 2.0 if dense else _settling(index)

    run = _schedule(monkeypatch, step, lidar=False, final_points=400)
    assert sum(r[3] for r in run.rounds) == MAX_FINAL_ROUNDS
    fit = run.fit
    assert fit.final_unsettled and not fit.converged
    assert fit.final_rounds == MAX_FINAL_ROUNDS
    assert fit.last_change.translation_m == pytest.approx(2e-3)
    cfg = CalibConfig()
    (finding,) = checks._convergence(fit, cfg)
    assert finding.severity == "fail"
    assert finding.text.startswith(
        f"The calibration did not converge: each of the {MAX_FINAL_ROUNDS} denser final rounds"
    )


def test_dense_rounds_that_converge_go_on_past_the_cap_until_they_settle(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Dense rounds moving 40, 16, 6.4 and 2.56 sigmas: each move shrinks to 0.4 of the one
    before, so a fourth round follows the cap of three and settles (within 5 sigmas)."""
    dense_moves: list[float] = []

    def step(index: int, dense: bool) -> float:
        if not dense:
            return _settling(index)
        dense_moves.append(40.0 * 0.4 ** len(dense_moves))
        return dense_moves[-1]

    run = _schedule(monkeypatch, step, lidar=False, final_points=400, sigma_mm=1.0)
    assert sum(r[3] for r in run.rounds) == MAX_FINAL_ROUNDS + 1
    fit = run.fit
    assert fit.converged and not fit.final_unsettled
    assert fit.final_rounds == MAX_FINAL_ROUNDS + 1
    assert fit.final_jump == pytest.approx(2.56)


@pytest.mark.parametrize(("shrink", "rounds"), [(0.6, MAX_FINAL_ROUNDS), (0.5, 6)])
def test_dense_rounds_that_shrink_too_slowly_or_too_long_are_a_non_convergence(
    monkeypatch: pytest.MonkeyPatch, shrink: float, rounds: int
) -> None:
    """Moves shrinking to 0.6 of the one before stop at the cap of three; to 0.5 (1000, 500,
    ... 31 sigmas) at the cap of converging rounds, still beyond 5 sigmas."""
    assert rounds == schedule.MAX_CONVERGING_FINAL_ROUNDS or shrink > schedule.FINAL_SHRINK
    dense_moves: list[float] = []

    def step(index: int, dense: bool) -> float:
        if not dense:
            return _settling(index)
        dense_moves.append(1000.0 * shrink ** len(dense_moves))
        return dense_moves[-1]

    run = _schedule(monkeypatch, step, lidar=False, final_points=400, sigma_mm=1.0)
    assert sum(r[3] for r in run.rounds) == rounds
    fit = run.fit
    assert fit.final_unsettled and not fit.converged
    assert fit.final_rounds == rounds
    (finding,) = checks._convergence(fit, CalibConfig())
    assert f"each of the {rounds} denser final rounds" in finding.text
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


def test_provisional_rounds_stop_early_with_or_without_intrinsics() -> None:
    """A provisional round (a denser final round follows) may leave its last tenths of a sigma
    to the next round, with intrinsics free too (the dense round's planes-free steps take the
    range scales' common mode to the optimum); the final round and every round when there is
    none are solved until a step would gain less than SETTLED_COST_TOLERANCE (under a third of
    a sigma along it), a smaller tolerance than the provisional rounds'."""
    from licalib_cli.pipeline.settings import (
        PROVISIONAL_COST_TOLERANCE,
        SETTLED_COST_TOLERANCE,
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

    assert tolerance(False, True) == tolerance(True, True) == PROVISIONAL_COST_TOLERANCE > 0.0
    assert tolerance(False, False) == tolerance(True, False) == SETTLED_COST_TOLERANCE
    assert 0.0 < SETTLED_COST_TOLERANCE < PROVISIONAL_COST_TOLERANCE


def test_coarse_rounds_stop_at_a_fraction_of_the_cost() -> None:
    """A round associating farther than the configured distance is followed by rounds on a
    rebuilt, tighter map: its solve stops once a step would gain less than
    COARSE_FUNCTION_TOLERANCE of the cost. At the configured distance (the rounds that decide
    convergence, the final round, the planes-free refinements) the solver's own tolerance
    holds."""
    from licalib_cli.pipeline.settings import (
        COARSE_FUNCTION_TOLERANCE,
        NoiseLevels,
        round_settings,
    )
    from licalib_cli.solver.lm import LMParams

    cfg = CalibConfig.model_validate({"surfels": {"max_distance_m": 0.03}})
    gyro, accel = np.full(3, 0.0035), np.full(3, 0.0118)
    noise = NoiseLevels(
        gyro, accel, 0.01, "config", "config", "config", np.full(16, np.nan), gyro, accel, 0.01
    )

    def tolerance(max_distance_m: float, **kwargs: bool) -> float:
        settings = round_settings(cfg, noise, max_distance_m, False, **kwargs)
        return settings.solver.function_tolerance

    assert COARSE_FUNCTION_TOLERANCE > 1e3 * LMParams.function_tolerance
    assert tolerance(0.09) == tolerance(0.031, provisional=True) == COARSE_FUNCTION_TOLERANCE
    assert tolerance(0.03) == tolerance(0.03, provisional=True) == LMParams.function_tolerance
    assert tolerance(0.03, evaluate_only=True) == LMParams.function_tolerance


def test_a_rounds_summary_after_the_planes_free_step_reports_the_refined_fit() -> None:
    """The result's point RMS, the residual histogram and the rounds table read the last round's
    summary: after a planes-free step it holds the distances on the refined planes at the
    refined estimate, not those the round left."""
    from licalib_cli.estimation import Planes
    from licalib_cli.pipeline.round import RoundSummary

    extrinsic = SimpleNamespace(label="round 5")
    summary = RoundSummary(
        index=5,
        free=("extrinsic",),
        max_distance_m=0.05,
        points=3,
        surfels=2,
        associated_fraction=0.9,
        rms_m=0.02,
        cost_start=10.0,
        cost_end=10.0,
        iterations=0,
        extrinsic=extrinsic,  # type: ignore[arg-type]
        seconds=1.0,
        distances_after_m=np.full(3, 0.02, np.float32),
    )
    # two planes z = 0.01 and x = -0.02; the refined points lie 0.01, -0.03 and 0.02 m off them
    planes = Planes(normal=np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]), d=np.array([-0.01, 0.02]))
    points = np.array([[5.0, 1.0, 0.02], [7.0, 2.0, -0.02], [0.0, 3.0, 9.0]])
    refined = SimpleNamespace(
        inputs=SimpleNamespace(lidar=SimpleNamespace(plane=np.array([0, 0, 1])), planes=planes),
        solved=SimpleNamespace(points_global=points),
        report=SimpleNamespace(final_cost=4.5, iterations=2),
        state=SimpleNamespace(R_imu_lidar=np.eye(3), t_imu_lidar=np.ones(3), time_offset_s=0.0),
        steps=1,
        seconds=0.5,
    )
    after = schedule.refined_summary(summary, refined)  # type: ignore[arg-type]
    np.testing.assert_allclose(after.distances_after_m, [0.01, -0.03, 0.02], atol=1e-7)
    assert after.rms_m == pytest.approx(np.sqrt((0.01**2 + 0.03**2 + 0.02**2) / 3))
    assert after.cost_end == 4.5 and after.cost_start == 10.0
    assert after.iterations == 3 and after.seconds == pytest.approx(1.5)
    np.testing.assert_array_equal(after.extrinsic.translation, np.ones(3))
    assert after.index == 5 and after.points == 3


def test_a_map_lost_after_the_first_round_is_told_as_a_divergence(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A map without planes in a later round means the rounds ran away from the initial guess
    (the first round's map had them): the error says so and how to start closer; in the first
    round it is the scene's own sentence."""
    from licalib_cli.errors import ExcitationError, MapLost

    scene = (
        "No planar surfaces were found in the LiDAR map; calibrate in a structured scene "
        "(walls, floor) or raise surfels.cell_sizes_m."
    )

    def lost_in(round_index: int) -> Callable[[int, bool], float]:
        def step_mm(index: int, dense: bool) -> float:
            if index == round_index:
                raise ExcitationError(scene)
            return 700.0

        return step_mm

    with pytest.raises(ExcitationError) as first:
        _schedule(monkeypatch, lost_in(1), lidar=False)
    assert str(first.value) == scene
    with pytest.raises(ExcitationError) as later:
        _schedule(monkeypatch, lost_in(3), lidar=False)
    text = str(later.value)
    assert text.startswith("No planar surfaces were found in the LiDAR map in round 3")
    assert "round 1 had 1 points" in text and "diverged" in text
    assert "1400.00 mm" in text  # how far the two rounds before it moved the estimate
    assert "give initialization.rotation_rpy_deg and initialization.translation_m" in text
    # the model holds the beams of a spinning LiDAR at nominal: beams that disagree blur the
    # map from the first round on, so the error also says how to estimate them
    assert text.endswith(
        "or, if the LiDAR's beams may disagree (per-beam range offsets or angles from an old or "
        "generic beam table blur the map from the first round on; round 1 had 60.0 % of its "
        "points on planes), estimate their intrinsics (licalib calibrate --intrinsics lidar, or "
        "model.lidar in the config)."
    ), text
    # diagnose reads whether the beams were held (it then frees them, beams_in_base)
    assert isinstance(later.value, MapLost) and later.value.beams_held
    with pytest.raises(ExcitationError) as estimated:
        _schedule(monkeypatch, lost_in(3), lidar=True, warm=False)
    assert "diverged" in str(estimated.value) and "--intrinsics lidar" not in str(estimated.value)
    assert isinstance(estimated.value, MapLost) and not estimated.value.beams_held
    # from a rotation and a lever arm the config gave: check those, not give them
    with pytest.raises(ExcitationError) as given:
        _schedule(monkeypatch, lost_in(3), lidar=False, sources=("config", "config"))
    text = " ".join(str(given.value).split())
    assert "check the initialization.rotation_rpy_deg and initialization.translation_m the " in text
    assert "or remove them to start from what the data show" in text and "give " not in text
    with pytest.raises(ExcitationError) as one:
        _schedule(monkeypatch, lost_in(3), lidar=False, sources=("hand-eye", "config"))
    text = str(one.value)
    assert "check the initialization.translation_m the config gives" in text
    assert "rotation_rpy_deg" not in text and "or remove it to start" in text


def test_the_initial_rotation_is_as_uncertain_as_the_gyro_rotation_when_that_is_estimated() -> None:
    names = ("ext.rotation.rx", "ext.translation.x", "imu.accel_misalignment.yz")
    scale = np.array([1e-3, 0.01, 1e-3])
    np.testing.assert_array_equal(initial_sd(names, scale), scale)
    with_gyro = (*names, "imu.gyro_rotation.rx")
    sd = initial_sd(with_gyro, np.r_[scale, 1e-2])
    # initialisation finds the LiDAR-to-gyro rotation: the extrinsic inherits R_wI's prior
    np.testing.assert_array_equal(sd, [1e-2, 0.01, 1e-3, 1e-2])
    # ... or the fit's move of R_wI when the data took it beyond that prior (0.04 rad here)
    sd = initial_sd(with_gyro, np.r_[scale, 1e-2], gyro_rotation_moved=0.04)
    np.testing.assert_allclose(sd, [np.hypot(1e-2, 0.04), 0.01, 1e-3, 1e-2])


def test_held_directions_cover_the_gyro_rotation_the_fit_found(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    names = ("ext.rotation.rx", "ext.rotation.ry", "imu.gyro_rotation.rx", "imu.gyro_rotation.ry")
    scale = np.array([1e-3, 1e-3, 1e-2, 1e-2])
    report: Any = SimpleNamespace(
        truncated=("a held direction",),
        calibration_names=names,
        information=SimpleNamespace(scale=scale),
    )
    seen: dict[str, np.ndarray] = {}

    def widen(report: Any, moved: np.ndarray, initial_sd: np.ndarray) -> Any:
        seen["moved"], seen["sd"] = moved, initial_sd
        return report

    moved = np.array([0.0, 0.0, 0.03, -0.04])  # R_wI moved 0.05 rad (2.9 deg) from its start
    monkeypatch.setattr(schedule, "calibration_moved", lambda a, b, n: moved)
    monkeypatch.setattr(schedule, "widen_along_truncated", widen)
    assert schedule.cover_truncated(report, Any, Any) is report
    np.testing.assert_array_equal(seen["moved"], moved)
    # the extrinsic started where the LiDAR-to-gyro rotation put it: as far off as R_wI is
    np.testing.assert_allclose(seen["sd"], [np.hypot(1e-2, 0.05)] * 2 + [1e-2] * 2)


def test_a_planes_free_step_at_the_cap_gets_the_rounds_that_check_it(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # eleven settling rounds (each under half the one before, above half a sigma), round 12 of
    # 12 crawls: the step after it is checked by a round beyond the cap, which settles
    steps = [200.0 * 0.49**k for k in range(11)] + [0.16, 1e-3, 1e-3, 1e-3]
    run = _schedule(monkeypatch, lambda i, dense: steps[i - 1], lidar=False)
    assert run.refined_from == ["round 12"]
    assert [label for label, *_ in run.rounds][-2:] == ["round 12", "round 13"]
    assert run.rounds[-1][1] == "step after round 12"  # round 13 starts from the step
    assert run.fit.converged and run.fit.extra_rounds == 1
    # a step that kept nothing has nothing to check: the cap holds
    run = _schedule(monkeypatch, lambda i, dense: steps[i - 1], lidar=False, kept_steps=0)
    assert run.refined_from == ["round 12"] and len(run.rounds) == 12
    assert not run.fit.converged and run.fit.extra_rounds == 0
    # without a step near the cap the cap holds: rounds that never settle stop at 12
    run = _schedule(monkeypatch, lambda i, dense: 200.0 * 0.49 ** (i - 1) + 0.0, lidar=False)
    assert len(run.rounds) == 12 and run.fit.extra_rounds == 0
