"""Information of the calibration parameters: Schur complement, scaling, singular directions.

The information matrix ``A = J^T W J`` of the linearised problem is split into the trajectory
group (spline, biases, gravity) and the calibration group (extrinsics, time offset, intrinsics).
The trajectory block is eliminated (Schur complement) to give the calibration information ``S``,
which is then made dimensionless with the per-coordinate characteristic scales ``d`` of the
parameter blocks: ``S_d = D S D`` with ``D = diag(d)`` (e.g. metres / 0.01 m, radians /
0.001 rad, seconds / 0.001 s). An eigenvalue ``s`` of ``S_d`` (its singular value: ``S_d`` is
symmetric positive semi-definite) means that the standard deviation along the corresponding unit
direction is ``1 / sqrt(s)`` characteristic scales; ``s = 1`` is "known to one characteristic
scale". Singular vectors are unit vectors in these scaled coordinates; within a block with a
uniform scale they are also the physical direction.

Metrics (comparable only within one bag and one scaling): minimum singular value (E-optimality,
the paper's choice), trace (A-), log-determinant (D-), and maximum eigenvalue.

Directions are named in parameter terms, with the frame their components are expressed in
(:data:`BLOCK_FRAMES`), e.g. ``"ext.translation along [0.00, 0.00, 1.00] in the IMU frame:
unobservable, not estimated (stays near its initial value)"``.
"""

from __future__ import annotations

from collections.abc import Collection, Iterable, Mapping, Sequence
from dataclasses import dataclass
from types import MappingProxyType

import numpy as np
import numpy.typing as npt

from licalib_cli.solver.problem import Linearization, Problem, ResidualBlock
from licalib_cli.solver.schur import SchurSystem, schur_complement

__all__ = [
    "BLOCK_FRAMES",
    "TRAJECTORY_REGULARISATION",
    "DirectionDescription",
    "InformationSummary",
    "Truncation",
    "absolute_threshold",
    "calibration_information",
    "describe_direction",
    "kept_directions",
    "marginal_information",
    "mostly_free",
    "summarize_information",
    "summed_information",
    "truncation_mask",
    "undamped_schur",
    "undamped_schur_system",
    "weak_directions",
]

F64 = npt.NDArray[np.float64]

TRAJECTORY_REGULARISATION = 1e-10
"""Relative diagonal regularisation of ``H_tt``, used for the undamped ``S`` only when ``H_tt``
itself cannot be factorised (a gauge freedom of the trajectory). It is a fallback and not the
default because even this little damping of the trajectory is not negligible for a calibration
direction that a trajectory direction can absorb: it charges the trajectory for taking it over and
so makes the calibration direction look observable (``S`` grows by orders of magnitude, e.g. a
translation along the rotation axis of planar motion)."""

_RCOND = 1e-12
"""Singular values below ``_RCOND * max`` are always treated as zero (numerical rank)."""

_MAX_BLOCK_LISTING = 6

BLOCK_FRAMES: Mapping[str, str] = MappingProxyType(
    {
        "ext.translation": "the IMU frame",  # t_imu_lidar: the LiDAR origin in {I}
        "ext.rotation": "the LiDAR frame",  # right perturbation R_IL Exp(delta): delta in {L}
        "imu.gyro_rotation": "the IMU frame",  # right perturbation R_wI Exp(delta): delta in {I}
    }
)
"""Frame of the tangent coordinates of the calibration blocks (names of
:mod:`licalib_cli.residuals`) that have one; :func:`describe_direction` states it."""


@dataclass(frozen=True)
class DirectionDescription:
    """A direction in calibration space, named in parameter terms.

    Attributes:
        vector: (Nc,) unit vector in scaled coordinates; sign chosen so that its largest
            component is positive.
        components: Dominant ``(coordinate name, weight)`` pairs, largest ``|weight|`` first.
        blocks: ``(block name, share)`` of the squared norm per block, largest first.
        text: Human description, e.g. ``"ext.translation along [0.00, -0.19, 0.98] in the IMU
            frame: unobservable, not estimated (stays near its initial value)"``.
    """

    vector: F64
    components: tuple[tuple[str, float], ...]
    blocks: tuple[tuple[str, float], ...]
    text: str


def _owner_of(name: str) -> str:
    base = name.split("[", 1)[0] if "[" in name else name
    return base.rsplit(".", 1)[0] if "." in base else base


def describe_direction(
    vector: npt.ArrayLike,
    names: Sequence[str],
    owners: Sequence[str] | None = None,
    *,
    verdict: str = "unobservable, not estimated (stays near its initial value)",
    min_weight: float = 0.1,
    frames: Mapping[str, str] | None = None,
) -> DirectionDescription:
    """Name a calibration-space direction in parameter terms.

    Blocks holding at least 1 % of the squared norm are listed, largest share first; a block with
    at most six coordinates is written as ``"<block> along [v0, v1, ...]"`` (its components of the
    unit vector) followed by ``" in <frame>"`` when the block's coordinates have a frame, a
    larger one by its dominant coordinates ``"name weight"``.

    Args:
        vector: (Nc,) direction (any norm, non-zero).
        names: (Nc,) coordinate names.
        owners: (Nc,) owning block names; default: the name up to its last ``.``.
        verdict: Text appended after a colon.
        min_weight: Smallest ``|weight|`` listed among the dominant components (the largest one
            is always listed).
        frames: Block name -> frame of its coordinates (default :data:`BLOCK_FRAMES`).

    Returns:
        The description.
    """
    v = np.asarray(vector, dtype=np.float64).reshape(-1)
    if v.size != len(names):
        msg = f"Direction has {v.size} components but {len(names)} names were given."
        raise ValueError(msg)
    v = v / np.linalg.norm(v)
    if v[np.argmax(np.abs(v))] < 0.0:
        v = -v
    owner = list(owners) if owners is not None else [_owner_of(n) for n in names]
    order = np.argsort(-np.abs(v), kind="stable")
    dominant = [int(i) for i in order if abs(v[i]) >= min_weight] or [int(order[0])]
    components = tuple((names[i], float(v[i])) for i in dominant)
    block_names = list(dict.fromkeys(owner))
    owner_arr = np.asarray(owner, dtype=object)
    shares = {b: float(np.sum(v[owner_arr == b] ** 2)) for b in block_names}
    ranked = sorted(((b, s) for b, s in shares.items() if s >= 0.01), key=lambda x: -x[1])
    frame_of = BLOCK_FRAMES if frames is None else frames
    parts = []
    for b, _ in ranked:
        sel = np.flatnonzero(owner_arr == b)
        if sel.size <= _MAX_BLOCK_LISTING:
            frame = f" in {frame_of[b]}" if b in frame_of else ""
            shown = np.round(v[sel], 2) + 0.0  # no "-0.00"
            parts.append(f"{b} along [{', '.join(f'{x:.2f}' for x in shown)}]{frame}")
        else:
            ranked_sel = sel[np.argsort(-np.abs(v[sel]), kind="stable")]
            listed = [i for i in ranked_sel if abs(v[i]) >= min_weight] or [ranked_sel[0]]
            parts.append(f"{b} ({', '.join(f'{names[i]} {v[i]:+.2f}' for i in listed)})")
    text = f"{' + '.join(parts)}: {verdict}" if verdict else " + ".join(parts)
    return DirectionDescription(v, components, tuple(ranked), text)


def mostly_free(
    directions: F64, owners: Sequence[str], bounded_blocks: Sequence[str]
) -> npt.NDArray[np.bool_]:
    """(k,) whether each unit direction (columns of ``directions``, scaled coordinates) is made
    mostly of coordinates outside ``bounded_blocks`` (the extrinsic, the time offset)."""
    bounded = np.array([any(o.startswith(p) for p in bounded_blocks) for o in owners], dtype=bool)
    return np.asarray(np.sum(directions[bounded] ** 2, axis=0) < 0.5)


def weak_directions(
    singular_values: npt.ArrayLike,
    vectors: F64,
    owners: Sequence[str],
    threshold: float,
    *,
    floor: float,
    bounded_blocks: Sequence[str],
) -> npt.NDArray[np.bool_]:
    """Which singular directions are weakly determined: below ``threshold`` (absolute), at
    least ``floor`` of it, made mostly of coordinates outside ``bounded_blocks``
    (:func:`mostly_free`). The solver estimates them and reports their standard deviation
    (``LMParams.weak_floor``); all False when ``floor`` is 0."""
    s = np.asarray(singular_values, dtype=np.float64)
    if floor <= 0.0 or s.size == 0:
        return np.zeros(s.size, dtype=bool)
    weak = ~truncation_mask(s, threshold) & truncation_mask(s, floor * threshold)
    return weak & mostly_free(vectors, owners, bounded_blocks)


@dataclass(frozen=True)
class Truncation:
    """Which calibration directions a step moves along (the solver's ``LMParams.tsvd_threshold``,
    ``tsvd_relative``, ``weak_floor`` and ``bounded_blocks``, as :func:`kept_directions` takes
    them).

    Attributes:
        threshold: Smallest scaled information of a calibration direction that moves.
        relative: ``threshold`` is a fraction of the largest singular value.
        weak_floor: Below the threshold, a direction of at least this fraction of it made
            mostly of coordinates outside ``bounded_blocks`` is weakly determined and moves too
            (:func:`weak_directions`); 0: none.
        bounded_blocks: Prefixes of the calibration blocks known a priori to within their
            characteristic scale (the intrinsics).
    """

    threshold: float = 1.0
    relative: bool = False
    weak_floor: float = 0.0
    bounded_blocks: tuple[str, ...] = ()

    def kept(
        self, singular_values: npt.ArrayLike, vectors: F64, owners: Sequence[str]
    ) -> npt.NDArray[np.bool_]:
        """(k,) which singular directions a step moves along (:func:`kept_directions`)."""
        return kept_directions(
            singular_values,
            vectors,
            owners,
            self.threshold,
            relative=self.relative,
            floor=self.weak_floor,
            bounded_blocks=self.bounded_blocks,
        )


def kept_directions(
    singular_values: npt.ArrayLike,
    vectors: F64,
    owners: Sequence[str],
    threshold: float,
    *,
    relative: bool = False,
    floor: float,
    bounded_blocks: Sequence[str],
) -> npt.NDArray[np.bool_]:
    """Which singular directions a step moves along: those the truncated SVD keeps
    (:func:`truncation_mask`) and the weakly determined ones (:func:`weak_directions`, with
    ``threshold`` made absolute when ``relative``)."""
    s = np.asarray(singular_values, dtype=np.float64)
    absolute = absolute_threshold(s, threshold, relative=relative)
    return truncation_mask(s, absolute) | weak_directions(
        s, vectors, owners, absolute, floor=floor, bounded_blocks=bounded_blocks
    )


def absolute_threshold(
    singular_values: npt.ArrayLike, threshold: float, *, relative: bool = False
) -> float:
    """The truncation threshold in singular-value units: ``threshold`` itself, or when
    ``relative`` that fraction of the largest singular value."""
    s = np.asarray(singular_values, dtype=np.float64)
    return threshold * (max(float(s.max()), 0.0) if relative and s.size else 1.0)


def truncation_mask(
    singular_values: npt.ArrayLike, threshold: float, *, relative: bool = False
) -> npt.NDArray[np.bool_]:
    """Which singular values are kept by the truncated SVD.

    Args:
        singular_values: (k,) singular values of the scaled information ``S_d``.
        threshold: ``epsilon``; absolute (in scaled information units, i.e. a standard deviation
            of ``1 / sqrt(epsilon)`` characteristic scales) or, when ``relative``, a fraction of
            the largest singular value.
        relative: Interpret ``threshold`` relative to the largest singular value.

    Returns:
        (k,) True for kept values: ``s > epsilon`` and ``s > 1e-12 * max(s)``.
    """
    s = np.asarray(singular_values, dtype=np.float64)
    if s.size == 0:
        return np.zeros(0, dtype=bool)
    smax = max(float(s.max()), 0.0)
    return (s > absolute_threshold(s, threshold, relative=relative)) & (s > _RCOND * smax)


@dataclass(frozen=True)
class InformationSummary:
    """Scaled calibration information and its spectrum.

    Attributes:
        names: (Nc,) calibration coordinate names.
        owners: (Nc,) owning block of each coordinate.
        scale: (Nc,) characteristic scales ``d`` used (``S_d = D S D``).
        scaling: Statement of the scaling.
        information: (Nc, Nc) scaled Schur complement ``S_d``.
        singular_values: (Nc,) singular values of ``S_d``, descending.
        singular_vectors: (Nc, Nc) matching unit vectors (columns), scaled coordinates.
        num_residuals: Scalar residuals that contributed.
    """

    names: tuple[str, ...]
    owners: tuple[str, ...]
    scale: F64
    scaling: str
    information: F64
    singular_values: F64
    singular_vectors: F64
    num_residuals: int

    @property
    def min_singular_value(self) -> float:
        """Smallest singular value (0 when there are no calibration coordinates)."""
        return float(self.singular_values[-1]) if self.singular_values.size else 0.0

    @property
    def max_eigenvalue(self) -> float:
        """Largest eigenvalue (= singular value) of ``S_d``."""
        return float(self.singular_values[0]) if self.singular_values.size else 0.0

    @property
    def trace(self) -> float:
        """Trace of ``S_d``."""
        return float(np.sum(self.singular_values))

    @property
    def log_determinant(self) -> float:
        """``log det S_d`` (``-inf`` when singular)."""
        s = self.singular_values
        if s.size == 0:
            return 0.0
        if np.any(s <= 0.0):
            return float("-inf")
        return float(np.sum(np.log(s)))

    @property
    def condition_number(self) -> float:
        """``max / min`` singular value (``inf`` when singular)."""
        smin = self.min_singular_value
        return float("inf") if smin <= 0.0 else self.max_eigenvalue / smin

    def metrics(self) -> dict[str, float]:
        """The ranking metrics: min singular value, trace, log-determinant, max eigenvalue."""
        return {
            "min_singular_value": self.min_singular_value,
            "trace": self.trace,
            "log_determinant": self.log_determinant,
            "max_eigenvalue": self.max_eigenvalue,
        }

    def kept(self, threshold: float, *, relative: bool = False) -> npt.NDArray[np.bool_]:
        """(Nc,) mask of singular values kept by a TSVD with ``threshold`` (see
        :func:`truncation_mask`)."""
        return truncation_mask(self.singular_values, threshold, relative=relative)

    def describe(self, index: int, verdict: str = "") -> DirectionDescription:
        """Describe singular vector ``index`` (0 = strongest, -1 = weakest)."""
        return describe_direction(
            self.singular_vectors[:, index], self.names, self.owners, verdict=verdict
        )


def scaling_statement(names: Sequence[str], scale: F64) -> str:
    """One-line statement of the calibration scaling used, grouped by value."""
    if len(names) == 0:
        return "no calibration coordinates"
    groups: dict[float, list[str]] = {}
    for n, d in zip(names, scale, strict=True):
        groups.setdefault(float(d), []).append(n)
    parts = []
    for d, ns in groups.items():
        shown = ", ".join(ns[:3]) + (f" and {len(ns) - 3} more" if len(ns) > 3 else "")
        parts.append(f"{d:g} ({shown})")
    return "S_d = D S D, D = diag of characteristic scales in each coordinate's unit: " + "; ".join(
        parts
    )


def summarize_information(
    S: F64,
    names: Sequence[str],
    owners: Sequence[str],
    scale: F64,
    num_residuals: int = 0,
) -> InformationSummary:
    """Scale a calibration information matrix and decompose it.

    Args:
        S: (Nc, Nc) Schur complement in physical units (whitened residuals).
        names: (Nc,) coordinate names.
        owners: (Nc,) owning block names.
        scale: (Nc,) characteristic scales ``d``.
        num_residuals: Number of scalar residuals behind ``S``.

    Returns:
        The summary (singular values descending; tiny negative round-off clipped to zero).
    """
    scale = np.asarray(scale, dtype=np.float64)
    sd = scale[:, None] * np.asarray(S, dtype=np.float64) * scale[None, :]
    return _scaled_summary(sd, names, owners, scale, num_residuals)


def _scaled_summary(
    sd: F64, names: Sequence[str], owners: Sequence[str], scale: F64, num_residuals: int
) -> InformationSummary:
    """The summary of an already scaled information ``sd`` (symmetrised and decomposed)."""
    sd = 0.5 * (sd + sd.T)
    if sd.size:
        w, u = np.linalg.eigh(sd)
        w, u = np.clip(w[::-1], 0.0, None), u[:, ::-1]
    else:
        w, u = np.zeros(0), np.zeros((0, 0))
    return InformationSummary(
        names=tuple(names),
        owners=tuple(owners),
        scale=scale.copy(),
        scaling=scaling_statement(names, scale),
        information=sd,
        singular_values=w,
        singular_vectors=u,
        num_residuals=num_residuals,
    )


def marginal_information(
    info: InformationSummary, owners: Collection[str], prior: float = 1.0
) -> InformationSummary:
    """The information of the coordinates of blocks ``owners`` when every other coordinate is
    unknown as well, to within ``1 / sqrt(prior)`` of its characteristic scale a priori.

    ``S_kk - S_kr (S_rr + prior I)^-1 S_rk`` in the scaled coordinates of ``info``: with the
    default prior of 1 the other coordinates are taken as known to one characteristic scale
    (the size the truncated SVD holds a direction at when the data say less), so a direction
    of the kept blocks that trades with them loses what the trade costs, and no more.

    Args:
        info: The summary over all coordinates.
        owners: Blocks whose coordinates are kept.
        prior: Scaled information added to the other coordinates (> 0).

    Returns:
        The summary of the kept coordinates (same scales); ``info`` itself when nothing
        else is in it.
    """
    keep = np.asarray([o in owners for o in info.owners], dtype=bool)
    if keep.all():
        return info
    s = info.information
    k, r = np.flatnonzero(keep), np.flatnonzero(~keep)
    s_rr = s[np.ix_(r, r)] + prior * np.eye(r.size)
    s_kr = s[np.ix_(k, r)]
    sd = s[np.ix_(k, k)] - s_kr @ np.linalg.solve(s_rr, s_kr.T)
    return _scaled_summary(
        sd,
        [info.names[i] for i in k],
        [info.owners[i] for i in k],
        info.scale[k],
        info.num_residuals,
    )


def summed_information(infos: Sequence[InformationSummary]) -> InformationSummary:
    """The information of independent data sets over the same coordinates (same names and
    scales): their scaled matrices added.

    Raises:
        ValueError: no summaries, or summaries over different coordinates or scales.
    """
    if not infos:
        msg = "no information to add"
        raise ValueError(msg)
    first = infos[0]
    if any(i.names != first.names or not np.array_equal(i.scale, first.scale) for i in infos):
        msg = "information over different coordinates or scales cannot be added"
        raise ValueError(msg)
    return _scaled_summary(
        sum((i.information for i in infos), np.zeros_like(first.information)),
        first.names,
        first.owners,
        first.scale,
        sum(i.num_residuals for i in infos),
    )


def undamped_schur(lin: Linearization) -> F64:
    """Calibration Schur complement ``S`` of a linearisation, without damping.

    ``H_tt`` is factorised as it is; only when that fails (exactly singular, or a result that is
    not finite) is the relative regularisation :data:`TRAJECTORY_REGULARISATION` added to its
    diagonal.

    Args:
        lin: Normal equations.

    Returns:
        (Nc, Nc) ``S``.
    """
    return undamped_schur_system(lin).S


def undamped_schur_system(lin: Linearization) -> SchurSystem:
    """:func:`undamped_schur`'s whole reduced system: ``S`` and the right-hand side ``b`` (the
    calibration's gradient with the trajectory eliminated)."""
    try:
        system = schur_complement(lin, 0.0)
        if np.all(np.isfinite(system.S)) and np.all(np.isfinite(system.b)):
            return system
    except np.linalg.LinAlgError:
        pass
    reg = TRAJECTORY_REGULARISATION * lin.H_tt.diagonal()
    return schur_complement(lin, reg)


def calibration_information(
    problem: Problem, residual_blocks: Iterable[ResidualBlock] | None = None
) -> InformationSummary:
    """Scaled calibration information of (a subset of) the residual blocks at the current estimate.

    Trajectory coordinates no chosen residual touches drop out (e.g. the spline outside a
    segment), so the result describes what the chosen data alone determine.

    Args:
        problem: The problem (its current values, fixed masks, scales and robust losses are used).
        residual_blocks: Residual blocks to include (default: all of the problem's).

    Returns:
        The information summary.
    """
    layout = problem.layout()
    evaluation = problem.evaluate(jacobians=True, residual_blocks=residual_blocks)
    lin = problem.linearize(evaluation, layout)
    return summarize_information(
        undamped_schur(lin),
        layout.calibration_names,
        layout.calibration_owner,
        layout.calibration_scale,
        evaluation.num_residuals,
    )
