"""The split-half comparison (``licalib_cli.pipeline.split.compare_halves``) and what the checks
take from it: only coordinates both halves determine are compared or enlarge the sigmas."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from licalib_cli.pipeline.checks import _split, _split_section, inflate
from licalib_cli.pipeline.split import COORDINATES, compare_halves
from licalib_cli.sections import Consistency, SplitHalf

SIGMA = np.array([1e-3, 1e-3, 1e-3, 2e-4, 2e-4, 2e-4, 3e-5])


def _cov(sigma: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A covariance with these sigmas and some correlation."""
    a = rng.normal(size=(7, 7))
    corr = np.corrcoef(a @ a.T + 7 * np.eye(7))
    return corr * np.outer(sigma, sigma)


def test_the_chi_square_is_the_mahalanobis_distance_when_both_halves_determine_all() -> None:
    rng = np.random.default_rng(0)
    c1, c2 = _cov(SIGMA, rng), _cov(2 * SIGMA, rng)
    diff = rng.normal(size=7) * SIGMA
    res = compare_halves(diff, SIGMA, 2 * SIGMA, c1, c2, 5.0)
    assert res.ran and res.dof == 7
    expected = float(diff @ np.linalg.solve(c1 + c2, diff))
    np.testing.assert_allclose(res.chi2, expected, rtol=1e-9)


def test_a_coordinate_one_half_does_not_determine_is_left_out() -> None:
    """The calm half holds t_z near the segment's value; the other half's tiny sigma must not
    turn the difference into a disagreement."""
    rng = np.random.default_rng(1)
    c1 = _cov(SIGMA, rng)
    s2 = 2 * SIGMA.copy()
    s2[2] = np.inf
    c2 = _cov(2 * SIGMA, rng)
    c2[2, :] = c2[:, 2] = 0.0  # not determined: zero row, as the solver reports it
    diff = 0.3 * SIGMA.copy()
    diff[2] = 50 * SIGMA[2]  # whatever the undetermined half did along t_z
    res = compare_halves(diff, SIGMA, s2, c1, c2, 5.0)
    keep = np.array([0, 1, 3, 4, 5, 6])
    sub = (c1 + c2)[np.ix_(keep, keep)]
    assert res.ran and res.dof == 6
    np.testing.assert_allclose(res.chi2, float(diff[keep] @ np.linalg.solve(sub, diff[keep])))
    assert res.chi2 < 10.0 and np.isnan(res.z[2]) and not np.isfinite(res.sigma[2])
    assert "translation.z" not in res.compared and len(res.compared) == 6
    # the checks enlarge no sigma by a difference the halves cannot both see
    sigma, _ = inflate(SIGMA, (), [], res, SimpleNamespace(jitter=False))
    assert sigma[2] == SIGMA[2]


def test_halves_that_share_no_determined_coordinate_are_not_compared() -> None:
    rng = np.random.default_rng(2)
    res = compare_halves(
        rng.normal(size=7), SIGMA, np.full(7, np.inf), _cov(SIGMA, rng), np.zeros((7, 7)), 5.0
    )
    assert not res.ran and "determined by both halves" in res.reason


def _figure(section: SplitHalf) -> str:
    rows = Consistency(split_half=section).rows()
    (row,) = [r for r in rows if r[0] == "split halves"]
    return row[1]


def test_the_checks_table_and_the_result_name_what_the_halves_compared() -> None:
    """An "agree" over the translation alone must not read as the whole extrinsic agreeing: the
    table names the compared coordinates when a half leaves some undetermined, and the result
    file lists them."""
    rng = np.random.default_rng(3)
    s1, s2 = SIGMA.copy(), 2 * SIGMA.copy()
    s1[[0, 3, 4, 5]] = np.inf  # the first half determines t_y, t_z and the time offset only
    c1 = _cov(SIGMA, rng)
    c1[[0, 3, 4, 5], :] = 0.0
    c1[:, [0, 3, 4, 5]] = 0.0
    res = compare_halves(0.5 * SIGMA, s1, s2, c1, _cov(2 * SIGMA, rng), 10.0)
    assert res.compared == ("translation.y", "translation.z", "time_offset")
    section = _split_section(res)
    assert section.to_dict()["compared"] == ["translation.y", "translation.z", "time_offset"]
    assert SplitHalf.from_dict(section.to_dict()).compared == res.compared
    assert _figure(section).endswith(
        "; only t_y, t_z, time offset: a half does not determine the others"
    )
    # every coordinate compared: the figure stays as it was
    full = _split_section(
        compare_halves(0.5 * SIGMA, SIGMA, SIGMA, _cov(SIGMA, rng), _cov(SIGMA, rng), 10.0)
    )
    assert full.compared == COORDINATES and "only" not in _figure(full)
    # a result file written before the list existed reads back without one
    old = {k: v for k, v in full.to_dict().items() if k != "compared"}
    assert SplitHalf.from_dict(old).compared == () and "only" not in _figure(
        SplitHalf.from_dict(old)
    )


def test_halves_that_disagree_name_the_coordinate_that_differs_most() -> None:
    rng = np.random.default_rng(6)
    diff = 0.5 * SIGMA.copy()
    diff[3] = 40 * SIGMA[3]  # the rotation about the LiDAR x axis changed between the halves
    res = compare_halves(diff, SIGMA, SIGMA, _cov(SIGMA, rng), _cov(SIGMA, rng), 10.0)
    (finding,) = _split(res)
    assert finding.severity == "warn" and "The two halves of the segment disagree" in finding.text
    assert f"the most, roll (LiDAR x) by {np.degrees(diff[3]):+.4f} deg" in finding.text
    # halves that agree add no finding
    assert (
        _split(compare_halves(0.5 * SIGMA, SIGMA, SIGMA, _cov(SIGMA, rng), _cov(SIGMA, rng), 10.0))
        == []
    )
