"""A small vectorised numpy particle splat renderer (no OpenGL).

Conventions: world y is up; images are ``uint8 (H, W, 3)`` with row 0 at the top.
Particles are drawn as shaded sphere impostors (Lambert + ambient) with a z-buffer,
the domain box as thin dark depth-tested edges, and optional collider triangles as
flat-shaded semi-transparent grey surfaces under the depth test, outlined by their
feature edges (rims, holes, creases: see :func:`abmpm.geometry.topology.feature_edges`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from abmpm.post.camera import Camera

__all__ = ["Camera", "region_outline", "render"]

_NEAR = 1e-4
# direction *towards* the light, in camera space (x right, y up, z towards the viewer):
# upper-left-front, so that the front-right-above views look naturally lit.
_LIGHT_CAM = np.array([-0.35, 0.65, 0.68])
_LIGHT_CAM = _LIGHT_CAM / np.linalg.norm(_LIGHT_CAM)
_AMBIENT = 0.35
_DIFFUSE = 0.65
_MAX_FRAGMENTS = 4_000_000  # fragments per chunk (memory bound)
_MAX_SPLAT_RADIUS_PX = 48


# ---------------------------------------------------------------------- helpers
def _as_colors(colors, n: int) -> np.ndarray:
    """Colors -> float32 (n, 3) in [0, 1]. Accepts (3,), (n,3), (n,4), uint8 or float."""
    if colors is None:
        return np.tile(np.array([[0.25, 0.5, 0.85]], dtype=np.float32), (n, 1))
    c = np.asarray(colors)
    # uint8 (or any integer array with values above 1) is 0..255
    is_255 = c.dtype == np.uint8 or (
        np.issubdtype(c.dtype, np.integer) and c.size and int(c.max()) > 1
    )
    c = c.astype(np.float32)
    if is_255:
        c = c / 255.0
    if c.ndim == 1:
        c = np.tile(c[None, :3], (n, 1))
    c = c[:, :3]
    if c.shape[0] != n:
        raise ValueError(f"colors has {c.shape[0]} rows, expected {n}")
    return np.clip(c, 0.0, 1.0)


def _background(h: int, w: int) -> np.ndarray:
    t = np.linspace(0.0, 1.0, h, dtype=np.float32)[:, None]
    top = np.array([0.93, 0.94, 0.95], dtype=np.float32)
    bottom = np.array([0.78, 0.79, 0.81], dtype=np.float32)
    g = top[None, :] * (1.0 - t[..., None]) + bottom[None, :] * t[..., None]
    return np.broadcast_to(g, (h, w, 3)).copy()


def _splat_particles(
    camera: Camera, x: np.ndarray, col: np.ndarray, radius: np.ndarray,
    rgb: np.ndarray, depth: np.ndarray,
) -> None:
    """Z-buffered sphere impostors into flat ``rgb`` (H*W,3) and ``depth`` (H*W,)."""
    h, w = camera.height, camera.width
    c = camera.to_camera(x)
    z = c[:, 2]
    keep = z > _NEAR
    if not np.any(keep):
        return
    c, z, col, radius = c[keep], z[keep], col[keep], radius[keep]
    f = camera.focal_px
    px = 0.5 * w + c[:, 0] * f / z
    py = 0.5 * h - c[:, 1] * f / z
    r_px = np.maximum(radius * f / z, 0.75)  # at least a ~1.5 px disc
    # cull particles entirely outside the image
    on = (px + r_px >= 0) & (px - r_px < w) & (py + r_px >= 0) & (py - r_px < h)
    if not np.any(on):
        return
    px, py, z, col, radius, r_px = px[on], py[on], z[on], col[on], radius[on], r_px[on]
    r_px = np.minimum(r_px, _MAX_SPLAT_RADIUS_PX)
    stamp = np.ceil(r_px - 0.5).astype(np.int64)  # stamp half-size in whole pixels
    light = _LIGHT_CAM.astype(np.float32)
    cx = np.floor(px).astype(np.int64)
    cy = np.floor(py).astype(np.int64)
    for s in np.unique(stamp):
        sel = np.nonzero(stamp == s)[0]
        off = np.arange(-s, s + 1)
        ox, oy = np.meshgrid(off, off)
        ox = ox.ravel()
        oy = oy.ravel()
        k = ox.size
        chunk = max(1, _MAX_FRAGMENTS // k)
        for start in range(0, sel.size, chunk):
            idx = sel[start:start + chunk]
            ix = cx[idx, None] + ox[None, :]
            iy = cy[idx, None] + oy[None, :]
            # pixel centre relative to the particle centre, in units of its radius
            inv_r = (1.0 / r_px[idx])[:, None]
            dx = ((ix + 0.5) - px[idx, None]) * inv_r
            dy = ((iy + 0.5) - py[idx, None]) * inv_r
            d2 = dx * dx + dy * dy
            # a pixel whose centre misses a tiny disc still gets the nearest pixel
            inside = (d2 <= 1.0) | ((ox == 0) & (oy == 0))[None, :]
            inside &= (ix >= 0) & (ix < w) & (iy >= 0) & (iy < h)
            if not np.any(inside):
                continue
            d2 = np.minimum(d2, 1.0)
            nz = np.sqrt(1.0 - d2)
            # normal in camera space: x right, y up (rows grow downwards), z to viewer
            shade = _AMBIENT + _DIFFUSE * np.maximum(
                dx * light[0] - dy * light[1] + nz * light[2], 0.0
            )
            fz = z[idx, None] - radius[idx, None] * nz
            pix = (iy * w + ix)[inside]
            fz = fz[inside]
            fshade = shade[inside].astype(np.float32)
            owner = np.broadcast_to(idx[:, None], inside.shape)[inside]
            np.minimum.at(depth, pix, fz)
            win = fz <= depth[pix]
            pix = pix[win]
            rgb[pix] = col[owner[win]] * fshade[win, None]


def _draw_triangles(
    camera: Camera, tris: np.ndarray, color: np.ndarray, tri_rgb: np.ndarray,
    tri_depth: np.ndarray,
) -> None:
    """Rasterise flat-shaded triangles (M,3,3) into flat buffers (nearest wins)."""
    h, w = camera.height, camera.width
    tris = np.asarray(tris, dtype=np.float64).reshape(-1, 3, 3)
    if tris.shape[0] == 0:
        return
    cam = camera.to_camera(tris)  # (M,3,3)
    z = cam[..., 2]
    ok = np.all(z > _NEAR, axis=1)  # drop triangles crossing the near plane
    cam, z = cam[ok], z[ok]
    if cam.shape[0] == 0:
        return
    f = camera.focal_px
    sx = 0.5 * w + cam[..., 0] * f / z
    sy = 0.5 * h - cam[..., 1] * f / z
    # flat shading, two-sided
    n = np.cross(cam[:, 1] - cam[:, 0], cam[:, 2] - cam[:, 0])
    nn = np.linalg.norm(n, axis=1)
    good = nn > 0
    n[good] /= nn[good, None]
    shade = 0.40 + 0.60 * np.abs(n @ np.array([_LIGHT_CAM[0], _LIGHT_CAM[1], -_LIGHT_CAM[2]]))
    x0 = np.clip(np.floor(sx.min(axis=1)), 0, w).astype(np.int64)
    x1 = np.clip(np.ceil(sx.max(axis=1)), 0, w).astype(np.int64)
    y0 = np.clip(np.floor(sy.min(axis=1)), 0, h).astype(np.int64)
    y1 = np.clip(np.ceil(sy.max(axis=1)), 0, h).astype(np.int64)
    bw = x1 - x0
    bh = y1 - y0
    area2 = (sx[:, 1] - sx[:, 0]) * (sy[:, 2] - sy[:, 0]) - (sx[:, 2] - sx[:, 0]) * (sy[:, 1] - sy[:, 0])
    vis = (bw > 0) & (bh > 0) & good & (np.abs(area2) > 1e-12)
    tid_all = np.nonzero(vis)[0]
    counts_all = (bw * bh)[tid_all]
    # process in batches bounded by the number of candidate pixels
    csum = np.cumsum(counts_all)
    start = 0
    while start < tid_all.size:
        base = csum[start - 1] if start > 0 else 0
        end = int(np.searchsorted(csum, base + _MAX_FRAGMENTS, side="right"))
        end = max(end, start + 1)
        tid = tid_all[start:end]
        counts = counts_all[start:end]
        start = end
        tot = int(counts.sum())
        owner = np.repeat(np.arange(tid.size), counts)
        local = np.arange(tot) - np.repeat(np.cumsum(counts) - counts, counts)
        t = tid[owner]
        ix = x0[t] + local % bw[t]
        iy = y0[t] + local // bw[t]
        qx = ix + 0.5
        qy = iy + 0.5
        ax, ay = sx[t, 0], sy[t, 0]
        bx, by = sx[t, 1], sy[t, 1]
        cx, cy = sx[t, 2], sy[t, 2]
        a = area2[t]
        w0 = ((bx - qx) * (cy - qy) - (cx - qx) * (by - qy)) / a
        w1 = ((cx - qx) * (ay - qy) - (ax - qx) * (cy - qy)) / a
        w2 = 1.0 - w0 - w1
        inside = (w0 >= 0) & (w1 >= 0) & (w2 >= 0)
        if not np.any(inside):
            continue
        t, w0, w1, w2 = t[inside], w0[inside], w1[inside], w2[inside]
        pix = (iy * w + ix)[inside]
        # perspective-correct depth: interpolate 1/z
        inv = w0 / z[t, 0] + w1 / z[t, 1] + w2 / z[t, 2]
        fz = 1.0 / inv
        np.minimum.at(tri_depth, pix, fz)
        win = fz <= tri_depth[pix]
        tri_rgb[pix[win]] = color[None, :] * shade[t[win], None]


def _clip_to_front(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Clip camera-space segments (K,3) a -> b to the front of the near plane;
    returns the clipped ends and a mask of the segments that survive."""
    za, zb = a[:, 2], b[:, 2]
    keep = (za > _NEAR) | (zb > _NEAR)
    a, b, za, zb = a[keep].copy(), b[keep].copy(), za[keep], zb[keep]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (_NEAR - za) / (zb - za)
    ca = za <= _NEAR
    a[ca] = a[ca] + s[ca, None] * (b[ca] - a[ca])
    cb = zb <= _NEAR
    b[cb] = a[cb] + s[cb, None] * (b[cb] - a[cb])
    return a, b, keep


def _draw_lines(
    camera: Camera, segments: np.ndarray, rgb: np.ndarray, depth: np.ndarray, color,
    bias: float, alpha: float = 1.0, write_depth: bool = True,
) -> None:
    """One-pixel lines along world-space segments (K,2,3), depth-tested against
    ``depth`` (``bias`` in world units lets a line win over the surface it lies on)."""
    h, w = camera.height, camera.width
    seg = np.asarray(segments, dtype=np.float64).reshape(-1, 2, 3)
    if seg.shape[0] == 0:
        return
    cam = camera.to_camera(seg)
    a, b, _ = _clip_to_front(cam[:, 0], cam[:, 1])
    if a.shape[0] == 0:
        return
    f = camera.focal_px
    pa = a[:, :2] * f / a[:, 2:3]
    pb = b[:, :2] * f / b[:, 2:3]
    # samples every half pixel along each segment (capped for segments far off-screen)
    n = (np.minimum(np.ceil(np.linalg.norm(pb - pa, axis=1) * 2.0), 4 * (w + h)) + 2).astype(np.int64)
    owner = np.repeat(np.arange(len(n)), n)
    t = (np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n)) / np.repeat(n - 1, n)
    p = a[owner] * (1.0 - t[:, None]) + b[owner] * t[:, None]
    px = 0.5 * w + p[:, 0] * f / p[:, 2]
    py = 0.5 * h - p[:, 1] * f / p[:, 2]
    ix = np.floor(px).astype(np.int64)
    iy = np.floor(py).astype(np.int64)
    ok = (ix >= 0) & (ix < w) & (iy >= 0) & (iy < h)
    pix = iy[ok] * w + ix[ok]
    pz = p[ok, 2]
    vis = pz <= depth[pix] + bias
    pix, pz = pix[vis], pz[vis]
    pix, first = np.unique(pix, return_index=True)  # blend each pixel once
    c = np.asarray(color, dtype=np.float32)
    rgb[pix] = c if alpha >= 1.0 else alpha * c + (1.0 - alpha) * rgb[pix]
    if write_depth:
        np.minimum.at(depth, pix, pz[first])


def _draw_box(
    camera: Camera, lo: np.ndarray, hi: np.ndarray, rgb: np.ndarray, depth: np.ndarray,
    color=(0.18, 0.19, 0.21),
) -> None:
    """Twelve thin box edges, depth-tested against (and written into) ``depth``."""
    corners = np.array(
        [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])],
        dtype=np.float64,
    )
    edges = [(i, j) for i in range(8) for j in range(i + 1, 8) if bin(i ^ j).count("1") == 1]
    segments = np.stack([corners[[i for i, _ in edges]], corners[[j for _, j in edges]]], axis=1)
    extent = float(np.linalg.norm(hi - lo))
    _draw_lines(camera, segments, rgb, depth, color, bias=1e-3 * extent)


def render(
    x: np.ndarray,
    colors=None,
    camera: Camera | None = None,
    radius: float | np.ndarray = 0.005,
    box: tuple[Sequence[float], Sequence[float]] | None = None,
    triangles: np.ndarray | None = None,
    *,
    edges: np.ndarray | None = None,
    triangle_color=(0.55, 0.58, 0.64),
    triangle_alpha: float = 0.5,
    edge_color=(0.22, 0.24, 0.28),
    edge_alpha: float = 0.85,
    lines: Sequence[tuple[np.ndarray, Sequence[float]]] = (),
) -> np.ndarray:
    """Render particles to an ``uint8 (H, W, 3)`` image.

    Args:
        x: (N,3) particle positions (world, y up).
        colors: (N,3)/(N,4) float in [0,1] or uint8, a single (3,) color, or None.
        camera: a :class:`Camera`; default frames ``box`` (or the particles' bounds).
        radius: world-space particle radius, scalar or (N,).
        box: ``(lo, hi)`` of the domain, drawn as thin dark edges; None for no box.
        triangles: optional (M,3,3) collider triangles, drawn flat-shaded
            semi-transparent grey under the depth test.
        edges: optional (K,2,3) world-space segments drawn as dark lines over the
            collider (its outline: ``vertices[feature_edges(vertices, faces)]``);
            particles in front of them hide them.
    """
    x = np.asarray(x, dtype=np.float64).reshape(-1, 3)
    n = x.shape[0]
    if camera is None:
        if box is not None:
            camera = Camera.framing_box(box[0], box[1])
        elif n:
            camera = Camera.framing_box(x.min(axis=0), x.max(axis=0))
        else:
            camera = Camera.framing_box((0, 0, 0), (1, 1, 1))
    h, w = int(camera.height), int(camera.width)
    rgb = _background(h, w).reshape(-1, 3)
    depth = np.full(h * w, np.inf)
    if n:
        col = _as_colors(colors, n)
        rad = np.broadcast_to(np.asarray(radius, dtype=np.float64), (n,))
        finite = np.all(np.isfinite(x), axis=1)
        _splat_particles(camera, x[finite], col[finite], np.asarray(rad)[finite], rgb, depth)
    if box is not None:
        _draw_box(camera, np.asarray(box[0], float), np.asarray(box[1], float), rgb, depth)
    if triangles is not None and len(triangles):
        tri_rgb = np.zeros_like(rgb)
        tri_depth = np.full(h * w, np.inf)
        _draw_triangles(
            camera, triangles, np.asarray(triangle_color, dtype=np.float32), tri_rgb, tri_depth
        )
        front = tri_depth < depth
        a = float(triangle_alpha)
        rgb[front] = a * tri_rgb[front] + (1.0 - a) * rgb[front]
    if edges is not None and len(edges):
        seg = np.asarray(edges, dtype=np.float64).reshape(-1, 2, 3)
        extent = float(np.linalg.norm(np.ptp(seg.reshape(-1, 3), axis=0)))
        if box is not None:
            extent = max(extent, float(np.linalg.norm(np.subtract(box[1], box[0]))))
        bias = 2e-3 * extent if math.isfinite(extent) else 0.0  # lines on a surface win over it
        _draw_lines(camera, seg, rgb, depth, edge_color, bias=bias, alpha=edge_alpha, write_depth=False)
    for segments, color in lines:  # e.g. the outline of the refined region
        seg = np.asarray(segments, dtype=np.float64).reshape(-1, 2, 3)
        if len(seg):
            _draw_lines(camera, seg, rgb, depth, color, bias=0.0, alpha=0.9, write_depth=False)
    img = np.clip(rgb.reshape(h, w, 3) * 255.0 + 0.5, 0, 255).astype(np.uint8)
    return img


def region_outline(cells: np.ndarray, origin, dx: float) -> np.ndarray:
    """(K, 2, 3) segments outlining a set of refined grid cells (bool array): the
    edges where the region's boundary surface turns, so a slab reads as a box."""
    cells = np.asarray(cells, dtype=bool)
    if not cells.any():
        return np.zeros((0, 2, 3))
    padded = np.pad(cells, 1)
    segs = []
    # an edge of the cell lattice (along axis a) is on the outline when the 4 cells
    # around it are neither all alike nor two half-planes (a flat face)
    for a in range(3):
        b, c = [k for k in range(3) if k != a]
        m = np.moveaxis(padded, (a, b, c), (0, 1, 2)).astype(np.int8)
        q00, q10, q01, q11 = m[:, :-1, :-1], m[:, 1:, :-1], m[:, :-1, 1:], m[:, 1:, 1:]
        total = q00 + q10 + q01 + q11
        flat = ((q00 == q10) & (q01 == q11)) | ((q00 == q01) & (q10 == q11))
        on = (total > 0) & (total < 4) & ~flat
        idx = np.argwhere(on)  # (i_a, j_b, k_c): edge from corner (i, j, k) to (i+1, j, k) in padded cells
        if len(idx) == 0:
            continue
        start = np.zeros((len(idx), 3))
        start[:, a] = idx[:, 0] - 1
        start[:, b] = idx[:, 1]
        start[:, c] = idx[:, 2]
        end = start.copy()
        end[:, a] += 1
        segs.append(np.stack([start, end], axis=1))
    seg = np.concatenate(segs) if segs else np.zeros((0, 2, 3))
    return np.asarray(origin, dtype=np.float64) + seg * dx
