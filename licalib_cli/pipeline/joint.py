"""Multi-segment calibration (``calibrate --segments``): one problem over several segments of a
bag (method.md section 8, the paper's Sec. VI "Calibration with Informative Segments").

The segments share the extrinsic (``ext.rotation``, ``ext.translation``) and every intrinsic
the model estimates; each keeps its own trajectory spline, IMU biases, gravity and time offset
(and clock or bias drifts when estimated). How it runs:

1. Every segment is calibrated on its own, exactly as ``calibrate --start/--duration`` does
   (its rounds, checks and sigmas): these are the per-segment estimates of the result.
2. The joint problem starts from those fits with the shared blocks at the estimate of the
   segment with the smallest sigmas (the problem: :mod:`licalib_cli.pipeline.joint_problem`).
   Each segment's residual blocks keep their own parameter
   block names; per-segment blocks are renamed ``seg<k>:<name>`` (a thin adapter renames the
   Jacobians), shared blocks keep their name, so the solver's Schur complement, truncated SVD
   and sigmas apply unchanged.
3. :data:`JOINT_ROUNDS` rounds: the first on each segment's own final associations, the next
   ones with every segment's map and associations rebuilt from the joint estimate.
4. With LiDAR intrinsics estimated, a planes-free refinement of the joint problem
   (:func:`~licalib_cli.pipeline.joint_planes.refine_segments_with_planes`): the rounds hold
   each segment's map planes fixed, which pull the common mode of the range offsets and scales
   towards the values the maps were built with; the refinement estimates every segment's planes
   with the rest, one segment eliminated at a time. The solver then settles the joint problem on
   the refined planes and its report gives the joint sigmas.

The joint sigmas start from the joint solver's and are enlarged from what each segment's checks
found (:func:`_growth`): a segment's own enlargements (the residuals' chi-square, the split
halves, the last round's change) are weighted by the information the segment brings; the shift
of an effect held fixed that a segment's checks cover enlarges the joint solver's sigma by the
largest factor any segment needed when the segments' tests of it together show it (an effect
of the rig), by that segment's share of the information otherwise (that window's misfit, or a
bias drift); the IMU priors, which every segment shares, are added whole.
The sigmas grow further when the segments' own estimates scatter about the joint one beyond
their sigmas (:func:`_scatter_factor`). The joint problem is not checked on its own beyond that.

The intrinsics written are the joint problem's (shared by the segments); the biases and gravity
are the reference segment's (the one with the smallest sigmas).

A segment whose own estimate differs from the joint one by more than
:data:`DISAGREEMENT_SIGMAS` of its own sigma (any translation or rotation axis) is flagged.
The verdict is ``warn`` when a segment disagrees, when a segment alone does not pass (a short
segment may not determine everything; the joint problem may), when the joint problem leaves
an extrinsic direction unobservable or when a measured lever arm
(``initialization.translation_sigma_m``) disagrees with the segments' data (their own joint
estimate, recovered as for one segment; the translation sigmas then grow by how far the
measurement pulled the estimate); ``pass`` otherwise.
"""

from __future__ import annotations

import itertools
import logging
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import numpy.typing as npt

from licalib_cli.config import CalibConfig
from licalib_cli.consistency.score import EffectScore, combined_score
from licalib_cli.errors import ConfigError, ExcitationError
from licalib_cli.estimation import (
    CalibrationState,
    Planes,
    state_from_values,
)
from licalib_cli.geometry import so3
from licalib_cli.io.bag import open_bag
from licalib_cli.io.window import MIN_SEGMENT_S
from licalib_cli.pipeline import CalibrationRun
from licalib_cli.pipeline.assemble import extra_terms
from licalib_cli.pipeline.checks import (
    Finding,
    accelerometer_frame_advice,
    entangled_intrinsics,
    extrinsic_truncated,
    moving_extrinsic,
    uncertainty_findings,
)
from licalib_cli.pipeline.inflation import (
    COVER_P_VALUE,
    effect_to_cover,
    prior_variance,
    uncovered,
)
from licalib_cli.pipeline.intrinsic_sigmas import intrinsics_uncertainty
from licalib_cli.pipeline.joint_planes import refine_segments_with_planes
from licalib_cli.pipeline.joint_problem import joint_problem, segment_values
from licalib_cli.pipeline.map_uncertainty import MapUncertainty
from licalib_cli.pipeline.points import (
    joint_point_budget,
    points_in_global,
    solver_points,
    usable_points,
)
from licalib_cli.pipeline.prior_directions import lever_arm_conflict, on_prior
from licalib_cli.pipeline.round import RoundInputs
from licalib_cli.pipeline.scan_pattern import with_scan_pattern
from licalib_cli.pipeline.schedule import cover_truncated
from licalib_cli.pipeline.segment_runs import calibrate_windows, sigma_size
from licalib_cli.pipeline.segments import select_segments
from licalib_cli.pipeline.segments_evident import add_evident_to_windows
from licalib_cli.pipeline.segments_model import SegmentsModel, model_for_segments
from licalib_cli.pipeline.settings import (
    association_distance,
    lm_params,
    prior_sd,
    round_settings,
)
from licalib_cli.pipeline.unchecked_priors import (
    UncheckedPrior,
    combined_unchecked_priors,
    prior_owner,
    unchecked_sections,
    unchecked_text,
    unchecked_warning,
)
from licalib_cli.progress import NullProgress, Progress
from licalib_cli.residuals import (
    EXT_ROTATION,
    EXT_TRANSLATION,
    TIME_OFFSET,
)
from licalib_cli.results import CalibrationResult, Extrinsic, rpy_deg_from_matrix, vec3
from licalib_cli.sections import (
    AddedEffect,
    Observability,
    SegmentEstimate,
    SegmentsSection,
    Uncertainty,
    VerdictSection,
)
from licalib_cli.solver.lm import SolverReport, solve
from licalib_cli.surfels import associate_points, build_surfels

__all__ = [
    "DISAGREEMENT_SIGMAS",
    "JOINT_ROUNDS",
    "JointRun",
    "calibrate_segments",
    "parse_segments",
]

logger = logging.getLogger(__name__)

F64 = npt.NDArray[np.float64]
_NS = 1_000_000_000

DISAGREEMENT_SIGMAS = 3.0
"""A segment whose estimate lies further than this many of its own sigmas from the joint one
(on any translation or rotation axis) is flagged."""

JOINT_ROUNDS = 2
"""Joint optimisation rounds (the later ones on maps rebuilt from the joint estimate)."""

# ---------------------------------------------------------------------------- parsing


def parse_segments(text: str, bag_s: float) -> list[tuple[float, float]]:
    """``"60-75,105-120"`` as ``[(60, 75), (105, 120)]`` (seconds after the bag start).

    Raises:
        ConfigError: a malformed window, an end before its start, a window beyond the bag, or
            overlapping windows.
        ExcitationError: a window shorter than :data:`MIN_SEGMENT_S`.
    """
    out: list[tuple[float, float]] = []
    for part in (p.strip() for p in text.split(",")):
        try:
            a_text, b_text = part.split("-")
            a, b = float(a_text), float(b_text)
        except ValueError:
            msg = (
                f"Invalid --segments window {part!r}: give START-END in seconds after the bag "
                "start, separated by commas (for example 60-75,105-120), or auto."
            )
            raise ConfigError(msg) from None
        if not (np.isfinite(a) and np.isfinite(b)) or b <= a:
            msg = f"Invalid --segments window {part!r}: its end must come after its start."
            raise ConfigError(msg)
        if b > bag_s + 1e-6:
            msg = (
                f"The --segments window {part} reaches past the end of the bag ({bag_s:.1f} s); "
                "give windows within the bag (licalib info shows its duration)."
            )
            raise ConfigError(msg)
        if b - a < MIN_SEGMENT_S:
            msg = (
                f"The --segments window {part} lasts only {b - a:g} s, too short to calibrate; "
                f"give at least {MIN_SEGMENT_S:g} s per window (10-20 s of varied motion)."
            )
            raise ExcitationError(msg)
        out.append((a, b))
    ordered = sorted(out)
    for (a0, b0), (a1, b1) in itertools.pairwise(ordered):
        if a1 < b0 - 1e-9:
            msg = (
                f"The --segments windows {a0:g}-{b0:g} and {a1:g}-{b1:g} overlap; give "
                "separate windows (a segment's data may enter the problem only once)."
            )
            raise ConfigError(msg)
    return ordered


def bag_duration_s(bag: Path) -> float:
    """Seconds from the bag's first to its last message."""
    with open_bag(bag) as handle:
        return (handle.end_ns - handle.start_ns) / _NS


def _reassociate(
    state: CalibrationState, data: RoundInputs, cfg: CalibConfig, run: CalibrationRun
) -> RoundInputs:
    """The segment's points associated afresh with a map built from ``state``."""
    settings = round_settings(
        cfg,
        run.noise,
        association_distance(cfg, run.noise),
        bool(cfg.model.imu or cfg.model.lidar),
    )
    pts = usable_points(state, data.points, settings.margin_s(state.knots))
    p_g = points_in_global(state, pts)
    surfels = build_surfels(p_g, settings.surfels)
    assoc = associate_points(p_g, surfels, settings.surfels)
    if len(assoc) < 100:
        return data
    order = np.argsort(assoc.point_index)
    used = pts.subset(assoc.point_index[order])
    lidar = solver_points(state, used, assoc.surfel_index[order])
    planes = Planes(normal=surfels.normal, d=surfels.d, thickness=surfels.thickness)
    return RoundInputs(data.imu, lidar, used, planes, data.noise, data.free)


# ------------------------------------------------------------------------------- result


@dataclass(frozen=True)
class JointRun:
    """What ``calibrate --segments`` produces.

    Attributes:
        result: the result file content (the joint extrinsic; ``segments`` lists each segment).
        runs: each segment's own calibration.
        windows: the segments, seconds after the bag start.
        report: the joint solver's report.
        states: each segment's state in the joint estimate.
        timings: wall seconds per stage.
        model: with ``model_auto``, what each window's diagnosis found and the model the joint
            calibration estimated (None otherwise).
        config: the configuration the segments were calibrated with (with ``model_auto``, its
            ``model:`` section is the one the diagnoses arrived at; ``lidar.scan_pattern`` the
            clouds').
    """

    result: CalibrationResult
    runs: tuple[CalibrationRun, ...]
    windows: tuple[tuple[float, float], ...]
    report: SolverReport
    states: tuple[CalibrationState, ...]
    timings: dict[str, float]
    model: SegmentsModel | None = None
    config: CalibConfig | None = None

    @property
    def segments(self) -> SegmentsSection:
        """The result's segments section."""
        assert self.result.segments is not None
        return self.result.segments


def _std(report: SolverReport, prefix: str) -> F64:
    names = report.calibration_names
    out = [s for n, s in zip(names, report.std, strict=True) if n.startswith(prefix)]
    return np.asarray(out, dtype=np.float64)


def _uncertainty(report: SolverReport) -> Uncertainty:
    t = _std(report, EXT_TRANSLATION)
    r = np.degrees(_std(report, EXT_ROTATION))
    return Uncertainty(vec3(t), vec3(r), float("nan"))


def _segment_z(run: CalibrationRun, joint: Extrinsic, clock_s: float = 0.0) -> F64:
    """(7,) a segment's own estimate minus the joint one over its own sigmas: translation,
    rotation (LiDAR frame, as the sigmas) and time offset (``clock_s`` puts the segment's on the
    joint's LiDAR clock); NaN where the segment's sigma is not finite and positive."""
    own, unc = run.result.extrinsic, run.result.uncertainty
    assert unc is not None
    sigma = unc.vector()
    diff = np.concatenate(
        [
            own.translation - joint.translation,
            so3.log(joint.rotation.T @ own.rotation),
            [own.time_offset_s + clock_s - joint.time_offset_s],
        ]
    )
    ok = np.isfinite(sigma) & (sigma > 0.0)
    return np.where(ok, diff / np.where(ok, sigma, 1.0), np.nan)


def _disagreement(run: CalibrationRun, joint: Extrinsic) -> float:
    """Largest ``|own - joint| / own sigma`` over the translation and rotation axes."""
    z = np.abs(_segment_z(run, joint)[:6])
    z = z[np.isfinite(z)]
    return float(z.max()) if z.size else 0.0


def _scatter_factor(runs: Sequence[CalibrationRun], joint: Extrinsic, clock: F64) -> F64:
    """(7,) how much more the segments' own estimates scatter about the joint one than their
    sigmas say: per coordinate the root of ``sum_k z_k^2 / (K - 1)`` (``z_k`` = a segment's
    difference from the joint over its sigma, :func:`_segment_z`; K the segments that determine
    the coordinate), at least one. The joint sigma weighs the segments as independent, which
    holds only while they agree within their sigmas; beyond that it grows by this factor (the
    Birge ratio).

    ``clock`` (K,) puts each segment's time offset on the joint's LiDAR clock.
    """
    zz = np.asarray([_segment_z(run, joint, float(clock[k])) for k, run in enumerate(runs)])
    count = np.sum(np.isfinite(zz), axis=0)
    chi2 = np.nansum(zz**2, axis=0)
    ratio = np.where(count > 1, chi2 / np.maximum(count - 1, 1), 1.0)
    return np.sqrt(np.maximum(ratio, 1.0))


class _KeptOpen:
    """The caller's progress for one segment's calibration after another: ``calibrate``
    closes its progress when it is done, the segments must not."""

    def __init__(self, inner: Progress) -> None:
        self.inner = inner

    def stage(self, name: str, total: int | None = None) -> None:
        self.inner.stage(name, total)

    def advance(self, done: int, total: int | None = None) -> None:
        self.inner.advance(done, total)

    def note(self, text: str) -> None:
        self.inner.note(text)

    def close(self) -> None:
        return None


def _only_information(findings: Sequence[Finding]) -> bool:
    """Whether every warning and failure among a segment's findings is about what its data do
    not determine (:attr:`Finding.information`), none about how the model fits them."""
    return all(f.information for f in findings if f.severity != "note")


def calibrate_segments(
    bag: Path,
    cfg: CalibConfig,
    segments: str,
    progress: Progress | None = None,
    *,
    length_s: float = 15.0,
    top: int | None = None,
    model_auto: bool = False,
) -> JointRun:
    """Calibrate over several segments of a bag in one problem.

    Args:
        bag: the bag (only read).
        cfg: configuration (``bag.start_s`` / ``duration_s`` restrict ``auto``'s search).
        segments: ``"auto"`` (windows chosen by :func:`select_segments`) or windows
            ``"60-75,105-120"`` in seconds after the bag start.
        progress: stage progress.
        length_s: window length of ``auto``, s.
        top: windows ``auto`` selects (default 3).
        model_auto: choose the model from the data: every window is diagnosed and the segments
            are calibrated estimating every effect any of them kept
            (:mod:`~licalib_cli.pipeline.segments_model`); ``cfg``'s ``model:`` is ignored.

    Raises:
        ConfigError, ExcitationError: invalid ``--segments``.
        BagError, TopicError, DataError, TimestampError: unreadable input.
        SolverError: the joint optimisation failed.
    """
    progress = progress or NullProgress()
    timings: dict[str, float] = {}
    clock = time.perf_counter()
    if segments.strip().lower() == "auto":
        sel = select_segments(bag, cfg, length_s, top=top)
        windows = [(w.start_s, w.end_s) for w in sel.selected]
        if not windows:
            msg = "No window of the bag carries enough information to calibrate."
            raise ExcitationError(msg)
        logger.info(
            "Segments selected: %s (together: min singular value %.3g).",
            ", ".join(f"{a:.1f}-{b:.1f} s" for a, b in windows),
            sel.together.min_singular_value if sel.together is not None else 0.0,
        )
        timings["selection"] = time.perf_counter() - clock
    else:
        windows = parse_segments(segments, bag_duration_s(bag))
    selection: SegmentsModel | None = None
    if model_auto:
        clock = time.perf_counter()
        selection = model_for_segments(bag, cfg, windows, progress)
        cfg = selection.config
        logger.info(
            "Model of the segments, from their diagnoses: %s.",
            ", ".join(selection.effects) or "the base model (no effect kept)",
        )
        timings["diagnoses"] = time.perf_counter() - clock
    adding = selection is None and cfg.model.add_evident_effects
    alone = calibrate_windows(
        bag,
        cfg,
        windows,
        _KeptOpen(progress),
        chosen=segments.strip().lower() == "auto",
        rivals=adding,
    )
    runs, kept = list(alone.runs), list(alone.windows)
    timings.update(alone.timings)
    added: tuple[AddedEffect, ...] = ()
    if adding:
        clock = time.perf_counter()
        evident = add_evident_to_windows(bag, runs, kept, cfg, _KeptOpen(progress))
        if evident is not None:  # refits tried: their time counts whether kept or not
            runs, cfg, added = list(evident.runs), evident.cfg, evident.added
            timings["effects shown beyond doubt"] = time.perf_counter() - clock

    clock = time.perf_counter()
    best = int(np.argmin([sigma_size(r) for r in runs]))
    ref = runs[best].state
    shared = {
        "R_imu_lidar": ref.R_imu_lidar,
        "t_imu_lidar": ref.t_imu_lidar,
        "imu_intrinsics": ref.imu_intrinsics,
        "lidar_intrinsics": ref.lidar_intrinsics,
    }
    states = [r.state.with_(**shared) for r in runs]
    inputs = [r.fit.inputs for r in runs]
    free = inputs[best].free
    report: SolverReport | None = None
    for rnd in range(JOINT_ROUNDS):
        if rnd > 0:
            inputs = [
                _reassociate(s, d, cfg, r) for s, d, r in zip(states, inputs, runs, strict=True)
            ]
        problem = joint_problem(states, inputs, free)
        report = solve(problem, lm_params(cfg))
        states = [state_from_values(s, segment_values(problem, k)) for k, s in enumerate(states)]
        logger.info(
            "Joint round %d over %d segments: cost %.1f -> %.1f in %d iterations.",
            rnd + 1,
            len(states),
            report.initial_cost,
            report.final_cost,
            report.iterations,
        )
    assert report is not None
    timings["joint"] = time.perf_counter() - clock
    if free.any_lidar_intrinsics:
        # The rounds hold each segment's map fixed, which holds back the common mode of the
        # range offsets and scales; the planes of every segment are estimated with the rest. As
        # each segment's own fit already had its planes free, this moves little (0.02-0.04 mm in
        # the mean range offset on 30 s simulated bags), but the result is the joint optimum.
        clock = time.perf_counter()
        refined = refine_segments_with_planes(states, inputs, free, lm_params(cfg))
        if refined is not None:
            logger.info(
                "Joint planes-free refinement: %d steps, cost without the range noise %.1f -> "
                "%.1f, translation moved %.2f mm (%.1f s).",
                refined.steps,
                refined.cost_start,
                refined.cost_end,
                1e3 * float(np.linalg.norm(refined.states[0].t_imu_lidar - states[0].t_imu_lidar)),
                refined.seconds,
            )
            states, inputs, report = list(refined.states), list(refined.inputs), refined.report
        timings["joint planes-free"] = time.perf_counter() - clock
    report = cover_truncated(report, runs[best].initial.state, states[best])
    result = _joint_result(runs, kept, states, report, best, cfg, alone.started_from)
    if added and result.model is not None:
        result = replace(result, model=replace(result.model, added=added))
    # the resolved config says what the windows' clouds showed (a non-repetitive scanner's)
    used = with_scan_pattern(cfg, runs[best].pattern)
    return JointRun(
        result, tuple(runs), tuple(kept), report, tuple(states), timings, selection, used
    )


def _growth(runs: Sequence[CalibrationRun]) -> tuple[F64, float, MapUncertainty | None, F64, F64]:
    """How much the joint solver's sigmas grow, from how the segments' checks enlarged theirs.

    A segment's reported sigma has a part of its own and a part every segment shares:

    * its own: the solver's sigma times the root of its residuals' chi-square, at least half the
      difference of its two halves, and the last round's change. These come from the segment's
      own data and noise, so they combine between segments as the segments' information does:
      with ``w_k = 1 / raw_k^2`` (the segment's solver information of a coordinate) and ``g_k``
      its own part over ``raw_k``, the joint solver's sigma grows by
      ``sqrt(sum w_k / sum (w_k / g_k^2))``, between the smallest and the largest ``g_k``. A
      window whose halves differ thus weighs in by the information it brings, instead of
      setting every coordinate's factor on its own.
    * the shift of an effect the model holds fixed and a segment's checks cover. A real effect
      of the rig (an IMU scale, a beam's offset) moves every segment alike: when the segments'
      score tests of it, combined (:func:`~licalib_cli.consistency.score.combined_score`),
      show it at the level at which a segment's checks cover an effect, the joint sigma keeps
      the largest ratio of such a variance to a segment's solver variance,
      ``max_k effects_k / raw_k^2``, times its own solver variance. When the segments together
      do not show it, the misfit is that window's (a burst the model follows less well), and a
      bias drift (:data:`WINDOW_EFFECTS`) differs from window to window anyway: the shift moves
      the joint estimate by the segment's share of the information only, which adds
      ``sum_k (w_k / sum w) effects_k / raw_k^2`` to that ratio. A group whose size differs
      between the segments (beams held in one of them) counts as the rig's.
    * the IMU priors, which do not shrink with more data: the joint adds the smallest of the
      segments' (all segments' data together determine the IMU blocks at least as well as the
      best one).

    Returns:
        ``(factor (7,) of translation, rotation and time offset, the root of the largest
        chi-square per sample, the largest map-plane factor of every coordinate or None, the
        effects' variance over the solver's (7,), the priors' variance (7,) to add)``.
    """
    info = np.zeros(7)  # sum w_k
    grown_info = np.zeros(7)  # sum w_k / g_k^2
    chi = 1.0
    names: dict[str, float] = {}
    planes_used = 0
    prior = np.full(7, np.inf)
    effect_ratio = np.zeros(7)
    window_ratio = np.zeros(7)  # sum w_k effects_k / raw_k^2 of the windows' own effects
    rig = _rig_effects(runs)
    for run in runs:
        c = run.checks
        u = c.uncertainty
        raw = np.asarray(c.raw_sigma, dtype=np.float64)
        shown = u.vector()
        own_prior = prior_variance(c.effects, raw)
        prior = np.minimum(prior, own_prior)
        rig_effects, window_effects = np.zeros(7), np.zeros(7)
        for e in c.effects:
            if effect_to_cover(e, raw):
                v = np.asarray(e.shift) ** 2 + np.asarray(e.shift_std) ** 2
                if e.score.name in rig:
                    rig_effects += v
                else:
                    window_effects += v
        own_effects = rig_effects + window_effects
        own = np.sqrt(np.clip(shown**2 - own_prior - own_effects, 0.0, None))
        ok = np.isfinite(raw) & (raw > 0) & np.isfinite(own)
        ratio = np.where(ok, rig_effects / np.where(ok, raw, 1.0) ** 2, 0.0)
        effect_ratio = np.maximum(effect_ratio, np.where(np.isfinite(ratio), ratio, 0.0))
        w = np.where(ok, 1.0 / np.where(ok, raw, 1.0) ** 2, 0.0)
        window_ratio += np.where(ok, w * window_effects / np.where(ok, raw, 1.0) ** 2, 0.0)
        g = np.where(ok, np.maximum(own / np.where(ok, raw, 1.0), 1.0), 1.0)
        info += w
        grown_info += w / g**2
        chi = max([chi, *(s.chi2_per_sample for s in c.consistency.sensors)])
        if c.planes is not None:
            planes_used = max(planes_used, c.planes.planes)
            for n, f in zip(c.planes.names, c.planes.factor, strict=True):
                names[n] = max(names.get(n, 1.0), float(f))
    grow = np.ones(7)
    some = grown_info > 0.0
    grow[some] = np.sqrt(info[some] / grown_info[some])
    effect_ratio[info > 0.0] += window_ratio[info > 0.0] / info[info > 0.0]
    planes = None
    if names:
        planes = MapUncertainty(tuple(names), np.array(list(names.values())), planes_used, 0.0)
    prior = np.where(np.isfinite(prior), prior, 0.0)
    return grow, float(np.sqrt(chi)), planes, effect_ratio, prior


WINDOW_EFFECTS = frozenset({"gyro_bias_walk", "accel_bias_walk"})
"""Effects that differ from one segment to the next (a bias's drift within the window): a
segment's shift of one moves the joint estimate by that segment's share only."""


def _rig_effects(runs: Sequence[CalibrationRun]) -> frozenset[str]:
    """The effects the segments' checks test whose combined score test (every segment's
    profiled gradient and information summed) is significant at the level at which a
    segment's checks cover an effect, or cannot be combined; never :data:`WINDOW_EFFECTS`."""
    by_name: dict[str, list[EffectScore]] = {}
    for run in runs:
        for e in run.checks.effects:
            by_name.setdefault(e.score.name, []).append(e.score)
    out = set()
    for name, scores in by_name.items():
        if name in WINDOW_EFFECTS:
            continue
        _, _, p = combined_score(scores) if len(scores) == len(runs) else (0.0, 0, float("nan"))
        if not p >= COVER_P_VALUE:  # NaN (not combinable) counts as the rig's
            out.add(name)
    return frozenset(out)


def joint_truncation_reasons(report: SolverReport) -> list[str]:
    """The joint verdict's reasons for the extrinsic directions the segments together do not
    determine: every truncated direction once one of them moves the extrinsic, then, when one
    turns the accelerometer's frame with the extrinsic rotation, what would determine it (the
    single run's advice, :func:`~licalib_cli.pipeline.checks.accelerometer_frame_advice`)."""
    directions, partners = extrinsic_truncated(report)
    if not directions:
        return []
    reasons = [f"Not observable from the segments together: {d.text}" for d in report.truncated]
    if partners:
        reasons.append(f"Segments together: {accelerometer_frame_advice(partners)}")
    return reasons


def _joint_result(
    runs: Sequence[CalibrationRun],
    windows: Sequence[tuple[float, float]],
    states: Sequence[CalibrationState],
    report: SolverReport,
    best: int,
    cfg: CalibConfig,
    started_from: Mapping[int, int] | None = None,
) -> CalibrationResult:
    started_from = started_from or {}
    names = report.calibration_names
    std = dict(zip(names, report.std, strict=True))
    # each segment's time offset is on its own LiDAR clock shift; put them on the reference's
    shift = [
        r.result.recording.lidar_clock_shift_s if r.result.recording is not None else 0.0
        for r in runs
    ]
    offsets = np.array([s.time_offset_s + shift[k] - shift[best] for k, s in enumerate(states)])
    sig = np.array([std.get(f"seg{k + 1}:{TIME_OFFSET}", np.inf) for k in range(len(states))])
    w = np.where(np.isfinite(sig) & (sig > 0), 1.0 / np.maximum(sig, 1e-12) ** 2, 0.0)
    if w.sum() > 0:
        tc = float(np.sum(w * offsets) / w.sum())
        tc_std = float(1.0 / np.sqrt(w.sum()))
    else:
        tc, tc_std = float(np.mean(offsets)), float("inf")
    joint = Extrinsic(states[0].R_imu_lidar.copy(), states[0].t_imu_lidar.copy(), tc)
    own_grow, chi_factor, planes, effect_ratio, prior = _growth(runs)
    scatter = _scatter_factor(runs, joint, np.asarray(shift) - shift[best])
    grow = np.sqrt(own_grow**2 + effect_ratio) * scatter
    raw = _uncertainty(report)
    shared = np.sqrt(prior)
    translation_std = np.hypot(np.asarray(raw.translation_std_m) * grow[:3], shared[:3])
    # compared with the joint solver's spread of the data's estimate: the joint enlargements
    # hold the segments' own (their checks widen the translation by the measurement's pull when
    # it disagrees with them), so they would hide the very disagreement; unbounded sigmas: the
    # data's own estimate is not known
    conflict = lever_arm_conflict(
        report, cfg, joint.translation, np.where(np.isfinite(translation_std), 0.0, np.inf)
    )
    unc = Uncertainty(
        translation_std_m=vec3(
            conflict.covered(translation_std) if conflict is not None else translation_std
        ),
        rotation_std_deg=vec3(
            np.hypot(np.asarray(raw.rotation_std_deg) * grow[3:6], np.degrees(shared[3:6]))
        ),
        time_offset_std_s=float(np.hypot(tc_std * float(grow[6]), shared[6])),
    )
    entries = []
    worst = "pass"
    reasons: list[str] = []
    if conflict is not None and conflict.disagrees:
        worst = "warn"
        reasons.append(f"Joint estimate: {conflict.text}")
    for k, (run, (a, b)) in enumerate(zip(runs, windows, strict=True)):
        own = run.result.extrinsic
        ou = run.result.uncertainty
        assert ou is not None
        z = _disagreement(run, joint)
        disagrees = z > DISAGREEMENT_SIGMAS
        status = run.checks.verdict.status
        if status != "pass" and _only_information(run.checks.findings):
            # what a short segment cannot determine alone, the others may: the joint
            # problem's observability and sigmas are checked below
            reasons.append(
                f"Segment {a:g}-{b:g} s alone: verdict {status} for what it does not determine "
                "on its own (its own reasons come from calibrating it alone); the joint "
                "problem is judged on what the segments determine together."
            )
        elif status != "pass":
            worst = "warn"
            reasons.append(
                f"Segment {a:g}-{b:g} s alone: verdict {status} (its own sections and "
                "reasons come from calibrating it alone)."
            )
        if disagrees:
            reasons.append(
                f"Segment {a:g}-{b:g} s disagrees with the joint estimate by {z:.1f} of its "
                "sigmas; check that segment (a loose mount, a bad stretch of data)."
            )
        entries.append(
            SegmentEstimate(
                start_s=float(a),
                end_s=float(b),
                translation=vec3(own.translation),
                rotation_rpy_deg=vec3(rpy_deg_from_matrix(own.rotation)),
                time_offset_s=float(own.time_offset_s),
                translation_std_m=vec3(ou.translation_std_m),
                rotation_std_deg=vec3(ou.rotation_std_deg),
                time_offset_std_s=float(ou.time_offset_std_s),
                joint_time_offset_s=float(states[k].time_offset_s),
                joint_time_offset_std_s=float(std.get(f"seg{k + 1}:{TIME_OFFSET}", np.inf)),
                disagreement_sigmas=round(z, 3),
                disagrees=bool(disagrees),
                verdict=status,
                started_from=started_from[k] + 1 if k in started_from else None,
            )
        )
    if any(e.disagrees for e in entries) and worst == "pass":
        worst = "warn"
    sigma = unc.vector()
    entangled = entangled_intrinsics(report, sigma[:3])
    resting = on_prior(report, prior_sd(cfg))
    # the joint problem takes each segment's last round's points
    points = joint_point_budget([r.fit.points for r in runs])
    for finding in uncertainty_findings(
        sigma, sigma, cfg.checks, entangled=entangled, resting=resting, points=points
    ):
        worst = "warn" if worst == "pass" else worst
        reasons.append(f"Joint estimate: {finding.text}")
    truncated = tuple(d.text for d in report.truncated)
    not_observable = joint_truncation_reasons(report)
    weak = [
        f"Weakly determined by the segments together: {d.text}; its sigmas rest on little "
        "information."
        for d in moving_extrinsic(report, report.weak)[0]
    ]
    if not_observable or weak:
        worst = "warn" if worst == "pass" else worst
        reasons += not_observable + weak
    reasons += [f"Rests on the prior (joint estimate): {r.text}." for r in resting]
    if np.any(own_grow > 1.005) or np.any(scatter > 1.005):
        reasons.append(
            f"Joint sigmas enlarged up to {float(own_grow.max()):.2f} times, the segments' own "
            "enlargements (residual chi-square, split halves) weighted by their information"
            + (
                f", and the segments' scatter about the joint estimate (times up to "
                f"{float(scatter.max()):.2f})."
                if np.any(scatter > 1.005)
                else "."
            )
        )
    if np.any(effect_ratio > 0.0):
        reasons.append(
            "Joint sigmas enlarged up to "
            f"{float(np.sqrt(1.0 + effect_ratio.max())):.2f} times by the shift of the effects "
            "held fixed that a segment's checks cover (by that segment's share of the "
            "information where the segments together do not show the effect)."
        )
    held = [uncovered(r.checks.effects, r.checks.raw_sigma) for r in runs]
    unchecked: list[UncheckedPrior] = combined_unchecked_priors(held, sigma)
    if np.any(prior > 0.0):
        what, where = prior_owner([e.score.name for e in held[best] if e.prior_sigma > 0.0])
        reasons.append(
            f"Joint sigmas include the {what} held fixed ({where}) as the best-determined "
            "segment's do: a sensor's calibration error moves every segment alike"
            + unchecked_text(unchecked)
            + "."
        )
        warning = unchecked_warning(unchecked)
        if warning is not None:
            worst = "warn" if worst == "pass" else worst
            reasons.insert(0, f"Joint estimate: {warning}")
    # the effects taken as exact that could hide as much are in the checks table's row
    # (consistency.unchecked_priors): a note, not a reason of the verdict
    base = runs[best].result
    section = SegmentsSection(
        reference=best + 1,
        disagreement_threshold_sigmas=DISAGREEMENT_SIGMAS,
        segments=tuple(entries),
    )
    ref = states[best]
    return replace(
        base,
        extrinsic=joint,
        imu_intrinsics=ref.imu_intrinsics,
        lidar_intrinsics=ref.lidar_intrinsics if cfg.model.lidar else None,
        intrinsics_uncertainty=intrinsics_uncertainty(
            report, cfg, chi_factor, ref.lidar_intrinsics.num_beams, planes
        ),
        gravity_G=vec3(round(float(x), 6) for x in ref.gravity_G),
        uncertainty=unc,
        observability=Observability(
            scaling=report.scaling,
            threshold=float(report.tsvd_threshold),
            singular_values=tuple(float(s) for s in report.singular_values),
            unobservable=truncated + tuple(r.text for r in resting),
            weakly_determined=tuple(d.text for d in report.weak),
            weak_floor=float(report.weak_floor),
        ),
        verdict=VerdictSection(worst, tuple(reasons)),
        segments=section,
        extra_terms=extra_terms(ref, cfg),
        # the priors the segments together cannot check, as the joint verdict judged them
        consistency=(
            replace(base.consistency, unchecked_priors=unchecked_sections(unchecked))
            if base.consistency is not None
            else None
        ),
    )
