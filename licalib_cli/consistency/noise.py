"""Sensor noise measured from the data alone, independently of the calibration model.

A consistency check compares the fit's residuals with the noise the sensors actually have; a
noise figure from a datasheet (or a default) is often off by a factor of two, and a real IMU
filters its output, so its noise at the sample rate is not the datasheet density times the root
of the rate. The estimates here use only smoothness, never the sensor models:

* IMU: each axis of the gyro (accelerometer) is fitted on its own with the functions the
  trajectory spline can produce for it: the first (second) derivative of a cubic B-spline with
  the calibration's knot spacing. What the free fit cannot explain is noise in the band the
  calibration's residuals live in; its variance, corrected for the fitted coordinates, is the
  noise variance. A calibration model that explains the data as well as this free fit has
  residuals of the same size; a model that lacks an effect has larger ones.
* LiDAR range: consecutive returns of one beam along its sweep lie on locally smooth surfaces;
  the second difference of the range over three consecutive azimuths is noise (times sqrt(6))
  except at edges, which a median absolute deviation ignores. Per-beam intrinsic errors are
  constant along a beam and cancel, so this is the noise without any model error.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import scipy.sparse.linalg as spla

from licalib_cli.spline import R3Spline, UniformKnots

__all__ = ["NoiseEstimate", "imu_noise", "line_range_noise", "range_noise"]

F64 = npt.NDArray[np.float64]

_MAD_TO_SIGMA = 1.4826


@dataclass(frozen=True)
class NoiseEstimate:
    """Noise standard deviation measured from the data.

    Attributes:
        sigma: (k,) standard deviation per axis (or per beam), in the data's unit.
        samples: number of values that entered the estimate.
        method: how it was measured, in words.
    """

    sigma: F64
    samples: int
    method: str

    @property
    def overall(self) -> float:
        """Root mean square of ``sigma`` over the axes with an estimate."""
        s = self.sigma[np.isfinite(self.sigma)]
        return float(np.sqrt(np.mean(s**2))) if s.size else float("nan")


def imu_noise(
    t_s: npt.ArrayLike, values: npt.ArrayLike, knot_spacing_s: float, derivative: int
) -> NoiseEstimate:
    """White-noise standard deviation of an IMU signal per axis, from a free spline fit.

    Args:
        t_s: (N,) sample times, seconds.
        values: (N, 3) readings (rad/s or m/s^2).
        knot_spacing_s: knot spacing of the calibration's trajectory spline, s.
        derivative: 1 for a gyro (angular rate of a rotation spline), 2 for an accelerometer
            (second derivative of a position spline).

    Returns:
        The estimate (NaN per axis with too few samples).
    """
    t = np.asarray(t_s, dtype=np.float64).reshape(-1)
    y = np.asarray(values, dtype=np.float64).reshape(t.shape[0], -1)
    if t.shape[0] < 20:
        return NoiseEstimate(np.full(y.shape[1], np.nan), int(t.shape[0]), "too few samples")
    knots = UniformKnots.for_interval(float(t[0]), float(t[-1]), knot_spacing_s)
    design = R3Spline(knots, np.zeros((knots.num_control_points, 3))).design_matrix(t, derivative)
    # The derivative removes the constant (and linear) part of the basis: holding the first
    # control point(s) at zero removes that null space without changing the fitted functions.
    design = design.tocsc()[:, derivative:]
    solve = spla.factorized((design.T @ design).tocsc())
    fitted = np.column_stack([design @ solve(design.T @ y[:, j]) for j in range(y.shape[1])])
    resid = y - fitted
    dof = t.shape[0] - (knots.num_control_points - derivative)
    sigma = np.sqrt(np.sum(resid**2, axis=0) / max(dof, 1))
    return NoiseEstimate(
        sigma,
        int(t.shape[0]),
        f"residual of a free spline fit per axis (knot spacing {knot_spacing_s:g} s)",
    )


_PACKED_GROUPS = 1 << 20
"""Most (scan, beam) groups that :func:`range_noise` sorts as one packed float key."""


def range_noise(
    scan_index: npt.ArrayLike,
    beam: npt.ArrayLike,
    azimuth: npt.ArrayLike,
    rho: npt.ArrayLike,
    num_beams: int,
    max_step_factor: float = 1.5,
) -> NoiseEstimate:
    """Range noise per beam from second differences along each beam's sweep.

    Args:
        scan_index: (N,) index of the sweep each return belongs to.
        beam: (N,) beam index in ``[0, num_beams)``.
        azimuth: (N,) azimuth, rad.
        rho: (N,) range, m.
        num_beams: number of beams.
        max_step_factor: a triple is used only when both azimuth steps are within this factor
            of the beam's median step (no gap, no dropped return in between).

    Returns:
        The estimate, one sigma per beam (NaN for beams with fewer than 30 usable triples).
    """
    scan = np.asarray(scan_index, dtype=np.int64).reshape(-1)
    b = np.asarray(beam, dtype=np.int64).reshape(-1)
    az = np.mod(np.asarray(azimuth, dtype=np.float64).reshape(-1), 2 * np.pi)
    r = np.asarray(rho, dtype=np.float64).reshape(-1)
    beams = max(num_beams, int(b.max()) + 1) if b.size else num_beams
    groups = (int(scan.max()) + 1) * beams if scan.size else 0
    if 0 < groups < _PACKED_GROUPS and scan.min() >= 0 and b.min() >= 0:
        # (scan, beam, azimuth) as one float: the azimuth, below 8, in the group's own interval
        # of 8; one stable sort of it is what lexsort of the three keys gives, in a third of
        # the time (resolution at the largest key: 2e-9 rad).
        order = np.argsort((scan * beams + b) * 8.0 + az, kind="stable")
    else:
        order = np.lexsort((az, b, scan))
    scan, b, az, r = scan[order], b[order], az[order], r[order]
    same = (scan[:-2] == scan[2:]) & (b[:-2] == b[2:])
    step1 = az[1:-1] - az[:-2]
    step2 = az[2:] - az[1:-1]
    sigma = np.full(num_beams, np.nan)
    if not np.any(same):
        return NoiseEstimate(sigma, 0, "no consecutive returns")
    beam_of = b[:-2]
    pos_steps = np.concatenate([step1[same & (step1 > 0)], np.zeros(0)])
    if pos_steps.size == 0:
        return NoiseEstimate(sigma, 0, "no consecutive returns")
    median_step = float(np.median(pos_steps))
    ok = (
        same
        & (step1 > 0)
        & (step2 > 0)
        & (step1 < max_step_factor * median_step)
        & (step2 < max_step_factor * median_step)
    )
    d2 = r[2:] - 2.0 * r[1:-1] + r[:-2]
    d2, beam_of = d2[ok], beam_of[ok]
    # Range changes smoothly with azimuth on a surface; the curvature term is removed by the
    # median of the beam (it is the same sign over long stretches only on cylinders).
    counts = np.bincount(beam_of, minlength=num_beams)
    if d2.size:
        srt = np.argsort(beam_of, kind="stable")
        d2s, bs = d2[srt], beam_of[srt]
        bounds = np.searchsorted(bs, np.arange(num_beams + 1))
        for i in range(num_beams):  # loop over beams, not points
            seg = d2s[bounds[i] : bounds[i + 1]]
            if seg.size >= 30:
                sigma[i] = _trimmed_sigma(seg) / np.sqrt(6.0)
    return NoiseEstimate(
        sigma,
        int(counts.sum()),
        "second differences of the range along each beam (variance within 3 sigma)",
    )


def line_range_noise(
    scan_index: npt.ArrayLike,
    line: npt.ArrayLike,
    t_ns: npt.ArrayLike,
    xyz: npt.ArrayLike,
    num_lines: int,
    max_step_factor: float = 1.5,
) -> NoiseEstimate:
    """Range noise per line of a non-repetitive scanner, from second differences along each
    line's point order.

    A line of such a scanner (a Livox ``line``) is one laser tracing a continuous curve, so
    its consecutive returns in time are neighbours on the surfaces as a spinning beam's
    consecutive azimuths are (:func:`range_noise`); their elevations differ, which an
    azimuth order would mix up.

    Args:
        scan_index: (N,) index of the sweep each return belongs to.
        line: (N,) line index in ``[0, num_lines)``.
        t_ns: (N,) time of each return, ns.
        xyz: (N, 3) points, m.
        num_lines: number of lines.
        max_step_factor: a triple is used only when both angular steps between consecutive
            rays are within this factor of the line's median step.

    Returns:
        The estimate, one sigma per line (NaN for lines with fewer than 30 usable triples).
    """
    scan = np.asarray(scan_index, dtype=np.int64).reshape(-1)
    b = np.asarray(line, dtype=np.int64).reshape(-1)
    t = np.asarray(t_ns, dtype=np.int64).reshape(-1)
    p = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    sigma = np.full(num_lines, np.nan)
    order = np.lexsort((t, b, scan))
    scan, b, p = scan[order], b[order], p[order]
    r = np.linalg.norm(p, axis=1)
    u = p / np.maximum(r, 1e-9)[:, None]
    same = (scan[:-2] == scan[2:]) & (b[:-2] == b[2:])
    if not np.any(same):
        return NoiseEstimate(sigma, 0, "no consecutive returns")
    step = np.arccos(np.clip(np.einsum("ij,ij->i", u[1:], u[:-1]), -1.0, 1.0))
    step1, step2 = step[:-1], step[1:]
    beam_of = b[:-2]
    median = np.full(num_lines, np.nan)
    usable = same & (step1 > 0)
    for i in range(num_lines):  # loop over lines (a few), not points
        s = step1[usable & (beam_of == i)]
        if s.size:
            median[i] = float(np.median(s))
    limit = max_step_factor * median[np.clip(beam_of, 0, num_lines - 1)]
    ok = usable & (step2 > 0) & (step1 < limit) & (step2 < limit)
    d2 = (r[2:] - 2.0 * r[1:-1] + r[:-2])[ok]
    beam_of = beam_of[ok]
    for i in range(num_lines):
        seg = d2[beam_of == i]
        if seg.size >= 30:
            sigma[i] = _trimmed_sigma(seg) / np.sqrt(6.0)
    return NoiseEstimate(
        sigma,
        int(d2.size),
        "second differences of the range along each line's point order (variance within 3 sigma)",
    )


# Variance of a unit normal truncated to +-3: 1 - 2 * 3 * phi(3) / (2 * Phi(3) - 1).
_TRUNCATED_VARIANCE_3 = 0.973339
_TRIM_SIGMAS = 3.0


def _trimmed_sigma(values: npt.NDArray[np.float64]) -> float:
    """Spread of ``values`` about their median: the median absolute deviation, then (three
    times) the mean square within 3 of that spread, divided by a normal's truncated variance.

    The median absolute deviation is inflated by the few second differences that span an edge
    (1.5 % on a 10 s VLP-16 shake); the trimmed variance, 0.7 %. The map planes'
    errors-in-variables correction subtracts this variance, so its error is what matters.
    """
    dev = np.abs(values - np.median(values))
    sigma = _MAD_TO_SIGMA * float(np.median(dev))
    for _ in range(3):
        inside = dev[dev < _TRIM_SIGMAS * sigma]
        if inside.size < 30:
            break
        sigma = float(np.sqrt(np.mean(inside**2) / _TRUNCATED_VARIANCE_3))
    return sigma
