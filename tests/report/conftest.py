"""A headless Chromium to look at report pages as a person would (skipped without one)."""

from __future__ import annotations

import re
import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt
import pytest

VERDICT_COLOURS = {
    "pass": (0x1E, 0x8E, 0x3E),
    "warn": (0xC7, 0x77, 0x00),
    "fail": (0xC5, 0x22, 0x1F),
}
"""The verdict box's background per verdict (the report's style)."""


@dataclass(frozen=True)
class Browser:
    """Debian's ``chromium`` in headless mode, with a fresh profile per call."""

    exe: str
    profiles: Path

    def _run(self, *args: str) -> subprocess.CompletedProcess[str]:
        profile = self.profiles / f"profile{len(list(self.profiles.iterdir()))}"
        return subprocess.run(
            [
                self.exe,
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

    def screenshot(
        self, page: Path, shot: Path, width: int, height: int
    ) -> npt.NDArray[np.float32]:
        """The page rendered in a ``width`` x ``height`` window, as RGB(A) floats in [0, 1]."""
        done = self._run(f"--screenshot={shot}", f"--window-size={width},{height}", page.as_uri())
        assert shot.is_file(), done.stderr
        import matplotlib.image as mpimg

        return np.asarray(mpimg.imread(shot), dtype=np.float32)

    def dom(self, page: Path) -> str:
        """The page's DOM after rendering (``--dump-dom``), images' data left out."""
        out = self._run("--dump-dom", page.as_uri()).stdout
        return re.sub(r"data:image/png;base64,[A-Za-z0-9+/=]+", "IMG", out)

    @staticmethod
    def text(dom: str) -> str:
        """The visible text of a dumped DOM, whitespace collapsed, entities decoded."""
        import html

        return " ".join(html.unescape(re.sub(r"<[^>]+>", " ", dom)).split())

    @staticmethod
    def table_cells(dom: str, cls: str) -> list[str]:
        """The cells of the first ``<table class="cls">`` of a dumped DOM, row by row."""
        table = dom[dom.index(f'<table class="{cls}">') :]
        table = table[: table.index("</table>")]
        return [Browser.text(c) for c in re.findall(r"<t[hd][^>]*>.*?</t[hd]>", table)]

    @staticmethod
    def verdict_share(pixels: npt.NDArray[np.float32], status: str, rows: int = 400) -> float:
        """Share of the top ``rows`` pixel rows painted in the verdict box's colour."""
        rgb = np.array(VERDICT_COLOURS[status]) / 255.0
        top = pixels[:rows, :, :3]
        return float(np.mean(np.all(np.abs(top - rgb) < 0.02, axis=-1)))


def _browser(tmp_path: Path) -> Browser | None:
    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    if exe is None:
        return None
    profiles = tmp_path / "chromium-profiles"
    profiles.mkdir()
    return Browser(exe, profiles)


@pytest.fixture
def browser(tmp_path: Path) -> Browser:
    """Headless Chromium; the test is skipped when it is not installed."""
    found = _browser(tmp_path)
    if found is None:
        pytest.skip(
            "chromium is not installed; `bash scripts/setup.sh --tests` installs Debian's "
            "chromium package"
        )
    return found


@pytest.fixture
def browser_if_installed(tmp_path: Path) -> Browser | None:
    """Headless Chromium, or None (for tests that check more than the page's looks)."""
    return _browser(tmp_path)
