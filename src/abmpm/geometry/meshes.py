"""Loading and placing triangle meshes given by the user.

A mesh file is user input: every way it can be wrong (missing, unreadable, empty,
open) raises :class:`MeshError` with a message that starts with the file's path, so
the CLI can print one line that says which file to fix and how.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from abmpm.errors import MeshError
from abmpm.geometry.transforms import euler_matrix

MESH_SUFFIXES = (".obj", ".stl", ".ply")


def load_mesh(path, where: str) -> trimesh.Trimesh:
    """Read an OBJ, STL or PLY file as one triangle mesh.

    ``where`` names the scene field that referenced the file (``"bodies[2].file"``)
    and is appended to the message so the user finds both the file and the key.
    Multi-object files are merged into one mesh (``force="mesh"``), and trimesh's
    default processing merges duplicate vertices, so an STL triangle soup becomes a
    connected surface whose closedness can be checked.
    """
    path = Path(path)
    ref = f" (referenced by {where})" if where else ""
    if not path.exists():
        raise MeshError(f"{path}: mesh file not found{ref}")
    if not path.is_file():
        raise MeshError(f"{path}: is not a file{ref}")
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise MeshError(
            f"{path}: unsupported mesh format '{path.suffix}'; use one of {', '.join(MESH_SUFFIXES)}{ref}"
        )
    try:
        mesh = trimesh.load(path, force="mesh")
    except Exception as exc:  # trimesh raises many types for a corrupt file
        raise MeshError(f"{path}: cannot read mesh ({type(exc).__name__}: {exc}){ref}") from exc
    if not isinstance(mesh, trimesh.Trimesh):
        raise MeshError(f"{path}: file holds no triangle mesh (got {type(mesh).__name__}){ref}")
    if len(mesh.faces) == 0 or len(mesh.vertices) == 0:
        raise MeshError(f"{path}: mesh is empty (no triangles){ref}")
    if not np.all(np.isfinite(mesh.vertices)):
        raise MeshError(f"{path}: mesh has non-finite vertex coordinates{ref}")
    return mesh


def require_closed(mesh: trimesh.Trimesh, path) -> None:
    """Refuse a mesh with holes as a solid body.

    Inside/outside is only defined for a closed surface; filling an open one would
    leak particles through the holes or depend on the query method, so it is an
    error rather than a guess. Open meshes are still fine as colliders.
    """
    if not mesh.is_watertight:
        raise MeshError(
            f"{path}: mesh is not closed (not watertight), so it cannot be filled as a solid body; "
            "close the holes or use it as a collider"
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
