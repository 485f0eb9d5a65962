"""The report's figures, drawn with matplotlib (Agg) and returned as PNG bytes.

Every function takes plain arrays (from the result file or its report data) and returns the PNG
of one figure; none reads files or knows about HTML.
"""

from __future__ import annotations

import io
import re
from collections.abc import Sequence
from typing import Any

import numpy as np
import numpy.typing as npt

from licalib_cli.plots import pyplot

__all__ = [
    "distances_png",
    "imu_residuals_png",
    "map_png",
    "motion_png",
    "rounds_png",
    "spectrum_png",
    "unobservable_png",
]

F64 = npt.NDArray[np.float64]
Floats = npt.NDArray[np.floating[Any]]
"""Arrays of any float dtype (the report data keeps its long series as float32)."""
_DPI = 100
_AXES = ("x", "y", "z")
_COLOURS = ("tab:red", "tab:green", "tab:blue")


def _png(fig: Any) -> bytes:
    plt = pyplot()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=_DPI)
    plt.close(fig)
    return buf.getvalue()


def spectrum_png(
    singular_values: Sequence[float], threshold: float, labels: Sequence[str] = ()
) -> bytes:
    """Scaled singular values against the truncation threshold; truncated ones in red."""
    plt = pyplot()
    s = np.asarray(singular_values, dtype=np.float64)
    fig, ax = plt.subplots(figsize=(max(7.0, 0.42 * s.size + 2.5), 4.2))
    if s.size == 0:
        ax.text(0.5, 0.5, "no calibration coordinates", ha="center", va="center")
        return _png(fig)
    positive = s[s > 0]
    floor = max(float(positive.min()) if positive.size else 1e-12, 1e-12) * 0.1
    floor = min(floor, threshold * 0.1) if threshold > 0 else floor
    x = np.arange(s.size)
    ax.bar(x, np.maximum(s, floor), color=np.where(s > threshold, "tab:blue", "tab:red"))
    ax.set_yscale("log")
    ax.axhline(
        threshold, color="k", ls="--", label=f"threshold {threshold:g}: below it, not updated"
    )
    ax.set_xticks(x)
    names = list(labels) if len(labels) == s.size else [f"#{i + 1}" for i in range(s.size)]
    ax.set_xticklabels(names, rotation=60, ha="right", fontsize=7)
    ax.set_ylabel("scaled singular value")
    ax.legend(fontsize=8, loc="upper right")
    ax.set_title("Blue: determined by the data; red: not observable", fontsize=10)
    fig.tight_layout()
    return _png(fig)


_ALONG = re.compile(r"(ext\.translation|ext\.rotation) along \[([^\]]+)\]")


def direction_parts(text: str) -> dict[str, F64]:
    """The extrinsic components of an unobservable direction as written in the result
    (``ext.translation along [0.00, 0.00, 1.00] in the IMU frame ...``)."""
    out = {}
    for block, values in _ALONG.findall(text):
        try:
            v = np.array([float(x) for x in values.split(",")], dtype=np.float64)
        except ValueError:
            continue
        if v.size == 3 and np.linalg.norm(v) > 0:
            out[block] = v / np.linalg.norm(v)
    return out


def unobservable_png(text: str, rotation: F64, translation: F64) -> bytes:
    """A sketch of the rig: the IMU axes, the LiDAR axes where the extrinsic puts them, and the
    direction the data did not determine (a shift of the LiDAR along an arrow, or a turn about
    an axis through it), with the direction's text as title."""
    plt = pyplot()
    parts = direction_parts(text)
    fig = plt.figure(figsize=(5.2, 4.4))
    ax = fig.add_subplot(111, projection="3d")
    rot = np.asarray(rotation, dtype=np.float64)
    t = np.asarray(translation, dtype=np.float64)
    size = max(float(np.linalg.norm(t)), 0.2)
    axis_len = 0.35 * size
    for i in range(3):
        e = np.zeros(3)
        e[i] = axis_len
        ax.quiver(0, 0, 0, *e, color=_COLOURS[i], arrow_length_ratio=0.15, lw=2)
        ax.text(*(1.15 * e), f"IMU {_AXES[i]}", color=_COLOURS[i], fontsize=8)
        d = rot[:, i] * axis_len * 0.8
        ax.quiver(*t, *d, color=_COLOURS[i], arrow_length_ratio=0.15, lw=1.2, linestyle="--")
        ax.text(*(t + 1.15 * d), f"LiDAR {_AXES[i]}", color=_COLOURS[i], fontsize=7)
    ax.plot([0, t[0]], [0, t[1]], [0, t[2]], color="grey", lw=0.8)
    if "ext.translation" in parts:
        v = parts["ext.translation"] * size * 0.6
        ax.quiver(*(t - v / 2), *v, color="black", lw=3, arrow_length_ratio=0.2)
        ax.text(*(t + v / 2), "shift not\ndetermined", fontsize=8)
    if "ext.rotation" in parts:
        axis = rot @ parts["ext.rotation"]  # LiDAR-frame axis, drawn in the IMU frame
        a = axis * size * 0.6
        ax.plot(*np.stack([t - a, t + a]).T, color="purple", lw=2.5)
        u = np.cross(axis, [1.0, 0.0, 0.0])
        if np.linalg.norm(u) < 0.1:
            u = np.cross(axis, [0.0, 1.0, 0.0])
        u /= np.linalg.norm(u)
        w = np.cross(axis, u)
        ang = np.linspace(0.0, 1.6 * np.pi, 40)
        ring = t + 0.25 * size * (np.outer(np.cos(ang), u) + np.outer(np.sin(ang), w))
        ax.plot(*ring.T, color="purple", lw=1.5)
        ax.text(*(t + a), "turn not\ndetermined", color="purple", fontsize=8)
    lim = size * 1.1
    ax.set_xlim(-lim * 0.3, lim)
    ax.set_ylim(-lim * 0.3 + min(t[1], 0), lim)
    ax.set_zlim(-lim * 0.6, lim * 0.6)
    ax.set_xlabel("IMU x (m)")
    ax.set_ylabel("IMU y (m)")
    ax.set_zlabel("IMU z (m)")
    if not parts:
        ax.set_title("(no extrinsic component)", fontsize=8)
    fig.tight_layout()
    return _png(fig)


def distances_png(before_m: Floats, after_m: Floats) -> bytes:
    """Histograms of the signed point-to-plane distances before round 1 and after the last."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7.5, 3.8))
    before = np.asarray(before_m, dtype=np.float64)
    after = np.asarray(after_m, dtype=np.float64)
    both = np.concatenate([before, after])
    lim = max(float(np.percentile(np.abs(both), 99.5)) * 100 if both.size else 5.0, 0.5)
    bins = np.linspace(-lim, lim, 81)
    for d, label, colour in (
        (before, "with the initial guess (before round 1)", "tab:orange"),
        (after, "with the result (after the final round)", "tab:blue"),
    ):
        if d.size:
            rms = float(np.sqrt(np.mean(np.square(d)))) * 100
            ax.hist(
                np.clip(d * 100, -lim, lim),
                bins=bins,
                density=True,
                alpha=0.55,
                color=colour,
                label=f"{label}: RMS {rms:.2f} cm",
            )
    ax.set_xlabel(f"signed point-to-plane distance (cm; beyond +-{lim:.1f} piled at the ends)")
    ax.set_ylabel("density")
    ax.legend(fontsize=8)
    fig.tight_layout()
    return _png(fig)


def imu_residuals_png(t_s: Floats, gyro: Floats, accel: Floats) -> bytes:
    """Gyro and accelerometer residuals (prediction minus reading) against time, per axis."""
    plt = pyplot()
    fig, (ax_g, ax_a) = plt.subplots(2, 1, figsize=(9.0, 5.0), sharex=True)
    for ax, r, unit, name in ((ax_g, gyro, "rad/s", "gyro"), (ax_a, accel, "m/s^2", "accel")):
        r = np.asarray(r, dtype=np.float64)
        for i in range(3):
            ax.plot(t_s, r[:, i], lw=0.6, color=_COLOURS[i], label=f"{_AXES[i]}")
        ax.axhline(0.0, color="grey", lw=0.6)
        ax.set_ylabel(f"{name} residual ({unit})")
        ax.legend(fontsize=7, ncol=3, loc="upper right")
        ax.grid(True, alpha=0.3)
    ax_a.set_xlabel("time on the trajectory (s)")
    fig.tight_layout()
    return _png(fig)


def rounds_png(
    index: Sequence[int] | npt.NDArray[np.integer[Any]],
    translation_m: F64,
    rpy_deg: F64,
    time_offset_s: F64,
    rms_m: F64,
    initial: tuple[F64, F64, float] | None,
) -> bytes:
    """How much each round moved the extrinsic, and the RMS point-to-plane distance."""
    plt = pyplot()
    idx = np.asarray(index)
    t = np.asarray(translation_m, dtype=np.float64)
    r = np.asarray(rpy_deg, dtype=np.float64)
    c = np.asarray(time_offset_s, dtype=np.float64)
    fig, ax = plt.subplots(figsize=(7.5, 3.8))
    if initial is not None:
        t = np.vstack([initial[0], t])
        r = np.vstack([initial[1], r])
        c = np.concatenate([[initial[2]], c])
    else:
        t, r, c = np.vstack([t[:1], t]), np.vstack([r[:1], r]), np.concatenate([c[:1], c])
    moved_t = 1e3 * np.linalg.norm(np.diff(t, axis=0), axis=1)
    moved_r = 1e3 * np.linalg.norm(np.diff(r, axis=0), axis=1)
    moved_c = 1e6 * np.abs(np.diff(c))
    ax.semilogy(idx, np.maximum(moved_t, 1e-4), "o-", label="translation moved (mm)")
    ax.semilogy(idx, np.maximum(moved_r, 1e-4), "s-", label="roll/pitch/yaw moved (mdeg)")
    ax.semilogy(idx, np.maximum(moved_c, 1e-4), "^-", label="time offset moved (us)")
    ax.set_xlabel("round (the last is the denser final round)")
    ax.set_ylabel("change in the round")
    ax.set_xticks(idx)
    ax.grid(True, which="both", alpha=0.3)
    ax2 = ax.twinx()
    ax2.plot(idx, 100 * np.asarray(rms_m), "k--", label="RMS distance (cm)")
    ax2.set_ylabel("RMS point-to-plane distance (cm)")
    h1, l1 = ax.get_legend_handles_labels()
    h2, l2 = ax2.get_legend_handles_labels()
    ax.legend(h1 + h2, l1 + l2, fontsize=8, loc="upper right")
    fig.tight_layout()
    return _png(fig)


def motion_png(t_s: Floats, angular_rate: Floats, specific_force: Floats, segments_s: F64) -> bytes:
    """Angular rate and specific force over the recording read, the segment(s) used shaded."""
    plt = pyplot()
    fig, (ax_w, ax_a) = plt.subplots(2, 1, figsize=(9.0, 5.0), sharex=True)
    for ax, v, unit, name in (
        (ax_w, angular_rate, "rad/s", "angular rate"),
        (ax_a, specific_force, "m/s^2", "specific force"),
    ):
        v = np.asarray(v, dtype=np.float64)
        for i in range(3):
            ax.plot(t_s, v[:, i], lw=0.7, color=_COLOURS[i], label=_AXES[i])
        ax.plot(t_s, np.linalg.norm(v, axis=1), lw=0.9, color="black", label="norm")
        for k, (a, b) in enumerate(np.asarray(segments_s).reshape(-1, 2)):
            ax.axvspan(a, b, color="gold", alpha=0.18, label="segment used" if k == 0 else None)
        ax.set_ylabel(f"{name} ({unit})")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7, ncol=5, loc="upper right")
    ax_a.set_xlabel("time since the first IMU sample read (s)")
    fig.tight_layout()
    return _png(fig)


def map_png(
    before_top: Floats,
    after_top: Floats,
    before_side: Floats,
    after_side: Floats,
    region: F64,
    entropies: tuple[float, float],
    slabs: tuple[float, float],
    zoom: tuple[Floats, Floats, F64] | None = None,
) -> bytes:
    """Top view and side slice of the map with the initial and the final calibration, and a
    zoomed top view (``zoom``: the points before, after, and the window ``[x0, x1, y0, y1]``)."""
    plt = pyplot()
    x0, x1, y0, y1, z0, z1 = (float(v) for v in region)
    top_ratio = (y1 - y0) / max(x1 - x0, 1e-6)
    side_ratio = (z1 - z0) / max(x1 - x0, 1e-6)
    width = 6.0
    ratios = [max(top_ratio, 0.2), max(side_ratio, 0.1)] + ([1.0] if zoom is not None else [])
    fig, axes = plt.subplots(
        len(ratios),
        2,
        figsize=(2 * width + 0.6, width * sum(ratios) + 1.2 + 0.5 * len(ratios)),
        gridspec_kw={"height_ratios": ratios},
        squeeze=False,
    )
    titles = ("initial calibration", "final calibration")
    for col, (top, side) in enumerate(((before_top, before_side), (after_top, after_side))):
        ent = entropies[col]
        ent_text = f"mean map entropy {ent:.3f}" if np.isfinite(ent) else "entropy n/a"
        ax = axes[0][col]
        top = np.asarray(top)
        ax.plot(top[:, 0], top[:, 1], ",", color="black", alpha=0.6)
        ax.set_xlim(x0, x1)
        ax.set_ylim(y0, y1)
        ax.set_aspect("equal")
        ax.set_title(f"Top view, {titles[col]} ({ent_text})", fontsize=9)
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
        ax = axes[1][col]
        side = np.asarray(side)
        ax.plot(side[:, 0], side[:, 1], ",", color="black", alpha=0.6)
        ax.set_xlim(x0, x1)
        ax.set_ylim(z0, z1)
        ax.set_aspect("equal")
        ax.set_title(f"Side slice, {titles[col]}", fontsize=9)
        ax.set_xlabel("x (m)")
        ax.set_ylabel("z, up (m)")
        if zoom is not None:
            ax = axes[2][col]
            pts = np.asarray(zoom[col])
            ax.plot(pts[:, 0], pts[:, 1], ".", color="black", markersize=1.0, alpha=0.5)
            w = np.asarray(zoom[2], dtype=np.float64)
            ax.set_xlim(w[0], w[1])
            ax.set_ylim(w[2], w[3])
            ax.set_aspect("equal")
            ax.set_title(f"Top view zoomed to {w[1] - w[0]:.1f} m, {titles[col]}", fontsize=9)
            ax.set_xlabel("x (m)")
            ax.set_ylabel("y (m)")
            ax.grid(True, alpha=0.3)
    fig.suptitle(
        f"Map: horizontal slab {slabs[0]:.2f} m thick at the first IMU position (top) and "
        f"vertical slab {slabs[1]:.2f} m thick through it (side); same region",
        fontsize=9,
    )
    fig.tight_layout()
    return _png(fig)
