"""The layout of a run's output folder and its housekeeping.

Names of the files and folders a run writes, the paths of numbered frames, the
checks made before a run writes anything, and the removal of what an interrupted
write or an earlier run left behind (only names abmpm's writers use).
"""

from __future__ import annotations

import os
import re
import tempfile
from pathlib import Path

from abmpm.errors import OutputError
from abmpm.io.checkpoint import checkpoint_name
from abmpm.scene.loader import load_scene
from abmpm.scene.model import Scene

__all__ = [
    "BEAUTY_FILE",
    "BEAUTY_POSTER_FILE",
    "BLEND_FILE",
    "CHECKPOINTS_DIR",
    "CHECKPOINT_RE",
    "COLLIDERS_DIR",
    "ENERGY_FILE",
    "FRAMES_DIR",
    "POSTER_FILE",
    "PREVIEW_FILE",
    "REGION_FILE",
    "SCENE_FILE",
    "SUMMARY_FILE",
    "SURFACES_DIR",
    "USD_FILE",
    "checkpoint_path",
    "clean_previous_run",
    "clean_temporaries",
    "collider_path",
    "frame_path",
    "numbered",
    "numbered_outputs",
    "prepare_out_dir",
    "scene_from_folder",
]

FRAMES_DIR = "frames"
COLLIDERS_DIR = "colliders"
CHECKPOINTS_DIR = "checkpoints"
SURFACES_DIR = "surfaces"  # output.surface: surface_NNNNN_<material>.ply
SCENE_FILE = "scene.json"
REGION_FILE = "region.npz"  # adaptive mode: the refined coarse cells (cells, origin, dx)
SUMMARY_FILE = "summary.json"
ENERGY_FILE = "energy.png"
PREVIEW_FILE = "preview.mp4"
POSTER_FILE = "preview.png"
USD_FILE = "particles.usd"
BEAUTY_FILE = "beauty.mp4"  # output.beauty / abmpm render --beauty: path-traced surfaces
BEAUTY_POSTER_FILE = "beauty.png"
BLEND_FILE = "abmpm.blend"  # abmpm blender: the run as a Blender scene

FRAME_RE = re.compile(r"^frame_(\d+)\.ply$")
COLLIDER_RE = re.compile(r"^collider_(\d+)\.ply$")
CHECKPOINT_RE = re.compile(r"^checkpoint_(\d+)\.npz$")
SURFACE_RE = re.compile(r"^surface_(\d+)_(.+)\.ply$")

# Hidden temporary files that an interrupted write leaves behind: atomic_write's
# ".{stem}.XXXXXXXX.tmp{suffix}" and the write probe ".abmpm-write-test-XXXXXXXX".
_TEMP_RE = re.compile(r"^\.(?:.+\.[a-z0-9_]{8}\.tmp(?:\.[A-Za-z0-9]+)?|abmpm-write-test-[a-z0-9_]{8})$")


def frame_path(out_dir: str | os.PathLike, frame: int) -> Path:
    return Path(out_dir) / FRAMES_DIR / f"frame_{frame:05d}.ply"


def collider_path(out_dir: str | os.PathLike, frame: int) -> Path:
    """Triangle mesh (binary PLY) of all the scene's colliders at output frame ``frame``."""
    return Path(out_dir) / COLLIDERS_DIR / f"collider_{frame:05d}.ply"


def checkpoint_path(out_dir: str | os.PathLike, frame: int) -> Path:
    return Path(out_dir) / CHECKPOINTS_DIR / checkpoint_name(frame)


def prepare_out_dir(out: Path) -> None:
    """Create ``out`` and check that files can be written in it (OutputError if not)."""
    full = Path(out).resolve()
    refused = {Path(full.anchor): "the filesystem root", Path.home().resolve(): "your home folder"}.get(full)
    if refused:
        raise OutputError(f"output folder {out} is {refused}: a run writes frames/, checkpoints/ and summary.json "
                          "there; name a folder for it")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except FileExistsError:
        raise OutputError(f"cannot create output folder {out}: a file with that name exists") from None
    except NotADirectoryError:
        raise OutputError(
            f"cannot create output folder {out}: a part of the path is a file, not a folder"
        ) from None
    except OSError as exc:
        raise OutputError(f"cannot create output folder {out}: {exc.strerror or exc}") from None
    if not out.is_dir():
        raise OutputError(f"cannot use output folder {out}: it is not a folder")
    try:
        fd, probe = tempfile.mkstemp(prefix=".abmpm-write-test-", dir=out)
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise OutputError(f"cannot write to output folder {out}: {exc.strerror or exc}") from None


def clean_temporaries(out: Path) -> list[Path]:
    """Remove the temporary files that interrupted writes left in ``out`` and in its
    frames/colliders/checkpoints folders (only names abmpm's writers use)."""
    removed = []
    for folder in (out, out / FRAMES_DIR, out / COLLIDERS_DIR, out / CHECKPOINTS_DIR, out / SURFACES_DIR):
        if not folder.is_dir():
            continue
        for p in folder.iterdir():
            if _TEMP_RE.match(p.name) and p.is_file() and not p.is_symlink():
                try:
                    p.unlink()
                except OSError as exc:
                    raise OutputError(f"cannot remove temporary file {p}: {exc.strerror or exc}") from None
                removed.append(p)
    return removed


def numbered(folder: Path, pattern: re.Pattern) -> list[tuple[int, Path]]:
    """[(number, path)] of the files in ``folder`` whose name ``pattern`` matches, sorted."""
    if not folder.is_dir():
        return []
    out = []
    for p in folder.iterdir():
        m = pattern.match(p.name)
        if m and p.is_file():
            out.append((int(m.group(1)), p))
    return sorted(out)


def clean_previous_run(out: Path) -> None:
    """Remove the outputs of an earlier run in ``out`` (only files abmpm writes)."""
    victims = [p for _, p in numbered(out / FRAMES_DIR, FRAME_RE)]
    victims += [p for _, p in numbered(out / COLLIDERS_DIR, COLLIDER_RE)]
    victims += [p for _, p in numbered(out / CHECKPOINTS_DIR, CHECKPOINT_RE)]
    victims += [p for _, p in numbered(out / SURFACES_DIR, SURFACE_RE)]
    victims += [out / n for n in (SUMMARY_FILE, ENERGY_FILE, PREVIEW_FILE, POSTER_FILE, USD_FILE, REGION_FILE,
                                BEAUTY_FILE, BEAUTY_POSTER_FILE)]
    found = [p for p in victims if p.exists()]
    if found and not (out / SCENE_FILE).is_file():
        # files with abmpm's names in a folder no abmpm run wrote (it would hold scene.json)
        names = ", ".join(str(p.relative_to(out)) for p in found[:3]) + (" ..." if len(found) > 3 else "")
        raise OutputError(f"output folder {out} is not an abmpm run folder (no {SCENE_FILE}) but holds files a run "
                          f"would replace ({names}); choose another --out, or move those files away")
    for p in victims:
        try:
            p.unlink(missing_ok=True)
        except OSError as exc:
            raise OutputError(f"cannot remove old output {p}: {exc.strerror or exc}") from None


def numbered_outputs(out: Path) -> dict[str, str]:
    """The numbered file families present in ``out`` (this run's or, after a resume, an
    earlier one's), as the summary lists them: ``{"frames": "frames/frame_NNNNN.ply", ...}``."""
    found = {}
    if numbered(out / FRAMES_DIR, FRAME_RE):
        found["frames"] = f"{FRAMES_DIR}/frame_NNNNN.ply"
    if numbered(out / COLLIDERS_DIR, COLLIDER_RE):
        found["colliders"] = f"{COLLIDERS_DIR}/collider_NNNNN.ply"
    if numbered(out / CHECKPOINTS_DIR, CHECKPOINT_RE):
        found["checkpoints"] = f"{CHECKPOINTS_DIR}/checkpoint_NNNNN.npz"
    if numbered(out / SURFACES_DIR, SURFACE_RE):
        found["surfaces"] = f"{SURFACES_DIR}/surface_NNNNN_<material>.ply"
    return found


def scene_from_folder(out: Path) -> Scene:
    """The scene a run saved in ``out`` (``scene.json``); OutputError if there is none
    or it cannot be read."""
    path = out / SCENE_FILE
    if not path.is_file():
        raise OutputError(f"{out}: not an abmpm output folder (no {SCENE_FILE})")
    try:
        return load_scene(path)  # the record as `abmpm run` reads it (scene/loader.py)
    except Exception as exc:  # corrupt or from an incompatible version
        raise OutputError(f"{path}: cannot read the scene ({type(exc).__name__}: {exc})") from None
