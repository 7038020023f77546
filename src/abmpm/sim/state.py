"""Particle state.

All particles of every level live in one set of arrays; ``level`` says which grid a
particle belongs to (0 = original, 1 = subdivided). The solver's step updates a
state in place (``step(state, dt, time)``).
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
import warp as wp

DYNAMIC = ("x", "v", "C", "F", "plastic", "cp", "cn", "cbody")
STATIC = ("mass", "volume", "material", "level", "id")
DTYPES = {
    "x": wp.vec3,
    "v": wp.vec3,
    "C": wp.mat33,
    "F": wp.mat33,
    "plastic": float,
    "mass": float,
    "volume": float,
    "material": wp.int32,
    "level": wp.int32,
    "id": wp.int32,
    "cp": wp.vec3,
    "cn": wp.vec3,
    "cbody": wp.int32,
}


@dataclass
class ParticleState:
    x: wp.array  # position, m
    v: wp.array  # velocity, m/s
    C: wp.array  # APIC affine matrix (~ velocity gradient), 1/s
    F: wp.array  # elastic deformation gradient
    plastic: wp.array  # scalar state: fluid volume ratio J; snow J_P; sand volume correction
    mass: wp.array  # kg
    volume: wp.array  # initial volume V0, m^3
    material: wp.array  # index into the scene's materials
    level: wp.array  # 0 original, 1 subdivided
    id: wp.array  # stable particle identifier (order changes when particles are sorted)
    # colour w.r.t. the nearest collider (CPIC): closest surface point, unit direction
    # from it to the particle, and the collider index (-1 when far from all)
    cp: wp.array
    cn: wp.array
    cbody: wp.array

    @property
    def count(self) -> int:
        return self.x.shape[0]

    @property
    def device(self):
        return self.x.device

    @staticmethod
    def from_numpy(arrays: dict[str, np.ndarray], device) -> "ParticleState":
        n = len(arrays["x"])
        kw = {}
        for f in fields(ParticleState):
            a = arrays.get(f.name)
            if a is None:
                a = _default(f.name, n)
            kw[f.name] = wp.array(np.ascontiguousarray(a), dtype=DTYPES[f.name], device=device)
        return ParticleState(**kw)

    def numpy(self) -> dict[str, np.ndarray]:
        # On the CPU, wp.array.numpy() is a zero-copy view that the next step overwrites
        # (double buffering); snapshots must be copies on every device.
        out = {}
        for f in fields(self):
            arr = getattr(self, f.name)
            a = arr.numpy()
            out[f.name] = a.copy() if arr.device.is_cpu else a
        return out


def _default(name: str, n: int) -> np.ndarray:
    if name == "F":
        return np.tile(np.eye(3, dtype=np.float32), (n, 1, 1))
    if name == "plastic":
        return np.ones(n, dtype=np.float32)
    if name in ("material", "level"):
        return np.zeros(n, dtype=np.int32)
    if name == "id":
        return np.arange(n, dtype=np.int32)
    if name == "cbody":
        return np.full(n, -1, dtype=np.int32)
    if name in ("C",):
        return np.zeros((n, 3, 3), dtype=np.float32)
    return np.zeros((n, 3), dtype=np.float32)
