"""Particle order: by coarse cell (and by level first in adaptive mode), and where
each level's particles lie.

P2G and G2P touch memory coherently when neighbouring particles are neighbours in
storage; after a sort by (level, cell) each level of adaptive mode is one
contiguous range, and its transfers run over that range alone (equal work per CPU
thread, no pass over particles that would return at once).
"""

from __future__ import annotations

import warp as wp

from .grid import GridSpec
from .parallel import Launcher
from .state import DTYPES, FIELDS, ParticleArrays, ParticleState
from .stencil import stencil_base
from .time_levels import cell_of

wp.set_module_options({"enable_backward": False})

Ranges = dict  # level (None: every level) -> [(first, count), ...]


def sort_by_cell(state: ParticleState, coarse: GridSpec, by_level: bool, launcher: Launcher,
                 scratch: ParticleState | None, near: wp.array | None = None,
                 first: int = 0) -> tuple[ParticleState | None, int]:
    """Reorder particles ``first`` on by coarse cell, by level first if ``by_level``;
    with ``near`` (a flag per coarse cell) the level-0 particles outside it come first,
    the slow set of a time step per level (sim/time_levels.py). Returns the scratch copy
    used (reuse it next time) and how many particles are slow."""
    n = state.count - first
    if n <= 0:
        return scratch, 0
    device = launcher.device
    keys = wp.empty(2 * n, dtype=wp.int32, device=device)
    perm = wp.empty(2 * n, dtype=wp.int32, device=device)
    slow = wp.full(1, n, dtype=wp.int32, device=device)  # the first key beyond the slow group
    classes = near if near is not None else slow
    launcher.launch(_cell_keys, n, [state.x, state.level, int(by_level), coarse, classes, int(near is not None),
                                    first, keys, perm], start=first)
    wp.utils.radix_sort_pairs(keys, perm, n)
    if near is not None:  # one thread writes: Warp's CPU atomics are plain adds, unsafe across threads
        wp.launch(_group_end, n, inputs=[keys, coarse, slow], device=device)
    if scratch is None or scratch.capacity < state.count:
        scratch = ParticleState(**{name: wp.empty(state.capacity, dtype=DTYPES[name], device=device)
                                   for name in FIELDS})
    launcher.launch(_permute, n, [state.arrays(), perm, first, scratch.arrays()], start=first)
    for name in FIELDS:
        wp.copy(getattr(state, name), getattr(scratch, name), dest_offset=first, src_offset=first, count=n)
    return scratch, int(slow.numpy()[0]) if near is not None else 0


def level_ranges(state: ParticleState, levels: list[int], two_levels: bool, scratch: wp.array) -> Ranges:
    """Where each level's particles lie: ``{level: [(first, count)], None: ...}``. With
    two levels one small read from the device says whether the particles are
    partitioned by level (a sort by (level, cell) leaves them so) and where; if they
    are not, every level gets one range over all particles. ``scratch``: 2 int32."""
    n = state.count
    full = [(0, n)]
    ranges = {None: full, **{level: full for level in levels}}
    if not two_levels or n == 0:
        return ranges
    scratch.zero_()
    wp.launch(_level_partition, n, inputs=[state.level, scratch], device=scratch.device)
    level0, unordered = (int(v) for v in scratch.numpy())
    if unordered == 0:
        ranges = {0: [(0, level0)], 1: [(level0, n - level0)], None: [(0, level0), (level0, n - level0)]}
    return ranges


@wp.kernel
def _cell_keys(first: int, x: wp.array(dtype=wp.vec3), level: wp.array(dtype=wp.int32), by_level: int,
               g: GridSpec, near: wp.array(dtype=wp.int32), slow_first: int, origin: int,
               keys: wp.array(dtype=wp.int32), perm: wp.array(dtype=wp.int32)):
    # keys and perm of particle p at p - origin (the sorted part's first particle)
    p = wp.tid() + first
    q = p - origin
    b = stencil_base(g, x[p])
    key = (b[0] * g.dims[1] + b[1]) * g.dims[2] + b[2]
    if by_level != 0:
        group = level[p]
        if slow_first != 0:  # slow (level 0 outside ``near``), level 0, level 1
            group = group + 1
            if level[p] == 0 and near[cell_of(g, x[p])] == 0:
                group = 0
        key = key + group * g.dims[0] * g.dims[1] * g.dims[2]
    keys[q] = key
    perm[q] = p


@wp.kernel
def _group_end(keys: wp.array(dtype=wp.int32), g: GridSpec, end: wp.array(dtype=wp.int32)):
    # end[0]: the first sorted key of group 1 or later (the slow group's size); at most
    # one thread writes
    q = wp.tid()
    cells = g.dims[0] * g.dims[1] * g.dims[2]
    if keys[q] >= cells:
        if q == 0:
            end[0] = 0
        elif keys[q - 1] < cells:
            end[0] = q


@wp.kernel
def _level_partition(level: wp.array(dtype=wp.int32), out: wp.array(dtype=wp.int32)):
    # out[0]: level-0 particles; out[1]: places where a level-0 particle follows a
    # level-1 one (0 when the particles are partitioned by level). One thread on the CPU.
    p = wp.tid()
    if level[p] == 0:
        wp.atomic_add(out, 0, 1)
        if p > 0:
            if level[p - 1] != 0:
                wp.atomic_add(out, 1, 1)


@wp.kernel
def _permute(first: int, src: ParticleArrays, perm: wp.array(dtype=wp.int32), origin: int, dst: ParticleArrays):
    # dst[p] = src[perm[p - origin]], every field in one pass
    p = wp.tid() + first
    q = perm[p - origin]
    dst.x[p] = src.x[q]
    dst.v[p] = src.v[q]
    dst.C[p] = src.C[q]
    dst.F[p] = src.F[q]
    dst.history[p] = src.history[q]
    dst.surface_point[p] = src.surface_point[q]
    dst.surface_side[p] = src.surface_side[q]
    dst.surface_body[p] = src.surface_body[q]
    dst.mass[p] = src.mass[q]
    dst.volume[p] = src.volume[q]
    dst.material[p] = src.material[q]
    dst.level[p] = src.level[q]
    dst.id[p] = src.id[q]
    dst.family[p] = src.family[q]
