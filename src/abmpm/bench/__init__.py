"""Performance benchmark: ``abmpm bench``.

Measures steps/s of the full solver on a weakly compressible fluid block and, in
the same run, of the minimal Warp MLS-MPM reference kernel at the same sizes, so
the figure that matters is a ratio taken on one (noisy) machine.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

# (particles, grid cells per side) of the fluid benchmark
FLUID_CASES = {"cpu": [(100_000, 64), (400_000, 128)], "cuda": [(100_000, 64), (400_000, 128), (1_000_000, 128)]}


def fluid_block_scene(n: int, grid: int):
    """The reference kernel's problem in scene form: unit box with a 3-cell wall band
    (same node count as the reference's grid), a fluid block of ~n particles at 8
    per cell, density 1 and bulk modulus 400 with a linear equation of state."""
    from ..scene.model import BoxBody, Fluid, Scene, SimulationSettings

    dx = 1.0 / grid
    # smallest near-cubic block holding at least n particles (never fewer than the reference)
    cells = np.full(3, int((n / 8.0) ** (1.0 / 3.0)))
    axis = 0
    while 8 * int(np.prod(cells)) < n:
        cells[axis] += 1
        axis = (axis + 1) % 3
    lo = np.array([0.5 - cells[0] * dx / 2, 0.45, 0.5 - cells[2] * dx / 2])
    lo = np.floor(lo / dx) * dx
    return Scene(
        name=f"bench_fluid_{n}",
        simulation=SimulationSettings(
            domain_min=(3 * dx,) * 3, domain_max=((grid - 4) * dx,) * 3, dx=dx, fps=30, cfl=0.4,
        ),
        materials=[Fluid(name="fluid", density=1.0, bulk_modulus=400.0, gamma=1.0)],
        bodies=[BoxBody(material="fluid", min=tuple(lo), max=tuple(lo + cells * dx))],
    )


def time_simulation(sim, seconds: float = 4.0, warmup_steps: int = 3) -> tuple[float, int]:
    """steps/s of ``sim.step()`` (frame bookkeeping, diagnostics and sorting included)."""
    import warp as wp

    for _ in range(warmup_steps):
        sim.step()
    wp.synchronize()
    t0 = time.perf_counter()
    sim.step()
    wp.synchronize()
    one = time.perf_counter() - t0
    n = max(5, int(seconds / max(one, 1e-4)))
    t0 = time.perf_counter()
    for _ in range(n):
        sim.step()
    wp.synchronize()
    return n / (time.perf_counter() - t0), n


def default_reference() -> Path | None:
    for base in (Path.cwd(), Path(__file__).resolve().parents[3]):
        p = base.parent / "shared" / "reference" / "mls_mpm_minimal_warp.py"
        if p.exists():
            return p
    return None


def run_reference(script: Path, n: int, grid: int, device: str) -> float | None:
    cmd = [sys.executable, str(script), "--n", str(n), "--grid", str(grid), "--device", device]
    out = subprocess.run(cmd, capture_output=True, text=True, cwd=script.parent)
    for line in out.stdout.splitlines():
        if line.startswith("RESULT "):
            return float(json.loads(line[7:])["steps_per_s"])
    print(f"reference run failed: {out.stderr.strip()[-400:]}", file=sys.stderr)
    return None


def run_bench(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(prog="abmpm bench", description=__doc__)
    ap.add_argument("--device", default=None, help="cpu or cuda (default: cuda when available)")
    ap.add_argument("--reference", type=Path, default=None, help="path to mls_mpm_minimal_warp.py")
    ap.add_argument("--seconds", type=float, default=4.0, help="timed seconds per case")
    ap.add_argument("--small", action="store_true", help="only the 100k case")
    ap.add_argument("--json", type=Path, default=None, help="also write the results here")
    args = ap.parse_args(argv or [])

    from ..simulation import Simulation, choose_device

    device = choose_device(args.device)
    kind = "cuda" if device.startswith("cuda") else "cpu"
    reference = args.reference or default_reference()
    cases = FLUID_CASES[kind][:1] if args.small else FLUID_CASES[kind]
    rows = []
    for n, grid in cases:
        sim = Simulation(fluid_block_scene(n, grid), device=device)
        sps, steps = time_simulation(sim, args.seconds)
        ref = run_reference(reference, n, grid, device) if reference else None
        row = {
            "case": f"fluid block {sim.particle_count} particles, {grid}^3",
            "particles": sim.particle_count, "grid": grid, "abmpm_steps_per_s": round(sps, 2),
            "timed_steps": steps, "reference_steps_per_s": ref,
            "ratio": round(sps / ref, 3) if ref else None,
        }
        rows.append(row)
        print(
            f"{row['case']:<40} abmpm {sps:8.2f} steps/s   reference "
            f"{(f'{ref:8.2f}' if ref else '     n/a')} steps/s   ratio {row['ratio']}",
            flush=True,
        )
        del sim
    result = {
        "device": device, "machine": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(), "python": platform.python_version(), "rows": rows,
    }
    if args.json:
        from ..io.summary import write_json

        write_json(args.json, result)
    return result
