"""Rotations from the scene's Euler angles.

Every rotated body in a scene (ellipsoid, mesh, bunny) takes ``rotation = (rx, ry, rz)``
in degrees. One function turns those angles into a matrix so that all shapes, the
sampler and the preview agree on the same convention.
"""

from __future__ import annotations

import numpy as np


def _axis_rotation(axis: int, radians: float) -> np.ndarray:
    """Right-handed rotation by ``radians`` about coordinate axis 0, 1 or 2."""
    c, s = np.cos(radians), np.sin(radians)
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    r = np.eye(3)
    r[i, i], r[i, j], r[j, i], r[j, j] = c, -s, s, c
    return r


def euler_matrix(degrees_xyz) -> np.ndarray:
    """Rotation matrix (3, 3, float64) for intrinsic X-Y-Z Euler angles in degrees.

    Convention: rotate the body first about its own x axis by ``rx``, then about its
    (already rotated) y axis by ``ry``, then about its z axis by ``rz``. Intrinsic
    rotations compose to the right, so ``R = Rx(rx) @ Ry(ry) @ Rz(rz)``; this equals
    ``scipy.spatial.transform.Rotation.from_euler("XYZ", angles, degrees=True)``
    and, read the other way, extrinsic (world-axis) rotations about z, then y, then x.

    A point given in the body frame maps to the world as ``world = center + R @ local``.
    """
    a = np.radians(np.asarray(degrees_xyz, dtype=np.float64).reshape(3))
    return _axis_rotation(0, a[0]) @ _axis_rotation(1, a[1]) @ _axis_rotation(2, a[2])
