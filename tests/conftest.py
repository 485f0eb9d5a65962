"""Shared test options and fixtures.

``pytest --update-golden`` rewrites the golden files under ``tests/golden`` instead of comparing
with them (review the diff before committing).
"""

from __future__ import annotations

import difflib
import os
from collections.abc import Callable
from pathlib import Path

import pytest

# The solver's dense products are small: OpenBLAS threads only add contention on them (and, with
# pytest -n, with the other workers). The command line sets this before numpy is imported
# (licalib_cli/cli.py); a test process imports numpy first, so the tests set it here, before
# the test modules are imported.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
# Under pytest -n every core already runs a worker: the spline's block loops stay on one thread
# (licalib_cli.parallel.threads; tests/core/test_threads.py forces both paths itself).
if os.environ.get("PYTEST_XDIST_WORKER"):
    os.environ.setdefault("LICALIB_THREADS", "1")

GOLDEN = Path(__file__).parent / "golden"


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        "--update-golden",
        action="store_true",
        default=False,
        help="rewrite the golden files under tests/golden instead of comparing with them",
    )


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Run the modules with the most slow tests first, each module's tests together and in
    their order. Under ``pytest -n 2 --dist loadscope`` (the README's test command) a module runs
    on one worker, so its module fixtures (simulated bags, calibrations) are built once, and
    the workers end on short modules instead of one of them still running a long one."""
    modules: dict[str, list[pytest.Item]] = {}
    for item in items:
        modules.setdefault(item.nodeid.split("::", 1)[0], []).append(item)

    def weight(group: list[pytest.Item]) -> float:
        return sum(1.0 if item.get_closest_marker("slow") else 0.02 for item in group)

    ordered = sorted(modules.values(), key=weight, reverse=True)  # stable: ties keep their order
    items[:] = [item for group in ordered for item in group]


@pytest.fixture
def golden(request: pytest.FixtureRequest) -> Callable[[str, str], None]:
    """``golden(name, text)``: compare ``text`` with ``tests/golden/<name>`` (or rewrite it)."""

    def check(name: str, text: str) -> None:
        path = GOLDEN / name
        if request.config.getoption("--update-golden"):
            path.write_text(text)
            return
        expected = path.read_text()
        if text != expected:
            diff = "".join(
                difflib.unified_diff(
                    expected.splitlines(keepends=True),
                    text.splitlines(keepends=True),
                    f"golden/{name}",
                    "now",
                )
            )
            pytest.fail(f"{diff}\nRun pytest --update-golden to accept the change.")

    return check
