"""Throughput of ``licalib batch`` and the cost Dask adds per bag.

Simulates a few small bags (a 3 s sinusoid, VLP-16 thinned to 1 deg of azimuth, as the batch
tests; ``--bags`` copies of ``--distinct`` simulations), then:

1. calibrates them all with ``run_batch`` on a local cluster of 1 and of 2 workers (a fresh
   output folder each time) and prints the bags per minute, wall clock from the call to the
   summary, cluster start and stop included;
2. times a local cluster's start and stop;
3. times the scheduler's round trip of a no-op task (``submit`` then ``result``, one at a
   time) and the batch's own overhead per bag: ``run_batch`` with a task that returns at
   once, on ``--noop-bags`` empty stand-in bags, less the cluster's start and stop.

Example::

    .venv/bin/python benchmarks/bench_batch.py --bags 4 --workers 1 2

The machine's load (``os.getloadavg``) is printed with the figures: on a shared machine they
move with it.
"""

from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

CONFIG = Path(__file__).resolve().parents[1] / "configs" / "vlp16.yaml"


def make_bags(root: Path, bags: int, distinct: int, duration_s: float) -> list[Path]:
    from licalib_cli.simulation import SimulationSpec, simulate

    sims = []
    for seed in range(distinct):
        spec = SimulationSpec(
            scenario="sinusoid",
            lidar="vlp16",
            fmt="ros1",
            duration_s=duration_s,
            seed=seed + 4,
            intrinsics="none",
            azimuth_resolution_deg=1.0,
        )
        sims.append(simulate(spec, root / f"sim{seed}").bag_path)
    paths = []
    for i in range(bags):
        path = root / "fleet" / f"rig{i % 2}" / f"run{i}.bag"
        path.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(sims[i % distinct], path)
        paths.append(path)
    return paths


def noop_task(task: object) -> object:
    """A task that returns at once: a refusal, so that nothing is written but the summary."""
    from licalib_cli.batch import TaskOutcome

    return TaskOutcome(result=None, exit_status="error", seconds=0.0, error="No-op.")


def _noop() -> None:
    return None


def throughput(bags: list[Path], root: Path, workers: int) -> dict[str, float]:
    from licalib_cli.batch import read_inputs, run_batch

    jobs = read_inputs([str(b) for b in bags], CONFIG)
    start = time.perf_counter()
    report = run_batch(jobs, root / f"out{workers}", workers=workers, retries=0)
    wall = time.perf_counter() - start
    seconds = [b.calibration_s for b in report.bags if b.status == "calibrated"]
    return {
        "wall_s": wall,
        "bags_per_min": 60.0 * len(bags) / wall,
        "calibrated": float(len(seconds)),
        "mean_task_s": sum(seconds) / max(1, len(seconds)),
    }


def overhead(root: Path, workers: int, round_trips: int, noop_bags: int) -> dict[str, float]:
    from licalib_cli.batch import read_inputs, run_batch
    from licalib_cli.batch.cluster import connect

    start = time.perf_counter()
    with connect(workers=workers) as client:
        started = time.perf_counter()
        client.submit(_noop, pure=False).result()  # a first task warms the worker up
        t0 = time.perf_counter()
        for _ in range(round_trips):
            client.submit(_noop, pure=False).result()
        round_trip = (time.perf_counter() - t0) / round_trips
        closing = time.perf_counter()
    stop = time.perf_counter()
    startup, shutdown = started - start, stop - closing
    for i in range(noop_bags):
        path = root / "noop" / f"b{i}.bag"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(b"x")
    jobs = read_inputs([str(root / "noop" / "*.bag")], CONFIG)
    t0 = time.perf_counter()
    run_batch(jobs, root / "noop_out", workers=workers, retries=0, task=noop_task)
    batch_wall = time.perf_counter() - t0
    return {
        "startup_s": startup,
        "shutdown_s": shutdown,
        "round_trip_ms": 1e3 * round_trip,
        "per_bag_ms": 1e3 * (batch_wall - startup - shutdown) / noop_bags,
        "batch_wall_s": batch_wall,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--bags", type=int, default=4, help="bags calibrated per run")
    parser.add_argument("--distinct", type=int, default=2, help="distinct simulations")
    parser.add_argument("--duration", type=float, default=3.0, help="seconds per bag")
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--round-trips", type=int, default=200)
    parser.add_argument("--noop-bags", type=int, default=100)
    args = parser.parse_args()

    with tempfile.TemporaryDirectory(prefix="bench_batch_") as tmp:
        root = Path(tmp)
        t0 = time.perf_counter()
        bags = make_bags(root, args.bags, args.distinct, args.duration)
        print(
            f"{args.bags} bags ({args.distinct} distinct {args.duration:g} s sinusoids, VLP-16 "
            f"at 1 deg azimuth), simulated in {time.perf_counter() - t0:.1f} s; "
            f"{os.cpu_count()} cores"
        )
        print()
        print("workers  bags/min  wall (s)  calibrated  mean task (s)  load (1 min)")
        for workers in args.workers:
            r = throughput(bags, root, workers)
            load = os.getloadavg()[0]
            print(
                f"{workers:>7}  {r['bags_per_min']:>8.2f}  {r['wall_s']:>8.1f}  "
                f"{int(r['calibrated']):>10}  {r['mean_task_s']:>13.1f}  {load:>12.1f}"
            )
        print()
        o = overhead(root, max(args.workers), args.round_trips, args.noop_bags)
        print(
            f"Local cluster of {max(args.workers)} workers: start {o['startup_s']:.2f} s, "
            f"stop {o['shutdown_s']:.2f} s"
        )
        print(
            f"No-op task round trip (submit -> result, {args.round_trips} in sequence): "
            f"{o['round_trip_ms']:.1f} ms"
        )
        print(
            f"Batch overhead per bag ({args.noop_bags} no-op bags: plan, fingerprints, task, "
            f"summary): {o['per_bag_ms']:.1f} ms (batch {o['batch_wall_s']:.2f} s with the "
            "cluster's start and stop)"
        )
        print(f"Load average (1 min) at the end: {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
