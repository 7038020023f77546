"""Surface meshes (``output.surface``, ``abmpm surface``): the enclosed volume of a
resting sphere, closed meshes, particles of two sizes, the CLI and its errors."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest

pytest.importorskip("pysplashsurf")
import trimesh  # noqa: E402

from abmpm.cli import main  # noqa: E402
from abmpm.errors import OutputError  # noqa: E402
from abmpm.io.ply import read_mesh_ply  # noqa: E402
from abmpm.post.surface import surface_meshes  # noqa: E402
from abmpm.runner import run  # noqa: E402
from abmpm.scene.model import Elastic, Fluid, Output, Scene, SimulationSettings, SphereBody  # noqa: E402

R = 0.1  # sphere radius, m: 5 coarse cells of dx 0.02, 10 particle spacings across
SPHERE_VOLUME = 4.0 / 3.0 * np.pi * R**3


def sphere_scene(material, **output) -> Scene:
    """A sphere of particles floating at rest (no gravity): what it meshes to is the
    sphere and nothing else."""
    return Scene(
        name="sphere",
        simulation=SimulationSettings(domain_max=(0.4, 0.4, 0.4), dx=0.02, gravity=(0.0, 0.0, 0.0)),
        materials=[material],
        bodies=[SphereBody(material=material.name, center=(0.2, 0.2, 0.2), radius=R)],
        output=Output(preview=False, **output),
    )


def mesh(v, f) -> trimesh.Trimesh:
    return trimesh.Trimesh(np.asarray(v, dtype=np.float64), np.asarray(f), process=False)


@pytest.mark.parametrize("material", [Fluid(name="water"), Elastic(name="jelly")], ids=["fluid", "solid"])
def test_resting_sphere_volume_and_closed(tmp_path, material):
    """The mesh of a resting sphere encloses the sphere's volume within 3% (the bound the
    surface-mesh issue sets; the defaults reach 0.2% for the smoothed fluid surface and
    2% for the plain solid one) and is closed (watertight, consistently wound, outward
    normals: positive volume). The fluid mesh runs through splashsurf's smoothing and
    decimation, the solid one through plain marching cubes: both paths are held."""
    out = tmp_path / "out"
    summary = run(sphere_scene(material, surface=True), out, frames=1, device="cpu", progress=False)
    assert summary["outputs"]["surfaces"] == "surfaces/surface_NNNNN_<material>.ply"
    assert summary["surface_seconds_per_frame"] > 0
    for frame in (0, 1):
        m = mesh(*read_mesh_ply(out / "surfaces" / f"surface_{frame:05d}_{material.name}.ply"))
        assert m.is_watertight and m.is_winding_consistent
        assert m.body_count == 1
        assert abs(m.volume / SPHERE_VOLUME - 1.0) < 0.03, m.volume / SPHERE_VOLUME
        # every vertex lies near the sphere: within one particle spacing (0.01 m)
        r = np.linalg.norm(m.vertices - 0.2, axis=1)
        assert np.abs(r - R).max() < 0.01


def _lattice(lo, hi, spacing):
    axes = [np.arange(a, b - 1e-9, spacing) + spacing / 2 for a, b in zip(lo, hi)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)


def _mesh_of(x, spacing_of_each, material=None):
    mass = 1000.0 * np.asarray(spacing_of_each) ** 3  # density 1000: volume = spacing^3
    got = surface_meshes({"x": x, "material": np.zeros(len(x), np.int32), "mass": mass},
                         sphere_scene(material or Elastic(name="jelly")))
    assert len(got) == 1
    return mesh(got[0].vertices, got[0].faces)


def test_two_particle_sizes_mesh_as_one_surface():
    """Adaptive runs mix parents (spacing 0.01 here) and their b^3 = 8 children (0.005);
    a solid (the narrow kernel).

    Half a sphere of parents beside half a sphere of children meshes to one closed
    surface enclosing the sphere within 3%, as a sphere of one size does. And a sheet
    of children two fine spacings thick (0.01 m, as in a slit), joined to a block of
    parents, keeps its thickness within 10% (1 mm, 0.4 marching-cubes cells): meshing
    the group at the parents' radius instead makes it 42% too thick (measured 14.2 mm),
    the detail the refinement resolved smeared out."""
    coarse, fine = _lattice((-R,) * 3, (R,) * 3, 0.01), _lattice((-R,) * 3, (R,) * 3, 0.005)
    coarse = coarse[(np.linalg.norm(coarse, axis=1) < R) & (coarse[:, 0] < 0)]
    fine = fine[(np.linalg.norm(fine, axis=1) < R) & (fine[:, 0] >= 0)]
    m = _mesh_of(np.concatenate([coarse, fine]), [0.01] * len(coarse) + [0.005] * len(fine))
    assert m.is_watertight and m.body_count == 1
    assert abs(m.volume / SPHERE_VOLUME - 1.0) < 0.03, m.volume / SPHERE_VOLUME

    block = _lattice((0.0, 0.0, 0.0), (0.1, 0.1, 0.1), 0.01)
    sheet = _lattice((0.1, 0.045, 0.0), (0.2, 0.055, 0.1), 0.005)
    m = _mesh_of(np.concatenate([block, sheet]), [0.01] * len(block) + [0.005] * len(sheet))
    assert m.is_watertight and m.body_count == 1
    v = m.vertices
    mid = (v[:, 0] > 0.13) & (v[:, 0] < 0.17) & (v[:, 2] > 0.03) & (v[:, 2] < 0.07)
    thickness = v[mid, 1].max() - v[mid, 1].min()
    assert abs(thickness - 0.01) < 0.001, thickness


@pytest.mark.parametrize("expansion", [1.5, 2.0])
def test_spread_fluid_stays_one_sheet(expansion):
    """Splashing MPM fluid spreads: particles of rest volume s^3 stand s * J^(1/3)
    apart with J up to 2 (measured in the dam break's splash). A slab of such fluid,
    jittered by a quarter spacing, meshes to one closed sheet without holes (one body,
    Euler number 2). With the solids' narrow kernel it falls apart (measured: 5 pieces
    at J = 1.5, 42 at J = 2)."""
    s = 0.01 * expansion ** (1 / 3)
    x = _lattice((0.0, 0.0, 0.0), (0.3, 0.05, 0.3), s)
    x = x + np.random.default_rng(1).uniform(-0.25, 0.25, x.shape) * s
    m = _mesh_of(x, [0.01] * len(x), Fluid(name="water"))
    assert m.is_watertight and m.body_count == 1 and m.euler_number == 2


def test_surface_command_meshes_a_finished_run(tmp_path, capsys):
    """``abmpm surface DIR`` meshes a run that wrote no surfaces, one mesh per frame,
    the same meshes the run itself would have written."""
    out = tmp_path / "out"
    run(sphere_scene(Fluid(name="water")), out, frames=2, device="cpu", progress=False)
    assert not (out / "surfaces").exists()
    assert main(["surface", str(out)]) == 0
    assert "meshed 3 frames" in capsys.readouterr().out
    names = sorted(p.name for p in (out / "surfaces").iterdir())
    assert names == [f"surface_{i:05d}_water.ply" for i in range(3)]
    v, f = read_mesh_ply(out / "surfaces" / "surface_00002_water.ply")
    assert mesh(v, f).is_watertight


def test_surface_command_errors(tmp_path, capsys):
    """A folder that is not a run, and a run without particle frames: one line each."""
    assert main(["surface", str(tmp_path)]) == 2
    assert "not an abmpm output folder" in capsys.readouterr().err
    out = tmp_path / "noframes"
    run(sphere_scene(Fluid(name="water"), frames=False), out, frames=1, device="cpu", progress=False)
    assert main(["surface", str(out)]) == 2
    err = capsys.readouterr().err
    assert "no particle frames" in err and "Traceback" not in err


def test_surface_needs_pysplashsurf(monkeypatch, tmp_path):
    """Without pysplashsurf, output.surface = true is refused before anything runs."""
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "pysplashsurf" else real(name, *a))
    with pytest.raises(OutputError, match=r"pip install 'abmpm\[surface\]'"):
        run(sphere_scene(Fluid(name="water"), surface=True), tmp_path / "o", frames=1, device="cpu", progress=False)
    assert not (tmp_path / "o" / "frames").exists()


def test_surface_options_validated():
    """Bad [output.surface_mesh] values name the field."""
    from pydantic import ValidationError

    with pytest.raises(ValidationError, match="surface_mesh.radius"):
        Scene.model_validate({**sphere_scene(Fluid(name="w")).model_dump(exclude={"base_dir"}),
                              "output": {"surface": True, "surface_mesh": {"radius": -1.0}}})
