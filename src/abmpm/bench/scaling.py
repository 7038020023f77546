"""What a run costs as the scene grows around a refined region of fixed size
(``abmpm bench --suite scaling``; the issue "cost follows the refined region, not the
domain: a time step per level").

A tank of water sloshing towards its right wall, 1, 2, 4 and 8 times 0.32 m long, with
the same refined region at its right end in every length: a refinement box 0.16 m wide
(``region = "box"``), or a wall across the tank 0.08 m from its right end with one small
round hole below the water line, which the feature criterion refines around
(``region = "hole"``: a small region, whose share of the particles falls with length). Each length
runs in original, adaptive (one global time step), adaptive with a time step per level
(``time_steps = "per_level"``, sim/time_levels.py) and finest mode, taking turns of
SLICE simulated seconds in the same process;
the figure is wall-clock seconds per simulated second (kernel compilation and the
first step outside the timing). If adaptive cost follows the refined region,
adaptive / original falls towards 1 as the tank grows and finest / adaptive rises; if
it follows the domain (every particle at the fine time step), adaptive / original
stays near b.
"""

from __future__ import annotations

import time
from pathlib import Path

from matplotlib.figure import Figure

from ..scene import model as sm
from ..scene.colliders import SHAPE_SCHEMAS
from ..simulation import Simulation

LENGTHS = (1, 2, 4, 8)  # tank length in units of BASE
BASE, BOX = 0.32, 0.16  # m: the shortest tank; the refinement box's width at the right end
HEIGHT, DEPTH, WIDTH = 0.24, 0.1, 0.08  # m: the tank's height, the water's depth, the tank's depth (z)
DX, FACTOR = 0.02, 2  # coarse spacing, refinement factor b
SLOSH = 0.5  # m/s: the water's initial speed towards the right wall
HOLE, HOLE_Y = 0.03, 0.05  # m: the hole's diameter (1.5 coarse cells) and height (mid-depth)
REGIONS = ("box", "hole")
MODES = ("original", "adaptive", "per_level", "finest")  # per_level: adaptive, a time step per level
LABELS = {"original": "original", "adaptive": "adaptive, global step", "per_level": "adaptive, step per level",
          "finest": "finest"}


def sloshing_tank(length: int, mode: str = "adaptive", region: str = "box") -> sm.Scene:
    """The tank ``length`` x BASE long, its water moving right at SLOSH, the refined
    region at its right end (``region`` one of REGIONS); ``mode`` one of MODES."""
    L = BASE * length
    steps = "per_level" if mode == "per_level" else "global"
    mode = "adaptive" if mode == "per_level" else mode
    refinement = {"mode": mode, "factor": FACTOR, "time_steps": steps}
    water_end, colliders = L, []  # the water's right end
    if region == "box":
        refinement["boxes"] = [((L - BOX, 0.0, 0.0), (L, HEIGHT, WIDTH))]
    else:  # a wall across the tank (normal x) with one hole, the water on its left
        x = L - BOX / 2
        colliders = [SHAPE_SCHEMAS["perforated_plate"](size=(2 * HEIGHT, WIDTH + 0.1), hole_diameter=HOLE,
                                                        center=(x, HOLE_Y, WIDTH / 2), rotation=(0.0, 0.0, 90.0))]
        water_end = x - DX / 2
    return sm.Scene(
        name=f"scaling_tank_{region}_{length}x",
        simulation=sm.SimulationSettings(domain_max=(L, HEIGHT, WIDTH), dx=DX, fps=20, walls={"type": "slip"},
                                         refinement=refinement),
        materials=[sm.Fluid(name="water", bulk_modulus=4.0e4)],
        bodies=[sm.BoxBody(material="water", min=(0.0, 0.0, 0.0), max=(water_end, DEPTH, WIDTH),
                           velocity=(SLOSH, 0.0, 0.0))],
        colliders=colliders,
    )


SLICE = 0.05  # s of simulated time per turn: the modes take turns, so the VM's drifts hit all alike


def time_tanks(length: int, seconds: float, device: str, region: str = "box") -> dict:
    """Every mode of one tank over the same ``seconds``, the modes taking turns SLICE at a
    time (this VM's speed changes by tens of percent within a minute; run one after the
    other, the modes saw different machines). Wall seconds per simulated second, steps per
    simulated second, particles and slow particles at the end, per mode."""
    sims = {m: Simulation(sloshing_tank(length, m, region), device=device) for m in MODES}
    for sim in sims.values():
        sim.step()  # compile and warm up outside the timing
    start = {m: (sim.time, sim.steps) for m, sim in sims.items()}
    wall = dict.fromkeys(MODES, 0.0)
    for _ in range(max(1, round(seconds / SLICE))):
        for m, sim in sims.items():
            t0 = time.perf_counter()
            sim.advance(seconds=SLICE)
            wall[m] += time.perf_counter() - t0
    out = {}
    for m, sim in sims.items():
        span = sim.time - start[m][0]
        out[m] = {"wall_per_sim_s": round(wall[m] / span, 3),
                  "steps_per_sim_s": round((sim.steps - start[m][1]) / span, 1),
                  "particles": sim.particle_count, "slow": sim.solver.slow_count}
    return out


def per_level_floor(row: dict) -> float:
    """What per level / original would read if every particle-step cost what an original
    one does: (n_S + s n_F) / n_O, with n_S the slow particles (one coarse step each), n_F
    the other particles of the per-level run (s substeps per coarse step, s = its substeps
    over original's steps) and n_O original's particles, the end counts of the run. No
    implementation of a time step per level goes below it (docs/method.md, "What the
    scaling suite's goal asks, by arithmetic")."""
    o, pl = row["original"], row["per_level"]
    s = pl["steps_per_sim_s"] / o["steps_per_sim_s"]
    return (pl["slow"] + s * (pl["particles"] - pl["slow"])) / o["particles"]


def run_scaling(device: str, seconds: float = 0.25, lengths=LENGTHS, plot: Path | None = None,
                regions=REGIONS) -> list[dict]:
    """Every region and length in every mode, printed as it finishes; with ``plot`` a PNG
    of the cost against the tank's length."""
    rows = []
    for region, length in ((r, n) for r in regions for n in lengths):
        row = {"region": region, "length_m": round(BASE * length, 3), **time_tanks(length, seconds, device, region)}
        o, a, pl, f = (row[m]["wall_per_sim_s"] for m in MODES)
        row["adaptive_over_original"] = round(a / o, 3)
        row["finest_over_adaptive"] = round(f / a, 3)
        row["per_level_over_original"] = round(pl / o, 3)
        row["finest_over_per_level"] = round(f / pl, 3)
        row["per_level_floor"] = round(per_level_floor(row), 3)
        rows.append(row)
        print(f"tank {row['length_m']} m, {region}: wall s per simulated s original {o}, adaptive {a}, per level {pl}, "
              f"finest {f} (particles {' / '.join(str(row[m]['particles']) for m in MODES)}; steps per simulated s "
              f"{' / '.join(str(row[m]['steps_per_sim_s']) for m in MODES)}; slow particles at the end "
              f"{row['per_level']['slow']}) -> adaptive / original {row['adaptive_over_original']}, per level / "
              f"original {row['per_level_over_original']} (at original's cost a particle-step: "
              f"{row['per_level_floor']}), finest / per level {row['finest_over_per_level']}",
              flush=True)
    if plot is not None:
        plot_scaling(rows, plot)
    return rows


def plot_scaling(rows: list[dict], path: Path) -> None:
    """One panel per region: wall seconds per simulated second of each mode against the
    tank's length."""
    regions = list(dict.fromkeys(r.get("region", "box") for r in rows))
    fig = Figure(figsize=(5.0 * len(regions), 4.0))  # no pyplot: a file, never a window
    axes = fig.subplots(1, len(regions), squeeze=False, sharey=True)[0]  # one scale: the tanks side by side
    titles = {"box": f"refined box {BOX} m wide at the end", "hole": f"a hole {HOLE * 100:g} cm across near the end"}
    for ax, region in zip(axes, regions):
        mine = [r for r in rows if r.get("region", "box") == region]
        x = [r["length_m"] for r in mine]
        for mode in MODES:
            ax.plot(x, [r[mode]["wall_per_sim_s"] for r in mine], "o-", label=LABELS[mode])
        ax.plot(x, [r["per_level_floor"] * r["original"]["wall_per_sim_s"] for r in mine], "k:",
                label="per level at original's cost a particle-step")
        ax.set_xscale("log", base=2)
        ax.set_yscale("log")
        ax.set_xticks(x, [f"{v:g}" for v in x], minor=False)
        ax.minorticks_off()
        ax.set_xlabel("tank length (m)")
        ax.set_ylabel("wall s per simulated s")
        ax.set_title(titles.get(region, region), fontsize="medium")
        ax.legend(loc="upper left", fontsize="small")
    fig.suptitle("Cost against the size of the scene")
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
