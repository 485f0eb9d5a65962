"""One typed configuration tree (pydantic v2, unknown keys rejected).

A YAML config mirrors :class:`CalibConfig`; every section is optional. Command-line options
override the file. ``licalib config dump`` prints the resolved tree.
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Sequence
from itertools import pairwise
from pathlib import Path
from typing import Annotated, Any, Literal

import yaml
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    field_validator,
    model_validator,
)
from pydantic.fields import FieldInfo

from licalib_cli.errors import ConfigError

OPTION_NAMES = {
    "imu.topic": "--imu-topic",
    "lidar.topic": "--lidar-topic",
    "bag.start_s": "--start",
    "bag.duration_s": "--duration",
    "model.imu": "--intrinsics",
    "model.lidar": "--intrinsics",
}
"""The command-line option that sets a config key, for messages about a bad option value."""


class _Section(BaseModel):
    # No inf or NaN anywhere: every setting is a finite number of seconds, metres, ...
    model_config = ConfigDict(extra="forbid", validate_assignment=True, allow_inf_nan=False)


class ImuInputConfig(_Section):
    """How to read the IMU messages."""

    topic: str | None = None
    """``sensor_msgs/Imu`` topic; found automatically when the bag has exactly one."""
    gyro_unit: Literal["rad/s", "deg/s"] | None = None
    """Unit of ``angular_velocity``; detected from the data when unset."""
    accel_unit: Literal["m/s^2", "g"] | None = None
    """Unit of ``linear_acceleration``; detected from the data when unset."""


class LidarInputConfig(_Section):
    """How to read the PointCloud2 messages."""

    topic: str | None = None
    """``sensor_msgs/PointCloud2`` topic; found automatically when the bag has exactly one."""
    time_field: str | None = None
    """Per-point time field name (``t``, ``time``, ``timestamp``, ``offset_time``, ...); detected.
    ``none`` ignores any time field and estimates per-point times from azimuth."""
    time_unit: Literal["s", "ms", "us", "ns"] | None = None
    """Unit of the per-point time field; detected from the data when unset."""
    time_reference: Literal["relative", "absolute"] | None = None
    """Whether the per-point times are relative to the header stamp or absolute; detected."""
    stamp_position: Literal["start", "end"] | None = None
    """Whether the header stamp marks the sweep start or end (used when times are estimated)."""
    ring_field: str | None = None
    """Beam index field (``ring`` or ``line``); detected. Recovered from elevation if absent;
    ``none`` forces recovery from elevation."""
    num_beams: int | None = Field(default=None, ge=1, le=512)
    """Number of beams, needed only when there is no ring field and elevations are ambiguous."""
    scan_period_s: float | None = Field(default=None, gt=0.0, le=1.0)
    """Sweep period used to estimate per-point times from azimuth; detected from stamps."""
    clockwise: bool = False
    """Spin direction used when per-point times are estimated from azimuth."""
    min_range_m: float = Field(default=0.5, ge=0.0)
    max_range_m: float = Field(default=100.0, gt=0.0)
    nominal_elevation_deg: list[Annotated[float, Field(ge=-90.0, le=90.0)]] | None = Field(
        default=None, min_length=1, max_length=512
    )
    """Beam table: nominal elevation of each ring (ring 0 first), degrees; estimated from the
    data when unset. Must list every ring of the clouds."""
    max_skipped_fraction: float = Field(default=0.5, ge=0.0, le=1.0)
    """Unusable clouds (empty, NaN, corrupt, too few points) are skipped with a warning; more
    than this fraction of the segment's clouds skipped is an error."""
    scan_pattern: Literal["auto", "spinning", "non_repetitive"] = "auto"
    """Whether the beam field numbers rings of fixed elevation (``spinning``: Velodyne, Ouster,
    Hesai, ...) or groups points of many elevations (``non_repetitive``: a Livox's ``line``
    field). ``auto``: from the spread of the elevations within each beam (a ring's spread is
    well under a degree). A non-repetitive scanner has no per-beam intrinsics to estimate
    (``model.lidar``'s per-beam blocks are refused); its points are grouped into elevation
    bins of :data:`~licalib_cli.pipeline.scan_pattern.BIN_DEG` for the LiDAR model and its
    range noise is measured along each line's point order."""

    @property
    def non_repetitive(self) -> bool:
        """Whether ``scan_pattern`` says lines of a non-repetitive scanner (as given, or as the
        data showed once the pipeline resolved it)."""
        return self.scan_pattern == "non_repetitive"

    @model_validator(mode="after")
    def _beam_table_matches_num_beams(self) -> LidarInputConfig:
        table = self.nominal_elevation_deg
        if table is not None and self.num_beams is not None and len(table) != self.num_beams:
            msg = (
                f"nominal_elevation_deg lists {len(table)} beams but num_beams is "
                f"{self.num_beams}; give one elevation per beam"
            )
            raise ValueError(msg)
        return self


class BagConfig(_Section):
    """Which part of the bag to use."""

    start_s: float = Field(default=0.0, ge=0.0)
    """Seconds after the first message at which the segment starts."""
    duration_s: float | None = Field(default=None, gt=0.0)
    """Length of the segment; the whole bag (up to ``max_duration_s``) when unset."""
    max_duration_s: float = Field(default=60.0, gt=0.0)
    """Without ``duration_s``, a longer bag is cut to this many seconds after ``start_s`` (with
    a warning): 15-60 s of well-excited motion determine the calibration, and memory and time
    grow with the length."""


class NoiseConfig(_Section):
    """Sensor noise used to weight the residuals; measured from the data when unset.

    The fit checks compare the residuals with this noise (docs/checks.md, "Noise"): a value
    given here is trusted as the sensor's noise, so a wrong value shows up as a misfit; leave a
    value unset to have it measured from the recording itself.
    """

    gyro_noise_density: float | None = Field(default=None, gt=0.0)
    """Gyro white noise, rad/s/sqrt(Hz) (Xsens MTi-100: 1.75e-4, i.e. 0.01 deg/s/sqrt(Hz))."""
    accel_noise_density: float | None = Field(default=None, gt=0.0)
    """Accelerometer white noise, m/s^2/sqrt(Hz) (Xsens MTi-100: 5.9e-4, i.e. 60 ug/sqrt(Hz))."""
    range_sigma_m: float | None = Field(default=None, gt=0.0)
    """LiDAR range noise, one sigma, metres (VLP-16: about 0.01)."""
    huber_sigmas: float = Field(default=2.0, gt=0.0)
    """Huber threshold of the point-to-plane residuals, in sigmas."""
    min_incidence_cos: float = Field(default=1.0, gt=0.0, le=1.0)
    """The range noise moves a point along its ray, so its distance to its plane varies by the
    range noise times the cosine of the ray's incidence angle. Below 1, each point-to-plane
    residual whose ray meets its plane with at least this cosine is weighted so; flatter rays
    keep the full range noise (their distances carry errors the cosine does not). 1 (the
    default): every point weighted with the full range noise. 0.2 made the paper's sinusoids'
    translation 6 % more accurate over twenty seeds but their gyro scales less so
    (docs/checks.md, "Noise")."""


class OdometrySection(_Section):
    """kiss-icp LiDAR odometry used for initialisation."""

    voxel_size_m: float | None = Field(default=1.0, gt=0.0)
    """kiss-icp voxel size, m; null: max_range/100. The default is kiss-icp's own for its
    100 m range: the refinement after kiss-icp registers every scan finely, so kiss-icp only
    has to be roughly right (a 15 s VLP-16 sinusoid: 2.1 s with 0.6 m, 0.7 s with 1 m)."""
    min_range_m: float = Field(default=0.5, ge=0.0)
    max_range_m: float = Field(default=60.0, gt=0.0)
    max_points_per_voxel: int = Field(default=20, ge=1)
    deskew: bool = True


MAX_LEVER_ARM_M = 10.0
"""The farthest ``initialization.translation_m`` may put the LiDAR from the IMU, m."""


class InitializationConfig(_Section):
    """Initial guesses and the checks on them."""

    time_offset_max_lag_s: float = Field(default=0.2, gt=0.0, le=30.0)
    """Largest |time offset| searched by cross-correlating angular speeds (and by the rotation
    search on violent motion); widened to the clocks' difference from record times plus 0.1 s
    when that is larger and under 1 s (from 1 s on the LiDAR times are shifted)."""
    min_peak_correlation: float = Field(default=0.7, ge=0.0, le=1.0)
    min_rotation_deg: float = Field(default=0.5, ge=0.0)
    """Scan-to-scan rotations smaller than this are not used for hand-eye alignment."""
    max_singular_ratio: float = Field(default=0.3, gt=0.0, le=1.0)
    """Hand-eye is refused when the ratio of its two smallest singular values exceeds this."""
    min_axis_ratio: float = Field(default=0.1, gt=0.0, le=1.0)
    """Hand-eye needs rotation about a second axis of at least this fraction of the first."""
    max_hand_eye_residual_deg: float = Field(default=1.0, gt=0.0)
    """Hand-eye on the LiDAR-only odometry is trusted below this RMS residual; above it (or when
    it is refused) the rotation is searched over all of SO(3) by map sharpness with the gyro."""
    rotation_search: bool = True
    """Allow that search (it needs rotation about two axes within half a second)."""
    rotation_rpy_deg: list[float] | None = Field(default=None, min_length=3, max_length=3)
    """Optional initial extrinsic rotation; hand-eye alignment is used when unset."""
    translation_m: list[float] | None = Field(default=None, min_length=3, max_length=3)
    """Optional initial extrinsic translation (the LiDAR's origin in the IMU frame), m, within
    :data:`MAX_LEVER_ARM_M` of the IMU; unset: the lever arm the odometry and the accelerometer
    show (zero along what the motion does not determine)."""
    translation_sigma_m: list[Annotated[float, Field(ge=1e-4)]] | None = Field(
        default=None, min_length=3, max_length=3
    )
    """How well ``translation_m`` is known (a tape measure, a CAD drawing): 1-sigma, one number
    or one per IMU axis, m, at least 0.1 mm (no lever arm is measured better; a tighter prior
    swamps the solver's information and its truncation drops real directions). The calibration
    then holds the translation to it as a Gaussian prior: what the data do not determine (the
    vertical on planar motion) comes from it with this sigma instead of being reported
    unobservable, and the result says which directions rest on it. Needs ``translation_m``;
    unset: no prior."""
    time_offset_s: float | None = None
    """Optional initial time offset; cross-correlation is used when unset."""

    @field_validator("translation_m")
    @classmethod
    def _a_rig_s_lever_arm(cls, value: list[float] | None) -> list[float] | None:
        # a lever arm in millimetres or centimetres read as metres: the rounds start hundreds
        # of metres off and settle in a wrong minimum (30, 15, 5 for 0.30, 0.15, 0.05 m ended
        # 8 m off, the verdict only warning)
        lever = math.hypot(*value) if value is not None else 0.0
        if lever > MAX_LEVER_ARM_M:
            msg = (
                f"translation_m puts the LiDAR {lever:.3g} m from the IMU, farther "
                f"than any rig's lever arm ({MAX_LEVER_ARM_M:g} m); give it in metres (the "
                "LiDAR's origin in the IMU frame), or remove it to start from the lever arm "
                "the data show"
            )
            raise ValueError(msg)
        return value

    @field_validator("translation_sigma_m", mode="before")
    @classmethod
    def _one_sigma_for_every_axis(cls, value: Any) -> Any:
        # one number: the same on every axis
        return (
            [value] * 3
            if isinstance(value, (int, float)) and not isinstance(value, bool)
            else value
        )

    @model_validator(mode="after")
    def _translation_sigma_needs_translation(self) -> InitializationConfig:
        if self.translation_sigma_m is not None and self.translation_m is None:
            msg = (
                "translation_sigma_m says how well translation_m is known, but translation_m "
                "is not set; give translation_m (the measured lever arm) too, or remove "
                "translation_sigma_m"
            )
            raise ValueError(msg)
        return self


class SplineConfig(_Section):
    """Continuous-time trajectory."""

    knot_spacing_s: float | None = Field(default=None, ge=0.005, le=0.2)
    """Time between the trajectory splines' knots, s. Unset: chosen from the IMU's signals,
    the coarsest spacing from ``min_knot_spacing_s`` to ``max_knot_spacing_s`` whose splines
    still follow the gyro and accelerometer readings as closely as the finest does (at most
    5 % more residual variance, ``pipeline/knot_spacing.py``): slow, smooth motion gets fewer
    knots and a faster fit, a shake keeps the finest. The resolved config gives the spacing
    chosen."""
    min_knot_spacing_s: float = Field(default=0.02, ge=0.005, le=0.2)
    """The finest spacing the choice considers, s (and the one it falls back to)."""
    max_knot_spacing_s: float = Field(default=0.05, ge=0.005, le=0.2)
    """The coarsest spacing the choice considers, s."""
    time_offset_padding_s: float = Field(default=0.05, ge=0.0, le=1.0)
    """Extra spline length at both ends so that ``tau + time_offset_s`` stays inside."""

    @model_validator(mode="after")
    def _spacing_range(self) -> SplineConfig:
        if self.min_knot_spacing_s > self.max_knot_spacing_s:
            msg = (
                f"min_knot_spacing_s ({self.min_knot_spacing_s:g}) is above max_knot_spacing_s "
                f"({self.max_knot_spacing_s:g}); give a range with min <= max"
            )
            raise ValueError(msg)
        return self

    @property
    def spacing_s(self) -> float:
        """The knot spacing the splines use: ``knot_spacing_s``, or ``min_knot_spacing_s``
        where the data have not chosen one."""
        return self.knot_spacing_s if self.knot_spacing_s is not None else self.min_knot_spacing_s


class SurfelSection(_Section):
    """Surfel map and point-to-plane association."""

    cell_sizes_m: list[Annotated[float, Field(ge=0.01, le=100.0)]] = Field(
        default=[1.0, 0.5], min_length=1
    )
    """Voxel sizes, coarse to fine (each smaller than the one before, 1 cm to 100 m);
    non-planar coarse cells are split."""
    min_points: int = Field(default=10, ge=4)
    min_planarity: float = Field(default=0.8, ge=0.0, le=1.0)
    """Plane-likeness P = 2 (l1 - l0) / (l0 + l1 + l2) a cell needs to become a surfel."""
    max_thickness_m: float | None = Field(default=None, gt=0.0)
    """Cells whose points spread more than this off their plane (RMS) are not surfels; unset:
    1.5 x the range noise (the larger of noise.range_sigma_m and the noise measured in the bag),
    at least 5 mm. A thicker cell usually straddles two surfaces (a
    corner, a step) and biases the translation by millimetres. A cell with any point farther
    than 6 x this from its plane holds a second surface too (a few returns of it hardly thicken
    the cell) and is left to the finer cells."""
    max_distance_m: float | None = Field(default=None, gt=0.0)
    """Points further from their surfel's plane are not associated (in the rounds that have
    settled; the first rounds reach further). Unset: 3 cm, or twice the range noise where that
    is more (the larger of the configured ``noise.range_sigma_m`` and the noise measured in the
    bag). A distance under twice the noise keeps only the returns nearest their planes, which
    pulls the fit towards its own map and hides the noise from the residual check: with 4 cm of
    range noise, 3 cm left clean sinusoids 10-40 mm off under PASS verdicts
    (benchmarks/RESULTS.md, forty-ninth stop); such a configured distance is warned about."""
    points_per_scan: int = Field(default=1000, ge=50)
    """Points kept per scan for the optimisation (uniformly over the sweep)."""
    max_points: int = Field(default=600_000, ge=1000)
    """Cap on the points of a round over all scans (memory and time); ``points_per_scan`` and
    ``final_points_per_scan`` shrink on long segments to respect it. The dense final round's
    points bound the accuracy: 1 500 000 with ``final_points_per_scan`` 15 000 took twenty 10 s
    sinusoids from 1.86 to 1.36 mm off on average, for about 8 s and 1.6 GB more (README)."""
    final_points_per_scan: int | None = Field(default=6000, ge=50)
    """Points per scan of one last round once the others have settled (the uncertainty of the
    time offset and translation shrinks with the number of points); None skips it. The default
    keeps ``max_points`` over 10 s of a 10 Hz LiDAR: on the paper's 10 s sinusoid with every
    intrinsic estimated, 6000 instead of 4000 took the mean time-offset error over twenty seeds
    from 0.065 to 0.043 ms and the beams' horizontal offsets' from 0.30 to 0.22 mm, for about
    1.7 s more (benchmarks/RESULTS.md, forty-fifth stop); from 15 s on the cap decides."""

    @field_validator("cell_sizes_m")
    @classmethod
    def _coarse_to_fine(cls, sizes: list[float]) -> list[float]:
        if any(b >= a for a, b in pairwise(sizes)):
            msg = (
                f"cell sizes go from coarse to fine, each smaller than the one before; got {sizes}"
            )
            raise ValueError(msg)
        return sizes


class ScheduleConfig(_Section):
    """Refinement rounds (method.md section 7)."""

    max_rounds: int = Field(default=12, ge=1, le=50)
    """Most refinement rounds (map rebuild + optimisation). Rounds run until the estimate
    settles; reaching this cap while it still moves is a non-convergence (verdict fail)."""
    iterations_per_round: int = Field(default=6, ge=1, le=200)
    """Levenberg-Marquardt iterations per round."""
    intrinsics_from_round: int = Field(default=0, ge=0)
    """Round (1-based) from which the intrinsics of ``model`` are estimated; 0 (default): from
    the round after the extrinsic and time offset first settle, round 4 at the latest."""
    intrinsic_tolerance_sigmas: float = Field(default=0.5, gt=0.0)
    """Once intrinsics are estimated, a round counts as settled only if no free intrinsic moved
    by more than this many of its own 1-sigma."""
    translation_tolerance_m: float = Field(default=5e-4, gt=0.0)
    """Settled when a round moves the translation less than this or than half its 1-sigma
    (and the rotation and time offset likewise)."""
    rotation_tolerance_deg: float = Field(default=0.005, gt=0.0)
    time_offset_tolerance_s: float = Field(default=5e-5, gt=0.0)


class SolverSection(_Section):
    """Levenberg-Marquardt and the observability-aware update."""

    use_tsvd: bool = True
    tsvd_threshold: float = Field(default=1.0, gt=0.0)
    """Eigenvalue threshold of the scaled calibration information (see the README)."""
    weak_floor: float = Field(default=0.1, ge=0.0, le=1.0)
    """A direction below ``tsvd_threshold`` whose singular value is at least this fraction of it
    and which is made mostly of the extrinsic is weakly determined: estimated, its (large)
    sigma reported, the verdict at most WARN (see the README). 0 or 1: none is; every direction
    below the threshold keeps its initial value."""


ImuBlock = Literal[
    "gyro_scale",
    "gyro_misalignment",
    "gyro_rotation",
    "accel_scale",
    "accel_misalignment",
    "g_sensitivity",
    "gyro_bias_walk",
    "accel_bias_walk",
    "clock_drift",
]
LidarBlock = Literal[
    "elevation",
    "azimuth",
    "vertical_offset",
    "horizontal_offset",
    "range_scale",
    "range_offset",
    "point_time",
]
SizedBlock = Literal[ImuBlock, "point_time"]  # nested: one literal of ten names
"""Blocks whose expected size ``model.expected_size`` may set (the per-beam intrinsics have
``model.lidar_spread`` instead)."""
IMU_BLOCKS: tuple[str, ...] = ImuBlock.__args__  # type: ignore[attr-defined]
LIDAR_BLOCKS: tuple[str, ...] = LidarBlock.__args__  # type: ignore[attr-defined]
SIZED_BLOCKS: tuple[str, ...] = SizedBlock.__args__  # type: ignore[attr-defined]
INTRINSIC_PRESETS: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    "none": ((), ()),
    "imu": (IMU_BLOCKS[:5], ()),
    "lidar": ((), LIDAR_BLOCKS[:6]),
    "all": (IMU_BLOCKS[:5], LIDAR_BLOCKS[:6]),
}
"""``calibrate --intrinsics``: the IMU and LiDAR blocks each choice estimates (g-sensitivity
only when listed in ``model.imu``)."""


class ImuPriorSection(_Section):
    """How well the IMU intrinsics the model holds fixed are known (one sigma each): the
    residual error of the IMU's factory calibration, from its datasheet.

    The reported sigmas of the extrinsic and the time offset include what these uncertainties
    move them by, as far as the recording does not determine the intrinsics better itself
    (docs/checks.md, "IMU intrinsics held fixed"); 0 treats a block as known exactly. Blocks the
    model estimates (``model.imu``) are not affected.
    """

    gyro_scale: float = Field(default=1e-3, ge=0.0, le=0.1)
    """Gyro scale factor error per axis, as a fraction (1e-3 = 0.1 %)."""
    gyro_misalignment: float = Field(default=1e-3, ge=0.0, le=0.1)
    """Gyro axis misalignment per pair of axes, rad."""
    gyro_rotation_deg: float = Field(default=0.05, ge=0.0, le=5.0)
    """Rotation between the gyro and accelerometer triads per axis, degrees."""
    accel_scale: float = Field(default=1e-3, ge=0.0, le=0.1)
    """Accelerometer scale factor error per axis, as a fraction."""
    accel_misalignment: float = Field(default=1e-3, ge=0.0, le=0.1)
    """Accelerometer axis misalignment per pair of axes, rad."""
    g_sensitivity: float = Field(default=0.0, ge=0.0, le=0.01)
    """Gyro g-sensitivity per entry, rad/s per m/s^2 (0.1 deg/s/g is about 1.8e-4); 0 by
    default, as the model leaves it out unless asked."""

    def sigma_of(self, effect: str) -> float:
        """Prior sigma of an IMU effect by its check name (``gyro_rotation`` in radians); 0
        for an effect without a prior here."""
        if effect == "gyro_rotation":
            return math.radians(self.gyro_rotation_deg)
        return float(getattr(self, effect, 0.0))


LIDAR_ANGLES = ("elevation", "azimuth")
"""The per-beam blocks given in degrees in ``model.lidar_spread`` and ``model.lidar_prior``
(their keys end in ``_deg``); the model's units are radians."""


def lidar_key(block: str) -> str:
    """The key of per-beam block ``block`` in ``model.lidar_spread`` and ``model.lidar_prior``:
    ``elevation_deg``, ``azimuth_deg``, or the block's own name."""
    return f"{block}_deg" if block in LIDAR_ANGLES else block


class LidarSpreadSection(_Section):
    """How far each beam's intrinsics are expected to lie from nominal (one sigma, the spread
    across beams): the prior of the per-beam intrinsics the model estimates (``model.lidar``).

    Unset, a block gets a weak prior of about ten times real sensors' spread, and each beam's
    value is the data's alone. Set, the beams' values are drawn toward nominal as far as the
    data leave them uncertain: many small per-beam errors are then estimated together with one
    number, their spread, instead of one free number each. ``licalib diagnose`` sets it from
    the data when a per-beam effect the data show pays only so (docs/diagnose.md, "one spread
    across beams").
    """

    elevation_deg: float | None = Field(default=None, gt=0.0, le=10.0)
    """Elevation correction per beam, degrees."""
    azimuth_deg: float | None = Field(default=None, gt=0.0, le=10.0)
    """Azimuth correction per beam, degrees."""
    vertical_offset: float | None = Field(default=None, gt=0.0, le=1.0)
    """Vertical offset per beam, m."""
    horizontal_offset: float | None = Field(default=None, gt=0.0, le=1.0)
    """Horizontal offset per beam, m."""
    range_scale: float | None = Field(default=None, gt=0.0, le=0.1)
    """Range scale error per beam, as a fraction (1e-4 = 100 ppm)."""
    range_offset: float | None = Field(default=None, gt=0.0, le=1.0)
    """Range offset per beam, m."""

    def sigma_of(self, block: str) -> float | None:
        """The spread of ``model.lidar`` block ``block`` in the model's units (radians for the
        angles); None when unset."""
        value = getattr(self, lidar_key(block), None)
        if value is None:
            return None
        return math.radians(value) if block in LIDAR_ANGLES else float(value)

    def configured(self, blocks: Sequence[str]) -> dict[str, float]:
        """The spreads set among ``model.lidar`` blocks ``blocks``, by their keys here (in this
        section's units)."""
        out = {}
        for block in blocks:
            key = lidar_key(block)
            value = getattr(self, key, None)
            if value is not None:
                out[key] = float(value)
        return out

    def with_sigma(self, block: str, sigma: float) -> LidarSpreadSection:
        """A copy with ``block``'s spread set to ``sigma`` (the model's units), kept to three
        significant digits in this section's units (as a config file would give it)."""
        value = math.degrees(sigma) if block in LIDAR_ANGLES else sigma
        return self.model_copy(update={lidar_key(block): float(f"{value:.3g}")})


class LidarPriorSection(_Section):
    """How well the LiDAR's own calibration is known for what the model holds fixed (one sigma
    per beam and block): the residual error of its factory calibration, and of the per-point
    times the driver writes.

    0 (the default) treats a block as exact: the sigmas then rest on it, and the checks say
    when an error of it this recording cannot show could move the extrinsic or time offset by
    three of their sigmas (docs/checks.md, "What the model takes as exact"). Set, a block enters the
    reported sigmas as the IMU's priors do (``model.imu_prior``), and the verdict warns when the
    recording cannot check it. Blocks the model estimates (``model.lidar``) are not affected.
    """

    elevation_deg: float = Field(default=0.0, ge=0.0, le=10.0)
    """Elevation error per beam, degrees."""
    azimuth_deg: float = Field(default=0.0, ge=0.0, le=10.0)
    """Azimuth error per beam, degrees."""
    vertical_offset: float = Field(default=0.0, ge=0.0, le=1.0)
    """Vertical offset error per beam, m."""
    horizontal_offset: float = Field(default=0.0, ge=0.0, le=1.0)
    """Horizontal offset error per beam, m."""
    range_scale: float = Field(default=0.0, ge=0.0, le=0.1)
    """Range scale error per beam, as a fraction (1e-4 = 100 ppm)."""
    range_offset: float = Field(default=0.0, ge=0.0, le=1.0)
    """Range offset error per beam, m."""
    point_time: float = Field(default=0.0, ge=0.0, le=0.1)
    """Error of the per-point times within a sweep, as a fraction of the sweep time (1e-3: a
    point at the sweep's end stamped 0.1 % of the sweep off)."""

    def sigma_of(self, effect: str) -> float:
        """Prior sigma of a LiDAR effect by its check name (``lidar_azimuth``, ...; the angles
        in radians); 0 for an effect without a prior here."""
        if not effect.startswith("lidar_"):
            return 0.0
        block = effect.removeprefix("lidar_")
        value = float(getattr(self, lidar_key(block), 0.0))
        return math.radians(value) if block in LIDAR_ANGLES else value


class ModelSection(_Section):
    """Which intrinsics the calibration estimates; the others stay at their nominal values (and
    the checks test whether the data show them)."""

    imu: list[ImuBlock] = Field(default_factory=list)
    """IMU blocks: gyro_scale, gyro_misalignment, gyro_rotation (R_wI), accel_scale,
    accel_misalignment, g_sensitivity (method.md section 3); and the effects gyro_bias_walk /
    accel_bias_walk (a bias drifting over the segment: linearly, or piecewise linearly with
    ``bias_walk_piece_s``) and clock_drift (the IMU clock running at another rate than the
    LiDAR's)."""
    lidar: list[LidarBlock] = Field(default_factory=list)
    """Per-beam LiDAR intrinsics: elevation, azimuth, vertical_offset, horizontal_offset,
    range_scale, range_offset (method.md section 4; the first beam with enough points keeps
    its angles and offsets, the gauge); and the effect point_time (the per-point times within
    a sweep off by a constant fraction)."""
    bias_walk_piece_s: float | None = Field(default=None, gt=0.0)
    """With gyro_bias_walk or accel_bias_walk: the bias is piecewise linear over pieces of about
    this many seconds (the segment cut into equal pieces, one drift per axis and piece); unset:
    one linear drift over the segment. ``diagnose`` sets it when finer pieces pay their BIC."""
    expected_size: dict[SizedBlock, Annotated[float, Field(gt=0.0)]] = Field(default_factory=dict)
    """How large each named block (of ``imu``, or ``point_time``) is expected to be, per
    coordinate in the solver's units: a fraction for scales, rad for misalignments and
    gyro_rotation, rad/s per m/s^2 for g_sensitivity, rad/s^2 and m/s^3 for a gyro and an
    accelerometer bias walk's drift (per piece: times ``K^1.5`` for ``K`` pieces), s/s for
    clock_drift, a fraction of the sweep time for point_time. The truncated SVD holds at nominal
    every direction the recording determines worse than this (README, ``observability``);
    unset: the built-in characteristic scale. ``diagnose`` sets it when a block's
    score test puts it far above the built-in scale and the refit at that scale held it."""
    min_points_per_beam: int = Field(default=200, ge=10)
    """Beams with fewer associated points keep their intrinsics at nominal (and are named)."""
    add_evident_effects: bool = True
    """``calibrate`` estimates too the effects the data show beyond doubt (score tests of at
    least 100 per degree of freedom; all such in one refit, two refits at most) when estimating
    them pays its BIC, and says so; the resolved config and the result's ``model.added`` name
    them. False (``calibrate --model config``): exactly the blocks above, such an effect only
    widening the sigmas and warning."""
    imu_prior: ImuPriorSection = ImuPriorSection()
    """How well the IMU intrinsics held fixed are known (their sigmas enter the reported
    sigmas)."""
    lidar_spread: LidarSpreadSection = LidarSpreadSection()
    """The spread across beams of each per-beam intrinsic estimated (its prior); unset: a weak
    prior."""
    lidar_prior: LidarPriorSection = LidarPriorSection()
    """How well the LiDAR intrinsics held fixed (and the per-point times) are known; 0: taken
    as exact."""

    def held_prior(self, effect: str) -> float:
        """Prior sigma of a held effect by its check name, from ``imu_prior`` or
        ``lidar_prior`` (solver units); 0: no prior, taken as exact."""
        if effect.startswith("lidar_"):
            return self.lidar_prior.sigma_of(effect)
        return self.imu_prior.sigma_of(effect)


class ChecksSection(_Section):
    """The largest 1-sigma of a PASS: a result whose reported sigma (after the checks'
    enlargements) exceeds one of these gets the verdict ``warn`` ("... is uncertain"). The
    defaults keep twice a PASS's translation sigma within 1 cm; the rotation's and the time
    offset's sit above what a well-excited 10 s bag gives with the default IMU priors (up to
    0.05 deg on a shake, 0.14 ms on a sinusoid)."""

    max_translation_sigma_m: float = Field(default=0.005, gt=0.0, le=10.0)
    """Translation, m (per IMU axis)."""
    max_rotation_sigma_deg: float = Field(default=0.1, gt=0.0, le=180.0)
    """Rotation, degrees (per LiDAR axis)."""
    max_time_offset_sigma_s: float = Field(default=0.0002, gt=0.0, le=10.0)
    """Time offset, s."""
    range_noise_draws: int = Field(default=2, ge=0, le=20)
    """On a LiDAR whose range noise is at least ``range_noise_draws_from_m``: refit this many
    times from the estimate with as much range noise again added, and take the spread of those
    refits as a floor of the sigmas (``pipeline/noise_draws.py``). 0: off."""
    range_noise_draws_from_m: float = Field(default=0.025, gt=0.0, le=1.0)
    """The range noise (m, the one the fit is weighted with) from which the draws run: at 4 cm
    the estimate scattered about twice as far as the linearised sigmas said. On a non-repetitive
    scanner (Livox) they run at any range noise."""
    refit_effects: bool = True
    """Refit once with the strongest effect the data show beyond doubt (a score of 100 per
    degree of freedom) to measure how far it moves the extrinsic, instead of trusting the
    linear prediction alone (``pipeline/effect_refit.py``; it costs one more optimisation on
    such bags). Off: faster, and the sigmas may not cover such an effect."""


class CalibConfig(_Section):
    """The whole configuration."""

    bag: BagConfig = BagConfig()
    imu: ImuInputConfig = ImuInputConfig()
    lidar: LidarInputConfig = LidarInputConfig()
    noise: NoiseConfig = NoiseConfig()
    odometry: OdometrySection = OdometrySection()
    initialization: InitializationConfig = InitializationConfig()
    spline: SplineConfig = SplineConfig()
    surfels: SurfelSection = SurfelSection()
    schedule: ScheduleConfig = ScheduleConfig()
    solver: SolverSection = SolverSection()
    model: ModelSection = ModelSection()
    checks: ChecksSection = ChecksSection()


def yaml_error_summary(err: yaml.YAMLError) -> str:
    """One-line description of a YAML parse error with its line and column."""
    if isinstance(err, yaml.reader.ReaderError):
        return f"a non-text character {err.character!r} at byte {err.position}"
    problem = getattr(err, "problem", None) or type(err).__name__
    mark = getattr(err, "problem_mark", None)
    where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
    return f"{problem}{where}"


class DuplicateKeyError(yaml.MarkedYAMLError):
    """A mapping of a YAML document names the same key twice."""


class _UniqueKeyLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` that refuses a key given twice in one mapping (PyYAML keeps the
    last one silently, so a setting written twice would quietly lose one of its values)."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        seen: set[Any] = set()
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=True)
            try:
                duplicate = key in seen
                seen.add(key)
            except TypeError:  # an unhashable key: the base class reports it
                break
            if duplicate:
                raise DuplicateKeyError(
                    problem=f"the key '{key}' twice", problem_mark=key_node.start_mark
                )
        return super().construct_mapping(node, deep=deep)


def read_text(
    path: Path, what: str, kind: str = "a YAML file", error: type[ConfigError] = ConfigError
) -> str:
    """The text of a file (UTF-8, a byte-order mark dropped), or one sentence naming why not.

    Args:
        path: the file.
        what: how the message names the file, e.g. ``"The config file"``.
        kind: what the file should be, for the fix, e.g. ``"a YAML file"``.
        error: the error class raised.

    Raises:
        ConfigError: (``error``) the file is missing, a folder, unreadable or not text.
    """
    try:
        data = Path(path).read_bytes()
    except FileNotFoundError as err:
        msg = f"{what} {path} does not exist; check the path."
        raise error(msg) from err
    except IsADirectoryError as err:
        msg = f"{what} {path} is a folder; pass {kind}."
        raise error(msg) from err
    except OSError as err:
        msg = f"{what} {path} cannot be read ({err.strerror}); check the path and its permissions."
        raise error(msg) from err
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as err:
        msg = f"{what} {path} is not a text file (byte {err.start} is not UTF-8); pass {kind}."
        raise error(msg) from err


def read_yaml(path: Path, what: str) -> Any:
    """The YAML document of a file, or one sentence naming why it cannot be read.

    Duplicated keys in a mapping are an error (PyYAML would keep the last one silently).

    Args:
        path: the file.
        what: how the message names the file, e.g. ``"The config file"``.

    Raises:
        ConfigError: the file is missing, a folder, unreadable, not text, or not valid YAML.
    """
    return parse_yaml(read_text(path, what), path, what)


def parse_yaml(text: str, path: Path, what: str) -> Any:
    """The YAML document of a file's text (:func:`read_yaml`'s parsing half).

    Raises:
        ConfigError: the text is not valid YAML or names a key twice.
    """
    try:
        return yaml.load(text, Loader=_UniqueKeyLoader)  # a SafeLoader
    except DuplicateKeyError as err:
        mark = err.problem_mark
        msg = f"{what} {path} gives {err.problem} (line {mark.line + 1}); keep one of them."
        raise ConfigError(msg) from err
    except yaml.YAMLError as err:
        why = yaml_error_summary(err)
        msg = f"{what} {path} is not valid YAML ({why}); fix the syntax."
        raise ConfigError(msg) from err
    except RecursionError as err:
        msg = f"{what} {path} nests too deeply to be a licalib YAML file; fix it."
        raise ConfigError(msg) from err


def _where(loc: tuple[Any, ...]) -> str:
    """A validation error's location as a dotted key: a mapping's key stands for itself (its
    ``[key]`` marker, and a union member's type tag, left out)."""
    kept = []
    for x in loc:
        if x == "[key]":
            break
        if isinstance(x, str) and "[" in x:  # a union member's tag, e.g. ``literal['a','b']``
            continue
        kept.append(str(x))
    return ".".join(kept)


def _put(data: dict[str, Any], dotted: str, value: Any) -> None:
    """Set the dotted key ``dotted`` of the nested mapping ``data`` to ``value``, making the
    sections on the way (a section given as a scalar is left for the validation to name)."""
    node: Any = data
    *parents, leaf = dotted.split(".")
    for key in parents:
        if node.get(key) is None:  # absent, or an empty section (``bag:``)
            node[key] = {}
        node = node[key]
        if not isinstance(node, dict):
            return
    node[leaf] = value


def load_config(
    path: Path | None,
    overrides: dict[str, Any] | None = None,
    settings: dict[str, Any] | None = None,
) -> CalibConfig:
    """Read a YAML config (or defaults) and apply dotted overrides such as ``{"imu.topic": "/x"}``.

    ``settings`` are the ``--set KEY=VALUE`` settings by dotted key, applied over the file as
    given (None sets a key to null); ``overrides`` are the dedicated options' (``--imu-topic``
    ...), applied last, None meaning "not given".

    Raises:
        ConfigError: the file is missing, a folder, not text, not YAML (or names a key twice),
            or has unknown keys or bad values; a setting or an override names an unknown key or
            has a bad value.
    """
    data: dict[str, Any] = {}
    if path is not None:
        path = Path(path)
        loaded = read_yaml(path, "The config file")
        if loaded is not None and not isinstance(loaded, dict):
            msg = f"The config file {path} must be a YAML mapping of sections."
            raise ConfigError(msg)
        data = loaded or {}
    given = {k: v for k, v in (overrides or {}).items() if v is not None}
    for dotted, value in {**(settings or {}), **given}.items():
        _put(data, dotted, value)
    try:
        return CalibConfig.model_validate(data)
    except ValidationError as err:
        raise ConfigError(_invalid(err, path, given, settings or {})) from err


def _field_at(dotted: str) -> tuple[type[BaseModel], FieldInfo] | None:
    """The section of :class:`CalibConfig` holding a dotted key and the key's field, None when
    the key names none."""
    model: Any = CalibConfig
    found = None
    for part in dotted.split("."):
        if not (isinstance(model, type) and issubclass(model, BaseModel)):
            return None
        field = model.model_fields.get(part)
        if field is None:
            return None
        found = (model, field)
        model = field.annotation
    return found


def _section_at(dotted: str) -> type[BaseModel] | None:
    """The section class of :class:`CalibConfig` at a dotted key, None when the key names no
    section."""
    found = _field_at(dotted)
    kind = found[1].annotation if found is not None else None
    return kind if isinstance(kind, type) and issubclass(kind, BaseModel) else None


def _valid_as(dotted: str, value: Any) -> bool:
    """Whether the section holding ``dotted`` takes ``value`` there (the other keys at their
    defaults)."""
    found = _field_at(dotted)
    if found is None:
        return False
    try:
        found[0].model_validate({dotted.rsplit(".", 1)[-1]: value})
    except (ValidationError, ValueError):
        return False
    return True


def _list_form(dotted: str) -> str:
    """How a list setting is written: its length when fixed, else its default as an example."""
    found = _field_at(dotted)
    if found is None:
        return ", such as [a, b]"
    field = found[1]
    shortest = next((m.min_length for m in field.metadata if hasattr(m, "min_length")), None)
    longest = next((m.max_length for m in field.metadata if hasattr(m, "max_length")), None)
    if shortest is not None and shortest == longest:
        return f" of {shortest} items"
    if isinstance(field.default, list) and field.default:
        return f", such as {yaml.safe_dump(field.default, default_flow_style=True).strip()}"
    return ", such as [a, b]"


def _reason(error: Any, where: str) -> str:
    """Why a value is invalid, in the config's own words: a section given a single value names
    one of its keys, a list given a single value shows the list form (pydantic's message names
    its class or says only "a valid list")."""
    kind = error["type"]
    if kind == "model_type":
        section = _section_at(where)
        if section is not None:
            key = next(iter(section.model_fields))
            return (
                f"'{where}' is a section of settings, not a value; give its keys one by one, "
                f"such as {where}.{key}"
            )
    if kind == "list_type":
        given = error.get("input")
        if _valid_as(where, [given]):
            return f"'{where}' takes a list; write [{given}] for that one item"
        return f"'{where}' takes a list{_list_form(where)}"
    if kind == "dict_type":
        return f"'{where}' takes a mapping of names to values, such as {{name: value}}"
    return str(error["msg"]).replace("Value error, ", "")


def _invalid(
    err: ValidationError, path: Path | None, given: dict[str, Any], settings: dict[str, Any]
) -> str:
    """One sentence on the first error of a config's validation, naming where the bad key or
    value came from: an option, a ``--set`` setting or the file."""
    first = err.errors()[0]
    where = _where(tuple(first["loc"]))
    why = _reason(first, where)
    option = next((k for k in given if where == k or where.startswith(k + ".")), None)
    setting = next((k for k in settings if where == k or where.startswith(k + ".")), None)
    if setting is None and first["type"] == "extra_forbidden":  # ``--set a.b.c`` under ``a.b``
        setting = next((k for k in settings if k.startswith(where + ".")), None)
    listed = "licalib config dump prints every setting with its default"
    if option is not None:
        flag = OPTION_NAMES.get(option, option)
        return f"Invalid value {given[option]!r} for {flag} ({option}): {why}."
    if setting is not None:
        if first["type"] == "extra_forbidden":
            return f"Unknown setting '{setting}' in --set; {listed}."
        return f"Invalid value {settings[setting]!r} for --set {setting}: {why}."
    source = f"config file {path}" if path else "options"
    if first["type"] == "extra_forbidden":
        return f"Unknown setting '{where}' in the {source}; {listed}."
    return f"Invalid setting '{where}' in the {source}: {why}."


def dump_config(cfg: CalibConfig) -> str:
    """The resolved configuration as YAML."""
    return yaml.safe_dump(cfg.model_dump(mode="json"), sort_keys=False)


def config_fingerprint(cfg: CalibConfig) -> str:
    """A short content fingerprint of the resolved configuration: the first 16 hex digits of
    the sha256 of :func:`dump_config` (two configs that resolve alike share it)."""
    return hashlib.sha256(dump_config(cfg).encode()).hexdigest()[:16]
