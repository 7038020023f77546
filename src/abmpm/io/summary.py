"""JSON summaries with numpy values converted to plain Python."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from abmpm.io.atomic import atomic_write


def to_builtin(obj: Any) -> Any:
    """Recursively convert numpy scalars/arrays, Paths, tuples and sets to JSON types.

    Non-finite floats become ``None`` (JSON has no NaN/Infinity).
    """
    if isinstance(obj, dict):
        return {str(k): to_builtin(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple, set, frozenset)):
        return [to_builtin(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_builtin(obj.tolist())
    if isinstance(obj, np.generic):
        return to_builtin(obj.item())
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    if obj is None or isinstance(obj, (bool, int, str)):
        return obj
    if hasattr(obj, "model_dump"):  # pydantic models
        return to_builtin(obj.model_dump(mode="json"))
    return str(obj)


def write_json(path: str | os.PathLike, obj: Any, indent: int = 2) -> None:
    """Write ``obj`` as JSON (atomic), numpy values converted to plain Python."""
    text = json.dumps(to_builtin(obj), indent=indent, sort_keys=False, allow_nan=False)
    with atomic_write(Path(path)) as tmp:
        tmp.write_text(text + "\n", encoding="utf-8")
