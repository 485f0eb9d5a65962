"""The chi-square and F tail probabilities against scipy.stats, and the far tail's ranking."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from scipy import stats

from licalib_cli.consistency.distributions import chi2_isf, chi2_logsf, chi2_sf, f_sf, ncx2_sf


@pytest.mark.parametrize("dof", [0.5, 1, 3, 7, 16, 64, 200])
def test_chi2_matches_scipy_stats(dof: float) -> None:
    x = np.array([0.0, 1e-3, 0.5, 1.0, dof, 3.0 * dof + 10.0, 400.0, 1200.0])
    np.testing.assert_allclose(chi2_sf(x, dof), stats.chi2.sf(x, dof), rtol=1e-12, atol=0.0)
    for xi in x:
        assert chi2_logsf(float(xi), dof) == pytest.approx(stats.chi2.logsf(xi, dof), rel=1e-12)
    for p in (0.5, 1e-3, 1e-5, 1e-12):
        assert chi2_isf(p, dof) == pytest.approx(stats.chi2.isf(p, dof), rel=1e-10)


def test_chi2_sf_of_a_negative_statistic_is_one() -> None:
    assert chi2_sf(-1.0, 3) == 1.0


def test_chi2_logsf_is_finite_and_ordered_where_the_probability_underflows() -> None:
    """scipy.stats gives -inf there, which would tie every huge statistic."""
    xs = [2000.0, 5000.0, 1e5]
    for dof in (1, 3, 16, 64):
        logs = [chi2_logsf(x, dof) for x in xs]
        assert all(np.isfinite(logs))
        assert logs[0] > logs[1] > logs[2]
    # continuous across the switch to the asymptotic series (p about 1e-300 near x = 1389, k = 3)
    left, right = chi2_logsf(1388.0, 3), chi2_logsf(1390.0, 3)
    assert chi2_sf(1388.0, 3) > 1e-300 > chi2_sf(1390.0, 3)
    assert left - right == pytest.approx(1.0, rel=1e-2)  # d/dx log sf -> -1/2 far in the tail
    # at fixed statistic, more degrees of freedom is less surprising
    assert chi2_logsf(5000.0, 64) > chi2_logsf(5000.0, 3)


@pytest.mark.parametrize(("dfn", "dfd"), [(1, 10), (3, 100), (15, 4000), (63, 250000)])
def test_f_matches_scipy_stats(dfn: int, dfd: int) -> None:
    for f in (0.0, 0.3, 1.0, 2.5, 9.0, 60.0):
        assert f_sf(f, dfn, dfd) == pytest.approx(stats.f.sf(f, dfn, dfd), rel=1e-10, abs=1e-300)


@pytest.mark.parametrize(("dof", "nc"), [(1, 0.5), (3, 10.0), (3, 40.0), (64, 50.0)])
def test_ncx2_matches_scipy_stats(dof: int, nc: float) -> None:
    for x in (1.0, 25.9, 100.0):
        assert ncx2_sf(x, dof, nc) == pytest.approx(stats.ncx2.sf(x, dof, nc), abs=1e-12)


def test_the_calibration_path_does_not_import_scipy_stats() -> None:
    """scipy.stats costs about 0.7 s to import; the CLI and pipeline must not need it."""
    code = "import sys, licalib_cli.cli, licalib_cli.pipeline; print('scipy.stats' in sys.modules)"
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True
    ).stdout
    assert out.strip() == "False"
