"""Figure for docs/surfaces.md: particles and their surface meshes side by side.

python docs/figures/surfaces.py  ->  docs/images/surfaces.png
(runs the built-in dam_break scene for 18 frames with output.surface = true, ~1 minute)
"""

import tempfile
from pathlib import Path

import imageio.v3 as iio
import numpy as np

from abmpm.io.ply import read_mesh_ply, read_particles_ply
from abmpm.post.camera import Camera
from abmpm.post.preview import particle_colors, splat_radius
from abmpm.post.render import render
from abmpm.post.surface import surface_path
from abmpm.runner import run
from abmpm.scene.loader import load_scene

FRAME = 18
root = Path(__file__).resolve().parents[2]
scene = load_scene("dam_break")
scene = scene.model_copy(update={"output": scene.output.model_copy(update={"surface": True, "preview": False})})
out = Path(tempfile.mkdtemp()) / "dam_break"
summary = run(scene, out, frames=FRAME, device="cpu", progress=True)
print("surface meshing:", summary["surface_seconds_per_frame"], "s per frame,", summary["particle_count"], "particles")

f = read_particles_ply(out / "frames" / f"frame_{FRAME:05d}.ply")
box = (scene.simulation.domain_min, scene.simulation.domain_max)
camera = Camera.framing_box(*box)
densities = np.array([m.density for m in scene.materials])
left = render(f["x"], particle_colors(f, scene, None), camera, splat_radius(f, densities), box)
v, faces = read_mesh_ply(surface_path(out, FRAME, "water"))
right = render(np.zeros((0, 3)), None, camera, 0.0, box, triangles=v[faces], triangle_color=(0.3, 0.55, 0.9),
               triangle_alpha=1.0)
iio.imwrite(root / "docs" / "images" / "surfaces.png", np.concatenate([left, right], axis=1))
