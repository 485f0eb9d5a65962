"""End to end: calibrate a short simulated bag with --report, --map and --map-before; read the
maps back with Open3D; draw the report again later with ``licalib report``; and, when Chromium
is installed, look at the page as a person would."""

from __future__ import annotations

import re

import numpy as np
import pytest
import yaml
from light_config import LIGHT_VLP16

from licalib_cli.cli import main
from licalib_cli.report import ReportData, report_data_path
from licalib_cli.simulation import SimulationSpec, simulate

CONFIG = LIGHT_VLP16  # configs/vlp16.yaml with a lighter final round

pytest.importorskip("matplotlib")
o3d = pytest.importorskip("open3d")


def _strip_images(page: str) -> str:
    return re.sub(r"data:image/png;base64,[A-Za-z0-9+/=]+", "IMG", page)


def _main(args: list[str]) -> int:
    with pytest.raises(SystemExit) as exc:
        main(args)
        raise SystemExit(0)
    return int(exc.value.code or 0)


@pytest.mark.slow
def test_calibrate_writes_report_and_maps(tmp_path, browser_if_installed):
    spec = SimulationSpec(
        scenario="sinusoid",
        lidar="vlp16",
        fmt="ros1",
        duration_s=3.0,
        seed=5,
        time_offset_s=-0.004,
        intrinsics="none",
        azimuth_resolution_deg=0.8,
    )
    sim = simulate(spec, tmp_path / "sim")
    out = tmp_path / "out"
    code = _main(
        [
            "calibrate",
            str(sim.bag_path),
            "-c",
            str(CONFIG),
            "-o",
            str(out / "calib.yaml"),
            "--truth",
            str(sim.bag_path.parent / "truth.yaml"),
            "--report",
            str(out / "report.html"),
            "--map",
            str(out / "map.ply"),
            "--map-before",
            str(out / "before.pcd"),
        ]
    )
    # A 3 s sinusoid may leave directions unobservable (verdict fail, exit 9): the report and
    # the maps are written for inspection all the same.
    assert code in (0, 9)
    assert sorted(p.name for p in out.iterdir()) == [
        "before.pcd",
        "calib.config.yaml",
        "calib.report-data.npz",
        "calib.yaml",
        "map.ply",
        "report.html",
    ]
    page = (out / "report.html").read_text()
    assert page.count("data:image/png;base64,") >= 7
    assert "no report data" not in page

    data = ReportData.load(report_data_path(out / "calib.yaml"))
    assert data.truth is not None and data.has_map
    assert np.isfinite(data.map_entropy_before) and np.isfinite(data.map_entropy_after)
    assert "--map-before" in data.command_line and data.command_line.startswith("licalib ")

    # The maps open in Open3D with beam and time per point; two calibrations, two maps.
    clouds = {}
    for name in ("map.ply", "before.pcd"):
        cloud = o3d.t.io.read_point_cloud(str(out / name))
        assert cloud.point["positions"].shape[0] > 50_000
        beam = cloud.point["beam"].numpy().ravel()
        assert beam.min() >= 0 and beam.max() == 15  # VLP-16
        t = cloud.point["time"].numpy().ravel()
        assert t.min() >= 0.0 and t.max() <= 3.1
        clouds[name] = cloud.point["positions"].numpy()
    m = min(len(c) for c in clouds.values())
    assert not np.allclose(clouds["map.ply"][:m], clouds["before.pcd"][:m])

    # The sensors' frame ids are recorded, so a URDF joint needs no names.
    truth = yaml.safe_load((sim.bag_path.parent / "truth.yaml").read_text())["simulation"]
    recording = yaml.safe_load((out / "calib.yaml").read_text())["recording"]
    assert recording["imu_frame"] == truth["imu"]["frame_id"]
    assert recording["lidar_frame"] == truth["lidar"]["frame_id"]
    assert recording["gravity_turn_deg"] > 5.0  # the sinusoid tilts the rig
    urdf = tmp_path / "joint.urdf"
    assert (
        _main(["export", str(out / "calib.yaml"), "--to", "urdf", "--force", "-o", str(urdf)]) == 0
    )
    assert f'<child link="{truth["lidar"]["frame_id"]}"/>' in urdf.read_text()

    # Later, from the result file alone (and its report data): the same page.
    again = tmp_path / "again.html"
    assert _main(["report", str(out / "calib.yaml"), "-o", str(again)]) == 0
    assert _strip_images(again.read_text()) == _strip_images(page)

    browser = browser_if_installed
    if browser is None:
        return  # test_page_in_chromium says it is skipped
    pixels = browser.screenshot(out / "report.html", tmp_path / "shot.png", 1200, 2400)
    assert pixels.shape[:2] == (2400, 1200)
    dom = browser.dom(out / "report.html")
    text = browser.text(dom)
    verdict = yaml.safe_load((out / "calib.yaml").read_text())["verdict"]
    assert f"Verdict: {verdict['status'].upper()}" in text
    for reason in verdict["reasons"]:
        assert " ".join(reason.split()) in text
    assert browser.verdict_share(pixels, verdict["status"]) > 0.05
    cells = browser.table_cells(dom, "estimate")
    assert cells[:6] == ["parameter", "estimate", "1-sigma", "initial guess", "truth", "error"]
    row = cells[cells.index("time offset") : cells.index("time offset") + 6]
    assert row[4] == "-4.000 ms"
