"""USD export of particles as a time-sampled ``UsdGeom.Points`` prim (usd-core)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from abmpm.errors import OutputError
from abmpm.io.atomic import atomic_write

_MISSING = "USD export needs usd-core: pip install 'abmpm[usd]'"


def _import_pxr():
    try:
        from pxr import Gf, Sdf, Usd, UsdGeom, Vt  # noqa: F401
    except ImportError as exc:
        raise OutputError(_MISSING) from exc
    return Usd, UsdGeom, Vt, Sdf


class UsdPointsWriter:
    """Accumulate particle frames and write them to one USD stage.

    ``add_frame(time_code, x, widths, colors=None)`` adds time samples;
    ``close()`` saves the stage atomically. The prim is ``/World/particles``, y-up,
    metres. ``widths`` is a scalar or an (N,) array of diameters.
    """

    def __init__(self, path: str | os.PathLike, fps: float, prim_path: str = "/World/particles"):
        self.path = Path(path)
        self.fps = float(fps)
        Usd, UsdGeom, Vt, Sdf = _import_pxr()
        self._Usd, self._UsdGeom, self._Vt, self._Sdf = Usd, UsdGeom, Vt, Sdf
        self._stage = Usd.Stage.CreateInMemory()
        UsdGeom.SetStageUpAxis(self._stage, UsdGeom.Tokens.y)
        UsdGeom.SetStageMetersPerUnit(self._stage, 1.0)
        self._stage.SetTimeCodesPerSecond(self.fps)
        self._stage.SetFramesPerSecond(self.fps)
        world = UsdGeom.Xform.Define(self._stage, "/World")
        self._stage.SetDefaultPrim(world.GetPrim())
        self._points = UsdGeom.Points.Define(self._stage, prim_path)
        self._color = None
        self._t0: float | None = None
        self._t1: float | None = None
        self._closed = False

    def add_frame(
        self,
        time_code: float,
        x: np.ndarray,
        widths: float | np.ndarray,
        colors: np.ndarray | None = None,
    ) -> None:
        """Add a time sample of positions (N,3), widths and optional RGB colors (N,3)."""
        if self._closed:
            raise OutputError(f"{self.path}: USD writer already closed")
        Vt = self._Vt
        t = float(time_code)
        x = np.ascontiguousarray(np.asarray(x, dtype=np.float32).reshape(-1, 3))
        n = x.shape[0]
        w = np.asarray(widths, dtype=np.float32)
        if w.ndim == 0:
            w = np.full(n, float(w), dtype=np.float32)
        self._points.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(x), t)
        self._points.GetWidthsAttr().Set(Vt.FloatArray.FromNumpy(np.ascontiguousarray(w)), t)
        if colors is not None:
            c0 = np.asarray(colors)
            c = c0.astype(np.float32)
            if c0.dtype == np.uint8 or c.max(initial=0.0) > 1.0:
                c = c / 255.0
            c = np.ascontiguousarray(c.reshape(-1, 3)[:, :3], dtype=np.float32)
            if self._color is None:
                self._color = self._points.CreateDisplayColorPrimvar(
                    self._UsdGeom.Tokens.vertex
                )
            self._color.Set(Vt.Vec3fArray.FromNumpy(c), t)
        self._t0 = t if self._t0 is None else min(self._t0, t)
        self._t1 = t if self._t1 is None else max(self._t1, t)

    def close(self) -> None:
        """Write the stage to ``path`` (atomic). Idempotent."""
        if self._closed:
            return
        if self._t0 is not None:
            self._stage.SetStartTimeCode(self._t0)
            self._stage.SetEndTimeCode(self._t1)
        with atomic_write(self.path) as tmp:
            if not self._stage.Export(str(tmp)):
                raise OutputError(f"cannot write USD file {self.path}")
        self._closed = True

    def __enter__(self) -> "UsdPointsWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
