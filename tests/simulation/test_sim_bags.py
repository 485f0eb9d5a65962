"""simulate(): bags in every format read back with rosbags, truth.yaml, determinism, overwrite."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml
from rosbags.highlevel import AnyReader

from licalib_cli.errors import ConfigError
from licalib_cli.io.writer import BagFormat
from licalib_cli.results import CalibrationResult
from licalib_cli.simulation import (
    LidarKind,
    Scenario,
    SimulationSpec,
    build_setup,
    generate_imu,
    generate_scans,
    simulate,
)
from licalib_cli.truth import Truth

SMALL = {"duration_s": 0.35, "azimuth_resolution_deg": 2.0}


def _read(bag: Path) -> dict[str, list[tuple[int, int, object]]]:
    """topic -> [(record_ns, header stamp ns, message)]."""
    out: dict[str, list[tuple[int, int, object]]] = {}
    with AnyReader([bag]) as reader:
        for conn, t_rec, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
            out.setdefault(conn.topic, []).append((t_rec, stamp, msg))
    return out


def _structured(msg: object) -> np.ndarray:
    names = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
    dt = np.dtype(
        {
            "names": [f.name for f in msg.fields],  # type: ignore[attr-defined]
            "formats": ["<" + names[f.datatype] for f in msg.fields],  # type: ignore[attr-defined]
            "offsets": [f.offset for f in msg.fields],  # type: ignore[attr-defined]
            "itemsize": msg.point_step,  # type: ignore[attr-defined]
        }
    )
    return np.frombuffer(np.asarray(msg.data, np.uint8).tobytes(), dtype=dt).reshape(  # type: ignore[attr-defined]
        msg.height,
        msg.width,  # type: ignore[attr-defined]
    )


@pytest.mark.parametrize("fmt", list(BagFormat))
def test_bag_round_trip(tmp_path: Path, fmt: BagFormat) -> None:
    spec = SimulationSpec(fmt=fmt, time_offset_s=0.004, lidar_clock_offset_s=50.0, **SMALL)
    out = simulate(spec, tmp_path / "sim")
    expected_path = tmp_path / "sim" / ("bag.bag" if fmt is BagFormat.ROS1 else "bag")
    assert out.bag_path == expected_path and expected_path.exists()
    msgs = _read(out.bag_path)
    assert set(msgs) == {"/imu/data", "/points_raw"}

    imu, imu_truth = generate_imu(spec)
    imu_msgs = msgs["/imu/data"]
    assert [s for _, s, _ in imu_msgs] == imu.t_ns.tolist()
    assert [r for r, _, _ in imu_msgs] == imu_truth.record_ns.tolist()
    m = imu_msgs[10][2]
    assert m.header.frame_id == "imu_link"  # type: ignore[attr-defined]
    assert [m.angular_velocity.x, m.angular_velocity.y, m.angular_velocity.z] == imu.gyro[
        10
    ].tolist()  # type: ignore[attr-defined]
    assert [m.linear_acceleration.x, m.linear_acceleration.y, m.linear_acceleration.z] == imu.accel[
        10
    ].tolist()  # type: ignore[attr-defined]

    scans = list(generate_scans(spec))
    cloud_msgs = msgs["/points_raw"]
    assert len(cloud_msgs) == len(scans) == out.num_scans == 3
    assert [s for _, s, _ in cloud_msgs] == [sc.stamp_ns for sc in scans]
    assert scans[1].stamp_ns == spec.base_time_ns + 100_000_000 - 4_000_000 + 50_000_000_000
    msg = cloud_msgs[1][2]
    assert msg.header.frame_id == "velodyne" and msg.point_step == 22  # type: ignore[attr-defined]
    assert msg.height == 1 and msg.is_bigendian is False  # type: ignore[attr-defined]
    assert [(f.name, f.offset, f.datatype) for f in msg.fields] == [  # type: ignore[attr-defined]
        ("x", 0, 7),
        ("y", 4, 7),
        ("z", 8, 7),
        ("intensity", 12, 7),
        ("ring", 16, 4),
        ("time", 18, 7),
    ]
    assert _structured(msg).reshape(-1).tobytes() == scans[1].points.tobytes()
    # Record order is time order across topics.
    records = sorted(r for topic in msgs.values() for r, _, _ in topic)
    assert records[0] == spec.base_time_ns


def test_ouster_round_trip(tmp_path: Path) -> None:
    spec = SimulationSpec(lidar=LidarKind.OS1_64, fmt=BagFormat.ROS2_DB3, **SMALL)
    out = simulate(spec, tmp_path)
    msgs = _read(out.bag_path)
    cloud = msgs["/ouster/points"][0][2]
    assert cloud.header.frame_id == "os_sensor"  # type: ignore[attr-defined]
    assert (cloud.height, cloud.width, cloud.point_step) == (64, 128, 48)  # type: ignore[attr-defined]
    assert cloud.row_step == 48 * 128  # type: ignore[attr-defined]
    names = [(f.name, f.offset) for f in cloud.fields]  # type: ignore[attr-defined]
    assert names == [
        ("x", 0),
        ("y", 4),
        ("z", 8),
        ("intensity", 16),
        ("t", 20),
        ("reflectivity", 24),
        ("ring", 26),
        ("ambient", 28),
        ("range", 32),
    ]
    scan = next(iter(generate_scans(spec, indices=[0])))
    assert _structured(cloud).tobytes() == scan.points.tobytes()


def test_truth_yaml(tmp_path: Path) -> None:
    spec = SimulationSpec(
        scenario=Scenario.FIGURE8,
        mounting="B",
        time_offset_s=0.0105,
        lidar_clock_offset_s=-3.0,
        seed=7,
        random_extrinsic=True,
        **SMALL,
    )
    out = simulate(spec, tmp_path)
    truth = Truth.load(out.truth_path)
    setup = build_setup(spec)
    err = truth.extrinsic.error_to(setup.extrinsic)
    assert err["translation_m"] < 1e-8 and err["rotation_deg"] < 1e-8
    assert truth.extrinsic.time_offset_s == pytest.approx(0.0105, abs=1e-12)
    assert np.allclose(truth.imu_intrinsics.gyro_scale, setup.imu_intrinsics.gyro_scale, atol=1e-9)
    assert truth.lidar_intrinsics is not None
    assert np.allclose(
        truth.lidar_intrinsics.range_offset, setup.lidar_intrinsics.range_offset, atol=1e-9
    )
    assert truth.scenario is not None and truth.simulation is not None
    assert truth.scenario.name == "figure8" and truth.scenario.mounting == "B"
    assert truth.seed == 7
    sim = truth.simulation
    assert sim.clock.lidar_clock_offset_s == -3.0 and truth.lidar_clock_offset_s == -3.0
    # g in G = R_W_I(t_first)^T g_W: for mounting B the IMU is tilted 30 deg about its y axis.
    assert np.allclose(
        sim.gravity_in_first_imu_frame, -9.81 * np.array([0.5, 0.0, 0.866]), atol=2e-3
    )
    assert sim.lidar.model == "vlp16" and sim.imu.rate_hz == 400.0
    # The simulation sections read back to what was written; as a result, the file gives the
    # true values alone.
    written = yaml.safe_load(out.truth_path.read_text())
    assert out.truth.to_yaml() == out.truth_path.read_text()
    for key in ("scenario", "seed", "simulation"):
        assert truth.to_dict()[key] == written[key]
    as_result = CalibrationResult.load(out.truth_path)
    assert as_result.extrinsic.error_to(truth.extrinsic)["translation_m"] == 0.0
    assert "simulation" not in as_result.to_dict()


def test_deterministic_per_seed(tmp_path: Path) -> None:
    spec = SimulationSpec(scenario=Scenario.SHAKE, seed=3, fmt=BagFormat.ROS2_MCAP, **SMALL)
    a = _read(simulate(spec, tmp_path / "a").bag_path)
    b = _read(simulate(spec, tmp_path / "b").bag_path)
    c = _read(simulate(spec.with_(seed=4), tmp_path / "c").bag_path)

    def digest(msgs: dict) -> list:  # type: ignore[type-arg]
        clouds = [bytes(_structured(m).tobytes()) for _, _, m in msgs["/points_raw"]]
        imu = [(m.angular_velocity.x, m.linear_acceleration.z) for _, _, m in msgs["/imu/data"]]
        return [clouds, imu]

    assert digest(a) == digest(b)
    assert digest(a) != digest(c)
    assert (tmp_path / "a" / "truth.yaml").read_text().replace("/a/", "/b/") == (
        tmp_path / "b" / "truth.yaml"
    ).read_text()


def test_refuses_to_overwrite_without_force(tmp_path: Path) -> None:
    spec = SimulationSpec(duration_s=0.1, azimuth_resolution_deg=5.0)
    out = simulate(spec, tmp_path)
    with pytest.raises(ConfigError, match="--force"):
        simulate(spec, tmp_path)
    again = simulate(spec.with_(seed=1), tmp_path, force=True)
    assert again.bag_path == out.bag_path and out.bag_path.is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bag.bag", "truth.yaml"]
    # A folder that is not a bag is never deleted, even with force.
    other = tmp_path / "x"
    (other / "bag").mkdir(parents=True)
    (other / "bag" / "notes.txt").write_text("keep")
    ros2 = spec.with_(fmt=BagFormat.ROS2_DB3)
    with pytest.raises(ConfigError, match="does not look like a bag"):
        simulate(ros2, other, force=True)
    assert (other / "bag" / "notes.txt").exists()


def test_progress_callback(tmp_path: Path) -> None:
    calls: list[tuple[int, int]] = []
    simulate(SimulationSpec(**SMALL), tmp_path, progress=lambda d, t: calls.append((d, t)))
    assert calls == [(1, 3), (2, 3), (3, 3)]
