"""Exporters: each output is read back with a parser of its format and, where the target tool
applies the numbers to data, with that tool's own use of them (read from its sources), so that
every direction and sign is pinned; mountings include 180 degree flips, a gimbal-lock pitch and
negative time offsets with a LiDAR clock shift.
"""

from __future__ import annotations

import argparse
import json
import math
import shlex
import xml.etree.ElementTree as ET
from dataclasses import dataclass, replace

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from licalib_cli.errors import ConfigError, VerdictFailure
from licalib_cli.export import (
    ExportTarget,
    Frames,
    ParentSensor,
    export,
    exportable,
    resolve_frames,
    to_fast_lio,
    to_json,
    to_kalibr,
    to_lio_sam,
    to_tf2,
    to_urdf,
)
from licalib_cli.results import CalibrationResult, Extrinsic
from licalib_cli.sections import (
    ExtraTerms,
    Provenance,
    RecordingSection,
    Uncertainty,
    VerdictSection,
)

TOL = 1e-9


@dataclass(frozen=True)
class Case:
    """A mounting: ``p_imu = R p_lidar + t``, ``t_imu = t_lidar + shift + dt``."""

    R: np.ndarray
    t: np.ndarray
    dt: float
    shift: float = 0.0

    def p_imu(self, p_lidar: np.ndarray) -> np.ndarray:
        return p_lidar @ self.R.T + self.t

    def p_lidar(self, p_imu: np.ndarray) -> np.ndarray:
        return np.linalg.solve(self.R, (p_imu - self.t).T).T

    def t_imu(self, t_lidar: float) -> float:
        return t_lidar + self.shift + self.dt


def _rpy_deg(roll: float, pitch: float, yaw: float) -> np.ndarray:
    r, p, y = np.radians([roll, pitch, yaw])
    rx = np.array([[1, 0, 0], [0, np.cos(r), -np.sin(r)], [0, np.sin(r), np.cos(r)]])
    ry = np.array([[np.cos(p), 0, np.sin(p)], [0, 1, 0], [-np.sin(p), 0, np.cos(p)]])
    rz = np.array([[np.cos(y), -np.sin(y), 0], [np.sin(y), np.cos(y), 0], [0, 0, 1]])
    return rz @ ry @ rx


CASES = {
    "general": Case(_rpy_deg(10.0, -20.0, 135.0), np.array([0.3, -1e-5, 0.05]), 0.005),
    # 180 degrees about x (upside-down LiDAR) and the LiDAR stamps late
    "flip-x-negative-offset": Case(np.diag([1.0, -1.0, -1.0]), np.array([0.1, 0.2, -0.3]), -0.0123),
    # 180 degrees about (1, 1, 0)/sqrt(2), LiDAR clock 3.5 s behind and a negative offset
    "flip-oblique-clock-shift": Case(
        np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]),
        np.array([-0.05, 0.4, 1.2]),
        -0.0042,
        -3.5,
    ),
    "pitch-90": Case(_rpy_deg(30.0, 90.0, -60.0), np.array([0.0, 0.0, -0.12]), 0.0),
}


def _result(
    case: Case,
    verdict: str = "pass",
    reasons: tuple[str, ...] = (),
    frames: tuple[str, str] | None = ("imu_link", "velodyne"),
) -> CalibrationResult:
    fields = (
        "bag.bag",
        "/imu/data",
        "/points_raw",
        4001,
        100,
        10.0,
        1700000000000000000,
        case.shift,
        case.shift,
    )
    recording = (
        RecordingSection(*fields)
        if frames is None
        else RecordingSection(*fields, imu_frame=frames[0], lidar_frame=frames[1])
    )
    return CalibrationResult(
        extrinsic=Extrinsic(case.R, case.t, case.dt),
        uncertainty=Uncertainty((0.001, 0.001, math.inf), (0.01, 0.01, 0.01), 1e-4),
        verdict=VerdictSection(verdict, reasons),
        recording=recording,
        provenance=Provenance("0.1.0", "0123456789abcdef", "2026-11-24T07:00:00Z"),
    )


@pytest.fixture(params=sorted(CASES), ids=sorted(CASES))
def case(request: pytest.FixtureRequest) -> Case:
    return CASES[request.param]


@pytest.fixture
def points() -> np.ndarray:
    return np.random.default_rng(7).normal(scale=5.0, size=(20, 3))


def _floats(values: list[object]) -> np.ndarray:
    """YAML numbers as floats, refusing ints (ROS 2 refuses them for double arrays) and
    strings (what PyYAML makes of ``1e-05``)."""
    assert all(isinstance(v, float) for v in values), values
    return np.asarray(values, dtype=np.float64)


# --------------------------------------------------------------------------------------------
# FAST-LIO / LI-Init
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("ros2", [False, True], ids=["ros1", "ros2"])
def test_fast_lio_maps_points_and_stamps_as_fast_lio_does(
    case: Case, points: np.ndarray, ros2: bool
) -> None:
    data = yaml.safe_load(to_fast_lio(_result(case), ros2=ros2))
    if ros2:
        data = data["/**"]["ros__parameters"]
    common, mapping = data["common"], data["mapping"]
    # laserMapping.cpp: Lidar_R_wrt_IMU << MAT_FROM_ARRAY(extrinR) (Eigen comma initialiser:
    # row-major), then p_imu = offset_R_L_I * p_lidar + offset_T_L_I
    R = _floats(mapping["extrinsic_R"]).reshape(3, 3)
    T = _floats(mapping["extrinsic_T"])
    np.testing.assert_allclose(points @ R.T + T, case.p_imu(points), atol=TOL)
    # imu_cbk: stamp = t_imu - time_offset_lidar_to_imu, i.e. the IMU moved onto the LiDAR clock
    offset = common["time_offset_lidar_to_imu"]
    assert isinstance(offset, float) and common["time_sync_en"] is False
    t_lidar = 1700000012.25
    assert case.t_imu(t_lidar) - offset == pytest.approx(t_lidar, abs=1e-6)
    assert offset == pytest.approx(case.shift + case.dt, abs=1e-12)
    assert common["lid_topic"] == "/points_raw" and common["imu_topic"] == "/imu/data"


def test_fast_lio_comments_state_each_convention() -> None:
    text = to_fast_lio(_result(CASES["general"]))
    for words in (
        "subtracts time_offset_lidar_to_imu from every IMU stamp",
        "p_imu = extrinsic_R * p_lidar + extrinsic_T",
        "row-major",
        "metres",
        "t_imu - t_lidar = 0.005 s",
    ):
        assert words in text


# --------------------------------------------------------------------------------------------
# LIO-SAM
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("ros2", [False, True], ids=["master", "ros2-branch"])
def test_lio_sam_turns_imu_readings_into_the_lidar_frame_as_lio_sam_does(
    case: Case, ros2: bool
) -> None:
    data = yaml.safe_load(to_lio_sam(_result(case), ros2=ros2))
    p = data["/**"]["ros__parameters"] if ros2 else data["lio_sam"]
    # utility.h: Eigen::Map<Matrix<double, -1, -1, RowMajor>> of each list
    ext_rot = _floats(p["extrinsicRot"]).reshape(3, 3)
    ext_rpy = _floats(p["extrinsicRPY"]).reshape(3, 3)
    ext_trans = _floats(p["extrinsicTrans"])
    rng = np.random.default_rng(3)

    # The rig turns at omega and feels the specific force f; in the LiDAR's axes these are
    # the same vectors expressed in the LiDAR frame (p_imu = R p_lidar for directions).
    omega_imu, f_imu = rng.normal(size=3), rng.normal(size=3)
    omega_lidar = np.linalg.solve(case.R, omega_imu)
    f_lidar = np.linalg.solve(case.R, f_imu)
    # imuConverter: acc = extRot * acc; gyr = extRot * gyr
    np.testing.assert_allclose(ext_rot @ omega_imu, omega_lidar, atol=TOL)
    np.testing.assert_allclose(ext_rot @ f_imu, f_lidar, atol=TOL)

    # imuConverter: q_final = q_from * extQRPY; master: extQRPY = Quaterniond(extRPY).inverse(),
    # ros2 branch: extQRPY = Quaterniond(extRPY). q_from = R_world_imu, wanted R_world_lidar.
    q_from = Rotation.random(random_state=5)
    ext_q = Rotation.from_matrix(ext_rpy)
    q_final = q_from * (ext_q if ros2 else ext_q.inv())
    R_world_lidar = q_from.as_matrix() @ case.R
    np.testing.assert_allclose(q_final.as_matrix(), R_world_lidar, atol=TOL)

    # imuPreintegration: lidar2Imu = Pose3(Rot3(), extTrans); T_world_imu =
    # lidarPose.compose(lidar2Imu): the IMU origin is p_wl + R_wl extTrans.
    R_wl, p_wl = Rotation.random(random_state=6).as_matrix(), rng.normal(size=3)
    imu_origin_world = p_wl + R_wl @ case.p_lidar(np.zeros((1, 3)))[0]
    np.testing.assert_allclose(p_wl + R_wl @ ext_trans, imu_origin_world, atol=TOL)
    assert p["pointCloudTopic"] == "/points_raw" and p["imuTopic"] == "/imu/data"


def test_lio_sam_says_its_direction_and_that_the_time_offset_is_not_applied() -> None:
    text = to_lio_sam(_result(CASES["flip-x-negative-offset"]))
    assert "T_lidar_imu, the INVERSE of licalib's T_imu_lidar" in text
    assert "no time offset parameter" in text and "t_imu - t_lidar = -0.0123 s" in text


# --------------------------------------------------------------------------------------------
# URDF
# --------------------------------------------------------------------------------------------


def _urdf_rpy_matrix(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """urdfdom ``Rotation::setFromRPY``: the quaternion from half angles."""
    sr, cr = math.sin(roll / 2.0), math.cos(roll / 2.0)
    sp, cp = math.sin(pitch / 2.0), math.cos(pitch / 2.0)
    sy, cy = math.sin(yaw / 2.0), math.cos(yaw / 2.0)
    q = [
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
        cr * cp * cy + sr * sp * sy,
    ]
    return Rotation.from_quat(q).as_matrix()


@pytest.mark.parametrize("parent_sensor", list(ParentSensor), ids=["imu-parent", "lidar-parent"])
def test_urdf_joint_origin_is_the_child_pose_in_the_parent(
    case: Case, points: np.ndarray, parent_sensor: ParentSensor
) -> None:
    result = _result(case)
    frames = resolve_frames(result, parent_sensor=parent_sensor)
    root = ET.fromstring(to_urdf(result, frames))
    assert root.tag == "robot"
    assert {link.get("name") for link in root.findall("link")} == {"imu_link", "velodyne"}
    (joint,) = root.findall("joint")
    assert joint.get("type") == "fixed"
    parent, child = joint.find("parent").get("link"), joint.find("child").get("link")
    origin = joint.find("origin")
    xyz = np.array([float(v) for v in origin.get("xyz").split()])
    rpy = [float(v) for v in origin.get("rpy").split()]
    # the joint origin maps child-frame points into the parent frame
    mapped = points @ _urdf_rpy_matrix(*rpy).T + xyz
    if parent_sensor is ParentSensor.IMU:
        assert (parent, child) == ("imu_link", "velodyne")
        np.testing.assert_allclose(mapped, case.p_imu(points), atol=TOL)
    else:
        assert (parent, child) == ("velodyne", "imu_link")
        np.testing.assert_allclose(mapped, case.p_lidar(points), atol=TOL)


# --------------------------------------------------------------------------------------------
# tf2 static_transform_publisher
# --------------------------------------------------------------------------------------------


def _tf2_lines(text: str) -> tuple[list[str], list[str]]:
    lines = [ln for ln in text.splitlines() if ln.strip() and not ln.startswith("#")]
    assert len(lines) == 2, text
    return shlex.split(lines[0]), shlex.split(lines[1])


def _ros2_args(argv: list[str]) -> argparse.Namespace:
    """The named arguments of ROS 2 ``static_transform_publisher`` (all required here)."""
    assert argv[:4] == ["ros2", "run", "tf2_ros", "static_transform_publisher"]
    parser = argparse.ArgumentParser(allow_abbrev=False)
    for name in ("--x", "--y", "--z", "--qx", "--qy", "--qz", "--qw"):
        parser.add_argument(name, type=float, required=True)
    parser.add_argument("--frame-id", required=True)
    parser.add_argument("--child-frame-id", required=True)
    return parser.parse_args(argv[4:])


@pytest.mark.parametrize("parent_sensor", list(ParentSensor), ids=["imu-parent", "lidar-parent"])
def test_tf2_command_lines_publish_the_child_pose_in_the_parent(
    case: Case, points: np.ndarray, parent_sensor: ParentSensor
) -> None:
    result = _result(case)
    frames = resolve_frames(result, parent_sensor=parent_sensor)
    ros2_argv, ros1_argv = _tf2_lines(to_tf2(result, frames))
    a = _ros2_args(ros2_argv)
    # ROS 1 tf: argc == 11 -> x y z qx qy qz qw frame_id child_frame_id period_ms
    assert ros1_argv[:3] == ["rosrun", "tf", "static_transform_publisher"]
    args1 = ros1_argv[3:]
    assert len(args1) == 10 and float(args1[9]) > 0
    assert (args1[7], args1[8]) == (a.frame_id, a.child_frame_id)
    pose2 = np.array([a.x, a.y, a.z, a.qx, a.qy, a.qz, a.qw])
    pose1 = np.array([float(v) for v in args1[:7]])
    np.testing.assert_allclose(pose1, pose2, atol=0)
    assert np.linalg.norm(pose2[3:]) == pytest.approx(1.0, abs=1e-9)
    # tf::Transform(Quaternion(qx, qy, qz, qw), Vector3(x, y, z)) from frame_id to child:
    # p_parent = q p_child + t
    mapped = Rotation.from_quat(pose2[3:]).apply(points) + pose2[:3]
    if parent_sensor is ParentSensor.IMU:
        assert (a.frame_id, a.child_frame_id) == ("imu_link", "velodyne")
        np.testing.assert_allclose(mapped, case.p_imu(points), atol=TOL)
    else:
        assert (a.frame_id, a.child_frame_id) == ("velodyne", "imu_link")
        np.testing.assert_allclose(mapped, case.p_lidar(points), atol=TOL)


def test_tf2_quotes_frame_names_for_the_shell() -> None:
    result = _result(CASES["general"], frames=None)
    frames = Frames("base imu", "lidar;rm", ParentSensor.IMU)
    ros2_argv, ros1_argv = _tf2_lines(to_tf2(result, frames))
    assert _ros2_args(ros2_argv).frame_id == "base imu"
    assert ros1_argv[-3:-1] == ["base imu", "lidar;rm"]


# --------------------------------------------------------------------------------------------
# Kalibr
# --------------------------------------------------------------------------------------------


def test_kalibr_transforms_and_timeshift(case: Case, points: np.ndarray) -> None:
    data = yaml.safe_load(to_kalibr(_result(case)))["lidar0"]
    T = np.array([_floats(row) for row in data["T_imu_lidar"]])
    T_inv = np.array([_floats(row) for row in data["T_lidar_imu"]])
    homogeneous = np.c_[points, np.ones(len(points))]
    np.testing.assert_allclose((homogeneous @ T.T)[:, :3], case.p_imu(points), atol=TOL)
    np.testing.assert_allclose(T_inv @ T, np.eye(4), atol=TOL)
    np.testing.assert_array_equal(T[3], [0, 0, 0, 1])
    # Kalibr: t_imu = t_cam + timeshift_cam_imu, here for the LiDAR
    shift = data["timeshift_lidar_imu"]
    t_lidar = 1700000012.25
    assert t_lidar + shift == pytest.approx(case.t_imu(t_lidar), abs=1e-6)
    assert data["rostopic"] == "/points_raw"


# --------------------------------------------------------------------------------------------
# JSON
# --------------------------------------------------------------------------------------------


def _strict(text: str) -> object:
    def refuse(name: str) -> None:
        raise AssertionError(f"non-standard JSON constant {name}")

    return json.loads(text, parse_constant=refuse)


@pytest.mark.filterwarnings("ignore:Gimbal lock")  # the result's own rpy_deg at pitch 90
def test_json_is_the_result_and_reads_back(case: Case, points: np.ndarray) -> None:
    result = _result(case)
    data = _strict(to_json(result))
    assert isinstance(data, dict)
    # unobservable (.inf) becomes null; everything else is the result file's content
    assert data["uncertainty"]["translation_std_m"] == [0.001, 0.001, None]
    back = CalibrationResult.from_dict(data)
    np.testing.assert_allclose(
        points @ back.extrinsic.rotation.T + back.extrinsic.translation,
        case.p_imu(points),
        atol=TOL,
    )
    assert back.extrinsic.time_offset_s == pytest.approx(case.dt, abs=1e-12)
    assert back.recording.lidar_clock_shift_s == case.shift
    assert back.verdict.status == "pass"
    file_data = yaml.safe_load(result.to_yaml())
    file_data["uncertainty"]["translation_std_m"][2] = None
    assert data == file_data


# --------------------------------------------------------------------------------------------
# Frames, verdicts and options
# --------------------------------------------------------------------------------------------


def test_frames_default_to_the_recorded_ones_with_the_imu_as_parent() -> None:
    result = _result(CASES["general"])
    assert resolve_frames(result) == Frames("imu_link", "velodyne", ParentSensor.IMU)
    lidar_parent = Frames("velodyne", "imu_link", ParentSensor.LIDAR)
    assert resolve_frames(result, parent_sensor=ParentSensor.LIDAR) == lidar_parent
    # naming the recorded LiDAR frame as the parent makes the LiDAR the parent
    assert resolve_frames(result, parent="velodyne") == lidar_parent
    assert resolve_frames(result, child="imu_link") == lidar_parent
    # other names keep the direction given
    renamed = resolve_frames(result, parent="base_imu", child="os_sensor")
    assert renamed == Frames("base_imu", "os_sensor", ParentSensor.IMU)


@pytest.mark.parametrize(
    ("kwargs", "words"),
    [
        ({}, "pass --parent and --child"),
        ({"parent": "imu"}, "pass --parent and --child"),
        ({"parent": "a", "child": "a"}, "both 'a'"),
    ],
    ids=["none", "parent-only", "same"],
)
def test_frames_without_recorded_ids_need_both_names(kwargs: dict, words: str) -> None:
    result = _result(CASES["general"], frames=None)
    with pytest.raises(ConfigError, match=words):
        resolve_frames(result, **kwargs)
    frames = resolve_frames(result, parent="imu", child="lidar")
    assert frames == Frames("imu", "lidar", ParentSensor.IMU)


def test_frames_contradicting_the_parent_sensor_are_refused() -> None:
    result = _result(CASES["general"])
    with pytest.raises(ConfigError, match="contradicts the frame names"):
        resolve_frames(result, parent="velodyne", parent_sensor=ParentSensor.IMU)


def test_fail_verdict_is_refused_unless_forced() -> None:
    result = _result(CASES["general"], "fail", ("the rounds did not converge",))
    with pytest.raises(VerdictFailure, match=r"not converge.*--force") as err:
        exportable(result)
    assert err.value.exit_code == 9
    (warning,) = exportable(result, force=True)
    assert "verdict is fail" in warning
    assert exportable(_result(CASES["general"])) == ()
    (warning,) = exportable(_result(CASES["general"], "warn", ("translation z weakly observable",)))
    assert "weakly observable" in warning


def test_clock_shift_is_named_in_a_warning_and_in_the_files() -> None:
    result = _result(CASES["flip-oblique-clock-shift"])
    (warning,) = exportable(result)
    assert "-3.5 s" in warning
    for text in (to_fast_lio(result), to_kalibr(result), to_lio_sam(result)):
        assert "recording.lidar_clock_shift_s -3.5 s + time_offset_s -0.0042 s" in text


def test_a_clock_drift_is_named_in_a_warning_and_beside_the_offset_it_moves() -> None:
    """A calibration that estimated an IMU clock drift exports the time offset at its reference
    stamp; the warning and the files say so and how fast the offset moves."""
    reference = 1700000005000000000
    result = replace(
        _result(CASES["general"]),
        extra_terms=ExtraTerms(reference_ns=reference, clock_drift=2.5e-4),
    )
    (warning,) = exportable(result)
    assert "+250 ppm" in warning and "+15 ms per minute" in warning and str(reference) in warning
    for text in (to_fast_lio(result), to_kalibr(result)):
        assert f"at LiDAR stamp {reference} ns only" in text
        assert "0.00025 s per s" in text
        yaml.safe_load(text)  # the note is a comment
    # the offset written is the offset at the reference stamp
    assert yaml.safe_load(to_kalibr(result))["lidar0"]["timeshift_lidar_imu"] == 0.005
    assert exportable(_result(CASES["general"])) == ()


def test_options_a_target_does_not_take_are_refused() -> None:
    result = _result(CASES["general"])
    with pytest.raises(ConfigError, match="--ros2 applies to fast-lio and lio-sam only"):
        export(result, ExportTarget.URDF, frames=resolve_frames(result), ros2=True)
    with pytest.raises(ConfigError, match="needs the parent and child frames"):
        export(result, ExportTarget.TF2)


def test_numbers_are_plain_decimals() -> None:
    """No exponents (PyYAML reads ``1e-05`` as a string), no ``-0.0`` and no 1e-16 residues of
    exact flips."""
    result = _result(replace(CASES["flip-x-negative-offset"], t=np.array([1e-5, -0.0, 2.5e-7])))
    text = to_fast_lio(result)
    assert "e-" not in text and "-0.0," not in text
    mapping = yaml.safe_load(text)["mapping"]
    assert mapping["extrinsic_R"] == [1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, -1.0]
    assert mapping["extrinsic_T"] == [1e-5, 0.0, 2.5e-7]


def test_a_long_verdict_is_one_line_on_screen_and_one_line_per_reason_in_the_file() -> None:
    reasons = (
        "Translation is uncertain (1-sigma up to 5.98 mm). It comes from the effects held fixed.",
        "The LiDAR residuals depend on the beam (20 % of their variance, 6.0 mm).",
        "The IMU data show an effect the model holds fixed, gyro_rotation.",
    )
    result = _result(CASES["general"], "warn", reasons)
    (warning,) = exportable(result)
    assert warning == (
        "The result's verdict is warn: Translation is uncertain (1-sigma up to 5.98 mm); "
        "and 2 more reasons in the result's verdict."
    )
    lines = to_fast_lio(result).splitlines()
    at = lines.index("# verdict: warn, because:")
    assert lines[at + 1 : at + 4] == [f"#   - {r}" for r in reasons]
    (warning,) = exportable(_result(CASES["general"], "warn", reasons[1:2]))
    assert warning == f"The result's verdict is warn: {reasons[1]}"
    (warning,) = exportable(_result(CASES["general"], "warn", reasons[:1]))
    assert warning == (
        "The result's verdict is warn: Translation is uncertain (1-sigma up to 5.98 mm); "
        "more in the result's verdict."
    )
    with pytest.raises(VerdictFailure) as err:
        exportable(_result(CASES["general"], "fail", reasons))
    assert "It comes from" not in str(err.value) and "2 more reasons" in str(err.value)
