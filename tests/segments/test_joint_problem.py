"""The multi-segment problem: shared extrinsic, per-segment trajectory, biases, gravity and time
offset; its cost and calibration information are those of the segments added up."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from licalib_cli.config import CalibConfig
from licalib_cli.estimation import (
    CalibrationState,
    FreeParameters,
    ImuData,
    LidarPoints,
    NoiseModel,
    Planes,
    build_problem,
)
from licalib_cli.geometry.so3 import exp as so3_exp
from licalib_cli.models.intrinsics import LidarIntrinsics
from licalib_cli.pipeline.checks import Finding
from licalib_cli.pipeline.joint import (
    _disagreement,
    _growth,
    _only_information,
    _scatter_factor,
)
from licalib_cli.pipeline.joint_problem import joint_problem, per_segment_blocks, segment_name
from licalib_cli.pipeline.map_uncertainty import MapUncertainty
from licalib_cli.pipeline.points import PointSample
from licalib_cli.pipeline.prior_directions import lever_arm_conflict
from licalib_cli.pipeline.round import RoundInputs
from licalib_cli.residuals import (
    ACCEL_BIAS,
    EXT_ROTATION,
    EXT_TRANSLATION,
    GRAVITY,
    GYRO_BIAS,
    TIME_OFFSET,
    TRAJ_R3,
    TRAJ_SO3,
)
from licalib_cli.results import Extrinsic
from licalib_cli.sections import Uncertainty
from licalib_cli.solver import LMParams, solve
from licalib_cli.solver.observability import calibration_information
from licalib_cli.spline import R3Spline, SO3Spline, UniformKnots

G = np.array([0.0, 0.0, -9.81])
BEAMS = np.deg2rad(np.linspace(-15.0, 15.0, 16))
R_TRUE = so3_exp(np.deg2rad([3.0, -2.0, 40.0]))
T_TRUE = np.array([0.1, -0.05, 0.2])


def _splines(seed: int, duration: float = 3.0) -> tuple[SO3Spline, R3Spline]:
    rng = np.random.default_rng(seed)
    knots = UniformKnots.for_interval(0.0, duration, 0.05)
    t = np.linspace(0.0, knots.t_end_s, int(knots.t_end_s * 200) + 1)
    f = rng.uniform(0.2, 0.5, 6) * 2 * np.pi
    rotvec = np.column_stack([0.5 * np.sin(f[i] * t + i) for i in range(3)])
    pos = np.column_stack([1.0 * np.sin(f[3 + i] * t + i) for i in range(3)])
    return SO3Spline.from_rotations(knots, t, so3_exp(rotvec)), R3Spline.fit(knots, t, pos)


def _segment(seed: int, tc: float) -> tuple[CalibrationState, RoundInputs]:
    """A segment in a box room with exact measurements (IMU and points on their planes)."""
    rng = np.random.default_rng(seed)
    so3, r3 = _splines(seed)
    t_imu = np.arange(0.0, so3.knots.t_end_s, 1.0 / 200)
    ev = so3.evaluate(t_imu, order=1)
    gyro = ev.angular_velocity
    accel = np.einsum("nji,nj->ni", ev.rotation, r3.acceleration(t_imu) - G)
    imu = ImuData(t_imu, gyro, accel)
    normal = np.array([[0, 0, 1], [0, 0, -1], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0.0]])
    planes = Planes(normal, np.array([1.5, 3.0, 6.0, 7.0, 5.0, 4.5]))
    n = 3000
    tau = np.sort(rng.uniform(0.3, so3.knots.t_end_s - 0.3, n))
    beam = rng.integers(0, BEAMS.shape[0], n)
    theta = rng.uniform(-np.pi, np.pi, n)
    phi = BEAMS[beam]
    u_l = np.column_stack([np.cos(phi) * np.cos(theta), np.cos(phi) * np.sin(theta), np.sin(phi)])
    rot = so3.rotation(tau + tc)
    origin = np.einsum("nij,j->ni", rot, T_TRUE) + r3.position(tau + tc)
    u_g = np.einsum("nij,nj->ni", rot @ R_TRUE, u_l)
    num = -(origin @ normal.T + planes.d)
    den = u_g @ normal.T
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(den != 0.0, num / den, np.inf)
    s = np.where(s > 0.0, s, np.inf)
    plane = np.argmin(s, axis=1)
    rho = s[np.arange(n), plane]
    lidar = LidarPoints(tau, beam, rho, theta, plane)
    state = CalibrationState(
        so3_spline=so3,
        r3_spline=r3,
        gyro_bias=np.zeros(3),
        accel_bias=np.zeros(3),
        gravity_G=G,
        R_imu_lidar=R_TRUE,
        t_imu_lidar=T_TRUE,
        time_offset_s=tc,
        lidar_intrinsics=LidarIntrinsics.nominal(BEAMS),
    )
    noise = NoiseModel(1e-3, 1e-2, range_sigma=0.01, huber_threshold=None)
    empty = PointSample(*(np.zeros(0, np.int64),) * 3, np.zeros(0), np.zeros(0), np.zeros((0, 3)))
    return state, RoundInputs(imu, lidar, empty, planes, noise, FreeParameters())


@pytest.fixture(scope="module")
def two_segments() -> tuple[list[CalibrationState], list[RoundInputs]]:
    a, b = _segment(1, 0.004), _segment(2, -0.003)
    return [a[0], b[0]], [a[1], b[1]]


def test_segments_share_the_extrinsic_and_keep_their_own_blocks(two_segments) -> None:
    states, inputs = two_segments
    problem = joint_problem(states, inputs, FreeParameters())
    names = {b.name for b in problem.parameter_blocks}
    assert EXT_ROTATION in names and EXT_TRANSLATION in names
    for k in range(2):
        for own in (TRAJ_SO3, TRAJ_R3, GYRO_BIAS, ACCEL_BIAS, GRAVITY, TIME_OFFSET):
            assert segment_name(k, own) in names
            assert own not in names
    assert TIME_OFFSET in per_segment_blocks() and EXT_ROTATION not in per_segment_blocks()
    # the time offsets are calibration coordinates of their own segment
    coords = problem.layout().calibration_names
    assert "seg1:ext.time_offset" in coords and "seg2:ext.time_offset" in coords
    assert sum(c.startswith("ext.translation") for c in coords) == 3


def test_joint_cost_and_information_add_up(two_segments) -> None:
    states, inputs = two_segments
    free = FreeParameters(time_offset=False)
    singles = [
        build_problem(s, d.imu, d.lidar, d.planes, d.noise, free)
        for s, d in zip(states, inputs, strict=True)
    ]
    joint = joint_problem(states, inputs, free)
    # perturb the shared extrinsic: the joint cost is the sum of the segments' costs
    for p in [*singles, joint]:
        p.set_values({EXT_TRANSLATION: T_TRUE + np.array([0.01, -0.02, 0.005])})
    cost = [p.evaluate(jacobians=False).cost for p in singles]
    assert joint.evaluate(jacobians=False).cost == pytest.approx(sum(cost), rel=1e-10)
    # the information about the shared extrinsic is the sum of the segments' (Schur complements
    # of disjoint trajectories)
    info = [calibration_information(p) for p in singles]
    joint_info = calibration_information(joint)
    assert joint_info.names == info[0].names
    np.testing.assert_allclose(
        joint_info.information, info[0].information + info[1].information, rtol=1e-6, atol=1e-6
    )


def test_joint_solve_recovers_shared_extrinsic_and_own_time_offsets(two_segments) -> None:
    states, inputs = two_segments
    start = [
        s.with_(
            t_imu_lidar=T_TRUE + np.array([0.02, -0.01, 0.015]),
            R_imu_lidar=R_TRUE @ so3_exp(np.deg2rad([0.5, -0.3, 0.4])),
            time_offset_s=0.0,
        )
        for s in states
    ]
    problem = joint_problem(start, inputs, FreeParameters())
    report = solve(problem, LMParams(max_iterations=30))
    assert report.converged, report.reason
    values = problem.values()
    np.testing.assert_allclose(values[EXT_TRANSLATION], T_TRUE, atol=1e-4)
    assert values["seg1:ext.time_offset"].reshape(-1)[0] == pytest.approx(0.004, abs=2e-5)
    assert values["seg2:ext.time_offset"].reshape(-1)[0] == pytest.approx(-0.003, abs=2e-5)


def test_disagreement_is_measured_in_the_segments_own_sigmas() -> None:
    own = Extrinsic(np.eye(3), np.array([0.3, 0.15, 0.05]), 0.0)
    unc = Uncertainty((0.001, 0.001, 0.002), (0.01, 0.01, 0.01), 1e-5)
    run = SimpleNamespace(result=SimpleNamespace(extrinsic=own, uncertainty=unc))
    moved = Extrinsic(np.eye(3), own.translation + np.array([0.0, 0.0, 0.01]), 0.0)
    assert _disagreement(run, moved) == pytest.approx(5.0)  # 1 cm on z, sigma 2 mm
    turned = Extrinsic(so3_exp(np.deg2rad([0.0, 0.03, 0.0])), own.translation, 0.0)
    assert _disagreement(run, turned) == pytest.approx(3.0, rel=1e-6)
    # an axis the segment alone cannot determine (infinite sigma) never disagrees
    blind = SimpleNamespace(
        result=SimpleNamespace(
            extrinsic=own, uncertainty=Uncertainty((np.inf,) * 3, (0.01,) * 3, 1)
        )
    )
    assert _disagreement(blind, moved) == 0.0


def _checked_run(raw: list[float], shown_t: float, chi: float, plane_factor: float):
    """A segment run whose checks enlarged the translation sigmas to ``shown_t``."""
    checks = SimpleNamespace(
        raw_sigma=np.array(raw),
        uncertainty=Uncertainty((shown_t,) * 3, tuple(np.degrees(raw[3:6])), raw[6]),
        consistency=SimpleNamespace(sensors=(SimpleNamespace(chi2_per_sample=chi),)),
        planes=MapUncertainty(
            ("ext.translation.x", "lidar.intrinsics[1].drho"),
            np.array([1.1, plane_factor]),
            40,
            0.0,
        ),
        effects=(),  # no IMU prior (tests/segments/test_joint_sigmas.py)
    )
    return SimpleNamespace(checks=checks)


def test_joint_sigmas_grow_by_the_segments_factors_weighted_by_their_information() -> None:
    raw = [0.001, 0.001, 0.001, 1e-4, 1e-4, 1e-4, 1e-5]
    a = _checked_run(raw, 0.0015, chi=1.44, plane_factor=3.0)
    b = _checked_run(raw, 0.0030, chi=0.8, plane_factor=2.0)
    grow, chi_factor, planes, effects, prior = _growth([a, b])
    np.testing.assert_array_equal(prior, 0.0)
    np.testing.assert_array_equal(effects, 0.0)
    # equal information: 1 / g^2 = (1 / 1.5^2 + 1 / 3^2) / 2, between the two factors
    np.testing.assert_allclose(grow[:3], np.sqrt(2.0 / (1 / 1.5**2 + 1 / 3.0**2)))
    np.testing.assert_allclose(grow[3:], 1.0, atol=1e-12)  # never below one
    assert chi_factor == pytest.approx(1.2)  # root of the largest chi-square per sample
    assert planes is not None
    assert planes.of("lidar.intrinsics[1].drho") == pytest.approx(3.0)
    assert planes.of("ext.translation.x") == pytest.approx(1.1)
    # the joint sigma (the joint solver's, the segments' information summed, times the factor)
    # is below each segment's enlarged sigma
    joint_raw = 0.001 / np.sqrt(2.0)
    assert joint_raw * grow[0] < min(0.0015, 0.0030)
    # a segment that brings four times the information weighs four times as much
    c = _checked_run([0.0005, 0.0005, 0.0005, *raw[3:]], 0.0005, chi=1.0, plane_factor=1.0)
    grow, *_ = _growth([c, b])
    np.testing.assert_allclose(grow[:3], np.sqrt(5.0 / (4.0 + 1 / 3.0**2)))
    # a coordinate a segment left undetermined (raw sigma infinite) does not poison the factor
    d = _checked_run([np.inf, *raw[1:]], 0.0015, chi=1.0, plane_factor=1.0)
    grow, *_ = _growth([d])
    assert np.all(np.isfinite(grow))
    assert grow[0] == 1.0 and grow[1] == pytest.approx(1.5)


def test_segments_scattering_beyond_their_sigmas_grow_the_joint_sigma() -> None:
    def run(t: list[float], sigma: float, dt: float = 0.0) -> SimpleNamespace:
        ext = Extrinsic(np.eye(3), np.array(t), 0.01 + dt)
        unc = Uncertainty((sigma,) * 3, (0.01,) * 3, 1e-5)
        return SimpleNamespace(result=SimpleNamespace(extrinsic=ext, uncertainty=unc))

    joint = Extrinsic(np.eye(3), np.zeros(3), 0.01)
    clock = np.zeros(3)
    # within their sigmas: no growth
    agree = [run([0.001, 0, 0], 0.002), run([-0.001, 0, 0], 0.002), run([0, 0, 0], 0.002)]
    np.testing.assert_array_equal(_scatter_factor(agree, joint, clock), 1.0)
    # x scattered by 3 and 4 sigmas: chi-square 25 on 2, the Birge ratio sqrt(12.5)
    far = [run([0.006, 0, 0], 0.002), run([-0.008, 0, 0], 0.002), run([0, 0, 0], 0.002)]
    f = _scatter_factor(far, joint, clock)
    assert f[0] == pytest.approx(np.sqrt(12.5))
    np.testing.assert_array_equal(f[1:], 1.0)
    # time offsets are compared on one LiDAR clock: a segment's clock shift is taken out
    shifted = [run([0, 0, 0], 0.002, dt=-0.5), run([0, 0, 0], 0.002), run([0, 0, 0], 0.002)]
    assert _scatter_factor(shifted, joint, np.array([0.5, 0.0, 0.0]))[6] == 1.0
    assert _scatter_factor(shifted, joint, clock)[6] > 100.0
    # a single segment determining a coordinate says nothing about scatter
    one = [run([0.01, 0, 0], 0.002), run([0.0, 0, 0], np.inf)]
    assert _scatter_factor(one, joint, np.zeros(2))[0] == 1.0


def test_a_measured_lever_arm_is_held_once_for_all_segments(two_segments) -> None:
    """The translation's prior enters the joint problem once (the segments share the extrinsic):
    the joint cost is the segments' costs without it plus the prior's own."""
    states, inputs = two_segments
    mean, sigma = (0.31, 0.14, 0.06), (0.01, 0.01, 0.02)
    with_prior = FreeParameters(time_offset=False, translation_prior=(mean, sigma))
    singles = [
        build_problem(s, d.imu, d.lidar, d.planes, d.noise, FreeParameters(time_offset=False))
        for s, d in zip(states, inputs, strict=True)
    ]
    joint = joint_problem(states, inputs, with_prior)
    moved = T_TRUE + np.array([0.01, -0.02, 0.005])
    for p in [*singles, joint]:
        p.set_values({EXT_TRANSLATION: moved})
    prior_cost = 0.5 * float(np.sum(((moved - np.array(mean)) / np.array(sigma)) ** 2))
    cost = sum(p.evaluate(jacobians=False).cost for p in singles)
    assert joint.evaluate(jacobians=False).cost == pytest.approx(cost + prior_cost, rel=1e-10)


@pytest.mark.parametrize(
    ("off_m", "disagrees"),
    [((0.004, -0.003, 0.002), False), ((0.05, -0.04, 0.0), True)],
)
def test_the_joint_estimate_compares_the_measured_lever_arm_with_the_segments_data(
    two_segments, off_m: tuple[float, float, float], disagrees: bool
) -> None:
    """A measured lever arm within its sigma of what the segments' data say passes; one 5 of its
    sigmas off is found from the joint problem's information (which holds the prior once), the
    data's own estimate recovered and the translation sigmas widened by the prior's pull."""
    states, inputs = two_segments
    mean, sigma = T_TRUE + np.array(off_m), 0.01
    free = FreeParameters(translation_prior=(tuple(mean), (sigma,) * 3))
    problem = joint_problem(states, inputs, free)
    report = solve(problem, LMParams(max_iterations=30))
    assert report.converged, report.reason
    cfg = CalibConfig.model_validate(
        {"initialization": {"translation_m": mean.tolist(), "translation_sigma_m": sigma}}
    )
    joint = problem.values()[EXT_TRANSLATION].reshape(-1)
    conflict = lever_arm_conflict(report, cfg, joint)
    assert conflict is not None and conflict.dof == 3
    assert conflict.disagrees is disagrees
    # exact measurements: the data's own estimate is the truth
    np.testing.assert_allclose(conflict.difference_m, T_TRUE - mean, atol=5e-4)
    widened = conflict.covered(np.full(3, 1e-3))
    if disagrees:
        assert "disagrees with the data" in conflict.text
        np.testing.assert_allclose(widened, np.hypot(1e-3, conflict.pull_m))
        assert np.all(widened > 1e-3)
    else:
        np.testing.assert_array_equal(widened, np.full(3, 1e-3))
    assert lever_arm_conflict(report, CalibConfig(), joint) is None


def test_a_segment_short_only_of_information_does_not_lower_the_joint_verdict() -> None:
    """What a segment alone leaves undetermined the joint problem judges for itself; a finding
    about the model's fit (or a note on the data) holds for the joint fit too."""
    unobservable = Finding("warn", "Not observable from this data: ...", information=True)
    too_few = Finding("fail", "The data determine only 3 of the 7 ...", information=True)
    misfit = Finding("warn", "The LiDAR residuals depend on the beam ...")
    note = Finding("note", "The gyro residuals are below their configured noise ...")
    assert _only_information([unobservable, too_few, note])
    assert not _only_information([unobservable, misfit])
    assert _only_information([])
