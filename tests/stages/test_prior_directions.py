"""A measured lever arm as a prior: what rests on it is named, and what the data determine is
counted without it."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import pytest

from licalib_cli.config import load_config
from licalib_cli.errors import ConfigError
from licalib_cli.estimation import (
    CALIBRATION_SCALES,
    PRIOR_SCALE_FACTOR,
    CalibrationState,
    FreeParameters,
)
from licalib_cli.pipeline.checks import _prior_conflict
from licalib_cli.pipeline.prior_directions import (
    added_variance,
    data_determined,
    data_translation_std,
    on_prior,
    prior_conflict,
)
from licalib_cli.pipeline.schedule import _translation_std
from licalib_cli.pipeline.settings import free_parameters, model_priors, prior_sd
from licalib_cli.residuals import EXT_TRANSLATION, GaussianPrior
from licalib_cli.solver.lm import LMParams, SolverReport, solve
from licalib_cli.solver.parameters import ParameterBlock
from licalib_cli.solver.problem import DenseJacobian, Problem, ResidualEval

NAMES = [f"{EXT_TRANSLATION}.{a}" for a in "xyz"]


def _fit(
    seen: np.ndarray, prior_sigma: np.ndarray | None, prior_mean: np.ndarray
) -> tuple[SolverReport, np.ndarray]:
    """The translation seen by a measurement of 1 mm along the rows of ``seen`` only (what a
    planar motion shows), with or without a prior; returns the report and the estimate."""
    problem = Problem()
    scale = CALIBRATION_SCALES[EXT_TRANSLATION][0]
    if prior_sigma is not None:
        scale = np.maximum(scale, PRIOR_SCALE_FACTOR * prior_sigma)
    problem.add_parameter_block(
        ParameterBlock(
            EXT_TRANSLATION,
            np.array([0.1, 0.2, 0.3]),
            group="calibration",
            coord_names=NAMES,
            scale=scale,
        )
    )
    # the data: 1 mm along each row of ``seen``, nothing across them
    basis = np.linalg.qr(np.asarray(seen, dtype=np.float64).T, mode="complete")[0]
    truth = np.array([0.11, 0.19, 0.25])
    for k in range(seen.shape[0]):
        u = basis[:, k]
        problem.add_residual_block(_Along(u, float(u @ truth), 0.001, name=f"data{k}"))
    if prior_sigma is not None:
        problem.add_residual_block(GaussianPrior(EXT_TRANSLATION, prior_mean, prior_sigma))
    report = solve(problem, LMParams())
    return report, problem[EXT_TRANSLATION].value


class _Along:
    """A measurement of the translation along unit vector ``u`` with standard deviation
    ``sigma``."""

    def __init__(self, u: np.ndarray, value: float, sigma: float, name: str) -> None:
        self.u, self.value, self.sigma, self.name = u, value, sigma, name

    def evaluate(self, params: Mapping[str, np.ndarray], jacobians: bool = True) -> ResidualEval:
        t = np.asarray(params[EXT_TRANSLATION], dtype=np.float64)
        r = np.array([[(self.u @ t - self.value) / self.sigma]])
        if not jacobians:
            return ResidualEval(r, ())
        values = (self.u / self.sigma)[None, None, None, :]
        jac = DenseJacobian(EXT_TRANSLATION, np.zeros((1, 1), dtype=np.intp), values)
        return ResidualEval(r, (jac,))


def test_without_a_prior_the_unseen_direction_is_unobservable_and_nothing_rests_on_a_prior():
    seen = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    report, _ = _fit(seen, None, np.zeros(3))
    assert np.isinf(report.std_of(f"{EXT_TRANSLATION}.z"))
    assert on_prior(report, {}) == ()
    assert data_determined(report, {}, NAMES).tolist() == [True, True, False]


def test_the_unseen_direction_takes_the_prior_with_its_sigma_and_is_named():
    seen = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    sigma = np.full(3, 0.02)
    report, estimate = _fit(seen, sigma, np.array([0.1, 0.2, 0.33]))
    sd = {n: 0.02 for n in NAMES}
    # z: the prior's mean and sigma; x and y: the data's
    assert estimate[2] == pytest.approx(0.33, abs=1e-6)
    assert report.std_of(f"{EXT_TRANSLATION}.z") == pytest.approx(0.02, rel=1e-3)
    assert report.std_of(f"{EXT_TRANSLATION}.x") == pytest.approx(0.001, rel=0.01)
    assert report.truncated == ()  # the prior's scale leaves its direction in
    (rests,) = on_prior(report, sd)
    assert np.allclose(rests.direction, [0.0, 0.0, 1.0], atol=1e-6)
    assert rests.sigma_m == pytest.approx(0.02)
    assert "not determined by the data" in rests.text
    assert "initialization.translation_sigma_m" in rests.text
    # the verdict counts what the data determine, not the prior
    assert data_determined(report, sd, NAMES).tolist() == [True, True, False]


def test_the_rounds_settle_against_what_the_data_determine_not_the_prior():
    """The schedule's settle tolerance takes half the translation's largest sigma: with a
    measured lever arm that is the data's 1 mm, not the prior's 20 mm along the vertical."""
    seen = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    plain, _ = _fit(seen, None, np.zeros(3))
    # without a prior: the largest finite sigma (z is not observable)
    assert _translation_std(plain, load_config(None)) == pytest.approx(0.001, rel=0.01)
    report, _ = _fit(seen, np.full(3, 0.02), np.array([0.1, 0.2, 0.33]))
    assert max(report.std) == pytest.approx(0.02, rel=1e-3)
    assert data_translation_std(report, {n: 0.02 for n in NAMES}) == pytest.approx(0.001, rel=0.01)
    measured = load_config(
        None,
        {
            "initialization.translation_m": [0.1, 0.2, 0.33],
            "initialization.translation_sigma_m": 0.02,
        },
    )
    assert _translation_std(report, measured) == pytest.approx(0.001, rel=0.01)


def test_a_tilted_vertical_and_sigmas_per_axis():
    """On a tilted IMU the unseen vertical mixes the axes: the prior's sigma along it combines
    the per-axis sigmas."""
    vertical = np.array([0.5, 0.0, np.sqrt(0.75)])
    seen = np.linalg.qr(np.column_stack([vertical, [0, 1, 0], [1, 0, 0]]))[0][:, 1:].T
    sigma = np.array([0.004, 0.01, 0.02])
    report, _ = _fit(seen, sigma, np.array([0.1, 0.2, 0.3]))
    sd = dict(zip(NAMES, sigma, strict=True))
    (rests,) = on_prior(report, sd)
    assert abs(float(np.dot(rests.direction, vertical))) == pytest.approx(1.0, abs=1e-6)
    expected = float(np.sqrt(np.sum(vertical**2 * sigma**2)))
    assert rests.sigma_m == pytest.approx(expected, rel=1e-6)


def test_a_prior_where_the_data_see_everything_rests_nothing_on_it():
    seen = np.eye(3)
    report, _ = _fit(seen, np.full(3, 0.01), np.zeros(3))
    sd = {n: 0.01 for n in NAMES}
    assert on_prior(report, sd) == ()
    assert data_determined(report, sd, NAMES).all()


def test_the_config_makes_the_prior_a_residual_of_every_round(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text(
        "initialization:\n  translation_m: [0.3, 0.1, 1.2]\n  translation_sigma_m: 0.02\n"
    )
    cfg = load_config(path)
    assert prior_sd(cfg) == {n: 0.02 for n in NAMES}
    for intrinsics in (False, True):
        free = free_parameters(cfg, intrinsics)
        assert free.translation_prior == ((0.3, 0.1, 1.2), (0.02, 0.02, 0.02))
    state = CalibrationState.__new__(CalibrationState)  # model_priors reads no state for it
    (prior,) = model_priors(state, free_parameters(cfg, False))
    assert isinstance(prior, GaussianPrior) and prior.block == EXT_TRANSLATION
    assert np.allclose(1.0 / prior.inv_sigma, 0.02)
    # without a prior, or with the translation held, there is none
    assert model_priors(state, FreeParameters()) == []
    held = FreeParameters(extrinsic_translation=False, translation_prior=((0, 0, 0), (1, 1, 1)))
    assert model_priors(state, held) == []


@pytest.mark.parametrize(
    ("text", "fragment"),
    [
        ("translation_sigma_m: 0.01\n", "translation_m is not set"),
        ("translation_m: [0, 0, 0]\n  translation_sigma_m: -0.01\n", "translation_sigma_m.0"),
        ("translation_m: [0, 0, 0]\n  translation_sigma_m: [0.01, 0.02]\n", "at least 3 items"),
        ("translation_m: [0, 0, 0]\n  translation_sigma_m: 1.0e-9\n", "greater than or equal"),
        ("translation_m: [0, 0, 0]\n  translation_sigma_m: .inf\n", "finite number"),
        ("translation_m: [0, 0, 0]\n  translation_sigma_m: abc\n", "takes a list of 3 items"),
    ],
)
def test_a_prior_the_run_cannot_use_is_refused_at_load_time(tmp_path, text, fragment):
    path = tmp_path / "c.yaml"
    path.write_text("initialization:\n  " + text)
    with pytest.raises(ConfigError, match=fragment) as info:
        load_config(path)
    assert "\n" not in str(info.value)


def test_a_measured_lever_arm_the_data_contradict_is_found_and_its_pull_measured():
    """A tight prior 20 mm off: the estimate ends half way, the data's own estimate is
    recovered from the balance, and the two disagree far beyond chance; a prior within its
    sigma of the data, or a loose one, agrees."""
    seen = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    wrong = np.array([0.13, 0.19, 0.3])  # the data say x = 0.11 (to 1 mm)
    report, estimate = _fit(seen, np.full(3, 0.001), wrong)
    sd = {n: 0.001 for n in NAMES}
    conflict = prior_conflict(report, sd, estimate, wrong)
    assert conflict is not None and conflict.disagrees
    assert conflict.difference_m[0] == pytest.approx(-0.02, abs=1e-6)  # data's own 0.11
    assert conflict.pull_m[0] == pytest.approx(-0.01, abs=1e-6)  # estimate 0.12
    assert conflict.dof == 2 and conflict.statistic == pytest.approx(200.0, rel=1e-4)
    (finding,) = _prior_conflict(conflict)
    assert finding.severity == "warn" and "initialization.translation_sigma_m" in finding.text
    for mean, sigma in ((np.array([0.111, 0.19, 0.3]), 0.001), (wrong, 0.02)):
        report, estimate = _fit(seen, np.full(3, sigma), mean)
        conflict = prior_conflict(report, {n: sigma for n in NAMES}, estimate, mean)
        assert conflict is not None and not conflict.disagrees
        assert _prior_conflict(conflict) == []
    plain, estimate = _fit(seen, None, np.zeros(3))
    assert prior_conflict(plain, {}, estimate, np.zeros(3)) is None


def test_the_data_estimate_is_as_uncertain_as_the_checks_found_the_result():
    """What the checks added to the translation's variances widens the data's own estimate before
    it is compared with the measurement: the 20 mm the data say to 1 mm is 2 sigma when the
    checks added 10 mm along x, and nothing is compared where they leave a sigma unbounded."""
    seen = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    wrong = np.array([0.13, 0.19, 0.3])
    report, estimate = _fit(seen, np.full(3, 0.001), wrong)
    sd = {n: 0.001 for n in NAMES}
    at_solver = prior_conflict(report, sd, estimate, wrong, np.zeros(3))
    assert at_solver is not None and at_solver.disagrees
    wider = prior_conflict(report, sd, estimate, wrong, np.array([1e-4, 0.0, 0.0]))
    assert wider is not None and not wider.disagrees
    assert wider.statistic == pytest.approx(4e-4 / (1e-6 + 1e-4 + 1e-6), rel=1e-4)
    assert wider.pull_m == at_solver.pull_m  # what the prior did does not change
    assert prior_conflict(report, sd, estimate, wrong, np.array([0.0, np.inf, 0.0])) is None
    np.testing.assert_allclose(
        added_variance([1e-3, 2e-3, np.inf, 1e-3], [2e-3, 2e-3, np.inf, np.inf]),
        [3e-6, 0.0, np.inf, np.inf],
    )
    assert added_variance([np.inf], [1e-3])[0] == 0.0
    sigma = np.array([1e-3, 2e-3, 3e-3])
    np.testing.assert_allclose(at_solver.covered(sigma), np.hypot(sigma, at_solver.pull_m))
    np.testing.assert_array_equal(wider.covered(sigma), sigma)


def test_an_estimated_clock_drift_gets_the_stamps_rate_as_its_prior() -> None:
    """The rate of the IMU's stamps against the LiDAR's (record times) measures the clock drift
    the model estimates: the rounds' settings carry it, and the problems add it as a prior on
    ``ext.time_drift``; a model that holds the drift, or a rate unknown, adds nothing."""
    from licalib_cli.io.clock_rate import ClockRate
    from licalib_cli.pipeline.settings import NoiseLevels, round_settings, with_clock_rate
    from licalib_cli.residuals import TIME_DRIFT

    gyro, accel = np.full(3, 1e-3), np.full(3, 1e-2)
    noise = NoiseLevels(
        gyro, accel, 0.01, "config", "config", "config", np.full(16, 0.01), gyro, accel, 0.01
    )
    cfg = load_config(None, {"model.imu": ["clock_drift"]})
    rate = ClockRate(rate=50e-6, sigma=2e-6, span_s=10.0)
    drifting = with_clock_rate(round_settings(cfg, noise, 0.03, True), rate)
    assert drifting.free.time_drift_prior == (50e-6, 2e-6)
    state = CalibrationState.__new__(CalibrationState)  # model_priors reads no state for it
    (prior,) = [p for p in model_priors(state, drifting.free) if p.block == TIME_DRIFT]
    assert np.allclose(prior.mean, 50e-6) and np.allclose(1.0 / prior.inv_sigma, 2e-6)
    held = round_settings(load_config(None, {}), noise, 0.03, True)
    assert with_clock_rate(held, rate) is held
    assert with_clock_rate(drifting, None).free.time_drift_prior == (50e-6, 2e-6)
    fresh = round_settings(cfg, noise, 0.03, True)
    assert with_clock_rate(fresh, None) is fresh
    assert not any(p.block == TIME_DRIFT for p in model_priors(state, fresh.free))
