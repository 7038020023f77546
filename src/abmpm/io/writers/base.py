"""The interface of the run's writers and what the runner hands them.

A writer turns a running :class:`~abmpm.simulation.Simulation` into one kind of
output. The runner (:func:`abmpm.runner.run`) calls, for every writer of the run and
in the order of :data:`abmpm.io.writers.WRITERS`:

``begin(run)``
    once, before the first frame: the output folder is ready, ``scene.json`` written
    and a resumed run's state loaded (``run.sim.frame`` is the frame it starts from).
``write_frame(frame, data)``
    after every simulated frame, and once before the first step of a fresh run
    (``data.first``); ``data.output_frame`` says whether it is one of the output
    frames (every ``output.frame_every``-th, the first and the last).
``finish(run)``
    once at the end, with ``run.status`` ``"completed"``, ``"blew_up"``, ``"out_of_memory"`` or
    ``"interrupted"`` and ``run.summary`` built; writers add the files they wrote to
    ``run.outputs`` (listed in ``summary.json`` in that order). Not called when a
    frame could not be written (the run stops with that error).

Writers use only the public interface of the Simulation (through ``run.sim`` and
``data``) and write their files atomically (:func:`abmpm.io.atomic.atomic_write`).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from abmpm.io.progress import Progress
from abmpm.post.preview import disk_frames
from abmpm.scene.model import Scene

__all__ = ["FrameData", "FrameStore", "RunContext", "Writer"]


class FrameData:
    """One frame of the simulation as the writers see it. Host copies are made on first
    use and shared by the writers of that frame."""

    def __init__(self, sim, *, output_frame: bool, first: bool = False, last: bool = False):
        self._sim = sim
        self.output_frame = output_frame  # every frame_every-th, the first and the last
        self.first = first  # the initial state of a fresh run, before the first step
        self.last = last  # the last frame the run asked for

    @cached_property
    def particles(self):
        """The particles (host copy) in stable id order (the solver reorders them)."""
        p = self._sim.particles()
        return p.by_id() if hasattr(p, "by_id") else p

    @cached_property
    def attributes(self) -> dict[str, np.ndarray]:
        """The per-particle values written next to the positions."""
        p = self.particles
        v = p.v
        return {
            "v": v,
            "speed": np.sqrt((v.astype(np.float64) ** 2).sum(axis=1)).astype(np.float32),
            "material": p.material,
            "level": p.level,
            "mass": p.mass,
            "id": p.id,
        }

    @cached_property
    def arrays(self) -> dict[str, np.ndarray]:
        """``x`` and :attr:`attributes`: a frame as :func:`abmpm.io.read_particles_ply` reads it."""
        return {"x": self.particles.x, **self.attributes}

    @cached_property
    def collider_vertices(self) -> np.ndarray | None:
        """The colliders' (V, 3) float32 vertices at this frame (None without colliders)."""
        got = self._sim.collider_faces()
        return None if got is None else np.asarray(got[0], dtype=np.float32)


class FrameStore:
    """The output frames of a run, for the writers that use them all at the end
    (preview, USD): read back from ``frames/`` when the PLY frames are written there,
    else kept in memory (once, however many writers keep them)."""

    def __init__(self, out: Path, on_disk: bool):
        self.out = out
        self.on_disk = on_disk
        self._kept: list[tuple[int, dict]] = []

    def keep(self, frame: int, data: FrameData) -> None:
        if self.on_disk or (self._kept and self._kept[-1][0] == frame):
            return
        self._kept.append((frame, data.arrays))

    def source(self, last: int) -> list:
        """[(frame, loader)] of the output frames up to ``last``."""
        if self.on_disk:
            return disk_frames(self.out, last)
        return [(n, (lambda f=f: f)) for n, f in self._kept if n <= last]


@dataclass(eq=False)
class RunContext:
    """What the writers of one run share."""

    out: Path
    scene: Scene
    sim: Any  # abmpm.simulation.Simulation; public interface only
    total: int  # frames asked for
    writers: tuple[str, ...]  # names of this run's writers
    progress: Progress
    resumed_from: int | None = None
    t_start: float = field(default_factory=time.perf_counter)
    status: str = "running"  # then "completed", "blew_up", "out_of_memory" or "interrupted"
    summary: dict = field(default_factory=dict)
    outputs: dict[str, str] = field(default_factory=dict)  # name -> path in out, for summary.json
    render_seconds: float = 0.0  # writers that render (preview, USD) add their time
    clock: dict[int, float] = field(default_factory=dict)  # frame -> simulation seconds of this run at its end
    frames: FrameStore = field(init=False)

    def __post_init__(self) -> None:
        self.frames = FrameStore(self.out, on_disk="frames" in self.writers)

    @property
    def interrupted(self) -> bool:
        return self.status == "interrupted"

    @property
    def last_frame(self) -> int:
        """The last completed (good) frame."""
        return int(self.sim.history[-1]["frame"])

    @cached_property
    def collider_mesh(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The colliders' (vertices, int64 faces) when the run began; None without colliders."""
        got = self.sim.collider_faces()
        return None if got is None else (np.asarray(got[0]), np.asarray(got[1], dtype=np.int64))


class Writer:
    """One kind of output of a run; see the module docstring for when each method is
    called. ``name`` is its key in :data:`abmpm.io.writers.WRITERS`. The methods do
    nothing here: a writer overrides those it needs."""

    name: ClassVar[str] = ""

    def begin(self, run: RunContext) -> None:
        pass

    def write_frame(self, frame: int, data: FrameData) -> None:
        pass

    def finish(self, run: RunContext) -> None:
        pass
