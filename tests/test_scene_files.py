"""Scene files: the built-in library and every way a user's scene file can be wrong.

Each bad input must give exit status 2 and a one-line ``error:`` message that names
the file and the key (or the mesh file / output folder), without a traceback.
"""

from __future__ import annotations

import subprocess
import sys
import textwrap

import numpy as np
import pytest

from abmpm.cli import main
from abmpm.errors import SceneError
from abmpm.scene.loader import list_builtin_scenes, load_scene
from abmpm.scene.model import Scene
from abmpm.simulation import Simulation, sample_scene

BUILTINS = [
    "blade_cut", "dam_break", "funnel", "hourglass", "jelly_drop", "letter_panel", "mixed", "plate_pour",
    "sand_pile",
]
COLLIDER_BUILTINS = ["blade_cut", "funnel", "hourglass", "letter_panel", "plate_pour"]

# A valid, tiny scene (a few hundred particles) that the bad cases start from.
GOOD = """\
name = "tiny"

[simulation]
domain_max = [0.4, 0.4, 0.4]
dx = 0.05
duration = 0.1

[[materials]]
name = "water"
model = "fluid"

[[materials]]
name = "jelly"
model = "elastic"
youngs_modulus = 1.0e4

[[bodies]]
shape = "box"
material = "water"
min = [0.05, 0.0, 0.05]
max = [0.2, 0.15, 0.2]
"""


def coarse(scene: Scene, dx: float = 0.05) -> Scene:
    sim = scene.simulation.model_copy(update={"dx": dx})
    return scene.model_copy(update={"simulation": sim})


# --------------------------------------------------------------------------- built-ins


def test_builtin_list():
    scenes = list_builtin_scenes()
    # the paper's experiments (paper_*, at the paper's scale) are tested in test_compare.py
    assert sorted(n for n in scenes if not n.startswith("paper_")) == BUILTINS
    for name, desc in scenes.items():
        assert desc, f"built-in scene {name} has no description"


@pytest.mark.parametrize("name", BUILTINS)
def test_builtin_loads_and_runs(name):
    scene = load_scene(name)
    assert scene.name == name
    assert scene.description
    assert scene.base_dir is not None and scene.base_dir.is_dir()
    # sized for a 1-2 minute first run on a laptop (an adaptive scene starts coarse
    # and may grow to b^3 particles per coarse one where it is refined)
    n = len(sample_scene(scene)["x"])
    r = scene.simulation.refinement
    n_max = n * r.split_count if r.mode == "adaptive" else n
    assert 15_000 <= n_max <= 45_000, n
    assert 0.015 <= scene.simulation.dx <= 0.03
    assert 1.0 <= scene.simulation.duration <= 3.0
    sim = Simulation(coarse(scene), device="cpu")
    for _ in range(3):
        sim.step()
    p = sim.particles()
    assert np.isfinite(p.x).all() and np.isfinite(p.v).all()


@pytest.mark.parametrize("name", COLLIDER_BUILTINS)
def test_collider_builtin_loads_and_runs(name):
    scene = load_scene(name)
    assert scene.colliders
    sim = Simulation(coarse(scene), device="cpu")
    tris = sim.collider_triangles()
    assert tris.ndim == 3 and tris.shape[1:] == (3, 3) and len(tris) > 0
    assert np.isfinite(tris).all()
    lo, hi = np.array(scene.simulation.domain_min), np.array(scene.simulation.domain_max)
    centre = tris.reshape(-1, 3).mean(axis=0)
    assert np.all(centre > lo) and np.all(centre < hi)  # the collider is in the box
    for _ in range(3):
        sim.step()
    p = sim.particles()
    assert np.isfinite(p.x).all() and np.isfinite(p.v).all()


def test_scene_file_defaults(tmp_path):
    path = tmp_path / "my_scene.toml"
    path.write_text(GOOD.replace('name = "tiny"\n', ""))
    scene = load_scene(path)
    assert scene.name == "my_scene"  # defaults to the file stem
    assert scene.base_dir == tmp_path.resolve()
    assert scene.simulation.dx == 0.05
    assert [m.model for m in scene.materials] == ["fluid", "elastic"]


def scene_with_a_mesh(tmp_path):
    """tmp_path/scenes/scene.toml: GOOD and a jelly body from meshes/cube.obj (a relative path)."""
    trimesh = pytest.importorskip("trimesh")
    sub = tmp_path / "scenes"
    (sub / "meshes").mkdir(parents=True)
    box = trimesh.creation.box(extents=(0.15, 0.15, 0.15))
    box.apply_translation((0.2, 0.1, 0.2))
    box.export(sub / "meshes" / "cube.obj")
    path = sub / "scene.toml"
    path.write_text(GOOD + '\n[[bodies]]\nshape = "mesh"\nmaterial = "jelly"\nfile = "meshes/cube.obj"\n'
                    'translation = [0.0, 0.15, 0.0]\n')
    return path


def test_relative_mesh_path_resolves_against_the_scene_file(tmp_path):
    path = scene_with_a_mesh(tmp_path)
    sub = path.parent
    scene = load_scene(path)
    assert scene.resolve(scene.bodies[1].file) == (sub / "meshes" / "cube.obj").resolve()
    assert len(sample_scene(scene)["x"]) > 0


def test_a_runs_scene_record_runs_as_its_file_did(tmp_path, monkeypatch, capsys):
    """A run writes its validated scene to scene.json; ``abmpm run out/scene.json`` runs it
    again, its relative mesh paths still resolved against the scene file's folder (which
    the record keeps), and a record that is not a scene is a clear error."""
    sub = scene_with_a_mesh(tmp_path).parent
    monkeypatch.chdir(tmp_path)
    first = ["--frames", "1", "--no-preview", "-q"]
    assert main(["run", "scenes/scene.toml", "--out", "a", *first]) == 0
    scene, record = load_scene(sub / "scene.toml"), load_scene(tmp_path / "a" / "scene.json")
    assert record.model_dump() == scene.model_dump()
    assert record.resolve(record.bodies[1].file) == (sub / "meshes" / "cube.obj").resolve()
    assert main(["run", "a/scene.json", "--out", "b", *first]) == 0
    assert len(sample_scene(record)["x"]) == len(sample_scene(scene)["x"])
    (tmp_path / "list.json").write_text("[1, 2]")
    code, err = run_cli(["run", "list.json", "--out", "c", *first], capsys)
    assert_user_error(code, err, "list.json: a scene is a table of settings, not a list")
    (tmp_path / "cut.json").write_text('{"name": ')
    code, err = run_cli(["run", "cut.json", "--out", "c", *first], capsys)
    assert_user_error(code, err, "cut.json: JSON syntax error:")


# --------------------------------------------------------------------------- bad input


def run_cli(args, capsys):
    code = main(args)
    captured = capsys.readouterr()
    return code, captured.err


def bad_scene(tmp_path, monkeypatch, text: str) -> list[str]:
    """Write scene.toml in tmp_path, run it from there; return the cli args."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "scene.toml").write_text(textwrap.dedent(text))
    return ["run", "scene.toml", "--out", str(tmp_path / "out"), "--frames", "1", "--no-preview", "-q"]


def assert_user_error(code, err, *expected):
    assert code == 2, err
    assert "Traceback" not in err
    assert err.startswith("error: "), err
    for e in expected:
        assert e in err, f"{e!r} not in {err!r}"


CASES = {
    "unknown_key": (
        GOOD.replace("dx = 0.05", "dx = 0.05\ndxx = 0.1"),
        ["error: scene.toml: simulation.dxx: unknown key"],
    ),
    "unknown_key_in_material": (
        GOOD.replace("youngs_modulus = 1.0e4", "youngs_modulus = 1.0e4\ncolour = 'red'"),
        ["error: scene.toml: materials[1].colour: unknown key"],
    ),
    "wrong_type": (
        GOOD.replace("dx = 0.05", 'dx = "fine"'),
        ["error: scene.toml: simulation.dx: expected a number, got 'fine'"],
    ),
    "wrong_type_vector": (
        GOOD.replace("max = [0.2, 0.15, 0.2]", 'max = [0.2, "high", 0.2]'),
        ["error: scene.toml: bodies[0].max[1]: expected a number"],
    ),
    "short_vector": (
        GOOD.replace("domain_max = [0.4, 0.4, 0.4]", "domain_max = [0.4, 0.4]"),
        ["error: scene.toml: simulation.domain_max: expected a list of 3 numbers"],
    ),
    "zero_dx": (
        GOOD.replace("dx = 0.05", "dx = 0"),
        ["error: scene.toml: simulation.dx: must be > 0"],
    ),
    "negative_youngs_modulus": (
        GOOD.replace("youngs_modulus = 1.0e4", "youngs_modulus = -1"),
        ["error: scene.toml: materials[1].youngs_modulus: must be > 0"],
    ),
    "unknown_model": (
        GOOD.replace('model = "elastic"', 'model = "jello"'),
        ['error: scene.toml: materials[1].model: unknown model "jello" (choose from fluid, elastic,'],
    ),
    "unknown_shape": (
        GOOD.replace('shape = "box"', 'shape = "cube"'),
        ['error: scene.toml: bodies[0].shape: unknown shape "cube" (choose from box, sphere,'],
    ),
    "unknown_material_reference": (
        GOOD.replace('material = "water"', 'material = "lava"'),
        ["error: scene.toml: bodies[0].material: unknown material 'lava'"],
    ),
    "body_outside_domain": (
        GOOD.replace("max = [0.2, 0.15, 0.2]", "max = [0.2, 0.15, 0.6]"),
        ["error: scene.toml: bodies[0]: body extends outside the domain", "axis z"],
    ),
    "unknown_collider_shape": (
        GOOD + '\n[[colliders]]\nshape = "plate"\n',
        ['error: scene.toml: colliders[0].shape: unknown shape "plate" (choose from mesh, sheet, thin_box,'],
    ),
    "collider_without_shape": (
        GOOD + "\n[[colliders]]\nsize = [0.3, 0.3]\n",
        ["error: scene.toml: colliders[0].shape: required key missing (choose from mesh, sheet,"],
    ),
    "unknown_collider_key": (
        GOOD + '\n[[colliders]]\nshape = "sheet"\nsizee = [0.3, 0.3]\n',
        ["error: scene.toml: colliders[0].sizee: unknown key"],
    ),
    "negative_collider_friction": (
        GOOD + '\n[[colliders]]\nshape = "sheet"\nfriction = -0.5\n',
        ["error: scene.toml: colliders[0].friction: must be >= 0"],
    ),
    "unknown_collider_boundary": (
        GOOD + '\n[[colliders]]\nshape = "sheet"\nboundary = "glue"\n',
        ["error: scene.toml: colliders[0].boundary: must be one of sticky, slip, separate, got 'glue'"],
    ),
    "collider_missing_required_key": (
        GOOD + '\n[[colliders]]\nshape = "sheet"\n\n[[colliders]]\nshape = "thin_box"\n',
        ["error: scene.toml: colliders[1].size: required key missing"],
    ),
    "keyframes_decreasing_times": (
        GOOD + '\n[[colliders]]\nshape = "sheet"\n'
        "[[colliders.motion.keyframes]]\ntime = 0.5\n[[colliders.motion.keyframes]]\ntime = 0.2\n",
        ["error: scene.toml: colliders[0].motion", "time"],
    ),
    "keyframe_negative_time": (
        GOOD + '\n[[colliders]]\nshape = "sheet"\n[[colliders.motion.keyframes]]\ntime = -1.0\n',
        ["error: scene.toml: colliders[0].motion.keyframes[0].time: must be >= 0"],
    ),
    "collider_short_velocity": (
        GOOD + '\n[[colliders]]\nshape = "sheet"\nmotion = { velocity = [1.0, 0.0] }\n',
        ["error: scene.toml: colliders[0].motion.velocity: expected a list of 3 numbers"],
    ),
    "impossible_collider_geometry": (
        GOOD + '\n[[colliders]]\nshape = "hourglass"\ncenter = [0.2, 0.2, 0.2]\nradius = 0.1\nneck_radius = 0.2\n',
        ["error: scene.toml: colliders[0]: hourglass neck_radius must be smaller than radius"],
    ),
    "toml_syntax": (
        GOOD.replace("[simulation]", "[simulation"),
        ["error: scene.toml: TOML syntax error:", "line 3"],
    ),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_bad_scene_file(case, tmp_path, monkeypatch, capsys):
    text, expected = CASES[case]
    args = bad_scene(tmp_path, monkeypatch, text)
    code, err = run_cli(args, capsys)
    assert_user_error(code, err, *expected)
    assert len(err.strip().splitlines()) == 1, err  # one problem, one line


def test_several_problems_one_line_each(tmp_path, monkeypatch, capsys):
    text = GOOD.replace("dx = 0.05", "dx = -1\nfps = 'fast'").replace(
        "youngs_modulus = 1.0e4", "youngs_modulus = 0\npoisson = 0.3"
    )
    code, err = run_cli(bad_scene(tmp_path, monkeypatch, text), capsys)
    assert_user_error(code, err)
    assert err.strip().splitlines() == [
        "error: scene.toml: simulation.dx: must be > 0",
        "error: scene.toml: simulation.fps: expected a number, got 'fast'",
        "error: scene.toml: materials[1].youngs_modulus: must be > 0",
        "error: scene.toml: materials[1].poisson: unknown key",
    ]


def test_load_scene_raises_scene_error(tmp_path):
    path = tmp_path / "scene.toml"
    path.write_text(GOOD.replace("dx = 0.05", "dx = 0"))
    with pytest.raises(SceneError) as info:
        load_scene(path)
    assert str(info.value) == f"{path}: simulation.dx: must be > 0"


def test_missing_scene_file(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    code, err = run_cli(["run", "nothere.toml", "-q"], capsys)
    assert_user_error(code, err, "nothere.toml", "not found")


def test_unknown_builtin(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    code, err = run_cli(["run", "dam_brake", "-q"], capsys)
    assert_user_error(code, err, "dam_brake", *BUILTINS)


def test_missing_mesh_file(tmp_path, monkeypatch, capsys):
    text = GOOD + '\n[[bodies]]\nshape = "mesh"\nmaterial = "jelly"\nfile = "meshes/missing.obj"\n'
    code, err = run_cli(bad_scene(tmp_path, monkeypatch, text), capsys)
    assert_user_error(code, err, "missing.obj", "not found", "bodies[1].file")


def test_missing_collider_mesh_file(tmp_path, monkeypatch, capsys):
    text = GOOD + '\n[[colliders]]\nshape = "mesh"\nfile = "meshes/missing_sheet.obj"\n'
    code, err = run_cli(bad_scene(tmp_path, monkeypatch, text), capsys)
    assert_user_error(code, err, "missing_sheet.obj", "not found", "colliders[0].file")
    assert len(err.strip().splitlines()) == 1, err


def test_open_mesh_as_collider_is_fine(tmp_path, monkeypatch, capsys):
    trimesh = pytest.importorskip("trimesh")
    sheet = trimesh.Trimesh(vertices=[[-0.3, 0, -0.3], [0.3, 0, -0.3], [0.3, 0, 0.3], [-0.3, 0, 0.3]],
                            faces=[[0, 2, 1], [0, 3, 2]])
    (tmp_path / "meshes").mkdir()
    sheet.export(tmp_path / "meshes" / "sheet.obj")
    text = GOOD + '\n[[colliders]]\nshape = "mesh"\nfile = "meshes/sheet.obj"\ncenter = [0.2, 0.3, 0.2]\n'
    code, err = run_cli(bad_scene(tmp_path, monkeypatch, text), capsys)
    assert code == 0, err
    assert (tmp_path / "out" / "colliders" / "collider_00001.ply").is_file()


def test_open_mesh_as_solid(tmp_path, monkeypatch, capsys):
    trimesh = pytest.importorskip("trimesh")
    box = trimesh.creation.box(extents=(0.1, 0.1, 0.1))
    box.apply_translation((0.3, 0.2, 0.3))
    open_box = trimesh.Trimesh(box.vertices, box.faces[:-2], process=False)  # one side missing
    assert not open_box.is_watertight
    open_box.export(tmp_path / "open.obj")
    text = GOOD + '\n[[bodies]]\nshape = "mesh"\nmaterial = "jelly"\nfile = "open.obj"\n'
    code, err = run_cli(bad_scene(tmp_path, monkeypatch, text), capsys)
    assert_user_error(code, err, "open.obj", "not closed")


def test_unwritable_output_folder(tmp_path, monkeypatch, capsys):
    args = bad_scene(tmp_path, monkeypatch, GOOD)
    blocker = tmp_path / "not_a_folder"
    blocker.write_text("a regular file")
    target = blocker / "out"
    args[args.index("--out") + 1] = str(target)
    code, err = run_cli(args, capsys)
    assert_user_error(code, err, "cannot create output folder", str(target))


def test_render_without_run(tmp_path, capsys):
    code, err = run_cli(["render", str(tmp_path)], capsys)
    assert_user_error(code, err, str(tmp_path), "scene.json")


def test_cli_subprocess_no_traceback(tmp_path):
    """`python -m abmpm.cli` and `python -m abmpm` both run and fail cleanly."""
    (tmp_path / "scene.toml").write_text(GOOD.replace("youngs_modulus = 1.0e4", "youngs_modulus = -1"))
    for module in ("abmpm.cli", "abmpm"):
        proc = subprocess.run(
            [sys.executable, "-m", module, "run", "scene.toml", "-q"],
            cwd=tmp_path, capture_output=True, text=True, timeout=120,
        )
        assert proc.returncode == 2, proc.stderr
        assert "Traceback" not in proc.stderr
        assert proc.stderr.strip() == "error: scene.toml: materials[1].youngs_modulus: must be > 0"
        assert not (tmp_path / "out").exists()


def test_cli_scenes_and_info(capsys):
    assert main(["scenes"]) == 0
    out = capsys.readouterr().out
    for name in BUILTINS:
        assert name in out
    assert main(["info"]) == 0
    out = capsys.readouterr().out
    assert "warp" in out and "cpu" in out


def test_a_folder_named_like_a_builtin_scene_does_not_hide_it(tmp_path, monkeypatch):
    # `abmpm run dam_break --out dam_break` leaves a folder of that name; the next
    # `abmpm run dam_break` there read "dam_break: is not a file" until 2026-11-27
    from abmpm.errors import SceneError
    from abmpm.scene.loader import load_scene

    monkeypatch.chdir(tmp_path)
    (tmp_path / "dam_break").mkdir()
    (tmp_path / "not_a_scene").mkdir()
    assert load_scene("dam_break").name == "dam_break"
    with pytest.raises(SceneError, match="not_a_scene: is not a file"):
        load_scene("not_a_scene")
