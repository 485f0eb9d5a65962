"""The points of the optimisation: the map and the solver apply one point model.

A driver converts its raw (beam, range, azimuth) with its own beam table; when that differs
from the table the calibration uses (a config's ``lidar.nominal_elevation_deg``, or per-beam
corrections applied by the driver), the published point is not the model's nominal point. The
sample keeps the difference (``model_gap``); the map (:func:`points_in_global`) and the
point-to-plane residual must both add it, or the solver fits other points than the map holds.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from licalib_cli.config import CalibConfig
from licalib_cli.estimation import (
    CalibrationState,
    FreeParameters,
    NoiseModel,
    Planes,
    build_problem,
)
from licalib_cli.geometry.so3 import exp as so3_exp
from licalib_cli.measurements import LidarScan
from licalib_cli.models.intrinsics import LidarIntrinsics
from licalib_cli.models.lidar import lidar_point, nominal_point
from licalib_cli.parallel import threads as thr
from licalib_cli.pipeline.points import (
    points_in_global,
    query_times,
    sample_points,
    solver_points,
)
from licalib_cli.spline import R3Spline, SO3Spline, UniformKnots

TABLE = np.radians(np.arange(-15.0, 16.0, 2.0))
T0_NS = 5_000_000_000
RANGE_SIGMA = 0.01


def _scans(rng: np.random.Generator, driver_table: np.ndarray) -> tuple[LidarScan, ...]:
    """Ten sweeps of 2 s whose points the driver converted with ``driver_table``."""
    scans = []
    for k in range(10):
        n = 400
        ring = rng.integers(0, 16, n).astype(np.int16)
        rho = rng.uniform(2.0, 30.0, n)
        theta = rng.uniform(-np.pi, np.pi, n)
        t_ns = T0_NS + 100_000_000 + k * 100_000_000 + np.sort(rng.integers(0, 99_000_000, n))
        xyz = nominal_point(rho, theta, driver_table[ring])
        scans.append(LidarScan(int(t_ns[0]), xyz, t_ns.astype(np.int64), ring))
    return tuple(scans)


def _state(rng: np.random.Generator) -> CalibrationState:
    knots = UniformKnots.for_interval(0.0, 1.4, 0.05)
    t = np.linspace(0.0, knots.t_end_s, 300)
    rot = so3_exp(np.column_stack([0.3 * np.sin(t), 0.2 * np.cos(2 * t), 0.5 * t]))
    pos = np.column_stack([np.sin(t), 0.5 * t, 0.1 * t**2])
    return CalibrationState(
        so3_spline=SO3Spline.from_rotations(knots, t, rot),
        r3_spline=R3Spline.fit(knots, t, pos),
        gyro_bias=np.zeros(3),
        accel_bias=np.zeros(3),
        gravity_G=np.array([0.0, 0.0, -9.81]),
        R_imu_lidar=so3_exp(np.array([0.1, -0.2, 0.3])),
        t_imu_lidar=np.array([0.3, 0.1, -0.05]),
        time_offset_s=0.004,
        lidar_intrinsics=LidarIntrinsics.nominal(TABLE),
        t0_ns=T0_NS,
        time_drift=2e-4,  # the timing terms too: the map and the solver query the same times
        point_time_scale=0.02,
        t_ref_s=0.7,
    )


def test_a_point_on_its_map_plane_has_zero_residual_whatever_the_driver_table() -> None:
    rng = np.random.default_rng(3)
    driver_table = TABLE + np.radians(rng.uniform(-0.5, 0.5, TABLE.size))
    state = _state(rng)
    sample = sample_points(_scans(rng, driver_table), TABLE, 400, CalibConfig())
    assert np.abs(sample.model_gap).max() > 0.05  # the driver's table is not the config's
    # A plane through every point where the map puts it.
    p_g = points_in_global(state, sample)
    normal = rng.standard_normal(p_g.shape)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    planes = Planes(normal=normal, d=-np.einsum("ij,ij->i", normal, p_g))
    lidar = solver_points(state, sample, np.arange(len(sample)))
    noise = NoiseModel(range_sigma=RANGE_SIGMA, huber_threshold=None)

    def distances(points: object) -> np.ndarray:
        problem = build_problem(state, None, points, planes, noise, FreeParameters())  # type: ignore[arg-type]
        return problem.evaluate(jacobians=False).evals[0].residuals[:, 0] * RANGE_SIGMA

    assert np.abs(distances(lidar)).max() < 1e-9
    # Without the gap the solver would fit points centimetres away from the map's; without the
    # sweep starts, at other times.
    assert np.abs(distances(replace(lidar, model_gap=None))).max() > 0.05
    assert np.abs(distances(replace(lidar, sweep_start_s=None))).max() > 1e-4


def test_with_the_drivers_table_the_gap_vanishes() -> None:
    rng = np.random.default_rng(4)
    sample = sample_points(_scans(rng, TABLE), TABLE, 400, CalibConfig())
    assert np.abs(sample.model_gap).max() < 1e-9


def test_the_map_on_block_threads_is_the_map_of_one_evaluation(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """points_in_global maps its points block by block, on the block threads: the same numbers,
    bit for bit, as the rotations and positions of all points evaluated at once."""
    rng = np.random.default_rng(5)
    state = _state(rng)
    scans = _scans(rng, TABLE) * 5  # 20 000 points: three blocks, the last one short
    sample = sample_points(scans, TABLE, 400, CalibConfig())
    assert len(sample) > 2 * thr.BLOCK
    t = query_times(state, sample)
    p_l = lidar_point(state.lidar_intrinsics, sample.beam, sample.rho, sample.theta)
    p_i = (p_l + sample.model_gap) @ state.R_imu_lidar.T + state.t_imu_lidar
    with thr.serial():
        expected = np.einsum(
            "nij,nj->ni", state.so3_spline.rotation(t), p_i
        ) + state.r3_spline.position(t)
    monkeypatch.setattr(thr, "THREADS", 2)  # also when the suite runs with LICALIB_THREADS=1
    assert np.array_equal(points_in_global(state, sample), expected)
    with thr.serial():
        assert np.array_equal(points_in_global(state, sample), expected)


def test_a_point_past_the_spline_is_mapped_at_its_end_as_the_residual_evaluates_it() -> None:
    """A round may move the time offset past the margin its points were chosen with: the points
    whose trajectory time then leaves the spline are mapped at its end (the point-to-plane
    residual clips their times the same way), not refused with an error."""
    rng = np.random.default_rng(6)
    state = replace(_state(rng), time_offset_s=0.5)  # the last sweeps' points are past the end
    sample = sample_points(_scans(rng, TABLE), TABLE, 400, CalibConfig())
    t = query_times(state, sample)
    past = t > state.knots.t_end_s
    assert past.any() and not past.all()
    with pytest.raises(ValueError, match="outside the spline range"):
        state.so3_spline.rotation(t)
    clipped = np.minimum(t, state.knots.t_end_s)
    p_l = lidar_point(state.lidar_intrinsics, sample.beam, sample.rho, sample.theta)
    p_i = (p_l + sample.model_gap) @ state.R_imu_lidar.T + state.t_imu_lidar
    expected = np.einsum(
        "nij,nj->ni", state.so3_spline.rotation(clipped), p_i
    ) + state.r3_spline.position(clipped)
    np.testing.assert_allclose(points_in_global(state, sample), expected, rtol=0, atol=1e-12)
