"""The Blender hand-off (``abmpm blender OUT``, ``src/abmpm/io/blender.py`` inside
Blender): a run folder opens as an animated scene with the run's frame range,
objects and materials. The Blender tests skip where ``bpy`` cannot be imported."""

from __future__ import annotations

import importlib.util
import json
import sys

import pytest

from abmpm.cli import main
from abmpm.io import blender, outdir
from abmpm.scene import model as sm

NO_BPY = ("bpy (Blender as a Python module) cannot be imported: pip install -e '.[blender]' "
          "(Python 3.11; it pins numpy < 2) to run the Blender tests")


def test_layout_agrees_with_outdir():
    """The script keeps its own copy of the folder layout (it runs without abmpm)."""
    for name in ("FRAMES_DIR", "COLLIDERS_DIR", "SURFACES_DIR", "SCENE_FILE", "SUMMARY_FILE", "BLEND_FILE"):
        assert getattr(blender, name) == getattr(outdir, name), name
    for name in ("FRAME_RE", "COLLIDER_RE", "SURFACE_RE"):
        assert getattr(blender, name).pattern == getattr(outdir, name).pattern, name


def test_missing_bpy_is_one_line(tmp_path, monkeypatch, capsys):
    (tmp_path / "scene.json").write_text('{"simulation": {"fps": 30}}')
    (tmp_path / "frames").mkdir()
    (tmp_path / "frames" / "frame_00000.ply").write_bytes(b"")
    monkeypatch.setitem(sys.modules, "bpy", None)
    assert main(["blender", str(tmp_path)]) == 2
    assert capsys.readouterr().err.strip() == 'error: abmpm blender needs Blender as a Python module: pip install -e ".[blender]"'


def test_not_a_run_folder(tmp_path, capsys):
    assert main(["blender", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "not an abmpm run folder" in err and "Traceback" not in err


@pytest.fixture(scope="module")
def blend(tmp_path_factory):
    """A 3-frame run (water on a moving sheet, with surfaces) written as a .blend."""
    if importlib.util.find_spec("bpy") is None:
        pytest.skip(NO_BPY)
    pytest.importorskip("pysplashsurf")
    from abmpm.runner import run

    scene = sm.Scene(
        name="blend",
        simulation=sm.SimulationSettings(domain_max=(0.4, 0.4, 0.4), dx=0.04, fps=40.0),
        materials=[sm.Fluid(name="water")],
        bodies=[sm.BoxBody(material="water", min=(0.1, 0.2, 0.1), max=(0.3, 0.3, 0.3))],
        colliders=[sm.SheetCollider(size=(0.3, 0.3), center=(0.2, 0.15, 0.2),
                                    motion=sm.Motion(velocity=(0.0, -0.5, 0.0)))],
        output=sm.Output(surface=True, preview=False),
    )
    out = tmp_path_factory.mktemp("blender") / "run"
    summary = run(scene, out, frames=3, device="cpu", progress=False)
    assert main(["blender", str(out), "-q"]) == 0
    return out, summary


def _check(bpy, summary):
    scene = bpy.context.scene
    assert (scene.frame_start, scene.frame_end) == (0, summary["frames"])
    assert scene.render.fps / scene.render.fps_base == pytest.approx(40.0)
    names = {o.name for o in bpy.data.objects}
    frames = range(summary["frames"] + 1)
    for kind in ("surface_water", "colliders", "particles"):  # the sheet moves: a collider per frame
        assert {f"{kind}_{n:05d}" for n in frames} <= names, kind
    assert scene.camera is not None and "abmpm ground" in names
    for n in frames:
        assert len(bpy.data.objects[f"surface_water_{n:05d}"].data.polygons) > 100
        assert bpy.data.objects[f"surface_water_{n:05d}"].active_material.name == "water"
        assert bpy.data.objects[f"colliders_{n:05d}"].active_material.name == "colliders (metal)"
        assert bpy.data.objects[f"particles_{n:05d}"].modifiers["abmpm particles"].node_group is not None
    water = bpy.data.materials["water"].node_tree.nodes["Principled BSDF"]
    assert water.inputs["Transmission Weight"].default_value == 1.0
    for n in frames:  # exactly one of each sequence is shown at each frame
        scene.frame_set(n)
        shown = sorted(o.name for o in bpy.data.objects if o.name.startswith("surface_") and not o.hide_render)
        assert shown == [f"surface_water_{n:05d}"]


def test_blend_has_the_run(blend):
    """The frame range is the run's, every frame's objects exist with their
    materials, and each frame shows its own surface; also after reopening the file."""
    import bpy

    out, summary = blend
    _check(bpy, summary)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.wm.open_mainfile(filepath=str(out / "abmpm.blend"))
    _check(bpy, summary)
    assert json.loads((out / "summary.json").read_text())["frames"] == 3
