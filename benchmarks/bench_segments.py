"""Segment selection and multi-segment calibration on simulated bags (issue: select-segments).

Parts (all by default; choose with ``--parts``):

* ``walk``: a 120 s walk with four shaking bursts (``licalib simulate --scenario walk``, seed 0;
  the bursts' intervals come from truth.yaml). ``select-segments --length 10 --top 4``: the
  selected windows must overlap the bursts' full-amplitude parts (the middle half of each
  burst: its ``sin^4`` envelope is above 1/4 there) and every window that does must rank above
  every calm window (one that touches no burst). Then ``calibrate --segments auto`` on the same
  selection: the joint error against the truth (target 0.3 cm / 0.05 deg / 0.1 ms) and the
  joint sigma against each segment's own.
* ``planar``: a 20 s planar figure-8 (mounting A) and a 20 s hand-held shaking bag, one 10 s
  window of each at the true extrinsic: the figure-8 window must rank below the shaking one,
  with the vertical translation as its weakest direction.
* ``long``: ranking a long walk (``--long-duration``, default 600 s = 10 minutes of VLP-16 at
  full resolution) with 15 s windows, in a subprocess: wall and CPU time and peak RSS
  (target: at most 60 s on the 2-core machine). ``--long-repeat 6`` ranks an hour instead: the
  walk played six times in a row (``benchmarks/_loop_bag.py``; the motion jumps at the seams),
  for the peak RSS of a one-hour bag.
* ``tilt`` (not run by default): with every intrinsic in the model (``--intrinsics all``; the
  IMU's count as unknown in the metric, the LiDAR's are not part of it), does the metric rank
  windows as the calibration turns out? For each seed of ``--tilt-seeds``
  a 20 s hand-held shake (VLP-16, the simulator's random intrinsic errors, a random mounting
  and time offset) is simulated plain and with ``--tilt-deg 30`` (the same shake); each bag's
  two 10 s windows are ranked with and without the intrinsics in the metric, then calibrated
  alone with ``--intrinsics all``: the error against the truth, the largest error over its
  sigma and the verdict, per window, in the order of the metric. Expected: the tilted windows
  rank above the plain ones and calibrate the extrinsic rotation better. ``--tilt-lidars``
  cycles LiDAR models over the seeds (their shipped config, or the defaults); ``--tilt-joint``
  also calibrates each bag's two windows together (``--segments 0-10,10-20``): the joint error,
  verdict and each segment's verdict alone.
* ``intrinsics`` (not run by default): 30 s sinusoids with the simulator's random intrinsic
  errors (``licalib simulate --scenario sinusoid --duration 30 --seed S --random-time-offset``,
  seeds ``--intrinsics-seeds``), ``calibrate --intrinsics all --segments 0-10,10-20,20-30``: each
  segment's own error, the joint rounds' and the joint result's (after the planes-free
  refinement of the joint problem) against the truth, translation and the mean of the LiDAR
  range offsets (their common mode), with the refinement's time and peak traced memory.
* ``model`` (not run by default): ``calibrate --segments 0-10,10-20 --model auto`` against the
  default (``evident``: the configured model and what a window shows beyond doubt) and the
  configured model alone (``config``), ``--model-modes`` choosing among them, on 20 s walks
  (``--model-seeds``, a random mounting and time offset, the LiDAR thinned to 2 deg of azimuth;
  ``--model-lidars`` cycled over the seeds with their shipped config, ``--model-scenario``
  another motion) with one effect hidden per seed (``--model-effects``, cycled; ``none`` hides
  nothing) at ``--model-effect-scale`` times its reference size. Per bag: what each window's
  diagnosis kept (or what ``evident`` added), the effects the joint calibration estimated, and
  each model's verdict, error and largest error over its sigma. Expected: the hidden effect kept
  by some window (unless the windows show it too weakly: each diagnosis says how large it would
  have to be), nothing on a clean walk, the joint error within 0.3 cm / 0.05 deg / 0.1 ms and
  within 3 of its sigmas.

Examples::

    .venv/bin/python benchmarks/bench_segments.py
    .venv/bin/python benchmarks/bench_segments.py --parts long --long-bag /tmp/walk600/bag.bag
    .venv/bin/python benchmarks/bench_segments.py --parts long --long-bag /tmp/walk600/bag.bag \
        --long-repeat 6 --workdir /tmp/hour
    .venv/bin/python benchmarks/bench_segments.py --parts intrinsics --intrinsics-seeds 3 5
    .venv/bin/python benchmarks/bench_segments.py --parts tilt --tilt-seeds 2811 2812 2813
    .venv/bin/python benchmarks/bench_segments.py --parts model --model-seeds 4201 4202 4203
    .venv/bin/python benchmarks/bench_segments.py --parts tilt --tilt-seeds 2821 2822 2823 \
        --tilt-lidars os1-64 hdl-32 os1-32 --tilt-joint

Bags are simulated into ``--workdir`` (default: a temporary folder) unless given.
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
sys.path.insert(0, str(Path(__file__).resolve().parent))

KNOWN = """\
initialization:
  rotation_rpy_deg: [1.0, 2.0, 5.0]
  translation_m: [0.3, 0.15, 0.05]
  time_offset_s: 0.0
"""


def _simulate(workdir: Path, name: str, **spec: object) -> Path:
    from licalib_cli.simulation import SimulationSpec, simulate

    folder = workdir / name
    if (folder / "bag.bag").exists():
        return folder / "bag.bag"
    t = time.perf_counter()
    spec.setdefault("intrinsics", "none")
    sim = simulate(SimulationSpec(**spec), folder)  # type: ignore[arg-type]
    print(f"simulated {name} in {time.perf_counter() - t:.0f} s", flush=True)
    return sim.bag_path


def _config() -> Path:
    from licalib_cli.config import load_config  # noqa: F401 - the package must import

    return Path(__file__).resolve().parents[1] / "configs" / "vlp16.yaml"


def walk(args: argparse.Namespace, workdir: Path) -> None:
    import numpy as np
    import yaml

    from licalib_cli.config import load_config
    from licalib_cli.pipeline.joint import calibrate_segments
    from licalib_cli.pipeline.segments import select_segments
    from licalib_cli.truth import Truth

    bag = Path(args.walk_bag) if args.walk_bag else _simulate(workdir, "walk", scenario="walk")
    truth_path = bag.parent / "truth.yaml"
    bursts = np.asarray(yaml.safe_load(truth_path.read_text())["scenario"]["bursts_s"])
    full = np.column_stack(
        [bursts[:, 0] + 0.25 * np.diff(bursts)[:, 0], bursts[:, 1] - 0.25 * np.diff(bursts)[:, 0]]
    )
    cfg = load_config(_config())
    t = time.perf_counter()
    cpu = time.process_time()
    sel = select_segments(bag, cfg, args.length, top=args.top)
    print(
        f"\nselect-segments --length {args.length:g} --top {args.top}: "
        f"{time.perf_counter() - t:.1f} s wall, {time.process_time() - cpu:.1f} s CPU "
        f"({', '.join(f'{k} {v:.1f} s' for k, v in sel.timings.items())}); "
        f"common estimate from {sel.estimate.source}"
    )

    def overlap(w, iv: np.ndarray) -> bool:
        return bool(np.any((iv[:, 0] < w.end_s) & (iv[:, 1] > w.start_s)))

    print(f"bursts {bursts.tolist()}, full amplitude {np.round(full, 2).tolist()}")
    print(" rank  window        min sv    kind   selected  weakest direction")
    for w in sel.ranked:
        kind = "burst" if overlap(w, full) else ("ramp" if overlap(w, bursts) else "calm")
        weak = w.weak_directions[0].split(" (singular")[0] if w.weak_directions else ""
        print(
            f" {w.rank:4d}  {w.start_s:5.1f}-{w.end_s:5.1f}  {w.min_singular_value:8.4f}  "
            f"{kind:5s}  {'yes' if w.selected else '':8s}  {weak}"
        )
    burst_vals = [w.min_singular_value for w in sel.windows if overlap(w, full)]
    calm_vals = [w.min_singular_value for w in sel.windows if not overlap(w, bursts)]
    sel_ok = all(overlap(w, full) for w in sel.selected)
    selected_vals = [w.min_singular_value for w in sel.selected]
    selected_above = min(selected_vals) > max(calm_vals)
    rank_ok = min(burst_vals) > max(calm_vals)
    print(
        f"selected windows overlap the bursts' full-amplitude parts: {sel_ok}; each above every "
        f"calm window: {selected_above} (lowest selected {min(selected_vals):.3g}, highest calm "
        f"{max(calm_vals):.3g}); every window touching a full-amplitude part above every calm "
        f"one: {rank_ok} (lowest {min(burst_vals):.3g})"
    )

    t = time.perf_counter()
    cpu = time.process_time()
    chosen = ",".join(f"{w.start_s:g}-{w.end_s:g}" for w in sel.selected)
    run = calibrate_segments(bag, cfg, chosen)
    wall = time.perf_counter() - t
    truth = Truth.load(truth_path)
    err = truth.extrinsic.error_to(run.result.extrinsic)
    unc = run.result.uncertainty
    print(
        f"\ncalibrate --segments {chosen} (the selection above): {wall:.0f} s wall, "
        f"{time.process_time() - cpu:.0f} s CPU "
        f"({', '.join(f'{k} {v:.0f} s' for k, v in run.timings.items())})"
    )
    print(" segment        error t [mm]  rot [deg]  dt [ms]   sigma t [mm]        sigma rot [deg]")
    for e in run.segments.segments:
        from licalib_cli.results import Extrinsic, matrix_from_rpy_deg

        own = Extrinsic(
            matrix_from_rpy_deg(e.rotation_rpy_deg), np.asarray(e.translation), e.time_offset_s
        )
        oe = truth.extrinsic.error_to(own)
        print(
            f" {e.start_s:5.1f}-{e.end_s:5.1f}  {1e3 * oe['translation_m']:10.2f}  "
            f"{oe['rotation_deg']:9.4f}  {1e3 * oe['time_offset_s']:7.3f}   "
            f"{np.round(1e3 * np.asarray(e.translation_std_m), 2)}  "
            f"{np.round(e.rotation_std_deg, 4)}  (off by {e.disagreement_sigmas:.1f} sigma)"
        )
    print(
        f" joint        {1e3 * err['translation_m']:10.2f}  {err['rotation_deg']:9.4f}  "
        f"{1e3 * err['time_offset_s']:7.3f}   "
        f"{np.round(1e3 * np.asarray(unc.translation_std_m), 2)}"
        f"  {np.round(unc.rotation_std_deg, 4)}"
    )
    within = (
        err["translation_m"] <= 0.003
        and err["rotation_deg"] <= 0.05
        and err["time_offset_s"] <= 1e-4
    )
    smaller = all(
        np.all(np.asarray(unc.translation_std_m) < np.asarray(e.translation_std_m))
        and np.all(np.asarray(unc.rotation_std_deg) < np.asarray(e.rotation_std_deg))
        for e in run.segments.segments
    )
    print(
        f"joint within 0.3 cm / 0.05 deg / 0.1 ms: {within}; joint sigma below every segment's "
        f"own: {smaller}; verdict {run.result.verdict.status}"
    )


def planar(args: argparse.Namespace, workdir: Path) -> None:
    from licalib_cli.config import load_config
    from licalib_cli.pipeline.segments import select_segments

    cfg_path = workdir / "known.yaml"
    cfg_path.write_text(KNOWN)
    cfg = load_config(cfg_path)
    out = {}
    for name, scenario in (("figure8", "figure8"), ("shake", "shake")):
        bag = _simulate(workdir, name, scenario=scenario, duration_s=20.0, seed=1)
        sel = select_segments(bag, cfg, 10.0, top=1)
        best = sel.ranked[0]
        out[name] = best
        weak = best.weak_directions[0] if best.weak_directions else ""
        print(
            f"{name:8s} best window {best.start_s:.0f}-{best.end_s:.0f} s: min sv "
            f"{best.min_singular_value:.4g}, weakest: {weak}"
        )
    f8, sh = out["figure8"], out["shake"]
    vertical = "ext.translation along [" in f8.weak_directions[0] and f8.weak_directions[0].split(
        "ext.translation along ["
    )[1].split("]")[0].split(", ")[2].lstrip("-") in (
        "1.00",
        "0.99",
        "0.98",
    )
    print(
        f"figure-8 ranks below shaking: {f8.min_singular_value < sh.min_singular_value}; its "
        f"weakest direction is the vertical translation: {vertical}"
    )


_LAUNCHER = """
import json, os, subprocess, sys
proc = subprocess.Popen(json.loads(sys.argv[1]))
_, status, usage = os.wait4(proc.pid, 0)
code = os.waitstatus_to_exitcode(status)
with open(sys.argv[2], "w") as f:
    json.dump([code, usage.ru_utime, usage.ru_stime, usage.ru_maxrss], f)
"""


def _run_measured(cmd: list[str]) -> tuple[int, str, str, float, float, float]:
    """Run ``cmd``: its exit code, output, error output, wall time, CPU seconds and peak RSS
    (MB), the last two of that process alone.

    Linux keeps a process's high-water RSS across ``exec`` and counts the memory of its parent
    at the fork in it, so a command started from this process (gigabytes after the simulations
    and calibrations before it) would report this process's peak as its own (2389 MB for a
    ranking that peaked at 587 MB), and ``RUSAGE_CHILDREN`` is the largest of every child ever
    waited for. A small launcher process starts the command instead and reports its usage.
    """
    with (
        tempfile.TemporaryFile("w+") as out,
        tempfile.TemporaryFile("w+") as err,
        tempfile.TemporaryDirectory() as tmp,
    ):
        usage_file = Path(tmp) / "usage.json"
        t = time.perf_counter()
        subprocess.run(
            [sys.executable, "-c", _LAUNCHER, json.dumps(cmd), str(usage_file)],
            stdout=out,
            stderr=err,
            text=True,
            check=True,
        )
        wall = time.perf_counter() - t
        code, utime, stime, maxrss_kb = json.loads(usage_file.read_text())
        out.seek(0)
        err.seek(0)
        return code, out.read(), err.read(), wall, utime + stime, maxrss_kb / 1024


def long_run(args: argparse.Namespace, workdir: Path) -> None:
    bag = (
        Path(args.long_bag)
        if args.long_bag
        else _simulate(workdir, "long", scenario="walk", duration_s=args.long_duration, seed=1)
    )
    if args.long_repeat > 1:
        from _loop_bag import loop_bag

        looped = workdir / f"long-x{args.long_repeat}" / "bag.bag"
        if not looped.exists():
            t = time.perf_counter()
            loop_bag(bag, looped, args.long_repeat)
            print(f"wrote {looped} ({args.long_repeat} passes) in {time.perf_counter() - t:.0f} s")
        bag = looped
    size = sum(p.stat().st_size for p in ([bag] if bag.is_file() else bag.rglob("*")))
    cmd = [
        sys.executable,
        "-m",
        "licalib_cli",
        "select-segments",
        str(bag),
        "-c",
        str(_config()),
        "--json",
    ]
    returncode, stdout, stderr, wall, cpu, peak_mb = _run_measured(cmd)
    if returncode != 0:
        print(stderr[-2000:])
        raise SystemExit(returncode)
    data = json.loads(stdout)
    print(
        f"\nlong bag {bag} ({size / 1e9:.2f} GB, {len(data['segments'])} windows of 15 s): "
        f"{wall:.1f} s wall, {cpu:.1f} s CPU, peak RSS {peak_mb:.0f} MB; "
        f"stages {data['timings_s']}"
    )
    top = [(s["start_s"], s["end_s"]) for s in data["segments"] if s["selected"]]
    print(f"selected {top}")


def _intrinsics_row(label: str, state, ref, true_mean: float) -> None:
    import numpy as np

    from licalib_cli.geometry.so3 import log as so3_log

    err_t = np.linalg.norm(state.t_imu_lidar - ref.translation)
    rot = np.degrees(np.linalg.norm(so3_log(ref.rotation.T @ state.R_imu_lidar)))
    mean = float(np.mean(state.lidar_intrinsics.range_offset))
    print(
        f" {label:14s} {1e3 * err_t:7.2f}  {rot:9.4f}  {1e3 * mean:+17.2f}  "
        f"{1e3 * (mean - true_mean):+14.2f}"
    )


def intrinsics(args: argparse.Namespace, workdir: Path) -> None:
    import tracemalloc

    import numpy as np

    import licalib_cli.pipeline.joint as joint
    from licalib_cli.config import INTRINSIC_PRESETS, load_config
    from licalib_cli.simulation import SimulationSpec, simulate
    from licalib_cli.truth import Truth

    imu_blocks, lidar_blocks = INTRINSIC_PRESETS["all"]
    cfg = load_config(_config(), {"model.imu": list(imu_blocks), "model.lidar": list(lidar_blocks)})
    refine = joint.refine_segments_with_planes
    seen: dict = {}

    def traced(states, inputs, free, lm):
        seen["rounds"] = states[0]  # the joint rounds' estimate
        tracemalloc.start()
        try:
            seen["refined"] = refine(states, inputs, free, lm)
        finally:
            seen["peak_mb"] = tracemalloc.get_traced_memory()[1] / 1e6
            tracemalloc.stop()
        return seen["refined"]

    joint.refine_segments_with_planes = traced
    try:
        for seed in args.intrinsics_seeds:
            folder = workdir / f"sinusoid30-{seed}"
            if not (folder / "bag.bag").exists():
                spec = SimulationSpec(
                    scenario="sinusoid", duration_s=30.0, seed=seed, random_time_offset=True
                )
                simulate(spec, folder)
            truth = Truth.load(folder / "truth.yaml")
            seen.clear()
            t = time.perf_counter()
            cpu = time.process_time()
            run = joint.calibrate_segments(folder / "bag.bag", cfg, args.intrinsics_segments)
            wall = time.perf_counter() - t
            ref = truth.extrinsic_for(run.result)
            true_mean = float(np.mean(truth.lidar_intrinsics.range_offset))
            print(
                f"\nseed {seed}: calibrate --intrinsics all --segments "
                f"{args.intrinsics_segments}: {wall:.0f} s wall, "
                f"{time.process_time() - cpu:.0f} s CPU "
                f"({', '.join(f'{k} {v:.0f} s' for k, v in run.timings.items())}); "
                f"true mean range offset {1e3 * true_mean:+.2f} mm"
            )
            print(" estimate        t [mm]  rot [deg]  offsets mean [mm]  its error [mm]")
            for r, (a, b) in zip(run.runs, run.windows, strict=True):
                _intrinsics_row(f"{a:g}-{b:g} s alone", r.state, ref, true_mean)
            if "rounds" in seen:
                _intrinsics_row("joint rounds", seen["rounds"], ref, true_mean)
            _intrinsics_row("joint", run.states[0], ref, true_mean)
            unc = run.result.uncertainty
            if unc is not None:
                sig_t = np.asarray(unc.translation_std_m)
                err_t = np.abs(run.result.extrinsic.translation - ref.translation)
                seg_t = [np.asarray(r.result.uncertainty.translation_std_m) for r in run.runs]
                print(
                    f" joint sigma t {np.round(1e3 * sig_t, 2)} mm (segments' smallest "
                    f"{np.round(1e3 * np.min(seg_t, axis=0), 2)}), |error| / sigma "
                    f"{np.round(err_t / sig_t, 2)}"
                )
            refined = seen.get("refined")
            if refined is not None:
                print(
                    f" planes-free refinement: {refined.steps} steps, cost "
                    f"{refined.cost_start:.1f} -> {refined.cost_end:.1f}, {refined.seconds:.1f} s, "
                    f"traced peak {seen['peak_mb']:.0f} MB; verdict {run.result.verdict.status}"
                )
    finally:
        joint.refine_segments_with_planes = refine
    print(f"peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB")


def _lidar_config(lidar: str) -> Path | None:
    """The shipped config of a LiDAR model, or None (the defaults) for one without."""
    path = Path(__file__).resolve().parents[1] / "configs" / f"{lidar}.yaml"
    return path if path.exists() else None


def _errors(truth, result) -> tuple[float, float, float, float]:
    """Translation (mm), rotation (deg), time offset (ms) errors and the largest error over
    its reported sigma."""
    import numpy as np

    d = truth.extrinsic_for(result).moved_to(result.extrinsic)
    unc = result.uncertainty
    sd = np.concatenate(
        [
            np.asarray(unc.translation_std_m),
            np.radians(np.asarray(unc.rotation_std_deg)),
            [unc.time_offset_std_s],
        ]
    )
    return (
        1e3 * float(np.linalg.norm(d[:3])),
        float(np.degrees(np.linalg.norm(d[3:6]))),
        1e3 * abs(float(d[6])),
        float(np.max(np.abs(d) / sd)),
    )


def tilt(args: argparse.Namespace, workdir: Path) -> None:
    from licalib_cli.config import INTRINSIC_PRESETS, load_config
    from licalib_cli.pipeline import calibrate
    from licalib_cli.pipeline.joint import calibrate_segments
    from licalib_cli.pipeline.segments import select_segments
    from licalib_cli.truth import Truth

    imu_blocks, lidar_blocks = INTRINSIC_PRESETS["all"]
    model = {"model.imu": list(imu_blocks), "model.lidar": list(lidar_blocks)}
    print(
        "\nwindows of 10 s, metric with the IMU intrinsics unknown (and without), then "
        "calibrate --intrinsics all on each window alone"
        + (" and on both together (--segments 0-10,10-20)" if args.tilt_joint else "")
    )
    print(
        " seed  lidar    tilt  window  metric imu  metric none  error t [mm]  rot [deg]  "
        "dt [ms]  max err/sigma  verdict"
    )
    summary = []
    for k, seed in enumerate(args.tilt_seeds):
        lidar = args.tilt_lidars[k % len(args.tilt_lidars)]
        config = _lidar_config(lidar)
        rows = []
        joints = []
        for amplitude in (0.0, 30.0):
            name = f"shake20-{seed}-tilt{amplitude:g}" + ("" if lidar == "vlp16" else f"-{lidar}")
            bag = _simulate(
                workdir,
                name,
                scenario="shake",
                lidar=lidar,
                duration_s=20.0,
                seed=seed,
                intrinsics="random",
                random_extrinsic=True,
                random_time_offset=True,
                tilt_deg=amplitude,
            )
            truth = Truth.load(bag.parent / "truth.yaml")
            with_imu = select_segments(bag, load_config(config, model), 10.0).windows
            without = select_segments(bag, load_config(config), 10.0).windows
            for w, w0 in zip(with_imu, without, strict=True):
                cfg = load_config(
                    config,
                    {**model, "bag.start_s": w.start_s, "bag.duration_s": w.end_s - w.start_s},
                )
                res = calibrate(bag, cfg).result
                rows.append(
                    (
                        w.min_singular_value,
                        amplitude,
                        f"{w.start_s:.0f}-{w.end_s:.0f}",
                        w0.min_singular_value,
                        *_errors(truth, res),
                        res.verdict.status,
                    )
                )
            if args.tilt_joint:
                run = calibrate_segments(bag, load_config(config, model), "0-10,10-20")
                alone = "/".join(e.verdict for e in run.segments.segments)
                joints.append(
                    (amplitude, *_errors(truth, run.result), run.result.verdict.status, alone)
                )
        rows.sort(key=lambda r: -r[0])
        for m, amp, win, m0, et, er, ec, ratio, verdict in rows:
            print(
                f" {seed:4d}  {lidar:7s}  {amp:4.0f}  {win:6s}  {m:10.3g}  {m0:11.3g}  {et:12.2f}  "
                f"{er:9.4f}  {ec:7.3f}  {ratio:13.2f}  {verdict}"
            )
        for amp, et, er, ec, ratio, verdict, alone in joints:
            print(
                f" {seed:4d}  {lidar:7s}  {amp:4.0f}  joint   {'':10s}  {'':11s}  {et:12.2f}  "
                f"{er:9.4f}  {ec:7.3f}  {ratio:13.2f}  {verdict} (alone {alone})"
            )
        tilted_first = all(r[1] > 0 for r in rows[:2])
        better = min(r[5] for r in rows if r[1] > 0) <= min(r[5] for r in rows if r[1] == 0)
        summary.append((seed, tilted_first, better))
    for seed, first, better in summary:
        print(
            f"seed {seed}: tilted windows ranked first: {first}; best tilted rotation error at "
            f"most the best plain one: {better}"
        )


def _shown_from(effect: str, truth, diagnoses) -> str:
    """The hidden effect's size against the size from which each window's diagnosis says its
    data show it (diagnose's own figure, in its display units)."""
    from bench_diagnose import injected_rms

    values = {
        e.name: list(e.values) for e in (truth.simulation.effects if truth.simulation else ())
    }
    rms = injected_rms({"injected_all": {effect: values.get(effect, [])}}).get(effect)
    parts = []
    for k, diag in enumerate(diagnoses, start=1):
        shown = next((n for n in diag.not_shown if n.effect == effect), None)
        if shown is not None:
            size, unit = shown.detectable
            parts.append(f"window {k} shows it from {size:.2g} {unit}")
    injected = f"injected {rms:.2g} RMS" if rms is not None else "injected"
    return injected + (", " + ", ".join(parts) if parts else "")


def model(args: argparse.Namespace, workdir: Path) -> None:
    from licalib_cli.config import load_config
    from licalib_cli.pipeline.joint import calibrate_segments
    from licalib_cli.truth import Truth

    print(
        f"\n20 s {args.model_scenario}s, --segments 0-10,10-20: --model auto (each window "
        "diagnosed, the joint "
        "model every effect any window kept), evident (the configured model and what a window "
        "shows beyond doubt) and config (the configured model)"
    )
    print(
        " seed  lidar   hidden                   model    kept (window 1 | window 2) or added      "
        "t [mm]  rot [deg]  dt [ms]  err/sigma  verdict  wall [s]"
    )
    misses = []
    for k, seed in enumerate(args.model_seeds):
        effect = args.model_effects[k % len(args.model_effects)]
        hidden = () if effect == "none" else (effect,)
        lidar = args.model_lidars[k % len(args.model_lidars)]
        scenario = args.model_scenario
        bag = _simulate(
            workdir,
            f"{scenario}20-{seed}-{effect}" + ("" if lidar == "vlp16" else f"-{lidar}"),
            scenario=scenario,
            lidar=lidar,
            duration_s=20.0,
            seed=seed,
            azimuth_resolution_deg=2.0,
            random_extrinsic=True,
            random_time_offset=True,
            effects=hidden,
            effect_scale=args.model_effect_scale,
        )
        truth = Truth.load(bag.parent / "truth.yaml")
        for mode in args.model_modes:
            auto = mode == "auto"
            t = time.perf_counter()
            exact = {"model.add_evident_effects": False} if mode == "config" else {}
            cfg = load_config(_lidar_config(lidar), exact)
            run = calibrate_segments(bag, cfg, "0-10,10-20", model_auto=auto)
            wall = time.perf_counter() - t
            et, er, ec, ratio = _errors(truth, run.result)
            kept = "-"
            if run.model is not None:
                kept = " | ".join(",".join(d.effects_found) or "none" for d in run.model.diagnoses)
            elif run.result.model is not None and run.result.model.added:
                from bench_consistency import added_label

                kept = "added " + ",".join(added_label(a) for a in run.result.model.added)
            verdict = run.result.verdict.status
            print(
                f" {seed:4d}  {lidar:6s}  {effect:23s}  {mode:7s}  "
                f"{kept:38s}  "
                f"{et:6.2f}  {er:9.4f}  {ec:7.3f}  {ratio:9.2f}  {verdict:7s}  {wall:8.1f}",
                flush=True,
            )
            if auto:
                assert run.model is not None
                found = set(run.model.effects)
                if hidden and not set(hidden) <= found:
                    misses.append(
                        f"{seed}: {effect} not kept (kept {sorted(found)}); "
                        + _shown_from(effect, truth, run.model.diagnoses)
                    )
                if not hidden and found:
                    misses.append(f"{seed}: clean walk, kept {sorted(found)}")
                for w, d in enumerate(run.model.diagnoses, start=1):
                    extra = sorted(set(d.effects_found) - set(hidden))
                    if hidden and extra:
                        misses.append(f"{seed}: window {w} kept {extra}, not hidden")
                if et > 3.0 or er > 0.05 or ec > 0.1:
                    misses.append(f"{seed}: joint error {et:.2f} mm / {er:.4f} deg / {ec:.3f} ms")
                if ratio > 3.0:
                    misses.append(f"{seed}: joint error {ratio:.2f} of its sigmas")
    print(f"{len(args.model_seeds)} bags, {len(misses)} misses with --model auto")
    for m in misses:
        print("  " + m)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--parts", nargs="+", default=["walk", "planar", "long"])
    p.add_argument("--workdir", default=None)
    p.add_argument("--walk-bag", default=None, help="an existing 120 s walk bag (truth beside)")
    p.add_argument("--long-bag", default=None, help="an existing long bag")
    p.add_argument("--long-duration", type=float, default=600.0)
    p.add_argument(
        "--long-repeat",
        type=int,
        default=1,
        help="play the long bag this many times in a row (6: one hour from the 10-minute walk)",
    )
    p.add_argument("--length", type=float, default=10.0)
    p.add_argument("--top", type=int, default=4)
    p.add_argument("--intrinsics-seeds", type=int, nargs="+", default=[3, 5])
    p.add_argument("--intrinsics-segments", default="0-10,10-20,20-30")
    p.add_argument("--tilt-seeds", type=int, nargs="+", default=[2811, 2812, 2813])
    p.add_argument("--model-seeds", type=int, nargs="+", default=[4201, 4202, 4203, 4204])
    p.add_argument(
        "--model-effects",
        nargs="+",
        default=["none", "lidar_range_offset", "lidar_elevation", "gyro_scale"],
        help="effects hidden, cycled over the seeds (none: a clean walk)",
    )
    p.add_argument("--model-effect-scale", type=float, default=3.0)
    p.add_argument(
        "--model-modes",
        nargs="+",
        default=["auto", "evident", "config"],
        choices=["auto", "evident", "config"],
        help="calibrate --model of each run: auto (every window diagnosed), evident (the "
        "default: the configured model plus what a window shows beyond doubt), config (exactly "
        "the configured model)",
    )
    p.add_argument("--model-lidars", nargs="+", default=["vlp16"], help="cycled over the seeds")
    p.add_argument("--model-scenario", default="walk", help="the simulator's motion")
    p.add_argument("--tilt-lidars", nargs="+", default=["vlp16"], help="cycled over the seeds")
    p.add_argument(
        "--tilt-joint",
        action="store_true",
        help="also calibrate each bag's two windows together (--segments 0-10,10-20)",
    )
    args = p.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        workdir = Path(args.workdir) if args.workdir else Path(tmp)
        workdir.mkdir(parents=True, exist_ok=True)
        for part in args.parts:
            parts = {
                "walk": walk,
                "planar": planar,
                "long": long_run,
                "intrinsics": intrinsics,
                "tilt": tilt,
                "model": model,
            }
            parts[part](args, workdir)


if __name__ == "__main__":
    main()
