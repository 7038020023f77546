"""Adaptive against finest where particles change level (issue: the level interface
made right). Each case runs the same scene in adaptive and finest mode and compares
them, or checks a law the fine grid obeys (hydrostatics). Tolerances are stated
inline."""

import numpy as np
import pytest

import abmpm
from abmpm.geometry.sampling import lattice_spacing
from abmpm.inputs import JITTER, sample_scene

RHO, G, K = 1000.0, 9.81, 4.0e4  # water at rest: density, gravity, a soft bulk modulus
W, DEPTH, Z = 0.8, 0.25, 0.2  # the tank; its right half is a refinement box


def tank(mode, dx=0.05, b=2):
    return abmpm.Scene(
        simulation=abmpm.SimulationSettings(
            domain_max=(W, 0.4, Z), dx=dx, fps=20, walls={"type": "slip"},
            refinement={"mode": mode, "factor": b, "boxes": [((W / 2, 0.0, 0.0), (W, 0.4, Z))]}),
        materials=[abmpm.Fluid(name="water", density=RHO, bulk_modulus=K)],
        bodies=[abmpm.BoxBody(material="water", min=(0, 0, 0), max=(W, DEPTH, Z))])


def hydrostatic_J(y):
    # Tait with gamma = 7: p = K/7 (J^-7 - 1) = rho g depth
    return (1.0 + 7.0 * RHO * G * np.clip(DEPTH - y, 0.0, None) / K) ** (-1.0 / 7.0)


def test_adaptive_parents_have_the_fine_lattice_jitter():
    # A family inherits its parent's jitter: with the coarse jitter (a quarter of the
    # parent spacing h, i.e. b/4 child spacings) neighbouring families overlapped or
    # left gaps of up to b/2 child spacings. Parents that may split are jittered like
    # finest mode's particles: at most JITTER/2 of a child spacing per axis.
    for b in (2, 4):
        scene = tank("adaptive", b=b)
        st = scene.simulation
        h = lattice_spacing(st.dx, 8)
        x = sample_scene(scene, b)["x"].astype(np.float64)
        off = x - (np.floor(x / h) + 0.5) * h  # from the unjittered lattice point
        assert np.abs(off).max() <= 0.5 * JITTER * h / b * (1 + 1e-4)
        assert np.abs(off).max() > 0.25 * JITTER * h / b  # still jittered
        # the same random draws scaled: the count and the pattern do not change
        coarse = sample_scene(scene, 1)["x"].astype(np.float64)
        assert len(coarse) == len(x)
        assert np.allclose(coarse - (np.floor(x / h) + 0.5) * h, b * off, atol=1e-6)


def _settled(mode):
    sim = abmpm.Simulation(tank(mode), device="cpu")
    p = sim.particles().by_id()
    sim.set_particles(history=hydrostatic_J(p.x[:, 1]).astype(np.float32))  # start at rest, hydrostatic
    sim.advance(seconds=0.3)
    return sim.particles()


@pytest.mark.slow
def test_tank_at_rest_across_the_level_interface():
    fine, ada = _settled("finest"), _settled("adaptive")
    dx = 0.05

    def spread(p, sel):
        # J minus its hydrostatic value, 1st to 99th percentile, away from the free
        # surface and the floor (two coarse cells)
        inner = sel & (p.x[:, 1] < DEPTH - 2 * dx) & (p.x[:, 1] > 2 * dx)
        d = p.J[inner] - hydrostatic_J(p.x[inner, 1])
        return np.percentile(d, 99) - np.percentile(d, 1)

    s_fine = spread(fine, np.ones(len(fine.x), bool))
    s_ada = spread(ada, ada.level == 1)
    # Finest's own spread (0.027 at this size) comes from its sampling jitter. The
    # children of a family share their parent's offset (correlated jitter of the
    # same amplitude), which may add up to sqrt(2) of it: 1.5x. Measured 1.27x
    # (0.035); 2.85x (0.078) before the parents were jittered at the fine scale and
    # reconstruction stopped moving the families along the walls and the floor.
    assert s_ada < 1.5 * s_fine, (s_ada, s_fine)
    # nothing moves much faster than in the finest tank: 1.5x its fastest particle,
    # the margin of the spread above (measured 1.03x)
    v_fine = np.linalg.norm(fine.v, axis=1).max()
    v_ada = np.linalg.norm(ada.v, axis=1).max()
    assert v_ada < 1.5 * v_fine, (v_ada, v_fine)
