"""Refined region B_s: which coarse cells get the fine level (paper Section 5.2).

Host-side (numpy/scipy) and independent of Warp. The pipeline is:

1. **Detection samples** (:func:`surface_samples`). Each collider that takes part is
   refined for detection only; the mesh used for collision is never modified.
   First ``subdivisions`` passes of Catmull-Clark (:func:`catmull_clark`; the smooth
   vertex rule is the paper's Eq. 26), then every triangle whose longest edge is still
   above ``max_edge`` (half the bandwidth by default) is split at its edge midpoints
   until none is (:func:`densify`). Midpoint splitting does not move the surface, so
   the sample density is set by the bandwidth without uniformly refining meshes whose
   triangles differ wildly in size (a letter panel, for instance). The samples are the
   vertices of the result, each weighted by a third of the area of its triangles.

2. **Kernel density** (:func:`kde_density`, :func:`kde_on_grid`; Eq. 27 with area
   weights instead of counts). At a point x,

       lambda(x) = sum_r w_r exp(-|x - x_r|^2 / (2 h^2)) / (2 pi h^2 (1 - e^-8)),

   the Gaussian cut at 4 h. This is the 3D Gaussian density times ``sqrt(2 pi) h``:
   integrating the 3D density over a plane through its centre gives
   ``1 / (sqrt(2 pi) h)``, so with area weights one infinite flat wall reads exactly
   1.0 on its surface whatever the tessellation (the ``1 - e^-8`` factor undoes the
   cut, which removes ``e^-8`` of that plane integral). Open surfaces (boundary edges
   exist) are zero-thickness sheets that material meets on both sides, so their
   samples weigh twice their area: a sheet reads 2.0, like a closed plate much
   thinner than h. Typical readings: thick wall 1.0, thin plate or sheet ~2, a gap of
   width g between two walls ``2 exp(-g^2 / (8 h^2))`` at its middle, a one-sided pipe
   of radius r on its axis ``sqrt(2 pi) (r/h) exp(-r^2 / (2 h^2))`` (at most 1.52, at
   r = h; more towards its wall).

3. **Cells** (:func:`refinement_region`). A coarse cell is refined when any of its
   eight corner nodes reads at least ``threshold``; the marked set is then dilated by
   ``halo`` cells (a cube, so Chebyshev distance) and the cells whose centre lies in
   one of the explicit ``boxes`` are added.

For a rigidly moving collider the samples can be computed once in the body frame
with :func:`surface_samples` and moved with the body (the weights do not change);
:func:`region_from_samples` then redoes only steps 2 and 3.

Catmull-Clark with sharp features: boundary edges, non-manifold edges and edges whose
dihedral angle exceeds ``crease_angle_deg`` are creases. A crease edge gets its
midpoint; a vertex on exactly two crease edges that continue each other (turning by
less than the crease angle) follows the cubic B-spline curve rule
``(a + 6 P + b) / 8``; a vertex where the crease turns more sharply, or where three or
more crease edges meet, stays where it is; every other vertex uses Eq. 26. So open
boundaries use the standard boundary (curve) rule, their corners are kept, and boxes
and flat plates keep their exact shape, while smooth tessellated surfaces move towards
their limit surface (a shift of order edge^2 x curvature).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import trimesh
from scipy import ndimage
from scipy.spatial import cKDTree

__all__ = [
    "RegionParams",
    "catmull_clark",
    "densify",
    "surface_samples",
    "kde_density",
    "kde_on_grid",
    "cells_from_lambda",
    "region_from_samples",
    "refinement_region",
]

#: Gaussian cut radius in units of the bandwidth.
CUTOFF = 4.0
# One flat wall reads 1 despite the cut: the plane integral inside radius CUTOFF h
# is (1 - exp(-CUTOFF^2 / 2)) of the whole.
_NORM = 1.0 / (2.0 * np.pi * (1.0 - np.exp(-0.5 * CUTOFF**2)))
# Guard against refining a mesh into more triangles than memory allows.
_MAX_TRIANGLES = 20_000_000


@dataclass
class RegionParams:
    """Parameters of the refined-region detection.

    ``bandwidth`` is the kernel bandwidth h in coarse cells; ``threshold`` the density
    at which a node marks its cells (one flat wall reads 1.0, a thin plate ~2);
    ``halo`` the dilation in cells; ``boxes`` explicit ``(min, max)`` world boxes
    whose cells (by centre) are always refined. ``subdivisions`` is the number of
    Catmull-Clark passes, ``max_edge`` the longest triangle edge of the detection
    mesh in units of h, ``crease_angle_deg`` the dihedral angle above which an edge
    is kept sharp by the subdivision.
    """

    bandwidth: float = 1.0
    threshold: float = 1.5
    halo: int = 1
    boxes: Sequence = ()
    subdivisions: int = 1
    max_edge: float = 0.5
    crease_angle_deg: float = 30.0

    def __post_init__(self):
        if not self.bandwidth > 0:
            raise ValueError(f"bandwidth must be positive, got {self.bandwidth}")
        if int(self.halo) != self.halo or self.halo < 0:
            raise ValueError(f"halo must be a non-negative integer, got {self.halo}")
        if int(self.subdivisions) != self.subdivisions or self.subdivisions < 0:
            raise ValueError(f"subdivisions must be a non-negative integer, got {self.subdivisions}")
        if not self.max_edge > 0:
            raise ValueError(f"max_edge must be positive, got {self.max_edge}")
        boxes = []
        for box in self.boxes:
            lo, hi = (np.asarray(b, dtype=np.float64).reshape(3) for b in box)
            if np.any(hi < lo):
                raise ValueError(f"box min {lo} exceeds max {hi}")
            boxes.append((lo, hi))
        self.boxes = tuple(boxes)


# ----------------------------------------------------------------------------- subdivision


def _face_normals(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Unit normals of triangles or quads (quads: cross product of the diagonals);
    zero rows for degenerate faces."""
    if f.shape[1] == 3:
        n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    else:
        n = np.cross(v[f[:, 2]] - v[f[:, 0]], v[f[:, 3]] - v[f[:, 1]])
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    return np.divide(n, norm, out=np.zeros_like(n), where=norm > 0)


def _catmull_clark_pass(v: np.ndarray, f: np.ndarray, cos_crease: float):
    """One Catmull-Clark pass over faces of one arity ``k``; returns quads."""
    nv, (m, k) = len(v), f.shape
    he_from = f.ravel()
    he_to = np.roll(f, -1, axis=1).ravel()
    he_face = np.repeat(np.arange(m), k)
    lo, hi = np.minimum(he_from, he_to), np.maximum(he_from, he_to)
    keys, he_edge = np.unique(lo * np.int64(nv) + hi, return_inverse=True)
    he_edge = he_edge.reshape(-1)
    edges = np.stack([keys // nv, keys % nv], 1)
    ne = len(edges)
    count = np.bincount(he_edge, minlength=ne)

    face_pt = v[f].mean(axis=1)

    # the two faces of each manifold edge: half-edges sorted by edge, pairs adjacent
    order = np.argsort(he_edge, kind="stable")
    first = np.concatenate([[0], np.cumsum(count)[:-1]])
    two = np.flatnonzero(count == 2)
    ha, hb = order[first[two]], order[first[two] + 1]
    fa, fb = he_face[ha], he_face[hb]
    normals = _face_normals(v, f)
    # a smooth edge of a consistently wound mesh is walked in opposite directions;
    # the same direction means one of the faces is flipped, so flip its normal back
    sign = np.where(he_from[ha] == he_from[hb], -1.0, 1.0)
    cos = np.einsum("ij,ij->i", normals[fa], normals[fb]) * sign
    degenerate = (np.abs(normals[fa]).sum(1) == 0) | (np.abs(normals[fb]).sum(1) == 0)
    smooth = np.zeros(ne, dtype=bool)
    smooth[two] = (cos >= cos_crease) | degenerate
    crease = ~smooth

    # edge points
    mid = 0.5 * (v[edges[:, 0]] + v[edges[:, 1]])
    edge_pt = mid.copy()
    s = two[smooth[two]]
    fa_s, fb_s = fa[smooth[two]], fb[smooth[two]]
    edge_pt[s] = 0.5 * mid[s] + 0.25 * (face_pt[fa_s] + face_pt[fb_s])

    # vertex points, smooth rule (Eq. 26): (F + 2 E + (n - 3) P) / n
    valence = np.bincount(edges.ravel(), minlength=nv).astype(np.float64)
    nfaces = np.bincount(he_from, minlength=nv).astype(np.float64)
    f_sum = np.stack([np.bincount(he_from, weights=face_pt[he_face, d], minlength=nv) for d in range(3)], 1)
    e_sum = np.stack(
        [np.bincount(edges.ravel(), weights=np.repeat(mid[:, d], 2), minlength=nv) for d in range(3)], 1
    )
    n_safe = np.maximum(valence, 1.0)[:, None]
    f_avg = f_sum / np.maximum(nfaces, 1.0)[:, None]
    e_avg = e_sum / n_safe
    vert_pt = (f_avg + 2.0 * e_avg + (n_safe - 3.0) * v) / n_safe

    # crease rules
    ce = edges[crease]
    n_crease = np.bincount(ce.ravel(), minlength=nv)
    other = np.zeros_like(v)
    turn = np.zeros_like(v)
    if len(ce):
        d = v[ce[:, 1]] - v[ce[:, 0]]
        length = np.linalg.norm(d, axis=1, keepdims=True)
        u = np.divide(d, length, out=np.zeros_like(d), where=length > 0)
        for a, b, sgn in ((0, 1, 1.0), (1, 0, -1.0)):
            for dd in range(3):
                other[:, dd] += np.bincount(ce[:, a], weights=v[ce[:, b], dd], minlength=nv)
                turn[:, dd] += np.bincount(ce[:, a], weights=sgn * u[:, dd], minlength=nv)
    # two crease edges continuing each other: the unit vectors to both neighbours
    # nearly cancel; their sum has length 2 sin(turning angle / 2)
    max_turn = 2.0 * np.sqrt(max(0.0, 0.5 * (1.0 - cos_crease)))
    curve = (n_crease == 2) & (np.linalg.norm(turn, axis=1) <= max_turn + 1e-12)
    corner = (n_crease >= 3) | ((n_crease == 2) & ~curve)
    vert_pt[curve] = (other[curve] + 6.0 * v[curve]) / 8.0
    vert_pt[corner] = v[corner]

    new_v = np.concatenate([vert_pt, edge_pt, face_pt])
    he_e = he_edge.reshape(m, k)
    quads = np.stack(
        [f, nv + he_e, np.broadcast_to((nv + ne + np.arange(m))[:, None], (m, k)), nv + np.roll(he_e, 1, axis=1)],
        axis=2,
    ).reshape(-1, 4)
    return new_v, quads


def catmull_clark(mesh, passes: int = 1, crease_angle_deg: float = 30.0):
    """Catmull-Clark subdivision of a triangle (or uniform quad) mesh, ``passes`` times.

    ``mesh`` is a :class:`trimesh.Trimesh` or a ``(vertices, faces)`` pair. Returns
    ``(vertices, quads)``: each input k-gon becomes k quads per pass. Smooth vertices
    follow Eq. 26; boundary, non-manifold and sharp edges (dihedral angle above
    ``crease_angle_deg``) are creases (see the module docstring). Unreferenced
    vertices are carried along unchanged. The input is not modified.
    """
    if isinstance(mesh, trimesh.Trimesh):
        v, f = mesh.vertices, mesh.faces
    else:
        v, f = mesh
    v = np.array(v, dtype=np.float64)
    f = np.array(f, dtype=np.int64)
    if f.ndim != 2 or f.shape[1] not in (3, 4):
        raise ValueError("faces must be an (M, 3) or (M, 4) array")
    cos_crease = float(np.cos(np.radians(crease_angle_deg)))
    for _ in range(int(passes)):
        if len(f) == 0:
            break
        v, f = _catmull_clark_pass(v, f, cos_crease)
    return v, f


def _triangulate(faces: np.ndarray) -> np.ndarray:
    if faces.shape[1] == 3:
        return faces
    return np.concatenate([faces[:, [0, 1, 2]], faces[:, [0, 2, 3]]])


def densify(vertices: np.ndarray, faces: np.ndarray, max_edge: float):
    """Split triangles (quads are cut into two first) at their edge midpoints until no
    edge is longer than ``max_edge``. The surface does not move and its area is kept
    exactly; the result may have T-junctions (irrelevant for sampling).
    Returns ``(vertices, triangles)``."""
    v = np.asarray(vertices, dtype=np.float64)
    t = _triangulate(np.asarray(faces, dtype=np.int64))
    if len(t) == 0:
        return v, t
    if not max_edge > 0:
        raise ValueError("max_edge must be positive")
    longest = np.linalg.norm(v[t] - v[np.roll(t, -1, axis=1)], axis=2).max(axis=1)
    levels = np.ceil(np.log2(np.maximum(longest / max_edge, 1.0)))
    if np.sum(4.0**levels) > _MAX_TRIANGLES:
        raise ValueError(
            f"detection mesh would need about {np.sum(4.0 ** levels):.3g} triangles at max_edge "
            f"{max_edge:g}; raise the bandwidth or max_edge"
        )
    verts = [v]
    nv = len(v)
    done = []
    while len(t):
        vv = np.concatenate(verts) if len(verts) > 1 else verts[0]
        verts = [vv]
        lengths = np.linalg.norm(vv[t] - vv[np.roll(t, -1, axis=1)], axis=2)
        split = lengths.max(axis=1) > max_edge
        done.append(t[~split])
        t = t[split]
        if len(t) == 0:
            break
        e = np.stack([t, np.roll(t, -1, axis=1)], axis=2).reshape(-1, 2)
        e.sort(axis=1)
        keys, inv = np.unique(e[:, 0] * np.int64(nv + 3 * len(t)) + e[:, 1], return_inverse=True)
        inv = inv.reshape(-1)
        first = np.zeros(len(keys), dtype=np.int64)
        first[inv] = np.arange(len(inv))
        ue = e[first]
        verts.append(0.5 * (vv[ue[:, 0]] + vv[ue[:, 1]]))
        mids = (nv + inv).reshape(-1, 3)  # midpoint of edge (j, j+1) of each triangle
        nv += len(keys)
        a, b, c = t[:, 0], t[:, 1], t[:, 2]
        mab, mbc, mca = mids[:, 0], mids[:, 1], mids[:, 2]
        t = np.concatenate(
            [np.stack(x, 1) for x in ((a, mab, mca), (mab, b, mbc), (mca, mbc, c), (mab, mbc, mca))]
        )
    return np.concatenate(verts), np.concatenate(done)


def _mesh_is_open(mesh: trimesh.Trimesh) -> bool:
    from ..geometry.colliders import is_open

    return bool(is_open(mesh))


def surface_samples(
    mesh,
    h: float,
    open: bool | None = None,
    subdivisions: int = 1,
    max_edge: float = 0.5,
    crease_angle_deg: float = 30.0,
):
    """Area-weighted detection samples of one collider for kernel bandwidth ``h``
    (world units): ``(points (N, 3), weights (N,))``.

    Catmull-Clark ``subdivisions`` times, then midpoint splitting to edges of at most
    ``max_edge * h``; each vertex carries a third of the area of its triangles. Open
    meshes (``open=None``: detected from boundary edges) weigh twice their area.
    """
    if not h > 0:
        raise ValueError(f"h must be positive, got {h}")
    if len(mesh.faces) == 0:
        return np.zeros((0, 3)), np.zeros(0)
    if open is None:
        open = _mesh_is_open(mesh)
    v, q = catmull_clark(mesh, passes=subdivisions, crease_angle_deg=crease_angle_deg)
    v, t = densify(v, q, max_edge * h)
    area = 0.5 * np.linalg.norm(np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]]), axis=1)
    w = np.bincount(t.ravel(), weights=np.repeat(area / 3.0, 3), minlength=len(v))
    if open:
        w *= 2.0
    keep = w > 0
    return v[keep], w[keep]


# ----------------------------------------------------------------------------- density


def kde_density(points, weights, nodes_xyz, h: float) -> np.ndarray:
    """Area-weighted Gaussian density (module docstring) at arbitrary ``nodes_xyz``
    ``(M, 3)``, via a k-d tree over the samples; the kernel is cut at ``4 h``."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    w = np.asarray(weights, dtype=np.float64).reshape(-1)
    x = np.asarray(nodes_xyz, dtype=np.float64).reshape(-1, 3)
    lam = np.zeros(len(x))
    if len(p) == 0 or len(x) == 0:
        return lam
    r = CUTOFF * h
    pairs = cKDTree(p).sparse_distance_matrix(cKDTree(x), r, output_type="ndarray")
    if len(pairs):
        k = w[pairs["i"]] * np.exp(-0.5 * (pairs["v"] / h) ** 2)
        lam = np.bincount(pairs["j"], weights=k, minlength=len(x))
    return lam * (_NORM / (h * h))


def kde_on_grid(points, weights, origin, dx: float, node_dims, h: float, chunk: int = 4096) -> np.ndarray:
    """The same density as :func:`kde_density` on all nodes of a regular grid
    (node ``(i, j, k)`` at ``origin + dx (i, j, k)``), shape ``node_dims``.

    Equivalent to the k-d tree query but several times faster: each sample scatters
    to the nodes of the box around it within 4 h (the Gaussian is separable, so the
    per-axis factors are computed once per sample); nodes further than 4 h are cut.
    """
    dims = np.asarray(node_dims, dtype=np.int64).reshape(3)
    origin = np.asarray(origin, dtype=np.float64).reshape(3)
    lam = np.zeros(int(np.prod(dims)))
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    w = np.asarray(weights, dtype=np.float64).reshape(-1)
    r = CUTOFF * h
    if len(p):
        hi = origin + dx * (dims - 1)
        inside = np.all((p > origin - r) & (p < hi + r), axis=1) & (w != 0)
        p, w = p[inside], w[inside]
    if len(p) == 0 or np.any(dims <= 0):
        return lam.reshape(dims)
    kr = int(np.ceil(r / dx))
    off = np.arange(-kr, kr + 2)  # floor(u) + off covers every node within r
    strides = np.array([dims[1] * dims[2], dims[2], 1], dtype=np.int64)
    inv2h2 = 0.5 / (h * h)
    r2 = r * r
    for s in range(0, len(p), chunk):
        u = (p[s : s + chunk] - origin) / dx
        base = np.floor(u).astype(np.int64)
        idx_axis, d2_axis = [], []
        for a in range(3):
            ia = base[:, a : a + 1] + off[None, :]
            da = ((ia - u[:, a : a + 1]) * dx) ** 2
            da = np.where((ia >= 0) & (ia < dims[a]), da, np.inf)  # off-grid nodes
            idx_axis.append(np.clip(ia, 0, dims[a] - 1) * strides[a])
            d2_axis.append(da)
        d2 = d2_axis[0][:, :, None, None] + d2_axis[1][:, None, :, None] + d2_axis[2][:, None, None, :]
        k = np.where(d2 <= r2, np.exp(-inv2h2 * np.minimum(d2, 1e300)), 0.0) * w[s : s + chunk, None, None, None]
        idx = idx_axis[0][:, :, None, None] + idx_axis[1][:, None, :, None] + idx_axis[2][:, None, None, :]
        idx, k = idx.ravel(), k.ravel()
        lo_i = int(idx.min())
        lam[lo_i : int(idx.max()) + 1] += np.bincount(idx - lo_i, weights=k)
    return (lam * (_NORM / (h * h))).reshape(dims)


# ----------------------------------------------------------------------------- cells


def cells_from_lambda(node_lambda: np.ndarray, threshold: float, halo: int = 0) -> np.ndarray:
    """Cells (``node_dims - 1`` per axis) with a corner node at or above ``threshold``,
    dilated by ``halo`` cells (cube structuring element)."""
    hot = np.asarray(node_lambda) >= threshold
    nx, ny, nz = hot.shape
    cells = np.zeros((max(nx - 1, 0), max(ny - 1, 0), max(nz - 1, 0)), dtype=bool)
    if cells.size == 0:
        return cells
    for i in (0, 1):
        for j in (0, 1):
            for k in (0, 1):
                cells |= hot[i : nx - 1 + i, j : ny - 1 + j, k : nz - 1 + k]
    if halo > 0 and cells.any():
        cells = ndimage.binary_dilation(cells, structure=np.ones((3, 3, 3), dtype=bool), iterations=int(halo))
    return cells


def _box_cells(cells: np.ndarray, origin, dx: float, boxes) -> np.ndarray:
    origin = np.asarray(origin, dtype=np.float64)
    centres = [origin[a] + dx * (np.arange(cells.shape[a]) + 0.5) for a in range(3)]
    for lo, hi in boxes:
        m = [(c >= lo[a]) & (c <= hi[a]) for a, c in enumerate(centres)]
        cells |= m[0][:, None, None] & m[1][None, :, None] & m[2][None, None, :]
    return cells


def region_from_samples(samples, origin, dx: float, node_dims, params: RegionParams | None = None):
    """Refined cells and node density from precomputed ``(points, weights)`` samples
    (see :func:`surface_samples`). Returns ``(cells_bool, node_lambda)``."""
    params = params or RegionParams()
    h = params.bandwidth * dx
    dims = tuple(int(d) for d in np.asarray(node_dims).reshape(3))
    if samples:
        p = np.concatenate([np.asarray(s[0], dtype=np.float64).reshape(-1, 3) for s in samples])
        w = np.concatenate([np.asarray(s[1], dtype=np.float64).reshape(-1) for s in samples])
    else:
        p, w = np.zeros((0, 3)), np.zeros(0)
    lam = kde_on_grid(p, w, origin, dx, dims, h)
    cells = cells_from_lambda(lam, params.threshold, params.halo)
    cells = _box_cells(cells, origin, dx, params.boxes)
    return cells, lam


def refinement_region(
    meshes,
    refine_flags,
    origin,
    dx: float,
    node_dims,
    params: RegionParams | None = None,
    open_flags=None,
):
    """The refined region B_s over the coarse grid.

    ``meshes``: world-space :class:`trimesh.Trimesh` colliders; ``refine_flags``: per
    mesh, whether it takes part; ``open_flags``: per mesh, whether it is a
    zero-thickness (two-sided) surface, ``None`` entries (or ``None`` for all) are
    detected from boundary edges. The grid has node ``(i, j, k)`` at
    ``origin + dx (i, j, k)`` and ``node_dims`` nodes per axis.

    Returns ``(cells, node_lambda)``: a boolean array of shape ``node_dims - 1`` (True =
    refined) and the density at the nodes, shape ``node_dims``.
    """
    params = params or RegionParams()
    meshes = list(meshes)
    flags = list(refine_flags) if refine_flags is not None else [True] * len(meshes)
    if len(flags) != len(meshes):
        raise ValueError("refine_flags must have one entry per mesh")
    opens = list(open_flags) if open_flags is not None else [None] * len(meshes)
    if len(opens) != len(meshes):
        raise ValueError("open_flags must have one entry per mesh")
    h = params.bandwidth * dx
    samples = [
        surface_samples(
            m,
            h,
            open=o,
            subdivisions=params.subdivisions,
            max_edge=params.max_edge,
            crease_angle_deg=params.crease_angle_deg,
        )
        for m, f, o in zip(meshes, flags, opens)
        if f
    ]
    return region_from_samples(samples, origin, dx, node_dims, params)
