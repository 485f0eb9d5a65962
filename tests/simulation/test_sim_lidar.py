"""LiDAR sweeps: firing pattern, point layout, per-point times, intrinsics, motion distortion.

Points are mapped into the world the way a calibration would: per-point time from the published
fields and the header stamp, the clock relations of ``truth.yaml``, the true IMU trajectory and
``T_imu_lidar``; then their distance to the surface each ray hit is measured.
"""

from __future__ import annotations

import numpy as np
import pytest

from licalib_cli.models.lidar import lidar_point, nominal_point, raw_from_nominal
from licalib_cli.simulation import (
    IntrinsicsMode,
    LidarKind,
    LidarStamp,
    SimulatedScan,
    SimulationSetup,
    SimulationSpec,
    build_setup,
    generate_scans,
    lidar_model,
)
from licalib_cli.simulation.lidar_models import OUSTER_DTYPE, VLP16_DTYPE


def _point_times_true_s(setup: SimulationSetup, scan: SimulatedScan) -> np.ndarray:
    """True (IMU-clock) time of each valid point from the published fields, s after base."""
    spec = setup.spec
    pts = scan.points.reshape(-1)
    if "timestamp" in pts.dtype.names:  # Livox: absolute ns
        tau_ns = pts["timestamp"].astype(np.float64)  # LiDAR clock
    else:
        if "time" in pts.dtype.names:
            rel_ns = pts["time"].astype(np.float64) * 1e9
        else:
            rel_ns = pts["t"].astype(np.float64)
        tau_ns = scan.stamp_ns + rel_ns  # LiDAR clock
    t_imu_ns = tau_ns - setup.lidar_clock_offset_ns + setup.time_offset_ns
    return (t_imu_ns - spec.base_time_ns) * 1e-9


def _plane_distance(
    setup: SimulationSetup, scan: SimulatedScan, xyz_l: np.ndarray, t_s: np.ndarray
) -> np.ndarray:
    """Distance of the valid points (N, 3) in the LiDAR frame at times (N,) to their planes."""
    r_wl, p_wl = setup.lidar_pose_at(t_s)
    p_w = np.einsum("nij,nj->ni", r_wl, xyz_l) + p_wl
    planes = setup.world.planes()[scan.truth.plane_id[scan.truth.valid]]
    return np.abs(np.einsum("ni,ni->n", planes[:, :3], p_w) + planes[:, 3])


def _xyz(scan: SimulatedScan) -> np.ndarray:
    pts = scan.points.reshape(-1)
    return np.stack([pts["x"], pts["y"], pts["z"]], -1).astype(np.float64)


def test_vlp16_firing_pattern() -> None:
    model = lidar_model(LidarKind.VLP16)
    pat = model.pattern(10.0)
    assert pat.t_ns.shape == (1808, 16)
    assert np.allclose(np.degrees(model.nominal_elevation), np.arange(-15, 16, 2))
    # Within a cycle the lasers fire every 2.304 us in the order -15, 1, -13, 3, ... deg.
    order = np.argsort(pat.t_ns[0])
    assert np.allclose(
        np.degrees(model.nominal_elevation[order]),
        [-15, 1, -13, 3, -11, 5, -9, 7, -7, 9, -5, 11, -3, 13, -1, 15],
    )
    assert np.array_equal(np.diff(pat.t_ns[0][order]), np.full(15, 2304))
    assert np.array_equal(np.diff(pat.t_ns[:, 0]), np.full(1807, 55296))
    # Clockwise: azimuth decreases by 0.199 deg per cycle.
    step = np.degrees(np.angle(np.exp(1j * (pat.theta[1, 0] - pat.theta[0, 0]))))
    assert step == pytest.approx(-360 * 55296e-9 * 10, rel=1e-9)
    thin = model.pattern(10.0, azimuth_resolution_deg=1.0)
    assert thin.t_ns.shape == (362, 16)


def test_hdl32_firing_pattern() -> None:
    model = lidar_model(LidarKind.HDL32)
    pat = model.pattern(10.0)
    assert pat.t_ns.shape == (2170, 32) and model.dtype == VLP16_DTYPE
    # Rings by elevation, 1.33 deg apart from -30.67 to +10.67 deg.
    elev = np.degrees(model.nominal_elevation)
    assert elev[[0, 31]] == pytest.approx([-30.67, 10.67]) and np.all(np.diff(elev) > 1.3)
    # Within a cycle the lasers fire every 1.152 us, alternating between the lower and the
    # upper block: -30.67, -9.33, -29.33, -8.00, ... deg.
    order = np.argsort(pat.t_ns[0])
    assert elev[order][:4] == pytest.approx([-30.67, -9.33, -29.33, -8.00])
    assert np.array_equal(np.diff(pat.t_ns[0][order]), np.full(31, 1152))
    assert np.array_equal(np.diff(pat.t_ns[:, 0]), np.full(2169, 46080))
    step = np.degrees(np.angle(np.exp(1j * (pat.theta[1, 0] - pat.theta[0, 0]))))
    assert step == pytest.approx(-360 * 46080e-9 * 10, rel=1e-9)


@pytest.mark.parametrize(
    ("lidar", "beams", "top_deg"),
    [(LidarKind.OS1_32, 32, 22.5), (LidarKind.OS1_64, 64, 16.6), (LidarKind.OS1_128, 128, 22.5)],
)
def test_ouster_beam_counts(lidar: LidarKind, beams: int, top_deg: float) -> None:
    model = lidar_model(lidar)
    pat = model.pattern(10.0)
    assert model.organized and pat.t_ns.shape == (1024, beams)
    elev = np.degrees(model.nominal_elevation)
    assert elev[[0, -1]] == pytest.approx([top_deg, -top_deg])
    assert np.allclose(np.diff(elev), -2 * top_deg / (beams - 1))


@pytest.mark.parametrize("stamp", list(LidarStamp))
def test_vlp16_cloud_layout_and_times(stamp: LidarStamp) -> None:
    spec = SimulationSpec(
        duration_s=0.3, lidar_stamp=stamp, time_offset_s=0.0123, lidar_clock_offset_s=-2.5
    )
    setup = build_setup(spec)
    scan = next(iter(generate_scans(spec, setup, indices=[2])))
    assert scan.points.dtype == VLP16_DTYPE and VLP16_DTYPE.itemsize == 22
    assert [VLP16_DTYPE.fields[n][1] for n in VLP16_DTYPE.names] == [0, 4, 8, 12, 16, 18]
    assert scan.points.ndim == 1 and 0.99 * 1808 * 16 < len(scan.points) <= 1808 * 16
    times = scan.points["time"]
    span = (1807 * 55296 + 15 * 2304) * 1e-9
    if stamp is LidarStamp.START:
        assert times.min() == 0.0 and times.max() == pytest.approx(span, abs=1e-8)
        t0_true_ns = 2 * 100_000_000
    else:
        assert times.max() == 0.0 and times.min() == pytest.approx(-span, abs=1e-8)
        t0_true_ns = 2 * 100_000_000 + round(span * 1e9)
    assert scan.stamp_ns == spec.base_time_ns + t0_true_ns - 12_300_000 - 2_500_000_000
    assert np.allclose(_point_times_true_s(setup, scan), scan.truth.t_true_s, atol=1e-8)
    assert set(np.unique(scan.points["ring"])) == set(range(16))


def test_ouster_cloud_layout() -> None:
    spec = SimulationSpec(lidar=LidarKind.OS1_64, duration_s=0.2, dropout=0.05)
    setup = build_setup(spec)
    scan = next(iter(generate_scans(spec, setup, indices=[1])))
    pts = scan.points
    assert pts.shape == (64, 1024) and pts.dtype == OUSTER_DTYPE and OUSTER_DTYPE.itemsize == 48
    assert [OUSTER_DTYPE.fields[n][1] for n in OUSTER_DTYPE.names] == [
        0,
        4,
        8,
        16,
        20,
        24,
        26,
        28,
        32,
    ]
    assert np.array_equal(pts["ring"], np.repeat(np.arange(64), 1024).reshape(64, 1024))
    # t: uint32 ns after the sweep start, one value per column.
    assert pts["t"].dtype == np.uint32 and pts["t"][0, 0] == 0
    assert np.array_equal(pts["t"][0], pts["t"][63])
    assert np.array_equal(pts["t"][0], np.round(np.arange(1024) * 1e8 / 1024).astype(np.uint32))
    assert scan.stamp_ns == spec.base_time_ns + 100_000_000
    # No-returns are zero points with range 0; others carry the raw range in mm.
    invalid = ~scan.truth.valid.reshape(64, 1024)
    assert 0.03 < invalid.mean() < 0.07
    assert np.all(pts["x"][invalid] == 0) and np.all(pts["range"][invalid] == 0)
    rng_mm = np.linalg.norm(_xyz(scan), axis=1).reshape(64, 1024)
    assert np.allclose(pts["range"][~invalid], rng_mm[~invalid] * 1000, atol=0.6)
    assert np.degrees(setup.lidar_intrinsics.nominal_elevation[[0, 63]]) == pytest.approx(
        [16.6, -16.6]
    )


@pytest.mark.parametrize("lidar", list(LidarKind))
def test_ideal_points_lie_on_planes(lidar: LidarKind) -> None:
    """Noise- and intrinsics-free points at their per-point times: < 1 mm from their plane."""
    spec = SimulationSpec(
        lidar=lidar,
        duration_s=1.0,
        noise_free=True,
        intrinsics=IntrinsicsMode.NONE,
        time_offset_s=0.0071,
        lidar_clock_offset_s=1234.5,
        azimuth_resolution_deg=0.8,
    )
    setup = build_setup(spec)
    for scan in generate_scans(spec, setup, indices=[0, 7]):
        valid = scan.truth.valid
        t = _point_times_true_s(setup, scan)[valid]
        dist = _plane_distance(setup, scan, _xyz(scan)[valid], t)
        assert dist.max() < 1e-3
        # Without per-point times (all points at the header stamp) motion distortion shows.
        dist_0 = _plane_distance(setup, scan, _xyz(scan)[valid], np.full_like(t, t.min()))
        assert dist_0.max() > 0.05


@pytest.mark.parametrize("lidar", [k for k in LidarKind if not k.is_non_repetitive])
def test_intrinsics_correction_puts_points_on_planes(lidar: LidarKind) -> None:
    """lidar_point(true intrinsics) on the raw (ring, range, azimuth) is exact; nominal is not."""
    spec = SimulationSpec(
        lidar=lidar, duration_s=0.5, noise_free=True, seed=4, azimuth_resolution_deg=0.8
    )
    setup = build_setup(spec)
    kin = setup.lidar_intrinsics
    scan = next(iter(generate_scans(spec, setup, indices=[3])))
    valid = scan.truth.valid
    xyz = _xyz(scan)[valid]
    ring = scan.points.reshape(-1)["ring"][valid].astype(np.int64)
    rho, theta = raw_from_nominal(xyz)
    t = _point_times_true_s(setup, scan)[valid]
    corrected = lidar_point(kin, ring, rho, theta)
    dist_c = _plane_distance(setup, scan, corrected, t)
    dist_n = _plane_distance(setup, scan, xyz, t)
    assert dist_c.max() < 1e-3
    assert np.median(dist_n) > 2e-3 and np.mean(dist_n > 1e-3) > 0.5
    # The model reproduces the true point from the truth's raw values to float precision.
    tr = scan.truth
    exact = lidar_point(kin, tr.beam[valid], tr.rho[valid], tr.theta[valid])
    r_wl, p_wl = setup.lidar_pose_at(tr.t_true_s[valid])
    hit_l = np.einsum("nji,nj->ni", r_wl, tr.hit_world[valid] - p_wl)
    assert np.max(np.abs(exact - hit_l)) < 1e-9
    assert np.allclose(
        nominal_point(tr.rho[valid], tr.theta[valid], kin.nominal_elevation[tr.beam[valid]]),
        xyz,
        atol=1e-5,
    )


def test_range_noise_has_the_requested_sigma() -> None:
    spec = SimulationSpec(duration_s=0.2, range_noise_m=0.02, intrinsics=IntrinsicsMode.NONE)
    setup = build_setup(spec)
    scan = next(iter(generate_scans(spec, setup, indices=[1])))
    resid = scan.truth.rho - scan.truth.rho_bar
    assert np.std(resid) == pytest.approx(0.02, rel=0.05)
    assert abs(np.mean(resid)) < 0.001


def test_scans_are_deterministic_per_seed() -> None:
    spec = SimulationSpec(duration_s=0.3, seed=11, azimuth_resolution_deg=2.0)
    a = next(iter(generate_scans(spec, indices=[2])))
    b = next(iter(generate_scans(spec, indices=[2])))
    c = next(iter(generate_scans(spec.with_(seed=12), indices=[2])))
    assert a.points.tobytes() == b.points.tobytes()
    assert a.points.tobytes() != c.points.tobytes()
