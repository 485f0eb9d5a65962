"""Calibration state, its parameter blocks, and the problem builder.

The state is everything the batch optimisation estimates for one segment: the trajectory
``T_G_I(t)`` (rotation and position splines), IMU biases, gravity in ``{G}``, the extrinsic
``T_imu_lidar`` (``p_I = R p_L + t``), the time offset ``t_c`` (``t_imu = t_lidar + t_c``), the
IMU intrinsics and the per-beam LiDAR intrinsics. :func:`build_problem` turns a state plus
measurements into a :class:`licalib_cli.solver.Problem` whose parameter blocks are named as in
:mod:`licalib_cli.residuals`; :func:`state_from_values` reads an estimate back.

Times: ``t0_ns`` is the reference; IMU sample times are IMU-clock seconds since ``t0_ns``, point
times LiDAR-clock seconds since ``t0_ns``; a point is evaluated on the trajectory at
``tau + t_c``. The splines must cover every such time (a clear ``ValueError`` otherwise).

Characteristic scales (the solver compares singular values of the calibration block after
dividing each coordinate by its scale, and measures steps in these units):

========================================  ==========================
coordinates                               scale
========================================  ==========================
``ext.rotation``                          1e-3 rad (0.057 deg)
``ext.translation``                       0.01 m
``ext.time_offset``                       1e-3 s
``imu.gyro_scale``                        1e-3
``imu.accel_scale``                       5e-3
``imu.*_misalignment``                    1e-3
``imu.gyro_rotation``                     1e-2 rad (0.57 deg)
``imu.gyro_g_sensitivity``                1e-4 rad/s per m/s^2
``lidar.intrinsics`` dphi, dtheta         1e-3 rad
``lidar.intrinsics`` V, H                 0.005 m
``lidar.intrinsics`` s                    1e-4
``lidar.intrinsics`` drho                 0.01 m
trajectory: so3 / r3 control points       1e-3 rad / 1e-3 m
trajectory: gyro / accel bias, gravity    1e-4 rad/s / 1e-3 m/s^2 / 1e-3 rad
========================================  ==========================

Gauge: the first beam with enough points keeps ``dphi, dtheta, V, H`` fixed (only ``s`` and
``drho`` free, method.md section 4); beams with fewer than ``min_points_per_beam`` points stay
fixed. Without LiDAR residuals and with a free trajectory, the first rotation control point and
the first two position control points are held (global rotation, position and velocity are not
observable from an IMU alone; gravity should then be free).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import numpy.typing as npt

from licalib_cli.geometry import so3
from licalib_cli.geometry.so3 import matrix_to_quat, quat_to_matrix
from licalib_cli.measurements import ImuSamples
from licalib_cli.models.imu import drift_pieces, resample_drift
from licalib_cli.models.intrinsics import ImuIntrinsics, LidarIntrinsics
from licalib_cli.models.lidar import (
    GAUGE_COLUMNS,
    INTRINSIC_NAMES,
    NUM_BEAM_INTRINSICS,
    intrinsics_from_array,
    intrinsics_to_array,
)
from licalib_cli.residuals import (
    ACCEL_BIAS,
    ACCEL_BIAS_DRIFT,
    ACCEL_MISALIGNMENT,
    ACCEL_SCALE,
    EXT_ROTATION,
    EXT_TRANSLATION,
    GRAVITY,
    GYRO_BIAS,
    GYRO_BIAS_DRIFT,
    GYRO_G_SENSITIVITY,
    GYRO_MISALIGNMENT,
    GYRO_ROTATION,
    GYRO_SCALE,
    LIDAR_INTRINSICS,
    POINT_TIME_SCALE,
    TIME_DRIFT,
    TIME_OFFSET,
    TRAJ_R3,
    TRAJ_SO3,
    AccelResidual,
    GyroResidual,
    PointToPlaneResidual,
)
from licalib_cli.solver.loss import HuberLoss
from licalib_cli.solver.parameters import Group, ManifoldName, ParameterBlock
from licalib_cli.solver.problem import Problem, ResidualBlock
from licalib_cli.spline import R3Spline, SO3EvaluationCache, SO3Spline, UniformKnots

__all__ = [
    "BLOCK_SPECS",
    "CALIBRATION_SCALES",
    "IMU_INTRINSIC_BLOCKS",
    "PRIOR_SCALE_FACTOR",
    "BlockSpec",
    "CalibrationState",
    "FreeParameters",
    "ImuData",
    "LidarPoints",
    "NoiseModel",
    "Planes",
    "SplineCoverageError",
    "beam_point_counts",
    "build_problem",
    "calibration_moved",
    "drift_suffixes",
    "free_effect_blocks",
    "intrinsic_coordinates",
    "parameter_blocks",
    "state_from_problem",
    "state_from_values",
    "state_to_values",
]

F64 = npt.NDArray[np.float64]

logger = logging.getLogger(__name__)

#: Characteristic scale of every coordinate, per block (per tangent coordinate of one element).
CALIBRATION_SCALES: Mapping[str, tuple[float, ...]] = {
    TRAJ_SO3: (1e-3,) * 3,
    TRAJ_R3: (1e-3,) * 3,
    GYRO_BIAS: (1e-4,) * 3,
    ACCEL_BIAS: (1e-3,) * 3,
    GRAVITY: (1e-3,) * 2,
    EXT_ROTATION: (1e-3,) * 3,
    EXT_TRANSLATION: (0.01,) * 3,
    TIME_OFFSET: (1e-3,),
    TIME_DRIFT: (1e-4,),
    POINT_TIME_SCALE: (1e-3,),
    GYRO_BIAS_DRIFT: (1e-5,) * 3,
    ACCEL_BIAS_DRIFT: (1e-4,) * 3,
    GYRO_SCALE: (1e-3,) * 3,
    GYRO_MISALIGNMENT: (1e-3,) * 3,
    # R_wI is not made small by a factory calibration the way scales and misalignments are
    # (sensor-to-case mounting; 0.5 deg per angle in the simulator): at 1 mrad a direction the
    # data determine to 0.1-0.5 deg was held at nominal and counted as known within 1 mrad.
    GYRO_ROTATION: (1e-2,) * 3,
    # Gravity stays near one axis on most recordings, so that axis's scale trades with its bias
    # and is determined to 0.1-0.2 % at best: at 1e-3 the truncation held it at nominal, and a
    # 0.5 % scale the score test showed at p = 3e-9 was neither estimated nor named.
    ACCEL_SCALE: (5e-3,) * 3,
    ACCEL_MISALIGNMENT: (1e-3,) * 3,
    GYRO_G_SENSITIVITY: (1e-4,) * 9,
    LIDAR_INTRINSICS: (1e-3, 1e-3, 0.005, 0.005, 1e-4, 0.01),
}

_XYZ = ("x", "y", "z")
_MISALIGNMENT = ("xy", "xz", "yz")  # M[0, 1], M[0, 2], M[1, 2]
_G_SENS = tuple(f"{a}{b}" for a in "xyz" for b in "xyz")


def _f64(x: npt.ArrayLike) -> F64:
    out = np.array(x, dtype=np.float64)
    out.setflags(write=False)
    return out


# ---------------------------------------------------------------------------------- data types


@dataclass(frozen=True)
class CalibrationState:
    """Everything estimated for one segment.

    Attributes:
        so3_spline: rotation spline ``R_G_I(t)``.
        r3_spline: position spline ``G p_I(t)``, m (same knots).
        gyro_bias: (3,) ``b_w``, rad/s.
        accel_bias: (3,) ``b_a``, m/s^2.
        gravity_G: (3,) gravity in ``{G}``, m/s^2 (its norm is kept).
        R_imu_lidar: (3, 3) extrinsic rotation (LiDAR -> IMU).
        t_imu_lidar: (3,) LiDAR origin in the IMU frame, m.
        time_offset_s: ``t_c``, seconds (``t_imu = t_lidar + t_c``).
        imu_intrinsics: scale, misalignment, gyro rotation, g-sensitivity; its bias fields are
            overwritten with ``gyro_bias`` / ``accel_bias`` so that
            :func:`~licalib_cli.models.intrinsics.imu_measure` reproduces the model.
        lidar_intrinsics: per-beam intrinsics.
        t0_ns: reference time of the splines' time axis, int nanoseconds (IMU clock).
        gyro_bias_drift: (3,) ``d_w``: the gyro bias is ``b_w + d_w (t - t_ref_s)``, rad/s^2;
            or (K, 3), one drift per piece of a bias that walks piecewise linearly over the
            segment (:func:`~licalib_cli.models.imu.bias_drift_basis`).
        accel_bias_drift: (3,) or (K, 3) ``d_a``, the same for the accelerometer, m/s^3.
        time_drift: ``k_drift``: the IMU time of a LiDAR time ``tau`` is
            ``tau + t_c + k_drift (tau - t_ref_s)`` (an IMU clock running at another rate).
        point_time_scale: ``k_point``: the per-point times within a sweep are off by this
            fraction (a point at ``tau`` was measured at ``tau - k_point (tau - sweep start)``).
        t_ref_s: reference time of the drifts, seconds on the splines' axis (the segment's
            middle).
    """

    so3_spline: SO3Spline
    r3_spline: R3Spline
    gyro_bias: F64
    accel_bias: F64
    gravity_G: F64
    R_imu_lidar: F64
    t_imu_lidar: F64
    time_offset_s: float
    imu_intrinsics: ImuIntrinsics = field(default_factory=ImuIntrinsics)
    lidar_intrinsics: LidarIntrinsics = field(
        default_factory=lambda: LidarIntrinsics.nominal([0.0])
    )
    t0_ns: int = 0
    gyro_bias_drift: F64 = field(default_factory=lambda: np.zeros(3))
    accel_bias_drift: F64 = field(default_factory=lambda: np.zeros(3))
    time_drift: float = 0.0
    point_time_scale: float = 0.0
    t_ref_s: float = 0.0

    def __post_init__(self) -> None:
        if self.so3_spline.knots != self.r3_spline.knots:
            msg = "the rotation and position splines must share one knot vector"
            raise ValueError(msg)
        for name in ("gyro_bias_drift", "accel_bias_drift"):
            value = _f64(getattr(self, name))
            if value.size == 0 or value.size % 3 or value.ndim > 2 or value.shape[-1] != 3:
                msg = f"CalibrationState.{name} must have shape (3,) or (K, 3), got {value.shape}"
                raise ValueError(msg)
            object.__setattr__(self, name, resample_drift(value, value.size // 3))
        for name, shape in (
            ("gyro_bias", (3,)),
            ("accel_bias", (3,)),
            ("gravity_G", (3,)),
            ("R_imu_lidar", (3, 3)),
            ("t_imu_lidar", (3,)),
        ):
            value = _f64(getattr(self, name))
            if value.shape != shape:
                msg = f"CalibrationState.{name} must have shape {shape}, got {value.shape}"
                raise ValueError(msg)
            object.__setattr__(self, name, value)
        object.__setattr__(self, "time_offset_s", float(self.time_offset_s))
        for name in ("time_drift", "point_time_scale", "t_ref_s"):
            object.__setattr__(self, name, float(getattr(self, name)))
        object.__setattr__(self, "t0_ns", int(self.t0_ns))
        object.__setattr__(
            self,
            "imu_intrinsics",
            replace(self.imu_intrinsics, gyro_bias=self.gyro_bias, accel_bias=self.accel_bias),
        )

    @property
    def knots(self) -> UniformKnots:
        """The shared knot vector."""
        return self.so3_spline.knots

    def with_(self, **changes: Any) -> CalibrationState:
        """Copy with some fields replaced."""
        return replace(self, **changes)


@dataclass(frozen=True)
class ImuData:
    """IMU readings on the problem's time axis.

    Attributes:
        t_s: (N,) IMU-clock seconds relative to ``t0_ns``.
        gyro: (N, 3) rad/s.
        accel: (N, 3) m/s^2.
    """

    t_s: F64
    gyro: F64
    accel: F64

    @classmethod
    def from_samples(cls, samples: ImuSamples, t0_ns: int) -> ImuData:
        """Convert int64-ns samples to seconds relative to ``t0_ns``."""
        t = (samples.t_ns - np.int64(t0_ns)).astype(np.float64) * 1e-9
        return cls(t, np.asarray(samples.gyro, np.float64), np.asarray(samples.accel, np.float64))

    def __len__(self) -> int:
        return int(np.asarray(self.t_s).shape[0])


@dataclass(frozen=True)
class LidarPoints:
    """Raw LiDAR measurements with their plane associations.

    Attributes:
        t_s: (N,) point times ``tau``, LiDAR-clock seconds relative to ``t0_ns``.
        beam: (N,) beam index.
        rho: (N,) raw range, m.
        theta: (N,) raw azimuth, rad.
        plane: (N,) index of the associated plane in :class:`Planes`.
        model_gap: (N, 3) published point minus the LiDAR model's nominal point (LiDAR frame,
            m), or None (zero).
        sweep_start_s: (N,) LiDAR-clock time of each point's sweep start, seconds relative to
            ``t0_ns``, or None.
    """

    t_s: F64
    beam: npt.NDArray[np.integer]
    rho: F64
    theta: F64
    plane: npt.NDArray[np.integer]
    model_gap: F64 | None = None
    sweep_start_s: F64 | None = None

    def __len__(self) -> int:
        return int(np.asarray(self.t_s).shape[0])

    def subset(self, index: npt.ArrayLike) -> LidarPoints:
        """The points selected by an index array or a boolean mask."""
        i = np.asarray(index)

        def pick(a: npt.ArrayLike | None) -> F64 | None:
            return None if a is None else np.asarray(a)[i]

        return LidarPoints(
            t_s=np.asarray(self.t_s)[i],
            beam=np.asarray(self.beam)[i],
            rho=np.asarray(self.rho)[i],
            theta=np.asarray(self.theta)[i],
            plane=np.asarray(self.plane)[i],
            model_gap=pick(self.model_gap),
            sweep_start_s=pick(self.sweep_start_s),
        )


@dataclass(frozen=True)
class Planes:
    """Planes ``n^T x + d = 0`` in ``{G}``, held fixed within an optimisation round.

    Attributes:
        normal: (P, 3) unit normals.
        d: (P,) offsets ``d``, m (minus the distance of the plane from the origin along n).
        thickness: (P,) RMS point-to-plane spread of each surfel, m, or None.
    """

    normal: F64
    d: F64
    thickness: F64 | None = None


@dataclass(frozen=True)
class NoiseModel:
    """Measurement noise and robust-loss settings.

    Attributes:
        gyro_sigma: discrete gyro noise std, rad/s (scalar or (3,)).
        accel_sigma: discrete accelerometer noise std, m/s^2 (scalar or (3,)).
        range_sigma: LiDAR range noise std, m (point-to-plane sigma before inflation).
        thickness_weight: the point sigma is ``sqrt((c * range_sigma)^2 + (w * thickness)^2)``.
        min_incidence_cos: ``c`` above is the cosine of the angle between the point's ray and its
            plane's normal (at the state the problem is built from) where it is at least this,
            else 1: the range noise moves a point along its ray, so its distance to the plane
            varies by the range noise times that cosine, but the distances of rays that graze
            their plane carry errors the cosine does not (on a simulated figure-8: RMS 9 mm at
            cosines 0.1-0.2 with 10 mm range noise, 1.5 mm expected). 1 weights every point with
            the full range noise.
        incidence_floor: ``c`` is the cosine, but at least ``min_incidence_cos``, for every ray
            (grazing ones included): how the fit checks weigh the distances
            (``pipeline/fitcheck.py``), not how the fit does.
        huber_threshold: Huber threshold on the whitened point residual (None: plain squares).
        range_noise_per_beam: (B,) the range noise each beam's returns carry, m, as measured
            from the data; None: ``range_sigma`` for every beam. ``range_sigma`` weights the
            residuals (a configured figure may be set wide on purpose); this is what the map
            planes' errors-in-variables correction subtracts, which must be the noise itself.
    """

    gyro_sigma: float | F64 = 1e-3
    accel_sigma: float | F64 = 1e-2
    range_sigma: float = 0.02
    thickness_weight: float = 0.0
    min_incidence_cos: float = 1.0
    incidence_floor: bool = False
    huber_threshold: float | None = 3.0
    range_noise_per_beam: F64 | None = field(default=None, compare=False)

    def range_noise(self, beam: npt.ArrayLike) -> F64:
        """(N,) the range noise of returns from ``beam`` (N,), m (see ``range_noise_per_beam``;
        a beam beyond it gets ``range_sigma``)."""
        b = np.asarray(beam, dtype=np.int64).reshape(-1)
        table = np.asarray(
            [] if self.range_noise_per_beam is None else self.range_noise_per_beam,
            dtype=np.float64,
        ).reshape(-1)
        if table.size == 0:
            return np.full(b.shape, float(self.range_sigma))
        inside = (b >= 0) & (b < table.size)
        return np.where(inside, table[np.clip(b, 0, table.size - 1)], float(self.range_sigma))

    @classmethod
    def from_densities(
        cls,
        gyro_noise_density: float,
        accel_noise_density: float,
        rate_hz: float,
        range_sigma: float = 0.02,
        **kwargs: float | None,
    ) -> NoiseModel:
        """Discrete sigmas ``density * sqrt(rate)`` from continuous noise densities.

        Args:
            gyro_noise_density: rad/s/sqrt(Hz).
            accel_noise_density: m/s^2/sqrt(Hz).
            rate_hz: IMU sample rate, Hz.
            range_sigma: LiDAR range noise std, m.
            **kwargs: other fields of :class:`NoiseModel`.

        Returns:
            The noise model.
        """
        root = float(np.sqrt(rate_hz))
        return cls(
            gyro_sigma=gyro_noise_density * root,
            accel_sigma=accel_noise_density * root,
            range_sigma=range_sigma,
            **kwargs,  # type: ignore[arg-type]
        )


@dataclass(frozen=True)
class FreeParameters:
    """Which parameter groups the optimiser may change in a round.

    Attributes:
        trajectory: spline control points (and, with ``biases``/``gravity``, those blocks).
        biases: IMU biases.
        gravity: gravity direction.
        extrinsic_rotation: ``ext.rotation``.
        extrinsic_translation: ``ext.translation``.
        time_offset: ``ext.time_offset``.
        imu_intrinsics: all 15 IMU intrinsics (scale, misalignment, gyro rotation).
        imu_blocks: further IMU intrinsic blocks free on their own (block names such as
            ``imu.gyro_scale``; :data:`IMU_INTRINSIC_BLOCKS`).
        g_sensitivity: the 9 gyro g-sensitivity parameters (adds the ``A_w a_I`` term).
        lidar_intrinsics: all six per-beam LiDAR intrinsics.
        lidar_columns: further per-beam intrinsics free on their own (names of
            :data:`~licalib_cli.models.lidar.INTRINSIC_NAMES`: ``dphi``, ``dtheta``, ``V``,
            ``H``, ``s``, ``drho``).
        min_points_per_beam: beams with fewer points keep their intrinsics fixed.
        gyro_bias_drift: a drift of the gyro bias (``imu.gyro_bias_drift``).
        accel_bias_drift: a drift of the accelerometer bias.
        bias_walk_piece_s: the bias drifts are piecewise linear with pieces of about this
            length (:func:`~licalib_cli.models.imu.drift_pieces`); None: one linear drift, or as
            many pieces as the state holds.
        time_drift: an IMU clock running at another rate (``ext.time_drift``).
        point_time: an error of the per-point times within a sweep
            (``lidar.point_time_scale``).
        translation_prior: ``(mean, sigma)`` (m, IMU frame) of a Gaussian prior on
            ``ext.translation`` (a measured lever arm), or None. Not a freedom but what the
            problems built for these parameters add to the data (the rounds' own priors).
        lidar_spread: ``(name, sigma)`` per per-beam intrinsic (``dphi`` ... ``drho``) whose
            prior toward nominal has this sigma instead of the weak default
            (``model.lidar_spread``); like ``translation_prior``, part of what the problems add.
        expected_size: ``(block, size)`` per calibration block (``imu.gyro_scale``,
            ``imu.gyro_bias_drift``, ...) whose characteristic scale is ``size`` per coordinate
            instead of :data:`CALIBRATION_SCALES`' (``model.expected_size``).
        time_drift_prior: ``(mean, sigma)`` (s/s) of the clock drift measured apart from the
            data the problems fit (the IMU's stamps against the LiDAR's, from the record
            times), a Gaussian prior on ``ext.time_drift`` when it is estimated; None: none.
            Like ``translation_prior``, part of what the problems add.
        beam_intrinsics: the LiDAR's beams have intrinsics of their own (a spinning LiDAR's
            rings); False for a non-repetitive scanner, whose beams are elevation bins
            (:mod:`licalib_cli.pipeline.scan_pattern`): what may be freed holds none of them.
    """

    trajectory: bool = True
    biases: bool = True
    gravity: bool = True
    extrinsic_rotation: bool = True
    extrinsic_translation: bool = True
    time_offset: bool = True
    imu_intrinsics: bool = False
    imu_blocks: frozenset[str] = frozenset()
    g_sensitivity: bool = False
    lidar_intrinsics: bool = False
    lidar_columns: frozenset[str] = frozenset()
    min_points_per_beam: int = 100
    gyro_bias_drift: bool = False
    accel_bias_drift: bool = False
    time_drift: bool = False
    point_time: bool = False
    bias_walk_piece_s: float | None = None
    translation_prior: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None
    lidar_spread: tuple[tuple[str, float], ...] = ()
    expected_size: tuple[tuple[str, float], ...] = ()
    time_drift_prior: tuple[float, float] | None = None
    beam_intrinsics: bool = True

    def imu_block_free(self, block: str) -> bool:
        """Whether IMU intrinsic block ``block`` (e.g. ``imu.gyro_scale``) is estimated."""
        if block == GYRO_G_SENSITIVITY:
            return self.g_sensitivity or block in self.imu_blocks
        return self.imu_intrinsics or block in self.imu_blocks

    def lidar_column_free(self, name: str) -> bool:
        """Whether per-beam intrinsic ``name`` (``dphi`` ... ``drho``) is estimated."""
        return self.lidar_intrinsics or name in self.lidar_columns

    @property
    def any_imu_intrinsics(self) -> bool:
        """Whether some IMU intrinsic (g-sensitivity included) is estimated."""
        return self.imu_intrinsics or self.g_sensitivity or bool(self.imu_blocks)

    @property
    def any_lidar_intrinsics(self) -> bool:
        """Whether some per-beam LiDAR intrinsic is estimated."""
        return self.lidar_intrinsics or bool(self.lidar_columns)


IMU_INTRINSIC_BLOCKS = (
    GYRO_SCALE,
    GYRO_MISALIGNMENT,
    GYRO_ROTATION,
    ACCEL_SCALE,
    ACCEL_MISALIGNMENT,
    GYRO_G_SENSITIVITY,
)
"""The IMU intrinsic parameter blocks, in the order of the model (method.md section 3)."""


# ----------------------------------------------------------------------- state <-> parameters


def state_to_values(
    state: CalibrationState,
    g_sensitivity: bool | None = None,
    effects: Sequence[str] | None = None,
) -> dict[str, F64]:
    """Parameter block values of a state.

    Args:
        state: the state.
        g_sensitivity: include ``imu.gyro_g_sensitivity`` (default: when non-zero).
        effects: drift blocks to include even when zero (``imu.gyro_bias_drift``,
            ``imu.accel_bias_drift``, ``ext.time_drift``, ``lidar.point_time_scale``; each is
            included anyway when non-zero).

    Returns:
        Block name -> value (construction shapes of :func:`parameter_blocks`).
    """
    imu = state.imu_intrinsics
    if g_sensitivity is None:
        g_sensitivity = bool(np.any(np.asarray(imu.gyro_g_sensitivity) != 0.0))
    values: dict[str, F64] = {
        TRAJ_SO3: np.array(state.so3_spline.control_quats),
        TRAJ_R3: np.array(state.r3_spline.control_points),
        GYRO_BIAS: np.array(state.gyro_bias),
        ACCEL_BIAS: np.array(state.accel_bias),
        GRAVITY: np.array(state.gravity_G),
        EXT_ROTATION: matrix_to_quat(state.R_imu_lidar),
        EXT_TRANSLATION: np.array(state.t_imu_lidar),
        TIME_OFFSET: np.array([state.time_offset_s]),
        GYRO_SCALE: np.array(imu.gyro_scale, dtype=np.float64),
        GYRO_MISALIGNMENT: np.array(imu.gyro_misalignment, dtype=np.float64),
        GYRO_ROTATION: np.array(imu.gyro_rotation, dtype=np.float64),
        ACCEL_SCALE: np.array(imu.accel_scale, dtype=np.float64),
        ACCEL_MISALIGNMENT: np.array(imu.accel_misalignment, dtype=np.float64),
        LIDAR_INTRINSICS: intrinsics_to_array(state.lidar_intrinsics),
    }
    if g_sensitivity:
        values[GYRO_G_SENSITIVITY] = np.array(imu.gyro_g_sensitivity, dtype=np.float64).reshape(9)
    extras = (
        (GYRO_BIAS_DRIFT, np.array(state.gyro_bias_drift)),
        (ACCEL_BIAS_DRIFT, np.array(state.accel_bias_drift)),
        (TIME_DRIFT, np.array([state.time_drift])),
        (POINT_TIME_SCALE, np.array([state.point_time_scale])),
    )
    for block, value in extras:
        if block in (effects or ()) or np.any(value != 0.0):
            values[block] = value
    return values


def state_from_values(
    state: CalibrationState, values: Mapping[str, npt.ArrayLike]
) -> CalibrationState:
    """A new state with the blocks present in ``values`` replaced (others kept from ``state``).

    Args:
        state: the state the values refer to (knots, nominal elevations, ``t0_ns``).
        values: block name -> value, e.g. ``problem.values()`` after solving.

    Returns:
        The updated state.
    """

    def get(name: str) -> F64 | None:
        v = values.get(name)
        return None if v is None else np.asarray(v, dtype=np.float64)

    knots = state.knots
    so3 = state.so3_spline if (v := get(TRAJ_SO3)) is None else SO3Spline(knots, v)
    r3 = state.r3_spline if (v := get(TRAJ_R3)) is None else R3Spline(knots, v)
    imu = state.imu_intrinsics
    imu_changes: dict[str, F64] = {}
    for block, attr in (
        (GYRO_SCALE, "gyro_scale"),
        (GYRO_MISALIGNMENT, "gyro_misalignment"),
        (GYRO_ROTATION, "gyro_rotation"),
        (ACCEL_SCALE, "accel_scale"),
        (ACCEL_MISALIGNMENT, "accel_misalignment"),
    ):
        if (v := get(block)) is not None:
            imu_changes[attr] = v.reshape(-1).copy()
    if (v := get(GYRO_G_SENSITIVITY)) is not None:
        imu_changes["gyro_g_sensitivity"] = v.reshape(3, 3).copy()
    lidar = state.lidar_intrinsics
    if (v := get(LIDAR_INTRINSICS)) is not None:
        lidar = intrinsics_from_array(lidar.nominal_elevation, v)
    rot = get(EXT_ROTATION)
    tc = get(TIME_OFFSET)
    return CalibrationState(
        so3_spline=so3,
        r3_spline=r3,
        gyro_bias=state.gyro_bias if (v := get(GYRO_BIAS)) is None else v.reshape(3),
        accel_bias=state.accel_bias if (v := get(ACCEL_BIAS)) is None else v.reshape(3),
        gravity_G=state.gravity_G if (v := get(GRAVITY)) is None else v.reshape(3),
        R_imu_lidar=state.R_imu_lidar if rot is None else quat_to_matrix(rot.reshape(4)),
        t_imu_lidar=state.t_imu_lidar if (v := get(EXT_TRANSLATION)) is None else v.reshape(3),
        time_offset_s=state.time_offset_s if tc is None else float(tc.reshape(-1)[0]),
        imu_intrinsics=imu.with_(**imu_changes) if imu_changes else imu,
        lidar_intrinsics=lidar,
        t0_ns=state.t0_ns,
        gyro_bias_drift=state.gyro_bias_drift if (v := get(GYRO_BIAS_DRIFT)) is None else v,
        accel_bias_drift=state.accel_bias_drift if (v := get(ACCEL_BIAS_DRIFT)) is None else v,
        time_drift=state.time_drift if (v := get(TIME_DRIFT)) is None else float(v.reshape(-1)[0]),
        point_time_scale=state.point_time_scale
        if (v := get(POINT_TIME_SCALE)) is None
        else float(v.reshape(-1)[0]),
        t_ref_s=state.t_ref_s,
    )


def intrinsic_coordinates(state: CalibrationState) -> dict[str, float]:
    """Every IMU and LiDAR intrinsic and drift of a state by its coordinate name (as in the
    solver's ``calibration_names``); the gyro rotation as a rotation vector, rad."""
    imu = state.imu_intrinsics
    out: dict[str, float] = {}

    def put(block: str, suffixes: Sequence[str], values: npt.ArrayLike) -> None:
        for s, v in zip(suffixes, np.asarray(values, dtype=np.float64).reshape(-1), strict=True):
            out[f"{block}.{s}"] = float(v)

    put(GYRO_SCALE, _XYZ, imu.gyro_scale)
    put(GYRO_MISALIGNMENT, _MISALIGNMENT, imu.gyro_misalignment)
    put(GYRO_ROTATION, ("rx", "ry", "rz"), so3.log(quat_to_matrix(imu.gyro_rotation)))
    put(ACCEL_SCALE, _XYZ, imu.accel_scale)
    put(ACCEL_MISALIGNMENT, _MISALIGNMENT, imu.accel_misalignment)
    put(GYRO_G_SENSITIVITY, _G_SENS, imu.gyro_g_sensitivity)
    lidar = intrinsics_to_array(state.lidar_intrinsics).reshape(-1, len(INTRINSIC_NAMES))
    for b, row in enumerate(lidar):
        put(f"{LIDAR_INTRINSICS}[{b}]", INTRINSIC_NAMES, row)
    for block, drift in (
        (GYRO_BIAS_DRIFT, state.gyro_bias_drift),
        (ACCEL_BIAS_DRIFT, state.accel_bias_drift),
    ):
        put(block, drift_suffixes(np.size(drift) // 3), drift)
    out[TIME_DRIFT] = state.time_drift
    out[POINT_TIME_SCALE] = state.point_time_scale
    return out


def state_from_problem(state: CalibrationState, problem: Problem) -> CalibrationState:
    """:func:`state_from_values` with the problem's current block values."""
    return state_from_values(state, problem.values())


def free_effect_blocks(free: FreeParameters) -> tuple[str, ...]:
    """The drift blocks ``free`` estimates."""
    return tuple(
        block
        for block, flag in (
            (GYRO_BIAS_DRIFT, free.gyro_bias_drift),
            (ACCEL_BIAS_DRIFT, free.accel_bias_drift),
            (TIME_DRIFT, free.time_drift),
            (POINT_TIME_SCALE, free.point_time),
        )
        if flag
    )


def beam_point_counts(lidar: LidarPoints | None, num_beams: int) -> npt.NDArray[np.int64]:
    """(B,) number of points per beam."""
    if lidar is None or len(lidar) == 0:
        return np.zeros(num_beams, dtype=np.int64)
    return np.bincount(np.asarray(lidar.beam, dtype=np.intp), minlength=num_beams)[:num_beams]


def _lidar_fixed_mask(counts: npt.NDArray[np.int64], free: FreeParameters) -> npt.NDArray[np.bool_]:
    """(B * 6,) fixed mask of ``lidar.intrinsics`` (gauge beam + under-observed beams)."""
    b = counts.shape[0]
    fixed = np.ones((b, NUM_BEAM_INTRINSICS), dtype=bool)
    columns = np.array([free.lidar_column_free(n) for n in INTRINSIC_NAMES])
    if np.any(columns):
        enough = counts >= free.min_points_per_beam
        fixed[np.ix_(enough, columns)] = False
        if np.any(enough):
            gauge = int(np.argmax(enough))
            fixed[gauge, list(GAUGE_COLUMNS)] = True
        weak = np.flatnonzero(~enough)
        if weak.size:
            logger.info(
                "LiDAR intrinsics of beam(s) %s stay fixed (fewer than %d points)",
                weak.tolist(),
                free.min_points_per_beam,
            )
    return fixed.reshape(-1)


@dataclass(frozen=True)
class BlockSpec:
    """How one parameter block of the state enters the problem.

    Attributes:
        name: block name (:mod:`licalib_cli.residuals`).
        group: ``"trajectory"`` (eliminated by the Schur complement) or ``"calibration"``.
        is_free: whether :class:`FreeParameters` lets the optimiser change it.
        manifold: ``"euclidean"``, ``"so3"`` or ``"s2"``.
        suffixes: coordinate names ``<name>.<suffix>`` (None: the solver's default names;
            empty: one coordinate named like the block).
    """

    name: str
    group: Group
    is_free: Callable[[FreeParameters], bool]
    manifold: ManifoldName = "euclidean"
    suffixes: tuple[str, ...] | None = None

    def coord_names(self, num_beams: int, size: int | None = None) -> list[str] | None:
        """Names of the block's tangent coordinates (the per-beam LiDAR block has one set per
        beam, a bias walk of ``size`` numbers one set per piece: :func:`drift_suffixes`)."""
        if self.name == LIDAR_INTRINSICS:
            return [f"{self.name}[{b}].{s}" for b in range(num_beams) for s in INTRINSIC_NAMES]
        if self.name in _DRIFT_BLOCKS and size is not None:
            return [f"{self.name}.{s}" for s in drift_suffixes(size // 3)]
        if self.suffixes is None:
            return None
        if not self.suffixes:
            return [self.name]
        return [f"{self.name}.{s}" for s in self.suffixes]


_DRIFT_BLOCKS = (GYRO_BIAS_DRIFT, ACCEL_BIAS_DRIFT)


def drift_suffixes(pieces: int) -> tuple[str, ...]:
    """Coordinate suffixes of a bias walk's block: ``x, y, z`` for one piece (a linear drift),
    else ``x_1, y_1, z_1, x_2, ...`` (the drift over piece 1, 2, ...)."""
    if pieces <= 1:
        return _XYZ
    return tuple(f"{a}_{k}" for k in range(1, pieces + 1) for a in _XYZ)


def _imu_block(name: str, suffixes: tuple[str, ...], manifold: ManifoldName) -> BlockSpec:
    return BlockSpec(
        name, "calibration", lambda f: f.imu_block_free(name), manifold, suffixes=suffixes
    )


BLOCK_SPECS: tuple[BlockSpec, ...] = (
    BlockSpec(TRAJ_SO3, "trajectory", lambda f: f.trajectory, "so3"),
    BlockSpec(TRAJ_R3, "trajectory", lambda f: f.trajectory),
    BlockSpec(GYRO_BIAS, "trajectory", lambda f: f.biases, suffixes=_XYZ),
    BlockSpec(ACCEL_BIAS, "trajectory", lambda f: f.biases, suffixes=_XYZ),
    BlockSpec(GRAVITY, "trajectory", lambda f: f.gravity, "s2"),
    BlockSpec(
        EXT_ROTATION, "calibration", lambda f: f.extrinsic_rotation, "so3", ("rx", "ry", "rz")
    ),
    BlockSpec(EXT_TRANSLATION, "calibration", lambda f: f.extrinsic_translation, suffixes=_XYZ),
    BlockSpec(TIME_OFFSET, "calibration", lambda f: f.time_offset, suffixes=()),
    _imu_block(GYRO_SCALE, _XYZ, "euclidean"),
    _imu_block(GYRO_MISALIGNMENT, _MISALIGNMENT, "euclidean"),
    _imu_block(GYRO_ROTATION, ("rx", "ry", "rz"), "so3"),
    _imu_block(ACCEL_SCALE, _XYZ, "euclidean"),
    _imu_block(ACCEL_MISALIGNMENT, _MISALIGNMENT, "euclidean"),
    _imu_block(GYRO_G_SENSITIVITY, _G_SENS, "euclidean"),
    BlockSpec(GYRO_BIAS_DRIFT, "calibration", lambda f: f.gyro_bias_drift, suffixes=_XYZ),
    BlockSpec(ACCEL_BIAS_DRIFT, "calibration", lambda f: f.accel_bias_drift, suffixes=_XYZ),
    BlockSpec(TIME_DRIFT, "calibration", lambda f: f.time_drift, suffixes=()),
    BlockSpec(POINT_TIME_SCALE, "calibration", lambda f: f.point_time, suffixes=()),
    BlockSpec(LIDAR_INTRINSICS, "calibration", lambda f: f.any_lidar_intrinsics),
)
"""Every parameter block of a state, in solver order (trajectory group first)."""


def parameter_blocks(
    state: CalibrationState,
    free: FreeParameters | None = None,
    *,
    beam_counts: npt.ArrayLike | None = None,
    fix_gauge: bool = False,
) -> list[ParameterBlock]:
    """Parameter blocks of a state, one per :data:`BLOCK_SPECS` entry, trajectory group first.

    Args:
        state: the state (initial values).
        free: what may change (default :class:`FreeParameters`).
        beam_counts: (B,) points per beam, for the LiDAR intrinsics mask (None: no points,
            every beam's intrinsics fixed).
        fix_gauge: hold the first rotation and first two position control points (IMU-only
            problems with a free trajectory).

    Returns:
        The blocks (``imu.gyro_g_sensitivity`` and the drift blocks only when enabled or
        non-zero).
    """
    free = FreeParameters() if free is None else free
    values = state_to_values(
        state,
        g_sensitivity=free.imu_block_free(GYRO_G_SENSITIVITY) or None,
        effects=free_effect_blocks(free),
    )
    if free.bias_walk_piece_s is not None:
        pieces = drift_pieces(state.t_ref_s, free.bias_walk_piece_s)
        for name in _DRIFT_BLOCKS:
            if name in values:
                values[name] = resample_drift(values[name], pieces)
    counts = None if beam_counts is None else np.asarray(beam_counts, dtype=np.int64)
    gauge = {TRAJ_SO3: 3, TRAJ_R3: 6}  # leading coordinates held by fix_gauge
    blocks = []
    for spec in BLOCK_SPECS:
        if spec.name not in values:
            continue
        fixed: bool | npt.NDArray[np.bool_] = not spec.is_free(free)
        if spec.name in gauge and free.trajectory and fix_gauge:
            fixed = np.zeros(3 * state.knots.num_control_points, dtype=bool)
            fixed[: gauge[spec.name]] = True
        elif spec.name == LIDAR_INTRINSICS and counts is not None:
            fixed = _lidar_fixed_mask(counts, free)
        elif spec.name == LIDAR_INTRINSICS:
            fixed = True  # no points: nothing to estimate them from, and nothing to name
        blocks.append(
            ParameterBlock(
                spec.name,
                values[spec.name],
                manifold=spec.manifold,
                group=spec.group,
                coord_names=spec.coord_names(
                    state.lidar_intrinsics.num_beams, np.size(values[spec.name])
                ),
                scale=_scale_of(spec.name, free, np.size(values[spec.name])),
                fixed=fixed,
            )
        )
    return blocks


PRIOR_SCALE_FACTOR = 2.0
"""With a prior on the extrinsic translation (``FreeParameters.translation_prior``), its
characteristic scale is at least this many times the prior's sigma: the truncated SVD keeps
every direction whose information exceeds one over the squared scale, and the prior alone then
gives each translation direction four times that, so the solver uses the prior where the data
say nothing instead of holding the estimate wherever the rounds left it."""


def _scale_of(name: str, free: FreeParameters, size: int = 0) -> F64:
    """Characteristic scales of calibration block ``name`` (:data:`CALIBRATION_SCALES` or the
    block's ``free.expected_size``, the translation's widened to :data:`PRIOR_SCALE_FACTOR`
    times its prior's sigma, a bias walk's in ``K`` pieces (``size = 3 K``) ``K^1.5`` times the
    one drift's).

    A piece holds ``1/K`` of the samples over ``1/K`` of the time, so the data determine its
    drift ``K^1.5`` times less well than one drift over the segment; with its scale grown alike,
    each piece faces the truncated SVD on the same footing as the one drift (at the one drift's
    scale a gyro walk's pieces over 10 s, each some five of its sigmas from zero, were held).
    """
    scale = np.asarray(CALIBRATION_SCALES[name], dtype=np.float64)
    expected = dict(free.expected_size)
    if name in expected:
        scale = np.full_like(scale, expected[name])
    if name in _DRIFT_BLOCKS and size > 3:
        scale = scale * (size // 3) ** 1.5
    if name == EXT_TRANSLATION and free.translation_prior is not None:
        sigma = np.asarray(free.translation_prior[1], dtype=np.float64)
        scale = np.maximum(scale, PRIOR_SCALE_FACTOR * sigma)
    return scale


def calibration_moved(
    before: CalibrationState, after: CalibrationState, names: Sequence[str]
) -> F64:
    """(len(names),) how ``after`` differs from ``before`` in the named calibration coordinates
    (the solver's tangent coordinates and units: ``before [+] moved == after``); 0 for a name
    neither state holds.

    Args:
        before: the earlier state (an initial guess).
        after: the later state (a fit's estimate).
        names: calibration coordinate names (a solver report's ``calibration_names``).
    """
    drifts = (GYRO_BIAS_DRIFT, ACCEL_BIAS_DRIFT, TIME_DRIFT, POINT_TIME_SCALE)
    v0 = state_to_values(before, g_sensitivity=True, effects=drifts)
    v1 = state_to_values(after, g_sensitivity=True, effects=drifts)
    for name in _DRIFT_BLOCKS:  # a walk's pieces as ``after`` has them
        v0[name] = resample_drift(v0[name], np.size(v1[name]) // 3)
    moved: dict[str, float] = {}
    for spec in BLOCK_SPECS:
        if spec.group != "calibration" or spec.name not in v0 or spec.name not in v1:
            continue
        block = ParameterBlock(
            spec.name,
            v0[spec.name],
            manifold=spec.manifold,
            group=spec.group,
            coord_names=spec.coord_names(before.lidar_intrinsics.num_beams, np.size(v0[spec.name])),
        )
        moved.update(zip(block.coord_names, block.local(v1[spec.name]), strict=True))
    return np.array([moved.get(n, 0.0) for n in names], dtype=np.float64)


# -------------------------------------------------------------------------------- builder


class SplineCoverageError(ValueError):
    """Measurement times outside the trajectory spline (a time offset moved past the spline's
    padding)."""


def _check_coverage(knots: UniformKnots, t_s: F64, what: str) -> None:
    if t_s.size == 0:
        return
    inside = knots.contains(t_s)
    if not np.all(inside):
        lo, hi = float(np.min(t_s)), float(np.max(t_s))
        msg = (
            f"{int(np.count_nonzero(~inside))} {what} fall outside the trajectory spline "
            f"[{knots.t0_s:.6f}, {knots.t_end_s:.6f}] s (they span [{lo:.6f}, {hi:.6f}] s); "
            "build the spline over a longer interval (with time-offset padding) or drop them"
        )
        raise SplineCoverageError(msg)


def incidence_cosine(
    state: CalibrationState,
    t_query_s: npt.ArrayLike,
    beam: npt.ArrayLike,
    theta: npt.ArrayLike,
    normal: npt.ArrayLike,
) -> F64:
    """(N,) |cosine| of the angle between each point's nominal ray and its plane's normal.

    Args:
        state: trajectory, extrinsic rotation and nominal elevations.
        t_query_s: (N,) IMU-clock times of the points on the trajectory, s.
        beam: (N,) beam indices.
        theta: (N,) raw azimuths, rad.
        normal: (N, 3) unit normals of the points' planes, ``{G}``.
    """
    rot = state.so3_spline.rotation(np.asarray(t_query_s, dtype=np.float64))
    phi = state.lidar_intrinsics.nominal_elevation[np.asarray(beam, dtype=np.intp)]
    az = np.asarray(theta, dtype=np.float64)
    ray_l = np.stack([np.cos(phi) * np.cos(az), np.cos(phi) * np.sin(az), np.sin(phi)], axis=-1)
    ray_g = np.einsum("nij,nj->ni", rot, ray_l @ state.R_imu_lidar.T)
    return np.abs(np.einsum("ij,ij->i", ray_g, np.asarray(normal, dtype=np.float64)))


def build_problem(
    state: CalibrationState,
    imu: ImuData | None,
    lidar: LidarPoints | None,
    planes: Planes | None,
    noise: NoiseModel | None = None,
    free: FreeParameters | None = None,
    *,
    fix_gauge: bool | None = None,
    extra_residuals: Sequence[ResidualBlock] = (),
) -> Problem:
    """Build the least-squares problem of one round.

    Args:
        state: initial values (and knots, nominal elevations).
        imu: IMU readings (seconds relative to ``state.t0_ns``), or None.
        lidar: LiDAR points with plane associations, or None.
        planes: the planes the points refer to (required with ``lidar``).
        noise: noise model (default :class:`NoiseModel`).
        free: what may change (default :class:`FreeParameters`).
        fix_gauge: hold the first control points (default: when there are no LiDAR points and
            the trajectory is free).
        extra_residuals: further residual blocks (e.g.
            :class:`~licalib_cli.residuals.GaussianPrior`), added without a robust loss.

    Returns:
        The problem: parameter blocks (names in :mod:`licalib_cli.residuals`) and residual blocks
        ``imu.gyro``, ``imu.accel`` and ``lidar.point_to_plane`` (Huber).

    Raises:
        ValueError: when an IMU time or a point time ``tau + t_c`` is outside the spline range,
            on inconsistent array shapes, or when points are given without planes.
    """
    noise = NoiseModel() if noise is None else noise
    free = FreeParameters() if free is None else free
    knots = state.knots
    has_lidar = lidar is not None and len(lidar) > 0
    if fix_gauge is None:
        fix_gauge = free.trajectory and not has_lidar
    counts = beam_point_counts(lidar, state.lidar_intrinsics.num_beams) if has_lidar else None
    problem = Problem()
    for block in parameter_blocks(state, free, beam_counts=counts, fix_gauge=fix_gauge):
        problem.add_parameter_block(block)
    use_gs = GYRO_G_SENSITIVITY in problem

    if imu is not None and len(imu) > 0:
        t_imu = np.asarray(imu.t_s, dtype=np.float64)
        _check_coverage(knots, t_imu, "IMU sample times")
        shared = SO3EvaluationCache()  # gyro and accelerometer: one rotation-spline evaluation
        problem.add_residual_block(
            GyroResidual(
                knots,
                t_imu,
                imu.gyro,
                noise.gyro_sigma,
                g_sensitivity=use_gs,
                t_ref_s=state.t_ref_s,
                so3_cache=shared,
            )
        )
        problem.add_residual_block(
            AccelResidual(
                knots, t_imu, imu.accel, noise.accel_sigma, t_ref_s=state.t_ref_s, so3_cache=shared
            )
        )

    if has_lidar:
        assert lidar is not None
        if planes is None:
            msg = "LiDAR points need their planes: pass the Planes their plane indices refer to"
            raise ValueError(msg)
        t_pts = np.asarray(lidar.t_s, dtype=np.float64)
        t_query = t_pts + state.time_offset_s + state.time_drift * (t_pts - state.t_ref_s)
        if lidar.sweep_start_s is not None:
            t_query = t_query - state.point_time_scale * (t_pts - np.asarray(lidar.sweep_start_s))
        _check_coverage(knots, t_query, "point times (tau + time offset)")
        plane = np.asarray(lidar.plane, dtype=np.intp)
        normal = np.asarray(planes.normal, dtype=np.float64)
        if plane.min() < 0 or plane.max() >= normal.shape[0]:
            msg = f"plane indices must lie in [0, {normal.shape[0]})"
            raise ValueError(msg)
        sigma2 = np.full(plane.shape[0], noise.range_sigma**2)
        if noise.min_incidence_cos < 1.0:
            cos_inc = incidence_cosine(state, t_query, lidar.beam, lidar.theta, normal[plane])
            c = noise.min_incidence_cos
            factor = (
                np.maximum(cos_inc, c)
                if noise.incidence_floor
                else np.where(cos_inc >= c, cos_inc, 1.0)
            )
            sigma2 *= factor**2
        if planes.thickness is not None and noise.thickness_weight > 0.0:
            sigma2 += (noise.thickness_weight * np.asarray(planes.thickness)[plane]) ** 2
        residual = PointToPlaneResidual(
            knots,
            t_pts,
            lidar.beam,
            lidar.rho,
            lidar.theta,
            normal[plane],
            np.asarray(planes.d, dtype=np.float64)[plane],
            np.sqrt(sigma2),
            state.lidar_intrinsics.nominal_elevation,
            model_gap=lidar.model_gap,
            t_ref_s=state.t_ref_s,
            sweep_start_s=lidar.sweep_start_s,
            whitening_range_scale=state.lidar_intrinsics.range_scale,
        )
        loss = None if noise.huber_threshold is None else HuberLoss(noise.huber_threshold)
        problem.add_residual_block(residual, loss)

    for extra in extra_residuals:
        problem.add_residual_block(extra)
    return problem
