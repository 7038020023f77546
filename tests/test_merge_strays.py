"""Children of torn families merged by place (``refine.group_strays`` + ``merge_families``).

A fluid that squeezed through a passage leaves the region with its families torn apart: a
family merges only when its b^3 children are still within one parent spacing of their
centre, and in the letter panel 5 of ~1,700 families out of the region could. ``group_strays``
gives the children of one cell of the parents' lattice a new family when that cell holds at
least b^3 of them (a whole parent's mass in a parent's volume), so that they merge. What is
checked here against quantities known outside the code: mass conserved exactly (masses that
are sums of powers of two), linear momentum to float32 round-off, each merged particle at the
centre of mass of b^3 children of one lattice cell, and nothing merged that must not be (a
cell short of b^3, a child in the region or by a collider, a material that keeps F).
"""

import numpy as np
import pytest

import abmpm
from abmpm.scene import model as sm
from abmpm.sim.refine import group_strays, merge_families

H = 0.05  # the parents' lattice spacing (dx = 0.1 at 8 particles per cell)


def torn_children(b: int, cells: int, seed: int, short: int = 0) -> dict[str, np.ndarray]:
    """A fluid block of ``cells``^3 parent-lattice cells sampled with b^3 children each on the
    child lattice (jittered within its own sub-cell), every child given the family of a parent
    that is not its neighbour (torn apart); the last cell short by ``short`` children."""
    rng = np.random.default_rng(seed)
    ns = b**3
    sub = (np.stack(np.meshgrid(*[np.arange(cells * b)] * 3, indexing="ij"), -1).reshape(-1, 3) + 0.5) * (H / b)
    x = 0.2 + sub + rng.uniform(-0.2, 0.2, sub.shape) * (H / b)
    if short:
        last = np.all(np.floor((x - 0.2) / H) == cells - 1, axis=1)
        x = x[~np.isin(np.arange(len(x)), np.flatnonzero(last)[:short])]
    n = len(x)
    fam = rng.permutation(np.repeat(np.arange(-(-n // ns)), ns))[:n]  # families scattered over the block
    return {
        "x": x.astype(np.float32), "v": rng.normal(0, 1, (n, 3)).astype(np.float32),
        "C": rng.normal(0, 3, (n, 3, 3)).astype(np.float32), "F": np.tile(np.eye(3, dtype=np.float32), (n, 1, 1)),
        "history": rng.uniform(0.9, 1.1, n).astype(np.float32),
        "mass": np.full(n, 0.125 / ns, np.float32), "volume": np.full(n, H**3 / ns, np.float32),
        "material": np.zeros(n, np.int32), "level": np.ones(n, np.int32),
        "id": (1000 + np.arange(n)).astype(np.int32), "family": fam.astype(np.int32),
        "surface_point": np.zeros((n, 3), np.float32), "surface_side": np.zeros((n, 3), np.float32),
        "surface_body": np.full(n, -1, np.int32),
    }


FLUID = np.array([True])


@pytest.mark.parametrize("b", [2, 3])
def test_torn_families_merge_by_place_conserving_mass_and_momentum(b):
    ns, cells = b**3, 3
    a = torn_children(b, cells, seed=b)
    keep = np.zeros(len(a["x"]), dtype=bool)
    as_is, k0 = merge_families({k: v.copy() for k, v in a.items()}, keep, b)
    assert k0 == 0  # torn: no family is complete and compact
    ids, before = a["id"].copy(), a["family"].copy()
    family, groups = group_strays(a, keep, b, FLUID, np.zeros(3))
    assert groups == cells**3  # every full cell of the parents' lattice
    assert np.array_equal(a["family"], before)  # a copy: the particles are not changed
    merged, k = merge_families({**a, "family": family}, keep, b)
    assert k == groups and len(merged["x"]) == len(a["x"]) - groups * (ns - 1)
    assert np.all(merged["level"] == 0)
    # each merged particle goes on under one of its children's ids: every id still unique
    assert np.isin(merged["id"], ids).all() and len(np.unique(merged["id"])) == len(merged["id"])
    # mass: ns children of 2^-3 / ns kg (b = 2: exact binary fractions; b = 3: one rounding each)
    assert merged["mass"].astype(np.float64).sum() == pytest.approx(a["mass"].astype(np.float64).sum(), rel=1e-6)
    if b == 2:
        assert merged["mass"].astype(np.float64).sum() == a["mass"].astype(np.float64).sum()
    P0 = (a["mass"][:, None].astype(np.float64) * a["v"]).sum(axis=0)
    P = (merged["mass"][:, None].astype(np.float64) * merged["v"]).sum(axis=0)
    scale = (a["mass"].astype(np.float64) * np.linalg.norm(a["v"], axis=1)).sum()
    assert np.abs(P - P0).max() <= 1e-5 * scale  # float32 averages
    # each merged particle lies in its own lattice cell, one per cell: the cell's centre of mass
    cell = np.floor((merged["x"].astype(np.float64) - 0.2) / H).astype(int)
    assert len(np.unique(cell, axis=0)) == groups and cell.min() >= 0 and cell.max() < cells
    assert np.allclose(merged["volume"], H**3, rtol=1e-6)


def test_what_must_not_merge_stays():
    b = 2
    a = torn_children(b, 2, seed=7, short=1)  # the last of 8 cells one child short
    keep = np.zeros(len(a["x"]), dtype=bool)
    in_region = np.all(np.floor((a["x"] - 0.2) / H) == 0, axis=1)  # the first cell: in the region
    keep[in_region] = True
    by_collider = np.all(np.floor((a["x"] - 0.2) / H) == (1, 0, 0), axis=1)
    a["surface_body"][by_collider] = 0  # colored children are flagged by the caller as well
    keep[by_collider] = True
    family, groups = group_strays(a, keep, b, FLUID, np.zeros(3))
    assert groups == 8 - 3  # not the region's cell, the collider's, or the short one
    assert np.array_equal(a["family"][keep], family[keep])
    # a material that keeps F (a solid's lattice) is never regrouped
    solid = torn_children(b, 2, seed=7)
    family, groups = group_strays(solid, np.zeros(len(solid["x"]), dtype=bool), b, np.array([False]), np.zeros(3))
    assert groups == 0 and np.array_equal(solid["family"], family)


def dam_into_coarse(merge_strays: bool) -> abmpm.Scene:
    """A refined water column (b = 2, a box over x < 0.2 m) collapses into the coarse rest of
    the box, its children torn apart as they flow out of the region."""
    return abmpm.Scene(
        simulation=abmpm.SimulationSettings(
            domain_max=(0.8, 0.4, 0.2), dx=0.05, fps=30,
            refinement={"mode": "adaptive", "factor": 2, "boxes": [((0.0, 0.0, 0.0), (0.2, 0.4, 0.2))],
                        "merge_strays": merge_strays}),
        materials=[sm.Fluid(name="water")],
        bodies=[sm.BoxBody(material="water", min=(0.0, 0.0, 0.0), max=(0.2, 0.3, 0.2))],
    )


def test_a_collapsed_column_goes_back_to_coarse_particles():
    """In a run: the strays out of the region merge (fewer children than without), the mass
    is the same to float32 round-off and every particle keeps a whole number of children's
    masses (no light particle is ever made)."""
    out = {}
    for flag in (False, True):
        sim = abmpm.Simulation(dam_into_coarse(flag), device="cpu")
        sim.advance(frames=12)
        out[flag] = sim.particles()
    child = out[False].mass[out[False].level == 1].min()
    without, with_ = (np.count_nonzero(out[f].level == 1) for f in (False, True))
    print(f"children at 0.4 s: {without} without, {with_} with merge_strays")
    assert with_ < 0.8 * without
    m0, m1 = (out[f].mass.astype(np.float64).sum() for f in (False, True))
    assert m1 == pytest.approx(m0, rel=1e-6)
    units = out[True].mass / child
    assert np.allclose(units, np.round(units), atol=1e-3) and units.min() >= 1


def test_a_resumed_run_merges_the_same_strays():
    """The regrouping is a function of the frame's particles alone (by place, ties by id) and
    leaves the checkpoint's families as they were: a run resumed from frame 6 is bit-identical
    to the straight run, strays merged by place in both halves."""
    scene = dam_into_coarse(True)
    straight = abmpm.Simulation(scene, device="cpu")
    straight.advance(frames=6)
    arrays, meta = straight.state_dict()
    at_six = int((straight.particles().level == 1).sum())
    resumed = abmpm.Simulation(scene, device="cpu")
    resumed.load_state_dict(arrays, meta)
    straight.advance(frames=6)
    resumed.advance(frames=6)
    a, b = straight.particles().by_id(), resumed.particles().by_id()
    assert len(a) == len(b) and np.array_equal(a.id, b.id)
    assert np.array_equal(a.x, b.x) and np.array_equal(a.v, b.v) and np.array_equal(a.family, b.family)
    assert (a.level == 1).sum() < at_six  # strays merged after the checkpoint too
