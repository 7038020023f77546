"""Surface reconstruction on many bodies split whole: ``abmpm bench --suite reconstruction``.

The suite's tests (tests/test_reconstruction.py) hold one case of each kind; this runs
the sets their bounds were checked on, so that a change to reconstruction can be read
against more than the cases it was made on (docs/method.md, "The outermost child's aim,
and Newton steps for solids"). The measure throughout: the spread of the outermost
particle per bin of the surface (per direction for a sphere, per column for a face),
reconstructed over the parents' (the issue's bound: 0.5).

* fluid spheres split whole: radius 4-7 coarse cells, centred on a node or 0.26 cells
  off it, three jitter seeds, b = 2 and 3;
* an elastic block sheared 0.6 and stretched 1.25, each particle's F off by 5%, ten seeds
  (its top face);
* water dropped into a tank and settled (four starting velocities, 0.4-0.8 s), and sand
  heaps thrown and settled (its free surface less a fitted quadratic, the slosh).
"""

from __future__ import annotations

import numpy as np

from ..geometry.sampling import particle_volume, sample_body
from ..scene import model as sm
from ..sim.materials import material_params
from ..sim.solver import MPMSolver, SolverConfig
from ..sim.state import ParticleState
from ..simulation import Simulation, init_warp

DX = 0.05  # coarse spacing of every case
H = DX / 2  # parent spacing (8 particles per cell)
SPHERES = [(radius, off, seed) for radius in (0.2, 0.25, 0.3, 0.35) for off in (0.0, 0.26) for seed in (7, 1, 2)]
BLOCK_SEEDS = tuple(range(3, 13))
# (settling seconds, initial velocity, jitter seed) of the tanks; the first is the test's
TANKS = [(0.6, (0.4, 0.0, -0.3), 0), (0.5, (0.4, 0.0, -0.3), 0), (0.8, (0.4, 0.0, -0.3), 0),
         (0.6, (-0.3, 0.0, 0.5), 1), (0.7, (0.6, 0.0, 0.2), 2), (0.4, (0.2, 0.0, 0.2), 3)]
HEAPS = [(0.6, (0.8, 0.0, -0.5), 0), (0.5, (-0.5, 0.0, 0.8), 1), (0.8, (0.6, 0.0, 0.3), 2)]
TANK_SIZE = 0.6  # m, the tank's width and depth


def split_whole(parents: dict, material, reconstruct: bool, b: int = 2, device: str = "cpu") -> dict:
    """Split every parent (the whole unit box is refined), as the adaptive step does;
    the children sorted by id."""
    init_warp()
    solver = MPMSolver(SolverConfig((0, 0, 0), (1, 1, 1), DX, gravity=(0, 0, 0), refine_factor=b,
                                    reconstruct=reconstruct), [material_params(material)], device)
    state = ParticleState.from_numpy(parents, device)
    solver.reserve_ids(len(parents["x"]))
    solver.set_region(np.ones(tuple(d - 1 for d in solver.grid.dims), dtype=bool), state)
    out = state.numpy()
    order = np.argsort(out["id"], kind="stable")
    return {k: a[order] for k, a in out.items()}


def parents_of(x, density, v=None, C=None, F=None) -> dict:
    """Parent arrays at 8 particles per cell; random v and C unless given."""
    n = len(x)
    vol = particle_volume(DX, 8)
    rng = np.random.default_rng(1)
    return {
        "x": np.asarray(x, np.float32),
        "v": (rng.normal(0, 1.0, (n, 3)) if v is None else v).astype(np.float32),
        "C": (rng.normal(0, 2.0, (n, 3, 3)) if C is None else C).astype(np.float32),
        "F": (np.tile(np.eye(3), (n, 1, 1)) if F is None else F).astype(np.float32),
        "mass": np.full(n, vol * density, np.float32),
        "volume": np.full(n, vol, np.float32),
    }


def fibonacci_directions(n: int) -> np.ndarray:
    k = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * k / n)
    theta = np.pi * (1 + 5**0.5) * k
    return np.stack([np.cos(theta) * np.sin(phi), np.cos(phi), np.sin(theta) * np.sin(phi)], axis=1)


def outermost_per_bin(height: np.ndarray, bins: np.ndarray) -> np.ndarray:
    top = np.full(bins.max() + 1, -np.inf)
    np.maximum.at(top, bins, height)
    return top[np.isfinite(top)]


def sphere_roughness(x: np.ndarray, centre: np.ndarray) -> float:
    """Spread of the outermost particle per direction bin (300 bins) about ``centre``."""
    d = x.astype(np.float64) - centre
    return outermost_per_bin(np.linalg.norm(d, axis=1), np.argmax(d @ fibonacci_directions(300).T, axis=1)).std()


def sphere_parents(radius: float, off: float, seed: int) -> tuple[dict, np.ndarray]:
    """A fluid sphere's parents, its centre ``off`` coarse cells off a node, and that centre."""
    centre = np.array([0.5, 0.5, 0.5]) + off * DX
    body = sm.SphereBody(material="m", center=tuple(centre), radius=radius)
    return parents_of(sample_body(body, sm.SimulationSettings(dx=DX), np.random.default_rng(seed)), 1000.0), centre


def sheared_block(seed: int = 3):
    """An elastic block sheared and stretched by A before the split, with each
    particle's F off A by a few percent (as after a real deformation): the F-deformed
    sub-lattices overlap and leave gaps. Returns the parents, A and the block's rest
    bounds about its centre."""
    lo, hi = np.array([0.3, 0.3, 0.3]), np.array([0.6, 0.5, 0.6])
    body = sm.BoxBody(material="m", min=tuple(lo), max=tuple(hi))
    x0 = sample_body(body, sm.SimulationSettings(dx=DX), np.random.default_rng(seed)).astype(np.float64)
    A = np.array([[1.0, 0.6, 0.0], [0.0, 1.25, 0.0], [0.0, 0.0, 0.85]])  # shear 0.6, stretch 1.25 in y
    centre = (lo + hi) / 2
    x = (x0 - centre) @ A.T + np.array([0.5, 0.5, 0.5])
    rng = np.random.default_rng(seed + 1)
    F = A[None] @ (np.eye(3) + rng.normal(0, 0.05, (len(x), 3, 3)))
    return parents_of(x, 1000.0, F=F), A, (lo - centre, hi - centre)


def block_top_roughness(x: np.ndarray, A: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> float:
    """The sheared block's top face (rest-frame y = hi[1]): outermost particle per rest-frame
    column of a coarse cell, away from the edges, as a distance along the face's normal."""
    Ainv = np.linalg.inv(A)
    r = (x.astype(np.float64) - 0.5) @ Ainv.T
    cols = np.floor((r[:, [0, 2]] - lo[[0, 2]]) / DX).astype(int)
    keep = np.all((cols >= 1) & (cols < np.floor((hi - lo)[[0, 2]] / DX) - 1), axis=1)
    _, bins = np.unique(cols[keep, 0] * 1000 + cols[keep, 1], return_inverse=True)
    height = r[keep, 1] / np.linalg.norm(Ainv.T @ [0, 1, 0])  # rest-frame y -> distance along the normal
    return outermost_per_bin(height, bins).std()


def settled(material, seconds: float = 0.6, velocity=(0.4, 0.0, -0.3), seed: int = 0, device: str = "cpu"):
    """``material`` dropped into a tank with ``velocity`` and settled for ``seconds`` in
    original mode: a disordered free surface, as when material that has flowed enters a
    region. Returns the parents (the run's masses, volumes, F and history) and the
    particles."""
    scene = sm.Scene(
        simulation=sm.SimulationSettings(dx=DX, fps=20, domain_max=(TANK_SIZE, 0.5, TANK_SIZE), seed=seed),
        materials=[material],
        bodies=[sm.BoxBody(material=material.name, min=(0.05, 0.05, 0.05), max=(0.55, 0.25, 0.55), velocity=velocity)],
    )
    sim = Simulation(scene, device=device)
    sim.advance(seconds=seconds)
    p = sim.particles()
    parents = parents_of(p.x, 1000.0, v=p.v, C=p.C, F=p.F)
    parents.update(history=p.history.astype(np.float32), mass=p.mass, volume=p.volume)
    return parents, p


def tank_top_roughness(x: np.ndarray) -> float:
    """The settled tank's free surface: the top particle per coarse column away from the
    walls, less a quadratic fitted over the columns (the slosh)."""
    cols = np.floor(x[:, [0, 2]] / DX).astype(int)
    keep = np.all((cols >= 2) & (cols < int(TANK_SIZE / DX) - 2), axis=1)
    _, bins = np.unique(cols[keep, 0] * 1000 + cols[keep, 1], return_inverse=True)
    y = x[keep, 1].astype(np.float64)
    top = np.full(bins.max() + 1, -np.inf)
    np.maximum.at(top, bins, y)
    # the column's position (its top particle's x, z) and the surface's large-scale shape
    at = np.zeros((len(top), 2))
    hit = y == top[bins]
    at[bins[hit]] = x[keep][hit][:, [0, 2]]
    X, Z = at[:, 0], at[:, 1]
    basis = np.stack([np.ones_like(X), X, Z, X * X, X * Z, Z * Z], axis=1)
    coef, *_ = np.linalg.lstsq(basis, top, rcond=None)
    return (top - basis @ coef).std()


def _stats(name: str, ratios: list[float]) -> dict:
    r = np.asarray(ratios)
    row = {"ratios": [round(float(a), 3) for a in r], "min": round(float(r.min()), 3),
           "mean": round(float(r.mean()), 3), "max": round(float(r.max()), 3), "above_half": int((r > 0.5).sum())}
    print(f"{name}: reconstructed / parents' roughness min {row['min']} mean {row['mean']} max {row['max']}, "
          f"{row['above_half']} of {len(r)} above 0.5", flush=True)
    return row


def run_reconstruction_suite(device: str = "cpu") -> dict:
    """Every set of the module docstring, reconstructed over the parents' roughness."""
    out = {}
    water = sm.Fluid(name="m")
    for b in (2, 3):
        ratios = []
        for radius, off, seed in SPHERES:
            parents, centre = sphere_parents(radius, off, seed)
            recon = split_whole(parents, water, True, b, device)
            ratios.append(sphere_roughness(recon["x"], centre) / sphere_roughness(parents["x"], centre))
        out[f"fluid spheres, b = {b}"] = _stats(f"fluid spheres, b = {b}", ratios)
    jelly, ratios = sm.Elastic(name="m", youngs_modulus=1e5), []
    for seed in BLOCK_SEEDS:
        parents, A, (lo, hi) = sheared_block(seed)
        recon = split_whole(parents, jelly, True, 2, device)
        ratios.append(block_top_roughness(recon["x"], A, lo, hi) / block_top_roughness(parents["x"], A, lo, hi))
    out["sheared elastic block"] = _stats("sheared elastic block, top face", ratios)
    for name, material, cases in (("settled water", sm.Fluid(name="m", bulk_modulus=4e4, viscosity=0.5), TANKS),
                                  ("settled sand", sm.Sand(name="m"), HEAPS)):
        ratios = []
        for seconds, velocity, seed in cases:
            parents, _ = settled(material, seconds, velocity, seed, device)
            recon = split_whole(parents, material, True, 2, device)
            ratios.append(tank_top_roughness(recon["x"]) / tank_top_roughness(parents["x"]))
        out[name] = _stats(name, ratios)
    return out
