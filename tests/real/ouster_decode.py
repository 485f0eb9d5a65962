"""Decode an Ouster pcap capture with ouster-sdk into plain arrays (one ``.npz``).

Run with the Python that has ouster-sdk (``.venv/ouster``, made by ``scripts/setup.sh --tests``):
ouster-sdk pins its own rosbags, so it lives in a virtual environment of its own and hands
its output over as numpy arrays, which the tests turn into bags with licalib's writer::

    .venv/ouster/bin/python tests/real/ouster_decode.py CAPTURE.pcap METADATA.json OUT.npz

What it writes, per complete frame ``k`` (destaggered, ``H`` beams x ``W`` columns, as the
ouster-ros driver publishes; ouster-sdk 1.0.1 API):

* ``xyz_sensor`` (K, H, W, 3) float64: ``core.XYZLut`` output in the sensor frame, m (zeros
  where the first return has no range);
* ``lidar_to_sensor`` (4, 4): the metadata transform used (mm), to bring points to ``os_lidar``;
* ``range_mm``, ``reflectivity``, ``signal``, ``near_ir`` (K, H, W): first-return fields
  (``signal`` zeros when the profile has none);
* ``t_ns`` (K, H, W) int64: each point's column timestamp minus the frame's first column
  timestamp (the header stamp), ns;
* ``stamp_ns`` (K,): first column timestamp (sensor clock), ``record_ns`` (K,): capture (host)
  time of the frame's last packet;
* IMU packets: ``imu_stamp_ns`` (gyro_ts, sensor clock), ``imu_record_ns`` (host time),
  ``accel_si`` / ``gyro_si`` (m/s^2, rad/s: ``ImuPacket.accel()`` / ``gyro()``) and
  ``accel_g`` / ``gyro_deg_s`` (the legacy packet's own f32 values, g and deg/s);
* ``metadata_json``: the metadata file's text, ``prod_line``.
"""

from __future__ import annotations

import sys
import warnings
from pathlib import Path

import numpy as np
from ouster.sdk import core, pcap

_LEGACY_IMU = np.dtype(
    [
        ("sys_ts", "<u8"),
        ("accel_ts", "<u8"),
        ("gyro_ts", "<u8"),
        ("acc", "<f4", (3,)),
        ("gyro", "<f4", (3,)),
    ]
)


def decode(capture: Path, meta: Path) -> dict[str, np.ndarray]:
    src = pcap.PcapPacketSource(str(capture), meta=[str(meta)])
    info = src.sensor_info[0]
    h, w = info.format.pixels_per_column, info.format.columns_per_frame
    lut = core.XYZLut(info)
    batch = core.ScanBatcher(info)
    scan = core.LidarScan(info)
    frames: list[dict[str, np.ndarray]] = []
    imu: list[tuple[int, int, np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []
    last_host = 0

    def finish(s: core.LidarScan, host: int) -> None:
        ts = np.asarray(s.timestamp, np.int64)
        if not s.complete() or np.any(ts == 0):
            return
        rng = np.asarray(s.field(core.ChanField.RANGE), np.uint32)
        xyz = np.asarray(lut(s), np.float64)
        xyz[rng == 0] = 0.0
        fields = set(s.fields)

        def field(name: str, dtype: type) -> np.ndarray:
            if name not in fields:
                return np.zeros((h, w), dtype)
            return np.asarray(s.field(name)).astype(dtype)

        t_stag = np.broadcast_to(ts - ts[0], (h, w)).copy()
        frames.append(
            {
                "xyz": core.destagger(info, xyz),
                "range": core.destagger(info, rng),
                "refl": core.destagger(info, field("REFLECTIVITY", np.uint16)),
                "signal": core.destagger(info, field("SIGNAL", np.uint16)),
                "nir": core.destagger(info, field("NEAR_IR", np.uint16)),
                "t": core.destagger(info, t_stag),
                "stamp": np.int64(ts[0]),
                "record": np.int64(host),
            }
        )

    for _, packet in src:
        if isinstance(packet, core.ImuPacket):
            raw = np.frombuffer(bytes(packet.buf)[: _LEGACY_IMU.itemsize], _LEGACY_IMU)[0]
            imu.append(
                (
                    int(packet.gyro_ts()),
                    int(packet.host_timestamp),
                    np.asarray(packet.accel(), np.float64).reshape(3),
                    np.asarray(packet.gyro(), np.float64).reshape(3),
                    raw["acc"].astype(np.float64),
                    raw["gyro"].astype(np.float64),
                )
            )
            continue
        if batch(packet, scan):  # the packet starts a new frame: ``scan`` is the last one
            finish(scan, last_host)
            scan = core.LidarScan(info)
            batch(packet, scan)
        last_host = int(packet.host_timestamp)
    finish(scan, last_host)
    if not frames:
        raise SystemExit(f"{capture}: no complete frame")
    return {
        "xyz_sensor": np.stack([f["xyz"] for f in frames]),
        "lidar_to_sensor": np.asarray(info.lidar_to_sensor_transform, np.float64),
        "range_mm": np.stack([f["range"] for f in frames]),
        "reflectivity": np.stack([f["refl"] for f in frames]),
        "signal": np.stack([f["signal"] for f in frames]),
        "near_ir": np.stack([f["nir"] for f in frames]),
        "t_ns": np.stack([f["t"] for f in frames]).astype(np.int64),
        "stamp_ns": np.array([f["stamp"] for f in frames], np.int64),
        "record_ns": np.array([f["record"] for f in frames], np.int64),
        "imu_stamp_ns": np.array([r[0] for r in imu], np.int64),
        "imu_record_ns": np.array([r[1] for r in imu], np.int64),
        "accel_si": np.array([r[2] for r in imu]).reshape(-1, 3),
        "gyro_si": np.array([r[3] for r in imu]).reshape(-1, 3),
        "accel_g": np.array([r[4] for r in imu]).reshape(-1, 3),
        "gyro_deg_s": np.array([r[5] for r in imu]).reshape(-1, 3),
        "metadata_json": np.array(meta.read_text()),
        "prod_line": np.array(str(info.prod_line)),
    }


def main(argv: list[str]) -> None:
    capture, meta, out = (Path(a) for a in argv)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        arrays = decode(capture, meta)
    np.savez(out, **arrays)


if __name__ == "__main__":
    main(sys.argv[1:])
