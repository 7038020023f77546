"""What a run, and the commands that read runs back, say when something outside the
scene fails: memory, a damaged frame file, a damaged comparison table, a window too long.
Each is one line naming the cause and what to change, never a traceback, and a run keeps
what it wrote (an audit of absurd inputs found these as tracebacks, 2026-11-29)."""

from __future__ import annotations

import json
import warnings

import pytest

from abmpm.cli import main
from abmpm.io.ply import read_particles_ply
from abmpm.errors import OutputError
from abmpm.scene import checks
from abmpm.scene.loader import scene_from_dict

def run_cli(args, capsys):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        code = main(args)
    return code, capsys.readouterr().err


def one_line_error(code, err, *expected):
    assert code == 2, err
    assert "Traceback" not in err, err
    lines = [line for line in err.splitlines() if line.strip() and not line.startswith("abmpm running")]
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    for e in expected:
        assert e in lines[0], f"{e!r} not in {lines[0]!r}"
    return lines[0]


@pytest.fixture
def in_tmp(tmp_path, monkeypatch, small_water_scene):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "scene.toml").write_text(small_water_scene)
    return tmp_path


RUN = ["run", "scene.toml", "--out", "out", "--no-preview", "-q", "--device", "cpu"]
WARP_OOM = "Failed to allocate 7776000000 bytes on device 'cpu'"  # what Warp raises


def test_an_allocation_failure_mid_run_keeps_the_frames_and_a_checkpoint(in_tmp, capsys, monkeypatch):
    import abmpm.simulation as simulation

    real = simulation.Simulation._run_segment

    def failing(self, *args, **kwargs):
        if self.frame >= 1:  # as a split that needs more memory than there is, in frame 2
            raise RuntimeError(WARP_OOM)
        return real(self, *args, **kwargs)

    monkeypatch.setattr(simulation.Simulation, "_run_segment", failing)
    code, err = run_cli(RUN, capsys)
    line = one_line_error(code, err, "out of memory", "last good frame is 1", "refinement.factor", "out")
    assert "summary.json" in line
    summary = json.loads((in_tmp / "out" / "summary.json").read_text())
    assert summary["status"] == "out_of_memory"
    assert (in_tmp / "out" / "frames" / "frame_00001.ply").exists()
    assert list((in_tmp / "out" / "checkpoints").glob("checkpoint_00001.npz"))


def test_an_allocation_failure_before_the_run_is_one_line(in_tmp, capsys, monkeypatch):
    import abmpm.runner as runner

    def failing(*args, **kwargs):
        raise RuntimeError(WARP_OOM)

    monkeypatch.setattr(runner, "Simulation", failing)
    code, err = run_cli(RUN, capsys)
    one_line_error(code, err, "out of memory", "7776000000 bytes", "simulation.dx")


def test_other_runtime_errors_are_not_called_out_of_memory(in_tmp, capsys, monkeypatch):
    # a bug stays a bug (with its traceback), not a message that blames the scene
    import abmpm.runner as runner

    def broken(*args, **kwargs):
        raise RuntimeError("something else")

    monkeypatch.setattr(runner, "Simulation", broken)
    with pytest.raises(RuntimeError, match="something else"):
        main(RUN)


def test_the_memory_check_counts_the_children_of_a_refinement_box(small_water_scene):
    # adaptive mode splits every particle in a refinement box at its first step: b^3 each.
    # A box over the whole body: adaptive's estimate is finest's particle count (the same
    # lattice at dx / b); over none of it, original's.
    doc = scene_from_dict(_toml(small_water_scene))
    base = checks.memory_estimate(doc, "original")["particles"]
    for box, factor in (([[0.0, 0.0, 0.0], [0.4, 0.4, 0.4]], 3 ** 3), ([[0.3, 0.3, 0.3], [0.4, 0.4, 0.4]], 1)):
        doc = _toml(small_water_scene)
        doc["simulation"]["refinement"] = {"mode": "adaptive", "factor": 3, "boxes": [box]}
        scene = scene_from_dict(doc)
        assert checks.memory_estimate(scene)["particles"] == pytest.approx(base * factor, rel=1e-9)


def _toml(text):
    import tomllib

    return tomllib.loads(text)


@pytest.fixture
def a_run(in_tmp, capsys):
    assert run_cli(RUN, capsys)[0] == 0
    return in_tmp / "out"


@pytest.mark.parametrize("damage", ["cut", "empty", "no_vertices", "no_x"])
def test_a_damaged_frame_file_is_named(a_run, damage):
    frame = a_run / "frames" / "frame_00001.ply"
    if damage == "cut":
        frame.write_bytes(frame.read_bytes()[:100])
    elif damage == "empty":
        frame.write_bytes(b"")
    elif damage == "no_vertices":
        frame.write_bytes(b"ply\nformat ascii 1.0\nelement face 0\nproperty list uchar int vertex_indices\nend_header\n")
    else:
        frame.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float y\nend_header\n0.5\n")
    with pytest.raises(OutputError, match="frame_00001.ply"):
        read_particles_ply(frame)


def test_render_of_a_damaged_frame_is_one_line(a_run, capsys):
    (a_run / "frames" / "frame_00001.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\n")
    code, err = run_cli(["render", str(a_run), "--quiet"], capsys)
    one_line_error(code, err, "frame_00001.ply")


@pytest.mark.parametrize("table", ["[]", "{not json", '{"records": [1, 2]}'])
def test_remeasure_names_a_damaged_table(in_tmp, capsys, table):
    (in_tmp / "cmp").mkdir()
    (in_tmp / "cmp" / "table1.json").write_text(table)
    code, err = run_cli(["compare", "scene.toml", "--out", "cmp", "--remeasure"], capsys)
    one_line_error(code, err, "table1.json", "cannot be read")


def test_a_paper_window_beyond_the_frame_limit_is_refused(in_tmp, capsys):
    code, err = run_cli(["paper", "--scenes", "paper_cut", "--modes", "original", "--quick", "--window", "1e9",
                         "--out", "p", "-q"], capsys)
    one_line_error(code, err, "--window", "frames", f"{checks.MAX_FRAMES:.0e}")
    assert not (in_tmp / "p").exists() or not any((in_tmp / "p").rglob("*.ply"))


def test_interrupted_while_setting_up_offers_no_resume(in_tmp, capsys, monkeypatch):
    # a large collider takes minutes to build; stopped then, there is no checkpoint to resume
    import abmpm.runner as runner

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(runner, "Simulation", interrupted)
    code, err = run_cli(RUN, capsys)
    assert code == 130 and "Traceback" not in err
    assert "--resume" not in err and "before the first checkpoint" in err


def test_overlapping_bodies_are_noted(in_tmp, capsys, small_water_scene):
    # two bodies sharing space add their masses there: said at the start of the run
    (in_tmp / "scene.toml").write_text(small_water_scene + '[[bodies]]\nshape = "sphere"\nmaterial = "water"\n'
                                       'center = [0.125, 0.075, 0.125]\nradius = 0.05\n')
    assert run_cli(RUN, capsys)[0] == 0
    notes = json.loads((in_tmp / "out" / "summary.json").read_text())["notes"]
    assert any("bodies[0] and bodies[1] overlap" in n for n in notes), notes
    (in_tmp / "scene.toml").write_text(small_water_scene + '[[bodies]]\nshape = "box"\nmaterial = "water"\n'
                                       'min = [0.2, 0.0, 0.05]\nmax = [0.3, 0.15, 0.2]\n')  # touching only
    assert run_cli(RUN, capsys)[0] == 0
    assert not any("overlap" in n for n in json.loads((in_tmp / "out" / "summary.json").read_text()).get("notes", []))


def test_a_scene_refused_while_its_particles_are_built_leaves_no_folder(in_tmp, capsys, small_water_scene):
    # a body outside the domain is found when the particles are sampled, after the output
    # folder was made: the empty folder goes again
    (in_tmp / "scene.toml").write_text(small_water_scene.replace("max = [0.2, 0.15, 0.2]", "max = [0.2, 0.15, 0.5]"))
    code, err = run_cli(RUN, capsys)
    one_line_error(code, err, "bodies[0]", "outside the domain")
    assert not (in_tmp / "out").exists()


def test_the_filesystem_root_is_no_output_folder(in_tmp, capsys):
    code, err = run_cli(["run", "scene.toml", "--out", "/", "--no-preview", "-q", "--device", "cpu"], capsys)
    one_line_error(code, err, "filesystem root", "name a folder")
