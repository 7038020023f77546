"""A procedural bunny: a union of ellipsoids.

Demo scenes want a recognisable, organic-looking body without shipping a mesh file.
A union of ellipsoids is enough for that, it has an exact and cheap inside test (no
mesh, no winding numbers), and its exact bounding box is known analytically.

An ellipsoid is a tuple ``(center (3,), radii (3,), R (3, 3))``: the world point ``p``
is inside when ``|R^T (p - center) / radii| <= 1``.
"""

from __future__ import annotations

import numpy as np
import trimesh

from abmpm.geometry.transforms import euler_matrix

Ellipsoid = tuple[np.ndarray, np.ndarray, np.ndarray]

# The bunny in its own frame, in arbitrary units: it faces +x, y is up, z is to its
# left. Each part is (center, radii, XYZ Euler angles in degrees). The parts overlap
# generously so that the union stays one connected body even when sampled with only
# a few particles across an ear. The whole set is rescaled to the requested height.
_BUNNY_PARTS = [
    # body: a large egg, slightly raised at the back like a sitting rabbit
    ((0.00, 0.40, 0.00), (0.46, 0.36, 0.33), (0.0, 0.0, 12.0)),
    # haunches: round thighs on both sides of the rear
    ((-0.15, 0.28, 0.17), (0.26, 0.24, 0.14), (0.0, 0.0, 0.0)),
    ((-0.15, 0.28, -0.17), (0.26, 0.24, 0.14), (0.0, 0.0, 0.0)),
    # head, set forward and above the chest
    ((0.42, 0.76, 0.00), (0.25, 0.22, 0.21), (0.0, 0.0, -10.0)),
    # two long ears, leaning back and splayed outwards
    ((0.34, 1.18, 0.09), (0.09, 0.34, 0.06), (-10.0, 0.0, 14.0)),
    ((0.34, 1.18, -0.09), (0.09, 0.34, 0.06), (10.0, 0.0, 14.0)),
    # a round tail on the rear
    ((-0.48, 0.50, 0.00), (0.11, 0.11, 0.11), (0.0, 0.0, 0.0)),
    # front paws under the chest
    ((0.30, 0.10, 0.11), (0.13, 0.10, 0.08), (0.0, 0.0, 0.0)),
    ((0.30, 0.10, -0.11), (0.13, 0.10, 0.08), (0.0, 0.0, 0.0)),
    # long hind feet under the haunches
    ((-0.12, 0.08, 0.19), (0.26, 0.08, 0.09), (0.0, 0.0, 0.0)),
    ((-0.12, 0.08, -0.19), (0.26, 0.08, 0.09), (0.0, 0.0, 0.0)),
]


def ellipsoid_half_extent(radii, rotation: np.ndarray) -> np.ndarray:
    """Exact half-size of the axis-aligned bounding box of a rotated ellipsoid.

    The support of ``{R diag(r) u : |u| <= 1}`` along world axis i is the norm of row i
    of ``R diag(r)``, so the box is exact, not a loose bound from the corners.
    """
    return np.linalg.norm(np.asarray(rotation) * np.asarray(radii)[None, :], axis=1)


def ellipsoids_bounds(ellipsoids: list[Ellipsoid]) -> tuple[np.ndarray, np.ndarray]:
    """Exact axis-aligned bounding box ``(lo, hi)`` of a union of ellipsoids."""
    lo = np.min([c - ellipsoid_half_extent(r, R) for c, r, R in ellipsoids], axis=0)
    hi = np.max([c + ellipsoid_half_extent(r, R) for c, r, R in ellipsoids], axis=0)
    return lo, hi


def _unit_bunny() -> list[Ellipsoid]:
    """The bunny scaled to height 1, lowest point at y = -0.5, centred in x and z."""
    parts = [
        (np.array(c, float), np.array(r, float), euler_matrix(a)) for c, r, a in _BUNNY_PARTS
    ]
    lo, hi = ellipsoids_bounds(parts)
    scale = 1.0 / (hi[1] - lo[1])
    shift = -np.array([(lo[0] + hi[0]) / 2, lo[1], (lo[2] + hi[2]) / 2]) * scale
    shift[1] -= 0.5
    return [(c * scale + shift, r * scale, R) for c, r, R in parts]


def bunny_ellipsoids(center, size: float, rotation_deg=(0.0, 0.0, 0.0)) -> list[Ellipsoid]:
    """The bunny as a list of world-space ellipsoids ``(center, radii, R)``.

    Unrotated, the bunny is exactly ``size`` tall, its lowest point is at
    ``center[1] - size / 2`` (so ``center`` is the middle of its height, which makes it
    easy to rest it on a floor) and its footprint is centred on ``center`` in x and z.
    ``rotation_deg`` (intrinsic XYZ, see :func:`euler_matrix`) turns it about ``center``;
    a rotated bunny keeps its size but no longer its height along y.
    """
    c0 = np.asarray(center, dtype=np.float64).reshape(3)
    rb = euler_matrix(rotation_deg)
    return [(c0 + rb @ (c * size), r * size, rb @ R) for c, r, R in _unit_bunny()]


def inside_ellipsoids(points, ellipsoids: list[Ellipsoid]) -> np.ndarray:
    """Boolean mask: which ``points`` (N, 3) lie inside (or on) any of the ellipsoids.

    Vectorised over points; the short loop is over the handful of ellipsoids.
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    mask = np.zeros(len(p), dtype=bool)
    for c, r, R in ellipsoids:
        # Row-vector form of R^T (p - c): body-frame coordinates of every point.
        local = (p - c) @ R / r
        mask |= np.einsum("ij,ij->i", local, local) <= 1.0
    return mask


def ellipsoid_mesh(center, radii, rotation: np.ndarray, subdivisions: int = 3):
    """A closed triangle mesh of one ellipsoid (a stretched icosphere)."""
    mesh = trimesh.creation.icosphere(subdivisions=subdivisions)
    mesh.vertices = mesh.vertices * np.asarray(radii) @ np.asarray(rotation).T + np.asarray(center)
    return mesh


def bunny_mesh(center, size: float, rotation_deg=(0.0, 0.0, 0.0), subdivisions: int = 3):
    """A triangle mesh of the bunny, for display and export.

    The parts are merged by a boolean union when the manifold3d engine is installed,
    which gives one closed surface without hidden inner faces. Without it the part
    meshes are simply concatenated: overlapping shells that render the same, but that
    are not a valid solid, so never use that fallback to fill a body (the sampler uses
    :func:`inside_ellipsoids` instead).
    """
    parts = [ellipsoid_mesh(c, r, R, subdivisions) for c, r, R in bunny_ellipsoids(center, size, rotation_deg)]
    try:  # manifold3d (a dependency) is trimesh's boolean engine
        union = trimesh.boolean.union(parts, engine="manifold")
        if isinstance(union, trimesh.Trimesh) and len(union.faces) > 0:
            return union
    except Exception:  # no engine or a failed union: display-only fallback below
        pass
    return trimesh.util.concatenate(parts)
