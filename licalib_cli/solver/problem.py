"""Least-squares problem: parameter blocks, residual blocks, evaluation and linearisation.

Residual blocks
    A residual block is any object with a ``name`` and
    ``evaluate(params, jacobians=True) -> ResidualEval``, where ``params`` maps every parameter
    block name to its current value (the block's construction shape). It returns *whitened*
    residuals ``(n, m)``: ``n`` measurements (robust-loss groups) of ``m`` residuals each (``m = 1``
    for a scalar point-to-plane residual, 3 for a gyro residual), and their Jacobians in the
    tangent coordinates of each parameter block it touches (see :mod:`.parameters`; so3 blocks use
    the right perturbation ``R Exp(delta)``). Two Jacobian forms exist:

    * :class:`DenseJacobian` (the fast path): measurement ``i`` touches elements
      ``elements[i, :a]`` of a block, with dense derivatives ``values[i, :m, :a, :d]``; e.g. a
      point touching 4 control points of 3 tangent dims has ``(n, 1, 4, 3)``.
    * :class:`SparseJacobian`: COO triplets ``(rows, cols, values)`` with ``rows`` indexing the
      flattened residual vector ``i * m + k`` and ``cols`` the block's tangent coordinates.

    Jacobians for blocks that are entirely fixed may be omitted. When called with
    ``jacobians=False`` a block may skip them (it may also return them anyway).

The free coordinates are ordered trajectory blocks first (insertion order), then calibration
blocks; fixed coordinates are dropped (:class:`Layout`).

Normal equations
    :meth:`Problem.linearize` turns an :class:`Evaluation` into ``H = J^T J`` and ``g = J^T r``
    (IRLS-reweighted, see :mod:`.loss`), split into the trajectory group ``t`` and the
    calibration group ``c`` (:class:`Linearization`); the accumulation is in :mod:`.assembly`,
    the elimination of the trajectory block in :mod:`.schur`.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol, runtime_checkable

import numpy as np
import numpy.typing as npt
import scipy.sparse as sp

from licalib_cli.parallel.threads import map_blocks
from licalib_cli.solver.assembly import (
    Accumulator,
    DensePart,
    GroupCache,
    TrajectoryPattern,
    add_dense_gradient,
    add_dense_split,
    add_sparse,
    add_sparse_gradient,
    first_with_same_elements,
)
from licalib_cli.solver.parameters import ParameterBlock

if TYPE_CHECKING:
    from licalib_cli.solver.loss import Loss

__all__ = [
    "DenseJacobian",
    "Evaluation",
    "Layout",
    "Linearization",
    "Problem",
    "ResidualBlock",
    "ResidualEval",
    "SparseJacobian",
    "dense_to_coo",
]

F64 = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.intp]


def dense_to_coo(
    values: npt.ArrayLike, elements: npt.ArrayLike, tangent_dim: int | None = None
) -> tuple[IntArray, IntArray, F64]:
    """COO triplets of dense per-measurement Jacobians.

    Args:
        values: (n, m, a, d) derivatives of the ``m`` residuals of measurement ``i`` with
            respect to the ``d`` tangent coordinates of its ``a`` elements.
        elements: (n, a) element indices into the block.
        tangent_dim: ``d``; taken from ``values`` when None.

    Returns:
        ``(rows, cols, vals)``, each (n * m * a * d,): ``rows = i * m + k`` (flattened residual
        index), ``cols = element * d + j`` (block tangent coordinate).
    """
    v = np.asarray(values, dtype=np.float64)
    e = np.asarray(elements, dtype=np.intp)
    n, m, _, d = v.shape
    if tangent_dim is not None and tangent_dim != d:
        msg = f"Dense Jacobian has {d} tangent coordinates per element, expected {tangent_dim}."
        raise ValueError(msg)
    rows = np.broadcast_to(np.arange(n * m, dtype=np.intp).reshape(n, m, 1, 1), v.shape)
    cols = np.broadcast_to(
        (e[:, None, :, None] * d + np.arange(d, dtype=np.intp)[None, None, None, :]), v.shape
    )
    return rows.reshape(-1), cols.reshape(-1), v.reshape(-1)


@dataclass(frozen=True)
class DenseJacobian:
    """Jacobian of a residual block with respect to one parameter block, per measurement.

    Attributes:
        block: Parameter block name.
        elements: (n, a) int element indices touched by each measurement.
        values: (n, m, a, d) derivatives of the ``m`` whitened residuals of each measurement with
            respect to the ``d`` tangent coordinates of each touched element.
    """

    block: str
    elements: npt.NDArray[np.integer]
    values: F64

    def __post_init__(self) -> None:
        elements = np.asarray(self.elements)
        if elements.ndim == 1:
            elements = elements[:, None]
        values = np.asarray(self.values, dtype=np.float64)
        if (
            values.ndim != 4
            or values.shape[0] != elements.shape[0]
            or (values.shape[2] != elements.shape[1])
        ):
            msg = (
                f"DenseJacobian for {self.block!r}: values must be (n, m, a, d) matching "
                f"elements (n, a); got {values.shape} and {elements.shape}."
            )
            raise ValueError(msg)
        object.__setattr__(self, "elements", elements.astype(np.intp, copy=False))
        object.__setattr__(self, "values", values)

    def to_coo(self) -> SparseJacobian:
        """The same Jacobian as COO triplets."""
        rows, cols, vals = dense_to_coo(self.values, self.elements)
        return SparseJacobian(self.block, rows, cols, vals)


@dataclass(frozen=True)
class SparseJacobian:
    """Jacobian of a residual block with respect to one parameter block, as COO triplets.

    Attributes:
        block: Parameter block name.
        rows: (K,) int flattened residual index ``i * m + k``.
        cols: (K,) int tangent coordinate of the block.
        values: (K,) derivatives (duplicates are summed).
    """

    block: str
    rows: npt.NDArray[np.integer]
    cols: npt.NDArray[np.integer]
    values: F64

    def __post_init__(self) -> None:
        rows = np.asarray(self.rows, dtype=np.intp).reshape(-1)
        cols = np.asarray(self.cols, dtype=np.intp).reshape(-1)
        values = np.asarray(self.values, dtype=np.float64).reshape(-1)
        if not rows.shape == cols.shape == values.shape:
            msg = f"SparseJacobian for {self.block!r}: rows, cols and values differ in length."
            raise ValueError(msg)
        object.__setattr__(self, "rows", rows)
        object.__setattr__(self, "cols", cols)
        object.__setattr__(self, "values", values)


@dataclass(frozen=True)
class ResidualEval:
    """Whitened residuals of one residual block and their Jacobians.

    Attributes:
        residuals: (n, m) whitened residuals; one robust-loss group per row. A 1-D (n,) input is
            taken as ``n`` scalar groups.
        jacobians: Jacobian pieces, at most one form per block is needed; several pieces for the
            same block are summed.
    """

    residuals: F64
    jacobians: tuple[DenseJacobian | SparseJacobian, ...] = ()

    def __post_init__(self) -> None:
        r = np.asarray(self.residuals, dtype=np.float64)
        if r.ndim == 1:
            r = r[:, None]
        if r.ndim != 2:
            msg = f"Residuals must be (n,) or (n, m); got shape {r.shape}."
            raise ValueError(msg)
        object.__setattr__(self, "residuals", r)
        object.__setattr__(self, "jacobians", tuple(self.jacobians))
        n, m = r.shape
        for jac in self.jacobians:
            if isinstance(jac, DenseJacobian) and jac.values.shape[:2] != (n, m):
                msg = (
                    f"DenseJacobian for {jac.block!r} has {jac.values.shape[:2]} measurement rows; "
                    f"the residuals are {(n, m)}."
                )
                raise ValueError(msg)


@runtime_checkable
class ResidualBlock(Protocol):
    """A group of residuals with a common model (e.g. all point-to-plane residuals of a round)."""

    name: str

    def evaluate(self, params: Mapping[str, F64], jacobians: bool = True) -> ResidualEval:
        """Whitened residuals and (if ``jacobians``) their tangent-space Jacobians.

        Args:
            params: Block name -> current value (construction shape).
            jacobians: Whether Jacobians are needed.

        Returns:
            The residuals and Jacobians.
        """
        ...


@dataclass(frozen=True)
class Layout:
    """Map from block tangent coordinates to the reduced (free) solver vector.

    Attributes:
        block_names: Blocks in solver order (trajectory blocks, then calibration blocks).
        index: Block name -> (size,) position of each tangent coordinate in the reduced vector, or
            -1 when fixed.
        num_trajectory: ``Nt``, free trajectory coordinates (they come first).
        num_calibration: ``Nc``, free calibration coordinates.
        names: (Nt + Nc,) coordinate names in solver order.
        scale: (Nt + Nc,) characteristic magnitudes in solver order.
        owner: (Nt + Nc,) owning block name of each coordinate.
    """

    block_names: tuple[str, ...]
    index: Mapping[str, IntArray]
    num_trajectory: int
    num_calibration: int
    names: tuple[str, ...]
    scale: F64
    owner: tuple[str, ...]

    @property
    def num_free(self) -> int:
        """``Nt + Nc``."""
        return self.num_trajectory + self.num_calibration

    @property
    def calibration_names(self) -> tuple[str, ...]:
        """(Nc,) calibration coordinate names."""
        return self.names[self.num_trajectory :]

    @property
    def calibration_scale(self) -> F64:
        """(Nc,) calibration coordinate scales."""
        return self.scale[self.num_trajectory :]

    @property
    def calibration_owner(self) -> tuple[str, ...]:
        """(Nc,) owning block of each calibration coordinate."""
        return self.owner[self.num_trajectory :]

    def same_coordinates(self, other: Layout) -> bool:
        """Whether ``other`` lays out the same free coordinates in the same order."""
        return (
            self.block_names == other.block_names
            and self.names == other.names
            and self.index.keys() == other.index.keys()
            and all(np.array_equal(v, other.index[k]) for k, v in self.index.items())
        )


@dataclass(frozen=True)
class Evaluation:
    """Residual evaluation of a problem at one state.

    Attributes:
        values: Block name -> value used.
        evals: One :class:`ResidualEval` per residual block evaluated.
        losses: The loss of each residual block (None = squared).
        block_costs: Cost ``0.5 * sum rho`` of each residual block.
        cost: Total cost.
        num_residuals: Total scalar residuals.
    """

    values: Mapping[str, F64]
    evals: tuple[ResidualEval, ...]
    losses: tuple[Loss | None, ...]
    block_costs: tuple[float, ...]
    cost: float
    num_residuals: int


@dataclass(frozen=True)
class Linearization:
    """Gauss-Newton normal equations ``H dx = -g`` at one state (IRLS-reweighted).

    Attributes:
        layout: Coordinate layout used.
        cost: Cost at the linearisation point.
        num_residuals: Number of scalar residuals.
        H_tt: (Nt, Nt) sparse CSC trajectory block.
        H_tc: (Nt, Nc) dense coupling block.
        H_cc: (Nc, Nc) dense calibration block.
        g: (Nt + Nc,) gradient ``J^T r`` of the cost.
    """

    layout: Layout
    cost: float
    num_residuals: int
    H_tt: sp.csc_matrix
    H_tc: F64
    H_cc: F64
    g: F64

    @property
    def g_t(self) -> F64:
        """(Nt,) trajectory part of the gradient."""
        return self.g[: self.layout.num_trajectory]

    @property
    def g_c(self) -> F64:
        """(Nc,) calibration part of the gradient."""
        return self.g[self.layout.num_trajectory :]

    def quadratic(self, dx: F64) -> float:
        """``dx^T H dx`` for a (Nt + Nc,) step."""
        nt = self.layout.num_trajectory
        dt, dc = dx[:nt], dx[nt:]
        return float(dt @ (self.H_tt @ dt) + 2.0 * dt @ (self.H_tc @ dc) + dc @ (self.H_cc @ dc))

    def dense(self) -> F64:
        """The full (Nt + Nc, Nt + Nc) ``H`` as a dense array (small problems and tests only)."""
        top = np.hstack([self.H_tt.toarray(), self.H_tc])
        bottom = np.hstack([self.H_tc.T, self.H_cc])
        return np.vstack([top, bottom])


class Problem:
    """Parameter blocks plus residual blocks (each with an optional robust loss)."""

    def __init__(self) -> None:
        """Create an empty problem."""
        self._blocks: dict[str, ParameterBlock] = {}
        self._residuals: list[ResidualBlock] = []
        self._losses: list[Loss | None] = []
        # sparsity pattern of the last assembled H_tt, reused while the contributions keep it
        self._tt_pattern: TrajectoryPattern | None = None
        # groupings of the measurements of the dense residual blocks, reused while unchanged
        self._group_cache = GroupCache()

    def share_assembly_caches(self, other: Problem) -> None:
        """Assemble with ``other``'s sparsity pattern and measurement groupings from now on.

        For a problem built like ``other`` (the same residual blocks on the same data, the
        parameters moved by a step): its first linearisation then reuses what ``other``'s last
        one computed wherever the elements each measurement touches are the same. Both caches
        compare the elements before reusing anything, so the result is what a fresh cache gives.
        """
        self._tt_pattern = other._tt_pattern
        self._group_cache = other._group_cache

    # ------------------------------------------------------------------------------ building
    def add_parameter_block(self, block: ParameterBlock) -> ParameterBlock:
        """Add a parameter block.

        Args:
            block: The block; its name must be unique.

        Returns:
            The same block.

        Raises:
            ValueError: When the name is taken.
        """
        if block.name in self._blocks:
            msg = f"A parameter block named {block.name!r} already exists."
            raise ValueError(msg)
        self._blocks[block.name] = block
        return block

    def add_residual_block(self, residual: ResidualBlock, loss: Loss | None = None) -> None:
        """Add a residual block.

        Args:
            residual: The residual block.
            loss: Robust loss applied to each of its residual groups (None = plain squares).
        """
        self._residuals.append(residual)
        self._losses.append(loss)

    @property
    def parameter_blocks(self) -> tuple[ParameterBlock, ...]:
        """All parameter blocks in insertion order."""
        return tuple(self._blocks.values())

    @property
    def residual_blocks(self) -> tuple[ResidualBlock, ...]:
        """All residual blocks in insertion order."""
        return tuple(self._residuals)

    @property
    def losses(self) -> tuple[Loss | None, ...]:
        """The robust loss of each residual block (None: plain squares), in the same order."""
        return tuple(self._losses)

    def __getitem__(self, name: str) -> ParameterBlock:
        """The parameter block called ``name``."""
        return self._blocks[name]

    def __contains__(self, name: object) -> bool:
        """Whether a parameter block called ``name`` exists."""
        return name in self._blocks

    # ------------------------------------------------------------------------------- state
    def values(self) -> dict[str, F64]:
        """Block name -> current value."""
        return {name: b.value for name, b in self._blocks.items()}

    def set_values(self, values: Mapping[str, npt.ArrayLike]) -> None:
        """Set the values of the named blocks."""
        for name, v in values.items():
            self._blocks[name].set_value(v)

    def layout(self) -> Layout:
        """The reduced-coordinate layout for the current fixed masks."""
        order = [b for b in self._blocks.values() if b.group == "trajectory"]
        order += [b for b in self._blocks.values() if b.group == "calibration"]
        index: dict[str, IntArray] = {}
        names: list[str] = []
        scales: list[F64] = []
        owner: list[str] = []
        offset = 0
        nt = 0
        for block in order:
            free = ~block.fixed_mask
            idx = np.full(block.size, -1, dtype=np.intp)
            k = int(np.count_nonzero(free))
            idx[free] = np.arange(offset, offset + k)
            index[block.name] = idx
            names.extend(np.asarray(block.coord_names, dtype=object)[free].tolist())
            scales.append(block.scale[free])
            owner.extend([block.name] * k)
            offset += k
            if block.group == "trajectory":
                nt = offset
        scale = np.concatenate(scales) if scales else np.zeros(0)
        return Layout(
            block_names=tuple(b.name for b in order),
            index=index,
            num_trajectory=nt,
            num_calibration=offset - nt,
            names=tuple(names),
            scale=scale,
            owner=tuple(owner),
        )

    def retracted_values(self, dx: F64, layout: Layout) -> dict[str, F64]:
        """Block values after a step in reduced coordinates (the problem is not changed).

        Args:
            dx: (Nt + Nc,) step in solver order.
            layout: The layout ``dx`` refers to.

        Returns:
            Block name -> stepped value (unchanged blocks keep their current value).
        """
        out = self.values()
        for name in layout.block_names:
            idx = layout.index[name]
            free = idx >= 0
            if not np.any(free):
                continue
            delta = np.zeros(idx.size)
            delta[free] = dx[idx[free]]
            out[name] = self._blocks[name].retracted(delta)
        return out

    # -------------------------------------------------------------------------- evaluation
    def evaluate(
        self,
        values: Mapping[str, F64] | None = None,
        *,
        jacobians: bool = True,
        residual_blocks: Iterable[ResidualBlock] | None = None,
    ) -> Evaluation:
        """Evaluate residual blocks.

        Args:
            values: Block values to use (default: the current values).
            jacobians: Whether Jacobians are requested.
            residual_blocks: Subset of the problem's residual blocks (default: all).

        Returns:
            The evaluation with costs.
        """
        vals = self.values() if values is None else dict(values)
        if residual_blocks is None:
            chosen = list(zip(self._residuals, self._losses, strict=True))
        else:
            loss_of = {id(r): loss for r, loss in zip(self._residuals, self._losses, strict=True)}
            chosen = [(r, loss_of.get(id(r))) for r in residual_blocks]
        evals: list[ResidualEval] = []
        losses: list[Loss | None] = []
        costs: list[float] = []
        num = 0
        for residual, loss in chosen:
            ev = residual.evaluate(vals, jacobians=jacobians)
            s = np.einsum("ij,ij->i", ev.residuals, ev.residuals)
            rho = s if loss is None else loss(s)[0]
            evals.append(ev)
            losses.append(loss)
            costs.append(0.5 * float(np.sum(rho)))
            num += ev.residuals.size
        cost = float(np.sum(costs)) if costs else 0.0
        return Evaluation(vals, tuple(evals), tuple(losses), tuple(costs), cost, num)

    def linearize(self, evaluation: Evaluation, layout: Layout | None = None) -> Linearization:
        """Assemble ``H`` and ``g`` from an evaluation with Jacobians.

        Args:
            evaluation: Output of :meth:`evaluate` with ``jacobians=True``.
            layout: Coordinate layout (default: :meth:`layout`).

        Returns:
            The normal equations.

        Raises:
            ValueError: When a Jacobian names an unknown block or has the wrong tangent size.
        """
        layout = self.layout() if layout is None else layout
        g = np.zeros(layout.num_free)
        acc = Accumulator(layout.num_trajectory, layout.num_calibration, self._tt_pattern)
        for ev, r, weight, sparse in _weighted_blocks(evaluation):
            sqrt_w = None if weight is None else np.sqrt(weight)
            if sparse:
                r_w = r if sqrt_w is None else r * sqrt_w[:, None]
                add_sparse(self._sparse_pieces(ev, layout), r_w, sqrt_w, g, acc)
            else:
                add_dense_split(
                    self._dense_parts(ev, layout), r, sqrt_w, layout, g, acc, self._group_cache
                )
        self._group_cache.done()
        h_tt, h_tc, h_cc = acc.result()
        self._tt_pattern = acc.pattern
        return Linearization(layout, evaluation.cost, evaluation.num_residuals, h_tt, h_tc, h_cc, g)

    def gradient(self, evaluation: Evaluation, layout: Layout | None = None) -> F64:
        """The gradient ``J^T r`` (IRLS-weighted) of :meth:`linearize` alone, without assembling
        the curvature (the same sums in another order: equal to rounding).

        Args:
            evaluation: Output of :meth:`evaluate` with ``jacobians=True``.
            layout: Coordinate layout (default: :meth:`layout`).

        Returns:
            (Nt + Nc,) the gradient.

        Raises:
            ValueError: When a Jacobian names an unknown block or has the wrong tangent size.
        """
        layout = self.layout() if layout is None else layout
        g = np.zeros(layout.num_free)
        for ev, r, weight, sparse in _weighted_blocks(evaluation):
            r_w = r if weight is None else r * weight[:, None]
            if sparse:
                add_sparse_gradient(self._sparse_pieces(ev, layout), r_w, g)
            else:
                add_dense_gradient(self._dense_parts(ev, layout), r_w, g)
        return g

    def jacobian_matrix(self, evaluation: Evaluation, block: int, layout: Layout) -> sp.csr_matrix:
        """The Jacobian of one residual block on the free coordinates, robust-loss weighted.

        Args:
            evaluation: An evaluation with Jacobians.
            block: Index of the residual block in ``evaluation.evals``.
            layout: The coordinate layout.

        Returns:
            (n m, Nt + Nc) sparse ``sqrt(w) J`` (rows ``i m + k``), the Jacobian whose Gram
            matrix is the block's share of :meth:`linearize`'s ``H``.
        """
        ev = evaluation.evals[block]
        loss = evaluation.losses[block]
        n, m = ev.residuals.shape
        if all(isinstance(j, DenseJacobian) for j in ev.jacobians):
            return self._dense_jacobian_matrix(ev, loss, layout)
        rows, cols, vals = self._free_triplets(ev, layout)
        if loss is not None:
            r = ev.residuals
            sqrt_w = np.sqrt(loss(np.einsum("ij,ij->i", r, r))[1])
            vals = vals * np.repeat(sqrt_w, m)[rows]
        return sp.csr_matrix((vals, (rows, cols)), shape=(n * m, layout.num_free))

    def coupling_matrix(
        self,
        evaluation: Evaluation,
        block: int,
        layout: Layout,
        jac_p: F64,
        group: IntArray,
        num_groups: int,
    ) -> sp.csr_matrix:
        """``J^T J_p`` of a block with one scalar residual per measurement and a nuisance.

        ``J`` is the block's Jacobian on the free coordinates (whitened, without the robust-loss
        weights: fold them into ``jac_p``); ``J_p`` holds each measurement's derivatives
        ``jac_p[i]`` in the ``k`` columns of its group. Measurements that touch the same
        elements of a parameter block and belong to the same group share their columns, so each
        dense piece is summed over such runs first (one sparse-dense product) and only the sums
        are scattered: the product of two sparse matrices with a row per measurement built
        about 30 times more entries.

        Args:
            evaluation: An evaluation with Jacobians.
            block: Index of the residual block in ``evaluation.evals``.
            layout: The coordinate layout.
            jac_p: (n, k) derivatives of each residual with respect to its group's coordinates.
            group: (n,) group of each measurement, in ``[0, num_groups)``.
            num_groups: ``G``.

        Returns:
            (Nt + Nc, G k) sparse coupling.
        """
        ev = evaluation.evals[block]
        n, m = ev.residuals.shape
        jp = np.asarray(jac_p, dtype=np.float64)
        grp = np.asarray(group, dtype=np.intp).reshape(-1)
        k = jp.shape[1]
        shape = (layout.num_free, num_groups * k)
        if m != 1 or jp.shape[0] != n or grp.shape != (n,):
            msg = "coupling_matrix needs one residual per measurement and (n, k) derivatives"
            raise ValueError(msg)
        if not all(isinstance(j, DenseJacobian) for j in ev.jacobians):
            x_rows, x_cols, x_vals = self._free_triplets(ev, layout)
            j_x = sp.csr_matrix((x_vals, (x_rows, x_cols)), shape=(n * m, layout.num_free))
            p_cols = grp[:, None] * k + np.arange(k)
            j_p = sp.csr_matrix(
                (jp.reshape(-1), p_cols.reshape(-1), np.arange(0, n * k + 1, k)),
                shape=(n, shape[1]),
            )
            return sp.csr_matrix(j_x.T @ j_p)
        parts = self._dense_parts(ev, layout)
        # pieces touching the same elements (a spline's rotation and position control points)
        # share their runs: found once for each
        firsts = first_with_same_elements(parts)
        distinct = list(dict.fromkeys(firsts))
        runs_of = dict(
            zip(
                distinct,
                map_blocks(
                    lambda d: _runs(
                        grp,
                        parts[distinct[d]].elements.reshape(n, -1),
                        num_groups,
                        parts[distinct[d]].table.shape[0],
                    ),
                    len(distinct),
                ),
                strict=True,
            )
        )

        def coupling(i: int) -> tuple[IntArray, IntArray, F64]:
            part = parts[i]
            first, run = runs_of[firsts[i]]
            runs = first.shape[0]
            # (n, runs k): measurement i's jac_p[i, j] in column run(i) k + j; its transpose
            # sums them over each run
            select = sp.csr_matrix(
                (
                    jp.reshape(-1),
                    (run[:, None] * k + np.arange(k)).reshape(-1),
                    np.arange(0, n * k + 1, k),
                ),
                shape=(n, runs * k),
            )
            sums = np.asarray(select.T @ part.values[:, 0, :]).reshape(runs, k, -1)  # (runs, k, w)
            cols_x = part.table[part.elements[first]].reshape(runs, -1)  # (runs, w)
            cols_p = grp[first][:, None] * k + np.arange(k)  # (runs, k)
            rows = np.broadcast_to(cols_x[:, None, :], sums.shape)
            cols = np.broadcast_to(cols_p[:, :, None], sums.shape)
            keep = rows >= 0
            return rows[keep], cols[keep], sums[keep]

        triplets = map_blocks(coupling, len(parts))
        rows_all = [t[0] for t in triplets]
        cols_all = [t[1] for t in triplets]
        vals_all = [t[2] for t in triplets]
        if not rows_all:
            return sp.csr_matrix(shape)
        return sp.csr_matrix(
            (np.concatenate(vals_all), (np.concatenate(rows_all), np.concatenate(cols_all))),
            shape=shape,
        )

    def _free_triplets(self, ev: ResidualEval, layout: Layout) -> tuple[IntArray, IntArray, F64]:
        """COO ``(rows, reduced columns, values)`` of every Jacobian piece of ``ev`` on the free
        coordinates (whitened, without robust-loss weights)."""
        rows_all, cols_all, vals_all = [], [], []
        for rows, cols, vals in self._sparse_pieces(ev, layout):
            keep = cols >= 0
            rows_all.append(rows[keep])
            cols_all.append(cols[keep])
            vals_all.append(vals[keep])
        rows = np.concatenate(rows_all) if rows_all else np.zeros(0, dtype=np.intp)
        cols = np.concatenate(cols_all) if cols_all else np.zeros(0, dtype=np.intp)
        vals = np.concatenate(vals_all) if vals_all else np.zeros(0)
        return rows, cols, vals

    def _dense_jacobian_matrix(
        self, ev: ResidualEval, loss: Loss | None, layout: Layout
    ) -> sp.csr_matrix:
        """:meth:`jacobian_matrix` when every piece is dense: every row has the same number of
        entries, so the CSR arrays are laid out directly (no COO sort); a fixed coordinate's
        entries stay as explicit zeros in column 0."""
        n, m = ev.residuals.shape
        cols_parts: list[IntArray] = []
        vals_parts: list[F64] = []
        for part in self._dense_parts(ev, layout):
            a_d = part.values.shape[2]
            touched = part.table[part.elements].reshape(n, 1, a_d)
            cols_parts.append(np.broadcast_to(touched, (n, m, a_d)))
            vals_parts.append(part.values)
        if not cols_parts:
            return sp.csr_matrix((n * m, layout.num_free))
        cols = np.concatenate(cols_parts, axis=2).reshape(n * m, -1)
        vals = np.concatenate(vals_parts, axis=2).reshape(n * m, -1)
        fixed = cols < 0
        if np.any(fixed):
            vals = np.where(fixed, 0.0, vals)
            cols = np.where(fixed, 0, cols)
        if loss is not None:
            r = ev.residuals
            sqrt_w = np.sqrt(loss(np.einsum("ij,ij->i", r, r))[1])
            vals = vals * np.repeat(sqrt_w, m)[:, None]
        k = cols.shape[1]
        indptr = np.arange(0, n * m * k + 1, k, dtype=np.intp)
        return sp.csr_matrix(
            (vals.reshape(-1), cols.reshape(-1), indptr), shape=(n * m, layout.num_free)
        )

    def _block_index(self, jac: DenseJacobian | SparseJacobian, layout: Layout) -> IntArray | None:
        if jac.block not in self._blocks:
            msg = f"A Jacobian refers to the unknown parameter block {jac.block!r}."
            raise ValueError(msg)
        block = self._blocks[jac.block]
        if isinstance(jac, DenseJacobian) and jac.values.shape[3] != block.tangent_dim:
            msg = (
                f"The Jacobian for {jac.block!r} has {jac.values.shape[3]} columns per element; "
                f"the block's tangent dimension is {block.tangent_dim}."
            )
            raise ValueError(msg)
        idx = layout.index[jac.block]
        if not np.any(idx >= 0):
            return None
        return idx

    def _dense_parts(self, ev: ResidualEval, layout: Layout) -> list[DensePart]:
        """The dense Jacobian pieces of ``ev`` on free coordinates, with their reduced columns."""
        n, m = ev.residuals.shape
        parts: list[DensePart] = []
        for jac in ev.jacobians:
            assert isinstance(jac, DenseJacobian)
            idx = self._block_index(jac, layout)
            if idx is None:
                continue
            block = self._blocks[jac.block]
            a, d = jac.values.shape[2:]
            parts.append(
                DensePart(
                    np.asarray(jac.elements, dtype=np.intp),
                    idx.reshape(block.num_elements, d),
                    jac.values.reshape(n, m, a * d),
                    block.group == "trajectory",
                )
            )
        return parts

    def _sparse_pieces(
        self, ev: ResidualEval, layout: Layout
    ) -> list[tuple[IntArray, IntArray, F64]]:
        """COO ``(rows, reduced columns (-1 fixed), values)`` of every Jacobian piece of ``ev``."""
        pieces: list[tuple[IntArray, IntArray, F64]] = []
        for jac in ev.jacobians:
            idx = self._block_index(jac, layout)
            if idx is None:
                continue
            coo = jac.to_coo() if isinstance(jac, DenseJacobian) else jac
            rows = np.asarray(coo.rows, dtype=np.intp)
            pieces.append((rows, idx[coo.cols], coo.values))
        return pieces


def _weighted_blocks(
    evaluation: Evaluation,
) -> Iterator[tuple[ResidualEval, F64, F64 | None, bool]]:
    """Each evaluated residual block with measurements: ``(its evaluation, (n, m) whitened
    residuals, (n,) robust-loss weights or None, whether any of its Jacobians is sparse)``, as
    :meth:`Problem.linearize` and :meth:`Problem.gradient` assemble them."""
    for ev, loss in zip(evaluation.evals, evaluation.losses, strict=True):
        r = ev.residuals
        if r.shape[0] == 0:
            continue
        weight = None if loss is None else loss(np.einsum("ij,ij->i", r, r))[1]
        yield ev, r, weight, any(isinstance(j, SparseJacobian) for j in ev.jacobians)


def _runs(
    group: IntArray, elements: IntArray, num_groups: int, num_elements: int
) -> tuple[IntArray, IntArray]:
    """Measurements with the same group and the same touched elements, as runs.

    Returns:
        (runs,) the first measurement of each run and (n,) the run of each measurement.
    """
    dims = (max(num_groups, 1),) + (max(num_elements, 1),) * elements.shape[1]
    if float(np.prod(np.asarray(dims, dtype=np.float64))) < 2.0**62:
        key = np.ravel_multi_index((group, *elements.T), dims)
        _, first, run = np.unique(key, return_index=True, return_inverse=True)
    else:
        rows = np.column_stack([group, elements])
        _, first, run = np.unique(rows, axis=0, return_index=True, return_inverse=True)
    return np.asarray(first, dtype=np.intp), np.asarray(run, dtype=np.intp).reshape(-1)
