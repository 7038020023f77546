"""Image stress at the domain walls: the wall's share of a particle's push.

A particle within a cell and a half of a wall plane has part of its 3x3x3 stencil on
or beyond the wall, where the wall's boundary condition overwrites what it scattered
there. In the bulk, a particle's stress is balanced by its neighbours' on every node;
next to a wall the nodes inside lose the share that material beyond the wall would
have given them, so the first layers of a fluid at rest see their own grid's truncated
stencil instead of the pressure the wall holds up: each grid settles into its own
near-wall equilibrium (a coarse grid's bottom cell a few hundred Pa above rho g depth,
a fine grid's below), and in adaptive mode the two grids' differences drive a current
along the floor (docs/method.md, "Wall images").

The remedy is the method of images: a wall is a mirror, and the particle's mirror
image beyond it (position reflected, Kirchhoff stress tau' = R tau R with R the
reflection) adds its MLS-MPM stress term (Eq. 9-10) to the nodes inside the domain.
Only the stress is imaged, not mass or momentum: an imaged momentum would hold
material at a wall it leaves (a separating wall) and double the nodes' inertia. At a
separating wall the image pushes only while the particle presses on the wall (tau_nn
< 0): a wall can push, never pull. Near an edge or a corner the images across two or
three walls are added too (the double and triple reflections), so that a fluid in a
corner is held from every side.

Opt-in (``[simulation.walls] images = true``, ``SolverConfig.wall_images``): it makes
original and finest mode's tanks at rest 4-5 times quieter, but in adaptive mode the
split families' shared jitter is then the larger noise, and a tank at rest across the
level interface moves faster than finest's with images (docs/method.md, "Wall images").

An image reaches a node inside only if the particle's own stencil reaches it (the
image lies farther from every node inside than the particle), so the images write
into the particle's own stencil nodes and need no block of their own on a sparse grid.
"""

from __future__ import annotations

import warp as wp

from .boundary import BOUNDARY_SEPARATE
from .footprint import Footprint, footprint_weights, stress_weight
from .grid import GridSpec, node_index, node_position
from .stencil import Stencil, bspline, weight_at

wp.set_module_options({"enable_backward": False})

REACH = wp.constant(1.5)  # cells: the quadratic B-spline's support radius
# the images' loops run with these as run-time values, so that Warp does not unroll them
# (7 images x 27 nodes unrolled made NVRTC's build of every P2G pass take minutes)
IMAGES = 8  # image 0 is the particle itself
STENCIL_NODES = 27


@wp.func
def image_weights(g: GridSpec, base: wp.vec3i, xi: wp.vec3):
    # N of the stencil's nodes base + q seen from an image at xi, laid out as Stencil.w (rows:
    # node offset q, columns: axis); once per image, not per node
    w = wp.mat33(0.0)
    for q in range(3):
        for d in range(3):
            w[q, d] = bspline((g.origin[d] + float(base[d] + q) * g.dx - xi[d]) * g.inv_dx)
    return w


@wp.func
def wall_sides(g: GridSpec, xp: wp.vec3, tau: wp.mat33, reach: float):
    """Per axis: -1 if the particle's image across the low wall may reach a node inside
    (the particle within ``reach`` cells of it), +1 the high wall, 0 neither (a
    separating wall only while the particle presses on it)."""
    sides = wp.vec3i(0)
    for d in range(3):
        lo = (xp[d] - g.domain_lo[d]) * g.inv_dx
        hi = (g.domain_hi[d] - xp[d]) * g.inv_dx
        if lo < reach and lo <= hi:
            if g.wall_type_lo[d] != BOUNDARY_SEPARATE or tau[d, d] < 0.0:
                sides[d] = -1
        elif hi < reach:
            if g.wall_type_hi[d] != BOUNDARY_SEPARATE or tau[d, d] < 0.0:
                sides[d] = 1
    return sides


@wp.func
def near_a_wall(g: GridSpec, xp: wp.vec3, reach: float):
    # the cheap test every particle takes: within ``reach`` cells of any wall plane
    a = wp.min(xp - g.domain_lo, g.domain_hi - xp) * g.inv_dx
    return wp.min(wp.min(a[0], a[1]), a[2]) < reach


@wp.func
def reflect_stress(stress: wp.mat33, R: wp.vec3):
    # R stress R for a diagonal reflection R: the entries (a, b) with one of a, b reflected change sign
    out = wp.mat33(0.0)
    for a in range(3):
        for b in range(3):
            out[a, b] = R[a] * R[b] * stress[a, b]
    return out


@wp.func
def image_axes(sides: wp.vec3i, image: int):
    # the reflection of image number ``image`` (bits 0-2: the axes it is reflected in): -1
    # on a reflected axis, 1 elsewhere; all 0 where it asks for an axis with no wall in reach
    R = wp.vec3(1.0)
    for d in range(3):
        if (image >> d) & 1 != 0:
            if sides[d] == 0:
                return wp.vec3(0.0)
            R[d] = -1.0
    return R


@wp.func
def image_position(g: GridSpec, xp: wp.vec3, R: wp.vec3, sides: wp.vec3i):
    # xp reflected in the wall planes of the axes R reflects
    xi = xp
    for d in range(3):
        if R[d] < 0.0:
            xi[d] = 2.0 * wp.where(sides[d] < 0, g.domain_lo[d], g.domain_hi[d]) - xp[d]
    return xi


@wp.func
def inside_reflected(g: GridSpec, x_node: wp.vec3, R: wp.vec3, sides: wp.vec3i):
    # the node lies inside the domain across every wall the image is reflected in (a
    # node on a wall plane belongs to the wall, whose condition overwrites it)
    tol = 1.0e-3 * g.dx
    inside = True
    for d in range(3):
        if R[d] < 0.0:
            if sides[d] < 0 and x_node[d] <= g.domain_lo[d] + tol:
                inside = False
            if sides[d] > 0 and x_node[d] >= g.domain_hi[d] - tol:
                inside = False
    return inside


@wp.func
def scatter_wall_images(g: GridSpec, st: Stencil, xp: wp.vec3, stress: wp.mat33, tau: wp.mat33, mask: int,
                        grid_mv: wp.array(dtype=wp.vec3)):
    """Add the images' stress terms to the stencil's nodes inside the domain.

    ``stress`` is the particle's stress part of the affine momentum, -dt 4/dx^2 V0 tau
    (Eq. 9-10, without m C); ``mask`` the CPIC bits of the nodes it may reach."""
    sides = wall_sides(g, xp, tau, REACH)
    if sides[0] == 0 and sides[1] == 0 and sides[2] == 0:
        return
    images = int(IMAGES)
    nodes = int(STENCIL_NODES)
    for image in range(1, images):  # a non-empty subset of the axes to reflect
        R = image_axes(sides, image)
        if R[0] != 0.0:
            xi = image_position(g, xp, R, sides)
            reflected = reflect_stress(stress, R)
            image_st = st  # the particle's stencil nodes, with the image's weights
            image_st.w = image_weights(g, st.base, xi)
            for q in range(nodes):  # stencil node (i, j, k) = (q / 9, q / 3 % 3, q % 3), CPIC bit q
                ijk = wp.vec3i(q // 9, (q // 3) % 3, q % 3)
                c = st.base + ijk
                x_node = node_position(g, c)
                if (mask >> q) & 1 != 0 and inside_reflected(g, x_node, R, sides):
                    dpos = x_node - xi
                    weight = weight_at(image_st, ijk[0], ijk[1], ijk[2])
                    if weight > 0.0:
                        n = node_index(g, c[0], c[1], c[2])
                        if n >= 0:
                            wp.atomic_add(grid_mv, n, weight * (reflected * dpos))


@wp.func
def scatter_footprint_images(g: GridSpec, fp: Footprint, xp: wp.vec3, stress: wp.mat33, tau: wp.mat33,
                             grid_mv: wp.array(dtype=wp.vec3)):
    """The same for a level-0 particle's footprint on the fine grid (sim/footprint.py,
    ``stress`` its -dt V tau): the image of its family is the family of its image, and
    it reaches only nodes of the particle's own footprint."""
    sides = wall_sides(g, xp, tau, REACH + fp.reach)
    if sides[0] == 0 and sides[1] == 0 and sides[2] == 0:
        return
    images = int(IMAGES)
    for image in range(1, images):
        R = image_axes(sides, image)
        if R[0] != 0.0:
            reflected = reflect_stress(stress, R)
            im = footprint_weights(g, image_position(g, xp, R, sides), fp)  # on the particle's nodes
            for i in range(fp.nodes):
                for j in range(fp.nodes):
                    for k in range(fp.nodes):
                        c = fp.base + wp.vec3i(i, j, k)
                        if im.wx[i] * im.wy[j] * im.wz[k] > 0.0 and inside_reflected(g, node_position(g, c), R, sides):
                            n = node_index(g, c[0], c[1], c[2])
                            if n >= 0:
                                wp.atomic_add(grid_mv, n, reflected * stress_weight(im, i, j, k, g.inv_dx))
