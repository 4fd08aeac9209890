"""The procedural village (the thesis' drone scene at CPU scale: houses, roofs, chimneys, ground) and vertex colours for
meshes that have none."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import mi_plugins  # noqa: F401
import mitsuba as mi
from mi_plugins.arrays import aligned


@dataclass
class Part:
    """A triangle soup with per-corner UVs and a material name."""

    vertices: np.ndarray  #: (3F, 3)
    uvs: np.ndarray  #: (3F, 2)
    material: str
    kind: str = "body"  #: "chimney" parts are the village's small, erodible pieces


def _quad(p0, p1, p2, p3, tile: float) -> tuple[np.ndarray, np.ndarray]:
    """Two triangles for a planar quad (counter-clockwise seen from outside); planar UVs in world units / tile."""
    p = np.array([p0, p1, p2, p3], float)
    u_axis = p[1] - p[0]
    w = np.linalg.norm(u_axis)
    u_axis /= max(w, 1e-12)
    n = np.cross(p[1] - p[0], p[3] - p[0])
    v_axis = np.cross(n, u_axis)
    v_axis /= max(np.linalg.norm(v_axis), 1e-12)
    uv = np.stack([(p - p[0]) @ u_axis, (p - p[0]) @ v_axis], axis=1) / tile
    idx = [0, 1, 2, 0, 2, 3]
    return p[idx], uv[idx]


def _tri(p0, p1, p2, tile: float):
    p = np.array([p0, p1, p2], float)
    u_axis = (p[1] - p[0]) / max(np.linalg.norm(p[1] - p[0]), 1e-12)
    n = np.cross(p[1] - p[0], p[2] - p[0])
    v_axis = np.cross(n, u_axis)
    v_axis /= max(np.linalg.norm(v_axis), 1e-12)
    return p, np.stack([(p - p[0]) @ u_axis, (p - p[0]) @ v_axis], axis=1) / tile


def _box(lo, hi, tile, top=True):
    x0, y0, z0 = lo
    x1, y1, z1 = hi
    c = [(x0, y0, z0), (x1, y0, z0), (x1, y1, z0), (x0, y1, z0), (x0, y0, z1), (x1, y0, z1), (x1, y1, z1), (x0, y1, z1)]
    # Side walls (outward normals), y up.
    quads = [(4, 5, 6, 7), (1, 0, 3, 2), (0, 4, 7, 3), (5, 1, 2, 6)]
    if top:
        quads.append((7, 6, 2, 3))
    vs, uvs = zip(*[_quad(c[a], c[b], c[cc], c[d], tile) for a, b, cc, d in quads])
    return np.concatenate(vs), np.concatenate(uvs)


def _rotate_y(v: np.ndarray, angle: float, centre: np.ndarray) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    r = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    return (v - centre) @ r.T + centre


def village_parts(n_houses: int, seed: int) -> list[Part]:
    """Houses with gable roofs and chimneys on a ground plane (units: metres-ish, scene ~20 wide)."""
    rng = np.random.default_rng(seed)
    parts: list[Part] = []
    g = 9.0
    v, uv = _quad((-g, 0, g), (g, 0, g), (g, 0, -g), (-g, 0, -g), tile=4.0)
    parts.append(Part(v, uv, "grass"))
    grid = [(x, z) for x in (-6.0, 0.0, 6.0) for z in (-5.0, 3.0)]
    rng.shuffle(grid)
    for h in range(n_houses):
        cx, cz = grid[h % len(grid)]
        cx += rng.uniform(-1, 1)
        cz += rng.uniform(-1, 1)
        w, d, hw = rng.uniform(2.6, 3.8), rng.uniform(2.2, 3.2), rng.uniform(1.8, 2.8)
        rh = rng.uniform(1.0, 1.8)
        ang = rng.uniform(0, np.pi)
        centre = np.array([cx, 0, cz])
        lo, hi = np.array([cx - w / 2, 0, cz - d / 2]), np.array([cx + w / 2, hw, cz + d / 2])
        wv, wuv = _box(lo, hi, tile=1.5, top=False)
        # Gable ends (triangles above the front and back walls).
        t1 = _tri((lo[0], hw, hi[2]), (hi[0], hw, hi[2]), (cx, hw + rh, hi[2]), 1.5)
        t2 = _tri((hi[0], hw, lo[2]), (lo[0], hw, lo[2]), (cx, hw + rh, lo[2]), 1.5)
        wv = np.concatenate([wv, t1[0], t2[0]])
        wuv = np.concatenate([wuv, t1[1], t2[1]])
        parts.append(Part(_rotate_y(wv, ang, centre), wuv, "brick"))
        ov = 0.25  # roof overhang
        # Roof slopes, wound so that their normals point up and out.
        r1 = _quad((lo[0] - ov, hw - 0.1, lo[2] - ov), (lo[0] - ov, hw - 0.1, hi[2] + ov),
                   (cx, hw + rh, hi[2] + ov), (cx, hw + rh, lo[2] - ov), 1.0)
        r2 = _quad((hi[0] + ov, hw - 0.1, hi[2] + ov), (hi[0] + ov, hw - 0.1, lo[2] - ov),
                   (cx, hw + rh, lo[2] - ov), (cx, hw + rh, hi[2] + ov), 1.0)
        parts.append(Part(_rotate_y(np.concatenate([r1[0], r2[0]]), ang, centre),
                          np.concatenate([r1[1], r2[1]]), "roof"))
        # Chimney on one roof side, poking out of the slope.
        px = cx + rng.choice([-1, 1]) * w * 0.22
        pz = cz + rng.uniform(-d / 4, d / 4)
        cw = 0.35
        base = hw + rh * (1 - abs(px - cx) / (w / 2 + ov)) - 0.3
        cv, cuv = _box((px - cw, base, pz - cw), (px + cw, hw + rh + 0.6, pz + cw), tile=1.0)
        parts.append(Part(_rotate_y(cv, ang, centre), cuv, "chimney", kind="chimney"))
    return parts


MATERIALS = {  # scikit-image photograph, linear RGB tint
    "grass": ("grass", (0.20, 0.32, 0.10)),
    "brick": ("brick", (0.60, 0.35, 0.25)),
    "roof": ("gravel", (0.45, 0.20, 0.14)),
    "chimney": ("brick", (0.35, 0.30, 0.28)),
}


def material_texture(name: str, size: int = 256) -> np.ndarray:
    """Linear RGB texture: a real scikit-image photograph (grayscale), normalised and tinted."""
    import skimage.data
    from PIL import Image

    photo, tint = MATERIALS[name]
    g = np.asarray(getattr(skimage.data, photo)(), np.float32)
    if g.ndim == 3:
        g = g.mean(-1)
    g = np.asarray(Image.fromarray(g).resize((size, size), Image.BILINEAR), np.float32)
    g = (g - g.min()) / max(float(g.max() - g.min()), 1e-6)
    return np.clip((0.55 + 0.9 * (g - 0.5))[..., None] * np.asarray(tint, np.float32)[None, None, :] * 1.6, 0, 1)


def part_mesh(part: Part, name: str) -> mi.Mesh:
    n = len(part.vertices)
    mesh = mi.Mesh(name, n, n // 3, has_vertex_texcoords=True)
    p = mi.traverse(mesh)
    p["vertex_positions"] = mi.Float(aligned(part.vertices).ravel())
    p["faces"] = mi.UInt32(aligned(np.arange(n), np.uint32))
    p["vertex_texcoords"] = mi.Float(aligned(part.uvs).ravel())
    p.update()
    return mesh


# -- generic meshes -------------------------------------------------------------------------------------------------


def procedural_colours(v: np.ndarray, seed: int) -> np.ndarray:
    """Smooth seeded per-vertex albedo for meshes without texture (bands + noise)."""
    rng = np.random.default_rng(seed)
    k = rng.normal(size=(6, 3)) * 3.0
    phase = rng.uniform(0, 2 * np.pi, 6)
    f = sum(np.sin(v @ k[i] + phase[i]) for i in range(6)) / 6.0
    base = np.array([0.55, 0.42, 0.30])
    alt = np.array([0.25, 0.35, 0.45])
    t = (0.5 + 0.8 * f)[:, None].clip(0, 1)
    return (base * (1 - t) + alt * t).astype(np.float32)
