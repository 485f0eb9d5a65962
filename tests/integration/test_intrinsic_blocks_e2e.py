"""End to end: each intrinsic block of the model estimated on its own.

A small simulated bag carries an error in one block only (the IMU's on a shake, which turns
the rig about every axis; the LiDAR's per beam on the paper's sinusoid), and the model names
that block alone (``model.imu`` / ``model.lidar``). The calibration must report the block's
numbers with sigmas that cover the truth, take most of the error out, and keep the extrinsic
accurate. ``test_intrinsics_e2e`` estimates the blocks together.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml
from light_config import LIGHT_VLP16
from test_intrinsics_e2e import VLP16_ELEVATION, _assert_sigmas_cover, _beam_errors

from licalib_cli.cli import main
from licalib_cli.geometry import so3
from licalib_cli.models.intrinsics import ImuIntrinsics, LidarIntrinsics
from licalib_cli.results import CalibrationResult
from licalib_cli.simulation import SimulationSpec, simulate

pytestmark = pytest.mark.slow

_RNG = np.random.default_rng(61)
_BEAMS = VLP16_ELEVATION.size


def _per_beam(std: float, gauge: bool = True) -> np.ndarray:
    """Errors drawn for every beam; with ``gauge`` beam 0 keeps its nominal (the gauge)."""
    values = _RNG.normal(0.0, std, _BEAMS)
    if gauge:
        values[0] = 0.0
    return values


IMU_ERRORS: dict[str, dict[str, np.ndarray]] = {
    # model.imu block -> ImuIntrinsics fields carrying its error (scales of 0.2-0.4 %,
    # misalignments of 0.06-0.11 deg, a gyro-to-IMU rotation of about 0.3 deg)
    "gyro_scale": {"gyro_scale": np.array([1.003, 0.997, 1.002])},
    "gyro_misalignment": {"gyro_misalignment": np.array([0.0015, -0.001, 0.0012])},
    "gyro_rotation": {"gyro_rotation": so3.matrix_to_quat(so3.exp(np.radians([0.2, -0.15, 0.15])))},
    "accel_scale": {"accel_scale": np.array([0.996, 1.003, 1.002])},
    "accel_misalignment": {"accel_misalignment": np.array([-0.0012, 0.0019, 0.001])},
}

LIDAR_ERRORS: dict[str, tuple[str, str, np.ndarray]] = {
    # model.lidar block -> (intrinsics_uncertainty key, LidarIntrinsics field, error per beam):
    # the paper's sizes (Table sensor_intrinsic_setting), the range scale ten times its 0.005 %
    # (at the paper's size it moves a 10 m return by 0.5 mm, below what 8 s determine)
    "elevation": ("elevation_deg", "elevation_correction", np.radians(_per_beam(0.1))),
    "azimuth": ("azimuth_deg", "azimuth_correction", np.radians(_per_beam(0.05))),
    "vertical_offset": ("vertical_offset_m", "vertical_offset", _per_beam(0.005)),
    "horizontal_offset": ("horizontal_offset_m", "horizontal_offset", _per_beam(0.005)),
    "range_scale": ("range_scale", "range_scale", 1.0 + _per_beam(0.0005, gauge=False)),
}


LONGER = {"accel_scale", "accel_misalignment", "range_scale"}
"""Blocks calibrated on 8 s bags; the others on 6 s. On 6 s the accelerometer's misalignment
kept 60 % of its error, its scales 30 % and the range scales 28 %, against at most 20 % for
the other blocks."""


def _calibrate(
    tmp_path: Path, scenario: str, imu: ImuIntrinsics, lidar: LidarIntrinsics, model: dict
) -> tuple[dict, CalibrationResult, CalibrationResult]:
    """Simulate a VLP-16 bag with these intrinsics and calibrate it with ``model`` (8 s for a
    block of :data:`LONGER`, else 6 s)."""
    (block,) = (*model["imu"], *model["lidar"])
    intrinsics = tmp_path / "intrinsics.yaml"
    CalibrationResult(imu_intrinsics=imu, lidar_intrinsics=lidar).save(intrinsics)
    spec = SimulationSpec(
        scenario=scenario,
        lidar="vlp16",
        duration_s=8.0 if block in LONGER else 6.0,
        seed=62,
        time_offset_s=0.004,
        intrinsics_file=intrinsics,
        azimuth_resolution_deg=0.4,
    )
    sim = simulate(spec, tmp_path / "sim")
    tree = yaml.safe_load(LIGHT_VLP16.read_text())
    tree["model"] = model
    config = tmp_path / "config.yaml"
    config.write_text(yaml.safe_dump(tree))
    out = tmp_path / "result.yaml"
    try:
        main(["calibrate", str(sim.bag_path), "-c", str(config), "-o", str(out)])
    except SystemExit as err:
        assert err.code in (0, None), f"exit {err.code}"
    return yaml.safe_load(out.read_text()), CalibrationResult.load(out), sim.truth


def _assert_extrinsic(raw: dict, result: CalibrationResult, truth: CalibrationResult) -> None:
    """The extrinsic within 5 mm and 0.1 deg, and within three times its reported sigmas (a
    gyro-to-IMU rotation leaves the extrinsic rotation to the accelerometer: its sigma grows)."""
    error = result.extrinsic.error_to(truth.extrinsic)
    sigma_t = float(np.linalg.norm(raw["uncertainty"]["translation_std_m"]))
    sigma_r = float(np.linalg.norm(raw["uncertainty"]["rotation_std_deg"]))
    assert error["translation_m"] < min(0.005, 3.0 * sigma_t), (error, sigma_t)
    assert error["rotation_deg"] < min(0.1, 3.0 * sigma_r), (error, sigma_r)


@pytest.mark.parametrize("block", sorted(IMU_ERRORS))
def test_an_imu_block_alone_is_recovered_within_its_sigmas(tmp_path: Path, block: str) -> None:
    imu = ImuIntrinsics().with_(**IMU_ERRORS[block])
    raw, result, truth = _calibrate(
        tmp_path,
        "shake",
        imu,
        LidarIntrinsics.nominal(VLP16_ELEVATION),
        {"imu": [block], "lidar": []},
    )
    assert raw["model"]["imu"] == [block] and raw["model"]["lidar"] == []
    est, true = result.imu_intrinsics, truth.imu_intrinsics
    if block == "gyro_rotation":
        relative = so3.quat_to_matrix(true.gyro_rotation).T @ so3.quat_to_matrix(est.gyro_rotation)
        err = np.degrees(so3.log(relative))
        injected = np.degrees(so3.log(so3.quat_to_matrix(true.gyro_rotation)))
        sigma = raw["intrinsics_uncertainty"]["gyro_rotation_deg"]
    else:
        err = np.asarray(getattr(est, block)) - getattr(true, block)
        injected = getattr(true, block) - (1.0 if block.endswith("scale") else 0.0)
        sigma = raw["intrinsics_uncertainty"][block]
    # measured: every block's three numbers determined, within 0.59-1.88 of their sigmas, 6-28 %
    # of the injected error left (the accelerometer's misalignment the most, on 8 s), the
    # extrinsic 0.2-0.7 mm and 0.009-0.052 deg off (the last with the gyro-to-IMU rotation, whose
    # extrinsic rotation sigma is 0.095 deg on 6 s)
    determined = np.array([s is not None for s in sigma])
    # a shake determines all three numbers of each block
    assert determined.all(), (block, sigma)
    sig = np.array(sigma, dtype=float)
    assert np.all(np.abs(err) < 3.0 * sig), (block, err, sig)
    assert np.mean(np.abs(err)) < np.mean(np.abs(injected)) / 3, (block, err, injected)
    _assert_extrinsic(raw, result, truth)


@pytest.mark.parametrize("block", sorted(LIDAR_ERRORS))
def test_a_lidar_block_alone_is_recovered_within_its_sigmas(tmp_path: Path, block: str) -> None:
    key, field, values = LIDAR_ERRORS[block]
    lidar = LidarIntrinsics.nominal(VLP16_ELEVATION).with_(**{field: values})
    raw, result, truth = _calibrate(
        tmp_path, "sinusoid", ImuIntrinsics(), lidar, {"imu": [], "lidar": [block]}
    )
    assert raw["model"]["lidar"] == [block] and raw["model"]["gauge_beam"] == 0
    errors = _beam_errors(raw, result, truth)
    assert set(errors) == {key}
    err, sig, injected = errors[key]
    # measured: every beam but the gauge determined, within 0.71-1.23 of their sigmas, 2-12 % of
    # the injected error left (the range scales' 26 %, on 8 s), the extrinsic 0.8-1.4 mm and
    # 0.004-0.008 deg off
    det = np.isfinite(sig)
    # every beam but the gauge's (whose angles and offsets are held: only its range scale and
    # offset are free)
    assert det.sum() >= _BEAMS - (0 if block == "range_scale" else 1), sig
    _assert_sigmas_cover(np.abs(err[det]) / sig[det])
    assert np.mean(np.abs(err[det])) < np.mean(np.abs(injected[det])) / 3, (err, injected)
    _assert_extrinsic(raw, result, truth)
