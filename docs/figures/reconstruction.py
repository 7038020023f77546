"""Figure for docs/validation.md: a split surface with and without reconstruction.

python docs/figures/reconstruction.py  ->  docs/images/reconstruction.png
(the helpers of ``abmpm bench --suite reconstruction``, src/abmpm/bench/reconstruction.py)
"""

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from abmpm.bench.reconstruction import H, sphere_parents, split_whole  # noqa: E402
from abmpm.scene import model as sm  # noqa: E402

root = Path(__file__).resolve().parents[2]
R = 0.3
parents, c = sphere_parents(R, 0.0, 7)
fluid = sm.Fluid(name="m")
plain, recon = split_whole(parents, fluid, False), split_whole(parents, fluid, True)

fig, axes = plt.subplots(1, 3, figsize=(13, 4.6), sharex=True, sharey=True)
titles = ["parents (jittered lattice)", "plain split (Eq. 15)", "with surface reconstruction (Eqs. 16-20)"]
for ax, pts, size, title in zip(axes, (parents["x"], plain["x"], recon["x"]), (14, 5, 5), titles):
    sel = np.abs(pts[:, 2] - c[2]) < (H / 2 if pts is parents["x"] else H / 4)  # one layer thick
    q = pts[sel]
    ax.scatter(q[:, 0], q[:, 1], s=size, c="#3a7bd5" if pts is parents["x"] else "#e0e0e0",
               edgecolors="#333333", linewidths=0.3)
    t = np.linspace(0, np.pi / 2, 200)
    ax.plot(c[0] + R * np.cos(t), c[1] + R * np.sin(t), color="#e4572e", lw=1.2, label="sphere surface")
    ax.set_title(title, fontsize=10)
    ax.set_aspect("equal")
    ax.set_xlim(c[0] + 0.05, c[0] + R + 0.03)
    ax.set_ylim(c[1] + 0.05, c[1] + R + 0.03)
    ax.set_facecolor("#20242a")
axes[0].legend(loc="lower left", fontsize=8)
fig.suptitle("A slice through a split sphere (R = 6 dx, b = 2): the children's envelope follows the surface, "
             "not the parents' jitter", fontsize=10)
fig.tight_layout()
out = root / "docs" / "images" / "reconstruction.png"
fig.savefig(out, dpi=110)
print(out)
