"""The split of Eq. 15: a level-0 particle in the refined region becomes b^3 level-1
children on the F-deformed sub-lattice of its own cube (docs/method.md, "Split"):

    x_c = x_p + F_p d_k,   m_c = m_p / N_s,   V_c = V_p / N_s,
    v_c = v_p + C_p (x_c - x_p),   C, F and the history state copied.

Since sum_k d_k = 0, mass and linear momentum are conserved exactly (up to float32
rounding of the products). Children remember their parent's id (``family``). Each child
is then placed off its lattice point by its own jitter, the family's mean taken out, with
the lattice point's velocity (``child_jitter``): the texture of finest mode's sampling,
mass and momentum still Eq. 15's. The family moves as a whole where surface
reconstruction (sim/reconstruct.py) or a domain wall asks it to; ``Refiner.split``
(sim/refine.py) decides who splits and launches this.
"""

from __future__ import annotations

import warp as wp

from .colliders import ColliderArrays, stop_crossing
from .grid import GridSpec
from .materials import MaterialParams, carries_F
from .state import ParticleArrays

wp.set_module_options({"enable_backward": False})


# child spacings: a split child starts at least this far inside a domain wall, as close
# as the outermost particles of a fine lattice sampled at the wall come (the sampling
# jitter, geometry/sampling.py, moves them up to a quarter spacing each way)
WALL_GAP = wp.constant(0.25)


# child spacings: each child is jittered by up to +-CHILD_JITTER / 2 per axis about its
# lattice point, as geometry/sampling.py jitters the points of a fine lattice (its JITTER),
# so that split material has the texture of material sampled fine (a solid's less along the
# surface's normal near its surface: sim/reconstruct.py, ``flat_jitter``; docs/method.md,
# "Split children sampled as finest samples")
CHILD_JITTER = wp.constant(0.5)


def jitter_seed(seed: int) -> int:
    """The children's jitter stream of a scene's seed (a 31-bit mix: nearby seeds, other draws)."""
    return (int(seed) * 2654435761 + 7919) % (2**31 - 1)


@wp.func
def child_jitter(seed: int, key: int):
    """A child's offset from its lattice point, in child spacings: uniform in
    +-CHILD_JITTER / 2 per axis, from the scene's ``seed`` (``jitter_seed``) and ``key``
    (its parent's id and its place in the family: the same on every thread and device, and
    again after a merge and a new split)."""
    rng = wp.rand_init(seed, key)
    u = wp.vec3(wp.randf(rng), wp.randf(rng), wp.randf(rng))
    return CHILD_JITTER * (u - wp.vec3(0.5))


@wp.func
def wall_shift(g: GridSpec, centre: wp.vec3, Fp: wp.mat33, h: float, b: int):
    """How far a family centred at ``centre`` moves so that its children lie inside the
    domain walls. The coarse grid lets a particle sink a few tenths of its own cell
    into a wall, the fine grid only that part of a fine cell: children placed on such a
    parent's lattice start squeezed into the wall (J ~ 0.6 in a dam break at b = 3,
    where finest never goes below 0.71). Per axis the outermost child's lattice point lies
    (1/2 - 1/2b) h sum_j |F_kj| from the centre; it moves to WALL_GAP child spacings,
    WALL_GAP h / b sum_j |F_kj|, inside the wall (a child its jitter would take closer
    stops there, ``keep_off_walls``). Positions only: mass and momentum stay those of
    Eq. 15."""
    out = wp.vec3(0.0)
    for k in range(3):
        row = wp.abs(Fp[k, 0]) + wp.abs(Fp[k, 1]) + wp.abs(Fp[k, 2])
        reach = (0.5 - 0.5 / float(b)) * h * row
        gap = WALL_GAP * h / float(b) * row
        lo = g.domain_lo[k] + gap - (centre[k] - reach)
        hi = g.domain_hi[k] - gap - (centre[k] + reach)
        if lo > 0.0 and hi > lo:
            out[k] = lo
        elif hi < 0.0 and lo < hi:
            out[k] = hi
    return out


@wp.func
def keep_off_walls(g: GridSpec, x: wp.vec3, Fp: wp.mat33, h: float, b: int):
    """A child's position no nearer a domain wall than its family's outermost lattice point
    may come (``wall_shift``'s gap): its jitter does not take it into the wall layer."""
    out = x
    for k in range(3):
        gap = WALL_GAP * h / float(b) * (wp.abs(Fp[k, 0]) + wp.abs(Fp[k, 1]) + wp.abs(Fp[k, 2]))
        lo = g.domain_lo[k] + gap
        hi = g.domain_hi[k] - gap
        if hi > lo:
            out[k] = wp.clamp(x[k], lo, hi)
    return out


@wp.kernel
def split_particles(
    first_parent: int,  # this launch's first particle (sim/parallel.py)
    flag: wp.array(dtype=wp.int32), offset: wp.array(dtype=wp.int32), n_old: int, b: int, next_id: int,
    s: ParticleArrays, materials: wp.array(dtype=MaterialParams), colliders: ColliderArrays, g1: GridSpec,
    reconstruct: int, shift: wp.array(dtype=wp.vec3), flatten: wp.array(dtype=wp.vec3), seed: int,
):
    p = wp.tid() + first_parent
    if flag[p] == 0:
        return
    # read the parent before child 0 overwrites it
    xp = s.x[p]
    vp = s.v[p]
    Cp = s.C[p]
    Fp = s.F[p]
    ns = b * b * b
    # side of the parent's lattice cube: its rest side, deformed by F; a model that keeps
    # J outside F (a fluid: F stays I) has its cube's current side (J V0)^(1/3), so that
    # the children of a compressed parent tile the volume it fills, not its rest volume
    cube = s.volume[p]
    if not carries_F(materials[s.material[p]]):
        cube = cube * wp.abs(s.history[p])
    h = wp.pow(cube, 1.0 / 3.0)
    # surface reconstruction (Section 4.3): the whole family moves by shift[p];
    # velocities stay those of the lattice points, so mass and momentum are the split's
    family_shift = wp.vec3(0.0)
    if reconstruct != 0:
        family_shift = shift[p]
    family_shift = family_shift + wall_shift(g1, xp + family_shift, Fp, h, b)
    mc = s.mass[p] / float(ns)
    Vc = s.volume[p] / float(ns)
    parent = s.id[p]
    surface_body = s.surface_body[p]
    surface_side = s.surface_side[p]
    first = n_old + offset[p] * (ns - 1)
    # the children's jitter, less its family mean: the family's centre stays the lattice's,
    # so a merge gives the parent back where it was. Its part along the normal of the
    # reconstruction's smoothed surface falls continuously to 0 towards that surface
    # (sim/reconstruct.py, ``flat_jitter``): the envelope the reconstruction places stays
    # smooth, the texture along it is finest's, and round-off in the field moves a child by
    # round-off only
    u = wp.vec3(0.0)
    if reconstruct != 0:
        u = flatten[p]
    mean_jitter = wp.vec3(0.0)
    for c in range(ns):
        mean_jitter += child_jitter(seed, parent * ns + c)
    mean_jitter = mean_jitter / float(ns)
    for c in range(ns):
        q = p
        if c > 0:
            q = first + c - 1
        d = (wp.vec3(float(c // (b * b)), float((c // b) % b), float(c % b)) + wp.vec3(0.5)) / float(b) - wp.vec3(0.5)
        xc = xp + Fp * (h * d)
        s.v[q] = vp + Cp * (xc - xp)  # the APIC affine field at the child (Eq. 15 holds exactly)
        # placed off its lattice point by its jitter, with the point's velocity: mass and
        # momentum stay the split's
        off = Fp * ((h / float(b)) * (child_jitter(seed, parent * ns + c) - mean_jitter))
        xc = keep_off_walls(g1, xc + family_shift + off - wp.dot(off, u) * u, Fp, h, b)
        if colliders.cpic != 0 and surface_body >= 0:
            # A child is never placed across a collider from its parent: near a sheet
            # it stops on the parent's side (its velocity stays that of the lattice
            # point, so momentum is still exact).
            hit = stop_crossing(colliders, g1, xp, xc, 0.0, surface_body, surface_side)
            if hit.hit != 0:
                xc = hit.x
        s.x[q] = xc
        s.C[q] = Cp
        s.F[q] = Fp
        s.history[q] = s.history[p]
        s.surface_point[q] = s.surface_point[p]
        s.surface_side[q] = surface_side
        s.surface_body[q] = surface_body
        s.mass[q] = mc
        s.volume[q] = Vc
        s.material[q] = s.material[p]
        s.level[q] = 1
        s.id[q] = next_id + offset[p] * ns + c
        s.family[q] = parent
