"""How the materials of a run look in a rendered picture, for any renderer.

A *look* is a small renderer-neutral description (``kind`` and a few parameters);
:mod:`abmpm.post.beauty_scene` turns it into Mitsuba BSDFs and
:mod:`abmpm.io.blender` into Blender's Principled BSDF. The material model of a
scene picks the look: fluids are a clear dielectric (water; a viscous fluid a tinted
goo), elastic and viscoelastic solids a rough translucent jelly, sand and snow
diffuse; colliders are metal, or glass (``[output] beauty_colliders``).

This module uses the standard library only: the Blender script loads it inside
Blender, where abmpm is not installed.
"""

from __future__ import annotations

__all__ = ["COLLIDER_LOOKS", "LOOKS", "MODEL_LOOK", "VISCOUS", "collider_look", "material_look"]

# kind: dielectric (clear, refracting), translucent (rough dielectric), diffuse,
# metal (rough conductor: brushed, satin), thin_glass (a zero-thickness pane).
# color: linear RGB (tint of the transmitted light for dielectrics).
LOOKS: dict[str, dict] = {
    "water": {"kind": "dielectric", "color": (0.80, 0.92, 1.0), "ior": 1.33, "roughness": 0.0},
    "goo": {"kind": "dielectric", "color": (0.62, 0.90, 0.42), "ior": 1.45, "roughness": 0.0},
    "jelly": {"kind": "translucent", "color": (0.98, 0.42, 0.52), "ior": 1.40, "roughness": 0.18},
    "sand": {"kind": "diffuse", "color": (0.72, 0.58, 0.38), "roughness": 1.0},
    "snow": {"kind": "diffuse", "color": (0.90, 0.92, 0.96), "roughness": 0.9},
    "metal": {"kind": "metal", "color": (0.62, 0.64, 0.67), "roughness": 0.2},
    "glass": {"kind": "thin_glass", "color": (0.95, 0.97, 1.0), "ior": 1.5, "roughness": 0.0},
    "ground": {"kind": "diffuse", "color": (0.45, 0.46, 0.48), "roughness": 1.0},
}

# material model (abmpm.sim.materials.MODULES) -> look
MODEL_LOOK = {"fluid": "water", "elastic": "jelly", "viscoelastic": "jelly", "sand": "sand", "snow": "snow"}
VISCOUS = 1.0  # Pa s: a fluid at least this viscous is drawn as goo
COLLIDER_LOOKS = ("metal", "glass")


def material_look(material: dict) -> str:
    """The look of a scene material (its ``model_dump()`` or its entry in scene.json)."""
    model = material.get("model", "")
    look = MODEL_LOOK.get(model, "snow")
    if model == "fluid" and float(material.get("viscosity") or 0.0) >= VISCOUS:
        look = "goo"
    return look


def collider_look(output: dict, override: str | None = None) -> str:
    """The colliders' look: ``override`` if given, else the scene's
    ``output.beauty_colliders`` (metal unless it says glass)."""
    look = override or output.get("beauty_colliders") or "metal"
    if look not in COLLIDER_LOOKS:
        raise ValueError(f"collider look must be one of {', '.join(COLLIDER_LOOKS)}, got {look!r}")
    return look
