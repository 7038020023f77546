"""The stiffening part of the CFL signal, node by node (docs/method.md, "Time step").

A compressed fluid is stiffer: its sound speed grows by ``s_p = sqrt(J^(1 - gamma))``
(``materials.sound_speed_ratio``). Up to ``SLACK`` of that growth the CFL number's
margin takes; beyond it the step shrinks. An explicit step is stable while it resolves
the fastest mode of the lumped-mass grid system K u = w^2 M u, and one stiff particle
among soft ones raises that mode far less than its own sound speed says: its
stiffness acts on its stencil's nodes, whose mass is mostly its neighbours'. So the
particles stiffer than ``SLACK`` report a bound of that mode instead of s_p:

* write K = A + B, A every particle with its stiffness capped at SLACK^2 (times the
  stiffness at rest), B the excess e_p = s_p^2 - SLACK^2 of the stiff ones. By Weyl's
  inequality w_max^2 <= w^2(A) + w^2(B), and w^2(A) <= SLACK^2 w^2(at rest);
* B is a sum of one rank-one term per stiff particle, b_p b_p^T with
  b_p = sqrt(e_p m_p) c M^-1/2 g_p (g_ip the MLS weight gradient 4 w_ip (x_i - x_p) / dx,
  in cells); its largest eigenvalue is at most max_p sum_q |b_p . b_q| (Gerschgorin on
  the Gram matrix), which node by node is at most
  R_p = sqrt(e_p m_p) sum_i |g_ip| G_i / m_i with G_i = sum_q sqrt(e_q m_q) |g_iq|,
  in units of c^2 / dx^2 (exact for one isolated stiff particle);
* w^2 at rest is KAPPA c^2 / dx^2 for uniform material (the largest eigenvalue of that
  system with 2 x 2 x 2 or 3 x 3 x 3 particles a cell, jittered or not: 1.89-2.10; 3.6 at
  one a cell), so the signal is sqrt(SLACK^2 + max_p R_p / KAPPA), and never more than
  the particle's own s_p (every particle at most s_max^2 times its stiffness at rest).

Three passes over the particles G2P moved, after it, each on its own level's grid and
3x3x3 stencil at the new position, with the node mass that grid's update kept
(``kept_m``; at least the stiff particles' own mass there, so an emptied node cannot
divide by zero): scatter G, gather R, clear G. Only particles stiffer than SLACK do any
work (the outliers of a mixed-level fluid, an impact), so the passes run on one thread.
"""

from __future__ import annotations

import warp as wp

from .grid import GridSpec, node_index
from .state import ParticleArrays, ParticleState
from .stencil import Stencil, dense_stencil, weight_at

wp.set_module_options({"enable_backward": False})

SLACK = wp.constant(2.0)  # sound-speed growth the CFL number's margin takes (cfl 0.4 -> at most 0.8 there)
SLACK_SQ = wp.constant(SLACK * SLACK)
# w^2 dx^2 / c^2 of uniform material at rest, 8 particles a cell (1.89; jittered 2.10, 27 a
# cell 1.94-2.00): the smallest, so that R / KAPPA is not understated
KAPPA = wp.constant(1.89)
ONE_THREAD = 1 << 30  # min_range of a launch that must run as one part (the sums are not atomic on the CPU)


@wp.func
def excess_weight(s: ParticleArrays, p: int, level: int, stiff: wp.array(dtype=float)):
    # sqrt(e_p m_p); 0 for a particle the margin takes, or of another level
    r = stiff[p]
    if r <= SLACK or s.level[p] != level:
        return 0.0
    return wp.sqrt((r * r - SLACK_SQ) * s.mass[p])


@wp.func
def node_at(g: GridSpec, st: Stencil, i: int, j: int, k: int):
    # storage index of stencil node (i, j, k) on either storage (-1: inactive)
    return node_index(g, st.base[0] + i, st.base[1] + j, st.base[2] + k)


@wp.func
def gradient_length(st: Stencil, i: int, j: int, k: int):
    # |g_ip| = |4 w_ip (x_i - x_p)| / dx of stencil node (i, j, k), in cells
    return 4.0 * weight_at(st, i, j, k) * wp.length(wp.vec3(float(i), float(j), float(k)) - st.fx)


@wp.func
def excess_nodes(g: GridSpec, st: Stencil, a: float, mass: float, excess: wp.array(dtype=float),
                 stiff_m: wp.array(dtype=float), clear: int):
    # the stencil's nodes: add a particle's excess a |g_ip| and its mass share (scatter_excess),
    # or zero both where it added them (clear_excess)
    for i in range(3):
        for j in range(3):
            for k in range(3):
                n = node_at(g, st, i, j, k)
                if n >= 0:
                    if clear != 0:
                        excess[n] = 0.0
                        stiff_m[n] = 0.0
                    else:
                        wp.atomic_add(excess, n, a * gradient_length(st, i, j, k))
                        wp.atomic_add(stiff_m, n, weight_at(st, i, j, k) * mass)


@wp.kernel
def scatter_excess(first: int, s: ParticleArrays, level: int, g: GridSpec, stiff: wp.array(dtype=float),
                   excess: wp.array(dtype=float), stiff_m: wp.array(dtype=float)):
    p = wp.tid() + first
    a = excess_weight(s, p, level, stiff)
    if a == 0.0:
        return
    excess_nodes(g, dense_stencil(g, s.x[p]), a, s.mass[p], excess, stiff_m, 0)


@wp.kernel
def gather_excess(first: int, s: ParticleArrays, level: int, g: GridSpec, stiff: wp.array(dtype=float),
                  excess: wp.array(dtype=float), stiff_m: wp.array(dtype=float), kept_m: wp.array(dtype=float),
                  signal: wp.array(dtype=float)):
    p = wp.tid() + first
    a = excess_weight(s, p, level, stiff)
    if a == 0.0:
        return
    st = dense_stencil(g, s.x[p])
    r = float(0.0)
    for i in range(3):
        for j in range(3):
            for k in range(3):
                n = node_at(g, st, i, j, k)
                if n >= 0:
                    m = wp.max(kept_m[n], stiff_m[n])
                    if m > 0.0:
                        r += gradient_length(st, i, j, k) * excess[n] / m
    bound = wp.sqrt(SLACK_SQ + a * r / KAPPA)
    wp.atomic_max(signal, 1, wp.min(bound, stiff[p]))


@wp.kernel
def clear_excess(first: int, s: ParticleArrays, level: int, g: GridSpec, stiff: wp.array(dtype=float),
                 excess: wp.array(dtype=float), stiff_m: wp.array(dtype=float)):
    p = wp.tid() + first
    if excess_weight(s, p, level, stiff) == 0.0:
        return
    excess_nodes(g, dense_stencil(g, s.x[p]), 0.0, 0.0, excess, stiff_m, 1)


class StiffnessSignal:
    """The node buffers of the three passes (``run``), per grid, and each particle's own
    stiffening as G2P leaves it (``stiff``)."""

    def __init__(self, device, enabled: bool = True):
        self.device = device
        self.enabled = enabled  # off: G2P reports each particle's own stiffening, nothing here runs
        self.stiff = wp.zeros(1, dtype=float, device=device)
        self.none = wp.zeros(1, dtype=float, device=device)  # G2P's ``stiff`` where it reports its own (the slow set)
        self._nodes: dict[int, tuple[wp.array, wp.array, wp.array]] = {}  # level -> excess, stiff_m, kept_m

    def reserve(self, grids: list, capacity: int) -> None:
        """Buffers for ``capacity`` particles and each grid's node storage (a host point)."""
        if not self.enabled:
            return
        if self.stiff.shape[0] < capacity:
            self.stiff = wp.zeros(capacity, dtype=float, device=self.device)
        for g in grids:
            have = self._nodes.get(g.level)
            if have is None or have[0].shape[0] != g.m.shape[0]:
                self._nodes[g.level] = tuple(wp.zeros(g.m.shape[0], dtype=float, device=self.device)
                                             for _ in range(3))

    def kernels(self) -> list:
        """The passes' kernels, where they run (loaded before the first segment)."""
        return [scatter_excess, gather_excess, clear_excess] if self.enabled else []

    def buffers(self) -> list[wp.array]:
        """Every buffer the passes use (what a captured substep bakes in)."""
        return [self.stiff] + [a for arrays in self._nodes.values() for a in arrays]

    def kept_m(self, level: int) -> wp.array:
        """Where the grid update of ``level``'s grid keeps its node masses (length 1: nowhere)."""
        return self._nodes[level][2] if self.enabled else self.none

    def run(self, launcher, state: ParticleState, grids: list, ranges: dict, signal: wp.array) -> None:
        """The three passes on each grid over the particles G2P moved (``ranges`` by level),
        into ``signal`` (a CPU part's slot: they run as one part)."""
        if not self.enabled:
            return
        for g in grids:
            excess, stiff_m, kept_m = self._nodes[g.level]
            args = [state.arrays(), g.level, g.spec, self.stiff]
            for kernel, extra in ((scatter_excess, [excess, stiff_m]),
                                  (gather_excess, [excess, stiff_m, kept_m, signal]),
                                  (clear_excess, [excess, stiff_m])):
                for site, (first, count) in enumerate(ranges[g.level]):
                    launcher.launch(kernel, count, [*args, *extra], start=first, label=f"stiffness {g.name}",
                                    min_range=ONE_THREAD, site=site)

