"""Per-particle colors for the renderer: by material, by speed, by refinement level.

Every function returns float32 ``(N, 3)`` RGB in [0, 1].
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from matplotlib import colormaps

__all__ = ["PALETTE", "colors_by_level", "colors_by_material", "colors_by_speed"]

_MODEL_COLORS = {
    "fluid": (0.22, 0.48, 0.86),  # water blue
    "water": (0.22, 0.48, 0.86),
    "elastic": (0.90, 0.36, 0.46),  # jelly red/pink
    "jelly": (0.90, 0.36, 0.46),
    "viscoelastic": (0.93, 0.55, 0.70),  # pink
    "sand": (0.84, 0.71, 0.48),  # tan
    "snow": (0.95, 0.96, 0.98),  # white
}
# distinct palette by material index (when the model of each material is not given)
PALETTE = np.array(
    [
        (0.22, 0.48, 0.86),  # water blue
        (0.90, 0.36, 0.46),  # jelly red/pink
        (0.84, 0.71, 0.48),  # sand tan
        (0.95, 0.96, 0.98),  # snow white
        (0.35, 0.70, 0.45),  # green
        (0.60, 0.42, 0.78),  # purple
        (0.96, 0.62, 0.25),  # orange
        (0.25, 0.72, 0.74),  # teal
    ],
    dtype=np.float32,
)


def colors_by_material(
    material_ids: np.ndarray, models: Sequence[str] | None = None
) -> np.ndarray:
    """Per-particle RGB float32 (N,3) from material indices.

    Without ``models`` index i gets ``PALETTE[i % 8]`` (blue, pink-red, tan, white, ...).
    With ``models`` (the constitutive model name of each material index, e.g.
    ``["fluid", "sand"]``) the color follows the model: fluid blue, elastic red/pink,
    viscoelastic pink, sand tan, snow white; materials sharing a model still differ
    slightly in brightness.
    """
    ids = np.asarray(material_ids).astype(np.int64).ravel()
    if models is None:
        table = PALETTE
    else:
        table = np.empty((len(models), 3), dtype=np.float32)
        seen: dict[str, int] = {}
        for i, m in enumerate(models):
            key = str(m).lower()
            base = np.array(_MODEL_COLORS.get(key, PALETTE[i % len(PALETTE)]), dtype=np.float32)
            k = seen.get(key, 0)
            seen[key] = k + 1
            table[i] = np.clip(base * (1.0 - 0.18 * k), 0.0, 1.0) if k else base
        if table.shape[0] == 0:
            table = PALETTE
    return table[np.mod(ids, table.shape[0])]


def colors_by_speed(v: np.ndarray, vmax: float | None = None, cmap: str = "viridis") -> np.ndarray:
    """Per-particle RGB float32 (N,3) from |v| via a matplotlib colormap.

    ``vmax`` defaults to the 99th percentile of the speed (robust to outliers).
    """
    v = np.asarray(v, dtype=np.float64).reshape(-1, 3)
    speed = np.linalg.norm(v, axis=1)
    if vmax is None:
        vmax = float(np.percentile(speed, 99)) if speed.size else 1.0
    vmax = vmax if vmax > 0 else 1.0
    t = np.clip(speed / vmax, 0.0, 1.0)
    return colormaps[cmap](t)[:, :3].astype(np.float32)


def colors_by_level(level: np.ndarray) -> np.ndarray:
    """Per-particle RGB float32 (N,3) from the refinement level: 0 blue, 1 white,
    higher levels orange/red (as in the paper's figures)."""
    table = np.array(
        [(0.20, 0.42, 0.85), (0.96, 0.96, 0.97), (0.96, 0.60, 0.25), (0.85, 0.25, 0.25)],
        dtype=np.float32,
    )
    lv = np.clip(np.asarray(level).astype(np.int64).ravel(), 0, table.shape[0] - 1)
    return table[lv]
