"""Adaptive against finest where particles change level (issue: the level interface
made right). Each case runs the same scene in adaptive and finest mode and compares
them, or checks a law the fine grid obeys (hydrostatics). Tolerances are stated
inline."""

import numpy as np
import pytest

import abmpm
from abmpm.geometry.sampling import lattice_spacing
from abmpm.inputs import JITTER, sample_scene
from abmpm.scene import model as sm

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


def plate_with_slit(mode, slit_cells, b, dx=0.04):
    """Water falling 0.04 m onto a zero-thickness plate that spans the box; its only
    way down is a slit ``slit_cells`` coarse cells wide across the box (the case the
    audit found adaptive mode passing half of finest's mass through)."""
    W, Z, yp = 0.4, 0.16, 0.2
    half = (W - slit_cells * dx) / 2
    plates = [sm.SheetCollider(size=(half, Z + 0.1), center=(c, yp, Z / 2))
              for c in (half / 2, W - half / 2)]
    scene = abmpm.Scene(
        simulation=abmpm.SimulationSettings(domain_max=(W, 0.5, Z), dx=dx, fps=10, max_dt=2e-3,
                                            walls={"type": "slip"}, refinement={"mode": mode, "factor": b}),
        materials=[abmpm.Fluid(name="water", bulk_modulus=2e4)],
        bodies=[abmpm.BoxBody(material="water", min=(0, 0.24, 0), max=(W, 0.44, Z))], colliders=plates)
    return scene, yp


@pytest.mark.slow
@pytest.mark.parametrize("slit_cells", [0.5, 1.0])
def test_slit_outside_the_paper_drains_like_finest(slit_cells):
    # A regression guard of the matrix in docs/method.md ("The level interface
    # against finest"), the cases that run in seconds: b = 2, default refinement
    # (feature criterion, reconstruction, merge), 0.5 s.
    out = {}
    for mode in ("adaptive", "finest"):
        scene, yp = plate_with_slit(mode, slit_cells, 2)
        sim = abmpm.Simulation(scene, device="cpu")
        p = sim.particles()
        M = p.mass.astype(np.float64).sum()
        sim.advance(seconds=0.5)
        p = sim.particles()
        out[mode] = (p.mass[p.x[:, 1] < yp].astype(np.float64).sum() / M, sim.steps)
    (a, steps_a), (f, steps_f) = out["adaptive"], out["finest"]
    assert f > 0.01  # the case is what it says: water does go through
    # the bound: the outcome within 10% of finest (measured 0.93 and 0.96)
    assert abs(a - f) < 0.10 * f, out
    # Steps: the goal is 5% above finest, not reached on every case yet
    # (measured 1.18 and 0.94): 1.25 guards against a compressed band coming back.
    assert steps_a < 1.25 * steps_f, out
