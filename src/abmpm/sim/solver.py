"""The MLS-MPM step, in one place.

``MPMSolver.step(state, dt, time)`` is the whole algorithm of a step:
move the colliders and rebuild their colour distance field, P2G with MLS forces
(compatible nodes only), grid update with walls and collider contact, G2P with
boundary velocities, deformation update and return mapping, advection without
crossing a collider. Everything else (sampling, output, diagnostics, time
stepping) lives outside.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import warp as wp

wp.set_module_options({"enable_backward": False})

from . import transfer
from ..scene.model import FACES
from .colliders import ColliderSet, colour_field, colour_particles, empty_spec
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
    def __init__(self, config: SolverConfig, materials: list[MaterialParams], device,
                 colliders: ColliderSet | None = None):
        self.config = config
        self.device = device
        self.materials = wp.array(materials, dtype=MaterialParams, device=device)
        self.grid = Grid.dense(
            config.domain_lo, config.domain_hi, config.dx, 0, config.gravity,
            {f: (config.walls or {}).get(f, ("separate", 0.0)) for f in FACES}, device,
        )
        self.colliders = colliders
        # compile-time CPIC variant of the transfers: only with colliders in CPIC mode
        self.cpic = colliders is not None and bool(colliders.spec.cpic)
        if colliders is None:
            self.collision = empty_spec(device)
            self.grid.colour = colour_field((1, 1, 1), device)
        else:
            self.collision = colliders.spec
            self.grid.colour = colour_field(self.grid.dims, device)
            colliders.colour(self.grid, self.grid.colour)

    def move_colliders(self, time: float) -> None:
        """Colliders to time t (Eq. 22 velocities), colour field rebuilt if they moved."""
        c = self.colliders
        if c is None or (c.static and c.time is not None):
            return
        c.set_time(time)
        self.collision = c.spec
        c.colour(self.grid, self.grid.colour)

    def colour_particles(self, state: ParticleState) -> None:
        """Initial CPIC colour of every particle (later steps update it in G2P)."""
        if self.colliders is None:
            return
        g = self.grid
        wp.launch(colour_particles, dim=state.count, device=self.device,
                  inputs=[state.x, self.collision, g.spec, g.colour], outputs=[state.cp, state.cn, state.cbody])

    def step(self, state: ParticleState, dt: float, time: float = 0.0) -> None:
        """Advance ``state`` in place from ``time`` by ``dt``. In place is safe: G2P
        reads and writes only its own particle, after P2G has read them all."""
        self.move_colliders(time)
        g, s = self.grid, state
        wp.launch(
            transfer.P2G[self.cpic], dim=s.count, device=self.device,
            inputs=[s.x, s.v, s.C, s.F, s.plastic, s.mass, s.volume, s.material, s.cp, s.cn, s.cbody,
                    self.materials, g.spec, g.colour, dt, g.mv, g.m],
        )
        wp.launch(transfer.grid_update, dim=g.dims, device=self.device,
                  inputs=[g.spec, self.collision, g.colour, dt, g.mv, g.m, g.v])
        wp.launch(
            transfer.G2P[self.cpic], dim=s.count, device=self.device,
            inputs=[self.materials, g.spec, self.collision, g.colour, dt, g.v,
                    s.x, s.v, s.C, s.F, s.plastic, s.material, s.cp, s.cn, s.cbody],
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
