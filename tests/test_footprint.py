"""A level-0 particle's footprint on the fine grid (sim/footprint.py): the weights
against the moments that Eqs. 8-10 rely on, and lattices of coarse particles against
the same material sampled fine, in the bulk, at the level interface and at a wall.
The footprint is the mean of the particle's b^3 children's quadratic B-splines, so
these are exact identities; the tolerances are float32 round-off."""

import numpy as np
import pytest
import warp as wp

from abmpm.sim.footprint import footprint, footprint_weights, stress_weight
from abmpm.sim.grid import GridSpec

DIMS = 40


@wp.kernel
def _moments(g: GridSpec, x: wp.array(dtype=wp.vec3), volume: float, out: wp.array2d(dtype=float)):
    # per particle: sum W, sum W r (3), sum W r_a r_a (3) in cells, sum of the stress
    # weights (3) and sum of g_a r_a (3), in cells
    p = wp.tid()
    fp = footprint_weights(g, x[p], footprint(g, x[p], volume))
    X = (x[p] - g.origin) * g.inv_dx
    for i in range(fp.nodes):
        for j in range(fp.nodes):
            for k in range(fp.nodes):
                w = fp.wx[i] * fp.wy[j] * fp.wz[k]
                s = stress_weight(fp, i, j, k, g.inv_dx) * g.dx
                r = wp.vec3(float(fp.base[0] + i), float(fp.base[1] + j), float(fp.base[2] + k)) - X
                out[p, 0] += w
                for a in range(3):
                    out[p, 1 + a] += w * r[a]
                    out[p, 4 + a] += w * r[a] * r[a]
                    out[p, 7 + a] += s[a]
                    out[p, 10 + a] += s[a] * r[a]


@wp.kernel
def _deposit(g: GridSpec, x: wp.array(dtype=wp.vec3), volume: float, field: wp.array3d(dtype=float),
             force: wp.array3d(dtype=wp.vec3)):
    # each particle's volume on the nodes, and its stress weights times its volume: the
    # nodes' force under a uniform unit pressure, up to sign
    p = wp.tid()
    fp = footprint_weights(g, x[p], footprint(g, x[p], volume))
    for i in range(fp.nodes):
        for j in range(fp.nodes):
            for k in range(fp.nodes):
                wp.atomic_add(field, fp.base[0] + i, fp.base[1] + j, fp.base[2] + k,
                              volume * fp.wx[i] * fp.wy[j] * fp.wz[k])
                wp.atomic_add(force, fp.base[0] + i, fp.base[1] + j, fp.base[2] + k,
                              volume * g.dx * stress_weight(fp, i, j, k, g.inv_dx))


def _grid(dx: float, b: int) -> GridSpec:
    g = GridSpec()
    g.dx, g.inv_dx = dx, 1.0 / dx
    g.origin = wp.vec3(0.0)
    g.dims = wp.vec3i(DIMS, DIMS, DIMS)
    g.domain_lo, g.domain_hi = wp.vec3(-1.0), wp.vec3(2.0)
    g.family = b
    return g


def _deposit_all(g: GridSpec, x: np.ndarray, volume: float):
    field = wp.zeros((DIMS, DIMS, DIMS), dtype=float, device="cpu")
    force = wp.zeros((DIMS, DIMS, DIMS), dtype=wp.vec3, device="cpu")
    wp.launch(_deposit, len(x), inputs=[g, wp.array(x, dtype=wp.vec3), volume, field, force], device="cpu")
    return field.numpy(), force.numpy()


def _coarse_lattice(b: int, x_lo: float, x_hi: float):
    # coarse particles (spacing h = b fine cells / 2) filling x_lo..x_hi (fine cells) along x
    # and 8..32 fine cells along y and z; their fine spacing and the points (m)
    dxf = 1.0 / DIMS
    h = b * dxf / 2
    cx = x_lo * dxf + (np.arange(int(round((x_hi - x_lo) * dxf / h))) + 0.5) * h
    c = (np.arange(int(round(24 * dxf / h))) + 0.5) * h + 8 * dxf
    return dxf, h, np.stack(np.meshgrid(cx, c, c, indexing="ij"), -1).reshape(-1, 3)


def _points_1d(k: np.ndarray, x: np.ndarray, weight: float):
    # volume and stress weight (4 r N, cells) on nodes k of points at x (cells), each ``weight``
    r = k[:, None] - x[None, :]
    a = np.abs(r)
    n = np.where(a < 0.5, 0.75 - a * a, np.where(a < 1.5, 0.5 * (1.5 - a) ** 2, 0.0))
    return weight * n.sum(axis=1), weight * (4 * r * n).sum(axis=1)


@pytest.mark.parametrize("b", [2, 3, 4])
def test_footprint_moments(b):
    # A coarse particle at 8 per cell (h = dx/2) on the grid of spacing dx/b: its b
    # children per axis sit (c + 1/2 - b/2)/2 fine cells from it. W sums to 1 (mass),
    # has zero first moment (momentum and affine momentum) and second moment 1/4 plus the
    # children's mean squared offset; the stress weights sum to zero (no net force from
    # a uniform stress) and their first moment is the identity (C of a linear velocity
    # field is its gradient), at any position.
    dxf = 1.0 / DIMS
    h = b * dxf / 2
    offsets = (np.arange(b) + 0.5 - b / 2) / 2
    rng = np.random.default_rng(1)
    x = (10 + 20 * rng.random((200, 3))) * dxf
    out = wp.zeros((200, 13), dtype=float, device="cpu")
    wp.launch(_moments, 200, inputs=[_grid(dxf, b), wp.array(x, dtype=wp.vec3), h**3, out], device="cpu")
    m = out.numpy()
    assert np.allclose(m[:, 0], 1.0, atol=1e-5)
    assert np.allclose(m[:, 1:4], 0.0, atol=1e-5)
    assert np.allclose(m[:, 4:7], 0.25 + np.mean(offsets**2), atol=1e-5)
    assert np.allclose(m[:, 7:10], 0.0, atol=1e-5)
    assert np.allclose(m[:, 10:13], 1.0, atol=1e-5)


@pytest.mark.parametrize("b", [2, 3, 4])
def test_a_lattice_of_footprints_is_the_material_sampled_fine(b):
    # Coarse particles on their lattice give every node one fine cell's volume and no
    # force under a uniform pressure, as the same material sampled fine does (the box
    # average with its MLS inertia, used until 2026-11-29, left 0.07 p dx'^2 on every
    # other node of the lattice at b = 3; points two cells apart at b = 4 gave the nodes
    # from 0.5^3 to 1.5^3 of the volume).
    dxf, h, x = _coarse_lattice(b, 8, 32)
    field, force = _deposit_all(_grid(dxf, b), x, h**3)
    assert np.allclose(field[14:26, 14:26, 14:26] / dxf**3, 1.0, atol=1e-4)
    assert np.allclose(force[14:26, 14:26, 14:26] / dxf**3, 0.0, atol=1e-4)


@pytest.mark.parametrize("b", [2, 3, 4])
def test_coarse_particles_meet_children_as_fine_material(b):
    # The level interface: coarse particles for x < X0 (a node plane), their children's
    # lattice (fine points half a fine cell apart) beyond it. Together they give the
    # nodes across the interface one cell's volume and no force under a uniform pressure
    # (points for the coarse particles gave the three nodes around X0 1.016, 1.0 and 0.984
    # of the volume and -0.078, +0.156, -0.078 p dx'^2 at b = 2, and the tank at rest a
    # current along its floor from the fine half into the coarse one).
    X0 = 20
    dxf, h, x = _coarse_lattice(b, X0 - 12, X0)
    field, force = _deposit_all(_grid(dxf, b), x, h**3)
    k = np.arange(14, 27, dtype=float)
    fine_v, fine_f = _points_1d(k, X0 + (np.arange(30) + 0.5) * 0.5, 0.5)
    along = field[14:27, 14:26, 14:26].mean(axis=(1, 2)) / dxf**3 + fine_v
    push = force[14:27, 14:26, 14:26, 0].mean(axis=(1, 2)) / dxf**3 + fine_f
    assert np.allclose(along, 1.0, atol=1e-4), along.round(4)
    assert np.allclose(push, 0.0, atol=1e-4), push.round(4)


@pytest.mark.parametrize("b", [2, 3, 4])
def test_footprints_up_to_a_wall_give_the_nodes_along_it_the_fine_volume(b):
    # Coarse particles on their lattice from a domain wall (the wall plane at fine node
    # WALL) give the fine nodes along it the volume and force the same material sampled
    # fine gives them (0.016, 0.5, 0.984, 1 of a cell's volume from the node beyond the
    # plane on), exactly: their children would sit where the fine lattice's particles do.
    WALL = 8
    dxf, h, x = _coarse_lattice(b, WALL, WALL + 24)
    g = _grid(dxf, b)
    g.domain_lo = wp.vec3(WALL * dxf, -1.0, -1.0)
    field, force = _deposit_all(g, x, h**3)
    k = np.arange(WALL - 1, WALL + 5, dtype=float)
    fine_v, fine_f = _points_1d(k, WALL + (np.arange(80) + 0.5) * 0.5, 0.5)
    along = field[WALL - 1:WALL + 5, 14:26, 14:26].mean(axis=(1, 2)) / dxf**3
    push = force[WALL - 1:WALL + 5, 14:26, 14:26, 0].mean(axis=(1, 2)) / dxf**3
    assert np.allclose(along, fine_v, atol=1e-4), (along.round(4), fine_v.round(4))
    assert np.allclose(push, fine_f, atol=1e-4), (push.round(4), fine_f.round(4))
