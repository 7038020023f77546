"""``beauty.mp4`` and ``beauty.png`` (``output.beauty = true``): the run's surface
meshes and colliders path-traced with Mitsuba 3 at the end of the run (see
:mod:`abmpm.post.beauty`). Surfaces come from the ``surface`` writer, or are meshed
here first when ``output.surface`` is off. Needs mitsuba (``abmpm[render]``)."""

from __future__ import annotations

import importlib.util
import time

from abmpm.errors import OutputError
from abmpm.io.outdir import BEAUTY_FILE, BEAUTY_POSTER_FILE
from abmpm.io.writers.base import RunContext, Writer
from abmpm.io.writers.surface import surface_folder
from abmpm.post.beauty import BeautySettings, render_beauty

INSTALL_HINT = 'output.beauty = true needs Mitsuba 3: pip install -e ".[render]"'


class BeautyWriter(Writer):
    name = "beauty"
    settings = None  # abmpm.post.beauty.BeautySettings; None: its defaults

    def __init__(self) -> None:
        if importlib.util.find_spec("mitsuba") is None:  # refused before anything runs
            raise OutputError(INSTALL_HINT)

    def begin(self, run: RunContext) -> None:
        if not run.frames.on_disk:
            raise OutputError("output.beauty = true needs output.frames = true (it renders the frames' surfaces "
                              "and colliders from the run folder)")
        if "surface" not in run.writers and importlib.util.find_spec("pysplashsurf") is None:
            raise OutputError("output.beauty = true renders surface meshes, which need pysplashsurf: "
                              "pip install -e \".[surface]\"")

    def finish(self, run: RunContext) -> None:
        if run.interrupted:
            return

        t0 = time.perf_counter()
        info = render_beauty(run.out, self.settings or BeautySettings(), bar=run.progress, mesh=surface_folder)
        run.outputs["beauty"] = BEAUTY_FILE
        run.outputs["beauty_poster"] = BEAUTY_POSTER_FILE
        run.summary["beauty"] = {k: info[k] for k in ("frames", "poster_frame", "variant", "size", "spp",
                                                      "seconds_per_frame")}
        run.render_seconds += time.perf_counter() - t0
