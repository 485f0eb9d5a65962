"""Spinning rings or non-repetitive lines: the beam field classified, lines binned by elevation,
their range noise measured along each line, per-beam intrinsics refused."""

from __future__ import annotations

import numpy as np
import pytest

from licalib_cli.config import CalibConfig
from licalib_cli.consistency import line_range_noise, range_noise
from licalib_cli.errors import ConfigError
from licalib_cli.io.beam_spread import SPREAD_DEG, elevation_spread_deg
from licalib_cli.measurements import LidarScan
from licalib_cli.pipeline.scan_pattern import (
    BIN_DEG,
    check_model,
    elevation_beams,
    scan_pattern,
    with_scan_pattern,
)
from licalib_cli.pipeline.settings import free_parameters

NS = 1_000_000_000
RATE = 50_000.0  # points a second per line


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(20261206)


def _room_range(u: np.ndarray) -> np.ndarray:
    """Range to the walls of an 8 x 6 x 4 m box centred on the sensor, along unit rays u."""
    half = np.array([4.0, 3.0, 2.0])
    with np.errstate(divide="ignore"):
        t = np.where(np.abs(u) > 1e-12, half / np.abs(u), np.inf)
    return np.min(t, axis=1)


def _line_scans(rng: np.random.Generator, num_scans: int, noise: float) -> list[LidarScan]:
    """Four lasers each tracing a rosette over a 70 deg field of view (an Avia-like pattern:
    petals that turn back and forth in azimuth and elevation), in a box room, range noise
    along the rays; about 0.7 deg between a line's consecutive points."""
    scans = []
    per_line = int(RATE * 0.1)
    for k in range(num_scans):
        xyz, t, line = [], [], []
        for i in range(4):
            tt = k * 0.1 + np.arange(per_line) / RATE
            radius = np.radians(35.0) * np.cos(3 * 2 * np.pi * 26.5 * tt)
            turn = 2 * np.pi * 1.3 * tt + i * np.pi / 2
            az, el = radius * np.cos(turn), radius * np.sin(turn)
            u = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=1)
            r = _room_range(u) + rng.normal(0.0, noise, per_line)
            xyz.append(u * r[:, None])
            t.append(np.round(tt * NS).astype(np.int64))
            line.append(np.full(per_line, i))
        order = np.argsort(np.concatenate(t), kind="stable")
        scans.append(
            LidarScan(
                stamp_ns=int(k * 0.1 * NS),
                xyz=np.concatenate(xyz)[order],
                t_ns=np.concatenate(t)[order],
                ring=np.concatenate(line)[order].astype(np.int16),
            )
        )
    return scans


def _ring_scans(rng: np.random.Generator, num_scans: int, noise: float) -> list[LidarScan]:
    """Sixteen rings at fixed elevations -15..15 deg, 1800 azimuths a sweep."""
    elev = np.radians(np.linspace(-15.0, 15.0, 16))
    scans = []
    for k in range(num_scans):
        az = np.repeat(np.linspace(-np.pi, np.pi, 1800, endpoint=False), 16)
        el = np.tile(elev, 1800)
        u = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=1)
        r = _room_range(u) + rng.normal(0.0, noise, az.size)
        t = int(k * 0.1 * NS) + np.arange(az.size, dtype=np.int64) * 3000
        ring = np.tile(np.arange(16), 1800).astype(np.int16)
        scans.append(LidarScan(int(k * 0.1 * NS), u * r[:, None], t, ring))
    return scans


def _spread(scans: list[LidarScan]) -> float:
    return elevation_spread_deg([s.xyz for s in scans], [s.ring for s in scans])


def test_a_lasers_lines_are_told_from_a_spinning_lidars_rings(rng: np.random.Generator) -> None:
    lines = _spread(_line_scans(rng, 3, 0.02))
    rings = _spread(_ring_scans(rng, 3, 0.02))
    assert lines > 5 * SPREAD_DEG
    assert rings < 0.01
    cfg = CalibConfig()
    assert scan_pattern(lines, cfg).non_repetitive
    assert not scan_pattern(rings, cfg).non_repetitive
    assert not scan_pattern(float("nan"), cfg).non_repetitive  # no ring field: recovered rings
    # the config decides when it says
    forced = CalibConfig.model_validate({"lidar": {"scan_pattern": "spinning"}})
    assert not scan_pattern(lines, forced).non_repetitive
    assert scan_pattern(lines, forced).source == "config"


def test_the_range_noise_of_lines_is_measured_along_each_lines_point_order(
    rng: np.random.Generator,
) -> None:
    """Sorted by azimuth, a line's neighbours lie at other elevations and the second
    differences measure the room, not the noise; along the line's own order they measure the
    noise."""
    scans = _line_scans(rng, 4, 0.02)
    xyz = np.concatenate([s.xyz for s in scans])
    index = np.concatenate([np.full(len(s), i) for i, s in enumerate(scans)])
    line = np.concatenate([s.ring for s in scans]).astype(np.int64)
    t = np.concatenate([s.t_ns for s in scans])
    along = line_range_noise(index, line, t, xyz, 4).sigma
    np.testing.assert_allclose(along, 0.02, rtol=0.1)
    by_azimuth = range_noise(
        index, line, np.arctan2(xyz[:, 1], xyz[:, 0]), np.linalg.norm(xyz, axis=1), 4
    ).sigma
    assert np.all(by_azimuth > 5 * 0.02)


def test_lines_are_binned_by_elevation_so_the_models_rays_are_the_points(
    rng: np.random.Generator,
) -> None:
    scans = tuple(_line_scans(rng, 2, 0.0))
    binned, phi = elevation_beams(scans)
    for before, after in zip(scans, binned, strict=True):
        assert after.ring is not None and before.ring is not None
        elev = np.arcsin(after.xyz[:, 2] / np.linalg.norm(after.xyz, axis=1))
        # every point within a bin of its beam's nominal elevation
        assert np.max(np.abs(elev - phi[after.ring])) <= np.radians(BIN_DEG)
        np.testing.assert_array_equal(after.xyz, before.xyz)
    assert np.all(np.diff(phi) > 0)  # bins numbered from the lowest
    assert 70.0 / BIN_DEG - 10 <= phi.shape[0] <= 70.0 / BIN_DEG + 10


def test_per_beam_intrinsics_of_a_non_repetitive_scanner_are_refused_and_never_freed(
    rng: np.random.Generator,
) -> None:
    cfg = CalibConfig.model_validate({"model": {"lidar": ["range_offset", "point_time"]}})
    pattern = scan_pattern(_spread(_line_scans(rng, 2, 0.02)), cfg)
    with pytest.raises(ConfigError, match=r"non-repetitive.*range_offset cannot be estimated"):
        check_model(cfg, pattern)
    # the per-point time is not a beam's: allowed
    check_model(CalibConfig.model_validate({"model": {"lidar": ["point_time"]}}), pattern)
    resolved = with_scan_pattern(CalibConfig(), pattern)
    assert resolved.lidar.scan_pattern == "non_repetitive"
    assert not free_parameters(resolved, intrinsics=True).beam_intrinsics
    assert not free_parameters(resolved, intrinsics=False).beam_intrinsics
    assert free_parameters(CalibConfig(), intrinsics=True).beam_intrinsics


def test_lines_facing_a_near_wall_are_still_lines(rng: np.random.Generator) -> None:
    """A forward-looking scanner facing a wall a metre away sees a few far points in one patch
    (an open door): those alone spread little; the near points tell the lines."""
    scans = _line_scans(rng, 3, 0.0)
    xyz, ring = [], []
    for s in scans:
        p = s.xyz * (1.5 / np.linalg.norm(s.xyz, axis=1))[:, None]  # a wall 1.5 m away
        door = np.abs(np.degrees(np.arctan2(p[:, 1], p[:, 0]))) < 2.0
        door &= np.abs(np.degrees(np.arcsin(p[:, 2] / 1.5))) < 2.0
        p[door] *= 4.0
        xyz.append(p)
        ring.append(s.ring)
    assert 0 < np.mean(np.concatenate([np.linalg.norm(p, axis=1) > 3.0 for p in xyz])) < 0.05
    assert elevation_spread_deg(xyz, ring) > 5 * SPREAD_DEG


def test_an_unknown_scan_pattern_is_refused_naming_the_choices(
    capsys: pytest.CaptureFixture[str],
) -> None:
    from licalib_cli.cli import main

    with pytest.raises(SystemExit) as stop:
        main(["config", "dump", "--set", "lidar.scan_pattern=rings"])
    assert stop.value.code == 6
    err = capsys.readouterr().err
    assert "lidar.scan_pattern" in err and "'spinning' or 'non_repetitive'" in err
    assert "Traceback" not in err


def test_a_non_repetitive_scanner_draws_noisier_refits_at_any_range_noise(
    rng: np.random.Generator,
) -> None:
    """The refits with more range noise run from checks.range_noise_draws_from_m (2.5 cm) on a
    spinning LiDAR, and at 2 cm or less on lines (a clean Avia-like shake at 2 cm was 3.6 of its
    linearised sigmas off); checks.range_noise_draws: 0 turns them off for both."""
    from licalib_cli.pipeline.noise_draws import draws_due
    from licalib_cli.pipeline.settings import NoiseLevels

    def levels(measured: float) -> NoiseLevels:
        gyro, accel = np.full(3, 1e-3), np.full(3, 1e-2)
        per_beam = np.full(4, measured)
        return NoiseLevels(
            gyro, accel, measured, "data", "data", "data", per_beam, gyro, accel, measured
        )

    lines = with_scan_pattern(
        CalibConfig(), scan_pattern(_spread(_line_scans(rng, 2, 0.02)), CalibConfig())
    )
    assert lines.lidar.scan_pattern == "non_repetitive"
    assert draws_due(levels(0.02), lines) and draws_due(levels(0.005), lines)
    assert not draws_due(levels(0.02), CalibConfig())
    assert draws_due(levels(0.03), CalibConfig())
    off = lines.model_copy(
        update={"checks": lines.checks.model_copy(update={"range_noise_draws": 0})}
    )
    assert not draws_due(levels(0.02), off)
