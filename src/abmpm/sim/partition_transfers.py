"""The transfers of the partition coupling (``sim/partition.py``): P2G (Eqs. 8-10) and G2P
(Eqs. 5-7, 11-14, 23-25) with each particle's functions on both grids.

Where every function a particle reaches is one grid's own B-spline (its coarse cell's kind,
``PURE_COARSE`` or ``PURE_FINE``, set by ``Partition.update``), it transfers exactly as in a
one-level run: MLS, the force folded into the affine momentum with D^-1 = 4 / dx^2. In the
band where both grids have weight (``BAND``) it uses the normalised weights W = r / S and
their exact gradients, for the force (-V0 tau grad W) and for the deformation update
(grad v = sum v_i grad W_i^T), and APIC's C = B D^-1 with its own D about the weights'
centroid: MLS's D^-1 on the blended functions lost energy in the one-dimensional model
(``docs/prototypes/partition_1d.py``). The helpers take values, not structs: Warp passes a
struct to a function it does not inline by copy, 54 times a particle here.
"""

from __future__ import annotations

import functools

import warp as wp

from .colliders import (
    ALL_NODES,
    ColliderArrays,
    ColorField,
    boundary_velocity,
    compatibility_mask,
    near_surface,
    node_bit,
    nodes_facing,
)
from .g2p import make_finish
from .grid import BLOCK_NODES, GridSpec, cell_flag, stencil_slots, vec8i
from .materials import ALL_MODELS, MaterialParams, dispatch
from .parallel import Reach, widen_reach
from .state import ParticleArrays
from .variant import variant

wp.set_module_options({"enable_backward": False})

PURE_COARSE = wp.constant(0)  # a coarse cell whose particles reach only coarse functions of share 1
BAND = wp.constant(1)  # both grids' functions
PURE_FINE = wp.constant(2)  # only fine functions of share 1


@wp.func
def stencil_at(g: GridSpec, x: wp.vec3):
    # lowest node of the 3x3x3 stencil (clamped into the grid) and x's offset from it, in cells
    X = (x - g.origin) * g.inv_dx
    base = wp.vec3i(wp.clamp(int(X[0] - 0.5), 0, g.dims[0] - 3), wp.clamp(int(X[1] - 0.5), 0, g.dims[1] - 3),
                    wp.clamp(int(X[2] - 0.5), 0, g.dims[2] - 3))
    return base, X - wp.vec3(float(base[0]), float(base[1]), float(base[2]))


@wp.func
def spline(fx: wp.vec3):
    # quadratic B-spline weights (rows: node 0, 1, 2; columns: axis) and their derivatives in fx
    a = wp.vec3(1.5) - fx
    b = fx - wp.vec3(1.0)
    c = fx - wp.vec3(0.5)
    w = wp.matrix_from_rows(0.5 * wp.cw_mul(a, a), wp.vec3(0.75) - wp.cw_mul(b, b), 0.5 * wp.cw_mul(c, c))
    dw = wp.matrix_from_rows(-a, -2.0 * b, c)
    return w, dw


@wp.func(inline=True)
def weight(w: wp.mat33, i: int, j: int, k: int):
    return w[i, 0] * w[j, 1] * w[k, 2]


@wp.func(inline=True)
def weight_gradient(w: wp.mat33, dw: wp.mat33, i: int, j: int, k: int, inv_dx: float):
    # grad N_i (per m) of stencil node (i, j, k)
    return inv_dx * wp.vec3(dw[i, 0] * w[j, 1] * w[k, 2], w[i, 0] * dw[j, 1] * w[k, 2], w[i, 0] * w[j, 1] * dw[k, 2])


@wp.func(inline=True)
def offset(fx: wp.vec3, i: int, j: int, k: int, dx: float):
    # x_i - x_p of stencil node (i, j, k)
    return (wp.vec3(float(i), float(j), float(k)) - fx) * dx


@wp.func(inline=True)
def coarse_node(dims: wp.vec3i, base: wp.vec3i, i: int, j: int, k: int):
    # dense_node_index from the grid's dims (a value: no GridSpec copied into the 27-node loops)
    return ((base[0] + i) * dims[1] + base[1] + j) * dims[2] + base[2] + k


@wp.func(inline=True)
def fine_node(slots: vec8i, base: wp.vec3i, i: int, j: int, k: int):
    # stencil_node of the fine grid from the stencil's block slots; -1 where inactive
    x = base[0] + i
    y = base[1] + j
    z = base[2] + k
    slot = slots[((x >> 2) - (base[0] >> 2)) * 4 + ((y >> 2) - (base[1] >> 2)) * 2 + ((z >> 2) - (base[2] >> 2))]
    n = int(-1)
    if slot >= 0:
        n = slot * BLOCK_NODES + ((x & 3) * 4 + (y & 3)) * 4 + (z & 3)
    return n


@wp.func(inline=True)
def fine_share(share_f: wp.array(dtype=float), n: int):
    s = float(0.0)
    if n >= 0:
        s = share_f[n]
    return s


@wp.func
def moments(gc: GridSpec, gf: GridSpec, share_c: wp.array(dtype=float), share_f: wp.array(dtype=float),
            base_c: wp.vec3i, fx_c: wp.vec3, base_f: wp.vec3i, fx_f: wp.vec3, slots: vec8i):
    # a band particle's S = sum r, grad S and sum r (x_i - x_p): the normalisation and the centroid
    wc, dwc = spline(fx_c)
    wf, dwf = spline(fx_f)
    S = float(0.0)
    dS = wp.vec3(0.0)
    X = wp.vec3(0.0)
    for i in range(3):
        for j in range(3):
            for k in range(3):
                s = share_c[coarse_node(gc.dims, base_c, i, j, k)]
                S += s * weight(wc, i, j, k)
                dS += s * weight_gradient(wc, dwc, i, j, k, gc.inv_dx)
                X += (s * weight(wc, i, j, k)) * offset(fx_c, i, j, k, gc.dx)
                s = fine_share(share_f, fine_node(slots, base_f, i, j, k))
                S += s * weight(wf, i, j, k)
                dS += s * weight_gradient(wf, dwf, i, j, k, gf.inv_dx)
                X += (s * weight(wf, i, j, k)) * offset(fx_f, i, j, k, gf.dx)
    return S, dS, X / S


@wp.func
def masks(gc: GridSpec, gf: GridSpec, color_c: ColorField, color_f: ColorField, x: wp.vec3, level: int,
          surface_point: wp.vec3, surface_side: wp.vec3, surface_body: int, base_c: wp.vec3i, fx_c: wp.vec3,
          base_f: wp.vec3i, fx_f: wp.vec3):
    # CPIC (sim/colliders.py): each grid's stencil nodes on the particle's side of every surface.
    # A level-1 particle's color reaches a few fine cells; on the coarse grid, beyond its own
    # band, the nodes' colors say which nodes face it (as p2g_overlap does)
    mask_c = ALL_NODES
    mask_f = ALL_NODES
    if surface_body >= 0:
        mask_c = compatibility_mask(surface_point, surface_side, surface_body, x, color_c, gc, base_c, fx_c)
        mask_f = compatibility_mask(surface_point, surface_side, surface_body, x, color_f, gf, base_f, fx_f)
    elif level == 1 and near_surface(color_c, gc, x):
        mask_c = nodes_facing(x, color_c, gc, base_c, fx_c)
    return mask_c, mask_f


@wp.func
def sparse_reach(slots: vec8i):
    lo = int(2147483647)
    hi = int(-1)
    for q in range(8):
        if slots[q] >= 0:
            lo = wp.min(lo, slots[q] * BLOCK_NODES)
            hi = wp.max(hi, slots[q] * BLOCK_NODES + BLOCK_NODES - 1)
    return lo, hi


@wp.func
def node_momentum(band: int, W: float, Wu: float, bit: float, mv: wp.vec3, mC: wp.mat33, affine: wp.mat33,
                  d: wp.vec3, centre: wp.vec3, stress: wp.mat33, grad_r: wp.vec3, dS: wp.vec3, S: float):
    # Eq. 8's momentum of one node: MLS's for one grid's B-splines; in the band APIC about the
    # weights' centroid and the force -V0 tau grad W, grad W = (grad r - W grad S) / S
    dp = W * (mv + affine * d)
    if band != 0:
        dp = W * (mv + mC * (d - centre)) + bit * (stress * ((grad_r - Wu * dS) / S))
    return dp


@wp.func
def gather_node(band: int, W: float, vi: wp.vec3, d: wp.vec3, grad_r: wp.vec3, dS: wp.vec3, S: float,
                v: wp.vec3, B: wp.mat33, D: wp.mat33, G: wp.mat33):
    # Eqs. 5-6 from one node: v and B; in the band also D and the exact velocity gradient
    v_out = v + W * vi
    B_out = B + W * wp.outer(vi, d)
    D_out = D
    G_out = G
    if band != 0:
        D_out = D + W * wp.outer(d, d)
        G_out = G + wp.outer(vi, (grad_r - W * dS) / S)
    return v_out, B_out, D_out, G_out


def _make_p2g(cpic: bool, models: tuple[int, ...]):
    particle_stress = dispatch(models).particle_stress

    @variant("p2g_partition", cpic, models=models)
    def p2g_partition(first: int, s: ParticleArrays, materials: wp.array(dtype=MaterialParams), gc: GridSpec,
                      gf: GridSpec, color_c: ColorField, color_f: ColorField, share_c: wp.array(dtype=float),
                      share_f: wp.array(dtype=float), kinds: wp.array3d(dtype=wp.int32), dt_now: wp.array(dtype=float),
                      mv_c: wp.array(dtype=wp.vec3), m_c: wp.array(dtype=float), reach_c: Reach,
                      mv_f: wp.array(dtype=wp.vec3), m_f: wp.array(dtype=float), reach_f: Reach):
        # Eq. 8's mass and APIC momentum, Eqs. 9-10's force folded into it
        p = wp.tid() + first
        xp = s.x[p]
        base_c, fx_c = stencil_at(gc, xp)
        base_f, fx_f = stencil_at(gf, xp)
        slots = stencil_slots(gf, base_f)
        kind = cell_flag(gc, kinds, xp)
        if kind == PURE_FINE and wp.min(slots) < 0:
            kind = BAND  # a fine node of its stencil is not active: its share is 0 there
        mask_c = ALL_NODES
        mask_f = ALL_NODES
        if wp.static(cpic):
            mask_c, mask_f = masks(gc, gf, color_c, color_f, xp, s.level[p], s.surface_point[p], s.surface_side[p],
                                   s.surface_body[p], base_c, fx_c, base_f, fx_f)
        tau = wp.static(particle_stress)(materials[s.material[p]], s.F, s.history, p, s.C[p])
        stress = (-dt_now[0] * s.volume[p]) * tau
        m = s.mass[p]
        mv = m * s.v[p]
        mC = m * s.C[p]
        wc, dwc = spline(fx_c)
        wf, dwf = spline(fx_f)
        S = float(1.0)
        dS = wp.vec3(0.0)
        centre = wp.vec3(0.0)  # the weights' centroid from x_p (0 for one grid's own B-splines)
        band = int(0)
        if kind == BAND:
            band = 1
            S, dS, centre = moments(gc, gf, share_c, share_f, base_c, fx_c, base_f, fx_f, slots)
        if kind != PURE_FINE:
            affine = mC + (4.0 * gc.inv_dx * gc.inv_dx) * stress  # MLS (Eqs. 9-10)
            for i in range(3):
                for j in range(3):
                    for k in range(3):
                        n = coarse_node(gc.dims, base_c, i, j, k)
                        sc = share_c[n]
                        if sc > 0.0:
                            Wu = sc * weight(wc, i, j, k) / S  # W before CPIC's mask
                            bit = node_bit(mask_c, i, j, k)
                            grad_r = sc * weight_gradient(wc, dwc, i, j, k, gc.inv_dx)
                            wp.atomic_add(mv_c, n, node_momentum(band, Wu * bit, Wu, bit, mv, mC, affine,
                                                                 offset(fx_c, i, j, k, gc.dx), centre, stress,
                                                                 grad_r, dS, S))
                            wp.atomic_add(m_c, n, Wu * bit * m)
            widen_reach(reach_c, coarse_node(gc.dims, base_c, 0, 0, 0), coarse_node(gc.dims, base_c, 2, 2, 2))
        if kind != PURE_COARSE:
            affine = mC + (4.0 * gf.inv_dx * gf.inv_dx) * stress
            for i in range(3):
                for j in range(3):
                    for k in range(3):
                        n = fine_node(slots, base_f, i, j, k)
                        sf = fine_share(share_f, n)
                        if sf > 0.0:
                            Wu = sf * weight(wf, i, j, k) / S  # W before CPIC's mask
                            bit = node_bit(mask_f, i, j, k)
                            grad_r = sf * weight_gradient(wf, dwf, i, j, k, gf.inv_dx)
                            wp.atomic_add(mv_f, n, node_momentum(band, Wu * bit, Wu, bit, mv, mC, affine,
                                                                 offset(fx_f, i, j, k, gf.dx), centre, stress,
                                                                 grad_r, dS, S))
                            wp.atomic_add(m_f, n, Wu * bit * m)
            lo, hi = sparse_reach(slots)
            widen_reach(reach_f, lo, hi)

    return p2g_partition


def _make_g2p(cpic: bool, models: tuple[int, ...]):
    finish = make_finish(cpic, models)  # Eqs. 7 (with the exact gradient in the band), 13-14, advection, CFL

    @variant("g2p_partition", cpic, models=models)
    def g2p_partition(first: int, materials: wp.array(dtype=MaterialParams), gc: GridSpec, gf: GridSpec,
                      colliders: ColliderArrays, color_c: ColorField, color_f: ColorField,
                      share_c: wp.array(dtype=float), share_f: wp.array(dtype=float), kinds: wp.array3d(dtype=wp.int32),
                      dt_now: wp.array(dtype=float), v_c: wp.array(dtype=wp.vec3), v_f: wp.array(dtype=wp.vec3),
                      s: ParticleArrays, stiff: wp.array(dtype=float), signal: wp.array(dtype=float)):
        # Eqs. 5-7 and 11-14 with the functions the particle scattered with; an incompatible
        # node lends the particle's boundary velocity (Eqs. 23-25)
        p = wp.tid() + first
        dt = dt_now[0]
        xp = s.x[p]
        base_c, fx_c = stencil_at(gc, xp)
        base_f, fx_f = stencil_at(gf, xp)
        slots = stencil_slots(gf, base_f)
        kind = cell_flag(gc, kinds, xp)
        if kind == PURE_FINE and wp.min(slots) < 0:
            kind = BAND
        mask_c = ALL_NODES
        mask_f = ALL_NODES
        v_bar = wp.vec3(0.0)
        if wp.static(cpic):
            mask_c, mask_f = masks(gc, gf, color_c, color_f, xp, s.level[p], s.surface_point[p], s.surface_side[p],
                                   s.surface_body[p], base_c, fx_c, base_f, fx_f)
            if s.surface_body[p] >= 0:
                v_bar = boundary_velocity(colliders, s.surface_body[p], s.surface_side[p], xp, s.v[p] + dt * gc.gravity)
        wc, dwc = spline(fx_c)
        wf, dwf = spline(fx_f)
        S = float(1.0)
        dS = wp.vec3(0.0)
        centre = wp.vec3(0.0)
        band = int(0)
        if kind == BAND:
            band = 1
            S, dS, centre = moments(gc, gf, share_c, share_f, base_c, fx_c, base_f, fx_f, slots)
        new_v = wp.vec3(0.0)
        B = wp.mat33(0.0)
        D = wp.mat33(0.0)
        G = wp.mat33(0.0)
        if kind != PURE_FINE:
            for i in range(3):
                for j in range(3):
                    for k in range(3):
                        n = coarse_node(gc.dims, base_c, i, j, k)
                        sc = share_c[n]
                        if sc > 0.0:
                            vi = wp.where(node_bit(mask_c, i, j, k) == 0.0, v_bar, v_c[n])
                            new_v, B, D, G = gather_node(band, sc * weight(wc, i, j, k) / S, vi,
                                                         offset(fx_c, i, j, k, gc.dx) - centre,
                                                         sc * weight_gradient(wc, dwc, i, j, k, gc.inv_dx), dS, S,
                                                         new_v, B, D, G)
        if kind != PURE_COARSE:
            for i in range(3):
                for j in range(3):
                    for k in range(3):
                        n = fine_node(slots, base_f, i, j, k)
                        sf = fine_share(share_f, n)
                        if sf > 0.0:
                            vi = wp.where(node_bit(mask_f, i, j, k) == 0.0, v_bar, v_f[n])
                            new_v, B, D, G = gather_node(band, sf * weight(wf, i, j, k) / S, vi,
                                                         offset(fx_f, i, j, k, gf.dx) - centre,
                                                         sf * weight_gradient(wf, dwf, i, j, k, gf.inv_dx), dS, S,
                                                         new_v, B, D, G)
        new_C = wp.mat33(0.0)
        if kind == BAND:
            new_C = B * wp.inverse(D)  # APIC's affine field with the particle's own D
        elif kind == PURE_COARSE:
            new_C = (4.0 * gc.inv_dx * gc.inv_dx) * B  # Eq. 6, MLS: the velocity gradient too
            G = new_C
        else:
            new_C = (4.0 * gf.inv_dx * gf.inv_dx) * B
            G = new_C
        g = gc  # the particle's own grid: its colors, band and advection
        cf = color_c
        if s.level[p] == gf.level:
            g = gf
            cf = color_f
        wp.static(finish)(materials, colliders, s, p, g, cf, xp, new_v, new_C, G, dt, stiff, signal)  # Eq. 7: G

    return g2p_partition


@functools.cache
def partition_kernels(cpic: bool, models: tuple[int, ...] = ALL_MODELS):
    """(P2G, G2P) of the partition coupling, with or without CPIC, for ``models``."""
    return _make_p2g(cpic, models), _make_g2p(cpic, models)
