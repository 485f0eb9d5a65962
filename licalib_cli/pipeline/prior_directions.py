"""What rests on the configured prior of the extrinsic translation, not on the data.

A measured lever arm (``initialization.translation_m`` with ``translation_sigma_m``) enters every
round's problem as a Gaussian prior, so the solver's information holds it too: a direction the
data leave undetermined (the vertical on planar motion) is then determined, by the prior. The
verdict must still say what the data determine, so the prior's part is taken out again: the
prior adds ``diag((d / sigma)^2)`` to the scaled calibration information ``S_d`` (``d`` the
characteristic scales; a prior on a calibration block couples with nothing else, so the
trajectory's elimination leaves it as it is), and ``S_d`` minus that is the data's own. It is
judged in the default characteristic scales (the prior widens the translation's to
:data:`~licalib_cli.estimation.PRIOR_SCALE_FACTOR` times its sigma in the problems, so that the
solver uses the prior along every direction): its directions below the truncation threshold that
lie mostly in the prior's coordinates rest on the prior (each named, with the prior's sigma along
it), and what the data determine is counted as the solver counts it, with those directions
counted as undetermined.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from licalib_cli.config import CalibConfig
from licalib_cli.consistency.distributions import chi2_sf
from licalib_cli.estimation import CALIBRATION_SCALES
from licalib_cli.pipeline.settings import prior_sd
from licalib_cli.residuals import EXT_TRANSLATION
from licalib_cli.sections import p_is
from licalib_cli.solver.lm import LMParams, SolverReport, observable_coordinates
from licalib_cli.solver.observability import describe_direction, truncation_mask

__all__ = [
    "PRIOR_CONFLICT_P",
    "OnPrior",
    "PriorConflict",
    "added_variance",
    "data_determined",
    "data_translation_std",
    "lever_arm_conflict",
    "on_prior",
    "prior_conflict",
]

F64 = npt.NDArray[np.float64]

PRIOR_CONFLICT_P = 1e-3
"""The measured lever arm and the data disagree below this p-value (the split halves' level)."""


@dataclass(frozen=True)
class OnPrior:
    """A direction of the extrinsic translation the data leave to the prior.

    Attributes:
        direction: (3,) unit vector, IMU frame (sign: largest component positive).
        sigma_m: the prior's standard deviation along it.
        text: one sentence naming it.
    """

    direction: tuple[float, float, float]
    sigma_m: float
    text: str


def _translation_index(names: Sequence[str]) -> list[int]:
    """Positions of the extrinsic translation's x, y, z among calibration coordinates ``names``."""
    return [names.index(f"{EXT_TRANSLATION}.{a}") for a in "xyz"]


def _data_spectrum(
    report: SolverReport, prior_sd: Mapping[str, float]
) -> tuple[F64, F64, F64, npt.NDArray[np.bool_]]:
    """Eigenvalues and eigenvectors of the data's own scaled information in the default scales,
    those scales, and which coordinates have a prior."""
    names = report.calibration_names
    scale = np.asarray(report.information.scale, dtype=np.float64)
    default = np.array(
        [
            CALIBRATION_SCALES[EXT_TRANSLATION][0] if n.startswith(f"{EXT_TRANSLATION}.") else d
            for n, d in zip(names, scale, strict=True)
        ]
    )
    ratio = default / scale
    info = np.asarray(report.information.information, dtype=np.float64)
    prior = np.array(
        [
            (d / prior_sd[n]) ** 2 if n in prior_sd else 0.0
            for n, d in zip(names, default, strict=True)
        ]
    )
    data = ratio[:, None] * info * ratio[None, :] - np.diag(prior)
    values, vectors = np.linalg.eigh(0.5 * (data + data.T))
    return values, vectors, default, prior > 0.0


def _undetermined(
    report: SolverReport, prior_sd: Mapping[str, float]
) -> tuple[F64, npt.NDArray[np.bool_]]:
    """The data's own truncated directions (columns, in the default scales) and which
    coordinates have a prior."""
    values, vectors, _, with_prior = _data_spectrum(report, prior_sd)
    keep = truncation_mask(values, float(report.tsvd_threshold))
    return vectors[:, ~keep], with_prior


def data_translation_std(report: SolverReport, prior_sd: Mapping[str, float]) -> float:
    """The largest 1-sigma of the extrinsic translation's axes along what the data determine,
    m, with a prior (``prior_sd`` not empty): from the truncated pseudo-inverse of the data's own
    information. The rounds settle against it: the prior's sigma along what the data leave to it
    says nothing of how far the rest may still move."""
    names = report.calibration_names
    values, vectors, default, _ = _data_spectrum(report, prior_sd)
    keep = truncation_mask(values, float(report.tsvd_threshold))
    idx = _translation_index(names)
    rows = vectors[idx][:, keep]
    variance = np.sum(rows**2 / values[keep], axis=1) * default[idx] ** 2
    return float(np.sqrt(np.max(variance)))


def on_prior(report: SolverReport, prior_sd: Mapping[str, float]) -> tuple[OnPrior, ...]:
    """Directions of the extrinsic translation that rest on its prior (``prior_sd``: calibration
    coordinate -> sigma): the data's own information along them is below the truncation
    threshold and they lie mostly in the prior's coordinates. Empty without a prior."""
    if not prior_sd or report.information.information.size == 0:
        return ()
    trunc, with_prior = _undetermined(report, prior_sd)
    names = report.calibration_names
    idx = _translation_index(names)
    sd = np.array([prior_sd.get(f"{EXT_TRANSLATION}.{a}", np.inf) for a in "xyz"])
    out = []
    for u in trunc.T:
        if np.sum(u[with_prior] ** 2) < 0.5:
            continue
        n = u[idx] / np.linalg.norm(u[idx])  # the translation's scales are equal
        if n[np.argmax(np.abs(n))] < 0.0:
            n = -n
        sigma = float(np.sqrt(np.sum(n**2 * sd**2)))
        text = describe_direction(u, names, report.information.owners, verdict="").text
        out.append(
            OnPrior(
                (float(n[0]), float(n[1]), float(n[2])),
                sigma,
                f"{text}: not determined by the data; taken from initialization.translation_m "
                f"with the prior's {1e3 * sigma:.1f} mm (initialization.translation_sigma_m)",
            )
        )
    return tuple(out)


def data_determined(
    report: SolverReport, prior_sd: Mapping[str, float], names: Sequence[str]
) -> npt.NDArray[np.bool_]:
    """Which of ``names`` (calibration coordinates) the data determine: ``report.observable``
    without a prior; with one, the solver's rule applied to the data's own information, the
    directions resting on the prior counted as undetermined (a direction made mostly of
    intrinsics known a priori leaves its coordinates determined, as in the solver)."""
    index = [report.calibration_names.index(n) for n in names]
    if not prior_sd:
        return np.asarray(report.observable, dtype=bool)[index]
    trunc, _ = _undetermined(report, prior_sd)
    observable, _ = observable_coordinates(
        trunc, report.information.owners, LMParams.bounded_blocks
    )
    return observable[index]


@dataclass(frozen=True)
class PriorConflict:
    """The measured lever arm against the data's own estimate of it.

    With a Gaussian prior the estimate is a compromise: at it the data's information
    ``S`` and the prior's ``P`` balance, ``S (x - x_data) + P (x - mean) = 0``, so the data's
    own estimate is ``x_data = x + S^+ P (x - mean)`` (``S^+`` the truncated pseudo-inverse of
    the data's information, nothing along what the data leave to the prior). Its difference from
    the measurement has the covariance ``S^+ + P^-1`` when both are right.

    Attributes:
        difference_m: (3,) the data's own translation minus the measurement, IMU frame.
        pull_m: (3,) how far the prior pulled the estimate from the data's own.
        statistic: chi-square of the difference with that covariance.
        dof: the translation directions the data determine.
        p_value: its probability when both are right.
    """

    difference_m: tuple[float, float, float]
    pull_m: tuple[float, float, float]
    statistic: float
    dof: int
    p_value: float

    @property
    def disagrees(self) -> bool:
        """Whether the measurement and the data disagree (:data:`PRIOR_CONFLICT_P`)."""
        return self.p_value < PRIOR_CONFLICT_P

    @property
    def text(self) -> str:
        """One sentence for the verdict: the disagreement, its size and what to do."""
        diff = ", ".join(f"{1e3 * v:+.1f}" for v in self.difference_m)
        pull = float(np.linalg.norm(self.pull_m))
        return (
            "The measured lever arm (initialization.translation_m) disagrees with the data: "
            f"their own estimate differs from it by [{diff}] mm (chi-square "
            f"{self.statistic:.1f} on {self.dof}, {p_is(self.p_value)}) and it pulled the "
            f"translation {1e3 * pull:.1f} mm away from that (the sigmas include this); check "
            "the measurement, or widen initialization.translation_sigma_m."
        )

    def covered(self, sigma_m: npt.ArrayLike) -> F64:
        """(3,) translation sigmas with the pull added in quadrature when the measurement and
        the data disagree (the estimate is then a compromise the data do not support: covered as
        far as the prior pulled it from the data's own); unchanged otherwise."""
        sigma = np.asarray(sigma_m, dtype=np.float64)
        if not self.disagrees:
            return sigma.copy()
        return np.sqrt(sigma**2 + np.square(self.pull_m))


def added_variance(raw: npt.ArrayLike, sigma: npt.ArrayLike) -> F64:
    """What the checks added to each solver variance, ``sigma**2 - raw**2`` (m^2; zero where the
    solver's sigma is unbounded, unbounded where the checks' is)."""
    r = np.asarray(raw, dtype=np.float64)
    s = np.asarray(sigma, dtype=np.float64)
    bounded = np.isfinite(r)
    added = np.where(bounded, s**2 - np.where(bounded, r, 0.0) ** 2, 0.0)
    return np.where(np.isfinite(s), np.maximum(added, 0.0), np.inf)


def lever_arm_conflict(
    report: SolverReport,
    cfg: CalibConfig,
    estimate_m: npt.ArrayLike,
    added_m2: npt.ArrayLike = 0.0,
) -> PriorConflict | None:
    """:func:`prior_conflict` of the configured measured lever arm
    (``initialization.translation_m`` with ``translation_sigma_m``; None without one) and the
    fit's ``report`` at ``estimate_m``."""
    mean = cfg.initialization.translation_m
    if mean is None:
        return None
    return prior_conflict(report, prior_sd(cfg), estimate_m, mean, added_m2)


def prior_conflict(
    report: SolverReport,
    prior_sd: Mapping[str, float],
    estimate_m: npt.ArrayLike,
    mean_m: npt.ArrayLike,
    added_m2: npt.ArrayLike = 0.0,
) -> PriorConflict | None:
    """How the measured lever arm (``mean_m``, sigmas ``prior_sd``) compares with the data's own
    estimate, from the fit's ``report`` at ``estimate_m`` (see :class:`PriorConflict`).

    ``added_m2`` (scalar or (3,), m^2) is what the checks added to the solver's variances of
    the translation's axes (:func:`added_variance`: the effects held fixed, the split halves,
    the residuals' chi-square): the data's own estimate is as uncertain as the checks found the
    result, so its spread grows alike before it is compared with the measurement; where the
    checks leave a sigma unbounded the data's own estimate is not known and nothing is
    compared. None without a prior, when the data determine no translation direction or when
    the checks bound none.
    """
    added = np.broadcast_to(np.asarray(added_m2, dtype=np.float64), (3,))
    if not prior_sd or report.information.information.size == 0 or not np.all(np.isfinite(added)):
        return None
    values, vectors, default, _ = _data_spectrum(report, prior_sd)
    keep = truncation_mask(values, float(report.tsvd_threshold))
    names = report.calibration_names
    idx = _translation_index(names)
    sd = np.array([prior_sd[f"{EXT_TRANSLATION}.{a}"] for a in "xyz"])
    d = default[idx]
    moved = np.asarray(estimate_m, dtype=np.float64) - np.asarray(mean_m, dtype=np.float64)
    g = np.zeros(len(names))
    g[idx] = (d / sd) ** 2 * moved / d  # the prior's pull on the scaled coordinates
    kept, w = vectors[:, keep], values[keep]
    pull = (kept @ ((kept.T @ g) / w))[idx] * d
    rows = kept[idx] * d[:, None]
    data_cov = (rows / w) @ rows.T
    own = np.linalg.eigvalsh(0.5 * (data_cov + data_cov.T))
    dof = int(np.count_nonzero(own > 1e-6 * sd.min() ** 2))
    if dof == 0:
        return None
    difference = moved + pull
    total = data_cov + np.diag(added + sd**2)
    statistic = float(difference @ np.linalg.solve(total, difference))
    return PriorConflict(
        (float(difference[0]), float(difference[1]), float(difference[2])),
        (float(pull[0]), float(pull[1]), float(pull[2])),
        statistic,
        dof,
        float(chi2_sf(statistic, dof)),
    )
