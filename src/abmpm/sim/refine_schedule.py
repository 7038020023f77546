"""When adaptive mode refines: as often as the particles' motion needs (docs/method.md,
"When to refine").

Refinement (``MPMSolver.refine``: the split of Eq. 15 and the fine blocks) gives every
level-1 particle the blocks of the nodes it reaches grown by ACTIVATION_MARGIN fine
nodes on each side, so nothing is lost while no particle has moved that far since; a
level-0 particle that entered the region in the meantime is split at the next one, at
most that far inside. So the schedule counts distance, not steps:

* the drift: the sum over the substeps since the last refinement of dt times the
  fastest particle's speed (the CFL signal each substep reports), which no particle's
  motion exceeds;
* a refinement is decided at the steps that are multiples of ``every`` (so that a run
  whose segments are captured graphs decides at the same steps as one that runs substep
  by substep): it is skipped while the drift plus
  ``every`` substeps at the CFL bound (a particle moves at most cfl fine cells a substep:
  the time step's own limit) stays within the margin, which keeps every particle
  covered until the next decision point;
* ``every`` is REFINE_EVERY, or fewer where cfl * REFINE_EVERY would exceed the margin;
* a refinement is due at once at the start, after a frame end (merges, a region that
  follows a moving collider, and a resumed run decide from the same state) and after the
  region changes.

Where the particles move at the CFL bound this refines every ``every`` steps, as a fixed
schedule did; where they move slower than the waves in them the drift grows by a fraction
of a cell a step and refinement comes less often (17-51% fewer refinements on the scenes
of docs/benchmarks.md, "Refinement when the particles need it").
"""

from __future__ import annotations

from .refine import ACTIVATION_MARGIN, REFINE_EVERY


class RefineSchedule:
    """The drift since the last refinement and the rule above (host numbers only)."""

    def __init__(self, cfl: float, fine_dx: float):
        margin = int(ACTIVATION_MARGIN)
        self.every = max(1, min(REFINE_EVERY, int(margin / cfl + 1e-9)))  # steps between decision points
        self.cfl = cfl
        self.reach = margin * fine_dx  # how far a particle may move between two refinements (m)
        self.drift = 0.0  # m since the last refinement, at most
        self.due = True  # refine at the next segment whatever the drift
        self._at_start = 0.0  # the drift at the segment's start (rewind)

    def refine_now(self, steps: int, step_dx: float) -> bool:
        """At the start of every segment, after ``steps`` steps: whether it refines first (the
        drift then starts again from 0). The time step keeps the CFL condition on the spacing
        ``step_dx`` (the coarse one before anything is fine)."""
        now = self.due or (steps % self.every == 0 and self.drift + self.every * self.cfl * step_dx > self.reach)
        if now:
            self.drift, self.due = 0.0, False
        self._at_start = self.drift
        return now

    def moved(self, dt: float, speeds) -> None:
        """The substeps of length ``dt`` whose fastest speeds are ``speeds``, in order."""
        for v in speeds:
            self.drift += dt * float(v)

    def rewound(self, dt: float, speeds) -> None:
        """The segment stopped after the substeps whose speeds are ``speeds``."""
        self.drift = self._at_start
        self.moved(dt, speeds)
