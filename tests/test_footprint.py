"""A level-0 particle's footprint on the fine grid (sim/footprint.py): the weights
against the moments that Eq. 8-10 rely on, and a lattice of boxes against a uniform
field. Exact identities of the box-averaged quadratic B-spline; the tolerances are
float32 round-off."""

import numpy as np
import pytest
import warp as wp

from abmpm.sim.footprint import footprint, footprint_weights
from abmpm.sim.grid import GridSpec

DIMS = 40


@wp.kernel
def _moments(g: GridSpec, x: wp.array(dtype=wp.vec3), volume: float, out: wp.array2d(dtype=float)):
    # per particle: sum W, sum W r (3), sum W r_a r_a (3) in cells, D^-1 diagonal (3)
    p = wp.tid()
    fp = footprint_weights(g, x[p], footprint(g, x[p], volume))
    X = (x[p] - g.origin) * g.inv_dx
    for i in range(fp.nodes):
        for j in range(fp.nodes):
            for k in range(fp.nodes):
                w = fp.wx[i] * fp.wy[j] * fp.wz[k]
                r = wp.vec3(float(fp.base[0] + i), float(fp.base[1] + j), float(fp.base[2] + k)) - X
                out[p, 0] += w
                for a in range(3):
                    out[p, 1 + a] += w * r[a]
                    out[p, 4 + a] += w * r[a] * r[a]
    for a in range(3):
        out[p, 7 + a] = fp.inertia_inv[a, a]


@wp.kernel
def _deposit(g: GridSpec, x: wp.array(dtype=wp.vec3), volume: float, field: wp.array3d(dtype=float)):
    p = wp.tid()
    fp = footprint_weights(g, x[p], footprint(g, x[p], volume))
    for i in range(fp.nodes):
        for j in range(fp.nodes):
            for k in range(fp.nodes):
                wp.atomic_add(field, fp.base[0] + i, fp.base[1] + j, fp.base[2] + k,
                              volume * fp.wx[i] * fp.wy[j] * fp.wz[k])


def _grid(dx: float) -> GridSpec:
    g = GridSpec()
    g.dx, g.inv_dx = dx, 1.0 / dx
    g.origin = wp.vec3(0.0)
    g.dims = wp.vec3i(DIMS, DIMS, DIMS)
    g.domain_lo, g.domain_hi = wp.vec3(-1.0), wp.vec3(2.0)  # far: no wall shrinks a box
    return g


@pytest.mark.parametrize("b", [3, 4])
def test_footprint_moments(b):
    # A coarse particle at 8 per cell (box h = dx/2) on the grid of spacing dx/b: the
    # half-width is a = b/4 fine cells. W sums to 1 (mass), has zero first moment
    # (momentum and affine momentum) and second moment 1/4 + a^2/3 (the D of MLS-MPM
    # whose inverse the stress uses), at any position.
    dxf = 1.0 / DIMS
    h = b * dxf / 2
    a = b / 4
    rng = np.random.default_rng(1)
    x = (10 + 20 * rng.random((200, 3))) * dxf
    out = wp.zeros((200, 10), dtype=float, device="cpu")
    wp.launch(_moments, 200, inputs=[_grid(dxf), wp.array(x, dtype=wp.vec3), h**3, out], device="cpu")
    m = out.numpy()
    assert np.allclose(m[:, 0], 1.0, atol=1e-5)
    assert np.allclose(m[:, 1:4], 0.0, atol=1e-5)
    assert np.allclose(m[:, 4:7], 0.25 + a * a / 3, atol=1e-5)
    assert np.allclose(m[:, 7:10], 1.0 / ((0.25 + a * a / 3) * dxf**2), rtol=1e-5)


@pytest.mark.parametrize("b", [3, 4])
def test_a_lattice_of_footprints_is_uniform(b):
    # Boxes that tile space give every node the same volume (one fine cell's), where
    # the same particles as points give the nodes from 0.5^3 to 1.5^3 of it at b = 4
    # (the product of the 1-D sums of points two cells apart): what the footprint is for.
    dxf = 1.0 / DIMS
    h = b * dxf / 2
    n = int(round(24 * dxf / h))
    c = (np.arange(n) + 0.5) * h + 8 * dxf
    x = np.stack(np.meshgrid(c, c, c, indexing="ij"), -1).reshape(-1, 3)
    field = wp.zeros((DIMS, DIMS, DIMS), dtype=float, device="cpu")
    wp.launch(_deposit, len(x), inputs=[_grid(dxf), wp.array(x, dtype=wp.vec3), h**3, field], device="cpu")
    inner = field.numpy()[14:26, 14:26, 14:26] / dxf**3
    assert np.allclose(inner, 1.0, atol=1e-4), (inner.min(), inner.max())


def _fine_points_1d(k: np.ndarray) -> np.ndarray:
    # the same material sampled fine from the wall plane (node 0) on: points half a fine
    # cell apart, each half a cell's volume, under the quadratic B-spline
    r = np.abs(k[:, None] - (np.arange(80) + 0.5) * 0.5)
    n = np.where(r < 0.5, 0.75 - r * r, np.where(r < 1.5, 0.5 * (1.5 - r) ** 2, 0.0))
    return 0.5 * n.sum(axis=1)


@pytest.mark.parametrize("b", [3, 4])
def test_boxes_up_to_a_wall_give_the_nodes_along_it_the_fine_volume(b):
    # Boxes that tile the material up to a domain wall (the wall plane at fine node
    # WALL, the first box's face on it) give the fine nodes along the wall the volume
    # the same material sampled fine gives them (0.016, 0.5, 0.984, 1 of a cell's from
    # the node beyond the plane on). Tolerance 0.01 of a cell's volume: a box and points
    # sample the same material differently (0.021 against 0.016 beyond the plane, 0.979
    # against 0.984 on the second node). A box cut half a cell inside the plane (the rule
    # until 2026-11-29) gave the second and third nodes 1.35 and 0.83 at b = 4 (1.17 and
    # 0.90 at b = 3), the lumps that squeezed the children in a tank's corner.
    dxf = 1.0 / DIMS
    h = b * dxf / 2
    WALL = 8
    n = int(round(24 * dxf / h))
    cx = WALL * dxf + (np.arange(n) + 0.5) * h
    c = (np.arange(n) + 0.5) * h + 8 * dxf
    x = np.stack(np.meshgrid(cx, c, c, indexing="ij"), -1).reshape(-1, 3)
    g = _grid(dxf)
    g.domain_lo = wp.vec3(WALL * dxf, -1.0, -1.0)
    field = wp.zeros((DIMS, DIMS, DIMS), dtype=float, device="cpu")
    wp.launch(_deposit, len(x), inputs=[g, wp.array(x, dtype=wp.vec3), h**3, field], device="cpu")
    along = field.numpy()[WALL - 1:WALL + 5, 14:26, 14:26].mean(axis=(1, 2)) / dxf**3
    expected = _fine_points_1d(np.arange(-1, 5, dtype=float))
    assert np.allclose(along, expected, atol=0.01), (along.round(3), expected.round(3))
