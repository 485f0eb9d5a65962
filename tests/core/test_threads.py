"""The block loops on the shared thread pool give bit-for-bit the serial results."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from licalib_cli.geometry import so3
from licalib_cli.geometry.so3 import quat_exp
from licalib_cli.models.lidar import nominal_intrinsics_array
from licalib_cli.parallel import threads as thr
from licalib_cli.parallel.threads import BLOCK
from licalib_cli.residuals import (
    EXT_ROTATION,
    EXT_TRANSLATION,
    LIDAR_INTRINSICS,
    TIME_OFFSET,
    TRAJ_R3,
    TRAJ_SO3,
    PointToPlaneResidual,
)
from licalib_cli.spline import R3Spline, SO3Spline, UniformKnots

# several blocks and a partial last one
NUM_QUERIES = 3 * BLOCK + 1234


@pytest.fixture(autouse=True)
def two_threads(monkeypatch: pytest.MonkeyPatch) -> None:
    """Exercise the threaded path even when the suite runs with ``LICALIB_THREADS=1``."""
    monkeypatch.setattr(thr, "THREADS", max(thr.THREADS, 2))


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(11)


def _spline(rng: np.random.Generator, n: int = 60) -> SO3Spline:
    R = so3.exp(rng.normal(scale=0.7, size=(n, 3)))
    return SO3Spline.from_matrices(UniformKnots(-0.3, 0.05, n), R)


def _times(knots: UniformKnots, rng: np.random.Generator, m: int = NUM_QUERIES) -> np.ndarray:
    # unsorted, so that neighbouring blocks use different control points
    return rng.uniform(knots.t0_s, knots.t_end_s, m)


def _assert_same(a: np.ndarray | None, b: np.ndarray | None, what: str) -> None:
    if a is None or b is None:
        assert a is None and b is None, what
        return
    assert a.shape == b.shape, what
    assert np.array_equal(a, b), f"{what}: threaded and serial results differ"


def test_map_blocks_uses_the_pool_keeps_order_and_raises() -> None:
    barrier = threading.Barrier(2, timeout=10.0)
    idents: list[int] = []

    def fn(k: int) -> int:
        if k < 2:  # both threads must hold one of the first two blocks
            idents.append(threading.get_ident())
            barrier.wait()
        return k * k

    assert thr.map_blocks(fn, 9) == [k * k for k in range(9)]
    assert len(set(idents)) == 2
    with thr.serial():
        assert thr.threads() == 1
        assert thr.map_blocks(lambda k: threading.get_ident(), 5) == [threading.get_ident()] * 5
    assert thr.threads() >= 2
    assert thr.map_blocks(lambda k: k, 0) == []

    def bad(k: int) -> int:
        if k == 3:
            msg = "block 3"
            raise RuntimeError(msg)
        return k

    with pytest.raises(RuntimeError, match="block 3"):
        thr.map_blocks(bad, 8)


def test_filled_lets_a_reader_wait_for_entries_and_raises_when_the_producer_stops() -> None:
    filled = thr.Filled()
    seen: list[int] = []

    def reader() -> None:
        filled.wait_for(3)
        seen.append(filled.count)

    waiting = threading.Thread(target=reader)
    waiting.start()
    filled.publish(2)
    waiting.join(timeout=0.2)
    assert waiting.is_alive() and not seen  # two of three: still waiting
    filled.publish(3)
    waiting.join(timeout=10.0)
    assert seen == [3]
    filled.publish(1)  # never counts down
    assert filled.count == 3
    filled.wait_for(3)  # already there: returns at once

    errors: list[BaseException] = []

    def stranded() -> None:
        try:
            filled.wait_for(5)
        except RuntimeError as err:
            errors.append(err)

    waiting = threading.Thread(target=stranded)
    waiting.start()
    filled.fail()
    waiting.join(timeout=10.0)
    assert not waiting.is_alive()
    assert len(errors) == 1 and "after 3 of 5" in str(errors[0])


@pytest.mark.parametrize(
    ("order", "jacobians", "jacobian_order"),
    [(0, False, None), (0, True, None), (1, True, None), (1, True, 0), (2, True, None)],
)
def test_so3_evaluate_threaded_equals_serial(
    rng: np.random.Generator, order: int, jacobians: bool, jacobian_order: int | None
) -> None:
    spline = _spline(rng)
    t = _times(spline.knots, rng)
    v = rng.normal(size=(t.size, 3))
    kwargs = {"order": order, "jacobians": jacobians, "jacobian_order": jacobian_order}
    with thr.serial():
        ref = spline.evaluate(t, rotation_vjp=True, **kwargs)
        assert ref.rotation_vjp is not None
        ref_vjp = ref.rotation_vjp(v)
    got = spline.evaluate(t, rotation_vjp=True, **kwargs)
    assert got.rotation_vjp is not None
    assert len(got.rotation_vjp.blocks) == len(ref.rotation_vjp.blocks) == -(-t.size // BLOCK)
    assert [b.rows for b in got.rotation_vjp.blocks] == [b.rows for b in ref.rotation_vjp.blocks]
    for name in (
        "index",
        "rotation",
        "angular_velocity",
        "angular_acceleration",
        "jac_rotation",
        "jac_angular_velocity",
        "jac_angular_acceleration",
    ):
        _assert_same(getattr(got, name), getattr(ref, name), name)
    # the products threaded and serial, from the threaded and from the serial terms
    _assert_same(got.rotation_vjp(v), ref_vjp, "rotation_vjp")
    with thr.serial():
        _assert_same(got.rotation_vjp(v), ref_vjp, "rotation_vjp (serial products)")
    _assert_same(ref.rotation_vjp(v), ref_vjp, "rotation_vjp (threaded products)")


def test_so3_evaluate_small_and_empty_queries(rng: np.random.Generator) -> None:
    spline = _spline(rng)
    for m in (0, 1, BLOCK, BLOCK + 1):
        t = _times(spline.knots, rng, m)
        with thr.serial():
            ref = spline.evaluate(t, order=2, jacobians=True, rotation_vjp=True)
        got = spline.evaluate(t, order=2, jacobians=True, rotation_vjp=True)
        for name in ("rotation", "angular_velocity", "jac_angular_acceleration"):
            _assert_same(getattr(got, name), getattr(ref, name), f"{name}, M={m}")


def test_r3_evaluate_threaded_equals_serial(rng: np.random.Generator) -> None:
    n = 60
    spline = R3Spline(UniformKnots(-0.3, 0.05, n), rng.normal(size=(n, 3)))
    t = _times(spline.knots, rng)
    for order in (0, 1, 2, 3):
        with thr.serial():
            ref = spline.evaluate(t, order=order)
        got = spline.evaluate(t, order=order)
        for name in (
            "index",
            "position",
            "velocity",
            "acceleration",
            "jerk",
            "weights",
            "velocity_weights",
            "acceleration_weights",
        ):
            _assert_same(getattr(got, name), getattr(ref, name), f"{name}, order {order}")


@pytest.mark.parametrize("blocks", [(), (TIME_OFFSET, LIDAR_INTRINSICS)])
def test_point_to_plane_threaded_equals_serial(
    rng: np.random.Generator, blocks: tuple[str, ...]
) -> None:
    knots = UniformKnots(0.0, 0.1, 30)
    n = NUM_QUERIES
    normal = rng.standard_normal((n, 3))
    t = rng.uniform(0.05, knots.t_end_s - 0.05, n)
    t[7] = knots.t_end_s - 1e-3  # the time offset pushes it outside: an infinite residual
    res = PointToPlaneResidual(
        knots,
        t,
        rng.integers(0, 3, n),
        rng.uniform(2.0, 30.0, n),
        rng.uniform(-np.pi, np.pi, n),
        normal / np.linalg.norm(normal, axis=1, keepdims=True),
        rng.standard_normal(n) * 3.0,
        rng.uniform(0.5, 2.0, n),
        np.deg2rad([-10.0, 0.0, 10.0]),
    )
    nc = knots.num_control_points
    params = {
        TRAJ_SO3: quat_exp(np.cumsum(0.25 * rng.standard_normal((nc, 3)), axis=0)),
        TRAJ_R3: np.cumsum(0.3 * rng.standard_normal((nc, 3)), axis=0),
        EXT_ROTATION: quat_exp(rng.standard_normal(3)),
        EXT_TRANSLATION: 0.2 * rng.standard_normal(3),
        TIME_OFFSET: np.array([0.004]),
        LIDAR_INTRINSICS: nominal_intrinsics_array(3) + 1e-3 * rng.standard_normal((3, 6)),
    }
    params = {
        k: v for k, v in params.items() if k in blocks or k not in (TIME_OFFSET, LIDAR_INTRINSICS)
    }
    for jacobians in (False, True):
        with thr.serial():
            ref = res.evaluate(params, jacobians=jacobians)
        got = res.evaluate(params, jacobians=jacobians)
        _assert_same(got.residuals, ref.residuals, "residuals")
        assert np.isinf(got.residuals[7, 0]) == (TIME_OFFSET in params)
        assert [j.block for j in got.jacobians] == [j.block for j in ref.jacobians]
        for a, b in zip(got.jacobians, ref.jacobians, strict=True):
            _assert_same(np.asarray(a.elements), np.asarray(b.elements), f"{a.block} elements")
            _assert_same(a.values, b.values, f"{a.block} values")


@pytest.mark.parametrize(
    ("value", "expected", "warns"),
    [("1", 1, False), ("3", 3, False), (" 2 ", 2, False), ("0", 1, True), ("two", 1, True)],
)
def test_licalib_threads_from_the_environment(
    value: str,
    expected: int,
    warns: bool,
    monkeypatch: pytest.MonkeyPatch,
    caplog: pytest.LogCaptureFixture,
) -> None:
    """``LICALIB_THREADS``: a positive whole number is taken as is; anything else runs serially
    and says so in one sentence; unset, two threads (one on a single usable core)."""
    monkeypatch.setenv("LICALIB_THREADS", value)
    with caplog.at_level("WARNING", logger="licalib_cli.parallel.threads"):
        assert thr._threads_from_env() == expected
    assert any("LICALIB_THREADS" in r.getMessage() for r in caplog.records) is warns
    monkeypatch.delenv("LICALIB_THREADS")
    assert thr._threads_from_env() == min(2, thr.usable_cores())
