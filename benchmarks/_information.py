"""What a fit's own information allows: the extrinsic errors an unbiased estimator with the
final solve's covariance makes (planes held fixed, none of the checks' enlargements).

A benchmark target below these is beyond the data, not beyond the solver: when the observed
errors over many seeds match the expected ones (their ratio to the solver's sigmas has an RMS
near 1), the estimator already uses the information the problem holds, and a lower target needs
more of it (motion, points, priors).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from licalib_cli.pipeline.checks import correlated_with

DRAWS = 100_000
"""Monte Carlo draws per run (the chances below to about 0.002)."""

LIMITS = (3.0, 0.05, 0.1)
"""The clean runs' extrinsic limits: translation mm, rotation deg, time offset ms."""


def outside_limits(errors: dict, limits: tuple[float, float, float] = LIMITS) -> bool:
    """Whether an extrinsic's errors (``translation_mm``, ``rotation_deg``, ``time_offset_ms``)
    miss ``limits``: any of the three beyond its limit (as :func:`information_bound` counts)."""
    return bool(
        errors["translation_mm"] > limits[0]
        or errors["rotation_deg"] > limits[1]
        or errors["time_offset_ms"] > limits[2]
    )


def _block(names: Sequence[str], prefix: str, axes: str) -> list[int]:
    return [list(names).index(f"{prefix}.{a}") for a in axes]


def plane_factors(report: object, raw_sigma: object) -> np.ndarray:
    """(7,) what the checks multiply the solver's extrinsic sigmas by for the map planes' own
    uncertainty (``run.checks.raw_sigma`` over the solver's sigmas; the solver holds the planes
    fixed although they were fitted to the same points). 1 where a sigma is not finite."""
    names = list(report.calibration_names)  # type: ignore[attr-defined]
    std = np.asarray(report.std, dtype=float)  # type: ignore[attr-defined]
    ix = [
        *_block(names, "ext.translation", "xyz"),
        *_block(names, "ext.rotation", ["rx", "ry", "rz"]),  # type: ignore[arg-type]
        names.index("ext.time_offset"),
    ]
    with np.errstate(divide="ignore", invalid="ignore"):
        f = np.asarray(raw_sigma, dtype=float) / std[ix]
    return np.where(np.isfinite(f) & (f > 0), f, 1.0)


def information_bound(
    names: Sequence[str],
    covariance: object,
    seed: int,
    limits: tuple[float, float, float] = LIMITS,
    factors: object = None,
) -> dict:
    """Expected errors and the chance of missing ``limits`` (translation mm, rotation deg,
    time offset ms; a run misses when any of the three is beyond its limit) for an unbiased
    estimator with ``covariance`` over the calibration coordinates ``names`` (the solver
    report's ``calibration_names``: ``ext.translation.x`` in m, ``ext.rotation.rx`` in rad,
    ``ext.time_offset`` in s). Also the per-axis translation sigmas and the three coordinates
    most correlated with the least determined translation axis. ``factors`` (7,): each
    extrinsic sigma times this (:func:`plane_factors`), the correlations kept."""
    cov = np.asarray(covariance, dtype=float)
    it = _block(names, "ext.translation", "xyz")
    ir = _block(names, "ext.rotation", ["rx", "ry", "rz"])  # type: ignore[arg-type]
    idt = list(names).index("ext.time_offset")
    ix = [*it, *ir, idt]
    units = np.array([1e3] * 3 + [np.degrees(1.0)] * 3 + [1e3])  # mm, deg, ms
    if factors is not None:
        units = units * np.asarray(factors, dtype=float)
    c = cov[np.ix_(ix, ix)] * np.outer(units, units)
    c = 0.5 * (c + c.T)
    draws = np.random.default_rng(seed).multivariate_normal(
        np.zeros(7), c, size=DRAWS, check_valid="ignore"
    )
    t = np.linalg.norm(draws[:, :3], axis=1)
    r = np.linalg.norm(draws[:, 3:6], axis=1)
    dt = np.abs(draws[:, 6])
    outside = (t > limits[0]) | (r > limits[1]) | (dt > limits[2])
    weak = names[it[int(np.argmax(np.diag(cov)[it]))]]
    return {
        "expected_translation_mm": float(t.mean()),
        "expected_rotation_deg": float(r.mean()),
        "expected_time_offset_ms": float(dt.mean()),
        "p_translation_over": float(np.mean(t > limits[0])),
        "p_time_offset_over": float(np.mean(dt > limits[2])),
        "p_outside": float(np.mean(outside)),
        "solver_translation_sd_mm": [round(float(x), 3) for x in np.sqrt(np.diag(c)[:3])],
        "solver_time_offset_sd_ms": round(float(np.sqrt(c[6, 6])), 4),
        "weakest_axis": weak,
        "weakest_axis_correlations": {
            n: round(c, 2) for n, c in correlated_with(names, cov, weak)[:3]
        },
    }
