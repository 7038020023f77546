"""A level-0 particle on the fine grid: its family's footprint, not a point (adaptive mode).

A coarse particle stands for a box of material one parent lattice spacing h wide, the
box its b^3 children fill when it splits (Eq. 15: a regular sub-lattice, h/b apart).
The coarse grid sees it through the quadratic B-spline of spacing dx, wide enough for
its size. The fine grid (spacing dx/b) is b times finer: seen there as a point, a
coarse particle is one sample per h^3 = (b/2)^3 fine cells (8 particles per cell), so
at b = 4 the fine nodes between two coarse particles get, per axis, a third of the
mass and volume of the nodes on them, and the stress of Eq. 10 pushes on those lumps.

Here it is seen as the family it would split into: per axis the weight of fine node i
and the stress's weight are the means over the family's b child offsets o_c,

    W(r) = mean_c N(r - o_c),      G(r) = mean_c 4 (r - o_c) N(r - o_c),

with r = (x_i - x_p)/dx' and o_c = (c + 1/2 - b/2) h/(b dx') (fine cells). A node's
weight is W_x W_y W_z, and its stress vector (Eq. 10's D^-1 (x_i - x_p) w_ip of each
child, summed over the family) (G_x W_y W_z, W_x G_y W_z, W_x W_y G_z) / dx'. So a coarse
particle puts on the fine grid exactly the mass, momentum (its children's velocities
v + C o_c, Eq. 15) and stress its family would: at the level interface and next to a
wall a lattice of coarse particles and the children beside them give every fine node the
volume and the zero net force of the same material sampled fine (`tests/test_footprint.py`).
(A coarse particle as a point, as at b = 2 until 2026-11-29, leaves a net force of
0.16 p dx'^2 under a uniform pressure p on the fine node at the level interface, which
in a tank at rest pushed the children along the floor into the coarse half at 15 m/s^2
in the first step; the box average of N with its MLS inertia, used at b = 3 and 4 until
then, 0.014 p dx'^2 at the interface at b = 4 and 0.07 on every other node of the boxes
at b = 3: docs/method.md, "A coarse particle on the fine grid as its family".) In G2P
the same weights give v = sum_i W_i v_i and C = sum_i v_i g_i^T, the mean of the
children's (the transpose of the stress's weights, as MLS-MPM pairs them).
"""

from __future__ import annotations

import warp as wp

from .grid import GridSpec
from .stencil import bspline

wp.set_module_options({"enable_backward": False})

FOOTPRINT_NODES = 5  # nodes per axis a footprint spans at most (offsets up to MAX_HALF_WIDTH)
MAX_HALF_WIDTH = 1.0  # fine cells: the outermost child's offset (b <= 5 at 8 particles per cell)
# fine nodes a footprint reaches past its particle's fine cell: 2 (offsets <= 1 cell: nodes
# from floor(X - 2.5) + 1 on), and one for round-off in X
FOOTPRINT_REACH = 3
vec5 = wp.types.vector(length=FOOTPRINT_NODES, dtype=float)


@wp.struct
class Footprint:
    base: wp.vec3i  # lowest node of the footprint
    wx: vec5  # W per axis: node base + q along x, y, z
    wy: vec5
    wz: vec5
    gx: vec5  # G per axis (module docstring), in fine cells^-1 times a cell
    gy: vec5
    gz: vec5
    nodes: int  # nodes per axis, a run-time value: loops over it are not unrolled
    children: int  # the family's children per axis (b)
    pitch: float  # their spacing, fine cells
    reach: float  # the outermost child's offset, fine cells


@wp.func
def family_weights(X: float, lo: int, nodes: int, children: int, pitch: float):
    # W(k - X) and G(k - X) of nodes k = lo .. lo + nodes - 1 (module docstring), 0 beyond;
    # ``nodes`` a run-time value, so that Warp does not unroll the loop (compile time)
    w = vec5()
    gr = vec5()
    inv = 1.0 / float(children)
    for q in range(nodes):
        sw = float(0.0)
        sg = float(0.0)
        for c in range(children):
            r = float(lo + q) - X - (float(c) + 0.5 - 0.5 * float(children)) * pitch
            n = bspline(r)
            sw += n
            sg += 4.0 * r * n
        w[q] = sw * inv
        gr[q] = sg * inv
    return w, gr


@wp.func
def footprint_base(X: float, reach: float, dim: int):
    # the first node with a nonzero weight, k > X - reach - 1.5; clamped to the grid like
    # stencil_base (only a particle flung out of the domain is ever clamped)
    return wp.clamp(int(wp.floor(X - reach - 1.5)) + 1, 0, dim - FOOTPRINT_NODES)


@wp.func
def footprint(g: GridSpec, x: wp.vec3, volume: float):
    """Where the footprint on grid ``g`` of a particle at ``x`` whose box has ``volume``
    lies: cheap, so that a particle far from the grid's active blocks can be left before
    ``footprint_weights``."""
    fp = Footprint()
    fp.children = wp.max(g.family, 1)
    h = wp.pow(volume, 1.0 / 3.0) * g.inv_dx  # the parent's spacing, fine cells
    fp.pitch = h / float(fp.children)
    fp.reach = 0.5 * float(fp.children - 1) * fp.pitch
    if fp.reach > MAX_HALF_WIDTH:  # a family wider than 5 nodes: squeezed (never at b <= 5)
        fp.pitch = fp.pitch * MAX_HALF_WIDTH / fp.reach
        fp.reach = MAX_HALF_WIDTH
    # nodes strictly within reach + 1.5 of X: at most ceil(2 (reach + 1.5))
    fp.nodes = wp.min(int(wp.ceil(2.0 * (fp.reach + 1.5) - 1.0e-4)), FOOTPRINT_NODES)
    X = (x - g.origin) * g.inv_dx
    fp.base = wp.vec3i(footprint_base(X[0], fp.reach, g.dims[0]), footprint_base(X[1], fp.reach, g.dims[1]),
                       footprint_base(X[2], fp.reach, g.dims[2]))
    return fp


@wp.func
def footprint_weights(g: GridSpec, x: wp.vec3, fp: Footprint):
    """``fp`` with the weights of its nodes (module docstring)."""
    X = (x - g.origin) * g.inv_dx
    out = fp
    wx, gx = family_weights(X[0], fp.base[0], fp.nodes, fp.children, fp.pitch)
    wy, gy = family_weights(X[1], fp.base[1], fp.nodes, fp.children, fp.pitch)
    wz, gz = family_weights(X[2], fp.base[2], fp.nodes, fp.children, fp.pitch)
    out.wx = wx
    out.wy = wy
    out.wz = wz
    out.gx = gx
    out.gy = gy
    out.gz = gz
    return out


@wp.func
def stress_weight(fp: Footprint, i: int, j: int, k: int, inv_dx: float):
    # node (i, j, k)'s stress vector: the family's sum of D^-1 (x_i - x_c) N (Eq. 10), 1/m
    return inv_dx * wp.vec3(fp.gx[i] * fp.wy[j] * fp.wz[k], fp.wx[i] * fp.gy[j] * fp.wz[k],
                            fp.wx[i] * fp.wy[j] * fp.gz[k])
