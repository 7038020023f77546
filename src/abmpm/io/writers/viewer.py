"""The live browser view of a running simulation (``abmpm run SCENE --view``): a
:class:`~abmpm.post.viewer.Viewer` in live mode that gets every output frame's
particles and collider vertices as the run writes them. Writes no files.

Called after the other writers (its place in :data:`abmpm.io.writers.WRITERS`), so
with ``keep_open`` the page stays up once ``summary.json`` and the preview are
written, until Ctrl-C; without it the server stops when the run ends.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass

from abmpm.io.outdir import frame_path
from abmpm.io.writers.base import FrameData, RunContext, Writer
from abmpm.post.viewer import Viewer, need_viser


@dataclass(frozen=True)
class ViewOptions:
    """How ``abmpm run --view`` serves the live view."""

    port: int = 8080  # first port tried (the next free one is taken); 0: any free port
    host: str = "127.0.0.1"
    keep_open: bool = False  # after the run, serve until Ctrl-C


class ViewerWriter(Writer):
    name = "view"

    def __init__(self, options: ViewOptions | bool | None = None):
        need_viser("abmpm run --view")  # refuse before the run starts
        self.options = options if isinstance(options, ViewOptions) else ViewOptions()
        self.viewer = None

    def begin(self, run: RunContext) -> None:
        o = self.options
        self.viewer = Viewer(run.out, scene=run.scene, live=True, host=o.host, port=o.port)
        self.sim, self.out, self.on_disk = run.sim, run.out, run.frames.on_disk
        if run.collider_mesh is not None:
            self.viewer.set_collider_faces(run.collider_mesh[1])
        self._update_region()
        print(f"live view: {self.viewer.url}", file=sys.stderr)  # before the progress bar starts

    def _update_region(self) -> None:
        region = self.sim.refined_region()
        if region is not None:
            self.viewer.set_region(region["cells"], region["origin"], region["dx"])

    def write_frame(self, frame: int, data: FrameData) -> None:
        if not data.output_frame:
            return
        self._update_region()  # it follows moving colliders
        # frames written to frames/ are read back from there when scrubbed to
        path = frame_path(self.out, frame) if self.on_disk else None
        self.viewer.push_frame(frame, data.arrays, data.collider_vertices, path=path)

    def finish(self, run: RunContext) -> None:
        if self.viewer is None:
            return
        try:
            self._update_region()
            status = run.status.replace("_", " ")  # completed, blew up, interrupted
            self.viewer.set_note(status)
            if self.options.keep_open and not run.interrupted:
                message = f"run {status}; still serving {self.viewer.url} (Ctrl-C to stop)"
                if run.progress.enabled:
                    run.progress.print(message)
                else:
                    print(message, file=sys.stderr)
                try:
                    self.viewer.wait()
                except KeyboardInterrupt:
                    pass  # the user is done looking; the run itself completed
        finally:
            self.viewer.close()
