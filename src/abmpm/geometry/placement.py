"""Scene collider descriptions -> triangle meshes in world space."""

from __future__ import annotations

import numpy as np
import trimesh

from ..errors import SceneError
from . import colliders as procedural
from .meshes import load_mesh
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
            raise SceneError(f"{where}: {exc}") from None
    return place(mesh, spec.center, spec.rotation)
