"""The two grids as one basis (beyond the paper; ``refinement.coupling = "partition"``).

The paper's coupling (Eq. 8, ``sim/p2g.py``) lets each level scatter to both grids and
gather from its own: each grid conserves momentum, the two together do not where they
disagree (docs/method.md, "Momentum across the level interface"). Here every particle,
whatever its level, transfers with one set of functions built from both grids:

    r_I = a_I N_I(x)  (coarse node I),   r_i = (1 - a(x_i)) N_i(x)  (fine node i),
    W = r / S,  S = sum of all r,  grad W = (grad r - W grad S) / S,

a partition of unity at every point, so P2G and G2P with the same W and the forces
-V0 tau grad W (which sum to zero over the nodes) conserve momentum exactly, as one grid
does. ``a`` is the coarse share of a node: 1 outside the refined region and on its edge,
falling to 0 ``SHARE_CELLS`` coarse cells inside it (``coarse_shares``); a fine node takes
1 - a interpolated at its position (``fine_shares``). The fine functions therefore live
only inside the region, where level-1 particles sample them: coarse particles never are
the only samples of a fine function (the bar in ``docs/prototypes/thb_interface_1d.py``
tore where they were). A particle whose functions are one grid's B-splines alone
transfers exactly as it would in a one-level run (MLS, Eqs. 9-10); a particle in the band
where both grids have weight uses the exact gradients (MLS's D^-1 is not consistent on
the blended functions: the 1D model lost energy with it). APIC's C is B D^-1 with the
particle's own D and the weights' centroid.

Measured on prototypes first (docs/prototypes/partition_1d.py, partition_3d.py): the free
bar's momentum exact, its kinetic energy between original's and finest's.
"""

from __future__ import annotations

import numpy as np
import warp as wp
from scipy import ndimage

from .grid import BLOCK_NODES, Grid, GridSpec, dense_node_index, node_coords, node_position
from .parallel import MIN_TRANSFER_RANGE, Launcher
from .partition_transfers import BAND, PURE_COARSE, PURE_FINE, partition_kernels

wp.set_module_options({"enable_backward": False})

SHARE_CELLS = 1.0  # coarse cells over which the coarse share falls from 1 (the region's edge) to 0


def coarse_shares(region_cells: np.ndarray, cells: float = SHARE_CELLS) -> np.ndarray:
    """a at every coarse node (node array, one more than the cells along each axis): 1 at
    nodes not inside the region (some cell around them is not refined), falling linearly
    with the distance to those nodes to 0 at ``cells`` coarse cells."""
    region = np.asarray(region_cells, dtype=bool)
    padded = np.pad(region, 1, constant_values=False)
    inside = np.ones(tuple(n + 1 for n in region.shape), dtype=bool)
    for di in (0, 1):  # node (i, j, k) touches cells i - 1 .. i (padded: i .. i + 1)
        for dj in (0, 1):
            for dk in (0, 1):
                inside &= padded[di:di + inside.shape[0], dj:dj + inside.shape[1], dk:dk + inside.shape[2]]
    if not inside.any():
        return np.ones(inside.shape, dtype=np.float32)
    depth = ndimage.distance_transform_edt(inside)
    return np.clip(1.0 - depth / cells, 0.0, 1.0).astype(np.float32)


def cell_kinds(a: np.ndarray) -> np.ndarray:
    """Each coarse cell's kind (``partition_transfers``): a particle in cell c reaches the coarse
    nodes c - 1 .. c + 2 along each axis, and fine nodes whose shares those nodes set. All of
    them 1: ``PURE_COARSE``; all 0: ``PURE_FINE`` (the fine functions' shares are 1); else ``BAND``."""
    lo = ndimage.minimum_filter(a, size=4, mode="nearest")[1:, 1:, 1:]  # out[i] covers nodes i - 2 .. i + 1
    hi = ndimage.maximum_filter(a, size=4, mode="nearest")[1:, 1:, 1:]
    kinds = np.full(lo.shape, int(BAND), dtype=np.int32)
    kinds[lo >= 1.0] = int(PURE_COARSE)
    kinds[hi <= 0.0] = int(PURE_FINE)
    return kinds


@wp.kernel
def fine_shares(first: int, g: GridSpec, coarse: GridSpec, a: wp.array(dtype=float), share: wp.array(dtype=float)):
    # 1 - a at fine node n (storage index), a interpolated from the coarse nodes (trilinear)
    n = wp.tid() + first
    X = (node_position(g, node_coords(g, n)) - coarse.origin) * coarse.inv_dx
    i0 = wp.clamp(int(wp.floor(X[0])), 0, coarse.dims[0] - 2)
    j0 = wp.clamp(int(wp.floor(X[1])), 0, coarse.dims[1] - 2)
    k0 = wp.clamp(int(wp.floor(X[2])), 0, coarse.dims[2] - 2)
    f = X - wp.vec3(float(i0), float(j0), float(k0))
    value = float(0.0)
    for i in range(2):
        wi = wp.where(i == 0, 1.0 - f[0], f[0])
        for j in range(2):
            wj = wp.where(j == 0, 1.0 - f[1], f[1])
            for k in range(2):
                wk = wp.where(k == 0, 1.0 - f[2], f[2])
                value += wi * wj * wk * a[dense_node_index(coarse, i0 + i, j0 + j, k0 + k)]
    share[n] = 1.0 - wp.clamp(value, 0.0, 1.0)



class Partition:
    """The partition coupling of a solver's two grids: the nodes' shares, and the transfers'
    launches (one P2G and one G2P over every particle, each to and from both grids)."""

    def __init__(self, coarse: Grid, fine: Grid, launcher: Launcher, device, cpic: bool, models: tuple[int, ...]):
        self.coarse, self.fine, self.launcher, self.device = coarse, fine, launcher, device
        self.kernels = partition_kernels(cpic, models)  # (P2G, G2P)
        self.share_c = wp.ones(coarse.capacity, dtype=float, device=device)
        self.share_f = wp.zeros(1, dtype=float, device=device)
        self.kinds = wp.zeros(tuple(d - 1 for d in coarse.dims), dtype=wp.int32, device=device)  # cell_kinds
        self.cpic = cpic
        self.masks = wp.zeros(1, dtype=wp.vec2i, device=device)  # each particle's CPIC masks, P2G -> G2P

    def reserve(self, capacity: int) -> None:
        """Room for ``capacity`` particles' masks (a host point: the substeps allocate nothing)."""
        if self.cpic and self.masks.shape[0] < capacity:
            self.masks = wp.zeros(capacity, dtype=wp.vec2i, device=self.device)

    def update(self, region_cells: np.ndarray | None, first_slot: int) -> None:
        """Shares after the region changed (``region_cells``, all of them) or after the fine
        grid gave out blocks from ``first_slot`` on (the new blocks' shares)."""
        if region_cells is not None:
            a = coarse_shares(region_cells)
            self.share_c.assign(a.ravel())
            self.kinds.assign(cell_kinds(a))
            first_slot = 0
        if self.share_f.shape[0] < self.fine.capacity:
            self.share_f = wp.zeros(self.fine.capacity, dtype=float, device=self.device)
            first_slot = 0
        n = (self.fine.active_slots - first_slot) * BLOCK_NODES
        if n > 0:
            wp.launch(fine_shares, n, inputs=[first_slot * BLOCK_NODES, self.fine.spec, self.coarse.spec,
                                              self.share_c, self.share_f], device=self.device)

    def p2g(self, s, ranges: list, materials, dt: wp.array) -> None:
        """Every particle to both grids (Eqs. 8-10), each CPU part into its own sums."""
        private = [self.launcher.private_grids(g.level, g.mv, g.m) for g in (self.coarse, self.fine)]
        common = [s.arrays(), materials, self.coarse.spec, self.fine.spec, self.coarse.color, self.fine.color,
                  self.share_c, self.share_f, self.kinds, dt]
        for site, (first, count) in enumerate(ranges):
            self.launcher.launch(self.kernels[0], count,
                                 lambda part, first, count: [*common, *private[0].parts[part], private[0].reach[part],
                                                             *private[1].parts[part], private[1].reach[part],
                                                             self.masks],
                                 start=first, label="P2G partition", min_range=MIN_TRANSFER_RANGE, site=site)

    def g2p(self, s, ranges: list, materials, colliders, dt: wp.array, stiff: wp.array, signal_slots: list) -> None:
        """Every particle from both grids (Eqs. 5-7, 11-14, 23-25), its CFL signal into ``signal_slots``."""
        common = [materials, self.coarse.spec, self.fine.spec, colliders, self.coarse.color, self.fine.color,
                  self.share_c, self.share_f, self.kinds, dt, self.coarse.v, self.fine.v, s.arrays(), self.masks,
                  stiff]
        for site, (first, count) in enumerate(ranges):
            self.launcher.launch(self.kernels[1], count, lambda part, first, count: [*common, signal_slots[part]],
                                 start=first, label="G2P partition", min_range=MIN_TRANSFER_RANGE, site=site)
