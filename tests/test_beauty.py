"""The beauty pass (``abmpm render --beauty``, ``[output] beauty``): Mitsuba renders
the surfaces where they are, the run folder gets beauty.mp4 / beauty.png, and user
mistakes get one line. The rendering tests skip without mitsuba."""

from __future__ import annotations

import importlib.util
import json
import shutil
import sys

import numpy as np
import pytest
import trimesh

from abmpm.cli import main
from abmpm.errors import OutputError
from abmpm.io.looks import LOOKS, MODEL_LOOK, collider_look, material_look
from abmpm.io.ply import write_mesh_ply
from abmpm.post.camera import Camera
from abmpm.scene import model as sm

NO_MITSUBA = "mitsuba is not installed (pip install -e '.[render]'): the beauty render cannot be tested"
needs_mitsuba = pytest.mark.skipif(importlib.util.find_spec("mitsuba") is None, reason=NO_MITSUBA)
DOMAIN = ((0.0, 0.0, 0.0), (0.4, 0.4, 0.4))


def _tiny_scene(**output) -> sm.Scene:
    """Water on a sheet that moves down (the scene of tests/test_usd.py: kernels cached)."""
    return sm.Scene(
        name="beauty",
        simulation=sm.SimulationSettings(domain_max=DOMAIN[1], dx=0.04, fps=40.0),
        materials=[sm.Fluid(name="water")],
        bodies=[sm.BoxBody(material="water", min=(0.1, 0.2, 0.1), max=(0.3, 0.3, 0.3))],
        colliders=[sm.SheetCollider(size=(0.3, 0.3), center=(0.2, 0.15, 0.2),
                                    motion=sm.Motion(velocity=(0.0, -0.5, 0.0)))],
        output=sm.Output(preview=False, **output),
    )


def test_every_material_model_has_a_look():
    from abmpm.sim.materials import MODULES

    assert set(MODULES) <= set(MODEL_LOOK)
    assert all(look in LOOKS for look in MODEL_LOOK.values())
    assert material_look({"model": "fluid", "viscosity": 0.0}) == "water"
    assert material_look({"model": "fluid", "viscosity": 20.0}) == "goo"
    assert collider_look({"beauty_colliders": "glass"}) == "glass"
    assert collider_look({}, "metal") == "metal"


@needs_mitsuba
def test_fluid_shows_where_it_is(tmp_path):
    """A sphere of water over the ground beside a metal sheet, rendered with and
    without the sphere: the image is neither empty nor uniform nor blown out, and it
    changes inside the sphere's outline much more than outside it."""
    from abmpm.post.beauty import import_mitsuba, render_frame
    from abmpm.post.beauty_scene import frame_scene

    mi = import_mitsuba("scalar_rgb", threads=1)
    center = np.array([0.2, 0.12, 0.2])
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.08)
    write_mesh_ply(tmp_path / "water.ply", sphere.vertices + center, sphere.faces)
    sheet = np.array([[0.05, 0.0, 0.05], [0.05, 0.3, 0.05], [0.35, 0.3, 0.05], [0.35, 0.0, 0.05]])
    write_mesh_ply(tmp_path / "sheet.ply", sheet, np.array([[0, 1, 2], [0, 2, 3]]))
    camera = Camera.framing_box(*DOMAIN, 96, 64)

    def image(surfaces):
        d = frame_scene(mi, camera, DOMAIN, surfaces, {"water": "water"}, tmp_path / "sheet.ply", "metal", spp=8)
        return render_frame(mi, d).astype(np.float64)

    with_fluid = image({"water": tmp_path / "water.ply"})
    without = image({})
    assert with_fluid.shape == (64, 96, 3)
    for img in (with_fluid, without):
        assert 30.0 < img.mean() < 230.0, img.mean()  # neither black nor white
        assert img.std() > 8.0  # not uniform: ground, sky and sheet differ
        assert (img >= 255).mean() < 0.02
    col, row, _ = camera.project(sphere.vertices + center)
    inside = np.zeros((64, 96), dtype=bool)
    inside[int(row.min()) + 2:int(row.max()) - 2, int(col.min()) + 2:int(col.max()) - 2] = True
    diff = np.abs(with_fluid - without).mean(axis=2)
    assert diff[inside].mean() > 15.0, diff[inside].mean()
    assert diff[inside].mean() > 3.0 * diff[~inside].mean()


@pytest.fixture(scope="module")
def beauty_run(tmp_path_factory):
    """A 2-frame run with ``[output] beauty = true`` rendered small and fast."""
    if importlib.util.find_spec("mitsuba") is None or importlib.util.find_spec("pysplashsurf") is None:
        pytest.skip(NO_MITSUBA + " (or pysplashsurf is missing)")
    from abmpm.io.writers.beauty import BeautyWriter
    from abmpm.post.beauty import BeautySettings
    from abmpm.runner import run

    out = tmp_path_factory.mktemp("beauty") / "run"
    BeautyWriter.settings = BeautySettings(width=64, height=48, spp=2, threads=1)
    try:
        summary = run(_tiny_scene(beauty=True), out, frames=2, device="cpu", progress=False)
    finally:
        BeautyWriter.settings = None
    return out, summary


def test_run_with_output_beauty(beauty_run):
    """``[output] beauty = true`` meshes the surfaces (output.surface is off) and
    writes beauty.mp4 and beauty.png, listed in summary.json."""
    import imageio.v3 as iio

    out, summary = beauty_run
    assert (out / "beauty.mp4").stat().st_size > 0
    img = iio.imread(out / "beauty.png")
    assert img.shape == (48, 64, 3) and img.std() > 5.0
    assert summary["outputs"]["beauty"] == "beauty.mp4"
    assert summary["beauty"]["frames"] == 3 and summary["beauty"]["spp"] == 2
    assert json.loads((out / "summary.json").read_text())["beauty"]["variant"]
    assert len(list((out / "surfaces").glob("surface_*_water.ply"))) == 3


def test_render_command(beauty_run, tmp_path, capsys):
    """``abmpm render OUT --beauty`` with a stride: every other frame."""
    out = tmp_path / "run"
    shutil.copytree(beauty_run[0], out)
    (out / "beauty.png").unlink()
    args = ["render", str(out), "--beauty", "--spp", "1", "--size", "32x24", "--stride", "2", "-j", "1", "-q"]
    assert main(args) == 0
    assert (out / "beauty.png").is_file()


def test_render_one_frame_of_a_run(beauty_run):
    """``render_run_frame`` (docs/figures/beauty_modes.py): one frame, as the beauty
    pass renders it; a frame with no surface mesh names the command."""
    from abmpm.post.beauty import BeautySettings, render_run_frame

    out = beauty_run[0]
    img = render_run_frame(out, 1, BeautySettings(width=64, height=48, spp=2, threads=1))
    assert img.shape == (48, 64, 3) and img.dtype == np.uint8 and img.std() > 5.0
    with pytest.raises(OutputError, match="abmpm surface"):
        render_run_frame(out, 7, BeautySettings(width=8, height=8, spp=1, threads=1))


def test_no_surfaces_and_no_splashsurf_names_the_command(beauty_run, tmp_path, monkeypatch, capsys):
    out = tmp_path / "run"
    shutil.copytree(beauty_run[0], out)
    shutil.rmtree(out / "surfaces")
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "pysplashsurf" else real(name, *a))
    assert main(["render", str(out), "--beauty", "-q"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and f"abmpm surface {out}" in err and "Traceback" not in err


def test_missing_mitsuba_is_one_line(tmp_path, monkeypatch, capsys):
    from abmpm.post.beauty import import_mitsuba

    monkeypatch.setitem(sys.modules, "mitsuba", None)
    with pytest.raises(OutputError, match=r'pip install -e "\.\[render\]"'):
        import_mitsuba()
    (tmp_path / "scene.json").write_text(_tiny_scene().model_dump_json())
    assert main(["render", str(tmp_path), "--beauty", "-q"]) == 2
    assert capsys.readouterr().err.strip() == 'error: the beauty render needs Mitsuba 3: pip install -e ".[render]"'


def test_beauty_flags_need_beauty(tmp_path, capsys):
    assert main(["render", str(tmp_path), "--spp", "4"]) == 2
    assert capsys.readouterr().err.strip() == "error: --spp: only with --beauty"
    assert main(["render", str(tmp_path), "--beauty", "--size", "big"]) == 2
    assert "WIDTHxHEIGHT" in capsys.readouterr().err
