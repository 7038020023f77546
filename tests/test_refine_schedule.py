"""When adaptive mode refines (sim/refine_schedule.py): as often as the particles' motion
needs, so that no level-1 particle ever reaches a fine node outside the active blocks."""

import numpy as np
import pytest

from abmpm.scene import model as sm
from abmpm.sim.refine import ACTIVATION_MARGIN
from abmpm.sim.refine_schedule import RefineSchedule
from abmpm.simulation import Simulation


def test_the_schedule_refines_when_the_drift_could_pass_the_margin():
    fine_dx = 0.01
    s = RefineSchedule(cfl=0.4, fine_dx=fine_dx)
    assert s.every == 4 and s.reach == pytest.approx(ACTIVATION_MARGIN * fine_dx)
    assert s.refine_now(0, fine_dx)  # due at the start
    assert not s.refine_now(1, fine_dx)  # no decision point
    s.moved(1e-3, [1.0, 1.0, 1.0])  # 3 mm in three substeps
    # at step 4: 3 mm + 4 substeps of 0.4 cells (16 mm) <= 20 mm, so nothing can leave its blocks yet
    assert not s.refine_now(4, fine_dx)
    s.moved(1e-3, [0.5, 0.5])  # 4 mm in all
    assert not s.refine_now(6, fine_dx)
    s.moved(1e-3, [0.5, 0.5])  # 5 mm: 5 + 16 > 20
    assert s.refine_now(8, fine_dx)
    assert s.drift == 0.0
    # a rewound segment keeps the drift of the substeps it kept
    s.moved(1e-3, [2.0, 2.0, 2.0, 2.0])
    s.rewound(1e-3, [2.0])
    assert s.drift == pytest.approx(2e-3)
    # before anything is fine the step keeps the CFL on the coarse spacing: every decision point refines
    s.drift = 0.0
    assert s.refine_now(12, 3 * fine_dx)
    s.due = True  # a frame end, a new region, a replaced state
    assert s.refine_now(13, fine_dx)


@pytest.mark.parametrize("cfl, every", [(0.2, 4), (0.4, 4), (0.6, 3), (0.9, 2), (1.0, 2)])
def test_decision_points_come_before_the_cfl_bound_can_pass_the_margin(cfl, every):
    s = RefineSchedule(cfl=cfl, fine_dx=1.0)
    assert s.every == every
    assert s.every * cfl <= ACTIVATION_MARGIN + 1e-9


def _fast_jelly(cfl: float) -> sm.Scene:
    # a soft jelly ball at 20 m/s, about 9x its wave speed, leaving a refined box: its
    # children outside the region move about cfl fine cells a substep
    return sm.Scene(
        simulation=sm.SimulationSettings(domain_max=(1.6, 0.4, 0.4), dx=0.05, fps=50, cfl=cfl, gravity=(0, 0, 0),
                                         refinement={"mode": "adaptive", "factor": 2,
                                                     "boxes": [((0.0, 0.0, 0.0), (0.45, 0.4, 0.4))]}),
        materials=[sm.Elastic(name="jelly", youngs_modulus=4e3, poisson_ratio=0.3)],
        bodies=[sm.SphereBody(material="jelly", center=(0.25, 0.2, 0.2), radius=0.1, velocity=(20.0, 0, 0))])


def test_fast_children_never_reach_an_inactive_fine_node_at_a_high_cfl():
    """At cfl 0.9 four substeps move a fast child 3.6 fine cells, past the blocks' margin of
    2 nodes: with refinement every 4 steps whatever the cfl, level-1 stencils reached inactive
    nodes (their share of P2G dropped, their G2P short of weight). The schedule decides every
    2 steps there. The check is exact: every stencil node of every level-1 particle, after
    every substep."""
    sim = Simulation(_fast_jelly(0.9), device="cpu")
    solver, substep = sim.solver, sim.solver.substep
    missing, outside = [], []

    def checked(state):
        substep(state)
        fine = solver.grids[1]
        blocks = fine.spec.blocks.numpy()
        n = state.count
        x, level = state.x.numpy()[:n], state.level.numpy()[:n]
        base = np.floor((x[level == 1] - fine.origin) / fine.dx - 0.5).astype(int)
        out = 0
        for off in np.ndindex(3, 3, 3):
            c = (base + np.array(off)) >> 2
            out += int((blocks[c[:, 0], c[:, 1], c[:, 2]] < 0).sum())
        missing.append(out)
        outside.append(int((x[level == 1, 0] > 0.55).sum()))

    solver.substep = checked
    sim.advance(seconds=0.05)
    assert max(outside) > 100  # children left the region (a cell beyond it)
    assert len(missing) > 20 and max(missing) == 0


def test_water_at_rest_refines_about_once_a_frame():
    """Particles that barely move need no refinement between frame ends (the cost the
    schedule saves); a fixed schedule refined every 4 steps."""
    scene = sm.Scene(
        simulation=sm.SimulationSettings(domain_max=(0.4, 0.3, 0.2), dx=0.04, fps=20, walls={"type": "slip"},
                                         refinement={"mode": "adaptive", "factor": 2,
                                                     "boxes": [((0.2, 0.0, 0.0), (0.4, 0.3, 0.2))]}),
        materials=[sm.Fluid(name="water", bulk_modulus=2e4)],
        bodies=[sm.BoxBody(material="water", min=(0, 0, 0), max=(0.4, 0.12, 0.2))])
    sim = Simulation(scene, device="cpu")
    calls, refine = [], sim.solver.refine
    sim.solver.refine = lambda state: (calls.append(sim.steps), refine(state))
    sim.advance(frames=4)
    assert sim.steps >= 40
    # one at each frame start, and a few while the water settles from its sampled state
    assert len(calls) <= 4 + sim.steps / 8, (len(calls), sim.steps)
