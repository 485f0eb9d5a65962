"""The allocator setting of the command line."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from licalib_cli.parallel import memory


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_the_allocator_accepts_the_settings_and_arrays_still_work() -> None:
    assert memory.keep_freed_memory() is True
    big = np.ones(memory.MMAP_THRESHOLD // 8 // 2)  # below the threshold: from the heap
    del big
    again = np.zeros(memory.MMAP_THRESHOLD // 8 // 2)
    assert float(again.sum()) == 0.0


def test_an_unknown_platform_is_left_alone(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(memory.sys, "platform", "win32")
    assert memory.keep_freed_memory() is False
