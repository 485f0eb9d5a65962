"""A long ROS1 bag made by playing a shorter one several times in a row (for memory figures).

Every message of the source bag is written ``times`` times, each pass shifted by the source's
span plus ``gap_ns`` (one IMU period of the simulator, so the IMU stream has no gap), with both
the record time and the ``std_msgs/Header`` stamp moved (``sensor_msgs/Imu`` and
``sensor_msgs/PointCloud2`` start with a header: ``seq`` then the stamp's ``sec``/``nsec``,
bytes 4-12 of the serialised message). The motion jumps at each seam; what the bag is for is
its size and its message rate, not its trajectory.
"""

from __future__ import annotations

import struct
from pathlib import Path

_NS = 1_000_000_000


def loop_bag(source: Path, target: Path, times: int, gap_ns: int = 2_500_000) -> Path:
    """Write ``target`` as ``times`` back-to-back passes over ``source`` (ROS1 ``.bag``).

    Returns:
        ``target``.
    """
    from rosbags.rosbag1 import Reader, Writer

    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = target.with_name(target.name + ".part")
    tmp.unlink(missing_ok=True)
    with Reader(source) as reader:
        span = reader.end_time - reader.start_time + gap_ns
        with Writer(tmp) as writer:
            out = {
                c.id: writer.add_connection(
                    c.topic, c.msgtype, msgdef=c.msgdef.data, md5sum=c.digest, callerid=None
                )
                for c in reader.connections
            }
            for k in range(times):
                shift = k * span
                for conn, stamp, raw in reader.messages():
                    data = bytearray(raw)
                    sec, nsec = struct.unpack_from("<II", data, 4)
                    t = sec * _NS + nsec + shift
                    struct.pack_into("<II", data, 4, t // _NS, t % _NS)
                    writer.write(out[conn.id], stamp + shift, bytes(data))
    tmp.replace(target)
    return target
