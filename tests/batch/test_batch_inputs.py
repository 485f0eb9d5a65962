"""``licalib batch`` inputs: bag paths, glob patterns and CSV/YAML manifests become jobs; every
bad input is one sentence with its exit code, before any cluster starts."""

from __future__ import annotations

from pathlib import Path

import pytest

from licalib_cli.batch import COLUMNS, read_inputs
from licalib_cli.batch.cluster import _scheduler_address
from licalib_cli.cli import main
from licalib_cli.errors import ClusterError, ConfigError, ManifestError

CONFIG = Path(__file__).resolve().parents[2] / "configs" / "vlp16.yaml"


def _run(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    with pytest.raises(SystemExit) as exc:
        main(argv)
        raise SystemExit(0)
    out = capsys.readouterr()
    return int(exc.value.code or 0), out.out, out.err


def _one_sentence(err: str) -> str:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert lines[0].startswith("Error: ") and lines[0].endswith("."), err
    assert "Traceback" not in err and "Internal error" not in err
    return lines[0]


@pytest.fixture
def fleet(tmp_path: Path) -> Path:
    """Empty stand-ins for bags (only their paths matter here)."""
    for name in ("robot1/a.bag", "robot1/b.bag", "robot2/a.bag", "robot2/ros2bag/x.mcap"):
        path = tmp_path / "fleet" / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(b"")
    return tmp_path / "fleet"


def test_paths_and_globs_become_jobs_with_the_folder_as_rig(fleet: Path) -> None:
    jobs = read_inputs([str(fleet / "*" / "*.bag"), str(fleet / "robot2" / "ros2bag")], CONFIG)
    assert [j.label for j in jobs] == ["robot1/a", "robot1/b", "robot2/a", "robot2/ros2bag"]
    assert all(j.config == CONFIG and j.bag.is_absolute() for j in jobs)
    # The same bag named twice (a pattern and its path) is calibrated once.
    again = read_inputs([str(fleet / "robot1" / "*.bag"), str(fleet / "robot1" / "a.bag")])
    assert [j.label for j in again] == ["robot1/a", "robot1/b"]


def test_csv_manifest(fleet: Path) -> None:
    manifest = fleet / "m.csv"
    manifest.write_text(
        "path,rig,config,start,duration,imu_topic\n"
        f"robot1/a.bag,r1,{CONFIG},2.5,30,/imu\n"
        "robot2/*.bag,,,,,\n"
        "\n"
    )
    jobs = read_inputs([str(manifest)], None)
    assert [j.label for j in jobs] == ["r1/a", "robot2/a"]
    first, second = jobs
    assert first.bag == fleet / "robot1" / "a.bag"
    assert (first.config, first.start_s, first.duration_s, first.imu_topic) == (
        CONFIG,
        2.5,
        30.0,
        "/imu",
    )
    assert first.overrides()["bag.start_s"] == 2.5
    assert second.config is None and second.start_s is None
    assert "m.csv, line 2" in first.source


def test_yaml_manifest_paths_are_read_from_its_folder(fleet: Path, tmp_path: Path) -> None:
    manifest = fleet / "m.yaml"
    manifest.write_text(
        "bags:\n"
        "  - robot1/b.bag\n"
        "  - {path: robot2/a.bag, rig: 7, config: ../c.yaml, duration: 12}\n"
    )
    jobs = read_inputs([str(manifest)], CONFIG)
    assert [j.label for j in jobs] == ["robot1/b", "7/a"]
    assert jobs[0].config == CONFIG  # -c for a row without a config
    assert jobs[1].config == fleet / ".." / "c.yaml"
    assert jobs[1].duration_s == 12.0


@pytest.mark.parametrize(
    ("text", "suffix", "message"),
    [
        ("path,rig\nrobot1/missing.bag,r\n", ".csv", "names in line 2 the bag robot1/missing.bag"),
        ("path,robot\nrobot1/a.bag,r\n", ".csv", "has an unknown column 'robot' (line 1)"),
        ("- {path: robot1/a.bag, colour: red}\n", ".yaml", "has an unknown key 'colour' (entry 1)"),
        ("path,start\nrobot1/a.bag,soon\n", ".csv", "has a bad start in line 2: 'soon'"),
        ("path,duration\nrobot1/a.bag,-3\n", ".csv", "has a bad duration in line 2: '-3'"),
        ("path,start\nrobot1/a.bag,nan\n", ".csv", "has a bad start in line 2"),
        ("path,rig\nrobot1/a.bag,../up\n", ".csv", "has a bad rig in line 2: '../up'"),
        ("rig\nr\n", ".csv", "has no 'path' column"),
        ("path\nrobot9/*.bag\n", ".csv", "the pattern robot9/*.bag, which matches no file"),
        ("path,rig\nrobot1/a.bag,r,extra\n", ".csv", "has 3 cells on line 2 but 2 columns"),
        ("", ".csv", "is empty"),
        ("path\n", ".csv", "lists no bags"),
        ("bags: {path: x}\n", ".yaml", "is not a list of bags"),
        ("- [1, 2]\n", ".yaml", "entry 1 that is neither a path nor a mapping"),
        ("- {rig: r}\n", ".yaml", "gives no path in entry 1"),
        ("bags: [a]\nbag: [b]\n", ".yaml", "unknown top-level key 'bag'"),
        ("- {path: [unclosed\n", ".yaml", "The manifest"),
    ],
    ids=[
        "missing-file",
        "unknown-column",
        "unknown-key",
        "bad-number",
        "negative-duration",
        "nan",
        "rig-not-a-folder",
        "no-path-column",
        "pattern-matches-nothing",
        "extra-cell",
        "empty",
        "header-only",
        "not-a-list",
        "entry-not-a-mapping",
        "no-path",
        "unknown-top-level-key",
        "invalid-yaml",
    ],
)
def test_manifest_errors_are_one_sentence_exit_6(
    fleet: Path, text: str, suffix: str, message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    manifest = fleet / f"manifest{suffix}"
    manifest.write_text(text)
    with pytest.raises(ManifestError) as exc:
        read_inputs([str(manifest)], None)
    assert message in str(exc.value)
    code, out, err = _run(["batch", str(manifest), "-o", str(fleet / "out")], capsys)
    assert code == ManifestError.exit_code == ConfigError.exit_code == 6
    line = _one_sentence(err)
    assert message in line and str(manifest) in line
    assert out == ""
    assert not (fleet / "out").exists()  # refused before anything is written


def test_unreadable_manifests(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    binary = tmp_path / "m.csv"
    binary.write_bytes(b"path\n\xff\xfe\x00bag\n")
    folder = tmp_path / "d.yaml"
    folder.mkdir()
    for path, message in (
        (binary, "is not a text file (byte 5 is not UTF-8)"),
        (folder, "is a folder"),
        (tmp_path / "none.csv", "does not exist"),
    ):
        code, _, err = _run(["batch", str(path), "-o", str(tmp_path / "out")], capsys)
        assert code == 6
        assert message in _one_sentence(err)


def test_bad_command_line_inputs(fleet: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = str(fleet / "out")
    cases = [
        ([str(fleet / "none.bag")], 6, "The bag"),
        ([str(fleet / "robot3" / "*.bag")], 6, "No file matches"),
        ([str(fleet / "*/a.bag"), "--workers", "0"], 6, "--workers 0 is not a number of workers"),
        ([str(fleet / "*/a.bag"), "--retries", "-1"], 6, "--retries -1"),
        (
            [str(fleet / "*/a.bag"), "--scheduler", "tcp://127.0.0.1:1", "--workers", "2"],
            6,
            "drop --workers",
        ),
        ([str(fleet / "*/a.bag"), "--scheduler", "tcp://host"], 11, "is not a Dask scheduler"),
        ([str(fleet / "*/a.bag"), "-c", str(fleet / "no.yaml")], 6, "does not exist"),
    ]
    for args, expected, message in cases:
        code, _, err = _run(["batch", *args, "-o", out], capsys)
        assert code == expected, err
        assert message in _one_sentence(err)


def test_two_bags_writing_one_result_are_refused(
    fleet: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    manifest = fleet / "m.csv"
    manifest.write_text("path,rig\nrobot1/a.bag,r\nrobot2/a.bag,r\n")
    code, _, err = _run(["batch", str(manifest), "-o", str(fleet / "out")], capsys)
    assert code == 6
    assert "would both write" in _one_sentence(err)


def test_an_output_inside_the_inputs_is_refused(
    fleet: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # With -o the fleet's own folder, the resolved config beside robot1/a.yaml would be
    # robot1/a.config.yaml, which is given as an input too.
    (fleet / "robot1" / "a.config.yaml").write_text("")
    code, _, err = _run(["batch", str(fleet / "robot1" / "*"), "-o", str(fleet)], capsys)
    assert code == 6
    assert "would destroy that input" in _one_sentence(err)


def test_scheduler_addresses() -> None:
    assert _scheduler_address("10.0.0.5:8786") == "tcp://10.0.0.5:8786"
    assert _scheduler_address(" tcp://host:8786 ") == "tcp://host:8786"
    for bad in ("tcp://host", "http://host:8786", "host:port", "tcp://:8786", "host:99999"):
        with pytest.raises(ClusterError, match="is not a Dask scheduler address"):
            _scheduler_address(bad)


def test_manifest_columns_are_documented() -> None:
    readme = (Path(__file__).resolve().parents[2] / "README.md").read_text()
    for column in COLUMNS:
        assert f"`{column}`" in readme
