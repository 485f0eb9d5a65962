"""Why freeing the beams' elevations biases the LiDAR's z-translation under range noise.

A least-squares model of the LiDAR part alone: one OS1-64-like scan (64 beams at -16.6..16.6
deg, 512 azimuths) from the origin of a box room whose six planes are known exactly; the
unknowns are the LiDAR translation and, per beam, a range offset and an elevation correction
(the directions of ``calibrate --intrinsics lidar`` that take a z-translation: the range
offsets its part along each ray, the elevations its part across it, as far as the ranges
within a beam agree). The ranges carry Gaussian noise along the rays. The derivative of a point
with respect to its beam's elevation is proportional to its range; the fit is solved three ways
per noise draw, with that derivative from the measured range, from the true one, and from the
range the fit itself predicts (where the ray meets its plane, refitted three times; what the
calibration uses since the bias was found). The mean of the translation over the draws shows
the bias: with the measured range the noise in the derivative is the residual's own, and their
product does not average out.

    .venv/bin/python benchmarks/study_range_noise_bias.py            # 200 draws, about 1 min
    .venv/bin/python benchmarks/study_range_noise_bias.py --draws 50 --sigma 0.005
"""

from __future__ import annotations

import argparse

import numpy as np

BEAMS, AZIMUTHS = 64, 512
PLANES = [  # (normal, d) of n.x + d = 0, facing the origin
    ((0.0, 0.0, 1.0), 1.5),
    ((0.0, 0.0, -1.0), 2.5),
    ((1.0, 0.0, 0.0), 4.0),
    ((-1.0, 0.0, 0.0), 3.0),
    ((0.0, 1.0, 0.0), 6.0),
    ((0.0, -1.0, 0.0), 5.0),
]


def scan() -> tuple[np.ndarray, ...]:
    """Rays, their elevation directions, beams, true ranges, hit normals and offsets."""
    phi, theta = np.meshgrid(
        np.radians(np.linspace(-16.6, 16.6, BEAMS)),
        np.linspace(0.0, 2.0 * np.pi, AZIMUTHS, endpoint=False),
        indexing="ij",
    )
    phi, theta = phi.ravel(), theta.ravel()
    beam = np.repeat(np.arange(BEAMS), AZIMUTHS)
    u = np.stack([np.cos(phi) * np.cos(theta), np.cos(phi) * np.sin(theta), np.sin(phi)], 1)
    e_phi = np.stack([-np.sin(phi) * np.cos(theta), -np.sin(phi) * np.sin(theta), np.cos(phi)], 1)
    rho = np.full(phi.shape[0], np.inf)
    hit = np.zeros(phi.shape[0], dtype=int)
    for k, (n, d) in enumerate(PLANES):
        den = u @ np.asarray(n)
        with np.errstate(divide="ignore"):
            r = -d / den
        closer = (den < 0.0) & (r > 0.0) & (r < rho)
        rho[closer], hit[closer] = r[closer], k
    normal = np.array([PLANES[k][0] for k in hit])
    offset = np.array([PLANES[k][1] for k in hit])
    return u, e_phi, beam, rho, normal, offset


def fit(
    rho_meas: np.ndarray,
    rho_jac: np.ndarray | None,
    geometry: tuple[np.ndarray, ...],
    iterations: int = 3,
) -> np.ndarray:
    """Translation (3,) of the linear fit, the elevation derivative taken at ``rho_jac``.

    ``rho_jac=None``: at the range the fit predicts (where each ray meets its plane after the
    fit), starting from the measured range and refitting ``iterations`` times.
    """
    u, e_phi, beam, _, normal, offset = geometry
    rows = np.arange(u.shape[0])
    along = np.einsum("ij,ij->i", normal, u)
    residual = along * rho_meas + offset
    jac = np.zeros((u.shape[0], 3 + 2 * BEAMS))
    jac[:, :3] = normal
    jac[rows, 3 + beam] = along
    across = np.einsum("ij,ij->i", normal, e_phi)
    rho_at = rho_meas if rho_jac is None else rho_jac
    x = np.zeros(jac.shape[1])
    for _ in range(1 if rho_jac is not None else 1 + iterations):
        jac[rows, 3 + BEAMS + beam] = rho_at * across
        x, *_ = np.linalg.lstsq(jac, -residual, rcond=None)
        # the fitted distance of each point; the ray meets its plane that far along it
        rho_at = rho_meas - (residual + jac @ x) / along
    return x[:3]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--draws", type=int, default=200)
    p.add_argument("--sigma", type=float, default=0.015, help="range noise, m (OS1-64: 0.015)")
    args = p.parse_args()
    geometry = scan()
    rho = geometry[3]
    rng = np.random.default_rng(0)
    measured, true, predicted = [], [], []
    for _ in range(args.draws):
        rho_meas = rho + rng.standard_normal(rho.shape[0]) * args.sigma
        measured.append(fit(rho_meas, rho_meas, geometry))
        true.append(fit(rho_meas, rho, geometry))
        predicted.append(fit(rho_meas, None, geometry))
    print(f"{args.draws} draws, range noise {1e3 * args.sigma:.1f} mm, ranges 3-7 m")
    for label, rows in (
        ("measured range", measured),
        ("true range", true),
        ("predicted range", predicted),
    ):
        t = np.array(rows) * 1e3
        sem = t.std(axis=0) / np.sqrt(t.shape[0])
        print(
            f"elevation derivative at the {label:<15}: mean translation "
            f"{np.array2string(t.mean(axis=0), precision=2)} mm "
            f"(standard error {np.array2string(sem, precision=2)})"
        )


if __name__ == "__main__":
    main()
