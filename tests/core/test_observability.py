"""Calibration information (Schur complement, scaling, spectrum) and direction naming."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import pytest

from licalib_cli.solver import ParameterBlock, Problem, ResidualEval, SparseJacobian
from licalib_cli.solver.observability import (
    calibration_information,
    describe_direction,
    marginal_information,
    summarize_information,
    truncation_mask,
)


class LinearResidual:
    """``r = sum_b A_b x_b - y`` with dense matrices per block, returned as COO triplets."""

    def __init__(self, name: str, mats: dict[str, np.ndarray], y: np.ndarray) -> None:
        self.name, self.mats, self.y = name, mats, y

    def evaluate(self, params: Mapping[str, np.ndarray], jacobians: bool = True) -> ResidualEval:
        r = -self.y.copy()
        pieces = []
        for block, a in self.mats.items():
            r += a @ np.asarray(params[block]).reshape(-1)
            rows, cols = np.nonzero(np.ones_like(a))
            pieces.append(SparseJacobian(block, rows, cols, a[rows, cols]))
        return ResidualEval(r, tuple(pieces))


def _schur(h: np.ndarray, nt: int) -> np.ndarray:
    return h[nt:, nt:] - h[nt:, :nt] @ np.linalg.solve(h[:nt, :nt], h[:nt, nt:])


def make_linear(rng: np.random.Generator) -> tuple[Problem, dict[str, np.ndarray]]:
    pr = Problem()
    pr.add_parameter_block(ParameterBlock("traj", np.zeros((20, 1))))
    pr.add_parameter_block(
        ParameterBlock("ext", np.zeros(3), group="calibration", scale=[0.01, 0.01, 0.02])
    )
    pr.add_parameter_block(ParameterBlock("dt", 0.0, group="calibration", scale=1e-3))
    a_first = np.zeros((60, 20))
    a_first[:, :10] = rng.normal(size=(60, 10))
    a_second = np.zeros((60, 20))
    a_second[:, 10:] = rng.normal(size=(60, 10))
    mats = {
        "first_traj": a_first,
        "first_cal": rng.normal(size=(60, 4)) * [50, 50, 50, 500],
        "second_traj": a_second,
        "second_cal": rng.normal(size=(60, 4)) * [30, 30, 30, 300],
    }
    for tag in ("first", "second"):
        cal = mats[f"{tag}_cal"]
        pr.add_residual_block(
            LinearResidual(
                tag,
                {"traj": mats[f"{tag}_traj"], "ext": cal[:, :3], "dt": cal[:, 3:]},
                np.zeros(60),
            )
        )
    return pr, mats


def test_information_equals_dense_schur_complement_scaled() -> None:
    pr, mats = make_linear(np.random.default_rng(1))
    info = calibration_information(pr)
    j = np.vstack(
        [
            np.hstack([mats["first_traj"], mats["first_cal"]]),
            np.hstack([mats["second_traj"], mats["second_cal"]]),
        ]
    )
    s = _schur(j.T @ j, 20)
    d = np.array([0.01, 0.01, 0.02, 1e-3])
    expected = np.sort(np.linalg.eigvalsh(d[:, None] * s * d[None, :]))[::-1]
    np.testing.assert_allclose(info.singular_values, expected, rtol=1e-8)
    assert info.names == ("ext.x", "ext.y", "ext.z", "dt")
    assert info.owners == ("ext", "ext", "ext", "dt")
    assert info.num_residuals == 120
    assert info.min_singular_value == pytest.approx(expected[-1], rel=1e-8)
    assert info.max_eigenvalue == pytest.approx(expected[0], rel=1e-8)
    assert info.trace == pytest.approx(expected.sum(), rel=1e-8)
    assert info.log_determinant == pytest.approx(np.sum(np.log(expected)), rel=1e-8)
    assert set(info.metrics()) == {
        "min_singular_value",
        "trace",
        "log_determinant",
        "max_eigenvalue",
    }
    # singular vectors are orthonormal eigenvectors of the scaled matrix
    u = info.singular_vectors
    np.testing.assert_allclose(u.T @ u, np.eye(4), atol=1e-12)
    np.testing.assert_allclose(
        info.information @ u, u * info.singular_values, atol=1e-8 * expected[0]
    )
    assert "0.01 (ext.x, ext.y)" in info.scaling and "0.001 (dt)" in info.scaling


def test_information_of_a_subset_drops_untouched_trajectory() -> None:
    pr, mats = make_linear(np.random.default_rng(2))
    first = pr.residual_blocks[0]
    info = calibration_information(pr, [first])
    j = np.hstack([mats["first_traj"][:, :10], mats["first_cal"]])
    s = _schur(j.T @ j, 10)
    d = np.array([0.01, 0.01, 0.02, 1e-3])
    expected = np.sort(np.linalg.eigvalsh(d[:, None] * s * d[None, :]))[::-1]
    np.testing.assert_allclose(info.singular_values, expected, rtol=1e-7)
    assert info.num_residuals == 60
    full = calibration_information(pr)
    assert full.min_singular_value > info.min_singular_value


def test_information_detects_an_unseen_coordinate() -> None:
    pr, _ = make_linear(np.random.default_rng(3))
    pr.add_parameter_block(ParameterBlock("unseen", 0.0, group="calibration", scale=0.1))
    info = calibration_information(pr)
    assert info.min_singular_value == 0.0
    weakest = info.describe(-1, "unobservable")
    np.testing.assert_allclose(np.abs(weakest.vector), [0, 0, 0, 0, 1], atol=1e-9)
    assert weakest.text == "unseen along [1.00]: unobservable"
    assert info.log_determinant == float("-inf")
    assert info.condition_number == float("inf")


def test_describe_direction_paper_example() -> None:
    names = [f"ext.rotation.r{a}" for a in "xyz"] + [f"ext.translation.{a}" for a in "xyz"]
    v = np.array([0.0, 0.0, 0.0, 0.007, -0.187, 0.982])
    for sign in (1.0, -1.0):
        d = describe_direction(sign * v, names)
        assert d.text == (
            "ext.translation along [0.01, -0.19, 0.98] in the IMU frame: "
            "unobservable, not estimated (stays near its initial value)"
        )
        assert d.components[0][0] == "ext.translation.z"
        assert d.components[0][1] == pytest.approx(0.982 / np.linalg.norm(v), abs=1e-12)
        assert [c[0] for c in d.components] == ["ext.translation.z", "ext.translation.y"]
        assert d.blocks[0][0] == "ext.translation"
        assert np.linalg.norm(d.vector) == pytest.approx(1.0)
    # the extrinsic rotation's coordinates are a right perturbation: the LiDAR frame
    mixed = describe_direction([0.0, 0.6, 0.0, 0.0, 0.0, 0.8], names, verdict="weak")
    assert mixed.text == (
        "ext.translation along [0.00, 0.00, 0.80] in the IMU frame "
        "+ ext.rotation along [0.00, 0.60, 0.00] in the LiDAR frame: weak"
    )
    # blocks without a frame, or an explicit (empty) table
    plain = describe_direction(v, names, frames={})
    assert plain.text.startswith("ext.translation along [0.01, -0.19, 0.98]: ")


def test_describe_direction_large_block_and_mixture() -> None:
    names = [f"lidar.beam{b}.{p}" for b in range(4) for p in ("range_offset", "range_scale")]
    names += ["time_offset"]
    owners = ["lidar"] * 8 + ["time_offset"]
    v = np.zeros(9)
    v[2], v[4], v[8] = 0.7, -0.7, 0.14
    d = describe_direction(v, names, owners, verdict="weak")
    assert d.text == (
        "lidar (lidar.beam1.range_offset +0.70, lidar.beam2.range_offset -0.70) "
        "+ time_offset along [0.14]: weak"
    )


def test_truncation_mask_absolute_and_relative() -> None:
    s = np.array([100.0, 2.0, 0.5, 1e-15])
    np.testing.assert_array_equal(truncation_mask(s, 1.0), [True, True, False, False])
    np.testing.assert_array_equal(
        truncation_mask(s, 0.01, relative=True), [True, True, False, False]
    )
    np.testing.assert_array_equal(truncation_mask(s, 0.0), [True, True, True, False])
    info = summarize_information(
        np.diag([4.0, 1.0]), ["a.x", "b"], ["a", "b"], np.array([0.5, 2.0])
    )
    np.testing.assert_allclose(info.singular_values, [4.0, 1.0])  # diag(1, 4) scaled
    np.testing.assert_allclose(np.abs(info.singular_vectors[:, 0]), [0.0, 1.0])


def _summary(rng: np.random.Generator) -> object:
    a = rng.normal(size=(40, 6)) * [30, 30, 3, 1, 0.5, 20]
    a[:, 4] = a[:, 0] + 0.01 * rng.normal(size=40)  # block b trades with a[0]
    names = ["a.x", "a.y", "a.z", "b.x", "b.y", "c.x"]
    owners = ["a", "a", "a", "b", "b", "c"]
    return summarize_information(a.T @ a, names, owners, np.array([1, 1, 1, 2, 2, 1.0]))


def test_marginal_information_is_the_inverse_of_the_kept_covariance() -> None:
    info = _summary(np.random.default_rng(4))
    for prior in (1.0, 0.25):
        out = marginal_information(info, {"a", "c"}, prior=prior)
        assert out.names == ("a.x", "a.y", "a.z", "c.x")
        assert out.owners == ("a", "a", "a", "c")
        np.testing.assert_array_equal(out.scale, [1, 1, 1, 1])
        # a prior of `prior` on the scaled b coordinates, then the kept block of the covariance
        h = info.information + np.diag([0, 0, 0, prior, prior, 0])
        keep = [0, 1, 2, 5]
        expected = np.linalg.inv(np.linalg.inv(h)[np.ix_(keep, keep)])
        np.testing.assert_allclose(out.information, expected, rtol=1e-8, atol=1e-8)
        np.testing.assert_allclose(
            out.singular_values, np.linalg.eigvalsh(expected)[::-1], rtol=1e-8, atol=1e-8
        )
    # what trades with b loses information; a weaker prior on b loses more
    full = info.information
    strong = marginal_information(info, {"a", "c"}, prior=100.0).information
    weak = marginal_information(info, {"a", "c"}, prior=0.01).information
    assert full[0, 0] > strong[0, 0] > weak[0, 0]
    assert weak[0, 0] < 0.05 * full[0, 0]


def test_marginal_information_of_every_block_is_the_summary_itself() -> None:
    info = _summary(np.random.default_rng(5))
    assert marginal_information(info, {"a", "b", "c"}) is info


def test_summed_information_adds_the_scaled_matrices() -> None:
    from licalib_cli.solver.observability import summed_information

    a, b = _summary(np.random.default_rng(6)), _summary(np.random.default_rng(7))
    total = summed_information([a, b])
    np.testing.assert_allclose(total.information, a.information + b.information)
    assert total.names == a.names and total.num_residuals == a.num_residuals + b.num_residuals
    np.testing.assert_allclose(
        total.singular_values, np.linalg.eigvalsh(total.information)[::-1], atol=1e-9
    )
    with pytest.raises(ValueError, match="different coordinates"):
        summed_information([a, marginal_information(b, {"a", "c"})])
    with pytest.raises(ValueError, match="no information"):
        summed_information([])
