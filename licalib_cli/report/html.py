"""One self-contained HTML page from a result and its report data.

The page needs no network access: the style is inline and every figure is a PNG embedded as a
``data:`` URI. It reads top to bottom: the verdict and its reasons; the estimate with its
1-sigma (and the truth); what the data determined and what not; the fit; the motion; the map;
the provenance. Without report data (a result whose ``<stem>.report-data.npz`` is missing) the
page shows what the result file holds and names the figures it cannot draw.
"""

from __future__ import annotations

import base64
import html
from collections.abc import Sequence

import numpy as np

from licalib_cli.geometry import so3
from licalib_cli.report import figures
from licalib_cli.report.data import ReportData
from licalib_cli.results import CalibrationResult, Extrinsic, estimate_rows, rpy_deg_from_matrix
from licalib_cli.sections import AddedEffect, Consistency

__all__ = ["render_html"]

_STYLE = """
body { font-family: -apple-system, "Segoe UI", "DejaVu Sans", Arial, sans-serif; margin: 0;
       color: #1d1d1f; background: #fafafa; }
main { max-width: 1100px; margin: 0 auto; padding: 24px 32px 48px; background: #fff; }
h1 { font-size: 26px; margin: 0 0 4px; }
h2 { font-size: 20px; border-bottom: 2px solid #ddd; padding-bottom: 4px; margin-top: 36px; }
h3 { font-size: 16px; margin-top: 22px; }
.sub { color: #666; margin: 0 0 18px; }
.verdict { border-radius: 8px; padding: 14px 20px; margin: 12px 0 8px; color: #fff; }
.verdict .status { font-size: 30px; font-weight: bold; letter-spacing: 1px; }
.verdict ul { margin: 8px 0 0; padding-left: 22px; }
.pass { background: #1e8e3e; } .warn { background: #c77700; } .fail { background: #c5221f; }
table { border-collapse: collapse; margin: 8px 0 12px; font-size: 14px; }
th, td { border: 1px solid #ccc; padding: 4px 10px; text-align: right; }
th { background: #f0f0f0; } td.l, th.l { text-align: left; }
tr.bad td { background: #fff1e0; }
figure { margin: 10px 0 18px; } figure img { max-width: 100%; border: 1px solid #eee; }
figcaption { color: #555; font-size: 13px; margin-top: 4px; }
pre { background: #f5f5f5; padding: 10px; overflow-x: auto; font-size: 12px; }
.missing { color: #8a5a00; background: #fff8e6; padding: 6px 10px; border-radius: 4px; }
.note { color: #444; font-size: 14px; }
table.provenance td, table.provenance th, table.rounds td:last-child, table.checks td,
table.checks th { text-align: left; }
table.provenance td { word-break: break-all; }
"""


def _e(text: object) -> str:
    return html.escape(str(text), quote=True)


def _img(png: bytes, alt: str, caption: str) -> str:
    data = base64.b64encode(png).decode("ascii")
    return (
        f'<figure><img alt="{_e(alt)}" src="data:image/png;base64,{data}">'
        f"<figcaption>{_e(caption)}</figcaption></figure>"
    )


def _table(header: Sequence[str], rows: Sequence[Sequence[str]], cls: str = "") -> str:
    head = "".join(
        f'<th class="{"l" if i == 0 else ""}">{_e(h)}</th>' for i, h in enumerate(header)
    )
    body = []
    for row in rows:
        cells = "".join(
            f'<td class="{"l" if i == 0 else ""}">{_e(c)}</td>' for i, c in enumerate(row)
        )
        body.append(f"<tr>{cells}</tr>")
    return f'<table class="{cls}"><tr>{head}</tr>{"".join(body)}</table>'


def _missing(what: str, result: CalibrationResult | None = None) -> str:
    if result is not None and result.segments is not None:
        return (
            f'<p class="missing">{_e(what)} not shown for the joint fit: a calibration over '
            "several segments has no single trajectory and map to draw (each window has its "
            "own); each window's own fit is drawn below, when its report data "
            "(&lt;stem&gt;.segK.report-data.npz, written by calibrate --segments) is beside "
            "the result.</p>"
        )
    return (
        f'<p class="missing">{_e(what)} not shown: the result has no report data '
        "(&lt;stem&gt;.report-data.npz, written by this licalib's calibrate next to the "
        "result).</p>"
    )


def _largest_sigma(translation_m: Sequence[float], rotation_deg: Sequence[float]) -> str:
    """The largest translation and rotation 1-sigma, or "not observable" where one is not."""
    t, r = max(translation_m), max(rotation_deg)
    t_text = f"{1e3 * t:.2f} mm" if np.isfinite(t) else "not observable"
    r_text = f"{r:.4f} deg" if np.isfinite(r) else "not observable"
    return f"{t_text} / {r_text}"


def _segments(result: CalibrationResult) -> str:
    """The segments of a joint calibration: each one's own estimate beside the joint one."""
    seg = result.segments
    if seg is None:
        return ""
    ref = seg.segments[seg.reference - 1] if 0 < seg.reference <= len(seg.segments) else None
    rows = []
    for k, e in enumerate(seg.segments, start=1):
        rows.append(
            [
                f"seg{k}" + (" (reference)" if k == seg.reference else ""),
                f"{e.start_s:.1f}-{e.end_s:.1f} s",
                " ".join(f"{1e3 * v:+.1f}" for v in e.translation),
                " ".join(f"{v:+.3f}" for v in e.rotation_rpy_deg),
                f"{1e3 * e.time_offset_s:+.3f} -> {1e3 * e.joint_time_offset_s:+.3f}",
                _largest_sigma(e.translation_std_m, e.rotation_std_deg),
                f"{e.disagreement_sigmas:.1f}" + (" (disagrees)" if e.disagrees else ""),
                e.verdict.upper()
                + (f" (started from seg{e.started_from})" if e.started_from else ""),
            ]
        )
    ext, unc = result.extrinsic, result.uncertainty
    rows.append(
        [
            "joint",
            "",
            " ".join(f"{1e3 * v:+.1f}" for v in ext.translation),
            " ".join(f"{v:+.3f}" for v in rpy_deg_from_matrix(ext.rotation)),
            f"{1e3 * ext.time_offset_s:+.3f}",
            _largest_sigma(unc.translation_std_m, unc.rotation_std_deg) if unc is not None else "-",
            "",
            result.verdict.status.upper() if result.verdict is not None else "",
        ]
    )
    header = [
        "segment",
        "window",
        "t (mm)",
        "roll pitch yaw (deg)",
        "time offset (ms): alone -> joint",
        "largest 1-sigma",
        "own sigmas off the joint",
        "verdict",
    ]
    out = [
        "<h2>Segments</h2>",
        '<p class="note">Calibrated over several windows of the bag in one problem: one '
        "extrinsic (and the model's intrinsics) for all, a trajectory, biases, gravity and time "
        "offset per window. Each row is the window calibrated alone; a window further than "
        f"{seg.disagreement_threshold_sigmas:g} of its own sigmas from the joint estimate "
        "disagrees with the others."
        + (
            f" The fit and motion sections below describe seg{seg.reference} "
            f"({ref.start_s:.1f}-{ref.end_s:.1f} s, the window with the smallest sigmas) "
            "calibrated alone; each window's own figures follow in a section of its own."
            if ref is not None
            else ""
        )
        + (
            ' A window marked "started from" could not give an initial guess from its own '
            "motion; its own calibration started from that window's estimate and ran on its "
            "own data from there."
            if any(e.started_from for e in seg.segments)
            else ""
        )
        + "</p>",
        _table(header, rows, "segments"),
    ]
    return "\n".join(out)


def _estimate(result: CalibrationResult, data: ReportData | None) -> str:
    ext = result.extrinsic
    truth: Extrinsic | None = data.truth if data is not None else None
    initial = None
    if data is not None and data.initial_translation_m.size == 3:
        initial = (
            [float(v) for v in data.initial_translation_m],
            [float(v) for v in data.initial_rpy_deg],
            float(data.initial_time_offset_s[0]),
        )
    header = ["parameter", "estimate", "1-sigma"]
    if initial is not None:
        header.append("initial guess")
    if truth is not None:
        header += ["truth", "error"]
    rows = estimate_rows(result, truth, initial, unobservable="not observable")
    out = [
        "<h2>Estimate</h2>",
        '<p class="note">T_imu_lidar maps LiDAR points into the IMU frame: p_imu = R p_lidar + '
        "t (t is the LiDAR origin in the IMU frame; roll, pitch, yaw with R = Rz(yaw) Ry(pitch) "
        "Rx(roll)). Time offset: t_imu = t_lidar + time offset. The rotation sigmas"
        + (" and errors" if truth is not None else "")
        + " are about the LiDAR x, y, z axes.</p>",
        _table(header, rows, "estimate"),
    ]
    q = ext.quaternion
    out.append(
        f'<p class="note">Quaternion [x, y, z, w]: [{", ".join(f"{v:.9f}" for v in q)}].</p>'
    )
    shift = result.recording.lidar_clock_shift_s if result.recording else 0.0
    if shift:
        out.append(
            f'<p class="note">The LiDAR clock was shifted by {shift:+.9f} s before calibrating: '
            f"t_imu = t_lidar + ({shift:+.9f} s) + time offset.</p>"
        )
    if truth is not None:
        err = ext.error_to(truth)
        out.append(
            f'<p class="note">Error against the truth: translation '
            f"{1e3 * err['translation_m']:.2f} mm, rotation {err['rotation_deg']:.4f} deg, time "
            f"offset {1e3 * err['time_offset_s']:.3f} ms.</p>"
        )
    out.append(_intrinsics(result))
    return "\n".join(out)


_IMU_BLOCKS = {
    # model name: (result field, sigma key, unit, labels, to the shown unit)
    "gyro_scale": ("gyro_scale", "gyro_scale", "", ("x", "y", "z")),
    "gyro_misalignment": ("gyro_misalignment", "gyro_misalignment", "", ("xy", "xz", "yz")),
    "gyro_rotation": ("gyro_rotation", "gyro_rotation_deg", "deg", ("roll", "pitch", "yaw")),
    "accel_scale": ("accel_scale", "accel_scale", "", ("x", "y", "z")),
    "accel_misalignment": ("accel_misalignment", "accel_misalignment", "", ("xy", "xz", "yz")),
    "g_sensitivity": (
        "gyro_g_sensitivity",
        "g_sensitivity",
        "rad/s per m/s^2",
        tuple(f"{a}{b}" for a in "xyz" for b in "xyz"),
    ),
}
_LIDAR_BLOCKS = {
    # model name: (result field, sigma key, unit, value and sigma factors to the shown unit)
    "elevation": ("elevation_correction", "elevation_deg", "deg", 180.0 / np.pi, 1.0),
    "azimuth": ("azimuth_correction", "azimuth_deg", "deg", 180.0 / np.pi, 1.0),
    "vertical_offset": ("vertical_offset", "vertical_offset_m", "mm", 1e3, 1e3),
    "horizontal_offset": ("horizontal_offset", "horizontal_offset_m", "mm", 1e3, 1e3),
    "range_scale": ("range_scale", "range_scale", "", 1.0, 1.0),
    "range_offset": ("range_offset", "range_offset_m", "mm", 1e3, 1e3),
}


def _sigma_of(values: dict[str, tuple[float | None, ...]], key: str, i: int, factor: float) -> str:
    sig = values.get(key, ())
    v = sig[i] if i < len(sig) else None
    return "-" if v is None or not np.isfinite(v) else f"{v * factor:.4g}"


def _rival_text(a: AddedEffect) -> str:
    """What an added effect's close rival showed (empty without one)."""
    if not a.rival:
        return ""
    if a.not_told_apart:
        return (
            f"; this recording does not tell it from {a.rival}, which fit the same data "
            f"{-a.rival_delta_bic:.0f} worse in BIC"
        )
    return f"; {a.rival}, which could stand in for it, fit the same data worse"


def _intrinsics(result: CalibrationResult) -> str:
    """Tables of the estimated intrinsics with their 1-sigma (empty when none were)."""
    model = result.model
    if model is None or not (model.imu or model.lidar):
        return ""
    sig = result.intrinsics_uncertainty.values if result.intrinsics_uncertainty else {}
    out = ["<h3>Intrinsics estimated as well</h3>"]
    if model.added:
        out.append(
            "<p>Added to the configured model because the data showed them beyond doubt: "
            + "; ".join(
                _e(
                    f"{a.effect} (score test {a.statistic:.0f} on {a.dof} degrees of freedom; "
                    f"its refit's BIC {a.delta_bic:+.0f}, extrinsic moved "
                    f"{1e3 * a.moved_translation_m:.2f} mm / {a.moved_rotation_deg:.4f} deg / "
                    f"{1e3 * abs(a.moved_time_offset_s):.3f} ms{_rival_text(a)})"
                )
                for a in model.added
            )
            + ".</p>"
        )
    if model.undetermined:
        out.append(
            "<p>"
            + _e(
                "The recording determines none of the numbers of "
                f"{', '.join(model.undetermined)}: estimated as configured, the sigmas include "
                f"how far holding {'it' if len(model.undetermined) == 1 else 'them'} at nominal "
                "moves the extrinsic."
            )
            + "</p>"
        )
    rows = []
    k = result.imu_intrinsics
    for name in model.imu:
        if name not in _IMU_BLOCKS:
            continue
        field_name, key, unit, labels = _IMU_BLOCKS[name]
        raw = np.asarray(getattr(k, field_name), dtype=np.float64)
        values = (
            rpy_deg_from_matrix(so3.quat_to_matrix(raw)) if name == "gyro_rotation" else raw
        ).reshape(-1)
        for i, label in enumerate(labels):
            rows.append(
                [f"{name} {label}", f"{values[i]:.6g} {unit}".strip(), _sigma_of(sig, key, i, 1.0)]
            )
    if rows:
        out.append(_table(["IMU intrinsic", "estimate", "1-sigma"], rows, "intrinsics"))
    lidar = result.lidar_intrinsics
    names = [n for n in model.lidar if n in _LIDAR_BLOCKS]
    if lidar is not None and names:
        header = ["beam"] + [
            f"{n} ({_LIDAR_BLOCKS[n][2]})" if _LIDAR_BLOCKS[n][2] else n for n in names
        ]
        beam_rows = []
        for b in range(lidar.num_beams):
            row = [str(b)]
            for n in names:
                field_name, key, _, factor, sigma_factor = _LIDAR_BLOCKS[n]
                value = float(np.asarray(getattr(lidar, field_name))[b]) * factor
                row.append(f"{value:.4g} +- {_sigma_of(sig, key, b, sigma_factor)}")
            beam_rows.append(row)
        held = ", ".join(str(b) for b in model.held_beams) or "none"
        spread = ", ".join(f"{k} {v:.3g}" for k, v in model.lidar_spread.items())
        drawn = f"; drawn toward nominal with the spread across beams {spread}" if spread else ""
        out.append(
            f"<details><summary>Per-beam LiDAR intrinsics (estimate +- 1-sigma; gauge beam "
            f"{model.gauge_beam}, beams held for lack of points: {_e(held)}{_e(drawn)})</summary>"
            + _table(header, beam_rows, "beams")
            + "</details>"
        )
    return "\n".join(out)


def _weak_rule(floor: float) -> str:
    """The exception for weakly determined directions, as the fit applied it
    (``solver.weak_floor``)."""
    if not 0.0 < floor < 1.0:
        return " (solver.weak_floor off: no direction below it was weakly determined)"
    return (
        ", unless it is made of the extrinsic and at least "
        f"{floor:g} of the threshold: then it is weakly determined, estimated with its (large) "
        "sigma"
    )


def _observability(result: CalibrationResult, data: ReportData | None) -> str:
    out = ["<h2>What the data determined</h2>"]
    obs = result.observability
    if obs is None:
        out.append('<p class="missing">The result has no observability section.</p>')
        return "\n".join(out)
    labels = list(data.singular_labels) if data is not None else []
    out.append(
        '<p class="note">Each bar is one direction in calibration space (labelled by its largest '
        f"coordinate). Scaling: {_e(obs.scaling)}. A singular value of 1 means the direction is "
        "known to one characteristic scale; below the threshold "
        f"({obs.threshold:g}) a direction is not updated and keeps its initial value"
        + _weak_rule(obs.weak_floor)
        + ".</p>"
    )
    out.append(
        _img(
            figures.spectrum_png(obs.singular_values, obs.threshold, labels),
            "singular-value spectrum",
            "Scaled singular values of the calibration information against the threshold.",
        )
    )
    if obs.weakly_determined:
        out.append(
            f"<p><b>{len(obs.weakly_determined)} direction(s) were weakly determined</b> (below "
            "the threshold but estimated, their large sigmas in the table above; a verdict with "
            "one is at most WARN):</p>"
        )
        out.append("<ul>" + "".join(f"<li>{_e(t)}</li>" for t in obs.weakly_determined) + "</ul>")
    if not obs.unobservable:
        if not obs.weakly_determined:
            out.append(
                "<p><b>Every calibration direction was determined by the data</b> (all singular "
                "values above the threshold).</p>"
            )
        return "\n".join(out)
    out.append(f"<p><b>{len(obs.unobservable)} direction(s) were not observable:</b></p>")
    for text in obs.unobservable:
        out.append(f"<h3>{_e(text)}</h3>")
        parts = figures.direction_parts(text)
        words = []
        if "ext.translation" in parts:
            v = parts["ext.translation"]
            words.append(
                "the LiDAR's position along the black arrow ("
                + ", ".join(f"{x:+.2f} IMU {a}" for x, a in zip(v, "xyz", strict=True))
                + ") cannot be told from this motion"
            )
        if "ext.rotation" in parts:
            v = parts["ext.rotation"]
            words.append(
                "a turn of the LiDAR about the purple axis ("
                + ", ".join(f"{x:+.2f} LiDAR {a}" for x, a in zip(v, "xyz", strict=True))
                + ") cannot be told from this motion"
            )
        if words:
            out.append(
                f"<p>In words: {_e('; '.join(words))}. It stays at its initial value; record "
                "with rotation about more axes or set it from a measurement.</p>"
            )
        out.append(
            _img(
                figures.unobservable_png(
                    text, result.extrinsic.rotation, result.extrinsic.translation
                ),
                "sketch of an unobservable direction",
                "The IMU axes (solid), the LiDAR axes where the result puts them (dashed) and the "
                "direction the data did not determine.",
            )
        )
    return "\n".join(out)


def _checks(consistency: Consistency) -> str:
    rows = [[check, figure or "-", outcome] for check, figure, outcome, _ in consistency.rows()]
    out = [_table(["check", "figure", "outcome"], rows, "checks")]
    for why in consistency.inflation:
        out.append(f'<p class="note">Sigmas enlarged {_e(why)}.</p>')
    return "\n".join(out)


def _fit(result: CalibrationResult, data: ReportData | None) -> str:
    out = ["<h2>The fit</h2>"]
    fit = result.fit
    if fit is not None:
        out.append(
            f'<p class="note">{fit.rounds} rounds, '
            f"{'converged' if fit.converged else 'NOT converged'}; the last fit used "
            f"{fit.points} points on {fit.surfels} surfels, RMS point-to-plane distance "
            f"{100 * fit.point_rms_m:.2f} cm, chi-square per degree of freedom "
            f"{fit.variance_factor:.3g}.</p>"
        )
    out += _fit_figures(result, data)
    out.append("<h3>Checks of the fit</h3>")
    if result.consistency is not None:
        out.append(_checks(result.consistency))
    else:
        out.append('<p class="missing">The result has no consistency section.</p>')
    out += _round_figures(result, data)
    return "\n".join(out)


def _fit_figures(result: CalibrationResult, data: ReportData | None) -> list[str]:
    """The distance histogram and the IMU residuals (or what is missing)."""
    out = ["<h3>Point-to-plane distances before and after</h3>"]
    if data is not None and data.distances_after_m.size:
        out.append(
            _img(
                figures.distances_png(data.distances_before_m, data.distances_after_m),
                "point-to-plane distances",
                "A good calibration gives a narrow peak about as wide as the range noise.",
            )
        )
    else:
        out.append(_missing("The distance histogram is", result))
    out.append("<h3>IMU residuals against time</h3>")
    if data is not None and data.imu_t_s.size:
        out.append(
            _img(
                figures.imu_residuals_png(data.imu_t_s, data.gyro_residual, data.accel_residual),
                "IMU residuals",
                "Prediction minus reading per axis; drifts or bursts show what the model lacks.",
            )
        )
    else:
        out.append(_missing("The IMU residuals are", result))
    return out


def _round_figures(result: CalibrationResult, data: ReportData | None) -> list[str]:
    """The convergence per round: figure and table (or what is missing)."""
    out = ["<h3>Convergence per round</h3>"]
    if data is not None and data.round_index.size:
        initial = (
            (data.initial_translation_m, data.initial_rpy_deg, float(data.initial_time_offset_s[0]))
            if data.initial_translation_m.size == 3
            else None
        )
        out.append(
            _img(
                figures.rounds_png(
                    data.round_index,
                    data.round_translation_m,
                    data.round_rpy_deg,
                    data.round_time_offset_s,
                    data.round_rms_m,
                    initial,
                ),
                "convergence per round",
                "How far each round moved the extrinsic, and the RMS distance after it.",
            )
        )
        rows = []
        for k in range(data.round_index.size):
            ent = float(data.round_map_entropy[k])
            rows.append(
                [
                    str(int(data.round_index[k])),
                    f"{100 * data.round_max_distance_m[k]:.1f} cm",
                    str(int(data.round_points[k])),
                    str(int(data.round_surfels[k])),
                    f"{100 * data.round_rms_m[k]:.2f} cm",
                    f"{ent:.3f}" if np.isfinite(ent) else "-",
                    str(int(data.round_iterations[k])),
                    f"{data.round_seconds[k]:.1f} s",
                    str(data.round_free[k]),
                ]
            )
        out.append(
            _table(
                [
                    "round",
                    "association",
                    "points",
                    "surfels",
                    "RMS",
                    "map entropy",
                    "iterations",
                    "time",
                    "estimated",
                ],
                rows,
                "rounds",
            )
        )
    else:
        out.append(_missing("The per-round convergence is", result))
    return out


def _motion(result: CalibrationResult, data: ReportData | None) -> str:
    out = ["<h2>The motion</h2>"]
    rec = result.recording
    if rec is not None:
        out.append(
            f'<p class="note">Segment used: {rec.duration_s:.2f} s, {rec.imu_samples} IMU '
            f"samples on {_e(rec.imu_topic)}, {rec.scans} sweeps on {_e(rec.lidar_topic)}.</p>"
        )
    out.append(_motion_figure(result, data))
    return "\n".join(out)


def _motion_figure(result: CalibrationResult, data: ReportData | None) -> str:
    if data is None or not data.motion_t_s.size:
        return _missing("The motion plot is", result)
    return _img(
        figures.motion_png(
            data.motion_t_s, data.angular_rate, data.specific_force, data.segments_s
        ),
        "angular rate and specific force",
        "Gyro and accelerometer readings; the shaded span is the segment calibrated. "
        "Rotation about all three axes makes every extrinsic direction observable.",
    )


def _map(result: CalibrationResult, data: ReportData | None) -> str:
    return "\n".join(["<h2>The map</h2>", *_map_views(result, data)])


def _map_views(result: CalibrationResult, data: ReportData | None) -> list[str]:
    """The entropy table and the map views (or what is missing)."""
    out: list[str] = []
    if data is None or not data.has_map:
        out.append(_missing("The map views are", result))
        return out
    before, after = data.map_entropy_before, data.map_entropy_after
    out.append(
        '<p class="note">The map built with the initial calibration (left) and with the final '
        "one (right), same region: walls that are doubled or thick with a wrong calibration "
        "become thin lines; the bottom row zooms into 1 m of the densest wall. The mean map "
        "entropy is lower for a sharper map.</p>"
    )
    out.append(
        _table(
            ["map", "mean map entropy (nats)"],
            [
                ["initial calibration", f"{before:.4f}" if np.isfinite(before) else "-"],
                ["final calibration", f"{after:.4f}" if np.isfinite(after) else "-"],
            ],
            "entropy",
        )
    )
    out.append(
        _img(
            figures.map_png(
                data.map_before_top_xy,
                data.map_after_top_xy,
                data.map_before_side_xz,
                data.map_after_side_xz,
                data.map_region_m,
                (before, after),
                (data.map_top_slab_m, data.map_side_slab_m),
                (data.map_before_zoom_xy, data.map_after_zoom_xy, data.map_zoom_m)
                if data.map_zoom_m.size == 4
                else None,
            ),
            "map views",
            "Level frame: z up against gravity, origin at the first IMU position.",
        )
    )
    return out


def _windows(result: CalibrationResult, windows: Sequence[ReportData | None]) -> str:
    """Each window of a joint calibration calibrated alone: its fit, motion and map figures."""
    seg = result.segments
    if seg is None or not windows:
        return ""
    out = []
    for k, (entry, data) in enumerate(zip(seg.segments, windows, strict=False), start=1):
        out.append(
            f'<h2 id="seg{k}">seg{k} ({entry.start_s:.1f}-{entry.end_s:.1f} s) calibrated '
            "alone</h2>"
        )
        if data is None:
            out.append(
                f'<p class="missing">seg{k}\'s figures not shown: its report data '
                "(&lt;stem&gt;.seg" + str(k) + ".report-data.npz) is not beside the result.</p>"
            )
            continue
        out.append(
            f'<p class="note">seg{k} calibrated on its own data (its row of the Segments table, '
            f"verdict {_e(entry.verdict.upper())}): its point-to-plane distances, IMU residuals, "
            "rounds, motion, and its map with its initial guess and with its own estimate. The "
            "joint estimate is the table's last row.</p>"
        )
        out += _fit_figures(result, data)
        out += _round_figures(result, data)
        out.append("<h3>Motion</h3>")
        out.append(_motion_figure(result, data))
        out.append("<h3>Map</h3>")
        out += _map_views(result, data)
    return "\n".join(out)


def _provenance(result: CalibrationResult, data: ReportData | None, source: str) -> str:
    rows = []
    prov = result.provenance
    if prov is not None:
        rows += [
            ["licalib version", prov.licalib_version],
            ["created (UTC)", prov.created_utc],
            ["bag fingerprint", prov.bag_fingerprint],
        ]
    rec = result.recording
    if rec is not None:
        rows += [
            ["bag", rec.bag],
            ["topics", f"{rec.imu_topic}, {rec.lidar_topic}"],
            ["segment start (ns, IMU clock)", str(rec.start_ns)],
            ["segment duration", f"{rec.duration_s:.3f} s"],
            ["clock offset t_imu - t_lidar", f"{rec.clock_offset_s:+.6f} s"],
        ]
        if rec.gravity_turn_deg is not None:
            rows.append(["gravity turned in the IMU frame", f"{rec.gravity_turn_deg:.1f} deg RMS"])
    rows.append(["result file", source])
    if data is not None and data.command_line:
        rows.append(["command line", data.command_line])
    out = ["<h2>Provenance</h2>", _table(["item", "value"], rows, "provenance")]
    if data is not None and data.config_text:
        out.append("<h3>Configuration (resolved)</h3>")
        out.append(f"<pre>{_e(data.config_text)}</pre>")
    elif data is None:
        out.append(_missing("The command line and configuration are", result))
    return "\n".join(out)


def render_html(
    result: CalibrationResult,
    data: ReportData | None,
    source: str = "",
    windows: Sequence[ReportData | None] = (),
) -> str:
    """The report page.

    Args:
        result: the result file's content.
        data: its report data, or None (the figures that need it are named as missing).
        source: how the page names the result file.
        windows: for a result of ``calibrate --segments``, each window's report data (its fit
            calibrated alone; None where missing): a section per window.

    Returns:
        The HTML text (UTF-8, self-contained).
    """
    verdict = result.verdict
    status = verdict.status if verdict is not None else "unknown"
    reasons = verdict.reasons if verdict is not None else ()
    cls = status if status in ("pass", "warn", "fail") else "warn"
    meaning = {
        "pass": "Every check could have failed and none did; the result can be used.",
        "warn": "Usable with care: read the reasons below.",
        "fail": "Do not use this result; it is shown for inspection only.",
    }.get(status, "The result carries no verdict.")
    items = "".join(f"<li>{_e(r)}</li>" for r in reasons)
    # what the result takes as exact though the recording cannot check it (a note beside the
    # verdict, as the console prints it)
    assumed = (
        result.consistency.assumed_exact
        if result.consistency is not None and status != "fail"
        else ()
    )
    assumes = (
        f"<div>It assumes {_e(', '.join(assumed))} exact, which this recording cannot check "
        "(the fit checks' row 'taken as exact').</div>"
        if assumed
        else ""
    )
    verdict_html = (
        f'<section class="verdict {cls}" id="verdict"><div class="status">Verdict: '
        f"{_e(status.upper())}</div><div>{_e(meaning)}</div>"
        + assumes
        + (f"<ul>{items}</ul>" if items else "")
        + "</section>"
    )
    title = f"licalib calibration report: {status.upper()}"
    created = result.provenance.created_utc if result.provenance else ""
    body = [
        f"<h1>LiDAR-IMU calibration report</h1>"
        f'<p class="sub">{_e(source)}{" - " + _e(created) if created else ""}</p>',
        verdict_html,
        _estimate(result, data),
        _segments(result),
        _observability(result, data),
        _fit(result, data),
        _motion(result, data),
        _map(result, data),
        _windows(result, windows),
        _provenance(result, data, source),
    ]
    return (
        '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
        f"<title>{_e(title)}</title><style>{_STYLE}</style></head>\n<body><main>\n"
        + "\n".join(body)
        + "\n</main></body></html>\n"
    )
