"""Do the reported sigmas match the estimate's scatter? Noise draws of one simulated bag.

``licalib simulate --noise-seed`` draws new sensor noise (IMU white noise and bias walks, LiDAR
range noise and dropouts) for the same motion, mounting, time offset and intrinsics. Calibrating
several such draws gives the estimate's actual scatter, which the reported 1-sigma should cover
(a ratio of at least 1) without being many times larger, and the mean error over the draws,
which shows a bias of the estimator (a mean beyond about ``2 scatter / sqrt(draws)``) that one
bag cannot tell from its own noise.

The reported sigmas also hold what no noise draw varies (the IMU intrinsics held fixed, known
only to ``model.imu_prior``), so ratios above 1 are expected; ratios below 1 are what matters.

Examples::

    .venv/bin/python benchmarks/bench_noise_draws.py --seed 1 --draws 6
    .venv/bin/python benchmarks/bench_noise_draws.py --scenario shake --seed 3 --draws 6 --jobs 2
    .venv/bin/python benchmarks/bench_noise_draws.py --lidar os1-64 --seed 5 --draws 4
    .venv/bin/python benchmarks/bench_noise_draws.py --config my.yaml   # another configuration
    .venv/bin/python benchmarks/bench_noise_draws.py --imu-noise-scale 10 --draws 8  # poor IMU

Each calibration runs in a fresh subprocess.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
from _noise import add_noise_options, noise_spec_kwargs  # noqa: E402

COORDINATES = ("t_x mm", "t_y mm", "t_z mm", "roll deg", "pitch deg", "yaw deg", "dt ms")


def one_draw(args: argparse.Namespace, noise_seed: int, folder: Path) -> dict:
    """Simulate one noise draw, calibrate it; errors and reported sigmas (result units)."""
    import numpy as np

    from licalib_cli.config import load_config
    from licalib_cli.geometry import so3
    from licalib_cli.pipeline import calibrate
    from licalib_cli.simulation import SimulationSpec, simulate

    spec = SimulationSpec(
        scenario=args.scenario,
        lidar=args.lidar,
        duration_s=args.duration,
        seed=args.seed,
        noise_seed=noise_seed,
        intrinsics="none",
        random_time_offset=True,
        random_extrinsic=args.random_extrinsic,
        **noise_spec_kwargs(args.range_noise, args.imu_noise_scale, args.noise_free),
    )
    out = simulate(spec, folder, force=True)
    cfg = load_config(Path(args.config) if args.config else ROOT / "configs" / f"{args.lidar}.yaml")
    t0 = time.perf_counter()
    run = calibrate(out.bag_path, cfg)
    res = run.result
    truth = out.truth.extrinsic_for(res)
    err = np.r_[
        1e3 * (res.extrinsic.translation - truth.translation),
        np.degrees(so3.log(truth.rotation.T @ res.extrinsic.rotation)),
        1e3 * (res.extrinsic.time_offset_s - truth.time_offset_s),
    ]
    u = res.uncertainty
    sigma = np.r_[
        1e3 * np.asarray(u.translation_std_m),
        np.asarray(u.rotation_std_deg),
        1e3 * u.time_offset_std_s,
    ]
    return {
        "noise_seed": noise_seed,
        "error": [float(x) for x in err],
        "sigma": [float(x) for x in sigma],
        "verdict": run.verdict.status,
        "seconds": time.perf_counter() - t0,
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--scenario", default="sinusoid", choices=["sinusoid", "shake", "figure8"])
    p.add_argument("--lidar", default="vlp16", choices=["vlp16", "os1-64"])
    p.add_argument("--seed", type=int, default=1, help="motion, mounting and time offset")
    p.add_argument("--duration", type=float, default=None)
    p.add_argument(
        "--random-extrinsic", action="store_true", help="the seed draws the mounting (any rotation)"
    )
    add_noise_options(p)
    p.add_argument("--config", default=None, help="config file (default: configs/LIDAR.yaml)")
    p.add_argument("--draws", type=int, default=6, help="noise draws (noise seeds 101, 102, ...)")
    p.add_argument("--jobs", type=int, default=1, help="draws at a time")
    p.add_argument("--json", default=None, help="also write the rows to this JSON file")
    p.add_argument("--one", type=int, default=None, help=argparse.SUPPRESS)
    p.add_argument("--workdir", default=None, help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.one is not None:
        print(json.dumps(one_draw(args, args.one, Path(args.workdir))))
        return

    import numpy as np

    base = [
        sys.executable,
        __file__,
        "--scenario",
        args.scenario,
        "--lidar",
        args.lidar,
        "--seed",
        str(args.seed),
    ]
    if args.duration is not None:
        base += ["--duration", str(args.duration)]
    if args.config is not None:
        base += ["--config", str(Path(args.config).resolve())]
    if args.range_noise is not None:
        base += ["--range-noise", str(args.range_noise)]
    if args.imu_noise_scale != 1.0:
        base += ["--imu-noise-scale", str(args.imu_noise_scale)]
    if args.noise_free:
        base.append("--noise-free")
    if args.random_extrinsic:
        base.append("--random-extrinsic")

    def run(noise_seed: int) -> dict:
        with tempfile.TemporaryDirectory() as tmp:
            cmd = [*base, "--one", str(noise_seed), "--workdir", tmp]
            done = subprocess.run(cmd, capture_output=True, text=True, check=False)
        if done.returncode != 0:
            return {"noise_seed": noise_seed, "failed": done.stderr.strip().splitlines()[-1:]}
        row: dict = json.loads(done.stdout.strip().splitlines()[-1])
        err = ", ".join(f"{x:+.3g}" for x in row["error"])
        print(f"noise seed {noise_seed}: {row['verdict']}, errors [{err}]", flush=True)
        return row

    seeds = [101 + k for k in range(args.draws)]
    with ThreadPoolExecutor(max(1, args.jobs)) as pool:
        rows = list(pool.map(run, seeds))
    ok = [r for r in rows if "error" in r]
    for r in rows:
        if "failed" in r:
            print(f"noise seed {r['noise_seed']} failed: {r['failed']}")
    if len(ok) < 2:
        print("fewer than two draws calibrated: no scatter")
        return
    err = np.array([r["error"] for r in ok])
    sig = np.array([r["sigma"] for r in ok])
    scatter = err.std(axis=0, ddof=1)
    mean = err.mean(axis=0)
    print(
        f"\n{args.scenario} {args.lidar} seed {args.seed}, {len(ok)} noise draws "
        f"({sum(r['verdict'] == 'pass' for r in ok)} PASS)"
    )
    print(f"{'':22s}" + "".join(f"{c:>11s}" for c in COORDINATES))
    for label, values in (
        ("mean error", mean),
        ("standard error", scatter / np.sqrt(len(ok))),
        ("scatter", scatter),
        ("mean reported sigma", sig.mean(axis=0)),
        ("sigma / scatter", sig.mean(axis=0) / scatter),
    ):
        print(f"{label:22s}" + "".join(f"{v:11.4g}" for v in values))
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
