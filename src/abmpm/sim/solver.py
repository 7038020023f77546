"""The adaptive-boundary MPM step, in one place (paper Algorithm 1).

A step is split into host work at points the solver announces and a pure device substep, so
that the substeps between two host points can run as one captured CUDA graph
(docs/architecture.md, "Segments and CUDA graphs"). ``begin_segment(state, time, dt, substeps)``,
a host point:

1. move the colliders to ``time`` and rebuild their color distance field;
2. adaptive mode, every ``refine_every(cfl)`` steps (4, fewer at a cfl above 0.5): split the
   level-0 particles that entered the refined region (Eq. 15), move the children of surface
   parents onto the parent-level surface (Eqs. 16-20), give the fine grid the blocks it needs;
3. reserve every buffer the substeps use, set dt on the device, reset the CFL signal slots
   (and keep a copy of the particles if the segment may be rewound).

``substep(state)``, launches only (no allocation, no read-back):

4. P2G of every particle to every grid, compatible nodes only (Eqs. 8-10);
5. grid update: gravity, domain walls, collider contact (Eqs. 3-4, 22);
6. G2P of each particle from its own level's grid (``coupling = "partition"``: from both, with
   the functions it scattered with, sim/partition.py), with boundary velocities at incompatible
   nodes (Eqs. 11-12, 23-25), deformation update and return mapping (Eqs. 7, 13-14), advection
   that never crosses a collider; the fastest particle into the CFL signal (sim/stiffness.py).

``run_segment(state)`` runs the segment's substeps (eagerly, or replaying a captured graph), ``end_segment()``
reads their signals back at once. Everything else (sampling, output, time stepping) lives outside.
"""

from __future__ import annotations

import warnings

import numpy as np
import warp as wp

from . import collider_set as collider_host
from . import colliders as collider_kernels
from . import grid_update as node_pass_kernels
from . import parallel, partition, reconstruct, refine, sorting, time_levels
from .boundary import FACES
from .collider_set import ColliderSet, color_field, empty_colliders, grow_color_field
from .config import SolverConfig
from .g2p import g2p_kernel
from .grid import Grid
from .grid_update import grid_update
from .materials import MaterialParams, model_ids
from .p2g import PASS_LABEL, PASS_LEVEL, p2g_kernel
from .parallel import CPU_NODE_CHUNK, MIN_TRANSFER_RANGE, KernelProfile, Launcher, reset_reach
from .partition import Partition
from .refine import REFINE_EVERY, Refiner, refine_every
from .segments import Graphs, SegmentStart, Signals, substep_buffers
from .sorting import level_ranges, sort_by_cell
from .state import ParticleState
from .stiffness import StiffnessSignal
from .time_levels import SORT_HALO, SlowSet, no_slow, p2g_slow_kernel, split_off_slow

wp.set_module_options({"enable_backward": False})

# The longest segment (substeps between host points): to every refinement step, in every mode (graphs reused)
SEGMENT_MAX = REFINE_EVERY

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
        self.grids = [Grid.create(*common, config.dx, config.base_level, config.gravity, walls, device,
                                  wall_images=config.wall_images)]
        self.refiner = None
        if config.refine_factor:
            fine = Grid.create(*common, config.dx / config.refine_factor, 1, config.gravity, walls, device,
                               sparse=True, wall_images=config.wall_images, family=config.refine_factor)
            self.grids.append(fine)
            self.refiner = Refiner(fine, self.grids[0], config.refine_factor, device,
                                   config.reconstruct, config.surface_threshold, self.launcher, config.seed)
        self.colliders = colliders
        # compile-time CPIC variant of the transfers: only with colliders in CPIC mode
        self.cpic = colliders is not None and bool(colliders.arrays.cpic)
        if colliders is not None:  # the particles' closest points, per cell (sim/face_cells.py)
            colliders.index_faces(self.grids[0], self.launcher)
        self.collider_arrays = colliders.arrays if colliders is not None else empty_colliders(device)
        # the two grids as one partition of unity (sim/partition.py), or the paper's overlap (Eq. 8)
        self.partition = (Partition(*self.grids, self.launcher, device, self.cpic, self.models)
                          if self.refiner is not None and config.coupling == "partition" else None)
        for g in self.grids:
            g.color = color_field(g.capacity if colliders is not None else 1, device)
            if colliders is not None and not g.sparse:
                colliders.color(g, self.launcher)
        self._next_id = 0  # id of the next particle a split creates
        self._first_split_id = None  # ids from here on were made by splits (set by the first reserve_ids)
        self._steps = 0
        self._tau = wp.empty(1, dtype=wp.mat33, device=device)  # stress per particle (two grids); buffers: _reserve
        self._no_occ = wp.zeros(1, dtype=wp.int32, device=device)
        self._occ = self._no_occ  # coarse nodes reached by level-0 particles (adaptive mode)
        self._cmask = self._no_occ  # per-particle compatibility mask, P2G -> G2P (CPIC)
        self._on_fine = self._no_occ  # level-0 particles the fine grid moves (p2g_sparse -> g2p_sparse)
        self._dt = wp.zeros(1, dtype=float, device=device)  # the segment's dt, read by the kernels
        self._dt_host = 0.0
        self._signals = Signals(SEGMENT_MAX, self.launcher.threads, device)  # the CFL signal of each substep
        self.signal = self._signals.array
        self.stiffness = StiffnessSignal(device, config.stiffening == "node")  # bounded node by node, after G2P
        # level (None: all) -> [(first, count)], one range per level once sorted (_find_level_ranges)
        self._level_scratch = wp.zeros(2, dtype=wp.int32, device=device)  # level_ranges' scratch
        self._ranges: dict[int | None, list[tuple[int, int]]] = {}
        self._sorted: ParticleState | None = None  # sort_by_cell's scratch copy
        self._segment, self._substep = 0, 0  # substeps in the current segment, of which taken
        self._segment_start = 0  # step count at its start
        self._start = SegmentStart(device)  # the particles at the segment's start (rewind)
        # Captured graphs (run_segment; moving colliders run eagerly); the tests set ``capture`` on the CPU too
        if config.cuda_graph and not self.launcher.device.is_cuda:
            warnings.warn("cuda_graph is ignored on the CPU: substeps run eagerly on all threads", stacklevel=2)
        self.capture = bool(config.cuda_graph) and self.launcher.device.is_cuda
        # A time step per level (sim/time_levels.py): the slow set, in adaptive mode
        # without moving colliders; ``block`` substeps of the fast set make one of its steps.
        per_level = config.time_steps == "per_level" and (colliders is None or colliders.static) and not self.partition
        self.slow = SlowSet(self.grid, self.launcher, device) if self.refiner and per_level else None
        self._no_slow = no_slow(device)
        self.slow_count = 0  # particles of the slow set, at the front of the storage (counted at each sort)
        self.block, self.choose_slow = 1, True  # the slow set's step in substeps; whether a sort chooses it
        self._kernels_loaded = False
        self._graphs = Graphs()  # captured segments (run_segment)
        self.refine_every = refine_every(config.cfl)  # steps between two refinements (adaptive mode)

    def transfer_kernels(self) -> list:
        """Every transfer kernel this solver's substeps may launch. Each is compiled
        on first use, in a module of its own: ``load_kernels`` loads them all before
        the first segment, so that a level reached only later in the run (the fine
        grid's) never compiles in the middle of it."""
        kernels = [reset_reach, grid_update, *self.stiffness.kernels()]
        if self.partition is not None:
            return kernels + list(self.partition.kernels)
        kernels += [p2g_kernel(name, self.cpic, self.models) for name, _ in self.p2g_passes()]
        kernels += [g2p_kernel(g.sparse, self.cpic, self.models) for g in self.grids]
        kernels += [p2g_slow_kernel(self.cpic, self.models)] if self.slow is not None else []
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
        modules = [node_pass_kernels, parallel, sorting] + ([time_levels] if self.slow is not None else [])
        if self.colliders is not None:
            modules += [collider_kernels, collider_host]
        if self.refiner is not None:
            modules += [refine, reconstruct, partition]
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
        """While set, every launch and phase of the step is timed into it (bench --profile)."""
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
        """The most substeps the next segment may have: up to the next refinement step (every
        ``refine_every`` steps); 1 while colliders move (pose and color field set on the host each substep)."""
        if self.colliders is not None and not self.colliders.static:
            return 1
        every = self.refine_every if self.refiner is not None else SEGMENT_MAX
        n = every - self._steps % every
        cap = self.slow.segment_cap(self.block, self.slow_due) if self.slow is not None else None
        return n if cap is None else min(n, cap)  # a segment ends with the slow set's step

    def fast_cost(self) -> float:
        """The fast set's cost a substep in level-0 particle substeps (sim/time_levels.py)."""
        return time_levels.fast_substep_cost(self._ranges, self.slow_count)

    @property
    def slow_due(self) -> bool:
        """Whether the slow set's open step must end (``close_slow``) before the next segment."""
        return self.slow is not None and self.slow.due(self.block)

    def close_slow(self, state: ParticleState) -> tuple[float, float] | None:
        """End the slow set's step (a host point): it gathers from the coarse grid with
        the step's whole length (Eqs. 11-14). Returns its CFL signal (fastest speed,
        stiffening), or None if no step was open."""
        if self.slow is None or not self.slow.open:
            return None
        g = self.grid
        common = [self.materials, g.spec, self.collider_arrays, g.color], [g.v, state.arrays(), self._cmask, g.spec,
                                                                           g.color, self._no_occ, self.stiffness.none]
        return self.slow.gather(state, self._ranges["slow"][0], g2p_kernel(False, self.cpic, self.models), common)

    def begin_segment(self, state: ParticleState, time: float, dt: float, substeps: int = 1) -> None:
        """Host point before ``substeps`` (at most ``segment_length``) substeps of length ``dt`` from
        ``time``: everything that allocates, reads back or uploads from the host happens here, never in a substep."""
        if not 1 <= substeps <= self.segment_length:
            raise ValueError(f"a segment has 1 to {self.segment_length} substeps now, not {substeps}")
        if self.slow_due:
            raise RuntimeError("the slow set's step is due: call close_slow first")
        with self.launcher.section("colliders"):
            self.move_colliders(time)  # 1. colliders to t, color field
        if self.refiner is not None and self._steps % self.refine_every == 0:
            with self.launcher.section("refinement"):
                self.refine(state)  # 2. split (Eq. 15), fine blocks
        self._reserve(state)  # 3. buffers, dt, CFL signal slots
        self.load_kernels()  # compiled once, here at the latest: never in a substep or a capture
        if self.slow is not None and not self.slow.open and self.block > 1 and self._ranges["slow"][0][1]:
            with self.launcher.section("slow set"):  # 3a. a step of the slow set begins (sim/time_levels.py)
                if self.slow.may_be_near():  # S chosen again
                    self.sort_by_cell(state)
                self.slow.scatter(state, self._ranges["slow"][0], self.materials, self.models, self.cpic,
                                  self.grid.color, self._cmask)
        self._dt.fill_(dt)
        self._dt_host = dt
        self._signals.reset()
        if substeps > 1:  # a longer segment can be stopped early: see rewind()
            self._start.keep(state)
        if self.slow is not None:
            self.slow.ran(substeps, dt, keep=substeps > 1)
        self._segment, self._substep, self._segment_start = substeps, 0, self._steps

    def substep(self, state: ParticleState) -> None:
        """One substep of the segment, in place: kernel launches on buffers that
        begin_segment reserved and nothing else, so it can be captured in a graph. In
        place is safe: G2P reads and writes only its own particle, after P2G has read
        them all."""
        if self._substep >= self._segment:
            raise RuntimeError("the segment is complete: call begin_segment first")
        if self.refiner is not None and self.partition is None:  # 3b. the grid that moves a particle among both levels
            self.refiner.coarse_children(state, self._on_fine, self.collider_arrays, self.grid.color, self.cpic,
                                         skip=self._ranges["slow"][0][1])
        self.p2g(state)  # 4. P2G (Eqs. 8-10)
        self.grid_update()  # 5. grid update (Eqs. 3-4, 22)
        self.g2p(state, self._signals.slots[self._substep])  # 6. G2P (Eqs. 11-14, 23-25), CFL signal
        self.stiffness.run(self.launcher, state, self.grids, self._ranges, self._signals.slots[self._substep][0])
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
        key = (self._substep, n)
        graph = self._graphs.find(substep_buffers(self, state), key)
        if graph is None:
            graph = self._capture(state, key)  # records, does not run
        else:
            self._substep += n
            self._steps += n
        wp.capture_launch(graph)

    def end_segment(self) -> np.ndarray:
        """Host point after the segment: for each of its substeps, the fastest
        particle's speed (m/s; 1e30 if a velocity was not finite) and the largest
        factor by which compression raised a fluid's sound speed, shape (substeps, 2).
        One small read from the device per segment: the CFL time step follows them."""
        a = self._signals.read(self._substep)
        if self.slow is not None:  # the fast particles moved this far at most
            self.slow.drift += self._dt_host * float(a[:, 0].sum())
        return a

    def rewind(self, state: ParticleState, substeps: int) -> None:
        """Stop the segment after its first ``substeps`` substeps: the particles go back
        to the segment's start and those substeps run again (eagerly; on the CPU the
        result is bit-identical). For a segment of more than one substep."""
        if not 1 <= substeps <= self._segment or self._segment < 2:
            raise ValueError(f"cannot rewind a segment of {self._segment} substeps to {substeps}")
        self._start.restore(state)
        if self.slow is not None:
            self.slow.unrun(self._segment - substeps, self._dt_host)
        self._signals.reset()
        self._segment, self._substep, self._steps = substeps, 0, self._segment_start
        for _ in range(substeps):
            self.substep(state)

    def _reserve(self, state: ParticleState) -> None:
        # every buffer a substep touches, at the size it needs now
        if len(self.grids) > 1 and self._tau.shape[0] < state.capacity:
            self._tau = wp.empty(state.capacity, dtype=wp.mat33, device=self.device)
            self._on_fine = wp.zeros(state.capacity, dtype=wp.int32, device=self.device)
        if self.cpic and self._cmask.shape[0] < state.capacity:
            self._cmask = wp.zeros(state.capacity, dtype=wp.int32, device=self.device)
        if self.refiner is not None and self._occ.shape[0] != self.grid.capacity:
            self._occ = wp.zeros(self.grid.capacity, dtype=wp.int32, device=self.device)
        for g in self.grids:
            self.launcher.private_grids(g.level, g.mv, g.m)
        if self.partition is not None:
            self.partition.reserve(state.capacity)
        self.stiffness.reserve(self.grids, state.capacity)
        state.arrays()
        self._find_level_ranges(state)

    def _find_level_ranges(self, state: ParticleState) -> None:  # self._ranges (__init__)
        ranges = level_ranges(state, [g.level for g in self.grids], self.refiner is not None, self._level_scratch)
        self._ranges = split_off_slow(ranges, self.slow_count if self.block > 1 else 0)

    def _capture(self, state: ParticleState, key: tuple):
        first, steps = self._substep, self._steps
        self.load_kernels()  # loaded before, not during, the capture
        try:
            return self._graphs.capture(key, self.device, self.launcher,
                                        lambda: [self.substep(state) for _ in range(key[1])])
        except BaseException:
            self._substep, self._steps = first, steps
            raise

    # ------------------------------------------------------------------ the passes

    def p2g(self, s: ParticleState) -> None:
        """Every particle to every grid (Eqs. 8-10), pass by pass (``p2g_passes``)."""
        if self.partition is not None:
            return self.partition.p2g(s, self._ranges[None], self.materials, self._dt)
        for name, g in self.p2g_passes():
            private = self.launcher.private_grids(g.level, g.mv, g.m)  # a CPU part's own sums
            kernel = p2g_kernel(name, self.cpic, self.models)
            common = [s.arrays(), self.materials, g.spec, g.color, self._dt, self._cmask]
            # the stress kept for the fine pass; the overlap marks; where the fine grid moves level 0
            kept = {"dense": [], "level0": [self._tau, self._occ], "overlap": [self._tau, self._occ, self._on_fine],
                    "sparse": [self._tau, self._on_fine, self.refiner and self.refiner.beside, self.grid.spec]}[name]
            # the overlap: the children the coarse grid moves first, then the rest (p2g_overlap);
            # each launch a site of its own, so that its recorded launch replays unchanged
            for k, extra in enumerate(([0], [1]) if name == "overlap" else ([],)):
                for site, (first, count) in enumerate(self._ranges[PASS_LEVEL[name]]):
                    self.launcher.launch(kernel, count,
                                         lambda part, first, count: [*common, *private.parts[part],
                                                                     private.reach[part], *kept, *extra],
                                         start=first, label=f"P2G {g.name}{PASS_LABEL[name]}",
                                         min_range=MIN_TRANSFER_RANGE, site=2 * site + k)

    def grid_update(self) -> None:
        """Momentum to velocity, gravity, contact and walls on every grid (Eqs. 3-4, 22)."""
        chunk = 1 if self.launcher.device.is_cuda else CPU_NODE_CHUNK
        for g in self.grids:
            private = self.launcher.private_grids(g.level, g.mv, g.m)  # the other CPU threads' sums
            coarse_adaptive = self.refiner is not None and not g.sparse and self.partition is None
            slow = self.slow.nodes if coarse_adaptive and self.slow is not None else self._no_slow
            self.launcher.launch(grid_update, -(-g.node_count // chunk),
                                 [g.spec, self.collider_arrays, g.color, self._dt, g.mv, g.m, g.v,
                                  self._occ if coarse_adaptive else self._no_occ, int(coarse_adaptive),
                                  self.grids[-1].dx, g.node_count, chunk, private.sums, slow,
                                  self.stiffness.kept_m(g.level)],
                                 label=f"grid update {g.name}", min_range=64)
            if private.extra > 0:  # every part's reach empty again
                self.launcher.launch(reset_reach, private.extra + 1, [private.bounds], label=f"reset {g.name}")

    def g2p(self, s: ParticleState, signal_slots: list) -> None:
        """Each particle from its own level's grid (Eqs. 11-14, 23-25); its speed and
        stiffening into ``signal_slots`` (one per CPU part)."""
        if self.partition is not None:
            return self.partition.g2p(s, self._ranges[None], self.materials, self.collider_arrays, self._dt,
                                      self.stiffness.stiff, signal_slots)
        for g in self.grids:
            kernel = g2p_kernel(g.sparse, self.cpic, self.models)
            common = [self.materials, g.spec, self.collider_arrays, g.color, self._dt, g.v, s.arrays(), self._cmask,
                      self.grid.spec, self.grid.color, self._on_fine, self.stiffness.stiff]
            # adaptive: a launch per level's fast range on each grid (on_fine marks who moves with which)
            for site, (first, count) in enumerate(self._ranges[None] if self.refiner else self._ranges[g.level]):
                self.launcher.launch(kernel, count, lambda part, first, count: [*common, signal_slots[part]],
                                     start=first, label=f"G2P {g.name}", min_range=MIN_TRANSFER_RANGE, site=site)

    def adopt(self, state: ParticleState, recolor: bool = True) -> None:
        """Fine blocks and colors for a state replaced wholesale (loaded, edited, merged)."""
        if self.slow is not None and self.slow.open:
            raise RuntimeError("close the slow set's step before replacing the particles")
        self.slow_count = 0  # every particle fast until the next sort
        if self.refiner is not None:
            self._after_activation(self.refiner.activate(state))
        if recolor:  # a checkpoint keeps the colors its run gave it
            self.color_particles(state)
        if self.slow is not None:  # the slow set is chosen again (as the sort at a frame end does)
            self.sort_by_cell(state)

    def reset_step_count(self, steps: int) -> None:
        """Steps taken so far (refinement runs every ``refine_every`` steps), for resuming."""
        self._steps = steps

    def move_colliders(self, time: float) -> None:
        """Colliders to time t (Eq. 22 velocities), color fields rebuilt if they moved."""
        if self.colliders is not None and self.colliders.move(time, self.grids, self.launcher):
            self.collider_arrays = self.colliders.arrays

    def color_particles(self, state: ParticleState, min_id: int = -1) -> None:
        """CPIC color of every particle (with an id from ``min_id`` on) from its own grid; G2P updates it."""
        if self.colliders is not None and self.cpic:
            self.colliders.color_particles(state, self.grids, self.launcher, min_id)

    # ------------------------------------------------------------------ refinement

    def set_region(self, cells: np.ndarray, state: ParticleState | None = None) -> None:
        """Refined coarse cells (adaptive mode)."""
        self.refiner.set_region(cells)
        self._after_activation(0, region_changed=True)
        if state is not None:
            self.refine(state)

    def refine(self, state: ParticleState) -> None:
        """Split particles that entered the region (Eq. 15); activate the fine blocks level 1 reaches."""
        first_child = self._next_id
        skip = 0 if self.slow is None or self.slow.may_be_near() else self.slow_count  # S: far from the region
        n_split = self.refiner.split(state, first_child, self.collider_arrays, self.materials, skip)
        if n_split:
            self._next_id += n_split * self.refiner.b**3
            self.color_particles(state, min_id=first_child)  # only the children moved
            self.sort_by_cell(state, keep_slow=True)  # the children joined at the end: each level contiguous again
        self._after_activation(self.refiner.activate(state, 0 if n_split else skip))

    def _after_activation(self, first_slot: int, region_changed: bool = False) -> None:
        fine = self.grids[1]  # the new blocks' colors and shares
        if self.colliders is not None:
            fine.color = grow_color_field(fine.color, fine.capacity)
            self.colliders.color(fine, self.launcher, first_slot)
        if self.partition is not None:
            self.partition.update(self.refiner.region_cells if region_changed else None, first_slot)

    def sort_by_cell(self, state: ParticleState, keep_slow: bool = False) -> None:
        """Reorder particles by coarse cell (P2G/G2P touch memory coherently), by level first
        in adaptive mode; the slow set keeps its particles while its step is open, and with
        ``keep_slow`` while its drift bound holds (after a split: only the rest is sorted)."""
        keep = self.slow is not None and (self.slow.open or (keep_slow and not self.slow.may_be_near()))
        near, first = None, self.slow_count if keep else 0
        if self.slow is not None and not keep and self.choose_slow:  # the slow set chosen again
            near = self.slow.grow_near(state, self.refiner.region_cells, (0, state.count), SORT_HALO)
            self.slow.drift = 0.0
        self._sorted, n_slow = sort_by_cell(state, self.grid.spec, self.refiner is not None, self.launcher,
                                            self._sorted, near, first)
        self.slow_count = n_slow if first == 0 else self.slow_count
        self._find_level_ranges(state)  # fresh for the time stepping's cost rule (and the next segment)
