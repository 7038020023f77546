"""Validation of the uniform-grid MLS-MPM core against analytic results and
conservation laws. Each tolerance is stated with its reason next to the assertion."""

import numpy as np
import pytest

import abmpm
from abmpm import BoxBody, Elastic, Fluid, Scene, SimulationSettings, SphereBody

G = 9.81


def make_sim(materials, bodies, **settings):
    return abmpm.Simulation(
        Scene(simulation=SimulationSettings(**settings), materials=materials, bodies=bodies), device="cpu"
    )


def test_free_fall_matches_half_g_t_squared():
    sim = make_sim(
        [Elastic(name="jelly", youngs_modulus=2e4)],
        [BoxBody(material="jelly", min=(0.4, 0.6, 0.4), max=(0.6, 0.8, 0.4 + 0.2))],
        dx=0.04, fps=20,
    )
    y0 = sim.particles().by_id().x[:, 1].astype(np.float64)
    sim.advance(frames=4)  # 0.2 s: falls 0.196 m, the body stays well above the floor
    t, dt = sim.time, sim.dt
    drop = y0 - sim.particles().by_id().x[:, 1].astype(np.float64)
    # Symplectic Euler (grid velocity updated before the move) gives exactly
    # 0.5 g t (t + dt); it differs from 0.5 g t^2 by 0.5 g t dt. Tolerance: that
    # O(dt) term plus float32 round-off of positions ~ 1e-6 m.
    assert np.abs(drop - 0.5 * G * t * t).max() <= 0.5 * G * t * dt + 1e-5
    assert np.abs(drop - 0.5 * G * t * (t + dt)).max() < 1e-5
    v = sim.particles().v
    # every particle falls at -g t (no stress in a free-falling body); float32 round-off
    assert np.allclose(v[:, 1], -G * t, atol=1e-4) and np.abs(v[:, [0, 2]]).max() < 1e-4


def _two_body_collision(gravity=(0.0, 0.0, 0.0)):
    return make_sim(
        [Elastic(name="a", youngs_modulus=5e4, poisson_ratio=0.3, density=800.0),
         Fluid(name="w", bulk_modulus=5e4, viscosity=0.1)],
        [SphereBody(material="a", center=(0.35, 0.5, 0.5), radius=0.1, velocity=(1.5, 0.2, 0.0)),
         BoxBody(material="w", min=(0.55, 0.4, 0.4), max=(0.75, 0.6, 0.6), velocity=(-1.0, 0.0, 0.3))],
        dx=0.025, fps=20, gravity=gravity,
    )


def test_mass_exact_and_linear_momentum_conserved_without_gravity_or_walls():
    sim = _two_body_collision()
    p0 = sim.particles().by_id()
    P0 = (p0.mass[:, None].astype(np.float64) * p0.v).sum(axis=0)
    scale = (p0.mass.astype(np.float64) * np.linalg.norm(p0.v, axis=1)).sum()
    sim.advance(frames=4)  # 0.2 s: the sphere and the water block collide
    p = sim.particles().by_id()
    assert len(p) == len(p0)
    # particle masses never change and none is lost: the sums are bit-identical
    assert p.mass.astype(np.float64).sum() == p0.mass.astype(np.float64).sum()
    assert np.all(p.x > 0.0) and np.all(p.x < 1.0)
    P = (p.mass[:, None].astype(np.float64) * p.v).sum(axis=0)
    # P2G, internal forces and G2P conserve momentum exactly in exact arithmetic;
    # float32 atomics over ~1e4 particles x 27 nodes x a few hundred steps drift by
    # ~1e-6 of the momentum scale sum(m|v|); 1e-5 leaves a 10x margin.
    assert np.abs(P - P0).max() / scale < 1e-5
    # the collision really happened (otherwise the test proves nothing)
    assert abs(P[0] - P0[0]) / scale < 1e-5 and np.abs(p.v[:, 0] - p0.v[:, 0]).max() > 0.3


def test_angular_momentum_of_spinning_ball_apic():
    sim = make_sim(
        [Elastic(name="ball", youngs_modulus=1e5, poisson_ratio=0.3)],
        [SphereBody(material="ball", center=(0.5, 0.5, 0.5), radius=0.15, angular_velocity=(0.0, 0.0, 6.0))],
        dx=0.03, fps=50, gravity=(0.0, 0.0, 0.0),
    )
    L0 = np.array(sim.diagnostics()["angular_momentum"])
    while sim.steps < 200:
        sim.step()
    L = np.array(sim.diagnostics()["angular_momentum"])
    # APIC conserves angular momentum (Jiang et al. 2015) including the affine
    # part; over 200 steps float32 round-off stays far below the 1e-3 asked.
    assert np.linalg.norm(L - L0) / np.linalg.norm(L0) < 1e-3
    assert L0[2] > 0 and sim.steps >= 200


def test_elastic_bar_axial_wave_speed():
    """First axial mode of a free-free bar: period T = 2 L / c with c = sqrt(E / rho)."""
    E, rho, L = 1e5, 1000.0, 1.0
    c = np.sqrt(E / rho)
    sim = make_sim(
        [Elastic(name="bar", youngs_modulus=E, poisson_ratio=0.3, density=rho)],
        [BoxBody(material="bar", min=(0.1, 0.45, 0.45), max=(0.1 + L, 0.55, 0.55))],
        domain_max=(1.2, 1.0, 1.0), dx=0.02, fps=100, gravity=(0.0, 0.0, 0.0),
    )
    p = sim.particles().by_id()
    xi = (p.x[:, 0] - 0.1) / L
    V = 0.02  # m/s: strain amplitude pi V / c ~ 6e-3, linear regime
    sim.set_particles(v=np.stack([V * np.cos(np.pi * xi), 0 * xi, 0 * xi], axis=1).astype(np.float32))
    left = xi < 0.5
    m = p.mass.astype(np.float64)
    times, mom = [], []
    T_theory = 2 * L / c
    while sim.time < 1.3 * T_theory:
        sim.step()
        q = sim.particles().by_id()
        times.append(sim.time)
        mom.append((m[left] * q.v[left, 0]).sum())  # ~ cos(2 pi t / T)
    times, mom = np.array(times), np.array(mom)
    s = np.sign(mom)
    idx = np.nonzero(s[1:] != s[:-1])[0]
    assert len(idx) >= 2, "the bar did not oscillate"
    # linear interpolation of the zero crossings at T/4 and 3T/4
    tz = [times[i] - mom[i] * (times[i + 1] - times[i]) / (mom[i + 1] - mom[i]) for i in idx[:2]]
    T = 2.0 * (tz[1] - tz[0])
    # 5% (the bound): at 50 cells per half wavelength the MPM dispersion
    # error is ~1%; the bar is 5 cells thick, thin enough for 1D bar theory.
    assert abs(T - T_theory) / T_theory < 0.05, (T, T_theory)


def test_fluid_at_rest_reaches_hydrostatic_pressure():
    """A weakly compressible water column in a tank: p(h) = rho g h."""
    from abmpm.sim.materials import pressure_from_J

    K, gamma, rho, H, dx, W = 2e5, 7.0, 1000.0, 0.3, 0.02, 0.24
    sim = make_sim(
        [Fluid(name="water", bulk_modulus=K, gamma=gamma, viscosity=1.0, density=rho)],
        [BoxBody(material="water", min=(0, 0, 0), max=(W, H, W))],
        domain_max=(W, 0.4, W), dx=dx, fps=50, walls=abmpm.Walls(type="slip"),
    )
    sim.advance(seconds=0.5)  # the column settles from its uncompressed start
    x_start = sim.particles().by_id().x
    depths = np.array([0.05, 0.1, 0.15, 0.2, 0.25])
    p_mean = np.zeros(len(depths))
    samples = 0
    # The column rings in its vertical acoustic mode (period 4H/c ~ 0.085 s) with a
    # small amplitude; average the pressure over 0.4 s (~5 periods), every 4 steps.
    while sim.time < 0.9:
        for _ in range(4):
            sim.step()
        p = sim.particles()
        pressure = pressure_from_J(K, gamma, p.J.astype(np.float64))
        central = (np.abs(p.x[:, 0] - W / 2) < W / 4) & (np.abs(p.x[:, 2] - W / 2) < W / 4)  # away from walls
        order = np.argsort(-p.x[:, 1])
        mass_above = np.cumsum(p.mass[order].astype(np.float64))
        for k, h in enumerate(depths):
            # depth h of undisturbed water (rho h per unit area) above this height;
            # the column is ~1% compressed, so this is where rho g h must hold
            y_h = p.x[order[np.searchsorted(mass_above, rho * h * W * W)], 1]
            p_mean[k] += pressure[central & (np.abs(p.x[:, 1] - y_h) < dx / 2)].mean()
        samples += 1
    p_mean /= samples
    ratio = p_mean / (rho * G * depths)
    # 5% (the bound): measured 1-4%, from the wall/free-surface layers of
    # half a cell and the residual ringing that the time average leaves.
    assert np.all(np.abs(ratio - 1.0) < 0.05), ratio
    # at rest: over the averaging window no particle moved a tenth of a cell
    drift = np.linalg.norm(sim.particles().by_id().x - x_start, axis=1).max()
    assert drift < 0.1 * dx, drift


# Martin & Moyce (1952), Phil. Trans. R. Soc. Lond. A 244, 312-324: surge front of a
# collapsing water column (width a, height 2a) on a dry floor, tabulated run with
# a = 2.25 in; Z = x_front / a from the wall, T = t sqrt(2 g / a).
MARTIN_MOYCE_T_Z = np.array([
    [0.41, 1.11], [0.84, 1.22], [1.19, 1.44], [1.43, 1.67], [1.63, 1.89], [1.83, 2.11],
    [1.98, 2.33], [2.20, 2.56], [2.32, 2.78], [2.51, 3.00],
])


def test_dam_break_front_matches_martin_moyce():
    a, dx = 0.1, 0.01  # resolution a/10: 10 x 20 cells in the column, slab 4 cells thick
    sim = make_sim(
        [Fluid(name="water", bulk_modulus=4e5)],  # c = 20 m/s, 10x the surge speed
        [BoxBody(material="water", min=(0, 0, 0), max=(a, 2 * a, 4 * dx))],
        domain_max=(0.5, 0.25, 4 * dx), dx=dx, fps=200, walls=abmpm.Walls(type="slip"),
    )
    scale = np.sqrt(2 * G / a)
    T, Z = [0.0], [a / a]
    while T[-1] < 2.6:
        sim.advance(frames=1)
        T.append(sim.time * scale)
        Z.append(sim.particles().x[:, 0].max() / a)  # leading edge
    Z_sim = np.interp(MARTIN_MOYCE_T_Z[:, 0], T, Z)
    err = Z_sim / MARTIN_MOYCE_T_Z[:, 1] - 1.0
    # 10% (the bound). Measured within 5.3% at a/10. At a/20 the front runs
    # up to 11% ahead, as published simulations commonly do against this
    # experiment (the gate release delays the real surge); see docs/validation.md.
    assert np.abs(err).max() < 0.10, np.round(err, 3)


@pytest.mark.parametrize("friction_angle", [20.0, 30.0, 40.0])
def test_granular_column_collapse_slope_follows_friction_angle(friction_angle):
    dx, H0 = 0.01, 0.1
    walls = abmpm.Walls(type="slip", y_min={"type": "sticky"})  # rough floor, smooth side walls
    sim = make_sim(
        [abmpm.Sand(name="sand", density=1600, youngs_modulus=1e5, poisson_ratio=0.3,
                    friction_angle=friction_angle)],
        [BoxBody(material="sand", min=(0, 0, 0), max=(H0, H0, 4 * dx))],
        domain_max=(0.5, H0 + 0.02, 4 * dx), dx=dx, fps=25, walls=walls,
    )
    sim.advance(seconds=0.6)  # collapse is over by ~0.3 s
    assert sim.diagnostics()["max_speed"] < 0.02  # at rest
    x = sim.particles().x
    edges = np.arange(0.0, x[:, 0].max() + dx, dx)
    col = np.digitize(x[:, 0], edges) - 1
    height = np.array([x[col == i, 1].max() if (col == i).any() else 0.0 for i in range(len(edges) - 1)])
    centre = edges[:-1] + dx / 2
    # straight part of the slope: between 20% and 80% of the pile height, downhill side
    on_slope = (height > 0.2 * height.max()) & (height < 0.8 * height.max()) & (centre > centre[np.argmax(height)])
    slope = -np.polyfit(centre[on_slope], height[on_slope], 1)[0]
    angle = np.degrees(np.arctan(slope))
    # 4 degrees (the bound): a cohesionless Drucker-Prager pile settles at
    # its friction angle; measured 1.5-2.5 degrees below it at this resolution.
    assert abs(angle - friction_angle) < 4.0, angle
