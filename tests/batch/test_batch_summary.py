"""The fleet summary: per-bag rows, per-rig spread, and the leave-one-out test that names a bag
whose calibration differs from its rig's others beyond their sigmas."""

from __future__ import annotations

import csv
import io
import math
from dataclasses import replace

import numpy as np
import pytest
from scipy import stats

from licalib_cli.batch.summary import (
    DIFFER_P,
    BagRow,
    RigRow,
    bag_row,
    compare_within_rig,
    rig_rows,
    summary_csv,
)
from licalib_cli.results import CalibrationResult, Extrinsic, matrix_from_rpy_deg
from licalib_cli.sections import (
    AddedEffect,
    ModelInfo,
    RecordingSection,
    Uncertainty,
    VerdictSection,
)


def _result(
    t: tuple[float, float, float],
    rpy: tuple[float, float, float] = (1.0, 2.0, 5.0),
    dt: float = 0.005,
    t_std: float = 0.001,
    verdict: str = "pass",
    start_ns: int = 1_700_000_000_000_000_000,
) -> CalibrationResult:
    return CalibrationResult(
        extrinsic=Extrinsic(matrix_from_rpy_deg(rpy), np.array(t), dt),
        uncertainty=Uncertainty((t_std, t_std, math.inf), (0.01, 0.01, 0.01), 1e-4),
        verdict=VerdictSection(verdict),
        recording=RecordingSection("b.bag", "/imu", "/points", 4000, 100, 10.0, start_ns, 0, 0),
    )


def test_leave_one_out_matches_the_chi_square_by_hand() -> None:
    rng = np.random.default_rng(3)
    x = rng.normal(size=(5, 3))
    sigma = rng.uniform(0.5, 2.0, size=(5, 3))
    sigma[2, 1] = np.inf  # left out for bag 2
    z, diff, chi2, dof, p = compare_within_rig(x, sigma)
    for i in range(5):
        others = [j for j in range(5) if j != i]
        expected = 0.0
        n = 0
        for k in range(3):
            if not np.isfinite(sigma[i, k]):
                assert z[i, k] == 0.0
                continue
            ok = [j for j in others if np.isfinite(sigma[j, k])]
            w = 1.0 / sigma[ok, k] ** 2
            mean = np.sum(w * x[ok, k]) / np.sum(w)
            zi = (x[i, k] - mean) / np.sqrt(sigma[i, k] ** 2 + 1.0 / np.sum(w))
            assert z[i, k] == pytest.approx(zi)
            assert diff[i, k] == pytest.approx(x[i, k] - mean)
            expected += zi**2
            n += 1
        assert chi2[i] == pytest.approx(expected)
        assert dof[i] == n
        assert p[i] == pytest.approx(stats.chi2.sf(expected, n))


def test_consistent_calibrations_do_not_differ() -> None:
    rng = np.random.default_rng(0)
    sigma = np.full((8, 7), 0.01)
    x = rng.normal(scale=0.01, size=(8, 7))
    p = compare_within_rig(x, sigma)[4]
    assert np.all(p > DIFFER_P)


def test_a_moved_sensor_is_named_with_its_largest_difference() -> None:
    rows = [
        bag_row("robot1", f"day{i}", "calibrated", _result((0.30, 0.15, 0.05))) for i in range(1, 4)
    ]
    # day4: the LiDAR moved 10 mm along y (10 sigma); z is unobservable (inf sigma), and a
    # 1 m difference there is not a difference the data can show.
    rows.append(bag_row("robot1", "day4", "calibrated", _result((0.30, 0.16, 1.05))))
    rows.append(bag_row("robot2", "day1", "calibrated", _result((0.0, 0.0, 0.0))))
    rows.append(bag_row("robot2", "day2", "failed", None, error="The bag is damaged."))
    rows.append(bag_row("robot2", "day3", "calibrated", _result((5.0, 0, 0), verdict="fail")))
    out, rigs = rig_rows(rows)
    assert [r.bag for r in out if r.differs] == ["day4"]
    moved = out[3]
    assert moved.difference.startswith("t_y +10 mm from the others (8.7 sigma")
    one, two = rigs
    assert (one.rig, one.bags, one.usable, one.failed, one.differing) == (
        "robot1",
        4,
        4,
        0,
        ("day4",),
    )
    assert one.spread_t_y_mm == pytest.approx(10.0)
    assert one.spread_t_z_mm == pytest.approx(1000.0)
    assert one.spread_rot_x_deg == pytest.approx(0.0, abs=1e-9)
    # A failed bag and a FAIL verdict are counted, and kept out of the comparison.
    assert (two.bags, two.usable, two.failed, two.differing) == (3, 1, 2, ())
    assert two.spread_t_x_mm == 0.0


def test_a_rotated_sensor_differs_about_the_lidar_axes() -> None:
    rows = [
        bag_row("r", f"b{i}", "calibrated", _result((0.3, 0.15, 0.05), rpy=(1.0, 2.0, 5.0)))
        for i in range(3)
    ]
    rows.append(bag_row("r", "b3", "calibrated", _result((0.3, 0.15, 0.05), rpy=(1.0, 2.0, 5.2))))
    out, rigs = rig_rows(rows)
    assert [r.bag for r in out if r.differs] == ["b3"]
    assert out[3].difference.startswith("rot_")
    assert max(rigs[0].spread_rot_x_deg, rigs[0].spread_rot_y_deg, rigs[0].spread_rot_z_deg) == (
        pytest.approx(0.2, rel=0.05)
    )


def test_two_bags_that_disagree_both_differ() -> None:
    rows = [
        bag_row("r", "a", "calibrated", _result((0.30, 0.15, 0.05))),
        bag_row("r", "b", "up to date", _result((0.33, 0.15, 0.05))),
    ]
    out, rigs = rig_rows(rows)
    assert [r.differs for r in out] == [True, True]
    assert rigs[0].differing == ("a", "b")


def test_summary_csv_columns_and_cells() -> None:
    start = 1_700_000_000_123_456_789
    row = bag_row(
        "r",
        "b",
        "calibrated",
        _result((0.3, 0.15, 0.05), start_ns=start),
        calibration_s=12.5,
        attempts=2,
        result="r/b.yaml",
    )
    failed = bag_row("r", "c", "failed", None, error="The bag, it is damaged.", exit_code=2)
    text = summary_csv([row, failed], BagRow)
    table = list(csv.DictReader(io.StringIO(text)))
    assert list(table[0]) == [f.name for f in BagRow.__dataclass_fields__.values()]
    first, second = table
    assert first["recorded_utc"] == "2023-11-14T22:13:20.123Z"
    assert float(first["t_y_m"]) == 0.15
    assert first["t_z_std_m"] == "inf"
    assert first["verdict"] == "pass" and first["attempts"] == "2"
    assert second["error"] == "The bag, it is damaged." and second["t_x_m"] == ""
    assert second["exit_code"] == "2"
    _, rigs = rig_rows([row, failed])
    rig_table = list(csv.DictReader(io.StringIO(summary_csv(rigs, RigRow))))
    assert rig_table[0]["failed"] == "1" and rig_table[0]["differing"] == ""


def test_a_bags_clock_rate_is_in_its_row() -> None:
    """The rate the bag's stamps showed against its record times goes into the summary, so
    that a rig whose clocks are not synchronised stands out; unknown is empty."""
    result = _result((0.3, 0.15, 0.05))
    assert result.recording is not None
    drifting = replace(
        result, recording=replace(result.recording, clock_rate_ppm=-48.25, clock_rate_sigma_ppm=2)
    )
    row = bag_row("r", "b1", "calibrated", drifting)
    assert row.clock_rate_ppm == -48.25
    assert math.isnan(bag_row("r", "b2", "calibrated", result).clock_rate_ppm)
    csv = summary_csv([row], BagRow).splitlines()
    column = csv[0].split(",").index("clock_rate_ppm")
    assert csv[1].split(",")[column] == "-48.25"


def test_the_effects_calibrate_added_are_in_the_bags_row() -> None:
    """Which effects the data showed beyond doubt, so that a rig whose bags keep needing one
    stands out; none is an empty cell."""
    result = _result((0.3, 0.15, 0.05))
    assert bag_row("r", "b1", "calibrated", result).added_effects == ""
    added = tuple(
        AddedEffect(name, 900.0, 16, -800.0, 0.01, 0.02, 1e-5)
        for name in ("lidar_range_offset", "lidar_elevation")
    )
    shown = replace(result, model=ModelInfo((), ("range_offset", "elevation"), added=added))
    row = bag_row("r", "b2", "calibrated", shown)
    assert row.added_effects == "lidar_range_offset+lidar_elevation"
    csv = summary_csv([row], BagRow).splitlines()
    column = csv[0].split(",").index("added_effects")
    assert csv[1].split(",")[column] == "lidar_range_offset+lidar_elevation"
