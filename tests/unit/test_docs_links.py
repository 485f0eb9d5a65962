"""Every relative link of the README and of ``docs/`` leads to a file that exists and, with an
anchor, to a heading of that file (GitHub's anchors: lower case, punctuation dropped, spaces as
hyphens)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]


def _anchors(page: Path) -> set[str]:
    anchors, code = set(), False
    for line in page.read_text().splitlines():
        if line.startswith("```"):
            code = not code
        heading = None if code else re.match(r"^#+ (.*)", line)
        if heading:
            text = re.sub(r"[^\w\- ]", "", heading.group(1).strip().lower())
            anchors.add(text.replace(" ", "-"))
    return anchors


def _links(page: Path) -> list[str]:
    return [
        link
        for link in re.findall(r"\]\(([^)\s]+)\)", page.read_text())
        if not link.startswith(("http://", "https://", "mailto:"))
    ]


def test_anchors_follow_github() -> None:
    page = ROOT / "README.md"
    assert "long-recordings-licalib-select-segments-and-calibrate---segments" in _anchors(page)
    assert "intrinsics---intrinsics-and-the-model-section" in _anchors(page)


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.relative_to(ROOT).as_posix())
def test_every_relative_link_resolves(page: Path) -> None:
    broken = []
    for link in _links(page):
        path, _, anchor = link.partition("#")
        target = (page.parent / path).resolve() if path else page
        if not target.exists():
            broken.append(f"{link}: no such file")
        elif anchor and target.suffix == ".md" and anchor not in _anchors(target):
            broken.append(f"{link}: no such heading in {target.name}")
    assert not broken, broken
