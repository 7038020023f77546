"""The adaptive-boundary MPM step, in one place (paper Algorithm 1).

``MPMSolver.step(state, dt, time)`` is the whole step:

1. move the colliders to ``time`` and rebuild their color distance field;
2. adaptive mode: split the level-0 particles that entered the refined region
   (Eq. 15), move the children of surface parents onto the parent-level surface
   (Eqs. 16-20), and give the fine grid the blocks its particles need;
3. P2G of every particle to every grid, compatible nodes only (Eqs. 8-10);
4. grid update: gravity, domain walls, collider contact (Eqs. 3-4, 22);
5. G2P of each particle from its own level's grid, with boundary velocities at
   incompatible nodes (Eqs. 11-12, 23-25), deformation update and return mapping
   (Eqs. 7, 13-14), advection that never crosses a collider.

Everything else (sampling, output, diagnostics, time stepping) lives outside.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import warp as wp

from . import transfer
from .boundary import FACES
from .colliders import (
    ColliderSet,
    color_field,
    color_particles,
    empty_colliders,
    grow_color_field,
)
from .grid import Grid
from .materials import MaterialParams
from .parallel import Launcher
from .reconstruct import DEFAULT_SURFACE_THRESHOLD
from .refine import REFINE_EVERY, Refiner
from .state import FIELDS, ParticleState

wp.set_module_options({"enable_backward": False})


@dataclass
class SolverConfig:
    domain_lo: tuple[float, float, float]
    domain_hi: tuple[float, float, float]
    dx: float  # spacing of the coarsest grid
    gravity: tuple[float, float, float] = (0.0, -9.81, 0.0)
    # face name ('x_min' ... 'z_max') -> (wall type, friction); missing faces: separate, 0
    walls: dict | None = None
    # refinement factor b of a block-sparse level-1 grid (adaptive mode), or None
    refine_factor: int | None = None
    # level the single dense grid serves (1 in finest mode, where every particle is fine)
    base_level: int = 0
    # surface particle reconstruction after each split (paper Section 4.3), and its
    # t_p (Eq. 16) in units of (mass of a full coarse cell) / dx
    reconstruct: bool = False
    surface_threshold: float = DEFAULT_SURFACE_THRESHOLD
    # CPU threads for the transfers (None: ABMPM_THREADS, else every core); CUDA: ignored
    threads: int | None = None


class MPMSolver:
    def __init__(self, config: SolverConfig, materials: list[MaterialParams], device,
                 colliders: ColliderSet | None = None):
        self.config = config
        self.device = device
        self.launcher = Launcher(device, config.threads)
        self.materials = wp.array(materials, dtype=MaterialParams, device=device)
        walls = {f: (config.walls or {}).get(f, ("separate", 0.0)) for f in FACES}
        common = (config.domain_lo, config.domain_hi)
        self.grids = [Grid.create(*common, config.dx, config.base_level, config.gravity, walls, device)]
        self.refiner = None
        if config.refine_factor:
            fine = Grid.create(*common, config.dx / config.refine_factor, 1, config.gravity, walls, device,
                               sparse=True)
            self.grids.append(fine)
            self.refiner = Refiner(fine, self.grids[0], config.refine_factor, device,
                                   config.reconstruct, config.surface_threshold, self.launcher)
        self.colliders = colliders
        # compile-time CPIC variant of the transfers: only with colliders in CPIC mode
        self.cpic = colliders is not None and bool(colliders.arrays.cpic)
        self.collider_arrays = colliders.arrays if colliders is not None else empty_colliders(device)
        for g in self.grids:
            g.color = color_field(g.capacity if colliders is not None else 1, device)
            if colliders is not None and not g.sparse:
                colliders.color(g)
        self._next_id = 0  # id of the next particle a split creates
        self._first_split_id = None  # ids from here on were made by splits (set by the first reserve_ids)
        self._steps = 0
        self._tau = wp.empty(1, dtype=wp.mat33, device=device)  # per-particle stress (two grids)
        self._no_occ = wp.zeros(1, dtype=wp.int32, device=device)
        self._occ = self._no_occ
        self._cmask = self._no_occ
        # [max speed, max sound-speed stiffening] per CPU thread, written by G2P (atomic max)
        at_rest = np.tile([0.0, 1.0], self.launcher.threads)
        self.signal = wp.array(at_rest, dtype=float, device=device)
        self._signal_at_rest = wp.array(at_rest, dtype=float, device=device)

    # ------------------------------------------------------------------ questions

    @property
    def grid(self) -> Grid:
        """The level-0 (coarsest) grid."""
        return self.grids[0]

    @property
    def grid_origin(self) -> np.ndarray:
        """Position of coarse node (0, 0, 0): the corner of coarse cell (0, 0, 0)."""
        return self.grid.origin

    @property
    def level_spacings(self) -> dict[int, float]:
        """Grid spacing of every level this solver runs (level -> dx)."""
        return {g.level: g.dx for g in self.grids}

    @property
    def finest_active_dx(self) -> float:
        """The spacing the CFL condition must respect now: dx/b once the fine level
        holds material or a refined region, else dx."""
        if self.refiner is not None and (self.refiner.region_cells.any() or self._next_id > (self._first_split_id or 0)):
            return self.grids[1].dx
        return self.grid.dx

    @property
    def region(self) -> np.ndarray | None:
        """The refined coarse cells B_s (bool, one per coarse cell; a copy), or None
        without a fine level."""
        return None if self.refiner is None else self.refiner.region_cells.copy()

    @property
    def reconstruction_seconds(self) -> float:
        """CPU seconds spent in surface reconstruction so far (0 on CUDA or without it)."""
        return self.refiner.reconstruct_seconds if self.refiner is not None else 0.0

    @property
    def next_id(self) -> int:
        """The id the next particle made by a split will get."""
        return self._next_id

    def reserve_ids(self, next_id: int) -> None:
        """Ids below ``next_id`` are taken (sampled or restored particles); splits
        number their children from there."""
        if self._first_split_id is None:
            self._first_split_id = int(next_id)
        self._next_id = int(next_id)

    # ------------------------------------------------------------------ the step

    def step(self, state: ParticleState, dt: float, time: float = 0.0) -> None:
        """Advance ``state`` in place from ``time`` by ``dt``. In place is safe: G2P
        reads and writes only its own particle, after P2G has read them all."""
        self.move_colliders(time)
        if self.refiner is not None and self._steps % REFINE_EVERY == 0:
            self.refine(state)
        self._steps += 1
        if self.refiner is None:
            self._p2g(state, self.grid, dt)
        else:
            coarse, fine = self.grids
            self._p2g(state, coarse, dt, only_level=0, overlap=1)
            self._p2g(state, coarse, dt, only_level=1, overlap=2)
            self._p2g(state, fine, dt)
        for g in self.grids:
            self._grid_update(g, dt)
        wp.copy(self.signal, self._signal_at_rest)  # no host array per step
        for g in self.grids:
            self._g2p(state, g, dt)

    def _p2g(self, s: ParticleState, g: Grid, dt: float, only_level: int = -1, overlap: int = 0) -> None:
        # with a second grid, the coarse P2G keeps each particle's stress for it
        store = len(self.grids) > 1 and not g.sparse
        if store and self._tau.shape[0] < s.count:
            self._tau = wp.empty(s.capacity, dtype=wp.mat33, device=self.device)
        # each CPU thread scatters into its own accumulators, added up afterwards
        grids = self.launcher.private_grids(g.level, g.mv, g.m)
        common = [s.arrays(), self._cmask_for(s), self.materials, g.spec, g.color, dt, self._tau, int(store),
                  only_level, overlap, self._occupied(g)]
        parts = self.launcher.launch(transfer.P2G[self.cpic, g.sparse, only_level >= 0], s.count,
                                     lambda part, first, count: [*common, *grids[part]])
        self.launcher.gather(g.level, g.mv, g.m, parts, g.node_count)

    def _cmask_for(self, s: ParticleState):
        # per-particle compatibility mask, written by P2G and read by G2P (CPIC only)
        if not self.cpic:
            return self._no_occ
        if self._cmask.shape[0] < s.capacity:
            self._cmask = wp.zeros(s.capacity, dtype=wp.int32, device=self.device)
        return self._cmask

    def _occupied(self, g: Grid):
        # coarse nodes reached by level-0 particles (adaptive mode only)
        if self.refiner is not None and not g.sparse:
            if self._occ.shape[0] != g.capacity:
                self._occ = wp.zeros(g.capacity, dtype=wp.int32, device=self.device)
            return self._occ
        return self._no_occ

    def _grid_update(self, g: Grid, dt: float) -> None:
        self.launcher.launch(transfer.grid_update, g.node_count,
                             [g.spec, self.collider_arrays, g.color, dt, g.mv, g.m, g.v, self._occupied(g),
                              int(self.refiner is not None and not g.sparse)])

    def _g2p(self, s: ParticleState, g: Grid, dt: float) -> None:
        common = [self.materials, g.spec, self.collider_arrays, g.color, dt, g.v, s.arrays(), self._cmask_for(s)]
        self.launcher.launch(transfer.G2P[self.cpic, g.sparse], s.count,
                             lambda part, first, count: [*common, self.signal[2 * part: 2 * part + 2]])

    def last_signal(self) -> tuple[float, float]:
        """After the last step: the fastest particle's speed (m/s; 1e30 if a velocity
        was not finite) and the largest factor by which compression raised a fluid's
        sound speed. One small read from the device: the CFL time step follows them."""
        a = self.signal.numpy().reshape(-1, 2).max(axis=0)
        return float(a[0]), float(a[1])

    def adopt(self, state: ParticleState) -> None:
        """Make the grids ready for a state that was replaced wholesale (loaded from a
        checkpoint, edited, merged): fine blocks for its level-1 particles, colors."""
        if self.refiner is not None:
            self._after_activation(self.refiner.activate(state))
        self.color_particles(state)

    def reset_step_count(self, steps: int) -> None:
        """Steps taken so far (refinement runs every REFINE_EVERY steps), for resuming."""
        self._steps = steps

    # ------------------------------------------------------------------ colliders

    def move_colliders(self, time: float) -> None:
        """Colliders to time t (Eq. 22 velocities), color fields rebuilt if they moved."""
        c = self.colliders
        if c is None or (c.static and c.time is not None):
            return
        c.set_time(time)
        self.collider_arrays = c.arrays
        for g in self.grids:
            c.color(g)

    def color_particles(self, state: ParticleState) -> None:
        """CPIC color of every particle from its own grid (later steps update it in G2P)."""
        if self.colliders is None or not self.cpic:
            return
        for g in self.grids:
            self.launcher.launch(color_particles, state.count,
                                 [state.x, state.level, self.collider_arrays, g.spec, g.color,
                                  state.surface_point, state.surface_side, state.surface_body])

    # ------------------------------------------------------------------ refinement

    def set_region(self, cells: np.ndarray, state: ParticleState | None = None) -> None:
        """Refined coarse cells (adaptive mode)."""
        self.refiner.set_region(cells)
        self._after_activation(0)
        if state is not None:
            self.refine(state)

    def refine(self, state: ParticleState) -> None:
        """Split particles that entered the region (Eq. 15); activate the fine blocks
        the level-1 particles reach."""
        n_split = self.refiner.split(state, self._next_id, self.collider_arrays, self.materials)
        if n_split:
            self._next_id += n_split * self.refiner.b**3
            self.color_particles(state)
        first = self.refiner.activate(state)
        self._after_activation(first)

    def _after_activation(self, first_slot: int) -> None:
        fine = self.grids[1]
        if self.colliders is not None:
            fine.color = grow_color_field(fine.color, fine.capacity)
            self.colliders.color(fine, first_slot)

    # ------------------------------------------------------------------ sorting

    def sort_by_cell(self, state: ParticleState) -> None:
        """Reorder particles by coarse cell so P2G/G2P touch memory coherently (on the device)."""
        n = state.count
        if n == 0:
            return
        keys = wp.empty(2 * n, dtype=wp.int32, device=self.device)
        perm = wp.empty(2 * n, dtype=wp.int32, device=self.device)
        self.launcher.launch(_cell_keys, n, [state.x, self.grid.spec, keys, perm])
        wp.utils.radix_sort_pairs(keys, perm, n)
        for name in FIELDS:
            src = getattr(state, name)
            tmp = wp.empty(n, dtype=src.dtype, device=self.device)
            self.launcher.launch(_gather, n, [src, perm, tmp])
            wp.copy(src, tmp, count=n)


@wp.kernel
def _cell_keys(first: int, x: wp.array(dtype=wp.vec3), g: transfer.GridSpec, keys: wp.array(dtype=wp.int32),
               perm: wp.array(dtype=wp.int32)):
    p = wp.tid() + first
    b = transfer.stencil_base(g, x[p])
    keys[p] = (b[0] * g.dims[1] + b[1]) * g.dims[2] + b[2]
    perm[p] = p


@wp.kernel
def _gather(first: int, src: wp.array(dtype=Any), perm: wp.array(dtype=wp.int32), dst: wp.array(dtype=Any)):
    p = wp.tid() + first
    dst[p] = src[perm[p]]

