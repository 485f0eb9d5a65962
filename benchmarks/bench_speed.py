"""Wall and CPU time of ``licalib calibrate`` per stage, against the data's own duration.

For every case a bag is simulated with known ground truth (``licalib simulate``'s library API),
then ``calibrate`` runs on it in a fresh process from no initial guess and the script prints,
per case: wall and CPU seconds of every stage (read, odometry, initialisation, the rounds'
steps - points mapped, surfels, associations, problem, solver, summary - and checks), the total
against the data's duration, the accuracy against the truth (translation mm, rotation deg, time
offset ms) and the verdict. ``--lengths`` adds the same motion at several segment lengths and
prints the cost per second of data, which should stay flat (linear cost).

The default cases are the issue's: the 10 s sinusoid (the sample's motion) and the 12 s
hand-held shake with a VLP-16, then the same motions with other seeds, random mountings and lever
arms, random time offsets, an OS1-64, the planar figure-8 and all three bag formats.

Examples::

    # every default case (about 15 bags; the bags are kept in --workdir for a second run)
    .venv/bin/python benchmarks/bench_speed.py --workdir /tmp/speed-bags

    # the same bags with another checkout of licalib (e.g. the code before a change)
    .venv/bin/python benchmarks/bench_speed.py --workdir /tmp/speed-bags --code /tmp/licalib-main

    # linearity: shaking at 5, 10 and 20 s
    .venv/bin/python benchmarks/bench_speed.py --cases shake --lengths 5 10 20

The machine's load average is printed before and after each run: on a shared machine the wall
time grows with the load while the CPU time stays (roughly) what the run costs.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

ROOT = Path(__file__).resolve().parent.parent


@dataclass(frozen=True)
class Case:
    """One simulated bag and the config it is calibrated with."""

    name: str
    scenario: str = "sinusoid"
    lidar: str = "vlp16"
    fmt: str = "ros1"
    duration: float = 10.0
    seed: int = 0
    mounting: str = "A"
    random_extrinsic: bool = False
    random_time_offset: bool = False
    time_offset: float = 0.005

    @property
    def config(self) -> Path:
        return ROOT / "configs" / f"{self.lidar}.yaml"

    @property
    def key(self) -> str:
        return (
            f"{self.scenario}-{self.lidar}-{self.fmt}-{self.duration:g}s-seed{self.seed}"
            f"-{self.mounting}{'-rx' if self.random_extrinsic else ''}"
            f"{'-rt' if self.random_time_offset else f'-t{self.time_offset:g}'}"
        )


CASES: dict[str, Case] = {
    c.name: c
    for c in (
        # the two targets: the bundled 10 s sample and a 12 s hand-held shake
        Case("sample"),
        Case("shake", scenario="shake", duration=12.0, seed=0, time_offset=0.0),
        # not tuned on: other seeds, mountings, lever arms, offsets, LiDARs, formats
        Case("sinusoid-s7-mcap", seed=7, fmt="ros2-mcap", random_extrinsic=True,
             random_time_offset=True),
        Case("shake-s11", scenario="shake", duration=12.0, seed=11, random_extrinsic=True,
             random_time_offset=True),
        Case("shake-s12-db3", scenario="shake", duration=12.0, seed=12, fmt="ros2-db3",
             random_extrinsic=True, random_time_offset=True),
        Case("shake-s13-mcap", scenario="shake", duration=12.0, seed=13, fmt="ros2-mcap",
             random_extrinsic=True, random_time_offset=True),
        Case("shake-os1-s14", scenario="shake", lidar="os1-64", duration=12.0, seed=14,
             fmt="ros2-db3", random_extrinsic=True, random_time_offset=True),
        Case("sinusoid-os1-s15", lidar="os1-64", seed=15, fmt="ros2-mcap"),
        Case("figure8-B-s16", scenario="figure8", seed=16, mounting="B"),
    )
}  # fmt: skip


def simulate_case(case: Case, workdir: Path) -> Path:
    """The case's bag folder (simulated once, then reused from ``workdir``)."""
    from licalib_cli.simulation import SimulationSpec, simulate

    if case.name == "sample":  # the bundled sample (sample_data/README.md)
        out = workdir / "sample"
        out.mkdir(parents=True, exist_ok=True)
        sample = ROOT / "sample_data" / "sinusoid_vlp16"
        (out / "truth.yaml").write_bytes((sample / "truth.yaml").read_bytes())
        (out / "bag_path.txt").write_text(str(sample / "bag.bag"))
        return out
    out = workdir / case.key
    if (out / "truth.yaml").exists():
        return out
    spec = SimulationSpec(
        scenario=case.scenario,
        lidar=case.lidar,
        fmt=case.fmt,
        duration_s=case.duration,
        seed=case.seed,
        time_offset_s=0.0 if case.random_time_offset else case.time_offset,
        intrinsics="none",
        random_extrinsic=case.random_extrinsic,
        random_time_offset=case.random_time_offset,
        mounting=case.mounting,
    )
    result = simulate(spec, out, force=True)
    (out / "bag_path.txt").write_text(str(result.bag_path))
    return out


def observable_translation_mm(run, err_vec) -> float:
    """Norm of the translation error without its components along the directions the run
    reported as not observable (what the calibration claims to know), mm."""
    import numpy as np

    owners = run.solver.information.owners
    idx = [i for i, o in enumerate(owners) if o == "ext.translation"]
    dirs = [d.vector[idx] for d in run.solver.truncated]
    dirs = [v for v in dirs if np.linalg.norm(v) > 0.5]  # mostly a translation direction
    if dirs:
        q, _ = np.linalg.qr(np.stack(dirs, axis=1))
        err_vec = err_vec - q @ (q.T @ err_vec)
    return 1e3 * float(np.linalg.norm(err_vec))


def one_run(folder: Path, config: Path) -> dict:
    """Calibrate one simulated bag in this process; figures as a JSON-able dict."""
    from licalib_cli.config import load_config
    from licalib_cli.pipeline import calibrate
    from licalib_cli.truth import Truth

    try:  # the allocator setting the command line makes at start (older checkouts lack it)
        from licalib_cli.parallel.memory import keep_freed_memory
    except ImportError:
        pass
    else:
        keep_freed_memory()
    bag = Path((folder / "bag_path.txt").read_text())
    truth = Truth.load(folder / "truth.yaml")
    cfg = load_config(config)
    load_before = os.getloadavg()[0]
    wall0, cpu0 = time.perf_counter(), time.process_time()
    run = calibrate(bag, cfg)
    wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
    ref = truth.extrinsic_for(run.result)
    err = run.result.extrinsic.error_to(ref)
    stage_times = getattr(run, "stage_times", None) or {}
    stages = {
        k: [round(v, 3), round(stage_times[k].cpu_s, 3) if k in stage_times else None]
        for k, v in run.timings.items()
    }
    steps: dict[str, list[float]] = {}
    for r in run.rounds:
        for k, t in (getattr(r, "stage_times", None) or {}).items():
            acc = steps.setdefault(k, [0.0, 0.0])
            acc[0] += t.wall_s
            acc[1] += t.cpu_s
    rec = run.result.recording
    imu_t = rec.duration_s if rec is not None else float("nan")
    return {
        "duration_s": float(imu_t),
        "wall_s": wall,
        "cpu_s": cpu,
        "stages": stages,
        "round_steps": {k: [round(a, 3), round(b, 3)] for k, (a, b) in steps.items()},
        "rounds": len(run.rounds),
        "translation_mm": 1e3 * err["translation_m"],
        "translation_observable_mm": observable_translation_mm(
            run, run.result.extrinsic.translation - ref.translation
        ),
        "rotation_deg": err["rotation_deg"],
        "time_offset_ms": 1e3 * err["time_offset_s"],
        "verdict": run.verdict.status,
        "rotation_source": run.initial.rotation_source,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "load_before": load_before,
        "load_after": os.getloadavg()[0],
    }


def _fmt_stage(name: str, wall_cpu: list) -> str:
    wall, cpu = wall_cpu
    return f"{name} {wall:.1f}" + (f"/{cpu:.1f}" if cpu is not None else "")


def print_row(label: str, row: dict) -> None:
    ratio = row["wall_s"] / row["duration_s"]
    print(
        f"{label}: {row['duration_s']:.1f} s of data, wall {row['wall_s']:.1f} s "
        f"({ratio:.2f}x the data), CPU {row['cpu_s']:.1f} s; "
        f"t {row['translation_mm']:.2f} mm (observable part "
        f"{row['translation_observable_mm']:.2f}), r {row['rotation_deg']:.4f} deg, "
        f"dt {row['time_offset_ms']:.3f} ms, {row['verdict']}, {row['rounds']} rounds, "
        f"rotation from {row['rotation_source']}; peak {row['peak_rss_mb']:.0f} MB; "
        f"load {row['load_before']:.1f} -> {row['load_after']:.1f}"
    )
    print(
        "    stages (wall/CPU s): " + ", ".join(_fmt_stage(k, v) for k, v in row["stages"].items())
    )
    if row["round_steps"]:
        print(
            "    rounds' steps (wall/CPU s): "
            + ", ".join(_fmt_stage(k, v) for k, v in row["round_steps"].items())
        )


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--cases", nargs="+", default=list(CASES), choices=list(CASES))
    p.add_argument(
        "--lengths",
        type=float,
        nargs="*",
        default=[],
        help="also run each case at these durations (s), for the cost per second",
    )
    p.add_argument("--workdir", default=None, help="keep the simulated bags here (reused)")
    p.add_argument(
        "--code",
        default=None,
        help="another licalib checkout to time (its licalib_cli goes first on the path)",
    )
    p.add_argument("--repeat", type=int, default=1, help="runs per case (the fastest is shown)")
    p.add_argument("--json", default=None, help="write every row to this JSON file")
    p.add_argument("--one", default=None, help=argparse.SUPPRESS)
    p.add_argument("--config", default=None, help=argparse.SUPPRESS)
    args = p.parse_args()  # fmt: skip
    if args.one is not None:
        print(json.dumps(one_run(Path(args.one), Path(args.config))))
        return
    import tempfile

    tmp = None
    if args.workdir is None:
        tmp = tempfile.TemporaryDirectory()
        workdir = Path(tmp.name)
    else:
        workdir = Path(args.workdir)
        workdir.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ)
    if args.code:
        env["PYTHONPATH"] = os.pathsep.join(
            [str(Path(args.code).resolve()), env.get("PYTHONPATH", "")]
        )
    print(
        f"Machine: {os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f} at the start; "
        f"code: {args.code or ROOT}"
    )
    rows = []
    for name in args.cases:
        base = CASES[name]
        variants = [base] + [
            replace(base, name=f"{name}@{d:g}s", duration=d)
            for d in args.lengths
            if d != base.duration
        ]
        for case in variants:
            folder = simulate_case(case, workdir)
            best = None
            for _ in range(max(args.repeat, 1)):
                cmd = [sys.executable, __file__, "--one", str(folder), "--config", str(case.config)]
                res = subprocess.run(cmd, capture_output=True, text=True, check=False, env=env)
                if res.returncode != 0:
                    tail = res.stderr.strip().splitlines()[-1:] or ["(no message)"]
                    print(f"{case.name}: FAILED: {tail[0]}")
                    break
                row = json.loads(res.stdout.strip().splitlines()[-1])
                if best is None or row["wall_s"] < best["wall_s"]:
                    best = row
            if best is None:
                continue
            best["case"] = case.name
            best["spec"] = asdict(case)
            rows.append(best)
            print_row(case.name, best)
    if args.lengths:
        print("Cost per second of data (wall / CPU s per s):")
        for name in args.cases:
            mine = sorted(
                (r for r in rows if r["spec"]["scenario"] == CASES[name].scenario
                 and r["case"].split("@")[0] == name),
                key=lambda r: r["duration_s"],
            )  # fmt: skip
            print(
                f"  {name}: "
                + ", ".join(
                    f"{r['duration_s']:.0f} s: {r['wall_s'] / r['duration_s']:.2f} / "
                    f"{r['cpu_s'] / r['duration_s']:.2f}"
                    for r in mine
                )
            )
    if rows:
        worst = max(rows, key=lambda r: r["wall_s"] / r["duration_s"])
        ratio = worst["wall_s"] / worst["duration_s"]
        print(
            f"Slowest relative to its data: {worst['case']} at {ratio:.2f}x "
            f"(CPU {worst['cpu_s'] / worst['duration_s']:.2f}x); load average at the end "
            f"{os.getloadavg()[0]:.2f}"
        )
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    if tmp is not None:
        tmp.cleanup()


if __name__ == "__main__":
    main()
