"""A level-0 particle on the fine grid: its footprint, not a point (adaptive mode).

A coarse particle stands for a box of material one parent lattice spacing h wide. The
coarse grid sees it through the quadratic B-spline of spacing dx, wide enough for its
size. The fine grid (spacing dx/b) is b times finer: seen there as a point, a coarse
particle is one sample per h^3 = (b/2)^3 fine cells (8 particles per cell), so at
b = 4 the fine nodes between two coarse particles get, per axis, a third of the
mass and volume of the nodes on them, and the stress of Eq. 10 pushes on those lumps. Level-1
particles next to the level interface read that lumpy field (their J scattered up to
0.15 from hydrostatic in a tank at rest at b = 4; docs/method.md, "The level
interface against finest").

Here the particle's mass is spread over its box instead: the weight of fine node i is
the quadratic B-spline averaged over the box,

    W(r) = 1/(2a) * integral_{-a}^{a} N(r - s) ds = (M(r + a) - M(r - a)) / (2a),

per axis, with r = (x_i - x_p)/dx' and a = h / (2 dx') the box's half-width in fine
cells (b/4 at 8 particles per cell; capped at 1 so that the footprint stays within
5 nodes per axis), M the integral of N. Like N, W sums to 1 and has zero first moment
at any position (momentum and affine momentum are transferred exactly), and the
footprints of a lattice of boxes tile space: their volume field is uniform on the
fine grid for every b. Its second moment is (1/4 + a^2/3) dx'^2 per axis (N's 1/4
plus the box's variance), the inertia D of MLS-MPM (Eq. 10) that the stress uses in
place of the point kernel's dx'^2/4. At b = 2 (a = 1/2) points one cell apart already
sum to 1, so only a particle in a collider's band next to the region takes its box there,
the kernel the fine grid moves it with (``p2g_sparse``; docs/method.md, "The contact
band's ties, and the band rule at b = 2").
"""

from __future__ import annotations

import warp as wp

from .grid import GridSpec

wp.set_module_options({"enable_backward": False})

FOOTPRINT_NODES = 5  # nodes per axis of a footprint of half-width a <= 1 fine cell
MAX_HALF_WIDTH = 1.0  # fine cells
# fine nodes a footprint reaches past its particle's fine cell: 2 (a <= 1: nodes from
# floor(X - a - 1.5) + 1 on), and one for round-off in X
FOOTPRINT_REACH = 3
WIDER_VOLUME = wp.constant(1.002**3)  # a box's volume over a cell's beyond which it is wider (round-off)
vec5 = wp.types.vector(length=FOOTPRINT_NODES, dtype=float)


@wp.struct
class Footprint:
    base: wp.vec3i  # lowest node of the 5x5x5 footprint
    wx: vec5  # weights per axis: node base + q along x, y, z
    wy: vec5
    wz: vec5
    nodes: int  # FOOTPRINT_NODES, as a run-time value: loops over it are not unrolled
    a: wp.vec3  # the box's half-width per axis, fine cells (cut at a domain wall's plane)
    inertia_inv: wp.mat33  # D^-1 of MLS-MPM for this kernel, 1/m^2 (4/dx^2 I for a point)


@wp.func
def spline_integral(t: float):
    # M(t): the quadratic B-spline N integrated from -infinity to t (piecewise cubic)
    if t <= -1.5:
        return 0.0
    if t <= -0.5:
        u = t + 1.5
        return u * u * u / 6.0
    if t <= 0.5:
        return 1.0 / 6.0 + 0.75 * (t + 0.5) - (t * t * t + 0.125) / 3.0
    if t < 1.5:
        u = 1.5 - t
        return 1.0 - u * u * u / 6.0
    return 1.0


@wp.func
def box_weights(X: float, a: float, lo: int):
    # W(k - X) of nodes k = lo .. lo + 4 (module docstring)
    w = vec5()
    nodes = int(FOOTPRINT_NODES)  # a loop Warp does not unroll (compile time)
    for q in range(nodes):
        r = float(lo + q) - X
        w[q] = (spline_integral(r + a) - spline_integral(r - a)) / (2.0 * a)
    return w


@wp.func
def footprint_base(X: float, a: float, dim: int):
    # the first node with a nonzero weight, k > X - a - 1.5; clamped to the grid like
    # stencil_base (only a particle flung out of the domain is ever clamped)
    return wp.clamp(int(wp.floor(X - a - 1.5)) + 1, 0, dim - FOOTPRINT_NODES)


@wp.func
def half_width(a: float, X: float, lo: float, hi: float):
    # Next to a domain wall the box is cut at the wall plane, where the material it
    # stands for ends: boxes that tile the material up to the wall then give the fine
    # nodes along it the volume that the same material sampled fine gives them. (Cut
    # half a cell inside the plane, as until 2026-11-29, they gave the second node
    # from the wall 1.35 and the third 0.83 of a cell's volume at b = 4.) The footprint
    # then reaches one node past the plane, as a fine particle within half a cell of
    # the wall does.
    return wp.clamp(wp.min(X - lo, hi - X), 1.0e-3, a)


@wp.func
def wider_than_a_cell(g: GridSpec, volume: float):
    # Points sampled at most one cell apart sum to 1 within 2% under the
    # quadratic B-spline (at exactly one cell, as b = 2 gives at 8 particles per cell,
    # exactly); two cells apart (b = 4) the sum swings between 0.5 and 1.5. So only
    # a box wider than a cell (by more than round-off, 0.2%) needs its footprint.
    return volume > WIDER_VOLUME * g.dx * g.dx * g.dx


@wp.func
def footprint(g: GridSpec, x: wp.vec3, volume: float):
    """Where the footprint on grid ``g`` of a particle at ``x`` whose box has ``volume``
    lies, and its inertia: cheap, so that a particle far from the grid's active blocks
    can be left before ``footprint_weights``."""
    a = wp.min(0.5 * wp.pow(volume, 1.0 / 3.0) * g.inv_dx, MAX_HALF_WIDTH)
    X = (x - g.origin) * g.inv_dx
    lo = (g.domain_lo - g.origin) * g.inv_dx
    hi = (g.domain_hi - g.origin) * g.inv_dx
    fp = Footprint()
    fp.nodes = FOOTPRINT_NODES
    fp.a = wp.vec3(half_width(a, X[0], lo[0], hi[0]), half_width(a, X[1], lo[1], hi[1]),
                   half_width(a, X[2], lo[2], hi[2]))
    fp.base = wp.vec3i(footprint_base(X[0], fp.a[0], g.dims[0]), footprint_base(X[1], fp.a[1], g.dims[1]),
                       footprint_base(X[2], fp.a[2], g.dims[2]))
    s = g.inv_dx * g.inv_dx
    fp.inertia_inv = wp.diag(wp.vec3(s / (0.25 + fp.a[0] * fp.a[0] / 3.0), s / (0.25 + fp.a[1] * fp.a[1] / 3.0),
                                      s / (0.25 + fp.a[2] * fp.a[2] / 3.0)))
    return fp


@wp.func
def footprint_weights(g: GridSpec, x: wp.vec3, fp: Footprint):
    """``fp`` with the weights of its nodes (module docstring)."""
    X = (x - g.origin) * g.inv_dx
    out = fp
    out.wx = box_weights(X[0], fp.a[0], fp.base[0])
    out.wy = box_weights(X[1], fp.a[1], fp.base[1])
    out.wz = box_weights(X[2], fp.a[2], fp.base[2])
    return out
