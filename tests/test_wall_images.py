"""Image stress at the domain walls (``walls.images``, sim/wall_images.py): a tank of
water at rest against hydrostatics, and a separating wall that never pulls."""

import numpy as np
import pytest

from abmpm.bench.interface import K, RHO, G, TANK_DEPTH, TANK_DX, hydrostatic_J, tank_at_rest
from abmpm.scene import model as sm
from abmpm.simulation import Simulation


def settle(mode: str, images: bool, seconds: float = 0.3):
    """The tank at rest started from hydrostatic J: its fastest particle over the run and
    the mean pressure minus rho g depth of the particles within a coarse cell of the floor
    (away from the side walls)."""
    sim = Simulation(tank_at_rest(mode, TANK_DX, 2, wall_images=images), device="cpu")
    sim.set_particles(history=hydrostatic_J(sim.particles().by_id().x[:, 1]).astype(np.float32))
    fastest = 0.0
    for _ in range(round(seconds / 0.05)):
        sim.advance(seconds=0.05)
        fastest = max(fastest, float(np.linalg.norm(sim.particles().v, axis=1).max()))
    p = sim.particles()
    excess = K / 7 * (p.J.astype(np.float64) ** -7.0 - 1.0) - RHO * G * np.clip(TANK_DEPTH - p.x[:, 1], 0, None)
    x, y, z = p.x[:, 0], p.x[:, 1], p.x[:, 2]
    floor = (x > 0.05) & (x < 0.75) & (z > 0.03) & (z < 0.17) & (y < TANK_DX)
    return fastest, float(excess[floor].mean())


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["original", "finest"])
def test_wall_images_hold_a_tank_at_rest(mode):
    # Hydrostatics is exact: water started at rho g depth has nothing to do. Without images
    # each grid's truncated stencils at the walls find their own equilibrium, and the tank
    # moves while it settles into it: measured over 0.3 s (dx 0.05, b = 2 for finest) the
    # fastest particle 0.064 (original) and 0.101 m/s (finest), the water within a coarse
    # cell of the floor 161 Pa above rho g depth in original mode. With images 0.014 and
    # 0.019 m/s, 11 and 12 Pa. Bounds: a third of the speed without images (what is left is
    # the settling of the sampling jitter), and the floor within 50 Pa, 2.5% of the floor's
    # rho g depth (1,962 Pa).
    fastest_off, _ = settle(mode, False)
    fastest_on, excess_on = settle(mode, True)
    assert fastest_on < fastest_off / 3, (fastest_on, fastest_off)
    assert abs(excess_on) < 50.0, excess_on


def lifted_block(images: bool, wall: str) -> Simulation:
    scene = sm.Scene(
        simulation=sm.SimulationSettings(domain_max=(0.4, 0.4, 0.4), dx=0.05, gravity=(0.0, 0.0, 0.0), fps=100,
                                         walls={"type": wall, "images": images}),
        materials=[sm.Fluid(name="water", density=1000.0, bulk_modulus=4.0e4)],
        bodies=[sm.BoxBody(material="water", min=(0.1, 0.0, 0.1), max=(0.3, 0.1, 0.3), velocity=(0.0, 0.2, 0.0))])
    sim = Simulation(scene, device="cpu")
    n = len(sim.particles().x)
    sim.set_particles(history=np.full(n, 1.01, np.float32))  # stretched: the water pulls (p < 0)
    return sim


def test_a_separating_wall_image_never_pulls():
    # Water in tension (J = 1.01, Tait pressure -K/7 (1 - 1.01^-7) = -380 Pa) rising off the
    # floor: a separating wall lets it go, so its images must add nothing (bit for bit the
    # run without them); a slip wall holds the normal motion both ways and its images pull,
    # so the same run there must differ (this test can tell images that act from images
    # that do not).
    for wall, same in (("separate", True), ("slip", False)):
        runs = []
        for images in (False, True):
            sim = lifted_block(images, wall)
            for _ in range(5):
                sim.step()
            runs.append(sim.particles().by_id())
        identical = np.array_equal(runs[0].x, runs[1].x) and np.array_equal(runs[0].v, runs[1].v)
        assert identical == same, wall
