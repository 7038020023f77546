"""A particle's color from the nodes' color distance field (paper Section 5.3, Eq. 21;
docs/method.md, "A particle's color from the nodes").

The color of a particle near a collider (closest surface point, the direction from
it to the particle, the body) is what CPIC's compatibility, its boundary velocity
(Eq. 23) and the crossing test read. Asking the BVH for the closest point costs
~1 us a particle on a CPU core; the nodes around the particle already know their
own closest points (``colliders.color_node``), so most particles can read theirs
from the nodes at the cost of a few grid lookups:

* **A bound.** Node i's distance D_i is exact, so the ball of radius D_i around it
  holds no surface point, and D_i - |x - x_i| is a lower bound of the particle's
  distance (triangle inequality). Nodes along the particle's side, 1 and 2 cells
  out, make it tight (their balls are large and nearly centred on its normal).
* **A plane.** Each of those nodes whose ball holds the particle is on its side of
  every surface; when each of them has its closest point inside a triangle (not on
  an edge, a rim or a corner: ``Color.flat``) and they all point the same way, the
  surface under the particle is that plane, and its closest point is its projection
  onto the tangent plane of the node with the largest ball.
* **Taken** when, besides, the plane's distance is within NODE_COLOR_TOL cells of the
  bound and the particle is at least NODE_COLOR_MIN cells from every surface. On a
  flat piece of a sheet (any tessellation) it is then exact; a hole or an edge that
  no node sees can make it wrong by at most the tolerance. The crossing test
  (``g2p.advect``) allows for the tolerance, so the guarantee that no particle changes
  sides does not rest on the plane: a particle that might reach a surface within its
  step still casts its ray.
* **Faces.** Where no plane vouches (curved glass, creases), the nearest point to the
  particle of the three nodes' closest triangles bounds its distance from above;
  within NODE_COLOR_TOL of the lower bound it is taken, on static colliders away from
  rims and only where no stencil node could be separated from the particle
  (``stencil_facing``), so that CPIC's test keeps every node whatever the color.
  Anything else (rims, moving colliders, particles close to a surface) asks for the
  exact closest point (``colliders.color_point``: the per-cell lists of face_cells.py
  on static colliders, the BVH otherwise).
"""

from __future__ import annotations

import warp as wp

from .colliders import NODE_BAND, ON_NODE, PARTICLE_BAND, Color, ColliderArrays, ColorField, behind_node, color_point
from .face_cells import closest_on_triangle, face_corners
from .grid import GridSpec, nearest_node_coords, node_index, node_position
from .stencil import stencil_base

wp.set_module_options({"enable_backward": False})

# cells: a color read from the nodes is taken when its distance exceeds the
# certified lower bound by at most this much; the crossing test allows for it
NODE_COLOR_TOL = 0.1
# cells: ... and only for a particle at least this far from every surface (closer,
# its side decides where the crossing test's ray starts: the BVH gives it)
NODE_COLOR_MIN = 0.1
NEEDS_QUERY = wp.constant(-2)  # Color.body of a color the nodes could not vouch for
FAR_BOUND = wp.constant(-1.0e10)
# the unit directions of those nodes may differ by this much (per-axis spread, ~6 degrees)
NODE_COLOR_SPREAD = 0.1


@wp.func(inline=True)
def node_ball(f: ColorField, g: GridSpec, x: wp.vec3, c: wp.vec3i):
    """Storage index of node c and D_c - |x - x_c|, a lower bound of x's distance to
    every surface (D_c is exact within the band, and at least NODE_BAND cells outside
    it). FAR_BOUND for an inactive node of a sparse grid."""
    n = node_index(g, c[0], c[1], c[2])
    b = float(FAR_BOUND)
    if n >= 0:
        b = wp.min(f.dist[n], NODE_BAND * g.dx) - wp.length(x - node_position(g, c))
    return n, b


@wp.func(inline=True)
def face_point(colliders: ColliderArrays, face: int, x: wp.vec3):
    # the point of collider triangle ``face`` closest to x
    a, b, c = face_corners(colliders.mesh, face)
    return closest_on_triangle(x, a, b, c)


@wp.func
def stencil_facing(f: ColorField, g: GridSpec, x: wp.vec3):
    """Whether no node of x's 3x3x3 stencil lies on a surface or has x behind its
    tangent plane: then CPIC's test (``colliders.compatible``) keeps every node, whatever
    x's own closest point, and the color only bounds x's distance."""
    base = stencil_base(g, x)
    for t in range(27):  # one loop, not unrolled: 27 copies of its body made every G2P slower
        c = base + wp.vec3i(t // 9, (t // 3) % 3, t % 3)
        n = node_index(g, c[0], c[1], c[2])
        if n >= 0:
            if f.body[n] >= 0:
                if f.dist[n] < ON_NODE * g.dx or behind_node(f, n, node_position(g, c), x):
                    return False
    return True


@wp.func(inline=True)
def color_from_faces(f: ColorField, g: GridSpec, colliders: ColliderArrays, x: wp.vec3, side: wp.vec3):
    """The color of x from the closest faces of its nodes (the nearest node and those 1
    and 2 cells out along ``side``) where no plane vouches for it (curved surfaces,
    creases); else ``body`` NEEDS_QUERY."""
    c = Color()
    c.body = NEEDS_QUERY
    step = g.dx * wp.normalize(side)
    lb = float(FAR_BOUND)
    nodes = wp.vec3i(-1)
    for k in range(3):
        n, b = node_ball(f, g, x, nearest_node_coords(g, x + float(k) * step))
        lb = wp.max(lb, b)
        nodes[k] = n
    # the cheap conditions first: a stencil that a surface cuts (the most common refusal
    # near a curved glass) then costs no triangle (one return: an early one made G2P slower)
    ok = lb >= NODE_COLOR_MIN * g.dx and stencil_facing(f, g, x)
    best = int(-1)
    best_d = float(PARTICLE_BAND) * g.dx
    best_x = wp.vec3(0.0)
    for k in range(3):
        n = nodes[k]
        if ok and n >= 0:
            if f.face[n] >= 0:
                # a point of the surface: its distance bounds x's from above
                q = face_point(colliders, f.face[n], x)
                dq = wp.length(x - q)
                if dq < best_d:
                    best_d = dq
                    best = f.face[n]
                    best_x = q
    # within the tolerance of the balls' lower bound it is x's closest point or off by at
    # most the tolerance; unless a rim is within 2 best_d of that face (x's closest point
    # may then lie on the rim, |rim - x| <= best_d, where x's side is not the face's: a
    # hole, a slit); and only where CPIC's test cannot tell the difference (stencil_facing)
    if best >= 0 and best_d - lb <= NODE_COLOR_TOL * g.dx and colliders.face_clear[best] > 2.0 * best_d:
        c.surface_point = best_x
        c.surface_side = (x - best_x) / best_d
        c.body = colliders.face_body[best]
    return c


@wp.func
def query_color(colliders: ColliderArrays, f: ColorField, g: GridSpec, x: wp.vec3, side: wp.vec3, bound: float):
    """The color of x where no node's plane vouches for it: from the nodes' closest faces
    (``color_from_faces``), else the BVH's closest point within ``bound``. One call,
    not inlined: G2P declares an inlined function's temporaries for every particle,
    and most particles never come here."""
    c = color_from_faces(f, g, colliders, x, side)
    if c.body == NEEDS_QUERY:
        c = color_point(colliders, g, x, bound, side)
    return c


@wp.func(inline=True)
def color_from_three_nodes(f: ColorField, g: GridSpec, x: wp.vec3, step: wp.vec3, far: wp.vec3i, n2: int, b2: float):
    """``color_from_nodes`` from the nearest node and those 1 and 2 cells out along
    ``step`` (the last, ``far``, already read: storage index ``n2``, ball bound ``b2``):
    every node whose ball holds x on the same flat plane, within the tolerance of the
    best of the three bounds."""
    c = Color()
    c.body = NEEDS_QUERY
    lb = float(FAR_BOUND)
    plane = int(-1)
    plane_lb = float(FAR_BOUND)
    plane_x = wp.vec3(0.0)
    lo = wp.vec3(1.0)  # per-axis bounds of the directions of the nodes whose balls hold x
    hi = wp.vec3(-1.0)
    flat = int(1)  # every such node's closest point has a plane around it (a rim distance)
    for k in range(3):
        node = far
        n = n2
        b = b2
        if k < 2:
            node = nearest_node_coords(g, x + float(k) * step)
            n, b = node_ball(f, g, x, node)
        lb = wp.max(lb, b)
        if n >= 0 and b > 0.0 and f.body[n] >= 0:
            # x lies in the node's ball, so on its side
            if f.rim[n] <= 0.0:
                flat = 0
            lo = wp.min(lo, f.dir[n])
            hi = wp.max(hi, f.dir[n])
            if b > plane_lb:
                plane_lb = b
                plane = n
                plane_x = node_position(g, node)
    if lb >= PARTICLE_BAND * g.dx:
        c.body = -1
    elif lb >= NODE_COLOR_MIN * g.dx and plane >= 0 and flat == 1 and wp.length(hi - lo) <= NODE_COLOR_SPREAD:
        nrm = f.dir[plane]
        foot = plane_x - f.dist[plane] * nrm
        d = wp.dot(x - foot, nrm)
        # a point of the surface (the node's plane reaches that far) within the distance
        # bound's tolerance: the closest point, or off by at most the tolerance
        if d - lb <= NODE_COLOR_TOL * g.dx and wp.length(x - d * nrm - foot) < f.rim[plane]:
            c.surface_point = x - d * nrm
            c.surface_side = nrm
            c.body = f.body[plane]
            c.flat = 1  # the plane's normal
    return c


@wp.func(inline=True)
def color_from_nodes(f: ColorField, g: GridSpec, x: wp.vec3, hint: wp.vec3, remembered: bool):
    """The color of x read from the nodes (module docstring), where they vouch for it;
    else ``body`` NEEDS_QUERY (ask the BVH). ``hint``: the side x had, away from the
    surface, when ``remembered``; else the nearest node's direction is used. ``body``
    is -1 when the bound puts x beyond PARTICLE_BAND cells."""
    c = Color()
    c.body = NEEDS_QUERY
    toward = hint
    if not remembered:
        n0, b0 = node_ball(f, g, x, nearest_node_coords(g, x))
        if n0 >= 0 and b0 > 0.0 and f.body[n0] >= 0:
            toward = f.dir[n0]
    step = g.dx * wp.normalize(toward)
    # One node first: the one 2 cells out along the remembered side, whose ball is the largest
    # and the tightest bound. Its ball alone certifies the plane's point as the rest of this
    # function does (a point of the surface within the tolerance of a lower bound of x's
    # distance to every surface); the other two nodes only when it does not.
    far = nearest_node_coords(g, x + 2.0 * step)
    n2, b2 = node_ball(f, g, x, far)
    if remembered:
        if n2 >= 0 and b2 >= NODE_COLOR_MIN * g.dx and b2 < PARTICLE_BAND * g.dx:
            if f.body[n2] >= 0 and f.rim[n2] > 0.0:
                # the plane test of color_from_three_nodes, written out again: the same test as one
                # inlined function returning a Color at both places made the G2P 7% slower
                nrm2 = f.dir[n2]
                foot2 = node_position(g, far) - f.dist[n2] * nrm2
                d2 = wp.dot(x - foot2, nrm2)
                if d2 - b2 <= NODE_COLOR_TOL * g.dx and wp.length(x - d2 * nrm2 - foot2) < f.rim[n2]:
                    c.surface_point = x - d2 * nrm2
                    c.surface_side = nrm2
                    c.body = f.body[n2]
                    c.flat = 1
    if c.body == NEEDS_QUERY:  # the three nodes, where the one did not vouch
        c = color_from_three_nodes(f, g, x, step, far, n2, b2)
    return c
