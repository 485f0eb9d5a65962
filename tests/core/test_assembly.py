"""Assembly of the normal equations from dense Jacobians, against an independent dense reference.

The residual block below has random whitened residuals and Jacobians with the structures the
calibration problem produces (and a few more), so that every assembly path is exercised:

* ``ctrl``: trajectory, 4 consecutive control points per measurement (keyed by segment; padded
  chunks), ``bias``: trajectory, the same element for every measurement (constant);
* ``beam``: calibration, one narrow element per measurement (one-hot product; its coupling with
  ``ctrl`` by the encoded sparse product), ``ext``: calibration, constant;
* ``wide``: calibration, one wide element per measurement (padded chunks, encoded coupling);
* ``pair``: trajectory, two arbitrary elements per measurement (its coupling with ``ctrl`` goes
  through the partition refining both);
* ``shared``: calibration, two arbitrary elements per measurement (groups share columns);
* a second ``ctrl`` piece touching one control point per measurement, grouped exactly like the
  first one (merged with it; pieces for the same block add up).

Coordinates of several blocks are fixed, measurements come sorted by segment or shuffled, with and
without a Huber loss, with one and with three residuals per measurement.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import replace

import numpy as np
import pytest

from licalib_cli.parallel import threads as thr
from licalib_cli.solver import (
    DenseJacobian,
    HuberLoss,
    ParameterBlock,
    Problem,
    ResidualEval,
)
from licalib_cli.solver.assembly import (
    MAP_ENTRIES,
    _compress_key,
    _element_key,
    _unique_entries,
)

NUM_CTRL = 14
NUM_BEAMS = 5
NUM_WIDE = 3
NUM_PAIR = 6
NUM_SHARED = 4


class RandomBlock:
    """Fixed random residuals and dense Jacobians with the structures listed in the docstring."""

    def __init__(
        self, rng: np.random.Generator, n: int, m: int, shuffled: bool, reverse: bool = False
    ) -> None:
        self.name = "random"
        seg = np.sort(rng.integers(0, NUM_CTRL - 3, n))
        if shuffled:
            seg = rng.permutation(seg)
        zeros = np.zeros((n, 1), dtype=int)
        self.r = rng.normal(0.0, 2.0, (n, m))
        self.jacobians = (
            DenseJacobian("ctrl", seg[:, None] + np.arange(4), rng.normal(size=(n, m, 4, 3))),
            DenseJacobian("bias", zeros, rng.normal(size=(n, m, 1, 3))),
            DenseJacobian(
                "beam", rng.integers(0, NUM_BEAMS, (n, 1)), rng.normal(size=(n, m, 1, 2))
            ),
            DenseJacobian("ext", zeros, rng.normal(size=(n, m, 1, 3))),
            DenseJacobian(
                "wide", rng.integers(0, NUM_WIDE, (n, 1)), rng.normal(size=(n, m, 1, 10))
            ),
            DenseJacobian("pair", rng.integers(0, NUM_PAIR, (n, 2)), rng.normal(size=(n, m, 2, 2))),
            DenseJacobian(
                "shared", rng.integers(0, NUM_SHARED, (n, 2)), rng.normal(size=(n, m, 2, 1))
            ),
            DenseJacobian("ctrl", seg[:, None] + 2, rng.normal(size=(n, m, 1, 3))),
        )
        if reverse:
            self.jacobians = self.jacobians[::-1]

    def evaluate(self, params: Mapping[str, np.ndarray], jacobians: bool = True) -> ResidualEval:
        return ResidualEval(self.r, self.jacobians if jacobians else ())


def make_problem(
    seed: int, n: int, m: int, shuffled: bool, loss: HuberLoss | None, reverse: bool = False
) -> tuple[Problem, RandomBlock]:
    rng = np.random.default_rng(seed)
    pr = Problem()
    pr.add_parameter_block(ParameterBlock("ctrl", np.zeros((NUM_CTRL, 3))))
    pr.add_parameter_block(ParameterBlock("bias", np.zeros(3)))
    pr.add_parameter_block(ParameterBlock("pair", np.zeros((NUM_PAIR, 2))))
    pr.add_parameter_block(ParameterBlock("beam", np.zeros((NUM_BEAMS, 2)), group="calibration"))
    pr.add_parameter_block(ParameterBlock("ext", np.zeros(3), group="calibration"))
    pr.add_parameter_block(ParameterBlock("wide", np.zeros((NUM_WIDE, 10)), group="calibration"))
    pr.add_parameter_block(ParameterBlock("shared", np.zeros((NUM_SHARED, 1)), group="calibration"))
    block = RandomBlock(rng, n, m, shuffled, reverse)
    pr.add_residual_block(block, loss)
    return pr, block


def dense_reference(pr: Problem, block: RandomBlock, loss: HuberLoss | None) -> tuple:
    """``J^T W J`` and ``J^T W r`` from a dense Jacobian built from COO triplets."""
    lay = pr.layout()
    n, m = block.r.shape
    jd = np.zeros((n * m, lay.num_free))
    for jac in block.jacobians:
        coo = jac.to_coo()
        cols = lay.index[jac.block][coo.cols]
        keep = cols >= 0
        np.add.at(jd, (coo.rows[keep], cols[keep]), coo.values[keep])
    w = np.ones(n) if loss is None else loss(np.sum(block.r**2, axis=1))[1]
    sw = np.repeat(np.sqrt(w), m)
    j = jd * sw[:, None]
    r = block.r.reshape(-1) * sw
    return j.T @ j, j.T @ r


@pytest.mark.parametrize("m", [1, 3])
@pytest.mark.parametrize("shuffled", [False, True])
@pytest.mark.parametrize(("huber", "reverse"), [(False, False), (True, False), (True, True)])
def test_dense_assembly_matches_reference(
    m: int, shuffled: bool, huber: bool, reverse: bool
) -> None:
    loss = HuberLoss(1.5) if huber else None
    pr, block = make_problem(7 + m + 2 * shuffled, 700, m, shuffled, loss, reverse)
    pr["ctrl"].fix([0, 1, 2, 40])  # the first control point (gauge) and one more coordinate
    pr["beam"].fix([0, 1, 5])  # a whole beam and half of another
    pr["wide"].fix([3, 17])
    pr["pair"].fix([4])
    pr["ext"].fix(["ext.y"])
    pr["shared"].fix([2])
    lin = pr.linearize(pr.evaluate())
    h, g = dense_reference(pr, block, loss)
    scale = np.abs(h).max()
    assert lin.layout.num_free == h.shape[0] == 38 + 3 + 11 + 7 + 2 + 28 + 3
    np.testing.assert_allclose(lin.dense(), h, rtol=0.0, atol=1e-12 * scale)
    np.testing.assert_allclose(lin.g, g, rtol=0.0, atol=1e-12 * np.abs(g).max())
    # the assembled H_tt is canonical CSC (sorted, no duplicates)
    assert lin.H_tt.has_canonical_format


@pytest.mark.parametrize("m", [1, 3])
@pytest.mark.parametrize("huber", [False, True])
@pytest.mark.parametrize("sparse", [False, True])
def test_the_gradient_alone_is_the_linearisations(m: int, huber: bool, sparse: bool) -> None:
    """``Problem.gradient`` equals the gradient ``linearize`` assembles with the curvature, from
    dense and from sparse Jacobian pieces, with fixed coordinates and a robust loss."""
    loss = HuberLoss(1.5) if huber else None
    pr, block = make_problem(31 + m, 600, m, True, loss)
    pr["ctrl"].fix([0, 1, 2, 40])
    pr["beam"].fix([0, 1, 5])
    pr["ext"].fix(["ext.y"])
    evaluation = pr.evaluate()
    if sparse:
        evaluation = replace(
            evaluation,
            evals=tuple(
                ResidualEval(ev.residuals, tuple(j.to_coo() for j in ev.jacobians))
                for ev in evaluation.evals
            ),
        )
    layout = pr.layout()
    got = pr.gradient(evaluation, layout)
    with thr.serial():  # the pieces on the block threads: the same sums, bit for bit
        np.testing.assert_array_equal(pr.gradient(evaluation, layout), got)
    _, expected = dense_reference(pr, block, loss)
    np.testing.assert_allclose(got, expected, rtol=0.0, atol=1e-12 * np.abs(expected).max())
    np.testing.assert_allclose(
        got, pr.linearize(evaluation, layout).g, rtol=0.0, atol=1e-12 * np.abs(expected).max()
    )


@pytest.mark.parametrize("pieces", [2, 3])
@pytest.mark.parametrize("shuffled", [False, True])
def test_a_large_block_assembled_in_parts_matches_the_reference(
    monkeypatch: pytest.MonkeyPatch, pieces: int, shuffled: bool
) -> None:
    """A block of at least SPLIT_ROWS measurements is assembled in SPLIT_PARTS consecutive parts
    on the block threads and summed: the same normal equations, again when the groupings and the
    trajectory pattern of the first assembly are reused, and the same bits with one thread."""
    from licalib_cli.parallel.threads import serial
    from licalib_cli.solver import assembly

    calls: list[int] = []
    whole = assembly.add_dense

    def counted(parts, r, *args):  # type: ignore[no-untyped-def]
        calls.append(r.shape[0])
        return whole(parts, r, *args)

    monkeypatch.setattr(assembly, "SPLIT_ROWS", 500)
    monkeypatch.setattr(assembly, "SPLIT_PARTS", pieces)
    monkeypatch.setattr(assembly, "add_dense", counted)
    loss = HuberLoss(1.5)
    pr, block = make_problem(11 + shuffled, 701, 3, shuffled, loss)
    pr["ctrl"].fix([0, 1, 2])
    pr["beam"].fix([0, 1])
    for _ in range(2):
        calls.clear()
        lin = pr.linearize(pr.evaluate())
        assert len(calls) == pieces and sum(calls) == 701
        h, g = dense_reference(pr, block, loss)
        np.testing.assert_allclose(lin.dense(), h, rtol=0.0, atol=1e-12 * np.abs(h).max())
        np.testing.assert_allclose(lin.g, g, rtol=0.0, atol=1e-12 * np.abs(g).max())
        assert lin.H_tt.has_canonical_format
    with serial():
        alone = pr.linearize(pr.evaluate())
    assert np.array_equal(alone.dense(), lin.dense()) and np.array_equal(alone.g, lin.g)
    calls.clear()
    small, _ = make_problem(3, 499, 1, shuffled, None)
    small.linearize(small.evaluate())
    assert calls == [499]  # below SPLIT_ROWS: one part


def test_assembly_reuses_and_refreshes_the_trajectory_pattern() -> None:
    pr, block = make_problem(3, 400, 1, False, None)
    first = pr.linearize(pr.evaluate())
    block.jacobians = tuple(
        DenseJacobian(j.block, j.elements, 2.0 * j.values) for j in block.jacobians
    )
    second = pr.linearize(pr.evaluate())  # same pattern, new values
    np.testing.assert_allclose(second.dense(), 4.0 * first.dense(), rtol=1e-12, atol=1e-12)
    pr["ctrl"].fix([5, 6])  # new layout: new pattern
    third = pr.linearize(pr.evaluate())
    h, _ = dense_reference(pr, block, None)
    np.testing.assert_allclose(third.dense(), h, rtol=0.0, atol=1e-12 * np.abs(h).max())
    # a measurement moving to a segment no other measurement uses changes the pattern too
    ctrl = block.jacobians[0]
    seg = np.minimum(ctrl.elements[:, 0], NUM_CTRL - 6)
    seg[0] = NUM_CTRL - 4
    elements = seg[:, None] + np.arange(4)
    block.jacobians = (DenseJacobian("ctrl", elements, ctrl.values), *block.jacobians[1:])
    fourth = pr.linearize(pr.evaluate())
    h, _ = dense_reference(pr, block, None)
    np.testing.assert_allclose(fourth.dense(), h, rtol=0.0, atol=1e-12 * np.abs(h).max())


def test_a_problem_sharing_anothers_caches_assembles_what_a_fresh_one_does() -> None:
    """A stepped copy of a problem (the planes-free trials) takes over its assembly caches: with
    the same elements it assembles bit for bit what its own fresh caches give, and with a
    measurement moved to another segment it does not reuse the stale pattern."""
    pr, _ = make_problem(3, 400, 1, False, None)
    pr.linearize(pr.evaluate())
    fresh, fresh_block = make_problem(3, 400, 1, False, None)
    shared, shared_block = make_problem(3, 400, 1, False, None)
    shared.share_assembly_caches(pr)
    for b in (fresh_block, shared_block):
        b.jacobians = tuple(DenseJacobian(j.block, j.elements, 2.0 * j.values) for j in b.jacobians)
    a = fresh.linearize(fresh.evaluate())
    b = shared.linearize(shared.evaluate())
    assert shared._tt_pattern is pr._tt_pattern  # reused, not rebuilt
    assert np.array_equal(b.dense(), a.dense()) and np.array_equal(b.g, a.g)
    ctrl = shared_block.jacobians[0]
    seg = np.minimum(ctrl.elements[:, 0], NUM_CTRL - 6)
    seg[0] = NUM_CTRL - 4
    moved = (DenseJacobian("ctrl", seg[:, None] + np.arange(4), ctrl.values),)
    shared_block.jacobians = (*moved, *shared_block.jacobians[1:])
    again = shared.linearize(shared.evaluate())
    h, _ = dense_reference(shared, shared_block, None)
    np.testing.assert_allclose(again.dense(), h, rtol=0.0, atol=1e-12 * np.abs(h).max())


def test_constant_only_block_and_empty_block() -> None:
    rng = np.random.default_rng(5)
    pr, block = make_problem(5, 300, 3, False, None)
    block.jacobians = tuple(j for j in block.jacobians if j.block in ("ext", "bias"))
    lin = pr.linearize(pr.evaluate())
    h, g = dense_reference(pr, block, None)
    np.testing.assert_allclose(lin.dense(), h, rtol=0.0, atol=1e-12 * np.abs(h).max())
    np.testing.assert_allclose(lin.g, g, rtol=0.0, atol=1e-12 * np.abs(g).max())
    block.r = rng.normal(size=(0, 3))
    block.jacobians = ()
    lin = pr.linearize(pr.evaluate())
    assert lin.H_tt.nnz == 0 and not np.any(lin.H_cc) and not np.any(lin.g)


def test_group_keys() -> None:
    rng = np.random.default_rng(2)
    raw = rng.integers(0, 10**9, 500)  # wide range: ranks by sorting
    for values in (raw, raw % 37):  # narrow range: ranks by counting
        key = _compress_key(values)
        uniq, inv, cnt = np.unique(values, return_inverse=True, return_counts=True)
        assert key.key is not None and key.num_groups == uniq.size
        np.testing.assert_array_equal(key.key, inv)
        np.testing.assert_array_equal(key.counts, cnt)
        assert not key.is_sorted
    assert _compress_key(np.sort(raw)).is_sorted
    assert _compress_key(np.full(9, 4)).key is None
    # element tuples: a shifted pattern, arbitrary small tuples and tuples too wide for a radix
    for elements in (
        rng.integers(0, 50, 400)[:, None] + np.arange(4),
        rng.integers(0, 5, (400, 3)),
        rng.integers(0, 2**40, (400, 2))[rng.integers(0, 7, 400)],
    ):
        key = _element_key(elements)
        _, inv = np.unique(elements, axis=0, return_inverse=True)
        inv = inv.reshape(-1)
        assert key.key is not None and key.num_groups == inv.max() + 1
        # the same partition (the numbering of the groups may differ)
        pairs = np.unique(np.column_stack([key.key, inv]), axis=0)
        assert pairs.shape[0] == key.num_groups
        np.testing.assert_array_equal(np.bincount(key.key), key.counts)
    assert _element_key(np.tile([3, 1], (5, 1))).key is None


@pytest.mark.parametrize("n", [1, 37, 4526, 16384, 16385, 2**16 - 1, 2**16 + 3])
def test_unique_entries_is_numpys_unique(n: int) -> None:
    """The pattern of ``H_tt`` by the index map, by radix sorts above :data:`MAP_ENTRIES` and by
    a comparison sort above 16-bit indices equals ``np.unique(..., return_inverse=True)``."""
    assert (16384**2 <= MAP_ENTRIES) and (16385**2 > MAP_ENTRIES)  # both sides of the map
    rng = np.random.default_rng(n)
    rows = rng.integers(0, n, 3000)
    cols = np.clip(rows + rng.integers(-5, 6, 3000), 0, n - 1)
    flat = np.concatenate([cols * n + rows, (cols * n + rows)[::7]]).astype(np.int64)
    uniq, inverse = _unique_entries(flat, n)
    expected, expected_inverse = np.unique(flat, return_inverse=True)
    np.testing.assert_array_equal(uniq, expected)
    np.testing.assert_array_equal(inverse, expected_inverse.reshape(-1))
    assert _unique_entries(np.zeros(0, dtype=np.int64), n)[0].size == 0
