"""The runner: output files, PLY contents, resume bit-identity, preview, blow-ups."""

from __future__ import annotations

import json
import os
import shlex
import signal

import numpy as np
import pytest

from abmpm.cli import main
from abmpm.errors import OutputError, SimulationBlowUp
from abmpm.io import load_checkpoint, read_particles_ply, save_checkpoint
from abmpm.runner import render_folder, run
from abmpm.scene.model import (
    BoxBody,
    Elastic,
    Fluid,
    Output,
    Scene,
    SimulationSettings,
    SphereBody,
)
from abmpm.simulation import Simulation


def tiny_scene(**output) -> Scene:
    """Water and a jelly ball, ~700 particles on an 8^3 grid: a frame takes ~0.1 s."""
    return Scene(
        name="tiny",
        simulation=SimulationSettings(domain_max=(0.4, 0.4, 0.4), dx=0.05, duration=0.2),
        materials=[Fluid(name="water"), Elastic(name="jelly", youngs_modulus=1.0e4)],
        bodies=[
            BoxBody(material="water", min=(0.0, 0.0, 0.0), max=(0.15, 0.2, 0.4)),
            SphereBody(material="jelly", center=(0.28, 0.25, 0.2), radius=0.07),
        ],
        output=Output(**output),
    )


def quiet_run(scene, out, **kw):
    kw.setdefault("device", "cpu")
    kw.setdefault("progress", False)
    return run(scene, out, **kw)


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    """One 4-frame run shared by the read-only tests."""
    out = tmp_path_factory.mktemp("run") / "tiny"
    summary = quiet_run(tiny_scene(checkpoint_every=2), out, frames=4)
    return out, summary


def test_outputs_written(finished):
    out, summary = finished
    for name in ("scene.json", "summary.json", "energy.png", "preview.mp4", "preview.png"):
        assert (out / name).is_file(), name
    assert sorted(p.name for p in (out / "frames").iterdir()) == [f"frame_{i:05d}.ply" for i in range(5)]
    assert sorted(p.name for p in (out / "checkpoints").iterdir()) == [
        "checkpoint_00002.npz", "checkpoint_00004.npz"
    ]
    on_disk = json.loads((out / "summary.json").read_text())
    assert on_disk["status"] == summary["status"] == "completed"
    assert on_disk["scene"] == "tiny"
    assert on_disk["frames"] == 4 and on_disk["device"] == "cpu"
    assert on_disk["particle_count"] == summary["particle_count"] > 0
    assert on_disk["steps"] > 0 and on_disk["steps_per_second"] > 0 and on_disk["wall_seconds"] > 0
    series = on_disk["series"]
    for key in ("time", "kinetic_energy", "total_mass", "momentum", "max_speed", "count_per_level"):
        assert len(series[key]) == 5, key
    assert series["time"][0] == 0.0 and series["time"][-1] == pytest.approx(4 / 30)
    assert np.allclose(series["total_mass"], series["total_mass"][0], rtol=1e-6)


def test_ply_frames_match_the_simulation(finished):
    out, summary = finished
    sim = Simulation(tiny_scene(), device="cpu")
    p0 = sim.particles().by_id()
    f0 = read_particles_ply(out / "frames" / "frame_00000.ply")
    np.testing.assert_array_equal(f0["x"], p0.x)
    sim.advance(frames=2)
    p = sim.particles().by_id()
    f = read_particles_ply(out / "frames" / "frame_00002.ply")
    np.testing.assert_array_equal(f["x"], p.x)
    np.testing.assert_array_equal(f["v"], p.v)
    np.testing.assert_array_equal(f["material"], p.material)
    np.testing.assert_array_equal(f["level"], p.level)
    np.testing.assert_array_equal(f["mass"], p.mass)
    np.testing.assert_allclose(f["speed"], np.linalg.norm(p.v, axis=1), rtol=1e-6)


def test_preview_decodes_with_one_frame_per_ply(finished):
    import imageio.v2 as imageio

    out, summary = finished
    reader = imageio.get_reader(str(out / "preview.mp4"), format="FFMPEG")
    try:
        frames = [f for f in reader]
    finally:
        reader.close()
    assert len(frames) == 5 == summary["preview_frames"]
    assert frames[0].shape == (480, 640, 3)
    poster = imageio.imread(out / "preview.png")
    assert poster.shape == (480, 640, 3) and poster.std() > 5  # not a blank image


def test_render_folder_rerenders(finished, tmp_path):
    out, _ = finished
    before = (out / "preview.mp4").stat().st_mtime_ns
    info = render_folder(out)
    assert info["frames"] == 5
    assert (out / "preview.mp4").stat().st_mtime_ns >= before


def test_resume_is_bit_identical(tmp_path):
    scene = tiny_scene(checkpoint_every=10)
    straight = tmp_path / "straight"
    split = tmp_path / "split"
    quiet_run(scene, straight, frames=4)
    first = quiet_run(scene, split, frames=2, preview=False)
    assert first["frames"] == 2
    assert sorted(p.name for p in (split / "checkpoints").iterdir()) == ["checkpoint_00002.npz"]
    resumed = quiet_run(scene, split, frames=4, resume=True)
    assert resumed["resumed_from_frame"] == 2 and resumed["status"] == "completed"

    for frame in range(5):
        a = read_particles_ply(straight / "frames" / f"frame_{frame:05d}.ply")
        b = read_particles_ply(split / "frames" / f"frame_{frame:05d}.ply")
        assert a.keys() == b.keys()
        for k in a:
            np.testing.assert_array_equal(a[k], b[k], err_msg=f"frame {frame} {k}")
    ca, ma = load_checkpoint(straight / "checkpoints" / "checkpoint_00004.npz")
    cb, mb = load_checkpoint(split / "checkpoints" / "checkpoint_00004.npz")
    assert ca.keys() == cb.keys()
    for k in ca:
        np.testing.assert_array_equal(ca[k], cb[k], err_msg=k)
    assert (ma["frame"], ma["steps"], ma["dt"], ma["substeps"]) == (mb["frame"], mb["steps"], mb["dt"], mb["substeps"])
    sa = json.loads((straight / "summary.json").read_text())["series"]
    sb = json.loads((split / "summary.json").read_text())["series"]
    # the simulation clock is wall time, not state: this run's frames only, from 0 at the resume
    clock_a, clock_b = sa.pop("sim_seconds"), sb.pop("sim_seconds")
    assert clock_b[:2] == [None, None] and clock_b[2] == 0.0 and None not in clock_a
    assert sa == sb


def test_resume_refuses_a_changed_scene(tmp_path):
    quiet_run(tiny_scene(), tmp_path / "out", frames=1, preview=False)
    changed = tiny_scene()
    changed = changed.model_copy(
        update={"simulation": changed.simulation.model_copy(update={"gravity": (0.0, -1.0, 0.0)})}
    )
    with pytest.raises(OutputError, match="simulation.gravity"):
        quiet_run(changed, tmp_path / "out", frames=2, resume=True)


def test_frames_off_still_previews_and_usd(tmp_path):
    pytest.importorskip("pxr")
    out = tmp_path / "out"
    summary = quiet_run(tiny_scene(frames=False, usd=True, color_by="speed"), out, frames=2)
    assert not (out / "frames").exists() or not any((out / "frames").iterdir())
    assert summary["preview_frames"] == 3
    assert (out / "particles.usd").is_file()
    assert summary["outputs"]["usd"] == "particles.usd"


def _explode_after_frame(monkeypatch, frame: int, poison) -> None:
    """Make the run blow up: after `frame` every particle's velocity becomes NaN."""
    original = Simulation.advance

    def advance(self, seconds=None, frames=None, callback=None):
        def poisoned(sim):
            if callback is not None:
                callback(sim)
            if sim.frame == frame:
                poison(sim)

        return original(self, seconds=seconds, frames=frames, callback=poisoned)

    monkeypatch.setattr(Simulation, "advance", advance)


def test_blow_up_keeps_frames_checkpoint_and_summary(tmp_path, monkeypatch, poison_velocity):
    _explode_after_frame(monkeypatch, 2, poison_velocity)
    out = tmp_path / "out"
    with pytest.raises(SimulationBlowUp, match="blew up"):
        quiet_run(tiny_scene(), out, frames=5)
    assert sorted(p.name for p in (out / "frames").iterdir()) == [f"frame_{i:05d}.ply" for i in range(3)]
    assert [p.name for p in (out / "checkpoints").iterdir()] == ["checkpoint_00002.npz"]
    arrays, meta = load_checkpoint(out / "checkpoints" / "checkpoint_00002.npz")
    assert meta["frame"] == 2 and np.isfinite(arrays["v"]).all() and np.isfinite(arrays["x"]).all()
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "blew_up"
    assert "blew up" in summary["message"] and "last good frame is 2" in summary["message"]
    assert summary["frames"] == 2 and len(summary["series"]["time"]) == 3
    assert (out / "preview.mp4").is_file()  # what happened up to the blow-up


def test_blow_up_cli_exit_code(tmp_path, monkeypatch, capsys, poison_velocity, small_water_scene):
    _explode_after_frame(monkeypatch, 1, poison_velocity)
    path = tmp_path / "tiny.toml"
    path.write_text(small_water_scene)
    out = tmp_path / "out"
    code = main(["run", str(path), "--out", str(out), "--frames", "3", "--no-preview", "-q"])
    err = capsys.readouterr().err
    assert code == 2
    assert "Traceback" not in err
    assert err.startswith("error: simulation blew up") and str(out) in err
    assert json.loads((out / "summary.json").read_text())["status"] == "blew_up"


@pytest.mark.parametrize("how", ["ctrl_c", "sigterm"])
def test_interrupt_checkpoints_last_frame_and_resumes(how, tmp_path, monkeypatch, capsys, small_water_scene):
    """Ctrl-C, or a SIGTERM (a job scheduler, `timeout`), mid-frame: the last whole frame
    is checkpointed, the summary says "interrupted", and the printed command resumes."""
    original = Simulation.advance

    def advance(self, seconds=None, frames=None, callback=None):
        def interrupted(sim):
            callback(sim)
            if sim.frame == 2:
                sim.step()  # mid-frame, as a Ctrl-C usually is
                if how == "ctrl_c":
                    raise KeyboardInterrupt
                assert callable(signal.getsignal(signal.SIGTERM))  # else the signal would end pytest
                os.kill(os.getpid(), signal.SIGTERM)  # the CLI's handler raises KeyboardInterrupt here
                raise AssertionError("SIGTERM did not interrupt the run")

        return original(self, seconds=seconds, frames=frames, callback=interrupted)

    monkeypatch.setattr(Simulation, "advance", advance)
    path = tmp_path / "tiny.toml"
    path.write_text(small_water_scene)
    out = tmp_path / "out"
    code = main(["run", str(path), "--out", str(out), "--frames", "4", "--mode", "original", "-q"])
    err = capsys.readouterr().err
    assert code == 130 and "Traceback" not in err and "--resume" in err
    # the printed command continues the run as asked for (its mode and frame count too)
    hint = shlex.split(err.split("continue with: ")[1].strip())
    assert hint[:2] == ["abmpm", "run"] and {"--mode", "--frames", "--resume"} <= set(hint)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "interrupted" and summary["frames"] == 2
    assert [p.name for p in (out / "checkpoints").iterdir()] == ["checkpoint_00002.npz"]
    monkeypatch.setattr(Simulation, "advance", original)
    assert main(hint[1:] + ["-q"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "completed" and summary["frames"] == 4 and summary["resumed_from_frame"] == 2


def test_cli_run_default_out(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "tiny.toml").write_text(
        '[simulation]\ndomain_max = [0.4, 0.4, 0.4]\ndx = 0.05\n'
        '[[materials]]\nname = "water"\nmodel = "fluid"\n'
        '[[bodies]]\nshape = "box"\nmaterial = "water"\nmin = [0.0, 0.0, 0.0]\nmax = [0.15, 0.2, 0.4]\n'
    )
    code = main(["run", "tiny.toml", "--frames", "1", "--device", "cpu", "--no-preview"])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    assert "done" in captured.out
    out = tmp_path / "out" / "tiny"
    assert (out / "summary.json").is_file() and (out / "frames" / "frame_00001.ply").is_file()
    assert not (out / "preview.mp4").exists()


def test_collider_meshes_written_and_drawn(tmp_path):
    """A moving collider: one PLY mesh per output frame at that frame's time, drawn in
    the preview, and read back by `abmpm render DIR`."""
    import imageio.v2 as imageio

    from abmpm.io import read_mesh_ply
    from abmpm.scene.model import Keyframe, Motion, SheetCollider

    sheet = SheetCollider(
        size=(0.3, 0.3), center=(0.2, 0.36, 0.2), rotation=(0.0, 0.0, 20.0),  # above the material
        motion=Motion(keyframes=[Keyframe(time=0.0), Keyframe(time=0.1, translation=(0.0, -0.03, 0.0))]),
    )
    scene = tiny_scene().model_copy(update={"colliders": [sheet]})
    out = tmp_path / "out"
    summary = quiet_run(scene, out, frames=2)
    assert summary["outputs"]["colliders"] == "colliders/collider_NNNNN.ply"
    names = sorted(p.name for p in (out / "colliders").iterdir())
    assert names == [f"collider_{i:05d}.ply" for i in range(3)]
    sim = Simulation(scene, device="cpu")
    for i in range(3):
        v, f = read_mesh_ply(out / "colliders" / f"collider_{i:05d}.ply")
        np.testing.assert_allclose(v[f], sim.collider_triangles(time=i / 30), atol=1e-6)
    # the sheet shows in the preview: compare with the same frames drawn without it
    from abmpm.post.render import Camera, render
    from abmpm.post.preview import PREVIEW_SIZE
    from abmpm.post.preview import material_densities as _densities
    from abmpm.post.preview import particle_colors as _colors
    from abmpm.post.preview import splat_radius as _radius

    f0 = read_particles_ply(out / "frames" / "frame_00000.ply")
    st = scene.simulation
    cam = Camera.framing_box(st.domain_min, st.domain_max, *PREVIEW_SIZE)
    bare = render(f0["x"], _colors(f0, scene, None), cam, _radius(f0, _densities(scene)),
                  box=(st.domain_min, st.domain_max))
    reader = imageio.get_reader(str(out / "preview.mp4"), format="FFMPEG")
    try:
        first = reader.get_data(0)
    finally:
        reader.close()
    assert np.abs(first.astype(int) - bare.astype(int)).sum(axis=2).__gt__(40).sum() > 500
    # re-rendering from disk gives the same video frame (up to the codec)
    render_folder(out)
    reader = imageio.get_reader(str(out / "preview.mp4"), format="FFMPEG")
    try:
        again = reader.get_data(0)
    finally:
        reader.close()
    assert np.abs(again.astype(int) - first.astype(int)).mean() < 1.0
    # a run that starts over removes the old collider meshes
    quiet_run(tiny_scene(), out, frames=1, preview=False)
    assert not any((out / "colliders").iterdir())


def test_colliders_in_preview_without_frames(tmp_path):
    """frames = false: no PLYs, but the preview still draws the (moving) collider."""
    from abmpm.scene.model import Motion, SheetCollider

    sheet = SheetCollider(size=(0.3, 0.3), center=(0.2, 0.36, 0.2), motion=Motion(velocity=(0.0, -0.5, 0.0)))
    with_sheet = tiny_scene(frames=False).model_copy(update={"colliders": [sheet]})
    a = quiet_run(with_sheet, tmp_path / "a", frames=1)
    b = quiet_run(tiny_scene(frames=False), tmp_path / "b", frames=1)
    assert not (tmp_path / "a" / "colliders").exists()
    assert a["preview_frames"] == b["preview_frames"] == 2
    import imageio.v2 as imageio

    pa = imageio.imread(tmp_path / "a" / "preview.png").astype(int)
    pb = imageio.imread(tmp_path / "b" / "preview.png").astype(int)
    assert (np.abs(pa - pb).sum(axis=2) > 40).sum() > 500


def test_adaptive_resume_after_splits_is_bit_identical(tmp_path):
    # In adaptive mode the particle count changes with every split: a checkpoint holds
    # more particles than the scene starts with, and resuming must still accept it
    # (it refused every adaptive run that had split a particle until 2026-11-27).
    scene = tiny_scene(checkpoint_every=10)
    scene.simulation.refinement.mode = "adaptive"
    scene.simulation.refinement.boxes = [[[0.1, 0.0, 0.0], [0.4, 0.4, 0.4]]]
    straight, split = tmp_path / "straight", tmp_path / "split"
    quiet_run(scene, straight, frames=4, preview=False)
    quiet_run(scene, split, frames=2, preview=False)
    saved, _ = load_checkpoint(split / "checkpoints" / "checkpoint_00002.npz")
    assert len(saved["x"]) > Simulation(scene, device="cpu").particle_count  # particles split since frame 0
    resumed = quiet_run(scene, split, frames=4, resume=True, preview=False)
    assert resumed["resumed_from_frame"] == 2 and resumed["status"] == "completed"
    ca, _ = load_checkpoint(straight / "checkpoints" / "checkpoint_00004.npz")
    cb, _ = load_checkpoint(split / "checkpoints" / "checkpoint_00004.npz")
    for k in ca:
        np.testing.assert_array_equal(ca[k], cb[k], err_msg=k)


def test_resume_refuses_another_scenes_particles(tmp_path):
    quiet_run(tiny_scene(), tmp_path / "out", frames=1, preview=False)
    ckpt = tmp_path / "out" / "checkpoints" / "checkpoint_00001.npz"
    arrays, meta = load_checkpoint(ckpt)
    keep = {k: a[:-5] for k, a in arrays.items()}  # five scene particles gone
    save_checkpoint(ckpt, keep, meta)
    with pytest.raises(OutputError, match="cannot resume"):
        quiet_run(tiny_scene(), tmp_path / "out", frames=2, resume=True, preview=False)


def test_notes_for_runs_that_do_nothing_new(tmp_path, capsys):
    # adaptive mode with nothing that can refine, and a resume already past --frames: said, not silent
    path = tmp_path / "tiny.toml"
    path.write_text(
        '[simulation]\ndomain_max = [0.4, 0.4, 0.4]\ndx = 0.05\n[simulation.refinement]\nmode = "adaptive"\n'
        '[[materials]]\nname = "water"\nmodel = "fluid"\n'
        '[[bodies]]\nshape = "box"\nmaterial = "water"\nmin = [0.0, 0.0, 0.0]\nmax = [0.15, 0.2, 0.4]\n'
    )
    out = tmp_path / "out"
    assert main(["run", str(path), "--out", str(out), "--frames", "2", "--no-preview"]) == 0
    assert "nothing to refine" in " ".join(capsys.readouterr().err.split())  # rich wraps lines
    assert main(["run", str(path), "--out", str(out), "--frames", "1", "--no-preview", "--resume"]) == 0
    assert "nothing left to simulate" in " ".join(capsys.readouterr().err.split())


@pytest.mark.parametrize("duration, fps, frames", [(0.125, 20.0, 3), (0.05, 30.0, 2), (1.5, 30.0, 45), (0.1, 30.0, 3),
                                                   (0.01, 30.0, 1)])
def test_frames_cover_the_duration(duration, fps, frames):
    # a part of a frame is a whole frame (round() took 2.5 frames down and 1.5 up)
    from abmpm.runner import total_frames

    scene = tiny_scene()
    scene.simulation.duration, scene.simulation.fps = duration, fps
    assert total_frames(scene) == frames


def test_particles_inside_a_closed_collider_are_noted(tmp_path):
    # a body overlapping a closed collider: its particles inside stay trapped (CPIC keeps
    # every particle on its side); the run says so instead of running silently
    scene = tiny_scene()
    scene = scene.model_copy(update={"colliders": [_thin_box_through_the_water()]})
    summary = quiet_run(scene, tmp_path / "out", frames=1, preview=False)
    assert any("colliders[0]" in n and "trapped" in n for n in summary["notes"])
    assert "notes" not in quiet_run(tiny_scene(), tmp_path / "clear", frames=1, preview=False)


def test_material_against_a_wall_between_node_planes_is_noted():
    # dx 0.03 m in a 0.4 m box: 13.33 cells, so the walls at x, y, z = 0.4 m lie between node
    # planes and the grid stops material at 0.42 m. The water fills the box along z, so it
    # starts about a centimetre short of where it is held (a tank so set up surges into the
    # gap, in every mode: docs/method.md, "Domain walls"); the run says so, naming the field
    # and the axis.
    # With dx 0.05 m (8 cells) or water short of the wall there is nothing to say.
    from abmpm.runner import _walls_between_nodes

    def notes(scene):
        sim = Simulation(scene, device="cpu")
        return _walls_between_nodes(scene, sim, sim.particles())

    off = tiny_scene()
    off.simulation.dx = 0.03
    said = notes(off)
    assert len(said) == 1 and said[0].startswith("simulation.domain_max: the wall at z = 0.4 m"), said
    assert "0.42 m" in said[0] and "domain_max z = 0.39 or 0.42" in said[0], said[0]
    assert notes(tiny_scene()) == []
    short = off.model_copy(update={"bodies": [BoxBody(material="water", min=(0.0, 0.0, 0.0), max=(0.15, 0.2, 0.3))]})
    assert notes(short) == []


def test_a_collider_that_can_touch_nothing_is_noted(tmp_path):
    # a static sheet wholly outside the domain (a typo in its center or units) does nothing;
    # the run says so
    from abmpm.scene import model as sm

    scene = tiny_scene().model_copy(update={"colliders": [sm.SheetCollider(size=(0.3, 0.3), center=(5.0, 5.0, 5.0))]})
    summary = quiet_run(scene, tmp_path / "out", frames=1, preview=False)
    assert any("colliders[0]" in n and "outside the domain" in n for n in summary["notes"])


def test_a_slow_start_is_noted():
    # a nearly incompressible jelly (Poisson ratio 0.49999999): its wave speed, ~13 km/s
    # here, makes each frame ~21,000 steps where this scene takes ~30 (the check is the
    # scene's alone: nothing runs)
    from abmpm.scene.checks import slow_start_note

    scene = tiny_scene()
    assert slow_start_note(scene) is None
    stiff = scene.model_copy(update={"materials": [Fluid(name="water"),
                                                   Elastic(name="jelly", youngs_modulus=1.0e4, poisson_ratio=0.49999999)]})
    note = slow_start_note(stiff)
    assert note is not None and note.startswith("materials[1]") and "slow" in note


def test_keep_checkpoints_keeps_the_newest(tmp_path):
    # output.keep_checkpoints = 2 with a checkpoint every frame: the newest two remain, and
    # the run resumes from the newest
    scene = tiny_scene(checkpoint_every=1, keep_checkpoints=2)
    out = tmp_path / "out"
    quiet_run(scene, out, frames=4, preview=False)
    assert sorted(p.name for p in (out / "checkpoints").iterdir()) == ["checkpoint_00003.npz", "checkpoint_00004.npz"]
    summary = quiet_run(scene, out, frames=5, preview=False, resume=True)
    assert summary["resumed_from_frame"] == 4
    assert sorted(p.name for p in (out / "checkpoints").iterdir()) == ["checkpoint_00004.npz", "checkpoint_00005.npz"]


def _thin_box_through_the_water():
    from abmpm.scene import model as sm

    return sm.ThinBoxCollider(size=(0.4, 0.05, 0.4), center=(0.2, 0.1, 0.2))  # through the water block


def test_an_adaptive_run_that_refined_most_of_its_material_says_finest_may_be_as_fast(tmp_path):
    # With a refinement box over the whole domain every particle splits into b^3 = 8
    # children: finest mode would hold as many particles as adaptive mode does, at a
    # fraction of the cost of each particle-step (docs/benchmarks.md, "When adaptive mode
    # pays"), and the run says so. A box over a corner the material never reaches refines
    # nothing (finest would hold 8 times the particles): nothing to say; nor in finest mode.
    from abmpm.scene.model import with_mode

    def notes(box, mode="adaptive"):
        scene = with_mode(tiny_scene(), mode, factor=2, boxes=[box])
        summary = quiet_run(scene, tmp_path / f"{mode}{box}", frames=1, preview=False)
        return [n for n in summary.get("notes", []) if n.startswith("adaptive mode refined")]

    whole = ((0.0, 0.0, 0.0), (0.4, 0.4, 0.4))
    said = notes(whole)
    assert len(said) == 1 and "finest mode would hold only 1.0 times its particles" in said[0], said
    assert "refined 100% of the material" in said[0], said[0]
    assert notes(((0.35, 0.35, 0.0), (0.4, 0.4, 0.05))) == []
    assert notes(whole, mode="finest") == []
