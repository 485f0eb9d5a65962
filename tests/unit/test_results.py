"""Result file (schema v1): round trips, conventions, atomic writes."""

from __future__ import annotations

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from licalib_cli.errors import ConfigError
from licalib_cli.models.intrinsics import ImuIntrinsics, LidarIntrinsics
from licalib_cli.results import (
    CalibrationResult,
    Extrinsic,
    matrix_from_rpy_deg,
    rpy_deg_from_matrix,
)


def _random_result(rng: np.random.Generator) -> CalibrationResult:
    rot = Rotation.random(random_state=1).as_matrix()
    imu = ImuIntrinsics(
        gyro_scale=1 + 1e-3 * rng.standard_normal(3),
        gyro_misalignment=1e-3 * rng.standard_normal(3),
        gyro_rotation=Rotation.from_rotvec(1e-2 * rng.standard_normal(3)).as_quat(),
        accel_scale=1 + 1e-3 * rng.standard_normal(3),
        accel_misalignment=1e-3 * rng.standard_normal(3),
        gyro_bias=1e-3 * rng.standard_normal(3),
        accel_bias=1e-2 * rng.standard_normal(3),
    )
    n = 16
    lidar = LidarIntrinsics(
        nominal_elevation=np.radians(np.linspace(-15, 15, n)),
        elevation_correction=np.radians(0.1) * rng.standard_normal(n),
        azimuth_correction=np.radians(0.05) * rng.standard_normal(n),
        vertical_offset=0.005 * rng.standard_normal(n),
        horizontal_offset=0.005 * rng.standard_normal(n),
        range_scale=1 + 5e-5 * rng.standard_normal(n),
        range_offset=0.01 * rng.standard_normal(n),
    )
    ext = Extrinsic(rot, np.array([0.3, -0.15, 0.05]), time_offset_s=-0.0123)
    return CalibrationResult(ext, imu, lidar, gravity_G=(0.0, 0.0, -9.81))


def test_yaml_round_trip_is_exact_to_printed_precision(tmp_path):
    res = _random_result(np.random.default_rng(0))
    path = tmp_path / "out" / "result.yaml"
    res.save(path)
    back = CalibrationResult.load(path)
    err = back.extrinsic.error_to(res.extrinsic)
    assert err["translation_m"] < 1e-9
    assert err["rotation_deg"] < 1e-8
    assert err["time_offset_s"] < 1e-12
    np.testing.assert_allclose(
        back.imu_intrinsics.gyro_scale, res.imu_intrinsics.gyro_scale, atol=1e-9
    )
    np.testing.assert_allclose(
        back.lidar_intrinsics.elevation_correction,
        res.lidar_intrinsics.elevation_correction,
        atol=1e-9,
    )
    assert back.gravity_G == (0.0, 0.0, -9.81)
    # Saving the loaded result reproduces the same text.
    assert back.to_yaml() == res.to_yaml()
    assert not [p for p in path.parent.iterdir() if p.name.startswith(".")]


def test_schema_keys_and_conventions():
    res = _random_result(np.random.default_rng(1))
    d = yaml.safe_load(res.to_yaml())
    assert d["schema_version"] == 1
    assert set(d["extrinsic"]) == {
        "translation",
        "rotation_quaternion",
        "rotation_rpy_deg",
        "time_offset_s",
    }
    q = np.array(d["extrinsic"]["rotation_quaternion"])
    assert q[3] >= 0  # [x, y, z, w], canonical sign
    np.testing.assert_allclose(
        Rotation.from_quat(q).as_matrix(), res.extrinsic.rotation, atol=1e-10
    )
    # The quaternion and the rpy describe the same rotation: R = Rz(yaw) Ry(pitch) Rx(roll).
    r, p, y = np.radians(d["extrinsic"]["rotation_rpy_deg"])
    rz = Rotation.from_rotvec([0, 0, y]).as_matrix()
    ry = Rotation.from_rotvec([0, p, 0]).as_matrix()
    rx = Rotation.from_rotvec([r, 0, 0]).as_matrix()
    np.testing.assert_allclose(rz @ ry @ rx, res.extrinsic.rotation, atol=1e-8)


def test_rpy_helpers_invert_each_other():
    rpy = np.array([1.0, 2.0, 5.0])
    np.testing.assert_allclose(rpy_deg_from_matrix(matrix_from_rpy_deg(rpy)), rpy, atol=1e-12)


def test_wrong_schema_version_is_refused(tmp_path):
    path = tmp_path / "r.yaml"
    path.write_text("schema_version: 7\nextrinsic: {}\n")
    with pytest.raises(ConfigError, match="schema_version 7"):
        CalibrationResult.load(path)


def test_missing_and_malformed_result_files(tmp_path):
    with pytest.raises(ConfigError, match="does not exist"):
        CalibrationResult.load(tmp_path / "nope.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("extrinsic: [1, 2\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        CalibrationResult.load(bad)


def test_truth_on_a_shifted_clock_compares_totals() -> None:
    """t_imu = t_lidar - L + c (simulator) and t_imu = t_lidar + shift + c' (calibration)."""
    true = Extrinsic(np.eye(3), np.zeros(3), -0.012)
    on = true.on_shifted_clock(lidar_clock_offset_s=1234.5, applied_shift_s=-1234.511)
    assert on.time_offset_s == pytest.approx(-0.001, abs=1e-9)
    assert true.on_shifted_clock(0.0, 0.0).time_offset_s == -0.012
    np.testing.assert_array_equal(on.rotation, true.rotation)


def test_extra_terms_round_trip_and_an_incomplete_section_is_one_sentence(tmp_path):
    from licalib_cli.sections import ExtraTerms

    terms = ExtraTerms(reference_ns=1_700_000_004_000_000_123, clock_drift=2.8e-4)
    path = tmp_path / "r.yaml"
    CalibrationResult(extra_terms=terms).save(path)
    back = CalibrationResult.load(path).extra_terms
    assert back == terms and isinstance(back.reference_ns, int)  # stamps stay exact
    data = yaml.safe_load(path.read_text())
    del data["extra_terms"]["reference_ns"]
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError, match=r"`extra_terms\.reference_ns` is missing"):
        CalibrationResult.load(path)


def test_truth_table_rotation_error_is_about_the_lidar_axes_near_a_pitch_of_90_deg() -> None:
    """Near a pitch of 90 deg a rotation of 0.006 deg moves roll and yaw by far more: the error
    column must show the error about the LiDAR axes, the axes of the sigma column."""
    from licalib_cli.results import estimate_rows
    from licalib_cli.sections import Uncertainty

    r_true = matrix_from_rpy_deg((30.0, -86.4, 120.0))
    small = np.radians([0.004, -0.003, 0.0035])  # about the LiDAR axes
    r_est = r_true @ Rotation.from_rotvec(small).as_matrix()
    truth = Extrinsic(r_true, np.array([0.1, 0.0, 0.0]), 0.0)
    est = Extrinsic(r_est, np.array([0.1, 0.0, 0.0]), 0.0)
    unc = Uncertainty(
        translation_std_m=(1e-3, 1e-3, 1e-3),
        rotation_std_deg=(0.01, 0.01, 0.01),
        time_offset_std_s=1e-5,
    )
    rows = estimate_rows(CalibrationResult(est, uncertainty=unc), truth)
    by_name = {r[0]: r for r in rows}
    shown = [float(by_name[n][-1].split()[0]) for n in ("roll", "pitch", "yaw")]
    np.testing.assert_allclose(shown, np.degrees(small), atol=6e-5)
    # the Euler differences would have claimed several sigmas on roll and yaw
    euler = rpy_deg_from_matrix(r_est) - rpy_deg_from_matrix(r_true)
    assert np.abs(euler[[0, 2]]).min() > 0.015  # against at most 0.004 deg about any axis
    assert [by_name[n][3] for n in ("roll", "pitch", "yaw")] == [
        f"{v:+.4f} deg" for v in rpy_deg_from_matrix(r_true)
    ]
