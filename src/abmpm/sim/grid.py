"""Background grids: one type for both levels.

A :class:`Grid` owns its spacing, its origin and its node storage. Node data live
in flat arrays addressed through :func:`node_index`:

* dense (level 0, spacing dx): index = (i ny + j) nz + k over the whole domain;
* block-sparse (level 1, spacing dx/b): the domain is cut into 4x4x4-node blocks;
  a small dense table maps a block to a slot in a pool of active blocks, or to -1.
  Blocks are activated from the refined region and from level-1 particles; memory
  and time follow them, not the domain volume. Slots are kept once given, so the
  color distance field of a block is built once for static colliders.

Transfer kernels take the :class:`GridSpec` struct, so the same code serves any
spacing and either storage.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from .boundary import BOUNDARY_IDS as WALL_IDS

wp.set_module_options({"enable_backward": False})

# Nodes outside the domain box on each side: a particle on the wall plane still has
# its 3x3x3 quadratic B-spline stencil inside the grid.
GRID_PAD = 3
BLOCK = 4  # nodes per block side (sparse grids)
BLOCK_NODES = BLOCK**3
# The adaptive coarse grid's overlap marks (P2G): a node that level-0 particles reach
# (where level-1 particles add to it, Eq. 8), and one that level-1 material reached
# too (its collider contact band is then a fine cell, grid_update)
REACHED_BY_LEVEL0 = wp.constant(1)
HOLDS_LEVEL1 = wp.constant(2)
# the solver's per-particle on_fine marks (bit flags): 1 a level-0 particle the fine grid moves (p2g_sparse),
# ON_COARSE a level-1 particle the coarse grid moves, AMONG_FINE a level-0 particle whose coarse cell
# holds mostly level-1 mass (both Refiner.coarse_children)
ON_COARSE = wp.constant(2)
AMONG_FINE = wp.constant(4)


@wp.func
def moving_level(on_fine: wp.array(dtype=wp.int32), p: int, level: int):
    """The level of the grid that moves particle p of ``level`` (its own unless ``on_fine``
    marks it; an ``on_fine`` of length 1, where no fine grid exists, marks no one)."""
    if on_fine.shape[0] <= p:
        return level
    if level == 0 and (on_fine[p] & 1) != 0:
        return 1
    if level == 1 and on_fine[p] == ON_COARSE:
        return 0
    return level


@wp.struct
class GridSpec:
    origin: wp.vec3  # position of node (0, 0, 0)
    dx: float
    inv_dx: float
    dims: wp.vec3i  # node counts per axis
    level: int  # particles of this level gather from this grid
    domain_lo: wp.vec3  # wall planes
    domain_hi: wp.vec3
    wall_type_lo: wp.vec3i  # per axis: type of the wall at domain_lo / domain_hi
    wall_type_hi: wp.vec3i
    friction_lo: wp.vec3  # Coulomb friction coefficients, same layout
    friction_hi: wp.vec3
    gravity: wp.vec3
    sparse: int
    wall_images: int  # 1: particles near a wall add their images' stress (sim/wall_images.py)
    family: int  # children per axis of a split (b) on the fine grid, 1 on the coarse (sim/footprint.py)
    blocks: wp.array3d(dtype=wp.int32)  # block -> slot, -1 inactive (sparse only)
    slot_block: wp.array(dtype=wp.vec3i)  # slot -> block coordinates (sparse only)


@wp.func
def node_index(g: GridSpec, i: int, j: int, k: int):
    """Flat storage index of node (i, j, k); -1 for an inactive node of a sparse grid."""
    if g.sparse == 0:
        return dense_node_index(g, i, j, k)
    s = g.blocks[i >> 2, j >> 2, k >> 2]
    if s < 0:
        return -1
    return s * BLOCK_NODES + ((i & 3) * BLOCK + (j & 3)) * BLOCK + (k & 3)


@wp.func
def dense_node_index(g: GridSpec, i: int, j: int, k: int):
    """node_index of a dense grid, for kernels compiled for dense grids only (the
    run-time test of ``g.sparse`` in the 27-node loops cost ~10% of the CPU P2G)."""
    return (i * g.dims[1] + j) * g.dims[2] + k


vec8i = wp.types.vector(length=8, dtype=wp.int32)


@wp.func
def stencil_slots(g: GridSpec, base: wp.vec3i):
    """Slots of the (at most) 2x2x2 blocks a 3x3x3 stencil at ``base`` spans (and a
    footprint of up to 5 nodes per axis too): one table lookup per block instead of one
    per node (sparse grids)."""
    s = vec8i()
    b0 = base[0] >> 2
    b1 = base[1] >> 2
    b2 = base[2] >> 2
    for a in range(2):
        for b in range(2):
            for c in range(2):
                i = wp.min(b0 + a, g.blocks.shape[0] - 1)
                j = wp.min(b1 + b, g.blocks.shape[1] - 1)
                k = wp.min(b2 + c, g.blocks.shape[2] - 1)
                s[a * 4 + b * 2 + c] = g.blocks[i, j, k]
    return s


@wp.func
def stencil_node(g: GridSpec, slots: vec8i, base: wp.vec3i, i: int, j: int, k: int):
    """node_index of stencil node base + (i, j, k) of a sparse grid, from the
    stencil's block slots."""
    x = base[0] + i
    y = base[1] + j
    z = base[2] + k
    s = slots[((x >> 2) - (base[0] >> 2)) * 4 + ((y >> 2) - (base[1] >> 2)) * 2 + ((z >> 2) - (base[2] >> 2))]
    if s < 0:
        return -1
    return s * BLOCK_NODES + ((x & 3) * BLOCK + (y & 3)) * BLOCK + (z & 3)


@wp.func
def node_coords(g: GridSpec, n: int):
    """Inverse of node_index for a storage index n."""
    if g.sparse == 0:
        k = n % g.dims[2]
        j = (n // g.dims[2]) % g.dims[1]
        return wp.vec3i(n // (g.dims[1] * g.dims[2]), j, k)
    b = g.slot_block[n >> 6]
    local = n & 63
    return wp.vec3i(b[0] * BLOCK + (local >> 4), b[1] * BLOCK + ((local >> 2) & 3), b[2] * BLOCK + (local & 3))


@wp.func
def node_position(g: GridSpec, c: wp.vec3i):
    return g.origin + wp.vec3(float(c[0]), float(c[1]), float(c[2])) * g.dx


@wp.func
def nearest_node_coords(g: GridSpec, x: wp.vec3):
    """Coordinates of the node nearest to x, clamped into the grid (any x, even NaN,
    gives a node inside it)."""
    X = (x - g.origin) * g.inv_dx
    return wp.vec3i(wp.clamp(int(X[0] + 0.5), 0, g.dims[0] - 1), wp.clamp(int(X[1] + 0.5), 0, g.dims[1] - 1),
                    wp.clamp(int(X[2] + 0.5), 0, g.dims[2] - 1))


@wp.func
def cell_flag(g: GridSpec, cells: wp.array3d(dtype=wp.int32), x: wp.vec3):
    """The value of a per-cell array of grid ``g`` (one entry per cell) at the cell
    holding x, clamped into the array (a region's flags and the masks grown from them)."""
    X = (x - g.origin) * g.inv_dx
    return cells[wp.clamp(int(X[0]), 0, cells.shape[0] - 1), wp.clamp(int(X[1]), 0, cells.shape[1] - 1),
                 wp.clamp(int(X[2]), 0, cells.shape[2] - 1)]


@dataclass
class Grid:
    spec: GridSpec
    mv: wp.array  # momentum during P2G (flat)
    m: wp.array  # mass
    v: wp.array  # velocity after the grid update (read by G2P)
    color: object = None  # ColorField of the colliders (CPIC), set by the solver
    active_slots: int = 0  # sparse: blocks in use

    @property
    def dims(self) -> tuple[int, int, int]:
        d = self.spec.dims
        return int(d[0]), int(d[1]), int(d[2])

    @property
    def dx(self) -> float:
        return float(self.spec.dx)

    @property
    def origin(self) -> np.ndarray:
        """Position of node (0, 0, 0), the corner of cell (0, 0, 0)."""
        return np.array([self.spec.origin[a] for a in range(3)], dtype=np.float64)

    @property
    def level(self) -> int:
        return int(self.spec.level)

    @property
    def name(self) -> str:
        """"coarse" (level 0, spacing dx) or "fine" (level 1, dx/b), for messages."""
        return "coarse" if self.level == 0 else "fine"

    @property
    def sparse(self) -> bool:
        return bool(self.spec.sparse)

    @property
    def node_count(self) -> int:
        """Nodes in storage: all of a dense grid, the active blocks of a sparse one."""
        return self.active_slots * BLOCK_NODES if self.sparse else int(np.prod(self.dims))

    @property
    def capacity(self) -> int:
        return self.m.shape[0]

    @staticmethod
    def create(domain_lo, domain_hi, dx: float, level: int, gravity, walls: dict, device,
               sparse: bool = False, capacity_blocks: int = 64, wall_images: bool = False, family: int = 1):
        """Grid over the domain plus GRID_PAD cells; ``walls`` maps face names
        ('x_min', ...) to (type, friction)."""
        lo = np.asarray(domain_lo, dtype=np.float64)
        hi = np.asarray(domain_hi, dtype=np.float64)
        cells = np.ceil((hi - lo) / dx - 1e-9).astype(int)
        dims = tuple(int(c) + 2 * GRID_PAD + 1 for c in cells)
        spec = GridSpec()
        spec.origin = wp.vec3(*(lo - GRID_PAD * dx))
        spec.dx = float(dx)
        spec.inv_dx = float(1.0 / dx)
        spec.dims = wp.vec3i(*dims)
        spec.level = int(level)
        spec.domain_lo = wp.vec3(*lo)
        spec.domain_hi = wp.vec3(*hi)
        spec.wall_type_lo = wp.vec3i(*[WALL_IDS[walls[f"{a}_min"][0]] for a in "xyz"])
        spec.wall_type_hi = wp.vec3i(*[WALL_IDS[walls[f"{a}_max"][0]] for a in "xyz"])
        spec.friction_lo = wp.vec3(*[float(walls[f"{a}_min"][1]) for a in "xyz"])
        spec.friction_hi = wp.vec3(*[float(walls[f"{a}_max"][1]) for a in "xyz"])
        spec.gravity = wp.vec3(*gravity)
        spec.sparse = int(sparse)
        spec.wall_images = int(wall_images)
        spec.family = int(family)
        if sparse:
            bdims = tuple(-(-d // BLOCK) for d in dims)
            spec.blocks = wp.full(bdims, -1, dtype=wp.int32, device=device)
            spec.slot_block = wp.zeros(int(np.prod(bdims)), dtype=wp.vec3i, device=device)
            n = capacity_blocks * BLOCK_NODES
        else:
            spec.blocks = wp.zeros((1, 1, 1), dtype=wp.int32, device=device)
            spec.slot_block = wp.zeros(1, dtype=wp.vec3i, device=device)
            n = int(np.prod(dims))
        return Grid(
            spec=spec,
            mv=wp.zeros(n, dtype=wp.vec3, device=device),
            m=wp.zeros(n, dtype=float, device=device),
            v=wp.zeros(n, dtype=wp.vec3, device=device),
        )

    def grow(self, slots: int) -> bool:
        """Make room for ``slots`` active blocks (sparse); True if storage moved."""
        self.active_slots = slots
        need = slots * BLOCK_NODES
        if need <= self.capacity:
            return False
        cap = max(need, 2 * self.capacity)
        for name in ("mv", "m", "v"):
            old = getattr(self, name)
            new = wp.zeros(cap, dtype=old.dtype, device=old.device)
            wp.copy(new, old, count=old.shape[0])
            setattr(self, name, new)
        return True
