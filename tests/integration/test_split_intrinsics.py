"""End to end: the split-half check of a calibration that estimates the IMU intrinsics.

The halves hold the intrinsics at the whole segment's estimate, so they determine the extrinsic
rotation (with the gyro-to-IMU rotation free, a half estimating it too would leave the rotation
to the accelerometer), and the difference's covariance carries the intrinsics' uncertainty
through each half's response to them, checked here against re-solving a half with a held
intrinsic moved.
"""

from __future__ import annotations

import numpy as np
import pytest
from light_config import LIGHT_VLP16

from licalib_cli.config import INTRINSIC_PRESETS, load_config
from licalib_cli.estimation import state_from_problem
from licalib_cli.pipeline import calibrate
from licalib_cli.pipeline.round import extrinsic_of
from licalib_cli.pipeline.settings import lm_params
from licalib_cli.pipeline.split import COORDINATES, half_problem, intrinsic_response
from licalib_cli.simulation import SimulationSpec, simulate
from licalib_cli.solver.lm import solve

CONFIG = LIGHT_VLP16  # configs/vlp16.yaml with a lighter final round
IMU_BLOCKS = list(INTRINSIC_PRESETS["imu"][0])

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory):  # type: ignore[no-untyped-def]
    spec = SimulationSpec(
        scenario="shake",
        lidar="vlp16",
        duration_s=6.0,
        seed=33,
        time_offset_s=0.004,
        intrinsics="none",  # a clean bag: nothing for calibrate to add beyond the model
        azimuth_resolution_deg=0.4,
    )
    sim = simulate(spec, tmp_path_factory.mktemp("split") / "sim")
    cfg = load_config(CONFIG, {"model.imu": IMU_BLOCKS})
    return calibrate(sim.bag_path, cfg), cfg


def test_the_halves_compare_the_rotation_with_the_imu_intrinsics_estimated(run) -> None:  # type: ignore[no-untyped-def]
    result, _ = run
    split = result.checks.split
    assert split is not None and split.ran, split
    assert {"rotation.x", "rotation.y", "rotation.z", "time_offset"} <= set(split.compared)
    assert split.p_value > 1e-3  # a clean bag: the halves agree
    assert result.result.consistency.split_half.compared == split.compared


def test_a_half_follows_a_held_intrinsic_as_its_response_says(run) -> None:  # type: ignore[no-untyped-def]
    result, cfg = run
    fit = result.fit
    t = np.asarray(fit.inputs.imu.t_s)
    lo, hi = float(t[0]), 0.5 * (float(t[0]) + float(t[-1]))
    params = lm_params(cfg, max_iterations=30)

    def half_estimate(state):  # type: ignore[no-untyped-def]
        built = half_problem(state, fit.inputs, lo, hi, cfg)
        assert not isinstance(built, str), built
        sub, problem = built
        solve(problem, params)
        return state_from_problem(sub, problem)

    base = half_estimate(fit.state)
    built = half_problem(base, fit.inputs, lo, hi, cfg, free=fit.inputs.free)
    assert not isinstance(built, str), built
    names, response = intrinsic_response(built[1])
    col = names.index("imu.gyro_scale.x")
    step = 2e-3
    imu = base.imu_intrinsics
    moved_imu = imu.with_(gyro_scale=np.asarray(imu.gyro_scale) + np.array([step, 0.0, 0.0]))
    moved = half_estimate(fit.state.with_(imu_intrinsics=moved_imu))
    change = extrinsic_of(base).moved_to(extrinsic_of(moved))
    predicted = response[:, col] * step
    assert np.linalg.norm(predicted[3:6]) > 1e-6, "the rotation follows the gyro scale"
    # linear response: the re-solved half moves as predicted (each coordinate, in its scale)
    scale = np.array([1e-3, 1e-3, 1e-3, 1e-5, 1e-5, 1e-5, 1e-6])
    np.testing.assert_allclose(
        change / scale, predicted / scale, atol=0.2 * np.max(np.abs(predicted / scale))
    )
    assert len(COORDINATES) == response.shape[0]
