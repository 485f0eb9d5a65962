"""The simulated room and exact, vectorised ray casting.

World frame ``{W}``: z up, metres. The room of the paper's simulation (about 12 x 10 x 10 m) is
placed at ``x in [-3.5, 8.5]``, ``y in [0, 10]``, ``z in [0, 10]`` so that both of the paper's
trajectories fit with margin: the sinusoid (centred at (5, 5, 5), x in [3, 7], y in [3.5, 6.5],
z in [4.2, 5.8]) and the figure-8 (x in [-2, 2], y in [4.25, 5.75], z = 2). The hand-held
scenarios (shake around (2.5, 5, 1.5), walk on an ellipse around (2.5, 5) at 1.4 m) use the same
free space.

Inside the room: floor boxes, pillars (one rotated about z), a wall shelf, a ceiling beam, a
floating tilted cube, two ceiling chamfers, a floor ramp, a board leaning on a wall and two
diagonal corner panels, plus fixed pseudo-random clutter (28 yawed/tilted wall-mounted boxes at
all heights, 4 ceiling ducts, 6 low floor boxes), so that plane normals point in many directions
and scans have edges and corners (what LiDAR odometry and point-to-plane calibration need).

Every surface is a plane ``n . x + d = 0`` (unit ``n``) with an integer id; ray casting returns
the distance and the id of the first surface hit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

F64 = npt.NDArray[np.float64]
I32 = npt.NDArray[np.int32]

_EPS = 1e-9
WALL_CLUTTER_PER_WALL = 7


@dataclass(frozen=True)
class World:
    """A closed room of planes with oriented boxes and convex quadrilaterals inside.

    Attributes:
        room_min: (3,) lower corner of the room, m.
        room_max: (3,) upper corner of the room, m.
        box_center: (B, 3) box centres, m.
        box_rotation: (B, 3, 3) ``R_W_box`` (box axes in the world).
        box_half: (B, 3) half extents along the box axes, m.
        quad_vertices: (Q, 4, 3) convex planar quadrilaterals, vertices in order, m.
    """

    room_min: F64
    room_max: F64
    box_center: F64
    box_rotation: F64
    box_half: F64
    quad_vertices: F64

    @property
    def num_boxes(self) -> int:
        return int(self.box_center.shape[0])

    @property
    def num_quads(self) -> int:
        return int(self.quad_vertices.shape[0])

    @property
    def num_planes(self) -> int:
        """6 room faces, 6 faces per box, 1 plane per quadrilateral."""
        return 6 + 6 * self.num_boxes + self.num_quads

    def planes(self) -> F64:
        """All surfaces as ``[nx, ny, nz, d]`` with ``n . x + d = 0``, (P, 4), indexed by id.

        Ids: 0-5 room faces ``[x=min, x=max, y=min, y=max, z=min, z=max]``; then 6 per box
        ``[-x, +x, -y, +y, -z, +z]`` in box axes; then one per quadrilateral.
        """
        out = np.zeros((self.num_planes, 4))
        for axis in range(3):
            n = np.zeros(3)
            n[axis] = 1.0
            out[2 * axis] = [*n, -self.room_min[axis]]
            out[2 * axis + 1] = [*n, -self.room_max[axis]]
        for b in range(self.num_boxes):
            for axis in range(3):
                n = self.box_rotation[b][:, axis]
                for side, sign in ((0, -1.0), (1, 1.0)):
                    point = self.box_center[b] + sign * self.box_half[b, axis] * n
                    out[6 + 6 * b + 2 * axis + side] = [*n, -float(n @ point)]
        n_q, off_q, _ = self._quad_geometry()
        out[6 + 6 * self.num_boxes :, :3] = n_q
        out[6 + 6 * self.num_boxes :, 3] = off_q
        return out

    def reflectivity(self) -> F64:
        """A fixed pseudo-random reflectivity in [0.2, 0.8] per plane id, (P,)."""
        ids = np.arange(self.num_planes, dtype=np.float64)
        return 0.2 + 0.6 * np.mod(np.sin(ids * 12.9898 + 1.0) * 43758.5453, 1.0)

    def _quad_geometry(self) -> tuple[F64, F64, F64]:
        """Unit normals (Q, 3), plane offsets (Q,), inward edge normals (Q, 4, 3)."""
        v = self.quad_vertices
        if v.shape[0] == 0:
            return np.zeros((0, 3)), np.zeros(0), np.zeros((0, 4, 3))
        n = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
        n /= np.linalg.norm(n, axis=-1, keepdims=True)
        off = -np.einsum("qi,qi->q", n, v[:, 0])
        edges = np.roll(v, -1, axis=1) - v
        m = np.cross(n[:, None, :], edges)
        centroid = v.mean(axis=1)
        sign = np.sign(np.einsum("qji,qji->qj", m, centroid[:, None, :] - v))
        return n, off, m * sign[..., None]

    def raycast(self, origins: F64, directions: F64, chunk: int = 16384) -> tuple[F64, I32]:
        """First hit of each ray.

        Args:
            origins: (N, 3) ray origins in ``{W}`` (inside the room), m.
            directions: (N, 3) unit directions in ``{W}``.
            chunk: rays processed per vectorised block.

        Returns:
            ``(distance (N,) m, plane_id (N,) int32)``; a ray always hits the closed room.
        """
        o_all = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
        d_all = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
        n = o_all.shape[0]
        dist = np.empty(n)
        pid = np.empty(n, dtype=np.int32)
        geo = self._cast_geometry()
        for i0 in range(0, n, chunk):
            sl = slice(i0, min(n, i0 + chunk))
            dist[sl], pid[sl] = self._raycast_block(o_all[sl], d_all[sl], geo)
        return dist, pid

    def _cast_geometry(self) -> dict[str, F64]:
        """Box axes and quad edge normals arranged for elementwise ray tests, as columns (K, 1)."""
        n_q, off_q, m_q = self._quad_geometry()
        axes = self.box_rotation.transpose(0, 2, 1)  # (B, 3 axes, 3 coords)
        return {
            "center": self.box_center.T[..., None].copy(),  # (3, B, 1)
            "radius": np.linalg.norm(self.box_half, axis=1)[:, None],  # (B, 1) bounding sphere
            "radius2": np.sum(self.box_half**2, axis=1)[:, None],
            "axes_flat": axes,  # (B, 3 axes, 3 coords)
            "center_flat": self.box_center,
            "half_flat": self.box_half,
            "n": n_q.T[..., None].copy(),  # (3 coords, Q, 1)
            "off": off_q[:, None],  # (Q, 1)
            "m": m_q.transpose(1, 2, 0)[..., None].copy(),  # (4 edges, 3 coords, Q, 1)
            "m_v": np.einsum("qji,qji->jq", m_q, self.quad_vertices)[..., None],  # (4, Q, 1)
        }

    def _raycast_block(self, o: F64, d: F64, geo: dict[str, F64]) -> tuple[F64, I32]:
        # Layout (K, N) with the rays along the last, contiguous axis: numpy is several times
        # faster this way than with (N, K) broadcasting or reductions over short axes.
        ot = np.ascontiguousarray(o.T)
        dt = np.ascontiguousarray(d.T)

        def dot(v: F64) -> tuple[F64, F64]:
            """``o . v`` and ``d . v`` for ``v`` (3, K, 1) -> (K, N) each."""
            return (
                v[0] * ot[0] + v[1] * ot[1] + v[2] * ot[2],
                v[0] * dt[0] + v[1] * dt[1] + v[2] * dt[2],
            )

        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            # Room: exit through the nearest wall.
            inv = 1.0 / dt
            t_axis = np.where(dt > 0, (self.room_max[:, None] - ot), (self.room_min[:, None] - ot))
            t_axis = np.where(dt == 0, np.inf, t_axis * inv)
            axis = np.argmin(t_axis, axis=0)
            best = np.min(t_axis, axis=0)
            d_axis = np.choose(axis, dt)
            best_id = (2 * axis + (d_axis > 0)).astype(np.int32)

            # Oriented boxes: bounding-sphere cull over (B, N), then the slab test on the
            # (box, ray) candidate pairs only.
            b = self.num_boxes
            if b:
                vx = geo["center"][0] - ot[0]
                vy = geo["center"][1] - ot[1]
                vz = geo["center"][2] - ot[2]
                along = vx * dt[0] + vy * dt[1] + vz * dt[2]
                perp2 = vx * vx + vy * vy + vz * vz - along * along
                cand = (perp2 <= geo["radius2"]) & (along >= -geo["radius"])
                cb, cn = np.nonzero(cand)
                if cb.size:
                    axes = geo["axes_flat"][cb]  # (M, 3 axes, 3 coords)
                    rel = o[cn] - geo["center_flat"][cb]
                    ob = np.einsum("mki,mi->mk", axes, rel)
                    db = np.einsum("mki,mi->mk", axes, d[cn])
                    half = geo["half_flat"][cb]
                    inv_b = 1.0 / db
                    t1 = (-half - ob) * inv_b
                    t2 = (half - ob) * inv_b
                    tmin = np.fmin(t1, t2)
                    t_near = tmin.max(axis=1)
                    t_far = np.fmax(t1, t2).min(axis=1)
                    hit = (t_near <= t_far) & (t_near > _EPS) & (t_near < best[cn])
                    if hit.any():
                        cb, cn, t_near = cb[hit], cn[hit], t_near[hit]
                        face_axis = np.argmax(tmin[hit], axis=1)
                        d_face = db[hit][np.arange(face_axis.shape[0]), face_axis]
                        box_id = 6 + 6 * cb + 2 * face_axis + (d_face < 0)
                        # Nearest candidate per ray: sort by (ray, distance), keep the first.
                        order = np.lexsort((t_near, cn))
                        cn, t_near, box_id = cn[order], t_near[order], box_id[order]
                        first = np.ones(cn.shape[0], dtype=bool)
                        first[1:] = cn[1:] != cn[:-1]
                        best[cn[first]] = t_near[first]
                        best_id[cn[first]] = box_id[first]

            # Convex quadrilaterals, (Q, N).
            q = geo["off"].shape[0]
            if q:
                on, dn = dot(geo["n"])
                tq = -(on + geo["off"]) / dn
                inside = np.isfinite(tq) & (tq > _EPS)
                for j in range(4):
                    om, dm = dot(geo["m"][j])
                    inside &= om + tq * dm - geo["m_v"][j] >= -1e-12
                tq = np.where(inside, tq, np.inf)
                qi = np.argmin(tq, axis=0)
                tqq = np.min(tq, axis=0)
                closer = tqq < best
                best = np.where(closer, tqq, best)
                best_id = np.where(closer, 6 + 6 * b + qi, best_id).astype(np.int32)
        return best, best_id

    def clearance(self, points: F64, *, room: bool = True) -> F64:
        """Distance of points to the nearest surface (negative inside a box or outside the room).

        Exact: signed distance to the room walls and the boxes, unsigned distance to the
        quadrilaterals. Used to check free space and as an independent ray-marching reference.
        Like every distance it changes by at most as much as the points move.

        Args:
            points: (N, 3) in ``{W}``.
            room: count the room's walls, floor and ceiling; False: only the objects inside
                (``inf`` for an empty room).

        Returns:
            (N,) metres.
        """
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if room:
            out = np.minimum(p - self.room_min, self.room_max - p).min(axis=1)
        else:
            out = np.full(p.shape[0], np.inf)
        if self.num_boxes:
            local = np.einsum("nbi,bij->nbj", p[:, None, :] - self.box_center, self.box_rotation)
            q = np.abs(local) - self.box_half
            outside = np.linalg.norm(np.maximum(q, 0.0), axis=2)
            inside = np.minimum(q.max(axis=2), 0.0)
            out = np.minimum(out, (outside + inside).min(axis=1))
        n_q, off_q, m_q = self._quad_geometry()
        if n_q.shape[0]:
            v = self.quad_vertices
            sd = p @ n_q.T + off_q  # (N, Q)
            proj = p[:, None, :] - sd[..., None] * n_q
            rel = proj[:, :, None, :] - v[None]
            inside_q = (np.einsum("nqji,qji->nqj", rel, m_q) >= 0).all(axis=2)
            # Distance to the edges (segments) for points projecting outside.
            a = v[None]  # (1, Q, 4, 3)
            e = np.roll(v, -1, axis=1)[None] - a
            ap = p[:, None, None, :] - a
            s = np.clip(np.sum(ap * e, -1) / np.sum(e * e, -1), 0.0, 1.0)
            d_edge = np.linalg.norm(ap - s[..., None] * e, axis=-1).min(axis=2)
            dq = np.where(inside_q, np.abs(sd), d_edge)
            out = np.minimum(out, dq.min(axis=1))
        return out


def _box(
    center: tuple[float, float, float],
    half: tuple[float, float, float],
    rpy_deg: tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> tuple[F64, F64, F64]:
    from scipy.spatial.transform import Rotation

    rot = Rotation.from_euler("ZYX", rpy_deg[::-1], degrees=True).as_matrix()
    return np.asarray(center, float), rot, np.asarray(half, float)


def _clutter(room_min: F64, room_max: F64) -> list[tuple[F64, F64, F64]]:
    """Fixed pseudo-random clutter that gives LiDAR odometry edges and corners to lock on.

    Wall-mounted boxes (within 1 m of the walls, any height, yawed and tilted up to 25/15 deg),
    ceiling ducts (above 7.6 m) and low floor boxes (below 0.4 m, under every trajectory).
    """
    rng = np.random.default_rng(20240611)
    out = []
    for wall in range(4):
        axis, side = divmod(wall, 2)  # axis 0: x walls, 1: y walls
        for _ in range(WALL_CLUTTER_PER_WALL):
            depth = rng.uniform(0.15, 0.6)
            along = rng.uniform(0.3, 1.4)
            height = rng.uniform(0.3, 1.4)
            c = np.empty(3)
            other = 1 - axis
            c[other] = rng.uniform(room_min[other] + 0.8, room_max[other] - 0.8)
            wall_pos = room_max[axis] if side else room_min[axis]
            c[axis] = wall_pos + (-1 if side else 1) * rng.uniform(0.0, 0.6)
            c[2] = rng.uniform(0.3, 9.0)
            hs = np.empty(3)
            hs[axis], hs[other], hs[2] = depth / 2, along / 2, height / 2
            rpy = (rng.uniform(-15, 15), rng.uniform(-15, 15), rng.uniform(-25, 25))
            out.append(_box((float(c[0]), float(c[1]), float(c[2])), (hs[0], hs[1], hs[2]), rpy))
    for _ in range(4):
        center = (rng.uniform(-2.5, 7.5), rng.uniform(1.0, 9.0), rng.uniform(8.3, 9.4))
        half = (rng.uniform(0.1, 0.3), rng.uniform(0.8, 2.0), rng.uniform(0.1, 0.3))
        out.append(_box(center, half, (0.0, 0.0, rng.uniform(0, 180))))
    for _ in range(6):
        h = rng.uniform(0.1, 0.2)
        center = (rng.uniform(-2.5, 7.5), rng.uniform(1.0, 9.0), h)
        half = (rng.uniform(0.2, 0.6), rng.uniform(0.2, 0.6), h)
        out.append(_box(center, half, (0.0, 0.0, rng.uniform(0, 90))))
    return out


def default_world() -> World:
    """The room used by every scenario (see the module docstring for its layout)."""
    room_min = np.array([-3.5, 0.0, 0.0])
    room_max = np.array([8.5, 10.0, 10.0])
    boxes = [
        _box((-2.85, 0.75, 0.6), (0.65, 0.75, 0.6)),  # corner box on the floor
        _box((6.25, 9.15, 1.0), (0.75, 0.85, 1.0)),  # box against the far wall
        _box((7.5, 2.3, 5.0), (0.3, 0.3, 5.0)),  # pillar
        _box((-2.5, 7.8, 5.0), (0.3, 0.3, 5.0), (0.0, 0.0, 30.0)),  # pillar rotated 30 deg
        _box((2.5, 9.6, 3.5), (1.0, 0.4, 0.5)),  # wall shelf
        _box((-1.2, 1.2, 0.45), (0.6, 0.4, 0.45), (0.0, 0.0, 35.0)),  # rotated floor box
        _box((1.0, 5.0, 9.0), (0.3, 3.0, 0.3)),  # ceiling beam
        _box((-2.6, 4.0, 4.5), (0.4, 0.4, 0.4), (30.0, 20.0, 40.0)),  # floating tilted cube
        *_clutter(room_min, room_max),
    ]
    quads = np.array(
        [
            # ceiling chamfer along the x = 8.5 wall (normal ~ (-1, 0, -1))
            [[8.5, 0.0, 7.0], [8.5, 10.0, 7.0], [5.5, 10.0, 10.0], [5.5, 0.0, 10.0]],
            # ceiling chamfer along the y = 10 wall (normal ~ (0, -1, -0.8))
            [[-3.5, 10.0, 7.5], [8.5, 10.0, 7.5], [8.5, 8.0, 10.0], [-3.5, 8.0, 10.0]],
            # floor ramp at the x = 8.5 wall
            [[7.0, 3.0, 0.0], [7.0, 7.0, 0.0], [8.5, 7.0, 2.5], [8.5, 3.0, 2.5]],
            # board leaning on the y = 0 wall
            [[0.5, 0.0, 4.5], [4.0, 0.0, 4.5], [4.0, 1.2, 0.0], [0.5, 1.2, 0.0]],
            # diagonal vertical panel in the (-3.5, 10) corner
            [[-3.5, 8.5, 0.0], [-2.0, 10.0, 0.0], [-2.0, 10.0, 6.0], [-3.5, 8.5, 6.0]],
            # diagonal vertical panel in the (8.5, 0) corner
            [[7.0, 0.0, 0.0], [8.5, 1.5, 0.0], [8.5, 1.5, 5.0], [7.0, 0.0, 5.0]],
        ]
    )
    return World(
        room_min=room_min,
        room_max=room_max,
        box_center=np.stack([b[0] for b in boxes]),
        box_rotation=np.stack([b[1] for b in boxes]),
        box_half=np.stack([b[2] for b in boxes]),
        quad_vertices=quads,
    )
