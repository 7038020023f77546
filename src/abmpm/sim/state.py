"""Particle state.

All particles of every level live in one set of arrays; ``level`` says which grid a
particle belongs to (0 = original, 1 = subdivided). The solver's step updates a
state in place (``step(state, dt, time)``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

DYNAMIC = ("x", "v", "C", "F", "history", "surface_point", "surface_side", "surface_body")
STATIC = ("mass", "volume", "material", "level", "id", "family")
FIELDS = DYNAMIC + STATIC
DTYPES = {
    "x": wp.vec3,
    "v": wp.vec3,
    "C": wp.mat33,
    "F": wp.mat33,
    "history": float,
    "mass": float,
    "volume": float,
    "material": wp.int32,
    "level": wp.int32,
    "id": wp.int32,
    "surface_point": wp.vec3,
    "surface_side": wp.vec3,
    "surface_body": wp.int32,
    "family": wp.int32,
}


@wp.struct
class ParticleArrays:
    """The particle arrays as one kernel argument (``s.x[p]``, ``s.F[p]``, ...)."""

    x: wp.array(dtype=wp.vec3)
    v: wp.array(dtype=wp.vec3)
    C: wp.array(dtype=wp.mat33)
    F: wp.array(dtype=wp.mat33)
    history: wp.array(dtype=float)
    surface_point: wp.array(dtype=wp.vec3)
    surface_side: wp.array(dtype=wp.vec3)
    surface_body: wp.array(dtype=wp.int32)
    mass: wp.array(dtype=float)
    volume: wp.array(dtype=float)
    material: wp.array(dtype=wp.int32)
    level: wp.array(dtype=wp.int32)
    id: wp.array(dtype=wp.int32)
    family: wp.array(dtype=wp.int32)


@dataclass
class ParticleState:
    x: wp.array  # position, m
    v: wp.array  # velocity, m/s
    C: wp.array  # APIC affine matrix (~ velocity gradient), 1/s
    F: wp.array  # elastic deformation gradient (identity for fluids)
    history: wp.array  # scalar state: fluid volume ratio J; snow J_P; sand volume correction
    # color w.r.t. the nearest collider (CPIC): closest surface point, unit direction
    # from it to the particle, and the collider index (-1 when far from all)
    surface_point: wp.array
    surface_side: wp.array
    surface_body: wp.array
    mass: wp.array  # kg
    volume: wp.array  # initial volume V0, m^3
    material: wp.array  # index into the scene's materials
    level: wp.array  # 0 original, 1 subdivided
    id: wp.array  # stable particle identifier (order changes when particles are sorted)
    family: wp.array  # id of the parent a subdivided particle was split from, else -1
    count: int = 0  # particles in use; the arrays may hold more (capacity)

    def arrays(self) -> ParticleArrays:
        """The arrays as a Warp struct for kernels (rebuilt after the arrays move)."""
        a = self.__dict__.get("_arrays")
        if a is None or a.x.ptr != self.x.ptr or a.x.shape != self.x.shape:
            a = ParticleArrays()
            for name in FIELDS:
                setattr(a, name, getattr(self, name))
            self.__dict__["_arrays"] = a
        return a

    @property
    def capacity(self) -> int:
        return self.x.shape[0]

    @property
    def device(self):
        return self.x.device

    @staticmethod
    def from_numpy(arrays: dict[str, np.ndarray], device, capacity: int = 0) -> "ParticleState":
        n = len(arrays["x"])
        cap = max(n, capacity)
        kw = {}
        for name in FIELDS:
            a = arrays.get(name)
            if a is None:
                a = _default(name, n)
            full = np.zeros((cap,) + a.shape[1:], dtype=a.dtype)
            full[:n] = a
            kw[name] = wp.array(full, dtype=DTYPES[name], device=device)
        return ParticleState(count=n, **kw)

    def numpy(self) -> dict[str, np.ndarray]:
        # wp.array.numpy() on the CPU is a zero-copy view that the next step
        # overwrites; snapshots must be copies on every device.
        out = {}
        for name in FIELDS:
            arr = getattr(self, name)
            a = arr.numpy()[: self.count]
            out[name] = a.copy() if arr.device.is_cpu else a
        return out

    def reserve(self, capacity: int) -> None:
        """Grow every array to hold ``capacity`` particles, keeping the first ``count``."""
        if capacity <= self.capacity:
            return
        cap = max(capacity, int(1.5 * self.capacity))
        for name in FIELDS:
            old = getattr(self, name)
            new = wp.zeros(cap, dtype=old.dtype, device=old.device)
            wp.copy(new, old, count=self.count)
            setattr(self, name, new)


def _default(name: str, n: int) -> np.ndarray:
    if name == "F":
        return np.tile(np.eye(3, dtype=np.float32), (n, 1, 1))
    if name == "history":
        return np.ones(n, dtype=np.float32)
    if name in ("material", "level"):
        return np.zeros(n, dtype=np.int32)
    if name == "id":
        return np.arange(n, dtype=np.int32)
    if name in ("surface_body", "family"):
        return np.full(n, -1, dtype=np.int32)
    if name in ("C",):
        return np.zeros((n, 3, 3), dtype=np.float32)
    return np.zeros((n, 3), dtype=np.float32)


def check_fields(arrays: dict, materials: int, colliders: int, levels: tuple[int, ...] = (0, 1),
                 domain: tuple | None = None) -> None:
    """ValueError naming the field for particle values a step cannot take: not numbers,
    not finite, a mass or volume not above 0, a material or collider index out of range,
    a level outside ``levels`` (the levels this mode has grids for: 0, 1 or both, so their
    range), a position outside ``domain`` (lo, hi). Fields absent from ``arrays`` are not
    checked."""
    for k, a in arrays.items():
        a = np.asarray(a)
        if a.dtype.kind not in "biuf":
            raise ValueError(f"{k}: expected numbers, got an array of {a.dtype}")
        if a.dtype.kind == "f" and not np.isfinite(a).all():
            raise ValueError(f"{k}: {int((~np.isfinite(a.reshape(len(a), -1))).any(axis=1).sum())} particles "
                             "have a NaN or infinite value")
        with np.errstate(over="ignore"):
            beyond = a.dtype.kind == "f" and not np.isfinite(a.astype(np.float32)).all()
        if beyond:
            raise ValueError(f"{k}: a value beyond single precision (~3.4e38)")
        if k in ("material", "level", "surface_body", "id", "family") and (a != np.round(a)).any():
            raise ValueError(f"{k}: expected whole numbers")
    bounds = {"mass": "positive", "volume": "positive", "material": (0, materials - 1),
              "surface_body": (-1, colliders - 1), "level": (min(levels), max(levels))}
    for k, bound in bounds.items():
        if k not in arrays or len(np.asarray(arrays[k])) == 0:
            continue
        a = np.asarray(arrays[k])
        if bound == "positive" and a.min() <= 0:
            raise ValueError(f"{k}: every value must be > 0, got {a.min():g}")
        if bound != "positive" and (a.min() < bound[0] or a.max() > bound[1]):
            raise ValueError(f"{k}: values from {bound[0]} to {bound[1]} here, got {a.min():g} to {a.max():g}")
    if domain is not None and "x" in arrays:
        x = np.asarray(arrays["x"])
        out = ((x < np.asarray(domain[0])) | (x > np.asarray(domain[1]))).any(axis=1)
        if out.any():
            raise ValueError(f"x: {int(out.sum())} particles lie outside the domain")
