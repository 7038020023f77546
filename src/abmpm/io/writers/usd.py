"""``particles.usd`` (``output.usd = true``): the output frames as one USD stage,
particles sized and colored as in the preview, with velocities and ids, the
colliders and the surface meshes (see :mod:`abmpm.io.usd`). Needs usd-core."""

from __future__ import annotations

import importlib.util
import time
from pathlib import Path

import numpy as np

from abmpm.errors import OutputError
from abmpm.io.outdir import COLLIDER_RE, COLLIDERS_DIR, USD_FILE, numbered
from abmpm.io.ply import read_mesh_ply
from abmpm.io.usd import UsdStageWriter
from abmpm.io.writers.base import FrameData, RunContext, Writer
from abmpm.post.colors import colors_by_material
from abmpm.post.preview import ColliderTrack, material_densities, particle_colors, speed_vmax, splat_radius
from abmpm.post.surface import file_stem, surfaces_of_folder
from abmpm.scene.model import Scene

COLLIDER_COLOR = (0.6, 0.6, 0.65)


def write_usd(path: Path, scene: Scene, source, colliders=None, surfaces=None) -> None:
    """Write the frames of ``source`` [(frame, loader)] to the USD file ``path``, with
    ``colliders`` {frame: (vertices, faces)} and ``surfaces`` {frame: {material: PLY
    path}} (see :func:`abmpm.post.surface.surfaces_of_folder`) where given."""
    densities = material_densities(scene)
    vmax = speed_vmax(source) if scene.output.color_by == "speed" else None
    colliders = colliders or {}
    surfaces = surfaces or {}
    mats = scene.materials
    tint = colors_by_material(np.arange(len(mats)), models=[m.model for m in mats])
    writer = UsdStageWriter(path, fps=scene.simulation.fps)
    for n, load in source:
        f = load()
        writer.add_frame(n, f["x"], 2.0 * splat_radius(f, densities), particle_colors(f, scene, vmax),
                         velocities=f["v"], ids=f["id"])
        if n in colliders:
            writer.add_mesh("/World/colliders", n, *colliders[n], color=COLLIDER_COLOR)
        for i, m in enumerate(mats if surfaces else ()):
            found = surfaces.get(n, {}).get(file_stem(m.name))
            v, faces = read_mesh_ply(found) if found else (np.zeros((0, 3)), np.zeros((0, 3)))
            writer.add_mesh(f"/World/surfaces/{m.name}", n, v, faces, color=tint[i])
    writer.close()


class UsdWriter(Writer):
    name = "usd"

    def __init__(self) -> None:
        # refused before anything is simulated
        if importlib.util.find_spec("pxr") is None:
            raise OutputError("output.usd = true needs usd-core: pip install 'abmpm[usd]'")

    def begin(self, run: RunContext) -> None:
        self.run = run
        # the colliders' vertices of every output frame (one array while they rest)
        self.track = None
        if run.collider_mesh is not None:
            self.track = ColliderTrack(*run.collider_mesh)

    def write_frame(self, frame: int, data: FrameData) -> None:
        if data.output_frame:
            self.run.frames.keep(frame, data)
            if self.track is not None:
                self.track.record(frame, data.collider_vertices)

    def finish(self, run: RunContext) -> None:
        if run.interrupted:
            return

        t0 = time.perf_counter()
        source = run.frames.source(run.last_frame)
        if source:
            colliders = {} if self.track is None else {n: (v, self.track.faces) for n, v in self.track.vertices.items()}
            # frames before a resume: the collider PLYs the run wrote then (if it wrote any)
            colliders |= {n: read_mesh_ply(p) for n, p in numbered(run.out / COLLIDERS_DIR, COLLIDER_RE)
                          if n not in colliders}
            write_usd(run.out / USD_FILE, run.scene, source, colliders, surfaces_of_folder(run.out))
            run.outputs["usd"] = USD_FILE
        run.render_seconds += time.perf_counter() - t0
