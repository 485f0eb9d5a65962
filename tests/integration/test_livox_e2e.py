"""End to end: non-repetitive Livox-like scanners (lines, not rings) are calibrated as such."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from licalib_cli.cli import main
from licalib_cli.config import CalibConfig
from licalib_cli.io.reader import read_imu
from licalib_cli.pipeline.read import measure_noise, read, read_recording
from licalib_cli.simulation import SimulationSpec, simulate


def _bag(tmp_path_factory: pytest.TempPathFactory, lidar: str, fmt: str, seed: int) -> Path:
    spec = SimulationSpec(
        scenario="sinusoid",
        lidar=lidar,
        fmt=fmt,
        duration_s=6.0,
        seed=seed,
        time_offset_s=0.006,
        intrinsics="none",
    )
    return simulate(spec, tmp_path_factory.mktemp(lidar)).bag_path


@pytest.fixture(scope="module")
def mid360_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _bag(tmp_path_factory, "mid360", "ros2-db3", 21)


def _errors(result: dict, truth: dict) -> tuple[np.ndarray, float]:
    ext, true = result["extrinsic"], truth["extrinsic"]
    dt = np.subtract(ext["translation"], true["translation"])
    return dt, abs(ext["time_offset_s"] - true["time_offset_s"])


@pytest.mark.slow
def test_a_mid360_is_calibrated_as_a_non_repetitive_scanner(
    mid360_bag: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "result.yaml"
    truth = mid360_bag.parent / "truth.yaml"
    main(["calibrate", str(mid360_bag), "-o", str(out), "--truth", str(truth)])
    printed = capsys.readouterr()
    result = yaml.safe_load(out.read_text())
    dt, dtime = _errors(result, yaml.safe_load(truth.read_text()))
    sigma = np.asarray(result["uncertainty"]["translation_std_m"])
    assert np.all(np.abs(dt) <= 3 * sigma) and np.linalg.norm(dt) < 0.005
    assert dtime < 0.0005
    # the lines are taken for what they are: no per-beam intrinsics tested or estimated, and the
    # resolved config says what the data showed
    assert "non-repetitive scanner" in printed.err
    names = {e["name"] for e in result["consistency"]["effects"]}
    assert "lidar_point_time" in names
    assert not names & {"lidar_range_offset", "lidar_elevation", "lidar_azimuth"}
    resolved = yaml.safe_load((tmp_path / "result.config.yaml").read_text())
    assert resolved["lidar"]["scan_pattern"] == "non_repetitive"
    # the range noise measured along the lines is the simulated 2 cm
    lidar_check = next(c for c in result["consistency"]["sensors"] if c["sensor"] == "lidar")
    assert lidar_check["noise"][0] == pytest.approx(0.02, rel=0.15)
    # at 2 cm, below the spinning LiDARs' 2.5 cm, the refits with more range noise ran
    assert "more range noise (2 draws)" in " ".join(printed.err.split())


def test_per_beam_intrinsics_of_a_mid360_are_refused_with_the_fix(
    mid360_bag: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["calibrate", str(mid360_bag), "--intrinsics", "all", "-o", str(tmp_path / "r.yaml")])
    assert exc.value.code == 6
    err = capsys.readouterr().err
    assert "non-repetitive scanner" in err and "--intrinsics imu or none" in err
    assert not (tmp_path / "r.yaml").exists()


@pytest.fixture(scope="module")
def livox_shake(tmp_path_factory: pytest.TempPathFactory) -> Path:
    spec = SimulationSpec(scenario="shake", lidar="mid360", duration_s=3.0, seed=13308)
    return simulate(spec, tmp_path_factory.mktemp("shake")).bag_path


def test_a_livox_imu_in_g_is_read_in_rad_s_where_the_data_cannot_tell(
    livox_shake: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A shake hardly tilts the rig, so the gyro's unit is not in the data; an accelerometer in
    g is taken with deg/s (IMUs' raw units), which made a Livox's shake 'hardly rotate' (0.6
    deg) and refused it. Beside Livox clouds it is taken in rad/s, as the driver publishes."""
    main(["info", str(livox_shake), "--json"])
    report = json.loads(capsys.readouterr().out)
    imu = report["imu"]
    assert (imu["accel_unit"], imu["gyro_unit"]) == ("g", "rad/s")
    assert imu["gyro_unit_basis"] == "Livox driver: g with rad/s"
    assert report["lidar"]["scan_pattern"] == "non_repetitive"
    # the IMU read on its own (select-segments' ranking) finds the clouds beside it too
    _, units, _ = read_imu(livox_shake, CalibConfig())
    assert (units.gyro_unit, units.gyro_source, units.livox) == ("rad/s", "assumed", True)


def test_an_avias_rosette_is_read_as_lines_and_its_noise_measured_along_them(
    tmp_path_factory: pytest.TempPathFactory,
) -> None:
    """The Avia's lines turn back and forth in azimuth (rosettes): sorted by azimuth, a line's
    neighbours lie on other petals, and the range noise measured so is many times the truth
    (the association, the surfel thickness and the weights follow from it)."""
    spec = SimulationSpec(scenario="sinusoid", lidar="avia", duration_s=2.0, seed=13212)
    bag = simulate(spec, tmp_path_factory.mktemp("avia")).bag_path
    cfg = CalibConfig()
    rec = read_recording(bag, cfg)
    by_azimuth = measure_noise(rec, cfg, 6).range_measured_m
    along = measure_noise(rec, cfg, 6, along_lines=True).range_measured_m
    assert along == pytest.approx(0.02, rel=0.15)
    assert by_azimuth > 5 * along
    segment = read(bag, cfg)
    assert segment.pattern.non_repetitive and segment.pattern.source == "data"
    assert segment.noise.range_measured_m == along
    # the model's beams are elevation bins, the lines' points within a bin of their beam's
    scan = segment.recording.scans[0]
    assert scan.ring is not None
    elevation = np.arcsin(scan.xyz[:, 2] / np.linalg.norm(scan.xyz, axis=1))
    assert np.max(np.abs(elevation - segment.nominal_elevation[scan.ring])) <= np.radians(0.1)
