"""A browser viewer of a run, on viser (``abmpm view OUT_DIR``, ``abmpm run SCENE --view``).

:class:`Viewer` serves one page (``http://127.0.0.1:8080`` by default) that shows
the particles of one frame as a point cloud, with a timeline slider, play/pause at
an adjustable fps, coloring by material / speed / refinement level, and toggles for
the colliders (``colliders/``), the outline of the refined region (``region.npz``)
and the surface meshes (``surfaces/surface_NNNNN_*.ply``) when the run has them.

Over an output folder it reads the frames from disk as they are shown (a few kept
in memory). In live mode (``live=True``, used by
:class:`abmpm.io.writers.viewer.ViewerWriter`) it starts empty and a running
simulation pushes its frames with :meth:`Viewer.push_frame`; the timeline grows and
follows the newest frame while "follow the run" is checked.

GUI callbacks run on viser's threads and the frames may be pushed from the
simulation's thread: the state below is guarded by one lock. Playing is a thread
that sleeps between frames.
"""

from __future__ import annotations

import contextlib
import io
import os
import socket
import threading
from collections import OrderedDict
from pathlib import Path

import numpy as np

from abmpm.errors import AbmpmError, OutputError
from abmpm.io.outdir import (
    COLLIDER_RE,
    COLLIDERS_DIR,
    FRAME_RE,
    FRAMES_DIR,
    REGION_FILE,
    numbered,
    scene_from_folder,
)
from abmpm.io.ply import read_mesh_ply, read_particles_ply
from abmpm.post.preview import REGION_COLOR, material_densities, particle_colors, speed_vmax, splat_radius
from abmpm.post.render import region_outline
from abmpm.post.surface import surfaces_of_folder
from abmpm.scene.model import Scene

__all__ = [
    "COLOR_MODES",
    "DEFAULT_HOST",
    "DEFAULT_PORT",
    "Viewer",
    "frame_colors",
    "need_viser",
    "point_size",
    "region_segments",
]

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 8080
COLOR_MODES = ("material", "speed", "level")
COLLIDER_COLOR = (150, 150, 165)
SURFACE_COLOR = (120, 180, 235)
DOMAIN_COLOR = (170, 170, 170)
_CACHED_FRAMES = 8  # frames read from disk kept in memory
_VMAX_FRAMES = 12  # frames sampled for the top of the speed scale


def need_viser(what: str = "abmpm view"):
    """The viser module, or an AbmpmError that says how to install it."""
    try:
        import viser
    except ImportError:
        raise AbmpmError(f"{what} needs viser: pip install 'abmpm[view]'") from None
    return viser


def frame_colors(frame: dict, scene: Scene, mode: str, vmax: float | None = None) -> np.ndarray:
    """(N, 3) float32 colors of a frame's particles by ``mode`` (one of
    :data:`COLOR_MODES`), as the preview colors them."""
    if mode not in COLOR_MODES:
        raise ValueError(f"color mode must be one of {COLOR_MODES}, got {mode!r}")
    if len(frame["x"]) == 0:
        return np.zeros((0, 3), dtype=np.float32)
    as_asked = scene.model_copy(update={"output": scene.output.model_copy(update={"color_by": mode})})
    return particle_colors(frame, as_asked, vmax)


def point_size(frame: dict, scene: Scene) -> float:
    """Diameter (world units) of the points: twice the preview's median splat radius
    (a bit more than the particle spacing)."""
    if len(frame["x"]) == 0:
        return scene.simulation.dx * 0.5
    return float(2.0 * np.median(splat_radius(frame, material_densities(scene))))


def region_segments(cells: np.ndarray, origin, dx: float) -> np.ndarray:
    """(K, 2, 3) float32 line segments outlining the refined coarse cells."""
    return np.asarray(region_outline(cells, origin, float(dx)), dtype=np.float32)


def _box_segments(lo, hi) -> np.ndarray:
    """The 12 edges of an axis-aligned box, (12, 2, 3) float32."""
    lo, hi = np.asarray(lo, dtype=np.float32), np.asarray(hi, dtype=np.float32)
    corners = np.array([[(hi if (i >> k) & 1 else lo)[k] for k in range(3)] for i in range(8)], dtype=np.float32)
    edges = [(i, i | (1 << k)) for i in range(8) for k in range(3) if not (i >> k) & 1]
    return np.stack([corners[[a, b]] for a, b in edges])


def _quiet():
    """viser prints a banner on start and a line on stop: keep them off the terminal."""
    return contextlib.redirect_stdout(io.StringIO())


def _check_host(host: str) -> None:
    """OutputError unless this machine can serve on ``host`` (a name it resolves to one
    of its own addresses)."""
    try:
        family, kind, proto, _, address = socket.getaddrinfo(host, 0, type=socket.SOCK_STREAM)[0]
        with socket.socket(family, kind, proto) as probe:
            probe.bind(address)
    except OSError as exc:
        raise OutputError(f"cannot serve the viewer on host {host!r}: {exc.strerror or exc}") from None


class Viewer:
    """A viser server showing the frames of an output folder (``out_dir``) or, with
    ``live=True``, the frames a running simulation of ``scene`` pushes to it.

    ``port`` is the first port tried (viser takes the next free one; 0: any free
    port); :attr:`url` is where it is served. Raises :class:`OutputError` for a
    folder that does not exist or has no particle frames, :class:`AbmpmError` when
    viser is not installed. Call :meth:`close` to stop it.
    """

    def __init__(
        self,
        out_dir: str | os.PathLike | None = None,
        *,
        scene: Scene | None = None,
        live: bool = False,
        host: str = DEFAULT_HOST,
        port: int = DEFAULT_PORT,
    ):
        viser = need_viser("abmpm run --view" if live else "abmpm view")
        _check_host(host)  # viser retries an address it cannot bind forever, silently
        self.live = live
        self.out = Path(out_dir) if out_dir is not None else None
        self._lock = threading.RLock()
        self._frames: dict[int, Path | dict] = {}  # frame -> PLY path or arrays
        self._colliders: dict[int, Path | np.ndarray] = {}  # frame -> PLY path or vertices
        self._collider_faces: np.ndarray | None = None
        self._surfaces: dict[int, list[tuple[str, Path]]] = {}
        self._region: np.ndarray | None = None  # (K, 2, 3) segments
        self._cache: OrderedDict[int, dict] = OrderedDict()
        self._vmax: float | None = None
        self._size: float | None = None
        if live:
            if scene is None:
                raise ValueError("a live viewer needs the scene")
            self.scene = scene
        else:
            self._scan_folder()
        self.numbers: list[int] = sorted(self._frames)
        self.frame: int | None = None  # frame shown
        self.note = "running" if live else ""  # shown after the scene's name

        self._drawn_colliders: np.ndarray | None = None  # collider vertices drawn
        self._surface_handles: list = []
        self.points = self.colliders = self.region = None  # scene handles
        with _quiet():
            self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.url = f"http://{host}:{self.server.get_port()}"
        self._setup_scene()
        self._viser = viser
        self._setup_gui()
        self._playing = threading.Event()
        self._closed = threading.Event()
        self._player = threading.Thread(target=self._play_loop, name="abmpm-viewer-play", daemon=True)
        self._player.start()
        if self.numbers:
            self._show_index(0)

    # ------------------------------------------------------------------ data

    def _scan_folder(self) -> None:
        out = self.out
        if not out.is_dir():
            raise OutputError(f"{out}: not an output folder" if out.exists() else f"{out}: no such output folder")
        frames = numbered(out / FRAMES_DIR, FRAME_RE)
        if not frames:
            raise OutputError(f"{out}: no particle frames in {out / FRAMES_DIR} to view")
        self.scene = scene_from_folder(out)
        self._frames = dict(frames)
        self._colliders = dict(numbered(out / COLLIDERS_DIR, COLLIDER_RE))
        self._scan_surfaces()
        if (out / REGION_FILE).is_file():
            try:
                with np.load(out / REGION_FILE, allow_pickle=False) as z:
                    self._region = region_segments(z["cells"], z["origin"], float(z["dx"]))
            except (OSError, ValueError, KeyError) as exc:
                raise OutputError(f"cannot read {out / REGION_FILE}: {exc}") from None

    def _scan_surfaces(self) -> None:
        """Find the surface meshes in ``surfaces/`` (any number per frame)."""
        if self.out is not None:
            self._surfaces = {n: list(found.items()) for n, found in surfaces_of_folder(self.out).items()}

    def load(self, frame: int) -> dict:
        """The particle arrays of output frame ``frame`` (``x``, ``v``, ``material``, ...)."""
        with self._lock:
            got = self._frames[frame]
            if isinstance(got, dict):
                return got
            if frame in self._cache:
                self._cache.move_to_end(frame)
                return self._cache[frame]
            f = read_particles_ply(got)
            self._cache[frame] = f
            while len(self._cache) > _CACHED_FRAMES:
                self._cache.popitem(last=False)
            return f

    def collider_mesh(self, frame: int) -> tuple[np.ndarray, np.ndarray] | None:
        """(vertices, faces) of the colliders at ``frame``, or None."""
        with self._lock:
            got = self._colliders.get(frame)
            if got is None:
                return None
            if isinstance(got, Path):
                return read_mesh_ply(got)
            return got, self._collider_faces

    def surface_meshes(self, frame: int) -> list[tuple[str, np.ndarray, np.ndarray]]:
        """[(name, vertices, faces)] of the surface meshes written for ``frame``."""
        return [(name, *read_mesh_ply(p)) for name, p in self._surfaces.get(frame, [])]

    def speed_vmax(self) -> float:
        """Top of the speed color scale: the largest 99th percentile of |v| over (up to
        12 evenly spaced) frames; in live mode, over the frames pushed so far."""
        with self._lock:
            if self._vmax is None:
                picks = self.numbers[:: max(1, -(-len(self.numbers) // _VMAX_FRAMES))]
                self._vmax = speed_vmax([(n, (lambda n=n: self.load(n))) for n in picks])
            return self._vmax

    # ------------------------------------------------------------------ live frames

    def push_frame(
        self, frame: int, arrays: dict, collider_vertices: np.ndarray | None = None, path: Path | None = None
    ) -> None:
        """Add output frame ``frame`` of a running simulation (its particle arrays as
        :attr:`abmpm.io.writers.FrameData.arrays`, and the colliders' vertices); shown
        at once while "follow the run" is checked. With ``path``, the frame's PLY file,
        the arrays are only cached: earlier frames are read back from their files
        when shown again, else every frame is kept in memory."""
        keep = {k: np.array(arrays[k]) for k in ("x", "v", "material", "level", "mass") if k in arrays}
        with self._lock:
            if path is None:
                self._frames[frame] = keep
            else:
                self._frames[frame] = Path(path)
                self._cache[frame] = keep
                while len(self._cache) > _CACHED_FRAMES:
                    self._cache.popitem(last=False)
            if collider_vertices is not None and self._collider_faces is not None:
                v = np.asarray(collider_vertices, dtype=np.float32)
                last = self._colliders.get(self.numbers[-1]) if self.numbers else None
                self._colliders[frame] = last if last is not None and np.array_equal(last, v) else v
            if frame not in self.numbers:
                self.numbers = sorted(self._frames)
            self._scan_surfaces()  # written by the run's surface writer, if any
            self._toggle_surfaces.disabled = not self._surfaces
            if len(keep["x"]):
                top = speed_vmax([(frame, lambda: keep)])
                self._vmax = max(self._vmax or 0.0, top)
            self._slider.max = max(len(self.numbers) - 1, 0)
            if self._follow.value or self.frame is None:
                self._show_index(self.numbers.index(frame))
            self._status.content = self._status_text()

    def set_collider_faces(self, faces: np.ndarray) -> None:
        """Live mode: the colliders' faces (their vertices come with each frame)."""
        with self._lock:
            self._collider_faces = np.asarray(faces, dtype=np.int64)
            self._toggle_colliders.disabled = False

    def set_note(self, note: str) -> None:
        """Live mode: how the run stands ("running", "completed", ...), shown in the page."""
        with self._lock:
            self.note = note
            self._status.content = self._status_text()

    def set_region(self, cells: np.ndarray, origin, dx: float) -> None:
        """Live mode: the refined coarse cells now (as ``region.npz`` holds them)."""
        segs = region_segments(cells, origin, dx)
        with self._lock:
            if self._region is not None and np.array_equal(segs, self._region):
                return
            self._region = segs
            self._toggle_region.disabled = False
            self._draw_region()

    # ------------------------------------------------------------------ scene and GUI

    def _setup_scene(self) -> None:
        st = self.scene.simulation
        lo, hi = np.asarray(st.domain_min, float), np.asarray(st.domain_max, float)
        g = np.asarray(st.gravity, float)
        up = -g / np.linalg.norm(g) if np.linalg.norm(g) > 0 else np.array([0.0, 1.0, 0.0])
        k = int(np.argmax(np.abs(up)))
        axis = np.eye(3)
        center, radius = (lo + hi) / 2, float(np.linalg.norm(hi - lo)) / 2
        # from the front, a little from the side and above, the domain's bounding sphere in view
        look = 1.3 * axis[(k + 1) % 3] + 0.45 * axis[(k + 2) % 3] + 0.5 * up
        eye = center + 1.9 * radius * look / np.linalg.norm(look)
        scene = self.server.scene
        scene.set_up_direction(tuple(float(c) for c in up))
        cam = self.server.initial_camera
        cam.position, cam.look_at, cam.up = eye, center, up
        scene.add_line_segments("/domain", _box_segments(lo, hi), DOMAIN_COLOR, thickness=1.0,
                                thickness_units="screen")

    def _setup_gui(self) -> None:
        gui, viser = self.server.gui, self._viser
        st, n = self.scene.simulation, len(self.numbers)
        self._status = gui.add_markdown(self._status_text())
        self._slider = gui.add_slider("frame", min=0, max=max(n - 1, 0), step=1, initial_value=0)
        self._play = gui.add_button("Play", icon=viser.Icon.PLAYER_PLAY)
        fps = st.fps / self.scene.output.frame_every
        self._fps = gui.add_number("fps", initial_value=round(float(fps), 2), min=0.5, max=120.0, step=0.5)
        if self.live:
            self._follow = gui.add_checkbox("follow the run", True, hint="show each new frame as it comes")
        mode = self.scene.output.color_by
        if mode == "auto":
            mode = "level" if st.refinement.mode == "adaptive" else "material"
        self._color = gui.add_dropdown("color by", COLOR_MODES, initial_value=mode)
        self._scale = gui.add_slider("point size", min=0.25, max=4.0, step=0.05, initial_value=1.0)
        self._toggle_colliders = gui.add_checkbox("colliders", True, disabled=not self._colliders)
        self._toggle_region = gui.add_checkbox("refined region", True, disabled=self._region is None)
        self._toggle_surfaces = gui.add_checkbox("surfaces", True, disabled=not self._surfaces)

        self._slider.on_update(lambda _: self._show_index(int(self._slider.value)))
        self._play.on_click(lambda _: self.play(not self._playing.is_set()))
        self._color.on_update(lambda _: self._redraw())
        self._scale.on_update(lambda _: self._redraw())
        self._toggle_colliders.on_update(lambda _: self._redraw())
        self._toggle_surfaces.on_update(lambda _: self._redraw())
        self._toggle_region.on_update(lambda _: self._draw_region())
        self._draw_region()

    def _status_text(self) -> str:
        sc = self.scene
        head = f"**{sc.name}**" + (f" ({self.note})" if self.note else "")
        if self.frame is None:
            return f"{head}  \nwaiting for the first frame"
        t = self.frame / sc.simulation.fps
        count = len(self.load(self.frame)["x"])
        return f"{head}  \nframe {self.frame} of {self.numbers[-1]}, t = {t:.3f} s  \n{count:,} particles"

    # ------------------------------------------------------------------ drawing

    @property
    def color_mode(self) -> str:
        return str(self._color.value)

    @color_mode.setter
    def color_mode(self, mode: str) -> None:
        if mode not in COLOR_MODES:
            raise ValueError(f"color mode must be one of {COLOR_MODES}, got {mode!r}")
        self._color.value = mode  # redraws

    def show(self, frame: int) -> None:
        """Show output frame ``frame`` (moves the timeline slider)."""
        with self._lock:
            self._show_index(self.numbers.index(frame))

    def _show_index(self, index: int) -> None:
        with self._lock:
            if not self.numbers:
                return
            index = min(max(int(index), 0), len(self.numbers) - 1)
            if int(self._slider.value) != index:
                self._slider.value = index  # calls back here with the same index
                return
            self.frame = self.numbers[index]
            self._redraw()
            self._status.content = self._status_text()

    def _redraw(self) -> None:
        """Draw the particles, colliders and surfaces of the current frame."""
        with self._lock:
            if self.frame is None:
                return
            f = self.load(self.frame)
            if self._size is None and len(f["x"]):
                self._size = point_size(f, self.scene)
            mode = self.color_mode
            vmax = self.speed_vmax() if mode == "speed" else None
            with self.server.atomic():
                self.points = self.server.scene.add_point_cloud(
                    "/particles",
                    np.asarray(f["x"], dtype=np.float32),
                    frame_colors(f, self.scene, mode, vmax),
                    point_size=(self._size or self.scene.simulation.dx * 0.5) * float(self._scale.value),
                    point_shape="circle",
                    precision="float32",
                )
                self._draw_colliders()
                self._draw_surfaces()

    def _draw_colliders(self) -> None:
        mesh = self.collider_mesh(self.frame) if self._toggle_colliders.value else None
        if mesh is None:
            if self.colliders is not None:
                self.colliders.remove()
                self.colliders, self._drawn_colliders = None, None
            return
        v, faces = mesh
        if self._drawn_colliders is not None and np.array_equal(self._drawn_colliders, v):
            return  # not moved
        self.colliders = self.server.scene.add_mesh_simple(
            "/colliders", np.asarray(v, dtype=np.float32), np.asarray(faces, dtype=np.uint32),
            color=COLLIDER_COLOR, opacity=0.35, side="double", cast_shadow=False, receive_shadow=False,
        )
        self._drawn_colliders = np.array(v)

    def _draw_surfaces(self) -> None:
        for h in self._surface_handles:
            h.remove()
        self._surface_handles = []
        if not self._toggle_surfaces.value:
            return
        for name, v, faces in self.surface_meshes(self.frame):
            self._surface_handles.append(self.server.scene.add_mesh_simple(
                f"/surfaces/{name}", np.asarray(v, dtype=np.float32), np.asarray(faces, dtype=np.uint32),
                color=SURFACE_COLOR, opacity=0.6, side="double", cast_shadow=False, receive_shadow=False,
            ))

    def _draw_region(self) -> None:
        with self._lock:
            if self.region is not None:
                self.region.remove()
                self.region = None
            if self._region is None or not len(self._region) or not self._toggle_region.value:
                return
            color = tuple(int(round(255 * c)) for c in REGION_COLOR)
            self.region = self.server.scene.add_line_segments(
                "/region", self._region, color, thickness=2.0, thickness_units="screen"
            )

    # ------------------------------------------------------------------ playing and serving

    def play(self, on: bool = True) -> None:
        """Start (or stop) stepping through the frames at the GUI's fps."""
        if on:
            self._playing.set()
        else:
            self._playing.clear()
        self._play.label = "Pause" if on else "Play"
        self._play.icon = self._viser.Icon.PLAYER_PAUSE if on else self._viser.Icon.PLAYER_PLAY

    @property
    def playing(self) -> bool:
        return self._playing.is_set()

    def _play_loop(self) -> None:
        while True:
            self._playing.wait()
            with self._lock:
                if self._closed.is_set():
                    return
                if self._playing.is_set() and self.numbers:  # not paused meanwhile
                    self._show_index((int(self._slider.value) + 1) % len(self.numbers))
            self._closed.wait(1.0 / max(float(self._fps.value), 0.5))

    def wait(self, timeout: float | None = None) -> bool:
        """Serve until the viewer is closed, Ctrl-C (KeyboardInterrupt propagates) or
        ``timeout`` seconds; True when closed."""
        return self._closed.wait(timeout)

    def close(self) -> None:
        """Stop playing and stop the server."""
        with self._lock:  # not while a frame is being drawn
            if self._closed.is_set():
                return
            self._closed.set()
            self._playing.set()  # wakes the play thread, which sees the viewer closed
        with _quiet():
            self.server.stop()
        self._player.join(timeout=2.0)

    def __enter__(self) -> Viewer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
