"""Adaptive refinement: who splits (Eq. 15, the kernel in sim/split.py), the surface
reconstruction before it (sim/reconstruct.py), fine-grid block activation, and merge.

The refined region B_s is a flag per coarse cell. A level-0 particle in a refined
cell becomes N_s = b^3 level-1 children on a sub-lattice of its own volume,
deformed by its F (docs/method.md, "Split").
"""

from __future__ import annotations

import time

import numpy as np
import warp as wp
from scipy import ndimage

from .colliders import PARTICLE_BAND, ColliderArrays, ColorField, color_point, near_surface
from .footprint import FOOTPRINT_REACH
from .grid import AMONG_FINE, BLOCK, ON_COARSE, Grid, GridSpec, cell_flag
from .parallel import CPU_NODE_CHUNK, Launcher, reset_reach
from .reconstruct import (
    DEFAULT_SURFACE_THRESHOLD,
    SurfaceField,
    add_surface_sums,
    family_shifts,
    keep_volume,
    scatter_surface_mass,
    smooth_surface_volume,
)
from .split import jitter_seed, split_particles
from .state import ParticleState
from .stencil import stencil_base
from .time_levels import cell_of

wp.set_module_options({"enable_backward": False})


@wp.kernel
def flag_splits(first: int, x: wp.array(dtype=wp.vec3), level: wp.array(dtype=wp.int32), g0: GridSpec,
                region: wp.array3d(dtype=wp.int32), flag: wp.array(dtype=wp.int32)):
    p = wp.tid() + first
    flag[p] = 0
    if level[p] != 0:
        return
    flag[p] = cell_flag(g0, region, x[p])


# A particle asks for the blocks of the nodes it reaches grown by ACTIVATION_MARGIN nodes
# on each side, and refinement runs again before any particle can have moved that far:
# every REFINE_EVERY steps, fewer where the CFL number lets REFINE_EVERY substeps move a
# particle farther (``refine_every``). A particle entering the region is split at most a
# few steps late, inside the region's halo.
REFINE_EVERY = 4
ACTIVATION_MARGIN = wp.constant(2)


def refine_every(cfl: float) -> int:
    """Steps between two refinements: at most REFINE_EVERY, and at most ACTIVATION_MARGIN /
    cfl (a substep moves a particle at most cfl fine cells, the time step's own limit), so
    that no level-1 particle outruns the margin of its blocks (docs/method.md, "Two levels")."""
    return max(1, min(REFINE_EVERY, int(int(ACTIVATION_MARGIN) / cfl + 1e-9)))


# A level-0 particle in a collider's band within BESIDE_CELLS coarse cells of the region
# (a cube around its cells) is moved by the fine grid (p2g_sparse; docs/method.md, "Where
# the fine grid moves coarse particles") and asks for the blocks of its footprint; until
# it has them (the next refinement) the coarse grid moves it. One cell: the coarse cells
# next to the region, where level-0 and level-1 material meet; 2 and 3 cells read better
# on the plate matrix but compress the coarse water at the edge of that zone in a deep
# tank on a plate
BESIDE_CELLS = 1


@wp.func
def want_blocks(g: GridSpec, lo: wp.vec3i, span: int, wanted: wp.array3d(dtype=wp.int32)):
    # every 4-node block holding a node of the cube lo .. lo + span - 1: nodes checked
    # every 3 along each axis, and the last one (several threads may write the same 1)
    steps = (span + 1) // 3 + 1
    for a in range(steps):
        i = wp.clamp(lo[0] + wp.min(3 * a, span - 1), 0, g.dims[0] - 1) >> 2
        for bb in range(steps):
            j = wp.clamp(lo[1] + wp.min(3 * bb, span - 1), 0, g.dims[1] - 1) >> 2
            for c in range(steps):
                k = wp.clamp(lo[2] + wp.min(3 * c, span - 1), 0, g.dims[2] - 1) >> 2
                if g.blocks[i, j, k] < 0:
                    wanted[i, j, k] = 1


@wp.kernel
def flag_particle_blocks(first: int, x: wp.array(dtype=wp.vec3), level: wp.array(dtype=wp.int32),
                         surface_body: wp.array(dtype=wp.int32), g: GridSpec, coarse: GridSpec,
                         beside: wp.array3d(dtype=wp.int32), wanted: wp.array3d(dtype=wp.int32)):
    p = wp.tid() + first
    if level[p] == g.level:  # its stencil's 3 nodes and the margin: 7 per axis
        want_blocks(g, stencil_base(g, x[p]) - wp.vec3i(ACTIVATION_MARGIN), 3 + 2 * ACTIVATION_MARGIN, wanted)
    elif surface_body[p] >= 0 and cell_flag(coarse, beside, x[p]) != 0:  # the nodes of its footprint
        X = (x[p] - g.origin) * g.inv_dx
        lo = wp.vec3i(int(wp.floor(X[0])), int(wp.floor(X[1])), int(wp.floor(X[2]))) - wp.vec3i(FOOTPRINT_REACH)
        want_blocks(g, lo, 2 + 2 * FOOTPRINT_REACH, wanted)


@wp.kernel
def allocate_blocks(g: GridSpec, wanted: wp.array3d(dtype=wp.int32), counter: wp.array(dtype=wp.int32)):
    # one thread per block: no race on the block table, slots from an atomic counter
    i, j, k = wp.tid()
    if wanted[i, j, k] != 0 and g.blocks[i, j, k] < 0:
        s = wp.atomic_add(counter, 0, 1)
        g.blocks[i, j, k] = s
        g.slot_block[s] = wp.vec3i(i, j, k)
    wanted[i, j, k] = 0


# A child outside the zone beside the region, in a coarse cell where level-0 mass is more
# than this share of the whole, moves with the coarse grid; a level-0 particle where level-1
# mass is, with the fine grid (``coarse_children``; docs/method.md, "Every particle with the
# grid that moves most of its cell"). Half: the grid that moves most of the cell's material.
COARSE_SHARE = 0.5


@wp.kernel
def cell_masses(first: int, x: wp.array(dtype=wp.vec3), level: wp.array(dtype=wp.int32), mass: wp.array(dtype=float),
                g: GridSpec, m0: wp.array(dtype=float), m1: wp.array(dtype=float)):
    # each level's mass per coarse cell (one CPU thread: Warp's CPU atomics are plain adds)
    p = wp.tid() + first
    if level[p] == 0:
        wp.atomic_add(m0, cell_of(g, x[p]), mass[p])
    else:
        wp.atomic_add(m1, cell_of(g, x[p]), mass[p])


@wp.kernel
def mark_coarse_children(first: int, x: wp.array(dtype=wp.vec3), level: wp.array(dtype=wp.int32), g: GridSpec,
                         m0: wp.array(dtype=float), m1: wp.array(dtype=float), beside: wp.array3d(dtype=wp.int32),
                         share: float, colliders: ColliderArrays, color: ColorField, cpic: int,
                         surface_point: wp.array(dtype=wp.vec3), surface_side: wp.array(dtype=wp.vec3),
                         surface_body: wp.array(dtype=wp.int32), on_fine: wp.array(dtype=wp.int32)):
    p = wp.tid() + first
    c = cell_of(g, x[p])
    if level[p] == 0:  # p2g_sparse moves it with the fine grid where its footprint is active
        on_fine[p] = wp.where(m1[c] > share * (m0[c] + m1[c]), AMONG_FINE, 0)
        return
    mark = int(0)
    if cell_flag(g, beside, x[p]) == 0:
        if m0[c] > share * (m0[c] + m1[c]):
            mark = ON_COARSE
    # a marked child with no color of its own (its band is PARTICLE_BAND fine cells) but
    # within the coarse band of a surface is colored on the coarse grid now, so that its
    # first coarse transfers keep to its side (CPIC's masks, the crossing test)
    if mark == ON_COARSE and cpic != 0 and surface_body[p] < 0 and near_surface(color, g, x[p]):
        col = color_point(colliders, g, x[p], PARTICLE_BAND * g.dx, wp.vec3(0.0))
        surface_point[p] = col.surface_point
        surface_side[p] = col.surface_side
        surface_body[p] = col.body
    on_fine[p] = mark


class Refiner:
    """Owns the refined region and keeps the particles and the fine grid in step with it."""

    def __init__(self, fine: Grid, coarse: Grid, factor: int, device, reconstruct: bool = False,
                 surface_threshold: float = DEFAULT_SURFACE_THRESHOLD, launcher: Launcher | None = None,
                 seed: int = 0):
        self.launcher = launcher or Launcher(device, 1)
        self.fine = fine
        self.coarse = coarse
        self.b = factor
        self.jitter_seed = jitter_seed(seed)
        self.device = device
        cells = tuple(d - 1 for d in coarse.dims)
        self.region_cells = np.zeros(cells, dtype=bool)
        self.region = wp.zeros(cells, dtype=wp.int32, device=device)
        # the region grown by BESIDE_CELLS: the level-0 band particles the fine grid moves
        # (p2g_sparse) and which ask for their footprints' blocks (flag_particle_blocks)
        self.beside = wp.zeros(cells, dtype=wp.int32, device=device)
        self._cell_m = [wp.zeros(int(np.prod(cells)), dtype=float, device=device) for _ in range(2)]  # coarse_children
        # surface reconstruction: Eq. 16's node masses and gradients on the coarse grid
        self.surface = SurfaceField()
        self.surface.enabled = int(reconstruct)
        self.surface.threshold = float(surface_threshold)
        nodes = coarse.capacity if reconstruct else 1
        self.surface.grad = wp.zeros(nodes, dtype=wp.vec3, device=device)
        self.surface.volume = wp.zeros(nodes, dtype=float, device=device)
        self.surface.smooth = wp.zeros(nodes, dtype=float, device=device)
        self.surface.near = wp.zeros(cells if reconstruct else (1, 1, 1), dtype=wp.int32, device=device)
        self.surface.read = wp.zeros(cells if reconstruct else (1, 1, 1), dtype=wp.int32, device=device)
        self.read_box = (wp.vec3i(0, 0, 0), wp.vec3i(0, 0, 0))  # set_region: the nodes smooth_surface_volume visits
        self._points = wp.HashGrid(64, 64, 64, device=device) if reconstruct else None  # neighbours: who is on top
        self._shift = wp.zeros(1, dtype=wp.vec3, device=device)
        self._flatten = wp.zeros(1, dtype=wp.vec3, device=device)  # the children's jitter along the surface (sim/split.py)
        self.reconstruct_seconds = 0.0  # CPU time spent reconstructing (for the benchmark)
        self.wanted = wp.zeros(fine.spec.blocks.shape, dtype=wp.int32, device=device)
        self.counter = wp.zeros(1, dtype=wp.int32, device=device)
        self._flag = wp.zeros(1, dtype=wp.int32, device=device)
        self._offset = wp.zeros(1, dtype=wp.int32, device=device)
        self.splits = 0

    def set_region(self, cells: np.ndarray) -> None:
        """Refined coarse cells (bool array over the coarse cells); their fine blocks
        are activated now, with the stencil reach of particles at the region's edge."""
        self.region_cells = np.asarray(cells, dtype=bool)
        self.region.assign(self.region_cells.astype(np.int32))
        cube = np.ones((3, 3, 3), dtype=bool)
        beside = ndimage.binary_dilation(self.region_cells, cube, iterations=BESIDE_CELLS)
        self.beside.assign(beside.astype(np.int32))
        if self.surface.enabled:
            # who scatters for Eq. 16: particles within the stencil reach (2 cells) of
            # a node that a splitting parent reads (1 cell beyond the region)
            self.surface.near.assign(ndimage.binary_dilation(self.region_cells, iterations=3).astype(np.int32))
            # the nodes a parent's occupied fraction reads (its stencil, and that of a point up
            # to a cell away from it): up to 3 cells from its own in any direction
            read = ndimage.binary_dilation(self.region_cells, cube, iterations=3)
            self.surface.read.assign(read.astype(np.int32))
            # the nodes smooth_surface_volume visits: every node whose cell (the node's
            # coordinates, clamped to the last cell) is read
            idx = np.argwhere(read)
            lo = idx.min(0) if len(idx) else np.zeros(3, dtype=int)
            hi = np.minimum(idx.max(0) + 1, np.array(self.coarse.dims) - 1) if len(idx) else lo - 1
            self.read_box = (wp.vec3i(*(int(v) for v in lo)), wp.vec3i(*(int(v) for v in hi - lo + 1)))
        wanted = np.zeros(self.wanted.shape, dtype=np.int32)
        idx = np.argwhere(self.region_cells)
        if len(idx):
            # coarse cell c spans fine nodes c b + shift ... (c + 1) b + shift: each grid's
            # node 0 lies GRID_PAD of its own cells outside the domain, so the fine grid's
            # starts (b - 1) GRID_PAD fine nodes nearer it (until 2026-11-28 the shift was
            # left out, and the blocks went to the region moved 3 (b - 1) fine nodes, 1.5-2.25
            # coarse cells, up every axis: docs/method.md, "The region's blocks were misplaced")
            shift = np.rint((self.coarse.origin - self.fine.origin) / self.fine.dx).astype(int)
            lo = np.maximum(idx * self.b + shift - 2, 0) // BLOCK
            hi = np.minimum((idx + 1) * self.b + shift + 2, np.array(self.fine.dims) - 1) // BLOCK
            for a, bb in zip(lo, hi):
                wanted[a[0]:bb[0] + 1, a[1]:bb[1] + 1, a[2]:bb[2] + 1] = 1
        self.wanted.assign(wanted)
        self._allocate()

    def _allocate(self) -> int:
        g = self.fine
        wp.launch(allocate_blocks, dim=self.wanted.shape, inputs=[g.spec, self.wanted, self.counter],
                  device=self.device)
        old = g.active_slots
        g.grow(int(self.counter.numpy()[0]))
        return old

    def split(self, state: ParticleState, next_id: int, colliders: ColliderArrays, materials: wp.array,
              skip: int = 0) -> int:
        """Split the level-0 particles inside the region; returns how many were split.
        The first ``skip`` particles are far from the region (a time step per level's
        slow set, sim/time_levels.py): no pass visits them but the surface field's."""
        n = state.count
        if n == 0 or not self.region_cells.any():
            return 0
        if self._flag.shape[0] < n:
            self._flag = wp.zeros(2 * n, dtype=wp.int32, device=self.device)
            self._offset = wp.zeros(2 * n, dtype=wp.int32, device=self.device)
        if skip:
            self._flag[:skip].zero_()
        self.launcher.launch(flag_splits, n - skip, [state.x, state.level, self.coarse.spec, self.region, self._flag],
                             start=skip)
        wp.utils.array_scan(self._flag, self._offset, inclusive=False)
        last = self._offset.numpy()[n - 1] + self._flag.numpy()[n - 1]  # host sync: the new count
        n_split = int(last)
        if n_split == 0:
            return 0
        ns = self.b**3
        if self.surface.enabled:
            t0 = time.perf_counter()
            self.surface.grad.zero_()
            self.surface.volume.zero_()
            f, spec = self.surface, self.coarse.spec
            private = self.launcher.private_grids("surface", f.grad, f.volume)
            # every particle's mass, the slow set's too: it may lie two coarse cells from a
            # parent at the region's edge, within the smoothed field that parent reads, where
            # leaving it out would put a surface (and move children onto it) inside the material
            self.launcher.launch(scatter_surface_mass, n, lambda part, first, count: [
                state.arrays(), materials, spec, f.near, *private.parts[part], private.reach[part]])
            if private.extra > 0:
                chunk = CPU_NODE_CHUNK
                self.launcher.launch(add_surface_sums, -(-self.coarse.node_count // chunk),
                                     [self.coarse.node_count, chunk, private.sums, f], min_range=64)
                self.launcher.launch(reset_reach, private.extra + 1, [private.bounds])
            box_lo, box_shape = self.read_box
            self.launcher.launch(smooth_surface_volume, box_shape[0] * box_shape[1] * box_shape[2],
                                 [self.coarse.spec, self.surface, box_lo, box_shape])
            self._points.build(state.x[:n], self.coarse.dx)
            if self._shift.shape[0] < n:
                self._shift = wp.zeros(2 * n, dtype=wp.vec3, device=self.device)
                self._raw_shift = wp.zeros(2 * n, dtype=wp.vec3, device=self.device)
                self._flatten = wp.zeros(2 * n, dtype=wp.vec3, device=self.device)
            self.launcher.launch(family_shifts, n - skip, [self._flag, state.arrays(), materials, self.surface,
                                                           self.coarse.spec, self.b, self._points.id,
                                                           self._raw_shift, self._flatten],
                                 start=skip)
            self.launcher.launch(keep_volume, n - skip, [self._flag, state.x, self._points.id, 3.0 * self.coarse.dx,
                                                         self._raw_shift, self._shift], start=skip)
            if wp.get_device(self.device).is_cpu:  # CPU launches are synchronous: this is the work itself
                self.reconstruct_seconds += time.perf_counter() - t0
        state.reserve(n + n_split * (ns - 1))
        self.launcher.launch(split_particles, n - skip, [self._flag, self._offset, n, self.b, next_id, state.arrays(),
                                                         materials, colliders, self.fine.spec, self.surface.enabled,
                                                         self._shift, self._flatten, self.jitter_seed], start=skip)
        state.count = n + n_split * (ns - 1)
        self.splits += n_split
        return n_split

    def coarse_children(self, state: ParticleState, on_fine: wp.array, colliders: ColliderArrays, color: ColorField,
                        cpic: bool, skip: int = 0) -> None:
        """Mark in ``on_fine`` (ON_COARSE, else 0) the level-1 particles the coarse grid moves:
        outside the zone beside the region (``beside``), in a coarse cell whose mass is more than
        COARSE_SHARE level 0; one with no color within the coarse grid's band of a collider
        (``color``: the coarse grid's) is colored on that grid. The other way round, a level-0
        particle in a coarse cell whose mass is more than COARSE_SHARE level 1 is marked
        AMONG_FINE (``p2g_sparse`` moves it with the fine grid where its footprint is active).
        Each level's J follows the grid that moves it; a child among coarse particles, moved by
        the fine grid, is squeezed by coarse material whose pressure that grid's nodes do not
        balance, and the converse (docs/method.md). The first pass of every substep. The first
        ``skip`` particles (the slow set while its step is open) are left out: they lie more
        than GUARD_HALO coarse cells from every level-1 particle, so no cell they share holds
        level-1 mass, and no pass of their step reads their marks."""
        n = state.count - skip
        if n <= 0:
            return
        self._cell_m[0].zero_()
        self._cell_m[1].zero_()
        wp.launch(cell_masses, n, [skip, state.x, state.level, state.mass, self.coarse.spec, *self._cell_m],
                  device=self.device)
        self.launcher.launch(mark_coarse_children, n, [state.x, state.level, self.coarse.spec, *self._cell_m,
                                                       self.beside, COARSE_SHARE, colliders, color, int(cpic),
                                                       state.surface_point, state.surface_side, state.surface_body,
                                                       on_fine], start=skip)

    def activate(self, state: ParticleState, skip: int = 0) -> int:
        """Give fine-grid blocks to level-1 particles that reach beyond the active ones
        (the first ``skip`` are level 0); returns the first new slot."""
        self.launcher.launch(flag_particle_blocks, state.count - skip,
                             [state.x, state.level, state.surface_body, self.fine.spec, self.coarse.spec, self.beside,
                              self.wanted], start=skip)
        return self._allocate()


def compact(a: dict[str, np.ndarray], idx: np.ndarray, group: np.ndarray, k: int) -> np.ndarray:
    """Per group of the particles ``idx`` (``group``: 0 .. k - 1 each): is every member within one
    parent lattice spacing (the cube root of the group's summed volume) of the group's centre of
    mass, so that merged it stands where its members did."""
    m = a["mass"][idx].astype(np.float64)
    M = np.bincount(group, m, minlength=k)
    com = np.stack([np.bincount(group, m * a["x"][idx, d], minlength=k) for d in range(3)], axis=1) / M[:, None]
    dist = np.linalg.norm(a["x"][idx] - com[group], axis=1)
    spread = np.zeros(k)
    np.maximum.at(spread, group, dist)
    return spread <= np.cbrt(np.bincount(group, a["volume"][idx].astype(np.float64), minlength=k))


def merge_families(a: dict[str, np.ndarray], keep_fine: np.ndarray, b: int) -> tuple[dict[str, np.ndarray], int]:
    """Merge back families of split particles (beyond the paper; switchable).

    A family (the b^3 children of one parent) merges into one level-0 particle when
    none of its children is flagged in ``keep_fine`` (per particle: inside the region
    grown by the hysteresis margin) and it is still compact: every child within one
    parent lattice spacing of the family's centre of mass. The merged particle has
    the summed mass and volume, the centre of mass, the mass-averaged velocity
    (linear momentum conserved to round-off), and mass-averaged C, F and history
    state; it takes back the parent's id. Host-side, once per frame.
    """
    ns = b**3
    fine = (a["level"] == 1) & (a["family"] >= 0)
    if not fine.any():
        return a, 0
    fam_ids, inv, counts = np.unique(a["family"][fine], return_inverse=True, return_counts=True)
    idx = np.nonzero(fine)[0]
    blocked = np.zeros(len(fam_ids), dtype=bool)
    np.logical_or.at(blocked, inv, keep_fine[idx])
    ok = (counts == ns) & ~blocked & compact(a, idx, inv, len(fam_ids))
    if not ok.any():
        return a, 0
    sel = ok[inv]  # children (positions in idx) that merge
    members, groups = idx[sel], inv[sel]
    merged_ids = np.nonzero(ok)[0]
    remap = np.full(len(fam_ids), -1)
    remap[merged_ids] = np.arange(len(merged_ids))
    g = remap[groups]
    k = len(merged_ids)
    mm = a["mass"][members].astype(np.float64)
    Mg = np.bincount(g, mm, minlength=k)

    def mass_average(field):
        f = a[field][members].astype(np.float64).reshape(len(members), -1)
        out = np.stack([np.bincount(g, mm * f[:, c], minlength=k) for c in range(f.shape[1])], axis=1) / Mg[:, None]
        return out.reshape((k,) + a[field].shape[1:]).astype(a[field].dtype)

    first = np.zeros(k, dtype=np.int64)
    first[g[::-1]] = members[::-1]  # one representative child per family
    new = {
        "x": mass_average("x"), "v": mass_average("v"), "C": mass_average("C"), "F": mass_average("F"),
        "history": mass_average("history"),
        "mass": Mg.astype(a["mass"].dtype),
        "volume": np.bincount(g, a["volume"][members].astype(np.float64), minlength=k).astype(a["volume"].dtype),
        "material": a["material"][first], "level": np.zeros(k, dtype=a["level"].dtype),
        "id": fam_ids[merged_ids].astype(a["id"].dtype), "family": np.full(k, -1, dtype=a["family"].dtype),
        "surface_point": a["surface_point"][first], "surface_side": a["surface_side"][first], "surface_body": np.full(k, -1, dtype=a["surface_body"].dtype),
    }
    stay = np.ones(len(a["x"]), dtype=bool)
    stay[members] = False
    out = {name: np.concatenate([a[name][stay], new[name]]) for name in a}
    return out, k


def group_strays(a: dict[str, np.ndarray], keep_fine: np.ndarray, b: int, may_group: np.ndarray,
                 origin: np.ndarray) -> tuple[np.ndarray, int]:
    """Children whose families tore apart, made into new families by place (beyond the paper,
    after Gao et al.'s merging by proximity, which the paper leaves optional; host-side).

    A level-1 particle of a material with ``may_group`` (per material: fluids, which keep no F
    of their lattice) and not flagged in ``keep_fine`` is a stray. Strays are binned by the cell
    of their parents' lattice (from ``origin``, spacing h = b V^(1/3), V a child's volume), material
    and V. In every cell that holds at least b^3 of them, the b^3 nearest its centre (ties by id)
    become one family, named after the least id among them, if they are as compact as
    ``merge_families`` asks (each within h of their centre of mass): it then merges them as it
    merges any family (mass exact, momentum to round-off), and the merged particle goes on under
    that child's id. Only full groups: a parent's worth of mass in a parent's volume, never a
    light particle among coarse ones. Returns the particles' families with the new ones (a copy;
    ``a`` is not changed) and the number of new families."""
    ns = b**3
    family = a["family"].copy()
    idx = np.nonzero((a["level"] == 1) & ~keep_fine & may_group[a["material"]])[0]
    if len(idx) < ns:
        return family, 0
    volumes, kind = np.unique(a["volume"][idx], return_inverse=True)  # one lattice per child volume
    h = (b * np.cbrt(volumes.astype(np.float64)))[kind.ravel()][:, None]
    cell = np.floor((a["x"][idx].astype(np.float64) - origin) / h).astype(np.int64)
    _, key = np.unique(np.column_stack([cell, a["material"][idx], kind.ravel()]), axis=0, return_inverse=True)
    key = key.ravel()
    dist = np.linalg.norm(a["x"][idx] - (origin + (cell + 0.5) * h), axis=1)
    order = np.lexsort((a["id"][idx], dist, key))
    start = np.r_[0, np.flatnonzero(np.diff(key[order])) + 1]
    counts = np.diff(np.r_[start, len(order)])
    rank = np.arange(len(order)) - np.repeat(start, counts)
    chosen = idx[order[np.repeat(counts >= ns, counts) & (rank < ns)]].reshape(-1, ns)  # a full cell's b^3 nearest
    chosen = chosen[compact(a, chosen.ravel(), np.repeat(np.arange(len(chosen)), ns), len(chosen))]  # as merge_families
    family[chosen] = a["id"][chosen].min(axis=1)[:, None]
    return family, len(chosen)
