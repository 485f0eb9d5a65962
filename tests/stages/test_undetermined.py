"""IMU blocks the recording determines none of: the choice to estimate them, in the sigmas
(``licalib_cli.pipeline.undetermined``).

Which blocks count as undetermined is read from the solver's report (every number of the block
not observable or held by the truncated SVD); the stage then fits the segment again from the
initial guess with them held and puts how far that moves the extrinsic into the sigmas. The fits
are stand-ins here: the stage's own decisions are tested (how the checks add the move is in
``tests/integration/test_checks_e2e.py``; ``bench_consistency.py --model imu --lidars avia
mid360`` runs it end to end).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from types import SimpleNamespace

import numpy as np
import pytest
from finished_runs import finished_run

from licalib_cli.config import CalibConfig
from licalib_cli.errors import SolverError
from licalib_cli.geometry import so3
from licalib_cli.pipeline import undetermined
from licalib_cli.pipeline.checks import Finding, rounds_accepted
from licalib_cli.pipeline.schedule import Change
from licalib_cli.pipeline.undetermined import Choice
from licalib_cli.results import Extrinsic
from licalib_cli.sections import ModelInfo, Uncertainty


def _report(held: dict[str, float], unobservable: tuple[str, ...] = ()) -> SimpleNamespace:
    """A solver report over the gyro scale, the accelerometer misalignment, the g-sensitivity
    (first row) and a gyro bias walk: ``held`` gives coordinates' truncated weights (0 else),
    ``unobservable`` the coordinates reported not observable."""
    names = (
        *(f"imu.gyro_scale.{a}" for a in "xyz"),
        *(f"imu.accel_misalignment.{a}" for a in "xyz"),
        *(f"imu.gyro_g_sensitivity.{k}" for k in range(3)),
        *(f"imu.gyro_bias_drift.{a}" for a in "xyz"),
        "ext.translation.x",
    )
    return SimpleNamespace(
        calibration_names=names,
        truncated_weight=np.array([held.get(n, 0.0) for n in names]),
        observable=np.array([n not in unobservable for n in names]),
    )


def _cfg() -> CalibConfig:
    cfg = CalibConfig()
    imu = ["gyro_scale", "accel_misalignment", "g_sensitivity", "gyro_bias_walk"]
    return cfg.model_copy(update={"model": cfg.model.model_copy(update={"imu": imu})})


ALL_HELD = {f"imu.accel_misalignment.{a}": 0.9 for a in "xyz"}


def test_a_block_with_every_number_held_is_undetermined() -> None:
    assert undetermined.undetermined_blocks(_report(ALL_HELD), _cfg()) == ("accel_misalignment",)
    g = {f"imu.gyro_g_sensitivity.{k}": 1.0 for k in range(3)}
    assert undetermined.undetermined_blocks(_report(g), _cfg()) == ("g_sensitivity",)


def test_a_block_with_one_number_determined_is_not() -> None:
    held = {**ALL_HELD, "imu.accel_misalignment.y": 0.3}  # below HELD_WEIGHT: determined
    assert undetermined.undetermined_blocks(_report(held), _cfg()) == ()
    some = {"imu.gyro_scale.x": 1.0, "imu.gyro_scale.y": 1.0}  # z determined
    assert undetermined.undetermined_blocks(_report(some), _cfg()) == ()


def test_numbers_not_observable_count_as_undetermined() -> None:
    names = tuple(f"imu.gyro_scale.{a}" for a in "xyz")
    assert undetermined.undetermined_blocks(_report({}, names), _cfg()) == ("gyro_scale",)


def test_a_held_effect_has_its_own_note() -> None:
    """A bias walk the fit held is said by ``held_effects``, not weighed here."""
    held = {f"imu.gyro_bias_drift.{a}": 1.0 for a in "xyz"}
    assert undetermined.undetermined_blocks(_report(held), _cfg()) == ()


STILL = Change(0.0, 0.0, 0.0)
SIGMA = np.array([1e-3, 1e-3, 2e-3, 1e-3, 1e-3, 1e-3, 2e-5])


def _extrinsic(tz: float = 0.0) -> Extrinsic:
    return Extrinsic(so3.exp(np.zeros(3)), np.array([0.1, 0.2, tz]), 0.0)


@dataclass(frozen=True)
class _Fit:
    """A stand-in for the rounds' outcome: how they ended and their estimates."""

    tz: float = 0.0
    converged: bool = True
    final_unsettled: bool = False
    last_change: Change = STILL
    moves: tuple[float, ...] = ()
    final_rounds: int = 1
    final_jump: float = 0.0
    report: SimpleNamespace = field(default_factory=lambda: _report(ALL_HELD))

    @property
    def state(self) -> SimpleNamespace:
        e = _extrinsic(self.tz)
        return SimpleNamespace(
            R_imu_lidar=e.rotation, t_imu_lidar=e.translation, time_offset_s=e.time_offset_s
        )

    @property
    def rounds(self) -> tuple[SimpleNamespace, ...]:
        return tuple(SimpleNamespace(extrinsic=_extrinsic(z)) for z in self.moves)


JITTER = (0.0, 1e-4, 0.0, 1e-4)
"""The last rounds' t_z: back and forth, not one way."""
CRAWL = (0.0, 3e-3, 6e-3, 9e-3, 12e-3)
"""The last rounds' t_z: one way, by more than its sigma each time."""


@pytest.mark.parametrize(
    ("fit", "settled"),
    [
        (_Fit(), True),
        (_Fit(converged=False, final_unsettled=True), False),
        # at the cap, the last change within the sigmas and the last rounds not going one way
        (_Fit(converged=False, last_change=Change(2e-4, 0.0, 0.0), moves=JITTER), True),
        # at the cap, still moving by more than the sigmas
        (_Fit(converged=False, last_change=Change(5e-3, 0.0, 0.0), moves=JITTER), False),
        # at the cap, the last rounds going one way by more than the sigmas
        (_Fit(converged=False, moves=CRAWL), False),
        # the same, but two denser final rounds after them came to rest
        (_Fit(converged=False, moves=CRAWL, final_rounds=2, final_jump=0.2), True),
    ],
)
def test_a_fit_with_the_blocks_held_counts_when_the_checks_would_accept_its_rounds(
    fit: _Fit, settled: bool
) -> None:
    """The stage takes the rule the checks judge convergence by (``rounds_accepted``)."""
    assert rounds_accepted(fit, SIGMA) is settled  # type: ignore[arg-type]


def _checks(status: str = "warn") -> SimpleNamespace:
    u = Uncertainty(
        translation_std_m=tuple(SIGMA[:3]),
        rotation_std_deg=tuple(np.degrees(SIGMA[3:6])),
        time_offset_std_s=float(SIGMA[6]),
    )
    return SimpleNamespace(exit_status=status, split="halves", effects=(), uncertainty=u)


class _Stage:
    """The fits and judgements the stage asks for, answered by stand-ins."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch, held: object) -> None:
        self.schedules: list[tuple[object, tuple[str, ...]]] = []
        self.choices: list[tuple[np.ndarray, str]] = []

        def run_schedule(rec, start, noise, cfg, progress):  # type: ignore[no-untyped-def]
            self.schedules.append((start, tuple(cfg.model.imu)))
            if isinstance(held, Exception):
                raise held
            return held

        def rejudge(fit, checks, effects, cfg, *, choice):  # type: ignore[no-untyped-def]
            self.choices.append(choice)
            return "judged again"

        def judged_again(prepared, run, checks, cfg, timer):  # type: ignore[no-untyped-def]
            return SimpleNamespace(name="judged again", checks=checks)

        monkeypatch.setattr(undetermined, "run_schedule", run_schedule)
        monkeypatch.setattr(undetermined, "rejudge", rejudge)
        monkeypatch.setattr(undetermined, "judged_again", judged_again)


class _Timer:
    def stage(self, *args: object, **kwargs: object) -> object:
        from contextlib import nullcontext

        return nullcontext()


def _weigh(run: SimpleNamespace, cfg: CalibConfig | None = None) -> tuple[object, Choice | None]:
    prepared = SimpleNamespace(rec=None, guess="the initial guess", noise=None)
    return undetermined.weigh_undetermined(prepared, run, cfg or _cfg(), None, _Timer())  # type: ignore[arg-type]


def test_the_move_of_a_fit_with_the_blocks_held_goes_into_the_sigmas(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    stage = _Stage(monkeypatch, _Fit(tz=3e-3))
    run = SimpleNamespace(fit=_Fit(), state=_Fit().state, checks=_checks())
    cfg = _cfg()
    judged, choice = _weigh(run, cfg)
    # from the initial guess, with the block left out of the model (the given config unchanged)
    assert stage.schedules == [
        ("the initial guess", ("gyro_scale", "g_sensitivity", "gyro_bias_walk"))
    ]
    assert cfg.model.imu[1] == "accel_misalignment"
    assert choice is not None and choice.blocks == ("accel_misalignment",)
    np.testing.assert_allclose(choice.moved, [0, 0, 3e-3, 0, 0, 0, 0], atol=1e-12)
    ((moved, text),) = stage.choices
    np.testing.assert_allclose(moved, choice.moved)
    assert text.startswith("by how far holding accel_misalignment at nominal")
    assert judged.name == "judged again"  # type: ignore[attr-defined]


@pytest.mark.parametrize(
    ("report", "status", "held"),
    [
        (_report({}), "warn", _Fit(tz=3e-3)),  # nothing undetermined
        (_report(ALL_HELD), "not converged", _Fit(tz=3e-3)),  # the rounds did not settle
        (_report(ALL_HELD), "warn", SolverError("no step reduced the cost")),  # the fit failed
        (_report(ALL_HELD), "warn", _Fit(converged=False, final_unsettled=True)),
    ],
)
def test_otherwise_the_run_stands_as_it_is(
    monkeypatch: pytest.MonkeyPatch, report: SimpleNamespace, status: str, held: object
) -> None:
    stage = _Stage(monkeypatch, held)
    run = SimpleNamespace(fit=_Fit(report=report), state=_Fit().state, checks=_checks(status))
    judged, choice = _weigh(run)
    assert judged is run and choice is None and stage.choices == []


def test_the_result_names_the_blocks_and_a_note_gives_the_move() -> None:
    run = finished_run(ModelInfo(imu=("gyro_scale",)), Finding("warn", "w"))
    moved = np.array([0.0, 0.0, 2.5e-3, 0.0, np.radians(0.1), 0.0, 3e-6])
    out = undetermined.with_choice(run, Choice(("accel_misalignment",), moved))  # type: ignore[arg-type]
    assert out.result.model.undetermined == ("accel_misalignment",)
    note, warning = out.checks.findings
    assert note.severity == "note"
    assert note.text.startswith("The recording determines none of the numbers of accel_misal")
    assert "2.50 mm / 0.1000 deg / 0.003 ms" in note.text
    assert warning == Finding("warn", "w")
    assert undetermined.with_choice(run, None) is run  # type: ignore[arg-type]


def test_the_result_file_keeps_the_blocks() -> None:
    info = replace(ModelInfo(imu=("gyro_scale",)), undetermined=("accel_misalignment",))
    assert ModelInfo.from_dict(info.to_dict()) == info
    assert ModelInfo.from_dict(ModelInfo().to_dict()).undetermined == ()
