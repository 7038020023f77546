"""Per-cell lists of the collider triangles that can be closest (issue 23; docs/method.md,
"The triangles a cell can be closest to").

A particle near a collider asks for its closest surface point (``colliders.color_point``)
wherever the nodes' field cannot vouch for it (``node_color.py``): on a curved glass
that is most particles within a cell or two of the surface, and the BVH's query costs
~1 us each on a CPU core. For static colliders the surface never moves, so the
question "which triangles can be closest to a point of this cell?" has one answer per
cell, computed once:

* a cell of edge h (half a coarse cell) with centre o and half-diagonal r, whose
  centre lies ``dmin`` from the surface. A point x of the cell lies within dmin + r of
  the surface (through o's closest point), so its closest triangle t has
  |x - t| <= dmin + r and |o - t| <= dmin + 2r; and a query bounded by B <= ``band``
  only looks at triangles with |o - t| <= B + r. The cell lists every triangle with
  |o - t| <= min(dmin + 2r, band + r), sorted by |o - t|.
* A query scans its cell's list and stops at the first triangle with |o - t| - |x - o|
  at least the best distance so far (no later one can be closer: |x - t| >= |o - t| -
  |x - o|). On the way it passes over a triangle whose disc (the circle around it in
  its plane, centred on its centroid) lies at least the best distance from x: with h
  x's height over the plane and r its distance from the disc within the plane,
  |x - t|^2 >= h^2 + r^2. Four loads and a dot product instead of the triangle's
  corners and its closest point: the paper hourglass's queries 1.6-2.5x cheaper.

So the answer is the BVH's, exactly (the same closest distance; measured to 1e-5 cells
on every query of the paper hourglass), at 0.3 of its cost there for a coarse
particle and 0.46 for a fine one (docs/benchmarks.md, "The triangles a cell can be
closest to"). Points outside the listed cells, the nodes' colors (colliders.color_point
says why) and moving colliders go to the BVH.
"""

from __future__ import annotations

import numpy as np
import warp as wp

wp.set_module_options({"enable_backward": False})

CELLS_PER_COARSE = 2  # list cells per coarse cell and axis (finer: shorter lists, 8x the memory)
MAX_ENTRIES = 32_000_000  # more list entries than this (8 bytes each) and the BVH stays
# Longer lists than this on average and the BVH stays (~19 ns a triangle looked at).
# Measured (docs/benchmarks.md, "The triangles a cell can be closest to"): the paper
# hourglass's glass (mean 31) its G2P 0.77x the BVH's; the paper panel (63) its step the
# BVH's (fine G2P 0.89x, coarse 1.11x) for 100 MB; the quick hourglass's glass (176) its
# step 1.25x the BVH's (measured before the tighter stop)
MAX_MEAN_LIST = 40
SLACK = 1.0e-4  # of a cell's edge: a point's cell lookup may round across the cell's face
BAND_SLACK = 1.0e-4  # relative: the lists answer bounds this much above the band asked for
CELL_RANGE = 256  # cells worth a thread of their own when building (a query and a box search each)
SAMPLE_CELLS = 4096  # cells counted first, evenly spread, to tell whether the lists would pay
NO_LIST = wp.constant(-2)  # closest_face: the point's cell has no list (ask the BVH)
# of the best distance, and of a list cell's edge: a triangle is passed over when x's distance
# to the disc around it exceeds the best so far by this much (float32 round-off of the bound)
DISC_SLACK = 1.0e-4
# twice a triangle's area over its longest edge squared below which it has no plane of its own
FLAT_AREA = 1.0e-6


@wp.struct
class FaceCells:
    """The lists, on a grid of cells CELLS_PER_COARSE times finer than the coarse grid."""

    enabled: int
    origin: wp.vec3  # the coarse grid's node (0, 0, 0)
    dx: float  # the coarse cell
    sub: int  # list cells per coarse cell and axis
    h: float  # a list cell's edge, dx / sub
    reach: float  # half its diagonal plus the lookup's slack
    band: float  # queries bounded by at most this are answered exactly
    dims: wp.vec3i  # coarse cells per axis
    first: wp.array(dtype=wp.int32)  # coarse cell -> slot of its first list cell (-1: no lists)
    start: wp.array(dtype=wp.int32)  # list cell slot -> its first entry (start[slot + 1]: its end)
    face: wp.array(dtype=wp.int32)  # entries: a triangle ...
    near: wp.array(dtype=float)  # ... and its distance from the cell's centre, ascending per cell
    disc: wp.array(dtype=wp.vec4)  # per triangle: the centre and radius of a circle around it in its plane
    normal: wp.array(dtype=wp.vec3)  # per triangle: its unit normal


@wp.func(inline=True)
def face_corners(mesh: wp.uint64, face: int):
    # the three corners of triangle ``face`` of a Warp mesh
    return wp.mesh_get_point(mesh, 3 * face), wp.mesh_get_point(mesh, 3 * face + 1), \
        wp.mesh_get_point(mesh, 3 * face + 2)


@wp.func
def closest_on_triangle(p: wp.vec3, a: wp.vec3, b: wp.vec3, c: wp.vec3):
    """The point of triangle abc closest to p: the face, an edge or a vertex, whichever
    Voronoi region of the triangle p projects into (Ericson, Real-Time Collision
    Detection, Section 5.1.5)."""
    ab = b - a
    ac = c - a
    d1 = wp.dot(ab, p - a)
    d2 = wp.dot(ac, p - a)
    if d1 <= 0.0 and d2 <= 0.0:
        return a
    d3 = wp.dot(ab, p - b)
    d4 = wp.dot(ac, p - b)
    if d3 >= 0.0 and d4 <= d3:
        return b
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        return a + (d1 / (d1 - d3)) * ab
    d5 = wp.dot(ab, p - c)
    d6 = wp.dot(ac, p - c)
    if d6 >= 0.0 and d5 <= d6:
        return c
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        return a + (d2 / (d2 - d6)) * ac
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and d4 - d3 >= 0.0 and d5 - d6 >= 0.0:
        return b + ((d4 - d3) / ((d4 - d3) + (d5 - d6))) * (c - b)
    den = 1.0 / (va + vb + vc)
    return a + (vb * den) * ab + (vc * den) * ac


@wp.func(inline=True)
def triangle_distance(mesh: wp.uint64, face: int, x: wp.vec3):
    a, b, c = face_corners(mesh, face)
    return wp.length(closest_on_triangle(x, a, b, c) - x)


@wp.func
def cell_slot(fc: FaceCells, x: wp.vec3):
    """The list cell holding x (-1 where there is none) and its centre."""
    q = (x - fc.origin) / fc.dx
    c = wp.vec3i(int(wp.floor(q[0])), int(wp.floor(q[1])), int(wp.floor(q[2])))
    if c[0] < 0 or c[1] < 0 or c[2] < 0 or c[0] >= fc.dims[0] or c[1] >= fc.dims[1] or c[2] >= fc.dims[2]:
        return -1, x
    s = fc.first[(c[0] * fc.dims[1] + c[1]) * fc.dims[2] + c[2]]
    if s < 0:
        return -1, x
    top = fc.sub - 1
    i = wp.clamp(int(wp.floor((q[0] - float(c[0])) * float(fc.sub))), 0, top)
    j = wp.clamp(int(wp.floor((q[1] - float(c[1])) * float(fc.sub))), 0, top)
    k = wp.clamp(int(wp.floor((q[2] - float(c[2])) * float(fc.sub))), 0, top)
    cell = c * fc.sub + wp.vec3i(i, j, k)
    return s + (i * fc.sub + j) * fc.sub + k, fc.origin + (wp.vec3(float(cell[0]), float(cell[1]), float(cell[2])) + wp.vec3(0.5)) * fc.h


@wp.func
def closest_face(fc: FaceCells, mesh: wp.uint64, x: wp.vec3, bound: float):
    """The triangle closest to x within ``bound`` (<= ``band``) and its point: (-1, ...)
    when none is that close, (NO_LIST, ...) when x's cell has no list."""
    s, o = cell_slot(fc, x)
    point = wp.vec3(0.0)
    if s < 0:
        return NO_LIST, point
    best = float(bound)
    hit = int(-1)
    # |x - t| >= |o - t| - |x - o|: x's own offset from the centre, not the cell's half-diagonal
    # (the same answer; 1.6-1.7x fewer triangles looked at), plus the lookup's slack
    lim = wp.length(x - o) + SLACK * fc.h
    for t in range(fc.start[s], fc.start[s + 1]):
        if fc.near[t] - lim >= best:
            break  # sorted: no later triangle comes closer to x
        f = fc.face[t]
        if not beyond_disc(fc, f, x, best):
            a, b, c = face_corners(mesh, f)
            q = closest_on_triangle(x, a, b, c)
            d = wp.length(q - x)
            if d < best:
                best = d
                hit = f
                point = q
    return hit, point


@wp.func(inline=True)
def beyond_disc(fc: FaceCells, f: int, x: wp.vec3, best: float):
    """Whether x's distance to the disc around triangle f, in f's plane, (a lower bound of
    its distance to f) reaches ``best``, beyond the slack of float32 round-off."""
    disc = fc.disc[f]
    w = x - wp.vec3(disc[0], disc[1], disc[2])
    h = wp.dot(w, fc.normal[f])
    r = wp.max(wp.sqrt(wp.max(wp.dot(w, w) - h * h, 0.0)) - disc[3], 0.0)
    lim = best * (1.0 + DISC_SLACK) + DISC_SLACK * fc.h
    return h * h + r * r >= lim * lim


@wp.func(inline=True)
def list_cell(fc: FaceCells, coarse: wp.array(dtype=wp.int32), slot: int):
    # centre of list cell ``slot`` (slots come in blocks of sub^3 per listed coarse cell)
    n = fc.sub * fc.sub * fc.sub
    c = coarse[slot // n]
    local = slot % n
    cell = wp.vec3i(c // (fc.dims[1] * fc.dims[2]), (c // fc.dims[2]) % fc.dims[1], c % fc.dims[2]) * fc.sub \
        + wp.vec3i(local // (fc.sub * fc.sub), (local // fc.sub) % fc.sub, local % fc.sub)
    return fc.origin + (wp.vec3(float(cell[0]), float(cell[1]), float(cell[2])) + wp.vec3(0.5)) * fc.h


@wp.kernel
def near_coarse_cells(first: int, mesh: wp.uint64, fc: FaceCells, lo: wp.vec3i, shape: wp.vec3i,
                      near: wp.array(dtype=wp.int32)):
    # 1 for a coarse cell of the box (lo, shape) some point of which lies within the band of a surface
    t = first + wp.tid()
    c = lo + wp.vec3i(t // (shape[1] * shape[2]), (t // shape[2]) % shape[1], t % shape[2])
    o = fc.origin + (wp.vec3(float(c[0]), float(c[1]), float(c[2])) + wp.vec3(0.5)) * fc.dx
    q = wp.mesh_query_point_no_sign(mesh, o, fc.band + 0.8661 * fc.dx + fc.reach)
    near[t] = int(q.result)


@wp.func
def list_radius(fc: FaceCells, mesh: wp.uint64, o: wp.vec3):
    # min(dmin + 2r, band + r) of the module docstring; -1 with no triangle within band + r
    q = wp.mesh_query_point_no_sign(mesh, o, fc.band + fc.reach)
    if not q.result:
        return -1.0
    dmin = wp.length(wp.mesh_eval_position(mesh, q.face, q.u, q.v) - o)
    return wp.min(dmin + 2.0 * fc.reach, fc.band + fc.reach)


@wp.kernel
def count_cell_faces(first: int, mesh: wp.uint64, fc: FaceCells, coarse: wp.array(dtype=wp.int32), stride: int,
                     count: wp.array(dtype=wp.int32)):
    # the list length of every ``stride``-th cell (a sample first: is it worth building?)
    t = first + wp.tid()
    o = list_cell(fc, coarse, t * stride)
    R = list_radius(fc, mesh, o)
    n = int(0)
    if R >= 0.0:
        box = wp.mesh_query_aabb(mesh, o - wp.vec3(R), o + wp.vec3(R))
        f = int(0)
        while wp.mesh_query_aabb_next(box, f):
            if triangle_distance(mesh, f, o) <= R:
                n += 1
    count[t] = n


@wp.kernel
def fill_cell_faces(first: int, mesh: wp.uint64, fc: FaceCells, coarse: wp.array(dtype=wp.int32)):
    # the same triangles as count_cell_faces, then sorted by distance (insertion sort: lists are short)
    s = first + wp.tid()
    o = list_cell(fc, coarse, s)
    R = list_radius(fc, mesh, o)
    if R < 0.0:
        return
    lo = fc.start[s]
    n = lo
    box = wp.mesh_query_aabb(mesh, o - wp.vec3(R), o + wp.vec3(R))
    f = int(0)
    while wp.mesh_query_aabb_next(box, f):
        d = triangle_distance(mesh, f, o)
        if d <= R:
            k = n
            while k > lo and fc.near[k - 1] > d:
                fc.near[k] = fc.near[k - 1]
                fc.face[k] = fc.face[k - 1]
                k -= 1
            fc.near[k] = d
            fc.face[k] = f
            n += 1


def no_face_cells(device) -> FaceCells:
    """Lists that answer nothing (every query goes to the BVH)."""
    fc = FaceCells()
    fc.enabled = 0
    fc.sub = 1
    fc.dims = wp.vec3i(0, 0, 0)
    for name in ("first", "start", "face"):
        setattr(fc, name, wp.zeros(1, dtype=wp.int32, device=device))
    fc.near = wp.zeros(1, dtype=float, device=device)
    fc.disc = wp.zeros(1, dtype=wp.vec4, device=device)
    fc.normal = wp.zeros(1, dtype=wp.vec3, device=device)
    return fc


def _count(mesh: wp.Mesh, fc: FaceCells, coarse: wp.array, launcher, stride: int, n: int) -> np.ndarray:
    count = wp.zeros(max(n, 1), dtype=wp.int32, device=mesh.device)
    launcher.launch(count_cell_faces, n, [mesh.id, fc, coarse, stride, count], label="face cells", min_range=CELL_RANGE)
    return count.numpy()[:n]


def _worth_building(counts: np.ndarray, stride: int, max_entries: int) -> bool:
    # every stride-th cell's list length: the entries within the limit, the lists short enough
    entries = int(counts.sum())
    return 0 < entries * stride <= max_entries and entries <= MAX_MEAN_LIST * np.count_nonzero(counts)


def build_face_cells(mesh: wp.Mesh, origin, dx: float, cells, band: float, launcher,
                     sub: int = CELLS_PER_COARSE, max_entries: int = MAX_ENTRIES) -> FaceCells:
    """The lists of a static mesh over a coarse grid of ``cells`` cells of edge ``dx``
    from ``origin``, exact for queries bounded by ``band``; no lists (every query to the
    BVH) when they would hold more than ``max_entries`` entries, or more than
    MAX_MEAN_LIST triangles a cell on average (triangles much smaller than the cells)."""
    device = mesh.device
    fc = no_face_cells(device)
    fc.origin = wp.vec3(*[float(a) for a in origin])
    fc.dx = float(dx)
    fc.sub = int(sub)
    fc.h = float(dx) / sub
    fc.reach = (0.5 * np.sqrt(3.0) + SLACK) * fc.h
    fc.band = float(band) * (1.0 + BAND_SLACK)  # a kernel's float32 PARTICLE_BAND * dx may round above it
    fc.dims = wp.vec3i(*[int(c) for c in cells])
    # the coarse cells around the mesh (its box grown by the band) are the only candidates
    points = mesh.points.numpy()
    pad = band / dx + 1.0
    lo = np.clip(np.floor((points.min(axis=0) - np.asarray(origin)) / dx - pad), 0, cells).astype(int)
    hi = np.clip(np.ceil((points.max(axis=0) - np.asarray(origin)) / dx + pad), 0, cells).astype(int)
    shape = np.maximum(hi - lo, 0)
    near = wp.zeros(max(int(np.prod(shape)), 1), dtype=wp.int32, device=device)
    launcher.launch(near_coarse_cells, int(np.prod(shape)), [mesh.id, fc, wp.vec3i(*lo), wp.vec3i(*shape), near],
                    label="face cells", min_range=CELL_RANGE)
    box = np.flatnonzero(near.numpy()[:int(np.prod(shape))])
    c = np.stack(np.unravel_index(box, shape), axis=1) + lo if len(box) else np.zeros((0, 3), int)
    listed = np.ravel_multi_index(c.T, cells).astype(np.int32) if len(box) else np.zeros(0, np.int32)
    total = int(np.prod(cells))
    first = np.full(total, -1, np.int32)
    first[listed] = np.arange(len(listed), dtype=np.int32) * sub**3
    fc.first = wp.array(first, dtype=wp.int32, device=device)
    coarse = wp.array(listed, dtype=wp.int32, device=device)
    slots = len(listed) * sub**3
    # a sample of SAMPLE_CELLS cells first: lists that would not pay are not counted in full
    stride = max(1, slots // SAMPLE_CELLS) | 1  # odd: not the same corner of every coarse cell
    if stride > 1 and not _worth_building(_count(mesh, fc, coarse, launcher, stride, slots // stride), stride, max_entries):
        return no_face_cells(device)
    counts = _count(mesh, fc, coarse, launcher, 1, slots)
    if not _worth_building(counts, 1, max_entries):
        return no_face_cells(device)
    start = np.zeros(slots + 1, np.int64)
    np.cumsum(counts, out=start[1:])
    fc.start = wp.array(start.astype(np.int32), dtype=wp.int32, device=device)
    fc.face = wp.zeros(int(start[-1]), dtype=wp.int32, device=device)
    fc.near = wp.zeros(int(start[-1]), dtype=float, device=device)
    launcher.launch(fill_cell_faces, slots, [mesh.id, fc, coarse], label="face cells", min_range=CELL_RANGE)
    disc, normal = face_discs(points, mesh.indices.numpy())
    fc.disc = wp.array(disc, dtype=wp.vec4, device=device)
    fc.normal = wp.array(normal, dtype=wp.vec3, device=device)
    fc.enabled = 1
    return fc


def face_discs(points: np.ndarray, indices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per triangle: its centroid and the radius of the circle around it there (x, y, z, r),
    and its unit normal (zero for a degenerate triangle, whose disc is then a ball)."""
    tri = points[indices.reshape(-1, 3)].astype(np.float64)
    centre = tri.mean(axis=1)
    radius = np.linalg.norm(tri - centre[:, None, :], axis=2).max(axis=1)
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(normal, axis=1, keepdims=True)
    # a (nearly) collinear triangle's cross product is round-off pointing anywhere, and its
    # corners need not lie in that plane: it keeps the ball around it
    edge = np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2).max(axis=1, keepdims=True)
    normal = np.divide(normal, length, out=np.zeros_like(normal), where=length > FLAT_AREA * edge**2)
    disc = np.concatenate([centre, radius[:, None]], axis=1)
    return disc.astype(np.float32), normal.astype(np.float32)
