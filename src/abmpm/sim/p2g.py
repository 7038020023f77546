"""Particle to grid (paper Eqs. 8-10), one kernel per pass.

Every particle scatters mass and momentum to every grid, with that grid's kernel
and spacing (Eq. 8); MLS-MPM folds the stress into the affine momentum (Eqs. 9-10).
With colliders, a particle scatters only to the nodes on its side of every surface
(CPIC, ``colliders.compatibility_mask``). The passes:

=====================  =========================================================
``p2g_dense``          original and finest modes: every particle to the one grid
``p2g_level0``         adaptive, coarse grid: level-0 particles; each node they
                       reach is marked as part of the overlap
``p2g_overlap``        adaptive, coarse grid: level-1 particles, into the marked
                       nodes only (the overlap of Eq. 8, where coarse particles
                       can feel them); elsewhere nobody gathers from the coarse grid;
                       a child the coarse grid moves (``Refiner.coarse_children``)
                       with its whole stencil
``p2g_sparse``         adaptive, fine block-sparse grid: every particle, to the
                       active blocks; a level-0 particle as the family it would
                       split into (``sim/footprint.py``)
=====================  =========================================================

With ``walls.images`` every pass adds, for a particle within reach of a domain wall, its
mirror images' stress (``sim/wall_images.py``).

The stress is evaluated once per step: the two coarse passes keep it per particle,
the fine pass reads it back. Each pass is compiled for CPIC or not and for the
scene's material models (``sim/variant.py``).

CPU threads (``sim/parallel.py``): part t > 0 of a threaded launch scatters into its
own accumulators and records the span of storage indices it reached in its
``Reach``; on part 0 and on CUDA ``reach.track`` is 0 and nothing is recorded.
"""

from __future__ import annotations

import functools

import warp as wp

from .colliders import ALL_NODES, ColorField, compatibility_mask, compatible, near_surface, node_bit, nodes_facing
from .footprint import MAX_HALF_WIDTH, footprint, footprint_weights, stress_weight
from .grid import (
    AMONG_FINE,
    BLOCK_NODES,
    HOLDS_LEVEL1,
    REACHED_BY_LEVEL0,
    GridSpec,
    cell_flag,
    dense_node_index,
    moving_level,
    node_index,
    node_position,
    stencil_node,
    stencil_slots,
)
from .materials import ALL_MODELS, MaterialParams, dispatch
from .parallel import EMPTY_BOUND, Reach, widen_reach
from .state import ParticleArrays
from .stencil import Stencil, dense_node_at, dense_stencil, offset_at, sparse_node_at, stencil_touches_active, weight_at
from .variant import variant
from .wall_images import REACH, near_a_wall, scatter_footprint_images, scatter_wall_images

wp.set_module_options({"enable_backward": False})

EMPTY = wp.constant(EMPTY_BOUND)  # the low end of a span nothing reached yet


@wp.func
def affine_momentum(s: ParticleArrays, p: int, g: GridSpec, dt: float, tau: wp.mat33):
    # MLS-MPM force folded into the affine momentum (Eqs. 9-10):
    # m_i v_i += w (m v_p + [m C_p - dt 4/dx^2 V0 tau] (x_i - x_p))
    return stress_momentum(s, p, g, dt, tau) + s.mass[p] * s.C[p]


@wp.func
def stress_momentum(s: ParticleArrays, p: int, g: GridSpec, dt: float, tau: wp.mat33):
    # the stress part of affine_momentum, which a wall image adds (sim/wall_images.py)
    return (-dt * s.volume[p] * 4.0 * g.inv_dx * g.inv_dx) * tau


@wp.func
def wall_images(s: ParticleArrays, p: int, g: GridSpec, st: Stencil, dt: float, tau: wp.mat33, mask: int,
                grid_mv: wp.array(dtype=wp.vec3)):
    # the particle's mirror images across the walls within its reach
    if g.wall_images != 0:
        if near_a_wall(g, s.x[p], REACH):
            scatter_wall_images(g, st, s.x[p], stress_momentum(s, p, g, dt, tau), tau, mask, grid_mv)


@wp.func
def scatter(grid_mv: wp.array(dtype=wp.vec3), grid_m: wp.array(dtype=float), n: int, weight: float, mv: wp.vec3,
            affine: wp.mat33, dpos: wp.vec3, m: float):
    # Eq. 8 for one node
    wp.atomic_add(grid_mv, n, weight * (mv + affine * dpos))
    wp.atomic_add(grid_m, n, weight * m)


@wp.func(inline=True)
def own_side_mask(surface_point: wp.vec3, surface_side: wp.vec3, surface_body: int, xp: wp.vec3, level: int,
                  color: ColorField, g: GridSpec, st: Stencil, cmask: wp.array(dtype=wp.int32), p: int):
    # CPIC for a particle near a collider (surface_body >= 0): the stencil nodes on its
    # side of every collider; its own grid keeps the mask for its G2P. (Values, not the
    # particle struct: a struct argument is copied, 1.1 kB a particle, and this
    # function is not inlined.)
    mask = compatibility_mask(surface_point, surface_side, surface_body, xp, color, g, st.base, st.fx)
    if level == g.level:
        cmask[p] = mask
    return mask


@wp.func
def record_reach(g: GridSpec, st: Stencil, reach: Reach):
    # widen [span[0], span[1]] to the storage indices of the stencil: the corner
    # nodes on a dense grid, the blocks' whole slots on a sparse one
    if reach.track == 0:
        return
    lo = int(0)
    hi = int(0)
    if g.sparse == 0:
        lo = dense_node_index(g, st.base[0], st.base[1], st.base[2])
        hi = dense_node_index(g, st.base[0] + 2, st.base[1] + 2, st.base[2] + 2)
    else:
        lo = EMPTY
        hi = -1
        for q in range(8):
            if st.slots[q] >= 0:
                lo = wp.min(lo, st.slots[q] * BLOCK_NODES)
                hi = wp.max(hi, st.slots[q] * BLOCK_NODES + BLOCK_NODES - 1)
    widen_reach(reach, lo, hi)


@wp.func
def overlap_reached(g: GridSpec, overlap: wp.array(dtype=wp.int32), base: wp.vec3i):
    # a cheap test on the stencil's 8 corners and centre (material reaching only
    # edge midpoints of the stencil is left out of the overlap)
    if overlap[node_index(g, base[0] + 1, base[1] + 1, base[2] + 1)] != 0:
        return True
    for a in range(2):
        for b in range(2):
            for c in range(2):
                if overlap[node_index(g, base[0] + 2 * a, base[1] + 2 * b, base[2] + 2 * c)] != 0:
                    return True
    return False


def _make_p2g_dense(cpic: bool, models: tuple[int, ...]):
    particle_stress = dispatch(models).particle_stress

    @variant("p2g_dense", cpic, models=models)
    def p2g_dense(first: int, s: ParticleArrays, materials: wp.array(dtype=MaterialParams), g: GridSpec,
                  color: ColorField, dt_now: wp.array(dtype=float), cmask: wp.array(dtype=wp.int32),
                  grid_mv: wp.array(dtype=wp.vec3), grid_m: wp.array(dtype=float), reach: Reach):
        p = wp.tid() + first
        st = dense_stencil(g, s.x[p])
        tau = wp.static(particle_stress)(materials[s.material[p]], s.F, s.history, p, s.C[p])
        affine = affine_momentum(s, p, g, dt_now[0], tau)
        mask = ALL_NODES
        if wp.static(cpic):
            if s.surface_body[p] >= 0:
                mask = own_side_mask(s.surface_point[p], s.surface_side[p], s.surface_body[p], s.x[p], s.level[p],
                                     color, g, st, cmask, p)
        record_reach(g, st, reach)
        mv = s.mass[p] * s.v[p]
        for i in range(3):
            for j in range(3):
                for k in range(3):
                    weight = weight_at(st, i, j, k)
                    if wp.static(cpic):
                        weight = weight * node_bit(mask, i, j, k)
                    scatter(grid_mv, grid_m, dense_node_at(g, st, i, j, k), weight, mv, affine,
                            offset_at(g, st, i, j, k), s.mass[p])
        wall_images(s, p, g, st, dt_now[0], tau, mask, grid_mv)

    return p2g_dense


def _make_p2g_level0(cpic: bool, models: tuple[int, ...]):
    particle_stress = dispatch(models).particle_stress

    @variant("p2g_level0", cpic, models=models)
    def p2g_level0(first: int, s: ParticleArrays, materials: wp.array(dtype=MaterialParams), g: GridSpec,
                   color: ColorField, dt_now: wp.array(dtype=float), cmask: wp.array(dtype=wp.int32),
                   grid_mv: wp.array(dtype=wp.vec3), grid_m: wp.array(dtype=float), reach: Reach,
                   tau_store: wp.array(dtype=wp.mat33), overlap: wp.array(dtype=wp.int32)):
        p = wp.tid() + first
        if s.level[p] != 0:
            return
        st = dense_stencil(g, s.x[p])
        tau = wp.static(particle_stress)(materials[s.material[p]], s.F, s.history, p, s.C[p])
        tau_store[p] = tau  # for p2g_sparse
        affine = affine_momentum(s, p, g, dt_now[0], tau)
        mask = ALL_NODES
        if wp.static(cpic):
            if s.surface_body[p] >= 0:
                mask = own_side_mask(s.surface_point[p], s.surface_side[p], s.surface_body[p], s.x[p], s.level[p],
                                     color, g, st, cmask, p)
        record_reach(g, st, reach)
        mv = s.mass[p] * s.v[p]
        for i in range(3):
            for j in range(3):
                for k in range(3):
                    n = dense_node_at(g, st, i, j, k)
                    overlap[n] = REACHED_BY_LEVEL0
                    weight = weight_at(st, i, j, k)
                    if wp.static(cpic):
                        weight = weight * node_bit(mask, i, j, k)
                    scatter(grid_mv, grid_m, n, weight, mv, affine, offset_at(g, st, i, j, k), s.mass[p])
        wall_images(s, p, g, st, dt_now[0], tau, mask, grid_mv)

    return p2g_level0


def _make_p2g_overlap(cpic: bool, models: tuple[int, ...]):
    particle_stress = dispatch(models).particle_stress

    @variant("p2g_overlap", cpic, models=models)
    def p2g_overlap(first: int, s: ParticleArrays, materials: wp.array(dtype=MaterialParams), g: GridSpec,
                    color: ColorField, dt_now: wp.array(dtype=float), cmask: wp.array(dtype=wp.int32),
                    grid_mv: wp.array(dtype=wp.vec3), grid_m: wp.array(dtype=float), reach: Reach,
                    tau_store: wp.array(dtype=wp.mat33), overlap: wp.array(dtype=wp.int32),
                    on_fine: wp.array(dtype=wp.int32), movers: int):
        # Two launches a substep: first the children the coarse grid moves (``movers`` 0,
        # Refiner.coarse_children), which scatter their whole stencil and mark its nodes, then
        # the others (1), onto the nodes level 0 or those children reached. Within each launch
        # no node's mark goes from none to some while another particle reads it, so the
        # result does not depend on which thread gets there first.
        p = wp.tid() + first
        if s.level[p] != 1:
            return
        mover = moving_level(on_fine, p, 1)
        if mover != movers:
            return
        st = dense_stencil(g, s.x[p])
        tau = wp.static(particle_stress)(materials[s.material[p]], s.F, s.history, p, s.C[p])
        tau_store[p] = tau  # for p2g_sparse
        if mover == 1 and not overlap_reached(g, overlap, st.base):
            return
        affine = affine_momentum(s, p, g, dt_now[0], tau)
        mask = ALL_NODES
        if wp.static(cpic):
            if s.surface_body[p] >= 0:
                mask = own_side_mask(s.surface_point[p], s.surface_side[p], s.surface_body[p], s.x[p], mover,
                                     color, g, st, cmask, p)
            elif near_surface(color, g, s.x[p]):
                # A level-1 particle's color reaches PARTICLE_BAND fine cells, but its
                # stencil on this coarser grid reaches up to 2.6 coarse cells: beyond
                # its own band it may still have coarse nodes behind a surface, and
                # would push the material on their far side of a thin wall. The nodes'
                # own colors tell which (no closest-point query needed).
                mask = nodes_facing(s.x[p], color, g, st.base, st.fx)
        record_reach(g, st, reach)
        mv = s.mass[p] * s.v[p]
        reached = int(0)  # the stencil's nodes in the overlap, for the wall images
        for i in range(3):
            for j in range(3):
                for k in range(3):
                    n = dense_node_at(g, st, i, j, k)
                    if overlap[n] != 0 or mover == 0:
                        reached = reached | (1 << (9 * i + 3 * j + k))
                        weight = weight_at(st, i, j, k)
                        if wp.static(cpic):
                            weight = weight * node_bit(mask, i, j, k)
                        if weight > 0.0 and overlap[n] != HOLDS_LEVEL1:  # a write only when it changes
                            overlap[n] = HOLDS_LEVEL1
                        scatter(grid_mv, grid_m, n, weight, mv, affine, offset_at(g, st, i, j, k), s.mass[p])
        wall_images(s, p, g, st, dt_now[0], tau, mask & reached, grid_mv)

    return p2g_overlap


def _make_scatter_footprint(cpic: bool):
    @wp.func
    def scatter_footprint(s: ParticleArrays, p: int, g: GridSpec, color: ColorField, dt: float, tau: wp.mat33,
                          grid_mv: wp.array(dtype=wp.vec3), grid_m: wp.array(dtype=float), reach: Reach):
        # A level-0 particle onto the fine grid as the family it would split into (sim/footprint.py):
        # Eq. 8's mass and momentum with the family's weights, Eq. 10's stress with the sum of
        # its children's. CPIC node by node: the particle's color is the exact closest
        # point, on any grid. Returns whether every node of the footprint is active.
        xp = s.x[p]
        fp = footprint(g, xp, s.volume[p])
        # its 5 nodes per axis lie in the 2 blocks per axis a 3x3x3 stencil at the same
        # base spans: one table lookup per block
        slots = stencil_slots(g, fp.base)
        if wp.max(slots) < 0:
            return False
        fp = footprint_weights(g, xp, fp)
        stress = (-dt * s.volume[p]) * tau  # Eq. 10, times each node's stress weight
        affine = s.mass[p] * s.C[p]
        mv = s.mass[p] * s.v[p]
        lo = EMPTY
        hi = int(-1)
        whole = bool(True)
        for i in range(fp.nodes):
            for j in range(fp.nodes):
                weight_ij = fp.wx[i] * fp.wy[j]
                for k in range(fp.nodes):
                    weight = weight_ij * fp.wz[k]
                    n = stencil_node(g, slots, fp.base, i, j, k)
                    if weight > 0.0 and n < 0:
                        whole = False
                    if weight > 0.0 and n >= 0:
                        dpos = node_position(g, fp.base + wp.vec3i(i, j, k)) - xp
                        ok = True
                        if wp.static(cpic):
                            ok = compatible(s.surface_point[p], s.surface_side[p], s.surface_body[p], xp, color,
                                            xp + dpos, n, g.dx)
                        if ok:
                            wp.atomic_add(grid_mv, n, weight * (mv + affine * dpos)
                                          + stress * stress_weight(fp, i, j, k, g.inv_dx))
                            wp.atomic_add(grid_m, n, weight * s.mass[p])
                            lo = wp.min(lo, n)
                            hi = wp.max(hi, n)
        if g.wall_images != 0 and near_a_wall(g, xp, REACH + MAX_HALF_WIDTH):
            # its images' stress (sim/wall_images.py), not in a collider's band: there each
            # footprint node passes CPIC's test of its own, which the images do not repeat
            images = True
            if wp.static(cpic):
                images = s.surface_body[p] < 0
            if images:
                scatter_footprint_images(g, fp, xp, stress, tau, grid_mv)
        widen_reach(reach, lo, hi)
        return whole

    return scatter_footprint


def _make_p2g_sparse(cpic: bool, models: tuple[int, ...]):
    scatter_footprint = _make_scatter_footprint(cpic)

    @variant("p2g_sparse", cpic, models=models)
    def p2g_sparse(first: int, s: ParticleArrays, materials: wp.array(dtype=MaterialParams), g: GridSpec,
                   color: ColorField, dt_now: wp.array(dtype=float), cmask: wp.array(dtype=wp.int32),
                   grid_mv: wp.array(dtype=wp.vec3), grid_m: wp.array(dtype=float), reach: Reach,
                   tau_store: wp.array(dtype=wp.mat33), on_fine: wp.array(dtype=wp.int32),
                   beside: wp.array3d(dtype=wp.int32), coarse: GridSpec):
        p = wp.tid() + first
        if s.level[p] == 0:
            # A level-0 particle in a collider's band beside the region (``Refiner.beside``, decided
            # by the region whatever the blocks' alignment) whose whole footprint lies in active
            # fine blocks is moved by the fine grid (g2p_sparse): its contact with the
            # collider is then the fine grid's, like the level-1 material it meets there
            # (docs/method.md, "Coarse particles in a collider's band move with the fine grid");
            # so is one among children (AMONG_FINE: its coarse cell holds mostly level-1 mass).
            # Every level-0 particle is its family's footprint here (sim/footprint.py), which
            # g2p_sparse gathers those two with; every other one is left to the coarse grid
            # (the mark's 1 bit set afresh)
            band_beside = s.surface_body[p] >= 0 and cell_flag(coarse, beside, s.x[p]) != 0
            among = on_fine[p] & AMONG_FINE  # Refiner.coarse_children, this substep
            whole = scatter_footprint(s, p, g, color, dt_now[0], tau_store[p], grid_mv, grid_m, reach)
            on_fine[p] = among | wp.where(whole and (band_beside or among != 0), 1, 0)
            return
        st = dense_stencil(g, s.x[p])
        if not stencil_touches_active(g, st.base):
            return
        st.slots = stencil_slots(g, st.base)
        affine = affine_momentum(s, p, g, dt_now[0], tau_store[p])  # the stress the coarse passes kept
        mask = ALL_NODES
        if wp.static(cpic):
            if s.surface_body[p] >= 0:  # a child the coarse grid moves keeps the coarse grid's mask
                mask = own_side_mask(s.surface_point[p], s.surface_side[p], s.surface_body[p], s.x[p],
                                     moving_level(on_fine, p, s.level[p]), color, g, st, cmask, p)
        record_reach(g, st, reach)
        mv = s.mass[p] * s.v[p]
        for i in range(3):
            for j in range(3):
                for k in range(3):
                    n = sparse_node_at(g, st, i, j, k)
                    if n >= 0:
                        weight = weight_at(st, i, j, k)
                        if wp.static(cpic):
                            weight = weight * node_bit(mask, i, j, k)
                        scatter(grid_mv, grid_m, n, weight, mv, affine, offset_at(g, st, i, j, k), s.mass[p])
        wall_images(s, p, g, st, dt_now[0], tau_store[p], mask, grid_mv)

    return p2g_sparse


_MAKERS = {"dense": _make_p2g_dense, "level0": _make_p2g_level0, "overlap": _make_p2g_overlap,
           "sparse": _make_p2g_sparse}
PASSES = tuple(_MAKERS)  # the P2G passes, by name
# which particles each pass visits (a level, None: all) and its name in a profile
PASS_LEVEL = {"dense": None, "level0": 0, "overlap": 1, "sparse": None}
PASS_LABEL = {"dense": "", "level0": " (level 0)", "overlap": " (level 1, overlap)", "sparse": ""}


@functools.cache
def p2g_kernel(name: str, cpic: bool, models: tuple[int, ...] = ALL_MODELS):
    """The P2G pass ``name`` (one of ``PASSES``), with or without CPIC, reaching only
    the material models ``models``."""
    return _MAKERS[name](cpic, models)
