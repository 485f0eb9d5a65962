"""The four motion scenarios as closed-form IMU trajectories (see ``trajectories.py``).

* ``sinusoid``: the paper's eq. (simu_traj1), fully excited, centred at (5, 5, 5).
* ``figure8``: the paper's eq. (simu_traj2), planar, at z = 2; the rig is mounted on the robot
  with a fixed rotation ``R_B_I`` such that the robot's vertical expressed in the IMU frame is
  ``[0, 0, 1]`` (case A), ``[0.5, 0, 0.866]`` (B) or ``[0.5, 0.433, 0.75]`` (C); the IMU sits at the
  robot's origin. ``R_B_I`` is the smallest rotation doing so.
* ``shake``: hand-held shaking around (2.5, 5, 1.5): per coordinate a sum of four sinusoids with
  random frequencies in 0.2-2 Hz and random phases, amplitudes bounded in value and in
  acceleration/angular rate. ``tilt_deg`` adds a slow tilt about each horizontal axis (one
  sinusoid per axis at 0.1-0.2 Hz, random phase), so the accelerometer sees gravity from attitudes
  tens of degrees apart (the shake alone turns it by 7-13 deg RMS).
* ``walk``: calm walking on an ellipse around (2.5, 5) at 1.4 m (one lap in 40 s, heading along
  the path, gait bob and sway) with short shaking bursts (3-6 s, every 15-30 s) whose intervals
  are returned so they can be written to ``truth.yaml``.
* ``translation``: the sinusoid's translation at a constant orientation, a degenerate recording
  with no rotation at all (the rotation extrinsic and the lever arm are not observable from it).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from licalib_cli.simulation.spec import Mounting, Scenario, SimulationSpec
from licalib_cli.simulation.trajectories import EulerTrajectory, Signal

F64 = npt.NDArray[np.float64]

MOUNTING_VERTICAL = {
    Mounting.A: np.array([0.0, 0.0, 1.0]),
    Mounting.B: np.array([0.5, 0.0, 0.866]),
    Mounting.C: np.array([0.5, 0.433, 0.75]),
}

SHAKE_CENTER = (2.5, 5.0, 1.5)
TILT_FREQUENCY_HZ = (0.1, 0.2)
WALK_CENTER = (2.5, 5.0, 1.4)
WALK_RADII = (4.0, 3.0)
WALK_LAP_S = 40.0
BURST_FIRST_S = (5.0, 10.0)
"""The walk's first shaking burst starts this far in (uniform), s."""
BURST_LENGTH_S = (3.0, 6.0)
"""Each burst lasts this long (uniform), s."""
BURST_GAP_S = (15.0, 30.0)
"""Calm walking between two bursts (uniform), s."""
BURST_END_MARGIN_S = 1.0
"""A burst ends at least this long before the recording does, s."""
WALK_SURE_OF_A_BURST_S = BURST_FIRST_S[1] + BURST_LENGTH_S[1] + BURST_END_MARGIN_S
"""A walk at least this long holds a shaking burst whatever its draws (17 s); a shorter one
may be calm walking only."""


@dataclass(frozen=True)
class ScenarioMotion:
    """A scenario's trajectory and its annotations.

    Attributes:
        trajectory: the IMU trajectory.
        bursts_s: (M, 2) shaking intervals ``[t0, t1]`` in true seconds (walk only, else empty).
        vertical_in_imu: (3,) the robot's vertical in the IMU frame (figure-8) or None.
    """

    trajectory: EulerTrajectory
    bursts_s: F64
    vertical_in_imu: F64 | None = None


def mount_rotation(vertical_in_imu: npt.ArrayLike) -> F64:
    """Smallest ``R_B_I`` with ``R_B_I^T e_z = v`` (``v``: the body vertical in the IMU frame)."""
    v = np.asarray(vertical_in_imu, dtype=np.float64)
    v = v / np.linalg.norm(v)
    ez = np.array([0.0, 0.0, 1.0])
    axis = np.cross(ez, v)
    s = np.linalg.norm(axis)
    if s < 1e-12:
        return np.eye(3) if v[2] > 0 else np.diag([1.0, -1.0, -1.0])
    k = axis / s
    angle = np.arctan2(s, float(ez @ v))
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    r_i_b = np.eye(3) + np.sin(angle) * kx + (1 - np.cos(angle)) * kx @ kx
    return r_i_b.T


def _sinusoid_position() -> tuple[Signal, Signal, Signal]:
    """The translation of eq. simu_traj1, centred at (5, 5, 5)."""
    w = np.pi / 5.0
    return (
        Signal.sines(2.0, w, np.pi / 2, offset=5.0),
        Signal.sines(1.5, w, 0.0, offset=5.0),
        Signal.sines(0.8, 4 * w, np.pi / 2, offset=5.0),
    )


def sinusoid() -> EulerTrajectory:
    """The paper's sinusoidal trajectory (eq. simu_traj1)."""
    return EulerTrajectory(
        position=_sinusoid_position(),
        euler=(
            Signal.sines(0.4, 1.0, np.pi / 2),
            Signal.sines(0.6, 1.0, 0.0),
            Signal(slope=0.7),
        ),
    )


def translation() -> EulerTrajectory:
    """The sinusoid's translation without any rotation (constant roll, pitch and yaw)."""
    return EulerTrajectory(
        position=_sinusoid_position(),
        euler=(Signal(offset=0.05), Signal(offset=-0.1), Signal(offset=0.6)),
    )


def figure8(mounting: Mounting = Mounting.A) -> EulerTrajectory:
    """The paper's figure-8 trajectory (eq. simu_traj2) with a mounting case."""
    w = np.pi / 5.0
    return EulerTrajectory(
        position=(
            Signal.sines(2.0, w, np.pi / 2),
            Signal.sines(0.75, 2 * w, 0.0, offset=5.0),  # 1.5 sin(wt) cos(wt)
            Signal(offset=2.0),
        ),
        euler=(Signal(), Signal(), Signal.sines(0.4, 1.0, 0.0)),
        mount=mount_rotation(MOUNTING_VERTICAL[Mounting(mounting)]),
    )


def _random_sines(
    rng: np.random.Generator,
    n: int,
    f_range: tuple[float, float],
    max_value: float,
    max_deriv: float,
    deriv_order: int,
    window: tuple[float, float] | None = None,
    offset: float = 0.0,
) -> Signal:
    """Sum of ``n`` sinusoids with ``sum |a| <= max_value`` and ``sum |a| w^order <= max_deriv``."""
    f = rng.uniform(*f_range, size=n)
    phase = rng.uniform(0.0, 2 * np.pi, size=n)
    u = rng.uniform(0.5, 1.0, size=n)
    omega = 2 * np.pi * f
    scale = min(max_value / u.sum(), max_deriv / float(np.sum(u * omega**deriv_order)))
    return Signal.sines(u * scale, omega, phase, offset=offset, window=window)


def shake(rng: np.random.Generator, tilt_rad: float = 0.0) -> EulerTrajectory:
    """Random hand-held shaking (smooth, seed-driven), with a slow tilt of ``tilt_rad`` about
    each horizontal axis when positive (drawn after the shaking, which it leaves unchanged)."""
    fr = (0.2, 2.0)
    pos = tuple(_random_sines(rng, 4, fr, 0.35, 5.0, 2, offset=c) for c in SHAKE_CENTER)
    yaw0 = float(rng.uniform(-np.pi, np.pi))
    rx = _random_sines(rng, 4, fr, 0.5, 2.5, 1)
    ry = _random_sines(rng, 4, fr, 0.5, 2.5, 1)
    rz = _random_sines(rng, 4, fr, 0.9, 2.5, 1, offset=yaw0)
    if tilt_rad > 0.0:
        omega = 2 * np.pi * rng.uniform(*TILT_FREQUENCY_HZ, size=2)
        phase = rng.uniform(0.0, 2 * np.pi, size=2)
        rx = rx + Signal.sines([tilt_rad], omega[0], phase[0])
        ry = ry + Signal.sines([tilt_rad], omega[1], phase[1])
    return EulerTrajectory(position=pos, euler=(rx, ry, rz))  # type: ignore[arg-type]


def burst_intervals(rng: np.random.Generator, duration_s: float) -> F64:
    """Shaking intervals of the walk: 3-6 s long, 15-30 s apart, first at 5-10 s, (M, 2)."""
    out = []
    t = float(rng.uniform(*BURST_FIRST_S))
    while True:
        length = float(rng.uniform(*BURST_LENGTH_S))
        if t + length > duration_s - BURST_END_MARGIN_S:
            break
        out.append((round(t, 3), round(t + length, 3)))
        t += length + float(rng.uniform(*BURST_GAP_S))
    return np.array(out, dtype=np.float64).reshape(-1, 2)


def walk(rng: np.random.Generator, duration_s: float) -> tuple[EulerTrajectory, F64]:
    """Calm walking on an ellipse with shaking bursts; returns the trajectory and the bursts."""
    w = 2 * np.pi / WALK_LAP_S
    phi0 = float(rng.uniform(0.0, 2 * np.pi))
    cx, cy, cz = WALK_CENTER
    ax, ay = WALK_RADII
    step_w = 2 * np.pi * 1.8  # steps per second
    sway_w = 2 * np.pi * 0.9  # one sway per two steps
    px = Signal.sines(ax, w, phi0 + np.pi / 2, offset=cx)
    py = Signal.sines(ay, w, phi0, offset=cy)
    pz = Signal.sines([0.03], step_w, 0.0, offset=cz)
    rx = Signal.sines([0.03], sway_w, 0.3)
    ry = Signal.sines([0.02], step_w, 1.1, offset=0.05)
    rz = Signal(offset=phi0 + np.pi / 2, slope=w) + Signal.sines([0.05], sway_w, 0.0)
    bursts = burst_intervals(rng, duration_s)
    channels = [px, py, pz, rx, ry, rz]
    fr = (0.5, 2.0)
    for t0, t1 in bursts:
        win = (t0, t1)
        extra = [
            _random_sines(rng, 3, fr, 0.25, 6.0, 2, window=win),
            _random_sines(rng, 3, fr, 0.25, 6.0, 2, window=win),
            _random_sines(rng, 3, fr, 0.2, 6.0, 2, window=win),
            _random_sines(rng, 3, fr, 0.4, 3.0, 1, window=win),
            _random_sines(rng, 3, fr, 0.4, 3.0, 1, window=win),
            _random_sines(rng, 3, fr, 0.6, 3.0, 1, window=win),
        ]
        channels = [c + e for c, e in zip(channels, extra, strict=True)]
    traj = EulerTrajectory(position=tuple(channels[:3]), euler=tuple(channels[3:]))  # type: ignore[arg-type]
    return traj, bursts


def make_motion(spec: SimulationSpec, rng: np.random.Generator) -> ScenarioMotion:
    """The trajectory of ``spec.scenario`` (random draws from ``rng`` for shake/walk)."""
    none = np.zeros((0, 2))
    if spec.scenario is Scenario.SINUSOID:
        return ScenarioMotion(sinusoid(), none)
    if spec.scenario is Scenario.FIGURE8:
        v = MOUNTING_VERTICAL[spec.mounting]
        return ScenarioMotion(figure8(spec.mounting), none, v / np.linalg.norm(v))
    if spec.scenario is Scenario.SHAKE:
        return ScenarioMotion(shake(rng, float(np.radians(spec.tilt_deg))), none)
    if spec.scenario is Scenario.TRANSLATION:
        return ScenarioMotion(translation(), none)
    traj, bursts = walk(rng, spec.resolved_duration_s)
    return ScenarioMotion(traj, bursts)
