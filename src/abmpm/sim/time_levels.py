"""A time step per level: the slow set (docs/method.md, "A time step per level").

In adaptive mode with ``time_steps = "per_level"`` the level-0 particles far from
everything fine (the refined region, the level-1 particles) form the slow set S. S
takes one coarse step DT = k dt while every other particle (the fast set F) takes k
substeps of dt, the fine CFL step. The temporal interface is between particles of the
coarse grid, so the level interface is untouched.

One coarse step of S, a block:

* **open** (a host point): S scatters once onto the coarse grid, into arrays of its
  own: mass m^S_i, APIC momentum p^S_i (Eq. 8) and internal force f^S_i (Eq. 10 per
  unit time, the stress of the block's start);
* **each substep** the grid update adds S to the node, m_i += m^S_i and
  m_i v_i += p^S_i + dt f^S_i, and after the update S's share keeps the node's new
  velocity, p^S_i = m^S_i v_i (S is material on the grid whose velocity evolves with
  the node's, its positions and stress frozen for the block);
* **close** (a host point): S gathers the last node velocities (Eqs. 11-12) and moves
  with the block's whole length T (Eq. 7, advection), as original mode does with a
  step T.

Momentum is exact: in every substep the grid holds F's scattered momentum plus
sum_i p^S_i, which is S's momentum after the last substep, and S's gather at the close
takes exactly sum_i m^S_i v_i = sum_i p^S_i. Far from F a node's velocity after k
substeps is u + T (f^S / m^S + g): original mode's update with step T.

Who is slow is decided when the particles are sorted (they are sorted by class, so S is
one range): a level-0 particle whose cell is farther than SORT_HALO cells from the
*core* (region cells, cells holding level-1 particles; ``SlowSet.grow_near``). Near a
static collider S takes CPIC's masks at the open (the compatible nodes of its frozen
positions) and its G2P at the close casts the whole step's path, as original mode does
with a step T. S must stay at least GUARD_HALO = 3 cells from the core: two particles'
coarse stencils (x +- 1.5 dx) share no node more than three cells apart, so no S particle
shares a node with a level-1 particle's overlap scatter or reaches a fine node a
level-1 particle gathers from (a guard of 1 cell, with S's nodes marked for the overlap,
was measured and not kept: docs/method.md, "A time step per level"). The solver adds up how
far the particles can have moved since that sort (each substep dt times the fastest fast
particle, each step of S its length times S's fastest); before the sum reaches
SORT_HALO - GUARD_HALO cells, the next open sorts (and chooses S) again. Frame ends sort
anyway. A split while a step of S is open sorts the other particles only: S keeps its
place in the storage.
"""

from __future__ import annotations

import functools
import math

import numpy as np
import warp as wp
from scipy import ndimage

from .colliders import ALL_NODES, ColorField, node_bit
from .grid import GridSpec
from .materials import ALL_MODELS, MaterialParams, dispatch
from .p2g import own_side_mask, record_reach
from .parallel import (CPU_NODE_CHUNK, MIN_TRANSFER_RANGE, REACH_STRIDE, Launcher, Reach, ThreadSums, add_thread_sums,
                       reset_reach)
from .segments import Signals
from .state import ParticleArrays, ParticleState
from .stencil import dense_node_at, dense_stencil, offset_at, weight_at
from .variant import variant

wp.set_module_options({"enable_backward": False})

GUARD_HALO = 3  # coarse cells: no S particle this close to the core (the drift bound keeps it so)
SORT_HALO = 5  # coarse cells: S at a sort lies beyond this (2 cells of drift before a re-sort)


@wp.struct
class SlowNodes:
    """The slow set on the coarse grid during a block (``on`` = 0: no block open)."""

    m: wp.array(dtype=float)  # S's mass per node
    p: wp.array(dtype=wp.vec3)  # S's node momentum: APIC at the open, m^S v after each substep
    f: wp.array(dtype=wp.vec3)  # S's internal force (Eq. 10 per unit time), frozen for the block
    on: int


@wp.func
def add_slow(slow: SlowNodes, n: int, dt: float, m: float, mv: wp.vec3):
    """Node ``n``'s mass and momentum with S added (nothing when no block is open)."""
    if slow.on == 0:
        return m, mv
    return m + slow.m[n], mv + slow.p[n] + dt * slow.f[n]


@wp.func
def keep_slow_share(slow: SlowNodes, n: int, vi: wp.vec3):
    """After the node update: S's share of the node moves with the node's velocity."""
    if slow.on != 0:
        ms = slow.m[n]
        if ms > 0.0:
            slow.p[n] = ms * vi


def _make_p2g_slow(cpic: bool, models: tuple[int, ...]):
    particle_stress = dispatch(models).particle_stress

    @variant("p2g_slow", cpic, models=models)
    def p2g_slow(first: int, s: ParticleArrays, materials: wp.array(dtype=MaterialParams), g: GridSpec,
                 color: ColorField, cmask: wp.array(dtype=wp.int32), m: wp.array(dtype=float),
                 p: wp.array(dtype=wp.vec3), f: wp.array(dtype=wp.vec3), reach: Reach):
        # S at a block's open: Eq. 8's mass and APIC momentum, Eq. 10's force per unit time;
        # near a collider only onto the nodes on its side (CPIC), the mask kept for the close
        q = wp.tid() + first
        st = dense_stencil(g, s.x[q])
        tau = wp.static(particle_stress)(materials[s.material[q]], s.F, s.history, q, s.C[q])
        force = (-s.volume[q] * 4.0 * g.inv_dx * g.inv_dx) * tau
        affine = s.mass[q] * s.C[q]
        mv = s.mass[q] * s.v[q]
        mask = ALL_NODES
        if wp.static(cpic):
            if s.surface_body[q] >= 0:
                mask = own_side_mask(s.surface_point[q], s.surface_side[q], s.surface_body[q], s.x[q], s.level[q],
                                     color, g, st, cmask, q)
        record_reach(g, st, reach)
        for i in range(3):
            for j in range(3):
                for k in range(3):
                    w = weight_at(st, i, j, k)
                    if wp.static(cpic):
                        w = w * node_bit(mask, i, j, k)
                    n = dense_node_at(g, st, i, j, k)
                    d = offset_at(g, st, i, j, k)
                    wp.atomic_add(p, n, w * (mv + affine * d))
                    wp.atomic_add(m, n, w * s.mass[q])
                    wp.atomic_add(f, n, w * (force * d))

    return p2g_slow


@functools.cache
def p2g_slow_kernel(cpic: bool, models: tuple[int, ...] = ALL_MODELS):
    return _make_p2g_slow(cpic, models)


@wp.kernel
def add_slow_sums(first: int, sums: ThreadSums, pf: wp.array(dtype=wp.vec3), p: wp.array(dtype=wp.vec3),
                  m: wp.array(dtype=float), f: wp.array(dtype=wp.vec3), count: int, chunk: int):
    # the extra CPU parts' S sums, in part order, where each reached; cleared after:
    # momentum and mass as the grid update adds P2G's, the forces (``pf``, stacked like
    # ``sums.mv``) over the same spans
    n0 = (wp.tid() + first) * chunk
    n1 = wp.min(n0 + chunk, count)
    for t in range(sums.extra):
        lo = wp.max(n0, sums.bounds[REACH_STRIDE * (t + 1)])
        hi = wp.min(n1 - 1, sums.bounds[REACH_STRIDE * (t + 1) + 1])
        for n in range(lo, hi + 1):
            q = t * sums.stride + n
            f[n] = f[n] + pf[q]
            pf[q] = wp.vec3(0.0)
    add_thread_sums(sums, n0, n1, p, m)


@wp.func
def cell_of(g: GridSpec, x: wp.vec3):
    # the flat index of the coarse cell holding x (clamped into the grid)
    X = (x - g.origin) * g.inv_dx
    i = wp.clamp(int(X[0]), 0, g.dims[0] - 2)
    j = wp.clamp(int(X[1]), 0, g.dims[1] - 2)
    k = wp.clamp(int(X[2]), 0, g.dims[2] - 2)
    return (i * (g.dims[1] - 1) + j) * (g.dims[2] - 1) + k


@wp.kernel
def mark_level1_cells(first: int, x: wp.array(dtype=wp.vec3), level: wp.array(dtype=wp.int32), g: GridSpec,
                      core: wp.array(dtype=wp.int32)):
    q = wp.tid() + first
    if level[q] != 0:
        core[cell_of(g, x[q])] = 1


class SlowSet:
    """The slow set's arrays and its open / close (the solver calls these at host points)."""

    def __init__(self, coarse, launcher: Launcher, device):
        self.coarse = coarse
        self.launcher = launcher
        self.device = device
        cells = tuple(d - 1 for d in coarse.dims)
        self.cells = cells
        self._core = wp.zeros(cells, dtype=wp.int32, device=device)
        self._fixed = None  # ((region, halo) key, near from the region alone)
        self.near = wp.zeros(cells, dtype=wp.int32, device=device)  # the core grown by a halo
        n = coarse.capacity
        self.nodes = SlowNodes()
        self.nodes.m = wp.zeros(n, dtype=float, device=device)
        self.nodes.p = wp.zeros(n, dtype=wp.vec3, device=device)
        self.nodes.f = wp.zeros(n, dtype=wp.vec3, device=device)
        self.nodes.on = 0
        extra = launcher.threads - 1
        self._pf = wp.zeros(max(1, extra * n), dtype=wp.vec3, device=device)  # extra parts' forces
        self.drift = 0.0  # how far the particles may have moved since the sort that chose S (m)
        self.elapsed = 0.0  # length of the open block so far (s)
        self.taken = 0  # substeps in the open block
        self.dt = wp.zeros(1, dtype=float, device=device)  # the block's length at its close (G2P)
        self.signal = Signals(1, launcher.threads, device)  # S's CFL signal at the close
        self._kept_p = None  # S's node momentum at a segment start (rewind; made on the first use)

    @property
    def open(self) -> bool:
        return self.nodes.on != 0

    def grow_near(self, state: ParticleState, region: np.ndarray, level1: tuple[int, int], halo: int) -> wp.array:
        """``near`` = the core (region, level-1 cells) grown by ``halo`` cells (a cube): a
        flag per coarse cell, flat. Grown on the host with scipy's maximum filter, at
        sorts only: the region's part (``region``, host flags per cell) once per region,
        the level-1 cells' part over their bounding box only (the whole grid cost 14 ms
        a sort at the paper panel's 290k cells). Colliders' bands are not excluded: S
        near a static collider takes CPIC's masks at its open and casts its whole
        step's path at its close, as original mode does with that step."""
        key = (hash(region.tobytes()), halo)  # ~0.1 ms; the region changes with set_region only
        if self._fixed is None or self._fixed[0] != key:
            fixed = ndimage.maximum_filter(region.astype(np.uint8), size=2 * halo + 1, mode="constant") > 0
            self._fixed = (key, fixed)
        self._core.zero_()
        self.launcher.launch(mark_level1_cells, level1[1], [state.x, state.level, self.coarse.spec,
                                                            self._core.flatten()], start=level1[0])
        core, near = self._core.numpy(), self._fixed[1].copy()
        if core.any():
            box = []
            for axis in range(3):
                hit = np.flatnonzero(core.any(axis=tuple(a for a in range(3) if a != axis)))
                box.append(slice(max(0, hit[0] - halo), hit[-1] + halo + 1))
            box = tuple(box)
            near[box] |= ndimage.maximum_filter(core[box], size=2 * halo + 1, mode="constant") > 0
        self.near.assign(near.astype(np.int32))
        return self.near.flatten()

    def scatter(self, state: ParticleState, slow: tuple[int, int], materials: wp.array, models, cpic: bool,
                color: ColorField, cmask: wp.array) -> None:
        """Open a block: S onto its node arrays (threads into private sums, added in part order);
        with ``cpic``, each S particle near a collider onto its side's nodes (``color``, the
        coarse grid's), its mask into ``cmask`` for the close's G2P."""
        s = self.nodes
        s.m.zero_()
        s.p.zero_()
        s.f.zero_()
        stride = s.m.shape[0]
        private = self.launcher.private_grids("slow", s.p, s.m)
        g = self.coarse.spec

        def inputs(part, first, count):
            f = s.f if part == 0 else self._pf[(part - 1) * stride:part * stride]
            pp, pm = private.parts[part]
            return [state.arrays(), materials, g, color, cmask, pm, pp, f, private.reach[part]]

        self.launcher.launch(p2g_slow_kernel(cpic, models), slow[1], inputs, start=slow[0], label="P2G coarse (slow)",
                             min_range=MIN_TRANSFER_RANGE)
        if private.extra > 0:
            chunk = CPU_NODE_CHUNK  # only CPU parts have extra sums
            self.launcher.launch(add_slow_sums, -(-self.coarse.node_count // chunk),
                                 [private.sums, self._pf, s.p, s.m, s.f, self.coarse.node_count, chunk],
                                 label="slow sums", min_range=64)
            self.launcher.launch(reset_reach, private.extra + 1, [private.bounds], label="reset slow")
        s.on = 1
        self.elapsed, self.taken = 0.0, 0

    def may_be_near(self) -> bool:
        """Whether the particles can have closed the gap between S and the core by
        SORT_HALO - GUARD_HALO cells since the sort that chose S (then sort again)."""
        return self.drift > (SORT_HALO - GUARD_HALO) * self.coarse.dx

    def due(self, block: int) -> bool:
        """Whether the open step must end before the next segment: it is ``block`` substeps long."""
        return self.open and self.taken >= block

    def segment_cap(self, block: int, due: bool) -> int | None:
        """The most substeps the next segment may have, so that S's step ends with a
        segment (None: no limit)."""
        if block < 2:
            return None
        return block - self.taken if self.open and not due else block

    def ran(self, substeps: int, dt: float, keep: bool) -> None:
        """A segment of ``substeps`` begins inside the open step (with ``keep``, a copy
        of S's node momentum for a rewind)."""
        if self.open:
            if keep:
                if self._kept_p is None:
                    self._kept_p = wp.empty_like(self.nodes.p)
                wp.copy(self._kept_p, self.nodes.p)
            self.taken += substeps
            self.elapsed += substeps * dt

    def unrun(self, substeps: int, dt: float) -> None:
        """A rewind takes ``substeps`` of the segment back."""
        if self.open:
            wp.copy(self.nodes.p, self._kept_p)
            self.taken -= substeps
            self.elapsed -= substeps * dt

    def gather(self, state: ParticleState, slow: tuple[int, int], g2p, common: list) -> tuple[float, float]:
        """Close the step: S gathers from the coarse grid with its whole length T
        (``g2p``, the coarse G2P kernel, with ``common`` up to its dt and signal, then
        ``self.dt``, the rest and each part's signal slot). Returns S's CFL signal."""
        elapsed = self.elapsed
        self.nodes.on = 0
        self.elapsed, self.taken = 0.0, 0
        self.dt.fill_(elapsed)
        self.signal.reset()
        head, tail = common
        slots = self.signal.slots[0]
        self.launcher.launch(g2p, slow[1], lambda part, first, count: [*head, self.dt, *tail, slots[part]],
                             start=slow[0], label="G2P coarse (slow)", min_range=MIN_TRANSFER_RANGE)
        a = self.signal.read(1)[0]
        self.drift += elapsed * float(a[0])  # S moved this far at most
        return float(a[0]), float(a[1])


def no_slow(device) -> SlowNodes:
    """The grid update's argument where no slow set exists."""
    s = SlowNodes()
    s.m = wp.zeros(1, dtype=float, device=device)
    s.p = wp.zeros(1, dtype=wp.vec3, device=device)
    s.f = wp.zeros(1, dtype=wp.vec3, device=device)
    s.on = 0
    return s


def split_off_slow(ranges: dict, n_slow: int) -> dict:
    """Level ranges with the first ``n_slow`` level-0 particles as the range ``"slow"``,
    left out of every other pass (if the particles are partitioned by level and there
    are that many level-0 particles; else no slow range)."""
    level0, level1 = ranges.get(0), ranges.get(1)
    if (level0 is None or level1 is None or n_slow <= 0 or len(level0) != 1 or level0[0][0] != 0
            or level0[0][1] < n_slow or level0 == ranges[None]):  # one level, none slow, or unsorted
        return {**ranges, "slow": [(0, 0)]}
    n0 = level0[0][1]
    fast0 = [(n_slow, n0 - n_slow)]
    return {0: fast0, 1: level1, None: fast0 + level1, "slow": [(0, n_slow)]}


# What a time step per level costs and saves, in units of one level-0 particle's substep
# (~190 ns on the 2-core CPU; paper panel and sloshing tank profiles, docs/benchmarks.md):
# a slow particle's step (scatter and gather) 1.4; per coarse node, clearing and summing
# the slow set's node arrays 0.032 a step and its share in the grid update 0.008 a substep.
SLOW_STEP_COST, SLOW_NODE_STEP_COST, SLOW_NODE_SUBSTEP_COST = 1.4, 0.032, 0.008
# A level-1 particle's substep (fine P2G and G2P, the overlap scatter, the contact band),
# in the same unit (docs/method.md, "A time step per level": the sloshing tank's profile)
LEVEL1_SUBSTEP_COST = 3.0


def slow_substep_cost(n_slow: int, nodes: int, k: int) -> float:
    """S's cost a substep when it takes a step every ``k`` substeps (``nodes``: the coarse
    grid's), or ``n_slow`` (stepping with everyone) where stepping apart would not pay:
    its particles' saving must outweigh the work the size of the coarse grid it adds."""
    apart = n_slow * SLOW_STEP_COST / k + nodes * (SLOW_NODE_STEP_COST / k + SLOW_NODE_SUBSTEP_COST)
    return apart if k >= 2 and apart < n_slow else float(n_slow)


def cut_for_levels(rest: float, dt_max: float, slow_dt: float, cap: int, n_slow: int, fast_cost: float,
                   nodes: int) -> tuple[int, int]:
    """The rest of a frame in equal substeps, and S's step in substeps: the cheapest of
    the cuts into substeps no longer than ``dt_max`` that give S a step of 1 ... ``cap``
    substeps no longer than ``slow_dt``. The first cut is the fewest substeps, with k as
    many of them as fit in ``slow_dt``; the others shorten the substep to slow_dt / k, so
    that F pays more substeps for S's fewer steps (``fast_cost``: F's cost a substep, in
    level-0 particle substeps). Ties keep the fewest substeps. Returns (substeps, block):
    block = k where S steps apart, 1 where it steps with everyone."""
    fewest = max(1, math.ceil(rest / dt_max - 1e-9))
    best = None
    for want in range(1, max(1, cap) + 1):
        n = fewest if want == 1 else max(fewest, math.ceil(rest * want / slow_dt - 1e-9))
        k = max(1, min(cap, math.floor(slow_dt * n / rest * (1.0 + 1e-9)), n))
        slow = slow_substep_cost(n_slow, nodes, k)
        cost = n * (fast_cost + slow)
        if best is None or cost < best[0] * (1.0 - 1e-9):
            best = (cost, n, k if slow < n_slow else 1)
    return best[1], best[2]


def fast_substep_cost(ranges: dict, n_slow: int) -> float:
    """The fast set's cost a substep in level-0 particle substeps, from the level ranges
    (``split_off_slow``'s) and the slow set's size: its level-0 particles at 1, its level-1
    particles at LEVEL1_SUBSTEP_COST (unsorted particles count at every level)."""
    count = lambda key: sum(c for _, c in ranges.get(key, ()))  # noqa: E731
    return count(0) + count("slow") - n_slow + LEVEL1_SUBSTEP_COST * count(1)
