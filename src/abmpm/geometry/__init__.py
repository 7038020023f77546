"""Geometry: host-side (numpy/scipy/trimesh) mesh work for the scene and the solver.

``sample_body`` turns a scene body into particle positions on a lattice aligned to
the simulation domain; the other functions exported here are its building blocks
(and ``place``, for colliders), used by the preview, the colliders and the tests.
Among the submodules:

* :mod:`~abmpm.geometry.meshes`: mesh files, ``transform_mesh`` and ``place``
  (the one placement of every collider shape);
* :mod:`~abmpm.geometry.procedural`: the procedural collider shapes;
  :mod:`~abmpm.geometry.collider_shapes`: their registry by scene name, one module
  a shape with the parameters a scene sets; :mod:`~abmpm.geometry.glyphs`: the
  letter panel's glyph outlines and triangulation;
  :mod:`~abmpm.geometry.placement`: scene collider -> world-space mesh;
* :mod:`~abmpm.geometry.topology`: edge adjacency, boundary edges and loops,
  feature edges;
* :mod:`~abmpm.geometry.subdivision` and :mod:`~abmpm.geometry.region`: the refined
  region B_s (Catmull-Clark, densification, kernel density, cells), handed to the
  solver as a boolean array of coarse cells.
"""

from abmpm.geometry.meshes import load_mesh, place, require_closed, transform_mesh
from abmpm.geometry.sampling import (
    inside_mesh,
    jitter_points,
    lattice,
    lattice_points,
    lattice_spacing,
    particle_volume,
    sample_body,
    sample_body_volume,
    shape_bounds_and_inside,
)
from abmpm.geometry.shapes import (
    bunny_ellipsoids,
    bunny_mesh,
    ellipsoid_half_extent,
    ellipsoid_mesh,
    ellipsoids_bounds,
    inside_ellipsoids,
)
from abmpm.geometry.transforms import euler_matrix

__all__ = [
    "bunny_ellipsoids",
    "bunny_mesh",
    "ellipsoid_half_extent",
    "ellipsoid_mesh",
    "ellipsoids_bounds",
    "euler_matrix",
    "inside_ellipsoids",
    "inside_mesh",
    "jitter_points",
    "lattice",
    "lattice_points",
    "lattice_spacing",
    "load_mesh",
    "particle_volume",
    "place",
    "require_closed",
    "sample_body",
    "sample_body_volume",
    "shape_bounds_and_inside",
    "transform_mesh",
]
