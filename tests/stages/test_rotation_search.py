"""The sharpness search for the rotation extrinsic and the initialisation that falls back on it."""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from licalib_cli.config import load_config
from licalib_cli.errors import ExcitationError
from licalib_cli.initialization.rotation import GyroIntegrator
from licalib_cli.initialization.rotation_search import (
    RotationSearchConfig,
    search_rotation_extrinsic,
    super_fibonacci_rotations,
)
from licalib_cli.initialization.single_axis import single_axis_rotation
from licalib_cli.io.reader import read_segment
from licalib_cli.measurements import ImuSamples
from licalib_cli.odometry import PoseSeries
from licalib_cli.parallel import threads as thr
from licalib_cli.pipeline.initialise import (
    SINGLE_AXIS,
    align_rotation_and_time,
    gyro_aided_alignment,
    lidar_odometry,
)
from licalib_cli.simulation.ground_truth import build_setup
from licalib_cli.simulation.simulate import simulate
from licalib_cli.simulation.spec import IntrinsicsMode, Mounting, Scenario, SimulationSpec


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(Rotation.from_matrix(a.T @ b).magnitude()))


def test_super_fibonacci_grid_covers_so3() -> None:
    """3000 quaternions: unit norm, and every rotation lies within about 17 deg of one of them."""
    q = super_fibonacci_rotations(3000)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-12)
    grid = Rotation.from_quat(q)
    probes = Rotation.random(300, random_state=4)
    # Distance of each probe to its nearest grid rotation: |q_p . q_g| = cos(angle / 2).
    dots = np.abs(probes.as_quat() @ q.T).max(axis=1)
    worst = np.degrees(2.0 * np.arccos(np.clip(dots, -1.0, 1.0))).max()
    assert worst < 17.0, worst
    assert len(grid) == 3000


@pytest.fixture(scope="module")
def shake(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, SimulationSpec]:
    """3 s of violent hand-held shaking with a random mounting (a flip of over 100 deg)."""
    spec = SimulationSpec(
        scenario=Scenario.SHAKE,
        duration_s=3.0,
        seed=5,
        intrinsics=IntrinsicsMode.NONE,
        random_extrinsic=True,
        time_offset_s=0.01,
    )
    out = simulate(spec, tmp_path_factory.mktemp("shake"))
    return out.bag_path, spec


def test_search_finds_any_mounting_without_odometry(shake: tuple[Path, SimulationSpec]) -> None:
    bag, spec = shake
    truth = build_setup(spec).extrinsic.rotation
    assert np.degrees(Rotation.from_matrix(truth).magnitude()) > 90.0
    rec = read_segment(bag, load_config(None))
    found = search_rotation_extrinsic(rec.scans, GyroIntegrator.from_imu(rec.imu))
    # Measured: 12.9 deg (translation and the 10 ms offset ignored bias the sharpness a little),
    # next distinct 1.08x; the gyro-aided rounds that follow converge from 30 deg and more.
    assert _angle_deg(found.R_imu_lidar, truth) < 20.0
    assert found.ambiguity > 1.03
    assert found.smear_score > 1.15 * found.score


def _fake_search(
    best_at: float,
    calls: list[float],
    sharp_within: float = 0.012,
    flat_beyond: float = 1.0,
    smear: float = 2.0,
    normals: Callable[[float], float] | None = None,
):
    """A search whose score is V-shaped in the time offset assumed (lowest at ``best_at``),
    flat with a little noise farther than ``flat_beyond`` from it, and that tells the rotation
    only within ``sharp_within`` of it, as on a violent shake. The full searches' offsets are
    appended to ``calls``; the coarse scan's cheaper ones (fewer starts) are not."""
    from licalib_cli.initialization.rotation_search import RotationSearch, RotationSearchConfig

    full_starts = RotationSearchConfig().refine_starts

    def search(scans, gyro, time_offset_s=0.0, cfg=None):
        if cfg is None or cfg.refine_starts == full_starts:
            calls.append(time_offset_s)
        off = abs(time_offset_s - best_at)
        noise = 0.01 * math.sin(997.0 * time_offset_s) if off > flat_beyond else 0.0
        return RotationSearch(
            R_imu_lidar=np.eye(3),
            score=1.28 + 2.5 * min(off, flat_beyond) + noise,
            ambiguity=1.10 if off < sharp_within else 1.007,
            smear_score=smear,
            windows=np.zeros((1, 2), dtype=np.int64),
            time_offset_s=time_offset_s,
            normal_sharpening=None if normals is None else normals(off),
        )

    return search


def test_an_ambiguous_search_searches_the_time_offset_too(monkeypatch: pytest.MonkeyPatch) -> None:
    """At the offset assumed (0 s) the rotation is ambiguous; the true one is -44 ms: the lag is
    scanned (40 ms steps, a cheaper search), the offset stepped downhill from the scan's best
    (20 ms steps) and refined by a parabola, and the sharpest search is returned, unambiguous,
    with its offset. Not searched when the first search is clear, nor beyond the lag allowed."""
    from licalib_cli.initialization import rotation_search as rs

    calls: list[float] = []
    scanned: list[float] = []
    fake = _fake_search(-0.044, calls)

    def recording(scans, gyro, time_offset_s=0.0, cfg=None):
        if cfg is not None and cfg.refine_starts < RotationSearchConfig().refine_starts:
            scanned.append(time_offset_s)
        return fake(scans, gyro, time_offset_s, cfg)

    monkeypatch.setattr(rs, "search_rotation_extrinsic", recording)
    found = rs.search_rotation_and_time_offset([], None, 0.0)  # type: ignore[arg-type]
    assert found.unambiguous and abs(found.time_offset_s + 0.044) < 0.005
    # two full searches (at the offset assumed and at the one found); the rest the cheaper one
    assert calls == [0.0, found.time_offset_s]
    # the scan: every 40 ms within the lag (0.2 s)
    grid = [-0.2, -0.16, -0.12, -0.08, -0.04, 0.0, 0.04, 0.08, 0.12, 0.16, 0.2]
    assert all(any(abs(t - g) < 1e-9 for t in scanned) for g in grid)
    assert len(scanned) <= len(grid) + 5
    calls.clear()
    clear = rs.search_rotation_and_time_offset([], None, -0.045)  # type: ignore[arg-type]
    assert calls == [-0.045] and clear.time_offset_s == -0.045
    calls.clear()
    scanned.clear()
    limited = rs.search_rotation_and_time_offset([], None, 0.0, max_lag_s=0.02)  # type: ignore[arg-type]
    assert not limited.unambiguous and abs(limited.time_offset_s) <= 0.0201
    assert min(scanned) >= -0.0401  # a step beyond the lag at most, for the parabola
    # an offset at which the search cannot run (too few scans inside the IMU data) is skipped
    calls.clear()

    def limited_data(scans, gyro, time_offset_s=0.0, cfg=None):
        if time_offset_s < -0.05:
            raise ExcitationError("too few scans")
        return fake(scans, gyro, time_offset_s, cfg)

    monkeypatch.setattr(rs, "search_rotation_extrinsic", limited_data)
    edge = rs.search_rotation_and_time_offset([], None, 0.0)  # type: ignore[arg-type]
    assert edge.unambiguous and abs(edge.time_offset_s + 0.044) < 0.005


def test_the_offset_scan_finds_an_offset_where_the_sharpness_is_flat(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """+180 ms on a shake: within 0.1 s of the assumed offset the sharpness is flat and noisy
    (the downhill steps alone stopped at once, or walked the wrong way); the scan over the lag
    finds the basin and the steps and the parabola its bottom."""
    from licalib_cli.initialization import rotation_search as rs

    for truth in (0.18, -0.18, 0.09):
        calls: list[float] = []
        monkeypatch.setattr(rs, "search_rotation_extrinsic", _fake_search(truth, calls, 0.012, 0.1))
        found = rs.search_rotation_and_time_offset([], None, 0.0)  # type: ignore[arg-type]
        assert found.unambiguous and abs(found.time_offset_s - truth) < 0.005, truth
        assert len(calls) == 2  # the full search at 0 s and at the offset found


def test_the_offset_scan_says_how_long_it_takes_and_shows_its_progress(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """A lag raised by hand to 1 s makes the scan 51 searches: the log gives their number and
    the time they take (from the first's) and names the settings that shorten it; the progress
    callback counts them."""
    from licalib_cli.initialization import rotation_search as rs

    calls: list[float] = []
    monkeypatch.setattr(rs, "search_rotation_extrinsic", _fake_search(0.5, calls, 0.012, 0.1))
    ticks: list[tuple[int, int]] = []
    with caplog.at_level("INFO", logger=rs.__name__):
        found = rs.search_rotation_and_time_offset(
            [],
            None,  # type: ignore[arg-type]
            0.0,
            max_lag_s=1.0,
            progress=lambda done, total: ticks.append((done, total)),
        )
    assert abs(found.time_offset_s - 0.5) < 0.005
    assert ticks == [(k, 51) for k in range(1, 52)]
    said = " ".join(r.getMessage() for r in caplog.records)
    assert "51 searches every 40 ms, about" in said
    assert "initialization.time_offset_s" in said and "time_offset_max_lag_s" in said
    assert rs._duration_text(42.0) == "42 s"
    assert rs._duration_text(210.0) == "3.5 min"
    assert rs._duration_text(3.0 * 3600) == "3.0 h"
    # the 51 cheaper searches report themselves at DEBUG, the full ones at INFO
    assert rs._scan_config(RotationSearchConfig()).log_level == logging.DEBUG
    assert RotationSearchConfig().log_level == logging.INFO
    # unambiguous at 0 s but hardly sharper than a random rotation (an OS1-32 shake at +190 ms:
    # 1.029 and 1.09x): the offset is scanned all the same, and the sharper one taken
    calls = []
    blurred = _fake_search(0.19, calls, sharp_within=1.0, flat_beyond=0.1, smear=1.8)
    monkeypatch.setattr(rs, "search_rotation_extrinsic", blurred)
    found = rs.search_rotation_and_time_offset([], None, 0.0)  # type: ignore[arg-type]
    assert abs(found.time_offset_s - 0.19) < 0.005
    # slow motion: the offset hardly changes the sharpness; the scan's minimum is noise and the
    # unambiguous search at the offset assumed is kept
    calls = []
    slow = _fake_search(0.0, calls, sharp_within=1.0, flat_beyond=0.0, smear=1.4)
    monkeypatch.setattr(rs, "search_rotation_extrinsic", slow)
    kept = rs.search_rotation_and_time_offset([], None, 0.0)  # type: ignore[arg-type]
    assert kept.time_offset_s == 0.0 and len(calls) > 1
    # the surface normals decide when there are any: a lever arm of metres blurs the points
    # (the whole score 1.25x) but not the normals (1.6x), and nothing is scanned
    calls = []
    lever = _fake_search(-0.03, calls, sharp_within=1.0, smear=1.6, normals=lambda off: 1.6)
    monkeypatch.setattr(rs, "search_rotation_extrinsic", lever)
    near = rs.search_rotation_and_time_offset([], None, 0.0)  # type: ignore[arg-type]
    assert calls == [0.0] and near.time_offset_s == 0.0
    # while normals hardly sharper than at random (1.25x) have the offset scanned, however
    # sharp the points look
    calls = []
    far = _fake_search(
        0.19, calls, 1.0, 0.1, smear=3.0, normals=lambda off: 1.8 if off < 0.05 else 1.25
    )
    monkeypatch.setattr(rs, "search_rotation_extrinsic", far)
    found = rs.search_rotation_and_time_offset([], None, 0.0)  # type: ignore[arg-type]
    assert abs(found.time_offset_s - 0.19) < 0.005


def test_an_ambiguous_search_names_the_lag_when_the_offset_was_searched(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The refusal after an ambiguous search says the clocks may differ by more than the lag
    scanned when the time offset was free (a +0.4 s offset on a shake, the lag 0.2 s), and only
    the rotation or the given offset when the offset was given (a shake given 0.3 s for 0 s was
    told to rotate about two axes)."""
    import importlib
    from types import SimpleNamespace

    ini = importlib.import_module("licalib_cli.pipeline.initialise")

    ambiguous = _fake_search(0.4, [], 0.012)(None, None, 0.0)
    monkeypatch.setattr(ini, "search_rotation_and_time_offset", lambda *a, **k: ambiguous)
    monkeypatch.setattr(ini, "search_rotation_extrinsic", lambda *a, **k: ambiguous)
    odo = SimpleNamespace(search=None)
    t = np.arange(5, dtype=np.int64) * 5_000_000
    imu = ImuSamples(t, np.zeros((5, 3)), np.tile([0.0, 0.0, 9.81], (5, 1)))
    rec = SimpleNamespace(scans=[], lidar_shift_ns=0, clock_offset_s=0.01, imu=imu)
    with pytest.raises(
        ExcitationError, match=r"more than the 0\.2 s searched: raise initialization\.time_offset"
    ) as free:
        ini._searched_rotation(rec, odo, None, 0.0, load_config(None))  # type: ignore[arg-type]
    assert str(free.value).count(". ") == 0  # one sentence
    given = load_config(None, {"initialization": {"time_offset_s": 0.3}})
    with pytest.raises(ExcitationError) as fixed:
        ini._searched_rotation(rec, odo, None, 0.3, given)  # type: ignore[arg-type]
    assert "max_lag" not in str(fixed.value)
    assert (
        "(the rig turned about one axis only, or the initialization.time_offset_s of 0.3 s the "
        "config gives is off, since the scans are deskewed with the gyro at that offset: remove "
        "it to search the offset)" in str(fixed.value)
    )


def test_an_ambiguous_search_that_a_mirrored_gyro_makes_clear_names_a_left_handed_imu(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """On violent motion no LiDAR-only odometry runs to compare rotations with: when the search
    on the gyro as recorded is ambiguous but the same search on the gyro with one axis's sign
    flipped is clear, the IMU's frame is left-handed against the LiDAR's (a shake whose IMU
    flips y stopped saying the rotation excitation was too weak)."""
    import importlib
    from types import SimpleNamespace

    from licalib_cli.errors import DataError

    ini = importlib.import_module("licalib_cli.pipeline.initialise")
    ambiguous = _fake_search(0.4, [], 0.012)(None, None, 0.0)
    clear = _fake_search(0.0, [], 0.012)(None, None, 0.0)
    assert not ambiguous.unambiguous and clear.unambiguous
    seen: list[object] = []

    def search(scans, gyro, *a, **k):  # type: ignore[no-untyped-def]
        seen.append(gyro)  # the gyro as recorded (None here), then the mirrored one
        return ambiguous if len(seen) == 1 else clear

    monkeypatch.setattr(ini, "search_rotation_and_time_offset", search)
    t = np.arange(5, dtype=np.int64) * 5_000_000
    imu = ImuSamples(t, np.zeros((5, 3)), np.tile([0.0, 0.0, 9.81], (5, 1)))
    rec = SimpleNamespace(scans=[], lidar_shift_ns=0, clock_offset_s=0.01, imu=imu)
    with pytest.raises(DataError) as flipped:
        ini._searched_rotation(rec, SimpleNamespace(search=None), None, 0.0, load_config(None))  # type: ignore[arg-type]
    assert len(seen) == 2 and seen[0] is None and seen[1] is not None
    assert str(flipped.value).startswith(
        "The IMU's axes form a left-handed frame against the LiDAR's: no rotation extrinsic"
    )
    # a mirrored search just unambiguous but no sharper than the recorded one names nothing (a
    # walk whose odometry did not follow): the motion is blamed, as without the mirror
    clear = replace(clear, score=ambiguous.score * 1.03, ambiguity=1.021)
    seen.clear()
    with pytest.raises(ExcitationError, match=r"^Rotation excitation is too weak"):
        ini._searched_rotation(rec, SimpleNamespace(search=None), None, 0.0, load_config(None))  # type: ignore[arg-type]
    assert len(seen) == 2


def test_the_lag_widens_to_the_clocks_difference_from_record_times() -> None:
    """The record times put the clocks 0.4 s apart (a LiDAR stamped late): the time offset is
    searched within +-0.5 s instead of the configured 0.2 s, still around zero; a smaller
    difference, or one shifted away (1 s and more), leaves the lag as configured."""
    import importlib
    from types import SimpleNamespace

    ini = importlib.import_module("licalib_cli.pipeline.initialise")
    cfg = load_config(None)
    for coarse, shift, lag in ((0.4, 0, 0.5), (-0.4, 0, 0.5), (0.15, 0, 0.2), (3.0, 3, 0.2)):
        rec = SimpleNamespace(clock_offset_s=coarse, lidar_shift_ns=shift)
        assert ini.time_offset_lag_s(rec, cfg) == pytest.approx(lag), coarse
    wide = load_config(None, {"initialization": {"time_offset_max_lag_s": 0.6}})
    rec = SimpleNamespace(clock_offset_s=0.4, lidar_shift_ns=0)
    assert ini.time_offset_lag_s(rec, wide) == pytest.approx(0.6)


def test_search_threaded_is_the_serial_search(
    shake: tuple[Path, SimulationSpec], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The candidate batches run on the block threads: the same scores, bit for bit."""
    bag, _ = shake
    rec = read_segment(bag, load_config(None))
    gyro = GyroIntegrator.from_imu(rec.imu)
    monkeypatch.setattr(thr, "THREADS", 2)  # also when the suite runs with LICALIB_THREADS=1
    threaded = search_rotation_extrinsic(rec.scans, gyro)
    with thr.serial():
        alone = search_rotation_extrinsic(rec.scans, gyro)
    assert np.array_equal(threaded.R_imu_lidar, alone.R_imu_lidar)
    assert threaded.score == alone.score
    assert threaded.ambiguity == alone.ambiguity


def test_search_is_ambiguous_for_rotation_about_one_axis(tmp_path: Path) -> None:
    """The paper's planar figure-8: yaw only, so the extrinsic's rotation about it is free."""
    spec = SimulationSpec(
        scenario=Scenario.FIGURE8,
        duration_s=2.0,
        seed=1,
        intrinsics=IntrinsicsMode.NONE,
        azimuth_resolution_deg=0.8,
    )
    out = simulate(spec, tmp_path)
    rec = read_segment(out.bag_path, load_config(None))
    found = search_rotation_extrinsic(rec.scans, GyroIntegrator.from_imu(rec.imu))
    assert found.ambiguity < 1.02


def test_initialisation_falls_back_to_the_search(shake: tuple[Path, SimulationSpec]) -> None:
    """LiDAR-only odometry cannot follow this motion; the search and gyro-aided rounds can."""
    bag, spec = shake
    truth = build_setup(spec).extrinsic.rotation
    cfg = load_config(None)
    rec = read_segment(bag, cfg)
    odo = lidar_odometry(rec, cfg)
    # The gyro shows the shaking before any registration: kiss-icp is not run, the scans are
    # deskewed and predicted with the gyro and the searched rotation from the first one.
    assert odo.constant_velocity_deg > 3.0
    assert odo.kiss is None and odo.gyro_aided and odo.search is not None
    gyro = GyroIntegrator.from_imu(rec.imu)
    a = align_rotation_and_time(rec, odo, gyro, cfg)
    assert a.rotation_source == "search + gyro-aided hand-eye"
    assert a.time_offset_source == "cross-correlation"
    # The gyro's timing leaks into the odometry it deskews, so the first coarse offset is pulled
    # towards the zero assumed (measured 6.1 ms); the gyro-aided rounds re-estimate it.
    assert abs(a.time_offset_s - spec.time_offset_s) < 0.006
    a = gyro_aided_alignment(rec, odo, gyro, a, cfg)
    # Measured: 9.7 ms, 0.06 deg, hand-eye residual 0.05 deg.
    assert abs(a.time_offset_s - spec.time_offset_s) < 0.002
    assert _angle_deg(a.rotation, truth) < 1.0
    assert a.hand_eye is not None
    assert a.hand_eye.residual_rms_deg < 0.3


def test_single_axis_motion_takes_the_rotation_from_the_accelerations(tmp_path: Path) -> None:
    """Figure-8 with mounting C: yaw only (in the robot frame); hand-eye cannot fix the angle
    about the axis, the accelerations within the plane do."""
    spec = SimulationSpec(
        scenario=Scenario.FIGURE8,
        duration_s=6.0,
        seed=2,
        intrinsics=IntrinsicsMode.NONE,
        azimuth_resolution_deg=0.8,
        mounting=Mounting.C,
    )
    out = simulate(spec, tmp_path)
    truth = build_setup(spec).extrinsic.rotation
    cfg = load_config(None)
    rec = read_segment(out.bag_path, cfg)
    odo = lidar_odometry(rec, cfg)
    gyro = GyroIntegrator.from_imu(rec.imu)
    a = align_rotation_and_time(rec, odo, gyro, cfg)
    assert a.rotation_source == SINGLE_AXIS
    assert a.hand_eye is None
    # Measured: 1.2 deg (10 s, seed 0); the optimisation refines it.
    assert _angle_deg(a.rotation, truth) < 4.0
    # The axis found is the robot's vertical in the IMU frame.
    found = single_axis_rotation(rec.imu, gyro, odo.refined, 0.0)
    vertical = np.array([0.5, 0.433, 0.75]) / np.linalg.norm([0.5, 0.433, 0.75])
    assert abs(abs(found.axis_imu @ vertical) - 1.0) < 1e-3
    # Odometry of the same rig: its rotations between scans are the gyro's to a few per cent.
    assert found.relative_residual < 0.15
    # Poses of another motion (turning about the LiDAR's axis as much, at other times): the
    # sensors do not turn together.
    steps = np.linalg.norm(
        (
            Rotation.from_matrix(odo.refined.T_map_lidar[:-1, :3, :3]).inv()
            * Rotation.from_matrix(odo.refined.T_map_lidar[1:, :3, :3])
        ).as_rotvec(),
        axis=1,
    )
    angles = np.concatenate([[0.0], np.cumsum(np.random.default_rng(5).permutation(steps))])
    turned = odo.refined.T_map_lidar.copy()
    turned[:, :3, :3] = (
        Rotation.from_rotvec(angles[:, None] * found.axis_lidar)
        * Rotation.from_matrix(turned[0, :3, :3])
    ).as_matrix()
    other = PoseSeries(
        t_ns=odo.refined.t_ns,
        T_map_lidar=turned,
        n_points=odo.refined.n_points,
        n_keypoints=odo.refined.n_keypoints,
        threshold_m=odo.refined.threshold_m,
        deviation_m=odo.refined.deviation_m,
        deviation_deg=odo.refined.deviation_deg,
    )
    with pytest.raises(ExcitationError, match="disagree on how the rig turned"):
        single_axis_rotation(rec.imu, gyro, other, 0.0)


def test_single_axis_rotation_refuses_a_rig_that_does_not_turn(tmp_path: Path) -> None:
    spec = SimulationSpec(
        scenario=Scenario.FIGURE8,
        duration_s=1.0,
        seed=2,
        intrinsics=IntrinsicsMode.NONE,
        azimuth_resolution_deg=1.0,
    )
    out = simulate(spec, tmp_path)
    rec = read_segment(out.bag_path, load_config(None), min_span_s=0.0)  # a 1 s stage test
    k = len(rec.scans)
    # A rig standing still: the gyro reads zero and the LiDAR poses never change.
    imu = ImuSamples(rec.imu.t_ns, np.zeros_like(rec.imu.gyro), rec.imu.accel)
    still = PoseSeries(
        t_ns=np.array([s.t_ns.max() for s in rec.scans]),
        T_map_lidar=np.tile(np.eye(4), (k, 1, 1)),
        n_points=np.zeros(k, np.int64),
        n_keypoints=np.zeros(k, np.int64),
        threshold_m=np.zeros(k),
        deviation_m=np.zeros(k),
        deviation_deg=np.zeros(k),
    )
    with pytest.raises(ExcitationError, match="hardly turns"):
        single_axis_rotation(imu, GyroIntegrator.from_imu(imu), still, 0.0)
