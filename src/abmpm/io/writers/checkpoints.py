"""``checkpoints/checkpoint_NNNNN.npz``: the complete state every
``output.checkpoint_every`` frames, at the last frame, and (last good frame) when the
run blows up or is interrupted, so that ``--resume`` continues bit-identically."""

from __future__ import annotations

import contextlib

from abmpm.errors import AbmpmError
from abmpm.io.checkpoint import save_checkpoint
from abmpm.io.outdir import checkpoint_path
from abmpm.io.writers.base import FrameData, RunContext, Writer


class CheckpointWriter(Writer):
    name = "checkpoints"

    def begin(self, run: RunContext) -> None:
        self.run = run
        self.every = run.scene.output.checkpoint_every
        self.saved = run.resumed_from  # frame of the newest checkpoint on disk

    def write_frame(self, frame: int, data: FrameData) -> None:
        if not data.first and (frame % self.every == 0 or data.last):
            self.save()

    def save(self, last_good: bool = False) -> None:
        """Checkpoint the state now (or the last good frame's), unless it is on disk."""
        arrays, meta = self.run.sim.state_dict(last_good=last_good)
        if self.saved == meta["frame"]:
            return  # already on disk (and bit-exact, taken after the particle sort)
        save_checkpoint(checkpoint_path(self.run.out, meta["frame"]), arrays, meta)
        self.saved = meta["frame"]

    def finish(self, run: RunContext) -> None:
        if run.status == "completed":
            if self.saved != run.sim.frame:  # a resumed run that had no frame left to do
                self.save()
            return
        # blown up or interrupted: keep the last good frame; the run's own error matters more
        quiet = (AbmpmError, OSError, RuntimeError) if run.interrupted else (AbmpmError, OSError)
        with contextlib.suppress(*quiet):
            self.save(last_good=True)
