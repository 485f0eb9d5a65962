"""End-to-end accuracy and speed of ``licalib calibrate`` on simulated bags.

For each seed, simulate a bag with known ground truth (``licalib simulate``'s library API), run the
calibration from no initial guess (identity rotation, zero translation, zero time offset) and print
the errors against the truth, the stage timings and the peak memory.

Examples::

    # The paper's sinusoidal case, 5 seeds (issue target: <= 3 mm, 0.05 deg, 0.1 ms; <= 15 s)
    .venv/bin/python benchmarks/bench_calibrate.py --seeds 0 1 2 3 4

    # Random mountings, shaking motion, OS1-64, ROS2 mcap
    .venv/bin/python benchmarks/bench_calibrate.py --scenario shake --random-extrinsic \\
        --random-time-offset --lidar os1-64 --format ros2-mcap --seeds 0 1 2

Each run happens in a fresh subprocess so that its peak memory is its own.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


def observable_translation_error(run, truth) -> float:
    """Norm of the translation error with its components along truncated (unobservable)
    translation directions removed: what the calibration claims to know."""
    import numpy as np

    owners = run.solver.information.owners
    idx = [i for i, o in enumerate(owners) if o == "ext.translation"]
    err = run.result.extrinsic.translation - truth.translation
    dirs = [d.vector[idx] for d in run.solver.truncated]
    dirs = [v for v in dirs if np.linalg.norm(v) > 0.5]  # mostly a translation direction
    if dirs:
        q, _ = np.linalg.qr(np.stack(dirs, axis=1))
        err = err - q @ (q.T @ err)
    return float(np.linalg.norm(err))


def one_run(args: argparse.Namespace, seed: int, workdir: Path) -> dict:
    from licalib_cli.config import load_config
    from licalib_cli.pipeline import calibrate
    from licalib_cli.simulation import SimulationSpec, simulate

    spec = SimulationSpec(
        scenario=args.scenario,
        lidar=args.lidar,
        fmt=args.format,
        duration_s=args.duration,
        seed=seed,
        time_offset_s=0.0 if args.random_time_offset else args.time_offset,
        intrinsics="none",
        random_extrinsic=args.random_extrinsic,
        random_time_offset=args.random_time_offset,
        mounting=args.mounting,
    )
    t = time.perf_counter()
    out = simulate(spec, workdir / f"seed{seed}", force=True)
    sim_s = time.perf_counter() - t
    cfg = load_config(Path(args.config) if args.config else None)
    t = time.perf_counter()
    run = calibrate(out.bag_path, cfg)
    wall = time.perf_counter() - t
    assert run.result.recording is not None and run.result.observability is not None
    truth = out.truth.extrinsic_for(run.result)
    err = run.result.extrinsic.error_to(truth)
    return {
        "seed": seed,
        "translation_mm": 1e3 * err["translation_m"],
        "translation_observable_mm": 1e3 * observable_translation_error(run, truth),
        "rotation_deg": err["rotation_deg"],
        "time_offset_ms": 1e3 * err["time_offset_s"],
        "verdict": run.verdict.status,
        "unobservable": list(run.result.observability.unobservable),
        "calibrate_s": wall,
        "simulate_s": sim_s,
        "stages": {k: round(v, 2) for k, v in run.timings.items()},
        "rounds": len(run.rounds),
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    p.add_argument("--scenario", default="sinusoid")
    p.add_argument("--lidar", default="vlp16")
    p.add_argument("--format", default="ros1")
    p.add_argument("--duration", type=float, default=10.0)
    p.add_argument("--time-offset", type=float, default=0.005)
    p.add_argument("--random-extrinsic", action="store_true")
    p.add_argument("--random-time-offset", action="store_true", help="within +-50 ms")
    p.add_argument("--mounting", default="A")
    p.add_argument("--config", default=None, help="calibration config YAML")
    p.add_argument("--one", type=int, default=None, help=argparse.SUPPRESS)
    p.add_argument("--workdir", default=None, help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.one is not None:
        print(json.dumps(one_run(args, args.one, Path(args.workdir))))
        return
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in args.seeds:
            cmd = [sys.executable, __file__, *sys.argv[1:], "--one", str(seed), "--workdir", tmp]
            res = subprocess.run(cmd, capture_output=True, text=True, check=False)
            if res.returncode != 0:
                print(f"seed {seed}: FAILED\n{res.stderr.strip().splitlines()[-1:]}")
                continue
            row = json.loads(res.stdout.strip().splitlines()[-1])
            rows.append(row)
            print(
                f"seed {seed}: t {row['translation_mm']:.2f} mm "
                f"(observable part {row['translation_observable_mm']:.2f})  "
                f"r {row['rotation_deg']:.4f} deg  "
                f"dt {row['time_offset_ms']:.3f} ms  verdict {row['verdict']}  "
                f"calibrate {row['calibrate_s']:.1f} s {row['stages']}  "
                f"peak {row['peak_rss_mb']:.0f} MB  rounds {row['rounds']}"
            )
            for text in row["unobservable"]:
                print(f"    not observable: {text}")
    if rows:
        worst = {
            k: max(r[k] for r in rows)
            for k in (
                "translation_mm",
                "translation_observable_mm",
                "rotation_deg",
                "time_offset_ms",
                "calibrate_s",
                "peak_rss_mb",
            )
        }
        print("worst: " + ", ".join(f"{k} {v:.4g}" for k, v in worst.items()))


if __name__ == "__main__":
    main()
