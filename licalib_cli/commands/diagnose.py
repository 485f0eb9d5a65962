"""``licalib diagnose``: which effects does the model lack? Add them one by one, show each gap
shrink. Thin wiring: parse, load the config, one call to
:func:`licalib_cli.pipeline.diagnose.diagnose`, render."""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import typer
from rich.table import Table

from licalib_cli.commands.options import (
    INPUT_PANEL,
    BagArgument,
    ConfigOption,
    DurationOption,
    ImuTopicOption,
    LidarTopicOption,
    SetOption,
    StartOption,
    input_overrides,
    settings_of,
)
from licalib_cli.commands.render import VERDICT_COLOURS, console, reason_lines
from licalib_cli.config import dump_config, load_config
from licalib_cli.errors import ConfigError
from licalib_cli.results import (
    check_not_an_input,
    create_folder,
    dump_yaml,
    write_text_atomic,
)
from licalib_cli.sections import p_is, p_text

_IO = INPUT_PANEL
_OUT = "Output"


def _num(x: float, digits: int = 6) -> float | None:
    v = float(x)
    if not math.isfinite(v):
        return None
    return float(f"{v:.{digits}g}")


def _unpaid_dict(u: Any) -> dict[str, Any] | None:
    if u is None:
        return None
    return {
        "coordinates": u.coordinates,
        "bic_penalty_per_coordinate": _num(u.log_n, 4),
        "sigmas_each": _num(u.sigmas_each, 3),
        "sigmas_to_pay": _num(u.sigmas_to_pay, 3),
        "data_factor": _num(u.data_factor, 3),
    }


def _spread_dict(s: Any) -> dict[str, Any] | None:
    """A per-beam effect refitted as one spread across beams: the spread (printed units), its
    BIC change and whether it was kept so; None when not tried."""
    if not math.isfinite(s.spread):
        return None
    from licalib_cli.consistency.power import display_size

    size, unit = display_size(s.effect, s.spread)
    return {
        "value": _num(size, 4),
        "unit": unit,
        "delta_bic": _num(s.spread_delta_bic),
        "kept": bool(s.kept),
    }


def spread_sentence(s: Any) -> str | None:
    """How a per-beam effect fared as one spread across beams (None when not tried)."""
    if not math.isfinite(s.spread):
        return None
    from licalib_cli.consistency.power import display_size

    size, unit = display_size(s.effect, s.spread)
    coordinates = len(s.estimate)
    if s.kept:
        return (
            f"{s.effect} was added as one spread across beams: as {coordinates} free numbers it "
            f"did not pay (BIC {s.delta_bic:+.0f}); as numbers drawn from a spread of "
            f"{size:.3g} {unit} (estimated from this bag, model.lidar_spread) it does (BIC "
            f"{s.spread_delta_bic:+.0f}, one parameter). Each beam's value is drawn toward "
            "nominal as far as the data leave it uncertain; its sigma says how far."
        )
    return (
        f"As one spread across beams ({size:.3g} {unit}) {s.effect} did not pay either (BIC "
        f"{s.spread_delta_bic:+.0f})."
    )


def pieces_sentence(s: Any) -> str | None:
    """How a bias walk kept in pieces fared against one linear drift (None otherwise)."""
    if s.pieces <= 1 or not s.kept:
        return None
    assert s.after is not None
    piece_s = 2.0 * s.after.state.t_ref_s / s.pieces
    return (
        f"{s.effect} was added as a bias that is linear over each of {s.pieces} pieces of "
        f"{piece_s:.1f} s (model.bias_walk_piece_s): one linear drift over the recording "
        f"changed the BIC by {s.linear_delta_bic:+.0f}, the pieces by {s.delta_bic:+.0f}."
    )


def size_sentence(s: Any) -> str | None:
    """How an effect held at its characteristic scale fared refitted expecting the size its
    score test showed (None when not tried, :mod:`licalib_cli.pipeline.effect_size`)."""
    from licalib_cli.consistency.power import display_size

    if not math.isfinite(s.expected_size):
        return None
    size, unit = display_size(s.effect, s.expected_size)
    expecting = f"refitted expecting {size:.3g} {unit} per coordinate (model.expected_size)"
    if s.kept:
        return (
            f"{s.effect} was held at nominal by the truncated SVD at its built-in scale and did "
            f"not pay (BIC {s.held_delta_bic:+.0f}), although its score test put it well above "
            f"that scale; {expecting}, it was estimated and pays (BIC {s.sized_delta_bic:+.0f})."
        )
    return (
        f"{s.effect}, {expecting} as its score test suggests, did not pay either (BIC "
        f"{s.sized_delta_bic:+.0f})."
    )


def unpaid_sentence(s: Any) -> str | None:
    """Why a significant effect was not added, and what data would add it (None unless its
    refit did not pay, :attr:`~licalib_cli.pipeline.diagnose.DiagnosisStep.unpaid`)."""
    u = s.unpaid
    if u is None:
        return None
    if u.coordinates == 1:
        part = f"its number is about {u.sigmas_each:.1f} of its sigma from nominal, and pays"
    else:
        part = (
            f"each of its {u.coordinates} numbers is about {u.sigmas_each:.1f} of its sigma from "
            "nominal on average, and one pays"
        )
    if math.isfinite(u.data_factor):
        seen_by = (
            "points that see it: a longer recording, or --segments over more of the bag, with "
            "surfels.max_points, the cap on a round's points, raised to keep them"
            if s.gap_before.sensor == "lidar"
            else "samples that see it: a longer recording, or --segments over more of the bag"
        )
        more = (
            f"It would pay with about {u.data_factor:.1f} times the information this bag holds "
            f"about it (more {seen_by})"
        )
    else:
        more = "The refit gained no more than fitting noise does"
    apart = (
        f"; this bag does not tell it from {' or '.join(s.not_told_apart)}"
        if s.not_told_apart
        else ""
    )
    return (
        f"{s.effect} shows in this bag (score {s.statistic:.0f} on {s.dof}, "
        f"{p_is(s.p_value, 1)}{apart}) but was not added: {part} the BIC penalty "
        f"(ln n = {u.log_n:.1f}) from about {u.sigmas_to_pay:.1f} (BIC {s.delta_bic:+.0f} with "
        f"it). {more}; with it the extrinsic moved {1e3 * s.moved_translation_m:.2f} mm / "
        f"{s.moved_rotation_deg:.4f} deg / {1e3 * s.moved_time_offset_s:.3f} ms."
    )


def rival_sentence(s: Any) -> str | None:
    """The sentence for a kept effect refitted as the rival of the step's leading candidate and
    picked in its place (None otherwise, or when the bag does not tell them apart)."""
    if not (s.kept and s.rival_of) or s.not_told_apart:
        return None
    share = (
        f"freed with it, {s.effect} explains {100.0 * s.rival_share:.0f} % of its score"
        if math.isfinite(s.rival_share)
        else f"{s.effect} explains most of its score"
    )
    better = (
        f"on the same data its BIC is {-s.rival_delta_bic:.1f} lower"
        if s.rival_delta_bic < 0.0
        else f"it pays its BIC ({s.delta_bic:+.1f}) where {s.rival_of} does not"
    )
    led = f"{s.effect} was named in place of {s.rival_of}, whose score test led"
    return f"{led}: {share}, and {better}."


def retried_sentence(s: Any) -> str | None:
    """The sentence for a rival tried again once the effect it lost to was kept (None for any
    other step)."""
    if not s.retried_after:
        return None
    first = s.retried_after
    outcome = (
        f"it paid too (BIC {s.delta_bic:+.1f}): both are in the model"
        if s.kept
        else f"it did not pay (BIC {s.delta_bic:+.1f})"
    )
    return (
        f"{s.effect} lost to {first} as its rival, and was tried again with {first} in: its "
        f"score test was still {s.statistic:.1f} on {s.dof} degrees of freedom; {outcome}."
    )


def beams_in_base_sentence(b: Any) -> str | None:
    """What a base model that lost its map did with the beams (None when it held its map)."""
    if b is None:
        return None
    where = b.reason.split(":")[0]
    kept = ", ".join(
        f"{e} (BIC {b.delta_bic[e]:+.1f} with it)" if e in b.delta_bic else e for e in b.kept
    )
    dropped = ", ".join(f"{e} (BIC {b.delta_bic[e]:+.1f})" for e in b.dropped)
    text = (
        f"The base model lost its map ({where}): beams that disagree blur it. The beams' "
        f"intrinsics joined the base model: {kept or 'none'} kept"
    )
    if dropped:
        text += f"; {dropped} dropped, the data do not need them"
    if b.lost_without:
        text += f"; without {b.lost_without} the map was lost again"
    return text + "."


def diagnosis_dict(diag: Any) -> dict[str, Any]:
    """The diagnosis as plain data (the JSON and ``diagnosis.yaml`` content)."""
    steps = []
    for s in diag.steps:
        steps.append(
            {
                "effect": s.effect,
                "statistic": _num(s.statistic),
                "dof": s.dof,
                "p_value": _num(s.p_value, 3),
                "delta_bic": _num(s.delta_bic),
                "kept": s.kept,
                "dropped_for": list(s.dropped_for),
                "drop_delta_bic": _num(s.drop_delta_bic),
                "not_told_apart": list(s.not_told_apart),
                "rival_delta_bic": _num(s.rival_delta_bic),
                "estimate": {k: _num(v[0]) for k, v in s.estimate.items()},
                "sigma": {k: _num(v[1]) for k, v in s.estimate.items()},
                "held": list(s.held),
                "rival_named": s.rival_named or None,
                "rival_of": s.rival_of or None,
                "rival_share": _num(s.rival_share, 3),
                "retried_after": s.retried_after or None,
                "final_p_value": _num(s.final_p_value, 3),
                "unpaid": _unpaid_dict(s.unpaid),
                "spread": _spread_dict(s),
                "pieces": s.pieces,
                "linear_delta_bic": _num(s.linear_delta_bic),
                "expected_size": _num(s.expected_size),
                "held_delta_bic": _num(s.held_delta_bic),
                "sized_delta_bic": _num(s.sized_delta_bic),
                "gap_before": _gap_dict(s.gap_before),
                "gap_after": _gap_dict(s.gap_after),
                "gap_shrink": _num(s.shrink, 3),
                # with the final model's other effects in: without it -> with it
                "share_gap_before": _gap_dict(s.share_before) if s.share_before else None,
                "share_gap_after": _gap_dict(s.share_after) if s.share_after else None,
                "share_shrink": _num(s.share, 3),
                "extrinsic_moved": {
                    "translation_m": _num(s.moved_translation_m),
                    "rotation_deg": _num(s.moved_rotation_deg),
                    "time_offset_s": _num(s.moved_time_offset_s),
                },
            }
        )
    not_shown = []
    for n in diag.not_shown:
        size, unit = n.detectable
        not_shown.append(
            {
                "effect": n.effect,
                "statistic": _num(n.statistic),
                "dof": n.dof,
                "p_value": _num(n.p_value, 3),
                "detectable_rms": _num(size, 3),
                "detectable_rms_best": _num(n.detectable_best[0], 3),
                "unit": unit,
            }
        )
    residuals = {"base": _residuals(diag.base, diag.base_twin)}
    if diag.effects_found:
        residuals["final"] = _residuals(diag.final, diag.final_twin)
    b = diag.beams_in_base
    return {
        "effects_found": list(diag.effects_found),
        "beams_in_base": None
        if b is None
        else {
            "reason": b.reason,
            "freed": list(b.freed),
            "kept": list(b.kept),
            "delta_bic": {k: _num(v) for k, v in b.delta_bic.items()},
            "lost_without": b.lost_without or None,
        },
        "steps": steps,
        "not_shown": not_shown,
        "residuals": residuals,
        "base_verdict": diag.base.verdict.status,
        "verdict": diag.final.verdict.status,
        "calibration": diag.final.result.to_dict(),
    }


def _finite(x: Any) -> Any:
    """``x`` with every non-finite float replaced by None (JSON has no inf)."""
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_finite(v) for v in x]
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def _patterns(check: Any) -> dict[str, Any]:
    return {p.feature: _num(p.explained, 3) for p in check.patterns}


def _residuals(run: Any, twin: Any) -> list[dict[str, Any]]:
    """Per sensor: the fit's residual statistics next to its twin recording's."""
    consistency = run.result.consistency
    out = []
    for c in consistency.sensors if consistency is not None else ():
        t = twin.sensor(c.sensor) if twin is not None else None
        row: dict[str, Any] = {
            "sensor": c.sensor,
            "unit": c.unit,
            "measured": {
                "chi2_per_sample": _num(c.chi2_per_sample),
                "rms": _num(c.rms),
                "explained_by": _patterns(c),
            },
            "twin": None,
        }
        if t is not None:
            row["twin"] = {
                "chi2_per_sample": _num(t.chi2_per_sample),
                "chi2_spread": _num(t.chi2_spread, 3),
                "rms": _num(t.rms),
                "explained_by": _patterns(t.check),
                "recordings": twin.realisations,
            }
            row["gap"] = _num(c.chi2_per_sample - t.chi2_per_sample)
        out.append(row)
    return out


def _gap_text(s: Any) -> str:
    """A step's gap before and after it, and with the final model's other effects in."""
    text = f"{s.gap_before.sensor}: {s.gap_before.excess:+.3f} -> {s.gap_after.excess:+.3f}"
    if s.share_before is not None and s.share_after is not None:
        text += (
            f"; with the other effects in {s.share_before.excess:+.3f} -> "
            f"{s.share_after.excess:+.3f}"
        )
    return text


def _gap_dict(g: Any) -> dict[str, Any]:
    out = {
        "sensor": g.sensor,
        "chi2_per_sample": _num(g.chi2_per_sample),
        "expected": _num(g.expected),
        "twin_chi2_per_sample": _num(g.twin_chi2_per_sample),
        "twin_spread": _num(g.twin_spread, 3),
        "reference": g.reference_source,
        "excess": _num(g.excess),
        "excess_sigma": _num(g.sigma, 3),
        "rms": _num(g.rms),
        "twin_rms": _num(g.twin_rms),
    }
    if math.isfinite(g.map_entropy):
        out["map_entropy"] = _num(g.map_entropy)
    return out


def _residual_table(title: str, run: Any, twin: Any) -> Table:
    """Per sensor: chi-square per sample and RMS, measured and on the twin, and the pattern
    that explains most of the measured residuals (its share there, and on the twin)."""
    table = Table(title=title)
    for name in ("sensor", "chi2/n", "twin", "gap", "RMS (twin)", "main pattern (twin)"):
        table.add_column(name)
    for row in _residuals(run, twin):
        m, t = row["measured"], row["twin"]
        patterns = sorted(m["explained_by"].items(), key=lambda kv: -(kv[1] or 0.0))
        pattern = "-"
        if patterns and (patterns[0][1] or 0.0) > 0.0:
            feature, share = patterns[0]
            twin_share = t["explained_by"].get(feature) if t else None
            pattern = f"{feature} {100 * share:.1f}%"
            if twin_share is not None:
                pattern += f" ({100 * twin_share:.1f}%)"
        unit = row["unit"]
        table.add_row(
            row["sensor"],
            f"{m['chi2_per_sample']:.3f}",
            f"{t['chi2_per_sample']:.3f}" if t else "-",
            f"{row['gap']:+.3f}" if t else "-",
            f"{m['rms']:.3g} ({t['rms']:.3g}) {unit}" if t else f"{m['rms']:.3g} {unit}",
            pattern,
        )
    return table


def steps_table(steps: Sequence[Any]) -> Table:
    """The diagnosis steps as a table, one row per effect tried (a rival tried again has two)."""
    table = Table(title="Effects the base model lacks, strongest first")
    # a narrow console folds the names rather than cut them: lidar_range_scale and
    # lidar_range_offset both end "lidar_ra..." at 80 columns
    table.add_column("effect", overflow="fold")
    for name in (
        "score (dof)",
        "p",
        "BIC change",
        "gap before -> after",
        "extrinsic moved",
        "kept",
    ):
        table.add_column(name)
    for s in steps:
        table.add_row(
            s.effect,
            f"{s.statistic:.0f} ({s.dof})",
            p_text(s.p_value, 1),
            f"{s.delta_bic:+.0f}"
            + (f", spread {s.spread_delta_bic:+.0f}" if math.isfinite(s.spread) else "")
            + (f" in {s.pieces} pieces" if s.pieces > 1 else ""),
            _gap_text(s),
            f"{1e3 * s.moved_translation_m:.2f} mm / {s.moved_rotation_deg:.4f} deg / "
            f"{1e3 * s.moved_time_offset_s:.3f} ms",
            "yes" if s.kept else ("dropped" if s.dropped_for else "no"),
        )
    return table


def render_diagnosis(diag: Any) -> None:
    """The residuals against the twin, the steps as a table, then the effects kept and the
    final verdict."""
    out = console()
    if (beams := beams_in_base_sentence(diag.beams_in_base)) is not None:
        out.print(beams)
    out.print(
        _residual_table(
            "Base model: residuals measured and on its twin recording",
            diag.base,
            diag.base_twin,
        )
    )
    table = steps_table(diag.steps)
    if diag.steps:
        out.print(table)
    if diag.effects_found:
        out.print(
            _residual_table(
                "With the effects: residuals measured and on its twin recording",
                diag.final,
                diag.final_twin,
            )
        )
    found = ", ".join(diag.effects_found) or "none"
    out.print(f"Effects added to the model: {found}")
    for s in diag.steps:
        if s.dropped_for:
            they = " and ".join(s.dropped_for)
            verb = "does" if len(s.dropped_for) == 1 else "do"
            out.print(
                f"{s.effect} was dropped again: once {they} joined the model it explained "
                f"nothing {they} {verb} not (on the final fit's data the BIC is "
                f"{s.drop_delta_bic:.1f} higher with it than without)."
            )
    for s in diag.steps:
        if s.kept and s.not_told_apart:
            out.print(
                f"This bag does not tell {s.effect} from {' or '.join(s.not_told_apart)}: "
                "each one's score test with the other freed is not significant "
                f"(BIC on the same data {s.rival_delta_bic:+.1f}); it shows an effect of the "
                "kind, not which one."
            )
        elif (picked := rival_sentence(s)) is not None:
            out.print(picked)
        if (again := retried_sentence(s)) is not None:
            out.print(again)
    for s in diag.steps:
        sentence, spread = unpaid_sentence(s), spread_sentence(s)
        if sentence is not None:
            out.print(sentence if spread is None else f"{sentence} {spread}")
        elif s.kept and spread is not None:
            out.print(spread)
        if (sized := size_sentence(s)) is not None:
            out.print(sized)
        if (pieces := pieces_sentence(s)) is not None:
            out.print(pieces)
    for s in diag.steps:
        if s.held:
            shown = ", ".join(s.held[:3]) + (
                f" and {len(s.held) - 3} more" if len(s.held) > 3 else ""
            )
            them, their = ("them", "their") if len(s.held) > 1 else ("it", "its")
            out.print(
                f"The refit with {s.effect} could not estimate {shown}: this bag determines "
                f"{them} worse than the characteristic scale, so the truncated SVD held {them} "
                f"near {their} starting value; the sigma shown is that scale, not a measurement, "
                f"and the BIC sees no gain from {them}."
            )
    if diag.not_shown:
        from licalib_cli.pipeline.diagnose import DETECTION_POWER

        quiet = Table(
            title="Not shown by this bag: the size (RMS per axis or beam) from which it would "
            f"be named {DETECTION_POWER:.0%} of the time"
        )
        for name in ("effect", "score (dof)", "in any direction", "in its best direction"):
            quiet.add_column(name)
        for n in diag.not_shown:
            size, unit = n.detectable
            best = n.detectable_best[0]
            quiet.add_row(
                n.effect,
                f"{n.statistic:.1f} ({n.dof})",
                f"{size:.2g} {unit}" if math.isfinite(size) else "not determinable from this bag",
                f"{best:.2g} {unit}" if math.isfinite(best) else "-",
            )
        out.print(quiet)
    colour = VERDICT_COLOURS
    v0, v1 = diag.base.verdict.status, diag.final.verdict.status
    base = "base model"
    if diag.beams_in_base is not None:  # the base that held its map is the one with the beams
        base = f"base model with {', '.join(diag.beams_in_base.kept) or 'the beams'}"
    out.print(
        f"Verdict: {base} [{colour[v0]}]{v0.upper()}[/], with the effects "
        f"[bold {colour[v1]}]{v1.upper()}[/]"
    )
    for line in reason_lines(diag.final.verdict.reasons):
        out.print(line)


def diagnose_command(
    bag: BagArgument,
    config: ConfigOption = None,
    settings: SetOption = None,
    imu_topic: ImuTopicOption = None,
    lidar_topic: LidarTopicOption = None,
    start: StartOption = None,
    duration: DurationOption = None,
    candidates: list[str] | None = typer.Option(
        None,
        "--candidates",
        help="Consider only these effects (repeatable); default all.",
        rich_help_panel=_IO,
    ),
    max_effects: int | None = typer.Option(
        None, "--max-effects", min=0, help="Add at most this many effects.", rich_help_panel=_IO
    ),
    out: Path | None = typer.Option(
        None,
        "--out",
        "-o",
        metavar="DIR",
        help="Write diagnosis.yaml, the final calibration.yaml and (with --plots) figures here.",
        rich_help_panel=_OUT,
    ),
    as_json: bool = typer.Option(
        False, "--json", help="Print one JSON object instead of tables.", rich_help_panel=_OUT
    ),
    plots: bool = typer.Option(
        False,
        "--plots",
        help="Write the residual patterns into the -o folder.",
        rich_help_panel=_OUT,
    ),
) -> None:
    """Find effects the model lacks (score tests), add each that pays (BIC), show the gap shrink."""
    from licalib_cli.commands.calibrate import RichProgress
    from licalib_cli.pipeline.diagnose import CANDIDATES, diagnose

    cfg = load_config(
        config,
        input_overrides(imu_topic, lidar_topic, start, duration),
        settings_of(settings),
    )
    if candidates:
        unknown = [c for c in candidates if c not in CANDIDATES]
        if unknown:
            msg = f"Unknown candidate effect {unknown[0]!r}; choose from {', '.join(CANDIDATES)}."
            raise ConfigError(msg)
    if plots and out is None:
        msg = "--plots writes into the -o folder; give -o DIR too."
        raise ConfigError(msg)
    if out is not None:
        if out.exists() and not out.is_dir():
            msg = f"-o needs a folder, but {out} is a file; give a folder path."
            raise ConfigError(msg)
        create_folder(out, "The output folder", "give a writable folder to -o")
        inputs = [("the input bag", bag), ("the config file", config)]
        for name in ("diagnosis.yaml", "calibration.yaml", "calibration.config.yaml"):
            check_not_an_input(out / name, inputs, f"The output {out / name} (written into -o)")
    progress = RichProgress() if not as_json else None
    try:
        diag = diagnose(bag, cfg, tuple(candidates or ()) or None, max_effects, progress)
    finally:
        if progress is not None:
            progress.close()
    data = diagnosis_dict(diag)
    if out is not None:
        write_text_atomic(
            out / "diagnosis.yaml", dump_yaml({k: v for k, v in data.items() if k != "calibration"})
        )
        diag.final.result.save(out / "calibration.yaml")
        write_text_atomic(out / "calibration.config.yaml", dump_config(diag.config or cfg))
        if plots:
            from licalib_cli.plots import save_diagnosis_plots

            save_diagnosis_plots(diag, out)
    if as_json:
        typer.echo(json.dumps(_finite(data), allow_nan=False))
        return
    render_diagnosis(diag)
    if out is not None:
        console().print(f"Written: {out / 'diagnosis.yaml'}, {out / 'calibration.yaml'}")
