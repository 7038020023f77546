"""Figure for docs/paper.md: one frame of a paper scene path-traced in original and
adaptive mode side by side (the beauty pass of ``abmpm render --beauty``).

python docs/figures/beauty_modes.py RUNS [FRAME] [SPP]  ->  docs/images/<scene>_beauty_modes.jpg

RUNS is a scene's folder of an ``abmpm paper`` comparison, holding ``original/`` and
``adaptive/`` run folders with particle frames (e.g. ``abmpm paper --quick --out
out/paper_quick``, then ``out/paper_quick/paper_panel``). Only FRAME's
particles are meshed (splashsurf), in a temporary copy (RUNS is not touched); default
frame: the scene's entry in FRAMES below, else the last one (the last column of the
splat montage). The colliders take the look of the built-in scene of that name (the
hourglass is glass), the rest is the beauty pass's: its camera, looks and lighting,
640 x 360 at SPP samples per pixel (default 16). Set ABMPM_THREADS to limit the
cores Mitsuba uses.
"""

import shutil
import sys
import tempfile
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from abmpm.io.outdir import (
    FRAME_RE,
    FRAMES_DIR,
    collider_path,
    frame_path,
    numbered,
    scene_from_folder,
)
from abmpm.io.ply import read_particles_ply
from abmpm.post.beauty import BeautySettings, render_run_frame
from abmpm.post.surface import surface_meshes, write_surfaces
from abmpm.scene.loader import load_scene

MODES = ("original", "adaptive")
# a scene's frame where the last one does not show the difference (none so far)
FRAMES = {}

runs = Path(sys.argv[1])
root = Path(__file__).resolve().parents[2]
scene = scene_from_folder(runs / MODES[0])
st = scene.simulation
last = numbered(runs / MODES[0] / FRAMES_DIR, FRAME_RE)[-1][0]
frame = int(sys.argv[2]) if len(sys.argv) > 2 else FRAMES.get(scene.name, last)
spp = int(sys.argv[3]) if len(sys.argv) > 3 else BeautySettings().spp
settings = BeautySettings(spp=spp, colliders=load_scene(scene.name).output.beauty_colliders)
tmp = Path(tempfile.mkdtemp())
panels = []
for mode in MODES:
    src, out = runs / mode, tmp / mode
    (out / "frames").mkdir(parents=True)
    (out / "colliders").mkdir()
    shutil.copy2(src / "scene.json", out / "scene.json")
    shutil.copy2(frame_path(src, frame), frame_path(out, frame))
    if collider_path(src, frame).is_file():
        shutil.copy2(collider_path(src, frame), collider_path(out, frame))
    t0 = time.perf_counter()
    particles = read_particles_ply(frame_path(out, frame))
    write_surfaces(out, frame, surface_meshes(particles, scene_from_folder(out)))
    t1 = time.perf_counter()
    panels.append((mode, render_run_frame(out, frame, settings)))
    t2 = time.perf_counter()
    print(f"{scene.name} {mode} frame {frame}: {len(particles['x'])} particles, meshed in {t1 - t0:.1f} s, "
          f"rendered in {t2 - t1:.1f} s ({settings.width}x{settings.height}, {spp} spp)")

h, w = panels[0][1].shape[:2]
fig = plt.figure(figsize=(2 * w / 100, h / 100), dpi=100)
for i, (mode, img) in enumerate(panels):
    ax = fig.add_axes((i / 2, 0, 1 / 2, 1))
    ax.imshow(img, interpolation="nearest")
    ax.set_axis_off()
    label = f"{mode}" if i else f"{mode}, t = {frame / st.fps:.2f} s"
    ax.text(8, 8, label, va="top", ha="left", fontsize=11, color="black",
            bbox={"facecolor": "white", "alpha": 0.75, "edgecolor": "none", "pad": 2.5})
path = root / "docs" / "images" / f"{scene.name}_beauty_modes.jpg"
fig.savefig(path, dpi=100, pil_kwargs={"quality": 85, "optimize": True})
plt.close(fig)
shutil.rmtree(tmp)
print(f"{path}: {path.stat().st_size / 1000:.0f} kB")
