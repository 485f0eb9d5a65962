"""A base model that lost its map: the beams' intrinsics join it and the check backwards keeps
those the data need (:mod:`licalib_cli.pipeline.beams_in_base`), and ``diagnose`` starts its
selection from that fit. Every fit is scripted."""

from __future__ import annotations

from dataclasses import dataclass
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

import licalib_cli.pipeline.beams_in_base as bb
import licalib_cli.pipeline.diagnose as dg
from licalib_cli.config import load_config
from licalib_cli.errors import ExcitationError, MapLost
from licalib_cli.pipeline.diagnosis_step import CANDIDATES
from licalib_cli.pipeline.lost_map import collapsed_map
from licalib_cli.pipeline.scan_pattern import SPINNING

OFFSET, SCALE, ELEVATION = "lidar_range_offset", "lidar_range_scale", "lidar_elevation"
LOST = MapLost(
    "Only 55 LiDAR points lie on planar surfaces in round 9, although round 1 had 2495 points "
    "on them: the estimate diverged from the initial guess.",
    beams_held=True,
)


def _round(index: int, fraction: float, points: int) -> Any:
    return SimpleNamespace(index=index, associated_fraction=fraction, points=points)


HELD = [_round(1, 0.15, 23451), _round(3, 0.2, 44974), _round(4, 0.25, 60000)]
COLLAPSED = [_round(1, 0.15, 23451), _round(3, 0.2, 44974), _round(12, 0.003, 144)]


@dataclass(frozen=True)
class _Guess:
    state: Any


def _blocks(cfg: Any) -> tuple[str, ...]:
    """The per-beam candidates a config's model estimates."""
    return tuple(
        name
        for name, (sensor, block, _) in CANDIDATES.items()
        if sensor == "lidar" and block in cfg.model.lidar
    )


def _script(
    monkeypatch: pytest.MonkeyPatch,
    deltas: list[dict[str, float]],
    lost_without: str = "",
    collapses: bool = False,
) -> list[tuple[str, ...]]:
    """Fits that record their model's blocks (the one without ``lost_without`` loses its map
    again: an error, or with ``collapses`` a fit on what is left of it), and ``deltas`` as the
    successive BIC tests; returns the models fitted."""
    fitted: list[tuple[str, ...]] = []

    def fit(prepared: Any, start: Any, cfg: Any, *a: Any, **k: Any) -> Any:
        blocks = _blocks(cfg)
        lost = bool(lost_without) and lost_without not in blocks
        if lost and not collapses:
            raise ExcitationError("Only 12 LiDAR points lie on planar surfaces in round 3.")
        fitted.append(blocks)
        return SimpleNamespace(state=blocks, rounds=COLLAPSED if lost else HELD)

    tests = iter(deltas)

    def tested(run: Any, kept: tuple[str, ...], effects: tuple[str, ...], *a: Any) -> Any:
        assert run.state == kept == effects, "each block is tested on the fit of the blocks left"
        out = next(tests)
        assert set(out) == set(kept)
        return out

    monkeypatch.setattr(bb, "fit_and_check", fit)
    monkeypatch.setattr(bb, "deltas_without", tested)
    monkeypatch.setattr(bb, "without_effect", lambda state, effect, start: state)
    return fitted


def _base(beams: tuple[str, ...]) -> tuple[Any, bb.BeamsInBase]:
    prepared = SimpleNamespace(guess=_Guess(state=()))
    return bb.base_with_beams(prepared, load_config(None), beams, str(LOST), None, None)  # type: ignore[arg-type]


def test_blocks_the_data_do_not_need_are_dropped_one_at_a_time_the_worst_first(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    fitted = _script(
        monkeypatch,
        [
            {OFFSET: -512.0, SCALE: 3.0, ELEVATION: 8.5},
            {OFFSET: -498.0, SCALE: 2.1},
            {OFFSET: -470.0},
        ],
    )
    run, beams = _base((OFFSET, SCALE, ELEVATION))
    assert fitted == [(OFFSET, SCALE, ELEVATION), (OFFSET, SCALE), (OFFSET,)]
    assert run.state == (OFFSET,)
    assert beams.kept == (OFFSET,)
    assert beams.dropped == (SCALE, ELEVATION)
    # each block's BIC change where it was last tested: the kept one's on the final fit
    assert beams.delta_bic == {OFFSET: -470.0, SCALE: 2.1, ELEVATION: 8.5}
    assert beams.lost_without == ""
    assert "round 1 had 2495 points" in beams.reason


@pytest.mark.parametrize("collapses", [False, True])
def test_a_block_whose_removal_loses_the_map_again_is_kept(
    monkeypatch: pytest.MonkeyPatch, collapses: bool
) -> None:
    """The BIC on the fit's data would drop the range offsets, but without them the map is
    lost (the planes vanish, or a few points stay on a few): the fit with them stays."""
    fitted = _script(
        monkeypatch, [{OFFSET: 1.5, SCALE: -40.0}], lost_without=OFFSET, collapses=collapses
    )
    run, beams = _base((OFFSET, SCALE))
    assert fitted == [(OFFSET, SCALE)] + ([(SCALE,)] if collapses else [])
    assert run.state == (OFFSET, SCALE)
    assert beams.kept == (OFFSET, SCALE)
    assert beams.lost_without == OFFSET


def test_a_map_lost_with_the_beams_free_too_is_the_error(monkeypatch: pytest.MonkeyPatch) -> None:
    """Beams freed and the map still lost: the user gets that fit's one-sentence error (exit
    code 7), not a diagnosis."""
    lost = MapLost("Only 63 LiDAR points lie on planar surfaces in round 5.", beams_held=False)

    def fit(*a: Any, **k: Any) -> Any:
        raise lost

    monkeypatch.setattr(bb, "fit_and_check", fit)
    with pytest.raises(MapLost, match="round 5") as err:
        _base((OFFSET, SCALE))
    assert err.value.exit_code == 7


def test_a_collapsed_map_is_told_apart_from_a_poor_scene_and_a_held_one() -> None:
    """The rounds lost the map when the last round holds under a tenth of the best round's
    share of points on planes and under a fifth in all; a scene poor from the first round, or
    a last round that keeps its share, is no collapse."""
    assert collapsed_map(COLLAPSED) == (
        "round 12 had 0.3 % of its points on planes (144), round 3 had 20.0 % (44974)"
    )
    assert collapsed_map(HELD) is None
    poor = [_round(1, 0.04, 900), _round(2, 0.03, 700), _round(3, 0.01, 300)]
    assert collapsed_map(poor) is None
    assert collapsed_map([*COLLAPSED[:2], _round(12, 0.019, 4000)]) is not None
    assert collapsed_map([*COLLAPSED[:2], _round(12, 0.021, 4400)]) is None
    assert collapsed_map([]) is None


class _Imu:
    t_ns = np.array([0, 10_000_000_000])

    def __len__(self) -> int:
        return 2


def _diagnose(monkeypatch: pytest.MonkeyPatch, lost: Any, candidates: Any = None) -> Any:
    """``diagnose`` whose base fit loses its map (``lost``: its error, or the rounds of a fit
    whose map collapsed); the beams' fit (``base_with_beams``, which records the candidates it
    was given) shows no further effect."""
    monkeypatch.setattr(
        dg,
        "prepare",
        lambda bag, cfg, *a, **k: SimpleNamespace(
            rec=SimpleNamespace(imu=_Imu()), guess=None, cfg=cfg, pattern=SPINNING
        ),
    )

    def lose(prepared: Any, start: Any, cfg: Any, *a: Any, **k: Any) -> Any:
        assert not cfg.model.lidar
        if isinstance(lost, MapLost):
            raise lost
        return SimpleNamespace(rounds=lost, effects=[])

    given: list[tuple[str, ...]] = []
    with_beams = SimpleNamespace(effects=[])

    def beams(prepared: Any, cfg: Any, allowed: tuple[str, ...], reason: str, *a: Any) -> Any:
        assert reason == (str(lost) if isinstance(lost, MapLost) else collapsed_map(lost))
        given.append(allowed)
        return with_beams, bb.BeamsInBase(
            reason=reason, freed=allowed, kept=(OFFSET,), delta_bic={OFFSET: -900.0}
        )

    monkeypatch.setattr(dg, "fit_and_check", lose)
    monkeypatch.setattr(dg, "base_with_beams", beams)
    monkeypatch.setattr(dg, "twin_of", lambda run, cfg: None)
    monkeypatch.setattr(dg, "_not_shown", lambda run, allowed, found: ())
    monkeypatch.setattr(dg, "noise_spread", lambda prepared, run, cfg, progress, timer: run)
    diag = dg.diagnose("bag.bag", load_config(None), candidates=candidates)
    return diag, given


@pytest.mark.parametrize("lost", [LOST, COLLAPSED], ids=["error", "collapsed"])
def test_diagnose_starts_from_the_beams_a_lost_map_needed(
    monkeypatch: pytest.MonkeyPatch, lost: Any
) -> None:
    diag, given = _diagnose(monkeypatch, lost, candidates=(OFFSET, SCALE, "gyro_scale"))
    assert given == [(OFFSET, SCALE)], "only the per-beam candidates allowed join the base"
    assert diag.effects_found == (OFFSET,)
    assert diag.beams_in_base.kept == (OFFSET,)
    assert diag.base is diag.final
    assert _blocks(diag.config) == (OFFSET,)


def test_a_lost_map_with_the_beams_already_estimated_is_the_error(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A non-repetitive scanner's lost map (no beams held) is not a beam problem."""
    lost = MapLost("Only 3 LiDAR points lie on planar surfaces in round 4.", beams_held=False)
    with pytest.raises(MapLost, match="round 4"):
        _diagnose(monkeypatch, lost)


def test_a_lost_map_without_a_beam_candidate_is_the_error(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    with pytest.raises(MapLost, match="round 1 had 2495 points"):
        _diagnose(monkeypatch, LOST, candidates=("gyro_scale",))


def test_a_fit_on_a_collapsed_map_fails_and_names_the_beams_when_they_are_held() -> None:
    """``calibrate``'s verdict on what diagnose reads as a lost map: a failure that says so,
    and to estimate the beams when the model holds a spinning LiDAR's at nominal; the poor
    map's warning is not repeated beside it."""
    from licalib_cli.pipeline.checks import _lost_map
    from licalib_cli.pipeline.checks import _map as _map_with

    def _map(fit: Any, report: Any) -> Any:  # as run_checks calls it
        return _map_with(fit, report, collapsed_map(fit.rounds))

    def _lost(fit: Any, cfg: Any) -> Any:
        return _lost_map(collapsed_map(fit.rounds), cfg)

    report = SimpleNamespace(variance_factor=1.0)
    held = load_config(None)
    collapsed = SimpleNamespace(rounds=COLLAPSED)
    (finding,) = _lost(collapsed, held)
    assert finding.severity == "fail"
    assert finding.text.startswith(
        "The rounds lost the map (round 12 had 0.3 % of its points on planes (144), round 3 "
        "had 20.0 % (44974)): the estimate ran away from where it started"
    )
    assert finding.text.endswith(
        "estimate their intrinsics (licalib calibrate --intrinsics lidar, or model.lidar in the "
        "config)."
    )
    assert _map(collapsed, report) == []
    estimated = held.model_copy(
        update={"model": held.model.model_copy(update={"lidar": ["range_offset"]})}
    )
    (finding,) = _lost(collapsed, estimated)
    assert finding.severity == "fail" and "--intrinsics lidar" not in finding.text
    # a poor map from the first round on is the warning it was
    poor = SimpleNamespace(rounds=[_round(1, 0.04, 900), _round(3, 0.01, 300)])
    assert _lost(poor, held) == []
    (finding,) = _map(poor, report)
    assert finding.severity == "warn" and finding.text.startswith("Only 1 % of the points")
    held_map = SimpleNamespace(rounds=HELD)
    assert _lost(held_map, held) == [] and _map(held_map, report) == []


def test_diagnose_says_which_beams_joined_the_base_and_which_the_data_do_not_need() -> None:
    from licalib_cli.commands.diagnose import beams_in_base_sentence

    assert beams_in_base_sentence(None) is None
    beams = bb.BeamsInBase(
        reason=str(LOST),
        freed=(OFFSET, SCALE, ELEVATION),
        kept=(OFFSET,),
        delta_bic={OFFSET: -4908080.0, SCALE: 194.2, ELEVATION: 183.9},
    )
    assert beams_in_base_sentence(beams) == (
        "The base model lost its map (Only 55 LiDAR points lie on planar surfaces in round 9, "
        "although round 1 had 2495 points on them): beams that disagree blur it. The beams' "
        "intrinsics joined the base model: lidar_range_offset (BIC -4908080.0 with it) kept; "
        "lidar_range_scale (BIC +194.2), lidar_elevation (BIC +183.9) dropped, the data do not "
        "need them."
    )
    again = bb.BeamsInBase(
        reason=collapsed_map(COLLAPSED) or "",
        freed=(OFFSET, SCALE),
        kept=(OFFSET, SCALE),
        delta_bic={OFFSET: 1.5, SCALE: -40.0},
        lost_without=OFFSET,
    )
    text = beams_in_base_sentence(again) or ""
    assert text.startswith("The base model lost its map (round 12 had 0.3 % of its points")
    assert text.endswith("; without lidar_range_offset the map was lost again.")
