"""The paper's Table 1 and the quick versions of its scenes.

Source of :data:`PAPER_TABLE1`: Table 1 ("Simulation performance and parameters") of
the adaptive boundary MPM paper (../shared/paper/adaptive-boundary-mpm.txt), measured
by its authors on an Nvidia GTX 1650 with an Intel i5-11260H. Particle counts are as
printed (k = thousand); dx and dx' are the coarse and fine grid spacings.
"""

from __future__ import annotations

PAPER_GPU = "Nvidia GTX 1650"

PAPER_TABLE1: dict[str, dict] = {
    "paper_panel": {"label": "Panel", "figure": "Figure 1", "dx": "1/100", "dx_fine": "1/200",
                    "particles": {"original": 28_000, "adaptive": 71_000, "finest": 141_000},
                    "steps_per_second": {"original": 3.9, "adaptive": 2.7, "finest": 2.4}},
    "paper_hourglass": {"label": "Hourglass", "figure": "Figure 6", "dx": "1/64", "dx_fine": "1/128",
                        "particles": {"original": 60_000, "adaptive": 167_000, "finest": 304_000},
                        "steps_per_second": {"original": 5.9, "adaptive": 3.0, "finest": 1.7}},
    "paper_cut": {"label": "Cut", "figure": "Figure 3", "dx": "1/30", "dx_fine": "1/90",
                  "particles": {"original": 9_200, "adaptive": 27_000, "finest": 250_000},
                  "steps_per_second": {"original": 14.5, "adaptive": 12.3, "finest": 7.8}},
    "paper_bunny_split": {"label": "Bunny split", "figure": "Figure 4", "dx": "1/64", "dx_fine": "1/128",
                          "particles": {"original": 10_000, "adaptive": 140_000, "finest": 280_000},
                          "steps_per_second": {"original": 15.1, "adaptive": 8.2, "finest": 5.6}},
    "paper_jelly": {"label": "Jelly collision", "figure": "Figure 8", "dx": "1/30", "dx_fine": "1/90",
                    "particles": {"original": 21_000, "adaptive": 100_000, "finest": 560_000},
                    "steps_per_second": {"original": 12.5, "adaptive": 6.5, "finest": 6.0}},
}

PAPER_SCENES = tuple(PAPER_TABLE1)

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
