"""Checks that a valid scene can run at all, made before anything is allocated.

The scene model checks every key on its own; these checks look at the scene as a
whole, the way the simulation will use it:

* **memory**: the dense grid and the particles must fit in the memory of the device
  (RAM for the CPU, the GPU's memory for CUDA). :func:`memory_estimate` gives the
  estimate; a scene that needs more is refused with the estimate and the key to change,
  instead of failing inside an allocation (or swapping the machine to a halt).
* **time stepping**: the run must have a finite number of frames, and the first time
  step (CFL on the stiffest material and the fastest body) must fill a frame in a
  sane number of steps, instead of dividing by zero or stepping forever.

:func:`check_feasible` raises :class:`~abmpm.errors.SceneError` naming the key
(``simulation.dx: the grid needs ...``); the CLI adds the scene file.
"""

from __future__ import annotations

import math
import os

import warp as wp

from abmpm.errors import AbmpmError, SceneError
from abmpm.geometry.sampling import shape_bounds_and_inside
from abmpm.runtime import MIN_DT_FRACTION, cfl_time_step, choose_device
from abmpm.sim.materials import kinematic_viscosity, wave_speed

__all__ = ["memory_estimate", "available_memory", "check_feasible", "GRID_NODE_BYTES", "PARTICLE_BYTES"]

# Grid storage per node: momentum (vec3), mass (float), velocity (vec3) as float32.
GRID_NODE_BYTES = 28
# Per node with colliders: the color field (distance float, direction vec3, body int).
COLOR_NODE_BYTES = 20
# Particle state per particle on the device: x, v, surface_point, surface_side (vec3), C, F (mat33),
# history, mass, volume (float), surface_body, material, level, id, family (int32).
PARTICLE_BYTES = 152
# Nodes a grid has beyond the domain's cells on each axis (GRID_PAD = 3 per side, +1).
GRID_EXTRA_NODES = 7
# The solver indexes nodes and particles with 32-bit integers.
MAX_INDEX = 2**31 - 1
# A run longer than this many frames, or a frame needing more time steps than this,
# is a mistake (an absurd fps or duration, a stiffness or speed off by many orders): a
# million frames are nine hours at 30 fps, each frame written and each taking steps.
MAX_FRAMES = 1e6
MAX_STEPS_PER_FRAME = 1e8
# typical scenes take 50-500 steps a frame; this many makes a run slow enough to say so
SLOW_STEPS_PER_FRAME = 1e4


def _gb(n: float) -> str:
    return f"{n / 1e9:.1f} GB"


def _mode(scene, mode: str | None) -> str:
    return mode or scene.simulation.refinement.mode


def _grid_dx(scene, mode: str | None) -> float:
    """Spacing of the dense grid (and of the particle lattice): dx / b in finest mode."""
    st = scene.simulation
    return st.dx / st.refinement.factor if _mode(scene, mode) == "finest" else st.dx


def _clipped_volume(lo, hi, st) -> float:
    vol = 1.0
    for a in range(3):
        vol *= max(0.0, min(hi[a], st.domain_max[a]) - max(lo[a], st.domain_min[a]))
    return vol


def _body_bounds(body, scene, i: int, load_meshes: bool):
    """Bounding box of a body, or None for a mesh body when meshes are not loaded."""
    if body.shape == "mesh" and not load_meshes:
        return None
    lo, hi, _ = shape_bounds_and_inside(body, scene.resolve, f"bodies[{i}]")
    return [float(x) for x in lo], [float(x) for x in hi]


def memory_estimate(scene, mode: str | None = None, load_meshes: bool = True) -> dict:
    """Bytes the simulation of ``scene`` needs at the start, by part.

    * grid: ``prod(ceil((max - min) / dx) + 7)`` nodes (dx / factor in finest mode) of
      28 bytes, plus 20 bytes of collider color field per node when there are colliders;
    * particles: each body's bounding box (clipped to the domain) filled at
      ``particles_per_cell`` per cell of the particle lattice (an upper estimate: the
      sampler does build that whole lattice), 152 bytes each. Mesh bodies count as the
      whole domain when ``load_meshes`` is false.

    Adaptive mode is estimated like original mode, plus the ``factor^3 - 1`` children of
    each particle of a body's bounding box within a refinement box (those split at the
    first step); particles that split near colliders and the sparse fine grid grow during
    the run.
    Returns ``{"grid_nodes", "grid_bytes", "particles", "particle_bytes",
    "body_particles", "total_bytes"}``.
    """
    st = scene.simulation
    dx = _grid_dx(scene, mode)
    nodes = 1.0
    for a in range(3):
        cells = (st.domain_max[a] - st.domain_min[a]) / dx
        nodes *= math.ceil(cells - 1e-9) + GRID_EXTRA_NODES if math.isfinite(cells) else math.inf
    node_bytes = GRID_NODE_BYTES + (COLOR_NODE_BYTES if scene.colliders else 0)
    ref = st.refinement
    boxes = ref.boxes if _mode(scene, mode) == "adaptive" else []
    per_body = []
    for i, body in enumerate(scene.bodies):
        bounds = _body_bounds(body, scene, i, load_meshes)
        lo, hi = (st.domain_min, st.domain_max) if bounds is None else bounds
        vol = _clipped_volume(lo, hi, st)
        # the part in refinement boxes splits at once (overlapping boxes counted once each: an upper estimate)
        boxed = min(vol, sum(_clipped_volume([max(lo[a], b_lo[a]) for a in range(3)],
                                             [min(hi[a], b_hi[a]) for a in range(3)], st) for b_lo, b_hi in boxes))
        per_body.append((vol + boxed * (ref.factor**3 - 1)) / dx**3 * body.particles_per_cell)
    particles = sum(per_body)
    return {
        "grid_nodes": nodes,
        "grid_bytes": nodes * node_bytes,
        "particles": particles,
        "particle_bytes": particles * PARTICLE_BYTES,
        "body_particles": per_body,
        "total_bytes": nodes * node_bytes + particles * PARTICLE_BYTES,
    }


def _ram_bytes() -> int | None:
    try:
        return int(os.sysconf("SC_PAGE_SIZE")) * int(os.sysconf("SC_PHYS_PAGES"))
    except (AttributeError, ValueError, OSError):  # not a POSIX system
        return None


def available_memory(device: str | None) -> tuple[int | None, str]:
    """(bytes, what) the simulation can use on ``device``: the machine's RAM for the CPU,
    the GPU's memory for 'cuda:N'. (None, ...) when unknown."""
    if device and str(device).startswith("cuda"):
        try:
            total = int(getattr(wp.get_device(device), "total_memory", 0) or 0)
            if total > 0:
                return total, f"GPU {device} has"
        except Exception:  # pragma: no cover - no driver, or an unknown device
            pass
    return _ram_bytes(), "this machine has"


def _resolve_device(scene, device: str | None) -> str:
    return choose_device(device if device is not None else scene.simulation.device)


def check_memory(scene, mode: str | None = None, device: str | None = None, memory: int | None = None) -> None:
    """SceneError if the grid or particles of ``scene`` cannot fit (see memory_estimate)."""
    st = scene.simulation
    est = memory_estimate(scene, mode, load_meshes=False)
    if memory is None:
        memory, what = available_memory(_resolve_device(scene, device) if device != "cpu" else "cpu")
    else:
        what = "this machine has"
    too_many = est["grid_nodes"] > MAX_INDEX or est["particles"] > MAX_INDEX
    if not too_many and (memory is None or est["total_bytes"] <= memory):
        return
    if any(b.shape == "mesh" for b in scene.bodies):  # refine: the mesh bodies' real bounds
        est = memory_estimate(scene, mode, load_meshes=True)
        too_many = est["grid_nodes"] > MAX_INDEX or est["particles"] > MAX_INDEX
        if not too_many and (memory is None or est["total_bytes"] <= memory):
            return
    finest = _mode(scene, mode) == "finest"
    grid = "the finest grid (dx / factor)" if finest else "the grid"
    if est["grid_nodes"] > MAX_INDEX:
        raise SceneError(
            f"simulation.dx: {grid} would have {est['grid_nodes']:.3g} nodes, more than the solver's "
            f"limit of {MAX_INDEX:.3g} (32-bit indices); raise dx or shrink the domain"
        )
    big = max(range(len(est["body_particles"])), key=lambda i: est["body_particles"][i])
    if est["particles"] > MAX_INDEX:
        raise SceneError(
            f"bodies[{big}]: the bodies would have {est['particles']:.3g} particles "
            f"({est['body_particles'][big]:.3g} in bodies[{big}]), more than the solver's limit of "
            f"{MAX_INDEX:.3g} (32-bit indices); raise simulation.dx, lower particles_per_cell or "
            "make the bodies smaller"
        )
    need = (
        f"needs {_gb(est['total_bytes'])} ({grid}: {est['grid_nodes']:.2g} nodes, {_gb(est['grid_bytes'])}; "
        f"particles: {est['particles']:.2g}, {_gb(est['particle_bytes'])}), more than the "
        f"{_gb(memory)} {what}"
    )
    if est["grid_bytes"] >= est["particle_bytes"]:
        hint = "raise dx or shrink the domain" + (" (or lower refinement.factor)" if finest else "")
        raise SceneError(f"simulation.dx: the scene {need}; {hint}")
    split = " (adaptive mode splits the particles in refinement.boxes into factor^3: lower simulation.refinement." \
        "factor or shrink the boxes)" if _mode(scene, mode) == "adaptive" and st.refinement.boxes else ""
    raise SceneError(
        f"bodies[{big}]: the scene {need}; raise simulation.dx, lower bodies[{big}].particles_per_cell "
        f"or make the bodies smaller{split}"
    )


def _wave_speed(material) -> float:

    try:
        c = wave_speed(material)
    except (OverflowError, ZeroDivisionError, ValueError):
        return math.inf
    return c if math.isfinite(c) else math.inf


def _material_key(material) -> str:
    """The key most likely to blame for a material's absurd wave speed."""
    if material.density < 1e-3:
        return "density"
    if material.model == "snow" and 0.5 * material.hardening * min(1.0, 10.0 * material.critical_compression) > 20:
        return "hardening"
    return "bulk_modulus" if material.model == "fluid" else "youngs_modulus"


def _first_step(scene, mode: str | None):
    """The run's first time step from the scene alone: its length, the steps a frame
    takes at it, and what sets it (SceneError where duration * fps is absurd)."""
    st = scene.simulation
    frames = st.duration * st.fps
    if not math.isfinite(frames) or frames > MAX_FRAMES:
        key = "fps" if st.fps / 30.0 > st.duration / 2.0 else "duration"
        raise SceneError(
            f"simulation.{key}: duration * fps = {frames:.3g} frames, more than {MAX_FRAMES:.0e}; "
            "shorten the duration or lower fps"
        )
    frame_dt = 1.0 / st.fps
    dx = st.dx / st.refinement.factor if _mode(scene, mode) in ("adaptive", "finest") else st.dx
    used = {b.material for b in scene.bodies}
    speeds = [(_wave_speed(m), i, m) for i, m in enumerate(scene.materials) if m.name in used]
    c, k, material = max(speeds, key=lambda t: t[0])
    # fastest initial particle: the body's velocity plus its spin times the largest
    # possible distance from its centre (the domain's diagonal)
    diag = math.dist(st.domain_min, st.domain_max)
    body_speeds = []
    for i, b in enumerate(scene.bodies):
        lin = math.hypot(*b.velocity)
        rot = math.hypot(*b.angular_velocity) * diag
        body_speeds.append((lin + rot, i, "velocity" if lin >= rot else "angular_velocity"))
    v, i, vkey = max(body_speeds)
    nu, kv = max(((kinematic_viscosity(m), k) for k, m in enumerate(scene.materials) if m.name in used),
                 default=(0.0, 0))
    try:
        dt = cfl_time_step(st.cfl, st.max_dt, dx, c + v, nu)
        steps = frame_dt / dt
    except (ZeroDivisionError, OverflowError):
        dt, steps = 0.0, math.inf
    return dict(dt=dt, steps=steps, frame_dt=frame_dt, dx=dx, c=c, k=k, material=material, v=v, i=i, vkey=vkey,
                nu=nu, kv=kv)


def slow_start_note(scene, mode: str | None = None) -> str | None:
    """A note when the first time step makes every frame cost more than SLOW_STEPS_PER_FRAME
    steps (a nearly incompressible solid, a very stiff fluid): the run will be slow."""
    f, st = _first_step(scene, mode), scene.simulation
    if not (f["steps"] > SLOW_STEPS_PER_FRAME and math.isfinite(f["c"])) or f["v"] > f["c"]:
        return None
    if f["dt"] != cfl_time_step(st.cfl, st.max_dt, f["dx"], f["c"] + f["v"]):
        return None  # viscosity sets the step, not the wave speed
    return (f"materials[{f['k']}]: its wave speed of {f['c']:.3g} m/s sets a time step of {f['dt']:.2g} s, "
            f"{f['steps']:.3g} steps a frame: the run will be slow (a Poisson ratio near 0.5 or a very stiff "
            f"material; lower {_material_key(f['material'])} or raise simulation.dx if that is not wanted)")


def check_time_stepping(scene, mode: str | None = None) -> None:
    """SceneError if the run cannot be time-stepped: an infinite or absurd number of
    frames, or a first time step that is zero or needs more than 1e8 steps per frame."""
    f = _first_step(scene, mode)
    st, dt, steps, frame_dt, dx = scene.simulation, f["dt"], f["steps"], f["frame_dt"], f["dx"]
    c, k, material, v, i, vkey, nu, kv = (f[n] for n in ("c", "k", "material", "v", "i", "vkey", "nu", "kv"))
    if dt > 0.0 and math.isfinite(steps) and steps <= MAX_STEPS_PER_FRAME:
        rest = cfl_time_step(st.cfl, st.max_dt, dx, c, nu)
        if dt < MIN_DT_FRACTION * rest:  # the run would stop at its first step as a blow-up
            raise SceneError(
                f"bodies[{i}].{vkey}: a start at {v:.3g} m/s needs a first time step of {dt:.3g} s, under "
                f"{MIN_DT_FRACTION:g} of the step at rest ({rest:.3g} s), where a run stops as blown up; "
                "lower the speed"
            )
        return
    per_frame = f"a frame (1/fps = {frame_dt:.3g} s) would need {steps:.3g} time steps of {dt:.3g} s"
    limit = f"more than the {MAX_STEPS_PER_FRAME:.0e} allowed"
    if nu > 0.0 and dt < cfl_time_step(st.cfl, st.max_dt, dx, c + v):
        raise SceneError(
            f"materials[{kv}].viscosity: explicit viscosity (viscosity / density = {nu:.3g} m^2/s on cells of "
            f"{dx:.3g} m) sets the time step: {per_frame}, {limit}; lower the viscosity or raise simulation.dx"
        )
    if dt == st.max_dt:
        raise SceneError(f"simulation.max_dt: {per_frame}, {limit}; raise max_dt")
    if v > c:
        raise SceneError(
            f"bodies[{i}].{vkey}: the body's initial speed (up to {v:.3g} m/s) sets the time step: "
            f"{per_frame}, {limit}"
        )
    if st.cfl < 1e-3:
        raise SceneError(f"simulation.cfl: {per_frame}, {limit}; raise cfl")
    if not math.isfinite(c):
        raise SceneError(
            f"materials[{k}].{_material_key(material)}: the material's wave speed (from its stiffness and "
            "density) overflows, so no time step is small enough"
        )
    raise SceneError(
        f"materials[{k}].{_material_key(material)}: the material's wave speed ({c:.3g} m/s, from its "
        f"stiffness and density) sets the time step: {per_frame}, {limit}"
    )


def check_feasible(scene, mode: str | None = None, device: str | None = None) -> None:
    """Refuse (SceneError, naming the key) a scene that cannot run: one whose grid or
    particles do not fit in memory, or that cannot be time-stepped. Cheap: nothing is
    allocated and mesh files are read only when their size matters."""
    if mode is not None and mode not in ("original", "adaptive", "finest"):
        raise AbmpmError(f"unknown mode {mode!r} (use original, adaptive or finest)")
    check_time_stepping(scene, mode)
    check_memory(scene, mode, device)
