"""Statistics of a fit's residuals: their size against the noise, and structure left in them.

A model that explains the data leaves residuals that are noise: of the noise's size and
uncorrelated with anything the sensors measured. Two kinds of statistics are computed here, on
plain arrays (the pipeline supplies residuals and features):

* :func:`normalised_chi2`: the residual sum of squares per sample over the noise variance.
* :func:`regression_pattern` / :func:`group_pattern`: how much of the residual variance a
  feature explains (a linear regression on features such as the angular rate, or group means
  such as one mean per beam), with an F test. With hundreds of thousands of samples a tiny
  pattern is significant, so a pattern is reported as material only when it is both
  significant and explains a share of the residual variance above a threshold.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from licalib_cli.consistency.distributions import f_sf

__all__ = [
    "Chi2",
    "Pattern",
    "group_pattern",
    "normalised_chi2",
    "regression_pattern",
]

F64 = npt.NDArray[np.float64]


@dataclass(frozen=True)
class Chi2:
    """Residual sum of squares against the noise.

    Attributes:
        per_dof: ``sum (r / sigma)^2 / n``; about 1 (slightly below: the fit absorbs a little
            noise) when the model explains the data and the noise is right.
        samples: number of scalar residuals ``n``.
        rms: root mean square of the residuals, in their unit.
        sigma: the noise standard deviation used (RMS over axes), in the residuals' unit.
    """

    per_dof: float
    samples: int
    rms: float
    sigma: float


@dataclass(frozen=True)
class Pattern:
    """Structure of residuals against one feature.

    Attributes:
        feature: what the residuals were compared with (e.g. ``"angular rate"``, ``"beam"``).
        explained: share of the residual variance the feature explains (R^2, 0..1).
        statistic: F statistic.
        p_value: probability of an F statistic at least this large if the residuals were noise.
        dof: (numerator, denominator) degrees of freedom.
        size: RMS of the part of the residuals the feature explains, in the residuals' unit.
    """

    feature: str
    explained: float
    statistic: float
    p_value: float
    dof: tuple[int, int]
    size: float

    def material(self, min_explained: float, max_p_value: float = 1e-6) -> bool:
        """Significant and large enough to matter."""
        return self.p_value < max_p_value and self.explained > min_explained


def normalised_chi2(residuals: npt.ArrayLike, sigma: float | npt.ArrayLike) -> Chi2:
    """``sum (r / sigma)^2 / n`` of (N,) or (N, k) residuals with per-column sigmas.

    Args:
        residuals: (N,) or (N, k) residuals.
        sigma: noise standard deviations (same unit): scalar, (k,) per column, (N, k) per
            residual, or (N,) per residual of (N,) residuals.

    Returns:
        The statistic (NaN with no residuals).
    """
    r = np.asarray(residuals, dtype=np.float64)
    if r.ndim == 1:
        r = r[:, None]
    s = np.asarray(sigma, dtype=np.float64)
    if s.ndim == 1 and r.shape[1] == 1 and s.shape[0] == r.shape[0]:
        s = s[:, None]  # one sigma per residual of a single column
    s = np.broadcast_to(s, r.shape)
    n = r.size
    if n == 0:
        return Chi2(float("nan"), 0, float("nan"), float("nan"))
    per_dof = float(np.sum((r / s) ** 2) / n)
    return Chi2(per_dof, int(n), float(np.sqrt(np.mean(r**2))), float(np.sqrt(np.mean(s**2))))


def regression_pattern(
    residuals: npt.ArrayLike, features: npt.ArrayLike, name: str, intercept: bool = True
) -> Pattern:
    """Variance of (N, k) residuals explained by a linear function of (N, m) features.

    Every residual column is regressed on the same features (with an intercept by default, so
    that a constant offset is not counted as structure); the explained sums of squares are
    pooled over the columns.

    Args:
        residuals: (N,) or (N, k).
        features: (N,) or (N, m).
        name: the feature's name, for the report.
        intercept: also fit a constant (not counted as explained).

    Returns:
        The pattern statistics.
    """
    r = np.asarray(residuals, dtype=np.float64)
    r = r[:, None] if r.ndim == 1 else r
    x = np.asarray(features, dtype=np.float64)
    x = x[:, None] if x.ndim == 1 else x
    n, k = r.shape
    m = x.shape[1]
    if intercept:
        r = r - r.mean(axis=0)
        x = x - x.mean(axis=0)
    scale = np.sqrt(np.mean(x**2, axis=0))
    x = x / np.where(scale > 0, scale, 1.0)
    coef, *_ = np.linalg.lstsq(x, r, rcond=None)
    fitted = x @ coef
    ss_model = float(np.sum(fitted**2))
    ss_total = float(np.sum(r**2))
    return _pattern(
        name, ss_model, ss_total - ss_model, m * k, (n - m - int(intercept)) * k, ss_total, n * k
    )


def group_pattern(residuals: npt.ArrayLike, groups: npt.ArrayLike, name: str) -> Pattern:
    """Variance of (N,) residuals explained by one mean per group (one-way ANOVA).

    Args:
        residuals: (N,) residuals.
        groups: (N,) integer group of each residual (e.g. the beam).
        name: the grouping's name, for the report.

    Returns:
        The pattern statistics (groups with a single residual add nothing).
    """
    r = np.asarray(residuals, dtype=np.float64).reshape(-1)
    g = np.asarray(groups, dtype=np.int64).reshape(-1)
    _, inverse = np.unique(g, return_inverse=True)
    counts = np.bincount(inverse)
    sums = np.bincount(inverse, weights=r)
    mean_all = float(r.mean()) if r.size else 0.0
    means = sums / np.maximum(counts, 1)
    ss_between = float(np.sum(counts * (means - mean_all) ** 2))
    ss_total = float(np.sum((r - mean_all) ** 2))
    n_groups = int(np.count_nonzero(counts))
    return _pattern(
        name,
        ss_between,
        ss_total - ss_between,
        n_groups - 1,
        r.size - n_groups,
        ss_total,
        r.size,
    )


def _pattern(
    name: str, ss_model: float, ss_resid: float, df1: int, df2: int, ss_total: float, n: int
) -> Pattern:
    if df1 <= 0 or df2 <= 0 or ss_total <= 0.0:
        return Pattern(name, 0.0, 0.0, 1.0, (max(df1, 0), max(df2, 0)), 0.0)
    f = (ss_model / df1) / max(ss_resid / df2, 1e-300)
    p = f_sf(f, df1, df2)
    return Pattern(
        feature=name,
        explained=ss_model / ss_total,
        statistic=float(f),
        p_value=p,
        dof=(df1, df2),
        size=float(np.sqrt(ss_model / max(n, 1))),
    )
