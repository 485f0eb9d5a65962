"""``licalib calibrate``: options and the errors a user can cause, through the real entry point."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from licalib_cli.cli import main
from licalib_cli.io.writer import BagWriter

NS = 1_000_000_000
T0 = 1_700_000_000 * NS
VELODYNE = np.dtype(
    {
        "names": ["x", "y", "z", "intensity", "ring", "time"],
        "formats": ["<f4", "<f4", "<f4", "<f4", "<u2", "<f4"],
        "offsets": [0, 4, 8, 12, 16, 18],
        "itemsize": 22,
    }
)


def _room_cloud(columns: int = 360) -> np.ndarray:
    """A VLP-16-like sweep inside a 12 x 10 x 6 m box, seen from a fixed pose."""
    el = np.radians(np.linspace(-15, 15, 16))
    az = -2 * np.pi * np.arange(columns) / columns
    azg, elg = np.meshgrid(az, el, indexing="ij")
    d = np.stack([np.cos(elg) * np.cos(azg), np.cos(elg) * np.sin(azg), np.sin(elg)], -1)
    d = d.reshape(-1, 3)
    half = np.array([6.0, 5.0, 3.0])
    with np.errstate(divide="ignore"):
        r = np.where(np.abs(d) > 1e-12, half / np.abs(d), np.inf).min(axis=1)
    pts = np.zeros(d.shape[0], VELODYNE)
    pts["x"], pts["y"], pts["z"] = (d * r[:, None]).T
    pts["intensity"] = 10.0
    pts["ring"] = np.tile(np.arange(16), columns)
    pts["time"] = np.repeat(np.arange(columns) / columns * 0.1, 16)
    return pts


def write_static_bag(path: Path, seconds: float = 3.0) -> Path:
    """A rig that never moves: constant gravity, zero rate, identical sweeps."""
    rng = np.random.default_rng(0)
    cloud = _room_cloud()
    with BagWriter(path, "ros1") as w:
        for i in range(int(seconds * 200)):
            t = T0 + i * 5_000_000
            w.write_imu("/imu", t, 1e-3 * rng.standard_normal(3), [0.0, 0.0, 9.81])
        for k in range(int(seconds * 10) - 1):
            w.write_cloud("/points", T0 + k * 100_000_000, cloud)
    return path


def run(args: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    with pytest.raises(SystemExit) as info:
        main(args)
    out, err = capsys.readouterr()
    return int(info.value.code or 0), out, err


def test_missing_bag(tmp_path, capsys):
    code, _, err = run(["calibrate", str(tmp_path / "none.bag")], capsys)
    assert code == 2
    assert "does not exist" in err
    assert "Traceback" not in err


def test_unknown_config_key_is_named(tmp_path, capsys):
    cfg = tmp_path / "c.yaml"
    cfg.write_text("spline:\n  knot_spacing: 0.02\n")
    bag = write_static_bag(tmp_path / "s.bag", 1.0)
    code, _, err = run(["calibrate", str(bag), "--config", str(cfg)], capsys)
    assert code == 6
    assert "spline.knot_spacing" in err
    assert "Traceback" not in err


def test_missing_topic_lists_candidates(tmp_path, capsys):
    bag = write_static_bag(tmp_path / "s.bag", 1.0)
    code, _, err = run(["calibrate", str(bag), "--imu-topic", "/nope"], capsys)
    assert code == 3
    assert "/imu" in err
    assert "Traceback" not in err


def test_a_beam_table_shorter_than_the_data_is_a_config_error(tmp_path, capsys):
    cfg = tmp_path / "c.yaml"
    cfg.write_text("lidar:\n  nominal_elevation_deg: [-15, -13, -11, -9, -7, -5, -3, -1]\n")
    bag = write_static_bag(tmp_path / "s.bag", 3.0)
    code, _, err = run(["calibrate", str(bag), "--config", str(cfg)], capsys)
    assert code == 6, err
    assert "lists 8 beams but the clouds on /points have 16" in err
    assert "Traceback" not in err


def test_no_motion_is_refused_with_a_reason(tmp_path, capsys):
    bag = write_static_bag(tmp_path / "s.bag", 3.0)
    out = tmp_path / "result.yaml"
    code, _, err = run(["calibrate", str(bag), "--out", str(out)], capsys)
    assert code == 7, err
    # refused before the rotation search (which cannot tell one rotation from another on a
    # still rig), with how far it turned
    assert "Rotation excitation is too weak: the IMU turned at most" in err
    assert "rotate the rig about at least two axes" in err
    assert "Traceback" not in err
    assert not out.exists()  # nothing written on failure


def test_plots_without_matplotlib_fail_before_any_work(tmp_path, capsys, monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import matplotlib -> ImportError

    def not_reached(*args, **kwargs):
        raise AssertionError("calibration started although plots cannot be drawn")

    monkeypatch.setattr("licalib_cli.pipeline.calibrate", not_reached)
    bag = write_static_bag(tmp_path / "s.bag", 1.0)
    code, _, err = run(["calibrate", str(bag), "--plots", str(tmp_path / "p")], capsys)
    assert code == 6, err
    assert "matplotlib" in err and "Traceback" not in err


@pytest.mark.parametrize(
    ("args", "words"),
    [
        (["--out", "{tmp}"], "is a folder; give a file name"),
        (["--out", "{tmp}/file.txt/result.yaml"], "is a file; give another output path"),
        (["--plots", "{tmp}/file.txt"], "--plots needs a folder"),
        (["--plots", "{tmp}/file.txt/plots"], "is a file; give a writable folder to --plots"),
    ],
)
def test_bad_output_paths_fail_before_any_work(tmp_path, capsys, monkeypatch, args, words):
    def not_reached(*a, **k):
        raise AssertionError("calibration started although its output cannot be written")

    monkeypatch.setattr("licalib_cli.pipeline.calibrate", not_reached)
    (tmp_path / "file.txt").write_text("x")
    bag = write_static_bag(tmp_path / "s.bag", 1.0)
    argv = ["calibrate", str(bag), *(a.format(tmp=tmp_path) for a in args)]
    code, _, err = run(argv, capsys)
    assert code == 6, err
    assert words in err and "Traceback" not in err and "Internal error" not in err


@pytest.mark.slow
def test_fail_verdict_exits_9_and_keeps_the_result(tmp_path, capsys):
    """2.5 s of the sample determine less than half of the extrinsic: verdict fail, exit code 9,
    the result is still written for inspection. Too short a segment is refused outright."""
    bag = Path(__file__).resolve().parents[2] / "sample_data" / "sinusoid_vlp16" / "bag.bag"
    out = tmp_path / "r.yaml"
    code, printed, err = run(["calibrate", str(bag), "--duration", "2.5", "-o", str(out)], capsys)
    assert code == 9, err
    assert "Verdict: FAIL" in printed and "The data determine only" in printed
    assert yaml.safe_load(out.read_text())["verdict"]["status"] == "fail"
    code, _, err = run(["calibrate", str(bag), "--duration", "1.5", "-o", str(out)], capsys)
    assert code == 7 and "is 1.5 s long (--duration), too short" in err
    assert "Traceback" not in err
