"""Adaptive against finest where particles change level (issue: the level interface
made right). The fast cases of the matrix that ``abmpm bench --suite interface``
runs in full (abmpm/bench/interface.py, docs/method.md "The level interface against
finest"). Tolerances are stated inline."""

import numpy as np
import pytest

from abmpm.bench.interface import (
    JET_SECONDS,
    PLATE_W,
    PLATE_Z,
    SEEDS4,
    SEEDS8,
    plate_with_slit,
    run_dam_break,
    run_layered_tank,
    run_piston,
    run_slit,
    run_tank,
    tank_at_rest,
)
from abmpm.bench.interface_report import plate_tally
from abmpm.compare.outcomes import mass_beyond_plane
from abmpm.geometry.sampling import JITTER, lattice_spacing
from abmpm.inputs import sample_scene
from abmpm.simulation import Simulation


def test_adaptive_parents_sit_on_their_lattice_and_their_children_have_finest_jitter():
    # A family used to inherit its parent's sampling offset: one offset shared by b^3
    # children, a texture no fine sampling has (docs/method.md, "Split children sampled as
    # finest samples"). Parents that may split are now sampled on their lattice points and
    # each child is jittered about its own, as finest mode samples every particle: up to
    # JITTER/2 child spacings per axis, less the family's mean.
    from test_adaptive import child_places, split_everything

    for b in (2, 4):
        scene = tank_at_rest("adaptive", b=b)
        h = lattice_spacing(scene.simulation.dx, 8)
        x = sample_scene(scene, b)["x"].astype(np.float64)
        site = (np.floor(x / h) + 0.5) * h  # the lattice point
        assert np.abs(x - site).max() < 1e-6
        coarse = sample_scene(scene, 1)["x"].astype(np.float64)  # original mode: jittered, same count
        assert len(coarse) == len(x) and np.abs(coarse - site).max() > 0.25 * JITTER * h
    # interior parents (no reconstruction, no wall near): their children's offsets from
    # their lattice points, in child spacings, against finest's uniform +-JITTER/2 less a
    # family mean of b^3 draws: standard deviation JITTER / sqrt(12) sqrt(1 - 1/b^3),
    # within 10% (1,536 samples: the estimate's own scatter is ~2%)
    b, h = 2, 0.05
    grid = (np.stack(np.meshgrid(*[np.arange(8)] * 3, indexing="ij"), -1).reshape(-1, 3) + 0.5) * h + 0.3
    n = len(grid)
    zeros3 = np.zeros((n, 3, 3), np.float32)
    F = np.repeat(np.eye(3, dtype=np.float32)[None], n, axis=0)
    out = split_everything(grid.astype(np.float32), np.zeros((n, 3), np.float32), zeros3, F,
                           np.full(n, 1000.0 * h**3, np.float32), b)
    parent = grid[np.argmin(np.linalg.norm(out["x"][:, None] - grid[None], axis=2), axis=1)]
    place, d = child_places(out, b)
    off = (out["x"] - parent - h * d) / (h / b)
    assert np.abs(off).max() <= JITTER + 1e-3  # at most a draw's range from its point
    want = JITTER / np.sqrt(12) * np.sqrt(1 - 1 / b**3)
    assert abs(off.std() / want - 1) < 0.10, off.std()
    # independent draws: the same place in two families is not the same offset, nor the
    # same child under another scene seed (the seed averages of the interface bench)
    first = off[place == 0]
    assert np.corrcoef(first[:-1].ravel(), first[1:].ravel())[0, 1] < 0.2
    other = split_everything(grid.astype(np.float32), np.zeros((n, 3), np.float32), zeros3, F,
                             np.full(n, 1000.0 * h**3, np.float32), b, seed=1)
    assert np.array_equal(other["id"], out["id"])
    moved = (other["x"] - parent - h * d) / (h / b)
    assert abs(np.corrcoef(moved.ravel(), off.ravel())[0, 1]) < 0.2


@pytest.mark.slow
def test_tank_at_rest_across_the_level_interface():
    r = run_tank(0.3, "cpu")
    # Finest's own J spread (0.027 at this size) comes from its sampling jitter. When the
    # children of a family shared their parent's offset (correlated jitter of the same
    # amplitude) it could add up to sqrt(2) of it: 1.5x, the bound. Measured 0.97x with
    # each child jittered as finest samples (1.27x with the shared offset; 2.85x before the
    # parents were jittered at the fine scale and reconstruction stopped moving the
    # families along the walls and the floor).
    assert r["J_spread_ratio"] < 1.5, r
    # nothing moves much faster than in the finest tank: 1.5x its fastest particle,
    # the margin of the spread above (measured 1.13x; 1.03x with the shared offset)
    assert r["fastest_ratio"] < 1.5, r
    # the issue's measure: J next to the interface within 0.01 of J at the same depth
    # far from it (per-depth means; 0.2 off at 0.5 s when the issue was filed; measured
    # 0.0012, finest 0.0004), and the free surface flat within half a fine cell
    # (0.0125 m) across the interface (measured 0.0085 over the four columns around it,
    # finest 0.0013; 0.0039 with the shared offset: the children's water now stands at
    # finest's level, the coarse half, sampled on its lattice points, ~5 mm lower, as
    # lattice water settles: docs/method.md, "Split children sampled as finest samples")
    # and over the tank (0.0105 over the columns away from the walls; original mode's own
    # surface 0.0068, finest 0.0017)
    assert r["adaptive"]["depth_J_gap"] < 0.01, r
    assert r["adaptive"]["interface_surface_range"] < 0.0125, r
    assert r["adaptive"]["surface_range"] < 0.0125, r


@pytest.mark.slow
def test_tank_at_rest_across_the_level_interface_at_b4():
    # At b = 4 a coarse particle is one sample per 2x2x2 fine cells. Seen by the fine
    # grid as a point, it made the nodes between coarse particles light and the level-1
    # particles next to the interface read that lumpy field: after 0.15 s their J
    # spread 7.5 times finest's at the same places, the fastest particle 2.4 times
    # finest's, 29% more steps (measured before sim/footprint.py). With each coarse
    # particle spread over its box: 2.3x, 0.94x, 1.01x. Bounds: the interface J spread
    # within 3x (not yet finest's: the children of a family share their parent's
    # jitter, and the two grids still move their own particles), nothing faster than
    # 1.5x finest's fastest, and the issue's goal for the steps (5% above finest's).
    # Run for 0.3 s: with each box shrunk half a fine cell inside the domain walls (until
    # 2026-11-29) a child where the interface meets the floor and a wall was squeezed
    # from about 0.15 s on and the run took 1.064x finest's steps by 0.3 s; with the box
    # cut at the wall plane 1.003x (interface J spread 1.62x, fastest 1.22x). And the
    # issue's flat surface across the interface: within half a fine cell (0.00625 m) over
    # the four columns around it (measured 0.00624, within the goal by 0.05 mm: the
    # children's water stands at finest's level, the coarse half ~5 mm lower, see the b = 2
    # test; 0.0047 when the children shared their parent's offset; finest 0.0007).
    r = run_tank(0.3, "cpu", b=4)
    assert r["interface_J_ratio"] < 3.0, r
    assert r["fastest_ratio"] < 1.5, r
    assert r["steps_ratio"] <= 1.05, r
    assert r["adaptive"]["interface_surface_range"] < r["half_fine_cell"], r


@pytest.mark.slow
@pytest.mark.parametrize("slit_cells, seeds", [(0.5, SEEDS8), (1.0, SEEDS4)])
def test_slit_outside_the_paper_drains_like_finest(slit_cells, seeds):
    # A plate spanning the box with a slit across it, b = 2, default refinement
    # (feature criterion, reconstruction, merge), 0.5 s. The mass through at one
    # instant varies with the particle jitter's seed by +-7% in finest mode itself
    # (1-cell slit, seeds 0-3: 0.0231-0.0266), as much as the bound: each mode is the
    # mean of four seeds. Seed 0 alone read 0.97 and 0.97 before the coarse grid's
    # contact band followed the level-1 material (grid_update); the four seeds' means
    # were 0.87 and 0.89, outside the bound. After: 0.96 and 1.06. Those rested on float32
    # round-off deciding which nodes one cell from the plate (on a node plane) took the
    # contact; with those ties in, 0.78 and 0.91 in 1.18x and 1.16x finest's steps (compressed
    # children), and with the band rule at b = 2 as well (level-0 particles in the band move
    # with the fine grid as their boxes) 0.920 and 1.094 in 1.009x and 0.962x (docs/method.md,
    # "The contact band's ties, and the band rule at b = 2"). All of that in a box of slip walls; in
    # the separating walls of the scenes' default (since 2026-11-29) 0.918 and 1.075 in 1.008x and
    # 0.953x finest's steps. The 0.5-cell slit drains least (1.3% of the mass): over seeds
    # 0-3 and 4-7 finest's means differ by 6.5% and adaptive's four-seed standard error is
    # 4.6%, so a change that leaves the eight-seed mean where it was (a coarse box cut at the
    # wall plane, 2026-11-29: 0.01249 -> 0.01261) moved the four-seed ratio 0.918 -> 0.865.
    # It takes the mean of eight seeds (measured 0.947; 0.931 and 1.068 with each split child
    # jittered as finest samples, 2026-11-29, in 0.944x and 0.94x finest's steps).
    r = run_slit(slit_cells, 2, 0.5, "cpu", seeds=seeds)
    assert r["finest"]["through"] > 0.01  # the case is what it says: water does go through
    # the issue's bound: the outcome within 10% of finest
    assert abs(r["through_ratio"] - 1.0) < 0.10, r
    # Steps: the issue's goal, at most 5% above finest's (measured 1.008 and 0.953; 1.18x and 1.16x
    # without the band rule at b = 2, the compressed band this guards against).
    assert r["steps_ratio"] <= 1.05, r


@pytest.mark.slow
def test_slit_at_b3_drains_like_finest_at_one_step():
    # At a sheet the mass through depends on the number of steps in any MPM (a minimal
    # MLS-MPM outside our code drains a hole 0.161 / 0.102 at cfl 0.4 / 0.1:
    # docs/prototypes/minimal_hole_drain.py), so at each mode's own step the ratio to finest
    # mixes the level interface with the step count. Here every mode takes one fixed step
    # (cfl 0.1 at the sound speed, below every mode's own): the 1-cell slit at b = 3, 0.5 s,
    # measured 0.1560 against finest's 0.1587 (0.983) in 1,680 steps each with the contact band's
    # ties in (2026-11-28; 1.009 while float32 round-off decided them, docs/benchmarks.md), and in
    # separating walls (since 2026-11-29) 0.991 of finest's 0.1619, with each split child
    # jittered as finest samples 0.976; the issue's bound is 10%.
    # (Before the band's ties were decided in, 2026-11-28, the 1-cell slit at b = 2 read 0.74
    # at one step and the round holes 1.08-1.25: docs/method.md, "At one step, where no node
    # sits on the band's edge, adaptive is finest"; with the ties in, before the band rule at b = 2,
    # 1.05 and 0.99-1.09.)
    r = run_slit(1.0, 3, 0.5, "cpu", step=0.1)
    # the fixed step in effect (a mode's own CFL step may dip under it for a few steps: 1,697
    # against 1,680 with the band's ties decided one way, docs/benchmarks.md)
    assert abs(r["steps_ratio"] - 1.0) < 0.02, r
    assert r["finest"]["through"] > 0.05, r  # the case is what it says: water goes through
    assert abs(r["through_ratio"] - 1.0) < 0.10, r
    # the coarse grid alone clogs the slit (0 at one step, 0.025 at its own)
    assert r["original"]["through"] < 0.5 * r["finest"]["through"], r


@pytest.mark.slow
def test_half_cell_slit_at_b3_drains_like_finest():
    # The slit half a coarse cell wide at b = 3 (1.5 fine cells), 0.5 s, seed 0: while each
    # family shared its parent's sampling offset adaptive let through 1.17-1.24x finest's
    # (docs/benchmarks.md, the interface tables of 2026-11-27 to 29); with each split child
    # jittered about its own lattice point as finest samples (2026-11-29) 1.000 (two threads)
    # and 1.002 (one) of finest's 0.0126 in 0.98x its steps. The guard of that change: the
    # issue's 10%, and its step goal (5% above finest's).
    r = run_slit(0.5, 3, 0.5, "cpu")
    assert r["finest"]["through"] > 0.005, r  # the case is what it says: water goes through
    assert abs(r["through_ratio"] - 1.0) <= 0.10, r
    assert r["steps_ratio"] <= 1.05, r


@pytest.mark.slow
def test_water_thrown_at_the_back_face_of_a_slit_plate():
    # The audit's "back face of a sheet": the 1-cell slit at b = 3 with the water thrown up at
    # the plate's underside at 2 m/s, against gravity, 0.3 s, in a box of separating walls
    # (bench/interface.py, JETS). Measured: finest 0.0657 of the mass above the plate, original
    # 0.0219 (0.33x), adaptive 1.054x finest's (seeds 1 and 2: 1.055, 1.067) in 0.89x its steps;
    # with each split child jittered as finest samples (2026-11-29) 1.082x in 0.886x.
    # In a box of slip walls the same case read 0.877x: the floor held the water thrown off it
    # in tension, 1.5 cells of its grid deep, and the floor's grid is the coarse one in adaptive
    # mode (docs/method.md, "Water thrown at a sheet's back face"). Bound: issue 26's 10%.
    r = run_slit(1.0, 3, JET_SECONDS, "cpu", jet=2.0)
    assert r["finest"]["through"] > 0.01, r  # the case is what it says: water goes through
    # the coarse grid clearly worse (0.33x), as the other slits' tests hold it (half of finest's)
    assert r["original"]["through"] < 0.5 * r["finest"]["through"], r
    assert abs(r["through_ratio"] - 1.0) <= 0.10, r
    assert r["steps_ratio"] <= 1.05, r  # the issue's step goal (0.89 measured)
    # Either winding: the same plates turned over (each half 180 degrees about z in place, normals
    # down) give the same adaptive run (measured: the same to 4 digits): the colors, CPIC's masks and
    # the region do not depend on which face the sheet calls its front. 1% allows float32 ties.
    scene, yp = plate_with_slit("adaptive", 1.0, 3, jet=2.0)
    turned = [c.model_copy(update={"rotation": (0.0, 0.0, 180.0)}) for c in scene.colliders]
    sim = Simulation(scene.model_copy(update={"colliders": turned}), device="cpu")
    assert sim.colliders.body_meshes()[0].face_normals[0][1] < -0.99  # turned over
    sim.advance(seconds=JET_SECONDS)
    p = sim.particles()
    through = mass_beyond_plane(p.x, p.mass, (PLATE_W / 2, yp, PLATE_Z / 2), (0.0, 1.0, 0.0))
    assert abs(through / r["adaptive"]["through"] - 1.0) < 0.01, (through, r["adaptive"]["through"])


@pytest.mark.slow
def test_round_hole_at_b3_takes_finests_steps():
    # The plate spanning the box with a round hole one coarse cell across, b = 3, 0.5 s.
    # Where coarse and refined water met on the plate, the coarse grid moved its
    # particles into the children lining the plate (their J 0.50-0.60, finest's lowest
    # 0.65-0.75 there), and the step, which follows the most compressed fluid, made the
    # run take 1.137x finest's steps. Since level-0 particles in a collider's band move
    # with the fine grid where it holds them whole (docs/method.md), 0.971x (1.001x in the
    # separating walls of the box since 2026-11-29; 1.04x with each split child jittered as
    # finest samples). The issue's bound: at most 5% above finest's.
    r = run_slit(1.0, 3, 0.5, "cpu", hole=True)
    assert r["steps_ratio"] <= 1.05, r
    # the case is what it says: the coarse grid clogs the hole (original 0.0019 of the
    # mass through, finest 0.0189 in separating walls). Adaptive let through 1.133x finest's
    # while a family shared its parent's sampling offset (1.20x in the slip walls the box had
    # until 2026-11-29; 1.41x before the sliding fix), outside the issue's 10%; with each
    # split child jittered as finest samples (2026-11-29) 1.045x: the issue's bound, asserted
    # since (docs/method.md, "Split children sampled as finest samples").
    assert r["original"]["through"] < 0.25 * r["finest"]["through"], r
    assert abs(r["through_ratio"] - 1.0) <= 0.10, r


@pytest.mark.slow
def test_dam_break_into_a_refined_box_takes_finests_steps():
    # Coarse water runs along the floor into a refinement box at the far wall and hits
    # the wall there (the issue's "fine and coarse fluid mixed against a wall"). The
    # issue's bound: adaptive takes at most 5% more steps than finest (no compressed
    # band; the step follows the most compressed fluid). Measured 1.015 with each split child
    # jittered as finest samples (2026-11-29), 1.009 before (553 / 548; in the
    # slip walls of the box until 2026-11-29 1.036, and 1.067 before split children were
    # kept inside the domain walls, when the children of coarse parents sunk into the floor
    # started squeezed into it).
    r = run_dam_break(0.5, "cpu", b=2)
    assert r["steps_ratio"] <= 1.05, r
    # the front reaches the box about when finest's does (the coarse part is original
    # mode's) and crosses it in about finest's time: within the issue's 10% (measured 0.946)
    assert 0.9 <= r["crossing_ratio"] <= 1.1, r
    # the run-up at the wall within the issue's 10% of finest's (measured 1.046 of finest's
    # 0.608 m), the coarse grid alone clearly short of it (0.468 m, 0.77). In the box's former
    # slip walls the run-up read 0.77 of finest's: the coarse floor held the sheet of water
    # running along it 1.5 coarse cells deep (docs/method.md, "What the interface matrix's
    # misses are made of").
    assert abs(r["runup_ratio"] - 1.0) <= 0.10, r
    assert r["original"]["runup"] < 0.9 * r["finest"]["runup"], r


@pytest.mark.slow
def test_coarse_water_resting_on_a_refined_layer_stays_at_rest():
    # The interface horizontal: the refinement box is the bottom 0.1 m of the tank, so
    # the children carry the coarse water's weight through the overlap (Eq. 8) alone.
    # Bounds as for the vertical interface above: the children's J spread (against
    # hydrostatic J) within 1.5x finest's at the same heights (the correlated jitter
    # of a family; measured 1.37x, and 0.74x with each split child jittered as finest samples),
    # nothing faster than 1.5x finest's fastest (measured 0.61x, then 0.49x), and the issue's steps bound, 5% over finest's (measured 300
    # against 300).
    r = run_layered_tank(0.3, "cpu", b=2)
    for key, bound in (("J_spread_ratio", 1.5), ("fastest_ratio", 1.5), ("steps_ratio", 1.05)):
        assert r[key] <= bound, (key, r)


@pytest.mark.parametrize("factor", [3, 4])
def test_a_symmetric_drop_gains_no_sideways_momentum(factor):
    """Water falling onto a plate with a slit down its middle: the scene is its own mirror
    image in x, so the water's net x momentum stays at what the particles' jitter leaves
    (finest 2e-6 of the vertical, the same drop in original mode 0.011 at seed 0 and 0.0007 at
    seed 1: the coarse jitter's share). While the region's blocks sat 3 (b - 1) fine nodes
    off it (before 2026-11-28), the level-0 water on one side moved with the fine grid and on
    the other with the coarse one: 0.10 of the vertical at b = 3 by 0.076 s; with the blocks
    in place, which level-0 particles the fine grid moved still hung on the 4-node blocks'
    alignment: 0.020 (b = 3) and 0.0078 (b = 4); decided by the region alone
    (``Refiner.beside``) 0.00045 and 0.0011. Bound 0.005: four times the larger, under both
    old readings."""
    scene, _ = plate_with_slit("adaptive", 1.0, factor)
    sim = Simulation(scene, device="cpu")
    sim.advance(seconds=0.076)
    p = sim.particles()
    px, py = (float((p.mass.astype(np.float64) * p.v[:, k]).sum()) for k in (0, 1))
    assert abs(px) < 0.005 * abs(py), (px, py)


def test_the_plate_tally_counts_issue_26s_goals():
    # the interface suite's summary line: 10% on the mass through (both ways), 1.05x steps
    rows = [{"through_ratio": 1.099, "steps_ratio": 1.05}, {"through_ratio": 0.899, "steps_ratio": 0.8},
            {"through_ratio": 1.2, "steps_ratio": 1.06}, {"through_ratio": None, "steps_ratio": None}]
    t = plate_tally(rows)
    assert (t["cases"], t["within_10pct"], t["steps_within_5pct"]) == (4, 1, 2)
    assert t["mean_log_ratio"] == pytest.approx((np.log(1.099) + np.log(0.899) + np.log(1.2)) / 3, abs=1e-4)


@pytest.mark.slow
def test_a_jelly_pressed_through_a_slit_passes_what_finest_passes():
    # An elastic block pressed through the 1.5-cell slit at b = 3 by a sticky piston (0.3 s):
    # the mass below the plate in adaptive mode within the issue's 10% of finest's, in no
    # more than 1.05x its steps, and original clearly short of both (the coarse grid holds
    # the jelly on the slit's rims). Measured 2026-11-29: 0.2612 / 0.2561 (1.020) in 0.983x
    # the steps, original 0.2107. Until that day the block (0.12 m thick, 7 coarse layers of
    # 0.02 m) was 17% heavier in adaptive mode than in finest and read 0.957.
    r = run_piston(0.3, "cpu", b=3)
    assert abs(r["through_ratio"] - 1.0) <= 0.10, r
    assert r["steps_ratio"] <= 1.05, r
    assert r["original"]["through"] < 0.9 * r["finest"]["through"], r
