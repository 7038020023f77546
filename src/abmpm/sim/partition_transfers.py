"""The transfers of the partition coupling (``sim/partition.py``): P2G (Eqs. 8-10) and G2P
(Eqs. 5-7, 11-14, 23-25) with each particle's functions on both grids.

Where every function a particle reaches is one grid's own B-spline (its coarse cell's kind,
``PURE_COARSE`` or ``PURE_FINE``, set by ``Partition.update``), it transfers exactly as in a
one-level run: MLS, the force folded into the affine momentum with D^-1 = 4 / dx^2. In the
band where both grids have weight (``BAND``) it uses the normalised weights W = r / S and
their exact gradients, for the force (-V0 tau grad W) and for the deformation update
(grad v = sum v_i grad W_i^T), and APIC's C = B D^-1 with its own D about the weights'
centroid: MLS's D^-1 on the blended functions lost energy in the one-dimensional model
(``docs/prototypes/partition_1d.py``). The stencils are the one-grid passes' own
(``sim/stencil.py``); only the weights' gradients are this module's.
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
from .grid import GridSpec, cell_flag
from .materials import ALL_MODELS, MaterialParams, dispatch
from .p2g import record_reach
from .parallel import Reach
from .state import ParticleArrays
from .stencil import Stencil, dense_node_at, dense_stencil, offset_at, sparse_node_at, sparse_stencil, weight_at
from .variant import variant

wp.set_module_options({"enable_backward": False})

PURE_COARSE = wp.constant(0)  # a coarse cell whose particles reach only coarse functions of share 1
BAND = wp.constant(1)  # both grids' functions
PURE_FINE = wp.constant(2)  # only fine functions of share 1


@wp.func
def spline_gradient(fx: wp.vec3):
    # derivatives in fx of ``bspline_weights`` (rows: node 0, 1, 2; columns: axis)
    return wp.matrix_from_rows(fx - wp.vec3(1.5), -2.0 * (fx - wp.vec3(1.0)), fx - wp.vec3(0.5))


@wp.func(inline=True)
def weight_gradient(st: Stencil, dw: wp.mat33, i: int, j: int, k: int, inv_dx: float):
    # grad N_i (per m) of stencil node (i, j, k)
    w = st.w
    return inv_dx * wp.vec3(dw[i, 0] * w[j, 1] * w[k, 2], w[i, 0] * dw[j, 1] * w[k, 2], w[i, 0] * w[j, 1] * dw[k, 2])


@wp.func(inline=True)
def fine_share(share_f: wp.array(dtype=float), n: int):
    s = float(0.0)
    if n >= 0:
        s = share_f[n]
    return s


@wp.func
def functions(gc: GridSpec, gf: GridSpec, share_c: wp.array(dtype=float), share_f: wp.array(dtype=float),
              kinds: wp.array3d(dtype=wp.int32), x: wp.vec3):
    # A particle's stencils on both grids, their weights' gradients, whether it is in the band (its
    # cell's kind; a PURE_FINE cell whose fine stencil reaches an inactive block, share 0 there, is
    # band too), and in the band S = sum r, grad S and the weights' centroid from x (Eq. 8's APIC
    # about it): for one grid's own B-splines S = 1, grad S = 0, the centroid x itself
    st_c = dense_stencil(gc, x)
    st_f = sparse_stencil(gf, x)
    dwc = spline_gradient(st_c.fx)
    dwf = spline_gradient(st_f.fx)
    kind = cell_flag(gc, kinds, x)
    if kind == PURE_FINE and wp.min(st_f.slots) < 0:
        kind = BAND
    S = float(1.0)
    dS = wp.vec3(0.0)
    centre = wp.vec3(0.0)
    if kind == BAND:
        S = float(0.0)
        X = wp.vec3(0.0)
        for i in range(3):
            for j in range(3):
                for k in range(3):
                    s = share_c[dense_node_at(gc, st_c, i, j, k)]
                    S += s * weight_at(st_c, i, j, k)
                    dS += s * weight_gradient(st_c, dwc, i, j, k, gc.inv_dx)
                    X += (s * weight_at(st_c, i, j, k)) * offset_at(gc, st_c, i, j, k)
                    s = fine_share(share_f, sparse_node_at(gf, st_f, i, j, k))
                    S += s * weight_at(st_f, i, j, k)
                    dS += s * weight_gradient(st_f, dwf, i, j, k, gf.inv_dx)
                    X += (s * weight_at(st_f, i, j, k)) * offset_at(gf, st_f, i, j, k)
        centre = X / S
    return st_c, st_f, dwc, dwf, kind, S, dS, centre


@wp.func
def masks(gc: GridSpec, gf: GridSpec, color_c: ColorField, color_f: ColorField, x: wp.vec3, level: int,
          surface_point: wp.vec3, surface_side: wp.vec3, surface_body: int, st_c: Stencil, st_f: Stencil):
    # CPIC (sim/colliders.py): each grid's stencil nodes on the particle's side of every surface.
    # A level-1 particle's color reaches a few fine cells; on the coarse grid, beyond its own
    # band, the nodes' colors say which nodes face it (as p2g_overlap does)
    mask_c = ALL_NODES
    mask_f = ALL_NODES
    if surface_body >= 0:
        mask_c = compatibility_mask(surface_point, surface_side, surface_body, x, color_c, gc, st_c.base, st_c.fx)
        mask_f = compatibility_mask(surface_point, surface_side, surface_body, x, color_f, gf, st_f.base, st_f.fx)
    elif level == 1 and near_surface(color_c, gc, x):
        mask_c = nodes_facing(x, color_c, gc, st_c.base, st_c.fx)
    return mask_c, mask_f


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
                      mv_f: wp.array(dtype=wp.vec3), m_f: wp.array(dtype=float), reach_f: Reach,
                      kept: wp.array(dtype=wp.vec2i)):
        # Eq. 8's mass and APIC momentum, Eqs. 9-10's force folded into it
        p = wp.tid() + first
        xp = s.x[p]
        st_c, st_f, dwc, dwf, kind, S, dS, centre = functions(gc, gf, share_c, share_f, kinds, xp)
        band = wp.where(kind == BAND, 1, 0)
        mask_c = ALL_NODES
        mask_f = ALL_NODES
        if wp.static(cpic):
            mask_c, mask_f = masks(gc, gf, color_c, color_f, xp, s.level[p], s.surface_point[p], s.surface_side[p],
                                   s.surface_body[p], st_c, st_f)
            kept[p] = wp.vec2i(mask_c, mask_f)  # for this substep's G2P
        tau = wp.static(particle_stress)(materials[s.material[p]], s.F, s.history, p, s.C[p])
        stress = (-dt_now[0] * s.volume[p]) * tau
        m = s.mass[p]
        mv = m * s.v[p]
        mC = m * s.C[p]
        if kind != PURE_FINE:
            affine = mC + (4.0 * gc.inv_dx * gc.inv_dx) * stress  # MLS (Eqs. 9-10)
            for i in range(3):
                for j in range(3):
                    for k in range(3):
                        n = dense_node_at(gc, st_c, i, j, k)
                        sc = share_c[n]
                        if sc > 0.0:
                            Wu = sc * weight_at(st_c, i, j, k) / S  # W before CPIC's mask
                            bit = node_bit(mask_c, i, j, k)
                            grad_r = sc * weight_gradient(st_c, dwc, i, j, k, gc.inv_dx)
                            wp.atomic_add(mv_c, n, node_momentum(band, Wu * bit, Wu, bit, mv, mC, affine,
                                                                 offset_at(gc, st_c, i, j, k), centre, stress,
                                                                 grad_r, dS, S))
                            wp.atomic_add(m_c, n, Wu * bit * m)
            record_reach(gc, st_c, reach_c)
        if kind != PURE_COARSE:
            affine = mC + (4.0 * gf.inv_dx * gf.inv_dx) * stress
            for i in range(3):
                for j in range(3):
                    for k in range(3):
                        n = sparse_node_at(gf, st_f, i, j, k)
                        sf = fine_share(share_f, n)
                        if sf > 0.0:
                            Wu = sf * weight_at(st_f, i, j, k) / S  # W before CPIC's mask
                            bit = node_bit(mask_f, i, j, k)
                            grad_r = sf * weight_gradient(st_f, dwf, i, j, k, gf.inv_dx)
                            wp.atomic_add(mv_f, n, node_momentum(band, Wu * bit, Wu, bit, mv, mC, affine,
                                                                 offset_at(gf, st_f, i, j, k), centre, stress,
                                                                 grad_r, dS, S))
                            wp.atomic_add(m_f, n, Wu * bit * m)
            record_reach(gf, st_f, reach_f)

    return p2g_partition


def _make_g2p(cpic: bool, models: tuple[int, ...]):
    finish = make_finish(cpic, models)  # Eqs. 7 (with the exact gradient in the band), 13-14, advection, CFL

    @variant("g2p_partition", cpic, models=models)
    def g2p_partition(first: int, materials: wp.array(dtype=MaterialParams), gc: GridSpec, gf: GridSpec,
                      colliders: ColliderArrays, color_c: ColorField, color_f: ColorField,
                      share_c: wp.array(dtype=float), share_f: wp.array(dtype=float), kinds: wp.array3d(dtype=wp.int32),
                      dt_now: wp.array(dtype=float), v_c: wp.array(dtype=wp.vec3), v_f: wp.array(dtype=wp.vec3),
                      s: ParticleArrays, kept: wp.array(dtype=wp.vec2i), stiff: wp.array(dtype=float),
                      signal: wp.array(dtype=float)):
        # Eqs. 5-7 and 11-14 with the functions the particle scattered with; an incompatible
        # node lends the particle's boundary velocity (Eqs. 23-25)
        p = wp.tid() + first
        dt = dt_now[0]
        xp = s.x[p]
        st_c, st_f, dwc, dwf, kind, S, dS, centre = functions(gc, gf, share_c, share_f, kinds, xp)
        band = wp.where(kind == BAND, 1, 0)
        mask_c = ALL_NODES
        mask_f = ALL_NODES
        v_bar = wp.vec3(0.0)
        if wp.static(cpic):
            mask_c = kept[p][0]  # the masks P2G scattered with
            mask_f = kept[p][1]
            if s.surface_body[p] >= 0:
                v_bar = boundary_velocity(colliders, s.surface_body[p], s.surface_side[p], xp, s.v[p] + dt * gc.gravity)
        new_v = wp.vec3(0.0)
        B = wp.mat33(0.0)
        D = wp.mat33(0.0)
        G = wp.mat33(0.0)
        if kind != PURE_FINE:
            for i in range(3):
                for j in range(3):
                    for k in range(3):
                        n = dense_node_at(gc, st_c, i, j, k)
                        sc = share_c[n]
                        if sc > 0.0:
                            vi = wp.where(node_bit(mask_c, i, j, k) == 0.0, v_bar, v_c[n])
                            new_v, B, D, G = gather_node(band, sc * weight_at(st_c, i, j, k) / S, vi,
                                                         offset_at(gc, st_c, i, j, k) - centre,
                                                         sc * weight_gradient(st_c, dwc, i, j, k, gc.inv_dx), dS, S,
                                                         new_v, B, D, G)
        if kind != PURE_COARSE:
            for i in range(3):
                for j in range(3):
                    for k in range(3):
                        n = sparse_node_at(gf, st_f, i, j, k)
                        sf = fine_share(share_f, n)
                        if sf > 0.0:
                            vi = wp.where(node_bit(mask_f, i, j, k) == 0.0, v_bar, v_f[n])
                            new_v, B, D, G = gather_node(band, sf * weight_at(st_f, i, j, k) / S, vi,
                                                         offset_at(gf, st_f, i, j, k) - centre,
                                                         sf * weight_gradient(st_f, dwf, i, j, k, gf.inv_dx), dS, S,
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
