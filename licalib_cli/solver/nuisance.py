"""Marginalising nuisance parameters that a problem holds fixed but that come from the same data.

A problem may hold some quantities fixed although they were estimated from the very residuals it
minimises (the map planes: each surfel is fitted to the points whose distances to it are then the
LiDAR residuals). The calibration information computed with those quantities fixed is too large:
it credits the data with knowing the planes exactly. Treating them as unknowns of the same
residuals and eliminating them gives the information the data really hold about the calibration.

For nuisance coordinates ``p`` (independent groups of ``k`` coordinates, e.g. a plane's two
normal directions and its offset) the full normal equations over trajectory ``t``, calibration
``c`` and ``p`` are::

    [ H_tt  H_tc  H_tp ]
    [ H_ct  H_cc  H_cp ]      H_xp = J_x^T J_p,   H_pp = J_p^T J_p  (block diagonal)
    [ H_pt  H_pc  H_pp ]

Eliminating ``t`` by the banded Cholesky factor ``A_tt = L L^T`` (``W = L^-1 [H_tc H_tp]``) and
then ``p`` gives the calibration information ``S = S_cc - S_cp S_pp^-1 S_pc`` with
``S_** = H_** - W_*^T W_*``. With the nuisance free, the trajectory and the nuisance share a gauge
(the whole map and trajectory may move together); the caller names trajectory coordinates to hold
(e.g. the first control point), which removes it.

:func:`nuisance_step` solves the same system for a Gauss-Newton step of all three (the nuisance
estimated with the problem instead of held fixed), with the calibration step restricted to the
directions the joint information determines. :func:`eliminate_nuisance` keeps the elimination
(:class:`NuisanceSystem`), whose steps for the gradient at a nearby estimate are chord steps on
the same curvature: a banded solve and a few products instead of a new elimination.

:func:`segmented_nuisance_step` is the same step for a problem made of segments that share only
the calibration (the multi-segment calibration: each segment has its own trajectory and its own
map planes). Ordered by segment, the full matrix is block-arrow shaped::

    [ A_1            C_1 ]      A_k = [ H_tt,k  H_tp,k ]    C_k = [ H_tc,k ]
    [      A_2       C_2 ]            [ H_pt,k  H_pp,k ]          [ H_pc,k ]
    [           ...  ... ]
    [ C_1^T C_2^T ... H_cc ]

so ``S = H_cc - sum_k C_k^T A_k^-1 C_k``: each segment is eliminated on its own (trajectory by its
banded factor, then its planes, as above) and only its reduced ``(Nc, Nc)`` share is kept.
Forming the dense blocks of all segments at once instead would take memory growing with the
product of the segments' trajectories and their planes. The back-substitution keeps per segment
only ``S_pp^-1 S_pc`` and ``S_pp^-1 b_p`` (planes by calibration) and the banded factor.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt
import scipy.linalg as sla
import scipy.sparse as sp

from licalib_cli.parallel.threads import map_blocks
from licalib_cli.solver.observability import Truncation
from licalib_cli.solver.problem import Evaluation, Layout, Linearization, Problem
from licalib_cli.solver.schur import _BandedCholesky, _sparse_lu_solver, _trajectory_diagonal

__all__ = [
    "GRAM_SPLIT",
    "NuisanceSegment",
    "NuisanceStep",
    "NuisanceSystem",
    "NuisanceTerms",
    "eliminate_nuisance",
    "gram",
    "marginal_schur",
    "marginal_system",
    "nuisance_gradient",
    "nuisance_step",
    "nuisance_terms",
    "segmented_nuisance_step",
    "whole_trajectory",
]

F64 = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.intp]

_HOLD = 1e8
"""A held coordinate gets this many times the largest diagonal of ``H_tt`` added: fixed."""

_NUISANCE_REGULARISATION = 1e-9
"""Nuisance directions whose (Jacobi-scaled) information is below this share of the largest are
not eliminated: the data do not determine them (points on a line fix no plane normal about it),
or what is left of them is rounding noise."""


@dataclass(frozen=True)
class NuisanceTerms:
    """Normal-equation terms of nuisance coordinates.

    Attributes:
        H_xp: (Nt + Nc, Np) coupling with the problem's free coordinates.
        H_pp: (G, k, k) diagonal blocks; group ``g`` holds nuisance columns ``g k .. g k + k``.
        g_p: (G, k) gradient ``J_p^T r`` of the cost (robust-loss weighted); empty when not
            computed.
    """

    H_xp: sp.csr_matrix
    H_pp: F64
    g_p: F64 = field(default_factory=lambda: np.zeros((0, 0)))

    @property
    def num_nuisance(self) -> int:
        """``Np = G k``."""
        return int(self.H_pp.shape[0] * self.H_pp.shape[1])


def nuisance_terms(
    problem: Problem,
    evaluation: Evaluation,
    layout: Layout,
    block: int,
    jac_p: F64,
    group: npt.ArrayLike,
    num_groups: int | None = None,
) -> NuisanceTerms:
    """``H_xp`` and ``H_pp`` of nuisance coordinates entering one residual block.

    Args:
        problem: The problem.
        evaluation: Its evaluation with Jacobians (the robust-loss weights are taken from it).
        layout: The coordinate layout of ``evaluation``'s linearisation.
        block: Index of the residual block (in ``evaluation.evals``) the nuisance enters; it must
            have one scalar residual per measurement.
        jac_p: (N, k) derivatives of each (whitened) residual with respect to the ``k``
            coordinates of its own group.
        group: (N,) group of each residual, in ``[0, G)``.
        num_groups: ``G`` (default: ``max(group) + 1``).

    Returns:
        The terms (with the block's robust-loss weights applied to both Jacobians).

    Raises:
        ValueError: On mismatched shapes.
    """
    r, weight, jp, grp = _nuisance_inputs(evaluation, block, jac_p, group, "nuisance_terms")
    n, k = jp.shape
    g = int(grp.max()) + 1 if num_groups is None and n else int(num_groups or 0)
    g_p = _nuisance_gradient(r, weight, jp, grp, g)
    h_xp = problem.coupling_matrix(evaluation, block, layout, jp * weight[:, None], grp, g)
    jp = jp * np.sqrt(weight)[:, None]
    h_pp = np.zeros((g, k, k))
    np.add.at(h_pp, grp, jp[:, :, None] * jp[:, None, :])
    return NuisanceTerms(h_xp, h_pp, g_p)


def nuisance_gradient(
    evaluation: Evaluation, block: int, jac_p: F64, group: npt.ArrayLike, num_groups: int
) -> F64:
    """The gradient ``J_p^T r`` (robust-loss weighted) of nuisance coordinates entering one
    residual block: :func:`nuisance_terms`'s ``g_p`` alone (arguments as its).

    Returns:
        (G, k) the gradient.

    Raises:
        ValueError: On mismatched shapes.
    """
    r, weight, jp, grp = _nuisance_inputs(evaluation, block, jac_p, group, "nuisance_gradient")
    return _nuisance_gradient(r, weight, jp, grp, num_groups)


def _nuisance_inputs(
    evaluation: Evaluation, block: int, jac_p: F64, group: npt.ArrayLike, caller: str
) -> tuple[F64, F64, F64, IntArray]:
    """``(r (N,), robust-loss weights (N,), jac_p (N, k), group (N,))`` of a nuisance entering
    one residual block, checked.

    Raises:
        ValueError: On mismatched shapes.
    """
    ev = evaluation.evals[block]
    loss = evaluation.losses[block]
    r = ev.residuals
    n = r.shape[0]
    jp = np.asarray(jac_p, dtype=np.float64)
    grp = np.asarray(group, dtype=np.intp).reshape(-1)
    if r.shape[1:] != (1,) or jp.ndim != 2 or jp.shape[0] != n or grp.shape != (n,):
        msg = f"{caller} needs one residual per measurement, (N, k) derivatives, (N,) groups"
        raise ValueError(msg)
    weight = np.ones(n) if loss is None else loss(r[:, 0] ** 2)[1]
    return r[:, 0], weight, jp, grp


def _nuisance_gradient(r: F64, weight: F64, jac_p: F64, group: IntArray, num_groups: int) -> F64:
    """``(G, k)`` sums of ``jac_p * weight * r`` over each group's measurements."""
    g_p = np.zeros((num_groups, jac_p.shape[1]))
    np.add.at(g_p, group, jac_p * (weight * r)[:, None])
    return g_p


def marginal_schur(lin: Linearization, terms: NuisanceTerms, hold: npt.ArrayLike = ()) -> F64:
    """The calibration information with the trajectory and the nuisance eliminated.

    Args:
        lin: The problem's normal equations (over its free trajectory and calibration).
        terms: The nuisance's terms at the same state.
        hold: Trajectory coordinates (reduced indices) to hold fixed: the shared gauge.

    Returns:
        (Nc, Nc) ``S``, symmetric.
    """
    nt = lin.layout.num_trajectory
    nc = lin.layout.num_calibration
    h_xp = sp.csr_matrix(terms.H_xp)
    h_cp = h_xp[nt:].toarray()
    g, k, _ = terms.H_pp.shape
    npar = g * k
    rhs = np.empty((nt, nc + npar), order="F")
    rhs[:, :nc] = lin.H_tc
    # the coupling's dense columns written in place (a column slice of an F-ordered array is
    # contiguous): no C-ordered copy to transpose into it
    h_xp[:nt].toarray(out=rhs[:, nc:])
    if nt:
        add = _trajectory_diagonal(lin.H_tt, 0.0)
        held = np.asarray(hold, dtype=np.intp).reshape(-1)
        if held.size:
            add[held] += _HOLD * float(max(np.max(lin.H_tt.diagonal()), 1.0))
        w = _whiten(lin, add, rhs)
        s_full = -gram(w)
    else:
        s_full = np.zeros((nc + npar, nc + npar))
    s_full[:nc, :nc] += lin.H_cc
    s_full[:nc, nc:] += h_cp
    s_full[nc:, :nc] += h_cp.T
    idx = nc + np.arange(npar).reshape(g, k)
    s_full[idx[:, :, None], idx[:, None, :]] += terms.H_pp
    s_cc, s_cp, s_pp = s_full[:nc, :nc], s_full[:nc, nc:], s_full[nc:, nc:]
    if npar:
        s_c = s_cc - _reduced_by(s_pp, s_cp)
    else:
        s_c = s_cc
    return 0.5 * (s_c + s_c.T)


def marginal_system(
    lin: Linearization,
    terms: NuisanceTerms,
    hold: npt.ArrayLike = (),
    calibration: npt.ArrayLike | None = None,
) -> tuple[F64, F64]:
    """The calibration system with the trajectory and the nuisance eliminated, and its
    right-hand side.

    As :func:`marginal_schur`, with the right-hand side ``b = -g`` reduced the same way (the
    trajectory's and the nuisance's gradients carried into the calibration coordinates), and
    optionally over a subset of the calibration coordinates (the others held fixed).

    Args:
        lin: The problem's normal equations.
        terms: The nuisance's terms at the same state, with their gradient ``g_p``.
        hold: Trajectory coordinates (reduced indices) to hold fixed: the shared gauge.
        calibration: (Nc_k,) calibration coordinates (``0 .. Nc``) to keep, increasing; None:
            all.

    Returns:
        ``(S (Nc_k, Nc_k), b (Nc_k,))``, ``S`` symmetric.

    Raises:
        ValueError: ``terms`` carries no gradient.
    """
    g, k, _ = terms.H_pp.shape
    if terms.g_p.shape != (g, k):
        msg = "marginal_system needs the nuisance gradient (nuisance_terms computes it)"
        raise ValueError(msg)
    nc = lin.layout.num_calibration
    cal = np.arange(nc) if calibration is None else np.asarray(calibration, dtype=np.intp)
    held = np.unique(np.asarray(hold, dtype=np.intp).reshape(-1))
    seg = NuisanceSegment(np.arange(lin.layout.num_trajectory), terms, held, cal)
    s_c = np.zeros((nc, nc))
    b_c = np.zeros(nc)
    _eliminate_segment(lin, seg, s_c, b_c)
    s = s_c[np.ix_(cal, cal)] + lin.H_cc[np.ix_(cal, cal)]
    b = b_c[cal] - lin.g_c[cal]
    return 0.5 * (s + s.T), b


def _psd_solver(a: F64) -> Callable[[F64], F64]:
    """``rhs -> a^+ rhs`` for a symmetric positive semi-definite ``a``, Jacobi-scaled first.

    Directions of ``a`` whose scaled eigenvalue is below :data:`_NUISANCE_REGULARISATION` (what
    the data do not determine, and rounding noise of the Schur complement) are dropped. When
    none would be, ``a`` is factored by Cholesky and each right-hand side is solved for (``a`` is
    the nuisance's information, thousands of rows; the right-hand sides are the calibration's
    few columns), instead of forming the inverse.
    """
    diag = np.diag(a).copy()
    if np.all(diag > 0.0):
        d = 1.0 / np.sqrt(diag)
        scaled = d[:, None] * a * d[None, :]
        try:
            low = np.linalg.cholesky(scaled)
        except np.linalg.LinAlgError:
            low = None
        # well conditioned enough that no direction would be dropped
        if low is not None and np.min(np.diag(low)) ** 2 > 10.0 * _NUISANCE_REGULARISATION:
            factor = (low, True)

            def cholesky_solve(rhs: F64) -> F64:
                r = np.asarray(rhs, dtype=np.float64)
                dr = d.reshape((-1,) + (1,) * (r.ndim - 1))
                return np.asarray(dr * sla.cho_solve(factor, dr * r))

            return cholesky_solve
    d = np.where(diag > 0.0, 1.0 / np.sqrt(np.where(diag > 0.0, diag, 1.0)), 0.0)
    scaled = d[:, None] * a * d[None, :]
    vals, vecs = np.linalg.eigh(0.5 * (scaled + scaled.T))
    keep = vals > _NUISANCE_REGULARISATION * max(float(vals.max(initial=0.0)), 1e-300)
    u = vecs[:, keep] * d[:, None]
    inv_vals = 1.0 / vals[keep]

    def eigen_solve(rhs: F64) -> F64:
        r = np.asarray(rhs, dtype=np.float64)
        proj = u.T @ r
        return np.asarray(u @ (inv_vals.reshape((-1,) + (1,) * (r.ndim - 1)) * proj))

    return eigen_solve


GRAM_SPLIT = 512
"""Columns from which :func:`gram` computes ``w^T w`` in blocks on the block threads."""


def gram(w: F64) -> F64:
    """``w^T w``: with :data:`GRAM_SPLIT` columns or more, the two diagonal blocks of the
    columns' halves on one block thread and the block between them on the other.

    The whitened couplings of the trajectory with the planes are a few thousand columns wide,
    and their Gram matrix is the largest product of a planes-free step (0.40 s for 4500 rows
    by 2300 columns on one core, 0.22-0.25 s split so). The blocks are the same whatever the
    threads, so the result is too.
    """
    k = w.shape[1]
    if k < GRAM_SPLIT:
        return np.asarray(w.T @ w)
    h = k // 2
    left, right = w[:, :h], w[:, h:]
    out = np.empty((k, k))

    def block(i: int) -> None:
        if i == 0:
            out[:h, :h] = left.T @ left
            out[h:, h:] = right.T @ right
        else:
            out[:h, h:] = left.T @ right

    map_blocks(block, 2)
    out[h:, :h] = out[:h, h:].T
    return out


def _reduced_by(a: F64, b: F64) -> F64:
    """``b a^+ b^T`` for a symmetric positive semi-definite ``a`` (:func:`_psd_solver`)."""
    return np.asarray(b @ _psd_solver(a)(b.T))


def _whiten(lin: Linearization, add: F64, rhs: F64) -> F64:
    """``W`` with ``W^T W = rhs^T (H_tt + diag(add))^-1 rhs``."""
    factor = _BandedCholesky.factorize(lin.H_tt, add)
    if factor is not None:
        return factor.forward(rhs)
    solve: Callable[[F64], F64] = _sparse_lu_solver(lin.H_tt, add)
    a_inv_rhs = solve(rhs)
    # W^T W must equal rhs^T A^-1 rhs: factor that Gram matrix instead of A.
    gram = rhs.T @ a_inv_rhs
    gram = 0.5 * (gram + gram.T)
    vals, vecs = np.linalg.eigh(gram)
    return (vecs * np.sqrt(np.clip(vals, 0.0, None))).T


@dataclass(frozen=True)
class NuisanceStep:
    """A Gauss-Newton step of the problem's free coordinates and the nuisance together.

    Attributes:
        dx: (Nt + Nc,) step of the problem's free coordinates, in solver order.
        dp: (G, k) step of the nuisance coordinates (of a segmented step: every segment's groups
            in turn).
        predicted_reduction: cost reduction the quadratic model predicts for the step.
        num_truncated: calibration directions the joint information does not determine (held).
        information: (Nc, Nc) the calibration information with the trajectory and the nuisance
            eliminated (:func:`marginal_schur`'s ``S`` for the same terms), before truncation.
    """

    dx: F64
    dp: F64
    predicted_reduction: float
    num_truncated: int
    information: F64


@dataclass(frozen=True)
class NuisanceSegment:
    """One independent part of a problem with nuisance: its own trajectory and nuisance.

    A segment's trajectory coordinates couple with no other segment's trajectory (``H_tt`` is
    block diagonal over the segments) and its nuisance enters only its own residuals, so it
    couples with its own trajectory and with calibration coordinates only.

    Attributes:
        trajectory: (Nt_k,) reduced indices of the segment's trajectory coordinates, increasing.
        terms: the nuisance's terms (rows of ``H_xp`` over all ``Nt + Nc`` free coordinates),
            with their gradient.
        hold: reduced indices of the segment's trajectory coordinates held fixed (its gauge).
        calibration: (Nc_k,) the calibration coordinates (``0 .. Nc``) the segment's residuals
            touch, increasing; None: all.
    """

    trajectory: IntArray
    terms: NuisanceTerms
    hold: IntArray = field(default_factory=lambda: np.zeros(0, dtype=np.intp))
    calibration: IntArray | None = None


@dataclass(frozen=True)
class _Reduced:
    """What the back-substitution needs of one eliminated segment (no dense block of its
    nuisance or of its trajectory-by-nuisance coupling: those are what grows with its size).

    ``dp = y - x dc[calibration]`` and ``dt = A_tt^-1 (-(g_t + H_tc dc + H_tp dp))``.
    """

    trajectory: IntArray
    calibration: IntArray
    solve_tt: Callable[[F64], F64] | None
    h_xp: sp.csr_matrix
    x: F64
    y: F64
    solve_pp: Callable[[F64], F64] | None


def _check_segments(lin: Linearization, segments: Sequence[NuisanceSegment]) -> None:
    """Raise ValueError unless the segments partition the trajectory and couple as stated."""
    nt = lin.layout.num_trajectory
    nc = lin.layout.num_calibration
    label = np.full(nt, -1, dtype=np.intp)
    for i, seg in enumerate(segments):
        t = np.asarray(seg.trajectory, dtype=np.intp)
        if np.any(np.diff(t) <= 0):
            msg = "a nuisance segment's trajectory coordinates must be increasing"
            raise ValueError(msg)
        if np.any(label[t] >= 0):
            msg = "nuisance segments must not share trajectory coordinates"
            raise ValueError(msg)
        label[t] = i
        g, k, _ = seg.terms.H_pp.shape
        if seg.terms.g_p.shape != (g, k):
            msg = "nuisance_step needs the nuisance gradient (nuisance_terms computes it)"
            raise ValueError(msg)
        if seg.terms.H_xp.shape != (nt + nc, g * k):
            msg = "a nuisance segment's H_xp must have a row per free coordinate"
            raise ValueError(msg)
    for seg in segments:
        if not np.all(np.isin(np.asarray(seg.hold, dtype=np.intp), seg.trajectory)):
            msg = "a nuisance segment can hold only its own trajectory coordinates"
            raise ValueError(msg)
    if np.any(label < 0):
        msg = "nuisance segments must cover every free trajectory coordinate"
        raise ValueError(msg)
    h_tt = sp.coo_matrix(lin.H_tt)
    if np.any(label[h_tt.row[h_tt.data != 0.0]] != label[h_tt.col[h_tt.data != 0.0]]):
        msg = "H_tt couples the trajectories of two nuisance segments"
        raise ValueError(msg)
    for i, seg in enumerate(segments):
        allowed = np.zeros(nt + nc, dtype=bool)
        allowed[seg.trajectory] = True
        cal = np.arange(nc) if seg.calibration is None else np.asarray(seg.calibration)
        allowed[nt + cal] = True
        h_xp = sp.csr_matrix(seg.terms.H_xp)
        rows = np.repeat(np.arange(nt + nc), np.diff(h_xp.indptr))[h_xp.data != 0.0]
        other = np.ones(nc, dtype=bool)
        other[cal] = False
        if not np.all(allowed[rows]) or np.any(lin.H_tc[np.ix_(label == i, other)] != 0.0):
            msg = f"nuisance segment {i} touches coordinates outside its own and its calibration"
            raise ValueError(msg)


def _eliminate_segment(lin: Linearization, seg: NuisanceSegment, s_c: F64, b_c: F64) -> _Reduced:
    """Eliminate one segment's trajectory and nuisance, adding its share to ``s_c`` and ``b_c``.

    The segment's trajectory is eliminated by the banded factor of its ``H_tt`` block (held
    coordinates fixed), then its nuisance (:func:`_psd_solver`); what is left acts on its
    calibration coordinates: ``S_k = -W_c^T W_c - S_cp S_pp^+ S_pc`` and the matching right-hand
    side, added in place.
    """
    nt = lin.layout.num_trajectory
    nc = lin.layout.num_calibration
    t = np.asarray(seg.trajectory, dtype=np.intp)
    c = np.arange(nc) if seg.calibration is None else np.asarray(seg.calibration, dtype=np.intp)
    terms = seg.terms
    g, k, _ = terms.H_pp.shape
    npar = g * k
    ncs = c.size
    ny = ncs + npar
    h_xp = sp.csr_matrix(terms.H_xp)
    h_cp = h_xp[nt + c].toarray()
    b = np.concatenate([np.zeros(ncs), -terms.g_p.reshape(-1)])
    solve_tt: Callable[[F64], F64] | None = None
    if not t.size:
        s_full = np.zeros((ny, ny))
    else:
        h_tt = lin.H_tt if t.size == nt else sp.csc_matrix(lin.H_tt[t][:, t])
        add = _trajectory_diagonal(h_tt, 0.0)
        held = np.searchsorted(t, np.asarray(seg.hold, dtype=np.intp).reshape(-1))
        if held.size:
            add[held] += _HOLD * float(max(np.max(h_tt.diagonal()), 1.0))
        factor = _BandedCholesky.factorize(h_tt, add)
        solve_tt = factor.solve if factor is not None else _sparse_lu_solver(h_tt, add)
        rhs = np.empty((t.size, ny + 1), order="F")
        rhs[:, :ncs] = lin.H_tc[np.ix_(t, c)]
        h_xp[t].toarray(out=rhs[:, ncs:ny])  # in place, as in marginal_schur
        rhs[:, ny] = lin.g_t[t]
        if factor is not None:
            w = factor.forward(rhs)
            del rhs
            products = gram(w)
            del w
        else:
            products = rhs.T @ solve_tt(rhs)
            del rhs
            products = 0.5 * (products + products.T)
        s_full = np.negative(products[:ny, :ny])
        b += products[:ny, ny]
        del products
    s_full[:ncs, ncs:] += h_cp
    s_full[ncs:, :ncs] += h_cp.T
    idx = ncs + np.arange(npar).reshape(g, k)
    s_full[idx[:, :, None], idx[:, None, :]] += terms.H_pp
    s_cp, s_pp = s_full[:ncs, ncs:], s_full[ncs:, ncs:]
    solve_pp: Callable[[F64], F64] | None = None
    if npar:
        solve_pp = _psd_solver(s_pp)
        x, y = solve_pp(s_cp.T), solve_pp(b[ncs:])
    else:
        x, y = np.zeros((0, ncs)), np.zeros(0)
    s_c[np.ix_(c, c)] += s_full[:ncs, :ncs] - s_cp @ x
    b_c[c] += b[:ncs] - s_cp @ y
    return _Reduced(t, c, solve_tt, h_xp, x, y, solve_pp)


@dataclass(frozen=True)
class NuisanceSystem:
    """The joint system of one linearisation with the trajectory and the nuisance eliminated
    (:func:`eliminate_nuisance`), ready to give steps.

    :meth:`step` gives the Gauss-Newton step for the linearisation's own gradient and, for any
    other gradient at a nearby estimate, the step on the same curvature (a chord step, as of the
    simplified Newton method). The elimination (the banded factor of each segment's trajectory,
    the Gram product of its couplings and the factor of its nuisance block) is what costs; a
    step for another gradient takes a banded solve and a few products a segment.

    Attributes:
        lin: The normal equations eliminated.
        segments: Their segments.
        information: (Nc, Nc) the calibration information with the trajectory and the nuisance
            eliminated, before truncation.
        num_truncated: calibration directions the joint information does not determine (held).
    """

    lin: Linearization
    segments: tuple[NuisanceSegment, ...]
    information: F64
    num_truncated: int
    _reduced: tuple[_Reduced, ...] = field(repr=False)
    _b_c: F64 = field(repr=False)  # the calibration's reduced right-hand side, own gradient
    _basis: F64 = field(repr=False)  # (Nc, kept) the kept scaled eigen-directions of S
    _values: F64 = field(repr=False)  # (kept,) their eigenvalues

    def step(self, g: F64 | None = None, g_p: Sequence[F64] | None = None) -> NuisanceStep:
        """The step for a gradient: the linearisation's own (None), or ``g`` (Nt + Nc,) with
        each segment's nuisance gradient ``g_p`` (G_k, k) at another estimate whose free
        coordinates are laid out as the linearisation's (a chord step: the same curvature).

        Returns:
            The step; its quadratic model is this system's curvature with the gradient given.

        Raises:
            ValueError: ``g`` and ``g_p`` are not given together, or do not match the system.
        """
        lin = self.lin
        nt = lin.layout.num_trajectory
        nc = lin.layout.num_calibration
        if (g is None) != (g_p is None):
            msg = "a chord step needs both the gradient and the nuisance gradients"
            raise ValueError(msg)
        if g is None or g_p is None:
            grad, grads_p = lin.g, [seg.terms.g_p for seg in self.segments]
            b_c = self._b_c
            ys = [red.y for red in self._reduced]
        else:
            grad = np.asarray(g, dtype=np.float64)
            grads_p = [np.asarray(gp, dtype=np.float64) for gp in g_p]
            if grad.shape != lin.g.shape or len(grads_p) != len(self.segments):
                msg = "the gradient does not match the eliminated system"
                raise ValueError(msg)
            b_c, ys = self._reduced_gradient(grad, grads_p)
        dc = np.zeros(nc)
        if nc:
            scale = np.asarray(lin.layout.calibration_scale, dtype=np.float64)
            u = self._basis
            dc = scale * (u @ ((u.T @ (scale * b_c)) / self._values))
        dt = np.zeros(nt)
        dps: list[F64] = []
        # quadratic model of the full system at the step, the nuisance's terms segment by segment
        quad_p = cross = grad_p = 0.0
        g_t = grad[:nt]
        for seg, red, y, gp in zip(self.segments, self._reduced, ys, grads_p, strict=True):
            dp = y - red.x @ dc[red.calibration]
            t = red.trajectory
            if t.size:
                assert red.solve_tt is not None
                rhs = g_t[t] + lin.H_tc[np.ix_(t, red.calibration)] @ dc[red.calibration]
                dt[t] = red.solve_tt(-(rhs + red.h_xp[t] @ dp))
            groups, k, _ = seg.terms.H_pp.shape
            dps.append(dp.reshape(groups, k))
            quad_p += float(np.einsum("gi,gij,gj->", dps[-1], seg.terms.H_pp, dps[-1]))
            grad_p += float(gp.reshape(-1) @ dp)
        dx = np.concatenate([dt, dc])
        for dp_k, red in zip(dps, self._reduced, strict=True):
            cross += float(dx @ (red.h_xp @ dp_k.reshape(-1)))
        quad = lin.quadratic(dx) + 2.0 * cross + quad_p
        predicted = -(float(grad @ dx) + grad_p + 0.5 * quad)
        dp_all = np.concatenate(dps) if dps else np.zeros((0, 0))
        return NuisanceStep(dx, dp_all, predicted, self.num_truncated, self.information)

    def _reduced_gradient(self, g: F64, g_p: Sequence[F64]) -> tuple[F64, list[F64]]:
        """The calibration's reduced right-hand side and each segment's ``S_pp^+ b_p`` for a
        gradient (``b = -g`` with the trajectory and the nuisance eliminated)."""
        lin = self.lin
        nt = lin.layout.num_trajectory
        nc = lin.layout.num_calibration
        b_c = np.zeros(nc)
        ys: list[F64] = []
        for seg, red, gp in zip(self.segments, self._reduced, g_p, strict=True):
            groups, k, _ = seg.terms.H_pp.shape
            if gp.shape != (groups, k):
                msg = "a nuisance gradient does not match its segment's nuisance"
                raise ValueError(msg)
            c, t = red.calibration, red.trajectory
            b_cal = np.zeros(c.size)
            b_p = -gp.reshape(-1)
            if t.size:
                assert red.solve_tt is not None
                v = red.solve_tt(g[t])  # A_tt^-1 g_t: the trajectory's gradient carried over
                b_cal += lin.H_tc[np.ix_(t, c)].T @ v
                b_p = b_p + red.h_xp[t].T @ v
            y = red.solve_pp(b_p) if red.solve_pp is not None else np.zeros(0)
            # S_cp S_pp^+ b_p = (S_pp^+ S_pc)^T b_p: S_pp^+ is symmetric
            b_c[c] += b_cal - red.x.T @ b_p
            ys.append(y)
        return b_c - g[nt:], ys


def eliminate_nuisance(
    lin: Linearization,
    segments: Sequence[NuisanceSegment],
    truncation: Truncation = Truncation(),
) -> NuisanceSystem:
    """Eliminate the trajectory and the nuisance of each segment (:class:`NuisanceSystem`).

    The segments share the calibration and nothing else, so the full system is block-arrow
    shaped: each segment's trajectory and nuisance couple with themselves and with the
    calibration. Each segment is eliminated in turn (its trajectory by the banded factor of its
    ``H_tt`` block, then its nuisance) and its reduced contribution added to the calibration
    system ``S = H_cc + sum_k S_k``, ``b = -g_c + sum_k b_k``; only one segment's dense blocks
    (its ``(Nc_k + Np_k)^2`` system and ``Nt_k x (Nc_k + Np_k)`` whitened coupling) exist at a
    time. The calibration step solves ``S`` in the coordinates scaled by
    ``lin.layout.calibration_scale``, restricted to the eigen-directions ``truncation`` keeps
    (the solver's rule); each segment's nuisance and trajectory steps follow by
    back-substitution.

    Args:
        lin: The problem's normal equations.
        segments: The segments, their trajectories partitioning the free trajectory
            coordinates.
        truncation: Which calibration directions move (the solver's rule,
            ``LMParams.truncation``); by default those known to one characteristic scale.

    Returns:
        The eliminated system.

    Raises:
        ValueError: a segment carries no gradient, the segments do not partition the
            trajectory, or a segment couples with another's coordinates.
    """
    _check_segments(lin, segments)
    nc = lin.layout.num_calibration
    s_c = np.zeros((nc, nc))
    b_c = np.zeros(nc)
    reduced = tuple(_eliminate_segment(lin, seg, s_c, b_c) for seg in segments)
    s_c += lin.H_cc
    b_c -= lin.g_c
    num_truncated = 0
    basis, values = np.zeros((nc, 0)), np.zeros(0)
    if nc:
        scale = np.asarray(lin.layout.calibration_scale, dtype=np.float64)
        s_d = scale[:, None] * s_c * scale[None, :]
        vals, vecs = np.linalg.eigh(0.5 * (s_d + s_d.T))
        vals = np.clip(vals, 0.0, None)
        keep = truncation.kept(vals, vecs, lin.layout.calibration_owner)
        num_truncated = int(nc - np.count_nonzero(keep))
        basis, values = vecs[:, keep], vals[keep]
    return NuisanceSystem(
        lin,
        tuple(segments),
        0.5 * (s_c + s_c.T),
        num_truncated,
        reduced,
        b_c,
        basis,
        values,
    )


def segmented_nuisance_step(
    lin: Linearization,
    segments: Sequence[NuisanceSegment],
    truncation: Truncation = Truncation(),
) -> NuisanceStep:
    """The Gauss-Newton step over trajectory, calibration and nuisance, segment by segment:
    :func:`eliminate_nuisance`, then the step for the linearisation's own gradient. With one
    segment holding the whole trajectory this is :func:`nuisance_step`.

    Arguments and errors as :func:`eliminate_nuisance`'s.

    Returns:
        The step; ``dp`` holds every segment's groups in turn.
    """
    return eliminate_nuisance(lin, segments, truncation).step()


def whole_trajectory(
    lin: Linearization, terms: NuisanceTerms, hold: npt.ArrayLike = ()
) -> NuisanceSegment:
    """The one segment of a problem whose nuisance couples with its whole trajectory, holding
    the trajectory coordinates ``hold`` (reduced indices: the shared gauge)."""
    held = np.unique(np.asarray(hold, dtype=np.intp).reshape(-1))
    return NuisanceSegment(np.arange(lin.layout.num_trajectory), terms, held)


def nuisance_step(
    lin: Linearization,
    terms: NuisanceTerms,
    hold: npt.ArrayLike = (),
    truncation: Truncation = Truncation(),
) -> NuisanceStep:
    """The Gauss-Newton step over trajectory, calibration and nuisance.

    The trajectory is eliminated by the banded factor of ``H_tt`` (held coordinates fixed), then
    the nuisance (Jacobi-scaled pseudo-inverse, as :func:`marginal_schur`); the calibration step
    solves the remaining system in the coordinates scaled by ``lin.layout.calibration_scale``,
    restricted to the eigen-directions ``truncation`` keeps (the solver's rule); the nuisance
    and the trajectory steps follow by back-substitution. This is
    :func:`segmented_nuisance_step` with one segment.

    Args:
        lin: The problem's normal equations.
        terms: The nuisance's terms at the same state, with their gradient ``g_p``.
        hold: Trajectory coordinates (reduced indices) held fixed: the shared gauge.
        truncation: Which calibration directions move (as :func:`eliminate_nuisance`).

    Returns:
        The step.

    Raises:
        ValueError: ``terms`` carries no gradient.
    """
    return segmented_nuisance_step(lin, [whole_trajectory(lin, terms, hold)], truncation)
