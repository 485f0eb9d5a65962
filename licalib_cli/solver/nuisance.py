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
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import scipy.linalg as sla
import scipy.sparse as sp

from licalib_cli.solver.problem import Evaluation, Layout, Linearization, Problem
from licalib_cli.solver.schur import _BandedCholesky, _sparse_lu_solver, _trajectory_diagonal

__all__ = ["NuisanceTerms", "marginal_schur", "nuisance_terms"]

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
    """

    H_xp: sp.csr_matrix
    H_pp: F64

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
    ev = evaluation.evals[block]
    loss = evaluation.losses[block]
    r = ev.residuals
    n = r.shape[0]
    jp = np.asarray(jac_p, dtype=np.float64)
    grp = np.asarray(group, dtype=np.intp).reshape(-1)
    if r.shape[1:] != (1,) or jp.ndim != 2 or jp.shape[0] != n or grp.shape != (n,):
        msg = "nuisance_terms needs one residual per measurement, (N, k) derivatives, (N,) groups"
        raise ValueError(msg)
    k = jp.shape[1]
    g = int(grp.max()) + 1 if num_groups is None and n else int(num_groups or 0)
    if loss is not None:
        jp = jp * np.sqrt(loss(r[:, 0] ** 2)[1])[:, None]
    j_x = problem.jacobian_matrix(evaluation, block, layout)
    cols = grp[:, None] * k + np.arange(k)
    j_p = sp.csr_matrix(
        (jp.reshape(-1), cols.reshape(-1), np.arange(0, n * k + 1, k)), shape=(n, g * k)
    )
    h_xp = sp.csr_matrix(j_x.T @ j_p)
    h_pp = np.zeros((g, k, k))
    np.add.at(h_pp, grp, jp[:, :, None] * jp[:, None, :])
    return NuisanceTerms(h_xp, h_pp)


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
    h_tp = h_xp[:nt].toarray()
    h_cp = h_xp[nt:].toarray()
    g, k, _ = terms.H_pp.shape
    npar = g * k
    rhs = np.empty((nt, nc + npar), order="F")
    rhs[:, :nc] = lin.H_tc
    rhs[:, nc:] = h_tp
    if nt:
        add = _trajectory_diagonal(lin.H_tt, 0.0)
        held = np.asarray(hold, dtype=np.intp).reshape(-1)
        if held.size:
            add[held] += _HOLD * float(max(np.max(lin.H_tt.diagonal()), 1.0))
        w = _whiten(lin, add, rhs)
        s_full = -(w.T @ w)
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


def _reduced_by(a: F64, b: F64) -> F64:
    """``b a^+ b^T`` for a symmetric positive semi-definite ``a``, Jacobi-scaled first.

    Directions of ``a`` whose scaled eigenvalue is below :data:`_NUISANCE_REGULARISATION` (what
    the data do not determine, and rounding noise of the Schur complement) are dropped. When
    none would be, ``a`` is factored by Cholesky and only ``b``'s few rows are solved for (``a``
    is the nuisance's information, thousands of rows; ``b`` has one row per calibration
    coordinate), instead of forming the inverse.
    """
    diag = np.diag(a).copy()
    if np.all(diag > 0.0):
        d = 1.0 / np.sqrt(diag)
        scaled = d[:, None] * a * d[None, :]
        try:
            low = np.linalg.cholesky(scaled)
            # well conditioned enough that no direction would be dropped
            if np.min(np.diag(low)) ** 2 > 10.0 * _NUISANCE_REGULARISATION:
                y = sla.solve_triangular(low, (b * d[None, :]).T, lower=True)
                return np.asarray(y.T @ y)
        except np.linalg.LinAlgError:
            pass
    d = np.where(diag > 0.0, 1.0 / np.sqrt(np.where(diag > 0.0, diag, 1.0)), 0.0)
    scaled = d[:, None] * a * d[None, :]
    vals, vecs = np.linalg.eigh(0.5 * (scaled + scaled.T))
    keep = vals > _NUISANCE_REGULARISATION * max(float(vals.max(initial=0.0)), 1e-300)
    bu = b @ (vecs[:, keep] * d[:, None])
    return np.asarray((bu / vals[keep]) @ bu.T)


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
