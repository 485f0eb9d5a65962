"""The split-half comparison (``licalib_cli.pipeline.split.compare_halves``) and what the checks
take from it: only coordinates both halves determine are compared or enlarge the sigmas."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from licalib_cli.pipeline.checks import SPLIT_HALF_P, _split, _split_section
from licalib_cli.pipeline.inflation import inflate
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


def test_the_sigmas_take_half_the_difference_beyond_its_spread() -> None:
    """Each compared sigma is lifted to half the difference's excess over its spread,
    ``0.5 sqrt(max(d^2 - sigma_d^2, 0))``, whether the halves disagree as a whole or not (a
    coordinate 2.5 of its combined sigma apart in halves that agree is lifted too); a
    difference within its spread lifts nothing."""
    c1 = c2 = np.diag(SIGMA**2)
    spread = np.sqrt(2.0) * SIGMA  # the difference's sigma: both halves' added
    raw = 0.1 * SIGMA  # tiny solver sigmas: only the halves could lift them
    within = 0.5 * spread
    within[0] = 2.5 * spread[0]
    res = compare_halves(within, SIGMA, SIGMA, c1, c2, 5.0)
    np.testing.assert_allclose(res.sigma, spread, rtol=1e-12)
    assert res.p_value > SPLIT_HALF_P  # the halves agree as a whole
    sigma, why = inflate(raw, (), [], res, SimpleNamespace(jitter=False))
    lifted = 0.5 * np.sqrt(2.5**2 - 1.0) * spread[0]
    np.testing.assert_allclose(sigma[0], lifted, rtol=1e-12)
    np.testing.assert_array_equal(sigma[1:], raw[1:])  # within their spread: as they were
    assert sigma[0] > raw[0] and len(why) == 1
    beyond = within.copy()
    beyond[1] = 8.0 * spread[1]  # t_y changed between the halves
    res = compare_halves(beyond, SIGMA, SIGMA, c1, c2, 5.0)
    assert res.p_value < SPLIT_HALF_P
    sigma, why = inflate(raw, (), [], res, SimpleNamespace(jitter=False))
    expected = np.maximum(raw, 0.5 * np.sqrt(np.maximum(beyond**2 - spread**2, 0.0)))
    np.testing.assert_allclose(sigma, expected, rtol=1e-12)
    assert sigma[1] > 10 * raw[1] and sigma[2] == raw[2]  # t_z within its spread: as it was
    assert why == (
        "to at least half the difference between the two halves of the segment beyond its "
        "expected spread",
    )


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


def _response(
    names: tuple[str, ...], rng: np.random.Generator
) -> tuple[tuple[str, ...], np.ndarray]:
    return names, rng.normal(size=(7, len(names))) * 1e-3


def test_what_the_halves_hold_adds_only_where_they_follow_it_differently() -> None:
    """The halves hold the intrinsics at the whole segment's estimate: an error of them moves
    both halves, and only the part they follow differently shows in their difference."""
    from types import SimpleNamespace as NS

    from licalib_cli.pipeline.split import common_covariance

    rng = np.random.default_rng(4)
    names = ("imu.gyro_scale.x", "imu.gyro_scale.y", "lidar.intrinsics[3].V")
    a = rng.normal(size=(4, 4))
    cov_full = a @ a.T * 1e-6
    report = NS(calibration_names=("ext.translation.x", *names), covariance=cov_full)
    first = _response(names, rng)
    # followed the same way by both halves: cancels
    np.testing.assert_allclose(common_covariance((first, first), report), 0.0, atol=1e-18)
    second = _response(names, rng)
    d = second[1] - first[1]
    expected = d @ cov_full[1:, 1:] @ d.T
    np.testing.assert_allclose(common_covariance((first, second), report), expected, rtol=1e-12)
    # a beam one half holds no point of is in neither its response nor its difference's share
    partial = (names[:2], second[1][:, :2])
    d = np.concatenate([partial[1] - first[1][:, :2], -first[1][:, 2:]], axis=1)
    np.testing.assert_allclose(
        common_covariance((first, partial), report), d @ cov_full[1:, 1:] @ d.T, rtol=1e-12
    )
    # no report (intrinsics taken as exact) or no intrinsics: nothing added
    assert not np.any(common_covariance((first, second), None))
    empty = ((), np.zeros((7, 0)))
    assert not np.any(common_covariance((empty, empty), report))


def test_the_common_covariance_enters_sigma_and_chi_square() -> None:
    rng = np.random.default_rng(5)
    c1, c2 = _cov(SIGMA, rng), _cov(SIGMA, rng)
    common = _cov(3 * SIGMA, rng)
    diff = 2.0 * SIGMA
    res = compare_halves(diff, SIGMA, SIGMA, c1, c2, 5.0, common=common)
    np.testing.assert_allclose(res.sigma, np.sqrt(2 * SIGMA**2 + np.diag(common)))
    np.testing.assert_allclose(res.chi2, float(diff @ np.linalg.solve(c1 + c2 + common, diff)))
    assert res.chi2 < compare_halves(diff, SIGMA, SIGMA, c1, c2, 5.0).chi2
