"""The colliders of a scene on the host: one BVH mesh, poses, and the color field's
upkeep (``ColliderSet``); the kernels they drive live in ``sim/colliders.py``."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
import trimesh
import warp as wp

from .boundary import BOUNDARY_IDS
from .colliders import (
    color_particles,
    FAR,
    NODE_BAND,
    NODE_RANGE,
    PARTICLE_BAND,
    ColliderArrays,
    ColliderBody,
    ColorField,
    color_node_box,
    face_clearance,
    color_node_range,
)
from .face_cells import build_face_cells, no_face_cells
from .grid import BLOCK_NODES, Grid

# two triangles meeting at more than this are a crease: the plane of node_color.py
# stops there (over a cell, 3 degrees put the plane ~0.05 cells off the surface)
CREASE_DEGREES = 3.0

wp.set_module_options({"enable_backward": False})


@wp.kernel
def transform_vertices(rest: wp.array(dtype=wp.vec3), vertex_body: wp.array(dtype=wp.int32),
                       rot: wp.array(dtype=wp.mat33), offset: wp.array(dtype=wp.vec3),
                       points: wp.array(dtype=wp.vec3)):
    v = wp.tid()
    b = vertex_body[v]
    points[v] = rot[b] * rest[v] + offset[b]


class Motion(Protocol):
    """What the solver needs of a collider's motion (see ``abmpm.geometry.motion``):
    ``pose(t)`` with ``rotation`` (3x3), ``offset`` (x = R x_rest + offset),
    ``pivot``, ``velocity`` and ``omega``; ``static`` if it never moves."""

    static: bool

    def pose(self, t: float): ...


@dataclass
class RigidBody:
    """One collider as the solver sees it: a rest mesh, its contact law and its motion."""

    vertices: np.ndarray  # (V, 3) at rest
    faces: np.ndarray  # (F, 3)
    motion: Motion
    boundary: str = "separate"  # sticky, slip or separate
    friction: float = 0.0  # Coulomb coefficient
    separation: float = 0.0  # separating speed c of paper Eq. 23, m/s


class ColliderSet:
    """All rigid colliders of a scene: one BVH mesh, per-body motion and boundary type."""

    def __init__(self, bodies: list[RigidBody], device, cpic: bool = True):
        self.device = device
        self.bodies = bodies
        verts, faces, vbody, fbody = [], [], [], []
        base = 0
        for b, body in enumerate(bodies):
            verts.append(np.asarray(body.vertices, dtype=np.float64))
            faces.append(np.asarray(body.faces, dtype=np.int64) + base)
            vbody.append(np.full(len(body.vertices), b, np.int32))
            fbody.append(np.full(len(body.faces), b, np.int32))
            base += len(body.vertices)
        self.rest = np.concatenate(verts)
        self.faces = np.concatenate(faces).astype(np.int32)
        self.vertex_body = np.concatenate(vbody)
        self.motions = [body.motion for body in bodies]
        self.static = all(m.static for m in self.motions)
        self._rest_d = wp.array(self.rest.astype(np.float32), dtype=wp.vec3, device=device)
        self._vbody_d = wp.array(self.vertex_body, dtype=wp.int32, device=device)
        self.mesh = wp.Mesh(
            points=wp.array(self.rest.astype(np.float32), dtype=wp.vec3, device=device),
            indices=wp.array(self.faces.ravel(), dtype=wp.int32, device=device),
        )
        self.arrays = ColliderArrays()
        self.arrays.enabled = 1
        self.arrays.cpic = int(cpic)
        self.arrays.mesh = self.mesh.id
        self.face_body_host = np.concatenate(fbody)
        self.arrays.face_body = wp.array(self.face_body_host, dtype=wp.int32, device=device)
        # the rims and creases, for node_color.py's planes and faces; static colliders
        # only (a moving collider's field is rebuilt every substep: no time for a second
        # query, and its rims move with it)
        boundary, creases = rim_edges(self.rest, self.faces) if self.static else (None, None)
        self.rims = edge_mesh(self.rest, np.concatenate([boundary, creases]), device) if self.static else None
        self.arrays.rims = self.rims.id if self.rims is not None else wp.uint64(0)
        self.arrays.face_clear = self._face_clearance(boundary, device)
        self.arrays.cells = no_face_cells(device)  # index_faces builds them
        self.time = None
        self._region = {}  # grid id -> node box last colored
        self.set_time(0.0)

    def _face_clearance(self, boundary: np.ndarray | None, device) -> wp.array:
        """Per triangle, a lower bound of its distance to the nearest of the ``boundary``
        edges (rims) of any collider, for node_color.py's nearby faces; zero (never
        enough) where the colliders move (``boundary`` None)."""
        n = len(self.faces)
        if boundary is None:
            return wp.zeros(n, dtype=float, device=device)
        rims = edge_mesh(self.rest, boundary, device)
        if rims is None:  # closed surfaces: no rim anywhere
            return wp.full(n, FAR, dtype=float, device=device)
        clear = wp.zeros(n, dtype=float, device=device)
        wp.launch(face_clearance, n, [self.mesh.id, rims.id, clear], device=device)
        return clear

    def index_faces(self, grid: Grid, launcher) -> None:
        """Static colliders in CPIC mode: per cell of ``grid`` (the coarse grid), the
        triangles that can be closest to a point in it, for the closest-point queries of
        the particles of every level (bounded by PARTICLE_BAND coarse cells; ``face_cells.py``).
        Moving colliders keep the BVH alone (their lists would change every substep)."""
        if self.static and self.arrays.cpic:
            cells = [int(d) - 1 for d in grid.dims]
            self.arrays.cells = build_face_cells(self.mesh, grid.origin, grid.dx, cells, PARTICLE_BAND * grid.dx, launcher)

    @property
    def triangle_count(self) -> int:
        return len(self.faces)

    def poses(self, t: float) -> list:
        return [m.pose(t) for m in self.motions]

    def set_time(self, t: float) -> None:
        """Move the colliders to time t: vertices, BVH refit, Eq. 22 velocities."""
        poses = self.poses(t)
        bodies = []
        for body, p in zip(self.bodies, poses):
            b = ColliderBody()
            b.boundary = BOUNDARY_IDS[body.boundary]
            b.friction = float(body.friction)
            b.separation = float(body.separation)
            b.velocity = wp.vec3(*p.velocity)
            b.omega = wp.vec3(*p.omega)
            b.pivot = wp.vec3(*p.pivot)
            bodies.append(b)
        self.arrays.bodies = wp.array(bodies, dtype=ColliderBody, device=self.device)
        if self.time is not None and self.static:
            return
        rot = wp.array(np.stack([p.rotation for p in poses]).astype(np.float32), dtype=wp.mat33, device=self.device)
        off = wp.array(np.stack([p.offset for p in poses]).astype(np.float32), dtype=wp.vec3, device=self.device)
        wp.launch(transform_vertices, dim=len(self.rest), inputs=[self._rest_d, self._vbody_d, rot, off],
                  outputs=[self.mesh.points], device=self.device)
        self.mesh.refit()
        self.time = t
        self._poses = poses

    def vertices(self, t: float | None = None) -> np.ndarray:
        poses = self._poses if t is None else self.poses(t)
        out = np.empty_like(self.rest)
        for b, p in enumerate(poses):
            sel = self.vertex_body == b
            out[sel] = self.rest[sel] @ p.rotation.T + p.offset
        return out

    def body_meshes(self, t: float | None = None) -> list[trimesh.Trimesh]:
        """One world-space mesh per collider at time t (default: the current pose)."""
        v = self.vertices(t)
        fb = self.face_body_host
        return [trimesh.Trimesh(v, self.faces[fb == b], process=False) for b in range(len(self.bodies))]

    def triangles(self, t: float | None = None) -> np.ndarray:
        """(M, 3, 3) world-space triangles, for rendering."""
        return self.vertices(t)[self.faces]

    def node_box(self, grid: Grid) -> tuple[np.ndarray, np.ndarray]:
        """Node index box covering the colliders plus the color band."""
        v = self.vertices()
        o = grid.origin
        pad = NODE_BAND + 1
        lo = np.floor((v.min(axis=0) - o) / grid.dx - pad).astype(int)
        hi = np.ceil((v.max(axis=0) - o) / grid.dx + pad).astype(int) + 1
        dims = np.array(grid.dims)
        return np.clip(lo, 0, dims), np.clip(hi, 0, dims)

    def move(self, t: float, grids: list[Grid], launcher) -> bool:
        """To time ``t`` with every grid's color field, unless static and placed
        already; whether anything was done."""
        if self.static and self.time is not None:
            return False
        self.set_time(t)
        for g in grids:
            self.color(g, launcher)
        return True

    def color_particles(self, state, grids: list[Grid], launcher, min_id: int = -1) -> None:
        """CPIC color of every particle (of those with an id from ``min_id`` on) from
        its own grid; later steps update it in G2P."""
        for g in grids:
            launcher.launch(color_particles, state.count,
                            [state.x, state.level, state.id, min_id, self.arrays, g.spec, g.color,
                             state.surface_point, state.surface_side, state.surface_body])

    def color(self, grid: Grid, launcher, first_slot: int = 0) -> None:
        """(Re)build the color distance field of a grid around the colliders: on a
        dense grid the node box around them (and what they covered before they
        moved), on a sparse grid the active blocks from ``first_slot`` on. A node
        costs a closest-point query (~1 us on a CPU core), so ``launcher`` (the
        solver's :class:`~abmpm.sim.parallel.Launcher`) shares them out over its
        threads: a moving collider rebuilds the field before every substep."""
        if grid.sparse:
            count = (grid.active_slots - first_slot) * BLOCK_NODES
            launcher.launch(color_node_range, count, [self.arrays, grid.spec, grid.color],
                            start=first_slot * BLOCK_NODES, label=f"color {grid.name}", min_range=NODE_RANGE)
            return
        lo, hi = self.node_box(grid)
        prev = self._region.get(id(grid))
        if prev is not None:
            lo, hi = np.minimum(prev[0], lo), np.maximum(prev[1], hi)
        self._region[id(grid)] = (lo, hi)
        shape = [int(s) for s in hi - lo]
        if min(shape) <= 0:
            return
        launcher.launch(color_node_box, shape[0] * shape[1] * shape[2],
                        [self.arrays, grid.spec, wp.vec3i(*[int(a) for a in lo]), wp.vec3i(*shape), grid.color],
                        label=f"color {grid.name}", min_range=NODE_RANGE)


def rim_edges(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The edges of a triangle mesh where it stops being one plane, as vertex pairs:
    boundary edges (one triangle: rims of sheets and holes) and creases (two triangles
    meeting at more than CREASE_DEGREES)."""
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    boundary = mesh.edges_sorted[trimesh.grouping.group_rows(mesh.edges_sorted, require_count=1)]
    creases = mesh.face_adjacency_edges[mesh.face_adjacency_angles > np.radians(CREASE_DEGREES)]
    return boundary.reshape(-1, 2), creases.reshape(-1, 2)


def edge_mesh(vertices: np.ndarray, edges: np.ndarray, device) -> wp.Mesh | None:
    """Edges (vertex pairs) as a BVH mesh of sliver triangles (a, b and b moved off the
    edge by 1e-4 of its length: Warp's query skips degenerate triangles). None when
    there is none."""
    if len(edges) == 0:
        return None
    a, b = vertices[edges[:, 0]], vertices[edges[:, 1]]
    e = b - a
    # any direction across the edge: e x (the axis least aligned with it)
    axis = np.eye(3)[np.argmin(np.abs(e), axis=1)]
    off = np.cross(e, axis)
    off *= (1e-4 * np.linalg.norm(e, axis=1) / np.maximum(np.linalg.norm(off, axis=1), 1e-30))[:, None]
    points = np.concatenate([a, b, b + off]).astype(np.float32)
    k = len(edges)
    tris = np.stack([np.arange(k), np.arange(k) + k, np.arange(k) + 2 * k], axis=1)
    return wp.Mesh(points=wp.array(points, dtype=wp.vec3, device=device),
                   indices=wp.array(tris.astype(np.int32).ravel(), dtype=wp.int32, device=device))


def empty_colliders(device) -> ColliderArrays:
    s = ColliderArrays()
    s.enabled = 0
    s.cpic = 0
    s.mesh = 0
    s.face_body = wp.zeros(1, dtype=wp.int32, device=device)
    s.bodies = wp.zeros(1, dtype=ColliderBody, device=device)
    s.rims = wp.uint64(0)
    s.face_clear = wp.zeros(1, dtype=float, device=device)
    s.cells = no_face_cells(device)
    return s


def without_face_cells(arrays: ColliderArrays) -> ColliderArrays:
    """The same colliders with no per-cell lists: every closest point from the BVH
    (the benchmarks' and the tests' reference)."""
    bvh = ColliderArrays()
    for name in ColliderArrays.vars:
        setattr(bvh, name, getattr(arrays, name))
    bvh.cells = no_face_cells(arrays.face_body.device)
    return bvh


def color_field(n: int, device) -> ColorField:
    """Color field for n nodes of storage, all far from every collider."""
    f = ColorField()
    f.dist = wp.full(n, FAR, dtype=float, device=device)
    f.dir = wp.zeros(n, dtype=wp.vec3, device=device)
    f.body = wp.full(n, -1, dtype=wp.int32, device=device)
    f.rim = wp.zeros(n, dtype=float, device=device)
    f.face = wp.full(n, -1, dtype=wp.int32, device=device)
    return f


def grow_color_field(f: ColorField, n: int) -> ColorField:
    """A color field with room for n nodes, keeping the existing entries."""
    if f.dist.shape[0] >= n:
        return f
    g = color_field(n, f.dist.device)
    for name in ("dist", "dir", "body", "rim", "face"):
        wp.copy(getattr(g, name), getattr(f, name), count=getattr(f, name).shape[0])
    return g

