"""``particles.usd`` (``output.usd = true``): the output frames as a time-sampled
``UsdGeom.Points`` prim, sized and colored as in the preview. Needs usd-core."""

from __future__ import annotations

import importlib.util
import time
from pathlib import Path

from abmpm.errors import OutputError
from abmpm.io.outdir import USD_FILE
from abmpm.io.writers.base import FrameData, RunContext, Writer
from abmpm.scene.model import Scene


def write_usd(path: Path, scene: Scene, source) -> None:
    """Write the frames of ``source`` [(frame, loader)] to the USD file ``path``."""
    from abmpm.io.usd import UsdPointsWriter
    from abmpm.post.preview import material_densities, particle_colors, speed_vmax, splat_radius

    densities = material_densities(scene)
    vmax = speed_vmax(source) if scene.output.color_by == "speed" else None
    writer = UsdPointsWriter(path, fps=scene.simulation.fps)
    for n, load in source:
        f = load()
        writer.add_frame(n, f["x"], 2.0 * splat_radius(f, densities), particle_colors(f, scene, vmax))
    writer.close()


class UsdWriter(Writer):
    name = "usd"

    def __init__(self) -> None:
        # refused before anything is simulated
        if importlib.util.find_spec("pxr") is None:
            raise OutputError("output.usd = true needs usd-core: pip install 'abmpm[usd]'")

    def begin(self, run: RunContext) -> None:
        self.run = run

    def write_frame(self, frame: int, data: FrameData) -> None:
        if data.output_frame:
            self.run.frames.keep(frame, data)

    def finish(self, run: RunContext) -> None:
        if run.interrupted:
            return
        t0 = time.perf_counter()
        source = run.frames.source(run.last_frame)
        if source:
            write_usd(run.out / USD_FILE, run.scene, source)
            run.outputs["usd"] = USD_FILE
        run.render_seconds += time.perf_counter() - t0
