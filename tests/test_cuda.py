"""The same kernels on CPU and CUDA give the same result (skipped without a GPU)."""

import numpy as np
import pytest

import abmpm


@pytest.mark.cuda
def test_cpu_and_cuda_agree_on_a_short_run(cuda_available):
    if not cuda_available:
        pytest.skip("no CUDA device on this machine")
    scene = abmpm.Scene(
        simulation=abmpm.SimulationSettings(dx=0.04, fps=30),
        materials=[abmpm.Elastic(name="jelly", youngs_modulus=5e4), abmpm.Fluid(name="water", viscosity=0.1)],
        bodies=[abmpm.SphereBody(material="jelly", center=(0.5, 0.3, 0.5), radius=0.15),
                abmpm.BoxBody(material="water", min=(0.2, 0.5, 0.2), max=(0.8, 0.7, 0.8))],
    )
    runs = {}
    for device in ("cpu", "cuda"):
        sim = abmpm.Simulation(scene, device=device)
        sim.advance(frames=3)
        runs[device] = sim.particles().by_id()
    a, b = runs["cpu"], runs["cuda"]
    # GPU atomics sum in a different order: float32 round-off (~1e-7 relative per
    # add) grows over ~100 steps of a contact-free-ish flow to ~1e-5 m at most;
    # 1e-4 m = dx/400 is far below any physical difference.
    assert np.abs(a.x - b.x).max() < 1e-4
    assert np.abs(a.v - b.v).max() < 1e-2 * max(1.0, np.abs(a.v).max())
