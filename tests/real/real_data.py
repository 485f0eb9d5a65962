"""Real sensor data for the tests: ``../shared/data/real`` beside the repository (helpers and
the session fixtures that ``conftest.py`` registers).

The data is read where it lies, never copied into the repository; tests skip (with the
reason) when it is absent. Ouster captures are decoded once per session with ouster-sdk,
which lives in a virtual environment of its own (``.venv/ouster``, made by
``scripts/setup.sh``: ouster-sdk pins an old rosbags) and hands numpy arrays over
(``ouster_decode.py``); the bags are then written with licalib's own writer into a session
temporary folder, in the ouster-ros driver's layout.
"""

from __future__ import annotations

import json
import os
import subprocess
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from licalib_cli.io.writer import BagFormat, BagWriter

REPO = Path(__file__).resolve().parents[2]


def _real_data() -> Path:
    """``../shared/data/real`` relative to the repository (a worktree one level deeper finds
    it one level up; ``LICALIB_REAL_DATA`` points elsewhere)."""
    if "LICALIB_REAL_DATA" in os.environ:
        return Path(os.environ["LICALIB_REAL_DATA"])
    near = REPO.parent / "shared" / "data" / "real"
    far = REPO.parent.parent / "shared" / "data" / "real"
    return far if not near.is_dir() and far.is_dir() else near


REAL = _real_data()
OUSTER = REAL / "ouster"
GYRO_ODOMETRY = REAL / "gyro_odometry"
OUSTER_PYTHON = REPO / ".venv" / "ouster" / "bin" / "python"
DECODER = Path(__file__).with_name("ouster_decode.py")

POINTS_TOPIC = "/ouster/points"
IMU_TOPIC = "/ouster/imu"
METADATA_TOPIC = "/ouster/metadata"

OUSTER_ROS_POINT = np.dtype(
    {
        "names": ["x", "y", "z", "intensity", "t", "reflectivity", "ring", "ambient", "range"],
        "formats": ["<f4", "<f4", "<f4", "<f4", "<u4", "<u2", "<u2", "<u2", "<u4"],
        "offsets": [0, 4, 8, 16, 20, 24, 26, 28, 32],
        "itemsize": 48,
    }
)
"""The ouster-ros PointCloud2 layout (see ``ouster/README.md`` of the data)."""


@dataclass(frozen=True)
class Capture:
    """One Ouster capture of the data folder and what it holds (``ouster/README.md``)."""

    name: str
    pcap: str
    metadata: str
    beams: int
    frames: int
    imu_messages: int
    factory: tuple[tuple[float, float, float], str] | None  # (t in m, sensor) of the README


_T_OS01 = (-0.006253, 0.011775, 0.028535)
CAPTURES = (
    Capture(
        "os1-128",
        "OS-1-128_v2.3.0_1024x10_lb_n3.pcap",
        "OS-1-128_v2.3.0_1024x10.json",
        128,
        3,
        30,
        (_T_OS01, "OS-1-128 sn 122201000998"),
    ),
    Capture(
        "os2-128",
        "OS-2-128-U1_v2.3.0_1024x10.pcap",
        "OS-2-128-U1_v2.3.0_1024x10.json",
        128,
        1,
        10,
        ((-0.006253, 0.011775, 0.066651), "OS-2-128 sn 992210000957"),
    ),
    Capture(
        "os0-128",
        "OS-0-128-U1_v2.3.0_1024x10.pcap",
        "OS-0-128-U1_v2.3.0_1024x10.json",
        128,
        1,
        10,
        (_T_OS01, "OS-0-128 sn 122150000150"),
    ),
    Capture(
        "os1-64",
        "OS-1-64_1024x10_fw20.pcap",
        "OS-1-64_sensor_config_reduced.json",
        64,
        1,
        11,
        None,  # the reduced legacy JSON has no transforms
    ),
    Capture(
        "os0-32",
        "OS-0-32-U1_v2.2.0_1024x10.pcap",
        "OS-0-32-U1_v2.2.0_1024x10.json",
        32,
        1,
        10,
        (_T_OS01, "OS-0-32-U1 sn 992137000142"),
    ),
)


@dataclass(frozen=True)
class DecodedBag:
    """A bag written from a decoded capture, with what ouster-sdk decoded."""

    capture: Capture
    units: str  # "si" or "gdeg"
    fmt: BagFormat
    path: Path
    arrays: dict[str, np.ndarray]

    @property
    def id(self) -> str:
        return f"{self.capture.name}-{self.units}-{self.fmt.value}"


def require_data(folder: Path) -> None:
    """Skip the test when a folder of the real data is absent."""
    if not folder.is_dir():
        pytest.skip(f"real data not found at {folder} (../shared/data/real beside the repo)")


def _ouster_sdk_reason() -> str | None:
    if not OUSTER_PYTHON.exists():
        where = OUSTER_PYTHON.parents[1]
        return f"ouster-sdk's environment {where} is missing (bash scripts/setup.sh --tests)"
    probe = subprocess.run(
        [str(OUSTER_PYTHON), "-c", "import ouster.sdk.pcap, ouster.sdk.core"],
        capture_output=True,
        text=True,
        check=False,
    )
    if probe.returncode:
        return f"ouster-sdk is not importable in {OUSTER_PYTHON}: {probe.stderr.strip()[-200:]}"
    return None


def lidar_points(arrays: dict[str, np.ndarray], k: int) -> np.ndarray:
    """ouster-sdk's XYZ of frame ``k`` in ``os_lidar`` (where ouster-ros publishes it), (H, W, 3)
    float64: the sensor-frame points mapped with ``inv(lidar_to_sensor)``, zeros kept zero."""
    t = arrays["lidar_to_sensor"]
    rot, trans = t[:3, :3], t[:3, 3] / 1000.0
    xyz = arrays["xyz_sensor"][k]
    out = (xyz - trans) @ rot  # R^T (p - t), row vectors
    out[arrays["range_mm"][k] == 0] = 0.0
    return out


def _cloud(arrays: dict[str, np.ndarray], k: int) -> np.ndarray:
    xyz = lidar_points(arrays, k)
    h, w = xyz.shape[:2]
    pts = np.zeros((h, w), OUSTER_ROS_POINT)
    pts["x"], pts["y"], pts["z"] = xyz[..., 0], xyz[..., 1], xyz[..., 2]
    pts["intensity"] = arrays["signal"][k]
    pts["t"] = arrays["t_ns"][k]
    pts["reflectivity"] = arrays["reflectivity"][k]
    pts["ring"] = np.arange(h, dtype=np.uint16)[:, None]
    pts["ambient"] = arrays["near_ir"][k]
    pts["range"] = arrays["range_mm"][k]
    return pts


def write_ouster_bag(path: Path, fmt: BagFormat, arrays: dict[str, np.ndarray], units: str) -> None:
    """The capture as ouster-ros records it: clouds, IMU messages (``si``: m/s^2 and rad/s;
    ``gdeg``: the packets' own g and deg/s) and the metadata string; header stamps on the
    sensor clock, record times the capture's host times."""
    si = units == "si"
    accel = arrays["accel_si"] if si else arrays["accel_g"]
    gyro = arrays["gyro_si"] if si else arrays["gyro_deg_s"]
    first_record = int(min(arrays["record_ns"].min(), arrays["imu_record_ns"].min()))
    with BagWriter(path, fmt) as w:
        string_t = w.typestore.types["std_msgs/msg/String"]
        w.write_message(
            METADATA_TOPIC,
            "std_msgs/msg/String",
            string_t(data=str(arrays["metadata_json"])),
            first_record - 1,
        )
        events = [(int(r), 0, i) for i, r in enumerate(arrays["imu_record_ns"])]
        events += [(int(r), 1, k) for k, r in enumerate(arrays["record_ns"])]
        for record, kind, i in sorted(events):
            if kind == 0:
                stamp = int(arrays["imu_stamp_ns"][i])
                w.write_imu(IMU_TOPIC, stamp, gyro[i], accel[i], "os_imu", record)
            else:
                stamp = int(arrays["stamp_ns"][i])
                w.write_cloud(POINTS_TOPIC, stamp, _cloud(arrays, i), "os_lidar", record, False)


def _variants(index: int) -> tuple[tuple[BagFormat, str], ...]:
    """Each capture in all three formats, and in both unit systems."""
    mcap_units = "si" if index % 2 == 0 else "gdeg"
    return (
        (BagFormat.ROS1, "si"),
        (BagFormat.ROS2_DB3, "gdeg"),
        (BagFormat.ROS2_MCAP, mcap_units),
    )


@pytest.fixture(scope="session")
def ouster_arrays(tmp_path_factory: pytest.TempPathFactory) -> dict[str, dict[str, np.ndarray]]:
    """Every capture decoded by ouster-sdk, by capture name."""
    require_data(OUSTER)
    reason = _ouster_sdk_reason()
    if reason is not None:
        pytest.skip(reason)
    folder = tmp_path_factory.mktemp("ouster_decoded")
    out: dict[str, dict[str, np.ndarray]] = {}
    for cap in CAPTURES:
        npz = folder / f"{cap.name}.npz"
        subprocess.run(
            [OUSTER_PYTHON, DECODER, OUSTER / cap.pcap, OUSTER / cap.metadata, npz],
            check=True,
            capture_output=True,
        )
        with np.load(npz) as data:
            out[cap.name] = {k: data[k] for k in data.files}
    return out


@pytest.fixture(scope="session")
def ouster_bags(
    ouster_arrays: dict[str, dict[str, np.ndarray]], tmp_path_factory: pytest.TempPathFactory
) -> list[DecodedBag]:
    """The decoded captures written as bags (see :func:`_variants`)."""
    folder = tmp_path_factory.mktemp("ouster_bags")
    bags = []
    for i, cap in enumerate(CAPTURES):
        arrays = ouster_arrays[cap.name]
        for fmt, units in _variants(i):
            name = f"{cap.name}_{units}_{fmt.value}"
            path = folder / (f"{name}.bag" if fmt is BagFormat.ROS1 else name)
            write_ouster_bag(path, fmt, arrays, units)
            bags.append(DecodedBag(cap, units, fmt, path, arrays))
    return bags


def metadata_of(cap: Capture) -> dict[str, object]:
    """The capture's metadata JSON."""
    return json.loads((OUSTER / cap.metadata).read_text())
