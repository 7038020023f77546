"""``surfaces/surface_NNNNN_<material>.ply`` (``output.surface = true``): a triangle
mesh of every material's surface at every output frame (splashsurf; see
:mod:`abmpm.post.surface`). The seconds spent meshing go into ``summary.json``
(``surface_seconds``, ``surface_seconds_per_frame``)."""

from __future__ import annotations

import importlib.util
import time
from pathlib import Path

from abmpm.errors import OutputError
from abmpm.io.outdir import COLLIDER_RE, COLLIDERS_DIR, FRAME_RE, FRAMES_DIR, USD_FILE, numbered, scene_from_folder
from abmpm.io.ply import read_mesh_ply, read_particles_ply
from abmpm.io.writers.base import FrameData, RunContext, Writer
from abmpm.io.writers.usd import write_usd
from abmpm.post.preview import disk_frames
from abmpm.post.surface import import_splashsurf, surface_meshes, surfaces_of_folder, write_surfaces


class SurfaceWriter(Writer):
    name = "surface"

    def __init__(self) -> None:
        if importlib.util.find_spec("pysplashsurf") is None:  # refused before anything runs
            raise OutputError("output.surface = true needs pysplashsurf: pip install 'abmpm[surface]'")
        self.seconds = 0.0
        self.frames = 0

    def begin(self, run: RunContext) -> None:
        self.run = run

    def write_frame(self, frame: int, data: FrameData) -> None:
        if not data.output_frame:
            return
        t0 = time.perf_counter()
        meshes = surface_meshes(data.arrays, self.run.scene)
        self.seconds += time.perf_counter() - t0
        self.frames += 1
        write_surfaces(self.run.out, frame, meshes)

    def finish(self, run: RunContext) -> None:
        # the files are listed with the other numbered outputs (io.outdir.numbered_outputs)
        run.summary["surface_seconds"] = round(self.seconds, 3)
        run.summary["surface_seconds_per_frame"] = round(self.seconds / self.frames, 4) if self.frames else None


def surface_folder(out_dir: str | Path, on_frame=None) -> dict:
    """Mesh the particle frames of a finished run (``abmpm surface OUT_DIR``) into
    ``surfaces/``, with the options of the scene it saved; when the run wrote a USD
    file, write it again with the surfaces. Returns the counts and the seconds spent."""
    out = Path(out_dir)
    scene = scene_from_folder(out)
    frames = numbered(out / FRAMES_DIR, FRAME_RE)
    if not frames:
        raise OutputError(f"{out}: no particle frames to mesh (the run had output.frames = false)")
    import_splashsurf()
    spent, count = 0.0, 0
    for n, path in frames:
        particles = read_particles_ply(path)
        t0 = time.perf_counter()
        meshes = surface_meshes(particles, scene)
        spent += time.perf_counter() - t0
        count += sum(len(m.faces) for m in meshes)
        write_surfaces(out, n, meshes)
        if on_frame is not None:
            on_frame()
    usd = out / USD_FILE
    if usd.is_file():
        colliders = {n: read_mesh_ply(p) for n, p in numbered(out / COLLIDERS_DIR, COLLIDER_RE)}
        write_usd(usd, scene, disk_frames(out), colliders, surfaces_of_folder(out))
    return {
        "frames": len(frames),
        "triangles": count,
        "seconds": round(spent, 3),
        "seconds_per_frame": round(spent / len(frames), 4),
        "usd": usd.is_file(),
    }
