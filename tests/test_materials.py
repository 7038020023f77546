"""Constitutive models: return mappings against their closed forms, and every
model running in a scene. Tolerances are float32 round-off unless stated."""

import numpy as np
import pytest
import warp as wp

import abmpm
from abmpm.scene import model as sm
from abmpm.sim.materials import (
    MaterialParams,
    kirchhoff_stress,
    material_params,
    update_deformation,
)
from abmpm.simulation import init_warp


@wp.kernel
def _update(mat: wp.array(dtype=MaterialParams), F: wp.array(dtype=wp.mat33), C: wp.array(dtype=wp.mat33),
            plastic: wp.array(dtype=float), dt: float, steps: int,
            F_out: wp.array(dtype=wp.mat33), plastic_out: wp.array(dtype=float)):
    i = wp.tid()
    f = F[i]
    pl = plastic[i]
    for _ in range(steps):
        d = update_deformation(mat[0], f, C[i], pl, dt)
        f = d.F
        pl = d.history
    F_out[i] = f
    plastic_out[i] = pl


@wp.kernel
def _stress(mat: wp.array(dtype=MaterialParams), F: wp.array(dtype=wp.mat33), tau: wp.array(dtype=wp.mat33)):
    i = wp.tid()
    tau[i] = kirchhoff_stress(mat[0], F[i], wp.mat33(0.0), 1.0)


def run_update(material, F, C=None, plastic=None, dt=1e-3, steps=1):
    init_warp()
    n = len(F)
    C = np.zeros((n, 3, 3), np.float32) if C is None else C
    plastic = np.ones(n, np.float32) if plastic is None else plastic
    mat = wp.array([material_params(material)], dtype=MaterialParams, device="cpu")
    F_out = wp.zeros(n, dtype=wp.mat33, device="cpu")
    p_out = wp.zeros(n, dtype=float, device="cpu")
    wp.launch(_update, dim=n, inputs=[mat, wp.array(F.astype(np.float32), dtype=wp.mat33), wp.array(C.astype(np.float32), dtype=wp.mat33),
                                      wp.array(plastic.astype(np.float32), dtype=float), dt, steps],
              outputs=[F_out, p_out], device="cpu")
    return F_out.numpy().astype(np.float64), p_out.numpy().astype(np.float64)


def log_singular_values(F):
    return np.log(np.linalg.svd(F, compute_uv=False))


def test_elastic_stress_vanishes_at_rest_and_rotation():
    init_warp()
    mat = wp.array([material_params(sm.Elastic(name="e", youngs_modulus=1e5))], dtype=MaterialParams, device="cpu")
    c, s = np.cos(0.7), np.sin(0.7)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    F = wp.array(np.stack([np.eye(3), R]).astype(np.float32), dtype=wp.mat33, device="cpu")
    tau = wp.zeros(2, dtype=wp.mat33, device="cpu")
    wp.launch(_stress, dim=2, inputs=[mat, F], outputs=[tau], device="cpu")
    # fixed-corotated energy is rotation invariant: no stress under a rigid rotation
    assert np.abs(tau.numpy()).max() < 1e-5 * 1e5


def test_fixed_corotated_uniaxial_stress_matches_closed_form():
    E, nu = 1e5, 0.25
    mu, lam = E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))
    init_warp()
    mat = wp.array([material_params(sm.Elastic(name="e", youngs_modulus=E, poisson_ratio=nu))], dtype=MaterialParams, device="cpu")
    F = np.diag([1.1, 0.95, 0.98]).astype(np.float32)
    tau = wp.zeros(1, dtype=wp.mat33, device="cpu")
    wp.launch(_stress, dim=1, inputs=[mat, wp.array(F[None], dtype=wp.mat33)], outputs=[tau], device="cpu")
    J = np.linalg.det(F.astype(np.float64))
    expected = 2 * mu * (F - np.eye(3)) @ F.T + lam * (J - 1) * J * np.eye(3)  # R = I for diagonal F
    assert np.allclose(tau.numpy()[0], expected, rtol=1e-4, atol=1e-2)


def test_fixed_corotated_stress_matches_the_float64_polar_decomposition():
    # tau = 2 mu (F - R) F^T + lam (J - 1) J I with R the polar factor of F, computed in
    # float64 by numpy's SVD, for rotated stretches from nearly flat (det F 0.03) to
    # strongly stretched (singular values 0.3-3). Tolerance: 1e-5 of the largest entry,
    # float32 round-off of a product of three F's (measured: 1.1e-6); with the float32
    # SVD's U V^T (the stress before the polar iteration) the same check reads 2.9e-3.
    E, nu = 1e5, 0.3
    mu, lam = E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))
    rng = np.random.default_rng(3)
    n = 2000
    Q = np.linalg.qr(rng.standard_normal((n, 3, 3)))[0]
    Q *= np.sign(np.linalg.det(Q))[:, None, None]  # rotations
    P = np.linalg.qr(rng.standard_normal((n, 3, 3)))[0]
    sig = np.exp(rng.uniform(np.log(0.3), np.log(3.0), (n, 3)))
    sig[: n // 4, 2] = rng.uniform(0.03, 0.1, n // 4) / (sig[: n // 4, 0] * sig[: n // 4, 1])  # nearly flat
    F = (Q @ P) @ (sig[:, :, None] * np.transpose(P, (0, 2, 1)))
    init_warp()
    mat = wp.array([material_params(sm.Elastic(name="e", youngs_modulus=E, poisson_ratio=nu))], dtype=MaterialParams, device="cpu")
    tau = wp.zeros(n, dtype=wp.mat33, device="cpu")
    wp.launch(_stress, dim=n, inputs=[mat, wp.array(F.astype(np.float32), dtype=wp.mat33)], outputs=[tau], device="cpu")
    F32 = F.astype(np.float32).astype(np.float64)
    U, s, Vt = np.linalg.svd(F32)
    R = U @ Vt
    J = np.linalg.det(F32)
    expected = 2 * mu * (F32 - R) @ np.transpose(F32, (0, 2, 1)) + (lam * (J - 1) * J)[:, None, None] * np.eye(3)
    err = np.abs(tau.numpy() - expected).max(axis=(1, 2)) / np.abs(expected).max(axis=(1, 2))
    assert err.max() < 1e-5, err.max()


def test_viscoelastic_deviatoric_strain_relaxes_exponentially():
    tau_relax, dt, steps = 0.05, 1e-3, 50
    F0 = np.diag([1.2, 0.9, 1.0])
    F, _ = run_update(sm.Viscoelastic(name="v", relaxation_time=tau_relax), F0[None], dt=dt, steps=steps)
    e0, e = log_singular_values(F0), log_singular_values(F[0])
    # volume (sum of log strains) is kept; the deviatoric part decays as exp(-t/tau)
    assert abs(e.sum() - e0.sum()) < 1e-5
    dev0, dev = e0 - e0.mean(), e - e.mean()
    assert np.allclose(np.sort(dev), np.sort(dev0) * np.exp(-steps * dt / tau_relax), atol=1e-5)


def test_sand_return_mapping_cone():
    sand = sm.Sand(name="s", youngs_modulus=1e5, poisson_ratio=0.3, friction_angle=30.0)
    # tension: cohesionless sand is projected to the cone tip (no elastic strain)
    F, _ = run_update(sand, np.diag([1.05, 1.02, 1.0])[None], dt=0.0)
    assert np.allclose(np.linalg.svd(F[0], compute_uv=False), 1.0, atol=1e-5)
    # pure compression: inside the cone, unchanged
    Fc = np.diag([0.98, 0.98, 0.98])
    F, _ = run_update(sand, Fc[None], dt=0.0)
    assert np.allclose(F[0], Fc, atol=1e-6)
    # compression with large shear: projected onto the cone surface, where the
    # Drucker-Prager yield function (Klar et al. 2016) is zero
    Fs = np.diag([0.85, 1.10, 1.0])  # yield function +0.11 before projection
    F, _ = run_update(sand, Fs[None], dt=0.0)
    mu, lam = 1e5 / 2.6, 1e5 * 0.3 / (1.3 * 0.4)
    e = log_singular_values(F[0])
    s = np.sin(np.radians(30.0))
    alpha = np.sqrt(2 / 3) * 2 * s / (3 - s)
    yield_fn = np.linalg.norm(e - e.mean()) + (3 * lam + 2 * mu) / (2 * mu) * e.sum() * alpha
    assert abs(yield_fn) < 1e-4 and not np.allclose(F[0], Fs, atol=1e-3)


def test_snow_clamps_singular_values_and_hardens():
    snow = sm.Snow(name="snow", critical_compression=0.025, critical_stretch=0.0075)
    F0 = np.diag([0.9, 1.05, 1.0])
    F, Jp = run_update(snow, F0[None], dt=0.0)
    sv = np.linalg.svd(F[0], compute_uv=False)
    assert sv.min() >= 1 - 0.025 - 1e-6 and sv.max() <= 1 + 0.0075 + 1e-6
    # J_E J_P = J of the trial F (Stomakhin et al. 2013): the plastic part takes the rest
    assert np.isclose(np.prod(sv) * Jp[0], np.linalg.det(F0), rtol=1e-5)


def test_fluid_volume_ratio_follows_divergence():
    dt, steps, div = 1e-3, 100, 0.5  # C = (div/3) I: uniform expansion rate div
    C = (div / 3) * np.eye(3)[None]
    F, J = run_update(sm.Fluid(name="w"), np.eye(3)[None], C=C, dt=dt, steps=steps)
    # J <- det(I + dt C) J each step: (1 + dt div/3)^(3 steps); float32 products
    # over 100 steps accumulate ~100 x 6e-8 relative error, so rtol 1e-4
    assert np.isclose(J[0], (1 + dt * div / 3) ** (3 * steps), rtol=1e-4)
    assert np.allclose(F[0], np.eye(3))  # a fluid keeps no deformation gradient


@pytest.mark.parametrize("material", [
    sm.Fluid(name="m", viscosity=0.5), sm.Elastic(name="m"), sm.Viscoelastic(name="m"),
    sm.Sand(name="m"), sm.Snow(name="m", youngs_modulus=1.4e5),
])
def test_every_material_falls_and_settles_without_blowing_up(material):
    scene = abmpm.Scene(
        simulation=abmpm.SimulationSettings(dx=0.05, fps=20, domain_max=(1.0, 0.8, 1.0)),
        materials=[material],
        bodies=[abmpm.SphereBody(material="m", center=(0.5, 0.35, 0.5), radius=0.15, velocity=(0.0, -1.0, 0.0))],
    )
    sim = abmpm.Simulation(scene, device="cpu")
    lowest = []
    sim.advance(frames=8, callback=lambda s: lowest.append(s.particles().x[:, 1].min()))  # 0.4 s
    p = sim.particles()
    assert np.isfinite(p.x).all() and np.isfinite(p.F).all()
    # no particle goes through the floor (by more than the half cell walls allow)
    assert min(lowest) > -0.5 * 0.05 and p.x[:, 1].max() < 0.8
    assert min(lowest) < 0.05  # it did reach the floor


@pytest.mark.parametrize("bodies", ["fluid only", "fluid and elastic"])
def test_kernels_for_a_scenes_models_match_the_kernels_for_every_model(bodies):
    """A scene's transfers are compiled for the models it uses (one model: no test at
    all; two: a test between those two). They must compute what the kernels over
    every registered model compute. A dispatch that reached the wrong model (an
    off-by-one id, a lost branch) differs at the first step by the whole stress.
    Tolerance: 1e-6 m after 20 steps, float32 round-off of positions near 0.5 m
    (the two builds may contract multiply-adds differently)."""
    from abmpm.sim.materials import ALL_MODELS

    materials = [abmpm.Fluid(name="water", bulk_modulus=1e4, viscosity=0.05)]
    # the water lands on the floor and the jelly runs into it: both are stressed from the first steps
    parts = [abmpm.BoxBody(material="water", min=(0.2, 0.0, 0.2), max=(0.5, 0.3, 0.5), velocity=(1.0, -1.0, 0.0))]
    if bodies == "fluid and elastic":
        materials.append(abmpm.Elastic(name="jelly", youngs_modulus=2e4))
        parts.append(abmpm.SphereBody(material="jelly", center=(0.62, 0.2, 0.35), radius=0.12, velocity=(-2.0, 0, 0)))
    scene = abmpm.Scene(simulation=abmpm.SimulationSettings(dx=0.05, fps=60), materials=materials, bodies=parts)
    runs = []
    for every_model in (False, True):
        sim = abmpm.Simulation(scene, device="cpu")
        if every_model:
            sim.solver.models = ALL_MODELS
        else:
            assert len(sim.solver.models) == len(materials) < len(ALL_MODELS)
        for _ in range(20):
            sim.step()
        runs.append(sim.particles())
    a, b = runs
    moved = np.abs(a.x - scene_start(scene)).max()
    assert moved > 1e-3  # the bodies did move (and collide, with two)
    assert np.abs(a.x - b.x).max() < 1e-6
    assert np.abs(a.J - b.J).max() < 1e-5


def scene_start(scene):
    return abmpm.Simulation(scene, device="cpu").particles().x
