"""Mesh refinement for detection: Catmull-Clark subdivision with creases (paper
Eq. 26) and densification by longest-edge bisection.

Host-side numpy; the input arrays are never modified.

Catmull-Clark with sharp features: boundary edges, non-manifold edges and edges whose
dihedral angle exceeds ``crease_angle_deg`` are creases. A crease edge gets its
midpoint; a vertex on exactly two crease edges that continue each other (turning by
less than the crease angle) follows the cubic B-spline curve rule
``(a + 6 P + b) / 8`` (the standard boundary rule); a vertex where the crease turns
more sharply, or where three or more crease edges meet, stays where it is (so the
corners of a sheet are kept); every other vertex uses Eq. 26. Boxes and flat plates
keep their exact shape, while smooth tessellated surfaces move towards their limit
surface (by about edge^2 x curvature). On a badly shaped flat triangulation the
smoothing can fold a few faces over (see :func:`abmpm.geometry.region.surface_samples`
for how the samples cancel such a fold).
"""

from __future__ import annotations

import numpy as np
import trimesh

from abmpm.geometry.topology import edge_adjacency, edge_ends, edge_keys, face_normals

__all__ = ["catmull_clark", "densify", "triangulate_quads"]

# Guard against refining a mesh into more triangles than memory allows.
_MAX_SAMPLES = 20_000_000


def _catmull_clark_pass(v: np.ndarray, f: np.ndarray, cos_crease: float):
    """One Catmull-Clark pass over faces of one arity ``k``; returns quads."""
    nv, (m, k) = len(v), f.shape
    adj = edge_adjacency(f)
    he_from, he_face, he_edge, edges = adj.tail, adj.face, adj.edge, adj.edges
    ne = len(edges)

    face_pt = v[f].mean(axis=1)

    # the two faces of each manifold edge
    two, ha, hb = adj.manifold()
    fa, fb = he_face[ha], he_face[hb]
    normals = face_normals(v, f)
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
    corner = (n_crease >= 3) | ((n_crease == 2) & ~curve) | (valence == 0)  # unreferenced: kept
    vert_pt[curve] = (other[curve] + 6.0 * v[curve]) / 8.0
    vert_pt[corner] = v[corner]

    new_v = np.concatenate([vert_pt, edge_pt, face_pt])
    he_e = he_edge.reshape(m, k)
    quads = np.stack(
        [f, nv + he_e, np.broadcast_to((nv + ne + np.arange(m))[:, None], (m, k)), nv + np.roll(he_e, 1, axis=1)],
        axis=2,
    ).reshape(-1, 4)
    return new_v, quads


def catmull_clark(mesh, passes: int = 1, crease_angle_deg: float = 30.0, return_parent: bool = False):
    """Catmull-Clark subdivision of a triangle (or uniform quad) mesh, ``passes`` times.

    ``mesh`` is a :class:`trimesh.Trimesh` or a ``(vertices, faces)`` pair. Returns
    ``(vertices, quads)``: each input k-gon becomes k quads per pass. Smooth vertices
    follow Eq. 26; boundary, non-manifold and sharp edges (dihedral angle above
    ``crease_angle_deg``) are creases (see the module docstring). Unreferenced
    vertices are carried along unchanged. The input is not modified. With
    ``return_parent`` also returns, per output quad, the index of the input face it
    lies in.
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
    parent = np.arange(len(f))
    for _ in range(int(passes)):
        if len(f) == 0:
            break
        k = f.shape[1]
        v, f = _catmull_clark_pass(v, f, cos_crease)
        parent = parent[np.arange(len(f)) // k]  # face j of input face i is row i k + j
    return (v, f, parent) if return_parent else (v, f)


def triangulate_quads(faces: np.ndarray) -> np.ndarray:
    """Triangles of a triangle or quad face array: a quad ``(a, b, c, d)`` becomes
    ``(a, b, c)`` (in the first half of the output) and ``(a, c, d)`` (second half)."""
    if faces.shape[1] == 3:
        return faces
    return np.concatenate([faces[:, [0, 1, 2]], faces[:, [0, 2, 3]]])


def _edge_lengths(v: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Lengths of edges (t0, t1), (t1, t2), (t2, t0) of each triangle, ``(M, 3)``."""
    return np.linalg.norm(v[np.roll(t, -1, axis=1)] - v[t], axis=2)


def densify(vertices, faces, max_edge: float, face_data=None):
    """Split triangles (quads are cut in two first) until no edge is longer than
    ``max_edge``, by bisecting the longest edge of each long triangle at its midpoint.

    The surface does not move and its area is kept exactly. Longest-edge bisection
    follows the shape of each triangle, so thin (anisotropic) triangles are cut only
    across their long side and the vertex count stays close to area / max_edge^2.
    Midpoints of an edge are shared by the triangles that split it; a neighbour that
    does not split it is left with a T-junction, harmless for sampling.
    Returns ``(vertices, triangles)``, and with ``face_data`` (one row per input face)
    also that data for each output triangle.
    """
    v = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    t = triangulate_quads(faces)
    data = None if face_data is None else np.asarray(face_data)
    if data is not None:
        if len(data) != len(faces):
            raise ValueError("face_data needs one row per face")
        data = data if faces.shape[1] == 3 else np.concatenate([data, data])
    if len(t) == 0:
        return (v, t) if data is None else (v, t, data)
    if not max_edge > 0:
        raise ValueError("max_edge must be positive")
    lengths = _edge_lengths(v, t)
    area = 0.5 * np.linalg.norm(np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]]), axis=1)
    estimate = len(v) + np.sum(np.where(lengths.max(axis=1) > max_edge, 2.0 * area / max_edge**2, 0.0))
    if estimate > _MAX_SAMPLES:
        raise ValueError(
            f"detection mesh would need about {estimate:.3g} vertices at edge length {max_edge:g}; "
            "raise the bandwidth or max_edge"
        )
    verts = [v]
    nv = len(v)
    known_keys = np.zeros(0, dtype=np.int64)  # sorted edge keys already split
    known_mid = np.zeros(0, dtype=np.int64)  # their midpoint vertex ids
    done, done_data = [], []
    while len(t):
        longest = lengths.argmax(axis=1)
        split = lengths[np.arange(len(t)), longest] > max_edge
        done.append(t[~split])
        t, longest = t[split], longest[split]
        if data is not None:
            done_data.append(data[~split])
            data = data[split]
        if len(t) == 0:
            break
        # rotate each triangle so that its longest edge is (a, b)
        rows = np.arange(len(t))[:, None]
        t = t[rows, (longest[:, None] + np.arange(3)[None, :]) % 3]
        a, b, c = t[:, 0], t[:, 1], t[:, 2]
        uniq, inv = np.unique(edge_keys(a, b), return_inverse=True)
        inv = inv.reshape(-1)
        pos = np.searchsorted(known_keys, uniq)
        pos_c = np.minimum(pos, max(len(known_keys) - 1, 0))
        found = (pos < len(known_keys)) & (known_keys[pos_c] == uniq) if len(known_keys) else np.zeros(len(uniq), bool)
        mid_id = np.empty(len(uniq), dtype=np.int64)
        mid_id[found] = known_mid[pos_c[found]]
        new = np.flatnonzero(~found)
        mid_id[new] = nv + np.arange(len(new))
        ends = edge_ends(uniq[new])
        vv = np.concatenate(verts) if len(verts) > 1 else verts[0]
        mids = 0.5 * (vv[ends[:, 0]] + vv[ends[:, 1]])
        verts = [vv, mids]
        nv += len(new)
        order = np.argsort(np.concatenate([known_keys, uniq[new]]), kind="stable")
        known_keys = np.concatenate([known_keys, uniq[new]])[order]
        known_mid = np.concatenate([known_mid, mid_id[new]])[order]
        m = mid_id[inv]
        t = np.concatenate([np.stack([a, m, c], 1), np.stack([m, b, c], 1)])
        if data is not None:
            data = np.concatenate([data, data])
        vv = np.concatenate(verts)
        verts = [vv]
        lengths = _edge_lengths(vv, t)
    v, t = np.concatenate(verts), np.concatenate(done)
    return (v, t) if data is None else (v, t, np.concatenate(done_data))
