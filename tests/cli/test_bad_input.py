"""Bad input, hardened: every malformed bag, config or option ends in one sentence with its
documented exit code, and ``info`` and ``calibrate`` stop on the same diagnosis.

Each case builds its bag in a temporary folder; ``calibrate`` stops while reading, so these
run fast.
"""

from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from licalib_cli.cli import main

_spec = importlib.util.spec_from_file_location(
    "licalib_test_layouts", Path(__file__).parents[1] / "io" / "_layouts.py"
)
assert _spec is not None and _spec.loader is not None
layouts = importlib.util.module_from_spec(_spec)
sys.modules[_spec.name] = layouts
_spec.loader.exec_module(layouts)

NS = layouts.NS
T0 = 1_700_000_000 * NS


def run(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    with pytest.raises(SystemExit) as exc:
        main(argv)
        raise SystemExit(0)
    out = capsys.readouterr()
    assert "Traceback" not in out.out + out.err
    return int(exc.value.code or 0), out.out, out.err


def error_line(err: str) -> str:
    """The one ``Error: ...`` sentence of standard error (log lines before it allowed)."""
    lines = [ln for ln in err.splitlines() if ln.startswith("Error: ")]
    assert len(lines) == 1, err
    msg = lines[0][len("Error: ") :]
    assert msg.endswith(".") and ". " not in msg.replace("e.g. ", ""), msg
    return msg


# --------------------------------------------------------------------------------------------
# Bags damaged in one way each


def _nan_all(i: int, t: int, g: np.ndarray, a: np.ndarray) -> list[tuple]:
    return [(t, np.array([np.nan, g[1], g[2]]), a, t)]


def _inf_run(i: int, t: int, g: np.ndarray, a: np.ndarray) -> list[tuple]:
    bad = 100 <= i < 140
    return [(t, g, np.array([a[0], a[1], np.inf]) if bad else a, t)]


def _zero(i: int, t: int, g: np.ndarray, a: np.ndarray) -> list[tuple]:
    return [(t, np.zeros(3), np.zeros(3), t)]


def _unset_stamps(i: int, t: int, g: np.ndarray, a: np.ndarray) -> list[tuple]:
    return [(0, g, a, t)]


def _recorded_later(i: int, t: int, g: np.ndarray, a: np.ndarray) -> list[tuple]:
    later = t + 100_000 * NS  # header stamps and record times both 1e5 s on
    return [(later, g, a, later)]


def _one_point(w: Any, k: int, stamp: int) -> Any:
    return w.cloud_message(stamp, layouts.velodyne_points(stamp)[:1])


def _one_row(w: Any, k: int, stamp: int) -> Any:
    pts = layouts.organised_points(stamp)
    pts["x"][1:] = np.nan  # every row but the first has no return
    return w.cloud_message(stamp, pts)


def _huge_point_step(w: Any, k: int, stamp: int) -> Any:
    msg = w.cloud_message(stamp, layouts.velodyne_points(stamp))
    msg.point_step = 2**31
    return msg


def _x_count_3(w: Any, k: int, stamp: int) -> Any:
    msg = w.cloud_message(stamp, layouts.velodyne_points(stamp))
    msg.fields[0].count = 3
    return msg


def _empty_with_double_time(w: Any, k: int, stamp: int) -> Any:
    msg = w.cloud_message(stamp, layouts.velodyne_points(stamp)[:0])
    msg.height, msg.point_step = 0, 26  # room for the two time values
    next(f for f in msg.fields if f.name == "time").count = 2
    return msg


def _bag_20hz(path: Path) -> Path:
    return layouts.write_bag(path, imu_rate_hz=20.0)


Builder = Callable[[Path], Path]

CASES: dict[str, tuple[Builder, list[str], int, str]] = {
    "imu all NaN": (
        lambda p: layouts.write_bag(p, imu=_nan_all),
        [],
        4,
        "All 600 IMU samples on /imu hold NaN or infinite values (between 0.000 s and 2.995 s)",
    ),
    "imu run of inf": (
        lambda p: layouts.write_bag(p, imu=_inf_run),
        [],
        4,
        "40 of 600 IMU samples on /imu hold NaN or infinite values (between 0.500 s and 0.695 s)",
    ),
    "imu all zero": (
        lambda p: layouts.write_bag(p, imu=_zero),
        [],
        4,
        "The accelerometer on /imu reads no gravity (median |a| 0 m/s^2",
    ),
    "imu at 20 Hz": (
        _bag_20hz,
        [],
        4,
        "The IMU on /imu publishes at 20.0 Hz, too slow for the motion model (a trajectory "
        "knot every 0.02 s needs at least 50 Hz",
    ),
    "one-point clouds": (
        lambda p: layouts.write_bag(p, cloud=_one_point),
        [],
        4,
        "All 30 LiDAR clouds of the segment have fewer than 100 valid points",
    ),
    "organised clouds with one row": (
        lambda p: layouts.write_bag(p, cloud=_one_row),
        [],
        4,
        "All 30 LiDAR clouds of the segment have valid points on one beam or row only",
    ),
    "point_step 2**31": (
        lambda p: layouts.write_bag(p, cloud=_huge_point_step),
        [],
        4,
        "(the first: cloud 1 of /points in the segment, stamp 1700000000.000000000: has point_step "
        "2147483648, more than 65536 bytes per point)",
    ),
    "x with count 3": (
        lambda p: layouts.write_bag(p, cloud=_x_count_3),
        [],
        4,
        "field 'x' holds 3 values per point instead of one",
    ),
    "height 0 and a time field of count 2": (
        lambda p: layouts.write_bag(p, cloud=_empty_with_double_time),
        [],
        4,
        "All 30 LiDAR clouds of the segment are empty",
    ),
    "header stamps all zero": (
        lambda p: layouts.write_bag(p, imu=_unset_stamps),
        [],
        5,
        "The IMU messages on /imu have unset header stamps (all zero)",
    ),
    "imu recorded 1e5 s later": (
        lambda p: layouts.write_bag(p, imu=_recorded_later),
        [],
        5,
        "The IMU messages (recorded 99999.9-100002.9 s after the bag start) and the LiDAR "
        "messages (0.0-2.9 s) were recorded at different times",
    ),
    "segment too short": (
        lambda p: layouts.write_bag(p),
        ["--start", "2.95"],
        7,
        "The segment from 2.95 s to the end of the bag (2.999 s) lasts only 0.05 s, too little",
    ),
    "beam table shorter than the rings": (
        lambda p: layouts.write_bag(p),
        ["-c", "{tmp}/beams.yaml"],
        6,
        "lidar.nominal_elevation_deg lists 2 beams but the clouds on /points have 16",
    ),
}


@pytest.mark.parametrize("name", list(CASES))
def test_info_and_calibrate_agree_on_the_diagnosis(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], name: str
) -> None:
    build, options, code, fragment = CASES[name]
    (tmp_path / "beams.yaml").write_text("lidar:\n  nominal_elevation_deg: [-1.0, 1.0]\n")
    bag = build(tmp_path / "bag")
    options = [o.format(tmp=tmp_path) for o in options]
    got_info, out, err = run(["info", str(bag), "--json", *options], capsys)
    msg_info = error_line(err)
    assert got_info == code, err
    assert fragment in msg_info
    data = json.loads(out)
    assert data["exit_code"] == code and not data["usable"]
    assert data["problems"][0] == {"severity": "error", "message": msg_info, "exit_code": code}
    result = tmp_path / "out" / "calib.yaml"
    got_cal, _, err = run(["calibrate", str(bag), "-o", str(result), *options], capsys)
    assert (got_cal, error_line(err)) == (code, msg_info)
    assert not result.exists()


# --------------------------------------------------------------------------------------------
# Damage that leaves the rest usable


def test_isolated_bad_imu_samples_are_dropped_with_a_warning(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    def few(i: int, t: int, g: np.ndarray, a: np.ndarray) -> list[tuple]:
        return [(t, g * np.nan if i in (50, 300) else g, a, t)]

    bag = layouts.write_bag(tmp_path / "bag", imu=few)
    code, out, err = run(["info", str(bag), "--json"], capsys)
    assert code == 0, err
    data = json.loads(out)
    assert data["imu"]["dropped_samples"] == 2 and data["imu"]["count"] == 598
    warned = [p["message"] for p in data["problems"]]
    assert (
        "2 IMU samples of 600 on /imu hold NaN or infinite values (between 0.250 s and "
        "1.500 s) and are dropped." in warned
    )


def test_one_truncated_cloud_is_skipped_naming_its_stamp(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    def truncated(w: Any, k: int, stamp: int) -> Any:
        msg = w.cloud_message(stamp, layouts.velodyne_points(stamp))
        if k == 17:
            msg.data = msg.data[: msg.data.size // 2].copy()
        return msg

    bag = layouts.write_bag(tmp_path / "bag", cloud=truncated)
    code, out, err = run(["info", str(bag), "--json"], capsys)
    assert code == 0, err
    data = json.loads(out)
    assert data["lidar"]["clouds_skipped"] == {"corrupt": 1}
    assert any(
        p["message"].startswith(
            "1 of 30 LiDAR clouds is corrupt and was skipped (cloud 18 of /points in the segment, "
            "stamp "
            "1700000001.700000000: data has 10560 bytes but its header announces 21120)"
        )
        for p in data["problems"]
    ), data["problems"]
    # Past the configured fraction the clouds are an error.
    cfg = tmp_path / "strict.yaml"
    cfg.write_text("lidar:\n  max_skipped_fraction: 0.0\n")
    code, _, err = run(["info", str(bag), "-c", str(cfg)], capsys)
    assert code == 4
    assert "more than `lidar.max_skipped_fraction` (0) of the clouds" in error_line(err)


def test_damaged_mcap_chunk_is_counted_and_explains_the_gap(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """MCAP records the reader skips silently (as in a damaged chunk) are counted against the
    bag's index, in the report and in the gap they leave."""
    bag = layouts.write_bag(tmp_path / "bag")
    mcap = next((tmp_path / "bag").glob("*.mcap"))
    layouts.damage_mcap_records(mcap, first=100, count=60)  # IMU messages 0.5-0.8 s
    code, out, err = run(["info", str(bag), "--json"], capsys)
    assert code == 5, err
    data = json.loads(out)
    assert next(t for t in data["topics"] if t["name"] == "/imu")["count"] == 600  # the index
    assert data["imu"]["count"] == 540 and data["imu"]["unreadable"] == 60
    msg = error_line(err)
    assert msg.startswith("The IMU stream has 1 gap longer than 5x its period")
    assert (
        "caused by 60 IMU messages of the bag that cannot be read (60 lost in damaged chunks)"
        in msg
    )
    code, _, err = run(["calibrate", str(bag), "-o", str(tmp_path / "c.yaml")], capsys)
    assert (code, error_line(err)) == (5, msg)


def test_undecodable_imu_message_is_counted_in_the_result(tmp_path: Path) -> None:
    """A message whose bytes do not decode is skipped, warned about and counted in the
    ``recording`` section of the result."""
    import sqlite3

    from licalib_cli.config import load_config
    from licalib_cli.io.reader import read_segment
    from licalib_cli.pipeline.assemble import recording_section

    bag = layouts.write_bag(tmp_path / "bag", fmt="ros2-db3")
    db = next(bag.glob("*.db3"))
    with sqlite3.connect(db) as con:
        row = con.execute(
            "SELECT m.id, m.data FROM messages m JOIN topics t ON m.topic_id = t.id "
            "WHERE t.name = '/imu' ORDER BY m.timestamp LIMIT 1 OFFSET 200"
        ).fetchone()
        con.execute("UPDATE messages SET data = ? WHERE id = ?", (row[1][:20], row[0]))
    rec = read_segment(bag, load_config(None))
    assert len(rec.imu) == 599 and rec.imu_unreadable == 1
    assert any("1 IMU message on /imu cannot be read (1 undecodable)" in w for w in rec.warnings)
    section = recording_section(bag, rec)
    assert section.imu_unreadable_messages == 1 and section.lidar_unreadable_messages == 0


# --------------------------------------------------------------------------------------------
# Configs and options


@pytest.mark.parametrize(
    ("options", "fragment"),
    [
        (["--duration", "inf"], "Invalid value inf for --duration (bag.duration_s)"),
        (["--start", "inf"], "Invalid value inf for --start (bag.start_s)"),
        (["--start", "nan"], "Invalid value nan for --start (bag.start_s)"),
        (["--start", "1e300"], "The segment starts at 1e+300 s but the bag lasts only 2.999 s"),
        (["--duration", "1e300"], None),
        (["-c", "{tmp}/inf.yaml"], "Invalid setting 'bag.max_duration_s'"),
        (["-c", "{tmp}/random.yaml"], "is not a text file"),
        (["-c", "{tmp}"], "is a folder; pass a YAML file"),
        (["-c", "{tmp}/dup.yaml"], "gives the key 'start_s' twice (line 3); keep one of them"),
        (["-c", "{tmp}/empty_table.yaml"], "'lidar.nominal_elevation_deg'"),
        (["-c", "{tmp}/cos0.yaml"], "Invalid setting 'noise.min_incidence_cos'"),
        (["-c", "{tmp}/cos2.yaml"], "Invalid setting 'noise.min_incidence_cos'"),
        (["-c", "{tmp}/refit.yaml"], "Invalid setting 'checks.refit_effects'"),
        (["-c", "{tmp}/evident.yaml"], "Invalid setting 'model.add_evident_effects'"),
        (["-c", "{tmp}/draws.yaml"], "Invalid setting 'checks.range_noise_draws'"),
        (["-c", "{tmp}/draws_from.yaml"], "Invalid setting 'checks.range_noise_draws_from_m'"),
        (["-c", "{tmp}/cells0.yaml"], "Invalid setting 'surfels.cell_sizes_m.0'"),
        (["-c", "{tmp}/cells_up.yaml"], "cell sizes go from coarse to fine"),
        (["-c", "{tmp}/lever_cm.yaml"], "translation_m puts the LiDAR 33.9 m from the IMU"),
    ],
)
def test_bad_options_and_configs_exit_6(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], options: list[str], fragment: str | None
) -> None:
    bag = layouts.write_bag(tmp_path / "bag")
    (tmp_path / "inf.yaml").write_text("bag:\n  max_duration_s: .inf\n")
    (tmp_path / "random.yaml").write_bytes(np.random.default_rng(0).bytes(300))
    (tmp_path / "dup.yaml").write_text("bag:\n  start_s: 0\n  start_s: 1\n")
    (tmp_path / "empty_table.yaml").write_text("lidar:\n  nominal_elevation_deg: []\n")
    (tmp_path / "cos0.yaml").write_text("noise:\n  min_incidence_cos: 0\n")
    (tmp_path / "cos2.yaml").write_text("noise:\n  min_incidence_cos: 1.5\n")
    (tmp_path / "refit.yaml").write_text("checks:\n  refit_effects: maybe\n")
    (tmp_path / "evident.yaml").write_text("model:\n  add_evident_effects: sometimes\n")
    (tmp_path / "draws.yaml").write_text("checks:\n  range_noise_draws: -1\n")
    (tmp_path / "draws_from.yaml").write_text("checks:\n  range_noise_draws_from_m: 0\n")
    # a zero cell ran into a voxel key overflow (said as points too far from the origin) and a
    # negative one calibrated; fine-to-coarse cells would split fine cells into coarse ones
    (tmp_path / "cells0.yaml").write_text("surfels:\n  cell_sizes_m: [0]\n")
    (tmp_path / "cells_up.yaml").write_text("surfels:\n  cell_sizes_m: [0.5, 1.0]\n")
    # a lever arm of 0.30, 0.15, 0.05 m written in centimetres ended 8 m off, only warning
    (tmp_path / "lever_cm.yaml").write_text("initialization:\n  translation_m: [30, 15, 5]\n")
    options = [o.format(tmp=tmp_path) for o in options]
    code, out, err = run(["info", str(bag), "--json", *options], capsys)
    data = json.loads(out)
    if fragment is None:  # a duration past the end reads to the end
        assert code == 0 and data["usable"], err
        return
    assert code == 6 and fragment in error_line(err)
    assert data["exit_code"] == 6 and fragment in data["problems"][0]["message"]
    code, _, err = run(["calibrate", str(bag), "-o", str(tmp_path / "c.yaml"), *options], capsys)
    assert code == 6 and fragment in error_line(err)
    # diagnose reads the same window of the same bag with the same options
    code, _, err = run(["diagnose", str(bag), *options], capsys)
    assert code == 6 and fragment in error_line(err)


# --------------------------------------------------------------------------------------------
# Unreadable files: the format detected, the file and the fix for that format


def test_unreadable_files_name_format_file_and_fix(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    mcap_bag = layouts.write_bag(tmp_path / "m")
    mcap = next(mcap_bag.glob("*.mcap"))
    renamed = tmp_path / "renamed.bag"
    renamed.write_bytes(mcap.read_bytes())
    db3 = layouts.write_bag(tmp_path / "d", fmt="ros2-db3")
    garbled = tmp_path / "garbled"
    garbled.mkdir()
    (garbled / mcap.name).write_bytes(mcap.read_bytes())
    (garbled / "metadata.yaml").write_text("rosbag2_bagfile_information:\n  version: [\n")
    split = tmp_path / "split"
    split.mkdir()
    layouts.write_bag(split / "run_0.bag", fmt="ros1")
    whole = (split / "run_0.bag").read_bytes()
    (split / "run_1.bag").write_bytes(whole[: len(whole) // 3])
    random_db3 = tmp_path / "random.db3"
    random_db3.write_bytes(np.random.default_rng(1).bytes(4000))
    expected = {
        renamed: f"{renamed} is a ROS2 MCAP file, not a ROS1 bag; rename it to renamed.mcap",
        garbled: (f"The ROS2 bag folder {garbled} has a damaged metadata.yaml (not valid YAML: "),
        split: (
            f"Of the 2 split bags in {split}, {split / 'run_1.bag'} is a ROS1 bag that cannot "
            "be read"
        ),
        random_db3: f"{random_db3} is not a ROS2 SQLite (.db3) file",
    }
    fixes = {
        renamed: "and pass that",
        garbled: f"pass {garbled / mcap.name} itself (licalib reads it without metadata.yaml)",
        split: f"`rosbag reindex {split / 'run_1.bag'}`",
        random_db3: "check the path",
    }
    for path, start in expected.items():
        code, _, err = run(["info", str(path)], capsys)
        msg = error_line(err)
        assert code == 2 and msg.startswith(start) and fixes[path] in msg, msg
        assert "utf-8" not in msg and "magic" not in msg
    assert db3.is_dir()  # a good ROS2 folder for contrast
    assert run(["info", str(db3)], capsys)[0] == 0


# --------------------------------------------------------------------------------------------
# info --json: one object whatever the outcome


@pytest.mark.parametrize(
    ("argv", "code"),
    [
        (["info", "{tmp}/missing.bag", "--json"], 2),
        (["info", "{tmp}/bag", "--json", "--start", "abc"], 6),
        (["info", "{tmp}/bag", "--json", "--no-such-option"], 6),
        (["info", "{tmp}/bag", "--json", "-c", "{tmp}/missing.yaml"], 6),
        (["info", "{tmp}/bag", "--json", "--imu-topic", "/nope"], 3),
    ],
)
def test_info_json_prints_one_object_for_errors(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], argv: list[str], code: int
) -> None:
    layouts.write_bag(tmp_path / "bag")
    got, out, err = run([a.format(tmp=tmp_path) for a in argv], capsys)
    assert got == code, err
    data = json.loads(out)
    assert data["exit_code"] == code and data["usable"] is False
    assert data["problems"][0]["severity"] == "error" and data["problems"][0]["exit_code"] == code


def test_info_json_for_internal_errors_and_interrupts(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    from licalib_cli import inspection

    bag = layouts.write_bag(tmp_path / "bag")

    def broken(*args: object, **kwargs: object) -> None:
        raise RuntimeError("boom")

    monkeypatch.setattr(inspection, "inspect_bag", broken)
    code, out, err = run(["info", str(bag), "--json"], capsys)
    assert code == 1 and "Internal error: RuntimeError: boom" in err
    assert json.loads(out)["problems"][0]["exit_code"] == 1

    def interrupted(*args: object, **kwargs: object) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(inspection, "inspect_bag", interrupted)
    code, out, err = run(["info", str(bag), "--json"], capsys)
    assert code == 130 and err.strip() == "Interrupted."
    assert json.loads(out)["exit_code"] == 130


# --------------------------------------------------------------------------------------------
# Outputs never overwrite an input


def _digest(path: Path) -> dict[str, bytes]:
    files = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]
    return {str(p): p.read_bytes() for p in files}


@pytest.mark.parametrize(
    ("bag_fmt", "config_name", "out", "what"),
    [
        ("ros1", None, "{bag}", "The output {out} is the input bag"),
        ("ros2-db3", None, "{bag}/metadata.yaml", "is a file of the input bag"),
        ("ros2-mcap", None, "{mcap}", "is a file of the input bag"),
        ("ros1", "my.yaml", "{tmp}/my.yaml", "The output {out} is the config file"),
        (
            "ros1",
            "calib.config.yaml",
            "{tmp}/calib.yaml",
            "The resolved config that calibrate writes next to the result, "
            "{tmp}/calib.config.yaml, is the config file",
        ),
    ],
)
def test_output_that_is_an_input_is_refused_and_the_input_unchanged(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    bag_fmt: str,
    config_name: str | None,
    out: str,
    what: str,
) -> None:
    bag = layouts.write_bag(tmp_path / ("in.bag" if bag_fmt == "ros1" else "in"), fmt=bag_fmt)
    mcap = next(iter(sorted(bag.glob("*.mcap"))), None) if bag.is_dir() else None
    argv = ["calibrate", str(bag)]
    inputs = [bag]
    if config_name is not None:
        config = tmp_path / config_name
        config.write_text("bag:\n  start_s: 0.0\n")
        argv += ["-c", str(config)]
        inputs.append(config)
    target = out.format(bag=bag, tmp=tmp_path, mcap=mcap)
    before = {k: v for p in inputs for k, v in _digest(p).items()}
    listing = sorted(tmp_path.rglob("*"))
    code, _, err = run([*argv, "-o", target], capsys)
    assert code == 6
    msg = error_line(err)
    assert what.format(out=target, tmp=tmp_path) in msg and "give another output path" in msg
    after = {k: v for p in inputs for k, v in _digest(p).items()}
    assert after == before and sorted(tmp_path.rglob("*")) == listing


def test_truth_file_is_checked_before_the_run(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bag = layouts.write_bag(tmp_path / "in.bag", fmt="ros1")
    code, _, err = run(["calibrate", str(bag), "--truth", str(tmp_path), "-o", "x.yaml"], capsys)
    assert code == 6 and "is a folder; pass a YAML file" in error_line(err)
    truth = tmp_path / "truth.yaml"
    truth.write_text("schema_version: 1\n")
    code, _, err = run(["calibrate", str(bag), "--truth", str(truth), "-o", str(truth)], capsys)
    assert code == 6 and "is the truth file" in error_line(err)
    assert truth.read_text() == "schema_version: 1\n"
    for key in ("seed", "noise_seed"):  # a seed that is not a whole number
        truth.write_text(f"schema_version: 1\n{key}: abc\n")
        code, _, err = run(["calibrate", str(bag), "--truth", str(truth), "-o", "x.yaml"], capsys)
        line = error_line(err)
        assert code == 6 and f"`{key}` is 'abc', not a whole number or null" in line
        assert str(truth) in line


# --------------------------------------------------------------------------------------------
# Interrupts, closed pipes and numpy's warnings


def _licalib(code: str, *args: str, **kwargs: Any) -> subprocess.CompletedProcess[str]:
    """Run a snippet as the console script does, in a fresh interpreter."""
    return subprocess.run(
        [sys.executable, "-c", code, *args],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
        **kwargs,
    )


def test_ctrl_c_while_the_command_line_loads_is_quiet() -> None:
    """An interrupt that lands while typer, numpy and rosbags are imported. The child starts
    with Python's own Ctrl-C handler, as from a terminal: a process started with SIGINT ignored
    (a test runner's worker may ignore it) passes that on, and would never see the interrupt."""
    code = (
        "import builtins, os, signal, sys\n"
        "signal.signal(signal.SIGINT, signal.default_int_handler)\n"
        "sys.argv = ['licalib', '--version']\n"
        "from licalib_cli.__main__ import run\n"
        "real = builtins.__import__\n"
        "def hook(name, *a, **k):\n"
        "    if name == 'typer':\n"
        "        os.kill(os.getpid(), signal.SIGINT)\n"
        "    return real(name, *a, **k)\n"
        "builtins.__import__ = hook\n"
        "run()\n"
    )
    done = _licalib(code)
    assert (done.returncode, done.stderr, done.stdout) == (130, "Interrupted.\n", "")


def test_ctrl_c_turned_into_another_error_by_a_library_is_an_interrupt(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """A library loading when Ctrl-C comes may raise something else (ImportError:
    initialization failed); it is still an interrupt, not an internal error."""
    import os
    import signal
    import time

    from licalib_cli import inspection

    def interrupted_import(*args: object, **kwargs: object) -> None:
        try:
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(5)
        except KeyboardInterrupt:
            raise ImportError("initialization failed") from None

    monkeypatch.setattr(inspection, "inspect_bag", interrupted_import)
    # Python's own Ctrl-C handler, as from a terminal (a test runner's worker may ignore SIGINT)
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        code, out, err = run(["info", str(tmp_path / "any.bag")], capsys)
    finally:
        signal.signal(signal.SIGINT, previous)
    assert (code, err.strip(), out) == (130, "Interrupted.", "")


def test_closed_output_pipe_ends_quietly(tmp_path: Path) -> None:
    """``licalib info BAG | head -1``: the reader closes the pipe before licalib writes."""
    import os

    bag = layouts.write_bag(tmp_path / "bag")
    for extra in ([], ["--json"]):
        read, write = os.pipe()
        os.close(read)
        done = subprocess.run(
            [sys.executable, "-m", "licalib_cli", "info", str(bag), *extra],
            stdout=write,
            stderr=subprocess.PIPE,
            text=True,
            timeout=120,
            check=False,
        )
        os.close(write)
        assert done.returncode == 1 and done.stderr == "", done.stderr


def test_no_numpy_runtime_warnings_on_stderr(tmp_path: Path) -> None:
    def bad(i: int, t: int, g: np.ndarray, a: np.ndarray) -> list[tuple]:
        nan, inf = np.full(3, np.nan), np.full(3, np.inf)
        return [(t, nan if i % 7 == 0 else g, inf if i % 5 == 0 else a, t)]

    bag = layouts.write_bag(tmp_path / "bag", imu=bad)
    done = subprocess.run(
        [sys.executable, "-m", "licalib_cli", "info", str(bag)],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert done.returncode == 4 and "Warning" not in done.stderr, done.stderr
    assert done.stderr.startswith("Error: 188 of 600 IMU samples on /imu hold NaN")


def test_diagnose_output_folder_that_holds_the_config_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bag = layouts.write_bag(tmp_path / "in.bag", fmt="ros1")
    config = tmp_path / "calibration.config.yaml"
    config.write_text("bag:\n  start_s: 0.0\n")
    code, _, err = run(["diagnose", str(bag), "-c", str(config), "-o", str(tmp_path)], capsys)
    assert code == 6 and "is the config file" in error_line(err)
    assert config.read_text() == "bag:\n  start_s: 0.0\n"
