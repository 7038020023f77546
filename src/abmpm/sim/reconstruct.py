"""Surface particle reconstruction (paper Section 4.3, Eqs. 16-20).

A parent split by Eq. 15 puts its b^3 children on the F-deformed sub-lattice of its
own cube. In the interior that is right. At the surface the parents' own sampling
jitter, the disorder of a fluid that has flowed, or an F that no longer matches the
particles' spacing, carries over to the children: a parent that sticks out gives a
bump of children, one that sits low a dent, and overlapping sub-lattices swell the
surface (the paper's Figure 5b). Reconstruction moves the children of the parents
that form the surface so that the children's envelope follows the parent-level
surface instead.

Our reading of the paper, with the decisions it leaves open (docs/method.md,
"Surface reconstruction"):

1. **Surface detection (Eq. 16).** Just before a split, every particle within three
   coarse cells of the refined region (both levels, so material split before counts)
   scatters its mass gradient m_p grad w_ip (G_i) and its volume V_p J w_ip to the
   coarse nodes. A parent is a *surface parent* when the node whose box Omega_i
   (one coarse cell, centred on the node) holds it has |G_i| > t_p (Eq. 18), with
   t_p = ``surface_threshold`` x rho_p dx^2 (the mass of a full coarse cell of the
   parent's material per dx).
2. **Parent-level surface (Eqs. 17, 19).** The level where the occupied fraction of
   space, interpolated from the node volumes after a light (1 6 1)/8 filter, is
   1/2: the material boundary of a uniform half-space, smooth on the scale of the
   coarse kernel, so the parents' jitter and a flowed fluid's disorder do not reach
   it. Its depth and inward direction at the parent, to first order:
   d_s = (phi - 1/2) / |grad phi| and N_s = grad phi / |grad phi|.
3. **Moving the children (Eq. 20).** The family of an *outermost* surface parent
   (no particle on top of it within a parent spacing) moves rigidly along N_s so
   that its outermost child lies half a fine lattice layer deep, where the outermost
   centres of a lattice sit on average (the layer spacing along N_s of the children's
   F-deformed lattice: a fine spacing on a face, less on an oblique cut). For
   materials with a deformation gradient the depth is taken onto the level set by
   Newton steps. Protruding families are pulled in, families in a dent pushed out
   (never by more than a spacing); lower layers, interior parents and lone droplets
   do not move. A rigid move keeps the family's sub-lattice (children are never
   projected onto one surface), and with the split's velocities (the parent's
   affine field about the family's centre) mass and momentum stay exactly those of
   Eq. 15.
4. **Keeping the volume.** The smoothed surface of a small or curved body lies
   inside the true one (by about kernel width^2 / radius). The mean move of the
   moving families within three coarse cells is taken out of each move, so the
   surface keeps its place on average and only the jitter goes.
"""

from __future__ import annotations

import warp as wp

from .grid import GridSpec, cell_flag, nearest_node_coords, node_index
from .materials import MaterialParams, carries_F, volume_ratio
from .parallel import EMPTY_BOUND, Reach, ThreadSums, add_thread_sums, widen_reach
from .state import ParticleArrays
from .stencil import bspline_weights, stencil_base, stencil_offset

wp.set_module_options({"enable_backward": False})

DEFAULT_SURFACE_THRESHOLD = 0.2  # t_p in units of (mass of a full coarse cell) / dx


@wp.struct
class SurfaceField:
    """Eq. 16 on the coarse grid: node masses and mass gradients of both levels."""

    enabled: int
    threshold: float  # t_p / (rho_p dx^2)
    grad: wp.array(dtype=wp.vec3)  # G_i of Eq. 16
    volume: wp.array(dtype=float)  # sum_p w_ip V_p J_p: the occupied volume at the node
    smooth: wp.array(dtype=float)  # the same, filtered once over the 27 neighbours
    near: wp.array3d(dtype=wp.int32)  # coarse cells near the refined region: who scatters
    read: wp.array3d(dtype=wp.int32)  # coarse cells whose nodes a splitting parent reads: smoothed


@wp.func
def bspline_slopes(fx: wp.vec3):
    # d/dfx of bspline_weights (rows: node offset 0,1,2; columns: axis), per cell
    return wp.matrix_from_rows(fx - wp.vec3(1.5), -2.0 * (fx - wp.vec3(1.0)), fx - wp.vec3(0.5))


@wp.func
def weight_gradient(w: wp.mat33, dw: wp.mat33, i: int, j: int, k: int):
    # grad of w_i = w(x) w(y) w(z) in cells^-1 (multiply by 1/dx for space)
    return wp.vec3(dw[i, 0] * w[j, 1] * w[k, 2], w[i, 0] * dw[j, 1] * w[k, 2], w[i, 0] * w[j, 1] * dw[k, 2])


# A particle this close to a wall (coarse cells) reaches nodes beyond it with its
# stencil (1.5 cells) and, through the (1 6 1)/8 filter, one node further.
WALL_REACH = wp.constant(2.5)


@wp.func
def scatter_image(g: GridSpec, grad: wp.array(dtype=wp.vec3), volume: wp.array(dtype=float), xp: wp.vec3, m: float,
                  vol: float, flip: wp.vec3):
    # one image of a particle: its mass gradient (Eq. 16) and volume on the coarse
    # nodes; ``flip`` is -1 on the axes it was mirrored across a wall, which mirrors
    # the gradient with it. Returns the storage span it reached.
    base = stencil_base(g, xp)
    fx = stencil_offset(g, xp, base)
    w = bspline_weights(fx)
    dw = bspline_slopes(fx)
    for i in range(3):
        for j in range(3):
            for k in range(3):
                n = node_index(g, base[0] + i, base[1] + j, base[2] + k)
                wp.atomic_add(grad, n, (m * g.inv_dx) * wp.cw_mul(flip, weight_gradient(w, dw, i, j, k)))
                wp.atomic_add(volume, n, vol * w[i, 0] * w[j, 1] * w[k, 2])
    return node_index(g, base[0], base[1], base[2]), node_index(g, base[0] + 2, base[1] + 2, base[2] + 2)


@wp.func
def mirrored(g: GridSpec, xp: wp.vec3, image: int, reach: float):
    # the image of xp across the walls named by the bits of ``image`` (bit d: the
    # nearer wall of axis d), or a sign 0 in the flip when the particle is not within
    # ``reach`` of that wall (no such image)
    x = xp
    flip = wp.vec3(1.0)
    for d in range(3):
        if (image >> d) & 1 != 0:
            lo = xp[d] - g.domain_lo[d]
            hi = g.domain_hi[d] - xp[d]
            if lo <= hi and lo < reach:
                x[d] = 2.0 * g.domain_lo[d] - xp[d]
                flip[d] = -1.0
            elif hi < lo and hi < reach:
                x[d] = 2.0 * g.domain_hi[d] - xp[d]
                flip[d] = -1.0
            else:
                flip[d] = 0.0
    return x, flip


@wp.kernel
def scatter_surface_mass(first: int, s: ParticleArrays, materials: wp.array(dtype=MaterialParams), g: GridSpec,
                         near: wp.array3d(dtype=wp.int32), grad: wp.array(dtype=wp.vec3),
                         volume: wp.array(dtype=float), reach: Reach):
    # Eq. 16: G_i = sum_p grad w_ip m_p, and beside it the occupied volume
    # sum_p w_ip V_p J_p (both levels: every particle belongs to the parent-level field).
    # A domain wall bounds the material, it is not a free surface: a particle near a
    # wall also scatters its mirror image across it (and across two or three walls in
    # an edge or a corner), so that beside a wall the field reads as if the material
    # went on, the mass gradient normal to the wall vanishes there and the smoothed
    # surface meets the wall at right angles. Without the images every family along
    # the walls and the floor of a tank at rest was moved by up to 0.8 of a spacing.
    # On the CPU each thread's part scatters into its own sums (``reach``: where),
    # which ``add_surface_sums`` adds in part order (sim/parallel.py).
    p = wp.tid() + first
    xp = s.x[p]
    if cell_flag(g, near, xp) == 0:
        return
    m = s.mass[p]
    vol = s.volume[p] * volume_ratio(materials[s.material[p]], s.F[p], s.history[p])
    lo = int(EMPTY_BOUND)
    hi = int(-1)
    for image in range(8):
        xi, flip = mirrored(g, xp, image, WALL_REACH * g.dx)
        if flip[0] * flip[1] * flip[2] != 0.0:
            a, b = scatter_image(g, grad, volume, xi, m, vol, flip)
            lo = wp.min(lo, a)
            hi = wp.max(hi, b)
    widen_reach(reach, lo, hi)


@wp.kernel
def add_surface_sums(first: int, count: int, chunk: int, sums: ThreadSums, f: SurfaceField):
    # the other CPU threads' parts of Eq. 16 into the field, before it is smoothed
    n0 = (wp.tid() + first) * chunk
    add_thread_sums(sums, n0, wp.min(n0 + chunk, count), f.grad, f.volume)


SIDE = wp.constant(0.125)  # filter weights per axis: (SIDE, 1 - 2 SIDE, SIDE)


@wp.func
def filter_weight(a: int):
    if a == 1:
        return 1.0 - 2.0 * SIDE
    return SIDE


@wp.kernel
def smooth_surface_volume(first: int, g: GridSpec, f: SurfaceField, lo: wp.vec3i, box: wp.vec3i):
    # (SIDE, 1 - 2 SIDE, SIDE)^3 filter of the node volumes, (1 6 1)/8 per axis: the
    # surface of a disordered material (a fluid that has flowed) follows its
    # particles' mean, not their noise; a wider filter shrinks curved surfaces. One
    # thread a node of the box [lo, lo + box) that holds every node a parent reads
    # (``Refiner.read_box``), not of the whole coarse grid (111k nodes on the paper
    # hourglass, ~2 ms a call for threads that returned at once)
    t = wp.tid() + first
    c = lo + wp.vec3i(t // (box[1] * box[2]), (t // box[2]) % box[1], t % box[2])
    n = node_index(g, c[0], c[1], c[2])
    shape = wp.vec3i(f.read.shape[0], f.read.shape[1], f.read.shape[2]) - wp.vec3i(1)
    if f.read[wp.min(c[0], shape[0]), wp.min(c[1], shape[1]), wp.min(c[2], shape[2])] == 0:
        return  # no parent reads it (family_shifts); left as it was
    acc = float(0.0)
    for a in range(3):
        for b in range(3):
            for e in range(3):
                i = wp.clamp(c[0] + a - 1, 0, g.dims[0] - 1)
                j = wp.clamp(c[1] + b - 1, 0, g.dims[1] - 1)
                k = wp.clamp(c[2] + e - 1, 0, g.dims[2] - 1)
                wgt = filter_weight(a) * filter_weight(b) * filter_weight(e)
                acc += wgt * f.volume[node_index(g, i, j, k)]
    f.smooth[n] = acc


@wp.func
def is_surface_parent(f: SurfaceField, g: GridSpec, xp: wp.vec3, rho_p: float):
    # Eq. 18: the parent lies in the box Omega_i of its nearest node i; Eq. 16's
    # |G_i| > t_p makes that node, and so the parent, part of the surface
    c = nearest_node_coords(g, xp)
    G = f.grad[node_index(g, c[0], c[1], c[2])]
    return wp.length(G) > f.threshold * rho_p * g.dx * g.dx


@wp.func
def covered(points: wp.uint64, x: wp.array(dtype=wp.vec3), p: int, out: wp.vec3, h: float):
    """Whether another particle lies on top of particle p: within a cylinder of
    radius 0.75 h from 0.5 h to 1.5 h along the outward normal ``out``."""
    xp = x[p]
    query = wp.hash_grid_query(points, xp, 1.7 * h)
    q = int(0)
    while wp.hash_grid_query_next(query, q):
        if q != p:
            d = x[q] - xp
            u = wp.dot(d, out)
            if u > 0.5 * h and u < 1.5 * h and wp.length(d - u * out) < 0.75 * h:
                return True
    return False


# Newton steps along N_s that take Eq. 17's first-order depth onto the level set phi = 1/2
# itself, for materials that keep a deformation gradient (solids, sand, snow): their
# particles keep an F-deformed lattice, and the first-order depth carries an error that
# depends on where that lattice sits against the coarse nodes, different from parent to
# parent. A fluid keeps no lattice, and phi at its surface point is made of fewer
# particles than at the parent: there the exact level set follows their noise, and the
# first-order depth from the parent is the smoother estimate (docs/method.md,
# "Surface reconstruction", has the measurements)
LEVEL_SET_STEPS = 2


@wp.func
def occupied_fraction(f: SurfaceField, g: GridSpec, x: wp.vec3):
    # phi (occupied fraction of space) and its gradient at x, interpolated from the
    # smoothed node volumes
    base = stencil_base(g, x)
    fx = stencil_offset(g, x, base)
    w = bspline_weights(fx)
    dw = bspline_slopes(fx)
    phi = float(0.0)
    grad = wp.vec3(0.0)
    for i in range(3):
        for j in range(3):
            for k in range(3):
                v = f.smooth[node_index(g, base[0] + i, base[1] + j, base[2] + k)]
                phi += w[i, 0] * w[j, 1] * w[k, 2] * v
                grad += v * weight_gradient(w, dw, i, j, k)
    cell = g.dx * g.dx * g.dx
    return phi / cell, grad * (g.inv_dx / cell)


# The children's jitter along the surface's normal (sim/split.py), for a material that keeps
# its lattice (a solid: carries_F), by the parent's depth below the smoothed surface in its
# spacings h: none within JITTER_FROM h (the outermost parents' centres lie about h / 2 deep),
# all of it from JITTER_FROM + JITTER_RAMP h (the next layer, about 3 h / 2 deep), linear
# between. Along the surface the jitter stays whole. A solid keeps the surface it is split
# with for the whole run; a fluid's children keep their whole jitter, finest's texture, which
# its flow soon replaces by its own disorder (docs/method.md, "Split children sampled as
# finest samples": flattening a fluid's too moved 4 of 26 plate cases out of 10% of finest).
JITTER_FROM = wp.constant(0.75)
JITTER_RAMP = wp.constant(0.5)


@wp.func
def flat_jitter(phi: float, grad: wp.vec3, slope: float, h: float, inv_dx: float):
    """The direction u along which a family's children lose part of their jitter: the
    smoothed surface's normal, scaled so that |u|^2 is the share of the jitter's normal
    part taken out (``split_particles`` takes out (j . u) u). From the first-order depth of
    the parent below the surface (Eq. 17); continuous in phi and its gradient, with no
    threshold, so float round-off in the field (another thread count adds its sums in
    another order) changes a child's place by round-off. Deep inside (phi flat at 1) 0.
    ``slope``: |grad phi|."""
    floor = wp.max(slope, 1.0e-3 * inv_dx)
    depth = (phi - 0.5) / floor
    share = wp.clamp((depth - JITTER_FROM * h) / (JITTER_RAMP * h), 0.0, 1.0)
    return wp.sqrt(1.0 - share) * (grad / floor)


@wp.kernel
def family_shifts(first: int, flag: wp.array(dtype=wp.int32), s: ParticleArrays, materials: wp.array(dtype=MaterialParams),
                  f: SurfaceField, g: GridSpec, b: int, points: wp.uint64, shift: wp.array(dtype=wp.vec3),
                  flatten: wp.array(dtype=wp.vec3)):
    """Rigid displacement of the family of each parent about to split (Eqs. 17-20,
    see the module docstring): an outermost family's outermost child goes half a fine
    layer inside the parent-level surface. Zero for interior parents, for lower layers (a
    family with another particle on top of it that sits too deep) and far from any
    surface. Beside it how the children's jitter is flattened along the surface
    (``flat_jitter``). Computed before the split, which overwrites the parents."""
    p = wp.tid() + first
    shift[p] = wp.vec3(0.0)
    flatten[p] = wp.vec3(0.0)
    if flag[p] == 0:
        return
    xp = s.x[p]
    J = volume_ratio(materials[s.material[p]], s.F[p], s.history[p])
    h = wp.pow(s.volume[p] * wp.abs(J), 1.0 / 3.0)  # current lattice spacing of the parent
    solid = carries_F(materials[s.material[p]])
    surface = is_surface_parent(f, g, xp, s.mass[p] / (s.volume[p] * J))
    if not solid and not surface:
        return  # an interior fluid parent: nothing to move, its children's jitter whole
    phi, grad = occupied_fraction(f, g, xp)
    slope = wp.length(grad)
    if solid:
        flatten[p] = flat_jitter(phi, grad, slope, h, g.inv_dx)
    if not surface:
        return
    # a surface takes phi from 1 to 0 over a few cells; a much flatter phi is noise
    if slope < 0.05 * g.inv_dx:
        return
    N = grad / slope  # N_s, inwards (Eq. 19)
    depth = (phi - 0.5) / slope  # d_s > 0 inside (Eq. 17, first order)
    # (within the surface layer: a deeper parent only needs to know that it is deep)
    if solid and wp.abs(depth) < g.dx:
        for _ in range(LEVEL_SET_STEPS):
            phi_s, grad_s = occupied_fraction(f, g, xp - depth * N)  # at the estimated surface point
            slope_s = wp.dot(grad_s, N)
            if slope_s > 0.05 * g.inv_dx:
                depth = depth + wp.clamp((phi_s - 0.5) / slope_s, -0.25 * g.dx, 0.25 * g.dx)
    if depth < -g.dx:
        return  # far outside the smoothed surface (a lone droplet): leave it
    # The outermost centres of a lattice cut by a plane sit on average half a layer
    # spacing deep. The parent lattice is F h0 Z^3 (h0 = V0^(1/3), scaled by the J a
    # model keeps outside F); its heights along N are h0 m . u with u = F^T N, so its
    # layers are h0 |u| / |u/|u||_1 apart: h on a face, h / sqrt(3) on a (111) cut, and
    # the children's lattice (spacing h0 / b) has layers b times closer. The family's
    # outermost child lies h0 (1 - 1/b) |u|_1 / 2 out from its centre (the sub-lattice's
    # corner along N), so aiming that child half a fine layer deep puts the centre
    # ``target`` deep: a face's families as before (half a layer), an oblique cut's
    # deeper, so that a family's corner no longer sticks out of a curved surface.
    u = wp.transpose(s.F[p]) * N
    ul = wp.length(u)
    u1 = wp.abs(u[0]) + wp.abs(u[1]) + wp.abs(u[2])
    h0 = wp.pow(s.volume[p] * wp.abs(J / wp.determinant(s.F[p])), 1.0 / 3.0)
    layer = h0 * ul * ul / u1
    bf = float(b)
    target = 0.5 * layer / bf + 0.5 * (1.0 - 1.0 / bf) * h0 * u1
    gap = target - depth  # > 0: the family sits too far out by gap; < 0: too deep
    if gap < -layer or (gap < 0.0 and covered(points, s.x, p, -N, h)):
        return  # a lower layer: the family on top of it forms the surface
    shift[p] = wp.clamp(gap, -h, h) * N  # Eq. 20; a family never moves by more than a spacing


# The mean below is continuous in the particles' positions and moves, so that float
# round-off (another thread count adds its sums in another order) changes it by round-off:
# a neighbour's weight tapers to 0 over the last TAPER of the radius (parents on their
# lattice points lie at the radius exactly), and a family counts as moving in proportion to
# its move up to MOVING x the radius (a surface family of a lattice sits where the
# reconstruction would put it, its move ~0, and round-off decides whether it moves at all)
TAPER = wp.constant(0.25)
MOVING = wp.constant(1.0e-3)


@wp.func
def moving_share(s: wp.vec3, radius: float):
    return wp.min(wp.length(s) / (MOVING * radius), 1.0)


@wp.kernel
def keep_volume(first: int, flag: wp.array(dtype=wp.int32), x: wp.array(dtype=wp.vec3), points: wp.uint64, radius: float,
                shift: wp.array(dtype=wp.vec3), out: wp.array(dtype=wp.vec3)):
    """Take out of each family's move the mean move of the moving families within
    ``radius`` (along its own direction; weights above): what remains is the jitter the
    move removes, and the surface keeps its place on average. The smoothed surface of a
    small or curved body lies inside the true one (by ~ kernel width^2 / radius);
    without this a sphere of 3 cells' radius lost 3% of its volume."""
    p = wp.tid() + first
    sp = shift[p]
    out[p] = sp
    if flag[p] == 0 or wp.length(sp) == 0.0:
        return
    N = wp.normalize(sp)
    total = float(0.0)
    count = float(0.0)
    query = wp.hash_grid_query(points, x[p], radius)
    q = int(0)
    while wp.hash_grid_query_next(query, q):
        sq = shift[q]
        r = wp.length(x[q] - x[p]) / radius
        if flag[q] != 0 and r < 1.0:
            wgt = wp.min((1.0 - r) / TAPER, 1.0) * moving_share(sq, radius)
            total += wgt * wp.dot(sq, N)
            count += wgt
    out[p] = sp - moving_share(sp, radius) * (total / count) * N
