"""The browser viewer (abmpm.post.viewer): frames, colors, region, colliders and
surfaces as the viser scene holds them; the live view of a run (abmpm run --view);
``abmpm view`` errors; and a real headless Chromium showing the particles."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from abmpm.cli import main
from abmpm.io import write_json, write_mesh_ply, write_particles_ply
from abmpm.io.outdir import SCENE_FILE, collider_path, frame_path
from abmpm.post import colors_by_level, colors_by_material, colors_by_speed
from abmpm.io.writers import viewer as viewer_writer
from abmpm.post.viewer import Viewer, region_segments
from abmpm.scene.model import BoxBody, Elastic, Fluid, Output, Scene, SimulationSettings

SPACING = 0.04  # of the test particles; they stand for cubes this wide


def small_scene(**output) -> Scene:
    return Scene(
        name="cube",
        simulation=SimulationSettings(domain_max=(1.0, 1.0, 1.0), dx=0.1, fps=30),
        materials=[Fluid(name="water"), Elastic(name="jelly")],
        bodies=[BoxBody(material="water", min=(0.3, 0.3, 0.3), max=(0.7, 0.7, 0.7))],
        output=Output(**output),
    )


def cube(lo=(0.3, 0.3, 0.3), n=10) -> np.ndarray:
    g = (np.arange(n) + 0.5) * SPACING
    return (np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3) + lo).astype(np.float32)


def frame_arrays(x: np.ndarray, speed: float = 0.0, mixed: bool = True) -> dict:
    n = len(x)
    v = np.zeros((n, 3), np.float32)
    v[:, 0] = speed * np.linspace(0.0, 1.0, n)  # a range of speeds
    return {
        "x": x,
        "v": v,
        "speed": np.abs(v[:, 0]),
        "material": (np.arange(n) % 2 * mixed).astype(np.int32),  # water and jelly, or water
        "level": (np.arange(n) % 3 == 0).astype(np.int32),
        "mass": np.full(n, 1000.0 * SPACING**3, np.float32),  # water's density
        "id": np.arange(n, dtype=np.int32),
    }


def write_folder(out: Path, frames: dict[int, np.ndarray], *, colliders=False, region=False, surfaces=False,
                 mixed=True) -> Path:
    """An output folder as a run writes it: scene.json and frames/, and if asked a
    collider that moves, region.npz and a surface mesh at frame 1."""
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / SCENE_FILE, small_scene().model_dump(mode="json"))
    for n, x in frames.items():
        f = frame_arrays(x, speed=1.0 + n, mixed=mixed)
        write_particles_ply(frame_path(out, n), f.pop("x"), f)
        if colliders:
            quad = np.array([[0, 0.1 * n, 0], [1, 0.1 * n, 0], [1, 0.1 * n, 1], [0, 0.1 * n, 1]], np.float32)
            write_mesh_ply(collider_path(out, n), quad, np.array([[0, 1, 2], [0, 2, 3]]))
    if region:
        cells = np.zeros((10, 10, 10), bool)
        cells[2:4, 2:4, 2:4] = True
        np.savez(out / "region.npz", cells=cells, origin=np.zeros(3), dx=np.float64(0.1))
    if surfaces:
        (out / "surfaces").mkdir()
        tet = np.array([[0.3, 0.3, 0.3], [0.7, 0.3, 0.3], [0.3, 0.7, 0.3], [0.3, 0.3, 0.7]], np.float32)
        faces = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
        write_mesh_ply(out / "surfaces" / "surface_00001_water.ply", tet, faces)
    return out


@pytest.fixture(scope="module")
def folder(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("view") / "run"
    return write_folder(out, {0: cube(), 1: cube((0.1, 0.2, 0.3)), 2: cube((0.5, 0.1, 0.2), n=6)},
                        colliders=True, region=True, surfaces=True)


@pytest.fixture()
def viewer(folder):
    v = Viewer(folder, port=0)
    yield v
    v.close()


def uint8(colors) -> np.ndarray:
    return np.round(np.asarray(colors) * 255).astype(int)


# --------------------------------------------------------------------------- the viewer, without a browser


def test_frames_and_scrubbing(viewer, folder):
    assert viewer.numbers == [0, 1, 2]
    assert viewer.url.startswith("http://127.0.0.1:") and viewer.server.get_port() > 0
    assert viewer.frame == 0 and np.array_equal(viewer.points.points, cube())
    # the particles' diameter: a bit more than their spacing (twice the preview's splat radius)
    assert viewer.points.point_size == pytest.approx(2 * 0.6 * SPACING, rel=1e-3)

    viewer.show(2)
    assert viewer.frame == 2 and viewer._slider.value == 2
    assert np.allclose(viewer.points.points, cube((0.5, 0.1, 0.2), n=6))
    viewer._slider.value = 1  # as the slider in the page does
    assert viewer.frame == 1 and np.allclose(viewer.points.points, cube((0.1, 0.2, 0.3)))
    assert "frame 1 of 2" in viewer._status.content and "1,000 particles" in viewer._status.content
    with pytest.raises(ValueError):
        viewer.show(7)  # not an output frame


def test_color_modes(viewer):
    f = viewer.load(0)
    # the scene's color_by is "auto": by material (not adaptive)
    assert viewer.color_mode == "material"
    want = colors_by_material(f["material"], models=["fluid", "elastic"])
    assert np.abs(viewer.points.colors.astype(int) - uint8(want)).max() <= 1
    assert len(np.unique(viewer.points.colors, axis=0)) == 2  # water and jelly

    viewer.color_mode = "level"
    assert np.abs(viewer.points.colors.astype(int) - uint8(colors_by_level(f["level"]))).max() <= 1

    viewer.color_mode = "speed"
    vmax = viewer.speed_vmax()
    assert vmax > 0
    assert np.abs(viewer.points.colors.astype(int) - uint8(colors_by_speed(f["v"], vmax=vmax))).max() <= 1
    assert len(np.unique(viewer.points.colors, axis=0)) > 10  # a colormap, not one color
    viewer.show(1)  # the mode stays while scrubbing
    assert viewer.color_mode == "speed"
    with pytest.raises(ValueError):
        viewer.color_mode = "temperature"


def test_region_lines(viewer):
    segs = viewer.region.points
    cells = np.zeros((10, 10, 10), bool)
    cells[2:4, 2:4, 2:4] = True
    assert np.allclose(segs, region_segments(cells, np.zeros(3), 0.1))
    # the outline of a 2x2x2 cell block: its 12 edges, two cells long each
    assert segs.shape == (24, 2, 3)
    assert np.allclose(segs.min(axis=(0, 1)), 0.2) and np.allclose(segs.max(axis=(0, 1)), 0.4)
    viewer._toggle_region.value = False
    assert viewer.region is None
    viewer._toggle_region.value = True
    assert viewer.region is not None


def test_colliders_and_surfaces(viewer):
    assert np.allclose(viewer.colliders.vertices[:, 1], 0.0)  # frame 0
    assert viewer._surface_handles == []  # no surface at frame 0
    viewer.show(1)
    assert np.allclose(viewer.colliders.vertices[:, 1], 0.1)  # the collider moved
    assert [h.name for h in viewer._surface_handles] == ["/surfaces/water"]
    assert viewer._surface_handles[0].vertices.shape == (4, 3)
    viewer._toggle_colliders.value = False
    viewer._toggle_surfaces.value = False
    assert viewer.colliders is None and viewer._surface_handles == []


def test_play(viewer):
    viewer._fps.value = 40.0
    viewer._play.value = True  # a click on Play
    assert viewer.playing and viewer._play.label == "Pause"
    seen = {viewer.frame}
    deadline = time.monotonic() + 5.0
    while len(seen) < 3 and time.monotonic() < deadline:
        time.sleep(0.02)
        seen.add(viewer.frame)
    viewer.play(False)
    assert seen == {0, 1, 2}
    assert not viewer.playing and viewer._play.label == "Play"


def test_live_push(folder):
    scene = small_scene()
    with Viewer(scene=scene, live=True, port=0) as v:
        assert v.numbers == [] and v.frame is None and v.points is None
        v.set_collider_faces(np.array([[0, 1, 2]]))
        v.push_frame(0, frame_arrays(cube()), np.eye(3, dtype=np.float32))
        assert v.frame == 0 and len(v.points.points) == 1000 and v.colliders is not None
        v.push_frame(3, frame_arrays(cube(n=4)), np.eye(3, dtype=np.float32))
        assert v.numbers == [0, 3] and v.frame == 3 and len(v.points.points) == 64  # follows the run
        v._follow.value = False
        v.push_frame(6, frame_arrays(cube(n=5)))
        assert v.frame == 3 and v._slider.max == 2
        cells = np.zeros((4, 4, 4), bool)
        cells[1, 1, 1] = True
        v.set_region(cells, (0.0, 0.0, 0.0), 0.1)
        assert v.region.points.shape == (12, 2, 3)


def test_run_with_view(tmp_path, monkeypatch, capsys):
    """abmpm run --view: the run pushes its output frames to a live viewer, which
    serves on after the run (here: until wait() returns) and is then closed."""
    made = []

    class Recording(Viewer):
        def __init__(self, *a, **kw):
            super().__init__(*a, **{**kw, "port": 0})
            made.append(self)

        def wait(self, timeout=None):
            made.append("waited")
            return True

    monkeypatch.setattr(viewer_writer, "Viewer", Recording)  # the class the view writer makes
    (tmp_path / "tiny.toml").write_text(
        'name = "tiny"\n[simulation]\ndomain_max = [0.4, 0.4, 0.4]\ndx = 0.05\n'
        '[[materials]]\nname = "water"\nmodel = "fluid"\n'
        '[[bodies]]\nshape = "box"\nmaterial = "water"\nmin = [0.0, 0.0, 0.0]\nmax = [0.15, 0.2, 0.4]\n'
    )
    out = tmp_path / "out"
    code = main(["run", str(tmp_path / "tiny.toml"), "--out", str(out), "--frames", "2", "--device", "cpu",
                 "--no-preview", "-q", "--view", "--view-port", "0"])
    err = capsys.readouterr().err
    assert code == 0, err
    v = made[0]
    assert made[1:] == ["waited"]  # served on after the run (--view keeps it open)
    assert v.numbers == [0, 1, 2] and v.frame == 2 and v.live and "(completed)" in v._status.content
    assert f"live view: {v.url}" in err and "still serving" in err
    assert v._closed.is_set()  # and stopped once wait() returned
    assert (out / "summary.json").is_file()  # written before serving on


# --------------------------------------------------------------------------- abmpm view errors


def test_cli_view_errors(tmp_path, capsys, monkeypatch):
    def one_error(args) -> str:
        code = main(args)
        err = capsys.readouterr().err
        assert code == 2 and "Traceback" not in err, err
        lines = err.strip().splitlines()
        assert len(lines) == 1, err
        return lines[0]

    assert one_error(["view", str(tmp_path / "nope")]) == f"error: {tmp_path / 'nope'}: no such output folder"
    (tmp_path / "empty" / "frames").mkdir(parents=True)
    assert "no particle frames" in one_error(["view", str(tmp_path / "empty")])
    write_particles_ply(frame_path(tmp_path / "noscene", 0), cube(), {})
    assert "no scene.json" in one_error(["view", str(tmp_path / "noscene")])
    assert one_error(["view", str(tmp_path), "--port", "http"]).startswith("abmpm: error: argument --port")
    monkeypatch.setitem(sys.modules, "viser", None)  # viser not installed
    assert one_error(["view", str(tmp_path)]) == "error: abmpm view needs viser: pip install 'abmpm[view]'"
    assert one_error(["run", "dam_break", "--out", str(tmp_path / "run"), "-q", "--view"]) == (
        "error: abmpm run --view needs viser: pip install 'abmpm[view]'"
    )  # before anything is simulated


def test_cli_view_serves_until_ctrl_c(folder, monkeypatch, capsys):
    def ctrl_c(self, timeout=None):
        raise KeyboardInterrupt

    monkeypatch.setattr(Viewer, "wait", ctrl_c)
    assert main(["view", str(folder), "--port", "0"]) == 0
    out = capsys.readouterr().out
    assert "http://127.0.0.1:" in out and "Ctrl-C" in out


# --------------------------------------------------------------------------- in a real browser


def find_chromium() -> str | None:
    for name in (os.environ.get("ABMPM_CHROMIUM"), "chromium", "chromium-browser", "google-chrome",
                 "google-chrome-stable", "chrome"):
        if name and shutil.which(name):
            return shutil.which(name)
    return None


def screenshot(chromium: str, url: str, png: Path, budget_ms: int) -> np.ndarray:
    """The page as headless Chromium draws it after ``budget_ms`` of virtual time
    (WebGL in software: SwiftShader)."""
    import imageio.v3 as iio

    png.unlink(missing_ok=True)
    cmd = [
        chromium, "--headless", "--no-sandbox", "--disable-gpu", "--use-gl=swiftshader",
        "--enable-unsafe-swiftshader", "--disable-dev-shm-usage", "--hide-scrollbars", "--window-size=800,600",
        f"--user-data-dir={png.parent / ('profile-' + png.stem)}",
        f"--virtual-time-budget={budget_ms}", f"--screenshot={png}", url,
    ]
    subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, timeout=90, check=False)
    assert png.is_file(), f"chromium wrote no screenshot: {' '.join(cmd)}"
    return iio.imread(png)[..., :3].astype(int)


def foreground(img: np.ndarray) -> np.ndarray:
    """Pixels of the 3D view (left of the control panel, below the notifications)
    whose color is far from the background (the most common color there)."""
    h, w = img.shape[:2]
    view = img[int(0.27 * h):int(0.88 * h), int(0.1 * w):int(0.57 * w)].reshape(-1, 3)
    colors, counts = np.unique(view, axis=0, return_counts=True)
    bg = colors[np.argmax(counts)]
    return view[np.abs(view - bg).max(axis=1) > 48]


@pytest.mark.browser
def test_browser_shows_particles(tmp_path):
    chromium = find_chromium()
    if chromium is None:
        pytest.skip("no chromium binary (apt-get install chromium)")
    # a cube of water in the left half of the domain (the control panel covers the right)
    out = write_folder(tmp_path / "run", {0: cube((0.1, 0.25, 0.3)), 1: cube()[:0]}, mixed=False)
    with Viewer(out, port=0) as v:
        v._scale.value = 1.5  # big points
        for budget in (2500, 8000):  # more virtual time if the page was not drawn yet
            full = foreground(screenshot(chromium, v.url, tmp_path / "full.png", budget))
            if len(full) > 3000:
                break
        v.show(1)  # the empty frame
        empty = foreground(screenshot(chromium, v.url, tmp_path / "empty.png", budget))
    assert len(full) > 3000, f"the particles are not in the screenshot ({len(full)} pixels off the background)"
    assert len(empty) < 0.25 * len(full), (len(empty), len(full))
    # they are water blue
    r, g, b = full.mean(axis=0)
    assert b > r + 30, (r, g, b)
