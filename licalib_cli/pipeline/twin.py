"""A twin recording: what the fitted model itself would measure, fitted and checked the same way.

``diagnose`` compares the residual statistics of a fit (chi-square per sample, RMS, the
patterns against angular rate, beam, range, ...) with those of a twin recording made from the
fitted model, so that "the data disagree with the model" means "they differ from what the fitted
model would produce", not "they differ from an assumed noise figure" (issue: the IMU's residuals
after a fit are below the noise because the trajectory spline absorbs some of it; the LiDAR's
because the surfel planes are fitted to the same points).

The twin has the recording's trajectory, sample times and rates, the fit's surfel map as the
world and the fitted noise levels:

* IMU: every sample is the fitted model's prediction at its time (the forward model of
  :mod:`licalib_cli.models.imu` on the fitted splines, biases, drifts and intrinsics, as the
  residual blocks evaluate it) plus white noise of the fitted sigma per axis.
* LiDAR: every associated ray (same beam, azimuth and time) is cast from the fitted pose onto
  its surfel plane; the twin's raw range is the hit distance plus range noise of the fitted
  sigma of its beam. The point-to-plane distance is affine in the raw range (the LiDAR model of
  :mod:`licalib_cli.models.lidar` is linear in it), so the hit is exact.

The twin is then fitted as the recording was, from the fitted state: each surfel's plane is
re-estimated from the twin's points mapped with the fitted state (as a round builds its map), and
the same problem (same free parameters, weights and priors) is solved for a few iterations; the
residual checks of :func:`licalib_cli.pipeline.fitcheck.sensor_checks` are computed at the twin's
estimate. Several realisations (fixed seeds) give the reference's mean and its spread.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterator
from dataclasses import dataclass, replace

import numpy as np
import numpy.typing as npt

from licalib_cli.estimation import (
    CalibrationState,
    ImuData,
    LidarPoints,
    Planes,
    build_problem,
    state_from_problem,
)
from licalib_cli.models.lidar import lidar_point
from licalib_cli.pipeline.fitcheck import beam_sigma, residual_table, sensor_checks
from licalib_cli.pipeline.points import query_times
from licalib_cli.pipeline.round import RoundInputs
from licalib_cli.pipeline.settings import NoiseLevels
from licalib_cli.residuals import PointToPlaneResidual
from licalib_cli.sections import SensorCheck
from licalib_cli.solver.lm import LMParams, solve

__all__ = [
    "TWIN_ITERATIONS",
    "TWIN_REALISATIONS",
    "Twin",
    "TwinSensor",
    "twin_checks",
    "twin_recordings",
]

logger = logging.getLogger(__name__)

F64 = npt.NDArray[np.float64]

TWIN_REALISATIONS = 2
"""Twin recordings per fit (their mean is the reference, their spread its uncertainty)."""

TWIN_ITERATIONS = 3
"""LM iterations of the twin's fit (it starts at its own optimum up to the noise)."""

MAX_TWIN_POINTS = 40_000
"""Points of a twin recording (a regular subset of the fit's associated points): the statistics
are means per residual, so their spread is about ``sqrt(2 / 40 000) = 0.007``; the fit's cost
grows with the points."""

MIN_RANGE_SLOPE = 0.05
"""Rays whose point-to-plane distance changes by less than this per metre of range (grazing
incidence) keep their range in the twin: the hit would be far away along the plane."""


@dataclass(frozen=True)
class TwinSensor:
    """One sensor's residual statistics on the twin recordings.

    Attributes:
        sensor: ``gyro``, ``accelerometer`` or ``lidar``.
        chi2_per_sample: mean over the realisations of the chi-square per residual.
        chi2_spread: standard deviation of that mean: the realisations' spread, at least the
            chi-square distribution's ``sqrt(2 chi2 / (n realisations))``.
        rms: mean residual RMS in the sensor's unit.
        check: the full check (patterns included) of the first realisation.
    """

    sensor: str
    chi2_per_sample: float
    chi2_spread: float
    rms: float
    check: SensorCheck


@dataclass(frozen=True)
class Twin:
    """The twin recordings of one fit.

    Attributes:
        sensors: per sensor, the twin's statistics (gyro, accelerometer, lidar).
        realisations: how many twin recordings were fitted.
        seconds: wall time, s.
    """

    sensors: tuple[TwinSensor, ...]
    realisations: int
    seconds: float

    def sensor(self, name: str) -> TwinSensor | None:
        """The twin's statistics of one sensor."""
        return next((s for s in self.sensors if s.sensor == name), None)


def _subset(inputs: RoundInputs, at_most: int) -> tuple[RoundInputs, npt.NDArray[np.intp]]:
    """``inputs`` with a regular subset of at most ``at_most`` points (planes unchanged), and
    the indices kept."""
    n = len(inputs.lidar)
    keep = np.arange(0, n, max(int(np.ceil(n / at_most)), 1))
    if keep.size == n:
        return inputs, keep
    return replace(inputs, lidar=inputs.lidar.subset(keep), points=inputs.points.subset(keep)), keep


@dataclass(frozen=True)
class _Model:
    """What every twin realisation of one fit shares: its predictions and ray geometry.

    ``p_g``, ``ray_g``, ``step`` and ``beam_sigma`` cover every associated point (the planes are
    re-fitted from all of them, as the fit's map was); ``fit_inputs`` and ``keep`` are the subset
    the twin is fitted and checked on.
    """

    fit_inputs: RoundInputs
    keep: npt.NDArray[np.intp]
    gyro_pred: F64
    accel_pred: F64
    rho: F64
    step: F64
    p_g: F64
    ray_g: F64
    beam_sigma: F64


def _model(state: CalibrationState, inputs: RoundInputs, noise: NoiseLevels) -> _Model:
    """The fitted model's prediction of every measurement of ``inputs``."""
    fit_inputs, keep = _subset(inputs, MAX_TWIN_POINTS)
    table = residual_table(state, fit_inputs)
    # every ray in {G}: the recorded point and the change per metre of raw range (the LiDAR
    # model is linear in the range), so the hit on its plane is exact
    sample = inputs.points
    t = query_times(state, sample)
    rot = state.so3_spline.rotation(t)
    p_l = lidar_point(state.lidar_intrinsics, sample.beam, sample.rho, sample.theta)
    p_l1 = lidar_point(state.lidar_intrinsics, sample.beam, sample.rho + 1.0, sample.theta)
    p_i = (p_l + sample.model_gap) @ state.R_imu_lidar.T + state.t_imu_lidar
    p_g = np.einsum("nij,nj->ni", rot, p_i) + state.r3_spline.position(t)
    ray_g = np.einsum("nij,nj->ni", rot, (p_l1 - p_l) @ state.R_imu_lidar.T)
    plane = np.asarray(inputs.lidar.plane, dtype=np.intp)
    normal = np.asarray(inputs.planes.normal, dtype=np.float64)[plane]
    d0 = np.einsum("ij,ij->i", normal, p_g) + np.asarray(inputs.planes.d)[plane]
    slope = np.einsum("ij,ij->i", normal, ray_g)  # d(distance)/d(range)
    ok = np.abs(slope) >= MIN_RANGE_SLOPE
    step = np.where(ok, -d0 / np.where(ok, slope, 1.0), 0.0)
    return _Model(
        fit_inputs=fit_inputs,
        keep=keep,
        gyro_pred=table.angular_rate,
        accel_pred=table.specific_force,
        rho=np.asarray(sample.rho, dtype=np.float64),
        step=step,
        p_g=p_g,
        ray_g=ray_g,
        beam_sigma=beam_sigma(noise, state.lidar_intrinsics.num_beams)[np.asarray(sample.beam)],
    )


def _twin_inputs(
    model: _Model,
    planes: Planes,
    plane: npt.NDArray[np.intp],
    noise: NoiseLevels,
    rng: np.random.Generator,
) -> RoundInputs:
    """One twin recording: the predictions plus noise of the fitted levels, re-fitted planes."""
    inputs = model.fit_inputs
    imu = inputs.imu
    gyro = model.gyro_pred + rng.standard_normal(imu.gyro.shape) * noise.gyro_sigma
    accel = model.accel_pred + rng.standard_normal(imu.accel.shape) * noise.accel_sigma
    move = model.step + rng.standard_normal(model.rho.shape[0]) * model.beam_sigma
    p_twin = model.p_g + move[:, None] * model.ray_g
    lidar = replace(inputs.lidar, rho=(model.rho + move)[model.keep])
    return replace(
        inputs,
        imu=ImuData(t_s=imu.t_s, gyro=gyro, accel=accel),
        lidar=lidar,
        points=replace(inputs.points, rho=lidar.rho),
        planes=_refit_planes(planes, plane, p_twin),
    )


def _distances(state: CalibrationState, inputs: RoundInputs, lidar: LidarPoints) -> F64:
    problem = build_problem(state, inputs.imu, lidar, inputs.planes, inputs.noise, inputs.free)
    block = next(b for b in problem.residual_blocks if isinstance(b, PointToPlaneResidual))
    return block.distances(problem.values())


def _refit_planes(planes: Planes, plane: npt.NDArray[np.intp], p_g: F64) -> Planes:
    """Each plane re-estimated from its points ``p_g`` in ``{G}`` (centroid and the normal of
    least variance, as the surfel map is built); planes with fewer than 3 points keep theirs."""
    normal0 = np.asarray(planes.normal, dtype=np.float64)
    d0 = np.asarray(planes.d, dtype=np.float64)
    n_planes = normal0.shape[0]
    count = np.bincount(plane, minlength=n_planes).astype(np.float64)
    sums = np.stack([np.bincount(plane, p_g[:, i], n_planes) for i in range(3)], -1)
    mean: F64 = sums.astype(np.float64) / np.maximum(count, 1.0)[:, None]
    q = p_g - mean[plane]
    cov = np.zeros((n_planes, 3, 3))
    for i in range(3):
        for j in range(i, 3):
            c = np.bincount(plane, q[:, i] * q[:, j], n_planes)
            cov[:, i, j] = c
            cov[:, j, i] = c
    _, vec = np.linalg.eigh(cov)
    normal = vec[:, :, 0]
    normal *= np.where(np.einsum("ij,ij->i", normal, normal0) < 0.0, -1.0, 1.0)[:, None]
    d = -np.einsum("ij,ij->i", normal, mean)
    ok = count >= 3
    return replace(planes, normal=np.where(ok[:, None], normal, normal0), d=np.where(ok, d, d0))


def _fit(
    state: CalibrationState, inputs: RoundInputs, params: LMParams
) -> tuple[CalibrationState, bool]:
    problem = inputs.problem(state)
    report = solve(problem, params)
    return state_from_problem(state, problem), report.status != "failed"


def twin_recordings(
    state: CalibrationState,
    inputs: RoundInputs,
    noise: NoiseLevels,
    params: LMParams,
    realisations: int = TWIN_REALISATIONS,
    seed: int = 0,
) -> Iterator[tuple[CalibrationState, RoundInputs]]:
    """Twin recordings of the fitted model, each fitted: ``(its estimate, its inputs)``.

    Args:
        state: the fit's estimate.
        inputs: the fit's final round (measurements, associations, planes, weights, free).
        noise: the noise levels the fit was weighted with (the twin's noise).
        params: LM settings of the twin's fit (a few iterations).
        realisations: twin recordings to make.
        seed: seed of the first one's noise (the others follow).

    Yields:
        One pair per twin whose fit did not fail.
    """
    model = _model(state, inputs, noise)
    plane = np.asarray(inputs.lidar.plane, dtype=np.intp)
    for k in range(max(realisations, 1)):
        rng = np.random.default_rng([seed, k])
        twin = _twin_inputs(model, inputs.planes, plane, noise, rng)
        fitted, ok = _fit(state, twin, params)
        if not ok:
            logger.info("Twin recording %d: its fit failed; left out.", k)
            continue
        yield fitted, twin


def twin_checks(
    state: CalibrationState,
    inputs: RoundInputs,
    noise: NoiseLevels,
    params: LMParams,
    realisations: int = TWIN_REALISATIONS,
    seed: int = 0,
) -> Twin | None:
    """Fit twin recordings of the fitted model and check their residuals as the fit's.

    Args:
        state: the fit's estimate.
        inputs: the fit's final round (measurements, associations, planes, weights, free).
        noise: the noise levels the fit was weighted with (the twin's noise).
        params: LM settings of the twin's fit (a few iterations).
        realisations: twin recordings to fit.
        seed: seed of the first one's noise (the others follow).

    Returns:
        The twin's statistics per sensor, or None when no twin could be fitted.
    """
    start = time.perf_counter()
    checks = [
        sensor_checks(fitted, twin, noise)
        for fitted, twin in twin_recordings(state, inputs, noise, params, realisations, seed)
    ]
    if not checks:
        return None
    sensors = []
    for i, first in enumerate(checks[0]):
        chi2 = np.array([c[i].chi2_per_sample for c in checks])
        rms = np.array([c[i].rms for c in checks])
        # at least what chi-square theory gives for the mean of the realisations (two give a
        # poor estimate of their own spread)
        theory = float(np.sqrt(2.0 * chi2.mean() / (max(first.samples, 1) * chi2.size)))
        spread = float(np.std(chi2, ddof=1) / np.sqrt(chi2.size)) if chi2.size > 1 else 0.0
        spread = max(spread, theory)
        sensors.append(
            TwinSensor(
                sensor=first.sensor,
                chi2_per_sample=float(chi2.mean()),
                chi2_spread=spread,
                rms=float(rms.mean()),
                check=first,
            )
        )
    seconds = time.perf_counter() - start
    logger.info(
        "Twin recordings (%d): %s in %.1f s.",
        len(checks),
        ", ".join(f"{s.sensor} chi2/sample {s.chi2_per_sample:.3f}" for s in sensors),
        seconds,
    )
    return Twin(sensors=tuple(sensors), realisations=len(checks), seconds=seconds)
