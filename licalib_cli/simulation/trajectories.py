"""Closed-form trajectories of the IMU frame in the world frame.

Conventions:

* World frame ``{W}``: z up, gravity ``g_W = [0, 0, -9.81]`` m/s^2.
* Time ``t`` is float seconds relative to the bag's base time (true time, IMU clock).
* Each coordinate (position x, y, z and Euler angles rx, ry, rz) is a :class:`Signal`: an offset, a
  linear term and a sum of sinusoids, each optionally multiplied by a ``sin^4`` window, so value,
  first and second derivative are exact at any time.
* ``R_W_I(t) = Rz(rz) Ry(ry) Rx(rx) @ mount`` (``mount`` = ``R_B_I``, a fixed rotation of the IMU in
  the body frame whose Euler angles are given; identity unless a mounting case is simulated).
* Angular velocity ``omega_I = R_W_I^T dR_W_I/dt`` (body frame, rad/s); specific force
  ``a_I = R_W_I^T (p_ddot - g_W)`` (m/s^2).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

F64 = npt.NDArray[np.float64]

GRAVITY_W = np.array([0.0, 0.0, -9.81])


def _empty() -> F64:
    return np.zeros(0)


@dataclass(frozen=True)
class Signal:
    """A smooth scalar function of time with exact derivatives.

    ``f(t) = offset + slope t + sum_k w_k(t) amp_k sin(omega_k t + phase_k)`` where ``w_k`` is 1, or
    ``sin^4(pi (t - t0_k) / (t1_k - t0_k))`` inside ``[t0_k, t1_k]`` and 0 outside (a window that is
    continuous up to the second derivative, so accelerations stay continuous).

    Attributes:
        offset: constant term.
        slope: linear term, per second.
        amp: (K,) amplitudes.
        omega: (K,) angular frequencies, rad/s.
        phase: (K,) phases, rad.
        window: (K, 2) ``[t0, t1]`` per term in seconds; ``[-inf, inf]`` for no window.
    """

    offset: float = 0.0
    slope: float = 0.0
    amp: F64 = field(default_factory=_empty)
    omega: F64 = field(default_factory=_empty)
    phase: F64 = field(default_factory=_empty)
    window: F64 = field(default_factory=lambda: np.zeros((0, 2)))

    @classmethod
    def sines(
        cls,
        amp: npt.ArrayLike,
        omega: npt.ArrayLike,
        phase: npt.ArrayLike,
        offset: float = 0.0,
        slope: float = 0.0,
        window: npt.ArrayLike | None = None,
    ) -> Signal:
        """Build from sequences (windows default to none)."""
        a = np.atleast_1d(np.asarray(amp, dtype=np.float64))
        w = np.broadcast_to(np.asarray(omega, dtype=np.float64), a.shape).copy()
        p = np.broadcast_to(np.asarray(phase, dtype=np.float64), a.shape).copy()
        if window is None:
            win = np.tile([-np.inf, np.inf], (a.shape[0], 1))
        else:
            win = np.broadcast_to(np.asarray(window, dtype=np.float64), (a.shape[0], 2)).copy()
        return cls(float(offset), float(slope), a, w, p, win)

    def __add__(self, other: Signal) -> Signal:
        return Signal(
            self.offset + other.offset,
            self.slope + other.slope,
            np.concatenate([self.amp, other.amp]),
            np.concatenate([self.omega, other.omega]),
            np.concatenate([self.phase, other.phase]),
            np.concatenate([self.window, other.window]),
        )

    def _active(self, tt: F64) -> npt.NDArray[np.bool_] | None:
        """The terms whose windows overlap the times ``tt`` (None: none does).

        Windowed terms that do not overlap the queried times contribute exact zeros: they are
        skipped (a long walk has many bursts, a sweep spans 0.1 s)."""
        if self.amp.size == 0 or tt.size == 0:
            return None
        bounded = np.all(np.isfinite(self.window), axis=1)
        active = ~bounded | ((self.window[:, 1] >= tt.min()) & (self.window[:, 0] <= tt.max()))
        return active if active.any() else None

    def value(self, t: npt.ArrayLike) -> F64:
        """The value alone, (N,): the first of :meth:`eval`'s, computed the same way."""
        tt = np.asarray(t, dtype=np.float64).reshape(-1)
        f = self.offset + self.slope * tt
        active = self._active(tt)
        if active is None:
            return f
        window = self.window[active]
        s = self.amp[active] * np.sin(tt[:, None] * self.omega[active] + self.phase[active])
        if np.isfinite(window).all(axis=1).any():
            s = _window(tt, window) * s
        return f + s.sum(axis=1)

    def eval(self, t: npt.ArrayLike) -> tuple[F64, F64, F64]:
        """Value and first two derivatives.

        Args:
            t: (N,) times, s.

        Returns:
            ``(f, f_dot, f_ddot)``, each (N,).
        """
        tt = np.asarray(t, dtype=np.float64).reshape(-1)
        f = self.offset + self.slope * tt
        d1 = np.full_like(tt, self.slope)
        d2 = np.zeros_like(tt)
        active = self._active(tt)
        if active is None:
            return f, d1, d2
        amp, omega, phase = self.amp[active], self.omega[active], self.phase[active]
        window = self.window[active]
        arg = tt[:, None] * omega + phase  # (N, K)
        s = amp * np.sin(arg)
        s1 = amp * omega * np.cos(arg)
        s2 = -(omega**2) * s
        if np.isfinite(window).all(axis=1).any():
            w, w1, w2 = _windows(tt, window)
            s2 = w2 * s + 2.0 * w1 * s1 + w * s2
            s1 = w1 * s + w * s1
            s = w * s
        return f + s.sum(axis=1), d1 + s1.sum(axis=1), d2 + s2.sum(axis=1)


def _window_phase(
    t: F64, window: F64
) -> tuple[F64, F64, npt.NDArray[np.bool_], npt.NDArray[np.bool_]]:
    """Each time's phase ``u`` in its term's window (N, K), ``k = pi / length`` (K,), and which
    are inside the window (N, K) and which windows are unbounded (K,)."""
    t0, t1 = window[:, 0], window[:, 1]
    unbounded = ~np.isfinite(t0) | ~np.isfinite(t1)
    length = np.where(unbounded, 1.0, t1 - t0)
    k = np.pi / length
    u = (t[:, None] - np.where(unbounded, 0.0, t0)) * k
    inside = (u >= 0.0) & (u <= np.pi)
    return u, k, inside, unbounded


def _window(t: F64, window: F64) -> F64:
    """``sin^4`` windows, (N, K): the first of :func:`_windows`'s."""
    u, _, inside, unbounded = _window_phase(t, window)
    return np.where(unbounded, 1.0, np.where(inside, np.sin(u) ** 4, 0.0))


def _windows(t: F64, window: F64) -> tuple[F64, F64, F64]:
    """``sin^4`` windows and their derivatives, (N, K) each."""
    u, k, inside, unbounded = _window_phase(t, window)
    su, cu = np.sin(u), np.cos(u)
    w = np.where(inside, su**4, 0.0)
    w1 = np.where(inside, 4.0 * su**3 * cu * k, 0.0)
    w2 = np.where(inside, (12.0 * su**2 * cu**2 - 4.0 * su**4) * k**2, 0.0)
    w = np.where(unbounded, 1.0, w)
    w1 = np.where(unbounded, 0.0, w1)
    w2 = np.where(unbounded, 0.0, w2)
    return w, w1, w2


def rot_x(a: F64) -> F64:
    """(N, 3, 3) rotations about x by angles ``a`` (N,), rad."""
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack([o, z, z, z, c, -s, z, s, c], axis=-1).reshape(-1, 3, 3)


def rot_y(a: F64) -> F64:
    """(N, 3, 3) rotations about y."""
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack([c, z, s, z, o, z, -s, z, c], axis=-1).reshape(-1, 3, 3)


def rot_z(a: F64) -> F64:
    """(N, 3, 3) rotations about z."""
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack([c, -s, z, s, c, z, z, z, o], axis=-1).reshape(-1, 3, 3)


def euler_zyx_matrix(rx: F64, ry: F64, rz: F64) -> F64:
    """``Rz(rz) Ry(ry) Rx(rx)``, (N, 3, 3)."""
    sa, ca = np.sin(rx), np.cos(rx)
    sb, cb = np.sin(ry), np.cos(ry)
    sc, cc = np.sin(rz), np.cos(rz)
    out = np.empty((*np.shape(rx), 3, 3))
    out[..., 0, 0] = cc * cb
    out[..., 0, 1] = cc * sb * sa - sc * ca
    out[..., 0, 2] = cc * sb * ca + sc * sa
    out[..., 1, 0] = sc * cb
    out[..., 1, 1] = sc * sb * sa + cc * ca
    out[..., 1, 2] = sc * sb * ca - cc * sa
    out[..., 2, 0] = -sb
    out[..., 2, 1] = cb * sa
    out[..., 2, 2] = cb * ca
    return out


def euler_zyx_body_rate(rx: F64, ry: F64, rx_dot: F64, ry_dot: F64, rz_dot: F64) -> F64:
    """Body-frame angular velocity ``R^T R_dot`` of ``R = Rz Ry Rx`` from Euler rates, (N, 3)."""
    sa, ca = np.sin(rx), np.cos(rx)
    sb, cb = np.sin(ry), np.cos(ry)
    return np.stack(
        [
            rx_dot - rz_dot * sb,
            ry_dot * ca + rz_dot * cb * sa,
            -ry_dot * sa + rz_dot * cb * ca,
        ],
        axis=-1,
    )


@dataclass(frozen=True)
class TrajectoryState:
    """The IMU state at N times (world frame ``{W}``, IMU frame ``{I}``).

    Attributes:
        t: (N,) times, s.
        position: (N, 3) ``p_W_I``, m.
        velocity: (N, 3) m/s, world frame.
        acceleration: (N, 3) ``p_ddot``, m/s^2, world frame.
        rotation: (N, 3, 3) ``R_W_I``.
        angular_velocity: (N, 3) ``omega_I``, rad/s, IMU frame.
    """

    t: F64
    position: F64
    velocity: F64
    acceleration: F64
    rotation: F64
    angular_velocity: F64

    def specific_force(self, gravity_w: F64 = GRAVITY_W) -> F64:
        """``a_I = R^T (p_ddot - g_W)``, (N, 3) m/s^2."""
        return np.einsum("nji,nj->ni", self.rotation, self.acceleration - gravity_w)


@dataclass(frozen=True)
class EulerTrajectory:
    """IMU pose from closed-form position and ZYX Euler-angle signals.

    Attributes:
        position: ``(px, py, pz)`` signals, m.
        euler: ``(rx, ry, rz)`` signals, rad; the body rotation is ``Rz(rz) Ry(ry) Rx(rx)``.
        mount: (3, 3) fixed ``R_B_I`` (IMU frame in the body frame): ``R_W_I = R_W_B @ mount``.
    """

    position: tuple[Signal, Signal, Signal]
    euler: tuple[Signal, Signal, Signal]
    mount: F64 = field(default_factory=lambda: np.eye(3))

    def state(self, t: npt.ArrayLike) -> TrajectoryState:
        """Full state at times ``t`` (N,), s."""
        tt = np.asarray(t, dtype=np.float64).reshape(-1)
        pos = [s.eval(tt) for s in self.position]
        eul = [s.eval(tt) for s in self.euler]
        p = np.stack([c[0] for c in pos], axis=-1)
        v = np.stack([c[1] for c in pos], axis=-1)
        a = np.stack([c[2] for c in pos], axis=-1)
        (rx, rx1, _), (ry, ry1, _), (rz, rz1, _) = eul
        r_wb = euler_zyx_matrix(rx, ry, rz)
        w_b = euler_zyx_body_rate(rx, ry, rx1, ry1, rz1)
        rot = r_wb @ self.mount
        w_i = w_b @ self.mount  # mount^T w_b, row-wise
        return TrajectoryState(tt, p, v, a, rot, w_i)

    def position_at(self, t: npt.ArrayLike) -> F64:
        """``p_W_I(t)``, (N, 3) m."""
        tt = np.asarray(t, dtype=np.float64).reshape(-1)
        return np.stack([s.value(tt) for s in self.position], axis=-1)

    def rotation_at(self, t: npt.ArrayLike) -> F64:
        """``R_W_I(t)``, (N, 3, 3)."""
        tt = np.asarray(t, dtype=np.float64).reshape(-1)
        rx, ry, rz = (s.value(tt) for s in self.euler)
        return euler_zyx_matrix(rx, ry, rz) @ self.mount

    def pose_at(self, t: npt.ArrayLike) -> tuple[F64, F64]:
        """``(R_W_I (N, 3, 3), p_W_I (N, 3))``."""
        return self.rotation_at(t), self.position_at(t)
