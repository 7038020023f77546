"""Surface particle reconstruction (paper Section 4.3, Eqs. 16-20), measured.

Each case splits the same parents twice, with and without reconstruction, and
measures the children against geometry known outside the code: an analytic sphere,
an analytic sheared parallelepiped, and (for a fluid that has flowed) a plane fitted
to its free surface. Units: h = parent lattice spacing (dx / 2 at 8
particles per cell), fine cell = dx / b.

Roughness is the spread (standard deviation) of the outermost particle per bin of
the surface (per direction for the sphere, per column for a face). The issue's
bounds: reconstructed roughness <= 0.5 x the parents'; largest outward protrusion
of a child beyond the parent-level surface <= 0.25 fine cells; volume change < 1%;
mass exact; momentum to float32 round-off; centre of mass moves < 0.1 fine cells;
interior children (more than a coarse cell inside) do not move at all.
"""

import numpy as np
import pytest

from abmpm.bench.reconstruction import (DX, H, block_top_roughness, parents_of, settled, sheared_block, sphere_parents,
                                        sphere_roughness, tank_top_roughness)
from abmpm.bench.reconstruction import split_whole as split  # every parent split (the whole domain refined)
from abmpm.geometry.sampling import sample_body
from abmpm.scene import model as sm

B = 2
FINE = DX / B


def smoothed_volume(x: np.ndarray, mass: np.ndarray, density: float, lo, hi) -> float:
    """Volume inside the half-density level of the particles' mass, deposited on
    voxels of h/2 (cloud in cell) and smoothed by a Gaussian of sigma = h: wider than
    the parents' spacing and the children's, so parents and children are measured
    alike, and the half level of a smoothed step is where the step was."""
    from scipy import ndimage

    voxel = H / 2
    lo = np.asarray(lo, np.float64)
    dims = np.ceil((np.asarray(hi) - lo) / voxel).astype(int) + 2
    grid = np.zeros(dims)
    X = (x.astype(np.float64) - lo) / voxel - 0.5
    i0 = np.floor(X).astype(int)
    f = X - i0
    for corner in np.ndindex(2, 2, 2):
        w = np.prod(np.where(corner, f, 1 - f), axis=1)
        idx = np.clip(i0 + corner, 0, dims - 1)
        np.add.at(grid, (idx[:, 0], idx[:, 1], idx[:, 2]), w * mass)
    rho = ndimage.gaussian_filter(grid / voxel**3, sigma=H / voxel, mode="constant")
    return (rho >= 0.5 * density).sum() * voxel**3


def conservation_checks(parents, plain, recon, inside):
    m = parents["mass"].astype(np.float64)
    # mass: every child keeps the split's m_p / b^3 (bit-identical with or without)
    assert np.array_equal(recon["mass"], plain["mass"])
    assert recon["mass"].astype(np.float64).sum() == plain["mass"].astype(np.float64).sum()
    # momentum: velocities are the split's, so the totals agree to the last bit
    assert np.array_equal(recon["v"], plain["v"])
    P0 = (m[:, None] * parents["v"]).sum(axis=0)
    P = (recon["mass"][:, None].astype(np.float64) * recon["v"]).sum(axis=0)
    scale = (m * np.linalg.norm(parents["v"], axis=1)).sum()
    assert np.abs(P - P0).max() <= 1e-5 * scale  # float32 products (see test_adaptive)
    # centre of mass
    com0 = (m[:, None] * parents["x"]).sum(axis=0) / m.sum()
    mc = recon["mass"].astype(np.float64)
    com = (mc[:, None] * recon["x"]).sum(axis=0) / mc.sum()
    assert np.linalg.norm(com - com0) < 0.1 * FINE
    # interior children: bit-identical to the plain split
    fam_inside = np.isin(recon["family"], np.flatnonzero(inside))
    assert fam_inside.any()
    assert np.array_equal(recon["x"][fam_inside], plain["x"][fam_inside])


@pytest.fixture(scope="module")
def sphere():
    parents, _ = sphere_parents(0.3, 0.0, 7)
    water = sm.Fluid(name="m")
    return parents, split(parents, water, False), split(parents, water, True)


def test_sphere_roughness_protrusion_and_volume(sphere):
    parents, plain, recon = sphere
    c, R = np.array([0.5, 0.5, 0.5]), 0.3
    rough_p, rough_plain, rough_recon = (sphere_roughness(x, c) for x in (parents["x"], plain["x"], recon["x"]))
    print(f"sphere roughness / h: parents {rough_p / H:.3f}, plain split {rough_plain / H:.3f}, "
          f"reconstructed {rough_recon / H:.3f}")
    assert rough_recon <= 0.5 * rough_p
    assert 0.7 * rough_p <= rough_plain <= 1.3 * rough_p  # today's split carries the parents' roughness

    # protrusion: a child centre beyond the analytic sphere (the parents' mass surface)
    def protrusion(x):
        return (np.linalg.norm(x.astype(np.float64) - c, axis=1) - R).max() / FINE

    print(f"sphere protrusion / fine cell: plain {protrusion(plain['x']):.3f}, reconstructed {protrusion(recon['x']):.3f}")
    assert protrusion(recon["x"]) <= 0.25

    lo, hi = c - R - 4 * H, c + R + 4 * H
    v_parents = smoothed_volume(parents["x"], parents["mass"], 1000.0, lo, hi)
    v_plain = smoothed_volume(plain["x"], plain["mass"], 1000.0, lo, hi)
    v_recon = smoothed_volume(recon["x"], recon["mass"], 1000.0, lo, hi)
    print(f"sphere volume / analytic: parents {v_parents / (4 / 3 * np.pi * R**3):.4f}, "
          f"plain {v_plain / v_parents:.4f} x parents, reconstructed {v_recon / v_parents:.4f} x parents")
    assert abs(v_recon / v_parents - 1) < 0.01

    r_par = np.linalg.norm(parents["x"] - c, axis=1)
    conservation_checks(parents, plain, recon, inside=r_par < R - DX)


def test_sphere_off_the_nodes_at_b3():
    """The case outside the suite that read 0.54-0.62 of the parents' roughness (issue
    26): a fluid sphere 6 coarse cells in radius, its centre 0.26 cells off a node, split
    whole at b = 3. Aiming each family's outermost child (not its centre) half a fine layer
    deep brought 48 such spheres (radius 4-7 cells, b = 2 and 3, on and off the nodes,
    three seeds) from 0.32-0.62 to 0.19-0.42 (docs/method.md); the bound is the issue's 0.5."""
    parents, centre = sphere_parents(0.3, 0.26, 1)
    recon = split(parents, sm.Fluid(name="m"), True, b=3)
    ratio = sphere_roughness(recon["x"], centre) / sphere_roughness(parents["x"], centre)
    print(f"sphere off the nodes, b = 3: roughness {ratio:.3f} x the parents'")
    assert ratio <= 0.5


def test_sheared_block_top_face():
    parents, A, (lo, hi) = sheared_block()
    jelly = sm.Elastic(name="m", youngs_modulus=1e5)
    plain, recon = split(parents, jelly, False), split(parents, jelly, True)
    # the top face: y0 = hi[1] in the rest frame, outward normal A^-T e_y
    Ainv = np.linalg.inv(A)

    def rest(x):
        return (x.astype(np.float64) - 0.5) @ Ainv.T

    rp, rplain, rrecon = (block_top_roughness(x, A, lo, hi) for x in (parents["x"], plain["x"], recon["x"]))
    print(f"sheared top face roughness / h: parents {rp / H:.3f}, plain {rplain / H:.3f}, reconstructed {rrecon / H:.3f}")
    assert rrecon <= 0.5 * rp

    # protrusion beyond the analytic parallelepiped (all six faces), in fine cells
    def protrusion(x):
        r = rest(x)
        normals = np.linalg.norm(Ainv, axis=1)  # |grad of rest coordinate a| = length of row a of A^-1
        out = np.maximum((r - hi) / normals, (lo - r) / normals)  # distance beyond each face pair
        return out.max() / FINE

    print(f"sheared protrusion / fine cell: plain {protrusion(plain['x']):.3f}, reconstructed {protrusion(recon['x']):.3f}")
    assert protrusion(recon["x"]) <= 0.25

    r_par = rest(parents["x"])
    # more than a coarse cell from every face in the world (a rest distance d is at
    # least d / 1.11 in the world: the longest row of A^-1)
    inside = np.all((r_par > lo + 1.2 * DX) & (r_par < hi - 1.2 * DX), axis=1)
    conservation_checks(parents, plain, recon, inside)


def test_fluid_that_has_flowed():
    """Water dropped into a tank, sloshed and settled for 0.6 s in original mode: a
    disordered free surface, as when material that has flowed enters a region. Its top
    particle per column less a fitted quadratic (the slosh), ``tank_top_roughness``."""
    water = sm.Fluid(name="m", bulk_modulus=4e4, viscosity=0.5)
    parents, _ = settled(water)
    plain, recon = split(parents, water, False), split(parents, water, True)

    rp, rplain, rrecon = (tank_top_roughness(x) for x in (parents["x"], plain["x"], recon["x"]))
    print(f"settled fluid top roughness / h: parents {rp / H:.3f}, plain {rplain / H:.3f}, reconstructed {rrecon / H:.3f}")
    assert rrecon <= 0.5 * rp

    # more than a coarse cell below the free surface (the lowest top of the column and
    # its neighbours), and from the floor and the walls
    from scipy import ndimage

    y, xz = parents["x"][:, 1].astype(np.float64), parents["x"][:, [0, 2]]
    cols = np.floor(xz / DX).astype(int)
    top = np.full((cols.max() + 1,) * 2, -np.inf)
    np.maximum.at(top, (cols[:, 0], cols[:, 1]), y)
    low = ndimage.minimum_filter(np.where(np.isfinite(top), top, 0.0), size=3)
    inside = (y < low[cols[:, 0], cols[:, 1]] - 1.2 * DX) & (y > 1.2 * DX)
    inside &= np.all((xz > 1.2 * DX) & (xz < 0.6 - 1.2 * DX), axis=1)
    conservation_checks(parents, plain, recon, inside)


@pytest.mark.parametrize("cells", [3, 4])
def test_small_spheres_keep_their_volume(cells):
    """The smoothed surface of a small body lies inside the true one (by about the
    kernel's width^2 / radius); the local mean move is taken out so that it does not
    shrink (without that a sphere of 3 cells' radius lost 2.9% of its volume)."""
    R, c = cells * DX, np.array([0.5, 0.45, 0.5])
    x = sample_body(sm.SphereBody(material="m", center=tuple(c), radius=R), sm.SimulationSettings(dx=DX),
                    np.random.default_rng(0))
    parents = parents_of(x, 1000.0)
    recon = split(parents, sm.Elastic(name="m", youngs_modulus=3e4), True)
    lo, hi = c - R - 4 * H, c + R + 4 * H
    v_parents = smoothed_volume(parents["x"], parents["mass"], 1000.0, lo, hi)
    v_recon = smoothed_volume(recon["x"], recon["mass"], 1000.0, lo, hi)
    assert abs(v_recon / v_parents - 1) < 0.01


def test_reconstruct_false_is_the_plain_split(sphere):
    parents, plain, _ = sphere
    again = split(parents, sm.Fluid(name="m"), False)
    assert all(np.array_equal(again[k], plain[k]) for k in plain)


def test_walls_and_floor_are_not_a_free_surface():
    # Water filling a corner of the domain (resting on the floor, against two walls):
    # reconstruction acts at the free surface only. Families against a wall or the
    # floor keep the plain split's places exactly: the wall bounds the material, there
    # is nothing to reconstruct (the mass field is mirrored across the wall). Before,
    # they were moved by up to 0.8 h.
    settings = sm.SimulationSettings(dx=DX)
    body = sm.BoxBody(material="m", min=(0.0, 0.0, 0.0), max=(0.4, 0.4, 0.4))
    x = sample_body(body, settings, np.random.default_rng(3))
    parents = parents_of(x, 1000.0, v=np.zeros((len(x), 3)), C=np.zeros((len(x), 3, 3)))
    water = sm.Fluid(name="m")
    plain, recon = split(parents, water, False), split(parents, water, True)
    moved = np.linalg.norm(recon["x"] - plain["x"], axis=1)
    xc = plain["x"]
    # children whose family lies within a coarse cell of a wall and two coarse cells
    # (beyond the surface test's reach) from the free faces at 0.4
    fam = recon["family"]
    px = parents["x"][fam]
    at_wall = (px.min(axis=1) < DX) & (px.max(axis=1) < 0.4 - 2 * DX)
    assert at_wall.sum() > 100
    assert moved[at_wall].max() == 0.0, moved[at_wall].max() / H
    # the free faces still are reconstructed (the test can tell moved from unmoved)
    top = px[:, 1] > 0.4 - H
    assert moved[top].max() > 0.0
    assert np.isfinite(xc).all()
