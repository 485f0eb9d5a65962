"""Checks stage: is the result trustworthy? The verdict, the sigmas and what the data cannot tell.

Every finding is a function returning zero or more :class:`Finding` (a severity and one
sentence); the verdict is the worst severity. A check that could not be computed says so (a
``note``) instead of passing silently. The findings:

* convergence: the rounds settled before ``schedule.max_rounds`` (else ``fail``, unless the
  last round moved the extrinsic by less than its reported sigmas: then a ``note``, and the
  sigmas include that change);
* observability: extrinsic directions the data do not determine (``warn``; ``fail`` when fewer
  than half of the coordinates are determined);
* uncertainty: sigmas above the ``checks`` limits, 5 mm / 0.1 deg / 0.2 ms by default (``warn``);
* fit per sensor: residuals beyond the noise, structure left in them (``warn``);
* fixed effects: an effect the model holds fixed that the data show and that would move the
  extrinsic by more than its sigma (``warn``);
* split-half: the two halves of the segment disagree beyond their sigmas (``warn``);
* map: few points on planar surfaces (``warn``), a very poor overall fit (``fail``);
* implausible estimates: a lever arm, a rotation away from a trusted hand-eye, or an IMU bias
  no rig can have (``fail``: the rounds settled in a wrong minimum;
  :mod:`licalib_cli.pipeline.implausible`);
* unchecked priors: a block held fixed whose prior (IMU, or LiDAR when set) the recording
  cannot check, and whose effect below what it shows could move the extrinsic by three of its
  sigmas (``warn``); an effect held fixed without a prior that could do the same (``note``: the
  result takes it as exact; :mod:`licalib_cli.pipeline.unchecked_priors`).

The reported sigmas start from the solver's, each times its factor for the map planes' own
uncertainty (:mod:`licalib_cli.pipeline.map_uncertainty`: the solver holds the planes fixed,
although they were fitted to the same points), and are inflated so that they cover what the
checks found (:mod:`licalib_cli.pipeline.inflation`); the intrinsics' sigmas come from
:mod:`licalib_cli.pipeline.intrinsic_sigmas`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np
import numpy.typing as npt

from licalib_cli.config import INTRINSIC_PRESETS, CalibConfig, ChecksSection
from licalib_cli.io.clock_rate import MATERIAL_MOVE_S, SIGNIFICANT_SIGMAS, ClockRate
from licalib_cli.pipeline.crawl import Crawl, crawl_at_cap
from licalib_cli.pipeline.fitcheck import (
    CHI2_QUIET,
    EffectEvidence,
    effect_evidence,
    model_entries,
    sensor_checks,
)
from licalib_cli.pipeline.held_effects import held_effect_text, held_effects
from licalib_cli.pipeline.implausible import implausible_estimates
from licalib_cli.pipeline.inflation import (
    COVER_P_VALUE,
    effect_is_material,
    effect_to_cover,
    inflate,
    largest_prior,
    split_floor,
    uncovered,
    with_change,
)
from licalib_cli.pipeline.initialise import SINGLE_AXIS, InitialGuess
from licalib_cli.pipeline.intrinsic_sigmas import intrinsics_uncertainty
from licalib_cli.pipeline.lost_map import (
    POOR_MAP_FRACTION,
    beams_advice,
    beams_held,
    collapsed_map,
)
from licalib_cli.pipeline.map_uncertainty import MapUncertainty, map_uncertainty
from licalib_cli.pipeline.points import PointBudget
from licalib_cli.pipeline.prior_directions import (
    OnPrior,
    PriorConflict,
    added_variance,
    data_determined,
    lever_arm_conflict,
    on_prior,
)
from licalib_cli.pipeline.schedule import (
    JITTER_FACTOR,
    Change,
    Fit,
    dense_rounds_rested,
    within,
)
from licalib_cli.pipeline.settings import NoiseLevels, narrow_association, prior_sd
from licalib_cli.pipeline.split import COORDINATES, SplitResult, split_half
from licalib_cli.pipeline.unchecked_priors import (
    assumed_note,
    prior_owner,
    unchecked_priors,
    unchecked_sections,
    unchecked_warning,
)
from licalib_cli.residuals import ACCEL_MISALIGNMENT, EXT_ROTATION, GYRO_ROTATION, TIME_DRIFT
from licalib_cli.results import vec3
from licalib_cli.sections import (
    SPLIT_LABELS,
    Consistency,
    EffectCheck,
    IntrinsicsUncertainty,
    Observability,
    SensorCheck,
    SplitHalf,
    Uncertainty,
    VerdictSection,
    p_is,
)
from licalib_cli.solver.lm import SolverReport
from licalib_cli.solver.observability import DirectionDescription

__all__ = [
    "ACCELEROMETER_FRAME_BLOCKS",
    "ACCELEROMETER_FRAME_SHARE",
    "ENTANGLED_CORRELATION",
    "SPLIT_HALF_P",
    "Checks",
    "Entangled",
    "Finding",
    "accelerometer_frame_advice",
    "accelerometer_frame_partners",
    "at_cap",
    "check",
    "correlated_with",
    "drift_against_stamps",
    "entangled_intrinsics",
    "extrinsic_truncated",
    "judge",
    "moving_extrinsic",
    "observability_of",
    "raw_uncertainty",
    "rejudge",
    "rounds_accepted",
    "run_checks",
    "uncertainty_findings",
]

F64 = npt.NDArray[np.float64]

SPLIT_HALF_P = 1e-3
"""The halves disagree when the chi-square of their difference (with their combined covariance)
has a p-value below this."""

IMU_PRESET = frozenset(INTRINSIC_PRESETS["imu"][0])
"""The IMU blocks ``--intrinsics imu`` estimates (the advice for a prior among them)."""

_SEVERITY = {"note": 0, "warn": 1, "fail": 2}


@dataclass(frozen=True)
class Finding:
    """One finding of a check: ``note`` (informational), ``warn`` or ``fail``.

    ``information``: the finding is about what the data do not determine (directions left
    unobservable, sigmas above the ``checks`` limits), not about how the model fits them; a
    joint problem over several segments checks those again for itself
    (:mod:`licalib_cli.pipeline.joint`).
    """

    severity: str
    text: str
    information: bool = False


@dataclass(frozen=True)
class Checks:
    """The checks' outcome.

    Attributes:
        verdict: the verdict section (status and reasons).
        uncertainty: the reported (inflated) sigmas.
        raw_sigma: (7,) the solver's sigmas before inflation (t m, r rad, dt s).
        observability: the observability section.
        consistency: the consistency section.
        findings: every finding, notes included.
        exit_status: ``"ok"``, ``"fail"`` or ``"not converged"``.
        intrinsics_uncertainty: 1-sigma of the estimated intrinsics (None when none were).
        effects: the score tests of the effects the fit held fixed (selected ones first).
        planes: the sigma factors for the map planes' own uncertainty (None: not computed).
        split: the split-half comparison (None: not kept).
        notes: warnings of earlier stages the verdict took.
        failures: failures of earlier stages the verdict took (estimates no rig can have,
            :mod:`~licalib_cli.pipeline.implausible`).
        choice: (7,) how far a fit with the IMU blocks the recording determines none of held
            instead of estimated moved the extrinsic (t m, r rad, dt s), in the sigmas, and the
            sentence that says so (:mod:`~licalib_cli.pipeline.undetermined`); None: none.
    """

    verdict: VerdictSection
    uncertainty: Uncertainty
    raw_sigma: F64
    observability: Observability
    consistency: Consistency
    findings: tuple[Finding, ...]
    exit_status: str
    intrinsics_uncertainty: IntrinsicsUncertainty | None = None
    effects: tuple[EffectEvidence, ...] = ()
    planes: MapUncertainty | None = None
    split: SplitResult | None = None
    notes: tuple[str, ...] = ()
    failures: tuple[str, ...] = ()
    choice: tuple[F64, str] | None = None


def _std(report: SolverReport, names: list[str]) -> F64:
    out = []
    for n in names:
        try:
            out.append(report.std_of(n))
        except ValueError:
            out.append(float("nan"))
    return np.asarray(out, dtype=np.float64)


_EXTRINSIC_NAMES = (
    *(f"ext.translation.{a}" for a in "xyz"),
    *(f"ext.rotation.r{a}" for a in "xyz"),
    "ext.time_offset",
)


def raw_uncertainty(report: SolverReport, planes: MapUncertainty | None = None) -> F64:
    """(7,) solver sigmas: translation (m), rotation (rad, LiDAR axes), time offset (s); with
    ``planes``, each times its factor for the map planes' own uncertainty."""
    std = _std(report, list(_EXTRINSIC_NAMES))
    if planes is not None:
        std = std * np.array([planes.of(n) for n in _EXTRINSIC_NAMES])
    return std


def observability_of(report: SolverReport, resting: Sequence[OnPrior] = ()) -> Observability:
    """Spectrum of the scaled calibration information, the truncated directions and the
    directions the data leave to the translation's prior (``resting``; the solver keeps those,
    the prior determining them)."""
    return Observability(
        scaling=report.scaling,
        threshold=float(report.tsvd_threshold),
        singular_values=tuple(float(f"{s:.6g}") for s in report.singular_values),
        unobservable=tuple(d.text for d in report.truncated) + tuple(r.text for r in resting),
        weakly_determined=tuple(d.text for d in report.weak),
        weak_floor=float(report.weak_floor),
    )


# ----------------------------------------------------------------------------- the checks


def within_sigmas(change: Change, sigma: F64) -> bool:
    """Whether a round's change of the extrinsic is below its reported 1-sigma: the translation's
    norm below the largest translation sigma, and the rotation and time offset likewise (the
    schedule's jitter band, twice half a sigma, measured with the sigmas the result reports)."""
    half = Change(
        0.5 * float(np.max(sigma[:3])),
        0.5 * float(np.degrees(np.max(sigma[3:6]))),
        0.5 * float(sigma[6]),
    )
    return bool(within(change, half, JITTER_FACTOR))


def at_cap(fit: Fit, sigma: F64) -> tuple[Crawl | None, bool]:
    """Rounds that ran out at the cap (the denser final rounds not unsettled), judged with the
    (7,) ``sigma``: the coordinate their last changes still crawl one way (None: none, or not
    at the cap), and whether the last change lies within ``sigma`` without such a crawl."""
    if fit.converged or fit.final_unsettled:
        return None, False
    crawl = crawl_at_cap([r.extrinsic for r in fit.rounds], sigma)
    return crawl, crawl is None and within_sigmas(fit.last_change, sigma)


def rounds_accepted(fit: Fit, sigma: F64) -> bool:
    """Whether the checks, with the (7,) ``sigma``, take ``fit``'s rounds as converged
    (:func:`_convergence` finds no non-convergence): converged, or at the cap within ``sigma``
    (:func:`at_cap`), or with the denser final rounds after them at rest."""
    if fit.converged:
        return True
    if fit.final_unsettled:
        return False
    return at_cap(fit, sigma)[1] or dense_rounds_rested(fit)


def _convergence(
    fit: Fit, cfg: CalibConfig, settled_in_sigmas: bool = False, crawl: Crawl | None = None
) -> list[Finding]:
    c = fit.last_change
    if fit.final_unsettled:
        return [
            Finding(
                "fail",
                f"The calibration did not converge: each of the {fit.final_rounds} denser final "
                f"rounds moved the estimate by many of its sigmas (the last "
                f"{1e3 * c.translation_m:.1f} mm / {c.rotation_deg:.3f} deg / "
                f"{1e3 * c.time_offset_s:.2f} ms): the denser points pull the estimate away "
                "from where the regular rounds settled (a direction those could not determine, "
                "or a model that does not fit the data) and it has not settled, so the result "
                "is not trustworthy; record more varied motion in a structured scene, and see "
                "the other findings for effects the model lacks.",
            )
        ]
    if not fit.converged and settled_in_sigmas:
        return [
            Finding(
                "note",
                f"After schedule.max_rounds = {cfg.schedule.max_rounds} rounds{_extra(fit)} "
                "the estimate "
                f"still moved {1e3 * c.translation_m:.2f} mm / {c.rotation_deg:.4f} deg / "
                f"{1e3 * c.time_offset_s:.3f} ms per round (the map is rebuilt each round), "
                "less than its reported sigmas; the sigmas include this change.",
            )
        ]
    if not fit.converged and dense_rounds_rested(fit):
        # The regular rounds ran out still moving, but the dense rounds after them, each on a
        # map rebuilt at the estimate, came to rest: a 10 s Avia sinusoid with the IMU's
        # intrinsics estimated wandered by 3-47 mm a round through twelve rounds (its
        # translation traded off with the gyro-to-IMU rotation), then its dense rounds moved
        # 98 mm, 15 mm and 0.7 mm (0.5 of its sigmas), 6.8 mm from the truth within 1.25 of its
        # sigmas; it failed as not converged before.
        return [
            Finding(
                "warn",
                f"After schedule.max_rounds = {cfg.schedule.max_rounds} rounds{_extra(fit)} the "
                f"estimate still moved {1e3 * c.translation_m:.1f} mm / {c.rotation_deg:.3f} deg "
                f"/ {1e3 * c.time_offset_s:.2f} ms per round; the {fit.final_rounds} denser "
                f"final rounds after them came to rest (the last moved it "
                f"{fit.final_jump:.1f} of its sigmas), so the result is where the rounds stop, "
                "but the regular rounds' wandering says the data hold it only loosely: record "
                "more varied motion in a structured scene, and see the other findings for what "
                "trades off with it.",
            )
        ]
    if not fit.converged:
        return [
            Finding(
                "fail",
                f"The calibration did not converge: after schedule.max_rounds = "
                f"{cfg.schedule.max_rounds} rounds{_extra(fit)} the estimate still moved "
                f"{1e3 * c.translation_m:.1f} mm / {c.rotation_deg:.3f} deg / "
                f"{1e3 * c.time_offset_s:.2f} ms per round"
                + (
                    f", and its last {crawl.rounds} rounds moved {crawl.describe()} the same way"
                    if crawl is not None
                    else ""
                )
                + ", so the result is not trustworthy; record more varied motion in a "
                "structured scene, or raise schedule.max_rounds.",
            )
        ]
    if fit.jitter:
        return [
            Finding(
                "note",
                f"The rounds settled to within {1e3 * c.translation_m:.2f} mm / "
                f"{c.rotation_deg:.4f} deg / {1e3 * c.time_offset_s:.3f} ms (the map is "
                "rebuilt each round); the sigmas include this.",
            )
        ]
    return []


def _extra(fit: Fit) -> str:
    """`` (and N more that checked a planes-free step)`` when the rounds ran beyond the cap."""
    n = fit.extra_rounds
    return f" (and {n} more that checked a planes-free step)" if n else ""


ACCELEROMETER_FRAME_SHARE = 0.5
"""An estimated block of the accelerometer's frame (:data:`ACCELEROMETER_FRAME_BLOCKS`) whose
part of a truncated direction is at least this fraction of the direction's extrinsic rotation
part (radians both) turns the accelerometer's frame against the gyro's and the LiDAR's with it.
On the diagnose benchmark's seed 809 (OS1-64 shake, the gyro-to-IMU rotation 1.7 deg per angle,
estimated) the truncated direction held 0.99 mrad of gyro-to-IMU rotation per 1.00 mrad of
extrinsic rotation, while in the scaled coordinates the truncation works in the gyro-to-IMU
rotation's share was 1 % (its characteristic scale is ten times the extrinsic rotation's), too
little to be named; on 20 s shakes with every intrinsic estimated (trust bags 4452, 4456, 4458)
the accelerometer's misalignment held 0.8-1.4 times the extrinsic rotation's part."""

ACCELEROMETER_FRAME_BLOCKS: Mapping[str, tuple[str, str]] = {
    GYRO_ROTATION: ("the gyro-to-IMU rotation", "gyro_rotation"),
    ACCEL_MISALIGNMENT: ("the accelerometer's misalignment", "accel_misalignment"),
}
"""The estimated blocks that turn the accelerometer's frame against the gyro's and the LiDAR's
together with the extrinsic rotation: how a finding calls each, and its name in ``model.imu``."""


def accelerometer_frame_partners(
    report: SolverReport, direction: DirectionDescription
) -> tuple[str, ...]:
    """The blocks of :data:`ACCELEROMETER_FRAME_BLOCKS` that a truncated direction of ``report``
    turns together with the extrinsic rotation (:data:`ACCELEROMETER_FRAME_SHARE`): the IMU frame
    turned against the gyro and the LiDAR, which only the accelerometer sees. Compared in the
    coordinates' own units (radians), not in the scaled ones the truncation and the direction's
    text use. Empty when the direction has no extrinsic rotation part."""
    names = report.calibration_names
    moved = np.asarray(direction.vector, dtype=np.float64) * np.asarray(
        report.information.scale, dtype=np.float64
    )

    def part(block: str) -> float:
        index = [i for i, n in enumerate(names) if n.startswith(block + ".")]
        return float(np.linalg.norm(moved[index])) if index else 0.0

    ext = part(EXT_ROTATION)
    if ext <= 0.0:
        return ()
    return tuple(
        b for b in ACCELEROMETER_FRAME_BLOCKS if part(b) >= ACCELEROMETER_FRAME_SHARE * ext
    )


def extrinsic_truncated(
    report: SolverReport,
) -> tuple[tuple[DirectionDescription, ...], tuple[str, ...]]:
    """The truncated directions of ``report`` that move the extrinsic, and the blocks of
    :data:`ACCELEROMETER_FRAME_BLOCKS` any of them turns with the extrinsic rotation
    (:func:`accelerometer_frame_partners`), in that mapping's order."""
    return moving_extrinsic(report, report.truncated)


def moving_extrinsic(
    report: SolverReport, directions: Sequence[DirectionDescription]
) -> tuple[tuple[DirectionDescription, ...], tuple[str, ...]]:
    """Those of ``directions`` that move the extrinsic, and the blocks of
    :data:`ACCELEROMETER_FRAME_BLOCKS` any of them turns with the extrinsic rotation."""
    moving = tuple(d for d in directions if any(b.startswith("ext.") for b, _ in d.blocks))
    found = {b for d in moving for b in accelerometer_frame_partners(report, d)}
    return moving, tuple(b for b in ACCELEROMETER_FRAME_BLOCKS if b in found)


def _blocks_said(partners: Sequence[str], which: int = 0) -> str:
    """``partners`` (:data:`ACCELEROMETER_FRAME_BLOCKS`) as a finding calls them (``which`` 0)
    or by their ``model.imu`` names (1), joined by "and"."""
    return " and ".join(ACCELEROMETER_FRAME_BLOCKS[b][which] for b in partners)


def accelerometer_frame_advice(partners: Sequence[str]) -> str:
    """What to do when an extrinsic direction is not observable because it turns the
    accelerometer's frame with ``partners`` (:func:`accelerometer_frame_partners`): more rotation
    about more axes, the generic advice, does not help a rig that rotated about all three axes
    without tilting much."""
    said, names = _blocks_said(partners), _blocks_said(partners, 1)
    them = "them" if len(partners) > 1 else "it"
    return (
        f"With {said} estimated ({names}), the extrinsic rotation trades off with {them}: the "
        "accelerometer alone places the IMU frame against the gyro and the LiDAR, from gravity "
        "seen at different attitudes and from the rig's accelerations, and this recording does "
        "not determine it. Record with the rig tilted by tens of degrees about both horizontal "
        "axes (in a longer recording, licalib select-segments with this model ranks the windows "
        f"that determine it), or leave {names} out of the model (model.imu) when the IMU's own "
        f"calibration covers {them} (most IMUs' gyro and accelerometer share one frame)."
    )


def _observability(report: SolverReport, prior: Mapping[str, float]) -> list[Finding]:
    out: list[Finding] = []
    # a prior's directions are never truncated (its scale widens to leave them in: estimation);
    # those the data leave to it are listed in ``observability`` (observability_of)
    ext_truncated, partners = extrinsic_truncated(report)
    if ext_truncated:
        out.extend(
            Finding("warn", f"Not observable from this data: {d.text}") for d in ext_truncated
        )
        out.append(
            Finding(
                "warn",
                accelerometer_frame_advice(partners)
                if partners
                else "Record with rotation about more axes, or set what is not observable from a "
                "measurement (initialization.translation_m, rotation_rpy_deg, time_offset_s).",
            )
        )
    weak, weak_partners = moving_extrinsic(report, report.weak)
    if weak:
        # estimated, its sigma reported: but from information below the threshold, where a
        # linearisation says less, so never a PASS
        out.extend(
            Finding(
                "warn",
                f"Weakly determined by this data: {d.text}; its sigmas rest on little information.",
            )
            for d in weak
        )
        if not ext_truncated:
            out.append(
                Finding(
                    "warn",
                    accelerometer_frame_advice(weak_partners)
                    if weak_partners
                    else "Record with rotation about more axes, or set what is weakly "
                    "determined from a measurement (initialization.translation_m, "
                    "rotation_rpy_deg, time_offset_s).",
                )
            )
    ext = [n for n in report.calibration_names if n.startswith("ext.")]
    n_observable = int(np.count_nonzero(data_determined(report, prior, ext))) if ext else 0
    if ext and n_observable < (len(ext) + 1) // 2:
        out.insert(
            0,
            Finding(
                "fail",
                f"The data determine only {n_observable} of the {len(ext)} extrinsic "
                "coordinates: each of the others lies partly along a direction the data do not "
                "determine (listed below), where the estimate is where the fit left it, not a "
                "measurement. "
                + (
                    f"The extrinsic rotation trades off with {_blocks_said(partners)} (below)."
                    if partners
                    else "Record 10-60 s with rotation about all three axes."
                ),
            ),
        )
    return [replace(f, information=True) for f in out]


ENTANGLED_CORRELATION = 0.7
"""An estimated intrinsic correlated at least this much with the least determined translation
axis is named when the translation is uncertain. On the paper's sinusoid with every intrinsic
free, x is correlated -0.79 with the accelerometer's x-z misalignment and -0.71 with the gyro's
rotation about y, z 0.9 with the accelerometer's x and y scales (benchmarks/RESULTS.md,
2026-12-01, seventeenth stop)."""


@dataclass(frozen=True)
class Entangled:
    """The least determined translation axis and the estimated intrinsics that move with it.

    Attributes:
        axis: ``x``, ``y`` or ``z`` (IMU frame).
        partners: ``(calibration coordinate, correlation)``, strongest first (at most three).
    """

    axis: str
    partners: tuple[tuple[str, float], ...]


def correlated_with(
    names: Sequence[str], covariance: npt.ArrayLike, name: str
) -> list[tuple[str, float]]:
    """Every other coordinate of ``names`` with its correlation to ``name`` in ``covariance``
    (a solver report's ``calibration_names`` and ``covariance``), strongest first; empty when
    ``name`` is not there or its variance is not finite and positive."""
    names = list(names)
    cov = np.asarray(covariance, dtype=float)
    if name not in names or cov.shape != (len(names), len(names)):
        return []
    i = names.index(name)
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    if not np.isfinite(sd[i]) or sd[i] <= 0:
        return []
    with np.errstate(divide="ignore", invalid="ignore"):
        corr = np.where(sd > 0, cov[i] / (sd[i] * sd), 0.0)
    return [(names[j], float(corr[j])) for j in np.argsort(-np.abs(corr), kind="stable") if j != i]


def entangled_intrinsics(report: SolverReport, sigma_t: F64) -> Entangled | None:
    """The estimated intrinsics (``imu.*``, ``lidar.*`` coordinates) correlated by at least
    :data:`ENTANGLED_CORRELATION` with the translation axis of the largest finite sigma in
    ``sigma_t``, from the final solve's covariance; None when there are none."""
    finite = np.isfinite(sigma_t)
    if not np.any(finite):
        return None
    axis = "xyz"[int(np.argmax(np.where(finite, sigma_t, -np.inf)))]
    partners = tuple(
        (n, c)
        for n, c in correlated_with(
            report.calibration_names, report.covariance, f"ext.translation.{axis}"
        )
        if n.startswith(("imu.", "lidar.")) and abs(c) >= ENTANGLED_CORRELATION
    )[:3]
    return Entangled(axis, partners) if partners else None


def _entangled_advice(entangled: Entangled | None) -> str:
    if entangled is None:
        return ""
    listed = ", ".join(f"{n} ({c:+.2f})" for n, c in entangled.partners)
    sections = " and ".join(
        f"model.{k}"
        for k in ("imu", "lidar")
        if any(n.startswith(k) for n, _ in entangled.partners)
    )
    return (
        f" The translation along {entangled.axis} moves with {listed}, which this run "
        f"estimates: leave out of the model (--intrinsics, {sections}) what your sensors' "
        "factory calibration already gives, or record motion that tells them apart."
    )


RESTING_COMPONENT = 0.5
"""A translation axis lies along a direction resting on the measured lever arm when that unit
direction's component on it exceeds this (60 deg)."""


def _resting_advice(sigma_m: F64, limit_m: float, resting: Sequence[OnPrior]) -> str:
    """Advice when a translation axis above ``limit_m`` lies mostly along a direction the data
    leave to the measured lever arm: only a better measurement narrows it there."""
    over = np.isfinite(sigma_m) & (sigma_m > limit_m)
    along = [
        r
        for r in resting
        if np.any(over & (np.abs(np.asarray(r.direction)) > RESTING_COMPONENT))
        and r.sigma_m > limit_m
    ]
    if not along:
        return ""
    widest = max(along, key=lambda r: r.sigma_m)
    axis = ", ".join(f"{v:.2f}" for v in widest.direction)
    return (
        f" Along [{axis}] (IMU frame) it is the measured lever arm's {1e3 * widest.sigma_m:.3g} "
        "mm (initialization.translation_sigma_m): the data do not determine the translation "
        "there, so only a more precise measurement (or rotation about more axes) narrows it."
    )


_MORE_ROTATION = " Record with more rotation about all axes (and a quieter IMU)."


def more_points_advice(points: PointBudget | None) -> str:
    """Advice when the last round kept far fewer points of each sweep than a sweep holds: the
    translation's and the time offset's information grows with them (on the paper's 10 s
    sinusoid 15 000 instead of 6000 a sweep took the translation from 1.86 to 1.36 mm off on
    average over twenty bags and turned both of their WARNs for a sigma into PASS)."""
    if points is None or not points.more_available:
        return ""
    return (
        f" The last round kept {points.kept} of about {points.available} points a sweep: more "
        "(surfels.final_points_per_scan, within surfels.max_points over the whole recording) "
        "narrow it, for time and memory."
    )


def uncertainty_findings(
    sigma: F64,
    without_effects: F64,
    limits: ChecksSection,
    covered: Sequence[str] = (),
    prior: str | None = None,
    entangled: Entangled | None = None,
    resting: Sequence[OnPrior] = (),
    halves: SplitResult | None = None,
    noisy: F64 | None = None,
    points: PointBudget | None = None,
) -> list[Finding]:
    """Sigmas above the ``checks`` limits (5 mm / 0.1 deg / 0.2 ms by default).

    ``noisy``: (7,) the spread of refits with more range noise
    (:mod:`~licalib_cli.pipeline.noise_draws`); a coordinate whose spread alone exceeds its
    limit is said to be held there by the LiDAR's range noise.

    ``without_effects`` are the sigmas without what the ``covered`` effects (held fixed, shown
    by the data) and the IMU priors (``prior``: the block that adds most, None when none do)
    add: when those alone are within the limits, the finding names them instead of the motion
    as the cause. ``entangled`` (:func:`entangled_intrinsics`): the estimated intrinsics that
    move with the least determined translation axis, named in the translation's finding.
    ``resting`` (:func:`~licalib_cli.pipeline.prior_directions.on_prior`): the translation
    directions the data leave to a measured lever arm; an axis above the limit along one is
    said to be the measurement's. ``halves``: the split-half comparison; a coordinate whose
    floor from it (:func:`split_floor`) alone exceeds the limit is said to be held there by the
    halves' difference. ``points``: the last round's points per sweep; when a sweep holds
    many more, the translation's and the time offset's findings say that more narrow them
    (:func:`more_points_advice`). Every finding is marked ``information``."""
    out = []
    t, r, c = sigma[:3], np.degrees(sigma[3:6]), float(sigma[6])
    t_max, r_max = limits.max_translation_sigma_m, limits.max_rotation_sigma_deg
    c_max = limits.max_time_offset_sigma_s
    sources = []
    if covered:
        sources.append(
            f"the effects the model holds fixed ({', '.join(covered)}); estimate them "
            f"({model_entries(covered)} in the config) where the data support them, which "
            "licalib diagnose (or calibrate --model auto) tests"
        )
    if prior is not None:
        what, where = prior_owner([prior])
        sensor = "LiDAR" if prior.startswith("lidar_") else "IMU"
        # --intrinsics imu estimates the IMU blocks but g-sensitivity; the LiDAR's point_time
        # is no intrinsic of --intrinsics lidar: its model entry then
        how = "--intrinsics imu" if prior in IMU_PRESET else model_entries([prior])
        sources.append(
            f"the {what} held fixed, known only to within {where} (most from {prior}); "
            f"estimate them ({how}) or set your {sensor}'s calibration accuracy there"
        )

    def cause(over_without_effects: bool, advice: str) -> str:
        if sources and not over_without_effects:
            return f" It comes from {'; and from '.join(sources)}."
        return advice

    def noise_advice(lo: int, hi: int, limit: float, advice: str) -> str:
        """``advice``, or the range noise's when the refits' spread alone exceeds ``limit``."""
        if noisy is None or not np.nanmax(noisy[lo:hi]) > limit:
            return advice
        return (
            " The LiDAR's range noise holds it there: refits with as much noise again scatter "
            "that far. A longer recording (or --segments over more of the bag), or a LiDAR with "
            "less range noise, narrows it."
        )

    floor = split_floor(halves) if halves is not None and halves.ran else np.zeros(7)

    def from_halves(k: int, limit: float) -> str:
        """Why coordinate ``k`` (the group's worst above ``limit``) is held up by the halves."""
        if not floor[k] > limit:
            return ""
        assert halves is not None
        label, size = _split_difference(halves, k)
        return (
            f" The two halves of the segment differ by {size} in {label} "
            f"({float(halves.z[k]):.1f} of their combined sigmas), and half of that beyond its "
            "expected spread stays in the sigma: a longer recording (or --segments over more "
            "of the bag) narrows it."
        )

    def worst(lo: int, hi: int) -> int:
        """The coordinate of ``lo:hi`` the halves hold highest (the floor is finite)."""
        return lo + int(np.argmax(floor[lo:hi]))

    finite_t = t[np.isfinite(t)]
    if finite_t.size and finite_t.max() > t_max:
        t0 = without_effects[:3]
        out.append(
            Finding(
                "warn",
                f"Translation is uncertain (1-sigma up to {1e3 * finite_t.max():.3g} mm, "
                f"above checks.max_translation_sigma_m = {1e3 * t_max:g} mm)."
                + cause(
                    bool(np.any(t0[np.isfinite(t0)] > t_max)),
                    noise_advice(0, 3, t_max, _MORE_ROTATION) + more_points_advice(points),
                )
                + from_halves(worst(0, 3), t_max)
                + _entangled_advice(entangled)
                + _resting_advice(t, t_max, resting),
            )
        )
    finite_r = r[np.isfinite(r)]
    if finite_r.size and finite_r.max() > r_max:
        r0 = np.degrees(without_effects[3:6])
        out.append(
            Finding(
                "warn",
                f"Rotation is uncertain (1-sigma up to {finite_r.max():.3g} deg, above "
                f"checks.max_rotation_sigma_deg = {r_max:g} deg)."
                + cause(
                    bool(np.any(r0[np.isfinite(r0)] > r_max)),
                    noise_advice(3, 6, np.radians(r_max), ""),
                )
                + from_halves(worst(3, 6), np.radians(r_max)),
            )
        )
    if np.isfinite(c) and c > c_max:
        out.append(
            Finding(
                "warn",
                f"Time offset is uncertain (1-sigma {1e3 * c:.3g} ms, above "
                f"checks.max_time_offset_sigma_s = {1e3 * c_max:g} ms)."
                + cause(
                    bool(without_effects[6] > c_max),
                    noise_advice(6, 7, c_max, "") + more_points_advice(points),
                )
                + from_halves(6, c_max),
            )
        )
    return [replace(f, information=True) for f in out]


_SENSOR_NAME = {"gyro": "gyro", "accelerometer": "accelerometer", "lidar": "LiDAR"}
_NOISE_KEY = {
    "gyro": "noise.gyro_noise_density",
    "accelerometer": "noise.accel_noise_density",
    "lidar": "noise.range_sigma_m",
}


def _sensors(sensors: tuple[SensorCheck, ...]) -> list[Finding]:
    out = []
    for s in sensors:
        name = _SENSOR_NAME[s.sensor]
        if s.status == "excess":
            where = (
                f"check {_NOISE_KEY[s.sensor]} in the config, or"
                if s.noise_source == "config"
                else "the noise was measured from the data, so"
            )
            out.append(
                Finding(
                    "warn",
                    f"The {name} residuals are {np.sqrt(s.chi2_per_sample):.2f} times their "
                    f"noise (chi-square {s.chi2_per_sample:.2f} per sample): {where} the "
                    f"{name} model does not explain the data.",
                )
            )
        elif s.noise_source == "config" and s.chi2_per_sample < CHI2_QUIET:
            out.append(
                Finding(
                    "note",
                    f"The {name} residuals are {np.sqrt(s.chi2_per_sample):.2f} of their noise "
                    f"(chi-square {s.chi2_per_sample:.2f} per sample, RMS "
                    f"{_size(s.rms, s.unit)} against {_size(max(s.noise), s.unit)}): "
                    f"{_NOISE_KEY[s.sensor]} in the config states the {name} noisier than the "
                    "data show, so the sigmas are wider than the data support; lower it, or "
                    "remove it to have the noise measured.",
                )
            )
        for p in s.patterns:
            if p.material:
                out.append(
                    Finding(
                        "warn",
                        f"The {name} residuals depend on the {p.feature} ({100 * p.explained:.0f} "
                        f"% of their variance, {_size(p.size, s.unit)}): the {name} model lacks "
                        "an effect.",
                    )
                )
    return out


def _size(value: float, unit: str) -> str:
    if unit == "m":
        return f"{1e3 * value:.1f} mm"
    return f"{value:.2g} {unit}"


def _effects(effects: list[EffectEvidence], raw_sigma: F64) -> list[Finding]:
    """One finding per sensor whose data show material effects the model holds fixed."""
    out = []
    for sensor, label in (("imu", "IMU"), ("lidar", "LiDAR")):
        material = sorted(
            (e for e in effects if e.sensor == sensor and effect_is_material(e, raw_sigma)),
            key=lambda e: -e.score.statistic,
        )
        if not material:
            continue
        top = material[0]
        shift = (
            f"{1e3 * float(np.linalg.norm(top.shift_translation_m)):.1f} mm / "
            f"{float(np.degrees(np.linalg.norm(top.shift_rotation_rad))):.3f} deg / "
            f"{1e3 * abs(top.shift_time_offset_s):.2f} ms"
        )
        moves = (
            "a refit with it estimated moved the extrinsic by"
            if top.refitted
            else "estimating it would move the extrinsic by about"
        )
        others = ", ".join(e.score.name for e in material[1:])
        also = f" (and beyond it: {others})" if others else ""
        if top.measured:
            out.append(
                Finding(
                    "warn",
                    f"The IMU's stamps drift against the LiDAR's by "
                    f"{1e6 * top.measured_value:+.1f} ppm (their record times), a clock drift "
                    f"the model holds fixed{also}; held fixed at that rate it moves the "
                    f"extrinsic by about {shift}, beyond its sigma. Add clock_drift to "
                    "model.imu, or synchronise the sensors' clocks and re-record.",
                )
            )
            continue
        out.append(
            Finding(
                "warn",
                f"The {label} data show an effect the model holds fixed, {top.score.name} "
                f"(score test {top.score.statistic:.0f} on {top.score.rank} degrees of "
                f"freedom){also}; {moves} {shift}, beyond its sigma. Estimate "
                f"{'them' if others else 'it'} ({model_entries([e.score.name for e in material])}"
                " in the config; licalib diagnose tests which effects the data support), or "
                "treat the extrinsic as off by at least that.",
            )
        )
    return out


def _split_difference(split: SplitResult, k: int) -> tuple[str, str]:
    """Coordinate ``k`` of the halves' difference as a user reads it: its label and the
    difference in mm, deg or ms (second half minus first)."""
    value = float(split.difference[k])
    text = (
        f"{1e3 * value:+.2f} mm"
        if k < 3
        else f"{np.degrees(value):+.4f} deg"
        if k < 6
        else f"{1e3 * value:+.3f} ms"
    )
    return SPLIT_LABELS[COORDINATES[k]], text


def _split(split: SplitResult) -> list[Finding]:
    if not split.ran:
        return [Finding("note", f"Split-half check not run: {split.reason}.")]
    if split.p_value >= SPLIT_HALF_P:
        return []
    most = ""
    if np.any(np.isfinite(split.z)):
        k = int(np.nanargmax(split.z))
        label, text = _split_difference(split, k)
        most = f"; the most, {label} by {text}, {split.z[k]:.1f} combined sigmas"
    return [
        Finding(
            "warn",
            f"The two halves of the segment disagree (chi-square {split.chi2:.0f} on {split.dof} "
            f"degrees of freedom, {p_is(split.p_value, 1)}{most}): something changes over the "
            "recording (a drifting bias, a clock running at another rate, a loose mount) that "
            "the model does not describe.",
        )
    ]


def _lost_map(collapsed: str | None, cfg: CalibConfig) -> list[Finding]:
    """The rounds lost the map they had (``collapsed``, :func:`collapsed_map`'s sentence): the
    fit rests on a few points on a few planes, and what the data seem not to determine follows
    from that. The verdict's first reason."""
    if collapsed is None:
        return []
    advice = f"; {beams_advice()}" if beams_held(cfg) else ""
    return [
        Finding(
            "fail",
            f"The rounds lost the map ({collapsed}): the estimate ran away from where it "
            "started and rests on the few points left on planes; start closer "
            "(initialization.rotation_rpy_deg and translation_m, or check them if the config "
            f"gives them){advice}.",
        )
    ]


def _map(fit: Fit, report: SolverReport, collapsed: str | None) -> list[Finding]:
    """A poor map (unless it collapsed: :func:`_lost_map` says so) and a poor fit."""
    out = []
    last = fit.rounds[-1]
    if last.associated_fraction < POOR_MAP_FRACTION and collapsed is None:
        out.append(
            Finding(
                "warn",
                f"Only {100 * last.associated_fraction:.0f} % of the points lie on planar "
                "surfaces; the map may be poor.",
            )
        )
    if report.variance_factor > 25:
        out.append(
            Finding(
                "fail",
                f"The fit is poor (residuals {np.sqrt(report.variance_factor):.0f}x their "
                "expected size); the model does not explain the data.",
            )
        )
    return out


def _prior_conflict(conflict: PriorConflict | None) -> list[Finding]:
    if conflict is None or not conflict.disagrees:
        return []
    return [Finding("warn", conflict.text)]


# ------------------------------------------------------------------------ verdict


def judge(findings: list[Finding]) -> tuple[VerdictSection, str]:
    """Verdict from the findings: the worst severity; notes do not count.

    Returns:
        ``(verdict, exit_status)`` with ``exit_status`` ``"not converged"`` when the rounds did
        not converge, ``"fail"`` for another failure, else ``"ok"``.
    """
    worst = max((_SEVERITY[f.severity] for f in findings), default=0)
    status = {0: "pass", 1: "warn", 2: "fail"}[worst]
    ordered = sorted(
        (f for f in findings if f.severity != "note"), key=lambda f: -_SEVERITY[f.severity]
    )
    reasons = tuple(f.text for f in ordered)
    if status != "fail":
        exit_status = "ok"
    elif any(f.text.startswith("The calibration did not converge") for f in findings):
        exit_status = "not converged"
    else:
        exit_status = "fail"
    return VerdictSection(status, reasons), exit_status


def check(
    fit: Fit,
    guess: InitialGuess,
    noise: NoiseLevels,
    cfg: CalibConfig,
    *,
    rivals: bool = False,
    clock_rate: ClockRate | None = None,
) -> Checks:
    """The checks stage: gather the evidence on the fit (residuals per sensor, score tests of
    the fixed effects, the two halves) and judge it (:func:`run_checks`). ``rivals``: also
    which candidates stand in for each significant effect (``effect_evidence``'s).
    ``clock_rate``: the rate of the IMU's stamps against the LiDAR's measured from the record
    times (:mod:`licalib_cli.io.clock_rate`), which an estimated clock drift must match."""
    # All in this process: a forked second process for the map planes' uncertainty was slower
    # (both processes then pay a page copy for every page of the freed heap they write,
    # which ``parallel.memory`` keeps for reuse; on a 10 s OS1-64 bag the checks took 2.2 s
    # forked and 1.3 s here). That uncertainty comes from the last planes-free step when the
    # final round took them; the two halves are estimated one per block thread.
    planes = map_uncertainty(fit.state, fit.inputs, fit.report, fit.solved)
    sensors = sensor_checks(fit.state, fit.inputs, noise, fit.solved)
    # a clock drift the model holds fixed is known to within the stamps' rate; one they show
    # moves the extrinsic by its shift at that rate
    measured = (
        {"imu_clock_drift": (clock_rate.rate, clock_rate.sigma, clock_rate.material)}
        if clock_rate is not None and TIME_DRIFT not in fit.report.calibration_names
        else None
    )
    effects = effect_evidence(
        fit.state,
        fit.inputs,
        fit.report.variance_factor,
        cfg.model,
        planes_free_p=COVER_P_VALUE,
        rivals=rivals,
        measured=measured,
        hint_p=COVER_P_VALUE,
    )
    split = split_half(fit.state, fit.inputs, cfg, fit.report)
    notes: tuple[str, ...] = ()
    if guess.rotation_source == SINGLE_AXIS:
        along = (
            "comes from initialization.translation_m and its sigma"
            if cfg.initialization.translation_sigma_m is not None
            else "is not observable"
        )
        notes = (
            "The rig turned about one axis only; the rotation about it rests on the "
            f"accelerations, and the translation along it {along}.",
        )
    narrow = narrow_association(cfg, noise)
    if narrow is not None:
        notes = (*notes, narrow)
    if clock_rate is not None and TIME_DRIFT in fit.report.calibration_names:
        k, sd = fit.state.time_drift, fit.report.std_of(TIME_DRIFT)
        differs = drift_against_stamps(k, sd, clock_rate)
        notes = (*notes, differs) if differs else notes
    return run_checks(
        fit,
        sensors,
        effects,
        split,
        cfg,
        notes,
        planes,
        failures=implausible_estimates(fit, guess, cfg),
    )


def drift_against_stamps(k: float, sd: float, rate: ClockRate) -> str | None:
    """A sentence when the estimated clock drift ``k`` (1-sigma ``sd``, s/s) differs from the
    rate the stamps show against the record times by more than :data:`~licalib_cli.io.
    clock_rate.SIGNIFICANT_SIGMAS` of their combined sigma and by at least
    :data:`~licalib_cli.io.clock_rate.MATERIAL_MOVE_S` over the segment; else None. Both
    measure the same stamps' relation, so a drift that differs stands in for something else."""
    if not (np.isfinite(k) and np.isfinite(sd)):
        return None
    gap = abs(k - rate.rate)
    z = gap / max(float(np.hypot(sd, rate.sigma)), 1e-300)
    if z <= SIGNIFICANT_SIGMAS or gap * rate.span_s < MATERIAL_MOVE_S:
        return None
    return (
        f"The clock drift estimated, {1e6 * k:+.1f} +/- {1e6 * sd:.1f} ppm, differs from the "
        f"rate of the sensors' stamps against the record times, {1e6 * rate.rate:+.1f} +/- "
        f"{1e6 * rate.sigma:.1f} ppm, by {z:.0f} sigmas: the drift stands in for something the "
        "model lacks (licalib diagnose names it), or the recorder's delays changed over the "
        "recording."
    )


def run_checks(
    fit: Fit,
    sensors: tuple[SensorCheck, ...],
    effects: list[EffectEvidence],
    split: SplitResult,
    cfg: CalibConfig,
    notes: tuple[str, ...] = (),
    planes: MapUncertainty | None = None,
    spread: tuple[F64, str] | None = None,
    failures: tuple[str, ...] = (),
    choice: tuple[F64, str] | None = None,
) -> Checks:
    """Every check on the fit, the inflated sigmas and the verdict.

    Args:
        fit: the rounds' outcome.
        sensors: residual checks per sensor (:func:`~licalib_cli.pipeline.fitcheck.
            sensor_checks`).
        effects: score tests of the fixed effects.
        split: the split-half comparison.
        cfg: the configuration.
        notes: warnings of earlier stages (one sentence each), e.g. single-axis motion.
        planes: the sigma factors of the map planes' own uncertainty
            (:func:`~licalib_cli.pipeline.map_uncertainty.map_uncertainty`); None: not applied.
        spread: (7,) a floor of the sigmas measured by refits with more noise, and the
            sentence that says so (:mod:`~licalib_cli.pipeline.noise_draws`); None: none.
        failures: failures of earlier stages (one sentence each), e.g. an estimate that ended
            far from the hand-eye rotation it started from.
        choice: (7,) how far holding the IMU blocks the recording determines none of moves
            the extrinsic, added to the sigmas in quadrature, and the sentence that says so
            (:mod:`~licalib_cli.pipeline.undetermined`); None: none.

    Returns:
        The checks' outcome.
    """
    report = fit.report
    raw = raw_uncertainty(report, planes)
    sigma, why = inflate(raw, sensors, effects, split, fit)
    # Rounds still moving at the cap, by less than the sigmas the checks arrived at (their
    # solver sigmas are smaller than what the fixed effects and the halves add): the change is
    # a jitter of the rounds within the result's uncertainty, covered like the schedule's;
    # unless their last changes crawl one way beyond the sigmas (pipeline/crawl.py): then they
    # are still on their way, and have not converged.
    crawl, settled_in_sigmas = at_cap(fit, sigma)
    if settled_in_sigmas:
        sigma = with_change(sigma, fit.last_change)
        why = (*why, "by the last round's change (the rounds settled only to within it)")
    worst = max((planes.of(n) for n in _EXTRINSIC_NAMES), default=1.0) if planes else 1.0
    if planes is not None and worst > 1.005:
        why = (
            f"times up to {worst:.2f} for the {planes.planes} map planes estimated from the "
            "same points (solver sigmas hold them fixed)",
            *why,
        )
    if spread is not None:
        floor, text = spread
        grown = np.maximum(sigma, floor)
        if np.any(grown > sigma * (1 + 1e-9)):
            why = (*why, _grown_by(sigma, grown, text))
        sigma = grown
    if choice is not None:
        moved, text = choice
        grown = np.sqrt(sigma**2 + np.asarray(moved) ** 2)
        why = (*why, _grown_by(sigma, grown, text))
        sigma = grown
    prior = prior_sd(cfg)
    resting = on_prior(report, prior)
    # the data's own estimate as uncertain as the checks found the result
    conflict = lever_arm_conflict(
        report, cfg, fit.state.t_imu_lidar, added_variance(raw[:3], sigma[:3])
    )
    if conflict is not None and conflict.disagrees:
        sigma = sigma.copy()
        sigma[:3] = conflict.covered(sigma[:3])
        why = (*why, "by how far the measured lever arm pulled the translation from the data's")
    collapsed = collapsed_map(fit.rounds)
    findings = _lost_map(collapsed, cfg)
    findings += [Finding("fail", f) for f in failures]
    findings += [Finding("warn", n) for n in notes]
    findings += _prior_conflict(conflict)
    findings += _convergence(fit, cfg, settled_in_sigmas, crawl)
    findings += _observability(report, prior)
    findings += [Finding("note", held_effect_text(*h), True) for h in held_effects(report, cfg)]
    covered = [e.score.name for e in effects if effect_to_cover(e, raw)]
    without_effects, _ = inflate(raw, sensors, [], split, fit)
    if spread is not None:  # the noise's spread is no effect held fixed
        without_effects = np.maximum(without_effects, spread[0])
    if choice is not None:  # nor the choice of the model's undetermined blocks
        without_effects = np.sqrt(without_effects**2 + np.asarray(choice[0]) ** 2)
    findings += uncertainty_findings(
        sigma,
        without_effects,
        cfg.checks,
        covered,
        largest_prior(effects, raw),
        entangled_intrinsics(report, sigma[:3]),
        resting,
        split,
        spread[0] if spread is not None else None,
        fit.points,
    )
    findings += _sensors(sensors)
    findings += _effects(effects, raw)
    findings += _split(split)
    findings += _map(fit, report, collapsed)
    # an IMU block held fixed whose prior the recording cannot check, and whose error of the
    # size it cannot show would move the extrinsic beyond its sigmas
    unchecked = unchecked_priors(uncovered(effects, raw), sigma)
    warning = unchecked_warning(unchecked)
    if warning is not None:
        findings.append(Finding("warn", warning, True))
    # an effect taken as exact whose error the recording cannot show could do the same
    assumed = assumed_note(unchecked)
    if assumed is not None:
        findings.append(Finding("note", assumed, True))
    verdict, exit_status = judge(findings)
    chi = max((c.chi2_per_sample for c in sensors), default=1.0)
    intrinsics = intrinsics_uncertainty(
        report, cfg, max(chi, 1.0) ** 0.5, fit.state.lidar_intrinsics.num_beams, planes
    )
    consistency = Consistency(
        sensors=sensors,
        effects=tuple(_effect_section(e, raw) for e in effects),
        split_half=_split_section(split),
        inflation=why,
        unchecked_priors=unchecked_sections(unchecked),
    )
    return Checks(
        verdict=verdict,
        uncertainty=Uncertainty(
            translation_std_m=vec3(sigma[:3]),
            rotation_std_deg=vec3(np.degrees(x) for x in sigma[3:6]),
            time_offset_std_s=float(sigma[6]),
        ),
        raw_sigma=raw,
        observability=observability_of(report, resting),
        consistency=consistency,
        findings=tuple(findings),
        exit_status=exit_status,
        intrinsics_uncertainty=intrinsics,
        effects=tuple(effects),
        planes=planes,
        split=split,
        notes=notes,
        failures=failures,
        choice=choice,
    )


def _grown_by(sigma: F64, grown: F64, text: str) -> str:
    """``text``, the reason the sigmas grew from ``sigma`` to ``grown``, with the largest
    factor (the result's ``consistency.inflation``)."""
    ratio = float(np.nanmax(np.where(sigma > 0, grown / sigma, 1.0)))
    return f"{text} (times up to {ratio:.2f})"


def rejudge(
    fit: Fit,
    checks: Checks,
    effects: Sequence[EffectEvidence],
    cfg: CalibConfig,
    spread: tuple[F64, str] | None = None,
    choice: tuple[F64, str] | None = None,
) -> Checks:
    """The checks again on the same evidence, with the effects' tests replaced by ``effects``
    (their shifts measured another way, :mod:`licalib_cli.pipeline.effect_refit`), the
    sigmas at least ``spread`` and ``choice`` (``checks.choice`` when None) in them
    (:func:`run_checks`)."""
    if checks.split is None:
        msg = "the checks kept no split-half comparison to judge again"
        raise ValueError(msg)
    return run_checks(
        fit,
        checks.consistency.sensors,
        list(effects),
        checks.split,
        cfg,
        checks.notes,
        checks.planes,
        spread,
        failures=checks.failures,
        choice=checks.choice if choice is None else choice,
    )


def _effect_section(e: EffectEvidence, raw: F64) -> EffectCheck:
    return EffectCheck(
        name=e.score.name,
        sensor=e.sensor,
        statistic=float(e.score.statistic),
        dof=int(e.score.rank),
        p_value=float(e.score.p_value),
        shift_translation_m=vec3(e.shift_translation_m),
        shift_rotation_deg=vec3(np.degrees(x) for x in e.shift_rotation_rad),
        shift_time_offset_s=float(e.shift_time_offset_s),
        selected=e.selected,
        material=effect_is_material(e, raw),
        covered=effect_to_cover(e, raw),
        refitted=e.refitted,
        measured=e.measured,
    )


def _split_section(s: SplitResult) -> SplitHalf:
    if not s.ran:
        return SplitHalf("not run", reason=s.reason, halves_s=s.half_s)
    return SplitHalf(
        status="disagree" if s.p_value < SPLIT_HALF_P else "agree",
        halves_s=s.half_s,
        max_z=s.max_z,
        chi2=s.chi2,
        dof=s.dof,
        p_value=s.p_value,
        difference_translation_m=tuple(float(x) for x in s.difference[:3]),
        difference_rotation_deg=tuple(float(np.degrees(x)) for x in s.difference[3:6]),
        difference_time_offset_s=float(s.difference[6]),
        compared=s.compared,
    )
