"""Geometry: shapes, mesh files and particle sampling of scene bodies.

``sample_body`` turns a scene body into particle positions on a lattice aligned to
the simulation domain; the other functions are its building blocks, exported for the
preview, the colliders and the tests.
"""

from abmpm.geometry.meshes import load_mesh, require_closed, transform_mesh
from abmpm.geometry.sampling import (
    inside_mesh,
    jitter_points,
    lattice,
    lattice_points,
    lattice_spacing,
    particle_volume,
    sample_body,
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
    "require_closed",
    "sample_body",
    "shape_bounds_and_inside",
    "transform_mesh",
]
