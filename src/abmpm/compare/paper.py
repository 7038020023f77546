"""The paper's Table 1 and the quick versions of its scenes.

Source of :data:`PAPER_TABLE1`: Table 1 ("Simulation performance and parameters") of
the adaptive boundary MPM paper (../shared/paper/adaptive-boundary-mpm.txt), measured
by its authors on an Nvidia GTX 1650 with an Intel i5-11260H. Particle counts are as
printed (k = thousand); dx and dx' are the coarse and fine grid spacings.
"""

from __future__ import annotations

PAPER_GPU = "Nvidia GTX 1650"

def _row(label: str, figure: str, dx: str, dx_fine: str, particles: tuple, steps_per_second: tuple) -> dict:
    # one line of Table 1; particles and steps/s in the order original, adaptive, finest
    modes = ("original", "adaptive", "finest")
    return {"label": label, "figure": figure, "dx": dx, "dx_fine": dx_fine,
            "particles": dict(zip(modes, particles)), "steps_per_second": dict(zip(modes, steps_per_second))}


PAPER_TABLE1: dict[str, dict] = {
    "paper_panel": _row("Panel", "Figure 1", "1/100", "1/200", (28_000, 71_000, 141_000), (3.9, 2.7, 2.4)),
    "paper_hourglass": _row("Hourglass", "Figure 6", "1/64", "1/128", (60_000, 167_000, 304_000), (5.9, 3.0, 1.7)),
    "paper_cut": _row("Cut", "Figure 3", "1/30", "1/90", (9_200, 27_000, 250_000), (14.5, 12.3, 7.8)),
    "paper_bunny_split": _row("Bunny split", "Figure 4", "1/64", "1/128", (10_000, 140_000, 280_000), (15.1, 8.2, 5.6)),
    "paper_jelly": _row("Jelly collision", "Figure 8", "1/30", "1/90", (21_000, 100_000, 560_000), (12.5, 6.5, 6.0)),
}

PAPER_SCENES = tuple(PAPER_TABLE1)

# When the material first meets what the scene is about (simulated seconds), from each
# scene's initial geometry and motion (ballistic, g = 9.81 m/s^2). ``abmpm paper
# --window W`` runs each scene to the first output frame at or after this time plus
# W seconds and times the steps of that window alone: the part of a run where the
# modes differ (before contact an adaptive run has no fine particle).
PAPER_CONTACT: dict[str, float] = {
    # the bunny's front (z 0.209) meets the panel (z 0.305) at 3 m/s
    "paper_panel": 0.032,
    # the water's lowest point (y 0.814) falls to the neck (y 0.7) from rest
    "paper_hourglass": 0.152,
    # the blade rests until 0.2 s, then moves down at 0.4 m/s; its edge starts 4 cm above the block
    "paper_cut": 0.3,
    # the bunny's lowest point (y 0.439) falls at 1 m/s plus gravity onto the blades' top edge (y 0.31)
    "paper_bunny_split": 0.090,
    # the two blocks, 0.2 m apart, close at 2 x 2 m/s (they reach the platform at 0.089 s)
    "paper_jelly": 0.05,
}

# `abmpm paper --quick`: coarser grids and shorter runs (dotted scene keys, list items
# by index). Chosen so that the 15 runs (5 scenes x 3 modes) take about 30 minutes on
# 2 CPU cores; the finest runs dominate. Where a coarser grid would make a hole or a
# neck narrower than a cell, the geometry is widened with it so that the comparison
# (coarse clogs, fine flows) still holds.
QUICK_OVERRIDES: dict[str, dict[str, object]] = {
    "paper_panel": {"simulation.dx": 0.02, "simulation.duration": 0.6, "colliders.0.text": "MPM"},
    "paper_hourglass": {"simulation.dx": 0.03125, "simulation.duration": 1.0, "colliders.0.neck_radius": 0.0234},
    "paper_cut": {"simulation.dx": 0.05, "simulation.duration": 1.0},
    "paper_bunny_split": {"simulation.dx": 0.03125, "simulation.duration": 0.8},
    "paper_jelly": {"simulation.dx": 0.0666666667, "simulation.duration": 1.0},
}
