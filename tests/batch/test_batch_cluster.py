"""``licalib batch`` on a real Dask ``LocalCluster``: four small simulated bags of two rigs, one
of them corrupt, and a worker that dies in the middle of a calibration; a rerun that calibrates
nothing new; Ctrl-C that keeps what is finished, and the rest done on an existing cluster."""

from __future__ import annotations

import csv
import json
import os
import shutil
import socket
import sys
import threading
import time
import uuid
from functools import partial
from pathlib import Path

import cloudpickle
import pytest
from light_config import LIGHT_VLP16

from licalib_cli import __version__
from licalib_cli.batch import TaskInput, TaskOutcome, calibrate_task, read_inputs, run_batch
from licalib_cli.cli import main
from licalib_cli.config import config_fingerprint
from licalib_cli.errors import BagError, BatchIncomplete, ClusterError
from licalib_cli.pipeline.assemble import bag_fingerprint
from licalib_cli.progress import NullProgress
from licalib_cli.results import CalibrationResult
from licalib_cli.sections import Provenance, VerdictSection
from licalib_cli.simulation import SimulationSpec, simulate

pytestmark = pytest.mark.slow

CONFIG = LIGHT_VLP16  # configs/vlp16.yaml with a lighter final round

# The tasks below run in worker processes: send them by value, not as a module to import.
cloudpickle.register_pickle_by_value(sys.modules[__name__])


def _dies_once(markers: Path, task: TaskInput) -> TaskOutcome:
    """Calibrate; on rigA/run2's first attempt the worker process exits half a second in."""
    marker = markers / "rigA_run2.died"
    if task.label == "rigA/run2" and not marker.exists():
        markers.mkdir(parents=True, exist_ok=True)
        marker.write_text(f"{os.getpid()} {task.attempt}")
        threading.Timer(0.5, os._exit, args=(1,)).start()
    return calibrate_task(task)


@pytest.fixture(scope="module")
def fleet(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """rigA/run1, rigA/run2, rigB/run1: a 3 s shake; rigB/run2: the same bag truncated."""
    spec = SimulationSpec(
        scenario="shake",
        lidar="vlp16",
        fmt="ros1",
        duration_s=3.0,
        # 3 s of shaking determine every coordinate (3 s of the sinusoid leave a direction of
        # the lever arm that a y component of 0.01 tips between a WARN and a FAIL)
        seed=5,
        intrinsics="none",
        azimuth_resolution_deg=1.0,
    )
    root = tmp_path_factory.mktemp("batch")
    bag = simulate(spec, root / "sim").bag_path
    fleet = root / "fleet"
    for name in ("rigA/run1.bag", "rigA/run2.bag", "rigB/run1.bag"):
        (fleet / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(bag, fleet / name)
    (fleet / "rigB" / "run2.bag").write_bytes(bag.read_bytes()[:100_000])
    return fleet


@pytest.fixture(scope="module")
def first_run(fleet: Path) -> tuple[Path, Path, object]:
    out = fleet.parent / "out"
    markers = fleet.parent / "markers"
    jobs = read_inputs([str(fleet / "*" / "*.bag")], CONFIG)
    report = run_batch(jobs, out, workers=2, retries=1, task=partial(_dies_once, markers))
    return out, markers, report


def test_three_results_one_failure_and_a_dead_worker_retried(first_run, fleet: Path) -> None:
    out, markers, report = first_run
    rows = {f"{b.rig}/{b.bag}": b for b in report.bags}
    assert list(rows) == ["rigA/run1", "rigA/run2", "rigB/run1", "rigB/run2"]
    assert report.workers == 2
    for label in ("rigA/run1", "rigA/run2", "rigB/run1"):
        row = rows[label]
        assert row.status == "calibrated", row
        assert row.verdict in ("pass", "warn")
        result = CalibrationResult.load(out / f"{label}.yaml")
        assert (out / f"{label}.config.yaml").exists()
        assert row.result == f"{label}.yaml"
        assert abs(result.extrinsic.translation[0] - row.t_x_m) < 1e-9
        assert result.provenance is not None and result.provenance.config_fingerprint
        assert row.calibration_s > 0
    # The worker calibrating rigA/run2 died; the bag was calibrated on the retry.
    assert (markers / "rigA_run2.died").read_text().endswith(" 1")
    assert rows["rigA/run2"].attempts == 2
    assert rows["rigA/run1"].attempts == 1
    # The corrupt bag failed at once (a refused bag is not retried), with its sentence.
    failed = rows["rigB/run2"]
    assert failed.status == "failed" and failed.attempts == 1
    assert failed.exit_code == BagError.exit_code
    assert "cannot be read" in failed.error and failed.error.endswith(".")
    assert not (out / "rigB" / "run2.yaml").exists()
    # The summaries.
    table = list(csv.DictReader((out / "summary.csv").open()))
    assert [r["status"] for r in table] == ["calibrated"] * 3 + ["failed"]
    assert table[3]["error"] == failed.error
    rigs = list(csv.DictReader((out / "rigs.csv").open()))
    assert [(r["rig"], r["bags"], r["usable"], r["failed"]) for r in rigs] == [
        ("rigA", "2", "2", "0"),
        ("rigB", "2", "1", "1"),
    ]
    assert rigs[0]["differing"] == ""  # the same recording twice agrees with itself
    assert not report.complete


def test_a_rerun_calibrates_nothing_new(first_run, fleet: Path, capsys) -> None:
    out, _, _ = first_run
    kept = {p: (p.read_bytes(), p.stat().st_mtime_ns) for p in out.glob("*/*.yaml")}
    assert len(kept) == 6
    argv = ["batch", str(fleet / "*" / "*.bag"), "-c", str(CONFIG), "-o", str(out), "--json"]
    with pytest.raises(SystemExit) as exc:
        main([*argv, "--workers", "1"])
    captured = capsys.readouterr()
    assert exc.value.code == BatchIncomplete.exit_code == 12
    report = json.loads(captured.out)
    assert report["counts"] == {
        "bags": 4,
        "calibrated": 0,
        "up_to_date": 3,
        "failed": 1,
        "verdict_fail": 0,
    }
    assert [b["status"] for b in report["bags"]] == ["up to date"] * 3 + ["failed"]
    assert report["bags"][0]["calibration_s"] > 0  # from the earlier summary
    assert {p: (p.read_bytes(), p.stat().st_mtime_ns) for p in out.glob("*/*.yaml")} == kept
    assert "Error: 1 of 4 bags failed; every other result is written" in captured.err


class _StopAfterFirst(NullProgress):
    """Ctrl-C as soon as the first bag is done."""

    def advance(self, done: int, total: int | None = None) -> None:
        if done >= 1:
            raise KeyboardInterrupt


def _quick(calls: Path, task: TaskInput) -> TaskOutcome:
    """A stand-in calibration: a result with the provenance a real one has, after 0.3 s."""
    calls.mkdir(parents=True, exist_ok=True)
    (calls / f"{task.label.replace('/', '_')}.{uuid.uuid4().hex}").write_text("")
    time.sleep(0.3)
    provenance = Provenance(
        __version__, bag_fingerprint(task.bag), "2026-11-25T00:00:00Z", config_fingerprint(task.cfg)
    )
    result = CalibrationResult(verdict=VerdictSection("pass"), provenance=provenance)
    return TaskOutcome(result=result, exit_status="ok", seconds=0.3)


def test_ctrl_c_keeps_finished_results_and_the_rest_runs_on_an_existing_cluster(
    tmp_path: Path,
) -> None:
    from distributed import LocalCluster

    for name in ("a", "b", "c"):
        (tmp_path / "r" / f"{name}.bag").parent.mkdir(exist_ok=True)
        (tmp_path / "r" / f"{name}.bag").write_bytes(name.encode() * 100)
    jobs = read_inputs([str(tmp_path / "r" / "*.bag")])
    out = tmp_path / "out"
    with pytest.raises(KeyboardInterrupt):
        run_batch(
            jobs,
            out,
            workers=1,
            task=partial(_quick, tmp_path / "calls1"),
            progress=_StopAfterFirst(),
        )
    written = sorted(p.name for p in out.glob("r/*.yaml") if not p.name.endswith(".config.yaml"))
    assert written == ["a.yaml"]
    before = (out / "r" / "a.yaml").read_bytes()
    table = list(csv.DictReader((out / "summary.csv").open()))
    assert [r["status"] for r in table] == ["calibrated", "not run", "not run"]
    # Resumed on an existing cluster (--scheduler): only the two unfinished bags are run.
    with LocalCluster(
        n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None
    ) as cluster:
        report = run_batch(
            jobs,
            out,
            scheduler=cluster.scheduler_address,
            task=partial(_quick, tmp_path / "calls2"),
        )
    assert [b.status for b in report.bags] == ["up to date", "calibrated", "calibrated"]
    assert sorted(p.name.split(".")[0] for p in (tmp_path / "calls2").iterdir()) == ["r_b", "r_c"]
    assert (out / "r" / "a.yaml").read_bytes() == before
    assert report.complete


def test_an_unreachable_scheduler_is_one_sentence(tmp_path: Path) -> None:
    (tmp_path / "a.bag").write_bytes(b"x")
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    jobs = read_inputs([str(tmp_path / "a.bag")])
    with pytest.raises(ClusterError) as exc:
        run_batch(jobs, tmp_path / "out", scheduler=f"127.0.0.1:{port}", connect_timeout_s=1.0)
    text = str(exc.value)
    assert text.startswith(f"Cannot reach the Dask scheduler at tcp://127.0.0.1:{port} within 1 s")
    assert text.endswith(".") and ClusterError.exit_code == 11
