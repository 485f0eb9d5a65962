"""Synthetic IMU readings (method.md section 3) from the closed-form trajectory.

For sample ``k`` taken at true time ``t_k``::

    gyro_k  = S_w M_w R_wI omega_I(t_k) + A_w a_I(t_k) + b_w + walk_w(t_k) + n_w
    accel_k = S_a M_a a_I(t_k)                        + b_a + walk_a(t_k) + n_a

with ``a_I = R_W_I^T (p_ddot - g_W)``. White noise has the discrete sigma
``density * sqrt(rate)``; the bias random walk adds ``N(0, walk_density^2 / rate)`` per sample
(``walk(0) = 0``); the gyro's and the accelerometer's walks have their own multipliers
(``gyro_bias_walk`` / ``accel_bias_walk`` effects). Stamps are
``base_time_ns + round(k 1e9 / rate)`` on the IMU clock; with clock drift the true sampling
time is ``t_k = (stamp_k - base) / (1 + ppm 1e-6)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from licalib_cli.measurements import ImuSamples
from licalib_cli.models.imu import imu_measure
from licalib_cli.simulation.ground_truth import SimulationSetup, Stream, build_setup, rng_for
from licalib_cli.simulation.spec import SimulationSpec

F64 = npt.NDArray[np.float64]


@dataclass(frozen=True)
class ImuTruth:
    """What produced each IMU sample.

    Attributes:
        t_true_s: (N,) true sampling times relative to ``base_time_ns``, s.
        record_ns: (N,) int64 bag record times (true arrival), ns.
        omega: (N, 3) true body rate ``omega_I``, rad/s.
        specific_force: (N, 3) true ``a_I``, m/s^2.
        gyro_bias: (N, 3) total gyro bias (constant + random walk), rad/s.
        accel_bias: (N, 3) total accelerometer bias, m/s^2.
        gyro_noise_sigma: discrete white-noise sigma used, rad/s.
        accel_noise_sigma: discrete white-noise sigma used, m/s^2.
    """

    t_true_s: F64
    record_ns: npt.NDArray[np.int64]
    omega: F64
    specific_force: F64
    gyro_bias: F64
    accel_bias: F64
    gyro_noise_sigma: float
    accel_noise_sigma: float


def _recorded(spec: SimulationSpec, t_true: F64) -> npt.NDArray[np.int64]:
    """Record times of the samples: their true times plus the transport delays
    (``spec.record_delay_ms``), in order (a sample never overtakes the one before)."""
    record = spec.base_time_ns + np.round(t_true * 1e9).astype(np.int64)
    if spec.record_delay_ms <= 0.0:
        return record
    rng = rng_for(spec.resolved_noise_seed, Stream.RECORD_DELAY, 0)
    delay = np.round(rng.exponential(spec.record_delay_ms * 1e6, t_true.shape[0]))
    return np.maximum.accumulate(record + delay.astype(np.int64))


def imu_sample_times(spec: SimulationSpec) -> tuple[npt.NDArray[np.int64], F64]:
    """Stamps relative to the base time (int64 ns) and true times (s) of every IMU sample."""
    n = int(np.floor(spec.resolved_duration_s * spec.imu_rate_hz + 1e-9)) + 1
    stamp_rel_ns = np.round(np.arange(n) * (1e9 / spec.imu_rate_hz)).astype(np.int64)
    rate_factor = 1.0 + spec.resolved_imu_clock_drift_ppm * 1e-6
    t_true = stamp_rel_ns.astype(np.float64) * 1e-9 / rate_factor
    return stamp_rel_ns, t_true


def generate_imu(
    spec: SimulationSpec, setup: SimulationSetup | None = None
) -> tuple[ImuSamples, ImuTruth]:
    """All IMU samples of a run, vectorised.

    Args:
        spec: the options.
        setup: resolved truth; built from ``spec`` when None.

    Returns:
        ``(samples, truth)``: samples with absolute stamps (int64 ns), and what produced them.
    """
    setup = setup or build_setup(spec)
    stamp_rel_ns, t_true = imu_sample_times(spec)
    n = t_true.shape[0]
    state = setup.trajectory.state(t_true)
    accel_true = state.specific_force(spec.gravity_w)
    gyro, accel = imu_measure(setup.imu_intrinsics, state.angular_velocity, accel_true)

    rng = rng_for(spec.resolved_noise_seed, Stream.IMU_NOISE)
    white = rng.standard_normal((n, 6))
    walk = rng.standard_normal((n, 6))
    rate = spec.imu_rate_hz
    noise_scale = 0.0 if spec.noise_free else 1.0
    walk_g_scale = 0.0 if spec.noise_free else spec.resolved_gyro_bias_walk_scale
    walk_a_scale = 0.0 if spec.noise_free else spec.resolved_accel_bias_walk_scale
    sig_g = noise_scale * spec.gyro_noise_density * np.sqrt(rate)
    sig_a = noise_scale * spec.accel_noise_density * np.sqrt(rate)
    step_g = walk_g_scale * spec.gyro_bias_walk_density / np.sqrt(rate)
    step_a = walk_a_scale * spec.accel_bias_walk_density / np.sqrt(rate)
    walk[0] = 0.0
    walk_g = np.cumsum(walk[:, :3] * step_g, axis=0)
    walk_a = np.cumsum(walk[:, 3:] * step_a, axis=0)
    gyro = gyro + walk_g + sig_g * white[:, :3]
    accel = accel + walk_a + sig_a * white[:, 3:]

    samples = ImuSamples(
        t_ns=spec.base_time_ns + stamp_rel_ns,
        gyro=gyro,
        accel=accel,
    )
    truth = ImuTruth(
        t_true_s=t_true,
        record_ns=_recorded(spec, t_true),
        omega=state.angular_velocity,
        specific_force=accel_true,
        gyro_bias=setup.imu_intrinsics.gyro_bias + walk_g,
        accel_bias=setup.imu_intrinsics.accel_bias + walk_a,
        gyro_noise_sigma=float(sig_g),
        accel_noise_sigma=float(sig_a),
    )
    return samples, truth
