"""Particle-grid transfers of MLS-MPM with APIC (paper Eqs. 1-12).

Kernels are parameterised by the receiving grid's :class:`GridSpec`, so they serve
the original grid (dx) and the subdivided grid (dx/b) alike.
"""

from __future__ import annotations

import warp as wp

from .boundary import boundary_response
from .colliders import (
    CollisionSpec, Colour, ColourField, boundary_velocity, colour_point, compatible, near_surface, node_contact,
    stop_crossing,
)
from .grid import GridSpec
from .materials import MaterialParams, kirchhoff_stress, update_deformation


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
    X = (x - g.origin) * g.inv_dx
    return wp.vec3i(int(X[0] - 0.5), int(X[1] - 0.5), int(X[2] - 0.5))


@wp.func
def stencil_offset(g: GridSpec, x: wp.vec3, base: wp.vec3i):
    X = (x - g.origin) * g.inv_dx
    return X - wp.vec3(float(base[0]), float(base[1]), float(base[2]))


@wp.kernel
def p2g(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    C: wp.array(dtype=wp.mat33),
    F: wp.array(dtype=wp.mat33),
    plastic: wp.array(dtype=float),
    mass: wp.array(dtype=float),
    volume: wp.array(dtype=float),
    material: wp.array(dtype=wp.int32),
    cp: wp.array(dtype=wp.vec3),
    cn: wp.array(dtype=wp.vec3),
    cbody: wp.array(dtype=wp.int32),
    materials: wp.array(dtype=MaterialParams),
    g: GridSpec,
    colour: ColourField,
    dt: float,
    grid_mv: wp.array3d(dtype=wp.vec3),
    grid_m: wp.array3d(dtype=float),
):
    p = wp.tid()
    xp = x[p]
    cb = cbody[p]
    base = stencil_base(g, xp)
    fx = stencil_offset(g, xp, base)
    w = bspline_weights(fx)
    m = mass[p]
    tau = kirchhoff_stress(materials[material[p]], F[p], C[p], plastic[p])
    # MLS-MPM force folded into the affine momentum (Eqs. 9-10):
    # m_i v_i += w (m v_p + [m C_p - dt 4/dx^2 V0 tau] (x_i - x_p))
    affine = (-dt * volume[p] * 4.0 * g.inv_dx * g.inv_dx) * tau + m * C[p]
    mv = m * v[p]
    for i in range(3):
        for j in range(3):
            for k in range(3):
                dpos = (wp.vec3(float(i), float(j), float(k)) - fx) * g.dx
                if cb >= 0:
                    # CPIC: scatter only to nodes on the particle's side of every collider
                    if not compatible(cp[p], cn[p], cb, xp, colour, xp + dpos, base[0] + i, base[1] + j, base[2] + k):
                        continue
                weight = w[i, 0] * w[j, 1] * w[k, 2]
                wp.atomic_add(grid_mv, base[0] + i, base[1] + j, base[2] + k, weight * (mv + affine * dpos))
                wp.atomic_add(grid_m, base[0] + i, base[1] + j, base[2] + k, weight * m)


@wp.kernel
def grid_update(
    g: GridSpec,
    spec: CollisionSpec,
    colour: ColourField,
    dt: float,
    grid_mv: wp.array3d(dtype=wp.vec3),
    grid_m: wp.array3d(dtype=float),
    grid_v: wp.array3d(dtype=wp.vec3),
):
    # v_i = m_i v_i / m_i + dt g (Eqs. 3-4), domain walls; also clears the P2G
    # accumulators for the next step so the grid is swept once per step.
    i, j, k = wp.tid()
    m = grid_m[i, j, k]
    vi = wp.vec3(0.0)
    if m > 0.0:
        vi = grid_mv[i, j, k] / m + dt * g.gravity
        xi = g.origin + wp.vec3(float(i), float(j), float(k)) * g.dx
        tol = 1.0e-3 * g.dx  # nodes on a wall plane belong to the wall despite round-off
        for d in range(3):
            if xi[d] <= g.domain_lo[d] + tol:
                n = wp.vec3(0.0)
                n[d] = 1.0
                vi = boundary_response(vi, wp.vec3(0.0), n, g.wall_type_lo[d], g.friction_lo[d], 0.0)
            if xi[d] >= g.domain_hi[d] - tol:
                n = wp.vec3(0.0)
                n[d] = -1.0
                vi = boundary_response(vi, wp.vec3(0.0), n, g.wall_type_hi[d], g.friction_hi[d], 0.0)
        if spec.enabled != 0:
            vi = node_contact(spec, colour, g, vi, xi, i, j, k)
    grid_v[i, j, k] = vi
    grid_mv[i, j, k] = wp.vec3(0.0)
    grid_m[i, j, k] = 0.0


@wp.kernel
def g2p(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    F: wp.array(dtype=wp.mat33),
    plastic: wp.array(dtype=float),
    material: wp.array(dtype=wp.int32),
    cp: wp.array(dtype=wp.vec3),
    cn: wp.array(dtype=wp.vec3),
    cbody: wp.array(dtype=wp.int32),
    materials: wp.array(dtype=MaterialParams),
    g: GridSpec,
    spec: CollisionSpec,
    colour: ColourField,
    dt: float,
    grid_v: wp.array3d(dtype=wp.vec3),
    x_out: wp.array(dtype=wp.vec3),
    v_out: wp.array(dtype=wp.vec3),
    C_out: wp.array(dtype=wp.mat33),
    F_out: wp.array(dtype=wp.mat33),
    plastic_out: wp.array(dtype=float),
    cp_out: wp.array(dtype=wp.vec3),
    cn_out: wp.array(dtype=wp.vec3),
    cbody_out: wp.array(dtype=wp.int32),
):
    p = wp.tid()
    xp = x[p]
    cb = cbody[p]
    base = stencil_base(g, xp)
    fx = stencil_offset(g, xp, base)
    w = bspline_weights(fx)
    new_v = wp.vec3(0.0)
    B = wp.mat33(0.0)
    for i in range(3):
        for j in range(3):
            for k in range(3):
                dpos = (wp.vec3(float(i), float(j), float(k)) - fx) * g.dx
                weight = w[i, 0] * w[j, 1] * w[k, 2]
                vi = grid_v[base[0] + i, base[1] + j, base[2] + k]
                if cb >= 0:
                    # Eqs. 24-25: an incompatible node lends the boundary velocity of Eq. 23
                    if not compatible(cp[p], cn[p], cb, xp, colour, xp + dpos, base[0] + i, base[1] + j, base[2] + k):
                        vi = boundary_velocity(spec, cb, cn[p], xp, v[p])
                new_v += weight * vi  # Eq. 5 / 11
                B += weight * wp.outer(vi, dpos)
    # Eq. 6 with the quadratic-spline inertia D^-1 = 4/dx^2 I
    new_C = (4.0 * g.inv_dx * g.inv_dx) * B
    # Eq. 7, then the material's return mapping (Eqs. 13-14)
    d = update_deformation(materials[material[p]], F[p], new_C, plastic[p], dt)
    # advect. Nodes on and beyond the wall planes enforce the walls, so a particle
    # can sink at most ~dx/2 into a wall before they stop it; the clamp one cell out
    # is only a safety net that keeps stencils inside the grid. (Clamping at the
    # plane itself would pile particles up there and silently compress material.)
    xn = xp + dt * new_v
    if spec.cpic != 0:
        if cb >= 0 or near_surface(colour, g, xn):
            hit = stop_crossing(spec, g, xp, xn, dt, cb)
            if hit.hit:
                xn = hit.x
                new_v = boundary_velocity(spec, hit.body, hit.n, xn, new_v)
        c = Colour()
        c.body = -1
        if near_surface(colour, g, xn):
            c = colour_point(spec, g, xn)  # colour for the next step's transfers
        cp_out[p] = c.cp
        cn_out[p] = c.cn
        cbody_out[p] = c.body
    for a in range(3):
        xn[a] = wp.clamp(xn[a], g.domain_lo[a] - g.dx, g.domain_hi[a] + g.dx)
    x_out[p] = xn
    v_out[p] = new_v
    C_out[p] = new_C
    F_out[p] = d.F
    plastic_out[p] = d.plastic
