"""End to end: calibrate a short simulated bag with --report, --map and --map-before; read the
maps back with Open3D; draw the report again later with ``licalib report``; and look at the page
as a person would, in headless Chromium (screenshot and the rendered text)."""

from __future__ import annotations

import html
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
import yaml

from licalib_cli.cli import main
from licalib_cli.report import ReportData, report_data_path
from licalib_cli.simulation import SimulationSpec, simulate

CONFIG = Path(__file__).resolve().parents[2] / "configs" / "vlp16.yaml"

pytest.importorskip("matplotlib")
o3d = pytest.importorskip("open3d")


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, str]:
    spec = SimulationSpec(
        scenario="sinusoid",
        lidar="vlp16",
        fmt="ros1",
        duration_s=4.0,
        seed=5,
        time_offset_s=-0.004,
        intrinsics="none",
        azimuth_resolution_deg=0.4,
    )
    sim = simulate(spec, tmp_path_factory.mktemp("sim"))
    out = tmp_path_factory.mktemp("out")
    args = [
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
    with pytest.raises(SystemExit) as exc:
        main(args)
        raise SystemExit(0)
    # A 4 s sinusoid may leave directions unobservable (verdict fail, exit 9): the report and
    # the maps are written for inspection all the same.
    assert exc.value.code in (0, None, 9)
    return out, (out / "report.html").read_text()


def _strip_images(page: str) -> str:
    return re.sub(r"data:image/png;base64,[A-Za-z0-9+/=]+", "IMG", page)


@pytest.mark.slow
def test_report_and_maps_are_written(calibrated):
    out, page = calibrated
    assert sorted(p.name for p in out.iterdir()) == [
        "before.pcd",
        "calib.config.yaml",
        "calib.report-data.npz",
        "calib.yaml",
        "map.ply",
        "report.html",
    ]
    assert page.count("data:image/png;base64,") >= 7
    assert "no report data" not in page
    data = ReportData.load(report_data_path(out / "calib.yaml"))
    assert data.truth is not None and data.has_map
    assert np.isfinite(data.map_entropy_before) and np.isfinite(data.map_entropy_after)
    assert "--map-before" in data.command_line
    for name in ("map.ply", "before.pcd"):
        cloud = o3d.t.io.read_point_cloud(str(out / name))
        n = cloud.point["positions"].shape[0]
        assert n > 50_000
        beam = cloud.point["beam"].numpy().ravel()
        assert beam.min() >= 0 and beam.max() == 15  # VLP-16
        t = cloud.point["time"].numpy().ravel()
        assert t.min() >= 0.0 and t.max() <= 4.1
    after = o3d.t.io.read_point_cloud(str(out / "map.ply")).point["positions"].numpy()
    before = o3d.t.io.read_point_cloud(str(out / "before.pcd")).point["positions"].numpy()
    m = min(len(after), len(before))
    assert not np.allclose(after[:m], before[:m])  # two calibrations, two maps


@pytest.mark.slow
def test_report_later_from_the_result_alone(calibrated, capsys):
    out, page = calibrated
    again = out.parent / "again.html"
    with pytest.raises(SystemExit) as exc:
        main(["report", str(out / "calib.yaml"), "-o", str(again)])
        raise SystemExit(0)
    assert exc.value.code in (0, None), capsys.readouterr().err
    assert _strip_images(again.read_text()) == _strip_images(page)


def _chromium() -> str:
    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    if exe is None:
        pytest.skip("chromium is not installed (bash scripts/setup.sh --with-browser installs it)")
    return exe


def _headless(exe: str, profile: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [
            exe,
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--hide-scrollbars",
            "--no-first-run",
            f"--user-data-dir={profile}",
            *args,
        ],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )


@pytest.mark.slow
def test_report_as_a_person_sees_it_in_chromium(calibrated, tmp_path):
    exe = _chromium()
    out, _ = calibrated
    url = (out / "report.html").as_uri()
    shot = tmp_path / "shot.png"
    done = _headless(exe, tmp_path / "p1", f"--screenshot={shot}", "--window-size=1200,2400", url)
    assert shot.is_file(), done.stderr
    import matplotlib.image as mpimg

    pixels = mpimg.imread(shot)
    assert pixels.shape[:2] == (2400, 1200)
    # Not a blank page: text, tables and figures; the verdict box's colour near the top.
    assert float(pixels[..., :3].std()) > 0.05
    top = pixels[:400, :, :3]
    colours = {"pass": (0x1E, 0x8E, 0x3E), "warn": (0xC7, 0x77, 0x00), "fail": (0xC5, 0x22, 0x1F)}
    dom = _headless(exe, tmp_path / "p2", "--dump-dom", url).stdout
    text = re.sub(r"<[^>]+>", " ", _strip_images(dom))
    status = re.search(r"Verdict:\s+(PASS|WARN|FAIL)", text)
    assert status is not None, text[:2000]
    verdict = yaml.safe_load((out / "calib.yaml").read_text())["verdict"]
    assert status.group(1) == verdict["status"].upper()
    for reason in verdict["reasons"]:
        assert " ".join(reason.split()) in " ".join(html.unescape(text).split())
    rgb = np.array(colours[status.group(1).lower()]) / 255.0
    share = np.mean(np.all(np.abs(top - rgb) < 0.02, axis=-1))
    assert share > 0.05
    # The estimate table as rendered: every row, with the truth beside the estimate.
    table = dom[dom.index('<table class="estimate">') :]
    table = table[: table.index("</table>")]
    cells = [
        re.sub(r"<[^>]+>", "", c).strip() for c in re.findall(r"<t[hd][^>]*>.*?</t[hd]>", table)
    ]
    assert cells[:6] == ["parameter", "estimate", "1-sigma", "initial guess", "truth", "error"]
    for name in ("t_x", "t_y", "t_z", "roll", "pitch", "yaw", "time offset"):
        assert name in cells
    row = cells[cells.index("time offset") : cells.index("time offset") + 6]
    assert row[4] == "-4.000 ms" and row[1].endswith(" ms")
    for heading in ("What the data determined", "The fit", "The motion", "The map", "Provenance"):
        assert heading in text
