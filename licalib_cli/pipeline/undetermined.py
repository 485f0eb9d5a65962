"""IMU blocks the recording determines none of: what estimating them instead of holding them
does to the extrinsic, in its sigmas.

A block of the model (``model.imu``: the accelerometer's misalignment, the gyro-to-IMU rotation
...) is estimated only where the data determine it: the truncated SVD holds every direction
below its threshold, and the sigmas include how far the fit moved along each. When none of a
block's numbers is determined, the fit still moved them in the rounds before the truncation
held them, and the numbers it determines, the extrinsic among them, moved with them by more than
the widening along the held directions covers. On a 10 s Avia shake that hardly tilted the rig,
``--intrinsics imu``: the accelerometer's misalignment (truth 0) ended at 1.2-2.3e-3 with every
number of it undetermined, the gyro's y scale 5.4 of its sigmas off, and the translation 8.83
mm off with t_x at 3.9 of its 0.61 mm sigma. The same bag with the block held at nominal came
out 6.08 mm off. Neither choice is better in general: holding the block leans on its prior
(``model.imu_prior``), and on six Livox shakes whose fits left the same block undetermined
holding it gave errors of 1.19-3.13 of the sigmas, where estimating it gave 0.75-1.58.

The data cannot choose between the two, so the result keeps the model as configured and its
sigmas include the difference: this stage fits the segment again from the initial guess with
those blocks held at nominal, and adds how far that moves the extrinsic, in quadrature, to the
sigmas (:func:`~licalib_cli.pipeline.checks.run_checks`'s ``choice``). The result's
``model.undetermined`` names the blocks, and a note says how far the choice moves the extrinsic.
On that Avia shake holding the block moved the extrinsic by 2.82 mm / 0.106 deg; with that in
the sigmas t_x lies at 1.7 and t_z at 2.3 of them (the second fit took 17 s). A fit whose
rounds did not converge, or a fit with the blocks held that does not, is left as it is (its own
findings say why).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
import numpy.typing as npt

from licalib_cli.config import CalibConfig
from licalib_cli.errors import LicalibError
from licalib_cli.pipeline import CalibrationRun, Prepared, judged_again
from licalib_cli.pipeline.checks import Checks, Finding, rejudge, rounds_accepted
from licalib_cli.pipeline.held_effects import EFFECT_BLOCKS, HELD_WEIGHT
from licalib_cli.pipeline.round import extrinsic_of
from licalib_cli.pipeline.schedule import run_schedule
from licalib_cli.pipeline.settings import calibration_block
from licalib_cli.pipeline.timing import Timer
from licalib_cli.progress import Progress
from licalib_cli.solver.lm import SolverReport

__all__ = [
    "Choice",
    "choice_note",
    "sigma_of",
    "undetermined_blocks",
    "weigh_undetermined",
    "with_choice",
    "without",
]

F64 = npt.NDArray[np.float64]

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class Choice:
    """How far holding the undetermined blocks moves the extrinsic.

    Attributes:
        blocks: the IMU blocks the recording determines none of, in the model's order.
        moved: (7,) the fit with them held minus the fit estimating them: translation (m, IMU
            frame), rotation (rad, about the LiDAR axes), time offset (s).
    """

    blocks: tuple[str, ...]
    moved: F64

    @property
    def text(self) -> str:
        """Why the sigmas grew (the result's ``consistency.inflation``)."""
        names = ", ".join(self.blocks)
        return (
            f"by how far holding {names} at nominal instead of estimating "
            f"{'it' if len(self.blocks) == 1 else 'them'} moves the estimate (the recording "
            f"determines none of {'its' if len(self.blocks) == 1 else 'their'} numbers)"
        )


def undetermined_blocks(report: SolverReport, cfg: CalibConfig) -> tuple[str, ...]:
    """The IMU intrinsic blocks of ``cfg.model.imu`` none of whose numbers ``report``
    determines: each not observable, or held (more than
    :data:`~licalib_cli.pipeline.held_effects.HELD_WEIGHT` of it in truncated directions, where
    the result gives it no sigma). The effects (a bias walk, a clock drift) have their own note
    (:mod:`~licalib_cli.pipeline.held_effects`)."""
    weight = dict(zip(report.calibration_names, report.truncated_weight, strict=True))
    determined = {
        n: bool(o) and weight[n] <= HELD_WEIGHT
        for n, o in zip(report.calibration_names, report.observable, strict=True)
    }
    out = []
    for block in cfg.model.imu:
        if block in EFFECT_BLOCKS:
            continue
        prefix = f"{calibration_block(block)}."
        mine = [d for n, d in determined.items() if n.startswith(prefix)]
        if mine and not any(mine):
            out.append(str(block))
    return tuple(out)


def without(cfg: CalibConfig, blocks: Sequence[str]) -> CalibConfig:
    """``cfg`` whose ``model.imu`` leaves out ``blocks``."""
    imu = [b for b in cfg.model.imu if b not in blocks]
    return cfg.model_copy(update={"model": cfg.model.model_copy(update={"imu": imu})})


def weigh_undetermined(
    prepared: Prepared,
    run: CalibrationRun,
    cfg: CalibConfig,
    progress: Progress,
    timer: Timer,
) -> tuple[CalibrationRun, Choice | None]:
    """``run`` judged again with the choice of its undetermined blocks in its sigmas
    (module docstring), and that choice; ``run`` and None when it has no such block, its rounds
    did not converge, or the fit with the blocks held failed or did not converge.

    Args:
        prepared: the segment, noise and initial guess.
        run: the calibration of ``cfg``'s model.
        cfg: the configuration.
        progress: progress sink.
        timer: stage timer (the fit with the blocks held adds a stage).
    """
    blocks = undetermined_blocks(run.fit.report, cfg)
    if not blocks or run.checks.exit_status == "not converged" or run.checks.split is None:
        return run, None
    names = ", ".join(blocks)
    logger.info(
        "The recording determines none of the numbers of %s: fitting again with %s held at "
        "nominal, to put the difference in the sigmas.",
        names,
        "it" if len(blocks) == 1 else "them",
    )
    try:
        with timer.stage("blocks held", progress, total=cfg.schedule.max_rounds):
            held = run_schedule(
                prepared.rec, prepared.guess, prepared.noise, without(cfg, blocks), progress
            )
    except LicalibError as exc:
        logger.warning("The fit with %s held failed (%s); not in the sigmas.", names, exc)
        return run, None
    if not rounds_accepted(held, sigma_of(run.checks)):
        logger.warning("The fit with %s held did not converge; not in the sigmas.", names)
        return run, None
    choice = Choice(blocks, extrinsic_of(run.state).moved_to(extrinsic_of(held.state)))
    logger.info(
        "Holding %s moves the extrinsic by %.2f mm / %.4f deg / %.3f ms.",
        names,
        1e3 * float(np.linalg.norm(choice.moved[:3])),
        float(np.degrees(np.linalg.norm(choice.moved[3:6]))),
        1e3 * abs(float(choice.moved[6])),
    )
    checks = rejudge(
        run.fit, run.checks, run.checks.effects, cfg, choice=(choice.moved, choice.text)
    )
    return judged_again(prepared, run, checks, cfg, timer), choice


def sigma_of(checks: Checks) -> F64:
    """(7,) the sigmas ``checks`` report: translation (m), rotation (rad), time offset (s)."""
    u = checks.uncertainty
    return np.array(
        [*u.translation_std_m, *np.radians(u.rotation_std_deg), u.time_offset_std_s], np.float64
    )


def choice_note(choice: Choice) -> str:
    """The verdict's note on the undetermined blocks (:func:`weigh_undetermined`)."""
    one = len(choice.blocks) == 1
    names = " and ".join(choice.blocks)
    m = choice.moved
    return (
        f"The recording determines none of the numbers of {names}: estimated, "
        f"{'it stays' if one else 'they stay'} where the fit left {'it' if one else 'them'}, "
        f"and held at nominal the extrinsic moves by {1e3 * np.linalg.norm(m[:3]):.2f} mm / "
        f"{np.degrees(np.linalg.norm(m[3:6])):.4f} deg / {1e3 * abs(m[6]):.3f} ms; the sigmas "
        "include that difference (the result's model.undetermined). Record with the rig tilted "
        "by tens of degrees about both horizontal axes and turned about all three (licalib "
        "select-segments with this model ranks the windows of a longer recording that "
        f"determine {'it' if one else 'them'}), or leave {'it' if one else 'them'} out of "
        "model.imu when the IMU's own calibration covers "
        f"{'it' if one else 'them'}."
    )


def with_choice(run: CalibrationRun, choice: Choice | None) -> CalibrationRun:
    """``run`` whose result names the undetermined blocks and whose findings note the choice
    (after the last stage that assembles the result again)."""
    if choice is None:
        return run
    result = run.result
    if result.model is not None:
        result = replace(result, model=replace(result.model, undetermined=choice.blocks))
    checks = replace(
        run.checks, findings=(Finding("note", choice_note(choice)), *run.checks.findings)
    )
    return replace(run, result=result, checks=checks)
