"""Post-processing: numpy particle renderer, color helpers, video and plots.

Knows nothing of the solver; takes numpy arrays and dicts.
"""

from abmpm.post.camera import Camera
from abmpm.post.colors import PALETTE, colors_by_level, colors_by_material, colors_by_speed
from abmpm.post.plots import plot_energy
from abmpm.post.render import render
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
