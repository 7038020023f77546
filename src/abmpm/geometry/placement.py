"""Scene collider descriptions -> triangle meshes in world space."""

from __future__ import annotations

import warnings

import numpy as np
import trimesh

from ..errors import SceneError
from . import colliders as procedural
from .meshes import MAX_COORDINATE, load_mesh
from .transforms import euler_matrix

# scene shape name -> (generator, the scene fields passed to it)
_PROCEDURAL = {
    "sheet": (procedural.sheet, ("size", "resolution")),
    "thin_box": (procedural.thin_box, ("size",)),
    "blade": (procedural.blade, ("length", "height", "thickness")),
    "crossed_plates": (procedural.crossed_plates, ("size", "thickness")),
    "letter_panel": (procedural.letter_panel, ("text", "size", "thickness")),
    "hourglass": (procedural.hourglass, ("height", "radius", "neck_radius", "wall_thickness")),
    "funnel": (procedural.funnel, ("top_radius", "pipe_radius", "cone_height", "pipe_length")),
    "paddle": (procedural.paddle, ("length", "height")),
}


def place(mesh: trimesh.Trimesh, center, rotation_deg) -> trimesh.Trimesh:
    """Rotate about the origin (the shape's own centre), then move to ``center``."""
    m = mesh.copy()
    T = np.eye(4)
    T[:3, :3] = euler_matrix(rotation_deg)
    T[:3, 3] = center
    m.apply_transform(T)
    return m


def collider_mesh(spec, resolve=lambda p: p, where: str = "colliders[0]") -> trimesh.Trimesh:
    """World-space rest-pose mesh of one scene collider (open meshes are fine)."""
    size = "scale" if spec.shape == "mesh" else "size"
    try:
        with warnings.catch_warnings():
            # overflow or an invalid cast while building or placing the shape means
            # absurd dimensions: an error, not a warning and a broken mesh
            warnings.simplefilter("error", RuntimeWarning)
            mesh = _build(spec, resolve, where)
    except RuntimeWarning as exc:
        raise SceneError(f"{where}: the collider cannot be built ({exc}); check its {size} and center") from None
    v = np.asarray(mesh.vertices, dtype=np.float64)
    reach = float(np.abs(v).max()) if len(v) else 0.0
    if not np.isfinite(v).all() or reach > MAX_COORDINATE:
        raise SceneError(
            f"{where}: the collider reaches {reach:.3g} m from the origin, more than {MAX_COORDINATE:.0e} m; "
            f"check its {size} and center"
        )
    return mesh


def _build(spec, resolve, where: str) -> trimesh.Trimesh:
    if spec.shape == "mesh":
        mesh = load_mesh(resolve(spec.file), where=f"{where}.file")
        scale = np.broadcast_to(np.asarray(spec.scale, dtype=np.float64), (3,))
        mesh = mesh.copy()
        if not np.all(scale == 1.0):
            mesh.apply_transform(np.diag([*scale, 1.0]))
    else:
        make, keys = _PROCEDURAL[spec.shape]
        try:
            mesh = make(**{k: getattr(spec, k) for k in keys})
        except ValueError as exc:  # e.g. an hourglass neck wider than its bulbs
            key = f"{where}.text" if spec.shape == "letter_panel" and "text" in str(exc) else where
            raise SceneError(f"{key}: {exc}") from None
    return place(mesh, spec.center, spec.rotation)
