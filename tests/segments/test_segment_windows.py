"""Window arithmetic of select-segments, the ranking rule, and --segments parsing."""

from __future__ import annotations

import numpy as np
import pytest

from licalib_cli.errors import ConfigError, ExcitationError
from licalib_cli.pipeline.joint import parse_segments
from licalib_cli.pipeline.segments import WindowScore, choose, plan_windows


def test_windows_side_by_side_cover_the_range_exactly() -> None:
    assert plan_windows(0.0, 12.0, 3.0, 3.0) == [(0, 3), (3, 6), (6, 9), (9, 12)]


def test_a_tail_window_is_aligned_to_the_end() -> None:
    # 10 s with 3 s windows: three regular ones, then [7, 10] so that no data are left out
    assert plan_windows(0.0, 10.0, 3.0, 3.0) == [(0, 3), (3, 6), (6, 9), (7, 10)]


def test_a_window_just_past_the_end_is_cut_there() -> None:
    # the last IMU sample 2.5 ms before the nominal end must not add a nearly identical window
    w = plan_windows(0.0, 39.9975, 10.0, 10.0)
    assert w[-1] == (30.0, 39.9975) and len(w) == 4


def test_overlapping_windows_with_a_shorter_step() -> None:
    w = plan_windows(2.0, 8.0, 3.0, 1.5)
    assert w == [(2.0, 5.0), (3.5, 6.5), (5.0, 8.0)]


def test_a_range_shorter_than_a_window_is_one_window() -> None:
    assert plan_windows(1.0, 6.0, 15.0, 15.0) == [(1.0, 6.0)]


@pytest.mark.parametrize(
    ("args", "error", "text"),
    [
        ((0.0, 1.5, 15.0, 15.0), ExcitationError, "lasts only 1.50 s"),
        ((0.0, 60.0, 1.0, 1.0), ConfigError, "--length"),
        ((0.0, 60.0, 15.0, 0.0), ConfigError, "--step"),
        ((0.0, 60.0, -3.0, 1.0), ConfigError, "--length"),
    ],
)
def test_invalid_window_plans(args, error, text) -> None:
    with pytest.raises(error, match=text):
        plan_windows(*args)


def _score(a: float, b: float, smin: float) -> WindowScore:
    return WindowScore(a, b, smin, 10 * smin, np.log(max(smin, 1e-300)), (), (), 0.0, 0.0, 1, 1)


def test_choose_ranks_by_min_singular_value_and_skips_overlaps() -> None:
    w = [_score(0, 4, 0.1), _score(2, 6, 5.0), _score(4, 8, 4.0), _score(6, 10, 3.0)]
    out = choose(w, top=2, threshold=None)
    assert [x.rank for x in out] == [4, 1, 2, 3]
    # 4-8 overlaps the best (2-6) and is skipped; 6-10 is next
    assert [x.selected for x in out] == [False, True, False, True]
    assert [(x.start_s, x.end_s) for x in out] == [(0, 4), (2, 6), (4, 8), (6, 10)]


def test_choose_by_threshold_and_default_top() -> None:
    w = [_score(4 * i, 4 * i + 4, s) for i, s in enumerate([1.0, 0.2, 3.0, 2.0, 0.5])]
    assert [x.selected for x in choose(w, None, 0.9)] == [True, False, True, True, False]
    assert sum(x.selected for x in choose(w, None, None)) == 3
    assert sum(x.selected for x in choose(w, 5, 1.5)) == 2
    # a window without data is never selected
    assert not any(x.selected for x in choose([_score(0, 4, 0.0)], 1, None))


def test_parse_segments() -> None:
    assert parse_segments("60-75, 105-120", 200.0) == [(60.0, 75.0), (105.0, 120.0)]
    assert parse_segments("105-120,60-75", 200.0) == [(60.0, 75.0), (105.0, 120.0)]
    assert parse_segments("0-2.5", 2.5) == [(0.0, 2.5)]


@pytest.mark.parametrize(
    ("text", "error", "match"),
    [
        ("60-75,abc", ConfigError, r"Invalid --segments window 'abc': give START-END"),
        ("60:75", ConfigError, "give START-END"),
        ("75-60", ConfigError, "its end must come after its start"),
        ("60-75,70-90", ConfigError, "60-75 and 70-90 overlap"),
        ("100-130", ConfigError, r"reaches past the end of the bag \(120.0 s\)"),
        ("60-61", ExcitationError, "lasts only 1 s, too short to calibrate"),
    ],
)
def test_parse_segments_errors_are_one_sentence(text, error, match) -> None:
    with pytest.raises(error, match=match) as info:
        parse_segments(text, 120.0)
    message = str(info.value)
    assert message.count(". ") == 0 and message.endswith(".")


def _rocking_imu(amplitude_deg: float, yaw_rate: float = 0.0) -> object:
    """An IMU rocking about its x axis by ``amplitude_deg`` (0.2 Hz, 10 s at 200 Hz), spinning
    about its z axis at ``yaw_rate`` rad/s first, with the specific force gravity gives."""
    from scipy.spatial.transform import Rotation

    from licalib_cli.measurements import ImuSamples

    t = np.arange(0.0, 10.0, 0.005)
    a, w = np.radians(amplitude_deg), 2 * np.pi * 0.2
    # R_W_I = Rx(a sin(w t)) Rz(yaw_rate t): body rate = Rz^T [a w cos, 0, 0] + [0, 0, yaw_rate]
    rx = Rotation.from_rotvec(np.outer(a * np.sin(w * t), [1.0, 0.0, 0.0]))
    rz = Rotation.from_rotvec(np.outer(yaw_rate * t, [0.0, 0.0, 1.0]))
    r = (rx * rz).as_matrix()
    gyro = np.add(
        rz.inv().apply(np.outer(a * w * np.cos(w * t), [1.0, 0.0, 0.0])), [0, 0, yaw_rate]
    )
    accel = np.einsum("nji,j->ni", r, [0.0, 0.0, 9.81])
    return ImuSamples((t * 1e9).astype(np.int64), gyro, accel)


def test_a_windows_tilt_is_the_rms_turn_of_gravity_in_the_imu_frame() -> None:
    """Rocking by A about a horizontal axis turns gravity in the IMU frame by A sin(w t): its
    RMS is A / sqrt(2); spinning about the vertical (0.5 turns a second, so that gravity's
    horizontal part averages out over the 10 s) does not tilt at all."""
    from licalib_cli.pipeline.segments import window_tilt_deg

    assert window_tilt_deg(_rocking_imu(30.0)) == pytest.approx(30.0 / np.sqrt(2), rel=0.02)
    assert window_tilt_deg(_rocking_imu(8.0)) == pytest.approx(8.0 / np.sqrt(2), rel=0.02)
    assert window_tilt_deg(_rocking_imu(0.0, yaw_rate=np.pi)) < 0.05
    assert window_tilt_deg(_rocking_imu(20.0, yaw_rate=np.pi)) == pytest.approx(
        20.0 / np.sqrt(2), rel=0.02
    )


def _window_info(weak_axis: int | None, coupled_axis: int | None = None):
    """A window's scaled information: strong everywhere but the extrinsic rotation about
    ``weak_axis``; the rotation about ``coupled_axis`` trades with the gyro rotation's."""
    from licalib_cli.solver.observability import summarize_information

    names = [f"ext.rotation.{a}" for a in "xyz"] + [f"ext.translation.{a}" for a in "xyz"]
    names += ["ext.time_offset"] + [f"imu.gyro_rotation.{a}" for a in "xyz"]
    owners = [n.rsplit(".", 1)[0] if n != "ext.time_offset" else n for n in names]
    d = np.full(10, 100.0)
    if weak_axis is not None:
        d[weak_axis] = 0.01
    s = np.diag(d)
    if coupled_axis is not None:
        k = 7 + coupled_axis
        s[coupled_axis, k] = s[k, coupled_axis] = 99.0
    return summarize_information(s, names, owners, np.ones(10))


def test_windows_together_add_their_information_and_keep_their_own_time_offsets() -> None:
    from licalib_cli.pipeline.segments import joint_information

    assert joint_information([]) is None
    a, b = _window_info(0), _window_info(1)
    alone = joint_information([a])
    assert alone is not None
    assert alone.names == tuple(a.names[:6])  # the extrinsic; the time offset is the window's
    assert alone.min_singular_value == pytest.approx(0.01, rel=1e-3)
    together = joint_information([a, b])
    assert together is not None
    # each window's weak rotation is the other's strong one
    assert together.min_singular_value == pytest.approx(100.01, rel=1e-3)
    # a rotation traded with the intrinsics (unknown to one characteristic size) is known
    # only as well as the trade allows: 100 - 99^2 / (100 + 1)
    traded = joint_information([_window_info(None, coupled_axis=2)])
    assert traded is not None
    assert traded.information[2, 2] == pytest.approx(100 - 99**2 / 101, rel=1e-6)
    assert traded.information[1, 1] == pytest.approx(100.0, rel=1e-6)


def test_the_next_window_chosen_is_the_one_that_adds_most_to_those_taken() -> None:
    """Windows weak in the same direction do not crowd out one that is strong there."""
    from dataclasses import replace

    rx, ry = _window_info(0), _window_info(1)
    w = [
        replace(_score(0, 4, 0.012), information=rx),  # best ranked
        replace(_score(4, 8, 0.011), information=rx),  # second: weak where the first is
        replace(_score(8, 12, 0.010), information=ry),  # third: strong there
    ]
    assert [x.selected for x in choose(w, top=2, threshold=None)] == [True, False, True]
    assert [x.rank for x in choose(w, top=2, threshold=None)] == [1, 2, 3]  # ranks unchanged
    # without the windows' information: by rank alone
    plain = [replace(x, information=None) for x in w]
    assert [x.selected for x in choose(plain, top=2, threshold=None)] == [True, True, False]
    # a threshold still bounds the candidates
    assert [x.selected for x in choose(w, top=2, threshold=0.0105)] == [True, True, False]
