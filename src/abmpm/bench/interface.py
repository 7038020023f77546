"""The level-interface matrix: adaptive against finest on cases outside the paper's
scenes (``abmpm bench --suite interface``; docs/method.md, "The level interface
against finest"). Each case runs in original, adaptive and finest mode with the
scene's defaults (feature criterion, reconstruction, merge) and reports the outcome
ratio adaptive / finest, the steps ratio and the wall-time ratio. The fast cases run
in the test suite (``tests/test_level_interface.py``) with the same scene builders.
"""

from __future__ import annotations

import time

import numpy as np

from ..compare.outcomes import cut_outcome, mass_beyond_plane
from ..scene import model as sm
from ..scene.colliders import SHAPE_SCHEMAS
from ..scene.loader import load_scene
from ..scene.model import with_mode
from ..simulation import Simulation
from .interface_report import plate_tally, seed_error, summary_line

# (slit width in coarse cells, refinement factor b, jitter seeds). The mass through
# at one instant depends on the seed: finest mode's 1-cell slit at b = 2 reads
# 0.0231-0.0266 over seeds 0-3 (+-7%), as large as the differences the matrix is
# after, so the cheap b = 2 cases take the mean of four seeds (the 0.5-cell slit, whose
# drain is smallest, eight: its four-seed means of seeds 0-3 and 4-7 differ by 6.5% in
# finest mode); the others one.
SEEDS4, SEEDS8 = (0, 1, 2, 3), tuple(range(8))
# (... , tilt of the plate in degrees, lift of the plate in coarse cells). At lift 0 the
# plate lies on a node plane of every grid, which suits a passage a few fine cells wide
# (its nodes have in-plane normals): finest's 0.75-cell slit at b = 3 passes 0.119 there
# and 0.045 a quarter cell higher, its 1-cell hole 0.0176 and 0.0099
SLITS = [(0.5, 2, SEEDS8, 0.0, 0.0), (1.0, 2, SEEDS4, 0.0, 0.0), (0.5, 3, (0,), 0.0, 0.0), (0.75, 3, (0,), 0.0, 0.0),
         (1.0, 3, (0,), 0.0, 0.0), (1.5, 3, (0,), 0.0, 0.0), (0.75, 4, (0,), 0.0, 0.0), (0.75, 3, (0,), 20.0, 0.0),
         (0.75, 3, (0,), 0.0, 0.25),
         # from the audit of 2026-11-29 (docs/benchmarks.md, "An audit outside the matrix"): the
         # issue's widths at the factors the rows above leave out
         (0.5, 4, (0,), 0.0, 0.0), (1.0, 4, (0,), 0.0, 0.0), (1.5, 2, SEEDS4, 0.0, 0.0)]
# round holes (diameter in coarse cells, b, lift), one seed: finest's 1-cell hole at b = 3
# reads 0.0176 and 0.0178 on seeds 0 and 1. The 0.5-cell slit at b = 3 and the 0.75-cell hole
# at b = 4 joined from an audit of cases outside the matrix (docs/benchmarks.md).
HOLES = [(1.0, 3, 0.0), (1.5, 2, 0.0), (1.5, 3, 0.0), (0.75, 4, 0.0), (1.0, 3, 0.25), (1.5, 3, 0.25)]
# the 1-cell slit at b = 3 with other fluids than the soft water (K = 2e4 Pa) of the rest:
# (name, Fluid parameters)
FLUIDS = [("stiff water", {"bulk_modulus": 2e5}), ("viscous fluid", {"bulk_modulus": 2e4, "viscosity": 1.0})]
# water thrown at 2 m/s at the plate (slit or round hole, b, speed: + from below, - from above),
# 0.3 s: an audit of 2026-11-28 found adaptive passing 0.70-0.92 of finest's mass through the
# back face in a box of slip walls, which held the water on the floor (docs/benchmarks.md,
# "Water thrown at a sheet" and "Thrown water leaves the floor")
JETS = [(1.0, 3, False, 2.0), (1.5, 3, False, 2.0), (1.0, 4, False, 2.0), (2.0, 4, True, 2.0), (1.0, 3, False, -2.0),
        (1.0, 4, False, -2.0)]
JET_SECONDS = 0.3
MODES = ("original", "adaptive", "finest")
TANK_FACTORS = (2, 3, 4)

# the tank at rest: water density, gravity, a soft bulk modulus; tank size (m)
RHO, G, K = 1000.0, 9.81, 4.0e4
TANK_W, TANK_DEPTH, TANK_Z = 0.8, 0.25, 0.2
TANK_DX = 0.05  # the tank's coarse spacing

# the plate cases: the box (x and z extent, m), the plate's height at its centre (m)
PLATE_W, PLATE_Z, PLATE_Y = 0.4, 0.16, 0.2


def water_over_plate(mode: str, b: int, dx: float, colliders: list, jet: float = 0.0) -> sm.Scene:
    """Water falling 0.04 m onto the plate made of ``colliders`` (K = 2e4 Pa), in a box of
    separating walls (the scenes' default; until 2026-11-29 slip walls, which hold water that
    leaves them 1.5 cells of their grid deep, and adaptive mode's walls are coarse: docs/method.md,
    "What the interface matrix's misses are made of"). ``jet`` (m/s): thrown at the plate
    instead, from below (its back face, against gravity) where positive, from above where
    negative (``JETS``)."""
    lo, hi = (0.0, PLATE_Y - 0.04) if jet > 0.0 else (0.24, 0.44)  # from below: the same gap under the plate
    water = sm.BoxBody(material="water", min=(0, lo, 0), max=(PLATE_W, hi, PLATE_Z), velocity=(0.0, jet, 0.0))
    return sm.Scene(
        simulation=sm.SimulationSettings(domain_max=(PLATE_W, 0.5, PLATE_Z), dx=dx, fps=10, max_dt=2e-3,
                                         refinement={"mode": mode, "factor": b}),
        materials=[sm.Fluid(name="water", bulk_modulus=2e4)], bodies=[water], colliders=colliders)


def plate_with_slit(mode: str, slit_cells: float, b: int, dx: float = 0.04,
                    tilt: float = 0.0, lift: float = 0.0, jet: float = 0.0) -> tuple[sm.Scene, float]:
    """Water falling 0.04 m onto a zero-thickness plate that spans the box; its only
    way down is a slit ``slit_cells`` coarse cells wide across the box. ``tilt``
    (degrees, up to 50) turns the plate about the x axis, across the slit's length: the
    slit and the plate are then on no grid plane. ``lift`` (coarse cells) raises the plate
    off the node plane it lies on (at 0, a node plane of every grid); ``jet`` as in
    ``water_over_plate``. Returns the scene and the plate's height at its centre."""
    half = (PLATE_W - slit_cells * dx) / 2
    y = PLATE_Y + lift * dx
    plates = [sm.SheetCollider(size=(half, PLATE_Z + 0.1), center=(c, y, PLATE_Z / 2),
                               rotation=(tilt, 0.0, 0.0)) for c in (half / 2, PLATE_W - half / 2)]
    return water_over_plate(mode, b, dx, plates, jet), y


def plate_with_hole(mode: str, hole_cells: float, b: int, dx: float = 0.04,
                    tilt: float = 0.0, lift: float = 0.0, jet: float = 0.0) -> tuple[sm.Scene, float]:
    """The case of ``plate_with_slit`` with the plate spanning the box and one round hole
    ``hole_cells`` coarse cells across at its centre as the only way down."""
    y = PLATE_Y + lift * dx
    plate = SHAPE_SCHEMAS["perforated_plate"](size=(PLATE_W + 0.1, PLATE_Z + 0.1), hole_diameter=hole_cells * dx,
                                              center=(PLATE_W / 2, y, PLATE_Z / 2), rotation=(tilt, 0.0, 0.0))
    return water_over_plate(mode, b, dx, [plate], jet), y


# the refinement box of the tank with a horizontal interface: the bottom 0.1 m
TANK_LAYER = 0.1


def jelly_through_slit(mode: str, slit_cells: float, b: int, dx: float = 0.04) -> tuple[sm.Scene, float]:
    """An elastic block (E = 5e4 Pa) resting on the slit plate of ``plate_with_slit`` and
    pressed through the slit by a sticky piston (a sheet that does not refine) coming
    down at 0.4 m/s. Returns the scene and the plate's height."""
    scene, yp = plate_with_slit(mode, slit_cells, b, dx)
    piston = sm.SheetCollider(size=(PLATE_W + 0.1, PLATE_Z + 0.1), center=(PLATE_W / 2, yp + 0.14, PLATE_Z / 2),
                              refine=False, boundary="sticky", motion={"velocity": (0.0, -0.4, 0.0)})
    return sm.Scene(simulation=scene.simulation, materials=[sm.Elastic(name="jelly", youngs_modulus=5e4, poisson_ratio=0.3)],
                    bodies=[sm.BoxBody(material="jelly", min=(0.1, yp + 0.01, 0.0), max=(0.3, yp + 0.13, PLATE_Z))],
                    colliders=[*scene.colliders, piston]), yp


def run_piston(seconds: float, device: str, b: int = 3, slit_cells: float = 1.5) -> dict:
    """The jelly pressed through the slit: mass below the plate after ``seconds`` and
    steps, every mode. (Its pieces are no measure: pressed through 1.5 cells, the jelly
    is stretched until most particles are farther than 1.5 spacings from any other.)"""
    res = {}
    for mode in MODES:
        scene, yp = jelly_through_slit(mode, slit_cells, b)
        sim = Simulation(scene, device=device)
        sim.advance(seconds=seconds)
        p = sim.particles()
        res[mode] = {"through": mass_beyond_plane(p.x, p.mass, (PLATE_W / 2, yp, PLATE_Z / 2), (0.0, -1.0, 0.0)),
                     "steps": sim.steps}
    return {**res, **_against_finest(res, through_ratio="through", steps_ratio="steps")}


def tank_at_rest(mode: str, dx: float = TANK_DX, b: int = 2, layered: bool = False,
                 wall_images: bool = False) -> sm.Scene:
    """A tank of water whose right half is a refinement box: the level interface runs
    through the water. ``layered``: the box is the bottom TANK_LAYER instead, coarse water
    resting on refined water. ``wall_images``: the walls' ``images`` option. Start it with
    ``hydrostatic_J`` for a state at rest."""
    box = ((0.0, 0.0, 0.0), (TANK_W, TANK_LAYER, TANK_Z)) if layered else ((TANK_W / 2, 0.0, 0.0), (TANK_W, 0.4, TANK_Z))
    return sm.Scene(
        simulation=sm.SimulationSettings(
            domain_max=(TANK_W, 0.4, TANK_Z), dx=dx, fps=20, walls={"type": "slip", "images": wall_images},
            refinement={"mode": mode, "factor": b, "boxes": [box]}),
        materials=[sm.Fluid(name="water", density=RHO, bulk_modulus=K)],
        bodies=[sm.BoxBody(material="water", min=(0, 0, 0), max=(TANK_W, TANK_DEPTH, TANK_Z))])


def hydrostatic_J(y: np.ndarray) -> np.ndarray:
    """J at height y in the tank at rest: Tait with gamma = 7, p = K/7 (J^-7 - 1) = rho g depth."""
    return (1.0 + 7.0 * RHO * G * np.clip(TANK_DEPTH - y, 0.0, None) / K) ** (-1.0 / 7.0)


def one_step(scene: sm.Scene, cfl: float) -> float:
    """The fixed step (s) of a plate case run "at one step": ``cfl`` fine cells a step at the
    fluid's sound speed at rest, far below every mode's own CFL step (0.4 with the fastest
    particle and the compressed fluid's stiffening), so that every mode takes the same steps."""
    st = scene.simulation
    water = scene.materials[0]
    return cfl * st.dx / st.refinement.factor / float(np.sqrt(water.bulk_modulus / water.density))


def run_slit(slit_cells: float, b: int, seconds: float, device: str, seeds: tuple[int, ...] = (0,),
             tilt: float = 0.0, hole: bool = False, lift: float = 0.0, fluid: dict | None = None,
             step: float | None = None, criterion: str | None = None, jet: float = 0.0,
             halo: int | None = None, coupling: str | None = None) -> dict:
    """Mass through (below the plate's plane), steps and wall seconds of one slit case
    in every mode, each the mean over the particle jitter's ``seeds`` (the single runs'
    mass through in ``through_seeds``); ``tilt`` and ``lift`` as in ``plate_with_slit``; ``hole``:
    a round hole ``slit_cells`` across instead of the slit (``plate_with_hole``); ``fluid``:
    the water's ``Fluid`` parameters instead of K = 2e4 Pa; ``step``: every mode at one fixed
    step (``one_step``) instead of its own CFL step. At a sheet the outcome depends on the
    number of steps in any MPM (docs/method.md, "Outcomes at a sheet depend on the step"), so
    only at one step does the ratio to finest measure the level interface alone. ``criterion``:
    the adaptive run's refinement criterion instead of the default ("both" refines the
    plate's whole band: docs/benchmarks.md, "The plate matrix over 24 cases, four ways"); ``jet``:
    the water thrown at the plate (``water_over_plate``), the mass through counted beyond it;
    ``halo``: the adaptive run's refinement halo instead of the default (docs/benchmarks.md, "The
    halo as the accuracy knob"); ``coupling``: the adaptive run's level coupling instead of the
    default (docs/method.md, "The two grids as one basis")."""
    out = {}
    for mode in MODES:
        runs = []
        for seed in seeds:
            build = plate_with_hole if hole else plate_with_slit
            scene, yp = build(mode, slit_cells, b, tilt=tilt, lift=lift, jet=jet)
            scene.simulation.seed = seed
            if fluid:
                scene.materials = [sm.Fluid(name="water", **fluid)]
            if step is not None:
                scene.simulation.max_dt = one_step(scene, step)
            if criterion is not None:
                scene.simulation.refinement.criterion = criterion
            if halo is not None:
                scene.simulation.refinement.halo = halo
            if coupling is not None:
                scene.simulation.refinement.coupling = coupling
            sim = Simulation(scene, device=device)
            up = sim.colliders.body_meshes()[0].face_normals[0]
            up = up if (up[1] > 0) == (jet <= 0.0) else -up  # against the way through
            centre = (0.5 * scene.simulation.domain_max[0], yp, 0.5 * scene.simulation.domain_max[2])
            sim.advance(frames=1)  # kernels compiled, the first frame's split done: not timed
            steps, t0 = sim.steps, time.perf_counter()
            sim.advance(seconds=max(0.0, seconds - sim.time))
            p = sim.particles()
            runs.append((mass_beyond_plane(p.x, p.mass, centre, tuple(-up)), sim.steps,
                         time.perf_counter() - t0, sim.steps - steps, sim.particle_count))
        through, steps, wall, timed, count = (np.mean([r[i] for r in runs]) for i in range(5))
        out[mode] = {"through": round(float(through), 5), "through_seeds": [round(float(r[0]), 5) for r in runs],
                     "steps": float(steps), "wall_s": round(float(wall), 2), "timed_steps": float(timed),
                     "particles": float(count)}
    return {**out, **_against_finest(out, through_ratio="through", steps_ratio="steps", wall_ratio="wall_s")}


def _against_finest(res: dict, **keys: str) -> dict:
    """``name: adaptive / finest`` of each ``name=key`` of ``res``'s runs, to 3 decimals
    (None where finest's is 0 or either is missing)."""
    a, f = res["adaptive"], res["finest"]
    return {name: round(a[k] / f[k], 3) if a[k] is not None and f[k] else None for name, k in keys.items()}


def _spread(d: np.ndarray) -> float:
    return float(np.percentile(d, 99) - np.percentile(d, 1))


def depth_J_gap(x: np.ndarray, J: np.ndarray, dx: float, b: int) -> float:
    """The issue's measure of the interface in the tank: the largest difference, over
    depth bins a fine cell thick (away from the floor and the surface), between the
    mean J within one coarse cell of the interface and at the same depth more than
    three coarse cells from it."""
    d = np.abs(x[:, 0] - TANK_W / 2)
    near, far = d < dx, d > 3 * dx
    edges = np.arange(2 * dx / b, TANK_DEPTH - dx / b, dx / b)
    gap = 0.0
    for lo, hi in zip(edges[:-1], edges[1:]):
        at = (x[:, 1] >= lo) & (x[:, 1] < hi)
        if (near & at).sum() > 3 and (far & at).sum() > 3:
            gap = max(gap, abs(float(J[near & at].mean() - J[far & at].mean())))
    return gap


def surface_range(x: np.ndarray, spacing: np.ndarray, dx: float, lo: float | None = None,
                  hi: float | None = None) -> float:
    """How far from flat the free surface is: over columns one coarse cell wide from
    ``lo`` to ``hi``, the range of the top particle's height plus half its own sampling
    spacing (the surface a particle layer stands for). By default every column but the
    two at the walls: the particles there stand higher in every mode (finest's wall
    columns 5 mm above the rest at b = 4, its inner columns within 1 mm)."""
    tops = []
    for left in np.arange(dx if lo is None else lo, (TANK_W - dx if hi is None else hi) - 1e-9, dx):
        m = np.flatnonzero((x[:, 0] >= left) & (x[:, 0] < left + dx))
        if len(m):
            k = m[np.argmax(x[m, 1])]
            tops.append(x[k, 1] + spacing[k] / 2)
    return float(np.ptp(tops))


def _settled_tank(mode: str, b: int, seconds: float, device: str, layered: bool = False):
    """``tank_at_rest`` from hydrostatic J run for ``seconds``: particles, J - J_hydrostatic,
    the fastest speed at the end and over the frames (an instant's swings 2x within 0.1 s
    in every mode: the settling waves), the steps."""
    sim = Simulation(tank_at_rest(mode, TANK_DX, b, layered), device=device)
    sim.set_particles(history=hydrostatic_J(sim.particles().by_id().x[:, 1]).astype(np.float32))
    p, fastest, fastest_over_run = sim.particles(), 0.0, 0.0
    while sim.time < seconds - 1e-9:
        sim.advance(frames=1)
        p = sim.particles()
        fastest = float(np.linalg.norm(p.v, axis=1).max())
        fastest_over_run = max(fastest_over_run, fastest)
    return p, p.J - hydrostatic_J(p.x[:, 1]), {"fastest": fastest, "fastest_over_run": fastest_over_run,
                                               "steps": sim.steps}


def run_tank(seconds: float, device: str, b: int = 2) -> dict:
    """The tank at rest after ``seconds``, refinement factor ``b``: the spread of J -
    J_hydrostatic (1st to 99th percentile, away from surface and floor) of the level-1
    particles and of those within a coarse cell of the interface, against finest's (at the
    same places); the fastest particle (at the end, over the run) and the steps against
    finest's; the surface's range over the tank and over the four columns within two coarse
    cells of the interface (the issue's "flat across the interface"), original's beside
    them: adaptive's coarse half is original mode (docs/benchmarks.md, "A coarse particle's
    box at a wall")."""
    dx = TANK_DX
    res = {}
    for mode in MODES:
        p, d, res[mode] = _settled_tank(mode, b, seconds, device)
        spacing = np.where(p.level == 1, dx / (2 * b), dx / 2)
        res[mode].update(surface_range=surface_range(p.x, spacing, dx),
                         interface_surface_range=surface_range(p.x, spacing, dx, TANK_W / 2 - 2 * dx,
                                                               TANK_W / 2 + 2 * dx))
        if mode == "original":
            continue
        inner = (p.x[:, 1] < TANK_DEPTH - 2 * dx) & (p.x[:, 1] > 2 * dx)
        fine = inner & (p.level == 1)  # finest: every particle is level 1
        res[mode].update(J_spread=_spread(d[fine]),
                         interface_J_spread=_spread(d[inner & (np.abs(p.x[:, 0] - TANK_W / 2) < dx)]),
                         depth_J_gap=depth_J_gap(p.x, p.J, dx, b))
    return {**res, "half_fine_cell": dx / (2 * b),
            **_against_finest(res, J_spread_ratio="J_spread", interface_J_ratio="interface_J_spread",
                              fastest_ratio="fastest", fastest_over_run_ratio="fastest_over_run",
                              steps_ratio="steps")}


def run_layered_tank(seconds: float, device: str, b: int = 2) -> dict:
    """The tank with coarse water resting on a refined bottom layer after ``seconds``:
    J - J_hydrostatic of the level-1 particles (1st to 99th percentile) against finest's
    at the same heights, the fastest particle and the steps against finest's."""
    res = {}
    for mode in ("adaptive", "finest"):
        p, d, res[mode] = _settled_tank(mode, b, seconds, device, layered=True)
        res[mode]["J_spread"] = _spread(d[(p.x[:, 1] < TANK_LAYER) & (p.level == 1)])  # finest: the same heights
    return {**res, **_against_finest(res, J_spread_ratio="J_spread", fastest_ratio="fastest", steps_ratio="steps")}


# the dam break: box (m), the water column, the refinement box at the far wall (x from)
DAM_W, DAM_H, DAM_Z = 0.8, 0.8, 0.16
COLUMN_W, COLUMN_H = 0.2, 0.3
DAM_REFINED = 0.56


def dam_break(mode: str, b: int, dx: float = 0.04) -> sm.Scene:
    """A water column (0.2 m wide, 0.3 m high, soft: K = 2e4 Pa) collapses along the
    floor from the coarse part into a refinement box at the far wall and runs up it:
    fine and coarse water meet against a wall. 100 frames a second, separating walls (slip
    walls until 2026-11-29: the coarse floor held the sheet of water running along it)."""
    ref = {"mode": mode, "factor": b, "boxes": [[[DAM_REFINED, 0.0, 0.0], [DAM_W, DAM_H, DAM_Z]]]}
    return sm.Scene(
        name=f"dam_break_{mode}_b{b}",
        simulation=sm.SimulationSettings(domain_max=(DAM_W, DAM_H, DAM_Z), dx=dx, fps=100, refinement=ref),
        materials=[sm.Fluid(name="water", bulk_modulus=2e4)],
        bodies=[sm.BoxBody(material="water", min=(0, 0, 0), max=(COLUMN_W, COLUMN_H, DAM_Z))])


def _weighted_quantile(v: np.ndarray, w: np.ndarray, q: float) -> float:
    order = np.argsort(v)
    c = np.cumsum(w[order])
    return float(v[order][np.searchsorted(c, q * c[-1])])


def run_dam_break(seconds: float, device: str, b: int = 2) -> dict:
    """The dam break in every mode, frame by frame. The front (the x below which 99.5%
    of the mass lies) reaches the refinement box at ``t_box`` and the far wall's last
    coarse cell at ``t_wall``; the run-up (the height below which 99.5% of the mass
    within a coarse cell of the wall lies) at its highest; the steps. In the coarse
    part adaptive mode is original mode, so adaptive is held to finest on what happens
    in the box: the crossing time t_wall - t_box and the run-up."""
    res = {}
    for mode in MODES:
        scene = dam_break(mode, b)
        dx = scene.simulation.dx
        sim = Simulation(scene, device=device)
        t_box = t_wall = None
        runup, t0, front0 = 0.0, 0.0, COLUMN_W
        while sim.time < seconds - 1e-9:
            sim.advance(frames=1)
            p = sim.particles()
            m = p.mass.astype(np.float64)
            front = _weighted_quantile(p.x[:, 0], m, 0.995)
            # the times the front passes the box and the wall's cell, between frames by interpolation
            if t_box is None and front >= DAM_REFINED:
                t_box = t0 + (sim.time - t0) * (DAM_REFINED - front0) / max(front - front0, 1e-12)
            if t_wall is None and front >= DAM_W - dx:
                t_wall = t0 + (sim.time - t0) * (DAM_W - dx - front0) / max(front - front0, 1e-12)
            t0, front0 = sim.time, front
            wall = p.x[:, 0] > DAM_W - dx
            if wall.any():
                runup = max(runup, _weighted_quantile(p.x[wall, 1], m[wall], 0.995))
        crossing = t_wall - t_box if t_wall is not None and t_box is not None else None
        res[mode] = {"t_box": t_box, "t_wall": t_wall, "crossing": crossing, "runup": runup, "steps": sim.steps}
    return {**res, **_against_finest(res, crossing_ratio="crossing", runup_ratio="runup", steps_ratio="steps")}


def free_bar(mode: str, b: int, dx: float = 0.05) -> sm.Scene:
    """A jelly bar in free flight (no gravity, walls far away) whose two halves start
    towards each other at 1 m/s: zero total momentum, an axial vibration, and the
    level interface (a refinement box over the right half) across its middle."""
    ref = {"mode": mode, "factor": b, "boxes": [[[0.8, 0.0, 0.0], [1.6, 1.0, 1.0]]], "merge": False}
    jelly = {"material": "jelly", "min": (0.4, 0.35, 0.35), "max": (0.8, 0.65, 0.65)}
    return sm.Scene(
        name=f"free_bar_{mode}_b{b}",
        simulation=sm.SimulationSettings(domain_max=(1.6, 1.0, 1.0), dx=dx, fps=60, gravity=(0.0, 0.0, 0.0),
                                         refinement=ref),
        materials=[sm.Elastic(name="jelly", youngs_modulus=2.0e4, poisson_ratio=0.3)],
        bodies=[sm.BoxBody(**jelly, velocity=(1.0, 0.0, 0.0)),
                sm.BoxBody(**{**jelly, "min": (0.8, 0.35, 0.35), "max": (1.2, 0.65, 0.65)}, velocity=(-1.0, 0.0, 0.0))],
    )


def run_free_bar(seconds: float, device: str, b: int = 2, coupling: str | None = None) -> dict:
    """The free bar frame by frame: the largest total momentum (a conservation law: it
    stays 0) against the halves' |momentum| at the start, and the kinetic energy at
    the end against finest's."""
    res = {}
    for mode in MODES:
        scene = free_bar(mode, b)
        if coupling is not None:
            scene.simulation.refinement.coupling = coupling
        sim = Simulation(scene, device=device)
        p = sim.particles()
        scale = 0.5 * float((p.mass * np.linalg.norm(p.v, axis=1)).sum())  # one half's momentum
        drift = 0.0
        while sim.time < seconds - 1e-9:
            sim.advance(frames=1)
            p = sim.particles()
            drift = max(drift, float(np.linalg.norm((p.mass.astype(np.float64)[:, None] * p.v).sum(0))) / scale)
        ke = 0.5 * float((p.mass * (p.v.astype(np.float64) ** 2).sum(1)).sum())
        res[mode] = {"momentum_drift": drift, "kinetic_energy": ke}
    return {**res, "drift": {m: float(f"{res[m]['momentum_drift']:.3g}") for m in MODES},
            **_against_finest(res, ke_ratio="kinetic_energy")}


def run_blade_cut(seconds: float, device: str, b: int = 2) -> dict:
    """The built-in ``blade_cut`` (a blade a tenth of a cell thick driven down through a
    jelly block) after ``seconds``, every mode at factor ``b``: the cut's width and
    roughness where the blade has been (``cut_outcome``, the paper's measure), steps."""
    res = {}
    for mode in MODES:
        sc = with_mode(load_scene("blade_cut"), mode, factor=b)
        sim = Simulation(sc, device=device)
        sim.advance(seconds=seconds)
        p = sim.particles()
        cut = cut_outcome(sc, [(sim.time, {"x": p.x, "mass": p.mass})], {})["final"]
        res[mode] = {"width": cut["cut_width"], "roughness": cut["cut_roughness"], "steps": sim.steps}
    return {**res, **_against_finest(res, width_ratio="width", roughness_ratio="roughness", steps_ratio="steps")}


def run_interface_suite(device: str, seconds: float = 0.5, step: float | None = None,
                        criterion: str | None = None, seeds: int = 1, halo: int | None = None,
                        coupling: str | None = None) -> dict:
    """Every case of the matrix, printed as it finishes; returns the results. ``step``: the
    plate cases at one fixed step for every mode, ``criterion`` and ``halo``: their adaptive runs
    with that refinement criterion and halo (``run_slit``), ``seeds``: the plate cases and the thrown water
    over at least that many jitter seeds (a single run's chaos moves some rows by 5-15%:
    docs/benchmarks.md); ``coupling``: the plate cases', the thrown water's and the free bar's
    adaptive runs with that level coupling; the other cases as always."""
    results = {}

    def lifted(lift: float) -> str:
        return f", {lift:g} cells off the node plane" if lift else ""

    passages = [(f"slit {w} cells, b = {b}" + (f", tilted {tilt:g} deg" if tilt else "") + lifted(lift), w, b, seeds,
                 tilt, False, lift) for w, b, seeds, tilt, lift in SLITS] + [
        (f"round hole {w} cells, b = {b}" + lifted(lift), w, b, (0,), 0.0, True, lift) for w, b, lift in HOLES]
    passages += [(f"slit 1.0 cells, b = 3, {name}", 1.0, 3, (0,), 0.0, False, 0.0, fluid) for name, fluid in FLUIDS]
    for name, w, b, own, tilt, hole, lift, *fluid in passages:
        runs = tuple(range(max(len(own), seeds)))
        r = results[name] = run_slit(w, b, seconds, device, runs, tilt, hole, lift, fluid[0] if fluid else None, step,
                                     criterion, halo=halo, coupling=coupling)
        at = (f" (one step, cfl {step:g} at rest)" if step else "") + (f" (criterion {criterion})" if criterion else "")
        at += f" (halo {halo})" if halo is not None else ""
        at += f" ({coupling} coupling)" if coupling is not None else ""
        print(f"{name}{at}: mass through original {r['original']['through']:.4f}  "
              f"adaptive {r['adaptive']['through']:.4f}  finest {r['finest']['through']:.4f}  "
              f"-> adaptive / finest {r['through_ratio']} (goal 0.9-1.1); steps {r['steps_ratio']}x finest's "
              f"(goal <= 1.05), wall {r['wall_ratio']}x ({len(runs)} seed{'s' if len(runs) > 1 else ''}"
              f"{seed_error(r)})", flush=True)
    jets = []
    for w, b, hole, jet in JETS:
        name = f"{'round hole' if hole else 'slit'} {w} cells, b = {b}, water thrown {'up' if jet > 0 else 'down'} at it"
        jets.append(name)
        r = results[name] = run_slit(w, b, JET_SECONDS, device, tuple(range(seeds)), hole=hole, step=step,
                                     criterion=criterion, jet=jet, halo=halo, coupling=coupling)
        print(f"{name}: mass through adaptive / finest {r['through_ratio']} (finest {r['finest']['through']:.4f}, "
              f"original {r['original']['through']:.4f}); steps {r['steps_ratio']}x, wall {r['wall_ratio']}x"
              f"{f' ({seeds} seeds{seed_error(r)})' if seeds > 1 else ''}", flush=True)
    for key, names in (("plate cases", [p[0] for p in passages]), ("thrown water", jets)):
        results[key] = t = plate_tally([results[n] for n in names])
        print(f"{key}: {t['within_10pct']} of {t['cases']} within 10% of finest's mass through (mean log ratio "
              f"{t['mean_log_ratio']:+.3f}, mean abs {t['mean_abs_log_ratio']:.3f}), {t['steps_within_5pct']} within "
              f"1.05x its steps", flush=True)
    for key, title, run, span, factors in (
            ("tank at rest", "tank at rest, interface through the water", run_tank, 0.3, TANK_FACTORS),
            ("jelly pressed through", "jelly pressed through the 1.5-cell slit by a piston", run_piston, 0.3, (3,)),
            ("layered tank at rest", "tank at rest, coarse water on a refined bottom layer", run_layered_tank, 0.3,
             (2, 4)),
            ("dam break", "dam break into a refined box at the far wall", run_dam_break, 0.5, (2, 3)),
            ("blade cut", "a blade cutting a jelly block (blade_cut, 0.6 s)", run_blade_cut, 0.6, (2,)),
            ("free bar", "free jelly bar across the interface", run_free_bar, 0.4, (2, 3))):
        for b in factors:
            extra = {"coupling": coupling} if run is run_free_bar and coupling is not None else {}
            r = results[f"{key}, b = {b}"] = run(span, device, b, **extra)
            print(f"{title}, b = {b}: {summary_line(key, r)}", flush=True)
    return results
