"""Open an abmpm run folder in Blender: its PLY sequences as an animated scene.

Two ways to use it:

* ``abmpm blender OUT`` (needs ``pip install -e ".[blender]"``, the ``bpy`` module)
  writes ``OUT/abmpm.blend``;
* inside Blender, where abmpm need not be installed: ``blender --python
  src/abmpm/io/blender.py -- OUT [FILE.blend]`` (add ``--background`` with a FILE
  to only write it), or open this file in Blender's Text Editor, set ``RUN_FOLDER``
  below and press Run Script. It needs ``looks.py`` next to it and
  ``../post/camera.py`` (the package's layout).

What it builds, under an empty ``abmpm_run`` that turns the run's y-up metres into
Blender's z-up: per output frame one object per surface mesh
(``surfaces/surface_NNNNN_<material>.ply``), per collider frame one collider mesh
(one object for all frames when the colliders do not move) and one particle cloud
(``frames/frame_NNNNN.ply``, drawn as spheres by a Geometry Nodes modifier; hidden
in renders when the run has surfaces). Each object is shown from its frame to the
next output frame (keyed ``hide_viewport`` / ``hide_render``), so Blender frame n is
simulation frame n; the scene's frame range is the run's first to last frame, at the
run's fps. Materials follow :mod:`abmpm.io.looks` (Principled BSDF); the camera is the
preview's, with a sun, a grey world and a ground plane at the domain's floor.
"""

from __future__ import annotations

import importlib.util
import json
import math
import re
import sys
from pathlib import Path


def _sibling(name: str, relpath: str):
    """A module of this package loaded from its file (inside Blender, without abmpm)."""
    spec = importlib.util.spec_from_file_location(name, Path(__file__).parent / relpath)
    if spec is None or spec.loader is None:
        raise RuntimeError(f"keep {relpath} next to {Path(__file__).name} (the abmpm package's layout)")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


try:
    from abmpm.errors import OutputError
    from abmpm.io.looks import LOOKS, collider_look, material_look
    from abmpm.post.camera import Camera
except ImportError:  # inside Blender: abmpm is not installed, its files are next to this one
    OutputError = RuntimeError
    _looks = _sibling("abmpm_looks", "looks.py")
    LOOKS, collider_look, material_look = _looks.LOOKS, _looks.collider_look, _looks.material_look
    Camera = _sibling("abmpm_camera", "../post/camera.py").Camera

__all__ = ["RUN_FOLDER", "build_scene", "main", "read_run", "write_blend"]

RUN_FOLDER = ""  # in Blender's Text Editor: the run folder to open, then Run Script

# the run folder's layout (abmpm.io.outdir; tests/test_blender.py checks they agree)
FRAMES_DIR, COLLIDERS_DIR, SURFACES_DIR = "frames", "colliders", "surfaces"
SCENE_FILE, SUMMARY_FILE, BLEND_FILE = "scene.json", "summary.json", "abmpm.blend"
FRAME_RE = re.compile(r"^frame_(\d+)\.ply$")
COLLIDER_RE = re.compile(r"^collider_(\d+)\.ply$")
SURFACE_RE = re.compile(r"^surface_(\d+)_(.+)\.ply$")
RESOLUTION = (640, 360)
INSTALL_HINT = 'abmpm blender needs Blender as a Python module: pip install -e ".[blender]"'


def _numbered(folder: Path, pattern: re.Pattern) -> dict[int, Path]:
    if not folder.is_dir():
        return {}
    found = {int(m.group(1)): p for p in folder.iterdir() if (m := pattern.match(p.name))}
    return dict(sorted(found.items()))


def _stem(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]", "_", name) or "material"  # as abmpm.post.surface.file_stem


def read_run(run_dir) -> dict:
    """What a run folder holds: its scene (scene.json), fps, output frames and the
    numbered PLY files {frame: path} (surfaces {frame: {material stem: path}})."""
    out = Path(run_dir)
    try:
        scene = json.loads((out / SCENE_FILE).read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise OutputError(f"{out}: not an abmpm run folder (cannot read {SCENE_FILE}: {exc})") from None
    particles = _numbered(out / FRAMES_DIR, FRAME_RE)
    surfaces: dict[int, dict[str, Path]] = {}
    for p in sorted((out / SURFACES_DIR).glob("surface_*.ply")):
        if m := SURFACE_RE.match(p.name):
            surfaces.setdefault(int(m.group(1)), {})[m.group(2)] = p
    frames = sorted(set(particles) | set(surfaces))
    if not frames:
        raise OutputError(f"{out}: no frames/*.ply or surfaces/*.ply to open (the run wrote no frames)")
    return {"dir": out, "scene": scene, "fps": float(scene["simulation"]["fps"]), "frames": frames,
            "particles": particles, "colliders": _numbered(out / COLLIDERS_DIR, COLLIDER_RE), "surfaces": surfaces}


# --------------------------------------------------------------------------- Blender side


def _material(bpy, name: str, look: str):
    """A Principled BSDF material for a look of :data:`abmpm.io.looks.LOOKS`."""
    d = LOOKS[look]
    mat = bpy.data.materials.new(name)
    if mat.node_tree is None:  # Blender < 5 makes node trees on request
        mat.use_nodes = True
    p = next(n for n in mat.node_tree.nodes if n.type == "BSDF_PRINCIPLED")
    color = (*d["color"], 1.0)
    p.inputs["Base Color"].default_value = color
    p.inputs["Roughness"].default_value = float(d.get("roughness", 0.5))
    if "ior" in d:
        p.inputs["IOR"].default_value = float(d["ior"])
    if d["kind"] in ("dielectric", "translucent", "thin_glass"):
        p.inputs["Transmission Weight"].default_value = 1.0
    if d["kind"] == "metal":
        p.inputs["Metallic"].default_value = 1.0
        p.inputs["Anisotropic"].default_value = 0.6  # brushed
    mat.diffuse_color = color  # the viewport's solid mode
    return mat


def _import_ply(bpy, path: Path, name: str, collection, parent, material):
    """One PLY file as an object in ``collection`` under ``parent``, with ``material``."""
    before = set(bpy.data.objects)
    bpy.ops.wm.ply_import(filepath=str(path))
    obj = next(o for o in bpy.data.objects if o not in before)
    obj.name = name
    for c in list(obj.users_collection):
        c.objects.unlink(obj)
    collection.objects.link(obj)
    obj.parent = parent
    obj.data.materials.clear()
    obj.data.materials.append(material)
    return obj


def _show_between(obj, start: int, end: int | None) -> None:
    """Key the object visible from frame ``start`` until ``end`` (None: to the end)."""
    for attr in ("hide_viewport", "hide_render"):
        for frame, hidden in ((start - 1, True), (start, False), (end, True)):
            if frame is None:
                continue
            setattr(obj, attr, hidden)
            obj.keyframe_insert(attr, frame=frame)


def _sequence(bpy, files: dict[int, Path], name: str, collection, parent, material) -> list:
    """A PLY sequence {frame: path}, each shown until the next one; one unkeyed object
    when every file is the same (colliders at rest)."""
    if not files:
        return []
    first = next(iter(files.values()))
    if len(files) > 1 and all(p.read_bytes() == first.read_bytes() for p in files.values()):
        return [_import_ply(bpy, first, name, collection, parent, material)]
    frames = list(files)
    objs = []
    for i, n in enumerate(frames):
        obj = _import_ply(bpy, files[n], f"{name}_{n:05d}", collection, parent, material)
        _show_between(obj, n, frames[i + 1] if i + 1 < len(frames) else None)
        objs.append(obj)
    return objs


def _points_modifier(bpy, radius: float, material):
    """A Geometry Nodes group that draws a mesh's vertices as spheres of ``radius``."""
    ng = bpy.data.node_groups.new("abmpm particles", "GeometryNodeTree")
    ng.interface.new_socket(name="Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    ng.interface.new_socket(name="Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    nodes, links = ng.nodes, ng.links
    source, sink = nodes.new("NodeGroupInput"), nodes.new("NodeGroupOutput")
    points = nodes.new("GeometryNodeMeshToPoints")
    points.inputs["Radius"].default_value = radius
    paint = nodes.new("GeometryNodeSetMaterial")
    paint.inputs["Material"].default_value = material
    links.new(source.outputs[0], points.inputs["Mesh"])
    links.new(points.outputs["Points"], paint.inputs["Geometry"])
    links.new(paint.outputs["Geometry"], sink.inputs[0])
    return ng


def _collection(bpy, name: str):
    c = bpy.data.collections.new(name)
    bpy.context.scene.collection.children.link(c)
    return c


def _camera(bpy, scene: dict, parent):
    """The preview's camera (abmpm.post.camera.Camera.framing_box) in the run's frame."""
    from mathutils import Matrix

    st = scene["simulation"]
    cam = Camera.framing_box(st["domain_min"], st["domain_max"], *RESOLUTION)
    right, up, back = cam.basis()
    data = bpy.data.cameras.new("abmpm camera")
    data.sensor_fit = "VERTICAL"
    data.angle_y = math.radians(cam.fov_deg)
    obj = bpy.data.objects.new("abmpm camera", data)
    bpy.context.scene.collection.objects.link(obj)
    obj.parent = parent
    obj.matrix_basis = Matrix([[right[i], up[i], back[i], cam.eye[i]] for i in range(3)] + [[0, 0, 0, 1]])
    return obj


def _stage(bpy, scene: dict, parent) -> None:
    """Sun, grey world and a ground plane at the domain's floor (normal +y)."""
    st = scene["simulation"]
    lo, hi = st["domain_min"], st["domain_max"]
    size = 20.0 * math.dist(lo, hi)
    bpy.ops.mesh.primitive_plane_add(size=size, location=(0.5 * (lo[0] + hi[0]), lo[1], 0.5 * (lo[2] + hi[2])),
                                     rotation=(-0.5 * math.pi, 0.0, 0.0))
    ground = bpy.context.active_object
    ground.name, ground.parent = "abmpm ground", parent
    ground.data.materials.append(_material(bpy, "abmpm ground", "ground"))
    sun = bpy.data.objects.new("abmpm sun", bpy.data.lights.new("abmpm sun", "SUN"))
    sun.data.energy, sun.data.angle = 3.0, math.radians(15.0)
    sun.rotation_euler = (math.radians(40.0), 0.0, math.radians(-40.0))
    bpy.context.scene.collection.objects.link(sun)
    world = bpy.context.scene.world or bpy.data.worlds.new("abmpm world")
    bpy.context.scene.world = world
    world.color = (0.45, 0.48, 0.52)
    if world.node_tree is not None and "Background" in world.node_tree.nodes:
        world.node_tree.nodes["Background"].inputs["Color"].default_value = (0.45, 0.48, 0.52, 1.0)


def build_scene(bpy, run_dir) -> dict:
    """Build the run in the open Blender file; returns the frame range, fps and the
    number of objects made."""
    run = read_run(run_dir)
    scene, first, last = run["scene"], run["frames"][0], run["frames"][-1]
    bscene = bpy.context.scene
    bscene.frame_start, bscene.frame_end = first, last
    bscene.render.fps = max(1, round(run["fps"]))
    bscene.render.fps_base = bscene.render.fps / run["fps"]
    bscene.render.resolution_x, bscene.render.resolution_y = RESOLUTION
    root = bpy.data.objects.new("abmpm_run", None)  # y up (abmpm) -> z up (Blender)
    root.rotation_euler = (0.5 * math.pi, 0.0, 0.0)
    bscene.collection.objects.link(root)
    objects = []
    looks = {_stem(m["name"]): material_look(m) for m in scene["materials"]}
    surfaces = _collection(bpy, "abmpm surfaces")
    for stem, look in looks.items():
        files = {n: got[stem] for n, got in run["surfaces"].items() if stem in got}
        objects += _sequence(bpy, files, f"surface_{stem}", surfaces, root, _material(bpy, stem, look))
    c_look = collider_look(scene.get("output", {}))
    objects += _sequence(bpy, run["colliders"], "colliders", _collection(bpy, "abmpm colliders"), root,
                         _material(bpy, f"colliders ({c_look})", c_look))
    cloud = _collection(bpy, "abmpm particles")
    cloud.hide_render = bool(run["surfaces"])  # the surfaces stand for the particles in a render
    mat = _material(bpy, "particles", material_look(scene["materials"][0]))
    spheres = _points_modifier(bpy, 0.3 * float(scene["simulation"]["dx"]), mat)
    for obj in (made := _sequence(bpy, run["particles"], "particles", cloud, root, mat)):
        obj.modifiers.new("abmpm particles", "NODES").node_group = spheres
    objects += made
    bscene.camera = _camera(bpy, scene, root)
    _stage(bpy, scene, root)
    bscene.frame_set(first)
    return {"frame_start": first, "frame_end": last, "fps": run["fps"], "objects": len(objects)}


def write_blend(run_dir, output=None) -> dict:
    """``abmpm blender``: build the run in an empty Blender file and save it
    (default ``RUN_DIR/abmpm.blend``); returns :func:`build_scene`'s dict and ``blend``."""
    run_dir = Path(run_dir)
    target = Path(output) if output else run_dir / BLEND_FILE
    read_run(run_dir)  # a bad folder is refused before Blender is loaded
    try:
        import bpy
    except ImportError:
        raise OutputError(INSTALL_HINT) from None
    bpy.ops.wm.read_factory_settings(use_empty=True)
    info = build_scene(bpy, run_dir)
    target.parent.mkdir(parents=True, exist_ok=True)
    bpy.ops.wm.save_as_mainfile(filepath=str(target.resolve()))
    return {**info, "blend": str(target)}


def main(argv: list[str] | None = None) -> None:
    """Inside Blender: ``blender [--background] --python blender.py -- RUN_DIR [FILE.blend]``
    builds the run in the open file (and saves it to FILE.blend when given); from
    the Text Editor, ``RUN_FOLDER`` names the run."""
    import bpy

    args = argv if argv is not None else (sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else [])
    run_dir = args[0] if args else RUN_FOLDER
    if not run_dir:
        raise SystemExit("abmpm: name the run folder: blender --python blender.py -- OUT (or set RUN_FOLDER)")
    info = build_scene(bpy, run_dir)
    if len(args) > 1:
        bpy.ops.wm.save_as_mainfile(filepath=str(Path(args[1]).resolve()))
    print(f"abmpm: {run_dir}: frames {info['frame_start']}-{info['frame_end']}, {info['objects']} objects")


if __name__ == "__main__":
    main()
