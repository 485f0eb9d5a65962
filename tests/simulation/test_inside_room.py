"""The simulated rig stays inside the room: a long lever arm pointing down put the LiDAR under
the floor for most of a shake, scanning the room from outside (``simulation.ground_truth.
inside_room``)."""

from __future__ import annotations

import numpy as np
import pytest

from licalib_cli.errors import ConfigError
from licalib_cli.simulation import SimulationSpec
from licalib_cli.simulation.ground_truth import ROOM_MARGIN_M, build_setup


def _spec(translation: tuple[float, float, float], **kw: object) -> SimulationSpec:
    base: dict[str, object] = {
        "scenario": "shake",
        "lidar": "os1-64",
        "duration_s": 30.0,
        "seed": 9642,
        "rpy_deg": (146.5, 19.4, -44.3),
        "translation": translation,
        "intrinsics": "none",
    }
    base.update(kw)
    return SimulationSpec(**base)  # type: ignore[arg-type]


def _paths(spec: SimulationSpec) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    setup = build_setup(spec)
    t = np.linspace(0.0, spec.duration_s, 3001)
    r_wi, p_wi = setup.trajectory.pose_at(t)
    _, p_wl = setup.lidar_pose_at(t)
    return r_wi, p_wi, p_wl, np.stack([setup.world.room_min, setup.world.room_max])


def test_a_lidar_below_the_floor_is_lifted_into_the_room_with_the_same_motion() -> None:
    down = (-0.793, 0.324, -1.54)  # the benchmark's seed 9642: under the floor 59 % of the time
    r_wi, p_wi, p_wl, room = _paths(_spec(down))
    for p in (p_wi, p_wl):
        assert np.all(p >= room[0] + ROOM_MARGIN_M - 1e-3)  # sampled at 200 Hz
        assert np.all(p <= room[1] - ROOM_MARGIN_M + 1e-3)
    assert p_wl[:, 2].min() == pytest.approx(ROOM_MARGIN_M, abs=0.01)  # the least lift
    # the same motion, only elsewhere: rotations equal, positions one constant apart
    r0, p0, _, _ = _paths(_spec((0.0, 0.0, 0.0)))
    np.testing.assert_array_equal(r_wi, r0)
    move = p_wi - p0
    np.testing.assert_allclose(move, np.broadcast_to(move[0], move.shape), atol=1e-12)
    assert move[0, 2] > 0.4 and abs(move[0, 0]) < 1e-12


def test_a_rig_inside_the_room_is_left_where_it_is() -> None:
    spec = _spec((0.01, 0.01, 0.0), seed=9646)
    _, p_wi, _, _ = _paths(spec)
    assert 1.4 < p_wi[:, 2].min() < 1.5  # the shake's own height, untouched


def test_a_lever_arm_longer_than_the_room_is_refused_in_one_sentence() -> None:
    with pytest.raises(ConfigError, match="does not fit in the simulated room"):
        build_setup(_spec((0.0, 0.0, 12.0)))
