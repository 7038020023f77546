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
        particles.usd                   (output.usd = true) time-sampled USD points

Checkpoints hold the complete state (particles, dt, substeps, history), so a resumed
run continues bit-identically (on the CPU) to one that was never interrupted.
"""

from __future__ import annotations

import contextlib
import importlib.util
import math
import os
import re
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
from rich.markup import escape

from abmpm.errors import AbmpmError, OutputError, SceneError, SimulationBlowUp
from abmpm.io.atomic import atomic_write
from abmpm.io.checkpoint import (
    checkpoint_name,
    latest_checkpoint,
    load_checkpoint,
    save_checkpoint,
)
from abmpm.io.ply import (
    read_mesh_ply,
    read_particles_ply,
    write_mesh_ply,
    write_particles_ply,
)
from abmpm.io.summary import write_json
from abmpm.scene.loader import load_scene
from abmpm.scene.model import Scene

__all__ = ["run", "render_folder", "total_frames", "frame_path", "collider_path"]

FRAMES_DIR = "frames"
COLLIDERS_DIR = "colliders"
CHECKPOINTS_DIR = "checkpoints"
SCENE_FILE = "scene.json"
REGION_FILE = "region.npz"  # adaptive mode: the refined coarse cells (cells, origin, dx)
REGION_COLOR = (0.95, 0.55, 0.1)  # outline of the refined region in the preview
SUMMARY_FILE = "summary.json"
ENERGY_FILE = "energy.png"
PREVIEW_FILE = "preview.mp4"
POSTER_FILE = "preview.png"
USD_FILE = "particles.usd"
PREVIEW_SIZE = (640, 480)

_FRAME_RE = re.compile(r"^frame_(\d+)\.ply$")
_COLLIDER_RE = re.compile(r"^collider_(\d+)\.ply$")
_CKPT_RE = re.compile(r"^checkpoint_(\d+)\.npz$")
_SERIES = ("time", "kinetic_energy", "potential_energy", "total_mass", "momentum", "max_speed", "count_per_level")


def frame_path(out_dir: str | os.PathLike, frame: int) -> Path:
    return Path(out_dir) / FRAMES_DIR / f"frame_{frame:05d}.ply"


def collider_path(out_dir: str | os.PathLike, frame: int) -> Path:
    """Triangle mesh (binary PLY) of all the scene's colliders at output frame ``frame``."""
    return Path(out_dir) / COLLIDERS_DIR / f"collider_{frame:05d}.ply"


def total_frames(scene: Scene, frames: int | None = None) -> int:
    """Frames of a run: ``frames`` if given, else ``duration * fps`` rounded (at least 1)."""
    if frames is not None:
        if int(frames) < 1:
            raise AbmpmError(f"frames must be >= 1, got {frames}")
        return int(frames)
    st = scene.simulation
    return max(1, round(st.duration * st.fps))


# --------------------------------------------------------------------------- output folder


def _prepare_out_dir(out: Path) -> None:
    """Create ``out`` and check that files can be written in it (OutputError if not)."""
    try:
        out.mkdir(parents=True, exist_ok=True)
    except FileExistsError:
        raise OutputError(f"cannot create output folder {out}: a file with that name exists") from None
    except NotADirectoryError:
        raise OutputError(
            f"cannot create output folder {out}: a part of the path is a file, not a folder"
        ) from None
    except OSError as exc:
        raise OutputError(f"cannot create output folder {out}: {exc.strerror or exc}") from None
    if not out.is_dir():
        raise OutputError(f"cannot use output folder {out}: it is not a folder")
    try:
        fd, probe = tempfile.mkstemp(prefix=".abmpm-write-test-", dir=out)
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise OutputError(f"cannot write to output folder {out}: {exc.strerror or exc}") from None


# Hidden temporary files that an interrupted write leaves behind: atomic_write's
# ".{stem}.XXXXXXXX.tmp{suffix}" and the write probe ".abmpm-write-test-XXXXXXXX".
_TEMP_RE = re.compile(r"^\.(?:.+\.[a-z0-9_]{8}\.tmp(?:\.[A-Za-z0-9]+)?|abmpm-write-test-[a-z0-9_]{8})$")


def _clean_temporaries(out: Path) -> list[Path]:
    """Remove the temporary files that interrupted writes left in ``out`` and in its
    frames/colliders/checkpoints folders (only names abmpm's writers use)."""
    removed = []
    for folder in (out, out / FRAMES_DIR, out / COLLIDERS_DIR, out / CHECKPOINTS_DIR):
        if not folder.is_dir():
            continue
        for p in folder.iterdir():
            if _TEMP_RE.match(p.name) and p.is_file() and not p.is_symlink():
                try:
                    p.unlink()
                except OSError as exc:
                    raise OutputError(f"cannot remove temporary file {p}: {exc.strerror or exc}") from None
                removed.append(p)
    return removed


def _numbered(folder: Path, pattern: re.Pattern) -> list[tuple[int, Path]]:
    if not folder.is_dir():
        return []
    out = []
    for p in folder.iterdir():
        m = pattern.match(p.name)
        if m and p.is_file():
            out.append((int(m.group(1)), p))
    return sorted(out)


def _clean_previous_run(out: Path) -> None:
    """Remove the outputs of an earlier run in ``out`` (only files abmpm writes)."""
    victims = [p for _, p in _numbered(out / FRAMES_DIR, _FRAME_RE)]
    victims += [p for _, p in _numbered(out / COLLIDERS_DIR, _COLLIDER_RE)]
    victims += [p for _, p in _numbered(out / CHECKPOINTS_DIR, _CKPT_RE)]
    victims += [out / n for n in (SUMMARY_FILE, ENERGY_FILE, PREVIEW_FILE, POSTER_FILE, USD_FILE, REGION_FILE)]
    for p in victims:
        try:
            p.unlink(missing_ok=True)
        except OSError as exc:
            raise OutputError(f"cannot remove old output {p}: {exc.strerror or exc}") from None


# --------------------------------------------------------------------------- scene bookkeeping


def _physics_dump(scene: Scene) -> dict:
    """The parts of a scene that a checkpoint depends on."""
    d = scene.model_dump(mode="json", exclude={"name", "description", "output", "base_dir"})
    d["simulation"].pop("duration", None)
    d["simulation"].pop("device", None)
    return d


def _diff_keys(a: Any, b: Any, prefix: str = "") -> list[str]:
    if isinstance(a, dict) and isinstance(b, dict):
        out = []
        for k in sorted(set(a) | set(b)):
            key = f"{prefix}.{k}" if prefix else str(k)
            out += _diff_keys(a.get(k), b.get(k), key) if k in a and k in b else [key]
        return out
    if isinstance(a, list) and isinstance(b, list) and len(a) == len(b) and not all(
        isinstance(v, (int, float)) for v in a + b
    ):
        out = []
        for i, (x, y) in enumerate(zip(a, b)):
            out += _diff_keys(x, y, f"{prefix}[{i}]")
        return out
    return [] if a == b else [prefix]


def _scene_from_folder(out: Path) -> Scene:
    path = out / SCENE_FILE
    if not path.is_file():
        raise OutputError(f"{out}: not an abmpm output folder (no {SCENE_FILE})")
    try:
        import json

        data = json.loads(path.read_text(encoding="utf-8"))
        return Scene.model_validate(data)
    except Exception as exc:  # corrupt or from an incompatible version
        raise OutputError(f"{path}: cannot read the scene ({type(exc).__name__}: {exc})") from None


# --------------------------------------------------------------------------- rendering


def _densities(scene: Scene) -> np.ndarray:
    return np.array([m.density for m in scene.materials], dtype=np.float64)


def _radius(frame: dict, densities: np.ndarray) -> np.ndarray:
    """Splat radius: a bit more than half the side of the cube a particle stands for."""
    mat = np.clip(frame["material"].astype(np.int64), 0, len(densities) - 1)
    vol = frame["mass"].astype(np.float64) / densities[mat]
    return 0.6 * np.cbrt(vol)


def _colors(frame: dict, scene: Scene, vmax: float | None) -> np.ndarray:
    from abmpm.post.render import colors_by_level, colors_by_material, colors_by_speed

    mode = scene.output.color_by
    if mode == "auto":
        mode = "level" if scene.simulation.refinement.mode == "adaptive" else "material"
    if mode == "speed":
        return colors_by_speed(frame["v"], vmax=vmax)
    if mode == "level":
        return colors_by_level(frame["level"])
    return colors_by_material(frame["material"], models=[m.model for m in scene.materials])


def _disk_frames(out: Path, last: int | None = None) -> list[tuple[int, Callable[[], dict]]]:
    """[(frame, loader)] of the particle PLYs in ``out``; a loader returns the frame's
    arrays plus ``"triangles"`` (M, 3, 3) when the frame has a collider PLY."""
    frames = _numbered(out / FRAMES_DIR, _FRAME_RE)
    if last is not None:
        frames = [(n, p) for n, p in frames if n <= last]
    colliders = dict(_numbered(out / COLLIDERS_DIR, _COLLIDER_RE))
    outline: dict[str, np.ndarray] = {}  # feature edges of the last face list seen

    def load(p: Path, c: Path | None) -> dict:
        f = read_particles_ply(p)
        if c is not None:
            v, faces = read_mesh_ply(c)
            if "faces" not in outline or not np.array_equal(outline["faces"], faces):
                from abmpm.post.render import feature_edges

                outline.update(faces=faces, edges=feature_edges(v, faces))
            f["triangles"] = v[faces]
            f["edges"] = v[outline["edges"]]
        return f

    return [(n, (lambda p=p, c=colliders.get(n): load(p, c))) for n, p in frames]


class _ColliderTrack:
    """What the preview needs of the colliders, taken from the Simulation as it runs:
    the faces and their outline once, and (when no frames go to disk, where
    ``colliders/collider_NNNNN.ply`` holds them) the vertices of every output frame.

    The faces never change, so a frame stores only its (V, 3) float32 vertices, and a
    frame whose colliders have not moved shares the previous frame's array.
    """

    def __init__(self, sim):
        got = sim.collider_faces()
        self.faces = None if got is None else np.asarray(got[1], dtype=np.int64)
        self.edges = None
        if got is not None:
            from abmpm.post.render import feature_edges

            # outline (rims, holes, creases): rigid motion keeps it, so one pose will do
            self.edges = feature_edges(np.asarray(got[0], dtype=np.float64), self.faces)
        self.vertices: dict[int, np.ndarray] = {}
        self._last: np.ndarray | None = None

    def __bool__(self) -> bool:
        return self.faces is not None

    def record(self, sim, keep: bool = True) -> np.ndarray:
        """The colliders' vertices now (float32), kept for the preview if ``keep``."""
        v = np.asarray(sim.collider_faces()[0], dtype=np.float32)
        if self._last is not None and np.array_equal(v, self._last):
            v = self._last
        self._last = v
        if keep:
            self.vertices[sim.frame] = v
        return v

    def attach(self, source):
        """Add this track's triangles to the frames of ``source`` that it has."""
        if not self:
            return source

        def load(n, inner):
            f = dict(inner())
            v = self.vertices.get(n)
            if v is not None:
                f["triangles"] = v[self.faces]
                f["edges"] = v[self.edges]
            return f

        return [(n, (lambda n=n, inner=inner: load(n, inner))) for n, inner in source]


def _speed_vmax(source) -> float:
    vmax = 0.0
    for _, load in source:
        f = load()
        s = f["speed"] if "speed" in f else np.linalg.norm(f["v"], axis=1)
        if len(s):
            vmax = max(vmax, float(np.percentile(s, 99)))
    return vmax if vmax > 0 else 1.0


def _internal_kinetic_energy(frame: dict) -> float:
    """Kinetic energy of the motion relative to the centre of mass (-1 if not finite)."""
    m = frame["mass"].astype(np.float64)
    v = frame["v"].astype(np.float64)
    if len(m) == 0 or m.sum() <= 0.0:
        return 0.0
    v = v - (m[:, None] * v).sum(axis=0) / m.sum()
    ke = float(0.5 * (m * (v * v).sum(axis=1)).sum())
    return ke if math.isfinite(ke) else -1.0


def _write_region(out: Path, sim) -> None:
    region = sim.refined_region()
    if region is None:
        return
    with atomic_write(out / REGION_FILE) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, cells=region["cells"], origin=region["origin"], dx=np.float64(region["dx"]))


def _region_lines(out: Path) -> list:
    """The refined region's outline for the preview, from region.npz if there is one."""
    from abmpm.post.render import region_outline

    path = out / REGION_FILE
    if not path.exists():
        return []
    with np.load(path, allow_pickle=False) as z:
        return [(region_outline(z["cells"], z["origin"], float(z["dx"])), REGION_COLOR)]


def _render_preview(
    out: Path, scene: Scene, source, fps: float, on_frame: Callable[[], None] | None = None
) -> dict:
    """Render ``source`` [(frame, loader)] to preview.mp4 and the poster preview.png."""
    from abmpm.post.render import Camera, render
    from abmpm.post.video import write_mp4, write_png

    if not source:
        raise OutputError(f"{out}: no particle frames to render")
    st = scene.simulation
    box = (st.domain_min, st.domain_max)
    camera = Camera.framing_box(st.domain_min, st.domain_max, *PREVIEW_SIZE)
    densities = _densities(scene)
    vmax = _speed_vmax(source) if scene.output.color_by == "speed" else None
    poster: dict[str, Any] = {"ke": -1.0, "image": None, "frame": None}
    lines = _region_lines(out)

    def images() -> Iterator[np.ndarray]:
        for n, load in source:
            f = load()
            img = render(
                f["x"], _colors(f, scene, vmax), camera, _radius(f, densities), box=box,
                triangles=f.get("triangles"), edges=f.get("edges"), lines=lines,
            )
            ke = _internal_kinetic_energy(f)
            # poster: the frame with the most motion relative to the centre of mass, so
            # that a body thrown or dropped as a whole shows its impact, not its flight
            # (last frame if nothing moves)
            if poster["image"] is None or ke > poster["ke"] or max(ke, poster["ke"]) <= 0.0:
                poster.update(ke=ke, image=img, frame=n)
            if on_frame is not None:
                on_frame()
            yield img

    count = write_mp4(out / PREVIEW_FILE, images(), fps=fps)
    write_png(out / POSTER_FILE, poster["image"])
    return {"frames": count, "poster_frame": poster["frame"]}


def _write_usd(out: Path, scene: Scene, source) -> None:
    from abmpm.io.usd import UsdPointsWriter

    densities = _densities(scene)
    vmax = _speed_vmax(source) if scene.output.color_by == "speed" else None
    writer = UsdPointsWriter(out / USD_FILE, fps=scene.simulation.fps)
    for n, load in source:
        f = load()
        writer.add_frame(n, f["x"], 2.0 * _radius(f, densities), _colors(f, scene, vmax))
    writer.close()


def render_folder(out_dir: str | os.PathLike, progress: bool = False) -> dict:
    """Re-render ``preview.mp4`` / ``preview.png`` of a finished run from its PLY frames
    (and the collider PLYs next to them, when the scene has colliders)."""
    out = Path(out_dir)
    if not out.is_dir():
        raise OutputError(f"{out}: no such output folder")
    scene = _scene_from_folder(out)
    source = _disk_frames(out)
    if not source:
        raise OutputError(f"{out}: no particle frames in {out / FRAMES_DIR} to render")
    fps = scene.simulation.fps / scene.output.frame_every
    with _Progress(progress) as bar:
        bar.start_render(len(source))
        info = _render_preview(out, scene, source, fps, on_frame=bar.advance_render)
    return {"preview": str(out / PREVIEW_FILE), "poster": str(out / POSTER_FILE), **info}


# --------------------------------------------------------------------------- progress


class _Progress:
    """A rich progress bar (frame i/N, sim time, steps/s, ETA), or nothing."""

    def __init__(self, enabled: bool, console=None):
        self.enabled = enabled
        self._console = console
        self._progress = None
        self._sim_task = None
        self._render_task = None

    def __enter__(self) -> "_Progress":
        if self.enabled:
            from rich.console import Console
            from rich.progress import (
                BarColumn,
                MofNCompleteColumn,
                Progress,
                TextColumn,
                TimeElapsedColumn,
                TimeRemainingColumn,
            )

            console = self._console or Console(stderr=True)
            self._progress = Progress(
                TextColumn("[bold]{task.description}"),
                BarColumn(),
                MofNCompleteColumn(),
                TextColumn("{task.fields[info]}"),
                TimeElapsedColumn(),
                TextColumn("ETA"),
                TimeRemainingColumn(),
                console=console,
                transient=False,
            )
            self._progress.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        if self._progress is not None:
            self._progress.__exit__(*exc)
            self._progress = None

    def print(self, message: str) -> None:
        if self._progress is not None:
            self._progress.console.print(message)

    def start_sim(self, done: int, total: int, t: float) -> None:
        if self._progress is not None:
            self._sim_task = self._progress.add_task(
                "simulating", total=total, completed=done, info=f"t = {t:.3f} s"
            )

    def update_sim(self, frame: int, t: float, steps_per_s: float) -> None:
        if self._progress is not None and self._sim_task is not None:
            self._progress.update(
                self._sim_task, completed=frame, info=f"t = {t:.3f} s  {steps_per_s:,.0f} steps/s"
            )

    def start_render(self, total: int) -> None:
        if self._progress is not None:
            self._render_task = self._progress.add_task("rendering preview", total=total, info="")

    def advance_render(self) -> None:
        if self._progress is not None and self._render_task is not None:
            self._progress.advance(self._render_task)


# --------------------------------------------------------------------------- run


def _frame_attributes(p) -> dict[str, np.ndarray]:
    v = p.v
    return {
        "v": v,
        "speed": np.sqrt((v.astype(np.float64) ** 2).sum(axis=1)).astype(np.float32),
        "material": p.material,
        "level": p.level,
        "mass": p.mass,
        "id": p.id,
    }


def _host_particles(sim):
    """The particles in stable id order (the solver reorders them every frame)."""
    p = sim.particles()
    return p.by_id() if hasattr(p, "by_id") else p


def _series(history: list[dict]) -> dict[str, list]:
    return {k: [h.get(k) for h in history] for k in _SERIES}


def run(
    scene: Scene | str | os.PathLike,
    out_dir: str | os.PathLike,
    device: str | None = None,
    frames: int | None = None,
    resume: bool = False,
    preview: bool = True,
    progress: bool = True,
    console=None,
) -> dict:
    """Simulate ``scene`` (a Scene, a ``.toml`` path or a built-in name) into ``out_dir``.

    ``frames`` overrides the number of frames (default ``duration * fps``);
    ``resume`` continues from the latest checkpoint in ``out_dir``; ``preview=False``
    skips the video. Returns the summary dict (also written to ``summary.json``).
    On :class:`SimulationBlowUp` the last good state is checkpointed, the summary is
    written with status ``"blew_up"`` and the exception is re-raised.
    """
    from abmpm.simulation import Simulation

    t_start = time.perf_counter()
    scene = load_scene(scene) if not isinstance(scene, Scene) else scene
    out = Path(out_dir)
    total = total_frames(scene, frames)
    # memory and time stepping, before the output folder or anything big is made
    scene.check_feasible(None, device)
    _prepare_out_dir(out)
    _clean_temporaries(out)
    if scene.output.usd and importlib.util.find_spec("pxr") is None:
        raise OutputError("output.usd = true needs usd-core: pip install 'abmpm[usd]'")
    out_cfg = scene.output

    sim = Simulation(scene, device)
    if not resume:
        _check_initial_state(scene, sim)
    notes: list[str] = []
    resumed_from = None
    if resume:
        ckpt = latest_checkpoint(out / CHECKPOINTS_DIR)
        if ckpt is None:
            notes.append(f"no checkpoint in {out / CHECKPOINTS_DIR}; starting from frame 0")
        else:
            _check_resumable(out, scene, sim, ckpt)
            arrays, meta = load_checkpoint(ckpt)
            if len(arrays.get("x", ())) != sim.particle_count:
                raise OutputError(
                    f"{ckpt}: holds {len(arrays.get('x', ()))} particles but the scene has "
                    f"{sim.particle_count}; cannot resume"
                )
            sim.load_state_dict(arrays, meta)
            resumed_from = sim.frame
            notes.append(f"resuming from {ckpt.name} (frame {sim.frame})")
    if resumed_from is None:
        _clean_previous_run(out)
    write_json(out / SCENE_FILE, scene.model_dump(mode="json"))
    _write_region(out, sim)

    kept: list[tuple[int, dict]] = []  # host frames for the preview when no PLY is written
    # collider vertices of every output frame: on disk next to the particle frames,
    # or in memory for the preview when no frames are written
    colliders = _ColliderTrack(sim)
    state = {"last_ckpt": resumed_from, "io_seconds": 0.0}

    def save_frame(force: bool = False) -> None:
        n = sim.frame
        if not (force or n % out_cfg.frame_every == 0):
            return
        p = _host_particles(sim)
        if colliders:
            verts = colliders.record(sim, keep=not out_cfg.frames and preview and out_cfg.preview)
            if out_cfg.frames:
                write_mesh_ply(collider_path(out, n), verts, colliders.faces)
        if out_cfg.frames:
            write_particles_ply(frame_path(out, n), p.x, _frame_attributes(p))
        elif preview and out_cfg.preview or out_cfg.usd:
            kept.append((n, {"x": p.x, **_frame_attributes(p)}))

    def save_checkpoint_now(last_good: bool = False) -> None:
        arrays, meta = sim.state_dict(last_good=last_good)
        if state["last_ckpt"] == meta["frame"]:
            return  # already on disk (and bit-exact, taken after the particle sort)
        save_checkpoint(out / CHECKPOINTS_DIR / checkpoint_name(meta["frame"]), arrays, meta)
        state["last_ckpt"] = meta["frame"]

    steps0 = sim.steps
    status, message = "completed", None
    with _Progress(progress, console) as bar:
        for note in notes:
            bar.print(f"[yellow]{escape(note)}[/yellow]")
        t_sim = time.perf_counter()

        def on_frame(s) -> None:
            t0 = time.perf_counter()
            try:
                save_frame(force=s.frame >= total)
                if s.frame % out_cfg.checkpoint_every == 0 or s.frame >= total:
                    save_checkpoint_now()
            except OSError as exc:
                raise OutputError(f"cannot write output in {out}: {exc.strerror or exc}") from None
            state["io_seconds"] += time.perf_counter() - t0
            busy = time.perf_counter() - t_sim - state["io_seconds"]
            bar.update_sim(s.frame, s.time, (s.steps - steps0) / max(busy, 1e-9))

        try:
            if resumed_from is None:
                save_frame(force=True)
            bar.start_sim(sim.frame, total, sim.time)
            if sim.frame < total:
                sim.advance(frames=total - sim.frame, callback=on_frame)
            elif state["last_ckpt"] != sim.frame:
                save_checkpoint_now()
        except SimulationBlowUp as exc:
            status, message = "blew_up", str(exc)
            with contextlib.suppress(AbmpmError, OSError):
                save_checkpoint_now(last_good=True)
            err: BaseException | None = exc
        except KeyboardInterrupt as exc:
            status, message = "interrupted", "interrupted by the user"
            with contextlib.suppress(AbmpmError, OSError, RuntimeError):
                save_checkpoint_now(last_good=True)
            err = exc
        else:
            err = None
        sim_seconds = time.perf_counter() - t_sim - state["io_seconds"]

        summary = {
            "scene": scene.name,
            "description": scene.description,
            "status": status,
            "message": message,
            "device": str(sim.device),
            "mode": sim.mode,
            "particle_count": int(sim.particle_count),
            "particle_count_per_level": [int(c) for c in sim.history[-1]["count_per_level"]],
            "frames": int(sim.history[-1]["frame"]),  # last completed (good) frame
            "frames_requested": total,
            "fps": scene.simulation.fps,
            "sim_time": float(sim.history[-1]["time"]),
            "steps": int(sim.history[-1]["steps"]),
            "dt": float(sim.dt),
            "substeps": int(sim.substeps),
            "resumed_from_frame": resumed_from,
            "sim_seconds": round(sim_seconds, 3),
            "steps_per_second": round((sim.steps - steps0) / sim_seconds, 2) if sim_seconds > 0 else None,
            "output_seconds": round(state["io_seconds"], 3),
            "render_seconds": None,
            "wall_seconds": None,
            "versions": _versions(),
            "outputs": {},
            "series": _series(sim.history),
        }

        def finish() -> None:
            outputs = {"scene": SCENE_FILE, "summary": SUMMARY_FILE}
            if _numbered(out / FRAMES_DIR, _FRAME_RE):
                outputs["frames"] = f"{FRAMES_DIR}/frame_NNNNN.ply"
            if _numbered(out / COLLIDERS_DIR, _COLLIDER_RE):
                outputs["colliders"] = f"{COLLIDERS_DIR}/collider_NNNNN.ply"
            if _numbered(out / CHECKPOINTS_DIR, _CKPT_RE):
                outputs["checkpoints"] = f"{CHECKPOINTS_DIR}/checkpoint_NNNNN.npz"
            if status != "interrupted":
                from abmpm.post.plots import plot_energy

                plot_energy(summary["series"], out / ENERGY_FILE, title=f"{scene.name}: energy and conservation")
                outputs["energy_plot"] = ENERGY_FILE
                t_render = time.perf_counter()
                last = summary["frames"]
                source = _disk_frames(out, last) if out_cfg.frames else [
                    (n, (lambda f=f: f)) for n, f in kept if n <= last
                ]
                source = colliders.attach(source)  # frames of this run: no need to read them back
                _write_region(out, sim)  # as it is at the end (it follows moving colliders)
                if preview and out_cfg.preview and source:
                    fps = scene.simulation.fps / out_cfg.frame_every
                    bar.start_render(len(source))
                    info = _render_preview(out, scene, source, fps, on_frame=bar.advance_render)
                    outputs["preview"] = PREVIEW_FILE
                    outputs["poster"] = POSTER_FILE
                    summary["preview_frames"] = info["frames"]
                if out_cfg.usd and source:
                    _write_usd(out, scene, source)
                    outputs["usd"] = USD_FILE
                summary["render_seconds"] = round(time.perf_counter() - t_render, 3)
            summary["outputs"] = outputs
            summary["wall_seconds"] = round(time.perf_counter() - t_start, 3)
            write_json(out / SUMMARY_FILE, summary)

        if err is None:
            finish()
            return summary
        try:
            finish()
        except (AbmpmError, OSError) as secondary:  # keep the original error
            summary["outputs_error"] = str(secondary)
            with contextlib.suppress(AbmpmError, OSError):
                write_json(out / SUMMARY_FILE, summary)
        raise err


def _check_initial_state(scene: Scene, sim) -> None:
    """Refuse to start from a state that is not finite in single precision (a frame 0
    of NaN would be written as if it were good)."""
    p = sim.particles()
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


def _check_resumable(out: Path, scene: Scene, sim, ckpt: Path) -> None:
    saved = out / SCENE_FILE
    if not saved.is_file():
        return
    try:
        old = _scene_from_folder(out)
    except OutputError:
        return
    diff = _diff_keys(_physics_dump(old), _physics_dump(scene))
    if diff:
        shown = ", ".join(diff[:5]) + (", ..." if len(diff) > 5 else "")
        raise OutputError(
            f"{out}: cannot resume from {ckpt.name}: the scene changed since it was written "
            f"(differs in {shown}); run without --resume to start over"
        )


def _versions() -> dict[str, str]:
    import abmpm

    out = {"abmpm": getattr(abmpm, "__version__", "?"), "numpy": np.__version__}
    try:
        import warp as wp

        out["warp"] = wp.config.version
    except Exception:  # pragma: no cover
        pass
    return out
