"""Rigid motion of a collider over time: constant velocities or interpolated keyframes.

The solver asks a motion for its :class:`Pose` at a time; it never sees the scene's
motion description.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from .transforms import euler_matrix


@dataclass
class Pose:
    rotation: np.ndarray  # (3,3) applied about the pivot's rest position
    offset: np.ndarray  # x = R x_rest + offset
    pivot: np.ndarray  # current pivot position
    velocity: np.ndarray  # of the pivot, m/s
    omega: np.ndarray  # angular velocity, rad/s


class KinematicMotion:
    """Pose of one collider at time t, from a scene ``Motion`` (velocities or keyframes)."""

    def __init__(self, motion, default_pivot):
        self.pivot0 = np.asarray(motion.pivot if motion.pivot is not None else default_pivot, dtype=np.float64)
        self.v = np.asarray(motion.velocity, dtype=np.float64)
        self.w = np.asarray(motion.angular_velocity, dtype=np.float64)
        self.keys = motion.keyframes
        self.static = motion.is_static
        if self.keys:
            self.times = np.array([k.time for k in self.keys])
            self.trans = np.array([k.translation for k in self.keys], dtype=np.float64)
            rots = Rotation.from_matrix(np.stack([euler_matrix(k.rotation) for k in self.keys]))
            self.slerp = Slerp(self.times, rots) if len(self.keys) > 1 else None
            self.rot0 = rots[0]

    def _keyframe(self, t):
        t = float(np.clip(t, self.times[0], self.times[-1]))
        trans = np.array([np.interp(t, self.times, self.trans[:, a]) for a in range(3)])
        rot = self.slerp([t])[0] if self.slerp is not None else self.rot0
        return rot, trans

    def pose(self, t: float) -> Pose:
        if self.keys:
            rot, trans = self._keyframe(t)
            # velocities of the current keyframe segment (zero outside the keyed range)
            h = 1e-4
            rot2, trans2 = self._keyframe(t + h)
            vel = (trans2 - trans) / h
            omega = (rot2 * rot.inv()).as_rotvec() / h
        else:
            rot = Rotation.from_rotvec(self.w * t)
            trans, vel, omega = self.v * t, self.v, self.w
        R = rot.as_matrix()
        pivot = self.pivot0 + trans
        return Pose(rotation=R, offset=pivot - R @ self.pivot0, pivot=pivot, velocity=vel, omega=omega)
