"""The simulated rig stays in the room's free space: a long lever arm pointing down put the LiDAR
under the floor for most of a shake, scanning the room from outside, and a LiDAR on a long lever
arm of a walking rig passed through the room's boxes
(``simulation.ground_truth.in_free_space``)."""

from __future__ import annotations

import numpy as np
import pytest

from licalib_cli.errors import ConfigError
from licalib_cli.simulation import SimulationSpec, ground_truth
from licalib_cli.simulation.ground_truth import ROOM_MARGIN_M, build_setup
from licalib_cli.simulation.world import World, default_world


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
    # the least lift that keeps it off the floor and off the low boxes on it
    assert ROOM_MARGIN_M - 1e-3 <= p_wl[:, 2].min() <= ROOM_MARGIN_M + 0.41
    assert default_world().clearance(p_wl).min() >= ROOM_MARGIN_M - 0.01
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


def test_a_lidar_walking_through_the_boxes_is_moved_clear_with_the_same_motion(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A HDL-32 mounted sideways 1.8 m from the IMU of a walking rig: at its place the LiDAR
    went into the room's boxes for a tenth of the walk; moved by the shortest clear move on the
    search grid it keeps the margin from every surface, sampled at 200 Hz (the search samples
    at 100 Hz)."""
    spec = _spec(
        (-0.74, -1.56, -0.57),
        scenario="walk",
        lidar="hdl-32",
        duration_s=10.0,
        seed=8504,
        rpy_deg=(-125.1, -88.1, 103.8),
    )
    _, p_wi, p_wl, _ = _paths(spec)
    world = default_world()
    assert world.clearance(p_wl).min() >= ROOM_MARGIN_M - 0.01
    assert world.clearance(p_wi).min() >= ROOM_MARGIN_M - 0.01
    with monkeypatch.context() as m:
        m.setattr(ground_truth, "_clear_of_objects", lambda points, w, start, lo, hi: start)
        _, p_before, p_wl_before, _ = _paths(spec)
    assert world.clearance(p_wl_before).min() < 0.0  # inside a box
    move = p_wi - p_before
    np.testing.assert_allclose(move, np.broadcast_to(move[0], move.shape), atol=1e-12)
    assert 0.05 < np.linalg.norm(move[0]) <= ground_truth.FREE_SPACE_SEARCH_M + 1e-9


def _one_box(half: float) -> World:
    return World(
        room_min=np.array([-10.0, -10.0, -10.0]),
        room_max=np.array([10.0, 10.0, 10.0]),
        box_center=np.zeros((1, 3)),
        box_rotation=np.eye(3)[None],
        box_half=np.full((1, 3), half),
        quad_vertices=np.zeros((0, 4, 3)),
    )


def test_the_shortest_clear_move_is_taken_and_none_when_the_search_cannot_clear() -> None:
    """Points 0.1 m inside a box face need 0.3 m to keep the margin: the shortest grid move
    does it, straight out through that face. Points spread through a box wider than the search
    cannot be cleared."""
    clear = ground_truth._clear_of_objects
    lo, hi = np.full(3, -5.0), np.full(3, 5.0)
    points = np.array([[0.4, 0.0, 0.0], [0.4, 0.2, 0.1], [0.45, -0.1, 0.0]])
    box = _one_box(0.5)
    move = clear(points, box, np.zeros(3), lo, hi)
    assert move is not None
    np.testing.assert_allclose(move, [0.3, 0.0, 0.0], atol=1e-9)
    assert box.clearance(points + move, room=False).min() >= ROOM_MARGIN_M
    # already clear: not moved; the walls' move is kept when it clears the objects too
    np.testing.assert_array_equal(clear(points + 3.0, box, np.zeros(3), lo, hi), 0.0)
    np.testing.assert_array_equal(clear(points, box, np.full(3, 2.0), lo, hi), 2.0)
    spread = np.linspace(-2.0, 2.0, 9)[:, None] * np.ones(3)
    assert clear(spread, _one_box(2.5), np.zeros(3), lo, hi) is None
    # the moves stay within the walls' bounds: the shortest way out blocked, the next is taken
    move = clear(points, box, np.zeros(3), lo, np.array([0.0, 5.0, 5.0]))
    assert move is not None and move[0] <= 0.0
    assert 0.3 < np.linalg.norm(move) <= 0.8 + 1e-9
    assert box.clearance(points + move, room=False).min() >= ROOM_MARGIN_M


def test_a_rig_no_move_can_clear_of_the_objects_is_refused_in_one_sentence() -> None:
    """A room filled by one box but for its margins: no move within the search keeps the rig
    out of it, and the simulator says so, naming the lever arm and the fix."""
    spec = _spec((0.5, 0.0, 0.0), duration_s=2.0)
    setup = build_setup(spec)
    room = default_world()
    filled = World(
        room_min=room.room_min,
        room_max=room.room_max,
        box_center=(0.5 * (room.room_min + room.room_max))[None],
        box_rotation=np.eye(3)[None],
        box_half=(0.5 * (room.room_max - room.room_min) - 0.3)[None],
        quad_vertices=np.zeros((0, 4, 3)),
    )
    with pytest.raises(
        ConfigError,
        match=r"^The rig's motion with the lever arm \[0\.5, 0\.0, "
        r"0\.0\] m passes through the simulated room's objects wherever it is "
        r"moved within 1 m; use a shorter lever arm \(--translation\) or another "
        r"seed\.$",
    ):
        ground_truth.in_free_space(setup.motion, setup.extrinsic, filled, spec.duration_s)
    # the same motion in the real room is already clear: returned as it is
    assert ground_truth.in_free_space(setup.motion, setup.extrinsic, room, 2.0) is setup.motion
