"""Adaptive boundary MPM: split, two-grid transfers, modes (paper Sections 3.2,
4.2, 5.2). Tolerances are stated inline."""

import numpy as np
import pytest
import warp as wp
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

import abmpm
from abmpm.scene import model as sm
from abmpm.sim.colliders import PARTICLE_BAND
from abmpm.sim.materials import material_params
from abmpm.sim.solver import MPMSolver, SolverConfig
from abmpm.sim.split import CHILD_JITTER, child_jitter, jitter_seed
from abmpm.sim.state import ParticleState
from abmpm.simulation import init_warp

# --------------------------------------------------------------------------- split


def split_everything(x, v, C, F, mass, b, material=None, history=None, seed=0):
    """Run the split kernel on particles that all lie in a refined region (elastic unless
    ``material``; ``history``: the particles' history scalar, J for a fluid; ``seed``: the
    scene's, which draws the children's jitter)."""
    init_warp()
    solver = MPMSolver(SolverConfig((0, 0, 0), (1, 1, 1), 0.1, refine_factor=b, seed=seed),
                       [material_params(material or sm.Elastic(name="e"))], "cpu")
    n = len(x)
    arrays = {"x": x, "v": v, "C": C, "F": F, "mass": mass, "volume": mass / 1000.0}
    if history is not None:
        arrays["history"] = history
    state = ParticleState.from_numpy(arrays, "cpu")
    solver.reserve_ids(n)
    solver.set_region(np.ones(tuple(d - 1 for d in solver.grid.dims), dtype=bool), state)
    return state.numpy()


@wp.kernel
def jitter_of_keys(seed: int, keys: wp.array(dtype=int), out: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    out[i] = child_jitter(seed, keys[i])


def child_places(out, b):
    """Each split child's place c in its family (ids are given in family order) and its
    lattice point's offset d_c from the family's centre, in parent spacings (Eq. 15).
    ``out`` holds only children."""
    place = (out["id"] - out["id"].min()) % b**3
    d = (np.stack([place // (b * b), (place // b) % b, place % b], -1) + 0.5) / b - 0.5
    return place, d


def child_offsets(out, b):
    """Each split child's jitter less its family's mean, in child spacings and in the
    parent's undeformed frame (sim/split.py): what the split added to the child's
    lattice point. ``out`` holds only children, of parents split with full jitter."""
    ns = b**3
    place, _ = child_places(out, b)
    keys = wp.array((out["family"] * ns + place).astype(np.int32), dtype=int, device="cpu")
    jit = wp.zeros(len(keys), dtype=wp.vec3, device="cpu")
    wp.launch(jitter_of_keys, len(keys), [jitter_seed(0), keys, jit], device="cpu")  # split_everything's seed
    jit = jit.numpy().astype(np.float64)
    for f in np.unique(out["family"]):
        jit[out["family"] == f] -= jit[out["family"] == f].mean(axis=0)
    return jit


def random_particles(n, seed):
    """Positions, velocities, affine C, deformation F near identity and masses."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(0.2, 0.8, (n, 3)).astype(np.float32)
    v = rng.normal(0, 2.0, (n, 3)).astype(np.float32)
    C = rng.normal(0, 5.0, (n, 3, 3)).astype(np.float32)
    F = (np.eye(3) + rng.normal(0, 0.1, (n, 3, 3))).astype(np.float32)
    mass = rng.uniform(1e-4, 1e-2, n).astype(np.float32)
    return x, v, C, F, mass


@settings(max_examples=15, deadline=None)
@given(n=st.integers(1, 40), b=st.sampled_from([2, 3]), seed=st.integers(0, 2**31 - 1))
def test_split_conserves_mass_and_momentum(n, b, seed):
    x, v, C, F, mass = random_particles(n, seed)
    out = split_everything(x, v, C, F, mass, b)
    ns = b**3
    assert len(out["x"]) == n * ns and np.all(out["level"] == 1)
    M0, M = mass.astype(np.float64).sum(), out["mass"].astype(np.float64).sum()
    if b == 2:
        assert M == M0  # m/8 is exact in binary floating point: the sum is bit-exact
    else:
        assert abs(M - M0) <= 4 * np.finfo(np.float32).eps * M0  # m/27 rounds once per child
    P0 = (mass[:, None].astype(np.float64) * v).sum(axis=0)
    P = (out["mass"][:, None].astype(np.float64) * out["v"]).sum(axis=0)
    scale = (mass.astype(np.float64) * np.linalg.norm(v, axis=1)).sum()
    # sum_k d_k = 0 makes the affine terms cancel; float32 products leave ~1e-7 x
    # (|C| |F d| / |v| ~ 5 x 0.05 / 2) relative round-off per child
    assert np.abs(P - P0).max() <= 1e-5 * scale
    # every parent's children sit around it, with the family link back to it
    fam = out["family"]
    assert len(np.unique(fam)) == n and np.all(np.bincount(fam) [np.unique(fam)] == ns)


@pytest.mark.parametrize("b", [2, 3, 4])
def test_split_children_start_inside_the_domain_walls(b):
    # The coarse grid lets a particle sink a few tenths of a coarse cell into a wall,
    # the fine grid only that part of a fine cell. A parent split there used to put
    # its outermost children up to ~0.5 fine cells past the wall, where the fine wall
    # nodes squeezed them (J 0.60 in a dam break at b = 3; finest's least 0.71). Each
    # family now moves rigidly inside, its outermost child WALL_GAP child spacings from
    # the wall (as close as the jittered fine lattice comes); the children's
    # velocities, hence mass and momentum, stay those of the split; a family clear of
    # the walls does not move.
    from abmpm.sim.split import WALL_GAP
    h = 0.05  # the parent lattice spacing at dx = 0.1, 8 particles per cell
    x = np.array([[0.5, -0.01, 0.5], [0.5, 0.5, 1.004], [0.003, 0.02, 0.5], [0.5, 0.5, 0.5]], np.float32)
    rng = np.random.default_rng(3)
    v = rng.normal(0, 1.0, (4, 3)).astype(np.float32)
    C = rng.normal(0, 2.0, (4, 3, 3)).astype(np.float32)
    F = np.repeat(np.eye(3, dtype=np.float32)[None], 4, axis=0)
    F[2] = [[0.9, 0.1, 0.0], [0.0, 1.1, 0.0], [0.0, 0.0, 1.0]]  # a sheared parent
    mass = np.full(4, 1000.0 * h**3, np.float32)
    out = split_everything(x, v, C, F, mass, b)
    # the outermost child's offset per axis is (1/2 - 1/2b) h sum_j |F_kj|, the gap
    # WALL_GAP h / b sum_j |F_kj|: at least the smallest row sum (0.9 + 0.1) times it
    gap = WALL_GAP * h / b * 1.0
    assert out["x"].min() >= gap * (1 - 1e-4) and out["x"].max() <= 1.0 - gap * (1 - 1e-4)
    P0 = (mass[:, None].astype(np.float64) * v).sum(axis=0)
    P = (out["mass"][:, None].astype(np.float64) * out["v"]).sum(axis=0)
    assert np.abs(P - P0).max() <= 1e-5 * (mass * np.linalg.norm(v, axis=1)).sum()
    # each family keeps its lattice: the centre moved, each child within its jitter (at most
    # CHILD_JITTER child spacings from its lattice point, the family's mean taken out; a child
    # the wall's gap stopped only nearer its point) of the lattice point d_c
    jit = child_offsets(out, b)
    _, d = child_places(out, b)
    for k in range(4):
        fam = out["family"] == out["family"][np.argmin(np.linalg.norm(out["x"] - x[k], axis=1))]
        assert fam.sum() == b**3
        rel = (out["x"][fam] - out["x"][fam].mean(axis=0)) @ np.linalg.inv(F[k]).T / h
        assert np.abs(rel - d[fam]).max() <= CHILD_JITTER / b + 1e-4
        if k == 3:  # clear of the walls: exactly its lattice plus its jitter
            assert np.allclose(rel, d[fam] + jit[fam] / b, atol=1e-4)
    interior = out["x"][np.linalg.norm(out["x"] - x[3], axis=1) < h]
    assert np.allclose(interior.mean(axis=0), x[3], atol=1e-6)


@pytest.mark.parametrize("b", [2, 3, 4])
def test_a_compressed_fluid_parent_splits_into_the_volume_it_fills(b):
    # A fluid keeps its volume ratio J in ``history`` and F = I. Its children must tile the
    # volume the parent fills now, J V0, not its rest volume: placed on the rest lattice,
    # the children of water compressed to J = 0.75 against a plate stood 1 - 0.75^(1/3) = 9%
    # of a spacing too far apart per axis, overlapping the neighbouring families. Each
    # child keeps the parent's J and V0 / b^3, so the children's current volumes add up to
    # the parent's. Spacing checked to float32 round-off (1e-5 relative).
    h = 0.05  # rest lattice spacing at dx = 0.1, 8 particles per cell
    J = np.array([0.75, 1.0, 1.2], np.float32)
    x = np.array([[0.3, 0.5, 0.5], [0.5, 0.5, 0.5], [0.7, 0.5, 0.5]], np.float32)
    zeros = np.zeros((3, 3), np.float32)
    F = np.repeat(np.eye(3, dtype=np.float32)[None], 3, axis=0)
    mass = np.full(3, 1000.0 * h**3, np.float32)
    out = split_everything(x, zeros, np.zeros((3, 3, 3), np.float32), F, mass, b,
                           material=sm.Fluid(name="w"), history=J)
    for k in range(3):
        kids = out["family"] == out["family"][np.argmin(np.linalg.norm(out["x"] - x[k], axis=1))]
        assert kids.sum() == b**3 and np.allclose(out["history"][kids], J[k])
        side = h * J[k] ** (1 / 3)  # the cube the parent fills now; less the children's jitter
        points = out["x"][kids] - side / b * child_offsets(out, b)[kids]
        span = points.max(axis=0) - points.min(axis=0)  # (b - 1) child spacings
        assert np.allclose(span, (b - 1) / b * side, rtol=1e-5)
        assert np.allclose(out["x"][kids].mean(axis=0), x[k], atol=1e-6)
        assert np.isclose((out["volume"][kids] * out["history"][kids]).sum(), h**3 * J[k], rtol=1e-5)


@pytest.mark.parametrize("b", [2, 3, 4])
def test_region_blocks_lie_around_the_region(b):
    """The fine blocks a region asks for cover its cells' fine nodes and the stencil
    margin of 2 nodes, rounded out to whole 4-node blocks, and nothing more: on every
    axis the first active node lies 2-5 nodes before the region's first fine node and
    the last one 2-5 nodes after its last. Each grid's node 0 lies 3 of its own cells
    outside the domain, so coarse cell c starts at fine node c b - 3 (b - 1), not c b:
    with that shift left out the blocks went 3 (b - 1) fine nodes up every axis, and
    the level-0 particles on one side of a region moved with the fine grid, on the
    other with the coarse one (a symmetric drop onto a slit plate gained sideways
    momentum)."""
    init_warp()
    solver = MPMSolver(SolverConfig((0, 0, 0), (0.8, 0.8, 0.8), 0.1, refine_factor=b),
                       [material_params(sm.Elastic(name="e"))], "cpu")
    cells = np.zeros(tuple(d - 1 for d in solver.grid.dims), dtype=bool)
    lo_cell, hi_cell = np.array([5, 6, 7]), np.array([7, 8, 9])  # inclusive, coarse cell indices
    cells[lo_cell[0]:hi_cell[0] + 1, lo_cell[1]:hi_cell[1] + 1, lo_cell[2]:hi_cell[2] + 1] = True
    solver.set_region(cells)
    fine, coarse = solver.refiner.fine, solver.grid
    blocks = np.argwhere(fine.spec.blocks.numpy() >= 0)
    first, last = blocks.min(axis=0) * 4, blocks.max(axis=0) * 4 + 3  # active fine nodes
    # the region's first and last fine node, from positions (not indices)
    region_lo = coarse.origin + lo_cell * coarse.dx
    region_hi = coarse.origin + (hi_cell + 1) * coarse.dx
    node_lo = np.rint((region_lo - fine.origin) / fine.dx).astype(int)
    node_hi = np.rint((region_hi - fine.origin) / fine.dx).astype(int)
    assert np.all(node_lo - first >= 2) and np.all(node_lo - first <= 5), (first, node_lo)
    assert np.all(last - node_hi >= 2) and np.all(last - node_hi <= 5), (last, node_hi)


# --------------------------------------------------------------------------- modes


def jelly_scene(mode, boxes=(), reconstruct=True):
    return abmpm.Scene(
        simulation=abmpm.SimulationSettings(
            dx=0.05, fps=20, refinement={"mode": mode, "boxes": list(boxes), "reconstruct": reconstruct}),
        materials=[abmpm.Elastic(name="jelly", youngs_modulus=3e4)],
        bodies=[abmpm.SphereBody(material="jelly", center=(0.5, 0.45, 0.5), radius=0.15)],
    )


def kinetic_energy_curve(scene, frames=10):
    sim = abmpm.Simulation(scene, device="cpu")
    sim.advance(frames=frames)
    return np.array([h["kinetic_energy"] for h in sim.history]), sim


def test_adaptive_with_empty_region_is_the_original_run():
    ke_o, o = kinetic_energy_curve(jelly_scene("original"), frames=6)
    ke_a, a = kinetic_energy_curve(jelly_scene("adaptive"), frames=6)
    assert a.particles().level.max() == 0
    # nothing refined: the same kernels on the same grid, bit for bit
    assert np.array_equal(o.particles().by_id().x, a.particles().by_id().x)
    assert np.array_equal(ke_o, ke_a)


def test_adaptive_covering_the_domain_behaves_like_finest():
    # The split itself against finest. Surface reconstruction (on by default) moves
    # the outer families of this small jelly (3 coarse cells' radius) by ~0.27 h:
    # the bounce then differs from finest by 6.1% of the peak (docs/validation.md).
    whole = [((0, 0, 0), (1, 1, 1))]
    ke_a, a = kinetic_energy_curve(jelly_scene("adaptive", whole, reconstruct=False))
    ke_f, f = kinetic_energy_curve(jelly_scene("finest"))
    ke_o, _ = kinetic_energy_curve(jelly_scene("original"))
    assert np.all(a.particles().level == 1)
    # The same body in both (the sphere's exact volume shared by its particles at either
    # spacing; its lattice cubes read +0.8% and -0.4% of it): float32 sums of ~7k masses
    m_a, m_f = (float(s.particles().mass.astype(np.float64).sum()) for s in (a, f))
    assert m_a == pytest.approx(m_f, rel=1e-5) and m_f == pytest.approx(1000.0 * 4 / 3 * np.pi * 0.15**3, rel=1e-5)
    # Same fine grid, same particle spacing; differences come from the samples
    # (children of the coarse lattice vs a fresh fine lattice) and from the coarse grid
    # that also receives the mass. 5% of the peak kinetic energy, while the coarse run
    # differs from finest by more than that at impact.
    peak = ke_f.max()
    assert np.abs(ke_a - ke_f).max() < 0.05 * peak, np.round((ke_a - ke_f) / peak, 3)
    assert np.abs(ke_o - ke_f).max() > np.abs(ke_a - ke_f).max()


def test_elastic_block_slides_into_refined_region_as_one_body():
    scene = abmpm.Scene(
        simulation=abmpm.SimulationSettings(
            dx=0.05, fps=20, gravity=(0, 0, 0),
            refinement={"mode": "adaptive", "boxes": [((0.45, 0.0, 0.0), (1.0, 1.0, 1.0))]}),
        materials=[abmpm.Elastic(name="jelly", youngs_modulus=2e4)],
        bodies=[abmpm.BoxBody(material="jelly", min=(0.1, 0.4, 0.4), max=(0.3, 0.6, 0.6), velocity=(1.0, 0, 0))],
    )
    sim = abmpm.Simulation(scene, device="cpu")
    x0 = sim.particles().x
    nn, _ = cKDTree(x0).query(x0, k=2)
    radius = 1.05 * nn[:, 1].max()  # the block is one piece at this radius
    sim.advance(seconds=0.25)  # the front half has crossed into the refined region
    p = sim.particles()
    assert 0 < (p.level == 1).sum() < len(p.x)  # both levels present
    pairs = cKDTree(p.x).query_pairs(radius, output_type="ndarray")
    n, _ = connected_components(coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])),
                                           shape=(len(p.x), len(p.x))), directed=False)
    assert n == 1  # no gap opens at the level interface
    # nothing sticks at the interface: every particle still moves with the block
    # (1 m/s; 20%: the elastic block rings after the levels start to interact)
    assert np.all(np.abs(p.v[:, 0] - 1.0) < 0.2), np.abs(p.v[:, 0] - 1.0).max()


def test_fluid_through_refined_band_keeps_momentum():
    def run(mode):
        scene = abmpm.Scene(
            simulation=abmpm.SimulationSettings(
                dx=0.05, fps=20, refinement={"mode": mode, "boxes": [((0.0, 0.35, 0.0), (1.0, 0.55, 1.0))]}),
            materials=[abmpm.Fluid(name="water", bulk_modulus=5e4)],
            bodies=[abmpm.BoxBody(material="water", min=(0.35, 0.65, 0.35), max=(0.65, 0.85, 0.65))],
        )
        sim = abmpm.Simulation(scene, device="cpu")
        P = []
        # 0.3 s: the water's bottom has fallen through the band, it has not reached the floor
        sim.advance(seconds=0.3, callback=lambda s: P.append(s.diagnostics()["momentum"][1]))
        return np.array(P), sim
    P_o, _ = run("original")
    P_a, a = run("adaptive")
    assert a.particles().level.max() == 1  # it did pass through the band
    # before the water reaches the floor it falls freely through the band: the
    # two-grid transfer (Eqs. 8-12) must not add or remove momentum; 1% of |P|
    assert np.abs(P_a - P_o).max() < 0.01 * np.abs(P_o).max(), (P_a, P_o)


# --------------------------------------------------------------------------- narrow passage


def slit_scene(mode):
    """Water drains through a slit 1.25 coarse cells (3.75 fine cells at b = 3) wide."""
    dx, W, Z, yp = 0.04, 0.4, 0.16, 0.2
    slit = 1.25 * dx
    half = (W - slit) / 2
    plates = [sm.ThinBoxCollider(size=(half, 0.004, Z + 0.1), center=(half / 2, yp, Z / 2)),
              sm.ThinBoxCollider(size=(half, 0.004, Z + 0.1), center=(W - half / 2, yp, Z / 2))]
    return abmpm.Scene(
        simulation=abmpm.SimulationSettings(domain_max=(W, 0.5, Z), dx=dx, fps=10, max_dt=2e-3,
                                            walls={"type": "slip"},
                                            # the paper's detector: both plates refined whole, as the
                                            # bound below was set for (the feature criterion refines
                                            # the slit +- 2 cells only and drains 17% slower than finest)
                                            refinement={"mode": mode, "factor": 3, "criterion": "density"}),
        materials=[abmpm.Fluid(name="water", bulk_modulus=2e4)],
        bodies=[abmpm.BoxBody(material="water", min=(0, 0.24, 0), max=(W, 0.44, Z))],
        colliders=plates,
    ), yp


@pytest.mark.slow
def test_narrow_slit_adaptive_drains_like_finest_and_original_clogs():
    passed = {}
    for mode in ("original", "adaptive", "finest"):
        scene, yp = slit_scene(mode)
        sim = abmpm.Simulation(scene, device="cpu")
        M = sim.particles().mass.astype(np.float64).sum()
        series = []
        sim.advance(frames=8, callback=lambda s: series.append(
            s.particles().mass[s.particles().x[:, 1] < yp].astype(np.float64).sum() / M))
        passed[mode] = np.array(series)
    o, a, f = passed["original"][-1], passed["adaptive"][-1], passed["finest"][-1]
    # ordering: the coarse grid clogs the slit (or is much slower)
    assert o < 0.3 * f, passed
    # the bound: adaptive within 15% of finest at the end
    assert abs(a - f) < 0.15 * f, passed


# --------------------------------------------------------------------------- merge


@settings(max_examples=10, deadline=None)
@given(n=st.integers(1, 30), seed=st.integers(0, 2**31 - 1))
def test_merge_after_split_conserves_mass_and_momentum(n, seed):
    from abmpm.sim.refine import merge_families

    x, v, C, F, mass = random_particles(n, seed)
    children = split_everything(x, v, C, F, mass, 2)
    merged, k = merge_families(children, np.zeros(len(children["x"]), dtype=bool), 2)
    assert k == n and len(merged["x"]) == n and np.all(merged["level"] == 0)
    assert merged["mass"].astype(np.float64).sum() == mass.astype(np.float64).sum()  # m/8 x 8: exact
    P0 = (mass[:, None].astype(np.float64) * v).sum(axis=0)
    P = (merged["mass"][:, None].astype(np.float64) * merged["v"]).sum(axis=0)
    scale = (mass.astype(np.float64) * np.linalg.norm(v, axis=1)).sum()
    assert np.abs(P - P0).max() <= 1e-5 * scale  # float32 round-off of split and average
    # each family comes back as its parent: same id, centre of mass at the parent
    order = np.argsort(merged["id"])
    assert np.allclose(merged["x"][order], x, atol=1e-6)


def column_on_a_coarse_layer(colliders: list | None = None) -> abmpm.Scene:
    """A refined water column (b = 2, a box over x < 0.2 m) beside a coarse layer 0.1 m deep,
    which it collapses on to: children and coarse particles mix."""
    return abmpm.Scene(
        simulation=abmpm.SimulationSettings(
            domain_max=(0.8, 0.4, 0.2), dx=0.05, fps=30,
            refinement={"mode": "adaptive", "factor": 2, "boxes": [((0.0, 0.0, 0.0), (0.2, 0.4, 0.2))]}),
        materials=[sm.Fluid(name="water")],
        bodies=[sm.BoxBody(material="water", min=(0.0, 0.0, 0.0), max=(0.2, 0.3, 0.2)),
                sm.BoxBody(material="water", min=(0.2, 0.0, 0.0), max=(0.8, 0.1, 0.2))],
        colliders=colliders or [],
    )


def test_children_among_coarse_particles_move_with_the_coarse_grid():
    """The marks of ``Refiner.coarse_children`` against the rule computed here from the
    particles: a level-1 particle outside the zone beside the region (no collider here),
    whose coarse cell holds more level-0 than level-1 mass, moves with the coarse grid
    (ON_COARSE); every other child with the fine grid. The converse: a level-0 particle whose
    coarse cell holds more level-1 mass is marked AMONG_FINE, and the fine pass moves it
    (the mark's 1 bit) where its footprint's blocks are active. A refined water column collapses on to a
    coarse layer (children and coarse particles mix), then the region is taken away."""
    from abmpm.sim.grid import AMONG_FINE, ON_COARSE

    sim = abmpm.Simulation(column_on_a_coarse_layer(), device="cpu")
    sim.advance(frames=4)
    solver, state = sim.solver, sim._state
    solver.set_region(np.zeros(solver.region.shape, dtype=bool))
    solver.begin_segment(state, sim.time, 1e-4)
    a = state.numpy()
    solver.substep(state)  # marks each particle at its start
    mark = solver._on_fine.numpy()[:state.count]
    cell = np.clip(np.floor((a["x"] - solver.grid_origin) / solver.grid.dx).astype(int), 0,
                   np.array(solver.region.shape) - 1)
    flat = np.ravel_multi_index(cell.T, solver.region.shape)
    m = [np.bincount(flat[a["level"] == lv], a["mass"][a["level"] == lv], minlength=flat.max() + 1)
         for lv in (0, 1)]
    child = a["level"] == 1
    expect = child & (m[0][flat] > 0.5 * (m[0][flat] + m[1][flat]))
    assert np.array_equal(mark[child] == ON_COARSE, expect[child])
    assert 0 < expect.sum() < child.sum()  # both kinds are there
    among = ~child & (m[1][flat] > 0.5 * (m[0][flat] + m[1][flat]))
    assert np.array_equal((mark[~child] & AMONG_FINE) != 0, among[~child])
    assert 0 < among.sum() < (~child).sum()
    moved = (mark & 1) != 0  # the fine pass moves the marked ones whose footprint is whole
    assert not moved[~among].any()  # no collider, so no band particle beside the region
    assert moved[among].mean() > 0.9


def test_a_child_the_coarse_grid_moves_is_colored_on_the_coarse_grid():
    """A child carries a color within PARTICLE_BAND fine cells of a surface; the coarse grid's
    stencil reaches farther. A child marked ON_COARSE with no color but within the coarse
    band of a sheet is colored at the mark, so that its first coarse transfers keep to its
    side: refined water collapses under a sheet 0.2 m up (b = 2), and every such child reads
    the sheet's closest point (float32)."""
    from abmpm.sim.colliders import PARTICLE_BAND
    from abmpm.sim.grid import ON_COARSE

    lo, hi, y_sheet = np.array([0.3, 0.2, -0.05]), np.array([0.8, 0.2, 0.25]), 0.2  # the sheet's rectangle
    sim = abmpm.Simulation(column_on_a_coarse_layer(
        [sm.SheetCollider(size=(0.5, 0.3), center=(0.55, y_sheet, 0.1), refine=False)]), device="cpu")
    sim.advance(frames=8)  # the children reach under the sheet
    solver, state = sim.solver, sim._state
    solver.set_region(np.zeros(solver.region.shape, dtype=bool))
    solver.begin_segment(state, sim.time, 1e-4)
    before = state.numpy()["surface_body"].copy()
    solver.refiner.coarse_children(state, solver._on_fine, solver.collider_arrays, solver.grid.color, solver.cpic)
    a = state.numpy()
    mark = solver._on_fine.numpy()[:state.count]
    foot = np.clip(a["x"], lo, hi)  # the closest point of the sheet
    near = np.linalg.norm(a["x"] - foot, axis=1) < PARTICLE_BAND * 0.05 - 1e-3
    new = (a["level"] == 1) & (mark == ON_COARSE) & (before < 0) & near
    assert new.sum() > 20  # uncolored children in the coarse band, marked
    assert (a["surface_body"][new] == 0).all()
    assert np.allclose(a["surface_point"][new], foot[new], atol=1e-5)


def test_families_merge_back_after_leaving_the_region():
    scene = abmpm.Scene(
        simulation=abmpm.SimulationSettings(
            dx=0.05, fps=20,
            refinement={"mode": "adaptive", "merge": True, "boxes": [((0, 0.6, 0), (1, 0.75, 1))]}),
        materials=[abmpm.Elastic(name="jelly", youngs_modulus=3e4)],
        bodies=[abmpm.SphereBody(material="jelly", center=(0.5, 0.9, 0.5), radius=0.08)],
    )
    sim = abmpm.Simulation(scene, device="cpu")
    n0 = sim.particle_count
    m0 = sim.diagnostics()["total_mass"]
    levels, momentum = [], []

    def record(s):
        d = s.diagnostics()
        levels.append(d["count_per_level"])
        momentum.append(d["momentum"][1])
        # the frame's recorded figures (summary.json's) are its particles' (after the frame
        # end's merge: until 2026-11-27 they were taken before it and disagreed with the PLY)
        assert s.history[-1]["count_per_level"] == np.bincount(s.particles().level, minlength=2).tolist()

    sim.advance(frames=7, callback=record)  # falls through the band, not yet at the floor
    assert max(c[1] for c in levels) > 0  # it was refined in the band
    assert levels[-1] == [n0, 0]  # and merged back to the original particles below it
    assert sim.diagnostics()["total_mass"] == m0
    # free fall: momentum grows by M g frame_dt per frame through split and merge (1e-4: float32)
    steps = np.diff(momentum)
    assert np.allclose(steps, -m0 * 9.81 * sim.frame_dt, rtol=1e-4), steps


@pytest.mark.parametrize("flip", [False, True], ids=["front-face", "back-face"])
def test_no_family_merges_while_it_touches_a_sheet(flip):
    """Merging is on by default. A jelly refined in a band falls onto a tilted sheet
    below it, outside the region, from either face of the sheet: no family merges while
    one of its children touches the sheet (carries its color: within the particle band),
    where a merged particle would stand a coarse cell's contact distance off it (a
    blade's cut was 1.5x finest's width that way, docs/method.md). No particle ever ends
    a step under the sheet, and mass is kept exactly."""
    rot = (187.0 if flip else 7.0, 0.0, 4.0)
    centre = np.array([0.5, 0.35, 0.5])
    scene = abmpm.Scene(
        simulation=abmpm.SimulationSettings(
            dx=0.05, fps=20, refinement={"mode": "adaptive", "boxes": [((0, 0.6, 0), (1, 0.75, 1))]}),
        materials=[abmpm.Elastic(name="jelly", youngs_modulus=3e4)],
        bodies=[abmpm.SphereBody(material="jelly", center=(0.5, 0.9, 0.5), radius=0.08)],
        colliders=[sm.SheetCollider(size=(0.8, 0.8), center=tuple(centre), rotation=rot)],
    )
    assert scene.simulation.refinement.merge
    sim = abmpm.Simulation(scene, device="cpu")
    normal = sim.colliders.body_meshes()[0].face_normals[0] * (-1.0 if flip else 1.0)
    assert normal[1] > 0.9  # the side the jelly comes from
    m0, fine = sim.diagnostics()["total_mass"], scene.simulation.dx / scene.simulation.refinement.factor
    refined, touched, lowest, before = 0, 0, np.inf, sim.particles()
    while sim.time < 0.6:
        sim.step()
        p = sim.particles()
        refined = max(refined, int((p.level == 1).sum()))
        lowest = min(lowest, float(((p.x - centre) @ normal).min()))
        # families merged in this step (their parent's id back at level 0): none had a
        # child in the sheet's particle band before (0.1 fine cells' slack for the band's edge)
        back = np.setdiff1d(p.id[p.level == 0], before.id[before.level == 0])
        near = (before.level == 1) & (np.abs((before.x - centre) @ normal) < (PARTICLE_BAND - 0.1) * fine)
        assert not (near & np.isin(before.family, back)).any()
        touched = max(touched, int(near.sum()))
        before = p
    assert refined > 0 and touched > 0  # split in the band, and its children reached the sheet
    assert sim.diagnostics()["total_mass"] == m0
    assert lowest > 0.0, lowest  # never through the sheet


@pytest.mark.parametrize("factor, rotation, width, gap", [
    (3, (0.0, 0.0, 0.0), 0.3, (0.43, 0.51)), (3, (180.0, 0.0, 0.0), 0.3, (0.43, 0.51)),  # both faces, level
    (2, (0.0, 0.0, 30.0), 0.16, (0.40, 0.53)),  # tilted: the coarse stencil reaches 1.5 dx |n|_1 across it
], ids=["b3-front-face", "b3-back-face", "b2-tilted"])
def test_refined_impact_does_not_push_through_a_sheet(factor, rotation, width, gap):
    """Water refined above a zero-thickness sheet hits it at 2 m/s; coarse water rests
    just under it, without gravity. Nothing but the sheet is between them, so the water
    below must not move: its momentum stays at float32 round-off, as in original and
    finest mode. It failed (2.3 kg m/s after one frame, 8% of the incoming momentum,
    at b = 3; 0.02 kg m/s at b = 2 on the tilted sheet) while a level-1 particle took
    part in the coarse P2G (Eq. 8) without a coarse-scale color beyond its own, finer
    band."""
    centre = np.array([0.5, 0.4625, 0.5])
    scene = abmpm.Scene(
        simulation=abmpm.SimulationSettings(
            dx=0.05, fps=40, gravity=(0, 0, 0),
            refinement={"mode": "adaptive", "factor": factor, "boxes": [((0, 0.5, 0), (1, 0.9, 1))],
                        "merge": False}),
        materials=[abmpm.Fluid(name="water", bulk_modulus=1e5)],
        bodies=[abmpm.BoxBody(material="water", min=(0.5 - width / 2, gap[1], 0.35),
                              max=(0.5 + width / 2, gap[1] + 0.15, 0.65), velocity=(0, -2, 0)),
                abmpm.BoxBody(material="water", min=(0.5 - width / 2, gap[0] - 0.1, 0.35),
                              max=(0.5 + width / 2, gap[0], 0.65))],
        colliders=[sm.SheetCollider(size=(1.5, 1.5), center=tuple(centre), rotation=rotation)],
    )
    sim = abmpm.Simulation(scene, device="cpu")
    normal = sim.colliders.body_meshes()[0].face_normals[0]
    normal = normal if normal[1] > 0 else -normal  # up, towards the impact
    below = ((sim.particles().x - centre) @ normal) < 0
    incoming = float(sim.particles().mass[~below].sum()) * 2.0
    for _ in range(2):
        sim.advance(frames=1)
        p = sim.particles()
        assert (p.level[~below] == 1).all() and (p.level[below] == 0).all()  # refined above, coarse below
        assert (((p.x[below] - centre) @ normal) < 0).all()
        # 1e-6 of the incoming momentum: far above float32 round-off (~1e-9 kg m/s
        # here), far below the 5% that leaked through before
        momentum = p.mass[below, None] * p.v[below]
        assert np.abs(momentum.sum(axis=0)).max() < 1e-6 * incoming, momentum.sum(axis=0)
        assert np.abs(p.v[below]).max() < 1e-4


def test_adaptive_resume_is_bit_identical():
    scene = jelly_scene("adaptive", [((0, 0, 0), (1, 0.35, 1))])
    straight = abmpm.Simulation(scene, device="cpu")
    straight.advance(frames=6)
    first = abmpm.Simulation(scene, device="cpu")
    first.advance(frames=3)
    arrays, meta = first.state_dict()
    resumed = abmpm.Simulation(scene, device="cpu")
    resumed.load_state_dict(arrays, meta)
    resumed.advance(frames=3)
    a, b = straight.particles().by_id(), resumed.particles().by_id()
    assert a.level.max() == 1 and len(a) == len(b)
    assert np.array_equal(a.x, b.x) and np.array_equal(a.v, b.v)



@pytest.mark.parametrize("mode", ["original", "adaptive"])
def test_resume_next_to_a_collider_is_bit_identical(mode):
    # The built-in hourglass (a glass, CPIC colors on most particles). Loading a
    # checkpoint recomputed every particle's color with the exact query, where the run
    # had G2P's (from the nodes, within NODE_COLOR_TOL): the resumed run drifted by
    # ~1e-7 m in two frames until 2026-11-27.
    scene = abmpm.load_scene("hourglass")
    straight = abmpm.Simulation(scene, device="cpu", mode=mode)
    straight.advance(frames=3)
    arrays, meta = straight.state_dict()
    resumed = abmpm.Simulation(scene, device="cpu", mode=mode)
    resumed.load_state_dict(arrays, meta)
    straight.advance(frames=2)
    resumed.advance(frames=2)
    a, b = straight.state_dict()[0], resumed.state_dict()[0]
    ia, ib = np.argsort(a["id"]), np.argsort(b["id"])
    assert len(ia) == len(ib) and (a["surface_body"] >= 0).any()
    for k in ("x", "v", "C", "F", "surface_point", "surface_side", "surface_body"):
        assert np.array_equal(a[k][ia], b[k][ib]), k


def test_last_good_checkpoint_is_the_frames_checkpoint():
    # What an interrupted or blown-up run saves (the last good frame) must be the
    # checkpoint a run writes at that frame's end: the same particles in the same order
    # (after the frame end's merge and sort) and the same next id and time-step signals.
    # Until 2026-11-27 it was the state before the merge and sort, with the next frame's
    # next id, so a run resumed from it was not the uninterrupted one.
    sim = abmpm.Simulation(abmpm.load_scene("hourglass"), device="cpu", mode="adaptive")
    sim.advance(frames=3)
    arrays, meta = sim.state_dict()
    while sim.solver.next_id == meta["next_id"]:  # into the next frame, past a split
        sim.step()
    assert sim.substep != 0
    kept, kept_meta = sim.state_dict(last_good=True)
    assert kept_meta == meta
    assert kept.keys() == arrays.keys()
    for k in arrays:
        assert np.array_equal(kept[k], arrays[k]), k

def test_region_follows_a_moving_collider():
    sheet = sm.SheetCollider(size=(0.3, 0.3), center=(0.3, 0.5, 0.5), motion=sm.Motion(velocity=(1.0, 0, 0)))
    scene = abmpm.Scene(
        simulation=abmpm.SimulationSettings(dx=0.05, fps=10, gravity=(0, 0, 0), refinement={"mode": "adaptive"}),
        materials=[abmpm.Elastic(name="jelly")],
        bodies=[abmpm.SphereBody(material="jelly", center=(0.5, 0.15, 0.5), radius=0.08)],
        colliders=[sheet],
    )
    sim = abmpm.Simulation(scene, device="cpu")
    g = sim.solver.grid
    origin = np.array([g.spec.origin[a] for a in range(3)])

    def refined_x():  # x extent of the refined cells
        idx = np.argwhere(sim.solver.refiner.region_cells)
        return origin[0] + g.dx * idx[:, 0].min(), origin[0] + g.dx * (idx[:, 0].max() + 1)

    lo0, hi0 = refined_x()
    sim.advance(frames=3)  # the sheet moves 0.3 m in +x
    lo1, hi1 = refined_x()
    # the region (sheet +- halo) moved with the sheet, to within a cell
    assert abs((lo1 - lo0) - 0.3) <= g.dx + 1e-9 and abs((hi1 - hi0) - 0.3) <= g.dx + 1e-9


def test_split_children_keep_the_parent_envelope():
    """Children sit on the sub-lattice of their parent's own cube (deformed by F), so
    splitting a block neither swells it nor roughens its faces beyond the parents'
    sampling jitter: the bumps that Eqs. 16-20 of the paper repair do not arise."""
    lo, hi = np.array([0.3, 0.3, 0.3]), np.array([0.5, 0.5, 0.5])
    scene = abmpm.Scene(
        simulation=abmpm.SimulationSettings(
            dx=0.05, fps=20, gravity=(0, 0, 0),
            refinement={"mode": "adaptive", "boxes": [((0, 0, 0), (1, 1, 1))], "reconstruct": False}),
        materials=[abmpm.Elastic(name="jelly")],
        bodies=[abmpm.BoxBody(material="jelly", min=tuple(lo), max=tuple(hi))],
    )
    sim = abmpm.Simulation(scene, device="cpu")
    p = sim.particles()
    assert np.all(p.level == 1)
    h_parent, h_child = 0.05 / 2, 0.05 / 4
    # parents sit at cell-lattice points jittered by up to h/4; a child is within
    # h_parent/2 - h_child/2 of its parent, so every child is inside the block grown
    # by the jitter, and the outermost children reach within h_child/2 + jitter of the faces
    jitter = h_parent / 4
    assert np.all(p.x >= lo + h_child / 2 - jitter - 1e-6) and np.all(p.x <= hi - h_child / 2 + jitter + 1e-6)
    assert np.allclose(p.x.min(axis=0), lo + h_child / 2, atol=jitter + 1e-6)
    assert np.allclose(p.x.max(axis=0), hi - h_child / 2, atol=jitter + 1e-6)
    # volume is conserved: children's volumes add up to the block's
    assert np.isclose(p.volume.astype(np.float64).sum(), np.prod(hi - lo), rtol=1e-6)


def test_region_outline_and_region_file(tmp_path):
    from abmpm.post.render import region_outline
    from abmpm.runner import run

    one = np.zeros((4, 4, 4), dtype=bool)
    one[1, 1, 1] = True
    assert len(region_outline(one, (0, 0, 0), 1.0)) == 12  # a cube's 12 edges
    slab = np.zeros((6, 6, 6), dtype=bool)
    slab[1:5, 2:3, 1:5] = True
    seg = region_outline(slab, (0, 0, 0), 0.5)
    assert len(seg) == 4 * 4 + 4 * 4 + 4 * 1  # a 4 x 1 x 4 box: 12 edges cut into unit segments
    assert np.allclose(seg.reshape(-1, 3).min(axis=0), [0.5, 1.0, 0.5])
    # an adaptive run writes its region for tools and the preview
    scene = jelly_scene("adaptive", [((0, 0, 0), (1, 0.3, 1))])
    run(scene, tmp_path / "out", frames=1, preview=False, progress=False)
    with np.load(tmp_path / "out" / "region.npz") as z:
        # one flag per coarse cell: 20 cells across the domain + 3 padding cells each side
        assert z["cells"].any() and z["cells"].shape == (26, 26, 26)
