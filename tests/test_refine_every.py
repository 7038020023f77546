"""How often adaptive mode refines (``refine.refine_every``): often enough that no level-1
particle ever reaches a fine node outside the active blocks, whatever the CFL number."""

import numpy as np
import pytest

from abmpm.scene import model as sm
from abmpm.sim.refine import ACTIVATION_MARGIN, refine_every
from abmpm.simulation import Simulation


@pytest.mark.parametrize("cfl, every", [(0.2, 4), (0.4, 4), (0.6, 3), (0.9, 2), (1.0, 2)])
def test_refinement_comes_before_the_cfl_bound_can_pass_the_margin(cfl, every):
    # a substep moves a particle at most cfl fine cells; the blocks reach ACTIVATION_MARGIN beyond
    assert refine_every(cfl) == every
    assert every * cfl <= ACTIVATION_MARGIN + 1e-9


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
    nodes (their share of P2G dropped, their G2P short of weight). It refines every 2 steps
    there. The check is exact: every stencil node of every level-1 particle, after
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
