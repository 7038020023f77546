"""The beauty pass of a run: ``beauty.mp4`` and ``beauty.png``, path-traced with Mitsuba 3.

Renders the surface meshes of a run (``surfaces/``, made by ``[output] surface`` or
``abmpm surface``; meshed here first when they are missing and splashsurf is
installed) and its colliders (``colliders/``) with the scene of
:mod:`abmpm.post.beauty_scene`, from the preview's camera. Mitsuba's variant is
chosen at run time: ``cuda_ad_rgb`` where a CUDA GPU answers, else ``scalar_rgb``
(the CPU; ``llvm_ad_rgb`` can be asked for with ``variant``). Path tracing is slow
on a CPU: the defaults (640 x 360, 16 samples per pixel) take a few seconds a
frame on 2 cores (docs/benchmarks.md).
"""

from __future__ import annotations

import contextlib
import importlib.util
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from abmpm.errors import OutputError
from abmpm.io.looks import collider_look, material_look
from abmpm.io.outdir import (
    BEAUTY_FILE,
    BEAUTY_POSTER_FILE,
    COLLIDER_RE,
    COLLIDERS_DIR,
    FRAME_RE,
    FRAMES_DIR,
    SURFACES_DIR,
    numbered,
    scene_from_folder,
)
from abmpm.io.ply import read_particles_ply
from abmpm.io.progress import Progress
from abmpm.post.beauty_scene import frame_scene
from abmpm.post.camera import Camera
from abmpm.post.preview import internal_kinetic_energy
from abmpm.post.surface import file_stem, surfaces_of_folder
from abmpm.post.video import write_mp4, write_png
from abmpm.scene.model import Scene

__all__ = ["CPU_VARIANT", "GPU_VARIANT", "INSTALL_HINT", "BeautySettings", "import_mitsuba", "render_beauty",
           "render_frame", "render_run_frame"]

GPU_VARIANT = "cuda_ad_rgb"
CPU_VARIANT = "scalar_rgb"
INSTALL_HINT = 'the beauty render needs Mitsuba 3: pip install -e ".[render]"'


@dataclass(frozen=True)
class BeautySettings:
    """How the beauty pass renders: image size, samples per pixel, every ``stride``-th
    surface frame, Mitsuba variant (None: automatic), the colliders' look (None: the
    scene's ``output.beauty_colliders``) and CPU threads (None: Mitsuba's default,
    every core, or ``$ABMPM_THREADS``)."""

    width: int = 640
    height: int = 360
    spp: int = 16
    stride: int = 1
    variant: str | None = None
    colliders: str | None = None
    threads: int | None = None


def import_mitsuba(variant: str | None = None, threads: int | None = None):
    """Mitsuba with a variant set (``variant``, else the GPU one if it works, else
    the CPU one); OutputError with the install hint when it is missing."""
    try:
        import drjit as dr
        import mitsuba as mi
    except ImportError:
        raise OutputError(INSTALL_HINT) from None
    mi.set_log_level(mi.LogLevel.Error)  # not "computed vertex normals" per frame
    threads = threads or int(os.environ.get("ABMPM_THREADS") or 0) or None
    if threads:
        dr.set_thread_count(int(threads))
    if variant is not None:
        if variant not in mi.variants():
            raise OutputError(f"Mitsuba has no variant {variant!r} (it has: {', '.join(mi.variants())})")
        _set_variant(mi, variant)
        return mi
    try:
        _set_variant(mi, GPU_VARIANT)
    except OutputError:
        _set_variant(mi, CPU_VARIANT)
    return mi


def _set_variant(mi, variant: str) -> None:
    try:
        mi.set_variant(variant)
    except (ImportError, RuntimeError, AttributeError) as exc:  # no GPU, no LLVM, ...
        raise OutputError(f"Mitsuba variant {variant} does not work here: {exc}") from None


def render_frame(mi, scene_dict: dict) -> np.ndarray:
    """Render a scene dictionary to an sRGB ``uint8 (H, W, 3)`` image."""
    image = mi.render(mi.load_dict(scene_dict))
    bitmap = mi.util.convert_to_bitmap(image)  # sRGB, 8 bit
    return np.array(bitmap, copy=True)[..., :3]


def _looks(scene: Scene) -> dict[str, str]:
    """{surface file stem: look} of the scene's materials."""
    return {file_stem(m.name): material_look(m.model_dump()) for m in scene.materials}


def _surface_frames(out: Path, on_missing: Callable[[], None] | None) -> dict[int, dict[str, Path]]:
    found = surfaces_of_folder(out)
    if found or on_missing is None:
        return found
    on_missing()
    return surfaces_of_folder(out)


def mesh_missing_surfaces(out: Path, mesh: Callable[[Path], object], bar: Progress | None = None) -> None:
    """Mesh a run's frames with ``mesh`` (``abmpm surface``) when it has none;
    OutputError naming what to run when splashsurf is not installed."""
    if not numbered(out / FRAMES_DIR, FRAME_RE):
        raise OutputError(f"{out}: no surface meshes in {out / SURFACES_DIR} and no particle frames to mesh "
                          f"(the run had output.frames = false); run it again with [output] surface = true")
    if importlib.util.find_spec("pysplashsurf") is None:
        raise OutputError(f"{out}: no surface meshes in {out / SURFACES_DIR}; the beauty pass renders them: "
                          f"pip install -e \".[surface]\", then run: abmpm surface {out}")
    if bar is not None:
        bar.print(f"no surface meshes in {out / SURFACES_DIR}: meshing them first (abmpm surface)")
    mesh(out)


def _poster(out: Path, frames: list[int]) -> int:
    """The frame with the most motion relative to the centre of mass (as the preview
    picks its poster), among ``frames``; the last one without particle frames."""
    paths = dict(numbered(out / FRAMES_DIR, FRAME_RE))
    best, best_ke = frames[-1], -1.0
    for n in frames:
        if n in paths:
            ke = internal_kinetic_energy(read_particles_ply(paths[n]))
            if ke > best_ke:
                best, best_ke = n, ke
    return best


def _frame_renderer(mi, out: Path, scene: Scene, settings: BeautySettings) -> Callable[[int, dict], np.ndarray]:
    """A function rendering frame ``n`` of the run ``out`` from its surface meshes
    {material: PLY path} and its collider, with the beauty pass's camera, looks and
    lighting: an sRGB ``uint8 (H, W, 3)`` image."""
    colliders = dict(numbered(out / COLLIDERS_DIR, COLLIDER_RE))
    st = scene.simulation
    camera = Camera.framing_box(st.domain_min, st.domain_max, settings.width, settings.height)
    looks = _looks(scene)
    c_look = collider_look(scene.output.model_dump(), settings.colliders)

    def render(n: int, surfaces: dict[str, Path]) -> np.ndarray:
        meshes = {m: p for m, p in surfaces.items() if m in looks}  # not a leftover of another scene
        d = frame_scene(mi, camera, (st.domain_min, st.domain_max), meshes, looks, colliders.get(n), c_look,
                        settings.spp)
        return render_frame(mi, d)

    return render


def render_run_frame(out_dir: str | os.PathLike, frame: int, settings: BeautySettings = BeautySettings()) -> np.ndarray:
    """One frame of a run folder as the beauty pass renders it (same camera, looks,
    lighting and settings), from that frame's surface meshes, which must be there
    (``surfaces/surface_NNNNN_<material>.ply``: ``abmpm surface``, or
    :func:`abmpm.post.surface.write_surfaces` for that frame alone). Returns an sRGB
    ``uint8 (H, W, 3)`` image; OutputError when the frame has no surface mesh."""
    out = Path(out_dir)
    scene = scene_from_folder(out)
    surfaces = surfaces_of_folder(out).get(frame)
    if not surfaces:
        raise OutputError(f"{out}: no surface meshes of frame {frame} in {out / SURFACES_DIR}; "
                          f"run: abmpm surface {out}")
    mi = import_mitsuba(settings.variant, settings.threads)
    return _frame_renderer(mi, out, scene, settings)(frame, surfaces)


def render_beauty(
    out_dir: str | os.PathLike, settings: BeautySettings = BeautySettings(), progress: bool = False,
    bar: Progress | None = None, mesh: Callable[[Path], object] | None = None,
) -> dict:
    """Path-trace ``beauty.mp4`` and ``beauty.png`` of a finished run. ``bar`` is the
    run's progress bar (else one is made when ``progress``); ``mesh`` (the writers'
    ``surface_folder``) meshes the frames first when the run has no surface meshes.
    Returns the files, the frames rendered, the variant, the poster frame and the
    seconds per frame."""
    out = Path(out_dir)
    if not out.is_dir():
        raise OutputError(f"{out}: not an output folder" if out.exists() else f"{out}: no such output folder")
    scene = scene_from_folder(out)
    mi = import_mitsuba(settings.variant, settings.threads)
    with contextlib.nullcontext(bar) if bar is not None else Progress(progress) as own:
        surfaces = _surface_frames(out, (lambda: mesh_missing_surfaces(out, mesh, own)) if mesh else None)
        if not surfaces:
            raise OutputError(f"{out}: no surface meshes in {out / SURFACES_DIR}; run: abmpm surface {out}")
        frames = sorted(surfaces)[:: settings.stride]
        render = _frame_renderer(mi, out, scene, settings)
        poster = _poster(out, frames)
        kept = {}
        own.start_render(len(frames), "rendering beauty")
        t0 = time.perf_counter()

        def images():
            for n in frames:
                img = render(n, surfaces[n])
                if n == poster:
                    kept["poster"] = img
                own.advance_render()
                yield img

        fps = scene.simulation.fps / scene.output.frame_every / settings.stride
        count = write_mp4(out / BEAUTY_FILE, images(), fps=fps)
        seconds = time.perf_counter() - t0
    write_png(out / BEAUTY_POSTER_FILE, kept["poster"])
    return {"beauty": str(out / BEAUTY_FILE), "poster": str(out / BEAUTY_POSTER_FILE), "frames": count,
            "poster_frame": poster, "variant": mi.variant(), "seconds_per_frame": round(seconds / count, 3),
            "size": f"{settings.width}x{settings.height}", "spp": settings.spp}
