"""Performance benchmark: ``abmpm bench``.

Measures steps/s of the full solver on a weakly compressible fluid block and, in
the same run, of the minimal Warp MLS-MPM reference kernel at the same sizes, so
the figure that matters is a ratio taken on one (noisy) machine.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import platform
import subprocess
import sys
import time
from contextlib import contextmanager
from pathlib import Path
from typing import get_args

import numpy as np
import warp as wp

from ..arguments import frames_arg, int_between, positive_float, threads_arg
from ..io.summary import write_json
from ..scene.model import (
    BoxBody,
    CrossedPlatesCollider,
    Elastic,
    Fluid,
    Refinement,
    Scene,
    SheetCollider,
    SimulationSettings,
    SphereBody,
    ThinBoxCollider,
)
from ..sim.parallel import THREADS_ENV, KernelProfile, default_threads
from ..simulation import Simulation, choose_device
from .colors import time_band_colors
from .interface import run_interface_suite
from .reconstruction import run_reconstruction_suite
from .scaling import run_scaling

ROUNDS = 3  # collider overhead: alternating timed rounds per case
# (particles, grid cells per side) of the fluid benchmark
FLUID_CASES = {"cpu": [(100_000, 64), (400_000, 128)], "cuda": [(100_000, 64), (400_000, 128), (1_000_000, 128)]}


def fluid_block_scene(n: int, grid: int):
    """The reference kernel's problem in scene form: unit box with a 3-cell wall band
    (same node count as the reference's grid), a fluid block of ~n particles at 8
    per cell, density 1 and bulk modulus 400 with a linear equation of state."""
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


def slit_scene(dx: float = 0.03, factor: int = 3):
    """Water drains through a slit 1.25 coarse cells wide in a floor of two thin plates."""
    W, Z, yp = 0.6, 0.24, 0.25
    half = (W - 1.25 * dx) / 2
    plates = [ThinBoxCollider(size=(half, 0.1 * dx, Z + 0.1), center=(half / 2, yp, Z / 2)),
              ThinBoxCollider(size=(half, 0.1 * dx, Z + 0.1), center=(W - half / 2, yp, Z / 2))]
    return Scene(
        name="bench_slit",
        simulation=SimulationSettings(domain_max=(W, 0.7, Z), dx=dx, fps=20, max_dt=2e-3, walls={"type": "slip"},
                                      refinement={"mode": "adaptive", "factor": factor}),
        materials=[Fluid(name="water", bulk_modulus=2e4)],
        bodies=[BoxBody(material="water", min=(0, 0.3, 0), max=(W, 0.6, Z))],
        colliders=plates,
    )


def jelly_scene(dx: float = 1 / 30, factor: int = 3):
    """A jelly ball dropped onto crossed thin blades (after the paper's jelly / bunny-split)."""
    return Scene(
        name="bench_jelly",
        simulation=SimulationSettings(domain_max=(1.0, 1.0, 1.0), dx=dx, fps=20,
                                      refinement={"mode": "adaptive", "factor": factor}),
        materials=[Elastic(name="jelly", density=1000.0, youngs_modulus=5e4, poisson_ratio=0.3)],
        bodies=[SphereBody(material="jelly", center=(0.5, 0.55, 0.5), radius=0.15, velocity=(0, -2.0, 0))],
        colliders=[CrossedPlatesCollider(size=(0.5, 0.2), center=(0.5, 0.15, 0.5))],
    )


ADAPTIVE_CASES = {"narrow slit": slit_scene, "jelly on crossed blades": jelly_scene}


def _imbalance(profile, sec: str, name: str) -> float:
    # the busiest CPU part's time over the parts' mean (1: the threads shared the pass
    # evenly; 2 on two threads: one thread did it all)
    t = [v for (s, k, _), v in profile.parts.items() if (s, k) == (sec, name)]
    return max(t) * len(t) / sum(t) if len(t) > 1 and sum(t) > 0 else 1.0


def profile_rows(profile, steps: int, wall: float) -> list[dict]:
    """A KernelProfile as rows (section, kernel, ms per step, launches per step, share
    of the wall time, imbalance of its CPU parts), largest first; "(other host work)"
    is what no section timed."""
    rows = [{"section": sec, "kernel": name, "ms_per_step": 1e3 * t / steps,
             "launches_per_step": profile.launches[(sec, name)] / steps, "share": t / wall,
             "imbalance": _imbalance(profile, sec, name)}
            for (sec, name), t in profile.seconds.items()]
    timed = sum(r["ms_per_step"] for r in rows if r["section"] == "substep" or r["kernel"] == "(all)")
    rows.append({"section": "", "kernel": "(other host work)", "ms_per_step": 1e3 * wall / steps - timed,
                 "launches_per_step": 0.0, "share": 1.0 - timed * steps / (1e3 * wall), "imbalance": 1.0})
    rows.sort(key=lambda r: -r["ms_per_step"])
    return [{k: round(v, 4) if isinstance(v, float) else v for k, v in r.items()} for r in rows]


def print_profile(title: str, rows: list[dict]) -> None:
    print(f"  {title}: ms per step by phase and kernel (imbalance: the busiest thread's share over the mean)")
    for r in rows:
        if r["share"] >= 0.005:
            print(f"    {r['section']:<12} {r['kernel']:<34} {r['ms_per_step']:8.3f} ms  "
                  f"{r['launches_per_step']:5.2f} launches  {100 * r['share']:5.1f}%  "
                  f"imbalance {r['imbalance']:4.2f}")


def time_modes(scene, frames: int, device: str, profile: bool = False) -> dict:
    """Wall-clock steps/s, mean particle count and cost per particle-step of the same
    scene in each mode; with ``profile`` also a breakdown by phase and kernel."""
    out = {}
    plain = scene.model_copy(deep=True)
    plain.simulation.refinement.reconstruct = False
    for mode, sc in (("original", scene), ("adaptive", scene), ("adaptive_plain_split", plain), ("finest", scene)):
        sim = Simulation(sc, device=device, mode=mode.split("_")[0])
        sim.step()  # compile and warm up outside the timing
        levels = []  # each frame's particles per level (their sum: the particle count)
        if profile and mode != "adaptive_plain_split":
            sim.solver.profile = KernelProfile()
        t0 = time.perf_counter()
        steps0, recon0 = sim.steps, sim.solver.reconstruction_seconds
        sim.advance(frames=frames, callback=lambda s: levels.append(s.history[-1]["count_per_level"]))
        wall = time.perf_counter() - t0
        steps = sim.steps - steps0
        per_level = np.mean(levels, axis=0)
        count = float(per_level.sum())
        out[mode] = {"steps_per_s": round(steps / wall, 2), "mean_particles": int(count),
                     "steps": steps, "wall_s": round(wall, 2),
                     "ns_per_particle_step": round(1e9 * wall / steps / count, 1),
                     "reconstruction_s": round(sim.solver.reconstruction_seconds - recon0, 3),
                     "mean_per_level": [int(c) for c in per_level[:2]]}
        if sim.solver.profile is not None:
            out[mode]["profile"] = profile_rows(sim.solver.profile, steps, wall)
    a, f = out["adaptive"], out["finest"]
    out["speedup_adaptive_over_finest"] = round(a["steps_per_s"] / f["steps_per_s"], 3)
    out["particle_ratio_finest_over_adaptive"] = round(f["mean_particles"] / a["mean_particles"], 3)
    out["speedup_per_particle_ratio"] = round(out["speedup_adaptive_over_finest"]
                                              / out["particle_ratio_finest_over_adaptive"], 3)
    # the same figure the other way up: what a particle-step costs in adaptive mode
    # against finest mode (issue goal <= 1.25, i.e. speedup per particle ratio >= 0.8)
    out["cost_per_particle_step_adaptive_over_finest"] = round(a["ns_per_particle_step"] / f["ns_per_particle_step"], 3)
    # against what each particle's own level costs in a one-level run: a level-0 particle-step at
    # original mode's cost, a level-1 one at finest's. Original mode pays more a particle-step than
    # finest on these small scenes (each step's fixed work over fewer particles, a coarse band
    # holding more of them), so this is the two-level machinery's own cost (docs/benchmarks.md)
    n0, n1 = a["mean_per_level"]
    own = (n0 * out["original"]["ns_per_particle_step"] + n1 * f["ns_per_particle_step"]) / max(n0 + n1, 1)
    out["cost_per_particle_step_adaptive_over_own_levels"] = round(a["ns_per_particle_step"] / own, 3)
    # what surface reconstruction adds to an adaptive step: its share of the run's
    # time (the plain-split run takes other time steps, so its steps/s is only a hint)
    out["reconstruction_cost"] = round(a["reconstruction_s"] / (a["wall_s"] - a["reconstruction_s"]), 3)
    return out


def time_simulation(sim, seconds: float = 4.0, warmup_steps: int = 3) -> tuple[float, int]:
    """steps/s of ``sim.step()`` (frame bookkeeping, diagnostics and sorting included)."""
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


def time_collider_overhead(device: str, seconds: float) -> dict:
    """A 100k-particle fluid block resting on a 20k-triangle static sheet, against the
    same block resting on the domain floor without the collider (steps/s ratio).
    Two layouts: the near-cubic block of the fluid benchmark (~10% of its particles
    within the collider band) and a thin layer 6 cells deep (~45% within it)."""
    dx = 1.0 / 64
    y0 = 0.3
    res = {}
    for layout, cells in (("cube", (23, 24, 23)), ("layer", (46, 6, 46))):
        lo = np.array([0.5 - cells[0] * dx / 2, 0.0, 0.5 - cells[2] * dx / 2])
        size = np.array(cells) * dx
        base = dict(materials=[Fluid(name="fluid", density=1000.0, bulk_modulus=2e5)],
                    simulation=SimulationSettings(dx=dx, fps=30))
        on_floor = Scene(bodies=[BoxBody(material="fluid", min=tuple(lo), max=tuple(lo + size))], **base)
        lifted = lo + np.array([0.0, y0, 0.0])
        # sheet(resolution=100): 2 x 100 x 100 = 20k triangles, just under the block
        sheet = SheetCollider(size=(1.2, 1.2), center=(0.5, y0 - 0.25 * dx, 0.5), resolution=100)
        on_sheet = Scene(bodies=[BoxBody(material="fluid", min=tuple(lifted), max=tuple(lifted + size))],
                         colliders=[sheet], **base)
        row = {}
        sims = {"without": Simulation(on_floor, device=device), "with": Simulation(on_sheet, device=device)}
        best = {name: 0.0 for name in sims}
        # the two alternate, best of ROUNDS each: the VM's speed drifts by tens of
        # percent over a minute, and one pass each read ratios from 0.77 to 1.05
        for _ in range(ROUNDS):
            for name, sim in sims.items():
                best[name] = max(best[name], time_simulation(sim, seconds / ROUNDS)[0])
        for name, sim in sims.items():
            row[name] = {"steps_per_s": round(best[name], 2), "particles": sim.particle_count,
                         "triangles": sim.colliders.triangle_count if sim.colliders else 0}
        row["ratio"] = round(row["with"]["steps_per_s"] / row["without"]["steps_per_s"], 3)
        res[layout] = row
    return res


def default_reference() -> Path | None:
    for base in (Path.cwd(), Path(__file__).resolve().parents[3]):
        p = base.parent / "shared" / "reference" / "mls_mpm_minimal_warp.py"
        if p.exists():
            return p
    return None


def _steps_per_s(script: Path, args: list[str], what: str) -> float | None:
    """Run a yardstick script and read the steps/s from its ``RESULT {json}`` line."""
    out = subprocess.run([sys.executable, str(script), *args], capture_output=True, text=True, cwd=script.parent)
    for line in out.stdout.splitlines():
        if line.startswith("RESULT "):
            return float(json.loads(line[7:])["steps_per_s"])
    print(f"{what} run failed: {out.stderr.strip()[-400:]}", file=sys.stderr)
    return None


def run_reference(script: Path, n: int, grid: int, device: str) -> float | None:
    return _steps_per_s(script, ["--n", str(n), "--grid", str(grid), "--device", device], "reference")


@contextmanager
def threads_env(n: int):
    """ABMPM_THREADS=n while building a simulation (its solver reads it)."""
    old = os.environ.get(THREADS_ENV)
    os.environ[THREADS_ENV] = str(n)
    try:
        yield
    finally:
        if old is None:
            os.environ.pop(THREADS_ENV, None)
        else:
            os.environ[THREADS_ENV] = old


def run_numba(reference: Path, n: int, grid: int, threads: int) -> float | None:
    """steps/s of the multi-core numba yardstick beside the reference (needs numba:
    ``pip install 'abmpm[bench]'``), or None."""
    script = reference.parent / "mls_mpm_numba_threads.py"
    if importlib.util.find_spec("numba") is None or not script.exists():
        return None
    return _steps_per_s(script, ["--n", str(n), "--grid", str(grid), "--threads", str(threads)], "numba yardstick")


def _seconds(text: str) -> float:
    """--seconds: a finite number above 0."""
    return positive_float(text, "a number of seconds")


def _one_step(text: str) -> float:
    """--one-step: a CFL number above 0 and at most 1."""
    c = positive_float(text, "a CFL number")
    if c > 1.0:
        raise argparse.ArgumentTypeError(f"must be at most 1, got {text}")
    return c


def _halo(text: str) -> int:
    """--halo: coarse cells, 0 to 8."""
    return int_between(text, "a halo in coarse cells", 0, 8)


def run_bench(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(prog="abmpm bench", description=__doc__)
    ap.add_argument("--device", default=None, help="cpu or cuda (default: cuda when available)")
    ap.add_argument("--reference", type=Path, default=None, help="path to mls_mpm_minimal_warp.py")
    ap.add_argument("--seconds", type=_seconds, default=4.0, help="timed seconds per case")
    ap.add_argument("--small", action="store_true", help="only the 100k case")
    ap.add_argument("--suite", choices=["fluid", "adaptive", "colliders", "interface", "scaling", "reconstruction", "all"],
                    default="all",
                    help="all: fluid, adaptive and colliders; interface (not in all, ~12 min on 2 cores): "
                         "adaptive against finest on slits and round holes outside the paper (on and off the node planes, water falling on them or thrown at either face), tanks at rest (a vertical and a horizontal interface), a dam break into a refined box, a blade cutting a jelly block, a jelly pressed through a slit and a free jelly bar; "
                         "scaling (not in all, ~2 min): a sloshing tank 1-8x as long around the same refined "
                         "region (a box, or a wall with a small hole), the modes' cost (a plot beside --json); "
                         "reconstruction (not in all, ~30 s): the roughness of fluid spheres, sheared elastic "
                         "blocks, settled water and sand split whole, against their parents'")
    ap.add_argument("--frames", type=frames_arg, default=10, help="frames per mode in the adaptive suite")
    ap.add_argument("--json", type=Path, default=None, help="also write the results here")
    ap.add_argument("--threads", type=threads_arg, default=None, help="CPU threads (default: every core)")
    ap.add_argument("--one-step", type=_one_step, default=None, metavar="CFL",
                    help="interface suite: run the plate cases in every mode at one fixed step, CFL fine cells a "
                         "step at the sound speed (0.1 keeps it below every mode's own step), so that the ratios "
                         "to finest measure the level interface apart from the number of steps")
    ap.add_argument("--criterion", choices=get_args(Refinement.model_fields["criterion"].annotation), default=None,
                    help="interface suite: the plate cases' adaptive runs refine by this criterion instead of "
                         "the default (both: every sheet's band too, closer to finest at more cost)")
    ap.add_argument("--halo", type=_halo, default=None, metavar="CELLS",
                    help="interface suite: the plate cases' and the thrown water's adaptive runs grow the refined "
                         "region by this many coarse cells instead of the scenes' 1 (2: closer to finest, more cost)")
    ap.add_argument("--coupling", choices=get_args(Refinement.model_fields["coupling"].annotation), default=None,
                    help="interface suite: the plate cases', the thrown water's and the free bar's adaptive runs "
                         "couple the levels this way instead of the default (partition: momentum exact, experimental)")
    ap.add_argument("--seeds", type=int, default=1,
                    help="interface suite: the plate cases and the thrown water over at least this many jitter "
                         "seeds each (one run's chaos moves some rows by 5-15%%; 4 seeds take about 4x as long)")
    ap.add_argument("--profile", action="store_true",
                    help="adaptive suite: time every kernel and phase of the step (ms per step) and how "
                         "evenly the CPU threads share each (busiest thread over the mean)")
    args = ap.parse_args(argv or [])
    if args.json is not None:  # checked before the benchmark runs, not after
        try:
            args.json.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            ap.error(f"--json {args.json}: cannot create its folder ({exc.strerror or exc})")
        if args.json.is_dir() or not os.access(args.json.parent, os.W_OK):
            ap.error(f"--json {args.json}: not a file that can be written")

    if args.reference is not None and not args.reference.is_file():
        ap.error(f"--reference {args.reference}: no such file")
    if args.one_step is not None and args.suite != "interface":
        ap.error("--one-step: only the interface suite runs at one step (add --suite interface)")
    for option in ("criterion", "halo", "coupling"):
        if getattr(args, option) is not None and args.suite != "interface":
            ap.error(f"--{option}: only the interface suite takes it (add --suite interface)")
    if args.seeds != 1 and (args.suite != "interface" or args.seeds < 1):
        ap.error(f"--seeds {args.seeds}: a count of at least 1, for the interface suite only (add --suite interface)")
    device = choose_device(args.device)
    kind = "cuda" if device.startswith("cuda") else "cpu"
    reference = args.reference or default_reference()
    if reference:  # the yardsticks run in their own folder
        reference = reference.resolve()
    cases = FLUID_CASES[kind][:1] if args.small else FLUID_CASES[kind]
    if args.suite not in ("fluid", "all"):
        cases = []
    rows = []
    if args.threads:
        os.environ[THREADS_ENV] = str(args.threads)  # every simulation of this run
    threads = args.threads or default_threads()
    for n, grid in cases:
        sps1 = None
        if kind == "cpu" and threads > 1:  # thread scaling: the same case on one thread first
            with threads_env(1):
                sim = Simulation(fluid_block_scene(n, grid), device=device)
                sps1, _ = time_simulation(sim, args.seconds)
                del sim
        with threads_env(threads):
            sim = Simulation(fluid_block_scene(n, grid), device=device)
            sps, steps = time_simulation(sim, args.seconds)
        ref = run_reference(reference, n, grid, device) if reference else None
        yard = run_numba(reference, n, grid, threads) if reference and kind == "cpu" else None
        row = {
            "case": f"fluid block {sim.particle_count} particles, {grid}^3",
            "particles": sim.particle_count, "grid": grid, "threads": threads if kind == "cpu" else None,
            "abmpm_steps_per_s": round(sps, 2), "abmpm_one_thread_steps_per_s": round(sps1, 2) if sps1 else None,
            "thread_speedup": round(sps / sps1, 3) if sps1 else None,
            "timed_steps": steps, "reference_steps_per_s": ref,
            "ratio": round(sps / ref, 3) if ref else None,
            "one_thread_ratio": round(sps1 / ref, 3) if ref and sps1 else None,
            "numba_steps_per_s": yard, "ratio_to_numba": round(sps / yard, 3) if yard else None,
        }
        rows.append(row)
        na = {k: "n/a" if row[k] is None else row[k] for k in ("thread_speedup", "ratio", "one_thread_ratio",
                                                             "ratio_to_numba")}  # what was not measured
        print(
            f"{row['case']:<40} abmpm {sps:8.2f} steps/s ({threads} threads; 1 thread "
            f"{(f'{sps1:.2f}' if sps1 else 'n/a')}, x{na['thread_speedup']})   reference "
            f"{(f'{ref:8.2f}' if ref else '     n/a')} steps/s   ratio {na['ratio']} (1 thread {na['one_thread_ratio']})"
            f"   numba {threads} threads {yard if yard else 'n/a'} -> {na['ratio_to_numba']}",
            flush=True,
        )
        del sim
    adaptive = {}
    if args.suite in ("adaptive", "all"):
        for name, make in ADAPTIVE_CASES.items():
            adaptive[name] = r = time_modes(make(), args.frames, device, profile=args.profile)
            print(f"{name}: " + "  ".join(f"{m} {r[m]['steps_per_s']} steps/s ({r[m]['mean_particles']} particles)"
                                          for m in ("original", "adaptive", "finest"))
                  + f"  speedup {r['speedup_adaptive_over_finest']} vs particle ratio "
                  f"{r['particle_ratio_finest_over_adaptive']} -> {r['speedup_per_particle_ratio']}; "
                  f"adaptive without reconstruction {r['adaptive_plain_split']['steps_per_s']} steps/s "
                  f"(reconstruction costs {100 * r['reconstruction_cost']:.1f}%); a particle-step costs "
                  f"{r['adaptive']['ns_per_particle_step']} ns adaptive, {r['finest']['ns_per_particle_step']} ns "
                  f"finest -> {r['cost_per_particle_step_adaptive_over_finest']}x; against each level's own "
                  f"mode (level 0 at original's cost, level 1 at finest's) "
                  f"{r['cost_per_particle_step_adaptive_over_own_levels']}x", flush=True)
            for mode in ("adaptive", "finest"):
                if "profile" in r[mode]:
                    print_profile(f"{name}, {mode}", r[mode]["profile"])
    colliders = {}
    if args.suite in ("colliders", "all"):
        colliders = time_collider_overhead(device, args.seconds)
        print(f"collider overhead: {colliders}", flush=True)
        # a band particle's color on curved glass: BVH query against the nodes' field
        colliders["band_colors"] = [time_band_colors(name, device=device) for name in ("paper_hourglass", "hourglass")]
        for row in colliders["band_colors"]:
            print(f"band colors, {row['scene']} ({row['triangles']} triangles): BVH {row['bvh_ns']} ns, "
                  + (f"lists {row['lists_ns']} ns, " if row["lists_built"] else "no lists (they would not pay), ")
                  + f"nodes {row['nodes_ns']} ns a band particle "
                  f"(taken {100 * row['taken']:.1f}%)", flush=True)
    interface = (run_interface_suite(device, step=args.one_step, criterion=args.criterion, seeds=args.seeds,
                                     halo=args.halo, coupling=args.coupling)
                 if args.suite == "interface" else {})
    scaling = []
    if args.suite == "scaling":
        scaling = run_scaling(device, plot=args.json.with_suffix(".png") if args.json else None)
    reconstruction = run_reconstruction_suite(device) if args.suite == "reconstruction" else {}
    result = {
        "device": device, "machine": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(), "python": platform.python_version(), "rows": rows,
        "adaptive": adaptive, "colliders": colliders, "interface": interface,
        "interface_options": {"one_step": args.one_step, "criterion": args.criterion, "seeds": args.seeds,
                              "halo": args.halo, "coupling": args.coupling}
        if interface else {},
        "scaling": scaling,
        "reconstruction": reconstruction,
    }
    if args.json:
        write_json(args.json, result)
    return result
