"""Thin rigid colliders: color distance field and compatible particle-in-cell (CPIC).

Paper Section 5 (Eqs. 21-25, 28-31), after Hu et al. 2018. All colliders of a
scene live in one Warp BVH mesh; each face knows its collider ("body").

Color distance field (on grid nodes, within ``NODE_BAND`` cells of a surface):
unsigned distance to the closest triangle (Warp's closest-point query is the
barycentric projection of Eqs. 28-31 with the edge fallback), the unit direction
from that closest point to the node, and the body.

Compatibility (our decision, see docs/method.md). The paper colors each node and
particle with the side of the surface it lies on (Eq. 21). A sign alone cannot tell
the two sides of a closed blade thinner than a cell (both read "outside") and
marks rim regions of open sheets wrongly, so we test sides with tangent
half-spaces: particle p and node i are separated by the surface when each lies
behind the other's tangent plane,

    (x_i - c_p) . n_p < 0   and   (x_p - c_i) . n_i < 0,

with c the closest surface point and n the direction from c to the point. This is
Eq. 21's side test made local; it agrees with it on smooth sheets, separates the
two faces of a thin closed blade, and keeps both ends of a narrow tube compatible.

No crossing (the guarantee of Eq. 21's kept particle color): after advection a
particle near a surface casts a ray along its motion relative to the collider; a
hit stops it just before the surface on its own side.
"""

from __future__ import annotations

import warp as wp

wp.set_module_options({"enable_backward": False})

from .boundary import boundary_response
from .face_cells import NO_LIST, FaceCells, closest_face, face_corners
from .grid import (
    GridSpec,
    dense_node_index,
    nearest_node_coords,
    node_coords,
    node_index,
    node_position,
)

# cells: nodes this close to a surface get a color: the stencil's reach 1.5 sqrt(3) ~ 2.6,
# and 2 cells more for the bounds of a particle's distance (node_color.py)
NODE_BAND = 4.5
PARTICLE_BAND = 2.6  # cells: particles this close test compatibility and crossings
# cells: nodes this close get the collider's boundary condition. A node one cell from a
# sheet on a node plane is in, whatever float32 round-off its distance carries (which
# differs between grids, nodes and devices): docs/method.md, "The contact band's ties"
CONTACT_BAND = 1.001
FAR = 1.0e10
NODE_RANGE = 512  # nodes worth a thread of their own when coloring (a query each)
# cells: closer than this a point is on the surface; its direction from the closest
# point is float32 noise, so the face normal stands in for it
ON_SURFACE = 1.0e-3
# cells: a node this close to a surface is inside it for CPIC (compatible with no
# particle near that surface); otherwise a node lying on a sheet couples both sides
ON_NODE = 1.0e-2
# cells: before its crossing test a particle near a surface steps this far back
# along its color direction, so the ray never starts on the surface itself (a ray
# from a point on a triangle may miss it, and a hit at t = 0 would freeze it there)
RAY_BACKOFF = 2.0e-2
# cells: a particle stopped before a surface stays this far from it (normal distance)
STOP_GAP = 5.0 * ON_SURFACE
# |cos| between a point's direction and its closest triangle's normal above which the
# closest point lies inside the triangle (on an edge or a vertex the direction leans)
FLAT = wp.constant(1.0 - 1.0e-5)
RIM_REACH = 2.0  # cells: how far from a node's closest point the search for a rim goes

@wp.struct
class ColliderBody:
    boundary: int
    friction: float
    separation: float  # c of Eq. 23
    velocity: wp.vec3  # v_r of Eq. 22
    omega: wp.vec3  # w_r of Eq. 22
    pivot: wp.vec3  # x_r of Eq. 22 (current position)


@wp.struct
class ColliderArrays:
    enabled: int
    cpic: int  # 0: plain grid boundary (node contact only), for comparison
    mesh: wp.uint64
    face_body: wp.array(dtype=wp.int32)
    bodies: wp.array(dtype=ColliderBody)
    rims: wp.uint64  # static colliders: their rims and creases as segments (0: none, node_color.py)
    face_clear: wp.array(dtype=float)  # per triangle: at least its distance to any rim (node_color.py)
    cells: FaceCells  # static colliders: per cell, the triangles that can be closest (face_cells.py)


@wp.struct
class ColorField:
    """Color distance field on the nodes of one grid."""

    dist: wp.array(dtype=float)  # flat, indexed like the grid's nodes
    dir: wp.array(dtype=wp.vec3)
    body: wp.array(dtype=wp.int32)
    rim: wp.array(dtype=float)  # from the closest point along the surface to its nearest rim (node_color.py)
    face: wp.array(dtype=wp.int32)  # the triangle of the closest point (-1: none)


@wp.func(inline=True)
def rigid_velocity(b: ColliderBody, x: wp.vec3):
    # Eq. 22: v_ir = v_r + w_r x (x_i - x_r)
    return b.velocity + wp.cross(b.omega, x - b.pivot)


@wp.func(inline=True)
def behind_node(f: ColorField, n: int, xi: wp.vec3, xp: wp.vec3):
    """The node's half of the separation test: x_p lies behind the tangent plane of
    colored node n at xi, (x_p - c_i) . n_i < 0."""
    ni = f.dir[n]
    ci = xi - f.dist[n] * ni
    return wp.dot(xp - ci, ni) < 0.0


@wp.func(inline=True)
def compatible(surface_point: wp.vec3, surface_side: wp.vec3, surface_body: int, xp: wp.vec3, f: ColorField, xi: wp.vec3, n: int, dx: float):
    """May particle p exchange momentum with node n at xi? (see module docstring)"""
    ok = True  # particle far from every surface, or an inactive node
    if surface_body >= 0 and n >= 0:
        # A node far from every surface carries FAR and no direction (color_node,
        # tests/test_node_color.py), so it passes both tests without a look at its body: a
        # node in front of the particle's tangent plane costs one load
        if f.dist[n] < ON_NODE * dx:
            ok = False  # a node on a surface belongs to neither side
        elif wp.dot(xi - surface_point, surface_side) < 0.0:
            ok = not behind_node(f, n, xi, xp)
    return ok


ALL_NODES = wp.constant(0x7FFFFFF)  # 27 bits: every node of the 3x3x3 stencil


@wp.func(inline=True)
def compatibility_mask(surface_point: wp.vec3, surface_side: wp.vec3, surface_body: int, xp: wp.vec3, f: ColorField, g: GridSpec,
                       base: wp.vec3i, fx: wp.vec3):
    """Bit (9 i + 3 j + k) set when stencil node (i, j, k) is compatible with the particle."""
    # Every stencil node lies within 1.5 dx |n|_1 of x_p along n, so a particle farther
    # than that from its tangent plane has no node behind it: all compatible (exact).
    reach = 1.5 * g.dx * (wp.abs(surface_side[0]) + wp.abs(surface_side[1]) + wp.abs(surface_side[2]))
    mask = int(ALL_NODES)
    if not (wp.dot(xp - surface_point, surface_side) > reach + 1.0e-3 * g.dx):
        mask = 0
        for i in range(3):
            for j in range(3):
                for k in range(3):
                    xi = xp + (wp.vec3(float(i), float(j), float(k)) - fx) * g.dx
                    if compatible(surface_point, surface_side, surface_body, xp, f, xi,
                                  node_index(g, base[0] + i, base[1] + j, base[2] + k), g.dx):
                        mask = mask | (1 << (9 * i + 3 * j + k))
    return mask


@wp.func
def nodes_facing(xp: wp.vec3, f: ColorField, g: GridSpec, base: wp.vec3i, fx: wp.vec3):
    """Compatibility mask of a particle with no color of its own on this grid's scale:
    node i stays compatible unless x_p lies behind node i's tangent plane
    (``behind_node``) or node i is on a surface. Only the node's half of the test of
    ``compatible`` (the particle's half needs its closest point): it separates
    every pair the full test separates, and some more near rims and concave corners,
    so it is the safe side for a particle that only lends its momentum (dense grid
    only: the coarse grid of the overlap P2G)."""
    mask = int(0)
    for i in range(3):
        for j in range(3):
            for k in range(3):
                n = dense_node_index(g, base[0] + i, base[1] + j, base[2] + k)
                ok = True
                if f.body[n] >= 0:
                    if f.dist[n] < ON_NODE * g.dx:
                        ok = False
                    else:
                        xi = xp + (wp.vec3(float(i), float(j), float(k)) - fx) * g.dx
                        ok = not behind_node(f, n, xi, xp)
                if ok:
                    mask = mask | (1 << (9 * i + 3 * j + k))
    return mask


@wp.func(inline=True)
def node_bit(mask: int, i: int, j: int, k: int):
    # 1.0 for a compatible node, 0.0 otherwise: branch-free in the transfer loops
    return float((mask >> (9 * i + 3 * j + k)) & 1)


@wp.func
def node_contact(colliders: ColliderArrays, f: ColorField, v: wp.vec3, xi: wp.vec3, n: int, band: float):
    """Boundary condition of the nearest collider on a node within ``band`` (m)."""
    b = f.body[n]
    if b < 0 or f.dist[n] > band:
        return v
    body = colliders.bodies[b]
    return boundary_response(v, rigid_velocity(body, xi), f.dir[n], body.boundary, body.friction, body.separation)


@wp.func(inline=True)
def boundary_velocity(colliders: ColliderArrays, surface_body: int, surface_side: wp.vec3, xp: wp.vec3, vp: wp.vec3):
    """Eq. 23: the velocity an incompatible node lends to particle p."""
    body = colliders.bodies[surface_body]
    return boundary_response(vp, rigid_velocity(body, xp), surface_side, body.boundary, body.friction, body.separation)


@wp.struct
class Color:
    surface_point: wp.vec3  # closest surface point
    surface_side: wp.vec3  # unit direction from surface_point to the particle
    body: int  # -1 when farther than PARTICLE_BAND cells
    face: int  # the triangle of surface_point
    flat: int  # 1: surface_point lies inside the triangle (the direction is its normal)


@wp.func(inline=True)
def near_surface(f: ColorField, g: GridSpec, x: wp.vec3):
    # Cheap filter before a closest-point query: can x be within the particle band of a
    # surface? The nearest node's exact distance, less the way from the node to x, is a
    # lower bound of x's own (triangle inequality); an uncolored node is farther than
    # NODE_BAND. Saves the query, the costliest part of a particle near a collider, in
    # the shell between PARTICLE_BAND and NODE_BAND + half a cell diagonal.
    c = nearest_node_coords(g, x)
    n = node_index(g, c[0], c[1], c[2])
    near = False
    if n >= 0:
        if f.body[n] >= 0:
            near = f.dist[n] - wp.length(x - node_position(g, c)) <= PARTICLE_BAND * g.dx
    return near


@wp.func
def color_point(colliders: ColliderArrays, g: GridSpec, x: wp.vec3, max_dist: float, side: wp.vec3):
    """Closest surface point within max_dist (-1 body if none) and the unit direction
    from it to x: a particle's from its cell's list of triangles on static colliders
    (face_cells.py), else from the BVH, where a tight bound prunes the search.

    On the surface itself (closer than ON_SURFACE cells) the direction is float32 noise
    and the face normal stands in. On an open sheet, or a mesh wound inwards, that
    normal may point to either side, so it is turned to agree with ``side``: the
    direction the point had before (its remembered color, Eq. 21), or minus its motion.
    A zero ``side`` (a node) keeps the face normal as it is."""
    c = Color()
    c.body = -1
    face = int(NO_LIST)
    point = wp.vec3(0.0)
    # a particle's query on static colliders (bounded by PARTICLE_BAND cells, never a node's
    # NODE_BAND): the per-cell lists give the BVH's answer, cheaper (face_cells.py). Nodes keep
    # the BVH: a node equidistant from two rims (the middle of a slit a fine cell wide) takes
    # whichever the search meets first, and the lists' choice moved such a slit's flow by 15%
    if colliders.cells.enabled != 0 and max_dist <= colliders.cells.band and max_dist < NODE_BAND * g.dx:
        face, point = closest_face(colliders.cells, colliders.mesh, x, max_dist)
    if face == NO_LIST:
        face = -1
        q = wp.mesh_query_point_no_sign(colliders.mesh, x, max_dist)
        if q.result:
            face = q.face
            point = wp.mesh_eval_position(colliders.mesh, q.face, q.u, q.v)
    if face >= 0:
        c.surface_point = point
        d = x - c.surface_point
        dl = wp.length(d)
        if dl > ON_SURFACE * g.dx:
            c.surface_side = d / dl
        else:
            c.surface_side = wp.mesh_eval_face_normal(colliders.mesh, face)
            if wp.dot(c.surface_side, side) < 0.0:
                c.surface_side = -c.surface_side
        c.body = colliders.face_body[face]
        c.face = face
        c.flat = int(wp.abs(wp.dot(c.surface_side, wp.mesh_eval_face_normal(colliders.mesh, face))) > FLAT)
    return c


@wp.struct
class Crossing:
    hit: int
    x: wp.vec3  # where the particle stops
    n: wp.vec3  # surface normal facing the particle's side
    body: int


@wp.func
def first_hit(colliders: ColliderArrays, g: GridSpec, start: wp.vec3, end: wp.vec3, carry: wp.vec3):
    """The stop of a motion from ``start`` to ``end`` (in the collider's frame) at the
    first surface it crosses, if any (``stop_crossing``)."""
    out = Crossing()
    out.hit = 0
    seg = end - start
    L = wp.length(seg)
    if L < 1.0e-9 * g.dx:
        return out
    dirn = seg / L
    # The ray reaches STOP_GAP cells past the end point: a step that ends within
    # round-off past a surface (or just short of it) is stopped like any other, so
    # the float32 intersection test can never let an end point slip through.
    q = wp.mesh_query_ray(colliders.mesh, start, dirn, L + STOP_GAP * g.dx)
    if q.result:
        out.hit = 1
        out.n = q.normal
        if wp.dot(q.normal, dirn) > 0.0:
            out.n = -q.normal
        # Stop on the path before the hit, STOP_GAP cells from the surface measured
        # along its normal: a grazing particle stops that far back along its path, so
        # it never ends inside the on-surface zone where its side would be ambiguous.
        # The stop lies between the start (on the particle's side) and the first hit,
        # so it is on the particle's side of every surface.
        cos_hit = wp.max(-wp.dot(out.n, dirn), 1.0e-3)
        out.x = start + wp.max(q.t - STOP_GAP * g.dx / cos_hit, 0.0) * dirn + carry
        out.body = colliders.face_body[q.face]
    return out


@wp.func
def stop_crossing(colliders: ColliderArrays, g: GridSpec, x_old: wp.vec3, x_new: wp.vec3, dt: float, surface_body: int,
                  surface_side: wp.vec3):
    """Continuous collision: if the particle's motion relative to the collider crosses a
    surface, stop it just before the hit, on its own side."""
    # The mesh stands where it is at the start of the step (time t), so the motion is
    # tested in its frame: from x_old to x_new less the body's motion over the step,
    # and a stop is carried along with the body.
    carry = wp.vec3(0.0)
    start = x_old
    if surface_body >= 0:
        carry = dt * rigid_velocity(colliders.bodies[surface_body], x_old)
        start = start + (RAY_BACKOFF * g.dx) * surface_side  # off the surface, on the particle's own side
    out = first_hit(colliders, g, start, x_new - carry, carry)
    out.x = wp.where(out.hit != 0, out.x, x_new)
    # The ray from the backed-off start is not the particle's path: moving along its
    # surface and into it, the path can cross the surface next to a rim where that ray
    # passes through the hole (found at b = 3: a particle 5e-5 m from a letter panel,
    # moving 4e-4 m mostly along it, crossed 4e-5 m from a letter's edge). The path
    # itself is cast too, up to the end the first ray allows, and a hit on it stops the
    # particle there. (Cast to x_new instead, it would pin a particle resting within
    # STOP_GAP of a surface wherever its motion leans into it, sliding or not: stuck
    # there while the fluid around it flows, its J fell to 0.55 on a plate at b = 3.)
    if surface_body >= 0 and wp.dot(x_new - carry - x_old, surface_side) < 0.0:
        on_path = first_hit(colliders, g, x_old, out.x - carry, carry)
        if on_path.hit != 0:
            out = on_path
    return out


@wp.kernel
def color_particles(first: int, x: wp.array(dtype=wp.vec3), level: wp.array(dtype=wp.int32), id: wp.array(dtype=wp.int32),
                     min_id: int, colliders: ColliderArrays, g: GridSpec, f: ColorField,
                     surface_point: wp.array(dtype=wp.vec3), surface_side: wp.array(dtype=wp.vec3), surface_body: wp.array(dtype=wp.int32)):
    # the particles of this grid's level with an id from min_id on (after a split: its children)
    p = wp.tid() + first
    if level[p] != g.level or id[p] < min_id:
        return
    c = Color()
    c.body = -1
    if colliders.cpic != 0 and near_surface(f, g, x[p]):
        side = wp.vec3(0.0)
        if surface_body[p] >= 0:
            side = surface_side[p]  # keep the side it had (a split child keeps its parent's)
        c = color_point(colliders, g, x[p], PARTICLE_BAND * g.dx, side)
    surface_point[p] = c.surface_point
    surface_side[p] = c.surface_side
    surface_body[p] = c.body


@wp.func
def rim_distance(colliders: ColliderArrays, g: GridSpec, col: Color):
    """How far the surface around a node's closest point is one plane: the distance
    from it to the nearest rim or crease of a static collider, at most RIM_REACH cells
    (0 where the point is on an edge, or the colliders move)."""
    if colliders.rims == wp.uint64(0) or col.flat == 0:
        return 0.0
    q = wp.mesh_query_point_no_sign(colliders.rims, col.surface_point, RIM_REACH * g.dx)
    if q.result:
        return wp.length(col.surface_point - wp.mesh_eval_position(colliders.rims, q.face, q.u, q.v))
    return RIM_REACH * g.dx


@wp.func
def color_node(colliders: ColliderArrays, g: GridSpec, f: ColorField, n: int, c: wp.vec3i):
    xi = node_position(g, c)
    col = color_point(colliders, g, xi, NODE_BAND * g.dx, wp.vec3(0.0))
    if col.body >= 0:
        f.dist[n] = wp.length(xi - col.surface_point)
        f.dir[n] = col.surface_side
        f.body[n] = col.body
        f.rim[n] = rim_distance(colliders, g, col)
        f.face[n] = col.face
    else:
        f.dist[n] = FAR
        f.dir[n] = wp.vec3(0.0)
        f.body[n] = -1
        f.rim[n] = 0.0
        f.face[n] = -1


@wp.kernel
def color_node_box(first: int, colliders: ColliderArrays, g: GridSpec, lo: wp.vec3i, shape: wp.vec3i, f: ColorField):
    # dense grid: the nodes of an index box, numbered along z, then y, then x
    t = first + wp.tid()
    node = wp.vec3i(lo[0] + t // (shape[1] * shape[2]), lo[1] + (t // shape[2]) % shape[1], lo[2] + t % shape[2])
    color_node(colliders, g, f, node_index(g, node[0], node[1], node[2]), node)


@wp.kernel
def color_node_range(first: int, colliders: ColliderArrays, g: GridSpec, f: ColorField):
    # sparse grid: a range of storage indices (whole blocks)
    n = first + wp.tid()
    color_node(colliders, g, f, n, node_coords(g, n))


@wp.kernel
def face_clearance(mesh: wp.uint64, rims: wp.uint64, clear: wp.array(dtype=float)):
    # the triangle lies in the ball of radius r around its centroid, so it is at least
    # the centroid's distance to the rims less r from every rim
    t = wp.tid()
    a, b, c = face_corners(mesh, t)
    m = (a + b + c) / 3.0
    r = wp.max(wp.length(a - m), wp.max(wp.length(b - m), wp.length(c - m)))
    clear[t] = 0.0
    q = wp.mesh_query_point_no_sign(rims, m, 1.0e10)
    if q.result:
        clear[t] = wp.max(0.0, wp.length(m - wp.mesh_eval_position(rims, q.face, q.u, q.v)) - r)
