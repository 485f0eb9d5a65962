"""Analytic rig motion shared by the stage tests: orientation, body rates, IMU and poses."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt
from scipy.spatial.transform import Rotation

from licalib_cli.measurements import ImuSamples
from licalib_cli.odometry import PoseSeries

T0_NS = 1_700_000_000_000_000_000


def _hat(v: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    z = np.zeros(v.shape[0])
    return np.stack(
        [
            np.stack([z, -v[:, 2], v[:, 1]], axis=1),
            np.stack([v[:, 2], z, -v[:, 0]], axis=1),
            np.stack([-v[:, 1], v[:, 0], z], axis=1),
        ],
        axis=1,
    )


def body_rate_from_rotvec(
    phi: npt.NDArray[np.float64], dphi: npt.NDArray[np.float64]
) -> npt.NDArray[np.float64]:
    """Body rate ``w = Jr(phi) dphi/dt`` of ``R = exp(phi)``, (N, 3) rad/s."""
    th = np.linalg.norm(phi, axis=1)[:, None, None]
    th = np.maximum(th, 1e-9)
    k = _hat(phi)
    jr = np.eye(3) - (1.0 - np.cos(th)) / th**2 * k + (th - np.sin(th)) / th**3 * (k @ k)
    return np.einsum("nij,nj->ni", jr, dphi)


class RotationMotion:
    """``R_w_imu(t) = exp(phi(t))`` with ``phi`` a sum of sinusoids; analytic body rates.

    ``amp``, ``freq`` and ``phase`` are (K, 3): component ``j`` of ``phi`` is
    ``sum_k amp[k, j] * sin(2 pi freq[k, j] t + phase[k, j])`` (t in seconds from T0_NS).
    """

    def __init__(
        self,
        amp: npt.NDArray[np.float64],
        freq: npt.NDArray[np.float64],
        phase: npt.NDArray[np.float64],
    ) -> None:
        self.amp, self.freq, self.phase = amp, freq, phase

    @classmethod
    def random(
        cls, seed: int, axes: tuple[float, float, float] = (1.0, 1.0, 1.0)
    ) -> RotationMotion:
        gen = np.random.default_rng(seed)
        amp = gen.uniform(0.2, 0.6, size=(3, 3)) * np.asarray(axes)
        freq = gen.uniform(0.15, 0.9, size=(3, 3))
        phase = gen.uniform(0.0, 2.0 * np.pi, size=(3, 3))
        return cls(amp, freq, phase)

    def _phi(self, t_ns: npt.NDArray[np.int64]) -> tuple[np.ndarray, np.ndarray]:
        t = (np.asarray(t_ns) - T0_NS) * 1e-9
        arg = 2.0 * np.pi * self.freq[None] * t[:, None, None] + self.phase[None]
        phi = np.sum(self.amp[None] * np.sin(arg), axis=1)
        dphi = np.sum(self.amp[None] * 2.0 * np.pi * self.freq[None] * np.cos(arg), axis=1)
        return phi, dphi

    def rotation(self, t_ns: npt.NDArray[np.int64]) -> Rotation:
        return Rotation.from_rotvec(self._phi(t_ns)[0])

    def body_rate(self, t_ns: npt.NDArray[np.int64]) -> npt.NDArray[np.float64]:
        """``w = Jr(phi) dphi/dt`` in the body frame, rad/s."""
        return body_rate_from_rotvec(*self._phi(t_ns))

    def imu(self, duration_s: float, rate_hz: float = 200.0, start_ns: int = T0_NS) -> ImuSamples:
        t = start_ns + np.round(np.arange(0.0, duration_s, 1.0 / rate_hz) * 1e9).astype(np.int64)
        gyro = self.body_rate(t)
        return ImuSamples(t_ns=t, gyro=gyro, accel=np.tile([0.0, 0.0, 9.81], (t.size, 1)))

    def lidar_poses(
        self,
        r_imu_lidar: Rotation,
        time_offset_s: float,
        duration_s: float,
        rate_hz: float = 10.0,
        noise_deg: float = 0.0,
        seed: int = 0,
        start_ns: int = T0_NS,
    ) -> PoseSeries:
        """LiDAR poses at LiDAR times ``tau``, true IMU time ``tau + time_offset_s``."""
        tau = start_ns + np.round(np.arange(0.0, duration_s, 1.0 / rate_hz) * 1e9).astype(np.int64)
        r_w_l = self.rotation(tau + np.int64(round(time_offset_s * 1e9))) * r_imu_lidar
        if noise_deg > 0.0:
            gen = np.random.default_rng(seed)
            r_w_l = r_w_l * Rotation.from_rotvec(
                np.radians(noise_deg) * gen.normal(size=(tau.size, 3))
            )
        r_m_l = r_w_l[0].inv() * r_w_l
        k = tau.size
        tf = np.tile(np.eye(4), (k, 1, 1))
        tf[:, :3, :3] = r_m_l.as_matrix()
        return PoseSeries(
            t_ns=tau,
            T_map_lidar=tf,
            n_points=np.zeros(k, np.int64),
            n_keypoints=np.zeros(k, np.int64),
            threshold_m=np.zeros(k),
            deviation_m=np.zeros(k),
            deviation_deg=np.zeros(k),
        )
