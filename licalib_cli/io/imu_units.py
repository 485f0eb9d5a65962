"""Detect and convert IMU units (gyro rad/s or deg/s, accelerometer m/s^2 or g).

Detection from the data of a segment:

* accelerometer: the median norm of ``linear_acceleration`` is close to gravity, so it is
  about 9.8 in m/s^2 and about 1.0 in g (Livox IMUs publish g);
* gyro, from physics first: while the rig tilts, the direction ``u = a / |a|`` of the
  measured specific force (mostly gravity) turns in the IMU frame as ``du/dt = -w x u`` with
  ``w`` in rad/s. The least-squares factor ``k`` in ``du/dt = -k (w_raw x u)`` (on 50 ms
  averages, at least 0.5 s of data) is about 1 for rad/s data and about pi/180 for deg/s data;
  it decides when the tilting explains the turning of ``u`` (correlation above 0.2 and above
  4 sigma of chance) and ``k`` lies within a factor of 3 of either value.
* gyro, from magnitude otherwise: rates above ~12 rad/s (690 deg/s) do not occur when a rig is
  moved by hand or on a vehicle, so a 99th-percentile ``|angular_velocity|`` above 12 means
  deg/s. Below that both units are plausible (5 may be brisk rad/s or slow deg/s): the unit is
  *assumed*, and :meth:`ImuUnits.warnings` says so and asks the user to set ``imu.gyro_unit``.
  The assumption is deg/s when the accelerometer is in g (drivers that keep the raw units of
  the IMU, as Ouster's IMU packets: g and deg/s), rad/s otherwise (ROS's unit). Under 0.5 s of
  data the tilting check cannot run: the warning says that the data is too short to tell.

The config (``imu.gyro_unit``, ``imu.accel_unit``) overrides detection, unless the data
contradict it beyond doubt (the accelerometer's median norm is gravity in the other unit, or the
tilting shows the other gyro unit): :attr:`ImuUnits.contradiction` says so, naming the unit the
data are in, and the stream refuses the data so read. Converted
samples are always rad/s and m/s^2.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import numpy.typing as npt

__all__ = [
    "GRAVITY",
    "ImuUnits",
    "contradicted_unit",
    "convert_imu",
    "detect_imu_units",
    "gravity_turn_factor",
]

GRAVITY = 9.80665
"""Standard gravity, m/s^2 (used to convert g)."""

_GYRO_DEG_THRESHOLD = 12.0
_GRAVITY_BIN_S = 0.05  # averaging window of the gravity-direction check, s
_GRAVITY_MIN_BINS = 10  # at least 0.5 s of data for the gravity-direction check
_GRAVITY_MIN_CORR = 0.2  # and at least 4 sigma of the correlation of noise
_GRAVITY_FACTOR_TOL = 3.0
_GRAVITY_MIN_SPAN_S = _GRAVITY_BIN_S * _GRAVITY_MIN_BINS

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
        gravity_turn_factor: least-squares ``k`` of ``du/dt = -k (w_raw x u)`` (about 1 for
            rad/s, 0.0175 for deg/s), or None when the data could not tell (too short, no
            tilting, or no stamps given).
        span_s: time the samples span, s (None: no stamps given).
        contradiction: a sentence when a configured unit contradicts what the data show beyond
            doubt (:func:`contradicted_unit`), else None.
        livox: the LiDAR's clouds are a Livox driver's, whose IMU publishes g with rad/s.
    """

    gyro_unit: GyroUnit
    accel_unit: AccelUnit
    gyro_source: Literal["config", "detected", "assumed"]
    accel_source: Literal["config", "detected", "assumed"]
    gyro_p99: float
    accel_norm_median: float
    gravity_turn_factor: float | None = None
    span_s: float | None = None
    contradiction: str | None = None
    livox: bool = False

    @property
    def too_short(self) -> bool:
        """The samples span less than the 0.5 s the tilting check of the gyro unit needs."""
        return self.span_s is not None and self.span_s < _GRAVITY_MIN_SPAN_S

    @property
    def gyro_assumption(self) -> str | None:
        """``"gyro unit assumed deg/s"`` when the gyro unit was assumed, else None (for
        sentences that rest on it, such as how much the rig rotated)."""
        return f"gyro unit assumed {self.gyro_unit}" if self.gyro_source == "assumed" else None

    def messages(self) -> list[str]:
        """Sentences telling the user what was detected and converted (informative notes)."""
        out = []
        if self.gyro_source == "detected" and self.gyro_unit == "deg/s":
            out.append(
                f"IMU gyro is in deg/s (99th percentile {self.gyro_p99:.1f}); converted to "
                "rad/s (set `imu.gyro_unit` to override)."
            )
        if self.accel_source == "detected" and self.accel_unit == "g":
            out.append(
                f"IMU accelerometer is in g (median norm {self.accel_norm_median:.3f}); "
                "converted to m/s^2 (set `imu.accel_unit` to override)."
            )
        return out

    def warnings(self) -> list[str]:
        """Sentences about units that were assumed rather than detected (user action advised)."""
        out = []
        if self.gyro_source == "assumed":
            other = "rad/s" if self.gyro_unit == "deg/s" else "deg/s"
            if self.gyro_unit == "deg/s":
                why = (
                    "as the accelerometer reads g (drivers that keep the IMU's raw units publish "
                    "g with deg/s, Livox's g with rad/s)"
                )
            elif self.livox and self.accel_unit == "g":
                why = "as the LiDAR's clouds are a Livox driver's, which publishes g with rad/s"
            else:
                why = "as ROS specifies"
            if self.too_short:
                evidence = (
                    f"{self.span_s:.2f} s of IMU data is too little to tell the gyro unit (the "
                    f"tilting check needs {_GRAVITY_MIN_SPAN_S:g} s, and the 99th percentile of "
                    f"|w|, {self.gyro_p99:.3g}, is plausible in rad/s and in deg/s)"
                )
            else:
                evidence = (
                    f"The IMU gyro unit cannot be told from the data (99th percentile of |w| "
                    f"{self.gyro_p99:.3g}, plausible in rad/s and in deg/s, and the tilting does "
                    "not settle it)"
                )
            evidence = evidence[0].upper() + evidence[1:]
            out.append(
                f"{evidence}; it is assumed {self.gyro_unit} {why}, set "
                f"`imu.gyro_unit: {other}` in the config if the data is in {other}."
            )
        if self.accel_source == "assumed":
            out.append(
                f"The IMU accelerometer median norm is {self.accel_norm_median:.3f}, neither ~9.8 "
                "(m/s^2) nor ~1 (g); it is assumed m/s^2, set `imu.accel_unit` in the config if "
                "that is wrong."
            )
        return out


def gravity_turn_factor(
    t_ns: npt.NDArray[np.int64], gyro: npt.NDArray[np.float64], accel: npt.NDArray[np.float64]
) -> float | None:
    """How fast the specific-force direction turns per raw gyro unit (see the module docstring).

    Args:
        t_ns: (N,) stamps, ns.
        gyro: (N, 3) raw angular velocity.
        accel: (N, 3) raw linear acceleration (any unit).

    Returns:
        ``k`` of ``du/dt = -k (w_raw x u)``: about 1 for rad/s data, about pi/180 for deg/s;
        None when the data does not tell (under 0.5 s, or the tilting does not explain the
        turning of ``u``: correlation below 0.2 or within 4 sigma of chance).
    """
    t = np.asarray(t_ns, dtype=np.int64)
    if t.size < 3 or gyro.shape[0] != t.size:
        return None
    ts = (t - t.min()).astype(np.float64) * 1e-9
    # the occupied bins only, in time order (stamps far apart must not allocate empty bins)
    _, idx = np.unique(np.floor(ts / _GRAVITY_BIN_S).astype(np.int64), return_inverse=True)
    idx = idx.reshape(-1)
    cnt = np.bincount(idx)
    if cnt.size < _GRAVITY_MIN_BINS:
        return None

    def binned(x: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        cols = [np.bincount(idx, x[:, j]) / cnt for j in range(x.shape[1])]
        return np.stack(cols, axis=1)

    tb = np.bincount(idx, ts) / cnt
    wb, ab = binned(np.asarray(gyro, np.float64)), binned(np.asarray(accel, np.float64))
    norm = np.linalg.norm(ab, axis=1)
    if not np.all(np.isfinite(norm)) or np.any(norm <= 0):
        return None
    u = ab / norm[:, None]
    du = (u[2:] - u[:-2]) / (tb[2:] - tb[:-2])[:, None]
    pred = -np.cross(wb[1:-1], u[1:-1])
    pp, dd, dp = float(np.sum(pred * pred)), float(np.sum(du * du)), float(np.sum(du * pred))
    if not (np.isfinite(pp) and np.isfinite(dd) and np.isfinite(dp)) or pp <= 0 or dd <= 0:
        return None
    min_corr = max(_GRAVITY_MIN_CORR, 4.0 / np.sqrt(du.size))
    if dp / np.sqrt(pp * dd) < min_corr:
        return None
    return dp / pp


def detect_imu_units(
    gyro: npt.NDArray[np.float64],
    accel: npt.NDArray[np.float64],
    gyro_override: GyroUnit | None = None,
    accel_override: AccelUnit | None = None,
    t_ns: npt.NDArray[np.int64] | None = None,
    livox: bool = False,
) -> ImuUnits:
    """Decide the units of raw IMU data.

    Args:
        gyro: (N, 3) raw angular velocity.
        accel: (N, 3) raw linear acceleration.
        gyro_override: ``imu.gyro_unit`` from the config, or None to detect.
        accel_override: ``imu.accel_unit`` from the config, or None to detect.
        t_ns: (N,) stamps, ns; enables the gravity-direction check of the gyro unit.
        livox: the LiDAR's clouds are a Livox driver's (``tag`` and ``line`` fields), whose
            IMU publishes g with rad/s: an accelerometer in g then pairs with rad/s where the
            data cannot tell the gyro's unit (deg/s otherwise, as IMUs' raw units).

    Returns:
        The decided units with their evidence.
    """
    gnorm = np.linalg.norm(gyro, axis=1) if len(gyro) else np.zeros(1)
    anorm = np.linalg.norm(accel, axis=1) if len(accel) else np.zeros(1)
    p99 = float(np.percentile(gnorm, 99))
    amed = float(np.median(anorm))
    factor = None
    if t_ns is not None and len(gyro) == len(accel):
        factor = gravity_turn_factor(t_ns, gyro, accel)
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
    gyro_unit: GyroUnit
    gsrc: Literal["config", "detected", "assumed"]
    if gyro_override is not None:
        gyro_unit, gsrc = gyro_override, "config"
    elif factor is not None and _within(factor, 1.0):
        gyro_unit, gsrc = "rad/s", "detected"
    elif factor is not None and _within(factor, np.pi / 180.0):
        gyro_unit, gsrc = "deg/s", "detected"
    elif p99 > _GYRO_DEG_THRESHOLD:
        gyro_unit, gsrc = "deg/s", "detected"
    elif accel_unit == "g" and asrc != "assumed" and not livox:
        gyro_unit, gsrc = "deg/s", "assumed"  # raw IMU units: g with deg/s
    else:
        gyro_unit, gsrc = "rad/s", "assumed"
    span = None
    if t_ns is not None and len(t_ns):
        span = float(np.max(t_ns) - np.min(t_ns)) * 1e-9
    contradiction = contradicted_unit(gyro_override, accel_override, amed, factor)
    return ImuUnits(
        gyro_unit, accel_unit, gsrc, asrc, p99, amed, factor, span, contradiction, livox
    )


def contradicted_unit(
    gyro_override: GyroUnit | None,
    accel_override: AccelUnit | None,
    accel_median: float,
    factor: float | None,
) -> str | None:
    """One sentence when a configured unit contradicts what the data show beyond doubt, else
    None: an accelerometer configured in g whose median norm is gravity's in m/s^2 (9.8 read as
    g is 96 m/s^2; the other way round it reads no gravity, which the stream's own check says),
    or a gyro whose rate, read in the other unit, is the rate at which gravity turns in the IMU
    frame (the units are a factor 57 apart; either reading within 3 of its own)."""
    if accel_override == "g" and 6.0 < accel_median < 14.0:
        return (
            f"imu.accel_unit 'g' makes the accelerometer read {accel_median * GRAVITY:.3g} m/s^2 "
            f"(median norm) where gravity is {GRAVITY:.2f}; the data are in m/s^2 (median norm "
            f"{accel_median:.3g}): set imu.accel_unit: m/s^2, or remove it to detect the unit."
        )
    if gyro_override is None or factor is None:
        return None
    scale = {"rad/s": 1.0, "deg/s": np.pi / 180.0}
    shown = next((u for u, k in scale.items() if _within(factor, k)), None)
    if shown is None or shown == gyro_override:
        return None
    return (
        f"imu.gyro_unit '{gyro_override}' contradicts the data: gravity turns in the IMU frame at "
        f"{factor / scale[shown]:.2f} times the gyro's rate read in {shown} "
        f"({factor / scale[gyro_override]:.3g} times it in {gyro_override}): set imu.gyro_unit: "
        f"{shown}, or remove it to detect the unit."
    )


def _within(value: float, target: float) -> bool:
    """Whether ``value`` lies within a factor :data:`_GRAVITY_FACTOR_TOL` of ``target``."""
    return target / _GRAVITY_FACTOR_TOL <= value <= target * _GRAVITY_FACTOR_TOL


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
