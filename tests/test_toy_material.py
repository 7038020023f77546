"""A new material is one new file plus one registry line.

The test copies the package, writes one module for a toy material (small-strain
Hookean elasticity, with device fields of its own) into ``sim/materials/`` and adds
its name to ``MODULES``, changing exactly one line. Then, in a fresh interpreter on
that copy:

* a TOML scene using ``model = "hookean"`` loads, with the toy's defaults, and a
  typo in one of its keys is refused naming the field (the schema came from the
  module's declaration);
* the stress dispatch reaches the toy: tau = lambda tr(eps) I + 2 mu eps with
  eps = (F + F^T)/2 - I, against the closed form (float32 round-off, 1e-5 relative);
* a block of the toy material falls freely for 0.1 s through the real transfer
  kernels: internal forces cancel, so its centre of mass follows symplectic Euler
  exactly, y_n = y0 - g dt^2 n (n + 1) / 2 with dt = max_dt = 1e-3 s (the CFL step,
  0.4 dx / 7.9 m/s ~ 2.5e-3 s, is longer). Tolerance 2e-5 m: float32 positions
  near 0.7 m round off by ~6e-8 m per step, over 100 steps.
"""

import textwrap

TOY = textwrap.dedent(
    '''
    """Toy: small-strain Hookean solid (test of the material registry)."""

    from typing import Any

    import warp as wp

    from .base import Deformation, MaterialModel, Parameter
    from .common import lame, p_wave_speed, trial_deformation


    @wp.func
    def stress(mat: Any, F: wp.mat33, C: wp.mat33, history: float):
        eps = 0.5 * (F + wp.transpose(F)) - wp.identity(n=3, dtype=float)
        tr = eps[0, 0] + eps[1, 1] + eps[2, 2]
        return 2.0 * mat.toy_mu * eps + wp.identity(n=3, dtype=float) * (mat.toy_lam * tr)


    @wp.func
    def update(mat: Any, F: wp.mat33, C: wp.mat33, history: float, dt: float):
        out = Deformation()
        out.F = trial_deformation(F, C, dt)
        out.history = history
        return out


    def values(m):
        mu, lam = lame(m.youngs_modulus, m.poisson_ratio)
        return {"toy_mu": mu, "toy_lam": lam}


    MODEL = MaterialModel(
        name="hookean",
        doc=__doc__.strip(),
        parameters=(
            Parameter("youngs_modulus", 2.0e4, "E, Pa", gt=0.0),
            Parameter("poisson_ratio", 0.25, "nu", gt=-1.0, lt=0.5),
        ),
        device_fields={"toy_mu": float, "toy_lam": float},
        device_values=values,
        wave_speed=p_wave_speed,
        stress=stress,
        update=update,
    )
    '''
)

SCENE = textwrap.dedent(
    """
    name = "toy"
    [simulation]
    dx = 0.05
    domain_min = [0.0, 0.0, 0.0]
    domain_max = [1.0, 1.0, 1.0]
    duration = 0.1
    fps = 10
    max_dt = 1.0e-3
    [[materials]]
    name = "toy"
    model = "hookean"
    density = 500.0
    [[bodies]]
    shape = "box"
    material = "toy"
    min = [0.4, 0.6, 0.4]
    max = [0.6, 0.8, 0.6]
    """
)

CHECK = textwrap.dedent(
    """
    import json, sys
    import numpy as np
    import warp as wp
    from abmpm.errors import SceneError
    from abmpm.scene.loader import load_scene
    from abmpm.sim import materials as M
    from abmpm.simulation import Simulation, init_warp

    out = {"models": [m.name for m in M.REGISTRY]}
    scene = load_scene(sys.argv[1])
    mat = scene.materials[0]
    out["defaults"] = [mat.youngs_modulus, mat.poisson_ratio]
    try:
        load_scene(sys.argv[2])
    except SceneError as exc:
        out["typo_error"] = str(exc)

    init_warp()

    @wp.kernel
    def stress(m: wp.array(dtype=M.MaterialParams), F: wp.array(dtype=wp.mat33), tau: wp.array(dtype=wp.mat33)):
        i = wp.tid()
        tau[i] = M.kirchhoff_stress(m[0], F[i], wp.mat33(0.0), 1.0)

    F = np.array([[1.01, 0.02, 0.0], [0.0, 0.98, 0.01], [0.005, 0.0, 1.02]], np.float32)
    tau = wp.zeros(1, dtype=wp.mat33, device="cpu")
    rows = wp.array([M.material_params(mat)], dtype=M.MaterialParams, device="cpu")
    wp.launch(stress, 1, inputs=[rows, wp.array(F[None], dtype=wp.mat33, device="cpu")], outputs=[tau], device="cpu")
    out["tau"] = tau.numpy()[0].tolist()
    out["F"] = F.tolist()

    sim = Simulation(scene, device="cpu")
    y0 = float(sim.particles().x[:, 1].astype(np.float64).mean())
    sim.advance(seconds=0.1)
    p = sim.particles()
    out["t"] = sim.time
    out["steps"] = sim.steps
    out["dy"] = float(p.x[:, 1].astype(np.float64).mean()) - y0
    out["finite"] = bool(np.isfinite(p.x).all())
    print("RESULT " + json.dumps(out))
    """
)


def test_a_new_material_is_one_file_and_one_registry_line(tmp_path, registry_copy):
    registry_copy.register("sim/materials", "hookean", TOY, last="snow")
    scene = tmp_path / "toy.toml"
    scene.write_text(SCENE)
    typo = tmp_path / "typo.toml"
    typo.write_text(SCENE.replace('density = 500.0', 'density = 500.0\nyoungs_modulos = 1.0e4'))
    out = registry_copy.run(CHECK, scene, typo)

    assert out["models"][-1] == "hookean"
    assert out["defaults"] == [2.0e4, 0.25]
    assert "materials[0].youngs_modulos: unknown key" in out["typo_error"]

    import numpy as np

    E, nu = 2.0e4, 0.25
    mu, lam = E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))
    F = np.array(out["F"], dtype=np.float64)
    eps = 0.5 * (F + F.T) - np.eye(3)
    expected = 2 * mu * eps + lam * np.trace(eps) * np.eye(3)
    assert np.allclose(out["tau"], expected, rtol=1e-5, atol=1e-5 * np.abs(expected).max())

    g, t = 9.81, out["t"]
    assert abs(t - 0.1) < 1e-9
    assert out["finite"]
    n = out["steps"]
    assert n == 100  # dt = max_dt throughout
    dt = t / n
    assert abs(out["dy"] - (-g * dt * dt * n * (n + 1) / 2)) < 2e-5
