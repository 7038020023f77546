"""``abmpm bench --suite scaling`` (issue "cost follows the refined region"): the tank
grows around a refinement box of fixed size, and the suite runs end to end."""

import json

import numpy as np
import pytest

from abmpm.bench import run_bench
from abmpm.bench.scaling import BASE, BOX, LENGTHS, REGIONS, per_level_floor, sloshing_tank
from abmpm.simulation import Simulation


def test_the_tank_grows_and_its_refined_box_does_not():
    for length in LENGTHS:
        sc = sloshing_tank(length)
        L = sc.simulation.domain_max[0]
        assert L == pytest.approx(BASE * length)
        (lo, hi), = sc.simulation.refinement.boxes
        assert (hi[0] - lo[0], hi[0]) == pytest.approx((BOX, L))  # the same box, at the right wall
    # the water fills the tank's length: original mode's particles grow with it
    counts = [Simulation(sloshing_tank(n, "original"), device="cpu").particle_count for n in (1, 2)]
    assert counts[1] == 2 * counts[0]


def test_the_tank_with_a_hole_refines_the_same_small_region_at_every_length():
    # the feature criterion's region around the hole is the same set of cells, counted
    # from the right wall, whatever the tank's length; and it is small (the box: 384 cells)
    regions = []
    for n in (1, 4):
        sim = Simulation(sloshing_tank(n, "adaptive", "hole"), device="cpu")
        cells = sim.refinement_cells()
        regions.append(np.argwhere(cells) - [cells.shape[0], 0, 0])
    assert len(regions[0]) and np.array_equal(regions[0], regions[1])
    assert len(regions[0]) < 384 / 2


def test_the_floor_counts_each_particle_at_its_own_steps():
    # 6k slow particles at original's step, 4k fast ones at two substeps a step, against
    # original's 9k particles: (6k + 2 x 4k) / 9k
    row = {"original": {"particles": 9000, "steps_per_sim_s": 1000.0},
           "per_level": {"particles": 10000, "slow": 6000, "steps_per_sim_s": 2000.0}}
    assert per_level_floor(row) == pytest.approx(14000 / 9000)
    # no slow set: every particle at the fine step
    row["per_level"]["slow"] = 0
    assert per_level_floor(row) == pytest.approx(20000 / 9000)


@pytest.mark.slow
def test_the_scaling_suite_runs_end_to_end(tmp_path, monkeypatch):
    import abmpm.bench.scaling as scaling

    real = scaling.run_scaling  # one length, 0.01 s: the suite's path, not its figures
    monkeypatch.setattr("abmpm.bench.run_scaling", lambda device, plot=None: real(device, 0.01, (1,), plot))
    out = tmp_path / "scaling.json"
    result = run_bench(["--device", "cpu", "--suite", "scaling", "--json", str(out)])
    row, hole_row = result["scaling"]
    assert (row["region"], hole_row["region"]) == REGIONS
    for mode in ("original", "adaptive", "per_level", "finest"):
        assert row[mode]["wall_per_sim_s"] > 0 and row[mode]["steps_per_sim_s"] > 0
    # per level the fast part takes at least the global step's substeps: the cut may
    # shorten them where the slow set's fewer steps pay for it (sim/time_levels.py)
    assert row["per_level"]["steps_per_sim_s"] >= row["adaptive"]["steps_per_sim_s"]
    # adaptive holds more particles than original and fewer than finest
    assert row["original"]["particles"] < row["adaptive"]["particles"] < row["finest"]["particles"]
    assert json.loads(out.read_text())["scaling"][0]["length_m"] == pytest.approx(BASE)
    assert out.with_suffix(".png").stat().st_size > 0
    assert np.isfinite(row["adaptive_over_original"])
    assert row["per_level_floor"] == pytest.approx(per_level_floor(row), abs=1e-3) and row["per_level_floor"] >= 1.0


def test_the_adaptive_suite_measures_each_level_against_its_own_mode():
    # `abmpm bench --suite adaptive` also prices each particle at its own level's mode (a
    # level-0 particle-step at original's cost, a level-1 one at finest's): with every
    # particle split (a box over the domain) that yardstick is finest's alone, with none
    # split (a box the water never reaches) original's alone
    from abmpm.bench import time_modes
    from abmpm.scene.model import BoxBody, Fluid, Scene, SimulationSettings

    def scene(box):
        return Scene(name="levels", simulation=SimulationSettings(
            domain_max=(0.4, 0.4, 0.4), dx=0.05, fps=30, refinement={"mode": "adaptive", "factor": 2, "boxes": [box]}),
            materials=[Fluid(name="water")], bodies=[BoxBody(material="water", min=(0, 0, 0), max=(0.2, 0.2, 0.2))])

    whole = time_modes(scene(((0.0, 0.0, 0.0), (0.4, 0.4, 0.4))), 1, "cpu")
    assert whole["adaptive"]["mean_per_level"][0] == 0
    assert whole["cost_per_particle_step_adaptive_over_own_levels"] == pytest.approx(
        whole["adaptive"]["ns_per_particle_step"] / whole["finest"]["ns_per_particle_step"], rel=1e-3)
    corner = time_modes(scene(((0.35, 0.35, 0.35), (0.4, 0.4, 0.4))), 1, "cpu")
    assert corner["adaptive"]["mean_per_level"][1] == 0
    assert corner["cost_per_particle_step_adaptive_over_own_levels"] == pytest.approx(
        corner["adaptive"]["ns_per_particle_step"] / corner["original"]["ns_per_particle_step"], rel=1e-3)
