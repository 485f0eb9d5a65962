"""Score (Lagrange-multiplier) tests of effects the model holds fixed, and what they would move.

At the estimate of a model, the cost's gradient with respect to the estimated parameters is
zero, but not with respect to a parameter the model holds fixed (an IMU scale, a per-beam range
offset). The score test asks whether freeing such a group of parameters would reduce the cost
more than noise explains, without refitting: with whitened residuals, the gradient ``g_e`` and
the information of the group after profiling out everything estimated,

    LM = g_e^T (S_ee - S_eb S_bb^-1 S_be)^+ g_e  ~  chi^2(rank)   when the group is zero,

where ``S`` is the calibration block of the information after the trajectory has been
eliminated (the Schur complement the solver uses; ``b`` the estimated calibration coordinates,
``e`` the group). The same quantities give the Gauss-Newton step that freeing the group would
take, and so how far the estimated coordinates would move with it (their *shift*), together
with the variance that shift has when the group is truly zero (noise alone moves them when a
group is freed). A significant score with a shift beyond the estimate's own uncertainty means
the fixed model biases the result.

Everything here is plain linear algebra on ``S`` and ``b`` (no I/O); the pipeline builds them.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
import numpy.typing as npt

from licalib_cli.consistency.distributions import chi2_logsf, chi2_sf

__all__ = [
    "EffectScore",
    "EffectSelection",
    "combined_score",
    "explained_shares",
    "measured_shift",
    "score_effects",
    "select_effects",
]

F64 = npt.NDArray[np.float64]


@dataclass(frozen=True)
class EffectScore:
    """Score test of one group of fixed parameters.

    Attributes:
        name: the group (e.g. ``"gyro_scale"``).
        statistic: LM statistic (divided by the variance factor).
        rank: degrees of freedom (directions of the group the data determine).
        p_value: probability of a statistic at least this large if the group is zero.
        estimate: (k,) one Gauss-Newton estimate of the group's parameters (their own units).
        sigma: (k,) its standard deviation (``inf`` along undetermined directions).
        shift: (m,) change of the estimated coordinates if the group were freed (own units).
        shift_sigma: (m,) standard deviation of that change when the group is zero.
        information: (rank,) eigenvalues of the group's profiled information along the
            directions the data determine, divided by the variance factor, ascending: an effect
            ``d`` raises the statistic's expectation from ``rank`` by ``d^T I d``, between
            ``|d|^2 information[0]`` and ``|d|^2 information[-1]`` depending on its direction.
        prior_shift_sigma: (m,) standard deviation the estimated coordinates gain when the
            group, held at zero, is in truth known only to within a prior (each coordinate with
            its own standard deviation, independent): the spread of the group's posterior (data
            and prior) carried into the estimated coordinates; zeros without a prior.
        gradient: (k,) the group's gradient with the estimated coordinates profiled out,
            divided by the variance factor (``statistic = gradient^T pinv(profiled_information)
            gradient``): the tests of one group on several recordings of the same rig combine
            by summing these two (:func:`combined_score`).
        profiled_information: (k, k) the group's information with the estimated coordinates
            profiled out, divided by the variance factor.
        prior_shift: (m,) the change of the estimated coordinates if the group, held at zero,
            were at its posterior mean (data and prior): what holding it at zero biases them by,
            as far as the data and the prior tell; zeros without a prior.
    """

    name: str
    statistic: float
    rank: int
    p_value: float
    estimate: F64
    sigma: F64
    shift: F64
    shift_sigma: F64
    information: F64 = field(default_factory=lambda: np.zeros(0))
    prior_shift_sigma: F64 = field(default_factory=lambda: np.zeros(0))
    gradient: F64 = field(default_factory=lambda: np.zeros(0))
    profiled_information: F64 = field(default_factory=lambda: np.zeros((0, 0)))
    prior_shift: F64 = field(default_factory=lambda: np.zeros(0))

    @property
    def shift_z(self) -> F64:
        """(m,) shift over its null standard deviation."""
        return self.shift / np.maximum(self.shift_sigma, 1e-300)


def _pinv_psd(a: F64, relative: float, floor: float = 0.0) -> tuple[F64, int]:
    """Pseudo-inverse of a symmetric PSD matrix keeping eigenvalues above ``relative * max``
    and above ``floor``."""
    if a.size == 0:
        return np.zeros_like(a), 0
    w, v = np.linalg.eigh(0.5 * (a + a.T))
    top = float(w.max()) if w.size else 0.0
    keep = (w > relative * max(top, 1e-300)) & (w > floor)
    return (v[:, keep] / w[keep]) @ v[:, keep].T, int(keep.sum())


def score_effects(
    S: npt.ArrayLike,
    b: npt.ArrayLike,
    base: npt.ArrayLike,
    groups: Mapping[str, npt.ArrayLike],
    variance_factor: float = 1.0,
    relative_rank: float = 1e-8,
    prior_sigma: Mapping[str, npt.ArrayLike] | None = None,
    floors: Mapping[str, float] | None = None,
) -> list[EffectScore]:
    """Score tests of several candidate groups against the same estimated coordinates.

    Args:
        S: (N, N) Schur complement (information) of the calibration coordinates: the estimated
            ones and every candidate's, trajectory eliminated, whitened residuals.
        b: (N,) right-hand side ``-g`` after the elimination (zero on estimated coordinates at
            a converged estimate).
        base: indices of the estimated coordinates in ``S``.
        groups: name -> indices of each candidate group (disjoint from ``base``).
        variance_factor: a-posteriori variance factor of the fit (chi-square per degree of
            freedom): the statistic is divided by it and the shifts' sigmas multiplied by its
            root, so that a noise level off by a constant factor does not make every group
            significant.
        relative_rank: eigenvalues below this fraction of a group's largest do not count
            (directions the data cannot determine).
        prior_sigma: name -> (k,) prior standard deviation of each coordinate of a group (its
            own units; 0 for a coordinate known exactly) for
            :attr:`EffectScore.prior_shift_sigma`. Freeing a group ``e`` with the Gaussian prior
            ``N(0, P)`` adds ``A (S_ee.b / f + P^-1)^-1 A^T`` to the covariance of the estimated
            coordinates, ``A = S_bb^-1 S_be`` its shift per unit of ``e``, ``S_ee.b`` its
            profiled information and ``f`` the variance factor (at least 1): between nothing
            (a prior far inside what the data determine) and the shift's null variance (a prior
            far wider).
        floors: name -> profiled information (eigenvalue) at or below which a direction of
            that group is not tested either (its own units): a direction the recording
            determines far worse than any plausible size of the effect, where only a misfit
            from elsewhere can show (default: none).

    Returns:
        One :class:`EffectScore` per group, in the order given.
    """
    s = np.asarray(S, dtype=np.float64)
    rhs = np.asarray(b, dtype=np.float64)
    bi = np.asarray(base, dtype=np.intp)
    vf = max(float(variance_factor), 1e-12)
    s_bb_inv, _ = _pinv_psd(s[np.ix_(bi, bi)], 1e-12)
    step_base = s_bb_inv @ rhs[bi]
    out = []
    for name, idx in groups.items():
        e = np.asarray(idx, dtype=np.intp)
        s_eb, s_ee_b, g_e = _profiled(s, rhs, bi, e, s_bb_inv, step_base)
        floor = 0.0 if floors is None else float(floors.get(name, 0.0))
        inv, rank = _pinv_psd(s_ee_b, relative_rank, floor)
        statistic = float(g_e @ inv @ g_e) / vf
        p_value = float(chi2_sf(statistic, rank)) if rank else 1.0
        d_e = inv @ g_e
        shift = -s_bb_inv @ s_eb.T @ d_e
        v_shift = s_bb_inv @ s_eb.T @ inv @ s_eb @ s_bb_inv * max(vf, 1.0)
        var_e = np.diag(inv) * max(vf, 1.0)
        w, v = (
            np.linalg.eigh(0.5 * (s_ee_b + s_ee_b.T)) if e.size else (np.zeros(0), np.zeros((0, 0)))
        )
        weak = (w <= relative_rank * max(float(w.max()) if w.size else 0.0, 1e-300)) | (w <= floor)
        undetermined = np.sum(v[:, weak] ** 2, axis=1) > 1e-4 if e.size else np.zeros(0, bool)
        sigma_e = np.where(undetermined, np.inf, np.sqrt(np.clip(var_e, 0.0, None)))
        prior = None if prior_sigma is None else prior_sigma.get(name)
        out.append(
            EffectScore(
                name=name,
                statistic=statistic,
                rank=rank,
                p_value=p_value,
                estimate=d_e,
                sigma=sigma_e,
                shift=shift,
                shift_sigma=np.sqrt(np.clip(np.diag(v_shift), 0.0, None)),
                information=np.sort(w[~weak]) / vf if e.size else np.zeros(0),
                prior_shift_sigma=_prior_shift_sigma(
                    s_bb_inv @ s_eb.T, s_ee_b / max(vf, 1.0), prior, bi.size
                ),
                prior_shift=_prior_shift(
                    s_bb_inv @ s_eb.T, s_ee_b / max(vf, 1.0), g_e / max(vf, 1.0), prior, bi.size
                ),
                gradient=g_e / vf,
                profiled_information=s_ee_b / vf,
            )
        )
    return out


def measured_shift(
    S: npt.ArrayLike,
    b: npt.ArrayLike,
    base: npt.ArrayLike,
    idx: npt.ArrayLike,
    value: npt.ArrayLike,
    sigma: npt.ArrayLike,
    variance_factor: float = 1.0,
) -> tuple[F64, F64]:
    """How far holding a group at zero moves the estimated coordinates when its size is
    measured apart from the fit.

    The data alone give the group ``N(I^-1 g, I^-1)`` (``I`` its information with the estimated
    coordinates profiled out, ``g`` its gradient, both divided by the variance factor); an
    independent measurement gives ``N(value, sigma^2)``. At their combined mean
    ``m = (I + Sigma^-1)^-1 (g + Sigma^-1 value)`` the estimated coordinates sit at ``-A m``
    from where the group held at zero put them (``A = S_bb^-1 S_be``, their shift per unit of the
    group), with the spread ``A (I + Sigma^-1)^-1 A^T``. A measurement far sharper than the
    data (an IMU clock's rate from the stamps against the record times) sets the group
    whatever the data say; a vague one leaves the data's own estimate.

    Args:
        S, b, base: as :func:`score_effects`'s.
        idx: (k,) indices of the group in ``S``.
        value: (k,) the measured size, the coordinates' own units.
        sigma: (k,) its 1-sigma (positive).
        variance_factor: as :func:`score_effects`'s (clamped below at 1).

    Returns:
        ``(shift (m,), its standard deviation (m,))`` of the estimated coordinates, in the
        order of ``base``.
    """
    s = np.asarray(S, dtype=np.float64)
    rhs = np.asarray(b, dtype=np.float64)
    bi = np.asarray(base, dtype=np.intp)
    e = np.asarray(idx, dtype=np.intp)
    vf = max(float(variance_factor), 1.0)
    s_bb_inv, _ = _pinv_psd(s[np.ix_(bi, bi)], 1e-12)
    s_eb, s_ee_b, g_e = _profiled(s, rhs, bi, e, s_bb_inv, s_bb_inv @ rhs[bi])
    a = s_bb_inv @ s_eb.T
    sd = np.broadcast_to(np.asarray(sigma, dtype=np.float64), (e.size,))
    return (
        _prior_shift(a, s_ee_b / vf, g_e / vf, sd, bi.size, mean=value),
        _prior_shift_sigma(a, s_ee_b / vf, sd, bi.size),
    )


def _profiled(
    s: F64, rhs: F64, bi: npt.NDArray[np.intp], e: npt.NDArray[np.intp], s_bb_inv: F64, step: F64
) -> tuple[F64, F64, F64]:
    """A group's coupling to the estimated coordinates ``S_eb``, its information with them
    profiled out ``S_ee - S_eb S_bb^-1 S_be`` and its gradient after their step ``step``."""
    s_eb = s[np.ix_(e, bi)]
    return s_eb, s[np.ix_(e, e)] - s_eb @ s_bb_inv @ s_eb.T, rhs[e] - s_eb @ step


def explained_shares(
    S: npt.ArrayLike,
    b: npt.ArrayLike,
    base: npt.ArrayLike,
    groups: Mapping[str, npt.ArrayLike],
    of: Sequence[str],
    relative_rank: float = 1e-8,
    floors: Mapping[str, float] | None = None,
) -> dict[str, dict[str, float]]:
    """How much of each named group's score another group explains: the share
    ``1 - LM(a | c) / LM(a)`` of group ``a``'s statistic against the estimated coordinates that
    is gone once group ``c`` is freed as well, for every ``a`` of ``of`` and every other ``c``.

    Were ``c`` the effect in the data, the profiled gradient of ``a`` would be what ``c``'s
    columns put there, and freeing ``c`` would explain all of ``a``'s score but noise: a share
    near one says ``c`` can stand in for ``a``, whatever sensors they belong to (a gyro triad
    rotated against the accelerometer's looks, with the extrinsic rotation re-estimated, much
    like an accelerometer misalignment). Plain linear algebra on the profiled information of
    the groups, as :func:`score_effects` (the variance factor cancels in the ratio).

    Args:
        S, b, base, groups, relative_rank, floors: as for :func:`score_effects`.
        of: the groups whose scores are explained (those worth asking about: the significant).

    Returns:
        ``{a: {c: share}}``, each share in ``[0, 1]`` (0 when ``a`` has no score).
    """
    s = np.asarray(S, dtype=np.float64)
    rhs = np.asarray(b, dtype=np.float64)
    bi = np.asarray(base, dtype=np.intp)
    idx = {k: np.asarray(v, dtype=np.intp) for k, v in groups.items()}
    if not idx:
        return {}
    # every group's coordinates profiled against the estimated ones, once
    every = np.concatenate(list(idx.values()))
    s_bb_inv, _ = _pinv_psd(s[np.ix_(bi, bi)], 1e-12)
    s_gb = s[np.ix_(every, bi)]
    info = s[np.ix_(every, every)] - s_gb @ s_bb_inv @ s_gb.T
    grad = rhs[every] - s_gb @ (s_bb_inv @ rhs[bi])
    offsets = np.cumsum([0] + [v.size for v in idx.values()])
    at = {k: np.arange(offsets[i], offsets[i + 1]) for i, k in enumerate(idx)}

    def floor(name: str | None) -> float:
        return 0.0 if floors is None or name is None else float(floors.get(name, 0.0))

    def statistic(a: str, c: str | None) -> float:
        # LM of ``a`` with ``c`` freed besides the estimated coordinates
        i_aa, g_a = info[np.ix_(at[a], at[a])], grad[at[a]]
        if c is not None:
            i_ac = info[np.ix_(at[a], at[c])]
            inv_cc, _ = _pinv_psd(info[np.ix_(at[c], at[c])], relative_rank, floor(c))
            i_aa = i_aa - i_ac @ inv_cc @ i_ac.T
            g_a = g_a - i_ac @ (inv_cc @ grad[at[c]])
        inv, _ = _pinv_psd(i_aa, relative_rank, floor(a))
        return float(g_a @ inv @ g_a)

    out: dict[str, dict[str, float]] = {}
    for a in of:
        if a not in at:
            continue
        alone = statistic(a, None)
        out[a] = {
            c: (float(np.clip(1.0 - statistic(a, c) / alone, 0.0, 1.0)) if alone > 0.0 else 0.0)
            for c in at
            if c != a
        }
    return out


def combined_score(
    scores: Sequence[EffectScore], relative_rank: float = 1e-8
) -> tuple[float, int, float]:
    """Score test of one group on several recordings of the same rig (segments of a bag).

    Each recording has its own estimated coordinates (profiled out in its own test); the group
    is common to them. The profiled gradients and informations add up:
    ``LM = (sum g_k)^T pinv(sum I_k) (sum g_k) ~ chi^2(rank)`` when the group is zero. A real
    effect of the rig raises every recording's gradient along the same direction, so the
    combined test's expectation is at least that of the strongest single one; a misfit of one
    recording alone is diluted by the others' information.

    Returns:
        ``(statistic, rank, p_value)``; ``(nan, 0, nan)`` when the recordings' groups differ in
        size or carry no gradient.
    """
    sizes = {s.gradient.shape[0] for s in scores}
    if len(sizes) != 1 or 0 in sizes:  # none, or groups of different sizes, or no gradient
        return float("nan"), 0, float("nan")
    g = np.sum([s.gradient for s in scores], axis=0)
    info = np.sum([s.profiled_information for s in scores], axis=0)
    inv, rank = _pinv_psd(info, relative_rank)
    statistic = float(g @ inv @ g)
    return statistic, rank, float(chi2_sf(statistic, rank)) if rank else 1.0


def _posterior(
    information: F64, prior: npt.ArrayLike | None
) -> tuple[npt.NDArray[np.bool_], F64] | None:
    """``(on, (I + P^-1)^-1)`` over the coordinates with a positive prior standard deviation
    (``on`` their mask); None without any."""
    if prior is None:
        return None
    p = np.broadcast_to(np.asarray(prior, dtype=np.float64), (information.shape[0],))
    on = p > 0.0
    if not np.any(on):
        return None
    post = np.linalg.inv(information[np.ix_(on, on)] + np.diag(1.0 / p[on] ** 2))
    return on, 0.5 * (post + post.T)


def _prior_shift_sigma(
    shift_map: F64, information: F64, prior: npt.ArrayLike | None, m: int
) -> F64:
    """(m,) root of the diagonal of ``A (I + P^-1)^-1 A^T`` over the coordinates with a
    positive prior standard deviation (see :func:`score_effects`); zeros without any."""
    found = _posterior(information, prior)
    if found is None:
        return np.zeros(m)
    on, post = found
    a = shift_map[:, on]
    return np.sqrt(np.clip(np.einsum("ij,jk,ik->i", a, post, a), 0.0, None))


def _prior_shift(
    shift_map: F64,
    information: F64,
    gradient: F64,
    prior: npt.ArrayLike | None,
    m: int,
    mean: npt.ArrayLike = 0.0,
) -> F64:
    """(m,) ``-A (I + P^-1)^-1 (g + P^-1 mean)`` over the coordinates with a positive prior
    standard deviation: the shift of the estimated coordinates with the group at its posterior
    mean, the prior ``N(mean, P)`` (zero-mean by default: see :func:`score_effects`; a
    measurement: :func:`measured_shift`); zeros without any prior."""
    found = _posterior(information, prior)
    if found is None:
        return np.zeros(m)
    on, post = found
    p = np.broadcast_to(np.asarray(prior, dtype=np.float64), (information.shape[0],))
    mu = np.broadcast_to(np.asarray(mean, dtype=np.float64), (information.shape[0],))
    return -shift_map[:, on] @ (post @ (gradient[on] + mu[on] / p[on] ** 2))


@dataclass(frozen=True)
class EffectSelection:
    """Forward selection of fixed effects by conditional score tests.

    Attributes:
        selected: the effects the data show, in the order added; each tested with the ones
            before it freed (so an effect that only echoes a stronger one is not selected).
        remaining: the other groups, tested with every selected effect freed (shifts of the
            base coordinates only).
        joint_shift: (m,) change of the estimated coordinates if every selected effect were
            freed together.
        alone: every group's statistic tested against the estimated coordinates only (before
            any selection), by name.
    """

    selected: tuple[EffectScore, ...]
    remaining: tuple[EffectScore, ...]
    joint_shift: F64
    alone: dict[str, float] = field(default_factory=dict)


def select_effects(
    S: npt.ArrayLike,
    b: npt.ArrayLike,
    base: npt.ArrayLike,
    groups: Mapping[str, npt.ArrayLike],
    p_value: float,
    variance_factor: float = 1.0,
    max_effects: int | None = None,
    prior_sigma: Mapping[str, npt.ArrayLike] | None = None,
    floors: Mapping[str, float] | None = None,
) -> EffectSelection:
    """Add the most significant group, re-test the others with it freed, repeat.

    One effect present in the data makes the score tests of others significant too when they
    partly explain the same residuals (a LiDAR range offset biases the trajectory, which a gyro
    scale could partly absorb). Testing each further group with the already selected ones freed
    separates them: only the groups that explain something the selected ones do not are added.

    Args:
        S, b, base, variance_factor, prior_sigma, floors: as for :func:`score_effects`.
        groups: candidate groups.
        p_value: a group is selected while its conditional p-value is below this.
        max_effects: at most this many groups (default: no limit).

    Returns:
        The selection; ``joint_shift`` is in the order of ``base``.
    """
    bi = np.asarray(base, dtype=np.intp)
    todo = {k: np.asarray(v, dtype=np.intp) for k, v in groups.items()}
    chosen: list[EffectScore] = []
    chosen_idx: list[npt.NDArray[np.intp]] = []
    current = list(bi)
    alone: dict[str, float] = {}
    while todo and (max_effects is None or len(chosen) < max_effects):
        scores = score_effects(
            S, b, current, todo, variance_factor, prior_sigma=prior_sigma, floors=floors
        )
        if not alone:
            alone = {s.name: s.statistic for s in scores}
        best = max(scores, key=lambda s: -chi2_logsf(s.statistic, max(s.rank, 1)))
        if not best.p_value < p_value:
            break
        # Keep only the shift of the original base coordinates.
        pos = [current.index(i) for i in bi]
        chosen.append(
            replace(
                best,
                shift=best.shift[pos],
                shift_sigma=best.shift_sigma[pos],
                prior_shift_sigma=best.prior_shift_sigma[pos],
            )
        )
        chosen_idx.append(todo.pop(best.name))
        current = current + list(chosen_idx[-1])
    pos = [current.index(i) for i in bi]
    remaining = tuple(
        replace(
            r,
            shift=r.shift[pos],
            shift_sigma=r.shift_sigma[pos],
            prior_shift_sigma=r.prior_shift_sigma[pos],
        )
        for r in (
            score_effects(
                S, b, current, todo, variance_factor, prior_sigma=prior_sigma, floors=floors
            )
            if todo
            else []
        )
    )
    if chosen_idx:
        freed = np.concatenate(chosen_idx)
        s = np.asarray(S, dtype=np.float64)
        rhs = np.asarray(b, dtype=np.float64)
        full = np.concatenate([bi, freed])
        inv_full, _ = _pinv_psd(s[np.ix_(full, full)], 1e-10)
        inv_base, _ = _pinv_psd(s[np.ix_(bi, bi)], 1e-12)
        joint = (inv_full @ rhs[full])[: bi.size] - inv_base @ rhs[bi]
    else:
        joint = np.zeros(bi.size)
    return EffectSelection(tuple(chosen), remaining, joint, alone)
