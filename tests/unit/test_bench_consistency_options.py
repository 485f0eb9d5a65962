"""The trust benchmark's ``--duration`` and sensor rates, the diagnose benchmark's
``--duration`` and the intrinsics benchmark's rates: every case carries them, and a bad one is
refused; the diagnose benchmark's report of rivals and of effects tried and not kept; the
segment benchmark's measure of the long ranking's own process."""

from __future__ import annotations

import ast
import contextlib
import importlib
import io
import runpy
import subprocess
import sys
from pathlib import Path
from types import ModuleType

import pytest

BENCH = Path(__file__).resolve().parents[2] / "benchmarks" / "bench_consistency.py"


def _script(path: Path, *args: str) -> subprocess.CompletedProcess[str]:
    """``python path ARGS``, run in this process (a new interpreter per call took a second of
    imports each): its exit code, stdout and stderr."""
    out, err = io.StringIO(), io.StringIO()
    code = 0
    command = [str(path), *args]
    argv, sys_path = sys.argv, list(sys.path)
    sys.argv = command
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            runpy.run_path(str(path), run_name="__main__")
    except SystemExit as exit_:
        code = exit_.code if isinstance(exit_.code, int) else (0 if exit_.code is None else 1)
        if isinstance(exit_.code, str):
            err.write(exit_.code)
    finally:
        sys.argv = argv
        sys.path[:] = sys_path
    return subprocess.CompletedProcess(command, code, out.getvalue(), err.getvalue())


def _run(*args: str) -> subprocess.CompletedProcess[str]:
    return _script(BENCH, *args, "--list")


def _listed(out: subprocess.CompletedProcess[str]) -> list[dict]:
    """The cases a ``--list`` run printed (it must have succeeded)."""
    assert out.returncode == 0, out.stderr
    return [ast.literal_eval(line) for line in out.stdout.splitlines() if line.startswith("{")]


def test_every_listed_case_carries_the_duration() -> None:
    out = _run("--duration", "15", "--only", "clean")
    cases = _listed(out)
    assert cases and all(c["duration"] == 15.0 for c in cases)


@pytest.mark.parametrize("value", ["0", "-3", "nan"])
def test_a_duration_that_is_not_a_positive_number_of_seconds_is_refused(value: str) -> None:
    out = _run("--duration", value)
    assert out.returncode == 2
    assert "--duration must be a positive number of seconds" in out.stderr
    assert "Traceback" not in out.stderr


def test_every_listed_case_carries_the_sensor_rates() -> None:
    out = _run("--imu-rate", "100", "--lidar-rate", "20", "--only", "clean")
    cases = _listed(out)
    assert cases and all(c["imu_rate"] == 100.0 and c["lidar_rate"] == 20.0 for c in cases)


def test_every_listed_case_carries_the_record_delay_and_none_by_default() -> None:
    out = _run("--record-delay-ms", "2", "--only", "clean")
    cases = _listed(out)
    assert cases and all(c["record_delay_ms"] == 2.0 for c in cases)
    plain = _run("--only", "clean")
    assert all("record_delay_ms" not in line for line in plain.stdout.splitlines())


@pytest.mark.parametrize("value", ["-1", "50", "nan"])
def test_a_record_delay_outside_its_range_is_refused(value: str) -> None:
    out = _run("--record-delay-ms", value)
    assert out.returncode == 2
    assert "--record-delay-ms must be in [0, 20] ms" in out.stderr
    assert "Traceback" not in out.stderr


def test_every_listed_case_carries_the_config_overrides_given_with_set() -> None:
    """``--set KEY=VALUE`` (YAML values, repeatable) joins every case's overrides, beside the
    case's own; a key without ``=`` is refused."""
    out = _run(
        "--set",
        "surfels.final_points_per_scan=15000",
        "--set",
        "surfels.max_points=1500000",
        "--exact-model",
        "--only",
        "clean",
    )
    cases = _listed(out)
    assert cases and all(
        c["overrides"]
        == {
            "model.add_evident_effects": False,
            "surfels.final_points_per_scan": 15000,
            "surfels.max_points": 1500000,
        }
        for c in cases
    )
    bad = _run("--set", "surfels.max_points")
    assert bad.returncode == 2 and "expected KEY=VALUE" in bad.stderr


def test_a_key_set_to_null_is_unset() -> None:
    """The benchmarks' ``--set KEY=null`` unsets the key, as ``licalib calibrate --set`` does
    (``load_config``'s settings, not its options, where None means "not given")."""
    sys.path.insert(0, str(BENCH.parent))
    from _settings import load_with

    cfg = load_with({"surfels.final_points_per_scan": None, "surfels.max_points": 8000})
    assert cfg.surfels.final_points_per_scan is None and cfg.surfels.max_points == 8000
    assert load_with({"surfels.max_points": 8000}).surfels.final_points_per_scan == 6000


def test_the_default_rates_are_left_to_the_simulator() -> None:
    out = _run("--only", "clean")
    cases = _listed(out)
    assert cases and all(c["imu_rate"] is None and c["lidar_rate"] is None for c in cases)


@pytest.mark.parametrize("flag", ["--imu-rate", "--lidar-rate"])
@pytest.mark.parametrize("value", ["0", "-100", "nan"])
def test_a_rate_that_is_not_a_positive_number_is_refused(flag: str, value: str) -> None:
    out = _run(flag, value)
    assert out.returncode == 2
    assert f"{flag} must be a positive number of samples per second" in out.stderr
    assert "Traceback" not in out.stderr


DIAGNOSE = BENCH.parent / "bench_diagnose.py"
INTRINSICS = BENCH.parent / "bench_intrinsics.py"


def _diagnose(*args: str) -> subprocess.CompletedProcess[str]:
    return _script(DIAGNOSE, *args)


def _bench_module(path: Path) -> ModuleType:
    """A benchmark script, imported as a module (its folder on the path while it imports)."""
    sys.path.insert(0, str(path.parent))
    try:
        return importlib.import_module(path.stem)
    finally:
        sys.path.remove(str(path.parent))


def _bench_diagnose() -> ModuleType:
    """The diagnose benchmark script, imported as a module."""
    return _bench_module(DIAGNOSE)


def test_the_diagnose_benchmark_carries_the_sensor_rates_into_every_case() -> None:
    out = _diagnose("--imu-rate", "200", "--only", "clean", "--list")
    cases = _listed(out)
    assert cases and all(c["imu_rate"] == 200.0 and c["lidar_rate"] is None for c in cases)


def test_the_diagnose_benchmark_carries_the_length_of_its_bags_into_every_case() -> None:
    out = _diagnose("--duration", "20", "--only", "clean", "--list")
    cases = _listed(out)
    assert cases and all(c["duration"] == 20.0 for c in cases)
    refused = _diagnose("--duration", "0", "--list")
    assert refused.returncode == 2
    assert "--duration must be a positive number of seconds" in refused.stderr


def test_a_diagnose_case_lasts_the_length_asked_or_its_effects_longer_one() -> None:
    bench_diagnose = _bench_diagnose()
    length = bench_diagnose._size_and_length
    assert length(["gyro_rotation"], 3.0)[1] == 10.0
    assert length(["gyro_rotation"], 3.0, 25.0)[1] == 25.0
    assert length(["gyro_bias_walk"], 3.0, 10.0)[1] == bench_diagnose.LONGER["gyro_bias_walk"]
    assert length(["gyro_bias_walk", "lidar_point_time"], 3.0, 30.0)[1] == 30.0
    assert length([], 3.0, 15.0) == (3.0, 15.0)


@pytest.mark.parametrize("bench", [DIAGNOSE, INTRINSICS], ids=["diagnose", "intrinsics"])
def test_the_other_benchmarks_refuse_a_rate_that_is_not_positive(bench: Path) -> None:
    out = _script(bench, "--lidar-rate", "-10")
    assert out.returncode == 2
    assert "--lidar-rate must be a positive number of samples per second" in out.stderr
    assert "Traceback" not in out.stderr


def test_the_diagnose_benchmark_counts_the_rivals_named_in_the_leaders_place(
    tmp_path: Path,
) -> None:
    """``--report`` of two rows: one named the injected gyro rotation in place of the leading
    accelerometer misalignment, one refitted a rival that was not named."""
    import json

    def row(seed: int, effects: list[str], named: list[str], rivals: list[list]) -> dict:
        err = {"translation_mm": 1.0, "rotation_deg": 0.01, "time_offset_ms": 0.01}
        return {
            "seed": seed,
            "effects": effects,
            "named": named,
            "scenario": "sinusoid",
            "lidar": "os1-64",
            "rivals": rivals,
            "shrink": {},
            "before": err,
            "after": err,
        }

    rows = [
        row(
            1,
            ["gyro_rotation"],
            ["gyro_rotation"],
            [["gyro_rotation", "accel_misalignment", 0.83, True]],
        ),
        row(
            2,
            ["lidar_range_scale"],
            ["lidar_range_scale"],
            [["lidar_range_offset", "lidar_range_scale", 0.91, False]],
        ),
        row(3, [], [], []),
    ]
    path = tmp_path / "rows.jsonl"
    path.write_text("".join(json.dumps(r) + "\n" for r in rows))
    out = _script(DIAGNOSE, "--report", str(path))
    assert out.returncode == 0, out.stderr
    assert (
        "rivals refitted beside the leader at 2 steps of 2 runs (shares 0.83-0.91); named in "
        "its place at 1, the injected effect at 1 of them"
    ) in out.stdout


def test_the_diagnose_benchmark_says_an_injected_effect_was_tried_and_not_kept() -> None:
    """A row whose injected walk was significant, refitted, and did not pay its BIC: the miss
    says so, apart from an effect below what the bag shows."""
    bench_diagnose = _bench_diagnose()
    err = {"translation_mm": 0.4, "rotation_deg": 0.008, "time_offset_ms": 0.01}
    row = {
        "effects": ["accel_bias_walk"],
        "named": [],
        "steps": [["accel_bias_walk", 27.7, 3, 9.76, False, -0.07, -0.07, 0.016]],
        "shrink": {},
        "before": err,
        "after": err,
    }
    misses = bench_diagnose.judge(row)
    assert misses[0] == "named [] for ['accel_bias_walk']"
    assert "accel_bias_walk tried (score 27.7 on 3), BIC change +9.8: not kept" in misses
    kept = {**row, "named": ["accel_bias_walk"]}
    kept["steps"] = [[*row["steps"][0][:4], True, *row["steps"][0][5:]]]
    assert not [m for m in bench_diagnose.judge(kept) if "not kept" in m]


def test_the_diagnose_benchmark_says_a_rival_whose_refit_paid_lost_to_its_leader() -> None:
    """An injected effect refitted as the rival of another and not kept although its refit
    paid (a BIC change below zero): the miss names the leader that paid more."""
    bench_diagnose = _bench_diagnose()
    err = {"translation_mm": 0.7, "rotation_deg": 0.13, "time_offset_ms": 0.008}
    row = {
        "effects": ["accel_misalignment", "gyro_rotation"],
        "named": ["gyro_rotation"],
        "steps": [
            ["accel_misalignment", 98.9, 3, -64.4, False, -0.014, -0.018, 0.015],
            ["gyro_rotation", 166.0, 3, -95.0, True, 0.005, 0.004, 0.015],
        ],
        "rivals": [["accel_misalignment", "gyro_rotation", 0.54, False]],
        "shrink": {},
        "before": err,
        "after": err,
    }
    assert (
        "accel_misalignment tried (score 98.9 on 3), BIC change -64.4: not kept, refitted as "
        "the rival of gyro_rotation, which paid more (BIC change -95.0)"
    ) in bench_diagnose.judge(row)


def test_a_seed_whose_rig_the_simulator_refuses_is_no_refusal_and_no_target_miss(
    tmp_path: Path,
) -> None:
    # seed 14612's 1.97 m lever arm takes the walking rig through the room's objects
    (case,) = _listed(
        _run(
            *("--first-seed", "14600", "--seeds", "14612", "--duration", "20"),
            *("--lidars", "hdl-32", "os1-32", "os1-128", "--scenarios", "walk", "shake"),
        )
    )
    bench = _bench_module(BENCH)
    row = bench.one_run(case, tmp_path)
    assert row["verdict"] == bench.NOT_SIMULATED
    assert "passes through the simulated room's objects" in row["reason"]
    assert bench.judge(row) == "ok"
    assert "NOT SIMULATED" in bench._line(row)
    assert bench.judge({**row, "verdict": "error"}) == "clean run refused"


def test_a_calm_walk_refused_for_too_little_rotation_is_no_target_miss() -> None:
    """A clean walk without a shaking burst (a 10 s walk often has none) refused because its
    rotation cannot show the extrinsic is the right answer; the same refusal of a walk with a
    burst, or another refusal of a calm walk, is still a miss."""
    bench = _bench_module(BENCH)
    row = {
        "name": "clean",
        "scenario": "walk",
        "seed": 18103,
        "verdict": "error",
        "bursts": 0,
        "reason": "ExcitationError: Rotation excitation is too weak: the LiDAR odometry did not "
        "follow the motion and no rotation extrinsic makes the map clearly sharper than others",
    }
    assert bench.calm_walk_refused(row) and bench.judge(row) == "ok"
    assert bench.judge({**row, "bursts": 1}) == "clean run refused"
    other = {**row, "reason": "DataError: the bag has no IMU messages"}
    assert bench.judge(other) == "clean run refused"
    assert bench.judge({k: v for k, v in row.items() if k != "bursts"}) == "clean run refused"


def test_the_peak_memory_is_the_measured_process_s_own() -> None:
    """Neither this process's own peak (a child counts its parent's memory at the fork in its
    high-water mark, across the exec) nor an earlier, larger child's is the command's."""
    bench = _bench_module(BENCH.parent / "bench_segments.py")
    grow = "b = bytearray(400_000_000); b[::4096] = b'x' * len(b[::4096])"
    subprocess.run([sys.executable, "-c", grow], check=True)  # a larger child waited for first
    ballast = bytearray(300_000_000)
    ballast[::4096] = b"x" * len(ballast[::4096])  # and this process 300 MB larger
    code, out, err, wall, cpu, peak_mb = bench._run_measured(
        [sys.executable, "-c", "import sys; print('ranked'); sys.stderr.write('note')"]
    )
    assert (code, out, err) == (0, "ranked\n", "note")
    assert 0.0 < wall < 60.0 and 0.0 < cpu < 60.0
    assert peak_mb < 150, peak_mb  # an interpreter, not 300 or 400 MB
    code, _, _, _, _, peak_mb = bench._run_measured(
        [sys.executable, "-c", "b = bytearray(200_000_000); b[::4096] = b'x' * len(b[::4096])"]
    )
    assert code == 0 and 200 < peak_mb < 350, peak_mb  # its own 200 MB counted
    code, _, _, _, _, _ = bench._run_measured([sys.executable, "-c", "raise SystemExit(3)"])
    assert code == 3
    del ballast
