"""Figure for the README: a scene in original and adaptive mode side by side.

python docs/figures/modes.py [SCENE] [FRAME]  ->  docs/images/<scene>_modes.png
(default: letter_panel at its last frame; runs the scene twice, ~2 minutes each on 2 cores)
"""

import sys
import tempfile
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from abmpm.post.camera import Camera
from abmpm.post.preview import PREVIEW_SIZE, disk_frames, frame_image, region_lines
from abmpm.runner import run
from abmpm.scene.loader import load_scene
from abmpm.scene.model import with_mode

# where the material has passed the boundary that matters: (axis, side, coordinate)
PASSED = {"letter_panel": (2, 1, 0.4), "hourglass": (1, -1, 0.35)}
name = sys.argv[1] if len(sys.argv) > 1 else "letter_panel"
axis, side, at = PASSED[name]
root = Path(__file__).resolve().parents[2]
scene = load_scene(name)
scene = scene.model_copy(update={"output": scene.output.model_copy(update={"color_by": "level", "preview": False})})
st = scene.simulation
frame = int(sys.argv[2]) if len(sys.argv) > 2 else round(st.duration * st.fps)
camera = Camera.framing_box(st.domain_min, st.domain_max, *PREVIEW_SIZE)
tmp = Path(tempfile.mkdtemp())
panels = []
for mode in ("original", "adaptive"):
    out = tmp / mode
    t0 = time.perf_counter()
    summary = run(with_mode(scene, mode), out, frames=frame, device="cpu", progress=True)
    wall = time.perf_counter() - t0
    f = dict(disk_frames(out))[frame]()
    beyond = side * (f["x"][:, axis] - at) > 0
    passed = f["mass"][beyond].sum() / f["mass"].sum()
    print(f"{mode}: {summary['particle_count']} particles, {wall:.0f} s, {100 * passed:.1f}% of the mass through")
    panels.append((mode, frame_image(scene, f, camera, lines=region_lines(out)), passed))

fig, axes = plt.subplots(1, 2, figsize=(12.8, 5.2))
for ax, (mode, img, passed) in zip(axes, panels):
    ax.imshow(img)
    ax.set_axis_off()
    what = "coarse grid only" if mode == "original" else "white: subdivided, orange: refined region"
    ax.set_title(f"{mode} ({what})\n{100 * passed:.1f}% of the mass through after {frame / st.fps:.1f} s", fontsize=10)
fig.tight_layout(rect=(0, 0, 1, 0.97))
fig.savefig(root / "docs" / "images" / f"{name}_modes.png", dpi=100)
