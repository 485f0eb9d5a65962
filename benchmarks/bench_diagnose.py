"""Does ``licalib diagnose`` name the effect hidden in a bag, close its gap, and fix the extrinsic?

Cases: each candidate the simulator can hide, alone, on shaking and sinusoid motion (VLP-16 and
OS1-64 in turn), pairs (five of unrelated effects, five of rivals: effects that explain most of
each other's score test), and clean controls. Per run it prints the effects injected and the
effects named, the gap shrink of each named effect's sensor, the extrinsic error before and after
and the wall time; at the end a confusion table (injected against named).

Targets: the right effect(s) named in every case and nothing on the clean controls; the gap of
the effect's sensor shrinks by at least 50 % once it is added (with several effects named, an
effect whose own step closed less counts with the others in: the final model refitted without
it against the final fit; the row keeps both, ``shrink`` and ``share``); the extrinsic after
diagnosis within 0.3 cm / 0.05 deg / 0.1 ms.

Examples::

    .venv/bin/python benchmarks/bench_diagnose.py --jobs 2
    .venv/bin/python benchmarks/bench_diagnose.py --only gyro_scale --list
    .venv/bin/python benchmarks/bench_diagnose.py --jobs 2 --first-seed 500   # new bags
    .venv/bin/python benchmarks/bench_diagnose.py --jobs 2 --imu-rate 100   # a slower IMU
    .venv/bin/python benchmarks/bench_diagnose.py --jobs 2 --duration 20   # longer bags

Sizes: every effect at ``--scale`` (default 3) times its reference size: the paper's table for
the intrinsics, 0.1 deg/s/g g-sensitivity, 50 ppm clock drift, bias walks ten times the
MTi-100's, a 1 % per-point time error (``licalib simulate --effect NAME --effect-scale K``, see
benchmarks/_effects.py and licalib_cli/simulation/effects.py); the IMU effects of
:data:`STRONGER` at five times, the bias walks over 20 s (:data:`LONGER`). Bags are 10 s
otherwise (``--duration``: another length). A case whose effect is not named also prints the
size diagnose says the bag would need to show it, against the RMS injected, or, when it was
tried (a rival that lost, or a refit that did not pay), its test on the final fit: not
significant there, the effects named explain what it showed (the confusion table says "not
shown given the effects named"). At the end: how
many runs end outside 0.3 cm / 0.05 deg / 0.1 ms, against how many an unbiased estimator with
each final fit's solver covariance would (``_information.py``).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parent))

from _effects import INTRINSIC_EFFECTS, SIMULATOR_EFFECTS
from _information import information_bound, outside_limits
from _motion import add_tilt_option, tilt_spec_kwargs
from _rates import add_rate_options, check_rates, rate_spec_kwargs
from _runner import run_cases

SINGLE = [*INTRINSIC_EFFECTS, *SIMULATOR_EFFECTS]
PAIRS = [
    ("gyro_scale", "lidar_range_offset"),
    ("gyro_rotation", "lidar_elevation"),
    ("accel_scale", "lidar_horizontal_offset"),
    ("gyro_misalignment", "imu_clock_drift"),
    ("gyro_bias_walk", "lidar_point_time"),
    # rivals: each explains most of the other's score test, and both are there
    ("lidar_elevation", "lidar_vertical_offset"),
    ("lidar_azimuth", "lidar_horizontal_offset"),
    ("lidar_range_offset", "lidar_range_scale"),
    ("gyro_rotation", "accel_misalignment"),
    ("gyro_misalignment", "g_sensitivity"),
]


STRONGER: dict[str, float] = {
    "gyro_scale": 5.0,
    "gyro_misalignment": 5.0,
    "accel_scale": 5.0,
    "gyro_bias_walk": 5.0,
    "accel_bias_walk": 5.0,
    "imu_clock_drift": 5.0,
}
"""Effects hidden at five times their reference size instead of ``--scale``: at three times,
10 s of data showed them at p 1e-4 to 0.6 (score tests of the 2026-11-25 run in RESULTS.md)."""

LONGER: dict[str, float] = {"gyro_bias_walk": 20.0, "accel_bias_walk": 20.0}
"""Effects hidden in a longer bag: a bias walk's realised drift grows with the square root of
the time and the information about a drift with its cube, so its score test grows with T^2."""


def _size_and_length(
    effects: list[str], scale: float, shortest: float = 10.0
) -> tuple[float, float]:
    """The multiple of the reference sizes and the bag length of a case (one multiple for all
    its effects: the simulator's ``effect_scale``). A pair with a LiDAR intrinsic stays at
    ``scale``: per-beam range offsets at five times the paper's (5 cm RMS) blur the map until
    fewer than a hundred points lie on planes, the base model loses its map and diagnose has to
    free the beams before it can test the IMU's effect (``beams_in_base``). Bags
    last ``shortest`` seconds, or :data:`LONGER`'s length for its effects when that is longer."""
    k = max([STRONGER.get(e, scale) for e in effects] or [scale])
    if any(e.startswith("lidar_") and e != "lidar_point_time" for e in effects):
        k = scale
    return max(k, scale), max([LONGER.get(e, shortest) for e in effects] + [shortest])


def injected_rms(row: dict) -> dict[str, float]:
    """RMS of each injected effect's values in ``diagnose``'s display units."""
    import math

    import numpy as np

    to_display = {  # truth file units -> DISPLAY_UNITS of licalib_cli.pipeline.diagnose
        "gyro_scale": 1e6,
        "accel_scale": 1e6,
        "gyro_bias_walk": math.degrees(1.0),
        "lidar_range_offset": 1e3,
        "lidar_range_scale": 1e6,
        "lidar_vertical_offset": 1e3,
        "lidar_horizontal_offset": 1e3,
        "lidar_point_time": 100.0,
    }
    out = {}
    for name, values in row.get("injected_all", {}).items():
        v = np.asarray(values, dtype=float)
        out[name] = float(np.sqrt(np.mean(v**2))) * to_display.get(name, 1.0) if v.size else 0.0
    return out


def cases(first_seed: int = 200) -> list[dict]:
    """Clean controls, then every effect once, the pairs, then every effect a second time (so
    that a run cut short has covered each effect). ``first_seed`` gives the same cases on other
    bags (the seed decides the mounting, the time offset and the effects' draws)."""
    out = []
    seed = first_seed
    combos = [
        ("shake", "vlp16"),
        ("sinusoid", "os1-64"),
        ("sinusoid", "vlp16"),
        ("shake", "os1-64"),
    ]
    for k in range(4):
        scenario, lidar = combos[k]
        out.append({"effects": [], "scenario": scenario, "lidar": lidar, "seed": seed})
        seed += 1
    singles: list[list[dict]] = [[], []]
    for i, effect in enumerate(SINGLE):
        for j in range(2):
            scenario, lidar = combos[(i + j) % 4]
            singles[j].append(
                {"effects": [effect], "scenario": scenario, "lidar": lidar, "seed": seed}
            )
            seed += 1
    pairs = []
    for i, pair in enumerate(PAIRS):
        scenario, lidar = combos[i % 4]
        pairs.append({"effects": list(pair), "scenario": scenario, "lidar": lidar, "seed": seed})
        seed += 1
    return out + singles[0] + pairs + singles[1]


def named_for(row: dict) -> set[str]:
    """The effects named, a named one that diagnose says this bag does not tell apart from an
    injected one counted as that one (the ambiguity is what the data show)."""
    injected = set(row["effects"])
    out = set()
    for n in row["named"]:
        alike = [e for e in row.get("not_told_apart", {}).get(n, []) if e in injected]
        out.add(alike[0] if n not in injected and alike else n)
    return out


def report(rows: list[dict]) -> None:
    """The confusion table (each injected effect against what was named for it: itself, or
    nothing; each effect named but not injected against "(none injected)") and the count of
    runs missing a target."""
    from licalib_cli.pipeline.fitcheck import EFFECT_P_VALUE

    confusion: Counter = Counter()
    for r in rows:
        injected, named = set(r["effects"]), named_for(r)
        rms = injected_rms(r)
        for e in sorted(injected) or ["(clean)"]:
            shown = r.get("not_shown", {}).get(e)
            quiet = shown is not None and e in rms and rms[e] < shown[0]
            final_p = r.get("final_p", {}).get(e)
            label = "(not named)"
            if quiet:
                label = "(not named, below what the bag shows)"
            elif final_p is not None and final_p >= EFFECT_P_VALUE:
                label = "(not named, not shown given the effects named)"
            alike = [
                n for n in r["named"] if n != e and e in r.get("not_told_apart", {}).get(n, [])
            ]
            hit = f"{alike[0]}, not told apart from {e}" if alike and e not in r["named"] else e
            confusion[(e, hit if e in named else label)] += 1
        for n in sorted(named - injected):
            for e in sorted(injected) or ["(clean)"]:
                confusion[(e, f"{n} (extra)")] += 1
    print("\nConfusion (injected -> named: runs)")
    for (e, n), k in sorted(confusion.items()):
        print(f"  {e:<26} -> {n:<40} {k}")
    bad = [r for r in rows if judge(r)]
    print(f"{len(rows)} runs, {len(bad)} missing a target")
    rivals = [(r, v) for r in rows for v in r.get("rivals", [])]
    if rivals:
        picked = [(r, v) for r, v in rivals if v[3]]
        right = sum(v[0] in r["effects"] for r, v in picked)
        print(
            f"rivals refitted beside the leader at {len(rivals)} steps of "
            f"{len({r['seed'] for r, _ in rivals})} runs (shares "
            f"{min(v[2] for _, v in rivals):.2f}-{max(v[2] for _, v in rivals):.2f}); named in "
            f"its place at {len(picked)}, the injected effect at {right} of them"
        )
    with_info = [r for r in rows if "information" in r["after"]]  # older --jsonl rows lack it
    if with_info:
        info = [r["after"]["information"] for r in with_info]
        outside = sum(outside_limits(r["after"]) for r in with_info)
        print(
            f"outside 0.3 cm / 0.05 deg / 0.1 ms after diagnosis: {outside} of {len(info)} runs; "
            f"expected from each final fit's information (solver covariance, unbiased): "
            f"{sum(i['p_outside'] for i in info):.1f} (time offset beyond 0.1 ms: "
            f"{sum(i['p_time_offset_over'] for i in info):.1f})"
        )


def one_run(case: dict, workdir: Path, scale: float) -> dict:
    import numpy as np
    from _effects import effect_spec_kwargs

    from licalib_cli.config import load_config
    from licalib_cli.geometry import so3
    from licalib_cli.pipeline.diagnose import diagnose
    from licalib_cli.simulation import SimulationSpec, simulate

    scale, duration = _size_and_length(case["effects"], scale, case.get("duration") or 10.0)
    kwargs = effect_spec_kwargs(
        case["effects"], case["lidar"], case["seed"], workdir, scale=scale, sim_scale=scale
    )
    spec = SimulationSpec(
        scenario=case["scenario"],
        lidar=case["lidar"],
        duration_s=duration,
        seed=case["seed"],
        intrinsics="none",
        random_time_offset=True,
        **tilt_spec_kwargs(case),
        **rate_spec_kwargs(case.get("imu_rate"), case.get("lidar_rate")),
        **kwargs,
    )
    out = simulate(spec, workdir / f"run{case['seed']}", force=True)
    t0 = time.perf_counter()
    diag = diagnose(out.bag_path, load_config(None))
    wall = time.perf_counter() - t0

    def err(run: object) -> dict:
        res = run.result  # type: ignore[attr-defined]
        t = out.truth.extrinsic_for(res)
        e = res.extrinsic.error_to(t)
        u = res.uncertainty
        ratio = np.concatenate(
            [
                np.abs(res.extrinsic.translation - t.translation) / np.asarray(u.translation_std_m),
                np.abs(so3.log(t.rotation.T @ res.extrinsic.rotation))
                / np.radians(np.asarray(u.rotation_std_deg)),
                [abs(res.extrinsic.time_offset_s - t.time_offset_s) / u.time_offset_std_s],
            ]
        )
        finite = ratio[np.isfinite(ratio)]
        report = run.fit.report  # type: ignore[attr-defined]
        return {
            "translation_mm": 1e3 * e["translation_m"],
            "rotation_deg": e["rotation_deg"],
            "time_offset_ms": 1e3 * e["time_offset_s"],
            # the largest error per axis in its reported sigmas (not observable axes left out)
            "max_error_over_sigma": float(finite.max()) if finite.size else float("nan"),
            # what the fit's own information allows against the 0.3 cm / 0.05 deg / 0.1 ms
            "information": information_bound(
                list(report.calibration_names), report.covariance, case["seed"]
            ),
        }

    return {
        **case,
        "named": list(diag.effects_found),
        # the beams' blocks that joined a base model which lost its map ("before" is then the
        # base with them)
        "beams_in_base": list(diag.beams_in_base.kept) if diag.beams_in_base else [],
        "shrink": {s.effect: s.shrink for s in diag.steps if s.kept},
        # with the final model's other effects in (when it holds several and the effect's own
        # step closed less than half): its sensor's gap refitted without it -> the final fit's
        "share": {s.effect: s.share for s in diag.steps if s.kept and s.share_before is not None},
        "share_gaps": {
            s.effect: [s.share_before.excess, s.share_after.excess, s.share_before.sigma]
            for s in diag.steps
            if s.kept and s.share_before is not None and s.share_after is not None
        },
        # rivals the bag does not tell apart from a named effect (diagnose says so)
        "not_told_apart": {s.effect: list(s.not_told_apart) for s in diag.steps if s.kept},
        # effects kept as one spread across beams (their free numbers did not pay): the spread
        "spread": {s.effect: s.spread for s in diag.steps if s.kept and np.isfinite(s.spread)},
        # bias walks kept in pieces: how many (and the one linear drift's BIC change)
        "pieces": {
            s.effect: [s.pieces, s.linear_delta_bic] for s in diag.steps if s.kept and s.pieces > 1
        },
        # effects refitted expecting the size their score test showed: [size, BIC held, sized]
        "sized": {
            s.effect: [s.expected_size, s.held_delta_bic, s.sized_delta_bic]
            for s in diag.steps
            if np.isfinite(s.expected_size)
        },
        # rivals refitted beside a step's leader: [rival, leader, share of the leader's score
        # it explains, named in its place]
        "rivals": [
            [s.effect, s.rival_of, s.rival_share, bool(s.kept)] for s in diag.steps if s.rival_of
        ],
        "before": err(diag.base),
        "after": err(diag.final),
        "steps": [
            [
                s.effect,
                s.statistic,
                s.dof,
                s.delta_bic,
                s.kept,
                s.gap_before.excess,
                s.gap_after.excess,
                s.gap_before.sigma,
            ]
            for s in diag.steps
        ],
        # how strongly the base fit's residuals show each injected effect (score test alone,
        # dof, p): below the significance level the data do not show it at that level
        "evidence": {
            e.score.name: [e.statistic_alone, int(e.score.rank), e.score.p_value]
            for e in diag.base.effects
            if e.score.name in case["effects"]
        },
        "twin": {
            s.sensor: [s.chi2_per_sample, s.chi2_spread]
            for s in (diag.base_twin.sensors if diag.base_twin else ())
        },
        "measured": {
            c.sensor: c.chi2_per_sample
            for c in (diag.base.result.consistency.sensors if diag.base.result.consistency else ())
        },
        "injected": {
            e.name: list(e.values)[:3]
            for e in (out.truth.simulation.effects if out.truth.simulation else ())
        },
        "injected_all": {
            e.name: list(e.values)
            for e in (out.truth.simulation.effects if out.truth.simulation else ())
            if e.name in case["effects"]
        },
        # an effect tried and not added: its score test's p-value on the final fit (with the
        # effects added in; at or above the significance level they explain what it showed)
        "final_p": {
            s.effect: s.final_p_value
            for s in diag.steps
            if not s.kept and s.effect not in diag.effects_found
        },
        # the size diagnose says this bag would need to show each candidate it did not add
        "not_shown": {n.effect: [*n.detectable, n.detectable_best[0]] for n in diag.not_shown},
        "scale": scale,
        "duration_s": duration,
        "verdict_before": diag.base.verdict.status,
        "verdict_after": diag.final.verdict.status,
        "reasons_after": list(diag.final.verdict.reasons),
        "seconds": wall,
    }


def _lost_to(row: dict, effect: str) -> str:
    """Why a tried effect whose refit paid was not kept: the rival it was refitted beside and
    whose refit paid more ("" when it was not such a rival)."""
    for rival, leader, _share, kept in row.get("rivals", []):
        if rival == effect and not kept:
            paid = [s[3] for s in row.get("steps", []) if s[0] == leader and s[4]]
            better = f" (BIC change {paid[0]:+.1f})" if paid else ""
            return f", refitted as the rival of {leader}, which paid more{better}"
    return ""


def judge(row: dict) -> list[str]:
    misses = []
    injected = set(row["effects"])
    named = named_for(row)
    if injected != named:
        misses.append(f"named {sorted(named)} for {sorted(injected)}")
    rms = injected_rms(row)
    for effect in sorted(injected - named):
        for step in row.get("steps", []):
            if step[0] == effect and not step[4]:
                misses.append(
                    f"{effect} tried (score {step[1]:.1f} on {step[2]}), BIC change "
                    f"{step[3]:+.1f}: not kept{_lost_to(row, effect)}"
                )
        final_p = row.get("final_p", {}).get(effect)
        if final_p is not None:
            from licalib_cli.pipeline.fitcheck import EFFECT_P_VALUE

            given = "not significant" if final_p >= EFFECT_P_VALUE else "still significant"
            misses.append(
                f"{effect}'s test on the final fit, with the effects named in: p = {final_p:.2g} "
                f"({given})"
            )
        shown = row.get("not_shown", {}).get(effect)
        if shown is not None and effect in rms:
            below = "below" if rms[effect] < shown[0] else "above"
            best = f", best direction {shown[2]:.2g}" if len(shown) > 2 else ""
            misses.append(
                f"{effect} injected {rms[effect]:.2g} {shown[1]} RMS, {below} the "
                f"{shown[0]:.2g} from which diagnose says this bag shows it in any direction{best}"
            )
    for effect, shrink in row["shrink"].items():
        # NaN: the gap was within 3 sigma of its noise (only the score test shows the effect).
        # With several effects named, the gap an effect closes once the others are in (its
        # share) counts: when it was added, another effect's part of the same sensor's gap
        # could still be open.
        share = row.get("share", {}).get(effect)
        closed = share if share is not None else shrink
        if effect in injected and closed == closed and not closed >= 0.5:
            also = f" (with the others in {share:.0%})" if share is not None else ""
            misses.append(f"{effect} gap shrank {shrink:.0%}{also}")
    a = row["after"]
    if outside_limits(a):
        misses.append("extrinsic after diagnosis outside 0.3 cm / 0.05 deg / 0.1 ms")
    z = a.get("max_error_over_sigma", float("nan"))
    if row.get("verdict_after") == "pass" and z > 3.0:
        misses.append(f"wrong PASS after diagnosis: an axis off by {z:.1f} of its sigmas")
    return misses


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--only", default=None, help="run only cases with this effect")
    p.add_argument("--list", action="store_true")
    p.add_argument("--jobs", type=int, default=1)
    p.add_argument("--scale", type=float, default=3.0)
    p.add_argument("--json", default=None)
    p.add_argument("--jsonl", default=None, help="append each row to this file as it comes")
    p.add_argument("--skip", default="", help="seeds not to run (comma separated)")
    p.add_argument("--seeds", type=int, nargs="+", default=None, help="run only these seeds")
    add_tilt_option(p)
    add_rate_options(p)
    p.add_argument(
        "--first-seed",
        type=int,
        default=200,
        help="seed of the first case (the others follow); another value gives new bags",
    )
    p.add_argument(
        "--duration",
        type=float,
        default=10.0,
        help="length of the bags in s (bias walks: at least 20 s; see LONGER)",
    )
    p.add_argument("--report", default=None, help="only print the tables of a --jsonl file")
    p.add_argument("--one", default=None, help=argparse.SUPPRESS)
    p.add_argument("--workdir", default=None, help=argparse.SUPPRESS)
    args = p.parse_args()
    if not args.duration > 0:
        p.error(f"--duration must be a positive number of seconds, not {args.duration}")
    check_rates(p, args)
    if args.report is not None:
        rows = [json.loads(x) for x in Path(args.report).read_text().splitlines() if x.strip()]
        for r in rows:
            print(r["seed"], r["scenario"], r["lidar"], r["effects"], r["named"], judge(r))
        report(rows)
        return
    if args.one is not None:
        row = one_run(json.loads(args.one), Path(args.workdir), args.scale)
        print(json.dumps(row))
        return
    todo = [
        {
            **c,
            "tilt_deg": args.tilt_deg,
            "imu_rate": args.imu_rate,
            "lidar_rate": args.lidar_rate,
            "duration": args.duration,
        }
        for c in cases(args.first_seed)
        if (
            args.only is None
            or args.only in c["effects"]
            or (args.only == "clean" and not c["effects"])
        )
        and str(c["seed"]) not in args.skip.split(",")
        and (args.seeds is None or c["seed"] in args.seeds)
    ]
    if args.list:
        for c in todo:
            print(c)
        return
    rows = []
    with tempfile.TemporaryDirectory() as tmp:

        def command(c: dict) -> list[str]:
            return [
                sys.executable,
                __file__,
                "--one",
                json.dumps(c),
                "--workdir",
                tmp,
                "--scale",
                str(args.scale),
            ]

        for c, row, error in run_cases(todo, command, args.jobs):
            if row is None:
                print(f"seed {c['seed']} {c['effects']}: FAILED {error}", flush=True)
                continue
            rows.append(row)
            if args.jsonl:
                with Path(args.jsonl).open("a") as f:
                    f.write(json.dumps(row) + "\n")
            b, a = row["before"], row["after"]
            misses = judge(row)
            from licalib_cli.sections import p_is

            evidence = " ".join(
                f"{k} score {v[0]:.1f} ({v[1]}) {p_is(v[2], 1)}" for k, v in row["evidence"].items()
            )
            if evidence:
                misses = [*misses, evidence] if misses else misses
            injected = ",".join(row["effects"]) or "none"
            named = (
                ",".join(
                    n
                    + (" [base lost its map]" if n in row.get("beams_in_base", []) else "")
                    + (" [spread]" if n in row.get("spread", {}) else "")
                    + (f" [{row['pieces'][n][0]} pieces]" if n in row.get("pieces", {}) else "")
                    + (f" [sized {row['sized'][n][0]:.0e}]" if n in row.get("sized", {}) else "")
                    + "".join(f" (~{a})" for a in row.get("not_told_apart", {}).get(n, []))
                    + "".join(
                        f" [rival of {r[1]}, {r[2]:.2f}]"
                        for r in row.get("rivals", [])
                        if r[0] == n and r[3]
                    )
                    for n in row["named"]
                )
                or "none"
            )
            print(
                f"{row['seed']} {row['scenario']:<8} {row['lidar']:<6} injected {injected:<40} "
                f"named {named:<40} before {b['translation_mm']:.1f} mm "
                f"{b['rotation_deg']:.3f} deg -> after {a['translation_mm']:.1f} mm "
                f"{a['rotation_deg']:.3f} deg {a['time_offset_ms']:.3f} ms "
                f"{row['verdict_after']} (at most "
                f"{a.get('max_error_over_sigma', float('nan')):.1f} sigma) "
                f"{row['seconds']:.0f} s  {'ok' if not misses else '; '.join(misses)}",
                flush=True,
            )
    report(rows)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
