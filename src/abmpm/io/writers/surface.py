"""``surfaces/surface_NNNNN_<material>.ply`` (``output.surface = true``): a triangle
mesh of every material's surface at every output frame (splashsurf; see
:mod:`abmpm.post.surface`). The seconds spent meshing go into ``summary.json``
(``surface_seconds``, ``surface_seconds_per_frame``)."""

from __future__ import annotations

import importlib.util
import time

from abmpm.errors import OutputError
from abmpm.io.writers.base import FrameData, RunContext, Writer


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
        from abmpm.post.surface import surface_meshes, write_surfaces

        t0 = time.perf_counter()
        meshes = surface_meshes(data.arrays, self.run.scene)
        self.seconds += time.perf_counter() - t0
        self.frames += 1
        write_surfaces(self.run.out, frame, meshes)

    def finish(self, run: RunContext) -> None:
        # the files are listed with the other numbered outputs (io.outdir.numbered_outputs)
        run.summary["surface_seconds"] = round(self.seconds, 3)
        run.summary["surface_seconds_per_frame"] = round(self.seconds / self.frames, 4) if self.frames else None
