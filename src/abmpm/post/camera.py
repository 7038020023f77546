"""Pinhole camera of the particle renderer: world -> pixel projection and framing.

World y is up; camera space has x right, y up and depth positive in front of the
camera; pixel rows grow downwards (row 0 at the top of the image).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

__all__ = ["Camera"]


def _normalize(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v)
    if n == 0.0:
        raise ValueError("zero-length vector")
    return v / n


@dataclass
class Camera:
    """Pinhole camera. ``fov_deg`` is the vertical field of view."""

    eye: tuple[float, float, float] | np.ndarray
    target: tuple[float, float, float] | np.ndarray
    up: tuple[float, float, float] | np.ndarray = (0.0, 1.0, 0.0)
    fov_deg: float = 40.0
    width: int = 640
    height: int = 480

    # ------------------------------------------------------------------ geometry
    def basis(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Camera axes in world space: right, up, back (back points towards the viewer)."""
        eye = np.asarray(self.eye, dtype=np.float64)
        fwd = _normalize(np.asarray(self.target, dtype=np.float64) - eye)
        up = np.asarray(self.up, dtype=np.float64)
        right = np.cross(fwd, up)
        if np.linalg.norm(right) < 1e-9:  # looking along `up`: pick any perpendicular
            alt = np.array([0.0, 0.0, 1.0]) if abs(fwd[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
            right = np.cross(fwd, alt)
        right = _normalize(right)
        cup = np.cross(right, fwd)
        return right, cup, -fwd

    @property
    def focal_px(self) -> float:
        """Focal length in pixels."""
        return 0.5 * self.height / math.tan(math.radians(self.fov_deg) * 0.5)

    def to_camera(self, p: np.ndarray) -> np.ndarray:
        """World points (..., 3) -> camera coords (..., 3): x right, y up, depth (>0 in front)."""
        right, cup, back = self.basis()
        d = np.asarray(p, dtype=np.float64) - np.asarray(self.eye, dtype=np.float64)
        return np.stack([d @ right, d @ cup, -(d @ back)], axis=-1)

    def project(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World points -> (column, row, depth) in pixels (row 0 at the top)."""
        c = self.to_camera(p)
        z = c[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            f = self.focal_px / z
        col = 0.5 * self.width + c[..., 0] * f
        row = 0.5 * self.height - c[..., 1] * f
        return col, row, z

    # ------------------------------------------------------------------ framing
    @classmethod
    def framing_box(
        cls,
        lo: Sequence[float],
        hi: Sequence[float],
        width: int = 640,
        height: int = 480,
        *,
        azimuth_deg: float = 35.0,
        elevation_deg: float = 25.0,
        fov_deg: float = 35.0,
        margin: float = 0.92,
    ) -> "Camera":
        """A 3/4 view from the front-right-above (+z is front, +x right, +y up) that
        fits all eight corners of the box ``[lo, hi]`` in the image.

        ``margin`` < 1 leaves a border (fraction of the half-extent that is used).
        """
        lo = np.asarray(lo, dtype=np.float64)
        hi = np.asarray(hi, dtype=np.float64)
        center = 0.5 * (lo + hi)
        az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
        d = np.array([math.sin(az) * math.cos(el), math.sin(el), math.cos(az) * math.cos(el)])
        fwd = -d
        right = _normalize(np.cross(fwd, [0.0, 1.0, 0.0]))
        cup = np.cross(right, fwd)
        tan_v = math.tan(math.radians(fov_deg) * 0.5) * margin
        tan_h = tan_v * width / height
        corners = np.array(
            [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
        )
        target = center.copy()
        for _ in range(4):
            rel = corners - target
            a = rel @ right
            b = rel @ cup
            e = rel @ fwd  # depth offset of a corner relative to the target
            # at distance D a corner has depth D + e; need |a| <= tan_h (D + e), |b| <= tan_v (D + e)
            dist = float(np.max(np.maximum(np.abs(a) / tan_h - e, np.abs(b) / tan_v - e)))
            dist = max(dist, float(np.max(-e)) + 1e-3, 1e-3)
            # re-centre: move the target (and eye) sideways so the projected box is centred
            u = a / (dist + e)
            v = b / (dist + e)
            du = 0.5 * (u.max() + u.min())
            dv = 0.5 * (v.max() + v.min())
            if abs(du) < 1e-4 and abs(dv) < 1e-4:
                break
            target = target + (du * right + dv * cup) * dist
        eye = target + d * dist
        center = target
        return cls(
            eye=tuple(eye), target=tuple(center), up=(0.0, 1.0, 0.0),
            fov_deg=fov_deg, width=int(width), height=int(height),
        )
