"""Scene collider descriptions -> triangle meshes in world space."""

from __future__ import annotations

import warnings

import numpy as np
import trimesh

from ..errors import SceneError
from .collider_shapes import REGISTRY as SHAPES
from .meshes import MAX_COORDINATE, load_mesh, place


def collider_mesh(collider, resolve=lambda p: p, where: str = "colliders[0]") -> trimesh.Trimesh:
    """World-space rest-pose mesh of one scene collider (open meshes are fine)."""
    size = "scale" if collider.shape == "mesh" else "size"
    try:
        with warnings.catch_warnings():
            # overflow or an invalid cast while building or placing the shape means
            # absurd dimensions: an error, not a warning and a broken mesh
            warnings.simplefilter("error", RuntimeWarning)
            mesh = _build(collider, resolve, where)
    except RuntimeWarning as exc:
        raise SceneError(f"{where}: the collider cannot be built: its {size} or center is out of range "
                         f"(the arithmetic overflowed: {exc})") from None
    v = np.asarray(mesh.vertices, dtype=np.float64)
    reach = float(np.abs(v).max()) if len(v) else 0.0
    if not np.isfinite(v).all() or reach > MAX_COORDINATE:
        raise SceneError(
            f"{where}: the collider reaches {reach:.3g} m from the origin, more than {MAX_COORDINATE:.0e} m; "
            f"check its {size} and center"
        )
    return mesh


def _build(collider, resolve, where: str) -> trimesh.Trimesh:
    if collider.shape == "mesh":
        mesh = load_mesh(resolve(collider.file), where=f"{where}.file")
        scale = np.broadcast_to(np.asarray(collider.scale, dtype=np.float64), (3,))
        mesh = mesh.copy()
        if not np.all(scale == 1.0):
            mesh.apply_transform(np.diag([*scale, 1.0]))
    else:
        shape = SHAPES[collider.shape]
        try:
            mesh = shape.build(**shape.arguments(collider))  # built around the origin, placed below
        except ValueError as exc:  # e.g. an hourglass neck wider than its bulbs
            key = f"{where}.text" if collider.shape == "letter_panel" and "text" in str(exc) else where
            raise SceneError(f"{key}: {exc}") from None
    try:
        return place(mesh, collider.center, collider.rotation)
    except ValueError as exc:  # a center or rotation that is not three finite numbers
        raise SceneError(f"{where}: {exc}") from None
