"""Loading and placing triangle meshes (mesh files given by the user, collider shapes).

A mesh file is user input: every way it can be wrong (missing, unreadable, empty,
open) raises :class:`MeshError` with a message that starts with the file's path, so
the CLI can print one line that says which file to fix and how.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import trimesh

from abmpm.errors import MeshError
from abmpm.geometry.arguments import vec3
from abmpm.geometry.transforms import euler_matrix

MESH_SUFFIXES = (".obj", ".stl", ".ply")
# Vertex coordinates (m, after scaling) beyond this are refused: merging duplicate
# vertices rounds coordinates / 1e-8 to 64-bit integers, and the solver works in
# single precision; no scene needs a mesh ten million kilometres across.
MAX_COORDINATE = 1.0e10


def load_mesh(path, where: str) -> trimesh.Trimesh:
    """Read an OBJ, STL or PLY file as one triangle mesh.

    ``where`` names the scene field that referenced the file (``"bodies[2].file"``)
    and is appended to the message so the user finds both the file and the key.
    Multi-object files are merged into one mesh (``force="mesh"``). The file is read
    without processing first, so that non-finite vertices are reported as such (the
    processing would silently drop them and leave a hole); then duplicate vertices are
    merged, so an STL triangle soup becomes a connected surface whose closedness can
    be checked.
    """
    path = Path(path)
    ref = f" (referenced by {where})" if where else ""
    if not path.exists():
        raise MeshError(f"{path}: mesh file not found{ref}")
    if not path.is_file():
        raise MeshError(f"{path}: is not a file{ref}")
    suffix = path.suffix.lower()
    if suffix not in MESH_SUFFIXES:
        raise MeshError(
            f"{path}: unsupported mesh format '{path.suffix}'; use one of {', '.join(MESH_SUFFIXES)}{ref}"
        )
    fmt = suffix[1:].upper()
    try:
        size = path.stat().st_size
        with open(path, "rb"):
            pass
    except OSError as exc:
        raise MeshError(f"{path}: cannot read mesh file ({exc.strerror or exc}){ref}") from None
    if size == 0:
        raise MeshError(f"{path}: mesh file is empty{ref}")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # a bad file must not print warnings as well
            mesh = trimesh.load(path, force="mesh", process=False)
    except ImportError:
        # trimesh falls back to an optional text-encoding detector for undecodable bytes
        raise MeshError(
            f"{path}: cannot read mesh: not a valid {fmt} file (binary or non-UTF-8 content){ref}"
        ) from None
    except Exception as exc:  # trimesh raises many types for a corrupt file
        detail = f"{type(exc).__name__}: {exc}".splitlines()[0][:200]
        raise MeshError(f"{path}: cannot read mesh: not a valid {fmt} file ({detail}){ref}") from None
    if not isinstance(mesh, trimesh.Trimesh):
        raise MeshError(f"{path}: file holds no triangle mesh (got {type(mesh).__name__}){ref}")
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces)
    if len(faces) == 0 or len(vertices) == 0:
        # garbage bytes decode to an empty mesh when a text-encoding detector is installed
        # (requests brings one), and raise when none is: the same message for both
        raise MeshError(f"{path}: cannot read mesh: not a valid {fmt} file (no triangles in its {size} bytes){ref}")
    bad = ~np.isfinite(vertices).all(axis=1)
    if bad.any():
        raise MeshError(
            f"{path}: mesh has non-finite vertex coordinates (nan or inf in {int(bad.sum())} of "
            f"{len(vertices)} vertices, the first is vertex {int(np.argmax(bad))}, counting from 0){ref}"
        )
    if np.abs(vertices).max() > MAX_COORDINATE:
        raise MeshError(
            f"{path}: mesh has vertex coordinates up to {np.abs(vertices).max():.3g}, more than "
            f"{MAX_COORDINATE:.0e}; is the file in the right units?{ref}"
        )
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise MeshError(f"{path}: a face refers to a vertex that the file does not have{ref}")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        mesh.process()
    if len(mesh.faces) == 0:
        raise MeshError(f"{path}: mesh is empty (only degenerate triangles){ref}")
    return mesh


def require_closed(mesh: trimesh.Trimesh, path, where: str = "") -> None:
    """Refuse a mesh with holes as a solid body.

    Inside/outside is only defined for a closed surface; filling an open one would
    leak particles through the holes or depend on the query method, so it is an
    error rather than a guess. Open meshes are still fine as colliders.
    """
    if not mesh.is_watertight:
        ref = f" (referenced by {where})" if where else ""
        raise MeshError(
            f"{path}: mesh is not closed (not watertight), so it cannot be filled as a solid body; "
            f"close the holes or use it as a collider{ref}"
        )


def transform_mesh(mesh: trimesh.Trimesh, scale=1.0, rotation_deg=(0.0, 0.0, 0.0), translation=(0.0, 0.0, 0.0)):
    """A copy of ``mesh`` scaled about its file origin, rotated, then translated.

    ``world = R @ (scale * v) + translation`` with ``R = euler_matrix(rotation_deg)``;
    ``scale`` is a number or a per-axis triple, applied in the file's own axes before
    the rotation so that a non-uniform scale stretches the model, not the world.
    """
    s = np.broadcast_to(np.asarray(scale, dtype=np.float64), (3,))
    out = mesh.copy()
    out.vertices = (np.asarray(mesh.vertices, dtype=np.float64) * s) @ euler_matrix(rotation_deg).T + np.asarray(
        translation, dtype=np.float64
    )
    return out


def place(mesh: trimesh.Trimesh, center, rotation_deg) -> trimesh.Trimesh:
    """A copy of ``mesh`` rotated about its own origin, then moved to ``center``:
    ``world = center + R @ local`` with ``R = euler_matrix(rotation_deg)``.

    Every collider shape (procedural or from a file) is placed with this function.
    ``center`` and ``rotation_deg`` must be three finite numbers each (else
    ``ValueError``); the vertices of the result are C-contiguous float64.
    """
    out = transform_mesh(mesh, 1.0, vec3(rotation_deg, "rotation_deg"), vec3(center, "center"))
    out.vertices = np.ascontiguousarray(out.vertices, dtype=np.float64)
    return out


def limit_edge_length(vertices: np.ndarray, faces: np.ndarray, max_edge: float,
                      max_faces: int = 2_000_000) -> tuple[np.ndarray, np.ndarray]:
    """The same surface with no edge longer than ``max_edge`` (long triangles split into
    four, as often as needed), or, if that would take more than ``max_faces``
    triangles (a sheet far larger than the domain at a fine spacing), with the
    shortest edge limit that stays within them.

    Why the solver's colliders need it: a closest-point query computes barycentric
    coordinates in float32, and on a long sliver triangle (a triangulated letter
    panel has faces 0.6 m long and 4 mm wide) its answer lands up to ~0.6 mm beside
    the true closest point. A particle 0.02 mm in front of the sheet then reads as
    0.2 mm away, farther than it moves, skips the crossing test and steps through.
    The error shrinks with the edge length (0.6 mm -> 2 um for 0.6 m -> 1 cm edges)."""
    v, f = np.asarray(vertices, np.float64), np.asarray(faces, np.int64)
    if len(f) == 0:
        return v, f
    longest = np.linalg.norm(v[f[:, [1, 2, 0]]] - v[f], axis=2).max(axis=1)
    if longest.max() <= max_edge:
        return v, f

    def faces_after(limit: float) -> float:
        # each round of splitting makes four triangles of one and halves the edges
        return float((4.0 ** np.ceil(np.log2(np.maximum(longest / limit, 1.0)))).sum())

    while faces_after(max_edge) > max_faces:
        max_edge *= 2.0
    v, f = trimesh.remesh.subdivide_to_size(v, f, max_edge=max_edge, max_iter=64)
    return np.asarray(v, np.float64), np.asarray(f, np.int64)
