"""The effects a simulation can hide, by the names ``licalib diagnose`` gives them.

Each effect has a reference size (``--effect-scale 1``): the paper's Table
sensor_intrinsic_setting where it has one (its "(%)" entries read as percent), otherwise a
realistic figure named below. ``--effect-scale K`` multiplies it (the benchmark uses 2 to 5).

=========================== =================================== =================================
effect                      reference size                      injected as
=========================== =================================== =================================
``gyro_scale``              0.01 % (paper)                      ``s_w - 1 ~ N(0, size)`` per axis
``gyro_misalignment``       0.05 deg (paper)                    3 angles ``~ N(0, size)``
``gyro_rotation``           0.5 deg                             ``R_wI``: 3 angles ``N(0, size)``
``accel_scale``             0.1 % (paper)                       ``s_a - 1 ~ N(0, size)`` per axis
``accel_misalignment``      0.05 deg (paper)                    3 angles ``~ N(0, size)``
``g_sensitivity``           0.1 deg/s per g                     9 entries of ``A_w ~ N(0, size)``
``gyro_bias_walk``          10 x MTi-100 walk density           gyro bias random walk
``accel_bias_walk``         10 x MTi-100 walk density           accelerometer bias random walk
``imu_clock_drift``         50 ppm                              IMU stamps run ``1 + ppm`` fast
``lidar_range_offset``      0.01 m (paper)                      ``drho ~ N(0, size)`` per beam
``lidar_range_scale``       0.005 % (paper)                     ``s - 1 ~ N(0, size)`` per beam
``lidar_elevation``         0.1 deg (paper)                     ``dphi ~ N(0, size)`` per beam
``lidar_azimuth``           0.05 deg (paper)                    ``dtheta ~ N(0, size)`` per beam
``lidar_vertical_offset``   0.005 m (paper)                     ``V ~ N(0, size)`` per beam
``lidar_horizontal_offset`` 0.005 m (paper)                     ``H ~ N(0, size)`` per beam
``lidar_point_time``        1 % of the time within the sweep    per-point times off by ``k = size``
=========================== =================================== =================================

The gauge beam 0 keeps zero ``dphi, dtheta, V, H`` (method.md section 4). The bias walks are the
MTi-100 densities of :mod:`~licalib_cli.simulation.spec` times ten (a consumer-grade MEMS IMU)
times the scale; ``lidar_point_time`` publishes each point's time within its sweep as the true
one divided by ``1 - k`` (a driver assuming a firing period ``1 / (1 - k)`` times the real one),
so a point published at ``tau`` was measured at ``tau - k (tau - sweep start)``, the model's
``lidar.point_time_scale``. A constant error of all per-point times would be a change of the
time offset itself, so the effect is the part that grows within the sweep. The per-beam LiDAR
effects (:attr:`Effect.per_beam`) do not apply to the non-repetitive ``mid360`` and ``avia``,
which have no fixed beams.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

__all__ = [
    "EFFECT_SIZES",
    "LEGACY_EFFECT_NAMES",
    "Effect",
    "EffectSize",
    "parse_effects",
]


class Effect(str, Enum):
    """An effect the simulator can hide (the candidates of ``licalib diagnose``)."""

    GYRO_SCALE = "gyro_scale"
    GYRO_MISALIGNMENT = "gyro_misalignment"
    GYRO_ROTATION = "gyro_rotation"
    ACCEL_SCALE = "accel_scale"
    ACCEL_MISALIGNMENT = "accel_misalignment"
    G_SENSITIVITY = "g_sensitivity"
    GYRO_BIAS_WALK = "gyro_bias_walk"
    ACCEL_BIAS_WALK = "accel_bias_walk"
    IMU_CLOCK_DRIFT = "imu_clock_drift"
    LIDAR_RANGE_OFFSET = "lidar_range_offset"
    LIDAR_RANGE_SCALE = "lidar_range_scale"
    LIDAR_ELEVATION = "lidar_elevation"
    LIDAR_AZIMUTH = "lidar_azimuth"
    LIDAR_VERTICAL_OFFSET = "lidar_vertical_offset"
    LIDAR_HORIZONTAL_OFFSET = "lidar_horizontal_offset"
    LIDAR_POINT_TIME = "lidar_point_time"

    @property
    def sensor(self) -> str:
        """``imu`` or ``lidar``: the sensor whose data carry the effect."""
        return "lidar" if self.value.startswith("lidar") else "imu"

    @property
    def per_beam(self) -> bool:
        """A LiDAR intrinsic drawn per beam (every LiDAR effect but ``lidar_point_time``); a
        scanner without fixed beams (``mid360``, ``avia``) has none."""
        return self.sensor == "lidar" and self is not Effect.LIDAR_POINT_TIME


@dataclass(frozen=True)
class EffectSize:
    """The reference size of an effect (``--effect-scale 1``).

    Attributes:
        size: the size in ``unit``: a standard deviation for drawn effects, the value itself
            for ``imu_clock_drift`` and ``lidar_point_time``, a multiple of the MTi-100 walk
            density for the bias walks.
        unit: unit of ``size``.
        source: where the figure comes from.
    """

    size: float
    unit: str
    source: str


_PAPER = "paper, Table sensor_intrinsic_setting"
EFFECT_SIZES: dict[Effect, EffectSize] = {
    Effect.GYRO_SCALE: EffectSize(1e-4, "1 (std of s - 1)", _PAPER),
    Effect.GYRO_MISALIGNMENT: EffectSize(0.05, "deg (std)", _PAPER),
    Effect.GYRO_ROTATION: EffectSize(0.5, "deg (std per Euler angle)", "simulator default"),
    Effect.ACCEL_SCALE: EffectSize(1e-3, "1 (std of s - 1)", _PAPER),
    Effect.ACCEL_MISALIGNMENT: EffectSize(0.05, "deg (std)", _PAPER),
    Effect.G_SENSITIVITY: EffectSize(0.1, "deg/s per g (std)", "MEMS gyro datasheets"),
    Effect.GYRO_BIAS_WALK: EffectSize(10.0, "x MTi-100 walk density", "consumer-grade MEMS"),
    Effect.ACCEL_BIAS_WALK: EffectSize(10.0, "x MTi-100 walk density", "consumer-grade MEMS"),
    Effect.IMU_CLOCK_DRIFT: EffectSize(50.0, "ppm", "uncompensated crystal"),
    Effect.LIDAR_RANGE_OFFSET: EffectSize(0.01, "m (std)", _PAPER),
    Effect.LIDAR_RANGE_SCALE: EffectSize(5e-5, "1 (std of s - 1)", _PAPER),
    Effect.LIDAR_ELEVATION: EffectSize(0.1, "deg (std)", _PAPER),
    Effect.LIDAR_AZIMUTH: EffectSize(0.05, "deg (std)", _PAPER),
    Effect.LIDAR_VERTICAL_OFFSET: EffectSize(0.005, "m (std)", _PAPER),
    Effect.LIDAR_HORIZONTAL_OFFSET: EffectSize(0.005, "m (std)", _PAPER),
    Effect.LIDAR_POINT_TIME: EffectSize(0.01, "fraction of the time within the sweep", "1 %"),
}
"""Reference size of every effect."""

LEGACY_EFFECT_NAMES: dict[str, tuple[Effect, ...]] = {
    "g-sensitivity": (Effect.G_SENSITIVITY,),
    "imu-clock-drift": (Effect.IMU_CLOCK_DRIFT,),
    "bias-random-walk": (Effect.GYRO_BIAS_WALK, Effect.ACCEL_BIAS_WALK),
}
"""Earlier names, still accepted: ``bias-random-walk`` is both bias walks."""


def parse_effects(names: tuple[object, ...] | list[object]) -> tuple[Effect, ...]:
    """Effects from names (or members), earlier names included, without repeats.

    Raises:
        ValueError: an unknown name (the message lists the known ones).
    """
    out: list[Effect] = []
    for name in names:
        value = getattr(name, "value", name)
        if isinstance(value, str) and value in LEGACY_EFFECT_NAMES:
            out.extend(LEGACY_EFFECT_NAMES[value])
            continue
        try:
            out.append(Effect(str(value).replace("-", "_")))
        except ValueError as err:
            choices = ", ".join(e.value for e in Effect)
            msg = f"Unknown effect {value!r}; choose from {choices}."
            raise ValueError(msg) from err
    return tuple(dict.fromkeys(out))
