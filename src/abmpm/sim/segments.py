"""Segments: the substeps between two host points (docs/architecture.md, "Segments and
CUDA graphs"). The CFL signal slots the substeps write (``Signals``), what the solver
keeps to go back to a segment's start (``SegmentStart``) and the graphs that replay a
segment's launches (``Graphs``)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import warp as wp

from .parallel import CACHE_LINE_WORDS, Launcher
from .state import DYNAMIC, FIELDS, ParticleState


class Signals:
    """[fastest speed, largest sound-speed stiffening] per substep of a segment and CPU
    part, written by G2P (atomic max over its particles) into its own slot; one view
    per slot, made here. Slots are a cache line apart: two CPU threads updating the
    same line on every particle cost G2P a tenth of its two-thread speed."""

    def __init__(self, substeps: int, threads: int, device):
        self._shape = (substeps, threads, CACHE_LINE_WORDS)
        at_rest = np.tile([0.0, 1.0] + [0.0] * (CACHE_LINE_WORDS - 2), substeps * threads)
        self.array = wp.array(at_rest, dtype=float, device=device)
        self._at_rest = wp.array(at_rest, dtype=float, device=device)
        w = CACHE_LINE_WORDS
        self.slots = [[self.array[w * i: w * i + 2] for i in range(k * threads, (k + 1) * threads)]
                      for k in range(substeps)]  # substep -> CPU part -> view

    def reset(self) -> None:
        wp.copy(self.array, self._at_rest)

    def read(self, substeps: int) -> np.ndarray:
        """The first ``substeps`` substeps' signals, shape (substeps, 2): one read."""
        return self.array.numpy().reshape(self._shape)[:substeps, :, :2].max(axis=1).astype(np.float64)


class SegmentStart:
    """A device copy of the dynamic particle fields at a segment's start (``rewind``)."""

    def __init__(self, device):
        self.device = device
        self._kept: dict[str, wp.array] = {}

    def keep(self, state: ParticleState) -> None:
        for name in DYNAMIC:
            src = getattr(state, name)
            if self._kept.get(name) is None or self._kept[name].shape[0] < state.capacity:
                self._kept[name] = wp.empty(state.capacity, dtype=src.dtype, device=self.device)
            wp.copy(self._kept[name], src, count=state.count)

    def restore(self, state: ParticleState) -> None:
        for name in DYNAMIC:
            wp.copy(getattr(state, name), self._kept[name], count=state.count)


class Graphs:
    """Captured segments by (first signal slot, substeps), valid while every buffer they
    baked in stays where it was (``buffers``: launch sizes and addresses)."""

    def __init__(self):
        self._graphs: dict[tuple, Any] = {}
        self._buffers: tuple | None = None

    def __len__(self) -> int:
        return len(self._graphs)

    def find(self, buffers: tuple, key: tuple):
        """The graph for ``key``, or None; every graph is dropped once anything moved
        (the old graphs point at freed memory)."""
        if buffers != self._buffers:
            self._graphs.clear()
            self._buffers = buffers
        return self._graphs.get(key)

    def capture(self, key: tuple, device, launcher: Launcher, record: Callable[[], None]):
        """Record ``record()``'s launches (on one thread, in order) as the graph for
        ``key``; records, does not run."""
        launcher.serial = True
        try:
            with wp.ScopedCapture(device=device, force_module_load=False) as capture:
                record()
        finally:
            launcher.serial = False
        self._graphs[key] = capture.graph
        return capture.graph


def buffer_key(count: int, arrays: list[wp.array], *sizes) -> tuple:
    """What a captured substep has baked in: the particle count, launch sizes (``sizes``)
    and every buffer's address and shape."""
    return (count, *sizes, tuple((a.ptr, a.shape) for a in arrays))


def substep_buffers(solver, state: ParticleState) -> tuple:
    """What a captured substep of ``solver`` (an ``MPMSolver``) has baked in: launch sizes and
    every buffer's address (its ``Graphs`` key)."""
    arrays = [getattr(state, name) for name in FIELDS]
    if solver.slow is not None:
        arrays += [solver.slow.nodes.m, solver.slow.nodes.p, solver.slow.nodes.f]
    arrays += [solver._tau, solver._cmask, solver._on_fine, solver._occ, solver._dt, solver.signal, solver.materials,
               solver.collider_arrays.bodies, solver.collider_arrays.face_body, *solver.stiffness.buffers()]
    for g in solver.grids:
        arrays += [g.mv, g.m, g.v, g.color.dist, g.color.dir, g.color.body, g.spec.blocks, g.spec.slot_block]
    arrays += solver.launcher.private_arrays()
    return buffer_key(state.count, arrays, solver.slow is not None and solver.slow.open,
                      tuple(map(tuple, solver._ranges.values())), tuple(g.node_count for g in solver.grids),
                      int(solver.collider_arrays.mesh))
