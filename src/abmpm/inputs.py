"""Scene -> solver inputs: the one place where the scene schema meets the solver.

The solver (``abmpm.sim``) knows nothing of scene files, pydantic models or mesh
files. Everything it needs is built here from a validated :class:`Scene`:

* :func:`solver_config`: domain, spacing, gravity, walls, refinement factor;
* :func:`material_rows`: one ``MaterialParams`` row per scene material;
* :func:`rigid_bodies`: collider meshes placed at rest, with their contact law and motion;
* :func:`sample_scene`: the initial particles;
* :func:`region_params`: how the refined region is detected from the colliders.
"""

from __future__ import annotations

import numpy as np

from .geometry.meshes import limit_edge_length
from .geometry.motion import KinematicMotion
from .geometry.placement import collider_mesh
from .geometry.region import RegionParams
from .geometry.sampling import JITTER, body_lattice, body_shape, sample_body_volume
from .scene.model import Scene
from .sim.boundary import FACES
from .sim.collider_set import RigidBody
from .sim.config import SolverConfig
from .sim.materials import MaterialParams, kinematic_viscosity, material_params, wave_speed


def solver_config(scene: Scene, mode: str) -> SolverConfig:
    """Grids of a run in ``mode`` (``scene`` already at the finest spacing in finest mode)."""
    st = scene.simulation
    b = st.refinement.factor
    return SolverConfig(
        domain_lo=st.domain_min, domain_hi=st.domain_max, dx=st.dx, gravity=st.gravity,
        walls={f: st.walls.face(f) for f in FACES},
        wall_images=st.walls.images,
        refine_factor=b if mode == "adaptive" else None,
        base_level=1 if mode == "finest" else 0,
        reconstruct=st.refinement.reconstruct,
        surface_threshold=st.refinement.surface_threshold,
        seed=st.seed,
        time_steps=st.refinement.time_steps,
        coupling=st.refinement.coupling,
        stiffening=st.stiffening,
        cuda_graph=st.cuda_graph,
        cfl=st.cfl,
    )


def material_rows(scene: Scene) -> list[MaterialParams]:
    return [material_params(m) for m in scene.materials]


def max_kinematic_viscosity(scene: Scene) -> float:
    """Largest viscosity / density (m^2/s) among the materials that bodies use (the
    explicit viscous step limit; 0 where none is viscous)."""
    used = {b.material for b in scene.bodies}
    return max((kinematic_viscosity(m) for m in scene.materials if m.name in used), default=0.0)


def max_wave_speed(scene: Scene) -> float:
    """Fastest wave speed at rest among the materials that bodies use (CFL)."""
    used = {b.material for b in scene.bodies}
    return max(wave_speed(m) for m in scene.materials if m.name in used)


# Longest triangle edge of a collider the solver sees, in coarse cells: closest
# points on long sliver triangles are too inexact for the no-crossing test
# (geometry.meshes.limit_edge_length).
MAX_COLLIDER_EDGE_CELLS = 2.0


def rigid_bodies(scene: Scene) -> list[RigidBody]:
    """The scene's colliders as solver bodies (meshes built or loaded, placed at rest,
    no edge longer than MAX_COLLIDER_EDGE_CELLS coarse cells)."""
    bodies = []
    for i, c in enumerate(scene.colliders):
        mesh = collider_mesh(c, scene.resolve, f"colliders[{i}]")
        vertices, faces = limit_edge_length(mesh.vertices, mesh.faces, MAX_COLLIDER_EDGE_CELLS * scene.simulation.dx)
        bodies.append(RigidBody(
            vertices=vertices, faces=faces,
            motion=KinematicMotion(c.motion, c.center),
            boundary=c.boundary, friction=c.friction, separation=c.separation,
        ))
    return bodies


def region_params(scene: Scene) -> RegionParams:
    r = scene.simulation.refinement
    st = scene.simulation
    return RegionParams(bandwidth=r.bandwidth, threshold=r.threshold, halo=r.halo, boxes=tuple(r.boxes),
                        criterion=r.criterion, gap_cells=r.gap_cells, walls=(st.domain_min, st.domain_max))


def skew(w) -> np.ndarray:
    """Matrix of the cross product w x (.)"""
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def sample_scene(scene: Scene, split_factor: int = 1) -> dict[str, np.ndarray]:
    """Particles of every body, as numpy arrays (deterministic by the scene's seed).

    ``split_factor`` b > 1: the particles may be split into b^3 children (adaptive
    mode with something to refine). They are then sampled on their lattice points, not
    jittered: each child is jittered about its own point when it splits (sim/split.py,
    CHILD_JITTER), so that split material has finest mode's texture, where a parent's
    offset would be shared by its whole family (docs/method.md, "Split children sampled
    as finest samples")."""
    st = scene.simulation
    rng = np.random.default_rng(st.seed)
    parts = []
    for i, body in enumerate(scene.bodies):
        x, vol = sample_body_volume(body, st, rng, resolve=scene.resolve, where=f"bodies[{i}]",
                                    jitter=JITTER if split_factor == 1 else 0.0)
        n = len(x)
        mat = scene.materials[scene.material_index(body.material)]
        w = np.asarray(getattr(body, "angular_velocity", (0.0, 0.0, 0.0)), dtype=np.float64)
        centre = x.astype(np.float64).mean(axis=0)
        v = np.asarray(body.velocity, dtype=np.float64) + np.cross(w, x - centre)
        parts.append(
            {
                "x": x.astype(np.float32),
                "v": v.astype(np.float32),
                # a rigid spin's velocity gradient is skew(w): start APIC consistent with it
                "C": np.tile(skew(w).astype(np.float32), (n, 1, 1)),
                "mass": np.full(n, vol * mat.density, dtype=np.float32),
                "volume": np.full(n, vol, dtype=np.float32),
                "material": np.full(n, scene.material_index(body.material), dtype=np.int32),
                "level": np.zeros(n, dtype=np.int32),
            }
        )
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


def overlapping_bodies(scene: Scene) -> list[str]:
    """A note for each pair of bodies that share space: the lattice points of one inside
    the shape of the other each carry both bodies' material there (their masses add).
    Only bodies whose bounding boxes overlap are sampled again."""
    st, notes = scene.simulation, []
    if len(scene.bodies) < 2:
        return notes
    shapes = [body_shape(b, scene.resolve, f"bodies[{i}]") for i, b in enumerate(scene.bodies)]
    for i, body in enumerate(scene.bodies):
        others = [j for j in range(i + 1, len(shapes))
                  if np.all(shapes[i].lo < shapes[j].hi) and np.all(shapes[j].lo < shapes[i].hi)]
        if not others:
            continue
        _, points = body_lattice(body, st, scene.resolve, f"bodies[{i}]", shapes[i])
        for j in others:
            shape = shapes[j]
            near = np.all((points > shape.lo) & (points < shape.hi), axis=1)
            n = int(shape.inside(points[near]).sum()) if near.any() else 0
            if n:
                notes.append(f"bodies[{i}] and bodies[{j}] overlap: {n} of bodies[{i}]'s {len(points)} particles lie "
                             f"inside bodies[{j}], where both bodies' material then is (twice the density); move or "
                             "shrink one")
    return notes
