"""Every CPU core in a step.

Warp runs a CPU kernel on one thread. Its CPU launches release the GIL and its
generated code keeps the thread index local, so the same kernel launched on
disjoint ranges from several Python threads runs on several cores. Warp's CPU
atomics are plain adds, though: two ranges must never add to the same grid node.
P2G therefore scatters each range into its own copy of the grid's accumulators
(``Launcher.private_grids``), which the grid update adds up node by node in a fixed
order (and clears for the next step), so that results depend on the thread count
but not on timing (a resumed run is bit-identical to an uninterrupted one with the
same threads). Each part's P2G also records the span of storage indices it reached,
and the grid update reads and clears a private grid only there: particles sorted by
cell reach a slab of the grid each, so the extra threads cost a slab, not the
whole grid (at 128^3 the whole private grid is 40 MB to read and clear per step).

Why private grids and not slabs of cell-sorted particles (two slabs processed at
once never sharing a node): they need no ordering of the particles, work on the
block-sparse fine grid unchanged, and on 2-8 cores the extra work in the grid
update is small next to the scatter itself (one read-add-clear per node per extra
thread against 27 scattered adds per particle).

A kernel that runs through the launcher takes the first index of its range as its
first argument (``p = wp.tid() + first``). On CUDA everything is one launch.

The cores are the launcher's: a CPU launcher limits the BLAS libraries numpy and scipy
loaded to one thread (``quiet_blas``). The host's per-frame diagnostics are dot products
over every particle, which OpenBLAS hands to its own threads; those then spin for a
while after each call, on the cores the kernels run on (a tenth of a core all run long
on the letter panel, which ran 9% faster at two threads without it).
"""

from __future__ import annotations

import os
import time
from collections import Counter
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np
import warp as wp
from threadpoolctl import threadpool_limits

wp.set_module_options({"enable_backward": False})

THREADS_ENV = "ABMPM_THREADS"
MIN_RANGE = 4096  # below this many items per thread, one thread is faster
# The transfers cost 100-1000 ns a particle (an elastic stress with its SVD, a
# collider's closest point), so 512 particles outweigh handing a part to another
# thread (~40 us on a 2-core VM with recorded launches); docs/benchmarks.md, "Small
# ranges and launch overhead", has the measurements.
MIN_TRANSFER_RANGE = 512
CPU_NODE_CHUNK = 64  # nodes per kernel thread of a node pass on the CPU (1 on a GPU)
EMPTY_BOUND = wp.constant(2**31 - 1)  # the low end of a private grid's reached range before any P2G
# 4-byte words in a 64-byte cache line: per-thread slots that every particle updates
# (P2G's reached spans, G2P's CFL signal) lie this far apart, or two threads writing
# one line slow each other down (false sharing)
CACHE_LINE_WORDS = 16
REACH_STRIDE = wp.constant(CACHE_LINE_WORDS)  # ints between two threads' reached spans


def quiet_blas() -> None:
    """One thread for every BLAS library loaded so far (module docstring); a library
    loaded later is limited by the next launcher."""
    threadpool_limits(limits=1, user_api="blas")


def default_threads(from_env: bool = True) -> int:
    """``ABMPM_THREADS`` if set (and ``from_env``), else every core this process may use."""
    value = os.environ.get(THREADS_ENV) if from_env else None
    if value:
        try:
            n = int(value)
        except ValueError:
            raise ValueError(f"{THREADS_ENV}={value!r}: expected a whole number of threads") from None
        if n < 1:
            raise ValueError(f"{THREADS_ENV}={value!r}: at least one thread")
        return n
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # macOS, Windows
        return os.cpu_count() or 1


@wp.struct
class Reach:
    """Where a part's P2G scattered: it widens ``span`` = [lo, hi] to the storage
    indices it reached, so that ``add_thread_sums`` reads and clears only those."""

    track: int  # 0: record nothing (part 0, which adds to the grid itself; CUDA)
    span: wp.array(dtype=wp.int32)  # [lo, hi], empty when lo > hi


@wp.func
def widen_reach(reach: Reach, lo: int, hi: int):
    """Widen a tracking part's ``span`` to take in storage indices [lo, hi] (nothing
    when hi < 0: nothing reached)."""
    if reach.track != 0 and hi >= 0:
        wp.atomic_min(reach.span, 0, lo)
        wp.atomic_max(reach.span, 1, hi)


@wp.struct
class ThreadSums:
    """The extra parts' P2G sums of one grid, as the grid update sees them: it adds
    them to the grid's own, in part order, where each part reached, and clears them
    (``add_thread_sums``). On CUDA, and with one thread, ``extra`` is 0: nothing to add."""

    mv: wp.array(dtype=wp.vec3)  # part t >= 1 at [(t - 1) * stride + n]
    m: wp.array(dtype=float)
    extra: int  # parts beyond the first
    stride: int  # node storage of the grid
    bounds: wp.array(dtype=wp.int32)  # each part's reached span, REACH_STRIDE apart


@dataclass
class PrivateGrids:
    """The P2G accumulators of a grid's extra threads, stacked: thread t >= 1 adds
    to ``mv[(t - 1) * stride + n]`` (its view ``parts[t]``), thread 0 to the grid's own."""

    mv: wp.array
    m: wp.array
    stride: int  # node storage of the grid
    extra: int  # threads beyond the first
    parts: list[tuple[wp.array, wp.array]]
    # the storage indices part t's P2G reached, [lo, hi] at REACH_STRIDE t + (0, 1) (empty: lo > hi):
    # the grid update adds and clears only those of each private grid
    bounds: wp.array
    reach: list[Reach]  # part t's P2G argument: its view of ``bounds``, tracking for t >= 1
    sums: ThreadSums  # the grid update's argument


@dataclass
class KernelProfile:
    """Wall seconds and launches per (section, kernel) of the launches made through a
    :class:`Launcher` while it is attached (``abmpm bench --profile``). A section
    names a phase of the step (``Launcher.section``); its own wall time, host work
    included, is kept under the kernel name ``"(all)"``."""

    seconds: Counter = field(default_factory=Counter)
    launches: Counter = field(default_factory=Counter)
    section: str = "substep"
    # (section, kernel, part): seconds of each CPU part's own run, to see whether the
    # threads share a pass evenly (``abmpm bench --profile``'s imbalance column)
    parts: Counter = field(default_factory=Counter)


def _same_argument(x, y) -> bool:
    # the same object (an array, a struct: a replay reads its fields afresh) or an equal number
    return x is y or (type(x) is type(y) and type(x) in (int, float, bool) and x == y)


class Launcher:
    """Launches range kernels over ``threads`` CPU threads (one launch on CUDA)."""

    def __init__(self, device, threads: int | None = None):
        self.device = wp.get_device(device)
        self.threads = 1 if self.device.is_cuda else max(1, int(threads or default_threads()))
        self._pool = ThreadPoolExecutor(self.threads - 1, thread_name_prefix="abmpm") if self.threads > 1 else None
        if self.device.is_cpu:
            quiet_blas()
        self._private: dict[int, PrivateGrids] = {}
        self._warm: set = set()  # kernels (a generic one: with its argument types) launched once already
        self._recorded: dict = {}  # (kernel, (label, site), part) -> [count, arguments, recorded launch]
        self.serial = False  # run the parts one after the other on this thread (graph capture)
        # Warp's debug build (every array access bounds-checked) is not re-entrant: a
        # trivial kernel launched from two Python threads at once dies with SIGSEGV,
        # with no abmpm code involved (tests/test_parallel.py). Under it the parts, with
        # their private grids and reach spans, run one after the other on this thread:
        # the threaded path is still bounds-checked, only not concurrently.
        self.one_at_a_time = wp.config.mode == "debug"
        self.profile: KernelProfile | None = None  # attach one to time every launch

    @contextmanager
    def section(self, name: str):
        """Launches inside are profiled under ``name`` (nothing happens unless profiling)."""
        prof = self.profile
        if prof is None:
            yield
            return
        outer, prof.section = prof.section, name
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self._record((name, "(all)"), t0)
            prof.section = outer

    def _record(self, key: tuple[str, str], t0: float) -> None:
        # the profile's time and count for ``key``, from ``t0`` to the device being done
        if self.device.is_cuda:
            wp.synchronize_device(self.device)
        self.profile.seconds[key] += time.perf_counter() - t0
        self.profile.launches[key] += 1

    def ranges(self, n: int, start: int = 0, min_range: int = MIN_RANGE) -> list[tuple[int, int]]:
        """(first, count) of each thread's part of ``range(start, start + n)``, in order
        (no part shorter than ``min_range`` items unless there is only one)."""
        t = min(self.threads, max(1, n // min_range))
        bounds = [start + n * i // t for i in range(t + 1)]
        return [(bounds[i], bounds[i + 1] - bounds[i]) for i in range(t)]

    def launch(self, kernel, n: int, inputs: Callable[[int, int, int], Sequence] | Sequence, start: int = 0,
               label: str | None = None, min_range: int = MIN_RANGE, site: int = 0) -> int:
        """Run ``kernel`` over ``range(start, start + n)``: ``inputs(part, first, count)``
        gives each part's arguments after ``first`` (or one list shared by all parts).
        Returns the number of parts. ``label`` names the launch in a profile and,
        with ``site`` (e.g. which of a call's ranges this is), the place the launch is
        made from; ``min_range`` is the fewest items worth a thread of their own."""
        if n <= 0:
            return 0
        if self.profile is not None:
            t0 = time.perf_counter()
            times = [0.0] * self.threads
            parts = self._launch(kernel, n, inputs, start, min_range, (label, site), times)
            key = (self.profile.section, label or kernel.key)
            self._record(key, t0)
            for part in range(parts):
                self.profile.parts[(*key, part)] += times[part]
            return parts
        return self._launch(kernel, n, inputs, start, min_range, (label, site))

    def _launch(self, kernel, n: int, inputs, start: int, min_range: int, site: tuple,
                times: list[float] | None = None) -> int:
        parts = self.ranges(n, start, min_range)
        make = inputs if callable(inputs) else (lambda part, first, count: inputs)
        args = [[first, *make(part, first, count)] for part, (first, count) in enumerate(parts)]

        def run(part: int) -> None:
            t0 = time.perf_counter() if times is not None else 0.0  # each part's own time (profiling)
            self._run(kernel, parts[part][1], args[part], (kernel, site, part))
            if times is not None:
                times[part] = time.perf_counter() - t0

        # The first launch of a kernel (for a generic one, of each argument type)
        # compiles or specialises it: that must not happen on two threads at once.
        key = (kernel, tuple(a.dtype if isinstance(a, wp.array) else type(a) for a in args[0])) \
            if kernel.is_generic else kernel
        if len(parts) == 1 or key not in self._warm or self.serial or self.one_at_a_time:
            self._warm.add(key)
            for part in range(len(parts)):
                run(part)
            return len(parts)
        futures = [self._pool.submit(run, part) for part in range(1, len(parts))]
        run(0)
        for f in futures:
            f.result()
        return len(parts)

    def _run(self, kernel, count: int, args: list, key: tuple) -> None:
        # On the CPU a launch from the same place with the same arguments replays the
        # launch recorded the first time: packing a kernel's arguments costs ~15 us of
        # Python per launch, a replay ~3 us, and a step makes dozens of launches.
        # Arguments are the same when each is the same object (an array, a struct,
        # whose fields a replay reads afresh) or an equal number. Graph capture and
        # CUDA launch afresh.
        if self.serial or self.device.is_cuda:
            wp.launch(kernel, dim=count, inputs=args, device=self.device)
            return
        rec = self._recorded.get(key)
        fresh = rec is None or len(rec[1]) != len(args)
        changed = [] if fresh else [i for i, arg in enumerate(args) if not _same_argument(rec[1][i], arg)]
        # a generic kernel's recorded launch is one overload: new arguments may want another
        if fresh or (kernel.is_generic and changed):
            rec = self._recorded[key] = [count, list(args), wp.launch(kernel, dim=count, inputs=args,
                                                                      device=self.device, record_cmd=True)]
        else:
            # a new range (a sort moved the level ranges) or a few new arguments: only
            # those are packed again (a whole launch recorded afresh cost ~25 us more)
            if rec[0] != count:
                rec[2].set_dim(count)
                rec[0] = count
            for i in changed:
                rec[2].set_param_at_index(i, args[i])
                rec[1][i] = args[i]
        rec[2].launch()

    def private_grids(self, grid_key: int, mv: wp.array, m: wp.array) -> PrivateGrids:
        """Per-part P2G accumulators of a grid: part 0 writes the grid's own, the
        others their zeroed slices of one stacked pair (each slice the size of the
        grid's storage). Made on the first call and when the grid's storage grows:
        the solver asks at its host points, so that its substeps find them ready.
        The grid update adds the slices to the grid and clears them."""
        extra, stride = self.threads - 1, m.shape[0]
        grids = self._private.get(grid_key)
        if grids is None or grids.stride != stride:
            size = max(1, extra * stride)
            stacked_mv = wp.zeros(size, dtype=wp.vec3, device=self.device)
            stacked_m = wp.zeros(size, dtype=float, device=self.device)
            parts = [(mv, m)] + [(stacked_mv[t * stride:(t + 1) * stride], stacked_m[t * stride:(t + 1) * stride])
                                 for t in range(extra)]
            bounds = wp.array(np.tile([EMPTY_BOUND, -1] + [0] * (REACH_STRIDE - 2), extra + 1), dtype=wp.int32,
                              device=self.device)
            grids = self._private[grid_key] = PrivateGrids(stacked_mv, stacked_m, stride, extra, parts, bounds,
                                                           [_reach(bounds, t) for t in range(extra + 1)],
                                                           _sums(stacked_mv, stacked_m, extra, stride, bounds))
        grids.parts[0] = (mv, m)
        return grids

    def private_arrays(self) -> list[wp.array]:
        """Every private accumulator allocated so far."""
        return [a for grids in self._private.values() for a in (grids.mv, grids.m, grids.bounds)]


def _reach(bounds: wp.array, part: int) -> Reach:
    r = Reach()
    r.track = int(part > 0)
    r.span = bounds[REACH_STRIDE * part:REACH_STRIDE * part + 2]
    return r


def _sums(mv: wp.array, m: wp.array, extra: int, stride: int, bounds: wp.array) -> ThreadSums:
    t = ThreadSums()
    t.mv, t.m, t.extra, t.stride, t.bounds = mv, m, extra, stride, bounds
    return t


@wp.func
def add_thread_sums(sums: ThreadSums, n0: int, n1: int, grid_mv: wp.array(dtype=wp.vec3),
                    grid_m: wp.array(dtype=float)):
    """Nodes [n0, n1): add the extra parts' sums in part order, only where each part's
    P2G reached, and clear them (nothing on CUDA). Called by the grid update on its
    own chunk of nodes, not as a pass of its own (docs/benchmarks.md, "The step as
    named passes")."""
    for t in range(sums.extra):
        lo = wp.max(n0, sums.bounds[REACH_STRIDE * (t + 1)])
        hi = wp.min(n1 - 1, sums.bounds[REACH_STRIDE * (t + 1) + 1])
        for n in range(lo, hi + 1):
            q = t * sums.stride + n
            grid_mv[n] = grid_mv[n] + sums.mv[q]
            grid_m[n] = grid_m[n] + sums.m[q]
            sums.mv[q] = wp.vec3(0.0)
            sums.m[q] = 0.0


@wp.kernel
def reset_reach(first: int, bounds: wp.array(dtype=wp.int32)):
    # after the sums: every part's span empty again
    t = wp.tid() + first
    bounds[REACH_STRIDE * t] = EMPTY_BOUND
    bounds[REACH_STRIDE * t + 1] = -1
