"""Tests of abmpm.io: PLY, checkpoints, JSON summaries, atomic writes, USD."""

from __future__ import annotations

import json

import numpy as np
import pytest

from abmpm.errors import OutputError
from abmpm.io import (
    atomic_write,
    latest_checkpoint,
    load_checkpoint,
    read_particles_ply,
    save_checkpoint,
    write_json,
    write_particles_ply,
)


@pytest.fixture
def particles():
    rng = np.random.default_rng(7)
    n = 257
    x = rng.uniform(-1.0, 2.0, (n, 3)).astype(np.float32)
    attrs = {
        "v": rng.normal(size=(n, 3)).astype(np.float32),
        "normal": rng.normal(size=(n, 3)).astype(np.float32),
        "mass": rng.uniform(0.1, 1.0, n).astype(np.float32),
        "material": rng.integers(0, 4, n).astype(np.int32),
        "level": rng.integers(0, 2, n).astype(np.uint8),
    }
    return x, attrs


def test_ply_roundtrip_plyfile(tmp_path, particles):
    from plyfile import PlyData

    x, attrs = particles
    path = tmp_path / "frame_00001.ply"
    write_particles_ply(path, x, attrs)
    ply = PlyData.read(str(path))
    assert ply.byte_order == "<" and not ply.text
    vert = ply["vertex"].data
    names = vert.dtype.names
    assert names[:3] == ("x", "y", "z")
    for c in ("vx", "vy", "vz", "normal_x", "normal_y", "normal_z", "mass", "material", "level"):
        assert c in names
    assert vert.dtype["x"] == np.dtype("<f4")
    assert vert.dtype["material"] == np.dtype("<i4")
    assert vert.dtype["level"] == np.dtype("u1")
    np.testing.assert_array_equal(np.stack([vert["x"], vert["y"], vert["z"]], 1), x)
    np.testing.assert_array_equal(np.stack([vert["vx"], vert["vy"], vert["vz"]], 1), attrs["v"])

    back = read_particles_ply(path)
    np.testing.assert_array_equal(back["x"], x)
    for k, a in attrs.items():
        np.testing.assert_array_equal(back[k], a)
        assert back[k].shape == a.shape
    assert set(back) == {"x", *attrs}


def test_ply_roundtrip_trimesh(tmp_path, particles):
    import trimesh

    x, attrs = particles
    path = tmp_path / "p.ply"
    write_particles_ply(path, x, attrs)
    pc = trimesh.load(str(path))
    assert isinstance(pc, trimesh.PointCloud)
    np.testing.assert_array_equal(np.asarray(pc.vertices, dtype=np.float32), x)


def test_ply_int64_and_float64_are_narrowed(tmp_path):
    x = np.arange(12, dtype=np.float64).reshape(4, 3)
    write_particles_ply(tmp_path / "a.ply", x, {"id": np.arange(4, dtype=np.int64),
                                                "phi": np.linspace(0, 1, 4)})
    back = read_particles_ply(tmp_path / "a.ply")
    assert back["x"].dtype == np.float32 and back["id"].dtype == np.int32
    assert back["phi"].dtype == np.float32
    np.testing.assert_array_equal(back["id"], np.arange(4))


def test_ply_bad_shape(tmp_path):
    with pytest.raises(OutputError):
        write_particles_ply(tmp_path / "a.ply", np.zeros((3, 2)), {})
    with pytest.raises(OutputError):
        write_particles_ply(tmp_path / "a.ply", np.zeros((3, 3)), {"m": np.zeros(4)})


def test_atomic_write_success_and_failure(tmp_path):
    target = tmp_path / "out.txt"
    with atomic_write(target) as tmp:
        assert tmp.parent == tmp_path and tmp != target
        tmp.write_text("first")
    assert target.read_text() == "first"
    with pytest.raises(RuntimeError):
        with atomic_write(target) as tmp:
            tmp.write_text("half-writ")
            raise RuntimeError("crash")
    assert target.read_text() == "first"  # untouched
    assert [p.name for p in tmp_path.iterdir()] == ["out.txt"]  # no temp file left


def test_writer_crash_leaves_nothing(tmp_path):
    with pytest.raises(OutputError):
        write_particles_ply(tmp_path / "bad.ply", np.zeros((3, 3)), {"m": np.zeros((3, 2, 2))})
    assert list(tmp_path.iterdir()) == []


def test_checkpoint_bit_exact(tmp_path):
    rng = np.random.default_rng(3)
    arrays = {
        "x": rng.normal(size=(100, 3)).astype(np.float32),
        "F": rng.normal(size=(100, 3, 3)).astype(np.float32),
        "material": rng.integers(-5, 5, 100).astype(np.int32),
        "weird": np.array([np.nan, -0.0, np.inf, 1e-45], dtype=np.float32),
    }
    meta = {"step": np.int64(42), "time": np.float64(0.125), "scene": "dam", "dx": 0.01,
            "shape": (3, 4)}
    path = tmp_path / "checkpoint_00042.npz"
    save_checkpoint(path, arrays, meta)
    with np.load(path, allow_pickle=False) as z:  # must not need pickle
        assert "x" in z.files
    back, meta2 = load_checkpoint(path)
    assert set(back) == set(arrays)
    for k, a in arrays.items():
        assert back[k].dtype == a.dtype and back[k].shape == a.shape
        assert back[k].tobytes() == a.tobytes()
    assert meta2 == {"step": 42, "time": 0.125, "scene": "dam", "dx": 0.01, "shape": [3, 4]}


def test_latest_checkpoint(tmp_path):
    assert latest_checkpoint(tmp_path) is None
    assert latest_checkpoint(tmp_path / "missing") is None
    for n in (3, 12, 7):
        save_checkpoint(tmp_path / f"checkpoint_{n:05d}.npz", {"a": np.zeros(2)}, {"n": n})
    (tmp_path / "checkpoint_99999.npz.tmp").write_text("x")
    (tmp_path / "other_00100.npz").write_text("x")
    best = latest_checkpoint(tmp_path)
    assert best is not None and best.name == "checkpoint_00012.npz"
    assert load_checkpoint(best)[1] == {"n": 12}


def test_write_json_numpy(tmp_path):
    obj = {"n": np.int32(5), "t": np.float32(0.5), "a": np.arange(3), "ok": np.bool_(True),
           "nested": {"v": np.array([[1.5, 2.0]]), "nan": float("nan")}, "tup": (1, 2)}
    path = tmp_path / "sub" / "summary.json"
    write_json(path, obj)
    back = json.loads(path.read_text())
    assert back == {"n": 5, "t": 0.5, "a": [0, 1, 2], "ok": True,
                    "nested": {"v": [[1.5, 2.0]], "nan": None}, "tup": [1, 2]}


def test_usd_points_roundtrip(tmp_path):
    pytest.importorskip("pxr")
    from pxr import Usd, UsdGeom

    from abmpm.io import UsdPointsWriter

    path = tmp_path / "particles.usd"
    w = UsdPointsWriter(path, fps=24)
    frames = [np.full((5, 3), float(i), dtype=np.float32) + np.arange(5)[:, None] for i in range(3)]
    for i, x in enumerate(frames):
        w.add_frame(i, x, 0.01, colors=np.tile([[0.1, 0.2, 0.3]], (5, 1)))
    w.close()
    stage = Usd.Stage.Open(str(path))
    pts = UsdGeom.Points(stage.GetPrimAtPath("/World/particles"))
    got = np.asarray(pts.GetPointsAttr().Get(2), dtype=np.float32)
    np.testing.assert_array_equal(got, frames[2])
    assert stage.GetEndTimeCode() == 2
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.y
    assert len(pts.GetWidthsAttr().Get(1)) == 5


def test_usd_missing_pxr_message(monkeypatch, tmp_path):
    import builtins

    from abmpm.io import usd

    real_import = builtins.__import__

    def fake_import(name, *args, **kwargs):
        if name == "pxr" or name.startswith("pxr."):
            raise ImportError("no pxr")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", fake_import)
    with pytest.raises(OutputError, match="usd-core"):
        usd.UsdPointsWriter(tmp_path / "a.usd", fps=30)
