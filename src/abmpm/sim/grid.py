"""Background grid: one type for every level.

A :class:`Grid` owns its spacing, its origin and its node arrays. Level 0 uses
spacing dx over the whole domain; the subdivided level (dx/b) will use the same
type with block-sparse storage. Transfer kernels take the :class:`GridSpec`
struct, so the same kernels serve any spacing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import warp as wp

# Nodes outside the domain box on each side: a particle on the wall plane still has
# its 3x3x3 quadratic B-spline stencil inside the grid.
GRID_PAD = 3

from .boundary import BOUNDARY_IDS as WALL_IDS


@wp.struct
class GridSpec:
    origin: wp.vec3  # position of node (0, 0, 0)
    dx: float
    inv_dx: float
    dims: wp.vec3i  # node counts per axis
    domain_lo: wp.vec3  # wall planes
    domain_hi: wp.vec3
    wall_type_lo: wp.vec3i  # per axis: type of the wall at domain_lo / domain_hi
    wall_type_hi: wp.vec3i
    friction_lo: wp.vec3  # Coulomb friction coefficients, same layout
    friction_hi: wp.vec3
    gravity: wp.vec3


@dataclass
class Grid:
    spec: GridSpec
    level: int
    mv: wp.array3d  # momentum during P2G
    m: wp.array3d  # mass
    v: wp.array3d  # velocity after the grid update (read by G2P)
    colour: object = None  # ColourField of the colliders (CPIC), set by the solver

    @property
    def dims(self) -> tuple[int, int, int]:
        d = self.spec.dims
        return int(d[0]), int(d[1]), int(d[2])

    @property
    def dx(self) -> float:
        return float(self.spec.dx)

    @staticmethod
    def dense(domain_lo, domain_hi, dx: float, level: int, gravity, walls: dict, device):
        """Dense grid over the domain; ``walls`` maps face names ('x_min', ...) to
        (type, friction)."""
        lo = np.asarray(domain_lo, dtype=np.float64)
        hi = np.asarray(domain_hi, dtype=np.float64)
        cells = np.ceil((hi - lo) / dx - 1e-9).astype(int)
        dims = tuple(int(c) + 2 * GRID_PAD + 1 for c in cells)
        spec = GridSpec()
        spec.origin = wp.vec3(*(lo - GRID_PAD * dx))
        spec.dx = float(dx)
        spec.inv_dx = float(1.0 / dx)
        spec.dims = wp.vec3i(*dims)
        spec.domain_lo = wp.vec3(*lo)
        spec.domain_hi = wp.vec3(*hi)
        spec.wall_type_lo = wp.vec3i(*[WALL_IDS[walls[f"{a}_min"][0]] for a in "xyz"])
        spec.wall_type_hi = wp.vec3i(*[WALL_IDS[walls[f"{a}_max"][0]] for a in "xyz"])
        spec.friction_lo = wp.vec3(*[float(walls[f"{a}_min"][1]) for a in "xyz"])
        spec.friction_hi = wp.vec3(*[float(walls[f"{a}_max"][1]) for a in "xyz"])
        spec.gravity = wp.vec3(*gravity)
        return Grid(
            spec=spec,
            level=level,
            mv=wp.zeros(dims, dtype=wp.vec3, device=device),
            m=wp.zeros(dims, dtype=float, device=device),
            v=wp.zeros(dims, dtype=wp.vec3, device=device),
        )

    def node_positions(self) -> np.ndarray:
        """(nx, ny, nz, 3) world positions of the nodes (host, for tests and plots)."""
        o = np.array([self.spec.origin[i] for i in range(3)], dtype=np.float64)
        idx = np.stack(np.meshgrid(*[np.arange(n) for n in self.dims], indexing="ij"), axis=-1)
        return o + idx * self.dx


def cells_across(lo, hi, dx) -> int:
    return int(math.ceil(max(h - l for l, h in zip(lo, hi)) / dx))
