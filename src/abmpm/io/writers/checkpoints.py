"""``checkpoints/checkpoint_NNNNN.npz``: the complete state every
``output.checkpoint_every`` frames, at the last frame, and (last good frame) when the
run blows up or is interrupted, so that ``--resume`` continues bit-identically."""

from __future__ import annotations

import contextlib

from abmpm.errors import AbmpmError
from abmpm.io.checkpoint import save_checkpoint
from abmpm.io.outdir import CHECKPOINT_RE, CHECKPOINTS_DIR, checkpoint_path, numbered
from abmpm.io.writers.base import FrameData, RunContext, Writer


class CheckpointWriter(Writer):
    name = "checkpoints"

    def begin(self, run: RunContext) -> None:
        self.run = run
        self.every = run.scene.output.checkpoint_every
        self.keep = run.scene.output.keep_checkpoints
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
        if self.keep is not None:  # output.keep_checkpoints: the oldest go once the new one is on disk
            old = [p for n, p in numbered(self.run.out / CHECKPOINTS_DIR, CHECKPOINT_RE) if n != self.saved]
            for p in old[: max(0, len(old) + 1 - self.keep)]:
                with contextlib.suppress(OSError):
                    p.unlink()

    def finish(self, run: RunContext) -> None:
        if run.status == "completed":
            if self.saved != run.sim.frame:  # a resumed run that had no frame left to do
                self.save()
            return
        # blown up or interrupted: keep the last good frame; the run's own error matters more
        quiet = (AbmpmError, OSError, RuntimeError) if run.interrupted else (AbmpmError, OSError)
        with contextlib.suppress(*quiet):
            self.save(last_good=True)
