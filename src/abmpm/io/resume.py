"""Resuming a run from the latest checkpoint in its output folder, after checking
that the scene has not changed in anything the checkpoint depends on."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from abmpm.errors import OutputError
from abmpm.io.checkpoint import latest_checkpoint, load_checkpoint
from abmpm.io.outdir import CHECKPOINTS_DIR, SCENE_FILE, scene_from_folder
from abmpm.scene.model import Scene

__all__ = ["resume_from_checkpoint"]


def resume_from_checkpoint(out: Path, scene: Scene, sim) -> tuple[int | None, list[str]]:
    """Load the latest checkpoint in ``out`` into ``sim``: (its frame, or None when
    there is none, and the notes to print)."""
    ckpt = latest_checkpoint(out / CHECKPOINTS_DIR)
    if ckpt is None:
        return None, [f"no checkpoint in {out / CHECKPOINTS_DIR}; starting from frame 0"]
    _check_resumable(out, scene, sim, ckpt)
    arrays, meta = load_checkpoint(ckpt)
    saved, scene_has = _scene_particles(arrays), _scene_particles(vars(sim.particles()))
    if saved.shape != scene_has.shape or (saved != scene_has).any():
        raise OutputError(
            f"{ckpt}: its {len(arrays.get('x', ()))} particles come from {len(saved)} particles of a scene, "
            f"but this scene has {len(scene_has)} (or others); cannot resume"
        )
    sim.load_state_dict(arrays, meta)
    return sim.frame, [f"resuming from {ckpt.name} (frame {sim.frame})"]


def _scene_particles(arrays: dict) -> np.ndarray:
    """The scene's particles a state holds, by id: a split child stands for its parent
    (``family``), every other particle for itself. In adaptive mode the particle count
    changes with every split and merge; these ids do not (a checkpoint without ids: one
    id per particle)."""
    ids, family = arrays.get("id"), arrays.get("family")
    if ids is None or family is None:
        return np.arange(len(arrays.get("x", ())))
    return np.unique(np.where(np.asarray(family) >= 0, family, ids))


def _physics_dump(scene: Scene) -> dict:
    """The parts of a scene that a checkpoint depends on."""
    d = scene.model_dump(mode="json", exclude={"name", "description", "output", "base_dir"})
    d["simulation"].pop("duration", None)
    d["simulation"].pop("device", None)
    return d


def _diff_keys(a: Any, b: Any, prefix: str = "") -> list[str]:
    if isinstance(a, dict) and isinstance(b, dict):
        out = []
        for k in sorted(set(a) | set(b)):
            key = f"{prefix}.{k}" if prefix else str(k)
            out += _diff_keys(a.get(k), b.get(k), key) if k in a and k in b else [key]
        return out
    if isinstance(a, list) and isinstance(b, list) and len(a) == len(b) and not all(
        isinstance(v, (int, float)) for v in a + b
    ):
        out = []
        for i, (x, y) in enumerate(zip(a, b)):
            out += _diff_keys(x, y, f"{prefix}[{i}]")
        return out
    return [] if a == b else [prefix]


def _check_resumable(out: Path, scene: Scene, sim, ckpt: Path) -> None:
    saved = out / SCENE_FILE
    if not saved.is_file():
        return
    try:
        old = scene_from_folder(out)
    except OutputError:
        return
    diff = _diff_keys(_physics_dump(old), _physics_dump(scene))
    if diff:
        shown = ", ".join(diff[:5]) + (", ..." if len(diff) > 5 else "")
        raise OutputError(
            f"{out}: cannot resume from {ckpt.name}: the scene changed since it was written "
            f"(differs in {shown}); run without --resume to start over"
        )
