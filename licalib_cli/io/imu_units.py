"""Detect and convert IMU units (gyro rad/s or deg/s, accelerometer m/s^2 or g).

Detection from the data of a segment:

* accelerometer: the median norm of ``linear_acceleration`` is close to gravity, so it is
  about 9.8 in m/s^2 and about 1.0 in g (Livox IMUs publish g);
* gyro: rates above ~12 rad/s (690 deg/s) do not occur when a rig is moved by hand or on a
  vehicle, so a 99th-percentile ``|angular_velocity|`` above 12 means deg/s. Slow data is
  ambiguous and assumed rad/s (the message says so).

The config (``imu.gyro_unit``, ``imu.accel_unit``) overrides detection. Converted samples are
always rad/s and m/s^2.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import numpy.typing as npt

__all__ = ["GRAVITY", "ImuUnits", "convert_imu", "detect_imu_units"]

GRAVITY = 9.80665
"""Standard gravity, m/s^2 (used to convert g)."""

_GYRO_DEG_THRESHOLD = 12.0

GyroUnit = Literal["rad/s", "deg/s"]
AccelUnit = Literal["m/s^2", "g"]


@dataclass(frozen=True)
class ImuUnits:
    """Units of the raw IMU messages and how they were decided.

    Attributes:
        gyro_unit: unit of ``angular_velocity`` in the messages.
        accel_unit: unit of ``linear_acceleration`` in the messages.
        gyro_source: ``config``, ``detected`` or ``assumed`` (ambiguous data).
        accel_source: ``config``, ``detected`` or ``assumed``.
        gyro_p99: 99th percentile of ``|angular_velocity|`` in the raw unit.
        accel_norm_median: median ``|linear_acceleration|`` in the raw unit.
    """

    gyro_unit: GyroUnit
    accel_unit: AccelUnit
    gyro_source: Literal["config", "detected", "assumed"]
    accel_source: Literal["config", "detected", "assumed"]
    gyro_p99: float
    accel_norm_median: float

    def messages(self) -> list[str]:
        """Sentences telling the user what was detected (for logs and ``info``)."""
        out = []
        if self.gyro_source == "detected" and self.gyro_unit == "deg/s":
            out.append(
                f"IMU gyro is in deg/s (99th percentile {self.gyro_p99:.1f}); converted to "
                "rad/s (set `imu.gyro_unit` to override)."
            )
        if self.gyro_source == "assumed":
            out.append(
                f"IMU gyro unit assumed rad/s (rates too low to tell, 99th percentile "
                f"{self.gyro_p99:.3f}); set `imu.gyro_unit` if it is deg/s."
            )
        if self.accel_source == "detected" and self.accel_unit == "g":
            out.append(
                f"IMU accelerometer is in g (median norm {self.accel_norm_median:.3f}); "
                "converted to m/s^2 (set `imu.accel_unit` to override)."
            )
        if self.accel_source == "assumed":
            out.append(
                f"IMU accelerometer median norm is {self.accel_norm_median:.3f}, neither ~9.8 "
                "(m/s^2) nor ~1 (g); assumed m/s^2, set `imu.accel_unit` if that is wrong."
            )
        return out


def detect_imu_units(
    gyro: npt.NDArray[np.float64],
    accel: npt.NDArray[np.float64],
    gyro_override: GyroUnit | None = None,
    accel_override: AccelUnit | None = None,
) -> ImuUnits:
    """Decide the units of raw IMU data.

    Args:
        gyro: (N, 3) raw angular velocity.
        accel: (N, 3) raw linear acceleration.
        gyro_override: ``imu.gyro_unit`` from the config, or None to detect.
        accel_override: ``imu.accel_unit`` from the config, or None to detect.

    Returns:
        The decided units with their evidence.
    """
    gnorm = np.linalg.norm(gyro, axis=1) if len(gyro) else np.zeros(1)
    anorm = np.linalg.norm(accel, axis=1) if len(accel) else np.zeros(1)
    p99 = float(np.percentile(gnorm, 99))
    amed = float(np.median(anorm))
    gyro_unit: GyroUnit
    gsrc: Literal["config", "detected", "assumed"]
    if gyro_override is not None:
        gyro_unit, gsrc = gyro_override, "config"
    elif p99 > _GYRO_DEG_THRESHOLD:
        gyro_unit, gsrc = "deg/s", "detected"
    elif p99 > 0.2:
        gyro_unit, gsrc = "rad/s", "detected"
    else:
        gyro_unit, gsrc = "rad/s", "assumed"
    accel_unit: AccelUnit
    asrc: Literal["config", "detected", "assumed"]
    if accel_override is not None:
        accel_unit, asrc = accel_override, "config"
    elif 0.6 < amed < 1.5:
        accel_unit, asrc = "g", "detected"
    elif 6.0 < amed < 14.0:
        accel_unit, asrc = "m/s^2", "detected"
    else:
        accel_unit, asrc = "m/s^2", "assumed"
    return ImuUnits(gyro_unit, accel_unit, gsrc, asrc, p99, amed)


def convert_imu(
    gyro: npt.NDArray[np.float64], accel: npt.NDArray[np.float64], units: ImuUnits
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """Convert raw IMU arrays to rad/s and m/s^2.

    Args:
        gyro: (N, 3) raw angular velocity in ``units.gyro_unit``.
        accel: (N, 3) raw linear acceleration in ``units.accel_unit``.
        units: decided units.

    Returns:
        ``(gyro_rad_s, accel_m_s2)``, both (N, 3) float64 (new arrays).
    """
    g = np.deg2rad(gyro) if units.gyro_unit == "deg/s" else np.array(gyro, dtype=np.float64)
    a = accel * GRAVITY if units.accel_unit == "g" else np.array(accel, dtype=np.float64)
    return g, a
