"""USD export of a run (usd-core): one stage, y up, metres, one time code per frame.

``/World/particles``
    ``UsdGeom.Points``: time-sampled positions, widths (diameters), velocities (m/s),
    ids (stable particle ids) and a per-vertex ``displayColor`` primvar.
``/World/colliders``
    ``UsdGeom.Mesh`` of all the colliders: the topology once, the points time-sampled.
``/World/surfaces/<material>``
    ``UsdGeom.Mesh`` per material surface: points and topology time-sampled (a
    reconstructed surface changes its triangles from frame to frame; a frame without
    a surface holds an empty mesh).

Each time-sampled ``points`` comes with its ``extent``, as the USD schema asks.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from abmpm.errors import OutputError
from abmpm.io.atomic import atomic_write

__all__ = ["UsdPointsWriter", "UsdStageWriter", "check_compliance"]

_MISSING = "USD export needs usd-core: pip install 'abmpm[usd]'"


def _import_pxr():
    try:
        from pxr import Tf, Usd, UsdGeom, Vt
    except ImportError as exc:
        raise OutputError(_MISSING) from exc
    return Usd, UsdGeom, Vt, Tf


def _vec3(a) -> np.ndarray:
    return np.ascontiguousarray(np.asarray(a, dtype=np.float32).reshape(-1, 3))


class UsdStageWriter:
    """Accumulate the frames of a run and write them to one USD stage.

    ``add_frame(time_code, x, widths, colors=None, velocities=None, ids=None)`` adds the
    particles' samples; ``add_mesh(name, time_code, vertices, faces)`` a mesh's;
    ``close()`` saves the stage atomically.
    """

    def __init__(self, path: str | os.PathLike, fps: float, prim_path: str = "/World/particles"):
        self.path = Path(path)
        self.fps = float(fps)
        Usd, UsdGeom, Vt, Tf = _import_pxr()
        self._UsdGeom, self._Vt, self._Tf = UsdGeom, Vt, Tf
        self._stage = Usd.Stage.CreateInMemory()
        UsdGeom.SetStageUpAxis(self._stage, UsdGeom.Tokens.y)
        UsdGeom.SetStageMetersPerUnit(self._stage, 1.0)
        self._stage.SetTimeCodesPerSecond(self.fps)
        self._stage.SetFramesPerSecond(self.fps)
        world = UsdGeom.Xform.Define(self._stage, "/World")
        self._stage.SetDefaultPrim(world.GetPrim())
        self._points = UsdGeom.Points.Define(self._stage, prim_path)
        self._color = None
        self._meshes: dict[str, tuple] = {}  # prim path -> (mesh, last faces)
        self._times: list[float] = []
        self._closed = False

    def _time(self, time_code: float) -> float:
        if self._closed:
            raise OutputError(f"{self.path}: USD writer already closed")
        t = float(time_code)
        self._times.append(t)
        return t

    def add_frame(
        self,
        time_code: float,
        x: np.ndarray,
        widths: float | np.ndarray,
        colors: np.ndarray | None = None,
        velocities: np.ndarray | None = None,
        ids: np.ndarray | None = None,
    ) -> None:
        """Add a time sample of positions (N,3), widths (scalar or (N,)) and optional
        RGB colors (N,3; 0-1 or 0-255), velocities (N,3) and ids (N,)."""
        Vt, pts = self._Vt, self._points
        t = self._time(time_code)
        x = _vec3(x)
        w = np.asarray(widths, dtype=np.float32)
        if w.ndim == 0:
            w = np.full(len(x), float(w), dtype=np.float32)
        w = np.ascontiguousarray(w)
        pts.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(x), t)
        pts.GetWidthsAttr().Set(Vt.FloatArray.FromNumpy(w), t)
        pts.GetExtentAttr().Set(self._UsdGeom.Points.ComputeExtent(Vt.Vec3fArray.FromNumpy(x), Vt.FloatArray.FromNumpy(w)), t)
        if velocities is not None:
            pts.GetVelocitiesAttr().Set(Vt.Vec3fArray.FromNumpy(_vec3(velocities)), t)
        if ids is not None:
            pts.GetIdsAttr().Set(Vt.Int64Array.FromNumpy(np.ascontiguousarray(ids, dtype=np.int64)), t)
        if colors is not None:
            c0 = np.asarray(colors)
            c = c0.astype(np.float32)
            if c0.dtype == np.uint8 or c.max(initial=0.0) > 1.0:
                c = c / 255.0
            if self._color is None:
                self._color = pts.CreateDisplayColorPrimvar(self._UsdGeom.Tokens.vertex)
            self._color.Set(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(c.reshape(-1, 3)[:, :3])), t)

    def add_mesh(self, prim_path: str, time_code: float, vertices: np.ndarray, faces: np.ndarray,
                 color: tuple[float, float, float] | None = None) -> None:
        """Add a time sample of a triangle mesh at ``prim_path`` (``/World/<name>`` or
        deeper; each part is made a valid identifier). The topology is written again
        only at the times it changes."""
        Vt, UsdGeom = self._Vt, self._UsdGeom
        t = self._time(time_code)
        prim_path = "/" + "/".join(self._Tf.MakeValidIdentifier(p) for p in prim_path.strip("/").split("/"))
        v = _vec3(vertices)
        f = np.ascontiguousarray(np.asarray(faces, dtype=np.int32).reshape(-1, 3))
        if prim_path not in self._meshes:
            mesh = UsdGeom.Mesh.Define(self._stage, prim_path)
            mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)  # triangles as they are
            if color is not None:
                mesh.CreateDisplayColorPrimvar(UsdGeom.Tokens.constant).Set(Vt.Vec3fArray([tuple(map(float, color))]))
            self._meshes[prim_path] = (mesh, None)
        mesh, last = self._meshes[prim_path]
        points = Vt.Vec3fArray.FromNumpy(v)
        mesh.GetPointsAttr().Set(points, t)
        mesh.GetExtentAttr().Set(UsdGeom.PointBased.ComputeExtent(points), t)
        if last is None or not np.array_equal(last, f):
            mesh.GetFaceVertexCountsAttr().Set(Vt.IntArray.FromNumpy(np.full(len(f), 3, dtype=np.int32)), t)
            mesh.GetFaceVertexIndicesAttr().Set(Vt.IntArray.FromNumpy(f.reshape(-1)), t)
            self._meshes[prim_path] = (mesh, f)

    def close(self) -> None:
        """Write the stage to ``path`` (atomic). Idempotent."""
        if self._closed:
            return
        if self._times:
            self._stage.SetStartTimeCode(min(self._times))
            self._stage.SetEndTimeCode(max(self._times))
        with atomic_write(self.path) as tmp:
            if not self._stage.Export(str(tmp)):
                raise OutputError(f"cannot write USD file {self.path}")
        self._closed = True

    def __enter__(self) -> "UsdStageWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()


UsdPointsWriter = UsdStageWriter  # the name of earlier versions


def check_compliance(path: str | os.PathLike) -> list[str]:
    """What USD's own checkers find wrong with the file at ``path`` (an empty list: it
    passes): ``UsdUtils.ComplianceChecker`` where usd-core has it (up to 25.8) and the
    errors of every registered ``UsdValidation`` validator, its successor (25.2 on)."""
    _import_pxr()
    from pxr import Usd, UsdUtils

    found = []
    if hasattr(UsdUtils, "ComplianceChecker"):
        checker = UsdUtils.ComplianceChecker()
        checker.CheckCompliance(str(path))
        found += [f"ComplianceChecker: {e}" for e in list(checker.GetErrors()) + list(checker.GetFailedChecks())]
    try:
        from pxr import UsdValidation
    except ImportError:  # usd-core before 25.2
        return found
    stage = Usd.Stage.Open(str(path))
    validators = UsdValidation.ValidationRegistry().GetOrLoadAllValidators()
    for e in UsdValidation.ValidationContext(validators).Validate(stage):
        if e.GetType() == UsdValidation.ValidationErrorType.Error:
            found.append(f"{e.GetName()}: {e.GetMessage()}")
    return found
