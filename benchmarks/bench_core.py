"""Speed of the numeric core: residual evaluation, assembly, and one LM step.

Synthetic segment (defaults = the target case): 400 Hz IMU, knot spacing 0.02 s, 6 667 LiDAR
point-to-plane residuals per second (100 000 for 15 s) on 400 random planes, 16-beam LiDAR with
every beam's intrinsics free (gauge beam: s, drho only), IMU intrinsics free, extrinsic and time
offset free, trajectory, biases and gravity free.

Figures (best of ``--repeat`` runs):

* ``evaluate``: all residuals and analytic Jacobians (``Problem.evaluate(jacobians=True)``).
* ``assemble``: the normal equations ``H_tt, H_tc, H_cc, g`` (``Problem.linearize``).
* ``(a) eval+assemble``: the two above.
* ``schur+tsvd l=...``: ``compute_step`` at damping ``lambda`` without a precomputed basis, i.e.
  as after an accepted step: the undamped Schur complement and its eigen-decomposition (which
  decide the truncation), then the factorisation of the damped ``H_tt``, Schur complement, the
  solve restricted to the kept directions and the back-substitution; ``1e-4`` is the initial
  damping, ``1e-6`` typical near convergence.
* ``(b) LM step``: one accepted iteration as in :func:`licalib_cli.solver.solve` at
  ``lambda = 1e-6``: ``compute_step`` (as above), the retraction, the trial evaluation with
  Jacobians and the assembly at the new point (so (b) includes (a)).

Every cell is the best of ``--repeat`` runs (all of them, for every segment length: a time budget
that cut the long segments to two or three runs made the 60 s row inconsistent before). The table
is followed by a consistency check ((a) about evaluate + assemble, (b) at least (a)) and the
machine: CPU, versions and the load average before and after (the machine may be shared).

Run: ``OPENBLAS_NUM_THREADS=1 .venv/bin/python benchmarks/bench_core.py`` (``--quick`` for the
15 s case only, ``--profile`` to print a cProfile of one LM step, ``--solve`` to time a full
solve).
"""

from __future__ import annotations

import argparse
import cProfile
import io
import os
import platform
import pstats
import time
from collections.abc import Callable

import numpy as np
import scipy

from licalib_cli.estimation import (
    CalibrationState,
    FreeParameters,
    ImuData,
    LidarPoints,
    NoiseModel,
    Planes,
    build_problem,
)
from licalib_cli.geometry.so3 import exp as so3_exp
from licalib_cli.models.imu import imu_measure
from licalib_cli.models.intrinsics import ImuIntrinsics, LidarIntrinsics
from licalib_cli.solver import LMParams, Problem, compute_step, solve
from licalib_cli.spline import R3Spline, SO3Spline, UniformKnots

GRAVITY = np.array([0.0, 0.0, -9.81])
POINTS_PER_SECOND = 100_000 / 15.0
LAMBDAS = (1e-4, 1e-6)  # LM damping: initial value, and a typical value near convergence


def make_segment(
    duration: float,
    rng: np.random.Generator,
    *,
    dt: float = 0.02,
    imu_rate: float = 400.0,
    points_per_second: float = POINTS_PER_SECOND,
    beams: int = 16,
    num_planes: int = 400,
) -> tuple[CalibrationState, ImuData, LidarPoints, Planes]:
    """A synthetic segment: smooth random trajectory, IMU readings, points on random planes."""
    knots = UniformKnots.for_interval(0.0, duration, dt, padding_s=0.05)
    tc = knots.control_point_times_s()
    f = 2.0 * np.pi
    phase = rng.uniform(0.0, f, 6)
    rotvec = np.column_stack(
        [
            a * np.sin(f * w * tc + p)
            for a, w, p in zip((0.5, 0.4, 1.0), (0.31, 0.23, 0.07), phase[:3], strict=True)
        ]
    )
    pos = np.column_stack(
        [
            a * np.sin(f * w * tc + p)
            for a, w, p in zip((3.0, 2.0, 0.5), (0.1, 0.13, 0.3), phase[3:], strict=True)
        ]
    )
    so3 = SO3Spline.from_matrices(knots, so3_exp(rotvec))
    r3 = R3Spline(knots, pos)

    t_imu = np.arange(0.0, duration, 1.0 / imu_rate)
    ev = so3.evaluate(t_imu, order=1)
    assert ev.angular_velocity is not None
    a_i = np.einsum("nji,nj->ni", ev.rotation, r3.acceleration(t_imu) - GRAVITY)
    gyro, accel = imu_measure(ImuIntrinsics(), ev.angular_velocity, a_i)
    imu = ImuData(
        t_imu,
        gyro + 1e-3 * rng.standard_normal(gyro.shape),
        accel + 1e-2 * rng.standard_normal(accel.shape),
    )

    # planes facing the trajectory, 8-25 m from the origin
    normal = rng.standard_normal((num_planes, 3))
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    offset = rng.uniform(8.0, 25.0, num_planes)  # n^T x + d = 0 with n pointing inwards
    phi_nominal = np.deg2rad(np.linspace(-15.0, 15.0, beams))
    R_il = so3_exp(np.array([0.01, -0.02, 1.2]))
    t_il = np.array([0.1, -0.05, 0.08])

    n = round(points_per_second * duration)
    tau = np.sort(rng.uniform(0.0, duration, n))
    rot = so3.rotation(tau)
    origin = np.einsum("nij,j->ni", rot, t_il) + r3.position(tau)
    beam = rng.integers(0, beams, n)
    theta = np.empty(n)
    plane = np.empty(n, dtype=np.intp)
    rho = np.empty(n)
    todo = np.arange(n)
    while todo.size:  # resample rays that do not hit their plane in front, 1-60 m away
        th = rng.uniform(-np.pi, np.pi, todo.size)
        pl = rng.integers(0, num_planes, todo.size)
        ph = phi_nominal[beam[todo]]
        u_l = np.column_stack([np.cos(ph) * np.cos(th), np.cos(ph) * np.sin(th), np.sin(ph)])
        u_g = np.einsum("nij,nj->ni", rot[todo] @ R_il, u_l)
        den = np.einsum("ni,ni->n", normal[pl], u_g)
        num = -(np.einsum("ni,ni->n", normal[pl], origin[todo]) + offset[pl])
        with np.errstate(divide="ignore", invalid="ignore"):
            s = num / den
        ok = (den < -0.2) & (s > 1.0) & (s < 60.0)
        theta[todo[ok]], plane[todo[ok]], rho[todo[ok]] = th[ok], pl[ok], s[ok]
        todo = todo[~ok]
    rho += 0.01 * rng.standard_normal(n)
    lidar = LidarPoints(tau, beam, rho, theta, plane)
    state = CalibrationState(
        so3_spline=so3,
        r3_spline=r3,
        gyro_bias=np.zeros(3),
        accel_bias=np.zeros(3),
        gravity_G=GRAVITY,
        R_imu_lidar=R_il @ so3_exp(np.array([0.01, 0.0, -0.01])),
        t_imu_lidar=t_il + 0.01,
        time_offset_s=0.0,
        lidar_intrinsics=LidarIntrinsics.nominal(phi_nominal),
    )
    return state, imu, lidar, Planes(normal, offset)


def build(duration: float, seed: int = 0) -> Problem:
    """The benchmark problem for a segment of ``duration`` seconds."""
    state, imu, lidar, planes = make_segment(duration, np.random.default_rng(seed))
    free = FreeParameters(imu_intrinsics=True, lidar_intrinsics=True, min_points_per_beam=100)
    return build_problem(state, imu, lidar, planes, NoiseModel(1e-3, 1e-2, 0.01), free)


def _best(fn: Callable[[], object], repeat: int) -> float:
    """Best wall time of ``repeat`` runs."""
    best = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def _machine() -> str:
    """CPU model, logical CPUs, Python / numpy / scipy versions."""
    model = "unknown CPU"
    try:
        with open("/proc/cpuinfo", encoding="ascii", errors="replace") as f:
            for line in f:
                if line.startswith("model name"):
                    model = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return (
        f"{model}, {os.cpu_count()} logical CPUs, Python {platform.python_version()}, "
        f"numpy {np.__version__}, scipy {scipy.__version__}, "
        f"OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS', 'unset')}"
    )


def _load() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


def measure(problem: Problem, repeat: int) -> dict[str, float]:
    """Best-of-``repeat`` timings (seconds) of the benchmark stages.

    The problem first takes one LM step from its perturbed initial state, so that the figures
    are those of the iterations near the solution (where most of them are spent).
    """
    layout = problem.layout()
    params = LMParams()
    lin0 = problem.linearize(problem.evaluate(jacobians=True), layout)
    problem.set_values(problem.retracted_values(compute_step(lin0, 1e-4, params).dx, layout))
    out: dict[str, float] = {}
    out["evaluate"] = _best(lambda: problem.evaluate(jacobians=True), repeat)
    ev = problem.evaluate(jacobians=True)
    out["assemble"] = _best(lambda: problem.linearize(ev, layout), repeat)
    out["(a) eval+assemble"] = _best(
        lambda: problem.linearize(problem.evaluate(jacobians=True), layout), repeat
    )
    lin = problem.linearize(ev, layout)
    for lam in LAMBDAS:
        out[f"schur+tsvd l={lam:g}"] = _best(lambda lam=lam: compute_step(lin, lam, params), repeat)

    def lm_step() -> None:
        step = compute_step(lin, LAMBDAS[-1], params)
        trial = problem.evaluate(problem.retracted_values(step.dx, layout), jacobians=True)
        problem.linearize(trial, layout)

    out["(b) LM step"] = _best(lm_step, repeat)
    out["num_residuals"] = float(ev.num_residuals)
    out["num_trajectory"] = float(layout.num_trajectory)
    out["num_calibration"] = float(layout.num_calibration)
    return out


def main() -> None:
    """Print the timing table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--quick", action="store_true", help="only the 15 s segment")
    parser.add_argument("--profile", action="store_true", help="cProfile one LM step (15 s)")
    parser.add_argument("--solve", action="store_true", help="also time a full solve (15 s)")
    args = parser.parse_args()

    durations = (15.0,) if args.quick else (5.0, 15.0, 60.0)
    load_before = _load()
    rows = []
    for duration in durations:
        problem = build(duration)
        res = measure(problem, args.repeat)
        rows.append((duration, res))
        if duration == 15.0 and args.profile:
            prof = cProfile.Profile()
            layout = problem.layout()
            lin = problem.linearize(problem.evaluate(jacobians=True), layout)
            prof.enable()
            step = compute_step(lin, LAMBDAS[-1], LMParams())
            trial = problem.evaluate(problem.retracted_values(step.dx, layout), jacobians=True)
            problem.linearize(trial, layout)
            prof.disable()
            buf = io.StringIO()
            pstats.Stats(prof, stream=buf).sort_stats("cumulative").print_stats(30)
            print(buf.getvalue())
        if duration == 15.0 and args.solve:
            t0 = time.perf_counter()
            report = solve(problem, LMParams(max_iterations=20))
            elapsed = time.perf_counter() - t0
            print(
                f"15 s solve: {elapsed:.2f} s, {report.iterations} iterations "
                f"({elapsed / max(report.iterations, 1):.2f} s each, final report included), "
                f"{report.status} ({report.reason}), truncated directions: {len(report.truncated)}"
            )

    keys = ["evaluate", "assemble", "(a) eval+assemble"]
    keys += [f"schur+tsvd l={lam:g}" for lam in LAMBDAS] + ["(b) LM step"]
    head = f"{'segment':>8} {'residuals':>10} {'Nt':>6} {'Nc':>4} "
    print(head + " ".join(f"{k:>20}" for k in keys))
    for duration, res in rows:
        print(
            f"{duration:7.0f}s {int(res['num_residuals']):10d} {int(res['num_trajectory']):6d} "
            f"{int(res['num_calibration']):4d} " + " ".join(f"{res[k]:19.3f}s" for k in keys)
        )
    for duration, res in rows:
        parts = res["evaluate"] + res["assemble"]
        notes = []
        if res["(a) eval+assemble"] > 1.15 * parts:
            notes.append(f"(a) exceeds evaluate + assemble ({parts:.3f} s) by more than 15 %")
        if res["(b) LM step"] < res["(a) eval+assemble"]:
            notes.append("(b) below (a) although it includes it")
        status = "; ".join(notes) if notes else "consistent"
        per_second = res["(b) LM step"] / duration
        print(f"{duration:.0f} s: {status}; (b) per second of data {per_second:.4f} s")
    print(f"machine: {_machine()}")
    print(f"load average (1, 5, 15 min): before {load_before}, after {_load()}")


if __name__ == "__main__":
    main()
