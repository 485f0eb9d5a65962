"""A simulated Ouster OS1-64 bag on a sensor clock (stamps from 1000 s, as an Ouster publishes
before PTP/GPS sync) that carries the driver's metadata topic: ``info`` reads ``t`` as ns
relative to the stamp and shows the factory extrinsic; ``calibrate`` calibrates it and reports
the difference from the factory extrinsic in the result file."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from rosbags.highlevel import AnyReader

from licalib_cli.cli import main
from licalib_cli.io.writer import BagFormat, BagWriter
from licalib_cli.results import matrix_from_rpy_deg, rpy_deg_from_matrix
from licalib_cli.simulation import SimulationSpec, simulate

TRANSLATION = (0.05, -0.02, 0.04)
RPY_DEG = (1.0, -2.0, 3.0)
# the factory's numbers are off the truth by this much (what the result must report)
FACTORY_T_ERROR = np.array([0.004, -0.003, 0.002])
FACTORY_YAW_ERROR_DEG = 0.5


def _metadata() -> str:
    """Legacy-format Ouster metadata whose transforms give the factory T_imu_lidar (mm)."""
    rot = matrix_from_rpy_deg(np.add(RPY_DEG, (0.0, 0.0, FACTORY_YAW_ERROR_DEG)))
    lidar_to_sensor = np.eye(4)
    lidar_to_sensor[:3, :3] = rot
    lidar_to_sensor[:3, 3] = 1000.0 * (np.asarray(TRANSLATION) + FACTORY_T_ERROR)
    return json.dumps(
        {
            "prod_line": "OS-1-64",
            "prod_sn": "000000000001",
            "lidar_to_sensor_transform": lidar_to_sensor.ravel().tolist(),
            "imu_to_sensor_transform": np.eye(4).ravel().tolist(),
        }
    )


def _with_metadata(src: Path, dst: Path) -> None:
    """A copy of the ROS1 bag ``src`` with an /ouster/metadata message first."""
    with AnyReader([src]) as reader, BagWriter(dst, BagFormat.ROS1) as w:
        string_t = w.typestore.types["std_msgs/msg/String"]
        w.write_message(
            "/ouster/metadata", "std_msgs/msg/String", string_t(data=_metadata()), reader.start_time
        )
        for conn, record_ns, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            w.write_message(conn.topic, conn.msgtype, msg, record_ns)


@pytest.fixture(scope="module")
def ouster_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("ouster_sim")
    spec = SimulationSpec(
        scenario="sinusoid",
        lidar="os1-64",
        fmt="ros1",
        duration_s=6.0,
        seed=3,
        translation=TRANSLATION,
        rpy_deg=RPY_DEG,
        intrinsics="none",
        azimuth_resolution_deg=0.5,
        base_time_ns=1000 * 1_000_000_000,
        lidar_frame="os_lidar",
    )
    sim = simulate(spec, folder / "sim")
    out = folder / "ouster.bag"
    _with_metadata(sim.bag_path, out)
    return out


def test_info_reads_a_sensor_clock_ouster_bag(
    ouster_bag: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["info", str(ouster_bag), "--json"])
        raise SystemExit(0)
    data = json.loads(capsys.readouterr().out)
    assert exc.value.code in (0, None)
    li = data["lidar"]
    assert (li["time_field"], li["time_unit"], li["time_reference"]) == ("t", "ns", "relative")
    assert not any("span" in p["message"] for p in data["problems"])
    f = data["factory_extrinsic"]
    assert f["sensor"] == "OS-1-64 sn 000000000001" and f["topic"] == "/ouster/metadata"
    np.testing.assert_allclose(f["translation"], np.add(TRANSLATION, FACTORY_T_ERROR), atol=1e-9)
    rpy = np.add(RPY_DEG, (0.0, 0.0, FACTORY_YAW_ERROR_DEG))
    np.testing.assert_allclose(f["rotation_rpy_deg"], rpy, atol=1e-6)


@pytest.mark.slow
def test_result_reports_the_difference_from_the_factory_extrinsic(
    ouster_bag: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "result.yaml"
    main(["calibrate", str(ouster_bag), "-o", str(out)])
    printed = " ".join(capsys.readouterr().out.split())
    result = yaml.safe_load(out.read_text())
    f = result["factory_extrinsic"]
    assert f["source"] == "Ouster metadata on /ouster/metadata"
    ext = result["extrinsic"]
    # the difference is calibrated minus factory, and the calibration is near the truth
    np.testing.assert_allclose(
        f["difference_translation_m"],
        np.subtract(ext["translation"], f["translation"]),
        atol=1e-8,
    )
    np.testing.assert_allclose(f["difference_translation_m"], -FACTORY_T_ERROR, atol=0.003)
    assert f["difference_rotation_deg"] == pytest.approx(FACTORY_YAW_ERROR_DEG, abs=0.1)
    r_cal = matrix_from_rpy_deg(ext["rotation_rpy_deg"])
    r_fac = matrix_from_rpy_deg(f["rotation_rpy_deg"])
    np.testing.assert_allclose(rpy_deg_from_matrix(r_fac), f["rotation_rpy_deg"], atol=1e-6)
    angle = np.degrees(np.arccos(np.clip((np.trace(r_fac.T @ r_cal) - 1) / 2, -1, 1)))
    assert f["difference_rotation_deg"] == pytest.approx(angle, abs=1e-4)
    assert "Against the factory extrinsic" in printed
