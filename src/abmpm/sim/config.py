"""What a solver is built with (``MPMSolver(config, ...)``): fixed for its life."""

from __future__ import annotations

from dataclasses import dataclass

from .reconstruct import DEFAULT_SURFACE_THRESHOLD


@dataclass
class SolverConfig:
    domain_lo: tuple[float, float, float]
    """Lower corner of the domain box, m (the wall planes)."""
    domain_hi: tuple[float, float, float]
    """Upper corner of the domain box, m."""
    dx: float
    """Spacing of the coarsest grid, m."""
    gravity: tuple[float, float, float] = (0.0, -9.81, 0.0)
    """m/s^2."""
    walls: dict | None = None
    """Face name ('x_min' ... 'z_max') -> (wall type, friction); missing faces: separate, 0."""
    wall_images: bool = False
    """Particles within 1.5 cells of a domain wall add the stress of their mirror images
    beyond it (sim/wall_images.py): the wall holds up the first layers as the bulk does."""
    refine_factor: int | None = None
    """Refinement factor b of a block-sparse level-1 grid (adaptive mode), or None."""
    base_level: int = 0
    """Level the single dense grid serves (1 in finest mode, where every particle is fine)."""
    reconstruct: bool = False
    """Surface particle reconstruction after each split (paper Section 4.3)."""
    surface_threshold: float = DEFAULT_SURFACE_THRESHOLD
    """Its t_p (Eq. 16), in units of (mass of a full coarse cell) / dx."""
    seed: int = 0
    """The scene's random seed: with the particle ids it draws the split children's jitter
    (sim/split.py), as it draws the sampling's (geometry/sampling.py)."""
    threads: int | None = None
    """CPU threads for the transfers (None: ABMPM_THREADS, else every core); CUDA: ignored."""
    coupling: str = "overlap"
    """Adaptive mode: how the two grids meet. "overlap", the paper's Eq. 8: each level
    scatters to both grids and gathers from its own; "partition": every particle transfers
    with one partition of unity built from both grids' functions (sim/partition.py), so
    momentum is conserved exactly (one time step for all particles)."""
    time_steps: str = "global"
    """Adaptive mode: "per_level" lets the level-0 particles far from the fine level take
    the coarse step (sim/time_levels.py); "global": every particle takes the finest step."""
    stiffening: str = "particle"
    """The CFL signal of compressed fluid: "particle", the largest sound-speed growth of any
    particle; "node", that growth bounded by the grid's fastest mode (sim/stiffness.py)."""
    cfl: float = 0.4
    """The CFL number of the caller's time steps: a substep moves no particle farther than
    cfl cells of the finest grid. Adaptive mode refines often enough for it
    (``refine.refine_every``)."""
    cuda_graph: bool = False
    """Run the substeps of a segment as one captured CUDA graph (CUDA only: ignored with
    a warning on the CPU, where a replayed graph would run on one thread)."""
