"""``calibrate --segments``: run the multi-segment calibration and show each segment's estimate
next to the joint one (the paper's Table segment_mit)."""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from rich.markup import escape
from rich.table import Table

from licalib_cli.commands.render import console
from licalib_cli.config import CalibConfig, dump_config
from licalib_cli.errors import VerdictFailure
from licalib_cli.results import (
    check_not_an_input,
    input_files,
    rpy_deg_from_matrix,
    write_text_atomic,
)

if TYPE_CHECKING:
    from licalib_cli.pipeline.joint import JointRun
    from licalib_cli.pipeline.segments_model import SegmentsModel
    from licalib_cli.report.data import ReportData
    from licalib_cli.sections import AddedEffect
    from licalib_cli.truth import Truth


def render_segments(run: JointRun, truth: Truth | None = None) -> Table:
    """One row per segment (calibrated alone) and one for the joint estimate."""
    table = Table(
        title="T_imu_lidar per segment (calibrated alone) and jointly, largest 1-sigma in "
        "brackets; time offset alone -> in the joint problem"
    )
    for col in ("segment", "t, mm", "roll/pitch/yaw, deg", "time offset, ms", "sigmas off"):
        table.add_column(col, justify="left" if col == "segment" else "right")

    def t_text(t: np.ndarray, s: tuple[float, ...]) -> str:
        return " ".join(f"{1e3 * v:+.1f}" for v in t) + f" ({1e3 * max(s):.2f})"

    def r_text(rot: np.ndarray, s: tuple[float, ...]) -> str:
        rpy = rpy_deg_from_matrix(rot)
        return " ".join(f"{v:+.3f}" for v in rpy) + f" ({max(s):.3f})"

    for e in run.segments.segments:
        from licalib_cli.results import matrix_from_rpy_deg

        flag = f"{e.disagreement_sigmas:.1f}" + (" DISAGREES" if e.disagrees else "")
        if e.started_from is not None:
            flag += f" (started from seg{e.started_from})"
        table.add_row(
            f"{e.start_s:g}-{e.end_s:g} s",
            t_text(np.asarray(e.translation), e.translation_std_m),
            r_text(matrix_from_rpy_deg(e.rotation_rpy_deg), e.rotation_std_deg),
            f"{1e3 * e.time_offset_s:+.3f} ({1e3 * e.time_offset_std_s:.3f}) -> "
            f"{1e3 * e.joint_time_offset_s:+.3f}",
            flag,
        )
    ext = run.result.extrinsic
    unc = run.result.uncertainty
    assert unc is not None
    table.add_row(
        "joint",
        t_text(ext.translation, unc.translation_std_m),
        r_text(ext.rotation, unc.rotation_std_deg),
        f"{1e3 * ext.time_offset_s:+.3f} ({1e3 * unc.time_offset_std_s:.3f})",
        "",
        style="bold",
    )
    if truth is not None:
        tr = truth.extrinsic
        table.add_row(
            "truth",
            " ".join(f"{1e3 * v:+.1f}" for v in tr.translation),
            " ".join(f"{v:+.3f}" for v in rpy_deg_from_matrix(tr.rotation)),
            f"{1e3 * tr.time_offset_s:+.3f}",
            "",
        )
    return table


@dataclass(frozen=True)
class SegmentOutputs:
    """Where ``calibrate --segments`` writes.

    Attributes:
        result: the result file (``-o``).
        config: the resolved configuration beside it.
        map_file: ``--map``: one map per segment (:func:`segment_map_path`), each window's
            points mapped with the joint calibration and its trajectory in the joint estimate.
        map_before: ``--map-before``: the same with each segment's initial guess. The segments'
            maps are not in one frame (each segment's trajectory starts its own), so they are
            not merged.
        report: ``--report``: the HTML report of the joint result (the joint estimate with each
            segment's own beside it, and each window's own fit, motion and map figures).
        plots: ``--plots``: :func:`~licalib_cli.plots.save_segment_plots`.
        inputs: the files no output may overwrite (label, path), for the report data of the
            windows, whose number is known only after the selection.
    """

    result: Path
    config: Path
    map_file: Path | None = None
    map_before: Path | None = None
    report: Path | None = None
    plots: Path | None = None
    inputs: tuple[tuple[str, Path | None], ...] = ()


def run_segments(
    bag: Path,
    cfg: CalibConfig,
    segments: str,
    outputs: SegmentOutputs,
    truth: Truth | None,
    model_auto: bool = False,
) -> JointRun:
    """Calibrate over the segments, write the result, its config and the outputs asked for,
    print the table (with ``model_auto``, each window's diagnosis and the model chosen first).

    Raises:
        VerdictFailure: the joint verdict is fail (the result is written for inspection).
    """
    from licalib_cli.commands.calibrate import RichProgress
    from licalib_cli.pipeline.joint import calibrate_segments

    out, config_out, report = outputs.result, outputs.config, outputs.report
    progress = RichProgress()
    try:
        run = calibrate_segments(bag, cfg, segments, progress, model_auto=model_auto)
    finally:
        progress.close()
    run.result.save(out)
    # with --model auto, the model the diagnoses arrived at: calibrating with it estimates it
    used = run.config if run.config is not None else cfg
    config_text = dump_config(used)
    write_text_atomic(config_out, config_text)
    con = console()
    if run.model is not None:
        _render_model(run.model)
    con.print(render_segments(run, truth))
    if truth is not None:
        err = truth.extrinsic.error_to(run.result.extrinsic)
        con.print(
            f"Joint error against truth: translation {1e3 * err['translation_m']:.2f} mm, "
            f"rotation {err['rotation_deg']:.4f} deg, time offset "
            f"{1e3 * err['time_offset_s']:.3f} ms"
        )
    model = run.result.model
    if model is not None and model.added:
        for line in added_notes(model.added):
            con.print(f"Note: {escape(line)}")
    verdict = run.result.verdict
    assert verdict is not None
    for reason in verdict.reasons:
        con.print(f"- {escape(reason)}")
    con.print(f"Verdict: {verdict.status.upper()}")
    stages = ", ".join(f"{k} {v:.1f} s" for k, v in run.timings.items())
    con.print(f"Stages: {stages}")
    con.print(f"Result: {out}  (resolved config: {config_out})")
    data, windows = _write_report_data(run, used, outputs, truth, config_text)
    if report is not None:
        from licalib_cli.report import write_report

        write_report(report, run.result, data, str(out), windows)
        con.print(f"Report: {report}")
    _write_segment_maps(run, cfg, outputs.map_file, outputs.map_before)
    if outputs.plots is not None:
        from licalib_cli.plots import save_segment_plots

        files = save_segment_plots(run, outputs.plots)
        con.print("Plots: " + ", ".join(str(f) for f in files))
    if verdict.status == "fail":
        msg = f"The verdict is FAIL; the result in {out} is for inspection only."
        raise VerdictFailure(msg)
    return run


def added_notes(added: Sequence[AddedEffect]) -> list[str]:
    """The notes on the effects added to every segment because one showed them beyond doubt,
    and on an added effect's close rival (refitted in its place in every segment)."""
    them = "it" if len(added) == 1 else "them"
    a = added[0]
    notes = [
        "a segment showed "
        + " and ".join(f"{e.effect} ({e.statistic:.0f} on {e.dof} dof)" for e in added)
        + f" beyond doubt; every segment estimated {them} (BIC {a.delta_bic:+.0f}; a segment's "
        f"extrinsic moved up to {1e3 * a.moved_translation_m:.2f} mm). The resolved config "
        f"estimates {them}; --model config keeps to the config's model."
    ]
    for e in added:
        if e.rival and e.not_told_apart:
            notes.append(
                f"no segment tells {e.effect} from {e.rival}: with either estimated, the other's "
                f"score test is no longer significant. Both were refitted in every segment; "
                f"{e.effect} fit the same data better (BIC {e.rival_delta_bic:+.0f} summed over "
                "the segments) and is estimated. Its numbers stand for an effect either one "
                "explains; a motion that excites more axes tells them apart, and licalib "
                "diagnose on a segment shows both."
            )
        elif e.rival:
            notes.append(
                f"{e.rival} could stand in for {e.effect}; refitted in its place in every "
                f"segment, it fit the same data worse (BIC {-e.rival_delta_bic:+.0f} summed over "
                "the segments)."
            )
    return notes


def _window_label(path: Path, index: int | str) -> str:
    return f"The report data of seg{index} that calibrate writes next to the result, {path},"


def check_window_outputs(out: Path, inputs: Sequence[tuple[str, Path | None]]) -> None:
    """Refuse, before anything is read, an input that a window's report data of ``calibrate
    --segments`` would overwrite: any ``<stem>.segK.report-data.npz`` beside the result ``out``
    (how many windows there are is known only once they are chosen).

    Raises:
        ConfigError: an input (or a file of an input folder, or what a link points to) bears
            such a name in the result's folder.
    """
    out = Path(out)
    name = re.compile(re.escape(out.stem) + r"\.seg([1-9][0-9]*)\.report-data\.npz")
    folder = out.parent.resolve()
    for _, given in inputs:
        if given is None:
            continue
        for file in input_files(Path(given)):
            for candidate in (file, file.resolve()):
                match = name.fullmatch(candidate.name)
                if match and candidate.parent.resolve() == folder:
                    path = out.parent / candidate.name
                    check_not_an_input(path, inputs, _window_label(path, match.group(1)))


def _write_report_data(
    run: JointRun,
    cfg: CalibConfig,
    outputs: SegmentOutputs,
    truth: Truth | None,
    config_text: str,
) -> tuple[ReportData, tuple[ReportData, ...]]:
    """The report data beside a joint result: ``<stem>.report-data.npz`` with the command line,
    the config and the truth, and per window ``<stem>.segK.report-data.npz`` with its own fit
    (:func:`~licalib_cli.report.data.window_report_data_path`), each tied to the joint result.
    """
    from licalib_cli.cli import command_line
    from licalib_cli.commands.report import with_truth
    from licalib_cli.report import build_report_data, report_data_path, window_report_data_path
    from licalib_cli.report.data import ReportData

    out = outputs.result
    created = run.result.provenance.created_utc if run.result.provenance else ""
    joint = ReportData(
        result_created_utc=created, command_line=command_line(), config_text=config_text
    )
    if truth is not None:
        joint = with_truth(joint, run.result, truth)
    paths = [report_data_path(out)]
    windows = []
    for k, seg_run in enumerate(run.runs, start=1):
        assert seg_run.segment is not None
        data = build_report_data(
            seg_run,
            seg_run.segment,
            cfg,
            truth=truth.extrinsic_for(seg_run.result) if truth is not None else None,
            command_line=joint.command_line,
            config_text=config_text,
        )
        path = window_report_data_path(out, k)
        check_not_an_input(path, list(outputs.inputs), _window_label(path, k))
        data = replace(data, result_created_utc=created)
        data.save(path)
        windows.append(data)
        paths.append(path)
    joint.save(paths[0])
    console().print("Report data: " + ", ".join(str(p) for p in paths))
    return joint, tuple(windows)


def _render_model(model: SegmentsModel) -> None:
    """Each window's diagnosis, then the model the joint calibration estimates."""
    from licalib_cli.commands.diagnose import render_diagnosis

    con = console()
    for k, ((a, b), diag) in enumerate(zip(model.windows, model.diagnoses, strict=True), 1):
        con.rule(f"seg{k} ({a:.1f}-{b:.1f} s) diagnosed alone")
        render_diagnosis(diag)
    con.rule()
    con.print(
        "Model of the joint calibration (every effect a window kept): "
        + (", ".join(model.effects) or "the base model, no effect kept")
        + "."
    )


def segment_map_path(path: Path, index: int) -> Path:
    """The map file of segment ``index`` (1-based) for ``--map path`` with ``--segments``:
    ``map.ply`` -> ``map.seg1.ply`` (the result's ``seg1`` names the same segment)."""
    return path.with_name(f"{path.stem}.seg{index}{path.suffix}")


def _write_segment_maps(
    run: JointRun, cfg: CalibConfig, map_file: Path | None, map_before: Path | None
) -> None:
    """Each segment's map with the joint calibration (``map_file``) and with its initial guess
    (``map_before``), one file per segment."""
    if map_file is None and map_before is None:
        return
    from licalib_cli.io.map_writer import write_map
    from licalib_cli.pipeline.map_export import map_chunks

    con = console()
    for path, which in ((map_file, "joint"), (map_before, "initial")):
        if path is None:
            continue
        for k, (seg_run, joint_state) in enumerate(zip(run.runs, run.states, strict=True)):
            assert seg_run.segment is not None
            state = joint_state if which == "joint" else seg_run.initial.state
            target = segment_map_path(path, k + 1)
            count, chunks = map_chunks(seg_run.segment, state, cfg)
            write_map(target, count, chunks)
            con.print(
                f"Map of segment {k + 1} with the {which} calibration: {target} ({count} points)"
            )
