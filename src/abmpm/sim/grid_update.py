"""Grid update (paper Eqs. 3-4, 22): momentum to velocity, gravity, collider contact,
domain walls; one kernel for every grid.

On the CPU the extra threads' P2G sums are added first (``parallel.add_thread_sums``,
on the kernel thread's own chunk of nodes; nothing to add on CUDA). It also clears the P2G accumulators (and the coarse grid's overlap marks) for the
next step, so that the grid is swept once per step.
"""

from __future__ import annotations

import warp as wp

from .boundary import boundary_response
from .colliders import CONTACT_BAND, ColliderArrays, ColorField, node_contact
from .grid import HOLDS_LEVEL1, GridSpec, node_coords, node_position
from .parallel import ThreadSums, add_thread_sums
from .time_levels import SlowNodes, add_slow, keep_slow_share

wp.set_module_options({"enable_backward": False})



@wp.func
def domain_walls(g: GridSpec, xi: wp.vec3, vi: wp.vec3):
    # the wall planes' boundary conditions; a node on a plane (within round-off)
    # belongs to the wall
    tol = 1.0e-3 * g.dx
    v = vi
    for d in range(3):
        if xi[d] <= g.domain_lo[d] + tol:
            nrm = wp.vec3(0.0)
            nrm[d] = 1.0
            v = boundary_response(v, wp.vec3(0.0), nrm, g.wall_type_lo[d], g.friction_lo[d], 0.0)
        if xi[d] >= g.domain_hi[d] - tol:
            nrm = wp.vec3(0.0)
            nrm[d] = -1.0
            v = boundary_response(v, wp.vec3(0.0), nrm, g.wall_type_hi[d], g.friction_hi[d], 0.0)
    return v


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
    overlap: wp.array(dtype=wp.int32),  # the coarse grid's overlap marks (adaptive mode)
    clear_overlap: int,
    fine_dx: float,  # adaptive coarse grid: the fine spacing, the band of a node holding level-1 material
    count: int,  # nodes
    chunk: int,  # nodes per kernel thread
    sums: ThreadSums,  # the other CPU threads' P2G sums
    slow: SlowNodes,  # the slow set's share of the coarse nodes (sim/time_levels.py), if a block is open
    kept_m: wp.array(dtype=float),  # the node masses, kept for the stiffening bound after G2P (sim/stiffness.py)
):
    # Warp's CPU backend spends a few ns per kernel thread, as much as a node's
    # update: a chunk of nodes per thread there, one on a GPU
    n0 = (wp.tid() + first) * chunk
    n1 = wp.min(n0 + chunk, count)
    add_thread_sums(sums, n0, n1, grid_mv, grid_m)
    for n in range(n0, n1):
        m, mv = add_slow(slow, n, dt_now[0], grid_m[n], grid_mv[n])
        vi = wp.vec3(0.0)
        if m > 0.0:
            # v_i = m_i v_i / m_i + dt g (Eqs. 3-4), then collider contact (Eq. 22)
            vi = mv / m + dt_now[0] * g.gravity
            xi = node_position(g, node_coords(g, n))
            if colliders.enabled != 0:
                band = CONTACT_BAND * g.dx
                if clear_overlap != 0:
                    if overlap[n] == HOLDS_LEVEL1:
                        band = CONTACT_BAND * fine_dx
                vi = node_contact(colliders, color, vi, xi, n, band)
            # the domain walls have the last word: a collider never pushes material through them
            vi = domain_walls(g, xi, vi)
            keep_slow_share(slow, n, vi)
        grid_v[n] = vi
        if kept_m.shape[0] > 1:
            kept_m[n] = m
        grid_mv[n] = wp.vec3(0.0)
        grid_m[n] = 0.0
        if clear_overlap != 0:
            overlap[n] = 0
