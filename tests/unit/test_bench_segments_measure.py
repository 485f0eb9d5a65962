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
    """Neither this process's own peak (a child counts its parent's memory at the fork in its
    high-water mark, across the exec) nor an earlier, larger child's is the command's."""
    bench = _bench_segments()
    grow = "b = bytearray(400_000_000); b[::4096] = b'x' * len(b[::4096])"
    subprocess.run([sys.executable, "-c", grow], check=True)  # a larger child waited for first
    ballast = bytearray(300_000_000)
    ballast[::4096] = b"x" * len(ballast[::4096])  # and this process 300 MB larger
    code, out, err, wall, cpu, peak_mb = bench._run_measured(
        [sys.executable, "-c", "import sys; print('ranked'); sys.stderr.write('note')"]
    )
    assert (code, out, err) == (0, "ranked\n", "note")
    assert 0.0 < wall < 60.0 and 0.0 < cpu < 60.0
    assert peak_mb < 150, peak_mb  # an interpreter, not 300 or 400 MB
    code, _, _, _, _, peak_mb = bench._run_measured(
        [sys.executable, "-c", "b = bytearray(200_000_000); b[::4096] = b'x' * len(b[::4096])"]
    )
    assert code == 0 and 200 < peak_mb < 350, peak_mb  # its own 200 MB counted
    code, _, _, _, _, _ = bench._run_measured([sys.executable, "-c", "raise SystemExit(3)"])
    assert code == 3
    del ballast
