"""MP4 and PNG writers (imageio + imageio-ffmpeg), atomic."""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path

import imageio.v2 as imageio
import imageio.v3 as iio
import numpy as np

from abmpm.errors import OutputError
from abmpm.io.atomic import atomic_write


def _rgb8(frame) -> np.ndarray:
    a = np.asarray(frame)
    if a.ndim == 2:
        a = np.stack([a] * 3, axis=-1)
    if a.ndim != 3 or a.shape[2] not in (3, 4):
        raise OutputError(f"frames must be (H, W, 3) images, got shape {a.shape}")
    a = a[..., :3]
    if a.dtype != np.uint8:
        if np.issubdtype(a.dtype, np.floating) and a.max(initial=0) <= 1.0:
            a = a * 255.0
        a = np.clip(a, 0, 255).astype(np.uint8)
    return a


def _even(a: np.ndarray) -> np.ndarray:
    """Pad to even height/width (yuv420p needs it) by repeating the last row/column."""
    h, w = a.shape[:2]
    ph, pw = h % 2, w % 2
    if ph or pw:
        a = np.pad(a, ((0, ph), (0, pw), (0, 0)), mode="edge")
    return a


def write_mp4(
    path: str | os.PathLike, frames: Iterable[np.ndarray], fps: float = 30.0, quality: int = 8
) -> int:
    """Encode uint8 (H,W,3) frames to an H.264 MP4 (libx264, yuv420p), atomically.

    Odd dimensions are padded to even. All frames must have the same size.
    Returns the number of frames written.
    """
    path = Path(path)
    count = 0
    shape = None
    with atomic_write(path) as tmp:
        try:
            writer = imageio.get_writer(
                str(tmp), format="FFMPEG", mode="I", fps=float(fps), codec="libx264",
                pixelformat="yuv420p", quality=quality, macro_block_size=1,
                ffmpeg_log_level="error",
            )
        except Exception as exc:  # missing ffmpeg backend, etc.
            raise OutputError(f"cannot open video writer for {path}: {exc}") from exc
        try:
            for frame in frames:
                a = _even(_rgb8(frame))
                if shape is None:
                    shape = a.shape
                elif a.shape != shape:
                    raise OutputError(
                        f"{path}: frame {count} has shape {a.shape}, expected {shape}"
                    )
                writer.append_data(a)
                count += 1
        finally:
            writer.close()
        if count == 0:
            raise OutputError(f"{path}: no frames to write")
    return count


def write_png(path: str | os.PathLike, image: np.ndarray) -> None:
    """Write an (H,W,3) uint8 image as PNG, atomically."""
    a = _rgb8(image)
    with atomic_write(Path(path)) as tmp:
        iio.imwrite(tmp, a, extension=".png")
