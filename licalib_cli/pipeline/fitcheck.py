"""Evidence that the fitted model explains the data (or not), computed at the final estimate.

Three kinds of evidence, each naming the sensor it concerns:

* per sensor, the residuals against the noise the fit was weighted with (chi-square per
  sample) and the structure left in them: their dependence on the angular rate, the specific
  force and time (IMU), on the beam, range, azimuth, elevation, incidence angle and the time
  within the sweep (LiDAR);
* per effect the model holds fixed (IMU scale, misalignment, gyro-to-IMU rotation,
  g-sensitivity, the six per-beam LiDAR intrinsics), a score test and how far estimating the
  effect would move the extrinsic (:mod:`licalib_cli.consistency.score`), from one
  linearisation of the final problem with those effects freed (for the LiDAR effects the data
  show, with the map planes freed too: :mod:`licalib_cli.pipeline.effect_shift`);
* the split-half agreement (:mod:`licalib_cli.pipeline.split`).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
import numpy.typing as npt

from licalib_cli.config import ModelSection
from licalib_cli.consistency import (
    EffectScore,
    EffectSelection,
    explained_shares,
    group_pattern,
    measured_shift,
    normalised_chi2,
    regression_pattern,
    score_effects,
    select_effects,
)
from licalib_cli.consistency.distributions import chi2_sf
from licalib_cli.estimation import CalibrationState, Planes, build_problem, incidence_cosine
from licalib_cli.pipeline.effect_shift import (
    freed_before,
    planes_free_shifts,
    planes_free_spreads,
    planes_free_system,
)
from licalib_cli.pipeline.points import PointSample
from licalib_cli.pipeline.round import RoundInputs, SolvedProblem
from licalib_cli.pipeline.settings import NoiseLevels, translation_priors
from licalib_cli.residuals import TIME_OFFSET, AccelResidual, GyroResidual, PointToPlaneResidual
from licalib_cli.sections import PatternCheck, SensorCheck
from licalib_cli.solver.schur import schur_complement

__all__ = [
    "CANDIDATES",
    "CHI2_EXCESS",
    "CHI2_QUIET",
    "EFFECT_P_VALUE",
    "PATTERN_EXPLAINED",
    "EffectEvidence",
    "ResidualTable",
    "beam_sigma",
    "effect_evidence",
    "model_entries",
    "residual_table",
    "sensor_checks",
    "with_measured",
]

logger = logging.getLogger(__name__)

F64 = npt.NDArray[np.float64]

CHI2_EXCESS = 1.5
"""A sensor whose chi-square per sample exceeds this (residual RMS 1.22 times the noise) is not
explained by the model (or its noise setting is wrong)."""

CHI2_QUIET = 0.5
"""A sensor weighted with a configured noise whose chi-square per sample is below this (residual
RMS 0.71 of that noise; a fit that explains the data leaves about 0.9) is stated noisier than
it is: its sigmas are wider than the data support."""

PATTERN_EXPLAINED = 0.01
"""A residual pattern counts when it explains more than this share of the residual variance
(and is significant, :data:`PATTERN_P_VALUE`)."""

PATTERN_P_VALUE = 1e-9

EFFECT_P_VALUE = 1e-5
"""A fixed effect is significant below this p-value (about 1e-4 over all effects tested)."""

MIN_INCIDENCE_COS = 0.3
"""The point-to-plane noise is the range noise times the cosine of the incidence angle, but at
least this fraction of it (grazing rays, plane-fit errors): how the checks weigh the distances,
whatever the fit's weighting (``noise.min_incidence_cos``)."""

MAX_EFFECT_POINTS = 400_000
"""Points used for the score tests at most (a regular subset of the final round's, which has
about 180 000-260 000 on a 10 s bag and 360 000 on a 40 s one): every point of a bag of usual
length. The tests' power grows with them: a regular subset of 80 000 left a 10 s VLP-16 shake
showing a gyro scale only from 550 ppm RMS and per-beam LiDAR intrinsics from twice the size they
show from with all 246 000 points (370 ppm; range offsets 0.42 -> 0.21 mm), while on 16 clean
10 s bags the statistics stayed chi-square (3.1 % of 256 tests below p = 0.05, the smallest p
0.0025). The linearisation with every intrinsic free costs in proportion (about 0.4 s more
on those 246 000 points)."""


UNTESTED_FACTOR = 100.0
"""A direction of a candidate effect that the recording determines worse than this many times
the effect's characteristic scale (:data:`~licalib_cli.estimation.CALIBRATION_SCALES`, as the
truncated SVD uses it) is not tested: no effect of a plausible size can show there, only a
misfit from elsewhere. On an 8 s planar figure-8 without any effect, the lever arm along the
one rotation axis held at its initial value (5.8 cm off) showed, with every point, as an
accelerometer scale at 45 on 3 degrees of freedom, all of it along a direction known to 114 %
(228 times the 0.5 % scale; one-step estimate 727 %), and the sigmas were enlarged for the
shift such a scale would cause."""


def _every_kth(n: int, at_most: int) -> npt.NDArray[np.intp]:
    """The indices of a regular subset of at most ``at_most`` of ``n`` points."""
    return np.arange(0, n, max(int(np.ceil(n / at_most)), 1), dtype=np.intp)


CANDIDATES: dict[str, tuple[str, str, str]] = {
    "gyro_scale": ("imu", "gyro_scale", "gyro"),
    "gyro_misalignment": ("imu", "gyro_misalignment", "gyro"),
    "gyro_rotation": ("imu", "gyro_rotation", "gyro"),
    "accel_scale": ("imu", "accel_scale", "accelerometer"),
    "accel_misalignment": ("imu", "accel_misalignment", "accelerometer"),
    "g_sensitivity": ("imu", "g_sensitivity", "gyro"),
    "gyro_bias_walk": ("imu", "gyro_bias_walk", "gyro"),
    "accel_bias_walk": ("imu", "accel_bias_walk", "accelerometer"),
    "imu_clock_drift": ("imu", "clock_drift", "lidar"),
    "lidar_range_offset": ("lidar", "range_offset", "lidar"),
    "lidar_range_scale": ("lidar", "range_scale", "lidar"),
    "lidar_elevation": ("lidar", "elevation", "lidar"),
    "lidar_azimuth": ("lidar", "azimuth", "lidar"),
    "lidar_vertical_offset": ("lidar", "vertical_offset", "lidar"),
    "lidar_horizontal_offset": ("lidar", "horizontal_offset", "lidar"),
    "lidar_point_time": ("lidar", "point_time", "lidar"),
}
"""Candidate effect -> (``model:`` list it joins, its name there, the sensor whose gap it
closes). The clock drift and the per-point time show in the LiDAR's residuals (points are placed
at the wrong trajectory time)."""


def model_entries(effects: Sequence[str]) -> str:
    """The ``model:`` entries that estimate candidate ``effects``, e.g. ``model.lidar:
    [range_scale]`` (one list per sensor, in the order the effects come)."""
    lists: dict[str, list[str]] = {}
    for name in effects:
        sensor, block = CANDIDATES[name][:2]
        lists.setdefault(sensor, []).append(block)
    return ", ".join(f"model.{sensor}: [{', '.join(blocks)}]" for sensor, blocks in lists.items())


_LIDAR_EFFECTS = {
    "dphi": "lidar_elevation",
    "dtheta": "lidar_azimuth",
    "V": "lidar_vertical_offset",
    "H": "lidar_horizontal_offset",
    "s": "lidar_range_scale",
    "drho": "lidar_range_offset",
}
_DRIFT_EFFECTS = {
    "imu.gyro_bias_drift": "gyro_bias_walk",
    "imu.accel_bias_drift": "accel_bias_walk",
    "ext.time_drift": "imu_clock_drift",
    "lidar.point_time_scale": "lidar_point_time",
}
_IMU_EFFECTS = {
    "imu.gyro_scale": "gyro_scale",
    "imu.gyro_misalignment": "gyro_misalignment",
    "imu.gyro_rotation": "gyro_rotation",
    "imu.accel_scale": "accel_scale",
    "imu.accel_misalignment": "accel_misalignment",
    "imu.gyro_g_sensitivity": "g_sensitivity",
}


def _patterns(
    residuals: F64, features: list[tuple[str, npt.NDArray[np.number], bool]], sigma: F64
) -> tuple[PatternCheck, ...]:
    """The residuals' dependence on each feature; ``sigma`` is the noise the fit is weighted
    with (any shape; its RMS is used).

    A pattern is material when it is significant, explains more than
    :data:`PATTERN_EXPLAINED` of the residual variance, and would do so of residuals that were
    only the weighted noise: residuals far quieter than the noise the fit assumes (a gyro ten
    times better than its configuration) show the spline's own approximation as a "pattern"
    that is a fraction of a percent of that noise and moves nothing.
    """
    floor = float(np.sqrt(PATTERN_EXPLAINED * np.mean(np.square(sigma))))
    out = []
    for name, x, grouped in features:
        p = group_pattern(residuals, x, name) if grouped else regression_pattern(residuals, x, name)
        out.append(
            PatternCheck(
                feature=name,
                explained=p.explained,
                p_value=p.p_value,
                size=p.size,
                material=p.material(PATTERN_EXPLAINED, PATTERN_P_VALUE) and p.size > floor,
            )
        )
    return tuple(out)


def _sensor(
    name: str,
    unit: str,
    residuals: F64,
    sigma: F64,
    noise: F64,
    source: str,
    patterns: tuple[PatternCheck, ...],
) -> SensorCheck:
    chi = normalised_chi2(residuals, sigma)
    return SensorCheck(
        sensor=name,
        unit=unit,
        noise=tuple(float(x) for x in np.atleast_1d(noise)),
        noise_source=source,
        chi2_per_sample=chi.per_dof,
        rms=chi.rms,
        samples=chi.samples,
        status="excess" if chi.per_dof > CHI2_EXCESS else "ok",
        patterns=patterns,
    )


@dataclass(frozen=True)
class ResidualTable:
    """Every residual of a fit in its sensor's unit, with what it may depend on.

    Attributes:
        t_imu_s: (N,) IMU sample times, s.
        gyro: (N, 3) gyro residuals (prediction minus reading), rad/s.
        accel: (N, 3) accelerometer residuals, m/s^2.
        angular_rate: (N, 3) the fit's prediction of the gyro readings, rad/s.
        specific_force: (N, 3) the fit's prediction of the accelerometer readings, m/s^2.
        point_t_s: (P,) point times, s.
        distance: (P,) signed point-to-plane distances, m.
        beam: (P,) beam of each point.
        rho: (P,) range, m.
        theta: (P,) azimuth, rad.
        elevation: (P,) nominal elevation of the beam, rad.
        cos_incidence: (P,) cosine of the angle between the ray and the plane's normal.
        time_in_sweep_s: (P,) time since the sweep's first point, s.

    The patterns are taken against the predictions, not the readings: a reading carries the
    very noise of its residual, so a regression on it finds that noise as a "dependence" (9 %
    of the gyro residuals' variance on a sinusoid with a gyro ten times noisier than the
    MTi-100's, every clean run a warning).
    """

    t_imu_s: F64
    gyro: F64
    accel: F64
    angular_rate: F64
    specific_force: F64
    point_t_s: F64
    distance: F64
    beam: npt.NDArray[np.intp]
    rho: F64
    theta: F64
    elevation: F64
    cos_incidence: F64
    time_in_sweep_s: F64


def residual_table(
    state: CalibrationState, inputs: RoundInputs, solved: SolvedProblem | None = None
) -> ResidualTable:
    """The residuals of ``state`` on a round's measurements and map.

    Args:
        state: the estimate.
        inputs: what the round's problem was built from.
        solved: that problem at ``state`` with the solver's evaluation there, whose residuals
            are then used instead of building and evaluating the problem again; None: they are
            computed here.
    """
    if solved is not None:
        problem = solved.problem
        evaluated = dict(
            zip(map(id, problem.residual_blocks), solved.evaluation.evals, strict=True)
        )
    else:
        problem = inputs.problem(state)  # the same problem as the solver's
        evaluated = {}
    params = problem.values()

    def whitened(block: GyroResidual | AccelResidual | PointToPlaneResidual) -> F64:
        ev = evaluated.get(id(block))
        if ev is None:
            ev = block.evaluate(params, jacobians=False)
        return np.asarray(ev.residuals, dtype=np.float64)

    gyro = next(b for b in problem.residual_blocks if isinstance(b, GyroResidual))
    accel = next(b for b in problem.residual_blocks if isinstance(b, AccelResidual))
    points = next(b for b in problem.residual_blocks if isinstance(b, PointToPlaneResidual))
    r_g = whitened(gyro) / gyro.inv_sigma
    r_a = whitened(accel) / accel.inv_sigma
    d = whitened(points)[:, 0] / points.whitening()  # as PointToPlaneResidual.distances
    tc = float(np.asarray(params[TIME_OFFSET]).reshape(-1)[0])
    phi = state.lidar_intrinsics.nominal_elevation[points.beam]
    cos_inc = incidence_cosine(state, points.t_s + tc, points.beam, points.theta, points.normal)
    return ResidualTable(
        t_imu_s=gyro.t_s,
        gyro=r_g,
        accel=r_a,
        angular_rate=gyro.gyro + r_g,
        specific_force=accel.accel + r_a,
        point_t_s=points.t_s,
        distance=d,
        beam=points.beam,
        rho=points.rho,
        theta=points.theta,
        elevation=phi,
        cos_incidence=cos_inc,
        time_in_sweep_s=np.asarray(
            (inputs.points.t_ns - inputs.points.sweep_start_ns) * 1e-9, dtype=np.float64
        ),
    )


def beam_sigma(noise: NoiseLevels, num_beams: int) -> F64:
    """(B,) range noise per beam, m: measured per beam when the noise comes from the data,
    else the one figure."""
    per_beam = noise.range_sigma_per_beam
    if noise.range_source == "data" and per_beam.shape[0] == num_beams:
        return np.where(np.isfinite(per_beam), per_beam, noise.range_sigma_m)
    return np.full(num_beams, noise.range_sigma_m)


def sensor_checks(
    state: CalibrationState,
    inputs: RoundInputs,
    noise: NoiseLevels,
    solved: SolvedProblem | None = None,
) -> tuple[SensorCheck, ...]:
    """Residual size and structure per sensor at the final estimate.

    Args:
        state: the final estimate.
        inputs: the final round's problem inputs.
        noise: the noise the fit was weighted with.
        solved: the final round's problem with the solver's evaluation at ``state``
            (:func:`residual_table`), or None.

    Returns:
        The gyro's, the accelerometer's and the LiDAR's checks.
    """
    r = residual_table(state, inputs, solved)
    out = [
        _sensor(
            "gyro",
            "rad/s",
            r.gyro,
            noise.gyro_sigma,
            noise.gyro_sigma,
            noise.gyro_source,
            _patterns(
                r.gyro,
                [
                    ("angular rate", r.angular_rate, False),
                    ("specific force", r.specific_force, False),
                    ("time", r.t_imu_s, False),
                ],
                noise.gyro_sigma,
            ),
        ),
        _sensor(
            "accelerometer",
            "m/s^2",
            r.accel,
            noise.accel_sigma,
            noise.accel_sigma,
            noise.accel_source,
            _patterns(
                r.accel,
                [
                    ("specific force", r.specific_force, False),
                    ("angular rate", r.angular_rate, False),
                    ("time", r.t_imu_s, False),
                ],
                noise.accel_sigma,
            ),
        ),
    ]
    sigma = beam_sigma(noise, state.lidar_intrinsics.num_beams)[r.beam] * np.maximum(
        r.cos_incidence, MIN_INCIDENCE_COS
    )
    out.append(
        _sensor(
            "lidar",
            "m",
            r.distance,
            sigma,
            np.array([noise.range_sigma_m]),
            noise.range_source,
            _patterns(
                r.distance,
                [
                    ("beam", r.beam, True),
                    ("range", r.rho, False),
                    ("azimuth", np.stack([np.sin(r.theta), np.cos(r.theta)], -1), False),
                    ("elevation", r.elevation, False),
                    ("incidence angle", r.cos_incidence, False),
                    ("time within sweep", r.time_in_sweep_s, False),
                ],
                sigma,
            ),
        )
    )
    return tuple(out)


@dataclass(frozen=True)
class EffectEvidence:
    """Score test of one fixed effect with its shift of the extrinsic in result units.

    Attributes:
        score: the test (shifts in solver coordinates).
        sensor: ``imu`` or ``lidar``.
        selected: whether the forward selection added it (it explains something the stronger
            effects do not).
        shift_translation_m: (3,) m.
        shift_rotation_rad: (3,) about the LiDAR axes, rad.
        shift_time_offset_s: s.
        statistic_alone: the score statistic tested against the estimated coordinates only
            (before any other effect was selected).
        shift_std: (7,) standard deviation of the shift when the effect is truly zero (in the
            order of :attr:`shift`).
        prior_std: (7,) what the effect, known only to within its prior (``model.imu_prior``,
            ``model.lidar_prior``; for the IMU clock drift, the stamps' rate against the record
            times), adds to the sigmas of the extrinsic and time offset (zeros without a
            prior).
        prior_sigma: that prior's sigma per coordinate, in the effect's solver coordinates (0:
            none).
        joint_prior_var: (7,) the variance every block with a prior adds to the estimate
            when all of them are held at zero together: the spread of their joint posterior
            (data and priors) carried into it (the same array on each block with a prior;
            zeros on the others). Blocks correlated with each other and with the extrinsic (the
            accelerometer's scale and misalignment with the gyro rotation) can move it together
            well beyond what each does alone.
        joint_prior_shift: (7,) the move of the estimate to the joint posterior mean of those
            blocks: what holding them all at zero biases it by, as far as the data and the
            priors tell (likewise on each).
        joint_p_value: the score test of those blocks together (NaN without a prior).
        refitted: the shift is (per coordinate, the larger of) the step's and a refit's with
            the effect estimated (:mod:`licalib_cli.pipeline.effect_refit`).
        measured: the effect's size is measured apart from the fit and the measurement shows
            it (the IMU clock's rate against the LiDAR's, from the stamps against the record
            times, a material one): the shift and its spread are those of holding it at zero
            given that measurement (:func:`~licalib_cli.consistency.measured_shift`), whatever
            the score test says; ``measured_value`` is the measurement (own units; NaN
            otherwise). A measurement that does not show it still bounds it: ``prior_std``.
        explained_by: the share of this effect's score (against the estimated coordinates)
            that each other candidate explains when freed as well
            (:func:`licalib_cli.consistency.explained_shares`): near one for a candidate that
            can stand in for it. Only for a significant effect, and only when asked
            (``effect_evidence(..., rivals=True)``, as diagnose does; empty otherwise).
    """

    score: EffectScore
    sensor: str
    selected: bool
    shift_translation_m: F64
    shift_rotation_rad: F64
    shift_time_offset_s: float
    statistic_alone: float = float("nan")
    shift_std: F64 = field(default_factory=lambda: np.zeros(7))
    prior_std: F64 = field(default_factory=lambda: np.zeros(7))
    refitted: bool = False
    prior_sigma: float = 0.0
    joint_prior_var: F64 = field(default_factory=lambda: np.zeros(7))
    joint_prior_shift: F64 = field(default_factory=lambda: np.zeros(7))
    joint_p_value: float = float("nan")
    explained_by: Mapping[str, float] = field(default_factory=dict)
    measured: bool = False
    measured_value: float = float("nan")

    @property
    def shift(self) -> F64:
        """(7,) the shift as translation (m), rotation (rad), time offset (s)."""
        return np.concatenate(
            [self.shift_translation_m, self.shift_rotation_rad, [self.shift_time_offset_s]]
        )


def _effect_of(name: str) -> str | None:
    if name.startswith("lidar.intrinsics"):
        return _LIDAR_EFFECTS.get(name.rsplit(".", 1)[1])
    if name in _DRIFT_EFFECTS:
        return _DRIFT_EFFECTS[name]
    block = name.rsplit(".", 1)[0]
    return _IMU_EFFECTS.get(block) or _DRIFT_EFFECTS.get(block)


def effect_evidence(
    state: CalibrationState,
    inputs: RoundInputs,
    variance_factor: float,
    priors: ModelSection | None = None,
    planes_free_p: float = 0.0,
    *,
    rivals: bool = True,
    measured: Mapping[str, tuple[float, float, bool]] | None = None,
    hint_p: float = 0.0,
) -> list[EffectEvidence]:
    """Score tests of every effect the final round held fixed, with forward selection.

    The final problem is rebuilt with every IMU and LiDAR intrinsic free (the gauge beam and
    beams with too few points stay fixed) and linearised once at the final estimate; the
    trajectory is eliminated as in the solver, and the fixed groups are tested against the
    coordinates the round estimated: the most significant is selected, the others re-tested
    with it freed, and so on (:func:`~licalib_cli.consistency.select_effects`).

    Args:
        state: the final estimate.
        inputs: the final round's problem inputs.
        variance_factor: the fit's a-posteriori variance factor (clamped below at 1).
        priors: the model whose ``imu_prior`` and ``lidar_prior`` say how well the
            intrinsics held fixed are known, for
            :attr:`EffectEvidence.prior_std` (none: known exactly).
        planes_free_p: the LiDAR effects with a p-value below this get their shift and its
            null spread with the map planes estimated too
            (:mod:`licalib_cli.pipeline.effect_shift`); the others keep the planes-fixed ones.
        rivals: size, for each significant effect, the share of its score each other
            candidate explains (:attr:`EffectEvidence.explained_by`); False: left empty.
        measured: effect name -> ``(value, sigma, shown)`` of a one-coordinate effect held
            fixed whose size is measured apart from the fit (own units). Its
            :attr:`EffectEvidence.prior_std` is the spread of its size given the data and the
            measurement, carried into the extrinsic: the effect is known only so well. When the
            measurement shows it (``shown``), its shift is that of holding it at zero given the
            measurement (:attr:`EffectEvidence.measured`); when its score test is below
            ``hint_p`` as well, per coordinate the larger of that and the data's own shift (the
            sigmas covered that shift before the measurement came).

    Returns:
        One entry per fixed group with at least one free coordinate: the selected ones first,
        in the order added, then the others (tested with the selected ones freed).
    """
    free = inputs.free
    all_free = replace(
        free,
        imu_intrinsics=True,
        lidar_intrinsics=free.beam_intrinsics,
        g_sensitivity=True,
        gyro_bias_drift=True,
        accel_bias_drift=True,
        time_drift=True,
        point_time=True,
    )
    subset = _every_kth(len(inputs.lidar), MAX_EFFECT_POINTS)
    lidar = inputs.lidar.subset(subset)
    # The score statistic is chi-square only when every whitened residual has unit variance: a
    # point-to-plane distance varies by the range noise times the cosine of the incidence angle
    # (MIN_INCIDENCE_COS at least, as the sensor check), whatever the fit weighted it with
    # (noise.min_incidence_cos). Weighted with the range noise alone, the statistics came out
    # about half their chi-square size on clean simulated data (twin recordings), so the test
    # lost power.
    weighted = replace(inputs.noise, min_incidence_cos=MIN_INCIDENCE_COS, incidence_floor=True)
    # the translation's prior as in the rounds (it bounds the shifts along what the data leave
    # to it); the intrinsics' weak priors stay out (the held ones' are the model's priors')
    problem = build_problem(
        state,
        inputs.imu,
        lidar,
        inputs.planes,
        weighted,
        all_free,
        extra_residuals=translation_priors(all_free),
    )
    evaluation = problem.evaluate(jacobians=True)
    n_free = problem.layout().num_free
    variance_factor = max(
        variance_factor, 2.0 * evaluation.cost / max(evaluation.num_residuals - n_free, 1)
    )
    lin = problem.linearize(evaluation, problem.layout())
    sch = schur_complement(lin)
    names = lin.layout.calibration_names
    groups: dict[str, list[int]] = {}
    base: list[int] = []
    estimated = {v for k, v in _IMU_EFFECTS.items() if free.imu_block_free(k)}
    estimated |= {v for k, v in _LIDAR_EFFECTS.items() if free.lidar_column_free(k)}
    estimated |= {
        name
        for name, flag in (
            ("gyro_bias_walk", free.gyro_bias_drift),
            ("accel_bias_walk", free.accel_bias_drift),
            ("imu_clock_drift", free.time_drift),
            ("lidar_point_time", free.point_time),
        )
        if flag
    }
    for i, n in enumerate(names):
        effect = _effect_of(n)
        if effect is None or effect in estimated:
            base.append(i)
        else:
            groups.setdefault(effect, []).append(i)
    prior = {
        name: np.full(len(idx), priors.held_prior(name))
        for name, idx in groups.items()
        if priors is not None and priors.held_prior(name) > 0.0
    }
    scale = np.asarray(lin.layout.calibration_scale, dtype=np.float64)
    floors = {
        name: 1.0 / (UNTESTED_FACTOR * float(np.max(scale[idx]))) ** 2
        for name, idx in groups.items()
    }
    selection = select_effects(
        sch.S,
        sch.b,
        base,
        groups,
        EFFECT_P_VALUE,
        max(variance_factor, 1.0),
        prior_sigma=prior,
        floors=floors,
    )
    # which candidates can stand in for a significant one (diagnose's rivals)
    shares = {}
    if rivals:
        significant = [
            s.name
            for s in (*selection.selected, *selection.remaining)
            if s.p_value < EFFECT_P_VALUE
            or chi2_sf(selection.alone.get(s.name, 0.0), max(s.rank, 1)) < EFFECT_P_VALUE
        ]
        shares = explained_shares(sch.S, sch.b, base, groups, significant, floors=floors)
    base_names = [names[i] for i in base]
    joint = _joint_prior(sch.S, sch.b, base, groups, prior, variance_factor)
    selected = [s.name for s in selection.selected]
    wanted = _lidar_wanted(selection, planes_free_p)
    # the priors' spread with the planes free, but not beside estimated LiDAR intrinsics
    free_prior = {} if free.any_lidar_intrinsics else prior
    system = (
        planes_free_system(
            problem,
            evaluation,
            lin,
            state,
            *_lidar_sample(inputs, subset),
            _columns(base, groups, [*free_prior, *selected, *wanted]),
        )
        if free_prior or wanted
        else None
    )
    planes_free = (
        {}
        if system is None or not wanted
        else planes_free_shifts(
            system,
            base,
            {
                name: (
                    np.asarray(groups[name], dtype=np.intp),
                    [np.asarray(groups[n], dtype=np.intp) for n in freed_before(name, selected)],
                )
                for name in wanted
            },
            max(variance_factor, 1.0),
        )
    )
    free_spread, free_joint = _planes_free_prior(
        system, sch.b, base, groups, free_prior, selected, variance_factor
    )

    # effects whose size is measured apart from the fit: the shift of holding them at zero
    sized = {
        name: measured_shift(
            sch.S, sch.b, base, groups[name], value, sigma, max(variance_factor, 1.0)
        )
        for name, (value, sigma, _) in (measured or {}).items()
        if name in groups and len(groups[name]) == 1 and sigma > 0.0
    }
    shown = {name for name in sized if (measured or {})[name][2]}

    def pick(prefix: str, shift: F64) -> F64:
        return np.array([s for n, s in zip(base_names, shift, strict=True) if n.startswith(prefix)])

    def pick_extrinsic(x: F64) -> F64:
        out = np.concatenate(
            [pick(p, x) for p in ("ext.translation", "ext.rotation", "ext.time_offset")]
        )
        return out if out.size == 7 else np.zeros(7)

    # every IMU block with a prior carries the group's figures; the others none
    no_group: tuple[F64, F64, float] = (np.zeros(7), np.zeros(7), float("nan"))
    group = (
        no_group
        if joint is None
        else (
            pick_extrinsic(_larger_spread(joint.prior_shift_sigma, free_joint) ** 2),
            pick_extrinsic(
                joint.prior_shift
                if free_joint is None
                else np.asarray(free_joint.prior_shift)[: joint.prior_shift.size]
            ),
            float(joint.p_value),
        )
    )
    out = []
    for sel, scores in ((True, selection.selected), (False, selection.remaining)):
        for s in scores:
            shift, shift_sigma = planes_free.get(s.name, (s.shift, s.shift_sigma))
            prior_std = pick_extrinsic(
                np.maximum(s.prior_shift_sigma, free_spread.get(s.name, 0.0))
            )
            if s.name in sized:  # known only to within its measurement and the data
                prior_std = pick_extrinsic(sized[s.name][1])
            if s.name in shown:
                shift, shift_sigma = with_measured(
                    (shift, shift_sigma), sized[s.name], hinted=s.p_value < hint_p
                )
            t = pick("ext.translation", shift)
            r = pick("ext.rotation", shift)
            c = pick("ext.time_offset", shift)
            joint_var, joint_shift, joint_p = group if s.name in prior else no_group
            out.append(
                EffectEvidence(
                    score=s,
                    sensor="lidar" if s.name.startswith("lidar") else "imu",
                    selected=sel,
                    shift_translation_m=t if t.size == 3 else np.zeros(3),
                    shift_rotation_rad=r if r.size == 3 else np.zeros(3),
                    shift_time_offset_s=float(c[0]) if c.size else 0.0,
                    statistic_alone=float(selection.alone.get(s.name, s.statistic)),
                    shift_std=pick_extrinsic(shift_sigma),
                    prior_std=prior_std,
                    prior_sigma=float(prior[s.name][0]) if s.name in prior else 0.0,
                    joint_prior_var=joint_var,
                    joint_prior_shift=joint_shift,
                    joint_p_value=joint_p,
                    explained_by=shares.get(s.name, {}),
                    measured=s.name in shown,
                    measured_value=(
                        float((measured or {})[s.name][0]) if s.name in shown else float("nan")
                    ),
                )
            )
    logger.debug(
        "effect scores (planes-free shifts for %s): %s",
        ", ".join(planes_free) or "none",
        ", ".join(f"{e.score.name} {e.score.statistic:.1f} (dof {e.score.rank})" for e in out),
    )
    return out


def with_measured(
    data: tuple[F64, F64], measured: tuple[F64, F64], *, hinted: bool
) -> tuple[F64, F64]:
    """The shift (and its spread) of an effect held fixed whose size is measured apart from the
    fit: the measurement's (:func:`~licalib_cli.consistency.measured_shift`); when the data
    hint at the effect too, per coordinate the larger of that and the data's own shift (and the
    larger spread), which the sigmas covered before the measurement came."""
    (shift, spread), (at_measured, measured_spread) = data, measured
    if not hinted:
        return at_measured, measured_spread
    return (
        np.where(np.abs(shift) > np.abs(at_measured), shift, at_measured),
        np.maximum(spread, measured_spread),
    )


def _joint_prior(
    S: F64,
    b: F64,
    base: list[int],
    groups: dict[str, list[int]],
    prior: dict[str, F64],
    variance_factor: float,
) -> EffectScore | None:
    """The score test of every block with a prior as one group, with its posterior spread and
    posterior-mean shift of the estimated coordinates (:attr:`EffectEvidence.joint_prior_var`
    and ``joint_prior_shift``); None without any prior."""
    if not prior:
        return None
    names = sorted(prior)
    idx = [i for n in names for i in groups[n]]
    sigma = np.concatenate([prior[n] for n in names])
    (joint,) = score_effects(
        S, b, base, {"held": idx}, max(variance_factor, 1.0), prior_sigma={"held": sigma}
    )
    return joint


def _planes_free_prior(
    system: tuple[F64, F64, npt.NDArray[np.intp]] | None,
    b: F64,
    base: list[int],
    groups: dict[str, list[int]],
    prior: dict[str, F64],
    selected: list[str],
    variance_factor: float,
) -> tuple[dict[str, F64], EffectScore | None]:
    """What the blocks held to their priors add to the estimate with the map planes free as
    well: each one's spread (:func:`~licalib_cli.pipeline.effect_shift.planes_free_spreads`)
    and all of them together (:func:`_joint_prior`); empty, None without a prior or LiDAR
    points (``system`` None). ``system`` is :func:`~licalib_cli.pipeline.effect_shift.
    planes_free_system` over ``base`` and the groups with a prior, ``b`` the planes-fixed
    right-hand side (all coordinates).

    The map planes were fitted to points mapped with the same estimate: held where they are,
    they take up part of what a held intrinsic moves, as for the LiDAR effects
    (:mod:`~licalib_cli.pipeline.effect_shift`). On a 10 s Avia sinusoid with the simulator's
    random IMU intrinsics (an accelerometer misalignment twice its prior), the gyro rotation
    estimated, the priors' spread with the planes held added 0.008 deg to the pitch and their
    posterior mean moved it 0.006 deg, with the planes free 0.014 and 0.027 deg, while the
    pitch was 0.049 deg off (a refit with every IMU block estimated took it to 0.015 deg).

    The information is the planes-free one, the right-hand side the planes-fixed one: at the
    optimum of a linear problem the planes' own gradient is zero and the two coincide, but the
    planes were fitted to their points, not by these weighted residuals on a sample of them,
    and with the planes-free gradient the posterior-mean move of a 10 s Avia shake reached 4.1
    deg and 41 mm (6.0 deg and 59 mm with only the planes' own gradient dropped) where the
    extrinsic was 0.03 deg and 1.2 mm off.

    Not beside estimated LiDAR intrinsics (the caller passes no prior then): their range offsets
    and scales trade off against the free planes, and on the tests' sample of the points the
    system is nearly singular along that trade. On 20 s VLP-16 and OS1-64 shakes and sinusoids
    with the LiDAR intrinsics estimated, the clean runs 0.3-1.7 mm off, the translation sigmas
    grew to 7-196 mm (a clean VLP-16 sinusoid 0.94 mm off: 196 mm, the IMU priors' part 713
    times the solver's sigma); with the planes held, 0.7-2.2 mm on that sinusoid."""
    if system is None or not prior:
        return {}, None
    s, _, at = system
    kept = np.asarray(b, dtype=np.float64)[at >= 0]  # the system's rows, in order
    spread = planes_free_spreads((s, kept, at), base, groups, prior, selected, variance_factor)
    joint = _joint_prior(
        s,
        kept,
        [int(i) for i in at[base]],
        {n: [int(i) for i in at[groups[n]]] for n in prior},
        prior,
        variance_factor,
    )
    return spread, joint


def _columns(
    base: list[int], groups: dict[str, list[int]], names: Sequence[str]
) -> npt.NDArray[np.intp]:
    """The calibration coordinates of ``base`` and of the ``names``' groups, sorted."""
    return np.unique(
        np.concatenate(
            [np.asarray(base, dtype=np.intp)]
            + [np.asarray(groups[n], dtype=np.intp) for n in names]
        )
    )


def _lidar_sample(
    inputs: RoundInputs, subset: npt.NDArray[np.intp]
) -> tuple[PointSample, npt.NDArray[np.intp], Planes, F64]:
    """The tests' sample of the final round's points: the points, each one's plane, the planes
    and each point's range noise (m)."""
    return (
        inputs.points.subset(subset),
        np.asarray(inputs.lidar.plane, dtype=np.intp)[subset],
        inputs.planes,
        inputs.noise.range_noise(inputs.points.beam[subset]),
    )


def _larger_spread(fixed: F64, free: EffectScore | None) -> F64:
    """Per coordinate, the larger of the planes-fixed posterior spread and the planes-free
    one (the planes-fixed one without the latter)."""
    if free is None:
        return fixed
    return np.maximum(fixed, np.asarray(free.prior_shift_sigma, dtype=np.float64)[: fixed.size])


def _lidar_wanted(selection: EffectSelection, p_value: float) -> list[str]:
    """The LiDAR effects tested below ``p_value``: their shifts are computed with the planes
    free (:func:`~licalib_cli.pipeline.effect_shift.planes_free_shifts`), each freed with the
    effects selected before it (as the tests).

    The IMU effects keep their planes-fixed shifts: with the planes free as well, an IMU effect
    that trades off with the extrinsic rotation (a gyro-to-IMU rotation) is only weakly
    determined on a window with little motion, and its linearised shift grew to degrees where
    the extrinsic was 0.03 deg off (a 10 s walking window with one fast burst, whose gyro
    misfit hints at a gyro rotation the data do not hold)."""
    return [
        s.name
        for s in (*selection.selected, *selection.remaining)
        if s.p_value < p_value and s.name.startswith("lidar")
    ]
