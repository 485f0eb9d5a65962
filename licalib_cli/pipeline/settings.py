"""Every translation of the config tree into the settings of a stage, in one place.

The stages (odometry, hand-eye, time offset, lever arm, surfels, solver) keep their own small
frozen settings types so that they can be used without a :class:`~licalib_cli.config.
CalibConfig`; this module is the only place that reads the config tree for them.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np
import numpy.typing as npt

from licalib_cli.config import CalibConfig
from licalib_cli.estimation import (
    CALIBRATION_SCALES,
    IMU_INTRINSIC_BLOCKS,
    CalibrationState,
    FreeParameters,
    NoiseModel,
)
from licalib_cli.initialization.rotation import HandEyeConfig
from licalib_cli.initialization.time_offset import TimeOffsetConfig
from licalib_cli.initialization.translation import LeverArmConfig
from licalib_cli.models.lidar import INTRINSIC_NAMES, nominal_intrinsics_array
from licalib_cli.odometry import OdometryConfig
from licalib_cli.residuals import (
    ACCEL_BIAS_DRIFT,
    ACCEL_SCALE,
    EXT_TRANSLATION,
    GYRO_BIAS_DRIFT,
    GYRO_G_SENSITIVITY,
    GYRO_ROTATION,
    GYRO_SCALE,
    LIDAR_INTRINSICS,
    POINT_TIME_SCALE,
    TIME_DRIFT,
    GaussianPrior,
)
from licalib_cli.solver.lm import LMParams
from licalib_cli.surfels import SurfelConfig

if TYPE_CHECKING:
    from licalib_cli.io.clock_rate import ClockRate
    from licalib_cli.spline import UniformKnots

__all__ = [
    "DEFAULT_MAX_DISTANCE_M",
    "DISTANCE_PER_RANGE_SIGMA",
    "IMU_INTRINSIC_NAMES",
    "LIDAR_COLUMNS",
    "LOOSE_BLUR_SHARE",
    "MIN_THICKNESS_M",
    "SETTLED_COST_TOLERANCE",
    "SIZED_CALIBRATION_BLOCKS",
    "THICKNESS_PER_RANGE_SIGMA",
    "NoiseLevels",
    "RoundSettings",
    "association_distance",
    "calibration_block",
    "estimates_intrinsics",
    "expected_size",
    "free_parameters",
    "hand_eye_config",
    "lever_arm_config",
    "lm_params",
    "narrow_association",
    "noise_model",
    "odometry_config",
    "range_noise_in_data",
    "round_settings",
    "spline_margin_s",
    "surfel_config",
    "time_offset_config",
    "with_clock_rate",
]

F64 = npt.NDArray[np.float64]

DEFAULT_MAX_DISTANCE_M = 0.03
"""The association distance of the settled rounds when ``surfels.max_distance_m`` is unset, for
a LiDAR of at most 1.5 cm range noise (:func:`association_distance`)."""

DISTANCE_PER_RANGE_SIGMA = 2.0
"""An unset ``surfels.max_distance_m`` is at least this many range-noise sigmas: the 3 cm of
the default at the 1.5 cm of the simulator's default noise. At 0.75 sigma (3 cm for 4 cm of
noise) clean sinusoids ended 10-40 mm off under PASS verdicts; 1.5, 2 and 3 sigmas all brought
the same bags within 2 of their sigmas (benchmarks/RESULTS.md, forty-ninth stop)."""


def range_noise_in_data(noise: NoiseLevels) -> float:
    """The range noise the points carry: the larger of the weighting sigma (configured or
    measured) and the noise measured in the bag, where measured."""
    measured = noise.range_measured_m
    return max(noise.range_sigma_m, measured) if np.isfinite(measured) else noise.range_sigma_m


def association_distance(cfg: CalibConfig, noise: NoiseLevels) -> float:
    """``surfels.max_distance_m``, or where unset the larger of :data:`DEFAULT_MAX_DISTANCE_M`
    and :data:`DISTANCE_PER_RANGE_SIGMA` times :func:`range_noise_in_data`, m."""
    if cfg.surfels.max_distance_m is not None:
        return float(cfg.surfels.max_distance_m)
    return max(DEFAULT_MAX_DISTANCE_M, DISTANCE_PER_RANGE_SIGMA * range_noise_in_data(noise))


def narrow_association(cfg: CalibConfig, noise: NoiseLevels) -> str | None:
    """A sentence when a configured ``surfels.max_distance_m`` is under
    :data:`DISTANCE_PER_RANGE_SIGMA` times the range noise in the data; else None."""
    configured = cfg.surfels.max_distance_m
    sigma = range_noise_in_data(noise)
    if configured is None or configured >= DISTANCE_PER_RANGE_SIGMA * sigma:
        return None
    return (
        f"surfels.max_distance_m = {100 * configured:.1f} cm is under twice the LiDAR's range "
        f"noise ({100 * sigma:.1f} cm): the association kept only the returns nearest their "
        "planes, which pulls the fit towards its own map and hides the noise from the residual "
        f"check; raise it to at least {100 * DISTANCE_PER_RANGE_SIGMA * sigma:.1f} cm, or leave "
        "it unset so that it follows the noise."
    )


THICKNESS_PER_RANGE_SIGMA = 1.5
"""Default ``surfels.max_thickness_m`` in units of the range noise: range noise alone gives an
RMS of at most one sigma off a plane; a cell much thicker than that straddles surfaces."""

SECOND_SURFACE_FACTOR = 6.0
"""A cell with a point farther from its plane than this many thickness limits (9 range-noise
sigmas by default, far beyond any return of a single plane) holds a second surface and is not a
surfel at its level (``SurfelConfig.max_point_distance_m``). Three and four limits removed the
same bias on shaking but split more cells than needed: with three the sinusoids' extrinsic with
the LiDAR intrinsics moved by a tenth of a millimetre, with four diagnose lost two effects it
had named (benchmarks/RESULTS.md)."""

MIN_THICKNESS_M = 0.005
"""Floor of the default ``surfels.max_thickness_m``: the map's own blur (the estimate, each
sweep's deskew) and real surfaces make any cell a few millimetres thick, so a nearly noise-free
LiDAR (a measured 0.03 mm) would otherwise leave no surfel at all ("No planar surfaces").
Not lower: at 2 mm a LiDAR with 2 mm of noise and per-beam errors still being estimated lost
its map in the rounds at the configured distance (three sinusoids of seven refused or failed,
benchmarks/RESULTS.md)."""

LOOSE_BLUR_SHARE = 0.5
"""While the association is loose, the default thickness limit is at least this share of how
far beyond ``surfels.max_distance_m`` it reaches: the points may still be that far off, so the
map is that blurred whatever the range noise. A nearly noise-free LiDAR (5 mm limit, 15 mm in
the first round) otherwise kept 2 % of the points of a first map blurred by the LiDAR
intrinsics, and the rounds never recovered (benchmarks/RESULTS.md). With the default distances
it binds only below about 7 mm of range noise."""


@dataclass(frozen=True)
class NoiseLevels:
    """The sensor noise the fit is weighted with (discrete, per sample).

    Attributes:
        gyro_sigma: (3,) rad/s.
        accel_sigma: (3,) m/s^2.
        range_sigma_m: LiDAR range noise, m.
        gyro_source: ``config`` or ``data``.
        accel_source: ``config`` or ``data``.
        range_source: ``config`` or ``data``.
        range_sigma_per_beam: (B,) measured range noise per beam (NaN where unknown), m.
        gyro_measured: (3,) the gyro noise measured from the data, rad/s.
        accel_measured: (3,) the accelerometer noise measured from the data, m/s^2.
        range_measured_m: the range noise measured from the data (median over beams), m.
    """

    gyro_sigma: F64
    accel_sigma: F64
    range_sigma_m: float
    gyro_source: str
    accel_source: str
    range_source: str
    range_sigma_per_beam: F64
    gyro_measured: F64
    accel_measured: F64
    range_measured_m: float


def odometry_config(cfg: CalibConfig) -> OdometryConfig:
    """kiss-icp settings."""
    o = cfg.odometry
    return OdometryConfig(
        voxel_size=o.voxel_size_m,
        max_range=o.max_range_m,
        min_range=o.min_range_m,
        deskew=o.deskew,
        max_points_per_voxel=o.max_points_per_voxel,
    )


def hand_eye_config(cfg: CalibConfig) -> HandEyeConfig:
    """Hand-eye rotation settings."""
    ini = cfg.initialization
    return HandEyeConfig(
        min_angle_deg=ini.min_rotation_deg,
        max_singular_ratio=ini.max_singular_ratio,
        min_axis_ratio=ini.min_axis_ratio,
    )


def time_offset_config(cfg: CalibConfig, max_lag_s: float | None = None) -> TimeOffsetConfig:
    """Angular-rate cross-correlation settings; the lag ``max_lag_s`` (default
    ``initialization.time_offset_max_lag_s``)."""
    ini = cfg.initialization
    return TimeOffsetConfig(
        max_lag_s=ini.time_offset_max_lag_s if max_lag_s is None else max_lag_s,
        min_peak_correlation=ini.min_peak_correlation,
    )


def lever_arm_config(cfg: CalibConfig, noise: NoiseLevels) -> LeverArmConfig:
    """Lever-arm least-squares settings (the accelerometer weight follows its noise, with room
    for what the gyro-only rotation and the spline cannot represent)."""
    return LeverArmConfig(accel_sigma=max(0.1, 5.0 * float(np.max(noise.accel_sigma))))


def surfel_config(cfg: CalibConfig, noise: NoiseLevels, max_distance_m: float) -> SurfelConfig:
    """Surfel and association settings of a round.

    The thickness limit scales with the association distance: while the association is loose
    (the map still blurred by the estimate) surfels may be thicker, and the default limit is at
    least :data:`LOOSE_BLUR_SHARE` of the looseness. A cell with a point beyond
    :data:`SECOND_SURFACE_FACTOR` thickness limits from its plane is left to the finer cells.
    """
    s = cfg.surfels
    base = association_distance(cfg, noise)
    if s.max_thickness_m is not None:
        limit = s.max_thickness_m * max_distance_m / base
    else:
        thickness = max(THICKNESS_PER_RANGE_SIGMA * range_noise_in_data(noise), MIN_THICKNESS_M)
        limit = max(
            thickness * max_distance_m / base,
            LOOSE_BLUR_SHARE * (max_distance_m - base),
        )
    return SurfelConfig(
        cell_sizes=tuple(s.cell_sizes_m),
        min_points=s.min_points,
        min_planarity=s.min_planarity,
        max_thickness_m=limit,
        max_point_distance_m=SECOND_SURFACE_FACTOR * limit,
        max_distance_m=max_distance_m,
    )


def noise_model(cfg: CalibConfig, noise: NoiseLevels) -> NoiseModel:
    """Residual weights of the problem, and the range noise the data carry per beam.

    The weights use the configured range sigma when one is set; the map planes'
    errors-in-variables correction uses the noise measured per beam (the beams' median where a
    beam has too few returns to measure, the weighting sigma when none could be measured). A
    correction with a configured 10 mm on data carrying 0.1 mm put the common range offset 40 mm
    off, as an uncorrected fit does the other way.
    """
    return NoiseModel(
        gyro_sigma=np.asarray(noise.gyro_sigma, dtype=np.float64),
        accel_sigma=np.asarray(noise.accel_sigma, dtype=np.float64),
        range_sigma=noise.range_sigma_m,
        huber_threshold=cfg.noise.huber_sigmas,
        min_incidence_cos=cfg.noise.min_incidence_cos,
        range_noise_per_beam=measured_range_noise(noise),
    )


def measured_range_noise(noise: NoiseLevels) -> F64:
    """(B,) the range noise per beam as measured, filled where a beam could not be measured
    (:func:`noise_model`)."""
    per_beam = np.asarray(noise.range_sigma_per_beam, dtype=np.float64).reshape(-1)
    fill = noise.range_measured_m if np.isfinite(noise.range_measured_m) else noise.range_sigma_m
    return np.where(np.isfinite(per_beam), per_beam, float(fill))


INITIAL_LAMBDA = 1e-9
"""Initial Levenberg-Marquardt damping of every solve, relative to ``diag(H)``.

The spline's weakest directions (knots seen by few points, moved mostly through the
accelerometer's double integration) carry eigenvalues far below their diagonal. A damping of
1e-6 held them back, so every round crawled along them for its full iteration cap, the steps
growing as the damping fell (a 12 s shake: rounds of six iterations whose cost kept falling by
10-20); at 1e-9 the same rounds end in two or three iterations at a lower cost. A step that
does not reduce the cost raises the damping as before (Nielsen)."""


SETTLED_COST_TOLERANCE = 0.05
"""Cost (half the whitened chi-square) the next step of a solve must still remove: a step that
would remove less moves the estimate by under ``sqrt(2 * 0.05)``, 0.32, of a sigma along its
own direction and the calibration by less than that of its own sigmas (its marginal
information being at most the joint one), as a planes-free step below
:data:`~licalib_cli.pipeline.free_planes.MIN_GAIN` is not taken either. Without it the relative
tolerance alone (1e-8 of costs of 1e4-1e5) let the solves after the planes-free steps and the
checks' refits run whole iterations for gains of 0.003-0.1."""


def lm_params(
    cfg: CalibConfig,
    max_iterations: int | None = None,
    cost_tolerance: float = SETTLED_COST_TOLERANCE,
    function_tolerance: float = LMParams.function_tolerance,
) -> LMParams:
    """Levenberg-Marquardt settings of a solve (a step must remove at least
    :data:`SETTLED_COST_TOLERANCE` of the cost unless ``cost_tolerance`` says otherwise)."""
    return LMParams(
        max_iterations=cfg.schedule.iterations_per_round
        if max_iterations is None
        else max_iterations,
        initial_lambda=INITIAL_LAMBDA,
        min_decrease=0.1,
        cost_tolerance=cost_tolerance,
        function_tolerance=function_tolerance,
        use_tsvd=cfg.solver.use_tsvd,
        tsvd_threshold=cfg.solver.tsvd_threshold,
        weak_floor=cfg.solver.weak_floor,
    )


LIDAR_COLUMNS: dict[str, str] = {
    "elevation": "dphi",
    "azimuth": "dtheta",
    "vertical_offset": "V",
    "horizontal_offset": "H",
    "range_scale": "s",
    "range_offset": "drho",
}
"""``model.lidar`` names -> per-beam intrinsic names of the LiDAR model."""


def free_parameters(cfg: CalibConfig, intrinsics: bool) -> FreeParameters:
    """What a round estimates: always the trajectory, biases, gravity, extrinsic and time
    offset; with ``intrinsics`` also the blocks of the ``model:`` section."""
    m = cfg.model
    prior = translation_prior(cfg)
    beams = not cfg.lidar.non_repetitive
    if not intrinsics:
        return FreeParameters(
            min_points_per_beam=m.min_points_per_beam,
            translation_prior=prior,
            beam_intrinsics=beams,
        )
    spread = tuple(
        (LIDAR_COLUMNS[name], sigma)
        for name in m.lidar
        if name in LIDAR_COLUMNS and (sigma := m.lidar_spread.sigma_of(name)) is not None
    )
    return FreeParameters(
        translation_prior=prior,
        lidar_spread=spread,
        imu_blocks=frozenset(f"imu.{name}" for name in m.imu if name in IMU_INTRINSIC_NAMES),
        g_sensitivity="g_sensitivity" in m.imu,
        lidar_columns=frozenset(LIDAR_COLUMNS[name] for name in m.lidar if name in LIDAR_COLUMNS),
        min_points_per_beam=m.min_points_per_beam,
        gyro_bias_drift="gyro_bias_walk" in m.imu,
        accel_bias_drift="accel_bias_walk" in m.imu,
        time_drift="clock_drift" in m.imu,
        point_time="point_time" in m.lidar,
        bias_walk_piece_s=m.bias_walk_piece_s,
        expected_size=tuple(
            (calibration_block(name), size) for name, size in sorted(m.expected_size.items())
        ),
        beam_intrinsics=beams,
    )


SIZED_CALIBRATION_BLOCKS: dict[str, str] = {
    "g_sensitivity": GYRO_G_SENSITIVITY,
    "gyro_bias_walk": GYRO_BIAS_DRIFT,
    "accel_bias_walk": ACCEL_BIAS_DRIFT,
    "clock_drift": TIME_DRIFT,
    "point_time": POINT_TIME_SCALE,
}
"""``model:`` names -> calibration blocks, where not ``imu.<name>``."""


def calibration_block(name: str) -> str:
    """The calibration block of ``model:`` block ``name`` (an IMU block, a drift effect or
    ``point_time``): ``imu.gyro_scale``, ``imu.gyro_bias_drift``, ``ext.time_drift`` ..."""
    return SIZED_CALIBRATION_BLOCKS.get(name, f"imu.{name}")


def expected_size(cfg: CalibConfig, block: str) -> float:
    """The size ``model:`` block ``block`` (``gyro_bias_walk``, ...) is expected to have per
    coordinate: ``model.expected_size``'s, else the built-in characteristic scale."""
    given = cfg.model.expected_size.get(block)  # type: ignore[call-overload]
    if given is not None:
        return float(given)
    return float(max(CALIBRATION_SCALES[calibration_block(block)]))


def translation_prior(
    cfg: CalibConfig,
) -> tuple[tuple[float, float, float], tuple[float, float, float]] | None:
    """``(mean, sigma)`` of the prior on the extrinsic translation
    (``initialization.translation_m`` and ``translation_sigma_m``), or None without one."""
    ini = cfg.initialization
    if ini.translation_m is None or ini.translation_sigma_m is None:
        return None  # the config refuses a sigma without translation_m
    (mx, my, mz), (sx, sy, sz) = ini.translation_m, ini.translation_sigma_m
    return (mx, my, mz), (sx, sy, sz)


def prior_sd(cfg: CalibConfig) -> dict[str, float]:
    """Calibration coordinate -> sigma of the configured prior on the extrinsic translation
    (empty without one)."""
    prior = translation_prior(cfg)
    if prior is None:
        return {}
    return {f"{EXT_TRANSLATION}.{a}": s for a, s in zip("xyz", prior[1], strict=True)}


def translation_priors(free: FreeParameters) -> list[GaussianPrior]:
    """The prior on the extrinsic translation of ``free`` (``free.translation_prior``), as a
    residual block; none without one or when the translation is held."""
    if free.translation_prior is None or not free.extrinsic_translation:
        return []
    return [GaussianPrior(EXT_TRANSLATION, *free.translation_prior)]


IMU_INTRINSIC_NAMES = (
    "gyro_scale",
    "gyro_misalignment",
    "gyro_rotation",
    "accel_scale",
    "accel_misalignment",
)
"""``model.imu`` names of the IMU intrinsic blocks (``imu.<name>``) besides g-sensitivity."""


INTRINSIC_PRIOR_SIGMA: dict[str, float | tuple[float, ...]] = {
    "imu.gyro_scale": 0.01,
    "imu.gyro_misalignment": 0.01,
    "imu.gyro_rotation": 0.05,
    "imu.accel_scale": 0.01,
    "imu.accel_misalignment": 0.01,
    "imu.gyro_g_sensitivity": 1e-3,
    "lidar.intrinsics": (0.01, 0.01, 0.05, 0.05, 1e-3, 0.05),
}
"""Standard deviations of the weak priors that keep estimated intrinsics near nominal where
the data hardly determine them (about ten times the spread of real sensors' intrinsics:
scales 1 %, misalignments 0.6 deg, gyro rotation 3 deg, beam angles 0.6 deg, beam offsets
5 cm, range scale 0.1 %, range offset 5 cm); they keep weak directions from drifting between
rounds and barely move well-observed ones."""


def model_priors(state: CalibrationState, free: FreeParameters) -> list[GaussianPrior]:
    """Weak priors toward nominal on every estimated intrinsic block, the configured prior on
    the extrinsic translation (``free.translation_prior``), and the clock drift the stamps
    measure on an estimated drift (``free.time_drift_prior``)."""
    out = translation_priors(free)
    for block in IMU_INTRINSIC_BLOCKS:
        if not free.imu_block_free(block):
            continue
        nominal = {
            GYRO_SCALE: np.ones(3),
            ACCEL_SCALE: np.ones(3),
            GYRO_ROTATION: np.array([0.0, 0.0, 0.0, 1.0]),
        }.get(block, np.zeros(9 if block == GYRO_G_SENSITIVITY else 3))
        out.append(
            GaussianPrior(
                block,
                nominal,
                INTRINSIC_PRIOR_SIGMA[block],
                manifold="so3" if block == GYRO_ROTATION else "euclidean",
            )
        )
    if free.any_lidar_intrinsics:
        b = state.lidar_intrinsics.num_beams
        nominal = nominal_intrinsics_array(b)
        columns = np.array(INTRINSIC_PRIOR_SIGMA[LIDAR_INTRINSICS], dtype=np.float64)
        for name, spread in free.lidar_spread:
            columns[INTRINSIC_NAMES.index(name)] = spread
        sigma = np.broadcast_to(columns, nominal.shape)
        out.append(GaussianPrior(LIDAR_INTRINSICS, nominal, sigma))
    if free.time_drift and free.time_drift_prior is not None:
        mean, sd = free.time_drift_prior
        out.append(GaussianPrior(TIME_DRIFT, np.array([mean]), sd))
    return out


def estimates_intrinsics(cfg: CalibConfig) -> bool:
    """Whether the ``model:`` section asks for any intrinsic."""
    return bool(cfg.model.imu or cfg.model.lidar)


def spline_margin_s(padding_s: float, knots: UniformKnots) -> float:
    """How far inside the spline a point's trajectory time ``tau + t_c`` must stay, s (room
    for the time offset to move): ``spline.time_offset_padding_s``, at least two intervals of
    the knots the splines were laid with."""
    return max(padding_s, 2 * knots.dt_s)


@dataclass(frozen=True)
class RoundSettings:
    """What one refinement round runs with (the schedule chooses them round by round).

    Attributes:
        surfels: surfel and association settings (the round's association distance).
        weights: residual weights.
        solver: Levenberg-Marquardt settings.
        free: what the round estimates.
        padding_s: ``spline.time_offset_padding_s``: points whose trajectory time comes closer
            to the spline's ends than :meth:`margin_s` are left out.
    """

    surfels: SurfelConfig
    weights: NoiseModel
    solver: LMParams
    free: FreeParameters
    padding_s: float

    def margin_s(self, knots: UniformKnots) -> float:
        """The margin on splines with ``knots`` (:func:`spline_margin_s`), s."""
        return spline_margin_s(self.padding_s, knots)


def with_clock_rate(settings: RoundSettings, rate: ClockRate | None) -> RoundSettings:
    """``settings`` whose estimated clock drift (if any) gets the rate the stamps show against
    the record times as a prior (``FreeParameters.time_drift_prior``): both measure how fast
    the IMU's stamps run against the LiDAR's, and free IMU scales take up most of a drift the
    data alone must tell (a 50 ppm drift on an 8 s sinusoid came out 10.9 +/- 32.3 ppm)."""
    if rate is None or not settings.free.time_drift or not rate.sigma > 0.0:
        return settings
    free = replace(settings.free, time_drift_prior=(float(rate.rate), float(rate.sigma)))
    return replace(settings, free=free)


PROVISIONAL_COST_TOLERANCE = 0.1
"""Cost (half the whitened chi-square) a provisional round's next step must still remove:
stopping there leaves the estimate within about ``sqrt(2 * 0.1)``, 0.45, of a sigma of that
round's optimum along the direction the step would take."""


COARSE_FUNCTION_TOLERANCE = 1e-3
"""Fraction of the cost a coarse round's next step must still remove (a round associating
farther than ``surfels.max_distance_m``). Its map is rebuilt and its associations tightened in
the rounds after it, which change the cost by far more (a 15 s sinusoid: 5.5e4 after the first
round, 1.6e5 at the start of the second), so its last steps of a few hundredths of a per cent
are left to them."""


def round_settings(
    cfg: CalibConfig,
    noise: NoiseLevels,
    max_distance_m: float,
    intrinsics: bool,
    *,
    provisional: bool = False,
    evaluate_only: bool = False,
) -> RoundSettings:
    """The settings of a round associating within ``max_distance_m``, with the intrinsics of
    the ``model:`` section free when ``intrinsics``.

    A ``provisional`` round is followed by another on a map rebuilt from its estimate (and, when
    the estimate settles, by the denser final round): its solve stops once a step would lower
    the cost by less than :data:`PROVISIONAL_COST_TOLERANCE`, the last few tenths of a sigma
    being left to the rounds after it. With intrinsics too: the rounds stopped early move the
    slow directions (the range scales' common mode) by less, but the dense round's planes-free
    steps take those to the optimum (ten 10 s sinusoids with every intrinsic free: range-scale
    mean absolute error 3.0e-5 either way, 3e-4 before the dense round estimated its planes;
    the rounds 5 % faster).

    A coarse round (associating farther than ``surfels.max_distance_m``) stops once a step
    would lower the cost by less than :data:`COARSE_FUNCTION_TOLERANCE` of it.

    An ``evaluate_only`` round builds its map, associations and problem and linearises them at
    its starting estimate without a solver step: the planes-free steps then take over from that
    linearisation (the denser final round, :mod:`schedule`)."""
    tolerance = PROVISIONAL_COST_TOLERANCE if provisional else SETTLED_COST_TOLERANCE
    coarse = max_distance_m > association_distance(cfg, noise)
    return RoundSettings(
        surfels=surfel_config(cfg, noise, max_distance_m),
        weights=noise_model(cfg, noise),
        solver=lm_params(
            cfg,
            max_iterations=0 if evaluate_only else None,
            cost_tolerance=tolerance,
            function_tolerance=COARSE_FUNCTION_TOLERANCE if coarse else LMParams.function_tolerance,
        ),
        free=free_parameters(cfg, intrinsics),
        padding_s=cfg.spline.time_offset_padding_s,
    )
