"""Run a scene to completion and write everything a user wants to look at.

``run(scene, "out/dam_break")`` produces::

    out/dam_break/
        scene.json                      the validated scene (used by resume and render)
        frames/frame_00000.ply ...      particles every output.frame_every frames
        colliders/collider_00000.ply    (scenes with colliders) their triangles at that frame
        checkpoints/checkpoint_00015.npz  every output.checkpoint_every frames and at the end
        summary.json                    run statistics and per-frame diagnostics
        energy.png                      kinetic, potential and total energy; mass and momentum
        preview.mp4, preview.png        a rendered preview and its poster frame
        surfaces/surface_00000_water.ply  (output.surface = true) surface mesh per material
        particles.usd                   (output.usd = true) particles, colliders, surfaces

Each output is a writer of :mod:`abmpm.io.writers`; the folder's layout and
housekeeping are in :mod:`abmpm.io.outdir`, the preview in :mod:`abmpm.post.preview`.
This module runs the loop: it checks the scene and the initial state, resumes from
a checkpoint, advances the Simulation and hands every frame to the writers.

Checkpoints hold the complete state (particles, dt, substeps, history), so a resumed
run continues bit-identically (on the CPU) to one that was never interrupted.
"""

from __future__ import annotations

import contextlib
import math
import os
import time
from pathlib import Path

import numpy as np
from rich.markup import escape

from abmpm.errors import (OUT_OF_MEMORY_HINT, AbmpmError, OutOfMemory, OutputError, SceneError, SimulationBlowUp,
                           allocation_failure)
from abmpm.geometry import inside_mesh
from abmpm.geometry.placement import collider_mesh
from abmpm.inputs import overlapping_bodies
from abmpm.io.outdir import SCENE_FILE, SUMMARY_FILE, clean_previous_run, clean_temporaries, prepare_out_dir
from abmpm.io.progress import Progress
from abmpm.io.resume import resume_from_checkpoint
from abmpm.io.summary import write_json
from abmpm.io.writers import FrameData, RunContext, Writer, build_writers
from abmpm.io.writers.summary import make_summary
from abmpm.post.preview import render_folder
from abmpm.scene.checks import MAX_FRAMES, slow_start_note
from abmpm.scene.loader import load_scene, scene_record
from abmpm.scene.model import Scene
from abmpm.simulation import Simulation, can_refine

__all__ = ["render_folder", "run", "total_frames"]


def total_frames(scene: Scene, frames: int | None = None) -> int:
    """Frames of a run: ``frames`` if given, else enough to cover ``duration`` (duration *
    fps rounded up, at least 1; a part of a frame is a whole one)."""
    if frames is not None:
        if int(frames) < 1:
            raise AbmpmError(f"frames must be >= 1, got {frames}")
        if int(frames) > MAX_FRAMES:
            raise AbmpmError(f"{int(frames):.3g} frames: more than {MAX_FRAMES:.0e}")
        return int(frames)
    st = scene.simulation
    return max(1, math.ceil(st.duration * st.fps - 1e-6))


def run(
    scene: Scene | str | os.PathLike,
    out_dir: str | os.PathLike,
    device: str | None = None,
    frames: int | None = None,
    resume: bool = False,
    preview: bool = True,
    progress: bool = True,
    console=None,
    view=None,
) -> dict:
    """Simulate ``scene`` (a Scene, a ``.toml`` path or a built-in name) into ``out_dir``.

    ``frames`` overrides the number of frames (default ``duration * fps``);
    ``resume`` continues from the latest checkpoint in ``out_dir``; ``preview=False``
    skips the video; ``view`` (True or a :class:`~abmpm.io.writers.viewer.ViewOptions`)
    serves a live browser view of the run. Returns the summary dict (also written to
    ``summary.json``).
    On :class:`SimulationBlowUp` the last good state is checkpointed, the summary is
    written with status ``"blew_up"`` and the exception is re-raised; a failed allocation
    the same way, with status ``"out_of_memory"``, as :class:`OutOfMemory`.
    """
    t_start = time.perf_counter()
    scene = load_scene(scene) if not isinstance(scene, Scene) else scene
    out = Path(out_dir)
    total = total_frames(scene, frames)
    # memory and time stepping, before the output folder or anything big is made
    scene.check_feasible(None, device)
    created = not out.exists()
    prepare_out_dir(out)
    clean_temporaries(out)
    try:
        writers = build_writers(scene.output, preview=preview, view=view)  # refuses USD without usd-core
        sim = Simulation(scene, device)
        start = None if resume else sim.particles()  # read from the device once for the checks and notes
        if start is not None:
            _check_initial_state(scene, start)
    except BaseException:  # a scene found impossible while building it: no empty folder left behind
        if created:
            with contextlib.suppress(OSError):
                out.rmdir()  # only if nothing was written in it
        raise
    resumed_from, notes = resume_from_checkpoint(out, scene, sim) if resume else (None, _trapped(scene, start))
    notes += _idle_colliders(scene, sim) + [n for n in (slow_start_note(scene, sim.mode),) if n]
    notes += [] if resume else _walls_between_nodes(scene, sim, start) + overlapping_bodies(scene)
    if sim.mode == "adaptive" and not can_refine(scene):
        notes.append("adaptive mode with nothing to refine (no refinement box, no collider with refine = true): "
                     "every particle stays on the coarse grid, as in original mode")
    if frames is None and abs(total - scene.simulation.duration * scene.simulation.fps) > 1e-6:
        notes.append(f"duration {scene.simulation.duration:g} s is {scene.simulation.duration * scene.simulation.fps:.3g} "
                     f"frames at {scene.simulation.fps:g} fps: simulating {total} frames ({total / scene.simulation.fps:.4g} s)")
    if resumed_from is not None and resumed_from >= total:
        notes.append(f"the checkpoint is at frame {resumed_from}, at or past the {total} frames asked for: "
                     "nothing left to simulate")
    if resumed_from is None:
        clean_previous_run(out)
    try:
        write_json(out / SCENE_FILE, scene_record(scene))
    except OSError as exc:  # a full or read-only disk: before anything was simulated
        raise OutputError(f"cannot write output in {out}: {exc.strerror or exc}") from None

    bar = Progress(progress, console)
    ctx = RunContext(out, scene, sim, total, tuple(w.name for w in writers), bar, resumed_from, t_start)
    for w in writers:
        w.begin(ctx)

    every = scene.output.frame_every
    sim.solver.load_kernels()  # compiling (a cold kernel cache) is not simulation time
    steps0 = sim.steps
    io_seconds = 0.0
    message, err = None, None
    with bar:
        for note in notes:
            bar.print(f"[yellow]{escape(note)}[/yellow]")
        t_sim = time.perf_counter()
        ctx.clock[int(sim.frame)] = 0.0

        def on_frame(s) -> None:
            nonlocal io_seconds
            t0 = time.perf_counter()
            try:
                last = s.frame >= total
                _write_frame(writers, s, output_frame=last or s.frame % every == 0, last=last)
            except OSError as exc:
                raise OutputError(f"cannot write output in {out}: {exc.strerror or exc}") from None
            io_seconds += time.perf_counter() - t0
            busy = time.perf_counter() - t_sim - io_seconds
            ctx.clock[int(s.frame)] = round(busy, 4)
            bar.update_sim(s.frame, s.time, (s.steps - steps0) / max(busy, 1e-9))

        ctx.status = "completed"
        try:
            if resumed_from is None:
                _write_frame(writers, sim, output_frame=True, first=True)
                io_seconds += time.perf_counter() - t_sim  # writing frame 0 is output, not simulation
            bar.start_sim(sim.frame, total, sim.time)
            if sim.frame < total:
                sim.advance(frames=total - sim.frame, callback=on_frame)
        except SimulationBlowUp as exc:
            ctx.status, message, err = "blew_up", str(exc), exc
        except KeyboardInterrupt as exc:
            ctx.status, message, err = "interrupted", "interrupted by the user", exc
        except (MemoryError, RuntimeError) as exc:
            if not allocation_failure(exc):
                raise
            message = (f"out of memory at step {sim.steps} (t = {sim.time:.4f} s; {exc}); {OUT_OF_MEMORY_HINT}; "
                       f"last good frame is {sim.history[-1]['frame']}")
            ctx.status, err = "out_of_memory", OutOfMemory(message)
        sim_seconds = time.perf_counter() - t_sim - io_seconds
        for note in _refined_share(scene, sim):
            notes.append(note)
            bar.print(f"[yellow]{escape(note)}[/yellow]")
        ctx.summary = make_summary(ctx, message, sim_seconds, io_seconds, sim.steps - steps0)
        if notes:
            ctx.summary["notes"] = notes
        inverted = [(h["frame"], h.get("inverted", 0)) for h in sim.history if h.get("inverted", 0)]
        if inverted:
            first, most = inverted[0][0], max(n for _, n in inverted)
            ctx.summary["inverted_particles"] = {"first_frame": first, "most": most}
            bar.print(f"[yellow]{escape(_INVERTED.format(most=most, first=first))}[/yellow]")

        if err is None:
            _finish(writers, ctx)
            return ctx.summary
        try:
            _finish(writers, ctx)
        except (AbmpmError, OSError) as secondary:  # keep the original error
            ctx.summary["outputs_error"] = str(secondary)
            with contextlib.suppress(AbmpmError, OSError):
                write_json(out / SUMMARY_FILE, ctx.summary)
        raise err


_INVERTED = ("up to {most} particles were crushed flat or turned inside out (det F <= 0), first at frame {first}: "
             "the solid was pressed beyond what its model describes; lower the speed of the impact, raise the "
             "stiffness or lower simulation.cfl / max_dt")


def _write_frame(writers: list[Writer], sim, **flags: bool) -> None:
    data = FrameData(sim, **flags)
    for w in writers:
        w.write_frame(sim.frame, data)


def _finish(writers: list[Writer], ctx: RunContext) -> None:
    for w in writers:
        w.finish(ctx)


# --------------------------------------------------------------------------- checks


def _trapped(scene: Scene, p) -> list[str]:
    """A note for each closed collider that particles (``p``, at the start) start inside:
    CPIC keeps them on the side they start on, so they stay there."""
    notes, x = [], p.x
    for i, c in enumerate(scene.colliders):
        mesh = collider_mesh(c, scene.resolve, f"colliders[{i}]")
        if not mesh.is_watertight:
            continue
        n = int(inside_mesh(x, mesh).sum())
        if n:
            notes.append(f"colliders[{i}]: {n} of the {len(x)} particles start inside this closed collider and stay "
                         "trapped there (no particle crosses a collider); move the bodies or the collider")
    return notes


def _idle_colliders(scene: Scene, sim) -> list[str]:
    """A note for each collider that can touch nothing: no area, or (static) wholly
    outside the domain. Likely a typo in its size, center or units. The meshes are the
    simulation's own (one per collider, world space), not built again."""
    if sim.colliders is None:
        return []
    notes = []
    lo, hi = np.asarray(scene.simulation.domain_min), np.asarray(scene.simulation.domain_max)
    for i, (c, mesh) in enumerate(zip(scene.colliders, sim.colliders.body_meshes())):
        if not mesh.area > 0.0:
            notes.append(f"colliders[{i}]: its mesh has no area, so it touches nothing")
        elif c.motion.is_static and (np.any(mesh.bounds[0] > hi) or np.any(mesh.bounds[1] < lo)):
            notes.append(f"colliders[{i}]: it lies wholly outside the domain ({np.round(mesh.bounds[0], 4).tolist()} "
                         f"to {np.round(mesh.bounds[1], 4).tolist()}), so it touches nothing; check its center and size")
    return notes


# What an adaptive particle-step costs against a finest one on a CPU: 3.3-3.6 times, measured
# (docs/benchmarks.md, "When adaptive mode pays" and, since finest shed the BLAS threads' load,
# "The BLAS libraries' idle threads"). Below this many finest particles per adaptive one,
# finest mode is about as fast.
ADAPTIVE_PARTICLE_COST = 3.5


def _refined_share(scene: Scene, sim) -> list[str]:
    """A note after an adaptive run on a CPU that refined so much of its material that
    finest mode would have held under ADAPTIVE_PARTICLE_COST times its particles (the
    mean over the run's frames): there finest mode, the reference, is likely as fast."""
    if sim.mode != "adaptive" or sim.device != "cpu" or not sim.history:
        return []
    n0, n1 = np.mean([h["count_per_level"][:2] for h in sim.history], axis=0)
    family = scene.simulation.refinement.factor ** 3  # a level-0 particle is that many finest ones
    ratio = (n0 * family + n1) / max(n0 + n1, 1.0)
    if ratio >= ADAPTIVE_PARTICLE_COST:
        return []
    share = n1 / family / max(n0 + n1 / family, 1e-9)
    return [f"adaptive mode refined {share:.0%} of the material over this run: finest mode would hold only "
            f"{ratio:.1f} times its particles, and on a CPU an adaptive particle-step costs about 3.5 times a finest "
            "one, so finest mode (the reference) is likely as fast here. Adaptive mode pays where a small part "
            "of the material is refined (docs/benchmarks.md, \"When adaptive mode pays\")"]


def _walls_between_nodes(scene: Scene, sim, p) -> list[str]:
    """A note for each upper domain wall that lies between two node planes of the grid and
    that material (the particles ``p``, at the start) starts against. A wall acts at the nodes on and beyond its plane, so such
    a wall stops material at the next node plane, up to a cell further out; material that
    fills the box to the wall starts that far short of where the grid holds it and flows
    into the gap (a tank of water at rest does not stay at rest; docs/method.md, "Domain
    walls"). A lower wall always lies on a node plane (the grid is anchored there)."""
    st, notes = scene.simulation, []
    dx = sim.solver.grid.dx  # the grid of the level-0 particles (finest mode's only grid)
    lo, hi = np.asarray(st.domain_min, dtype=np.float64), np.asarray(st.domain_max, dtype=np.float64)
    if len(p.x) == 0:
        return notes
    edge = p.x.astype(np.float64) + 0.5 * np.cbrt(p.volume.astype(np.float64))[:, None]  # each particle's box
    spacing = float(np.cbrt(np.median(p.volume)))
    for d, axis in enumerate("xyz"):
        cells = (hi[d] - lo[d]) / dx
        plane = lo[d] + math.ceil(cells - 1.0e-3) * dx  # where the grid stops material (grid_update.domain_walls)
        reach = float(edge[:, d].max())
        if plane - hi[d] <= 1.0e-3 * dx or hi[d] - reach > 0.5 * spacing or plane - reach <= 0.25 * spacing:
            continue
        n = math.floor((hi[d] - lo[d]) / st.dx + 1.0e-6)  # whole cells of the scene's dx: on a node plane of every grid
        notes.append(f"simulation.domain_max: the wall at {axis} = {hi[d]:g} m lies between the grid's node planes "
                     f"({cells:.4g} cells of {dx:g} m), so the grid stops material at {axis} = {plane:.4g} m; the "
                     f"bodies reach the wall, so they start {1e3 * (plane - reach):.3g} mm short of it and will flow "
                     f"into that gap (water filling the box will not stay at rest); for a wall on a node plane set "
                     f"domain_max {axis} = {lo[d] + n * st.dx:.6g} or {lo[d] + (n + 1) * st.dx:.6g}")
    return notes


def _check_initial_state(scene: Scene, p) -> None:
    """Refuse to start from particles ``p`` that are not finite in single precision (a
    frame 0 of NaN would be written as if it were good)."""
    for name in ("x", "v", "mass", "volume", "C", "F"):
        a = getattr(p, name)
        bad = ~np.isfinite(a.reshape(len(a), -1)).all(axis=1)
        if not bad.any():
            continue
        mat = scene.materials[int(p.material[np.argmax(bad)])].name
        bodies = [i for i, b in enumerate(scene.bodies) if b.material == mat]
        where = f"bodies[{bodies[0]}]" if len(bodies) == 1 else f"bodies of material {mat!r}"
        key = {"x": "", "v": ".velocity"}.get(name, "") if len(bodies) == 1 else ""
        raise SceneError(
            f"{where}{key}: the initial particle field '{name}' is not finite in single precision "
            f"({int(bad.sum())} particles); check the body's velocity, angular_velocity, material and mesh"
        )
