"""Edge topology of triangle and quad meshes: edge keys, edge-face adjacency,
boundary edges, boundary loops and feature edges.

Host-side numpy (plus scipy for the loops). Faces are an ``(M, k)`` integer array,
``k = 3`` (triangles) or ``k = 4`` (quads). Half-edge ``i k + j`` of a face array
runs from ``faces[i, j]`` to ``faces[i, (j + 1) % k]`` ("face order"). An undirected
edge is identified by one int64 key, ``min * KEY + max``, so sorting keys sorts
edges by their smaller vertex, then by the larger one.

Every module that needs edge adjacency (the letter panel's triangulation, the
subdivision and densification for the refined region, the rim samples, the
preview's collider outline) uses the functions here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

__all__ = [
    "KEY",
    "EdgeAdjacency",
    "boundary_edges",
    "boundary_halfedges",
    "boundary_loops",
    "edge_adjacency",
    "edge_ends",
    "edge_keys",
    "face_normals",
    "feature_edges",
    "halfedges",
    "is_open",
    "mesh_boundary_edges",
]

#: Multiplier of the smaller vertex index in an edge key (vertex indices < 2**31).
KEY = np.int64(1) << 31


def edge_keys(a, b) -> np.ndarray:
    """Int64 key of the undirected edges ``(a, b)``: ``min * KEY + max``."""
    a = np.asarray(a, dtype=np.int64)
    b = np.asarray(b, dtype=np.int64)
    return np.minimum(a, b) * KEY + np.maximum(a, b)


def edge_ends(keys) -> np.ndarray:
    """The ``(K, 2)`` sorted vertex pairs ``(min, max)`` of edge keys."""
    keys = np.asarray(keys, dtype=np.int64)
    return np.stack([keys // KEY, keys % KEY], 1)


def halfedges(faces) -> tuple[np.ndarray, np.ndarray]:
    """``(tail, head)`` vertex indices of every half-edge, in face order."""
    f = np.asarray(faces, dtype=np.int64)
    return f.ravel(), np.roll(f, -1, axis=1).ravel()


def face_normals(vertices, faces) -> np.ndarray:
    """Unit normals of triangles or quads (quads: cross product of the diagonals);
    zero rows for degenerate faces."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    if f.shape[1] == 3:
        n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    else:
        n = np.cross(v[f[:, 2]] - v[f[:, 0]], v[f[:, 3]] - v[f[:, 1]])
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    return np.divide(n, norm, out=np.zeros_like(n), where=norm > 0)


@dataclass(frozen=True)
class EdgeAdjacency:
    """Edges of a face array and the faces on each edge (see :func:`edge_adjacency`).

    ``edges``: ``(E, 2)`` sorted vertex pairs in key order; ``face_count``: ``(E,)``
    faces using each edge (1: boundary, 2: manifold, more: non-manifold); ``tail``,
    ``head``, ``face``, ``edge``: per half-edge (face order) its two vertices, its
    face and the index of its edge in ``edges``; ``order``: the half-edges sorted by
    edge (stable, so the half-edges of one edge stay in face order) and ``first``: the
    position in ``order`` of each edge's first half-edge.
    """

    edges: np.ndarray
    face_count: np.ndarray
    tail: np.ndarray
    head: np.ndarray
    face: np.ndarray
    edge: np.ndarray
    order: np.ndarray
    first: np.ndarray

    def manifold(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(edge ids, half-edge a, half-edge b)`` of the edges with exactly two faces;
        ``a`` comes before ``b`` in face order."""
        two = np.flatnonzero(self.face_count == 2)
        return two, self.order[self.first[two]], self.order[self.first[two] + 1]


def edge_adjacency(faces) -> EdgeAdjacency:
    """The edges of a triangle or uniform quad face array and their faces."""
    f = np.asarray(faces, dtype=np.int64)
    m, k = f.shape
    tail, head = halfedges(f)
    keys, edge = np.unique(edge_keys(tail, head), return_inverse=True)
    edge = edge.reshape(-1)
    count = np.bincount(edge, minlength=len(keys))
    return EdgeAdjacency(
        edges=edge_ends(keys),
        face_count=count,
        tail=tail,
        head=head,
        face=np.repeat(np.arange(m), k),
        edge=edge,
        order=np.argsort(edge, kind="stable"),
        first=np.concatenate([[0], np.cumsum(count)[:-1]]).astype(np.int64),
    )


def boundary_halfedges(faces) -> np.ndarray:
    """Indices (face order, ascending) of the half-edges whose edge belongs to one face."""
    f = np.asarray(faces, dtype=np.int64)
    if len(f) == 0:
        return np.zeros(0, dtype=np.int64)
    _, inv, count = np.unique(edge_keys(*halfedges(f)), return_inverse=True, return_counts=True)
    return np.flatnonzero(count[inv.reshape(-1)] == 1)


def boundary_edges(faces) -> np.ndarray:
    """Edges used by exactly one face of a triangle or uniform quad mesh, ``(K, 2)``
    vertex indices in the direction of their face, in face order."""
    f = np.asarray(faces, dtype=np.int64)
    if len(f) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    once = boundary_halfedges(f)
    tail, head = halfedges(f)
    return np.stack([tail[once], head[once]], 1)


def mesh_boundary_edges(mesh) -> np.ndarray:
    """Boundary edges of a :class:`trimesh.Trimesh` (or anything with ``faces``):
    ``(K, 2)`` int64 sorted vertex pairs."""
    return np.sort(boundary_edges(mesh.faces), axis=1)


def is_open(mesh) -> bool:
    """True when the surface has a boundary (some edge belongs to only one face)."""
    return len(boundary_halfedges(mesh.faces)) > 0


def boundary_loops(mesh) -> list[np.ndarray]:
    """The boundary edges grouped into connected components (one per hole outline),
    each as the array of its vertex indices. Loops that touch at a vertex count as one."""
    edges = mesh_boundary_edges(mesh)
    if len(edges) == 0:
        return []
    verts, inv = np.unique(edges.ravel(), return_inverse=True)
    e = inv.reshape(-1, 2)
    n = len(verts)
    graph = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n))
    count, labels = connected_components(graph, directed=False)
    return [verts[labels == k] for k in range(count)]


def feature_edges(vertices: np.ndarray, faces: np.ndarray, angle_deg: float = 35.0) -> np.ndarray:
    """Edges worth outlining on a collider mesh, as (K, 2) sorted vertex index pairs:
    boundary edges (rims of sheets, hole outlines: used by one face) and creases (two
    faces whose normals differ by more than ``angle_deg``; the corners of a thin box).

    Rigid motion keeps the angles, so the pairs of one pose serve every frame.
    """
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if len(f) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    n = face_normals(vertices, f)
    adj = edge_adjacency(f)
    keep = adj.face_count == 1  # boundary
    two, ha, hb = adj.manifold()
    fa, fb = adj.face[ha], adj.face[hb]
    # unsigned angle: open sheets and revolved surfaces may be wound either way
    crease = np.abs(np.einsum("ij,ij->i", n[fa], n[fb])) < math.cos(math.radians(angle_deg))
    keep[two[crease]] = True
    return adj.edges[keep]
