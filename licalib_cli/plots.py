"""Figures of a calibration run, for people who would rather look than read.

:func:`save_plots` writes PNG files into a folder:

* ``fit.png``: the point-to-plane distances before the first round and after the last one
  (histograms; a good calibration gives a narrow peak about as wide as the range noise), and
  per round the RMS distance and how much the extrinsic and the time offset moved.
* ``observability.png``: the singular values of the scaled calibration information (the
  spectrum the truncated SVD acts on) against the truncation threshold, each labelled with the
  coordinate that dominates its direction; truncated directions in red.
* ``map_entropy.png``: the mean map entropy per round (the paper's MME figure).

:func:`save_segment_plots` writes those of a calibration over several segments: the joint
problem's ``observability.png``, ``segments.png`` (each window calibrated alone against the
joint estimate, in its own sigmas) and each window's own ``segK.fit.png`` and
``segK.map_entropy.png``.

matplotlib is an optional dependency (the ``plot`` extra); it is imported here only, with the
non-interactive Agg backend, so plots work without a display.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from licalib_cli.errors import ConfigError
from licalib_cli.results import Extrinsic, create_folder

if TYPE_CHECKING:
    from licalib_cli.pipeline import CalibrationRun
    from licalib_cli.pipeline.joint import JointRun
    from licalib_cli.solver.lm import SolverReport

__all__ = ["dominant_labels", "prepare_plots", "pyplot", "save_plots", "save_segment_plots"]

_DPI = 110


def pyplot() -> Any:
    """matplotlib's pyplot with the Agg backend, or a ConfigError saying how to install it."""
    try:
        import matplotlib
    except ImportError as err:
        msg = (
            "Plots need matplotlib, which is not installed; install it with "
            "`.venv/bin/pip install matplotlib` (or the package's `plot` extra)."
        )
        raise ConfigError(msg) from err
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def prepare_plots(folder: Path) -> None:
    """Check, before a long run, that plots can be drawn into ``folder`` (created if needed).

    Raises:
        ConfigError: matplotlib is missing, or ``folder`` is a file or cannot be created.
    """
    pyplot()
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        msg = f"--plots needs a folder, but {folder} is a file; give a folder path."
        raise ConfigError(msg)
    create_folder(folder, "The plot folder", "give a writable folder to --plots")


def save_plots(run: CalibrationRun, folder: Path) -> list[Path]:
    """Write the figures of ``run`` into ``folder`` (created if needed).

    Args:
        run: a finished calibration.
        folder: output folder.

    Returns:
        The files written.

    Raises:
        ConfigError: matplotlib is not installed.
    """
    plt = pyplot()
    folder = Path(folder)
    prepare_plots(folder)
    return [
        _save(plt, _fit_figure(plt, run), folder / "fit.png"),
        _save(plt, _spectrum_figure(plt, run.solver), folder / "observability.png"),
        _save(plt, _entropy_figure(plt, run), folder / "map_entropy.png"),
    ]


def save_segment_plots(run: JointRun, folder: Path) -> list[Path]:
    """Write the figures of a calibration over several segments into ``folder``.

    ``observability.png`` is the joint problem's spectrum; ``segments.png`` shows how far each
    window calibrated alone lies from the joint estimate; ``segK.fit.png`` and
    ``segK.map_entropy.png`` are window K's own fit (``segK`` as in the result).

    Raises:
        ConfigError: matplotlib is not installed.
    """
    plt = pyplot()
    folder = Path(folder)
    prepare_plots(folder)
    written = [
        _save(
            plt, _spectrum_figure(plt, run.report, "joint problem"), folder / "observability.png"
        ),
        _save(plt, _segments_figure(plt, run), folder / "segments.png"),
    ]
    for k, seg_run in enumerate(run.runs, start=1):
        fig = _fit_figure(plt, seg_run)
        fig.suptitle(f"seg{k} calibrated alone: verdict {seg_run.verdict.status.upper()}")
        written.append(_save(plt, fig, folder / f"seg{k}.fit.png"))
        fig = _entropy_figure(plt, seg_run)
        fig.axes[0].set_title(f"seg{k} calibrated alone: map sharpness over the rounds")
        written.append(_save(plt, fig, folder / f"seg{k}.map_entropy.png"))
    return written


def _save(plt: Any, fig: Any, path: Path) -> Path:
    """Write ``fig`` to ``path`` as PNG atomically and close it."""
    tmp = path.with_name(f".{path.name}.tmp")
    fig.savefig(tmp, dpi=_DPI, format="png")
    plt.close(fig)
    tmp.replace(path)
    return path


def segment_offsets(run: JointRun) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Each window alone minus the joint estimate, and the sigmas to judge it by.

    Returns:
        ``(own, own_sigma, joint_sigma, windows)``: (K, 7) differences of each window's own
        estimate from the joint one, translation per IMU axis (mm), rotation about the LiDAR
        axes (deg, ``log(R_joint^T R_own)``) and time offset (ms, against that window's own time
        offset in the joint problem); (K, 7) the window's own 1-sigma; (K, 7) the joint
        1-sigma (the time offset's that of the window in the joint problem); (K, 2) windows, s.
    """
    from licalib_cli.geometry import so3
    from licalib_cli.results import matrix_from_rpy_deg

    result = run.result
    ext, unc = result.extrinsic, result.uncertainty
    t_joint = np.asarray(ext.translation, dtype=np.float64)
    joint_t_sd = np.asarray(unc.translation_std_m) if unc is not None else np.full(3, np.nan)
    joint_r_sd = np.asarray(unc.rotation_std_deg) if unc is not None else np.full(3, np.nan)
    own, own_sd, joint_sd, windows = [], [], [], []
    for e in run.segments.segments:
        rot = so3.log(np.asarray(ext.rotation).T @ matrix_from_rpy_deg(e.rotation_rpy_deg))
        own.append(
            [
                *(1e3 * (np.asarray(e.translation) - t_joint)),
                *np.degrees(rot),
                1e3 * (e.time_offset_s - e.joint_time_offset_s),
            ]
        )
        own_sd.append([*(1e3 * np.asarray(e.translation_std_m)), *e.rotation_std_deg])
        own_sd[-1].append(1e3 * e.time_offset_std_s)
        joint_sd.append([*(1e3 * joint_t_sd), *joint_r_sd, 1e3 * e.joint_time_offset_std_s])
        windows.append([e.start_s, e.end_s])
    return np.array(own), np.array(own_sd), np.array(joint_sd), np.array(windows)


def _segments_figure(plt: Any, run: JointRun) -> Any:
    """Each window calibrated alone against the joint estimate, one panel per coordinate."""
    own, own_sd, joint_sd, windows = segment_offsets(run)
    labels = (
        "t_x (mm)",
        "t_y (mm)",
        "t_z (mm)",
        "rotation about LiDAR x (deg)",
        "rotation about LiDAR y (deg)",
        "rotation about LiDAR z (deg)",
        "time offset (ms)",
    )
    fig, axes = plt.subplots(1, 7, figsize=(17, 3.8))
    x = np.arange(1, own.shape[0] + 1)
    names = [f"seg{k}\n{a:.0f}-{b:.0f} s" for k, (a, b) in zip(x, windows, strict=True)]
    for j, ax in enumerate(axes):
        seen = np.isfinite(own_sd[:, j])
        ax.errorbar(
            x[seen],
            own[seen, j],
            yerr=own_sd[seen, j],
            fmt="o",
            color="tab:blue",
            capsize=4,
            label="alone",
        )
        band = np.nanmax(joint_sd[:, j]) if np.any(np.isfinite(joint_sd[:, j])) else np.nan
        if np.isfinite(band):
            ax.axhspan(-band, band, color="tab:green", alpha=0.2, label="joint +-1 sigma")
        ax.axhline(0.0, color="tab:green", lw=1.0)
        if not np.all(seen):
            ax.plot(x[~seen], own[~seen, j], "x", color="tab:red", label="not observable alone")
        ax.set_xticks(x)
        ax.set_xticklabels(names, fontsize=7)
        ax.set_xlim(0.5, x[-1] + 0.5)
        ax.set_title(labels[j], fontsize=9)
        ax.grid(True, alpha=0.3)
    axes[0].set_ylabel("alone minus joint")
    legend: dict[str, Any] = {}
    for ax in axes:  # every kind of mark once, wherever it was drawn
        for handle, label in zip(*ax.get_legend_handles_labels(), strict=True):
            legend.setdefault(label, handle)
    fig.legend(list(legend.values()), list(legend), fontsize=8, loc="lower center", ncol=3)
    fig.suptitle(
        "Each window calibrated alone minus the joint estimate, with its own 1-sigma bars; "
        f"joint verdict {run.result.verdict.status.upper() if run.result.verdict else '-'}",
        fontsize=10,
    )
    fig.tight_layout(rect=(0.0, 0.07, 1.0, 1.0))
    return fig


def _fit_figure(plt: Any, run: CalibrationRun) -> Any:
    rounds = run.rounds
    fig, (ax_h, ax_r) = plt.subplots(1, 2, figsize=(12, 4.5))
    first, last = rounds[0].distances_before_m, rounds[-1].distances_after_m
    both = np.concatenate([first, last]) if first.size + last.size else np.zeros(1)
    lim = float(np.percentile(np.abs(both), 99.5)) if both.size else 0.05
    lim = max(lim * 1e2, 0.5)  # cm
    bins = np.linspace(-lim, lim, 81)
    for d, label, colour in (
        (first, "before round 1 (initial guess)", "tab:orange"),
        (last, f"after round {rounds[-1].index} (result)", "tab:blue"),
    ):
        if d.size:
            rms = float(np.sqrt(np.mean(np.square(d, dtype=np.float64)))) * 1e2
            ax_h.hist(
                np.clip(d * 1e2, -lim, lim),
                bins=bins,
                density=True,
                alpha=0.55,
                color=colour,
                label=f"{label}: RMS {rms:.2f} cm, {d.size} points",
            )
    ax_h.set_xlabel(f"signed point-to-plane distance (cm; beyond +-{lim:.1f} piled at the ends)")
    ax_h.set_ylabel("density")
    ax_h.set_title("Point-to-plane distances")
    ax_h.legend(fontsize=8)

    idx = [r.index for r in rounds]
    ini = run.initial
    prev = Extrinsic(ini.R_imu_lidar, ini.t_imu_lidar, ini.time_offset_s)
    moves_t, moves_r, moves_c = [], [], []
    for r in rounds:
        err = r.extrinsic.error_to(prev)
        moves_t.append(1e3 * err["translation_m"])
        moves_r.append(err["rotation_deg"])
        moves_c.append(1e3 * err["time_offset_s"])
        prev = r.extrinsic
    ax_r.semilogy(idx, np.maximum(moves_t, 1e-4), "o-", label="translation moved (mm)")
    ax_r.semilogy(idx, np.maximum(np.multiply(moves_r, 1e3), 1e-4), "s-", label="rotation (mdeg)")
    ax_r.semilogy(idx, np.maximum(np.multiply(moves_c, 1e3), 1e-4), "^-", label="time offset (us)")
    ax_r.set_xlabel("round")
    ax_r.set_ylabel("change in the round")
    ax_r.set_xticks(idx)
    ax_r.grid(True, which="both", alpha=0.3)
    ax_rms = ax_r.twinx()
    ax_rms.plot(idx, [1e2 * r.rms_m for r in rounds], "k--", label="RMS distance (cm)")
    ax_rms.set_ylabel("RMS point-to-plane distance (cm)")
    lines = ax_r.get_legend_handles_labels()
    more = ax_rms.get_legend_handles_labels()
    ax_r.legend(lines[0] + more[0], lines[1] + more[1], fontsize=8, loc="upper right")
    ax_r.set_title("Convergence over the rounds")
    fig.suptitle(f"Fit: verdict {run.verdict.status.upper()}")
    fig.tight_layout()
    return fig


def _entropy_figure(plt: Any, run: CalibrationRun) -> Any:
    """Mean map entropy per round (the paper's MME figure): lower is a sharper map."""
    rounds = run.rounds
    fig, ax = plt.subplots(figsize=(6.5, 4.0))
    idx = [r.index for r in rounds]
    ax.plot(idx, [r.map_entropy for r in rounds], "o-", color="tab:green")
    joined = [r.index for r in rounds if any("intrinsics" in f for f in r.free)]
    if joined:
        ax.axvline(joined[0] - 0.5, color="grey", ls=":", label="intrinsics estimated from here")
        ax.legend(fontsize=8)
    ax.set_xlabel("round (the last one is the denser final round)")
    ax.set_ylabel("mean map entropy (nats, metres)")
    ax.set_xticks(idx)
    ax.grid(True, alpha=0.3)
    ax.set_title("Map sharpness over the rounds")
    fig.tight_layout()
    return fig


def dominant_labels(vectors: np.ndarray, names: Sequence[str]) -> list[str]:
    labels = []
    for j in range(vectors.shape[1]):
        v = vectors[:, j]
        i = int(np.argmax(np.abs(v)))
        labels.append(f"{names[i]} ({abs(v[i]):.2f})")
    return labels


def _spectrum_figure(plt: Any, report: SolverReport, what: str = "") -> Any:
    info = report.information
    s = np.asarray(info.singular_values, dtype=np.float64)
    fig, ax = plt.subplots(figsize=(max(8.0, 0.45 * s.size + 2.0), 4.8))
    if s.size == 0:
        ax.text(0.5, 0.5, "no calibration coordinates", ha="center", va="center")
        return fig
    thr = float(report.tsvd_threshold)
    floor = max(float(s[s > 0].min()) if np.any(s > 0) else 1e-12, 1e-12) * 0.1
    kept = s > thr
    colours = np.where(kept, "tab:blue", "tab:red")
    x = np.arange(s.size)
    ax.bar(x, np.maximum(s, floor), color=colours)
    ax.set_yscale("log")
    ax.axhline(thr, color="k", linestyle="--", label=f"truncation threshold {thr:g}")
    ax.set_xticks(x)
    ax.set_xticklabels(
        dominant_labels(info.singular_vectors, info.names), rotation=60, ha="right", fontsize=7
    )
    ax.set_ylabel("singular value of the scaled information")
    ax.set_title(
        f"Observability{' of the ' + what if what else ''}: one bar per direction in calibration "
        "space (labelled by its\nlargest coordinate); red: not observable, not updated; 1 = "
        "known to one characteristic scale",
        fontsize=9,
    )
    ax.legend(fontsize=8)
    fig.tight_layout()
    return fig


_PATTERN = {
    "gyro_scale": ("gyro", "angular_rate", "angular rate (rad/s)"),
    "gyro_misalignment": ("gyro", "angular_rate", "angular rate (rad/s)"),
    "gyro_rotation": ("gyro", "angular_rate", "angular rate (rad/s)"),
    "g_sensitivity": ("gyro", "specific_force", "specific force (m/s^2)"),
    "gyro_bias_walk": ("gyro", "t_imu_s", "time (s)"),
    "accel_scale": ("accel", "specific_force", "specific force (m/s^2)"),
    "accel_misalignment": ("accel", "specific_force", "specific force (m/s^2)"),
    "accel_bias_walk": ("accel", "t_imu_s", "time (s)"),
    "imu_clock_drift": ("distance", "point_t_s", "time (s)"),
    "lidar_point_time": ("distance", "time_in_sweep_s", "time within the sweep (s)"),
}
"""Effect -> (residual, feature, axis label) of the pattern it explains; LiDAR intrinsics show
per beam."""


def _binned(x: np.ndarray, y: np.ndarray, bins: int = 24) -> tuple[np.ndarray, np.ndarray]:
    """Mean of ``y`` in equal-count bins of ``x``."""
    order = np.argsort(x)
    parts = np.array_split(order, bins)
    return (
        np.array([x[p].mean() for p in parts if p.size]),
        np.array([y[p].mean() for p in parts if p.size]),
    )


def _pattern_axes(ax: Any, effect: str, tables: list[tuple[str, Any, str]]) -> None:
    if effect in _PATTERN:
        residual, feature, label = _PATTERN[effect]
        for name, table, colour in tables:
            r = np.asarray(getattr(table, residual))
            x = np.asarray(getattr(table, feature))
            if r.ndim == 2:
                for axis in range(3):
                    xx = x[:, axis] if x.ndim == 2 else x
                    bx, by = _binned(xx, r[:, axis])
                    ls = ("-", "--", ":")[axis]
                    ax.plot(bx, by, ls, color=colour, label=f"{name}, axis {'xyz'[axis]}")
            else:
                bx, by = _binned(x, r)
                ax.plot(bx, 1e3 * by, "-", color=colour, label=name)
        unit = "mm" if residual == "distance" else ("rad/s" if residual == "gyro" else "m/s^2")
        ax.set_xlabel(label)
        ax.set_ylabel(f"mean residual ({unit})")
    else:
        for k, (name, table, colour) in enumerate(tables):
            beams = np.asarray(table.beam)
            d = np.asarray(table.distance)
            n = int(beams.max()) + 1 if beams.size else 0
            counts = np.maximum(np.bincount(beams, minlength=n), 1)
            means = np.bincount(beams, d, minlength=n) / counts
            ax.bar(np.arange(n) + 0.4 * k - 0.2, 1e3 * means, width=0.4, color=colour, label=name)
        ax.set_xlabel("beam")
        ax.set_ylabel("mean point-to-plane distance (mm)")
    ax.axhline(0.0, color="grey", lw=0.8)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=7)


def save_diagnosis_plots(diag: Any, folder: Path) -> list[Path]:
    """One figure per diagnosis step: the residual pattern its effect explains, before and
    after it was added (``diagnose_<n>_<effect>.png``)."""
    from licalib_cli.pipeline.fitcheck import residual_table

    plt = pyplot()
    folder = Path(folder)
    prepare_plots(folder)
    written = []
    for n, step in enumerate(diag.steps, start=1):
        before, after = step.before, step.after
        fig, ax = plt.subplots(figsize=(7.0, 4.2))
        tables = [
            ("before", residual_table(before.state, before.fit.inputs), "tab:orange"),
            ("after", residual_table(after.state, after.fit.inputs), "tab:blue"),
        ]
        _pattern_axes(ax, step.effect, tables)
        ax.set_title(
            f"Step {n}: {step.effect} ({'kept' if step.kept else 'rejected'}; "
            f"{step.gap_before.sensor} gap {step.gap_before.excess:+.3f} -> "
            f"{step.gap_after.excess:+.3f})"
        )
        fig.tight_layout()
        written.append(_save(plt, fig, folder / f"diagnose_{n}_{step.effect}.png"))
    return written
