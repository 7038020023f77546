"""Particle-grid transfers of MLS-MPM with APIC (paper Eqs. 1-12).

Kernels are parameterised by the receiving grid's :class:`GridSpec`, so they serve
the original grid (dx) and the subdivided grid (dx/b) alike. P2G and G2P come in
compile-time variants ``P2G[cpic, sparse]``: with colliders they test compatibility
(CPIC), on a block-sparse grid they skip inactive nodes; otherwise they are the
plain loops. On Warp's CPU backend such code costs time even where it is skipped,
so the variants that do not need it do not carry it.
"""

from __future__ import annotations

import functools

import warp as wp

wp.set_module_options({"enable_backward": False})

from .boundary import boundary_response
from .colliders import (
    ALL_NODES,
    PARTICLE_BAND,
    ColliderArrays,
    Color,
    ColorField,
    boundary_velocity,
    color_point,
    compatibility_mask,
    near_surface,
    node_bit,
    node_contact,
    nodes_facing,
    rigid_velocity,
    stop_crossing,
)
from .grid import (
    BLOCK_NODES,
    GridSpec,
    dense_node_index,
    node_coords,
    node_index,
    node_position,
    stencil_node,
    stencil_slots,
    vec8i,
)
from .materials import ALL_MODELS, MaterialParams, dispatch
from . import parallel
from .state import ParticleArrays

FAST = wp.constant(1.0e30)  # m/s: the speed a non-finite velocity reports
REACH_STRIDE = wp.constant(parallel.REACH_STRIDE)  # ints between two CPU threads' reached spans
EMPTY_BOUND = wp.constant(parallel.EMPTY_BOUND)  # the low end of a span nothing reached yet


@wp.func
def bspline_weights(fx: wp.vec3):
    # Quadratic B-spline weights of the 3 nodes per axis; rows = node offset 0,1,2,
    # columns = axis. fx is the particle position relative to the base node, in cells.
    a = wp.vec3(1.5) - fx
    b = fx - wp.vec3(1.0)
    c = fx - wp.vec3(0.5)
    return wp.matrix_from_rows(0.5 * wp.cw_mul(a, a), wp.vec3(0.75) - wp.cw_mul(b, b), 0.5 * wp.cw_mul(c, c))


@wp.func
def stencil_base(g: GridSpec, x: wp.vec3):
    # Lowest node of the 3x3x3 stencil, clamped so that the whole stencil lies in the
    # grid for any x (a particle flung out of the domain, or NaN after a blow-up, must
    # never index outside the node storage; the run is stopped by the speed check).
    X = (x - g.origin) * g.inv_dx
    return wp.vec3i(
        wp.clamp(int(X[0] - 0.5), 0, g.dims[0] - 3),
        wp.clamp(int(X[1] - 0.5), 0, g.dims[1] - 3),
        wp.clamp(int(X[2] - 0.5), 0, g.dims[2] - 3),
    )


@wp.func
def stencil_offset(g: GridSpec, x: wp.vec3, base: wp.vec3i):
    X = (x - g.origin) * g.inv_dx
    return X - wp.vec3(float(base[0]), float(base[1]), float(base[2]))


def _variant(kind: str, *flags: bool, models: tuple[int, ...] = ALL_MODELS):
    # A kernel named after its variant (e.g. p2g_101_m0): Warp's CPU graph replay finds
    # kernels by name, so variants sharing the closure's name all replayed as the last.
    # Each variant gets a module of its own, compiled the first time a scene asks for
    # it (``p2g_kernel``): a scene compiles the few it uses, not all of them for every
    # model (27 s on this CPU with a cold kernel cache).
    def kernel(f):
        f.__qualname__ = kind + "_" + "".join(str(int(flag)) for flag in flags) + "_m" + "".join(map(str, models))
        return wp.kernel(f, enable_backward=False, module="unique")

    return kernel


def _make_p2g(cpic: bool, sparse: bool, overlap_pass: bool, models: tuple[int, ...] = ALL_MODELS):
    particle_stress = dispatch(models).particle_stress

    @_variant("p2g", cpic, sparse, overlap_pass, models=models)
    def p2g(
        first: int,  # this launch's first particle (sim/parallel.py)
        s: ParticleArrays,
        cmask: wp.array(dtype=wp.int32),
        materials: wp.array(dtype=MaterialParams),
        g: GridSpec,
        color: ColorField,
        dt_now: wp.array(dtype=float),  # [dt]: on the device, so a captured graph replays any dt
        tau_store: wp.array(dtype=wp.mat33),
        store: int,
        only_level: int,
        overlap: int,
        grid_occupied: wp.array(dtype=wp.int32),
        grid_mv: wp.array(dtype=wp.vec3),
        grid_m: wp.array(dtype=float),
        track: int,  # a CPU thread's private accumulators: record the span reached in ``reached``
        reached: wp.array(dtype=wp.int32),
    ):
        # Eqs. 8-10: every particle scatters to every grid, with that grid's kernel
        # and spacing; on a sparse grid only to its active nodes. The stress is
        # evaluated once per step: the dense (first) P2G stores it when ``store`` is
        # set, the sparse (second) P2G reads it back.
        #
        # Adaptive mode splits the coarse P2G in two passes: level-0 particles
        # (``only_level`` 0) mark the nodes they reach (``overlap`` 1); level-1
        # particles (``only_level`` 1, ``overlap`` 2) then add to those nodes only:
        # the overlap where the coarse particles can feel them (Eq. 8). Elsewhere
        # nobody gathers from the coarse grid.
        p = wp.tid() + first
        if wp.static(overlap_pass):
            if s.level[p] != only_level:
                return
        dt = dt_now[0]
        xp = s.x[p]
        base = stencil_base(g, xp)
        if wp.static(sparse):
            if not stencil_touches_active(g, base):
                return
        fx = stencil_offset(g, xp, base)
        w = bspline_weights(fx)
        m = s.mass[p]
        Cp = s.C[p]
        tau = wp.mat33()
        if wp.static(sparse):
            tau = tau_store[p]
        else:
            tau = wp.static(particle_stress)(materials[s.material[p]], s.F, s.history, p, Cp)
            if store != 0:
                tau_store[p] = tau
        if wp.static(overlap_pass):
            if overlap == 2:
                if not stencil_occupied(g, grid_occupied, base):
                    return
        # MLS-MPM force folded into the affine momentum (Eqs. 9-10):
        # m_i v_i += w (m v_p + [m C_p - dt 4/dx^2 V0 tau] (x_i - x_p))
        affine = (-dt * s.volume[p] * 4.0 * g.inv_dx * g.inv_dx) * tau + m * Cp
        mv = m * s.v[p]
        mask = ALL_NODES
        if wp.static(cpic):
            # CPIC: scatter only to nodes on the particle's side of every collider
            if s.surface_body[p] >= 0:
                mask = compatibility_mask(s.surface_point[p], s.surface_side[p], s.surface_body[p], xp, color, g, base, fx)
                if s.level[p] == g.level:
                    cmask[p] = mask  # G2P from this grid reuses it
            elif wp.static(overlap_pass):
                if s.level[p] > g.level:
                    # A level-1 particle's color reaches PARTICLE_BAND fine cells, but its
                    # stencil on this coarser grid (Eq. 8) reaches up to 2.6 coarse cells:
                    # beyond its own band it may still have coarse nodes behind a surface,
                    # and would push the material on their far side of a thin wall. The
                    # nodes' own colors tell which (no closest-point query needed). A
                    # node behind a surface is at most 1.5 sqrt(3) = 2.6 cells away, so
                    # particles farther than that from every surface skip the test.
                    if near_surface(color, g, xp):
                        mask = nodes_facing(xp, color, g, base, fx)
        slots = vec8i()
        if wp.static(sparse):
            slots = stencil_slots(g, base)
        if track != 0:
            record_reach(g, slots, base, reached)
        for i in range(3):
            for j in range(3):
                for k in range(3):
                    n = int(0)
                    if wp.static(sparse):
                        n = stencil_node(g, slots, base, i, j, k)
                    else:
                        n = dense_node_index(g, base[0] + i, base[1] + j, base[2] + k)
                    if wp.static(sparse):
                        if n < 0:
                            continue
                    if wp.static(overlap_pass):
                        if overlap == 1:
                            grid_occupied[n] = 1
                        elif grid_occupied[n] == 0:
                            continue
                    dpos = (wp.vec3(float(i), float(j), float(k)) - fx) * g.dx
                    weight = w[i, 0] * w[j, 1] * w[k, 2]
                    if wp.static(cpic):
                        weight = weight * node_bit(mask, i, j, k)
                    wp.atomic_add(grid_mv, n, weight * (mv + affine * dpos))
                    wp.atomic_add(grid_m, n, weight * m)

    return p2g


@wp.func
def record_reach(g: GridSpec, slots: vec8i, base: wp.vec3i, reached: wp.array(dtype=wp.int32)):
    # widen [reached[0], reached[1]] to the storage indices of the stencil at base:
    # the corner nodes on a dense grid, the blocks' whole slots on a sparse one
    lo = int(0)
    hi = int(0)
    if g.sparse == 0:
        lo = dense_node_index(g, base[0], base[1], base[2])
        hi = dense_node_index(g, base[0] + 2, base[1] + 2, base[2] + 2)
    else:
        lo = EMPTY_BOUND
        hi = -1
        for q in range(8):
            if slots[q] >= 0:
                lo = wp.min(lo, slots[q] * BLOCK_NODES)
                hi = wp.max(hi, slots[q] * BLOCK_NODES + BLOCK_NODES - 1)
    wp.atomic_min(reached, 0, lo)
    wp.atomic_max(reached, 1, hi)


@wp.kernel
def reset_reach(first: int, reached: wp.array(dtype=wp.int32)):
    # after the grid update: every part's span empty again
    t = wp.tid() + first
    reached[REACH_STRIDE * t] = EMPTY_BOUND
    reached[REACH_STRIDE * t + 1] = -1


@wp.func
def stencil_touches_active(g: GridSpec, base: wp.vec3i):
    # the 3x3x3 stencil spans at most 2 blocks per axis: test their corners
    for a in range(2):
        for b in range(2):
            for c in range(2):
                if node_index(g, base[0] + 2 * a, base[1] + 2 * b, base[2] + 2 * c) >= 0:
                    return True
    return False


@wp.func
def stencil_occupied(g: GridSpec, occupied: wp.array(dtype=wp.int32), base: wp.vec3i):
    # a cheap test on the stencil's 8 corners and centre (material reaching only
    # edge midpoints of the stencil is left out of the overlap)
    if occupied[node_index(g, base[0] + 1, base[1] + 1, base[2] + 1)] != 0:
        return True
    for a in range(2):
        for b in range(2):
            for c in range(2):
                if occupied[node_index(g, base[0] + 2 * a, base[1] + 2 * b, base[2] + 2 * c)] != 0:
                    return True
    return False


CPU_NODE_CHUNK = 64  # nodes per kernel thread of the grid update on the CPU (1 on a GPU)


@wp.func
def add_sums(n0: int, n1: int, grid_mv: wp.array(dtype=wp.vec3), grid_m: wp.array(dtype=float),
             private_mv: wp.array(dtype=wp.vec3), private_m: wp.array(dtype=float), extra: int, stride: int,
             reached: wp.array(dtype=wp.int32)):
    # With more than one CPU thread: add the other threads' P2G sums to nodes
    # [n0, n1), in a fixed order, only where each thread's P2G reached, and clear them
    # for the next step.
    for t in range(extra):
        lo = wp.max(n0, reached[REACH_STRIDE * (t + 1)])
        hi = wp.min(n1 - 1, reached[REACH_STRIDE * (t + 1) + 1])
        for n in range(lo, hi + 1):
            q = t * stride + n
            grid_mv[n] = grid_mv[n] + private_mv[q]
            grid_m[n] = grid_m[n] + private_m[q]
            private_mv[q] = wp.vec3(0.0)
            private_m[q] = 0.0


@wp.kernel
def grid_update(
    first: int,  # this launch's first chunk of ``chunk`` nodes (sim/parallel.py)
    g: GridSpec,
    colliders: ColliderArrays,
    color: ColorField,
    dt_now: wp.array(dtype=float),  # [dt]
    grid_mv: wp.array(dtype=wp.vec3),
    grid_m: wp.array(dtype=float),
    grid_v: wp.array(dtype=wp.vec3),
    grid_occupied: wp.array(dtype=wp.int32),
    clear_occupied: int,
    count: int,  # nodes
    chunk: int,  # nodes per kernel thread
    private_mv: wp.array(dtype=wp.vec3),  # the other CPU threads' P2G sums (sim/parallel.py)
    private_m: wp.array(dtype=float),
    extra: int,  # threads beyond the first
    stride: int,  # node storage per private grid
    reached: wp.array(dtype=wp.int32),  # [lo, hi] of the storage indices each part's P2G reached
):
    # Eqs. 3-4 over a chunk of nodes per kernel thread: Warp's CPU backend spends a
    # few ns per kernel thread, as much as adding a node's private sums. (Adding them
    # node by node inside a one-node kernel had made every node three times slower,
    # even with nothing to add.)
    n0 = (wp.tid() + first) * chunk
    n1 = wp.min(n0 + chunk, count)
    add_sums(n0, n1, grid_mv, grid_m, private_mv, private_m, extra, stride, reached)
    for n in range(n0, n1):
        # v_i = m_i v_i / m_i + dt g (Eqs. 3-4), domain walls, collider contact; also
        # clears the P2G accumulators for the next step so the grid is swept once.
        m = grid_m[n]
        vi = wp.vec3(0.0)
        if m > 0.0:
            vi = grid_mv[n] / m + dt_now[0] * g.gravity
            xi = node_position(g, node_coords(g, n))
            if colliders.enabled != 0:
                vi = node_contact(colliders, color, g, vi, xi, n)
            # the domain walls have the last word: a collider never pushes material through them
            tol = 1.0e-3 * g.dx  # nodes on a wall plane belong to the wall despite round-off
            for d in range(3):
                if xi[d] <= g.domain_lo[d] + tol:
                    nrm = wp.vec3(0.0)
                    nrm[d] = 1.0
                    vi = boundary_response(vi, wp.vec3(0.0), nrm, g.wall_type_lo[d], g.friction_lo[d], 0.0)
                if xi[d] >= g.domain_hi[d] - tol:
                    nrm = wp.vec3(0.0)
                    nrm[d] = -1.0
                    vi = boundary_response(vi, wp.vec3(0.0), nrm, g.wall_type_hi[d], g.friction_hi[d], 0.0)
        grid_v[n] = vi
        grid_mv[n] = wp.vec3(0.0)
        grid_m[n] = 0.0
        if clear_occupied != 0:
            grid_occupied[n] = 0


def _make_g2p(cpic: bool, sparse: bool, models: tuple[int, ...] = ALL_MODELS):
    ops = dispatch(models)
    deform_particle, sound_speed_ratio = ops.deform_particle, ops.sound_speed_ratio

    @_variant("g2p", cpic, sparse, models=models)
    def g2p(
        first: int,  # this launch's first particle (sim/parallel.py)
        materials: wp.array(dtype=MaterialParams),
        g: GridSpec,
        colliders: ColliderArrays,
        color: ColorField,
        dt_now: wp.array(dtype=float),  # [dt]
        grid_v: wp.array(dtype=wp.vec3),
        # particle state, updated in place (each thread touches only its own particle)
        s: ParticleArrays,
        cmask: wp.array(dtype=wp.int32),
        signal: wp.array(dtype=float),
    ):
        # Eqs. 11-12: a particle gathers from its own level's grid only
        p = wp.tid() + first
        if s.level[p] != g.level:
            return
        dt = dt_now[0]
        xp = s.x[p]
        base = stencil_base(g, xp)
        fx = stencil_offset(g, xp, base)
        w = bspline_weights(fx)
        new_v = wp.vec3(0.0)
        B = wp.mat33(0.0)
        slots = vec8i()
        if wp.static(sparse):
            slots = stencil_slots(g, base)
        for i in range(3):
            for j in range(3):
                for k in range(3):
                    dpos = (wp.vec3(float(i), float(j), float(k)) - fx) * g.dx
                    weight = w[i, 0] * w[j, 1] * w[k, 2]
                    vi = wp.vec3(0.0)
                    if wp.static(sparse):
                        n = stencil_node(g, slots, base, i, j, k)
                        if n >= 0:  # a level-1 particle's blocks are active; never read outside
                            vi = grid_v[n]
                    else:
                        vi = grid_v[node_index(g, base[0] + i, base[1] + j, base[2] + k)]
                    new_v += weight * vi  # Eq. 5 / 11
                    B += weight * wp.outer(vi, dpos)
        if wp.static(cpic):
            cb = s.surface_body[p]
            if cb >= 0:
                # Eqs. 24-25: an incompatible node lends the particle's boundary velocity (Eq. 23)
                mask = cmask[p]  # from this step's P2G
                if mask != ALL_NODES:
                    # the particle's velocity advanced by gravity like the grid's, then
                    # projected by the collider's boundary type
                    v_bar = boundary_velocity(colliders, cb, s.surface_side[p], xp, s.v[p] + dt * g.gravity)
                    for i in range(3):
                        for j in range(3):
                            for k in range(3):
                                if node_bit(mask, i, j, k) == 0.0:
                                    dpos = (wp.vec3(float(i), float(j), float(k)) - fx) * g.dx
                                    weight = w[i, 0] * w[j, 1] * w[k, 2]
                                    dv = v_bar - grid_v[node_index(g, base[0] + i, base[1] + j, base[2] + k)]
                                    new_v += weight * dv
                                    B += weight * wp.outer(dv, dpos)
        # Eq. 6 with the quadratic-spline inertia D^-1 = 4/dx^2 I
        new_C = (4.0 * g.inv_dx * g.inv_dx) * B
        # Eq. 7, then the material's return mapping (Eqs. 13-14)
        mat = materials[s.material[p]]
        wp.static(deform_particle)(mat, s.F, s.history, p, new_C, dt)
        xn = xp + dt * new_v
        # Nodes on and beyond the wall planes enforce the walls, so a particle can sink
        # at most ~dx/2 into a wall before they stop it; the clamp one cell out is only
        # a safety net. It comes before the collider test, so that the clamp can never
        # move a particle through a surface after that test has stopped it.
        for a in range(3):
            xn[a] = wp.clamp(xn[a], g.domain_lo[a] - g.dx, g.domain_hi[a] + g.dx)
        if wp.static(cpic):
            # No crossing: stop at the surface on the particle's own side. A particle
            # farther from every surface than it moves (relative to the collider)
            # cannot cross one: only the others cast the ray. A particle outside the
            # band casts one only if it moved farther than the band (a CFL violation).
            cb = s.surface_body[p]
            reach = PARTICLE_BAND * g.dx
            dist = PARTICLE_BAND * g.dx
            side = xp - xn  # on the surface with no remembered side: it came from behind its motion
            move = wp.length(xn - xp)
            if cb >= 0:
                move = move + dt * wp.length(rigid_velocity(colliders.bodies[cb], xp))
                dist = wp.length(xp - s.surface_point[p])
                reach = dist + move + 0.01 * g.dx
                side = s.surface_side[p]
            if move >= dist - 0.01 * g.dx:
                hit = stop_crossing(colliders, g, xp, xn, dt, cb, s.surface_side[p])
                if hit.hit != 0:
                    xn = hit.x
                    new_v = boundary_velocity(colliders, hit.body, hit.n, xn, new_v)
                    side = hit.n
            c = Color()
            c.body = -1
            if near_surface(color, g, xn):
                # color for the next step's transfers; the new closest point lies
                # within the old distance plus the motion (triangle inequality)
                c = color_point(colliders, g, xn, wp.min(reach, PARTICLE_BAND * g.dx), side)
                if c.body < 0 and reach < PARTICLE_BAND * g.dx:
                    c = color_point(colliders, g, xn, PARTICLE_BAND * g.dx, side)
            s.surface_point[p] = c.surface_point
            s.surface_side[p] = c.surface_side
            s.surface_body[p] = c.body
        # The fastest particle, and the most compressed fluid's sound speed over its
        # speed at rest, set the next step's CFL time step; a non-finite velocity
        # reads as infinitely fast, which stops the run.
        speed = wp.length(new_v)
        if not wp.isfinite(speed):
            speed = FAST
        wp.atomic_max(signal, 0, speed)
        wp.atomic_max(signal, 1, wp.static(sound_speed_ratio)(mat, s.history[p]))
        s.x[p] = xn
        s.v[p] = new_v
        s.C[p] = new_C

    return g2p


# The compile-time variants: P2G[cpic, sparse, overlap_pass] (the overlap pass is the
# level-split coarse P2G of adaptive mode) and G2P[cpic, sparse], each for a set of
# material models.
P2G_VARIANTS = [(c, s, o) for c in (False, True) for s in (False, True) for o in ((False, True) if not s else (False,))]
G2P_VARIANTS = [(c, s) for c in (False, True) for s in (False, True)]


@functools.cache
def p2g_kernel(cpic: bool, sparse: bool, overlap_pass: bool, models: tuple[int, ...] = ALL_MODELS):
    """P2G[cpic, sparse, overlap_pass] reaching only the material models ``models``."""
    return _make_p2g(cpic, sparse, overlap_pass, models)


@functools.cache
def g2p_kernel(cpic: bool, sparse: bool, models: tuple[int, ...] = ALL_MODELS):
    """G2P[cpic, sparse] reaching only the material models ``models``."""
    return _make_g2p(cpic, sparse, models)
