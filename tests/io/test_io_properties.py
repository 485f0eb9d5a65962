"""Property tests: whatever a deserialised message can hold, only licalib's own errors escape.

The PointCloud2 decoder (and the per-cloud checks after it) and the IMU/stamp validation are
fed values of the types a bag's messages carry (uint32 sizes and offsets, uint8 datatypes,
arbitrary field names and bytes, int32/uint32 stamps, any float64 reading); they either
return or raise a :class:`LicalibError`, and never let numpy warn.
"""

from __future__ import annotations

import warnings
from types import SimpleNamespace

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from licalib_cli.config import load_config
from licalib_cli.errors import LicalibError
from licalib_cli.io.cloud_layout import CloudLayout, Skip
from licalib_cli.io.findings import IMU_GAP_FACTOR, stamp_stats
from licalib_cli.io.imu_stream import RawImu, validate_imu
from licalib_cli.io.pointcloud2 import decode_cloud, valid_mask
from licalib_cli.io.scan_stream import make_scan
from licalib_cli.io.timestamps import TimeLayout
from licalib_cli.measurements import LidarScan

NS = 1_000_000_000
UINT32 = 2**32 - 1
CFG = load_config(None)

small = st.integers(0, 64)
uint32 = st.one_of(small, st.integers(0, UINT32), st.sampled_from([2**31, 2**31 - 1, UINT32]))
names = st.one_of(
    st.sampled_from(["x", "y", "z", "intensity", "t", "time", "ring", "timestamp", ""]),
    st.text(max_size=4),
)
fields = st.lists(
    st.builds(
        SimpleNamespace,
        name=names,
        offset=st.one_of(small, uint32),
        datatype=st.one_of(st.integers(1, 8), st.integers(0, 255)),
        count=st.one_of(st.integers(0, 3), uint32),
    ),
    max_size=7,
)
clouds = st.builds(
    SimpleNamespace,
    height=st.one_of(st.integers(0, 4), uint32),
    width=st.one_of(st.integers(0, 64), uint32),
    fields=fields,
    is_bigendian=st.booleans(),
    point_step=st.one_of(st.integers(0, 48), uint32),
    row_step=st.one_of(st.integers(0, 1024), uint32),
    data=st.binary(max_size=2048).map(lambda b: np.frombuffer(b, dtype=np.uint8)),
)

# Valid clouds with values anywhere in float32/float64/integer ranges: the checks after decoding.
LAYOUT = CloudLayout(
    topic="/points",
    fields=(),
    point_step=20,
    is_bigendian=False,
    height=1,
    width=0,
    time=TimeLayout("t", "s", "relative", "start", 100_000_000),
    ring_field="ring",
    beams=16,
)
POINT = np.dtype(
    {
        "names": ["x", "y", "z", "t", "ring"],
        "formats": ["<f4", "<f4", "<f4", "<f4", "<u2"],
        "offsets": [0, 4, 8, 12, 16],
        "itemsize": 20,
    }
)


def _message(points: np.ndarray) -> SimpleNamespace:
    codes = {"f4": 7, "u2": 4}
    return SimpleNamespace(
        height=1,
        width=points.size,
        fields=[
            SimpleNamespace(
                name=n,
                offset=POINT.fields[n][1],
                datatype=codes[POINT.fields[n][0].str[1:]],
                count=1,
            )
            for n in POINT.names
        ],
        is_bigendian=False,
        point_step=POINT.itemsize,
        row_step=POINT.itemsize * points.size,
        data=points.view(np.uint8),
    )


@settings(max_examples=1500, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    msg=clouds,
    time_field=st.sampled_from([None, "t", "time"]),
    ring=st.sampled_from([None, "ring"]),
)
def test_pointcloud2_decoder_raises_only_licalib_errors(
    msg: SimpleNamespace, time_field: str | None, ring: str | None
) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        try:
            dec = decode_cloud(msg, 1_700_000_000 * NS, time_field, ring)
        except LicalibError:
            return
        n = len(dec)
        assert dec.xyz.shape == (n, 3)
        for arr in (dec.time_raw, dec.ring, dec.intensity):
            assert arr is None or arr.shape == (n,)
        assert valid_mask(dec.xyz).shape == (n,)


floats32 = st.floats(width=32, allow_nan=True, allow_infinity=True)


@settings(max_examples=400, deadline=None)
@given(
    values=st.lists(
        st.tuples(floats32, floats32, floats32, floats32, st.integers(0, 2**16 - 1)),
        min_size=0,
        max_size=300,
    )
)
def test_cloud_checks_raise_nothing_and_keep_arrays_aligned(values: list[tuple]) -> None:
    pts = np.array(
        values, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("t", "<f4"), ("ring", "<u2")]
    )
    points = np.zeros(len(values), POINT)
    for name in POINT.names:
        points[name] = pts[name] if len(values) else points[name]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        dec = decode_cloud(_message(points), 1_700_000_000 * NS, "t", "ring")
        scan = make_scan(dec, LAYOUT, CFG, 0)
    if isinstance(scan, Skip):
        return
    assert isinstance(scan, LidarScan)
    n = len(scan)
    assert scan.t_ns.shape == (n,) and scan.ring is not None and scan.ring.shape == (n,)
    assert np.isfinite(scan.xyz).all() and int(scan.ring.min()) >= 0


stamps = st.lists(
    st.one_of(
        st.just(0),
        st.integers(-(2**31) * NS, (2**31) * NS),
        st.integers(1_700_000_000 * NS, 1_700_000_010 * NS),
    ),
    max_size=120,
)
readings = st.floats(allow_nan=True, allow_infinity=True, width=64)


@settings(max_examples=500, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    t=stamps,
    data=st.data(),
    regular=st.booleans(),
)
def test_imu_and_stamp_validation_raises_nothing(
    t: list[int], data: st.DataObject, regular: bool
) -> None:
    n = len(t)
    if regular:  # a plausible stream (sorted 200 Hz stamps) with arbitrary readings
        t = [1_700_000_000 * NS + 5_000_000 * i for i in range(n)]
    vals = np.array(
        data.draw(st.lists(st.tuples(*[readings] * 6), min_size=n, max_size=n)), dtype=np.float64
    ).reshape(n, 6)
    raw = RawImu(np.asarray(t, np.int64), vals[:, :3], vals[:, 3:], np.asarray(t, np.int64))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        imu = validate_imu(raw, "/imu", CFG)
        stats = stamp_stats(raw.t_ns, IMU_GAP_FACTOR)
    assert stats.count == n
    for f in imu.findings:
        assert issubclass(f.error, LicalibError) and f.message.endswith(".")
    if not any(f.fatal for f in imu.findings):
        assert np.isfinite(imu.samples.gyro).all() and np.isfinite(imu.samples.accel).all()
        assert len(imu.samples) == imu.samples.t_ns.size


floats64 = st.floats(allow_nan=True, allow_infinity=True)


@settings(max_examples=400, deadline=None)
@given(
    rows=st.lists(st.tuples(floats64, floats64, floats64), min_size=0, max_size=50),
    limits=st.tuples(st.floats(0.0, 5.0), st.sampled_from([10.0, 1e200, np.inf])),
)
def test_valid_mask_is_the_pointwise_rule(rows: list[tuple], limits: tuple[float, float]) -> None:
    """Finite, not the origin, range within the limits, point by point (huge but finite
    coordinates overflow the squared range and count as out of range unless the limit is inf)."""
    xyz = np.array(rows, dtype=np.float64).reshape(-1, 3)
    lo, hi = limits
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        got = valid_mask(xyz, lo, hi)
    want = []
    for p in xyz:
        if not np.all(np.isfinite(p)):
            want.append(False)
            continue
        with np.errstate(over="ignore"):
            r = float(np.sqrt(np.sum(p * p)))
        want.append(r > 0.0 and lo <= r <= hi)
    assert got.tolist() == want
