"""The preview of a run: ``preview.mp4`` and its poster frame ``preview.png``.

Rendered from a *frame source*, a list ``[(frame, loader)]`` whose loaders return a
frame's particle arrays (``x``, ``v``, ``mass``, ``material``, ``level``, ...) and,
when the scene has colliders, their ``triangles`` (M, 3, 3) and outline ``edges``.
The source is either the PLY files of an output folder (:func:`disk_frames`) or frames
kept in memory while the simulation ran. Knows nothing of the solver.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from abmpm.errors import OutputError
from abmpm.geometry.topology import feature_edges
from abmpm.io.outdir import (
    COLLIDER_RE,
    COLLIDERS_DIR,
    FRAME_RE,
    FRAMES_DIR,
    POSTER_FILE,
    PREVIEW_FILE,
    REGION_FILE,
    numbered,
    scene_from_folder,
)
from abmpm.io.ply import read_mesh_ply, read_particles_ply
from abmpm.io.progress import Progress
from abmpm.post import Camera, colors_by_level, colors_by_material, colors_by_speed, render, write_mp4, write_png
from abmpm.post.render import region_outline
from abmpm.scene.model import Scene

__all__ = [
    "PREVIEW_SIZE",
    "REGION_COLOR",
    "ColliderTrack",
    "disk_frames",
    "frame_image",
    "internal_kinetic_energy",
    "material_densities",
    "particle_colors",
    "render_folder",
    "region_lines",
    "render_preview",
    "speed_vmax",
    "splat_radius",
]

PREVIEW_SIZE = (640, 480)
REGION_COLOR = (0.95, 0.55, 0.1)  # outline of the refined region in the preview

FrameSource = list[tuple[int, Callable[[], dict]]]


def material_densities(scene: Scene) -> np.ndarray:
    return np.array([m.density for m in scene.materials], dtype=np.float64)


def splat_radius(frame: dict, densities: np.ndarray) -> np.ndarray:
    """Splat radius: a bit more than half the side of the cube a particle stands for."""
    mat = np.clip(frame["material"].astype(np.int64), 0, len(densities) - 1)
    vol = frame["mass"].astype(np.float64) / densities[mat]
    return 0.6 * np.cbrt(vol)


def particle_colors(frame: dict, scene: Scene, vmax: float | None) -> np.ndarray:
    """The particles' colors as ``output.color_by`` asks (auto: by level in adaptive
    mode, else by material)."""
    mode = scene.output.color_by
    if mode == "auto":
        mode = "level" if scene.simulation.refinement.mode == "adaptive" else "material"
    if mode == "speed":
        return colors_by_speed(frame["v"], vmax=vmax)
    if mode == "level":
        return colors_by_level(frame["level"])
    return colors_by_material(frame["material"], models=[m.model for m in scene.materials])


def disk_frames(out: Path, last: int | None = None) -> FrameSource:
    """[(frame, loader)] of the particle PLYs in ``out``; a loader returns the frame's
    arrays plus ``"triangles"`` (M, 3, 3) when the frame has a collider PLY."""
    frames = numbered(out / FRAMES_DIR, FRAME_RE)
    if last is not None:
        frames = [(n, p) for n, p in frames if n <= last]
    colliders = dict(numbered(out / COLLIDERS_DIR, COLLIDER_RE))
    outline: dict[str, np.ndarray] = {}  # feature edges of the last face list seen

    def load(p: Path, c: Path | None) -> dict:
        f = read_particles_ply(p)
        if c is not None:
            v, faces = read_mesh_ply(c)
            if "faces" not in outline or not np.array_equal(outline["faces"], faces):
                outline.update(faces=faces, edges=feature_edges(v, faces))
            f["triangles"] = v[faces]
            f["edges"] = v[outline["edges"]]
        return f

    return [(n, (lambda p=p, c=colliders.get(n): load(p, c))) for n, p in frames]


class ColliderTrack:
    """The colliders as the preview draws them when no collider PLYs are written: the
    faces and their outline once, and the vertices of every output frame.

    The faces never change, so a frame stores only its (V, 3) float32 vertices, and a
    frame whose colliders have not moved shares the previous frame's array.
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        self.faces = np.asarray(faces, dtype=np.int64)
        # outline (rims, holes, creases): rigid motion keeps it, so one pose will do
        self.edges = feature_edges(np.asarray(vertices, dtype=np.float64), self.faces)
        self.vertices: dict[int, np.ndarray] = {}
        self._last: np.ndarray | None = None

    def record(self, frame: int, vertices: np.ndarray) -> None:
        """Keep the colliders' vertices at output frame ``frame`` (as float32)."""
        v = np.asarray(vertices, dtype=np.float32)
        if self._last is not None and np.array_equal(v, self._last):
            v = self._last
        self._last = v
        self.vertices[frame] = v

    def attach(self, source: FrameSource) -> FrameSource:
        """Add this track's triangles to the frames of ``source`` that it has."""

        def load(n, inner):
            f = dict(inner())
            v = self.vertices.get(n)
            if v is not None:
                f["triangles"] = v[self.faces]
                f["edges"] = v[self.edges]
            return f

        return [(n, (lambda n=n, inner=inner: load(n, inner))) for n, inner in source]


def speed_vmax(source: FrameSource) -> float:
    """The speed that tops the color scale: the largest 99th percentile of a frame."""
    vmax = 0.0
    for _, load in source:
        f = load()
        s = f["speed"] if "speed" in f else np.linalg.norm(f["v"], axis=1)
        if len(s):
            vmax = max(vmax, float(np.percentile(s, 99)))
    return vmax if vmax > 0 else 1.0


def internal_kinetic_energy(frame: dict) -> float:
    """Kinetic energy of the motion relative to the centre of mass (-1 if not finite)."""
    m = frame["mass"].astype(np.float64)
    v = frame["v"].astype(np.float64)
    if len(m) == 0 or m.sum() <= 0.0:
        return 0.0
    v = v - (m[:, None] * v).sum(axis=0) / m.sum()
    ke = float(0.5 * (m * (v * v).sum(axis=1)).sum())
    return ke if math.isfinite(ke) else -1.0


def region_lines(out: Path) -> list:
    """The refined region's outline for the preview, from region.npz if there is one."""
    path = out / REGION_FILE
    if not path.exists():
        return []
    with np.load(path, allow_pickle=False) as z:
        return [(region_outline(z["cells"], z["origin"], float(z["dx"])), REGION_COLOR)]


def frame_image(scene: Scene, frame: dict, camera, vmax: float | None = None, lines: list = ()) -> np.ndarray:
    """One frame (as :func:`disk_frames` loads it) drawn as the preview draws it: the
    particles sized by their volume and colored as ``output.color_by`` asks, the domain
    box, the colliders and ``lines`` (the refined region: :func:`region_lines`)."""
    st = scene.simulation
    return render(
        frame["x"], particle_colors(frame, scene, vmax), camera, splat_radius(frame, material_densities(scene)),
        box=(st.domain_min, st.domain_max), triangles=frame.get("triangles"), edges=frame.get("edges"), lines=lines,
    )


def render_preview(
    out: Path, scene: Scene, source: FrameSource, fps: float, on_frame: Callable[[], None] | None = None
) -> dict:
    """Render ``source`` [(frame, loader)] to preview.mp4 and the poster preview.png in
    ``out``: ``{"frames": count, "poster_frame": frame}``."""
    if not source:
        raise OutputError(f"{out}: no particle frames to render")
    st = scene.simulation
    camera = Camera.framing_box(st.domain_min, st.domain_max, *PREVIEW_SIZE)
    vmax = speed_vmax(source) if scene.output.color_by == "speed" else None
    poster: dict[str, Any] = {"ke": -1.0, "image": None, "frame": None}
    lines = region_lines(out)

    def images() -> Iterator[np.ndarray]:
        for n, load in source:
            f = load()
            img = frame_image(scene, f, camera, vmax, lines)
            ke = internal_kinetic_energy(f)
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


def render_folder(out_dir: str | os.PathLike, progress: bool = False) -> dict:
    """Re-render ``preview.mp4`` / ``preview.png`` of a finished run from its PLY frames
    (and the collider PLYs next to them, when the scene has colliders)."""
    out = Path(out_dir)
    if not out.is_dir():
        raise OutputError(f"{out}: not an output folder" if out.exists() else f"{out}: no such output folder")
    scene = scene_from_folder(out)
    source = disk_frames(out)
    if not source:
        raise OutputError(f"{out}: no particle frames in {out / FRAMES_DIR} to render")
    fps = scene.simulation.fps / scene.output.frame_every
    with Progress(progress) as bar:
        bar.start_render(len(source))
        info = render_preview(out, scene, source, fps, on_frame=bar.advance_render)
    return {"preview": str(out / PREVIEW_FILE), "poster": str(out / POSTER_FILE), **info}
