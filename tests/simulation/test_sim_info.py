"""Simulator bags in every format are read back by ``licalib info`` with the right layout."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from licalib_cli.cli import main
from licalib_cli.io.writer import BagFormat
from licalib_cli.simulation import LidarKind, SimulationSpec, simulate

# (lidar, spec options, expected info --json lidar fields). The OS1-64 keeps its native
# 1024 columns so that the organised 64 x 1024 layout is checked; the HDL-32E and the OS1-128
# are thinned (128 columns: 1024 / 8); 2.2 s is just above the 2 s a calibration (and so
# ``info``) needs.
LIDARS = {
    LidarKind.VLP16: (
        {"duration_s": 2.2, "azimuth_resolution_deg": 2.0},
        {
            "topic": "/points_raw",
            "time_field": "time",
            "time_unit": "s",
            "time_reference": "relative",
            "stamp_position": "start",
            "beams": 16,
            "ring_field": "ring",
            "height": 1,
            "point_step": 22,
            "is_bigendian": False,
        },
    ),
    LidarKind.HDL32: (
        {"duration_s": 2.2, "azimuth_resolution_deg": 2.0},
        {
            "topic": "/points_raw",
            "time_field": "time",
            "time_unit": "s",
            "beams": 32,
            "ring_field": "ring",
            "height": 1,
            "point_step": 22,
        },
    ),
    LidarKind.OS1_128: (
        {"duration_s": 2.2, "azimuth_resolution_deg": 2.8},
        {
            "topic": "/ouster/points",
            "time_field": "t",
            "time_unit": "ns",
            "beams": 128,
            "ring_field": "ring",
            "height": 128,
            "width": 128,
            "point_step": 48,
        },
    ),
    LidarKind.OS1_64: (
        {"duration_s": 2.2},
        {
            "topic": "/ouster/points",
            "time_field": "t",
            "time_unit": "ns",
            "time_reference": "relative",
            "stamp_position": "start",
            "beams": 64,
            "ring_field": "ring",
            "height": 64,
            "width": 1024,
            "point_step": 48,
            "is_bigendian": False,
        },
    ),
}


@pytest.mark.parametrize("lidar", list(LIDARS), ids=[k.value for k in LIDARS])
@pytest.mark.parametrize("fmt", list(BagFormat), ids=[f.value for f in BagFormat])
def test_info_reads_simulated_bag_layout(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], fmt: BagFormat, lidar: LidarKind
) -> None:
    options, expected = LIDARS[lidar]
    spec = SimulationSpec(lidar=lidar, fmt=fmt, seed=1, **options)
    out = simulate(spec, tmp_path / "sim")
    with pytest.raises(SystemExit) as exc:
        main(["info", str(out.bag_path), "--json"])
        raise SystemExit(0)
    captured = capsys.readouterr()
    assert exc.value.code == 0, captured.err
    data = json.loads(captured.out)
    assert data["format"] == fmt.value and data["usable"] is True
    assert not [p for p in data["problems"] if p["severity"] == "error"]
    li = data["lidar"]
    assert {k: li[k] for k in expected} == expected
    assert li["count"] == out.num_scans and li["rate_hz"] == pytest.approx(10.0)
    assert li["clouds_skipped"] == {}
    imu = data["imu"]
    assert imu["topic"] == "/imu/data" and imu["count"] == out.num_imu
    assert imu["rate_hz"] == pytest.approx(400.0)
    assert (imu["gyro_unit"], imu["accel_unit"]) == ("rad/s", "m/s^2")
    assert abs(data["clock_offset_s"]) < 0.01


@pytest.mark.parametrize(
    ("scenario", "ok", "words"),
    [
        ("sinusoid", True, "all three axes"),
        ("figure8", False, "one axis only ([0.00, 0.00, 1.00]"),
        ("translation", False, "hardly any rotation"),
    ],
)
def test_info_judges_the_motion(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], scenario: str, ok: bool, words: str
) -> None:
    """The pre-flight excitation check: rotation about 3 axes, one axis (planar), none."""
    spec = SimulationSpec(
        scenario=scenario, duration_s=3.0, seed=2, azimuth_resolution_deg=4.0, intrinsics="none"
    )
    out = simulate(spec, tmp_path / "sim")
    with pytest.raises(SystemExit) as exc:
        main(["info", str(out.bag_path), "--json"])
        raise SystemExit(0)
    captured = capsys.readouterr()
    assert exc.value.code == 0, captured.err  # usable; a weak motion is a warning
    data = json.loads(captured.out)
    e = data["imu"]["excitation"]
    assert e["ok"] is ok and words in e["summary"], e
    warned = [p for p in data["problems"] if "The IMU shows" in p["message"]]
    assert bool(warned) is (not ok)
    if scenario == "figure8":
        assert e["rotation_axis_strength_deg_s"][1] < 0.1 * e["rotation_axis_strength_deg_s"][0]
    # the tilt the IMU intrinsics need: the sinusoid turns gravity (16 deg RMS in these 3 s),
    # the planar figure-8 and the pure translation hardly
    if scenario == "sinusoid":
        assert e["gravity_turn_deg"] > 15.0 and "enough" in e["imu_intrinsics"], e
    else:
        # (3 deg: the path's own accelerations tilt the specific force a little)
        assert e["gravity_turn_deg"] < 5.0 and "tilted by tens of degrees" in e["imu_intrinsics"]


def test_motion_excitation_two_axes_and_units() -> None:
    import numpy as np

    from licalib_cli.inspection import motion_excitation

    t = np.linspace(0.0, 10.0, 4001)
    gyro = np.stack([0.5 * np.sin(t), 0.4 * np.cos(1.3 * t), 0.001 * np.sin(7 * t)], axis=1)
    accel = np.tile([0.0, 0.0, 9.81], (t.size, 1))
    e = motion_excitation(gyro, accel)
    assert e.ok and "two axes only" in e.summary
    expected_x = np.degrees(np.sqrt(np.mean(gyro[:, 0] ** 2)))
    assert e.rotation_rms_deg_s[0] == pytest.approx(expected_x, rel=1e-9)
    assert e.rotation_axis_strength[2] < 0.1 * e.rotation_axis_strength[0]
    assert e.accel_std_m_s2 == pytest.approx((0.0, 0.0, 0.0), abs=1e-9)


def test_the_excitation_says_whether_gravity_turned_enough_for_the_imu_intrinsics() -> None:
    """Rocking slowly by A about a horizontal axis turns gravity in the IMU frame by A / sqrt(2)
    RMS (the 0.5 s means shrink a 0.2 Hz swing by 1.6 %): 30 deg is enough for the
    accelerometer's frame, 8 deg is not and the note says what to do. Stamps out of order and
    repeated give the same figure; without stamps there is no such note."""
    import numpy as np
    from scipy.spatial.transform import Rotation

    from licalib_cli.inspection import GRAVITY_TURN_FOR_IMU_DEG, motion_excitation

    def rocking(amplitude_deg: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        t = np.arange(0.0, 10.0, 0.005)
        a, w = np.radians(amplitude_deg), 2 * np.pi * 0.2
        r = Rotation.from_rotvec(np.outer(a * np.sin(w * t), [1.0, 0.0, 0.0])).as_matrix()
        gyro = np.outer(a * w * np.cos(w * t), [1.0, 0.0, 0.0])
        accel = np.einsum("nji,j->ni", r, [0.0, 0.0, 9.81])
        return (t * 1e9).astype(np.int64), gyro, accel

    t, gyro, accel = rocking(30.0)
    e = motion_excitation(gyro, accel, t_ns=t)
    assert e.gravity_turn_deg == pytest.approx(30.0 / np.sqrt(2), rel=0.03)
    assert e.gravity_turn_ok and e.imu_intrinsics_note.startswith("gravity turned 21 deg RMS")
    t, gyro, accel = rocking(8.0)
    e = motion_excitation(gyro, accel, t_ns=t)
    assert e.gravity_turn_deg == pytest.approx(8.0 / np.sqrt(2), rel=0.03)
    assert e.gravity_turn_deg < GRAVITY_TURN_FOR_IMU_DEG and not e.gravity_turn_ok
    assert "only 6 deg" in e.imu_intrinsics_note
    assert "tilted by tens of degrees" in e.imu_intrinsics_note
    # two samples swapped and one repeated: the same turn
    i = np.arange(t.size)
    i[[100, 101]] = i[[101, 100]]
    i = np.insert(i, 500, 500)
    messy = motion_excitation(gyro[i], accel[i], t_ns=t[i])
    assert messy.gravity_turn_deg == pytest.approx(e.gravity_turn_deg, rel=1e-3)
    # an accelerometer reading zeros shows no direction: no figure, rather than 90 deg
    assert motion_excitation(gyro, 0.0 * accel, t_ns=t).gravity_turn_deg is None
    plain = motion_excitation(gyro, accel)
    assert plain.gravity_turn_deg is None and plain.imu_intrinsics_note == ""
    assert plain.gravity_turn_ok
