"""``particles.usd``: what a run writes is what its PLY files hold, at the right time
codes, and USD's own checkers pass it."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("pxr")
pytest.importorskip("pysplashsurf")
from pxr import Usd, UsdGeom  # noqa: E402

from abmpm.io.ply import read_mesh_ply, read_particles_ply  # noqa: E402
from abmpm.io.usd import UsdStageWriter, check_compliance  # noqa: E402
from abmpm.runner import run  # noqa: E402
from abmpm.scene import model as sm  # noqa: E402

FPS = 40.0


def water_on_a_falling_sheet(name: str, **output) -> sm.Scene:
    """Water poured on a sheet that moves down at 0.5 m/s, written to USD."""
    return sm.Scene(
        name=name,
        simulation=sm.SimulationSettings(domain_max=(0.4, 0.4, 0.4), dx=0.04, fps=FPS),
        materials=[sm.Fluid(name="water")],
        bodies=[sm.BoxBody(material="water", min=(0.1, 0.2, 0.1), max=(0.3, 0.3, 0.3))],
        colliders=[sm.SheetCollider(size=(0.3, 0.3), center=(0.2, 0.15, 0.2),
                                    motion=sm.Motion(velocity=(0.0, -0.5, 0.0)))],
        output=sm.Output(usd=True, preview=False, **output),
    )


@pytest.fixture(scope="module")
def usd_run(tmp_path_factory):
    """Water poured on a sheet that moves down: particles, a moving collider, and the
    water's surface, 3 frames."""
    scene = water_on_a_falling_sheet("usd", surface=True)
    out = tmp_path_factory.mktemp("usd") / "run"
    run(scene, out, frames=3, device="cpu", progress=False)
    return out, Usd.Stage.Open(str(out / "particles.usd"))


def test_stage_settings(usd_run):
    _, stage = usd_run
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.y
    assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    assert stage.GetTimeCodesPerSecond() == FPS and stage.GetFramesPerSecond() == FPS
    # one time code per frame: frame n is at n / fps seconds
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (0.0, 3.0)
    assert stage.GetDefaultPrim().GetPath() == "/World"


def test_particles_round_trip(usd_run):
    """Positions, velocities (m/s) and ids at every time code are the PLY frame's;
    widths are positive, one per particle."""
    out, stage = usd_run
    pts = UsdGeom.Points(stage.GetPrimAtPath("/World/particles"))
    assert pts.GetPointsAttr().GetTimeSamples() == [0.0, 1.0, 2.0, 3.0]
    for n in range(4):
        f = read_particles_ply(out / "frames" / f"frame_{n:05d}.ply")
        np.testing.assert_array_equal(np.asarray(pts.GetPointsAttr().Get(n)), f["x"])
        np.testing.assert_array_equal(np.asarray(pts.GetVelocitiesAttr().Get(n)), f["v"])
        np.testing.assert_array_equal(np.asarray(pts.GetIdsAttr().Get(n)), f["id"])
        widths = np.asarray(pts.GetWidthsAttr().Get(n))
        assert widths.shape == (len(f["x"]),) and (widths > 0).all()
        lo, hi = np.asarray(pts.GetExtentAttr().Get(n))
        assert (lo <= f["x"].min(axis=0)).all() and (hi >= f["x"].max(axis=0)).all()
    # the particles move: the last sample is not the first
    assert not np.array_equal(np.asarray(pts.GetPointsAttr().Get(0)), np.asarray(pts.GetPointsAttr().Get(3)))


def test_colliders_and_surfaces_round_trip(usd_run):
    """The colliders' mesh is time-sampled as it moves (0.5 m/s down: 12.5 mm a frame);
    the surface mesh of every frame is the PLY surface of that frame."""
    out, stage = usd_run
    sheet = UsdGeom.Mesh(stage.GetPrimAtPath("/World/colliders"))
    for n in range(4):
        v, faces = read_mesh_ply(out / "colliders" / f"collider_{n:05d}.ply")
        np.testing.assert_allclose(np.asarray(sheet.GetPointsAttr().Get(n)), v, atol=1e-7)
        np.testing.assert_array_equal(np.asarray(sheet.GetFaceVertexIndicesAttr().Get(n)), faces.ravel())
        assert np.asarray(sheet.GetPointsAttr().Get(n))[:, 1].max() == pytest.approx(0.15 - 0.5 * n / FPS, abs=1e-6)
    water = UsdGeom.Mesh(stage.GetPrimAtPath("/World/surfaces/water"))
    for n in range(4):
        v, faces = read_mesh_ply(out / "surfaces" / f"surface_{n:05d}_water.ply")
        assert len(faces) > 100
        np.testing.assert_allclose(np.asarray(water.GetPointsAttr().Get(n)), v, atol=1e-7)
        np.testing.assert_array_equal(np.asarray(water.GetFaceVertexIndicesAttr().Get(n)), faces.ravel())
        assert set(np.asarray(water.GetFaceVertexCountsAttr().Get(n))) == {3}



def test_a_resumed_run_keeps_the_colliders_of_every_frame(tmp_path):
    """Resumed at frame 2, the USD still holds the moving sheet of frames 0-2 (it held
    only the frames simulated after the resume until 2026-11-27, so USD showed the
    sheet's frame-3 pose in frames 0-2)."""
    scene = water_on_a_falling_sheet("usd_resumed")
    out = tmp_path / "run"
    run(scene, out, frames=2, device="cpu", progress=False)
    run(scene, out, frames=4, device="cpu", progress=False, resume=True)
    stage = Usd.Stage.Open(str(out / "particles.usd"))
    sheet = UsdGeom.Mesh(stage.GetPrimAtPath("/World/colliders"))
    assert sheet.GetPointsAttr().GetTimeSamples() == [0.0, 1.0, 2.0, 3.0, 4.0]
    for n in range(5):
        assert np.asarray(sheet.GetPointsAttr().Get(n))[:, 1].max() == pytest.approx(0.15 - 0.5 * n / FPS, abs=1e-6)

def test_passes_usd_checkers(usd_run):
    """UsdUtils.ComplianceChecker (usd-core <= 25.8, what the tests install) and every
    UsdValidation validator find nothing."""
    out, _ = usd_run
    from pxr import UsdUtils

    assert hasattr(UsdUtils, "ComplianceChecker"), "the test extras pin usd-core < 25.11 for it"
    assert check_compliance(out / "particles.usd") == []


def test_checkers_can_fail(tmp_path):
    """A stage without up axis, units or default prim is refused by the same check."""
    path = tmp_path / "bad.usda"
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.Points.Define(stage, "/particles")
    stage.GetRootLayer().Save()
    found = check_compliance(path)
    assert found and any("upAxis" in f or "metersPerUnit" in f or "default" in f.lower() for f in found), found


def test_surface_command_adds_surfaces_to_the_usd(tmp_path):
    """A run with USD but no surfaces, then ``abmpm surface``: the USD gains them."""
    from abmpm.cli import main

    scene = sm.Scene(
        name="u2", simulation=sm.SimulationSettings(domain_max=(0.4, 0.4, 0.4), dx=0.04),
        materials=[sm.Elastic(name="jelly")],
        bodies=[sm.SphereBody(material="jelly", center=(0.2, 0.2, 0.2), radius=0.1)],
        output=sm.Output(usd=True, preview=False),
    )
    out = tmp_path / "run"
    run(scene, out, frames=1, device="cpu", progress=False)
    assert not Usd.Stage.Open(str(out / "particles.usd")).GetPrimAtPath("/World/surfaces/jelly")
    assert main(["surface", "-q", str(out)]) == 0
    stage = Usd.Stage.Open(str(out / "particles.usd"))
    jelly = UsdGeom.Mesh(stage.GetPrimAtPath("/World/surfaces/jelly"))
    assert len(jelly.GetFaceVertexIndicesAttr().Get(1)) > 300
    assert check_compliance(out / "particles.usd") == []


def test_writer_api(tmp_path):
    """The stage writer alone: a mesh whose topology changes keeps one sample of it per
    change; a closed writer refuses more samples."""
    w = UsdStageWriter(tmp_path / "a.usd", fps=24)
    tri = np.array([[0, 1, 2]])
    w.add_frame(0, np.zeros((2, 3)), 0.01)
    w.add_mesh("/World/m", 0, np.eye(3), tri)
    w.add_mesh("/World/m", 1, np.eye(3) * 2, tri)
    w.add_mesh("/World/m", 2, np.eye(4)[:, :3], np.array([[0, 1, 2], [0, 2, 3]]))
    w.close()
    stage = Usd.Stage.Open(str(tmp_path / "a.usd"))
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/World/m"))
    assert mesh.GetFaceVertexIndicesAttr().GetTimeSamples() == [0.0, 2.0]
    assert mesh.GetPointsAttr().GetTimeSamples() == [0.0, 1.0, 2.0]
    from abmpm.errors import OutputError

    with pytest.raises(OutputError, match="closed"):
        w.add_frame(3, np.zeros((1, 3)), 0.01)
