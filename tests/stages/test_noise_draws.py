"""The spread of refits with as much range noise again (``licalib_cli.pipeline.noise_draws``).

At a few centimetres of range noise the estimate scatters beyond its linearised sigmas. The
stage adds as much noise again along every ray, refits from the estimate, and the root mean
square of the moves becomes a floor of the sigmas; a sigma held over its limit by that floor
alone is said to be the range noise's. The refits here are stand-ins (the end-to-end run is in
``tests/integration/test_checks_e2e.py``).
"""

from __future__ import annotations

from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np
import pytest

from licalib_cli.config import CalibConfig, load_config
from licalib_cli.geometry import so3
from licalib_cli.measurements import LidarScan
from licalib_cli.pipeline import noise_draws
from licalib_cli.pipeline.checks import uncertainty_findings


@dataclass(frozen=True)
class _Recording:
    """What the stage reads of a recording: its scans."""

    scans: tuple[LidarScan, ...]


def _recording() -> _Recording:
    rng = np.random.default_rng(0)
    return _Recording(
        tuple(
            LidarScan(
                stamp_ns=k,
                xyz=rng.normal(0.0, 5.0, (4000, 3)),
                t_ns=np.arange(4000, dtype=np.int64) + k,
            )
            for k in range(3)
        )
    )


def test_the_added_noise_moves_each_point_along_its_ray_by_the_range_noise() -> None:
    rec = _recording()
    out = noise_draws.noisier(rec, 0.04, seed=1)  # type: ignore[arg-type]
    again = noise_draws.noisier(rec, 0.04, seed=1)  # type: ignore[arg-type]
    for before, after, same in zip(rec.scans, out.scans, again.scans, strict=True):
        np.testing.assert_array_equal(after.xyz, same.xyz)  # a seed repeats
        np.testing.assert_array_equal(after.t_ns, before.t_ns)
        r0 = np.linalg.norm(before.xyz, axis=1)
        r1 = np.linalg.norm(after.xyz, axis=1)
        u0 = before.xyz / r0[:, None]
        u1 = after.xyz / r1[:, None]
        np.testing.assert_allclose(u1, u0, atol=1e-12)  # along the ray only
        assert np.std(r1 - r0) == pytest.approx(0.04, rel=0.05)
        assert abs(np.mean(r1 - r0)) < 0.004
    other = noise_draws.noisier(rec, 0.04, seed=2)  # type: ignore[arg-type]
    assert not np.allclose(other.scans[0].xyz, out.scans[0].xyz)


def _state(tx: float) -> SimpleNamespace:
    return SimpleNamespace(
        t_imu_lidar=np.array([tx, 0.0, 0.0]), R_imu_lidar=so3.exp(np.zeros(3)), time_offset_s=0.0
    )


def test_the_spread_is_the_rms_of_the_refits_moves_and_runs_only_for_a_noisy_lidar(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    moves = iter([0.006, -0.008])
    seen: list[float] = []

    def schedule(rec, start, noise, cfg, progress, *, warm):  # type: ignore[no-untyped-def]
        assert warm
        seen.append(noise.range_sigma_m)
        return SimpleNamespace(state=_state(0.5 + next(moves)))

    monkeypatch.setattr(noise_draws, "run_schedule", schedule)
    monkeypatch.setattr(noise_draws, "noisier", lambda rec, sigma, seed: rec)

    @dataclass(frozen=True)
    class Noise:
        range_sigma_m: float
        range_sigma_per_beam: np.ndarray
        range_measured_m: float = float("nan")

    @dataclass(frozen=True)
    class Guess:
        state: object

    noisy = Noise(0.04, np.full(16, 0.04))
    cfg = CalibConfig()
    spread = noise_draws.range_noise_spread(None, Guess(None), _state(0.5), noisy, cfg)  # type: ignore[arg-type]
    assert spread is not None
    assert spread[0] == pytest.approx(np.sqrt((0.006**2 + 0.008**2) / 2))
    np.testing.assert_allclose(spread[1:], 0.0, atol=1e-12)
    assert seen == pytest.approx([0.04 * np.sqrt(2)] * 2)  # weighted with the combined noise
    # a LiDAR weighted at its configured 1 cm that carries 4 cm: the noise in the data counts
    pinned = Noise(0.01, np.full(16, 0.01), 0.04)
    moves = iter([0.006, -0.008])
    assert noise_draws.range_noise_spread(None, Guess(None), _state(0.5), pinned, cfg) is not None  # type: ignore[arg-type]
    assert seen[2:] == pytest.approx([0.01 * np.sqrt(2)] * 2)  # its weight scaled alike
    del seen[2:]
    quiet = Noise(0.02, np.full(16, 0.02))
    assert noise_draws.range_noise_spread(None, Guess(None), _state(0.5), quiet, cfg) is None  # type: ignore[arg-type]
    off = load_config(None, {"checks.range_noise_draws": 0})
    assert noise_draws.range_noise_spread(None, Guess(None), _state(0.5), noisy, off) is None  # type: ignore[arg-type]
    assert len(seen) == 2


def test_a_sigma_held_over_its_limit_by_the_noise_spread_says_so() -> None:
    limits = CalibConfig().checks
    sigma = np.array([7.2e-3, 1e-3, 1e-3, 1e-4, 1e-4, 1e-4, 2e-5])
    noisy = np.array([7.2e-3, 0.5e-3, 0.2e-3, 2e-5, 2e-5, 2e-5, 1e-5])
    (finding,) = uncertainty_findings(sigma, sigma, limits, noisy=noisy)
    assert "The LiDAR's range noise holds it there" in finding.text
    assert "more rotation" not in finding.text
    (plain,) = uncertainty_findings(sigma, sigma, limits)
    assert "more rotation" in plain.text and "range noise" not in plain.text
