"""Which bags a rerun calibrates again: a result is kept only when its provenance holds the
fingerprints of the same bag content and the same resolved configuration."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest

from licalib_cli.batch import BatchJob, plan
from licalib_cli.config import config_fingerprint, load_config
from licalib_cli.errors import ConfigError
from licalib_cli.pipeline.assemble import bag_fingerprint
from licalib_cli.results import CalibrationResult
from licalib_cli.sections import Provenance, VerdictSection

CONFIG = Path(__file__).resolve().parents[2] / "configs" / "vlp16.yaml"


def _write_result(path: Path, bag: Path, config_fp: str | None) -> None:
    CalibrationResult(
        verdict=VerdictSection("pass"),
        provenance=Provenance("0.1.0", bag_fingerprint(bag), "2026-11-25T00:00:00Z", config_fp),
    ).save(path)


def test_up_to_date_results_are_kept_and_the_rest_calibrated(tmp_path: Path) -> None:
    bags = []
    for name in ("a", "b", "c", "d", "e"):
        bag = tmp_path / "fleet" / f"{name}.bag"
        bag.parent.mkdir(exist_ok=True)
        bag.write_bytes(name.encode() * 1000)
        bags.append(bag)
    jobs = [BatchJob(bag=b, rig="r", config=CONFIG) for b in bags]
    out = tmp_path / "out"
    first = plan(jobs, out)
    assert [p.reason for p in first] == ["new"] * 5
    assert first[0].result_path == out / "r" / "a.yaml"
    assert first[0].config_path == out / "r" / "a.config.yaml"
    cfg_fp = config_fingerprint(load_config(CONFIG))
    assert first[0].config_fingerprint == cfg_fp
    for p in first:
        _write_result(p.result_path, p.job.bag, cfg_fp)
    bags[1].write_bytes(b"other content")  # b: the bag changed
    jobs[2] = replace(jobs[2], start_s=1.0)  # c: another segment
    _write_result(first[3].result_path, bags[3], None)  # d: written before config fingerprints
    first[4].result_path.write_text("schema_version: 7\n")  # e: not a result of this version
    again = plan(jobs, out)
    assert [p.reason for p in again] == [
        "up to date",
        "bag changed",
        "config changed",
        "config changed",
        "result unreadable",
    ]
    assert again[0].existing is not None and again[0].existing.verdict.status == "pass"
    assert all(p.existing is None for p in again[1:])


def test_the_calibration_writes_the_config_fingerprint(tmp_path: Path) -> None:
    """``calibrate``'s result carries the fingerprint ``batch`` compares (provenance)."""
    cfg = load_config(CONFIG, {"bag.duration_s": 3.0})
    prov = Provenance("0.1.0", "0123456789abcdef", "2026-11-25T00:00:00Z", config_fingerprint(cfg))
    back = Provenance.from_dict(prov.to_dict())
    assert back == prov
    assert config_fingerprint(cfg) != config_fingerprint(load_config(CONFIG))
    assert config_fingerprint(cfg) == config_fingerprint(load_config(CONFIG, {"bag.duration_s": 3}))
    old = Provenance("0.1.0", "0123456789abcdef", "2026-11-25T00:00:00Z")
    assert "config_fingerprint" not in old.to_dict()


def test_settings_apply_to_every_bag_and_a_changed_one_calibrates_again(tmp_path: Path) -> None:
    """``batch --set``: the settings go over every bag's config (a manifest row's options over
    them), a result made with other settings is out of date, and a bad one is one sentence."""
    bag = tmp_path / "a.bag"
    bag.write_bytes(b"a" * 1000)
    jobs = [BatchJob(bag=bag, rig="r", config=CONFIG, start_s=2.0)]
    out = tmp_path / "out"
    dense = {"surfels.final_points_per_scan": 15000, "bag.start_s": 5.0}
    (first,) = plan(jobs, out, dense)
    assert first.cfg.surfels.final_points_per_scan == 15000
    assert first.cfg.bag.start_s == 2.0  # the row's start
    _write_result(first.result_path, bag, first.config_fingerprint)
    (same,) = plan(jobs, out, dense)
    assert same.reason == "up to date"
    (other,) = plan(jobs, out)
    assert other.reason == "config changed" and other.cfg.surfels.final_points_per_scan == 6000
    with pytest.raises(ConfigError, match=r"^Unknown setting 'surfels.final_points' in --set;"):
        plan(jobs, out, {"surfels.final_points": 15000})
    # a setting valid only with what the bag's config file gives is taken (a lever arm's sigma
    # needs the lever arm, which the file holds)
    measured = tmp_path / "measured.yaml"
    lever_arm = "\ninitialization:\n  translation_m: [0.3, 0.1, 0.0]\n"
    measured.write_text(CONFIG.read_text() + lever_arm)
    (lever,) = plan(
        [BatchJob(bag=bag, rig="m", config=measured)],
        out,
        {"initialization.translation_sigma_m": 0.01},
    )
    assert lever.cfg.initialization.translation_sigma_m == [0.01, 0.01, 0.01]
