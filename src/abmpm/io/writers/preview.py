"""``preview.mp4`` and its poster frame ``preview.png``, rendered at the end of the run
from the output frames (PLYs on disk, or frames kept in memory when none are written).
See :mod:`abmpm.post.preview`."""

from __future__ import annotations

import time

from abmpm.io.outdir import POSTER_FILE, PREVIEW_FILE
from abmpm.io.writers.base import FrameData, RunContext, Writer
from abmpm.post.preview import ColliderTrack, render_preview


class PreviewWriter(Writer):
    name = "preview"

    def begin(self, run: RunContext) -> None:
        self.run = run
        # without collider PLYs on disk, the colliders' vertices of every output frame
        # are kept in memory
        self.track = None
        if not run.frames.on_disk and run.collider_mesh is not None:
            self.track = ColliderTrack(*run.collider_mesh)

    def write_frame(self, frame: int, data: FrameData) -> None:
        if not data.output_frame:
            return
        if self.track is not None:
            self.track.record(frame, data.collider_vertices)
        self.run.frames.keep(frame, data)

    def finish(self, run: RunContext) -> None:
        if run.interrupted:
            return

        t0 = time.perf_counter()
        source = run.frames.source(run.last_frame)
        if self.track is not None:
            source = self.track.attach(source)  # frames of this run: no need to read them back
        if source:
            fps = run.scene.simulation.fps / run.scene.output.frame_every
            run.progress.start_render(len(source))
            info = render_preview(run.out, run.scene, source, fps, on_frame=run.progress.advance_render)
            run.outputs["preview"] = PREVIEW_FILE
            run.outputs["poster"] = POSTER_FILE
            run.summary["preview_frames"] = info["frames"]
        run.render_seconds += time.perf_counter() - t0
