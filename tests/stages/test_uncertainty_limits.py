"""A PASS promises its accuracy: a sigma above the ``checks`` limits makes the verdict warn."""

from __future__ import annotations

import numpy as np
import pytest

from licalib_cli.config import CalibConfig, ChecksSection, load_config
from licalib_cli.errors import ConfigError
from licalib_cli.pipeline.checks import uncertainty_findings
from licalib_cli.pipeline.prior_directions import OnPrior


def _sigma(t_mm: float, r_deg: float, dt_ms: float) -> np.ndarray:
    return np.array([1e-3 * t_mm, 0.0, 0.0, np.radians(r_deg), 0.0, 0.0, 1e-3 * dt_ms])


def _texts(sigma: np.ndarray, limits: ChecksSection) -> list[str]:
    return [f.text for f in uncertainty_findings(sigma, sigma, limits)]


def test_the_default_limits_are_5_mm_0_1_deg_and_0_2_ms() -> None:
    limits = CalibConfig().checks
    assert _texts(_sigma(4.9, 0.099, 0.199), limits) == []
    texts = _texts(_sigma(7.6, 0.12, 0.25), limits)
    assert len(texts) == 3
    assert texts[0].startswith("Translation is uncertain (1-sigma up to 7.6 mm")
    assert "checks.max_translation_sigma_m = 5 mm" in texts[0]
    assert "checks.max_rotation_sigma_deg = 0.1 deg" in texts[1]
    assert "Time offset is uncertain (1-sigma 0.25 ms" in texts[2]


def test_an_unobservable_direction_is_not_an_uncertain_one() -> None:
    """An infinite sigma is reported by the observability check, not as uncertain."""
    sigma = _sigma(1.0, 0.01, 0.05)
    sigma[2] = np.inf
    assert _texts(sigma, CalibConfig().checks) == []


def test_the_limits_come_from_the_config(tmp_path) -> None:
    path = tmp_path / "c.yaml"
    path.write_text("checks:\n  max_translation_sigma_m: 0.01\n  max_time_offset_sigma_s: 0.001\n")
    limits = load_config(path).checks
    assert _texts(_sigma(7.6, 0.01, 0.21), limits) == []
    assert len(_texts(_sigma(12.0, 0.01, 0.21), limits)) == 1
    path.write_text("checks:\n  max_translation_sigma_m: 0\n")
    with pytest.raises(ConfigError, match="max_translation_sigma_m"):
        load_config(path)


def test_a_sigma_over_the_limit_by_the_imu_priors_names_them_not_the_motion() -> None:
    """A clean sinusoid's translation sigma went from about 3 to 5.05 mm by the IMU priors
    alone: the finding says so instead of asking for more rotation."""
    sigma = _sigma(5.05, 0.01, 0.05)
    without = _sigma(3.1, 0.01, 0.05)
    limits = CalibConfig().checks
    (finding,) = uncertainty_findings(sigma, without, limits, prior="gyro_rotation")
    assert "model.imu_prior (most from gyro_rotation)" in finding.text
    assert "more rotation" not in finding.text
    (both,) = uncertainty_findings(sigma, without, limits, ["accel_scale"], "gyro_rotation")
    assert "(accel_scale)" in both.text and "(most from gyro_rotation)" in both.text
    assert "estimate them (model.imu: [accel_scale] in the config)" in both.text
    (motion,) = uncertainty_findings(sigma, sigma, limits, prior="gyro_rotation")
    assert "more rotation" in motion.text
    assert "estimate them (--intrinsics imu) or set your IMU's" in finding.text
    # a LiDAR prior (model.lidar_prior) named as such, with the entry that estimates it:
    # the per-point times are no intrinsic of --intrinsics lidar
    (lidar,) = uncertainty_findings(sigma, without, limits, prior="lidar_point_time")
    assert "the LiDAR intrinsics held fixed, known only to within model.lidar_prior" in lidar.text
    assert "estimate them (model.lidar: [point_time]) or set your LiDAR's" in lidar.text
    # about what the data determine: a joint over segments judges its own sigmas instead
    assert finding.information and both.information and motion.information


def _report(corr_with_scale: float):
    """A solver report whose x translation (5.5 mm) is correlated ``corr_with_scale`` with the
    accelerometer's x scale and 0.95 with the extrinsic pitch (not an intrinsic)."""
    from licalib_cli.solver.lm import SolverReport

    names = (
        "ext.rotation.ry",
        "ext.translation.x",
        "ext.translation.y",
        "ext.translation.z",
        "imu.accel_scale.x",
        "lidar.intrinsics[3].range_offset",
    )
    sd = np.array([1e-4, 5.5e-3, 1e-3, 1e-3, 1e-4, 1e-3])
    corr = np.eye(6)
    corr[0, 1] = corr[1, 0] = 0.95
    corr[1, 4] = corr[4, 1] = corr_with_scale
    corr[1, 5] = corr[5, 1] = -0.72
    corr[0, 4] = corr[4, 0] = corr_with_scale * 0.95
    fields = {f: None for f in SolverReport.__dataclass_fields__}
    fields.update(calibration_names=names, covariance=corr * np.outer(sd, sd))
    return SolverReport(**fields)  # type: ignore[arg-type]


def test_an_uncertain_translation_names_the_estimated_intrinsics_it_moves_with() -> None:
    from licalib_cli.pipeline.checks import entangled_intrinsics

    sigma = _sigma(5.5, 0.01, 0.05)
    sigma[1:3] = 1e-3
    limits = CalibConfig().checks
    found = entangled_intrinsics(_report(-0.8), sigma[:3])
    assert found is not None and found.axis == "x"
    # strongest first; the extrinsic pitch (0.95) is not an intrinsic the user can leave out
    assert [n for n, _ in found.partners] == [
        "imu.accel_scale.x",
        "lidar.intrinsics[3].range_offset",
    ]
    (finding,) = uncertainty_findings(sigma, sigma, limits, entangled=found)
    assert "along x moves with imu.accel_scale.x (-0.80), lidar.intrinsics[3].range_offset " in (
        finding.text
    )
    assert "model.imu and model.lidar" in finding.text and "more rotation" in finding.text
    # below 0.7 an intrinsic is not named
    weak = entangled_intrinsics(_report(-0.5), sigma[:3])
    assert weak is not None and [n for n, _ in weak.partners] == [
        "lidar.intrinsics[3].range_offset"
    ]
    # the y axis, the largest sigma now, moves with nothing
    sigma[1] = 9e-3
    assert entangled_intrinsics(_report(-0.8), sigma[:3]) is None


def test_a_translation_over_the_limit_along_the_measured_lever_arm_says_so() -> None:
    """On a planar vehicle the vertical takes the measured lever arm's sigma: above the limit,
    the finding says the data do not determine it there and that a better measurement narrows
    it; a measurement within the limit, or a direction across the axis over the limit, does not
    take the blame."""
    limits = CalibConfig().checks
    sigma = _sigma(2.0, 0.01, 0.05)
    sigma[2] = 0.0101  # the vertical, from a 1 cm measurement
    vertical = OnPrior((0.0, 0.02, 0.9998), 0.01, "ext.translation along [0.00, 0.02, 1.00] ...")
    (text,) = [f.text for f in uncertainty_findings(sigma, sigma, limits, resting=[vertical])]
    assert text.startswith("Translation is uncertain (1-sigma up to 10.1 mm")
    assert "Along [0.00, 0.02, 1.00] (IMU frame) it is the measured lever arm's 10 mm" in text
    assert "initialization.translation_sigma_m" in text
    precise = OnPrior(vertical.direction, 0.004, vertical.text)
    sideways = OnPrior((1.0, 0.0, 0.0), 0.01, vertical.text)
    for resting in ([], [precise], [sideways]):
        (text,) = [f.text for f in uncertainty_findings(sigma, sigma, limits, resting=resting)]
        assert "initialization.translation_sigma_m" not in text


def test_a_sigma_held_over_the_limit_by_the_halves_says_so() -> None:
    """A clean OS1-64 sinusoid warned for a time offset of 0.298 ms: the halves differed by 0.70
    ms (1.9 of their combined sigmas) and half the excess over that spread stayed in the sigma.
    The finding says where it comes from; a floor below the limit is not named."""
    from licalib_cli.pipeline.inflation import split_floor
    from licalib_cli.pipeline.split import SplitResult

    limits = CalibConfig().checks
    difference = np.array([1e-3, 0.0, 0.0, np.radians(0.01), 0.0, 0.0, -0.698e-3])
    spread = np.array([2e-3, 2e-3, 2e-3, np.radians(0.02), np.radians(0.02), 1.0, 0.371e-3])
    halves = SplitResult(
        ran=True, half_s=5.0, difference=difference, sigma=spread, z=np.abs(difference) / spread
    )
    floor = split_floor(halves)
    assert floor[6] == pytest.approx(0.5 * np.sqrt(0.698**2 - 0.371**2) * 1e-3)
    sigma = _sigma(1.0, 0.01, 1e3 * floor[6])
    (finding,) = uncertainty_findings(sigma, _sigma(1.0, 0.01, 0.15), limits, halves=halves)
    assert finding.text.startswith("Time offset is uncertain (1-sigma 0.296 ms")
    assert "The two halves of the segment differ by -0.698 ms in time offset (1.9 of" in (
        finding.text
    )
    assert "a longer recording" in finding.text
    # the same sigma with halves that agree within their spread: no such sentence
    calm = SplitResult(
        ran=True, half_s=5.0, difference=0.5 * spread, sigma=spread, z=0.5 + 0 * spread
    )
    (finding,) = uncertainty_findings(sigma, sigma, limits, halves=calm)
    assert "halves" not in finding.text
    # halves not compared (a segment too short to split): nothing either
    (finding,) = uncertainty_findings(sigma, sigma, limits, halves=SplitResult(ran=False))
    assert "halves" not in finding.text


def test_the_model_entries_that_estimate_held_effects_are_named() -> None:
    """The paper's case under calibrate --model auto: the per-beam range scales, held and
    hinted at, made the translation sigma 11.8 mm; the finding pointed to --model auto, the
    very command run. It names the config entries that estimate them instead."""
    from licalib_cli.pipeline.checks import model_entries

    assert model_entries(["lidar_range_scale"]) == "model.lidar: [range_scale]"
    assert (
        model_entries(
            ["lidar_vertical_offset", "gyro_scale", "lidar_point_time", "imu_clock_drift"]
        )
        == "model.lidar: [vertical_offset, point_time], model.imu: [gyro_scale, clock_drift]"
    )
    sigma = _sigma(11.8, 0.01, 0.05)
    (finding,) = uncertainty_findings(
        sigma, _sigma(1.4, 0.01, 0.05), CalibConfig().checks, ["lidar_range_scale"]
    )
    assert "estimate them (model.lidar: [range_scale] in the config)" in finding.text
    # every candidate's entry is one the config accepts
    from licalib_cli.pipeline.fitcheck import CANDIDATES

    lists: dict[str, list[str]] = {}
    for sensor, block, _ in CANDIDATES.values():
        lists.setdefault(sensor, []).append(block)
    cfg = CalibConfig.model_validate({"model": lists})
    assert len(cfg.model.imu) + len(cfg.model.lidar) == len(CANDIDATES)


def test_a_sweep_holding_many_more_points_than_the_last_round_kept_is_said() -> None:
    """On a short bag the dense final round's points bound the translation and the time offset
    (twenty 10 s sinusoids: 15 000 instead of 6000 a sweep turned both WARNs for a sigma into
    PASS): their findings say so when a sweep holds at least twice the points kept, unless the
    IMU priors are the cause; the rotation's (the gyro's) does not."""
    from licalib_cli.pipeline.points import PointBudget

    limits = CalibConfig().checks
    sigma = _sigma(5.95, 0.12, 0.216)
    few = PointBudget(kept=6000, available=28_800)
    texts = [f.text for f in uncertainty_findings(sigma, sigma, limits, points=few)]
    said = "The last round kept 6000 of about 28800 points a sweep: more"
    assert said in texts[0] and "more rotation" in texts[0]
    assert said not in texts[1]
    assert said in texts[2] and "surfels.final_points_per_scan" in texts[2]
    # every point of a sweep kept, or nearly: nothing to add
    for budget in (PointBudget(6000, 11_999), None):
        assert not any(
            "points a sweep" in f.text
            for f in uncertainty_findings(sigma, sigma, limits, points=budget)
        )
    # the IMU priors, not the points, hold it: the finding names them alone
    (prior,) = uncertainty_findings(
        _sigma(5.05, 0.01, 0.05), _sigma(3.1, 0.01, 0.05), limits, prior="gyro_rotation", points=few
    )
    assert "points a sweep" not in prior.text


def test_segments_estimated_together_are_told_of_more_points_only_when_every_one_holds_them() -> (
    None
):
    """``joint_point_budget``: the joint problem takes each segment's last round's points; the
    advice on points stands only when every segment's sweep holds at least twice the most any
    segment kept, and not when a segment's budget is unknown."""
    from licalib_cli.pipeline.points import PointBudget, joint_point_budget

    both = joint_point_budget([PointBudget(6000, 28_800), PointBudget(4000, 14_000)])
    assert both == PointBudget(6000, 14_000) and both.more_available
    # one segment kept nearly all of its sweeps: more do not help it
    full = joint_point_budget([PointBudget(6000, 28_800), PointBudget(6000, 11_000)])
    assert full == PointBudget(6000, 11_000) and not full.more_available
    assert joint_point_budget([PointBudget(6000, 28_800), None]) is None
    assert joint_point_budget([]) is None
    limits = CalibConfig().checks
    sigma = _sigma(5.95, 0.12, 0.216)
    texts = [f.text for f in uncertainty_findings(sigma, sigma, limits, points=both)]
    assert "The last round kept 6000 of about 14000 points a sweep: more" in texts[0]


def test_the_point_budget_is_the_last_round_s_against_the_median_sweep() -> None:
    """``point_budget``: the dense round's points per sweep (within ``max_points``), the
    regular rounds' without one, against the median sweep."""
    from licalib_cli.measurements import LidarScan
    from licalib_cli.pipeline.points import point_budget

    def scan(n: int) -> LidarScan:
        return LidarScan(0, np.zeros((n, 3)), np.zeros(n, dtype=np.int64))

    scans = tuple(scan(n) for n in (20_000, 30_000, 25_000, 40))
    cfg = CalibConfig()
    budget = point_budget(cfg, scans)
    assert budget is not None and (budget.kept, budget.available) == (6000, 22_500)
    assert budget.more_available
    capped = load_config(None, {"surfels.max_points": 8000})
    assert point_budget(capped, scans) == type(budget)(2000, 22_500)
    none = CalibConfig.model_validate({"surfels": {"final_points_per_scan": None}})
    assert point_budget(none, scans) == type(budget)(1000, 22_500)
    assert point_budget(cfg, ()) is None
    # a "denser" round no denser than the regular ones is none: the regular rounds' points
    from licalib_cli.pipeline.points import round_points

    sparse = CalibConfig.model_validate({"surfels": {"final_points_per_scan": 500}})
    assert round_points(sparse, len(scans)) == (1000, None)
    assert point_budget(sparse, scans) == type(budget)(1000, 22_500)
    assert round_points(cfg, len(scans)) == (1000, 6000)
