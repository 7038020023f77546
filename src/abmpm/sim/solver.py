"""The MLS-MPM step, in one place.

``MPMSolver.step(state_in, state_out, dt)`` is the whole algorithm of a step on the
uniform grid: P2G with MLS forces, grid update with walls, G2P with deformation
update and return mapping, advection. Everything else (sampling, output,
diagnostics, time stepping) lives outside.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import warp as wp

from . import transfer
from ..scene.model import FACES
from .grid import Grid
from .materials import MaterialParams
from .state import DYNAMIC, STATIC, ParticleState


@dataclass
class SolverConfig:
    domain_lo: tuple[float, float, float]
    domain_hi: tuple[float, float, float]
    dx: float
    gravity: tuple[float, float, float] = (0.0, -9.81, 0.0)
    # face name ('x_min' ... 'z_max') -> (wall type, friction); missing faces: separate, 0
    walls: dict | None = None


class MPMSolver:
    def __init__(self, config: SolverConfig, materials: list[MaterialParams], device):
        self.config = config
        self.device = device
        self.materials = wp.array(materials, dtype=MaterialParams, device=device)
        self.grid = Grid.dense(
            config.domain_lo, config.domain_hi, config.dx, 0, config.gravity,
            {f: (config.walls or {}).get(f, ("separate", 0.0)) for f in FACES}, device,
        )

    def step(self, state_in: ParticleState, state_out: ParticleState, dt: float) -> None:
        """Advance by dt. ``state_out`` may be ``state_in`` (in place): G2P reads and
        writes only its own particle, after P2G has read them all."""
        g = self.grid
        n = state_in.count
        wp.launch(
            transfer.p2g, dim=n, device=self.device,
            inputs=[state_in.x, state_in.v, state_in.C, state_in.F, state_in.plastic,
                    state_in.mass, state_in.volume, state_in.material, self.materials,
                    g.spec, dt, g.mv, g.m],
        )
        wp.launch(transfer.grid_update, dim=g.dims, device=self.device, inputs=[g.spec, dt, g.mv, g.m, g.v])
        wp.launch(
            transfer.g2p, dim=n, device=self.device,
            inputs=[state_in.x, state_in.F, state_in.plastic, state_in.material, self.materials,
                    g.spec, dt, g.v],
            outputs=[state_out.x, state_out.v, state_out.C, state_out.F, state_out.plastic],
        )

    # ------------------------------------------------------------------ sorting

    def sort_by_cell(self, state: ParticleState) -> None:
        """Reorder particles by grid cell so P2G/G2P touch memory coherently (on the device)."""
        n = state.count
        keys = wp.empty(2 * n, dtype=wp.int32, device=self.device)
        perm = wp.empty(2 * n, dtype=wp.int32, device=self.device)
        wp.launch(_cell_keys, dim=n, inputs=[state.x, self.grid.spec], outputs=[keys, perm], device=self.device)
        wp.utils.radix_sort_pairs(keys, perm, n)
        for name in DYNAMIC + STATIC:
            src = getattr(state, name)
            tmp = wp.empty_like(src)
            wp.launch(_gather, dim=n, inputs=[src, perm], outputs=[tmp], device=self.device)
            wp.copy(src, tmp)


@wp.kernel
def _cell_keys(x: wp.array(dtype=wp.vec3), g: transfer.GridSpec, keys: wp.array(dtype=wp.int32),
               perm: wp.array(dtype=wp.int32)):
    p = wp.tid()
    b = transfer.stencil_base(g, x[p])
    keys[p] = (b[0] * g.dims[1] + b[1]) * g.dims[2] + b[2]
    perm[p] = p


@wp.kernel
def _gather(src: wp.array(dtype=Any), perm: wp.array(dtype=wp.int32), dst: wp.array(dtype=Any)):
    p = wp.tid()
    dst[p] = src[perm[p]]
