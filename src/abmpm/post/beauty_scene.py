"""The Mitsuba 3 scene of one beauty frame, as a dictionary for ``mi.load_dict``.

The surface meshes and the colliders of a frame (PLY files, loaded by Mitsuba's own
``ply`` plugin) with BSDFs from the materials' looks (:mod:`abmpm.io.looks`), a
ground plane at the floor of the domain, a studio sky (an environment map: bright
above, grey below the horizon, with a soft key light above the front left), and the
preview's camera (:class:`abmpm.post.camera.Camera`). World y is up, as in the
simulation. Mitsuba itself is imported by the caller (:mod:`abmpm.post.beauty`) and
passed in as ``mi``, so this module imports without it.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np

from abmpm.io.looks import LOOKS
from abmpm.post.camera import Camera

__all__ = ["MAX_DEPTH", "bsdf", "environment", "frame_scene", "sky_image"]

MAX_DEPTH = 12  # bounces: light crosses a dielectric blob at 2 interfaces per pass
SKY_ZENITH = np.array([0.72, 0.82, 1.0])
SKY_HORIZON = np.array([1.0, 1.0, 1.0])
SKY_GROUND = np.array([0.18, 0.18, 0.19])
SKY_SCALE = 0.6
KEY_DIRECTION = np.array([-0.9, 1.6, 1.1])  # towards the key light: above, front (+z), left (-x)
KEY_RADIANCE = 6.0  # peak of the key light over the sky
KEY_WIDTH = 0.05  # 1 - cos of its radius, about 18 degrees


def _rgb(color) -> dict:
    return {"type": "rgb", "value": [float(c) for c in color]}


def bsdf(look: str) -> dict:
    """The Mitsuba BSDF of a look of :data:`abmpm.io.looks.LOOKS`."""
    d = LOOKS[look]
    kind, color, rough = d["kind"], d["color"], float(d.get("roughness", 0.0))
    if kind == "dielectric":
        return {"type": "dielectric", "int_ior": d["ior"], "ext_ior": 1.0, "specular_transmittance": _rgb(color)}
    if kind == "translucent":
        return {"type": "roughdielectric", "distribution": "ggx", "alpha": rough, "int_ior": d["ior"],
                "ext_ior": 1.0, "specular_transmittance": _rgb(color)}
    if kind == "metal":  # satin, isotropic: brushing (anisotropy) would follow UVs the meshes do not have
        metal = {"type": "roughconductor", "material": "Al", "distribution": "ggx", "alpha": rough,
                 "specular_reflectance": _rgb(color)}
        return {"type": "twosided", "bsdf": metal}  # sheets are seen from both sides
    if kind == "thin_glass":
        return {"type": "thindielectric", "int_ior": d["ior"], "ext_ior": 1.0, "specular_transmittance": _rgb(color)}
    return {"type": "twosided", "bsdf": {"type": "diffuse", "reflectance": _rgb(color)}}


def _directions(height: int) -> np.ndarray:
    """Unit directions (height, 2 height, 3) of the pixels of a latitude-longitude map
    as Mitsuba's ``envmap`` reads it (u = atan2(x, -z) / 2 pi, v = acos(y) / pi)."""
    v = (np.arange(height) + 0.5) / height
    u = (np.arange(2 * height) + 0.5) / (2 * height)
    theta, phi = np.meshgrid(np.pi * v, 2.0 * np.pi * u, indexing="ij")
    return np.stack([np.sin(theta) * np.sin(phi), np.cos(theta), -np.sin(theta) * np.cos(phi)], axis=-1)


def sky_image(height: int = 128) -> np.ndarray:
    """A latitude-longitude studio sky (height, 2 height, 3) float32: white at the
    horizon, blue towards the zenith, dark grey below the horizon, and a bright soft
    key light (a round softbox) above the front left, which Mitsuba samples by
    importance: soft shadows without the noise of a small area light."""
    d = _directions(height)
    s = np.clip(d[..., 1:2], 0.0, 1.0)
    rgb = SKY_HORIZON * (1.0 - s) + SKY_ZENITH * s
    rgb = np.where(d[..., 1:2] < 0.0, SKY_GROUND, rgb)
    key = KEY_DIRECTION / np.linalg.norm(KEY_DIRECTION)
    cos = d @ key
    rgb = rgb + KEY_RADIANCE * np.exp((cos - 1.0) / KEY_WIDTH)[..., None]
    return np.ascontiguousarray(rgb, dtype=np.float32)


def environment(mi) -> dict:
    """The sky as a Mitsuba ``envmap`` emitter (its up is +y)."""
    return {"type": "envmap", "bitmap": mi.Bitmap(sky_image()), "scale": SKY_SCALE}


def _ground(mi, lo: np.ndarray, hi: np.ndarray) -> dict:
    """A large floor at the bottom of the domain (normal +y)."""
    center = 0.5 * (lo + hi)
    size = 20.0 * float(np.linalg.norm(hi - lo))
    T = mi.ScalarTransform4f
    to_world = T().translate([float(center[0]), float(lo[1]), float(center[2])]) @ T().rotate([1, 0, 0], -90.0) @ T().scale(size)
    return {"type": "rectangle", "to_world": to_world, "bsdf": bsdf("ground")}


def _sensor(mi, camera: Camera, spp: int, seed: int) -> dict:
    T = mi.ScalarTransform4f
    to_world = T().look_at(origin=[float(c) for c in camera.eye], target=[float(c) for c in camera.target],
                           up=[float(c) for c in camera.up])
    return {
        "type": "perspective", "fov": float(camera.fov_deg), "fov_axis": "y", "to_world": to_world,
        "film": {"type": "hdrfilm", "width": int(camera.width), "height": int(camera.height),
                 "rfilter": {"type": "gaussian"}, "pixel_format": "rgb"},
        "sampler": {"type": "multijitter", "sample_count": int(spp), "seed": int(seed)},
    }


def frame_scene(
    mi, camera: Camera, domain: tuple, surfaces: Mapping[str, Path], looks: Mapping[str, str],
    collider: Path | None, collider_look: str, spp: int, seed: int = 0,
) -> dict:
    """The scene dictionary of one frame: ``surfaces`` {material: PLY path} drawn
    with ``looks`` {material: look}, the collider PLY (or None) with
    ``collider_look``, ground, sky, key light and the camera."""
    lo, hi = (np.asarray(d, dtype=np.float64) for d in domain)
    scene = {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": MAX_DEPTH, "rr_depth": 6},
        "sensor": _sensor(mi, camera, spp, seed),
        "sky": environment(mi),
        "ground": _ground(mi, lo, hi),
    }
    for i, (material, path) in enumerate(sorted(surfaces.items())):
        scene[f"surface_{i}"] = {"type": "ply", "filename": str(path), "bsdf": bsdf(looks[material])}
    if collider is not None:
        scene["colliders"] = {"type": "ply", "filename": str(collider), "face_normals": True,
                              "bsdf": bsdf(collider_look)}
    return scene
