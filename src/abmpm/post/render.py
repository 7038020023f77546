"""A small vectorised numpy particle splat renderer (no OpenGL).

Conventions: world y is up; images are ``uint8 (H, W, 3)`` with row 0 at the top.
Particles are drawn as shaded sphere impostors (Lambert + ambient) with a z-buffer,
the domain box as thin dark depth-tested edges, and optional collider triangles as
flat-shaded semi-transparent grey surfaces under the depth test, outlined by their
feature edges (rims, holes, creases: see :func:`feature_edges`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

_NEAR = 1e-4
# direction *towards* the light, in camera space (x right, y up, z towards the viewer):
# upper-left-front, so that the front-right-above views look naturally lit.
_LIGHT_CAM = np.array([-0.35, 0.65, 0.68])
_LIGHT_CAM = _LIGHT_CAM / np.linalg.norm(_LIGHT_CAM)
_AMBIENT = 0.35
_DIFFUSE = 0.65
_MAX_FRAGMENTS = 4_000_000  # fragments per chunk (memory bound)
_MAX_SPLAT_RADIUS_PX = 48


def _normalize(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v)
    if n == 0.0:
        raise ValueError("zero-length vector")
    return v / n


@dataclass
class Camera:
    """Pinhole camera. ``fov_deg`` is the vertical field of view."""

    eye: tuple[float, float, float] | np.ndarray
    target: tuple[float, float, float] | np.ndarray
    up: tuple[float, float, float] | np.ndarray = (0.0, 1.0, 0.0)
    fov_deg: float = 40.0
    width: int = 640
    height: int = 480

    # ------------------------------------------------------------------ geometry
    def basis(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Camera axes in world space: right, up, back (back points towards the viewer)."""
        eye = np.asarray(self.eye, dtype=np.float64)
        fwd = _normalize(np.asarray(self.target, dtype=np.float64) - eye)
        up = np.asarray(self.up, dtype=np.float64)
        right = np.cross(fwd, up)
        if np.linalg.norm(right) < 1e-9:  # looking along `up`: pick any perpendicular
            alt = np.array([0.0, 0.0, 1.0]) if abs(fwd[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
            right = np.cross(fwd, alt)
        right = _normalize(right)
        cup = np.cross(right, fwd)
        return right, cup, -fwd

    @property
    def focal_px(self) -> float:
        """Focal length in pixels."""
        return 0.5 * self.height / math.tan(math.radians(self.fov_deg) * 0.5)

    def to_camera(self, p: np.ndarray) -> np.ndarray:
        """World points (..., 3) -> camera coords (..., 3): x right, y up, depth (>0 in front)."""
        right, cup, back = self.basis()
        d = np.asarray(p, dtype=np.float64) - np.asarray(self.eye, dtype=np.float64)
        return np.stack([d @ right, d @ cup, -(d @ back)], axis=-1)

    def project(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World points -> (column, row, depth) in pixels (row 0 at the top)."""
        c = self.to_camera(p)
        z = c[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            f = self.focal_px / z
        col = 0.5 * self.width + c[..., 0] * f
        row = 0.5 * self.height - c[..., 1] * f
        return col, row, z

    # ------------------------------------------------------------------ framing
    @classmethod
    def framing_box(
        cls,
        lo: Sequence[float],
        hi: Sequence[float],
        width: int = 640,
        height: int = 480,
        *,
        azimuth_deg: float = 35.0,
        elevation_deg: float = 25.0,
        fov_deg: float = 35.0,
        margin: float = 0.92,
    ) -> "Camera":
        """A 3/4 view from the front-right-above (+z is front, +x right, +y up) that
        fits all eight corners of the box ``[lo, hi]`` in the image.

        ``margin`` < 1 leaves a border (fraction of the half-extent that is used).
        """
        lo = np.asarray(lo, dtype=np.float64)
        hi = np.asarray(hi, dtype=np.float64)
        center = 0.5 * (lo + hi)
        az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
        d = np.array([math.sin(az) * math.cos(el), math.sin(el), math.cos(az) * math.cos(el)])
        fwd = -d
        right = _normalize(np.cross(fwd, [0.0, 1.0, 0.0]))
        cup = np.cross(right, fwd)
        tan_v = math.tan(math.radians(fov_deg) * 0.5) * margin
        tan_h = tan_v * width / height
        corners = np.array(
            [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
        )
        target = center.copy()
        for _ in range(4):
            rel = corners - target
            a = rel @ right
            b = rel @ cup
            e = rel @ fwd  # depth offset of a corner relative to the target
            # at distance D a corner has depth D + e; need |a| <= tan_h (D + e), |b| <= tan_v (D + e)
            dist = float(np.max(np.maximum(np.abs(a) / tan_h - e, np.abs(b) / tan_v - e)))
            dist = max(dist, float(np.max(-e)) + 1e-3, 1e-3)
            # re-centre: move the target (and eye) sideways so the projected box is centred
            u = a / (dist + e)
            v = b / (dist + e)
            du = 0.5 * (u.max() + u.min())
            dv = 0.5 * (v.max() + v.min())
            if abs(du) < 1e-4 and abs(dv) < 1e-4:
                break
            target = target + (du * right + dv * cup) * dist
        eye = target + d * dist
        center = target
        return cls(
            eye=tuple(eye), target=tuple(center), up=(0.0, 1.0, 0.0),
            fov_deg=fov_deg, width=int(width), height=int(height),
        )


# ---------------------------------------------------------------------- helpers
def _as_colors(colors, n: int) -> np.ndarray:
    """Colours -> float32 (n, 3) in [0, 1]. Accepts (3,), (n,3), (n,4), uint8 or float."""
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


def feature_edges(vertices: np.ndarray, faces: np.ndarray, angle_deg: float = 35.0) -> np.ndarray:
    """Edges worth outlining on a collider mesh, as (K, 2) vertex index pairs: boundary
    edges (rims of sheets, hole outlines: used by one face) and creases (two faces
    whose normals differ by more than ``angle_deg``; the corners of a thin box).

    Rigid motion keeps the angles, so the pairs of one pose serve every frame.
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if len(f) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    face_of = np.tile(np.arange(len(f)), 3)
    order = np.lexsort((e[:, 1], e[:, 0]))
    e, face_of = e[order], face_of[order]
    new = np.ones(len(e), dtype=bool)
    new[1:] = np.any(e[1:] != e[:-1], axis=1)
    start = np.nonzero(new)[0]
    count = np.diff(np.append(start, len(e)))
    keep = count == 1  # boundary
    pair = count == 2
    fa, fb = face_of[start[pair]], face_of[start[pair] + 1]
    # unsigned angle: open sheets and revolved surfaces may be wound either way
    crease = np.abs(np.einsum("ij,ij->i", n[fa], n[fb])) < math.cos(math.radians(angle_deg))
    keep[np.nonzero(pair)[0][crease]] = True
    return e[start[keep]]


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
        colors: (N,3)/(N,4) float in [0,1] or uint8, a single (3,) colour, or None.
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


# ---------------------------------------------------------------------- colours
_MODEL_COLORS = {
    "fluid": (0.22, 0.48, 0.86),  # water blue
    "water": (0.22, 0.48, 0.86),
    "elastic": (0.90, 0.36, 0.46),  # jelly red/pink
    "jelly": (0.90, 0.36, 0.46),
    "viscoelastic": (0.93, 0.55, 0.70),  # pink
    "sand": (0.84, 0.71, 0.48),  # tan
    "snow": (0.95, 0.96, 0.98),  # white
}
# distinct palette by material index (when the model of each material is not given)
PALETTE = np.array(
    [
        (0.22, 0.48, 0.86),  # water blue
        (0.90, 0.36, 0.46),  # jelly red/pink
        (0.84, 0.71, 0.48),  # sand tan
        (0.95, 0.96, 0.98),  # snow white
        (0.35, 0.70, 0.45),  # green
        (0.60, 0.42, 0.78),  # purple
        (0.96, 0.62, 0.25),  # orange
        (0.25, 0.72, 0.74),  # teal
    ],
    dtype=np.float32,
)


def colors_by_material(
    material_ids: np.ndarray, models: Sequence[str] | None = None
) -> np.ndarray:
    """Per-particle RGB float32 (N,3) from material indices.

    Without ``models`` index i gets ``PALETTE[i % 8]`` (blue, pink-red, tan, white, ...).
    With ``models`` (the constitutive model name of each material index, e.g.
    ``["fluid", "sand"]``) the colour follows the model: fluid blue, elastic red/pink,
    viscoelastic pink, sand tan, snow white; materials sharing a model still differ
    slightly in brightness.
    """
    ids = np.asarray(material_ids).astype(np.int64).ravel()
    if models is None:
        table = PALETTE
    else:
        table = np.empty((len(models), 3), dtype=np.float32)
        seen: dict[str, int] = {}
        for i, m in enumerate(models):
            key = str(m).lower()
            base = np.array(_MODEL_COLORS.get(key, PALETTE[i % len(PALETTE)]), dtype=np.float32)
            k = seen.get(key, 0)
            seen[key] = k + 1
            table[i] = np.clip(base * (1.0 - 0.18 * k), 0.0, 1.0) if k else base
        if table.shape[0] == 0:
            table = PALETTE
    return table[np.mod(ids, table.shape[0])]


def colors_by_speed(v: np.ndarray, vmax: float | None = None, cmap: str = "viridis") -> np.ndarray:
    """Per-particle RGB float32 (N,3) from |v| via a matplotlib colormap.

    ``vmax`` defaults to the 99th percentile of the speed (robust to outliers).
    """
    from matplotlib import colormaps

    v = np.asarray(v, dtype=np.float64).reshape(-1, 3)
    speed = np.linalg.norm(v, axis=1)
    if vmax is None:
        vmax = float(np.percentile(speed, 99)) if speed.size else 1.0
    vmax = vmax if vmax > 0 else 1.0
    t = np.clip(speed / vmax, 0.0, 1.0)
    return colormaps[cmap](t)[:, :3].astype(np.float32)


def colors_by_level(level: np.ndarray) -> np.ndarray:
    """Per-particle RGB float32 (N,3) from the refinement level: 0 blue, 1 white,
    higher levels orange/red (as in the paper's figures)."""
    table = np.array(
        [(0.20, 0.42, 0.85), (0.96, 0.96, 0.97), (0.96, 0.60, 0.25), (0.85, 0.25, 0.25)],
        dtype=np.float32,
    )
    lv = np.clip(np.asarray(level).astype(np.int64).ravel(), 0, table.shape[0] - 1)
    return table[lv]
