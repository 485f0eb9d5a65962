"""Coarse time offset by cross-correlating angular speed from the gyro and from LiDAR odometry.

Conventions:
    - ``time_offset_s``: a LiDAR stamp ``tau`` corresponds to IMU time ``t = tau + time_offset_s``
      (the IMU sees an event ``time_offset_s`` later on its clock than the LiDAR does).
    - The LiDAR angular speed is ``|log(R_k^T R_{k+1})| / (t_{k+1} - t_k)`` at the interval
      midpoints, i.e. the mean rotation rate over each pose interval. The gyro signal is made
      comparable by averaging the gyro *vector* over a window of the same length (the exact
      integral of the rate, linear between samples) before taking its norm.
    - Both signals are resampled on one uniform grid (``rate_hz``) of absolute time; the
      normalised (Pearson) correlation is evaluated for every lag within ``+-max_lag_s`` over the
      overlap of the two signals, using FFT sums; the peak is refined by a parabola.
    - A whole-bag clock difference (for example LiDAR stamps on UNIX time and IMU stamps on boot
      time) is estimated separately by :func:`estimate_clock_shift`; it is a property of the
      recording, not a calibration result.
    - Times are int64 nanoseconds at the interface; float seconds inside.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import numpy as np
import numpy.typing as npt

from licalib_cli.errors import ExcitationError, TimestampError
from licalib_cli.measurements import ImuSamples
from licalib_cli.odometry import PoseSeries

__all__ = [
    "ClockShift",
    "TimeOffsetConfig",
    "TimeOffsetEstimate",
    "angular_speed_from_gyro",
    "angular_speed_from_poses",
    "correlate_angular_speed",
    "estimate_clock_shift",
    "estimate_time_offset",
    "estimate_time_offset_joint",
]

logger = logging.getLogger(__name__)

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


@dataclass(frozen=True)
class TimeOffsetConfig:
    """Settings of the angular-speed cross-correlation.

    Attributes:
        rate_hz: rate of the common resampling grid, Hz.
        max_lag_s: lags searched are within ``+-max_lag_s``; raise it (seconds or more) when the
            sensors may be far apart.
        min_peak_correlation: peaks below this normalised correlation are flagged not ok.
        min_speed_std: an angular-speed signal whose standard deviation over the overlap is
            below this (rad/s) is considered flat (no usable motion).
        min_overlap_fraction: a lag is only evaluated if the two signals overlap over at least
            this fraction of the shorter one.
    """

    rate_hz: float = 100.0
    max_lag_s: float = 0.2
    min_peak_correlation: float = 0.7
    min_speed_std: float = 0.05
    min_overlap_fraction: float = 0.5


@dataclass(frozen=True)
class TimeOffsetEstimate:
    """Result of the cross-correlation.

    Attributes:
        time_offset_s: ``t_imu = t_lidar + time_offset_s``, seconds.
        peak_correlation: normalised correlation at the peak, in [-1, 1].
        ok: True when the peak is high enough and not at the edge of the lag window.
        reason: why ``ok`` is False ("" when ok).
        lags_s: (L,) lags evaluated, seconds.
        correlation: (L,) normalised correlation per lag (NaN where the overlap is too short).
    """

    time_offset_s: float
    peak_correlation: float
    ok: bool
    reason: str
    lags_s: FloatArray
    correlation: FloatArray


@dataclass(frozen=True)
class ClockShift:
    """Whole-bag clock difference between the sensors (not a calibration result).

    Attributes:
        shift_ns: ``t_imu = t_lidar + shift_ns`` to apply to LiDAR stamps before calibrating,
            nanoseconds (0 when the stamp ranges already overlap).
        method: "none" (stamp ranges overlap), "correlation" (start difference refined by the
            angular-speed correlation) or "stamp_ranges" (start difference only; the
            correlation was inconclusive).
        peak_correlation: correlation at the refined shift, NaN when not computed.
        overlap_fraction: overlap of the raw stamp ranges relative to the shorter one.
    """

    shift_ns: int
    method: str
    peak_correlation: float
    overlap_fraction: float


def angular_speed_from_poses(poses: PoseSeries) -> tuple[IntArray, FloatArray]:
    """Mean angular speed over each pose interval.

    Args:
        poses: K >= 2 poses with strictly increasing stamps.

    Returns:
        (K-1,) int64 interval midpoints (ns) and (K-1,) float64 speeds (rad/s).

    Raises:
        TimestampError: fewer than two poses or stamps not increasing.
    """
    t = poses.t_ns
    if t.shape[0] < 2 or np.any(np.diff(t) <= 0):
        msg = "Angular speed from odometry needs at least two poses with increasing stamps."
        raise TimestampError(msg)
    rot = poses.rotations
    angle = (rot[:-1].inv() * rot[1:]).magnitude()
    dt = np.diff(t).astype(np.float64) * 1e-9
    mid = t[:-1] + np.diff(t) // 2
    return mid, np.asarray(angle / dt, dtype=np.float64)


def _gyro_integral(imu: ImuSamples) -> tuple[FloatArray, FloatArray]:
    """Cumulative trapezoidal integral of the gyro vector: times (s, rel. to first) and (N, 3)."""
    t = (imu.t_ns - imu.t_ns[0]).astype(np.float64) * 1e-9
    dt = np.diff(t)
    inc = 0.5 * (imu.gyro[1:] + imu.gyro[:-1]) * dt[:, None]
    return t, np.concatenate([np.zeros((1, 3)), np.cumsum(inc, axis=0)])


def angular_speed_from_gyro(imu: ImuSamples, t_ns: IntArray, window_s: float) -> FloatArray:
    """Gyro angular speed ``|mean(w)|`` over a window centred at each query time.

    Args:
        imu: IMU samples, strictly increasing stamps.
        t_ns: (M,) int64 query times, nanoseconds (clamped to the IMU range).
        window_s: averaging window, seconds (0 gives the interpolated ``|w|``).

    Returns:
        (M,) float64 rad/s.
    """
    t_rel = (np.asarray(t_ns) - imu.t_ns[0]).astype(np.float64) * 1e-9
    if window_s <= 0.0:
        t_imu = (imu.t_ns - imu.t_ns[0]).astype(np.float64) * 1e-9
        w = np.stack([np.interp(t_rel, t_imu, imu.gyro[:, j]) for j in range(3)], axis=1)
        return np.asarray(np.linalg.norm(w, axis=1), dtype=np.float64)
    tg, cum = _gyro_integral(imu)
    lo = np.clip(t_rel - 0.5 * window_s, tg[0], tg[-1])
    hi = np.clip(t_rel + 0.5 * window_s, tg[0], tg[-1])
    span = np.maximum(hi - lo, 1e-12)
    delta = np.stack(
        [np.interp(hi, tg, cum[:, j]) - np.interp(lo, tg, cum[:, j]) for j in range(3)], axis=1
    )
    return np.asarray(np.linalg.norm(delta, axis=1) / span, dtype=np.float64)


def _to_grid(
    t_ns: IntArray, x: FloatArray, t0_ns: int, h_ns: float, n: int
) -> tuple[FloatArray, FloatArray]:
    """Linear resampling of ``x(t)`` on the grid ``t0 + i h``; the mask is 1 inside its range."""
    grid = np.arange(n) * h_ns  # relative to t0, float64 stays exact enough (< 1 ns)
    rel = (np.asarray(t_ns) - t0_ns).astype(np.float64)
    inside = (grid >= rel[0]) & (grid <= rel[-1])
    vals = np.where(inside, np.interp(grid, rel, x), 0.0)
    return vals, inside.astype(np.float64)


def _full_correlation(v: FloatArray, u: FloatArray) -> FloatArray:
    """``scipy.signal.correlate(v, u, "full")`` for equal-length real signals, by FFT.

    Entry ``k`` is ``sum_i v[i + k - (n - 1)] u[i]`` (lags ``-(n-1) .. n-1``).
    """
    n = v.shape[0]
    size = 1 << int(np.ceil(np.log2(max(2 * n - 1, 1))))
    spec = np.fft.rfft(v, size) * np.conj(np.fft.rfft(u, size))
    circ = np.fft.irfft(spec, size)
    return np.concatenate([circ[size - (n - 1) :], circ[:n]]) if n > 1 else circ[:1]


def correlate_angular_speed(
    t_lidar_ns: IntArray,
    speed_lidar: FloatArray,
    t_imu_ns: IntArray,
    speed_imu: FloatArray,
    cfg: TimeOffsetConfig | None = None,
) -> TimeOffsetEstimate:
    """Normalised cross-correlation of two angular-rate signals on different clocks.

    Finds ``c`` maximising the correlation of ``speed_lidar(tau)`` with ``speed_imu(tau + c)``.
    The signals are scalar speeds (A,) / (B,) or vectors (A, k) / (B, k) in a common frame; for
    vectors the covariances and variances of the components are summed.

    Args:
        t_lidar_ns: (A,) int64 increasing sample times of the LiDAR signal, LiDAR clock.
        speed_lidar: (A,) or (A, k) float64 rad/s.
        t_imu_ns: (B,) int64 increasing sample times of the IMU signal, IMU clock.
        speed_imu: (B,) or (B, k) float64 rad/s.
        cfg: settings; defaults when None.

    Returns:
        The offset in the convention ``t_imu = t_lidar + time_offset_s``.

    Raises:
        ExcitationError: either signal is flat (no varying rotation).
        TimestampError: the signals cannot overlap within the lag window.
    """
    cfg = cfg or TimeOffsetConfig()
    sig_a = np.asarray(speed_lidar, dtype=np.float64)
    sig_b = np.asarray(speed_imu, dtype=np.float64)
    sig_a = sig_a[:, None] if sig_a.ndim == 1 else sig_a
    sig_b = sig_b[:, None] if sig_b.ndim == 1 else sig_b
    h_ns = 1e9 / cfg.rate_hz
    max_lag = int(np.ceil(cfg.max_lag_s * cfg.rate_hz))
    t0 = int(min(t_lidar_ns[0], t_imu_ns[0]))
    t1 = int(max(t_lidar_ns[-1], t_imu_ns[-1]))
    n = int((t1 - t0) // h_ns) + 1
    if n > 50_000_000:
        msg = (
            "The IMU and LiDAR stamps are too far apart to correlate on one grid; estimate the "
            "whole-bag clock shift first (estimate_clock_shift)."
        )
        raise TimestampError(msg)
    std_a = float(np.sqrt(np.sum(np.var(sig_a, axis=0))))
    std_b = float(np.sqrt(np.sum(np.var(sig_b, axis=0))))
    if std_a < cfg.min_speed_std or std_b < cfg.min_speed_std:
        msg = (
            "Rotation excitation is too weak for the time offset: the angular rate hardly varies "
            f"(std {std_a:.3f} rad/s LiDAR, {std_b:.3f} rad/s IMU, need {cfg.min_speed_std:g}); "
            "rotate the rig with changing speed during the recording."
        )
        raise ExcitationError(msg)
    scale_a = max(float(np.abs(sig_a).max()), 1e-12)
    scale_b = max(float(np.abs(sig_b).max()), 1e-12)

    def xc(u: FloatArray, v: FloatArray) -> FloatArray:
        """sum_i u[i] v[i + L] for L = -(n-1) .. n-1."""
        return _full_correlation(v, u)

    lags = np.arange(-(n - 1), n)
    sel = np.abs(lags) <= max_lag
    ma = mb = None
    cnt = s_ab_sum = var_a_sum = var_b_sum = None
    for j in range(sig_a.shape[1]):  # loop over the (at most 3) components
        a, ma = _to_grid(t_lidar_ns, sig_a[:, j] / scale_a, t0, h_ns, n)
        b, mb = _to_grid(t_imu_ns, sig_b[:, j] / scale_b, t0, h_ns, n)
        if cnt is None:
            cnt = np.rint(xc(ma, mb))[sel]
        cnt_safe = np.where(cnt > 0, cnt, 1.0)
        s_a = xc(a, mb)[sel]
        s_b = xc(ma, b)[sel]
        var_a = (xc(a * a, mb)[sel] - s_a**2 / cnt_safe) / cnt_safe
        var_b = (xc(ma, b * b)[sel] - s_b**2 / cnt_safe) / cnt_safe
        cov = (xc(a, b)[sel] - s_a * s_b / cnt_safe) / cnt_safe
        s_ab_sum = cov if s_ab_sum is None else s_ab_sum + cov
        var_a_sum = var_a if var_a_sum is None else var_a_sum + var_a
        var_b_sum = var_b if var_b_sum is None else var_b_sum + var_b
    assert cnt is not None and ma is not None and mb is not None
    assert s_ab_sum is not None and var_a_sum is not None and var_b_sum is not None
    lags = lags[sel]
    need = cfg.min_overlap_fraction * min(ma.sum(), mb.sum())
    valid = cnt >= max(need, 3.0)
    if not np.any(valid):
        msg = (
            "The IMU and LiDAR angular-speed signals do not overlap within the lag window of "
            f"+-{cfg.max_lag_s:g} s; estimate the whole-bag clock shift first or raise max_lag_s."
        )
        raise TimestampError(msg)
    with np.errstate(invalid="ignore", divide="ignore"):
        r = s_ab_sum / np.sqrt(var_a_sum * var_b_sum)
    r = np.where(valid & (var_a_sum > 0) & (var_b_sum > 0), r, np.nan)
    if np.all(np.isnan(r)):
        msg = "The angular-speed signals are constant over every overlap; rotate the rig."
        raise ExcitationError(msg)
    i = int(np.nanargmax(r))
    frac = 0.0
    if 0 < i < r.size - 1 and np.isfinite(r[i - 1]) and np.isfinite(r[i + 1]):
        den = r[i - 1] - 2.0 * r[i] + r[i + 1]
        if den < 0.0:
            frac = float(np.clip(0.5 * (r[i - 1] - r[i + 1]) / den, -0.5, 0.5))
    offset = (lags[i] + frac) * h_ns * 1e-9
    peak = float(r[i])
    reason = ""
    if abs(lags[i]) >= max_lag:
        reason = f"the peak is at the edge of the +-{cfg.max_lag_s:g} s lag window"
    elif peak < cfg.min_peak_correlation:
        reason = f"the peak correlation {peak:.2f} is below {cfg.min_peak_correlation:g}"
    logger.info("time offset %.4f s (peak correlation %.3f) %s", offset, peak, reason)
    return TimeOffsetEstimate(
        time_offset_s=float(offset),
        peak_correlation=peak,
        ok=not reason,
        reason=reason,
        lags_s=np.asarray(lags * h_ns * 1e-9, dtype=np.float64),
        correlation=r,
    )


def angular_velocity_from_poses(poses: PoseSeries) -> tuple[IntArray, FloatArray]:
    """Mean body angular velocity of the LiDAR over each pose interval.

    Returns:
        (K-1,) int64 interval midpoints (ns) and (K-1, 3) rad/s in the LiDAR frame.
    """
    t = poses.t_ns
    if t.shape[0] < 2 or np.any(np.diff(t) <= 0):
        msg = "Angular velocity from odometry needs at least two poses with increasing stamps."
        raise TimestampError(msg)
    rot = poses.rotations
    rotvec = (rot[:-1].inv() * rot[1:]).as_rotvec()
    dt = np.diff(t).astype(np.float64) * 1e-9
    return t[:-1] + np.diff(t) // 2, np.asarray(rotvec / dt[:, None], dtype=np.float64)


def angular_velocity_from_gyro(imu: ImuSamples, t_ns: IntArray, window_s: float) -> FloatArray:
    """Gyro angular velocity averaged over a window centred at each query time, (M, 3) rad/s."""
    t_rel = (np.asarray(t_ns) - imu.t_ns[0]).astype(np.float64) * 1e-9
    tg, cum = _gyro_integral(imu)
    lo = np.clip(t_rel - 0.5 * window_s, tg[0], tg[-1])
    hi = np.clip(t_rel + 0.5 * window_s, tg[0], tg[-1])
    span = np.maximum(hi - lo, 1e-12)
    delta = np.stack(
        [np.interp(hi, tg, cum[:, j]) - np.interp(lo, tg, cum[:, j]) for j in range(3)], axis=1
    )
    return np.asarray(delta / span[:, None], dtype=np.float64)


def estimate_time_offset_aligned(
    imu: ImuSamples,
    poses: PoseSeries,
    R_imu_lidar: FloatArray,
    cfg: TimeOffsetConfig | None = None,
) -> TimeOffsetEstimate:
    """Coarse time offset from the angular-velocity *vectors* once the rotation is known.

    The LiDAR body rate from odometry is rotated into the IMU frame with ``R_imu_lidar`` and
    correlated component-wise with the gyro. Unlike the angular speed, this works when the
    speed is nearly constant but the rotation axis changes (e.g. a tumbling motion).

    Args:
        imu: IMU samples (gyro in rad/s).
        poses: LiDAR odometry poses.
        R_imu_lidar: (3, 3) extrinsic rotation (LiDAR vectors -> IMU frame).
        cfg: settings; defaults when None.

    Returns:
        ``t_imu = t_lidar + time_offset_s``, with the peak correlation and a quality flag.
    """
    cfg = cfg or TimeOffsetConfig()
    t_mid, w_lidar = angular_velocity_from_poses(poses)
    w_lidar_imu = w_lidar @ np.asarray(R_imu_lidar, dtype=np.float64).T
    window_s = float(np.median(np.diff(poses.t_ns))) * 1e-9
    h_ns = 1e9 / cfg.rate_hz
    n = int((imu.t_ns[-1] - imu.t_ns[0]) // h_ns) + 1
    t_grid = imu.t_ns[0] + np.rint(np.arange(n) * h_ns).astype(np.int64)
    w_imu = angular_velocity_from_gyro(imu, t_grid, window_s)
    return correlate_angular_speed(t_mid, w_lidar_imu, t_grid, w_imu, cfg)


_JOINT_LAG_STEP_S = 0.001
_JOINT_MIN_INTERVALS = 10
_JOINT_TRIM_FACTOR = 3.0


def _procrustes_fit(w_imu: FloatArray, w_lidar: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Best rotations ``w_imu ~ R w_lidar`` for a batch of lags.

    Args:
        w_imu: (L, K, 3) gyro rates at each lag.
        w_lidar: (K, 3) LiDAR rates.

    Returns:
        (L,) normalised fit ``sum w_imu . R w_lidar / sqrt(sum |w_imu|^2 sum |w_lidar|^2)`` and
        (L, 3, 3) the rotations.
    """
    m = np.einsum("lki,kj->lij", w_imu, w_lidar)
    u, sv, vt = np.linalg.svd(m)
    sign = np.sign(np.linalg.det(u @ vt))
    sv[:, 2] *= sign
    u[:, :, 2] *= sign[:, None]
    norm = np.sqrt(np.sum(w_imu**2, axis=(1, 2)) * np.sum(w_lidar**2))
    return sv.sum(axis=1) / np.maximum(norm, 1e-300), u @ vt


def estimate_time_offset_joint(
    imu: ImuSamples,
    poses: PoseSeries,
    cfg: TimeOffsetConfig | None = None,
) -> tuple[TimeOffsetEstimate, FloatArray]:
    """Coarse time offset and rotation together, from the angular-velocity vectors.

    For every lag ``c`` within ``+-max_lag_s`` (1 ms steps) the rotation best mapping the LiDAR
    body rates onto the gyro rates at ``tau + c`` is solved in closed form (Procrustes) and the
    lag with the best fit wins (refined by a parabola). Solving the rotation first at a zero
    offset and correlating afterwards is biased: when the rotation axis turns steadily (a
    constant yaw rate with rocking), a small rotation of the extrinsic mimics a time shift, so
    that rotation absorbs much of the offset. Intervals whose fit is much worse than the median
    (odometry glitches) are dropped once.

    Args:
        imu: IMU samples (gyro in rad/s).
        poses: LiDAR odometry poses.
        cfg: settings; defaults when None.

    Returns:
        The estimate (``peak_correlation`` is the normalised fit at the best lag) and the (3, 3)
        rotation ``R_imu_lidar`` at that lag.

    Raises:
        ExcitationError: too few intervals, or the LiDAR rate hardly varies.
    """
    cfg = cfg or TimeOffsetConfig()
    t_mid, w_lidar = angular_velocity_from_poses(poses)
    window_s = float(np.median(np.diff(poses.t_ns))) * 1e-9
    t_rel = (t_mid - imu.t_ns[0]).astype(np.float64) * 1e-9
    span = float(imu.t_ns[-1] - imu.t_ns[0]) * 1e-9
    reach = cfg.max_lag_s + 0.5 * window_s
    inside = (t_rel - reach >= 0.0) & (t_rel + reach <= span)
    if np.count_nonzero(inside) < _JOINT_MIN_INTERVALS:
        msg = (
            f"Only {np.count_nonzero(inside)} odometry intervals lie inside the IMU data within "
            f"+-{cfg.max_lag_s:g} s; record longer or check the clock offset between the sensors."
        )
        raise ExcitationError(msg)
    t_mid, w_lidar = t_mid[inside], w_lidar[inside]
    if float(np.sqrt(np.sum(np.var(w_lidar, axis=0)))) < cfg.min_speed_std:
        msg = (
            "Rotation excitation is too weak for the time offset: the LiDAR angular velocity "
            "hardly varies; rotate the rig with changing speed during the recording."
        )
        raise ExcitationError(msg)
    n_lag = int(np.ceil(cfg.max_lag_s / _JOINT_LAG_STEP_S))
    lags = np.arange(-n_lag, n_lag + 1) * _JOINT_LAG_STEP_S
    lag_ns = np.rint(lags * 1e9).astype(np.int64)
    queries = (t_mid[None, :] + lag_ns[:, None]).reshape(-1)
    w_imu = angular_velocity_from_gyro(imu, queries, window_s).reshape(lags.size, -1, 3)
    keep = np.ones(t_mid.shape[0], dtype=bool)
    fit, rots = _procrustes_fit(w_imu, w_lidar)
    i = int(np.argmax(fit))
    err = np.linalg.norm(w_imu[i] - w_lidar @ rots[i].T, axis=1)
    trimmed = err <= _JOINT_TRIM_FACTOR * max(float(np.median(err)), 1e-9)
    if not trimmed.all() and np.count_nonzero(trimmed) >= _JOINT_MIN_INTERVALS:
        keep = trimmed
        fit, rots = _procrustes_fit(w_imu[:, keep], w_lidar[keep])
        i = int(np.argmax(fit))
    frac = 0.0
    if 0 < i < fit.size - 1:
        den = fit[i - 1] - 2.0 * fit[i] + fit[i + 1]
        if den < 0.0:
            frac = float(np.clip(0.5 * (fit[i - 1] - fit[i + 1]) / den, -0.5, 0.5))
    offset = lags[i] + frac * _JOINT_LAG_STEP_S
    peak = float(fit[i])
    reason = ""
    if i in (0, fit.size - 1):
        reason = f"the best fit is at the edge of the +-{cfg.max_lag_s:g} s lag window"
    elif peak < cfg.min_peak_correlation:
        reason = f"the best fit {peak:.2f} is below {cfg.min_peak_correlation:g}"
    logger.info(
        "time offset and rotation together: %.4f s (fit %.4f, %d/%d intervals) %s",
        offset,
        peak,
        np.count_nonzero(keep),
        keep.size,
        reason,
    )
    est = TimeOffsetEstimate(
        time_offset_s=float(offset),
        peak_correlation=peak,
        ok=not reason,
        reason=reason,
        lags_s=np.asarray(lags, dtype=np.float64),
        correlation=fit,
    )
    return est, rots[i]


def estimate_time_offset(
    imu: ImuSamples,
    poses: PoseSeries,
    cfg: TimeOffsetConfig | None = None,
) -> TimeOffsetEstimate:
    """Coarse time offset from gyro and odometry angular speed.

    Args:
        imu: IMU samples (gyro in rad/s).
        poses: LiDAR odometry poses stamped with the times they refer to.
        cfg: settings; defaults when None.

    Returns:
        ``t_imu = t_lidar + time_offset_s``, with the peak correlation and a quality flag.

    Raises:
        ExcitationError: the rotation speed is flat in either sensor.
        TimestampError: the streams do not overlap within the lag window.
    """
    cfg = cfg or TimeOffsetConfig()
    t_mid, w_lidar = angular_speed_from_poses(poses)
    window_s = float(np.median(np.diff(poses.t_ns))) * 1e-9
    h_ns = 1e9 / cfg.rate_hz
    n = int((imu.t_ns[-1] - imu.t_ns[0]) // h_ns) + 1
    t_grid = imu.t_ns[0] + np.rint(np.arange(n) * h_ns).astype(np.int64)
    w_imu = angular_speed_from_gyro(imu, t_grid, window_s)
    # Drop the grid ends where the window is cut short.
    half = int(np.ceil(0.5 * window_s * 1e9 / h_ns))
    if n > 2 * half + 3:
        t_grid, w_imu = t_grid[half:-half], w_imu[half:-half]
    return correlate_angular_speed(t_mid, w_lidar, t_grid, w_imu, cfg)


def estimate_clock_shift(
    imu: ImuSamples,
    poses: PoseSeries,
    cfg: TimeOffsetConfig | None = None,
    *,
    max_search_s: float = 30.0,
    min_overlap_fraction: float = 0.5,
) -> ClockShift:
    """Whole-bag clock difference when the IMU and LiDAR stamp ranges do not overlap.

    When the raw stamp ranges overlap over at least ``min_overlap_fraction`` of the shorter
    stream, no shift is applied. Otherwise the starts are aligned (``shift = imu_start -
    lidar_start``) and the shift is refined by correlating angular speed over lags up to
    ``max_search_s`` (bounded by half the shorter stream), rounded to whole milliseconds. The
    remaining sub-millisecond part is left to :func:`estimate_time_offset` and the optimiser.

    Args:
        imu: IMU samples.
        poses: LiDAR odometry poses (LiDAR clock).
        cfg: correlation settings (its ``max_lag_s`` is replaced by the search range).
        max_search_s: largest refinement searched around the start alignment, seconds.
        min_overlap_fraction: stamp-range overlap regarded as "same clock".

    Returns:
        The shift to add to LiDAR stamps; ``method`` tells how it was found.
    """
    cfg = cfg or TimeOffsetConfig()
    i0, i1 = int(imu.t_ns[0]), int(imu.t_ns[-1])
    l0, l1 = int(poses.t_ns[0]), int(poses.t_ns[-1])
    shorter = max(min(i1 - i0, l1 - l0), 1)
    overlap = max(0, min(i1, l1) - max(i0, l0)) / shorter
    if overlap >= min_overlap_fraction:
        return ClockShift(0, "none", float("nan"), float(overlap))
    coarse = i0 - l0
    shifted = replace(poses, t_ns=poses.t_ns + np.int64(coarse))
    search = min(max_search_s, 0.5 * shorter * 1e-9)
    try:
        est = estimate_time_offset(
            imu, shifted, replace(cfg, max_lag_s=search, min_overlap_fraction=0.3)
        )
    except (ExcitationError, TimestampError) as err:
        logger.warning("clock shift from stamp ranges only (%s)", err)
        return ClockShift(int(coarse), "stamp_ranges", float("nan"), float(overlap))
    if not est.ok:
        logger.warning("clock shift from stamp ranges only (%s)", est.reason)
        return ClockShift(int(coarse), "stamp_ranges", est.peak_correlation, float(overlap))
    refine_ns = round(est.time_offset_s * 1e3) * 1_000_000
    logger.info(
        "clock shift %.3f s between LiDAR and IMU stamps (peak correlation %.2f)",
        (coarse + refine_ns) * 1e-9,
        est.peak_correlation,
    )
    return ClockShift(int(coarse + refine_ns), "correlation", est.peak_correlation, float(overlap))
