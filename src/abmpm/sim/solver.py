"""The adaptive-boundary MPM step, in one place (paper Algorithm 1).

A step is split into host work at points the solver announces and a pure device
substep, so that the substeps between two host points can run as one captured
CUDA graph (docs/architecture.md, "Segments and CUDA graphs"):

``begin_segment(state, time, dt, substeps)``, a host point:

1. move the colliders to ``time`` and rebuild their color distance field;
2. adaptive mode, every REFINE_EVERY steps: split the level-0 particles that
   entered the refined region (Eq. 15), move the children of surface parents onto
   the parent-level surface (Eqs. 16-20), and give the fine grid the blocks its
   particles need;
3. reserve every buffer the substeps use, set dt on the device, reset the CFL
   signal slots (and keep a copy of the particles if the segment may be rewound).

``substep(state)``, launches only (no allocation, no read-back):

4. P2G of every particle to every grid, compatible nodes only (Eqs. 8-10);
5. grid update: gravity, domain walls, collider contact (Eqs. 3-4, 22);
6. G2P of each particle from its own level's grid, with boundary velocities at
   incompatible nodes (Eqs. 11-12, 23-25), deformation update and return mapping
   (Eqs. 7, 13-14), advection that never crosses a collider; the fastest particle
   into this substep's CFL signal slot.

``run_segment(state)`` runs the segment's substeps (eagerly, or by replaying a
captured graph), ``end_segment()`` reads the per-substep signals back at once.
``step(state, dt, time)`` is a segment of one substep.

Everything else (sampling, output, diagnostics, time stepping) lives outside.
"""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np
import warp as wp

from . import collider_set as collider_host
from . import colliders as collider_kernels
from . import grid_update as node_pass_kernels
from . import parallel, reconstruct, refine, sorting
from .boundary import FACES
from .collider_set import ColliderSet, color_field, empty_colliders, grow_color_field
from .colliders import color_particles
from .config import SolverConfig
from .g2p import g2p_kernel
from .grid import Grid
from .grid_update import CPU_NODE_CHUNK, grid_update
from .materials import MaterialParams, model_ids
from .p2g import p2g_kernel
from .parallel import CACHE_LINE_WORDS, MIN_TRANSFER_RANGE, KernelProfile, Launcher, reset_reach
from .refine import REFINE_EVERY, Refiner
from .sorting import level_ranges, sort_by_cell
from .state import DYNAMIC, FIELDS, ParticleState

wp.set_module_options({"enable_backward": False})

# The longest segment (substeps between two host points): segments end at every
# refinement step, in every mode, so that their lengths repeat and graphs are reused.
SEGMENT_MAX = REFINE_EVERY
SIGNAL_STRIDE = CACHE_LINE_WORDS  # floats between two CFL signal slots

# the P2G passes (sim/p2g.py): which particles each visits (a level, or None for
# all) and how a profile names it
_P2G_LEVEL = {"dense": None, "level0": 0, "overlap": 1, "sparse": None}
_P2G_LABEL = {"dense": "", "level0": " (level 0)", "overlap": " (level 1, overlap)", "sparse": ""}


class MPMSolver:
    def __init__(self, config: SolverConfig, materials: list[MaterialParams], device,
                 colliders: ColliderSet | None = None):
        self.config = config
        self.device = device
        self.launcher = Launcher(device, config.threads)
        self.materials = wp.array(materials, dtype=MaterialParams, device=device)
        # the transfers are compiled for the scene's material models only (materials.dispatch)
        self.models = model_ids(materials)
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
                colliders.color(g, self.launcher)
        self._next_id = 0  # id of the next particle a split creates
        self._first_split_id = None  # ids from here on were made by splits (set by the first reserve_ids)
        self._steps = 0
        # buffers of the substeps, (re)sized at host points only (_reserve)
        self._tau = wp.empty(1, dtype=wp.mat33, device=device)  # per-particle stress (two grids)
        self._no_occ = wp.zeros(1, dtype=wp.int32, device=device)
        self._occ = self._no_occ  # coarse nodes reached by level-0 particles (adaptive mode)
        self._cmask = self._no_occ  # per-particle compatibility mask, P2G -> G2P (CPIC)
        self._dt = wp.zeros(1, dtype=float, device=device)  # the segment's dt, read by the kernels
        # [max speed, max sound-speed stiffening] per substep of a segment and CPU thread,
        # written by G2P (atomic max, every particle) into its own slot; one view per
        # slot, made here. Slots are a cache line apart: two CPU threads updating the
        # same line on every particle cost G2P a tenth of its two-thread speed.
        threads = self.launcher.threads
        at_rest = np.tile([0.0, 1.0] + [0.0] * (SIGNAL_STRIDE - 2), SEGMENT_MAX * threads)
        self.signal = wp.array(at_rest, dtype=float, device=device)
        self._signal_at_rest = wp.array(at_rest, dtype=float, device=device)
        self._signal_slots = [[self.signal[SIGNAL_STRIDE * i: SIGNAL_STRIDE * i + 2]
                               for i in range(k * threads, (k + 1) * threads)] for k in range(SEGMENT_MAX)]
        # Where each level's particles lie: level (None: every level) -> ranges
        # (first, count). After a sort by (level, cell) each level of adaptive mode
        # is one contiguous range and its transfers run over it alone: equal work per
        # CPU thread, no pass over particles that would return at once. Checked at
        # every host point; unsorted particles get one range over all.
        self._partition = wp.zeros(2, dtype=wp.int32, device=device)  # level_ranges' scratch
        self._ranges: dict[int | None, list[tuple[int, int]]] = {}
        self._sorted: ParticleState | None = None  # sort_by_cell's scratch copy
        self._segment = 0  # substeps in the current segment
        self._substep = 0  # of which taken
        self._segment_start = 0  # step count at its start
        self._kept: dict[str, wp.array] = {}  # dynamic particle fields at the segment start (rewind)
        # Captured graphs (run_segment). Moving colliders run eagerly: their pose comes
        # from the host before every substep. ``capture`` may be set on the CPU too:
        # Warp (>= 1.19) replays CPU graphs, on one thread; the tests use that to check
        # the captured path without a GPU.
        if config.cuda_graph and not self.launcher.device.is_cuda:
            warnings.warn("cuda_graph is ignored on the CPU: substeps run eagerly on all threads", stacklevel=2)
        self.capture = bool(config.cuda_graph) and self.launcher.device.is_cuda
        self._kernels_loaded = False
        self._graphs: dict[tuple, Any] = {}  # (first slot, substeps) -> graph, for _graph_buffers
        self._graph_buffers: tuple | None = None

    def transfer_kernels(self) -> list:
        """Every transfer kernel this solver's substeps may launch. Each is compiled
        on first use, in a module of its own: ``load_kernels`` loads them all before
        the first segment, so that a level reached only later in the run (the fine
        grid's) never compiles in the middle of it."""
        kernels = [reset_reach, grid_update]
        kernels += [p2g_kernel(name, self.cpic, self.models) for name, _ in self.p2g_passes()]
        kernels += [g2p_kernel(g.sparse, self.cpic, self.models) for g in self.grids]
        return kernels

    def p2g_passes(self) -> list[tuple[str, Grid]]:
        """The P2G passes of a substep (sim/p2g.py), in order, with their grid."""
        if self.refiner is None:
            return [("dense", self.grid)]
        coarse, fine = self.grids
        return [("level0", coarse), ("overlap", coarse), ("sparse", fine)]

    def load_kernels(self) -> None:
        """Load, compiling where the kernel cache lacks them, the kernel modules this
        solver's step uses and the transfer kernels made for its scene's models. Runs before
        the first segment at the latest; a runner calls it before starting its clock,
        so that compiling is not counted as simulation time."""
        if self._kernels_loaded:
            return
        modules = [node_pass_kernels, parallel, sorting]
        if self.colliders is not None:
            modules += [collider_kernels, collider_host]
        if self.refiner is not None:
            modules += [refine, reconstruct]
        for module in modules:
            wp.load_module(module, device=self.device)
        for k in self.transfer_kernels():
            k.module.load(self.device)
        self._kernels_loaded = True

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
    def profile(self) -> KernelProfile | None:
        """While set, every launch and phase of the step is timed into it (``abmpm
        bench --profile``)."""
        return self.launcher.profile

    @profile.setter
    def profile(self, profile: KernelProfile | None) -> None:
        self.launcher.profile = profile

    def section(self, name: str):
        """A context: the launches inside are profiled as the phase ``name``."""
        return self.launcher.section(name)

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

    @property
    def segment_length(self) -> int:
        """The most substeps the next segment may have: up to the next refinement step
        (every REFINE_EVERY steps); 1 while colliders move (their pose and color field
        are set on the host before every substep)."""
        if self.colliders is not None and not self.colliders.static:
            return 1
        return SEGMENT_MAX - self._steps % SEGMENT_MAX

    def step(self, state: ParticleState, dt: float, time: float = 0.0) -> None:
        """Advance ``state`` in place from ``time`` by ``dt``: a segment of one substep
        (its CFL signal is ``end_segment()[0]``)."""
        self.begin_segment(state, time, dt, 1)
        self.run_segment(state)

    def begin_segment(self, state: ParticleState, time: float, dt: float, substeps: int = 1) -> None:
        """Host point before ``substeps`` (at most ``segment_length``) substeps of
        length ``dt`` from ``time``: everything that allocates, reads back or uploads
        from the host happens here, never in a substep."""
        if not 1 <= substeps <= self.segment_length:
            raise ValueError(f"a segment has 1 to {self.segment_length} substeps now, not {substeps}")
        with self.launcher.section("colliders"):
            self.move_colliders(time)  # 1. colliders to t, color field
        if self.refiner is not None and self._steps % REFINE_EVERY == 0:
            with self.launcher.section("refinement"):
                self.refine(state)  # 2. split (Eq. 15), fine blocks
        self._reserve(state)  # 3. buffers, dt, CFL signal slots
        self.load_kernels()  # compiled once, here at the latest: never in a substep or a capture
        self._dt.fill_(dt)
        wp.copy(self.signal, self._signal_at_rest)
        if substeps > 1:  # a longer segment can be stopped early: see rewind()
            for name in DYNAMIC:
                src = getattr(state, name)
                if self._kept.get(name) is None or self._kept[name].shape[0] < state.capacity:
                    self._kept[name] = wp.empty(state.capacity, dtype=src.dtype, device=self.device)
                wp.copy(self._kept[name], src, count=state.count)
        self._segment, self._substep, self._segment_start = substeps, 0, self._steps

    def substep(self, state: ParticleState) -> None:
        """One substep of the segment, in place: kernel launches on buffers that
        begin_segment reserved and nothing else, so it can be captured in a graph. In
        place is safe: G2P reads and writes only its own particle, after P2G has read
        them all."""
        if self._substep >= self._segment:
            raise RuntimeError("the segment is complete: call begin_segment first")
        self.p2g(state)  # 4. P2G (Eqs. 8-10)
        self.grid_update()  # 5. grid update (Eqs. 3-4, 22)
        self.g2p(state, self._signal_slots[self._substep])  # 6. G2P (Eqs. 11-14, 23-25), CFL signal
        self._substep += 1
        self._steps += 1

    def run_segment(self, state: ParticleState) -> None:
        """The segment's remaining substeps: one after the other, or with ``capture``
        as one graph, captured the first time its launches (particle count, buffers,
        substeps) occur and replayed after that; dt is read on the device."""
        n = self._segment - self._substep
        if not self.capture or (self.colliders is not None and not self.colliders.static):
            for _ in range(n):
                self.substep(state)
            return
        buffers = self._graph_buffer_key(state)
        if buffers != self._graph_buffers:  # anything moved: the old graphs point at freed memory
            self._graphs.clear()
            self._graph_buffers = buffers
        key = (self._substep, n)
        graph = self._graphs.get(key)
        if graph is None:
            graph = self._graphs[key] = self._capture(state, n)  # records, does not run
        else:
            self._substep += n
            self._steps += n
        wp.capture_launch(graph)

    def end_segment(self) -> np.ndarray:
        """Host point after the segment: for each of its substeps, the fastest
        particle's speed (m/s; 1e30 if a velocity was not finite) and the largest
        factor by which compression raised a fluid's sound speed, shape (substeps, 2).
        One small read from the device per segment: the CFL time step follows them."""
        a = self.signal.numpy().reshape(SEGMENT_MAX, self.launcher.threads, SIGNAL_STRIDE)[: self._substep, :, :2]
        return a.max(axis=1).astype(np.float64)

    def rewind(self, state: ParticleState, substeps: int) -> None:
        """Stop the segment after its first ``substeps`` substeps: the particles go back
        to the segment's start and those substeps run again (eagerly; on the CPU the
        result is bit-identical). For a segment of more than one substep."""
        if not 1 <= substeps <= self._segment or self._segment < 2:
            raise ValueError(f"cannot rewind a segment of {self._segment} substeps to {substeps}")
        for name in DYNAMIC:
            wp.copy(getattr(state, name), self._kept[name], count=state.count)
        wp.copy(self.signal, self._signal_at_rest)
        self._segment, self._substep, self._steps = substeps, 0, self._segment_start
        for _ in range(substeps):
            self.substep(state)

    def _reserve(self, state: ParticleState) -> None:
        # every buffer a substep touches, at the size it needs now
        if len(self.grids) > 1 and self._tau.shape[0] < state.capacity:
            self._tau = wp.empty(state.capacity, dtype=wp.mat33, device=self.device)
        if self.cpic and self._cmask.shape[0] < state.capacity:
            self._cmask = wp.zeros(state.capacity, dtype=wp.int32, device=self.device)
        if self.refiner is not None and self._occ.shape[0] != self.grid.capacity:
            self._occ = wp.zeros(self.grid.capacity, dtype=wp.int32, device=self.device)
        for g in self.grids:
            self.launcher.private_grids(g.level, g.mv, g.m)
        state.arrays()
        self._find_level_ranges(state)

    def _find_level_ranges(self, state: ParticleState) -> None:
        # adaptive mode: where each level's particles lie (one range per level once
        # sorted by level; else every range over all particles)
        self._ranges = level_ranges(state, [g.level for g in self.grids], self.refiner is not None, self._partition)

    def _graph_buffer_key(self, state: ParticleState) -> tuple:
        # what a captured substep has baked in: launch sizes and every buffer's address
        arrays = [getattr(state, name) for name in FIELDS]
        arrays += [self._tau, self._cmask, self._occ, self._dt, self.signal, self.materials,
                   self.collider_arrays.bodies, self.collider_arrays.face_body]
        for g in self.grids:
            arrays += [g.mv, g.m, g.v, g.color.dist, g.color.dir, g.color.body, g.spec.blocks, g.spec.slot_block]
        arrays += self.launcher.private_arrays()
        return (state.count, tuple(map(tuple, self._ranges.values())), tuple(g.node_count for g in self.grids),
                int(self.collider_arrays.mesh),
                tuple((a.ptr, a.shape) for a in arrays))

    def _capture(self, state: ParticleState, n: int):
        first, steps = self._substep, self._steps
        self.load_kernels()  # loaded before, not during, the capture
        self.launcher.serial = True  # one thread records the launches in order
        try:
            with wp.ScopedCapture(device=self.device, force_module_load=False) as capture:
                for _ in range(n):
                    self.substep(state)
        except BaseException:
            self._substep, self._steps = first, steps
            raise
        finally:
            self.launcher.serial = False
        return capture.graph

    # ------------------------------------------------------------------ the passes

    def p2g(self, s: ParticleState) -> None:
        """Every particle to every grid (Eqs. 8-10), pass by pass (``p2g_passes``)."""
        for name, g in self.p2g_passes():
            private = self.launcher.private_grids(g.level, g.mv, g.m)  # a CPU part's own sums
            kernel = p2g_kernel(name, self.cpic, self.models)
            common = [s.arrays(), self.materials, g.spec, g.color, self._dt, self._cmask]
            kept = {"dense": [], "level0": [self._tau, self._occ], "overlap": [self._tau, self._occ],
                    "sparse": [self._tau]}[name]  # the stress kept for the fine pass; the overlap marks
            for site, (first, count) in enumerate(self._ranges[_P2G_LEVEL[name]]):
                self.launcher.launch(kernel, count,
                                     lambda part, first, count: [*common, *private.parts[part],
                                                                 private.reach[part], *kept],
                                     start=first, label=f"P2G {g.name}{_P2G_LABEL[name]}",
                                     min_range=MIN_TRANSFER_RANGE, site=site)

    def grid_update(self) -> None:
        """Momentum to velocity, gravity, contact and walls on every grid (Eqs. 3-4, 22)."""
        chunk = 1 if self.launcher.device.is_cuda else CPU_NODE_CHUNK
        for g in self.grids:
            private = self.launcher.private_grids(g.level, g.mv, g.m)  # the other CPU threads' sums
            coarse_adaptive = self.refiner is not None and not g.sparse
            self.launcher.launch(grid_update, -(-g.node_count // chunk),
                                 [g.spec, self.collider_arrays, g.color, self._dt, g.mv, g.m, g.v,
                                  self._occ if coarse_adaptive else self._no_occ, int(coarse_adaptive),
                                  self.grids[-1].dx, g.node_count, chunk, private.sums],
                                 label=f"grid update {g.name}", min_range=64)
            if private.extra > 0:  # every part's reach empty again
                self.launcher.launch(reset_reach, private.extra + 1, [private.bounds], label=f"reset {g.name}")

    def g2p(self, s: ParticleState, signal_slots: list) -> None:
        """Each particle from its own level's grid (Eqs. 11-14, 23-25); its speed and
        stiffening into ``signal_slots`` (one per CPU part)."""
        for g in self.grids:
            kernel = g2p_kernel(g.sparse, self.cpic, self.models)
            common = [self.materials, g.spec, self.collider_arrays, g.color, self._dt, g.v, s.arrays(), self._cmask]
            for site, (first, count) in enumerate(self._ranges[g.level]):
                self.launcher.launch(kernel, count, lambda part, first, count: [*common, signal_slots[part]],
                                     start=first, label=f"G2P {g.name}", min_range=MIN_TRANSFER_RANGE, site=site)

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
            c.color(g, self.launcher)

    def color_particles(self, state: ParticleState, min_id: int = -1) -> None:
        """CPIC color of every particle (of those with an id from ``min_id`` on) from
        its own grid; later steps update it in G2P."""
        if self.colliders is None or not self.cpic:
            return
        for g in self.grids:
            self.launcher.launch(color_particles, state.count,
                                 [state.x, state.level, state.id, min_id, self.collider_arrays, g.spec, g.color,
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
        first_child = self._next_id
        n_split = self.refiner.split(state, first_child, self.collider_arrays, self.materials)
        if n_split:
            self._next_id += n_split * self.refiner.b**3
            self.color_particles(state, min_id=first_child)  # only the children moved
            self.sort_by_cell(state)  # the children joined at the end: each level contiguous again
        first = self.refiner.activate(state)
        self._after_activation(first)

    def _after_activation(self, first_slot: int) -> None:
        fine = self.grids[1]
        if self.colliders is not None:
            fine.color = grow_color_field(fine.color, fine.capacity)
            self.colliders.color(fine, self.launcher, first_slot)

    # ------------------------------------------------------------------ sorting

    def sort_by_cell(self, state: ParticleState) -> None:
        """Reorder particles by coarse cell so P2G/G2P touch memory coherently (on the
        device); in adaptive mode by level first, so that each level is one range."""
        self._sorted = sort_by_cell(state, self.grid.spec, self.refiner is not None, self.launcher, self._sorted)
