"""``region.npz`` (adaptive mode): the refined coarse cells (``cells``, ``origin``,
``dx``), written when the run begins and again at its end (the region follows moving
colliders); the preview outlines it."""

from __future__ import annotations

import time

import numpy as np

from abmpm.io.atomic import atomic_write
from abmpm.io.outdir import REGION_FILE
from abmpm.io.writers.base import RunContext, Writer


class RegionWriter(Writer):
    name = "region"

    def begin(self, run: RunContext) -> None:
        self.write(run)

    def finish(self, run: RunContext) -> None:
        if run.interrupted:
            return
        t0 = time.perf_counter()
        self.write(run)  # as it is at the end
        run.render_seconds += time.perf_counter() - t0

    @staticmethod
    def write(run: RunContext) -> None:
        region = run.sim.refined_region()
        if region is None:
            return
        with atomic_write(run.out / REGION_FILE) as tmp:
            with open(tmp, "wb") as fh:
                np.savez(fh, cells=region["cells"], origin=region["origin"], dx=np.float64(region["dx"]))
