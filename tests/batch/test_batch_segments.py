"""``licalib batch`` with segments: the manifest column ``segments`` and ``--segments``, checked
on the client as ``calibrate --segments`` checks them; the choice is part of the rerun
fingerprint; the task runs the multi-segment calibration and its result is written."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest
from light_config import LIGHT_VLP16

from licalib_cli.batch import BatchJob, read_inputs
from licalib_cli.batch.plan import job_fingerprint, plan
from licalib_cli.batch.run import _Tracker
from licalib_cli.batch.task import TaskOutcome
from licalib_cli.cli import main
from licalib_cli.config import config_fingerprint, load_config
from licalib_cli.errors import ConfigError, ExcitationError, ManifestError
from licalib_cli.pipeline.assemble import bag_fingerprint
from licalib_cli.results import CalibrationResult
from licalib_cli.sections import Provenance, SegmentsSection, VerdictSection

CONFIG = LIGHT_VLP16  # configs/vlp16.yaml with a lighter final round


@pytest.fixture
def fleet(tmp_path: Path) -> Path:
    """Stand-ins for bags (only their paths and content matter here)."""
    for name in ("robot1/a.bag", "robot1/b.bag", "robot2/a.bag"):
        path = tmp_path / "fleet" / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(name.encode() * 100)
    return tmp_path / "fleet"


def _one_sentence(err: str) -> str:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert lines[0].startswith("Error: ") and lines[0].endswith("."), err
    assert "Traceback" not in err
    return lines[0]


def test_segments_column_and_option(fleet: Path) -> None:
    manifest = fleet / "m.csv"
    manifest.write_text(
        "path,rig,segments,start\n"
        "robot1/a.bag,r1,AUTO,\n"
        'robot1/b.bag,r1," 105-120, 60-75 ",\n'
        "robot2/a.bag,,,\n"
    )
    jobs = read_inputs([str(manifest)], CONFIG)
    # normalised: auto in lower case, the windows in time order
    assert [j.segments for j in jobs] == ["auto", "60-75,105-120", None]
    assert all(j.start_s is None and j.duration_s is None for j in jobs)
    # --segments applies to every bag without its own value, paths included
    jobs = read_inputs([str(manifest), str(fleet / "robot2" / "a.bag")], CONFIG, "auto")
    assert [j.segments for j in jobs] == ["auto", "60-75,105-120", "auto"]
    assert len(jobs) == 3  # the same bag with the same settings once
    yaml_manifest = fleet / "m.yaml"
    yaml_manifest.write_text("- {path: robot1/a.bag, segments: 2.5-5.5}\n- robot2/a.bag\n")
    jobs = read_inputs([str(yaml_manifest)], None, "10-20,0-5")
    assert [j.segments for j in jobs] == ["2.5-5.5", "0-5,10-20"]


@pytest.mark.parametrize(
    ("row", "message"),
    [
        (
            "robot1/a.bag,60-x,,",
            "has bad segments in line 2: '60-x'; invalid --segments window '60-x': give "
            "START-END in seconds",
        ),
        ("robot1/a.bag,1-5;4-8,,", "invalid --segments window '1-5;4-8'"),
        ("robot1/a.bag,9-3,,", "window '9-3': its end must come after its start"),
        ("robot1/a.bag,1-5,,", None),
        ("robot1/a.bag,10-20,5,", "gives segments and start in line 2; segments chooses"),
        ("robot1/a.bag,auto,,30", "gives segments and duration in line 2"),
        ('robot1/a.bag,"1-5,4-8",,', "windows 1-5 and 4-8 overlap"),
        ("robot1/a.bag,2-3,,", "lasts only 1 s, too short to calibrate"),
    ],
)
def test_bad_segments_are_a_manifest_error_naming_the_row(
    fleet: Path, row: str, message: str | None, capsys: pytest.CaptureFixture[str]
) -> None:
    manifest = fleet / "m.csv"
    manifest.write_text(f"path,segments,start,duration\n{row}\n")
    if message is None:  # the good row of the lot: nothing to refuse
        assert read_inputs([str(manifest)])[0].segments == "1-5"
        return
    with pytest.raises(ManifestError) as exc:
        read_inputs([str(manifest)])
    assert message in str(exc.value) and str(manifest) in str(exc.value)
    with pytest.raises(SystemExit) as code:
        main(["batch", str(manifest), "-o", str(fleet / "out")])
    assert code.value.code == 6
    out = capsys.readouterr()
    assert message in _one_sentence(out.err) and out.out == ""
    assert not (fleet / "out").exists()


def test_the_option_is_checked_like_calibrates(
    fleet: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(ConfigError, match="Invalid --segments window 'x'"):
        read_inputs([str(fleet / "robot1" / "a.bag")], None, "x")
    with pytest.raises(ExcitationError, match="too short to calibrate"):
        read_inputs([str(fleet / "robot1" / "a.bag")], None, "0-1")
    # a row with its own start cannot take --segments (as calibrate --segments --start)
    manifest = fleet / "m.csv"
    manifest.write_text("path,start\nrobot1/a.bag,5\n")
    with pytest.raises(SystemExit) as code:
        main(["batch", str(manifest), "--segments", "auto", "-o", str(fleet / "out")])
    assert code.value.code == 6
    line = _one_sentence(capsys.readouterr().err)
    assert "gives start in line 2, but --segments auto chooses the data" in line
    with pytest.raises(SystemExit) as code:
        main(["batch", str(fleet / "robot1" / "a.bag"), "--segments", "4-y", "-o", "o"])
    assert code.value.code == 6
    assert "Invalid --segments window '4-y'" in _one_sentence(capsys.readouterr().err)


def _result(bag: Path, config_fp: str | None) -> CalibrationResult:
    return CalibrationResult(
        verdict=VerdictSection("pass"),
        provenance=Provenance("0.1.0", bag_fingerprint(bag), "2026-11-25T00:00:00Z", config_fp),
        segments=SegmentsSection(reference=1, disagreement_threshold_sigmas=3.0),
    )


def test_a_changed_segments_choice_calibrates_again(fleet: Path, tmp_path: Path) -> None:
    bag = fleet / "robot1" / "a.bag"
    cfg_fp = config_fingerprint(load_config(CONFIG))
    assert job_fingerprint(load_config(CONFIG), None) == cfg_fp
    fps = {job_fingerprint(load_config(CONFIG), s) for s in (None, "auto", "0-5", "0-6")}
    assert len(fps) == 4
    out = tmp_path / "out"
    job = BatchJob(bag=bag, rig="r", config=CONFIG, segments="auto")
    (first,) = plan([job], out)
    assert first.reason == "new" and first.config_fingerprint == job_fingerprint(first.cfg, "auto")
    # The client writes the result with the planned fingerprint (a multi-segment result
    # carries its reference segment's provenance, whose config is that segment's range).
    tracker = _Tracker([first], out)
    tracker.attempts[0] = 1
    tracker.finished(
        0, TaskOutcome(result=_result(bag, "0123456789abcdef"), exit_status="ok", seconds=1.0)
    )
    written = CalibrationResult.load(first.result_path)
    assert written.segments is not None
    assert written.provenance is not None
    assert written.provenance.config_fingerprint == first.config_fingerprint
    assert first.config_path.exists()
    assert [p.reason for p in plan([job], out)] == ["up to date"]
    for other in (replace(job, segments="0-5,10-20"), replace(job, segments=None)):
        assert [p.reason for p in plan([other], out)] == ["config changed"]


@pytest.mark.slow
def test_a_batch_calibrates_over_segments_on_a_local_cluster(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """4 s of sinusoid, calibrated over 0-2 and 2-4 s in one problem on a real LocalCluster."""
    import json

    from licalib_cli.simulation import SimulationSpec, simulate

    spec = SimulationSpec(
        scenario="sinusoid",
        lidar="vlp16",
        fmt="ros1",
        duration_s=4.0,
        seed=4,
        intrinsics="none",
        azimuth_resolution_deg=1.0,
    )
    bag = simulate(spec, tmp_path / "sim").bag_path
    manifest = tmp_path / "m.csv"
    manifest.write_text(f'path,rig,segments\n{bag},rigA,"2-4, 0-2"\n')
    out = tmp_path / "out"
    argv = ["batch", str(manifest), "-c", str(CONFIG), "-o", str(out), "--workers", "1"]
    for rerun in (False, True):
        with pytest.raises(SystemExit) as code:
            main([*argv, "--json"])
            raise SystemExit(0)
        assert code.value.code == 0, capsys.readouterr().err
        report = json.loads(capsys.readouterr().out)
        if not rerun:
            assert report["counts"]["calibrated"] == 1
            result = CalibrationResult.load(out / "rigA" / f"{bag.stem}.yaml")
            assert result.segments is not None
            windows = [(e.start_s, e.end_s) for e in result.segments.segments]
            assert windows == [(0.0, 2.0), (2.0, 4.0)]
            assert result.verdict is not None and result.verdict.status != "fail"
            assert (out / "rigA" / f"{bag.stem}.config.yaml").exists()
            assert report["bags"][0]["status"] == "calibrated"
        else:  # the rerun: the same bag, config and segments
            assert report["counts"]["up_to_date"] == 1
    job = read_inputs([str(manifest)], CONFIG)[0]
    assert [p.reason for p in plan([replace(job, segments="auto")], out)] == ["config changed"]
