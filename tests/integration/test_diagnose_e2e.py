"""End to end: ``licalib diagnose`` on small simulated bags with a hidden effect, and on a clean
one."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from licalib_cli.cli import main
from licalib_cli.models.intrinsics import ImuIntrinsics, LidarIntrinsics
from licalib_cli.results import CalibrationResult
from licalib_cli.simulation import SimulationSpec, simulate

CONFIG = Path(__file__).resolve().parents[2] / "configs" / "vlp16.yaml"
VLP16_ELEVATION = np.radians(np.arange(-15.0, 16.0, 2.0))

pytestmark = pytest.mark.slow


def _bag(tmp_path: Path, imu: ImuIntrinsics | None = None) -> Path:
    path = tmp_path / "intrinsics.yaml"
    CalibrationResult(
        imu_intrinsics=imu or ImuIntrinsics(),
        lidar_intrinsics=LidarIntrinsics.nominal(VLP16_ELEVATION),
    ).save(path)
    spec = SimulationSpec(
        scenario="sinusoid",
        lidar="vlp16",
        duration_s=8.0,
        seed=41,
        time_offset_s=0.004,
        intrinsics_file=path,
        azimuth_resolution_deg=0.4,
    )
    return simulate(spec, tmp_path / "sim").bag_path


def _diagnose(args: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    try:
        main(["diagnose", *args])
        code = 0
    except SystemExit as err:
        code = int(err.code or 0)
    return code, capsys.readouterr().out


def test_a_hidden_gyro_scale_is_named_added_and_its_gap_shrinks(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bag = _bag(tmp_path, ImuIntrinsics(gyro_scale=np.array([1.004, 0.996, 1.003])))
    out = tmp_path / "diag"
    code, printed = _diagnose([str(bag), "-c", str(CONFIG), "--json", "-o", str(out)], capsys)
    assert code == 0
    data = json.loads(printed)
    assert data["effects_found"][0] == "gyro_scale"
    step = next(s for s in data["steps"] if s["effect"] == "gyro_scale")
    assert step["kept"] and step["delta_bic"] < 0 and step["p_value"] < 1e-6
    assert step["gap_shrink"] >= 0.5
    determined = 0
    for a, true in zip("xyz", (1.004, 0.996, 1.003), strict=True):
        value, sigma = step["estimate"][f"imu.gyro_scale.{a}"], step["sigma"][f"imu.gyro_scale.{a}"]
        if sigma is not None and sigma < 1e-3:  # determined by the motion
            determined += 1
            assert abs(value - true) < max(4 * sigma, 3e-4)
    assert determined >= 2
    assert set(data) >= {"effects_found", "steps", "calibration", "verdict"}
    assert data["calibration"]["model"]["imu"] == ["gyro_scale"]
    written = yaml.safe_load((out / "diagnosis.yaml").read_text())
    assert written["effects_found"] == data["effects_found"]
    assert CalibrationResult.load(out / "calibration.yaml").imu_intrinsics.gyro_scale[0] > 1.002


def test_a_clean_bag_shows_no_effect(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bag = _bag(tmp_path)
    code, printed = _diagnose([str(bag), "-c", str(CONFIG)], capsys)
    assert code == 0
    assert "Effects added to the model: none" in printed
    assert "base model PASS" in printed


def test_bad_diagnose_options_end_in_one_sentence(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bag = tmp_path / "missing.bag"
    with pytest.raises(SystemExit) as err:
        main(["diagnose", str(bag), "--candidates", "gyro_wobble"])
    assert err.value.code == 6
    assert "Unknown candidate effect 'gyro_wobble'" in capsys.readouterr().err
    with pytest.raises(SystemExit) as err:
        main(["diagnose", str(bag), "--plots"])
    assert err.value.code == 6
