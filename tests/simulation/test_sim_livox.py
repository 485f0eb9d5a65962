"""The non-repetitive Livox-like LiDARs, the Mid-360 (360 deg around) and the Avia (a
forward-looking rosette): their scan patterns, their ``livox_ros_driver2`` clouds read back by
licalib's reader, their IMU in g, and the per-beam effects they refuse."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from licalib_cli.cli import main
from licalib_cli.config import load_config
from licalib_cli.errors import ConfigError
from licalib_cli.io.reader import read_segment
from licalib_cli.models.lidar import nominal_point
from licalib_cli.simulation import (
    LidarKind,
    SimulationSpec,
    build_setup,
    generate_scans,
    lidar_model,
    simulate,
)
from licalib_cli.simulation.lidar_models import LIVOX_DTYPE, FiringPattern
from licalib_cli.simulation.spec import AVIA_RPY_DEG, DEFAULT_RPY_DEG, STANDARD_GRAVITY
from licalib_cli.truth import Truth


def _directions(pattern: FiringPattern) -> np.ndarray:
    """(C, B, 3) unit direction of every ray."""
    assert pattern.elevation is not None
    return nominal_point(np.ones(pattern.theta.shape), pattern.theta, pattern.elevation)


def _angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip(np.einsum("...i,...i->...", a, b), -1.0, 1.0)))


def test_mid360_pattern_is_four_continuous_lines_over_the_field_of_view() -> None:
    model = lidar_model(LidarKind.MID360)
    assert not model.repeats and model.dtype == LIVOX_DTYPE
    pats = [model.pattern(10.0, sweep=k) for k in range(3)]
    pat = pats[0]
    # 200 000 points/s: 20 000 a 10 Hz sweep, 5000 per line, lines 0..3
    assert pat.t_ns.shape == (5000, 4) and pat.elevation is not None
    assert np.array_equal(np.unique(pat.ring), np.arange(4))
    # one ray every 5 us, in time order line 0, 1, 2, 3, 0, ...
    order = pat.t_ns.reshape(-1)
    assert np.array_equal(order, np.arange(20_000) * 5000)
    assert np.array_equal(pat.ring.reshape(-1), np.arange(20_000) % 4)
    # elevations over -7..52 deg, reached
    elev = np.degrees(np.concatenate([p.elevation.reshape(-1) for p in pats]))  # type: ignore[union-attr]
    assert elev.min() == pytest.approx(-7.0, abs=0.05) and elev.max() == pytest.approx(52, abs=0.05)
    # each line's consecutive points (in time, across the sweep boundaries too) are close
    dirs = np.concatenate([_directions(p) for p in pats])  # (3 x 5000, 4, 3)
    steps = _angle_deg(dirs[1:], dirs[:-1])
    assert steps.max() < 1.0 and np.median(steps) > 0.2
    # one azimuth turn per sweep, the lines a quarter turn apart
    turn = np.unwrap(pat.theta[:, 0])
    assert turn[0] - turn[-1] == pytest.approx(2 * np.pi * 4999 / 5000, rel=1e-9)
    gap = np.angle(np.exp(1j * (pat.theta[:, 0] - pat.theta[:, 1])))  # line 1 fires 5 us later
    assert np.allclose(gap, np.pi / 2 + 2 * np.pi * 5000 / 100_000_000, atol=1e-9)


def test_successive_mid360_sweeps_cover_other_directions() -> None:
    """The elevation runs on the time of the run, so sweep 1 does not repeat sweep 0 (a spinning
    LiDAR repeats every ray exactly)."""
    model = lidar_model(LidarKind.MID360)
    s0, s1 = (model.pattern(10.0, sweep=k) for k in (0, 1))
    assert np.array_equal(s0.t_ns, s1.t_ns) and np.array_equal(s0.theta, s1.theta)
    assert s0.elevation is not None and s1.elevation is not None
    d_elev = np.degrees(np.abs(s1.elevation - s0.elevation))
    assert np.median(d_elev) > 10.0
    # hardly any ray of sweep 1 lies within 0.05 deg of a ray of sweep 0
    d0, d1 = (_directions(p).reshape(-1, 3) for p in (s0, s1))
    near, _ = cKDTree(d0).query(d1)
    assert np.mean(near < np.radians(0.05)) < 0.05
    # nor does sweep 10 (a whole number of oscillations per second would repeat it)
    d10 = _directions(model.pattern(10.0, sweep=10)).reshape(-1, 3)
    near, _ = cKDTree(d0).query(d10)
    assert np.mean(near < np.radians(0.05)) < 0.05


def test_avia_pattern_is_six_continuous_lines_over_the_forward_field_of_view() -> None:
    model = lidar_model(LidarKind.AVIA)
    assert not model.repeats and model.dtype == LIVOX_DTYPE
    assert (model.min_range, model.max_range) == (1.0, 190.0)
    pats = [model.pattern(10.0, sweep=k) for k in range(3)]
    pat = pats[0]
    # 240 000 points/s: 24 000 a 10 Hz sweep, 4000 per line, lines 0..5 firing in turn
    assert pat.t_ns.shape == (4000, 6) and pat.elevation is not None
    assert np.array_equal(np.unique(pat.ring), np.arange(6))
    assert np.array_equal(pat.ring.reshape(-1), np.arange(24_000) % 6)
    order = pat.t_ns.reshape(-1)
    assert np.all(np.diff(order) > 0) and order[-1] < 100_000_000
    assert np.array_equal(pat.t_ns[:, 0], np.arange(4000) * 25_000)  # each line every 25 us
    assert np.abs(np.diff(pat.t_ns, axis=1) - 25_000 / 6).max() <= 2  # 4.17 us between lasers
    # each line's consecutive points (in time, across the sweep boundaries too) are close
    dirs = np.concatenate([_directions(p) for p in pats])  # (3 x 4000, 6, 3)
    steps = _angle_deg(dirs[1:], dirs[:-1])
    assert steps.max() < 1.0 and np.median(steps) > 0.2


def test_avia_lines_turn_back_in_azimuth() -> None:
    """A rosette: each line's azimuth runs back and forth across the field of view within a
    sweep (the Mid-360's turns one way only)."""
    avia = lidar_model(LidarKind.AVIA).pattern(10.0, sweep=4)
    turns = np.sign(np.diff(avia.theta, axis=0))
    reversals = np.sum(turns[1:] * turns[:-1] < 0, axis=0)  # per line
    assert reversals.shape == (6,) and np.all(reversals >= 20)
    # the azimuth crosses the field of view each way, not a jitter about one direction
    for line in range(6):
        theta = np.degrees(avia.theta[:, line])
        assert theta.max() - theta.min() > 35.0
    mid360 = lidar_model(LidarKind.MID360).pattern(10.0, sweep=4)
    spin = np.diff(np.unwrap(mid360.theta, axis=0), axis=0)
    assert np.all(spin < 0)


def test_avia_field_of_view_is_70_by_77_deg_forward() -> None:
    model = lidar_model(LidarKind.AVIA)
    pats = [model.pattern(10.0, sweep=k) for k in (0, 1, 2, 13)]
    theta = np.degrees(np.concatenate([p.theta.reshape(-1) for p in pats]))
    elev = np.degrees(np.concatenate([p.elevation.reshape(-1) for p in pats]))  # type: ignore[union-attr]
    assert np.abs(theta).max() <= 35.2 + 1e-9 and np.abs(elev).max() <= 38.6 + 1e-9
    assert np.abs(theta).max() > 35.1 and np.abs(elev).max() > 38.5  # reached
    assert np.all(_directions(pats[0])[..., 0] > 0.45)  # forward: within 64 deg of +x
    # the rosette fills the field of view in every sweep: each 2 x 2 deg cell well inside
    # the ellipse holds points of it
    az_c, el_c = np.meshgrid(np.arange(-35.0, 35.0, 2.0) + 1, np.arange(-38.0, 38.0, 2.0) + 1)
    inside = (az_c / 35.2) ** 2 + (el_c / 38.6) ** 2 < 0.8
    for p in pats:
        a = np.floor((np.degrees(p.theta) + 35.0) / 2.0).astype(int).reshape(-1)
        e = np.floor((np.degrees(p.elevation) + 38.0) / 2.0).astype(int).reshape(-1)  # type: ignore[arg-type]
        hit = np.zeros(inside.shape, dtype=bool)
        ok = (a >= 0) & (a < hit.shape[1]) & (e >= 0) & (e < hit.shape[0])
        hit[e[ok], a[ok]] = True
        assert np.all(hit[inside])


def _rose(pattern: FiringPattern) -> tuple[np.ndarray, np.ndarray]:
    """|radius| and angle of each ray on the rose (the angle holds mod pi only: the radius
    takes both signs)."""
    assert pattern.elevation is not None
    a, e = pattern.theta / np.radians(35.2), pattern.elevation / np.radians(38.6)
    return np.hypot(a, e), np.arctan2(e, a)


def test_successive_avia_sweeps_cover_other_directions() -> None:
    """The rose runs on the time of the run: neither its radius (the petals' swing) nor its
    angle (their turn) is back at sweep 0's phase in the sweeps after it, so no sweep repeats
    another (a spinning LiDAR repeats every ray exactly)."""
    model = lidar_model(LidarKind.AVIA)
    s0 = model.pattern(10.0, sweep=0)
    r0, psi0 = _rose(s0)
    d0 = cKDTree(_directions(s0).reshape(-1, 3))
    for k in [*range(1, 21), 100]:
        sk = model.pattern(10.0, sweep=k)
        assert np.array_equal(s0.t_ns, sk.t_ns)
        rk, psik = _rose(sk)
        assert np.abs(rk - r0).max() > 0.02, k  # the radius swings at another phase
        both = (rk > 0.2) & (r0 > 0.2)  # where the angle is well defined
        turn = np.angle(np.exp(2j * (psik - psi0)[both])) / 2  # mod pi
        assert np.degrees(np.median(np.abs(turn))) > 1.0, k  # the petals turned
        # hardly any ray of sweep k lies within 0.01 deg of a ray of sweep 0 (a repeated
        # sweep: all of them)
        near, _ = d0.query(_directions(sk).reshape(-1, 3))
        assert np.mean(near < np.radians(0.01)) < 0.05, k
    # so the coverage accumulates: 0.25 deg cells hit by 5 sweeps, against those hit by one
    cells: list[set[tuple[int, int]]] = []
    for k in range(5):
        p = model.pattern(10.0, sweep=k)
        cell = np.floor(np.degrees(np.stack([p.theta, p.elevation])) / 0.25).astype(int)  # type: ignore[list-item]
        cells.append(set(zip(cell[0].ravel().tolist(), cell[1].ravel().tolist(), strict=True)))
    assert len(set().union(*cells)) > 2.5 * len(cells[0])


def test_avia_looks_into_the_room_by_default() -> None:
    """The forward-looking avia is mounted along the IMU's +y: along +x it would face a wall
    1.5 m away at the sinusoid's start."""
    spec = SimulationSpec(lidar="avia", duration_s=1.0, azimuth_resolution_deg=0.5)
    assert spec.resolved_rpy_deg == AVIA_RPY_DEG == (1.0, 2.0, 95.0)
    assert SimulationSpec(lidar="mid360").resolved_rpy_deg == DEFAULT_RPY_DEG == (1.0, 2.0, 5.0)
    assert SimulationSpec(lidar="avia", rpy_deg=(0.0, 0.0, 5.0)).resolved_rpy_deg[2] == 5.0
    for rpy, looks_in in ((None, True), ((1.0, 2.0, 5.0), False)):
        s = spec.with_(rpy_deg=rpy)
        scan = next(iter(generate_scans(s, build_setup(s), indices=[0])))
        far = np.mean(scan.truth.rho > 3.0)  # share of the points beyond 3 m
        _, counts = np.unique(scan.truth.plane_id, return_counts=True)
        top = counts.max() / counts.sum()  # share of the points on the likeliest plane
        assert (far > 0.8 and top < 0.8) if looks_in else (far < 0.1 and top > 0.9)


@pytest.mark.parametrize(("lidar", "lines", "points"), [("mid360", 4, 20_000), ("avia", 6, 24_000)])
def test_livox_bag_reads_back_as_livox_with_an_imu_in_g(
    tmp_path: Path, lidar: str, lines: int, points: int
) -> None:
    spec = SimulationSpec(lidar=lidar, duration_s=1.2, seed=3, time_offset_s=0.003)
    assert spec.resolved_range_noise_m == 0.02
    out = simulate(spec, tmp_path / "sim")
    truth = Truth.load(out.truth_path)
    assert truth.lidar_intrinsics is not None and truth.lidar_intrinsics.num_beams == lines
    assert np.all(truth.lidar_intrinsics.elevation_correction == 0.0)
    assert truth.simulation is not None and truth.simulation.imu.accel_unit == "g"

    cfg = load_config(None, {"lidar.min_range_m": 0.0, "lidar.max_range_m": 100.0})
    rec = read_segment(out.bag_path, cfg, min_span_s=0.0)
    lay = rec.layout
    assert rec.lidar_topic == "/livox/lidar" and lay.point_step == 26 and lay.height == 1
    assert lay.fields == (
        "x:f4",
        "y:f4",
        "z:f4",
        "intensity:f4",
        "tag:u1",
        "line:u1",
        "timestamp:f8",
    )
    assert lay.ring_field == "line" and lay.beams == lines
    assert (lay.time.field, lay.time.unit, lay.time.reference) == ("timestamp", "ns", "absolute")
    assert lay.time.stamp_position == "start"
    # the accelerometer is detected as g and converted back to m/s^2
    assert (rec.imu_units.accel_unit, rec.imu_units.accel_source) == ("g", "detected")
    assert np.median(np.linalg.norm(rec.imu.accel, axis=1)) == pytest.approx(9.81, abs=0.5)

    setup = build_setup(spec)
    scans = list(generate_scans(spec, setup))
    assert len(rec.scans) == len(scans) == 12
    assert abs(len(scans[0].points) - points) < 100
    for got, sim in zip(rec.scans, scans, strict=True):
        tr = sim.truth
        assert got.stamp_ns - rec.lidar_shift_ns == sim.stamp_ns
        # absolute point times on the LiDAR clock (t_lidar = t_true - time offset)
        t_pub_ns = np.round(tr.t_published_s * 1e9).astype(np.int64)
        t_lidar = spec.base_time_ns + t_pub_ns - setup.time_offset_ns
        t_got = got.t_ns - rec.lidar_shift_ns
        # the stamp is the first point's time (float64 ns hold it to 256 ns), then time order
        assert abs(int(t_got[0]) - sim.stamp_ns) <= 128 and np.all(np.diff(t_got) > 0)
        # each point is the truth's point of its time (points 5 us or 4.17 us apart)
        idx = np.clip(np.searchsorted(t_lidar, t_got - 2500), 0, t_lidar.size - 1)
        assert np.all(np.abs(t_lidar[idx] - t_got) <= 128)
        assert got.ring is not None and np.array_equal(got.ring, tr.beam[idx])
        # the points, placed by the true pose at their time, are the truth's hits up to noise
        r_wl, p_wl = setup.lidar_pose_at(tr.t_true_s[idx])
        p_w = np.einsum("nij,nj->ni", r_wl, got.xyz) + p_wl
        err = np.linalg.norm(p_w - tr.hit_world[idx], axis=1)
        assert np.sqrt(np.mean(err**2)) == pytest.approx(0.02, rel=0.1)
        assert err.max() < 6 * 0.02


@pytest.mark.parametrize("lidar", [LidarKind.MID360, LidarKind.AVIA])
def test_livox_messages_hold_acceleration_in_g(tmp_path: Path, lidar: LidarKind) -> None:
    from rosbags.highlevel import AnyReader

    from licalib_cli.simulation import generate_imu

    spec = SimulationSpec(lidar=lidar, duration_s=0.3, azimuth_resolution_deg=1.0)
    out = simulate(spec, tmp_path)
    imu, _ = generate_imu(spec)
    with AnyReader([out.bag_path]) as reader:
        conns = [c for c in reader.connections if c.topic == "/imu/data"]
        msgs = [reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages(conns)]
    accel = np.array(
        [[m.linear_acceleration.x, m.linear_acceleration.y, m.linear_acceleration.z] for m in msgs]
    )
    gyro = np.array(
        [[m.angular_velocity.x, m.angular_velocity.y, m.angular_velocity.z] for m in msgs]
    )
    assert np.allclose(accel * STANDARD_GRAVITY, imu.accel, rtol=1e-12, atol=1e-12)
    assert np.array_equal(gyro, imu.gyro)  # rad/s


@pytest.mark.parametrize(("lidar", "name"), [("mid360", "Mid-360"), ("avia", "Avia")])
@pytest.mark.parametrize(
    "effect",
    [
        "lidar_elevation",
        "lidar_azimuth",
        "lidar_vertical_offset",
        "lidar_horizontal_offset",
        "lidar_range_scale",
        "lidar_range_offset",
    ],
)
def test_livox_refuses_per_beam_lidar_effects(effect: str, lidar: str, name: str) -> None:
    msg = f"--effect {effect} is a per-beam LiDAR effect and the {name} has no fixed beams"
    with pytest.raises(ConfigError, match=msg):
        SimulationSpec(lidar=lidar, effects=(effect,))
    SimulationSpec(lidar="vlp16", effects=(effect,))  # a spinning LiDAR takes it


@pytest.mark.parametrize(("lidar", "lines"), [("mid360", 4), ("avia", 6)])
def test_livox_intrinsics_and_the_effects_it_takes(lidar: str, lines: int) -> None:
    spec = SimulationSpec(
        lidar=lidar, duration_s=1.0, effects=("lidar_point_time", "gyro_scale", "g_sensitivity")
    )
    assert spec.resolved_point_time_error != 0.0
    setup = build_setup(spec)  # random intrinsics: the IMU's drawn, none of the LiDAR's
    assert not np.allclose(setup.imu_intrinsics.gyro_scale, 1.0)
    assert not np.allclose(setup.imu_intrinsics.accel_bias, 0.0)
    kin = setup.lidar_intrinsics
    assert kin.num_beams == lines
    for name in ("elevation_correction", "azimuth_correction", "vertical_offset", "range_offset"):
        assert np.all(getattr(kin, name) == 0.0), name
    assert np.all(kin.range_scale == 1.0)


def test_cli_takes_livox_and_refuses_their_per_beam_effects(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    out_dir = tmp_path / "sim"
    args = ["simulate", str(out_dir), "--lidar", "mid360", "--effect", "lidar_range_offset"]
    with pytest.raises(SystemExit) as exc:
        main(args)
    assert exc.value.code == ConfigError.exit_code
    err = capsys.readouterr().err
    assert "per-beam LiDAR effect" in err and "Mid-360" in err and "Traceback" not in err
    assert not out_dir.exists()
    monkeypatch.setenv("COLUMNS", "200")  # the choices on one line
    main(["simulate", "--help"])
    assert "|os1-128|mid360|avia>" in capsys.readouterr().out
    with pytest.raises(SystemExit) as exc:
        main(["simulate", str(out_dir), "--lidar", "avia", "--effect", "lidar_elevation"])
    assert exc.value.code == ConfigError.exit_code
    err = capsys.readouterr().err
    assert "per-beam LiDAR effect" in err and "Avia" in err and "Traceback" not in err
    assert not out_dir.exists()
