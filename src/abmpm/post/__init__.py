"""Post-processing: numpy particle renderer, colour helpers, video and plots.

Knows nothing of the solver; takes numpy arrays and dicts.
"""

from abmpm.post.plots import plot_energy
from abmpm.post.render import (
    PALETTE,
    Camera,
    colors_by_level,
    colors_by_material,
    colors_by_speed,
    render,
)
from abmpm.post.video import write_mp4, write_png

__all__ = [
    "PALETTE",
    "Camera",
    "colors_by_level",
    "colors_by_material",
    "colors_by_speed",
    "plot_energy",
    "render",
    "write_mp4",
    "write_png",
]
