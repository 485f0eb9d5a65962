"""The segment benchmark measures the long ranking's own process, not the largest of every
process the benchmark ran before it."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path
from types import ModuleType

BENCH = Path(__file__).resolve().parents[2] / "benchmarks" / "bench_segments.py"


def _bench_segments() -> ModuleType:
    spec = importlib.util.spec_from_file_location("bench_segments_measured", BENCH)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    path = list(sys.path)
    try:
        spec.loader.exec_module(module)
    finally:
        sys.path[:] = path  # the script puts its folder first on the path
    return module


def test_the_peak_memory_is_the_measured_process_s_own() -> None:
    bench = _bench_segments()
    # a larger process first, waited for as every earlier simulation's worker was
    subprocess.run(
        [sys.executable, "-c", "b = bytearray(400_000_000); b[::4096] = b'x' * len(b[::4096])"],
        check=True,
    )
    code, out, err, wall, usage = bench._run_measured(
        [sys.executable, "-c", "import sys; print('ranked'); sys.stderr.write('note')"]
    )
    assert (code, out, err) == (0, "ranked\n", "note")
    assert 0.0 < wall < 60.0
    assert usage.ru_maxrss / 1024 < 200, usage.ru_maxrss  # MB: an interpreter, not the 400 MB
    code, _, _, _, _ = bench._run_measured([sys.executable, "-c", "raise SystemExit(3)"])
    assert code == 3
