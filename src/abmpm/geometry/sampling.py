"""Filling bodies with particles.

Every body is sampled the same way: take the axis-aligned bounding box of its shape,
put a regular sub-lattice of the simulation grid in it, keep the lattice points whose
(unjittered) position is inside the shape, and jitter the kept points a little.

* The sub-lattice has spacing ``h = dx / k`` with ``k**3 = particles_per_cell`` and is
  anchored at ``domain_min`` (points at ``domain_min + (i + 0.5) h``). Every body uses
  the same lattice, so two bodies that touch share no lattice point and never overlap,
  and a box aligned to grid cells gets exactly ``ppc`` particles per cell.
* Each particle stands for a cube of volume ``h**3`` (:func:`particle_volume`), except
  where the lattice does not fill the shape whole: a box whose sides are no multiple of
  ``h``, a sphere, an ellipsoid, a closed mesh. There the particles share the shape's
  exact volume (:func:`sample_body_volume`), so that the body's mass is ``density x
  volume`` at every ``h``, and a run on the coarse lattice and one on the fine lattice
  (original, adaptive and finest mode) hold the same mass. The inside test runs on the
  unjittered lattice points, so the particle count, and with it the body's mass, does
  not depend on the random seed.
* The jitter (at most a quarter of ``h`` per axis by default) breaks the lattice's
  symmetry, which otherwise shows up as grid-aligned artefacts in MPM, while keeping
  particles apart and inside the domain.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import numpy as np
import warp as wp

from abmpm.errors import SceneError
from abmpm.geometry.meshes import MAX_COORDINATE, load_mesh, require_closed, transform_mesh
from abmpm.geometry.shapes import (
    bunny_ellipsoids,
    ellipsoid_half_extent,
    ellipsoids_bounds,
    inside_ellipsoids,
)
from abmpm.geometry.transforms import euler_matrix

InsideTest = Callable[[np.ndarray], np.ndarray]


class Shape(NamedTuple):
    """A body's shape as the sampler reads it: its exact bounding box, an inside test of
    float64 points (N, 3) and its exact volume (None where there is no closed form: the
    bunny's overlapping ellipsoids)."""

    lo: np.ndarray
    hi: np.ndarray
    inside: InsideTest
    volume: float | None
    # a mesh's surface area: its signed volume is trusted only within area x h of the
    # lattice cubes' (a layer one spacing thick over the surface, the most that the cubes
    # can miss or add); beyond, its shells overlap or nest the same way round (the signed
    # volume counts such parts twice, the inside test once), and the cubes stay
    area: float | None = None


# A body's particles keep h**3 each where that sums to the shape's volume within this
# relative tolerance (a box of whole lattice cubes: bit-identical to h**3 then)
EXACT_VOLUME_RTOL = 1e-9


# --------------------------------------------------------------------------- lattice


def lattice_spacing(dx: float, ppc: int) -> float:
    """Particle lattice spacing ``h = dx / k`` for ``ppc = k**3`` particles per cell."""
    k = max(1, round(ppc ** (1.0 / 3.0)))
    return float(dx) / k


def particle_volume(dx: float, ppc: int) -> float:
    """Volume represented by one particle, ``h**3``: the lattice cube it stands for."""
    return lattice_spacing(dx, ppc) ** 3


def lattice_points(lo, hi, dx: float, ppc: int, domain_min) -> np.ndarray:
    """Unjittered sub-lattice points inside the box ``[lo, hi]``, float64 (N, 3).

    Points are ``domain_min + (i + 0.5) h``; the index range per axis is the set of
    ``i`` whose point lies in ``[lo, hi]``. Points are ordered x-major (C order over
    ``i, j, k``), which keeps the output order, and thus the jitter each point gets
    from the random stream, independent of anything but the inputs.
    """
    h = lattice_spacing(dx, ppc)
    lo = np.asarray(lo, dtype=np.float64)
    hi = np.asarray(hi, dtype=np.float64)
    origin = np.asarray(domain_min, dtype=np.float64)
    i_lo = np.ceil((lo - origin) / h - 0.5).astype(np.int64)
    i_hi = np.floor((hi - origin) / h - 0.5).astype(np.int64)
    if np.any(i_hi < i_lo):
        return np.zeros((0, 3), dtype=np.float64)
    axes = [origin[a] + (np.arange(i_lo[a], i_hi[a] + 1) + 0.5) * h for a in range(3)]
    grid = np.meshgrid(*axes, indexing="ij")
    return np.stack([g.ravel() for g in grid], axis=1)


JITTER = 0.5  # default sampling jitter, in lattice spacings: up to +-JITTER * h / 2 per axis


def jitter_points(points: np.ndarray, h: float, rng: np.random.Generator, jitter: float = JITTER) -> np.ndarray:
    """Move each point uniformly by up to ``±jitter * h / 2`` per axis.

    With ``jitter <= 1`` a point never leaves its own lattice cube, so jittered
    particles stay distinct and inside the domain.
    """
    if jitter <= 0 or len(points) == 0:
        return np.array(points, dtype=np.float64, copy=True)
    return points + rng.uniform(-1.0, 1.0, size=points.shape) * (0.5 * jitter * h)


def lattice(lo, hi, dx: float, ppc: int, domain_min, rng: np.random.Generator, jitter: float = JITTER) -> np.ndarray:
    """Jittered sub-lattice points in ``[lo, hi]`` (float64, (N, 3)).

    The lattice has spacing ``h = dx / round(ppc ** (1/3))`` and is aligned to the
    domain (points at ``domain_min + (i + 0.5) h``), so two touching bodies never
    overlap; each point is then jittered by up to ``±jitter * h / 2`` per axis.
    """
    base = lattice_points(lo, hi, dx, ppc, domain_min)
    return jitter_points(base, lattice_spacing(dx, ppc), rng, jitter)


# --------------------------------------------------------------------------- shapes


def _box(body, resolve, where):
    lo = np.asarray(body.min, dtype=np.float64)
    hi = np.asarray(body.max, dtype=np.float64)
    # Every lattice point of the bounding box is inside the box itself.
    return Shape(lo, hi, lambda p: np.ones(len(p), dtype=bool), float(np.prod(hi - lo)))


def _sphere(body, resolve, where):
    c = np.asarray(body.center, dtype=np.float64)
    r = float(body.radius)

    def inside(p):
        d = p - c
        return np.einsum("ij,ij->i", d, d) <= r * r

    return Shape(c - r, c + r, inside, 4.0 / 3.0 * np.pi * r**3)


def _ellipsoid(body, resolve, where):
    c = np.asarray(body.center, dtype=np.float64)
    r = np.asarray(body.radii, dtype=np.float64)
    R = euler_matrix(body.rotation)
    ell = [(c, r, R)]
    half = ellipsoid_half_extent(r, R)
    return Shape(c - half, c + half, lambda p: inside_ellipsoids(p, ell), 4.0 / 3.0 * np.pi * float(np.prod(r)))


def _bunny(body, resolve, where):
    ells = bunny_ellipsoids(body.center, body.size, body.rotation)
    lo, hi = ellipsoids_bounds(ells)
    return Shape(lo, hi, lambda p: inside_ellipsoids(p, ells), None)


def _mesh(body, resolve, where):
    path = Path(resolve(body.file))
    mesh = load_mesh(path, f"{where}.file")
    require_closed(mesh, path, f"{where}.file")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # overflow: reported below
        mesh = transform_mesh(mesh, body.scale, body.rotation, body.translation)
    reach = np.abs(np.asarray(mesh.vertices, dtype=np.float64)).max()
    if not np.isfinite(reach) or reach > MAX_COORDINATE:
        raise SceneError(
            f"{where}.scale: the placed mesh reaches {reach:.3g} m from the origin, more than "
            f"{MAX_COORDINATE:.0e} m; check scale and translation"
        )
    lo, hi = mesh.bounds
    return Shape(np.asarray(lo, np.float64), np.asarray(hi, np.float64), lambda p: inside_mesh(p, mesh),
                 abs(float(mesh.volume)), float(mesh.area))


_SHAPES = {"box": _box, "sphere": _sphere, "ellipsoid": _ellipsoid, "mesh": _mesh, "bunny": _bunny}


# --------------------------------------------------------------------------- mesh inside test


_inside_kernel = None


def _warp_inside_kernel():
    """Build (once) the Warp kernel that classifies points by winding number.

    Created lazily so that importing :mod:`abmpm.geometry` does not initialise Warp.
    """
    global _inside_kernel
    if _inside_kernel is None:
        @wp.kernel
        def inside_mesh_kernel(
            mesh: wp.uint64,
            points: wp.array(dtype=wp.vec3),
            inside: wp.array(dtype=wp.int32),
        ):
            tid = wp.tid()
            # The sign comes from the generalised winding number over the whole mesh,
            # which is robust to slightly imperfect (but closed) surfaces; max_dist
            # only bounds the closest-point search, not the sign.
            q = wp.mesh_query_point_sign_winding_number(mesh, points[tid], 1.0e30)
            if q.result and q.sign < 0.0:
                inside[tid] = 1

        _inside_kernel = inside_mesh_kernel
    return _inside_kernel


def _inside_mesh_warp(points: np.ndarray, mesh) -> np.ndarray:
    kernel = _warp_inside_kernel()
    device = "cpu"
    wmesh = wp.Mesh(
        points=wp.array(np.asarray(mesh.vertices, dtype=np.float32), dtype=wp.vec3, device=device),
        indices=wp.array(np.asarray(mesh.faces, dtype=np.int32).ravel(), dtype=wp.int32, device=device),
        support_winding_number=True,
    )
    pts = wp.array(points.astype(np.float32), dtype=wp.vec3, device=device)
    inside = wp.zeros(len(points), dtype=wp.int32, device=device)
    wp.launch(kernel, dim=len(points), inputs=[wmesh.id, pts, inside], device=device)
    return inside.numpy().astype(bool)


def inside_mesh(points, mesh) -> np.ndarray:
    """Boolean mask: which ``points`` (N, 3) lie inside the closed triangle ``mesh``.

    Uses a Warp winding-number query on the CPU (BVH-accelerated, fast for millions of
    points); falls back to trimesh's ray-based ``contains`` if Warp cannot run. A mesh
    whose faces all point inwards (negative volume) is flipped first, since the
    winding number of an inside-out surface is -1 inside.
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(p) == 0:
        return np.zeros(0, dtype=bool)
    if mesh.volume < 0:
        mesh = mesh.copy()
        mesh.invert()
    try:
        return _inside_mesh_warp(p, mesh)
    except Exception:  # pragma: no cover - Warp missing or unable to compile on this host
        return np.asarray(mesh.contains(p), dtype=bool)


# --------------------------------------------------------------------------- body sampling


def _fmt(v) -> str:
    return "(" + ", ".join(f"{x:.6g}" for x in v) + ")"


def _check_in_domain(lo, hi, settings, where: str) -> None:
    """Refuse a body whose bounding box crosses the domain walls.

    Particles outside the grid would be silently lost (or index out of bounds), so
    this is a scene error naming the body, the axis and both boxes.
    """
    dmin = np.asarray(settings.domain_min, dtype=np.float64)
    dmax = np.asarray(settings.domain_max, dtype=np.float64)
    tol = 1e-9 * float(np.max(dmax - dmin))
    bad = [a for a in range(3) if lo[a] < dmin[a] - tol or hi[a] > dmax[a] + tol]
    if bad:
        axes = ", ".join("xyz"[a] for a in bad)
        raise SceneError(
            f"{where}: body extends outside the domain (on axis {axes}: body bounds {_fmt(lo)} to {_fmt(hi)}, "
            f"domain {_fmt(dmin)} to {_fmt(dmax)})"
        )


def body_shape(body, resolve: Callable = lambda p: p, where: str = "bodies[0]") -> Shape:
    """A body's :class:`Shape`. Mesh bodies load (and check) their file here, so
    MeshError is raised before any sampling work."""
    try:
        make = _SHAPES[body.shape]
    except (AttributeError, KeyError):
        raise SceneError(f"{where}: unknown body shape {getattr(body, 'shape', None)!r}") from None
    return make(body, resolve, where)


def shape_bounds_and_inside(body, resolve: Callable = lambda p: p, where: str = "bodies[0]"):
    """``(lo, hi, inside)`` of a body: its exact bounding box and an inside test
    (``inside`` maps float64 points (N, 3) to a boolean mask)."""
    return body_shape(body, resolve, where)[:3]


def body_lattice(body, settings, resolve: Callable = lambda p: p, where: str = "bodies[0]",
                 shape: Shape | None = None):
    """``(shape, points)``: a body's :class:`Shape` (``shape`` where already read) and its
    unjittered lattice points (float64, (N, 3)), which its particles are jittered about."""
    shape = shape or body_shape(body, resolve, where)
    _check_in_domain(shape.lo, shape.hi, settings, where)
    # Clip to the domain so that rounding at a wall can never yield a point outside it.
    lo = np.maximum(shape.lo, settings.domain_min)
    hi = np.minimum(shape.hi, settings.domain_max)
    base = lattice_points(lo, hi, settings.dx, body.particles_per_cell, settings.domain_min)
    return shape, (base[shape.inside(base)] if len(base) else base)


def sample_body_volume(
    body,
    settings,
    rng: np.random.Generator,
    resolve: Callable = lambda p: p,
    where: str = "bodies[0]",
    jitter: float = JITTER,
) -> tuple[np.ndarray, float]:
    """Particle positions (N, 3, float32) filling ``body``, and the volume each stands for.

    ``settings`` supplies ``dx``, ``domain_min`` and ``domain_max``; ``resolve`` maps a
    mesh file path from the scene to a real path (``Scene.resolve``); ``where`` names
    the body in error messages. The same ``rng`` state gives identical output; ``jitter``
    scales the jitter (``jitter_points``) and not the random stream, so the count and the
    draws do not depend on it. The volume is ``particle_volume(dx, ppc)`` where the
    lattice fills the shape whole, else the shape's exact volume over the particle count
    (a box 0.25 m deep on a lattice of 0.02 m holds 13 layers, 0.26 m of cubes: 4% too
    much mass at that spacing, 1.3% at a third of it, so that adaptive and finest mode
    would start with different masses); the bunny keeps ``h**3`` (no closed form).
    """
    shape, kept = body_lattice(body, settings, resolve, where)
    ppc = body.particles_per_cell
    if len(kept) == 0:
        raise SceneError(f"{where}: body is smaller than the particle spacing; no particles sampled")
    volume = particle_volume(settings.dx, ppc)
    cubes = len(kept) * volume
    trusted = shape.volume is not None and (shape.area is None
                                            or abs(shape.volume - cubes) <= shape.area * lattice_spacing(settings.dx, ppc))
    if trusted and abs(shape.volume / cubes - 1.0) > EXACT_VOLUME_RTOL:
        volume = shape.volume / len(kept)
    return jitter_points(kept, lattice_spacing(settings.dx, ppc), rng, jitter).astype(np.float32), volume


def sample_body(*args, **kwargs) -> np.ndarray:
    """The positions of :func:`sample_body_volume` (the same arguments)."""
    return sample_body_volume(*args, **kwargs)[0]
