"""Checkpoints: ``.npz`` files readable with ``allow_pickle=False``."""

from __future__ import annotations

import json
import os
import re
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from abmpm.errors import OutputError
from abmpm.io.atomic import atomic_write
from abmpm.io.summary import to_builtin

_META_KEY = "__meta_json__"
_NAME_RE = re.compile(r"^checkpoint_(\d+)\.npz$")


def checkpoint_name(index: int) -> str:
    """File name of checkpoint number ``index`` (``checkpoint_00042.npz``)."""
    return f"checkpoint_{index:05d}.npz"


def save_checkpoint(
    path: str | os.PathLike, arrays: dict[str, np.ndarray], meta: dict[str, Any]
) -> None:
    """Save ``arrays`` plus JSON-serialisable ``meta`` to an ``.npz`` (atomic).

    Arrays are stored as-is (bit-exact); ``meta`` is stored as a JSON string in a
    0-d unicode array so the file loads with ``allow_pickle=False``.
    """
    path = Path(path)
    if _META_KEY in arrays:
        raise OutputError(f"{path}: array name {_META_KEY!r} is reserved")
    payload: dict[str, np.ndarray] = {}
    for k, v in arrays.items():
        a = np.asarray(v)
        if a.dtype == object:
            raise OutputError(f"{path}: array {k!r} has object dtype")
        payload[k] = a
    payload[_META_KEY] = np.array(json.dumps(to_builtin(meta), sort_keys=True))
    with atomic_write(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, **payload)


def load_checkpoint(path: str | os.PathLike) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Load a checkpoint written by :func:`save_checkpoint`: ``(arrays, meta)``."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as npz:
            arrays = {k: npz[k] for k in npz.files}
    except (OSError, ValueError, zipfile.BadZipFile) as exc:
        why = "not a checkpoint's arrays" if isinstance(exc, ValueError) else "truncated, or not an .npz archive"
        if isinstance(exc, OSError) and not path.is_file():
            why = exc.strerror or str(exc)
        raise OutputError(f"cannot read checkpoint {path}: {why}; remove it to resume from the checkpoint "
                          f"before it, or run again without --resume") from exc
    meta_arr = arrays.pop(_META_KEY, None)
    meta = json.loads(str(meta_arr[()])) if meta_arr is not None else {}
    return arrays, meta


def latest_checkpoint(folder: str | os.PathLike) -> Path | None:
    """The ``checkpoint_NNNNN.npz`` in ``folder`` with the highest N, or None."""
    folder = Path(folder)
    if not folder.is_dir():
        return None
    best: tuple[int, Path] | None = None
    for p in folder.iterdir():
        m = _NAME_RE.match(p.name)
        if m and p.is_file():
            n = int(m.group(1))
            if best is None or n > best[0]:
                best = (n, p)
    return best[1] if best else None
