"""Grid to particle (paper Eqs. 5-7, 11-14, 23-25): one pass per level.

A particle gathers velocity and its affine matrix from its own level's grid (Eqs.
11-12): ``g2p_dense`` on the coarse grid (or the single grid of the original and
finest modes), ``g2p_sparse`` on the fine block-sparse grid. Beyond the paper, a
level-0 particle in a collider's band whose footprint lies whole in active fine
blocks (``p2g_sparse`` marks it, ``on_fine``) moves with the fine grid, its family's
footprint the kernel (``gather_footprint``, sim/footprint.py; docs/method.md, "Coarse
particles in a collider's band move with the fine grid"), and keeps its own grid's
band and colors; so does one whose coarse cell holds mostly level-1 mass
(``Refiner.coarse_children``). The other way round, a child among coarse particles
away from the region (marked ON_COARSE) moves with the coarse grid as a point of it.
With colliders an incompatible node lends the particle's boundary velocity instead of
its own (Eqs. 23-25), and advection never crosses a surface (``advect``). Then the
deformation update and the material's return mapping (Eqs. 7, 13-14), and the
particle's speed and sound-speed stiffening into the CFL signal.
"""

from __future__ import annotations

import functools

import warp as wp

from .colliders import (
    ALL_NODES,
    PARTICLE_BAND,
    ColliderArrays,
    Color,
    ColorField,
    boundary_velocity,
    color_point,
    compatible,
    near_surface,
    node_bit,
    rigid_velocity,
    stop_crossing,
)
from .footprint import footprint, footprint_weights, stress_weight
from .grid import GridSpec, moving_level, node_index, node_position, stencil_node, stencil_slots
from .materials import ALL_MODELS, MaterialParams, dispatch
from .node_color import NEEDS_QUERY, NODE_COLOR_TOL, color_from_nodes, query_color
from .state import ParticleArrays
from .stencil import STORAGE, Stencil, offset_at, weight_at
from .stiffness import SLACK
from .variant import variant

wp.set_module_options({"enable_backward": False})

FAST = wp.constant(1.0e30)  # m/s: the speed a non-finite velocity reports


@wp.func
def clamp_to_domain(g: GridSpec, x: wp.vec3):
    # Nodes on and beyond the wall planes enforce the walls, so a particle can sink at
    # most ~dx/2 into a wall before they stop it; the clamp one cell out is only a
    # safety net. It comes before the collider test, so that the clamp can never move
    # a particle through a surface after that test has stopped it.
    lo = g.domain_lo - wp.vec3(g.dx)
    hi = g.domain_hi + wp.vec3(g.dx)
    return wp.vec3(wp.clamp(x[0], lo[0], hi[0]), wp.clamp(x[1], lo[1], hi[1]), wp.clamp(x[2], lo[2], hi[2]))


@wp.func(inline=True)
def lend_boundary_velocity(g: GridSpec, st: Stencil, grid_v: wp.array(dtype=wp.vec3), mask: int, v_bar: wp.vec3):
    """Eqs. 24-25: what the incompatible nodes of ``mask`` change in the gathered
    velocity and B (Eq. 6) when each lends v_bar instead of its own velocity.

    A function of its own, called only for a particle with an incompatible node:
    Warp declares (and zeroes) every temporary of a kernel at its top, so these 27
    unrolled nodes inline in the G2P kernel cost every particle their temporaries."""
    dv = wp.vec3(0.0)
    dB = wp.mat33(0.0)
    for i in range(3):
        for j in range(3):
            for k in range(3):
                if node_bit(mask, i, j, k) == 0.0:
                    weight = weight_at(st, i, j, k)
                    d = v_bar - grid_v[node_index(g, st.base[0] + i, st.base[1] + j, st.base[2] + k)]
                    dv += weight * d
                    dB += weight * wp.outer(d, offset_at(g, st, i, j, k))
    return dv, dB


@wp.func(inline=True)
def advect(colliders: ColliderArrays, color: ColorField, g: GridSpec, cb: int, surface_point: wp.vec3,
           surface_side: wp.vec3, xp: wp.vec3, xn: wp.vec3, new_v: wp.vec3, dt: float):
    """CPIC advection from xp to xn of a particle with color (surface_point,
    surface_side, cb): stop at the surface on the particle's own side, and color the
    particle for the next step. Returns (position, velocity, color). (Values, not the
    particle struct: Warp copies a struct argument into a function it does not inline.)"""
    # A particle farther from every surface than it moves (relative to the collider)
    # cannot cross one: only the others cast the ray. A particle outside the band
    # casts one only if it moved farther than the band (a CFL violation).
    x_end = xn
    v_end = new_v
    reach = PARTICLE_BAND * g.dx
    dist = PARTICLE_BAND * g.dx
    side = xp - xn  # on the surface with no remembered side: it came from behind its motion
    move = wp.length(xn - xp)
    if cb >= 0:
        move = move + dt * wp.length(rigid_velocity(colliders.bodies[cb], xp))
        dist = wp.length(xp - surface_point)
        reach = dist + move + 0.01 * g.dx
        side = surface_side
    # a color read from the nodes may overstate the distance by NODE_COLOR_TOL cells
    if move >= dist - (0.01 + NODE_COLOR_TOL) * g.dx:
        hit = stop_crossing(colliders, g, xp, xn, dt, cb, surface_side)
        if hit.hit != 0:
            x_end = hit.x
            v_end = boundary_velocity(colliders, hit.body, hit.n, x_end, new_v)
            side = hit.n
    c = Color()
    c.body = -1
    if near_surface(color, g, x_end):
        # color for the next step's transfers; the new closest point lies within the
        # old distance plus the motion (triangle inequality)
        c = color_from_nodes(color, g, x_end, side, cb >= 0)
        if c.body == NEEDS_QUERY:
            c = query_color(colliders, color, g, x_end, side, wp.min(reach, PARTICLE_BAND * g.dx))
            if c.body < 0 and reach < PARTICLE_BAND * g.dx:
                c = color_point(colliders, g, x_end, PARTICLE_BAND * g.dx, side)
    return x_end, v_end, c


def _make_gather_footprint(cpic: bool):
    @wp.func
    def gather_footprint(g: GridSpec, colliders: ColliderArrays, color: ColorField,
                         grid_v: wp.array(dtype=wp.vec3), s: ParticleArrays, p: int, dt: float):
        """Eqs. 5-6 for a level-0 particle on the fine grid with the kernel it scattered
        with there, its family's (``sim/footprint.py``): v and C its children's mean. Every node
        of its footprint is active (``p2g_sparse`` says so); an incompatible node lends
        the particle's boundary velocity (Eqs. 23-25). Returns (v, C)."""
        xp = s.x[p]
        fp = footprint_weights(g, xp, footprint(g, xp, s.volume[p]))
        slots = stencil_slots(g, fp.base)
        cb = s.surface_body[p]
        v_bar = wp.vec3(0.0)
        if wp.static(cpic):
            if cb >= 0:
                v_bar = boundary_velocity(colliders, cb, s.surface_side[p], xp, s.v[p] + dt * g.gravity)
        v = wp.vec3(0.0)
        C = wp.mat33(0.0)
        for i in range(fp.nodes):
            for j in range(fp.nodes):
                for k in range(fp.nodes):
                    weight = fp.wx[i] * fp.wy[j] * fp.wz[k]
                    n = stencil_node(g, slots, fp.base, i, j, k)
                    if weight > 0.0 and n >= 0:
                        vi = grid_v[n]
                        if wp.static(cpic):
                            dpos = node_position(g, fp.base + wp.vec3i(i, j, k)) - xp  # as p2g's test reads it
                            if not compatible(s.surface_point[p], s.surface_side[p], cb, xp, color, xp + dpos, n, g.dx):
                                vi = v_bar
                        v += weight * vi
                        C += wp.outer(vi, stress_weight(fp, i, j, k, g.inv_dx))
        return v, C

    return gather_footprint


def make_finish(cpic: bool, models: tuple[int, ...]):
    """The end of every G2P: Eq. 7 with the velocity gradient ``grad``, then the material's
    return mapping (Eqs. 13-14), advection that never crosses a collider (and the particle's
    colors on its own grid ``g``), the CFL signal, and the particle's new x, v and C."""
    ops = dispatch(models)
    deform_particle, sound_speed_ratio = ops.deform_particle, ops.sound_speed_ratio

    @wp.func(inline=True)
    def finish(materials: wp.array(dtype=MaterialParams), colliders: ColliderArrays, s: ParticleArrays, p: int,
               g: GridSpec, cf: ColorField, xp: wp.vec3, new_v: wp.vec3, new_C: wp.mat33, grad: wp.mat33, dt: float,
               stiff: wp.array(dtype=float), signal: wp.array(dtype=float)):
        mat = materials[s.material[p]]
        wp.static(deform_particle)(mat, s.F, s.history, p, grad, dt)
        xn = clamp_to_domain(g, xp + dt * new_v)
        v_end = new_v
        if wp.static(cpic):
            cb = s.surface_body[p]
            # a particle with no color that ends its step outside the band, after a move
            # shorter than the band, stays uncolored: only the others pay for the
            # call (Warp copies its struct arguments)
            if cb >= 0 or wp.length(xn - xp) >= PARTICLE_BAND * g.dx or near_surface(cf, g, xn):
                xn, v_end, c = advect(colliders, cf, g, cb, s.surface_point[p], s.surface_side[p], xp, xn, new_v, dt)
                s.surface_point[p] = c.surface_point
                s.surface_side[p] = c.surface_side
                s.surface_body[p] = c.body
        # The fastest particle, and the most compressed fluid's sound speed over its
        # speed at rest, set the next step's CFL time step; a non-finite velocity
        # reads as infinitely fast, which stops the run. Beyond the CFL number's
        # margin the stiffening is bounded node by node (sim/stiffness.py).
        speed = wp.length(v_end)
        if not wp.isfinite(speed):
            speed = FAST
        wp.atomic_max(signal, 0, speed)
        stiffening = wp.static(sound_speed_ratio)(mat, s.history[p])
        if stiff.shape[0] > 1:  # sim/stiffness.py bounds what lies beyond the margin
            stiff[p] = stiffening
            stiffening = wp.min(stiffening, SLACK)
        wp.atomic_max(signal, 1, stiffening)
        s.x[p] = xn
        s.v[p] = v_end
        s.C[p] = new_C

    return finish


def _make_g2p(sparse: bool, cpic: bool, models: tuple[int, ...]):
    stencil, node_at = STORAGE[sparse]
    gather_footprint = _make_gather_footprint(cpic)
    finish = make_finish(cpic, models)  # Eqs. 7, 13-14, advection, the CFL signal

    @variant("g2p_sparse" if sparse else "g2p_dense", cpic, models=models)
    def g2p(
        first: int,  # this launch's first particle (sim/parallel.py)
        materials: wp.array(dtype=MaterialParams),
        g: GridSpec,
        colliders: ColliderArrays,
        color: ColorField,
        dt_now: wp.array(dtype=float),  # [dt]
        grid_v: wp.array(dtype=wp.vec3),
        s: ParticleArrays,  # updated in place: each thread touches only its own particle
        cmask: wp.array(dtype=wp.int32),  # compatibility masks from this step's P2G
        coarse: GridSpec,  # the coarse grid and its colors: a level-0 particle's band
        coarse_color: ColorField,
        on_fine: wp.array(dtype=wp.int32),  # which grid moves a particle (grid.moving_level)
        stiff: wp.array(dtype=float),  # each particle's stiffening, for sim/stiffness.py (length 1: not kept)
        signal: wp.array(dtype=float),  # [fastest speed, largest sound-speed stiffening]
    ):
        p = wp.tid() + first
        if moving_level(on_fine, p, s.level[p]) != g.level:  # another grid moves it
            return
        # a level-0 particle on the fine grid (a child on the coarse grid is a point of it)
        level0_here = s.level[p] < g.level
        dt = dt_now[0]
        xp = s.x[p]
        new_v = wp.vec3(0.0)
        new_C = wp.mat33(0.0)
        if level0_here:  # with its family's footprint, the kernel it scattered with here
            new_v, new_C = wp.static(gather_footprint)(g, colliders, color, grid_v, s, p, dt)
        else:
            st = wp.static(stencil)(g, xp)
            B = wp.mat33(0.0)
            for i in range(3):
                for j in range(3):
                    for k in range(3):
                        weight = weight_at(st, i, j, k)
                        vi = wp.vec3(0.0)
                        n = wp.static(node_at)(g, st, i, j, k)
                        if wp.static(sparse):
                            if n >= 0:  # a level-1 particle's blocks are active; never read outside
                                vi = grid_v[n]
                        else:
                            vi = grid_v[n]
                        new_v += weight * vi  # Eq. 5 / 11
                        B += weight * wp.outer(vi, offset_at(g, st, i, j, k))
            if wp.static(cpic):
                cb = s.surface_body[p]
                if cb >= 0:
                    # Eqs. 24-25: an incompatible node lends the particle's boundary velocity (Eq. 23)
                    mask = cmask[p]
                    if mask != ALL_NODES:
                        # the particle's velocity advanced by gravity like the grid's, then
                        # projected by the collider's boundary type
                        v_bar = boundary_velocity(colliders, cb, s.surface_side[p], xp, s.v[p] + dt * g.gravity)
                        dv, dB = lend_boundary_velocity(g, st, grid_v, mask, v_bar)
                        new_v += dv
                        B += dB
            # Eq. 6 with the quadratic-spline inertia D^-1 = 4/dx^2 I
            new_C = (4.0 * g.inv_dx * g.inv_dx) * B
        # a level-0 particle keeps its own grid's band and colors
        gb = g
        cf = color
        if wp.static(sparse):
            if level0_here:
                gb = coarse
                cf = coarse_color
        wp.static(finish)(materials, colliders, s, p, gb, cf, xp, new_v, new_C, new_C, dt, stiff, signal)

    return g2p


@functools.cache
def g2p_kernel(sparse: bool, cpic: bool, models: tuple[int, ...] = ALL_MODELS):
    """``g2p_sparse`` or ``g2p_dense``, with or without CPIC, reaching only the
    material models ``models``."""
    return _make_g2p(sparse, cpic, models)
