"""Tests of abmpm.post: renderer, colours, video, plots."""

from __future__ import annotations

import numpy as np

from abmpm.post import (
    Camera,
    colors_by_level,
    colors_by_material,
    colors_by_speed,
    plot_energy,
    render,
    write_mp4,
    write_png,
)


def _sphere(n=3000, seed=0):
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    r = rng.uniform(0, 1, n) ** (1 / 3)
    return 0.5 + 0.3 * d * r[:, None]


def test_render_sphere_not_blank():
    x = _sphere()
    red = np.array([0.9, 0.1, 0.1], dtype=np.float32)
    cam = Camera.framing_box((0, 0, 0), (1, 1, 1), width=160, height=120)
    img = render(x, np.tile(red, (len(x), 1)), cam, radius=0.01, box=((0, 0, 0), (1, 1, 1)))
    assert img.shape == (120, 160, 3) and img.dtype == np.uint8
    assert img.std() > 10.0
    f = img.astype(int)
    reddish = (f[..., 0] > 80) & (f[..., 0] > 2 * f[..., 1]) & (f[..., 0] > 2 * f[..., 2])
    assert reddish.sum() > 500  # the sphere covers a good part of the image
    # centre of the image shows the sphere
    assert reddish[50:70, 70:90].mean() > 0.8


def test_render_depth_order():
    cam = Camera(eye=(0.0, 0.0, 5.0), target=(0.0, 0.0, 0.0), up=(0, 1, 0), fov_deg=30,
                 width=64, height=64)
    near = np.array([[0.0, 0.0, 1.0]])
    far = np.array([[0.0, 0.0, -1.0]])
    red, green = [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]
    for order in (0, 1):  # result must not depend on the input order
        if order == 0:
            x = np.concatenate([near, far]); c = np.array([red, green])
        else:
            x = np.concatenate([far, near]); c = np.array([green, red])
        img = render(x, c, cam, radius=0.3).astype(int)
        centre = img[32, 32]
        assert centre[0] > 100 and centre[1] < 30, centre
    # a lone far particle is visible
    img = render(far, np.array([green]), cam, radius=0.3).astype(int)
    assert img[32, 32, 1] > 100 and img[32, 32, 0] < 30


def test_render_y_up_and_tiny_particles_visible():
    cam = Camera(eye=(0.0, 0.0, 5.0), target=(0.0, 0.0, 0.0), fov_deg=30, width=64, height=64)
    x = np.array([[0.0, 0.8, 0.0]])  # above the centre -> upper half of the image
    img = render(x, [0.0, 0.0, 0.0], cam, radius=1e-6).astype(int)
    dark = np.argwhere(img.sum(axis=2) < 60)
    assert len(dark) >= 1 and np.all(dark[:, 0] < 32)


def test_render_triangles_and_box():
    cam = Camera(eye=(0.0, 0.0, 5.0), target=(0.0, 0.0, 0.0), fov_deg=30, width=64, height=64)
    bg = render(np.zeros((0, 3)), None, cam, 0.1)
    tri = np.array([[[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [0.0, 1.0, 0.0]]])
    img = render(np.zeros((0, 3)), None, cam, 0.1, triangles=tri)
    assert np.abs(img.astype(int) - bg.astype(int)).sum(axis=2)[32, 32] > 10
    assert np.array_equal(img[2, 2], bg[2, 2])
    # a particle in front of the triangle is not tinted; one behind is
    p = render(np.array([[0.0, 0.0, 0.5]]), [1.0, 0.0, 0.0], cam, 0.2, triangles=tri)
    q = render(np.array([[0.0, 0.0, -0.5]]), [1.0, 0.0, 0.0], cam, 0.2, triangles=tri)
    assert int(p[32, 32, 1]) < 10 and int(q[32, 32, 1]) > 40
    boxed = render(np.zeros((0, 3)), None, cam, 0.1, box=((-1, -1, -1), (1, 1, 1)))
    assert (boxed.astype(int).sum(axis=2) < 250).sum() > 50  # dark edges drawn


def test_framing_box_fits_corners():
    lo, hi = np.array([0.0, 0.0, 0.0]), np.array([2.0, 1.0, 0.5])
    cam = Camera.framing_box(lo, hi, width=320, height=200)
    corners = np.array([[x, y, z] for x in (0, 2) for y in (0, 1) for z in (0, 0.5)])
    col, row, depth = cam.project(corners)
    assert np.all(depth > 0)
    assert np.all((col >= 0) & (col < 320) & (row >= 0) & (row < 200))
    eye = np.asarray(cam.eye)
    c = 0.5 * (lo + hi)
    assert eye[0] > c[0] and eye[1] > c[1] and eye[2] > c[2]  # front-right-above


def test_colors():
    m = colors_by_material(np.array([0, 1, 2, 3, 0]))
    assert m.shape == (5, 3) and np.allclose(m[0], m[4]) and not np.allclose(m[0], m[1])
    assert m[0, 2] > m[0, 0]  # water is blue
    mm = colors_by_material(np.array([0, 1]), models=["sand", "fluid"])
    assert mm[1, 2] > mm[1, 0] and mm[0, 0] > mm[0, 2]
    s = colors_by_speed(np.array([[0.0, 0, 0], [3.0, 4.0, 0]]), vmax=5.0)
    assert s.shape == (2, 3) and not np.allclose(s[0], s[1])
    lv = colors_by_level(np.array([0, 1]))
    assert lv[0, 2] > lv[0, 0] and np.all(lv[1] > 0.9)


def test_render_100k_fast():
    import time

    rng = np.random.default_rng(1)
    x = rng.uniform(0, 1, (100_000, 3))
    cam = Camera.framing_box((0, 0, 0), (1, 1, 1))
    t = time.perf_counter()
    img = render(x, colors_by_material(rng.integers(0, 3, len(x))), cam, 0.003,
                 box=((0, 0, 0), (1, 1, 1)))
    dt = time.perf_counter() - t
    assert img.shape == (480, 640, 3)
    assert dt < 2.0  # generous: shared CI machines; typically ~0.15 s


def test_write_mp4_12_frames(tmp_path):
    frames = []
    for i in range(12):
        f = np.zeros((48, 64, 3), dtype=np.uint8)
        f[:, : 5 * (i + 1)] = (200, 50, 50)
        f[10:30, 20:40, 2] = 255
        frames.append(f)
    path = tmp_path / "movie.mp4"
    n = write_mp4(path, iter(frames), fps=12)
    assert n == 12
    import imageio.v2 as imageio

    reader = imageio.get_reader(str(path), format="FFMPEG")
    decoded = [np.asarray(fr) for fr in reader]
    reader.close()
    assert len(decoded) == 12
    assert all(fr.shape == (48, 64, 3) for fr in decoded)
    assert all(fr.std() > 5 for fr in decoded)
    assert [p.name for p in tmp_path.iterdir()] == ["movie.mp4"]


def test_write_mp4_odd_size(tmp_path):
    import imageio.v2 as imageio

    frames = [np.full((31, 45, 3), 10 * i, dtype=np.uint8) for i in range(3)]
    write_mp4(tmp_path / "odd.mp4", frames, fps=10)
    reader = imageio.get_reader(str(tmp_path / "odd.mp4"), format="FFMPEG")
    first = reader.get_data(0)
    reader.close()
    assert first.shape == (32, 46, 3)


def test_write_png(tmp_path):
    import imageio.v3 as iio

    img = (np.arange(20 * 30 * 3) % 256).astype(np.uint8).reshape(20, 30, 3)
    write_png(tmp_path / "a.png", img)
    np.testing.assert_array_equal(iio.imread(tmp_path / "a.png"), img)


def test_plot_energy(tmp_path):
    t = np.linspace(0, 1, 50)
    series = {
        "time": t,
        "kinetic_energy": 0.5 * (9.81 * t) ** 2,
        "mass": np.full(50, 2.0) * (1 + 1e-7 * t),
        "momentum": np.stack([np.zeros(50), -9.81 * t - 1.0, np.zeros(50)], 1),
    }
    path = tmp_path / "energy.png"
    plot_energy(series, path)
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 5000
    assert [p.name for p in tmp_path.iterdir()] == ["energy.png"]


def test_feature_edges_and_outline():
    import trimesh

    from abmpm.geometry.topology import feature_edges

    box = trimesh.creation.box(extents=(1.0, 0.1, 1.0))
    assert len(feature_edges(box.vertices, box.faces)) == 12  # creases only, not the diagonals
    sheet = np.array([[0, 0, 0], [1, 0, 0], [1, 0, 1], [0, 0, 1]], dtype=float)
    faces = np.array([[0, 2, 1], [0, 3, 2]])
    edges = feature_edges(sheet, faces)
    assert sorted(map(tuple, edges)) == [(0, 1), (0, 3), (1, 2), (2, 3)]  # the rim
    cam = Camera(eye=(0.5, 3.0, 0.5), target=(0.5, 0.0, 0.5), up=(0.0, 0.0, -1.0), fov_deg=40,
                 width=64, height=64)
    tris = sheet[faces]
    plain = render(np.zeros((0, 3)), None, cam, 0.1, triangles=tris).astype(int)
    outlined = render(np.zeros((0, 3)), None, cam, 0.1, triangles=tris, edges=sheet[edges]).astype(int)
    darker = (outlined.sum(axis=2) < plain.sum(axis=2) - 100).sum()
    assert darker > 4 * 20  # four sides of ~20+ px
