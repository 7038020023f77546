"""A particle's 3x3x3 quadratic B-spline stencil on one grid, and ``node_at``.

Every transfer starts the same way: the stencil's lowest node ``base``, the
particle's offset from it ``fx`` (in cells) and the weights ``w`` (paper Eq. 2 with
the quadratic B-spline). ``dense_stencil`` / ``sparse_stencil`` build it, and
``dense_node_at`` / ``sparse_node_at`` give the storage index of stencil node
(i, j, k): the same arithmetic for both storages, except that a sparse node may be
inactive (-1). A kernel made for one storage picks its pair at compile time
(``STORAGE[sparse]``): a run-time test of the storage inside the 27-node loops
cost ~10% of the CPU P2G.
"""

from __future__ import annotations

import warp as wp

from .grid import GridSpec, dense_node_index, node_index, stencil_node, stencil_slots, vec8i

wp.set_module_options({"enable_backward": False})


@wp.struct
class Stencil:
    base: wp.vec3i  # lowest node of the 3x3x3 stencil
    fx: wp.vec3  # particle position relative to ``base``, in cells
    w: wp.mat33  # weights: rows = node offset 0, 1, 2; columns = axis
    slots: vec8i  # sparse grids: slots of the (at most) 2x2x2 blocks the stencil spans


@wp.func
def bspline(r: float):
    # the 1D quadratic B-spline N(r), r in cells
    a = wp.abs(r)
    if a < 0.5:
        return 0.75 - a * a
    if a < 1.5:
        return 0.5 * (1.5 - a) * (1.5 - a)
    return 0.0


@wp.func
def bspline_weights(fx: wp.vec3):
    # Quadratic B-spline weights of the 3 nodes per axis; rows = node offset 0,1,2,
    # columns = axis. fx is the particle position relative to the base node, in cells.
    a = wp.vec3(1.5) - fx
    b = fx - wp.vec3(1.0)
    c = fx - wp.vec3(0.5)
    return wp.matrix_from_rows(0.5 * wp.cw_mul(a, a), wp.vec3(0.75) - wp.cw_mul(b, b), 0.5 * wp.cw_mul(c, c))


@wp.func
def stencil_base(g: GridSpec, x: wp.vec3):
    # Lowest node of the 3x3x3 stencil, clamped so that the whole stencil lies in the
    # grid for any x (a particle flung out of the domain, or NaN after a blow-up, must
    # never index outside the node storage; the run is stopped by the speed check).
    X = (x - g.origin) * g.inv_dx
    return wp.vec3i(
        wp.clamp(int(X[0] - 0.5), 0, g.dims[0] - 3),
        wp.clamp(int(X[1] - 0.5), 0, g.dims[1] - 3),
        wp.clamp(int(X[2] - 0.5), 0, g.dims[2] - 3),
    )


@wp.func
def stencil_offset(g: GridSpec, x: wp.vec3, base: wp.vec3i):
    X = (x - g.origin) * g.inv_dx
    return X - wp.vec3(float(base[0]), float(base[1]), float(base[2]))


@wp.func
def dense_stencil(g: GridSpec, x: wp.vec3):
    st = Stencil()
    st.base = stencil_base(g, x)
    st.fx = stencil_offset(g, x, st.base)
    st.w = bspline_weights(st.fx)
    return st


@wp.func
def sparse_stencil(g: GridSpec, x: wp.vec3):
    st = dense_stencil(g, x)
    st.slots = stencil_slots(g, st.base)  # one block-table lookup per block, not per node
    return st


@wp.func
def dense_node_at(g: GridSpec, st: Stencil, i: int, j: int, k: int):
    """Storage index of stencil node (i, j, k) of a dense grid."""
    return dense_node_index(g, st.base[0] + i, st.base[1] + j, st.base[2] + k)


@wp.func
def sparse_node_at(g: GridSpec, st: Stencil, i: int, j: int, k: int):
    """Storage index of stencil node (i, j, k) of a sparse grid; -1 where inactive."""
    return stencil_node(g, st.slots, st.base, i, j, k)


@wp.func
def weight_at(st: Stencil, i: int, j: int, k: int):
    # w_ip of Eq. 2, the product of the three axes' weights
    return st.w[i, 0] * st.w[j, 1] * st.w[k, 2]


@wp.func
def offset_at(g: GridSpec, st: Stencil, i: int, j: int, k: int):
    # x_i - x_p of stencil node (i, j, k)
    return (wp.vec3(float(i), float(j), float(k)) - st.fx) * g.dx


@wp.func
def stencil_touches_active(g: GridSpec, base: wp.vec3i):
    # sparse grids: the 3x3x3 stencil spans at most 2 blocks per axis, test their corners
    for a in range(2):
        for b in range(2):
            for c in range(2):
                if node_index(g, base[0] + 2 * a, base[1] + 2 * b, base[2] + 2 * c) >= 0:
                    return True
    return False


# storage -> (stencil, node_at), chosen at compile time: STORAGE[sparse]
STORAGE = {False: (dense_stencil, dense_node_at), True: (sparse_stencil, sparse_node_at)}
