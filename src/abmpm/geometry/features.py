"""The feature-size criterion of the refined region (``criterion = "feature"``, the
default): refine where the free space is narrow, not wherever a boundary is.

The paper's detector (:mod:`abmpm.geometry.region`: Catmull-Clark + kernel density)
reads a zero-thickness sheet as 2.0 everywhere, so a whole plate, and all the
material resting on it, would be refined. Here each collider marked ``refine`` is
sampled about once per coarse cell; from every sample the free width is measured
across its free side (along the normal, and in the sheet's plane from a free edge),
to the nearest collider point within a cone or to the domain walls. Widths below
``gap_cells`` coarse cells mark the cells they cross: slits, holes and letters in a
panel, necks, a collider close to a wall, concave corners. Moving colliders also
mark their free edges and creases (a blade's edge moving through material).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from abmpm.geometry.subdivision import densify
from abmpm.geometry.topology import boundary_halfedges, feature_edges, halfedges, is_open

__all__ = ["CONE_DEG", "CONTACT_CELLS", "FEATURE_SPACING", "feature_cells", "feature_samples", "narrow_points"]


#: Spacing of the feature samples, in coarse cells.
FEATURE_SPACING = 1.0
#: Half-angle of the cone in which a sample looks for the surface across its free side.
CONE_DEG = 30.0
#: Free widths below this (coarse cells) are contacts or self-hits, not gaps.
CONTACT_CELLS = 0.25
#: Samples closer than these (in feature spacings) count once: sources per direction, targets
#: (on every built-in scene and plate case the marked cells are the same as without it).
SOURCE_BIN, TARGET_BIN = 0.25, 0.125


def feature_samples(mesh, spacing: float, open_surface: bool | None = None, moving: bool = False,
                    crease_angle_deg: float = 30.0):
    """Samples of one collider for the feature-size criterion (:func:`narrow_points`).

    The mesh is densified to edges of at most ``spacing`` (:func:`densify`, the surface
    does not move). Returns ``(targets, sources, directions, edges)``:

    * ``targets`` ``(T, 3)``: the vertices and free-edge midpoints, what a look across
      the free space can hit;
    * ``sources``/``directions`` ``(S, 3)``: where the free width is measured and along
      which unit direction: every triangle centroid along its normal (both normals for
      an open, two-sided surface; the outward one for a closed mesh, oriented by its
      signed volume), and every free-edge midpoint along the in-plane direction away
      from its face (across a hole, or towards whatever faces the rim);
    * ``edges`` ``(E, 3)``: points at most ``spacing`` apart along the free edges and
      creases (dihedral angle above ``crease_angle_deg``) of the input mesh, only when
      ``moving`` (a blade's cutting edges), else empty.
    """
    empty = np.zeros((0, 3))
    v0 = np.asarray(mesh.vertices, dtype=np.float64)
    f0 = np.asarray(mesh.faces, dtype=np.int64)
    if len(f0) == 0:
        return empty, empty, empty, empty
    if open_surface is None:
        open_surface = bool(is_open(mesh))
    v, t = densify(v0, f0, spacing)
    cross = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
    if not open_surface and np.einsum("ij,ij->", v[t[:, 0]], np.cross(v[t[:, 1]], v[t[:, 2]])) < 0:
        cross = -cross  # inward winding: make the normals point out of the solid
    norm = np.linalg.norm(cross, axis=1, keepdims=True)
    ok = norm[:, 0] > 0
    fn = np.divide(cross, norm, out=np.zeros_like(cross), where=norm > 0)
    centroid = v[t].mean(axis=1)
    src, dirs = [centroid[ok]], [fn[ok]]
    if open_surface:
        src.append(centroid[ok])
        dirs.append(-fn[ok])
    he = boundary_halfedges(t)
    targets = [v]
    if len(he):
        tail, head = halfedges(t)
        face = he // 3
        a, b = v[tail[he]], v[head[he]]
        mid = 0.5 * (a + b)
        out = np.cross(b - a, fn[face])
        out /= np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-300)
        out[np.einsum("ij,ij->i", out, centroid[face] - mid) > 0] *= -1.0
        good = ok[face]
        src.append(mid[good])
        dirs.append(out[good])
        targets.append(mid)
    edges = empty
    if moving:
        fe = feature_edges(v0, f0, crease_angle_deg)
        if len(fe):
            a, b = v0[fe[:, 0]], v0[fe[:, 1]]
            n = np.maximum(np.ceil(np.linalg.norm(b - a, axis=1) / spacing), 1).astype(np.int64)
            k = np.repeat(np.arange(len(fe)), n + 1)
            start = np.concatenate([[0], np.cumsum(n + 1)[:-1]])
            frac = (np.arange(len(k)) - start[k]) / n[k]
            edges = a[k] + frac[:, None] * (b - a)[k]
    return np.concatenate(targets), np.concatenate(src), np.concatenate(dirs), edges


def thin_samples(points, size: float, directions=None):
    """At most one sample per cube of side ``size`` (and, with ``directions``, per
    direction to 0.1 in each component): a mesh much finer than the samples' spacing
    (a sheet of a million triangles) measures the same widths with far fewer pairs of
    points. Returns (points, directions or None), the first sample of each cube kept."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(p) == 0:
        return p, directions
    key = np.floor(p / size).astype(np.int64)
    if directions is not None:
        key = np.concatenate([key, np.rint(np.asarray(directions) * 10.0).astype(np.int64)], axis=1)
    _, first = np.unique(key, axis=0, return_index=True)
    first.sort()
    return p[first], (None if directions is None else np.asarray(directions)[first])


def narrow_points(sources, directions, targets, gap: float, contact: float, tolerance: float,
                  walls=None, chunk: int = 4096) -> np.ndarray:
    """Points of the narrow free space: for each source, the free width w along its
    direction d is the nearest target ahead of it, i.e. at an axial distance a > ``contact``
    inside the cone of half-angle ``CONE_DEG`` about d (widened to a lateral distance
    ``tolerance``, so that a surface sampled ``tolerance / 0.6`` apart cannot slip
    between its samples), or the distance to the ``walls`` box ``(min, max)`` along d.
    Where ``contact < w < gap`` the source, the middle of its gap and the far side
    ``p + w d`` are returned. A source whose direction leaves the domain at once (a
    sheet touching a wall) is not a gap; widths up to ``contact`` are contacts or the
    source's own, curving surface."""
    p = np.asarray(sources, dtype=np.float64).reshape(-1, 3)
    d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    q = np.asarray(targets, dtype=np.float64).reshape(-1, 3)
    if len(p) == 0:
        return np.zeros((0, 3))
    w = np.full(len(p), np.inf)
    if walls is not None:
        lo, hi = (np.asarray(b, dtype=np.float64).reshape(3) for b in walls)
        with np.errstate(divide="ignore", invalid="ignore"):
            exit_t = np.where(d > 0, (hi - p) / d, np.where(d < 0, (lo - p) / d, np.inf)).min(axis=1)
        w = np.where(exit_t > contact, exit_t, -np.inf)  # -inf: leaves the domain at once
    if len(q):
        tan = np.tan(np.radians(CONE_DEG))
        tree = cKDTree(q)
        for s in range(0, len(p), chunk):
            ps, ds = p[s : s + chunk], d[s : s + chunk]
            pairs = cKDTree(ps).sparse_distance_matrix(tree, gap, output_type="ndarray")
            if len(pairs) == 0:
                continue
            i, j = pairs["i"], pairs["j"]
            r = q[j] - ps[i]
            a = np.einsum("ij,ij->i", r, ds[i])
            lat2 = np.maximum(np.einsum("ij,ij->i", r, r) - a * a, 0.0)
            hit = (a > contact) & (lat2 <= np.maximum(a * tan, tolerance) ** 2)
            best = np.full(len(ps), np.inf)
            np.minimum.at(best, i[hit], a[hit])
            seg = w[s : s + chunk]
            w[s : s + chunk] = np.where(seg > -np.inf, np.minimum(seg, best), seg)
    narrow = (w > contact) & (w < gap * (1.0 - 1e-6))  # a width of exactly gap (to rounding) is wide
    p, d, w = p[narrow], d[narrow], w[narrow, None]
    return np.concatenate([p, p + 0.5 * w * d, p + w * d])


def _point_cells(points, origin, dx: float, cell_dims) -> np.ndarray:
    """Cells containing the points; a point on a cell face marks the cells on both sides."""
    cells = np.zeros(tuple(int(c) for c in cell_dims), dtype=bool)
    x = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(x) == 0 or cells.size == 0:
        return cells
    u = (x - np.asarray(origin, dtype=np.float64)) / dx
    eps = 1e-6
    for sx in (-eps, eps):
        for sy in (-eps, eps):
            for sz in (-eps, eps):
                ijk = np.floor(u + np.array([sx, sy, sz])).astype(np.int64)
                inside = np.all((ijk >= 0) & (ijk < np.array(cells.shape)), axis=1)
                ijk = ijk[inside]
                cells[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = True
    return cells


def feature_cells(meshes, refine_flags, origin, dx: float, node_dims, params,
                  open_flags=None, moving_flags=None) -> np.ndarray:
    """Cells marked by the feature-size criterion, before the halo and the boxes.

    A coarse cell is marked when narrow free space passes through it: a gap narrower
    than ``gap_cells`` coarse cells measured across the free side of a collider marked
    ``refine`` (:func:`narrow_points`) to any collider (refining or not) or, with
    ``params.walls``, to the domain walls. That covers a slit between two plates, a hole
    or a letter in a panel narrower than ``gap_cells`` (measured in the panel's plane
    from its rim), the neck of an hourglass (measured across the neck), a collider close
    to a wall, and concave corners (within about ``gap_cells`` of their edge). A flat
    sheet or a thick wall with room on both sides marks nothing. Colliders that move
    (``moving_flags``) also mark the cells along their free edges and creases.
    """
    # params: a RegionParams (gap_cells, walls, crease_angle_deg)
    meshes = list(meshes)
    n = len(meshes)
    flags = list(refine_flags) if refine_flags is not None else [True] * n
    opens = list(open_flags) if open_flags is not None else [None] * n
    moving = list(moving_flags) if moving_flags is not None else [False] * n
    if not (len(flags) == len(opens) == len(moving) == n):
        raise ValueError("refine_flags, open_flags and moving_flags must have one entry per mesh")
    dims = np.asarray(node_dims, dtype=np.int64).reshape(3)
    cell_dims = np.maximum(dims - 1, 0)
    spacing = FEATURE_SPACING * dx
    targets, sources, dirs, marks = [], [], [], []
    for m, f, o, mv in zip(meshes, flags, opens, moving):
        t, s, d, e = feature_samples(m, spacing, open_surface=o, moving=bool(mv and f),
                                     crease_angle_deg=params.crease_angle_deg)
        targets.append(t)
        if f:
            sources.append(s)
            dirs.append(d)
            marks.append(e)
    if not sources:
        return np.zeros(tuple(cell_dims), dtype=bool)
    sources, dirs = thin_samples(np.concatenate(sources), spacing * SOURCE_BIN, np.concatenate(dirs))
    targets, _ = thin_samples(np.concatenate(targets), spacing * TARGET_BIN)
    narrow = narrow_points(sources, dirs, targets,
                           gap=params.gap_cells * dx, contact=CONTACT_CELLS * dx, tolerance=0.6 * spacing,
                           walls=params.walls)
    return _point_cells(np.concatenate([narrow, *marks]), origin, dx, cell_dims)


