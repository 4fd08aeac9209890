"""Seeded tileable SVBRDFs (seed 002 §4.1): one generator per family in :data:`FAMILIES` — procedural FFT-filtered noise,
periodic Voronoi cells, woven/tiled/board patterns and scikit-image's photographs made periodic. Every map tiles."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
import mi_plugins  # noqa: F401  (sets the variant and registers ggx_uv)

FAMILIES: tuple[str, ...] = ("fabric", "metal", "stone", "wood", "plaster", "leather", "ceramic", "ground")


@dataclass
class SVBRDF:
    """Tileable material maps over the unit tile; row y of every map is v = (y + ½)/R."""

    name: str
    family: str
    seed: int
    base_color: np.ndarray  #: (R, R, 3) linear RGB in [0, 1]
    normal: np.ndarray  #: (R, R, 3) unit tangent-space normals (z up): fine detail only
    height: np.ndarray  #: (R, R) float32, tile units (the tile spans 1 × 1)
    roughness: np.ndarray  #: (R, R) perceptual roughness in [0, 1] (generators: [0.05, 1])
    metallic: np.ndarray  #: (R, R) in [0, 1]
    specular: float = 0.5  #: ggx_uv's dielectric specular level (F0 = 0.08·specular); §4.1 maps have none

    def __post_init__(self) -> None:
        for k in ("base_color", "normal", "height", "roughness", "metallic"):
            setattr(self, k, np.ascontiguousarray(getattr(self, k), dtype=np.float32))
        r = self.height.shape[0] if self.height.ndim == 2 else -1
        shapes = {"base_color": (r, r, 3), "normal": (r, r, 3), "height": (r, r), "roughness": (r, r),
                  "metallic": (r, r)}
        for k, shape in shapes.items():
            a = getattr(self, k)
            if a.shape != shape or r < 2:
                raise ValueError(f"SVBRDF {self.name}: '{k}' has shape {a.shape}, expected {shape} (R >= 2)")
            if not np.isfinite(a).all():
                raise ValueError(f"SVBRDF {self.name}: '{k}' has non-finite values")
        for k in ("base_color", "roughness", "metallic"):
            a = getattr(self, k)
            if a.min() < 0.0 or a.max() > 1.0:
                raise ValueError(f"SVBRDF {self.name}: '{k}' leaves [0, 1] ({a.min():.3g}..{a.max():.3g})")
        if not (0.0 <= float(self.specular) <= 1.0):
            raise ValueError(f"SVBRDF {self.name}: 'specular' = {self.specular} must be in [0, 1]")
        norm = np.linalg.norm(self.normal, axis=-1)
        if np.abs(norm - 1.0).max() > 1e-3 or self.normal[..., 2].min() <= 0.0:
            raise ValueError(f"SVBRDF {self.name}: 'normal' must hold unit vectors with z > 0")

    @property
    def res(self) -> int:
        return int(self.height.shape[0])


def constant_svbrdf(res: int = 16, albedo=(0.5, 0.5, 0.5), roughness: float = 0.5, metallic: float = 0.0,
                    normal=(0.0, 0.0, 1.0), height: np.ndarray | None = None, specular: float = 0.5,
                    name: str = "constant") -> SVBRDF:
    """Spatially constant maps (optionally over a given height map): the oracle cases of the tests."""
    n = np.asarray(normal, np.float64)
    n = n / np.linalg.norm(n)
    h = np.zeros((res, res), np.float32) if height is None else np.asarray(height, np.float32)
    res = h.shape[0]
    return SVBRDF(name, "constant", 0, np.broadcast_to(np.asarray(albedo, np.float32), (res, res, 3)),
                  np.broadcast_to(n.astype(np.float32), (res, res, 3)), h,
                  np.full((res, res), roughness, np.float32), np.full((res, res), metallic, np.float32), specular)


# -- periodic building blocks -------------------------------------------------------------------


def _grid(res: int) -> tuple[np.ndarray, np.ndarray]:
    """Texel-centre (u, v) coordinates, each (R, R), indexed [y, x]."""
    c = (np.arange(res) + 0.5) / res
    v, u = np.meshgrid(c, c, indexing="ij")
    return u, v


def _fft_noise(rng: np.random.Generator, res: int, beta: float = 2.0, f_lo: float = 1.0,
               f_hi: float | None = None, stretch: tuple[float, float] = (1.0, 1.0)) -> np.ndarray:
    """Zero-mean, unit-std 1/f^β noise: white noise filtered in Fourier space, so periodic by construction.

    Frequencies are in cycles per tile; ``stretch`` = (sx, sy) > 1 suppresses variation along that
    axis (sx > 1 gives streaks along u: brushed metal, wood grain).
    """
    fy = np.fft.fftfreq(res)[:, None] * res
    fx = np.fft.rfftfreq(res)[None, :] * res
    f = np.hypot(fx * stretch[0], fy * stretch[1])
    amp = np.where(f >= f_lo, np.maximum(f, 1e-9) ** (-beta / 2.0), 0.0)
    if f_hi is not None:
        amp = amp * np.exp(-((f / f_hi) ** 2))
    n = np.fft.irfft2(np.fft.rfft2(rng.standard_normal((res, res))) * amp, s=(res, res))
    return ((n - n.mean()) / max(float(n.std()), 1e-12)).astype(np.float32)


def _voronoi(rng: np.random.Generator, res: int, cells: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Periodic jittered-grid Voronoi: (F1, F2, cell id) per texel, distances in grid-cell units."""
    g = max(2, int(round(math.sqrt(cells))))
    pts = rng.uniform(0.0, 1.0, (g, g, 2))  # one feature point per grid cell (wraps: index mod g)
    u, v = _grid(res)
    x, y = u * g, v * g
    ix, iy = np.floor(x).astype(int), np.floor(y).astype(int)
    f1 = np.full((res, res), np.inf)
    f2 = np.full((res, res), np.inf)
    cid = np.zeros((res, res), int)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            cx, cy = ix + dx, iy + dy
            p = pts[cy % g, cx % g]
            d = np.hypot(cx + p[..., 0] - x, cy + p[..., 1] - y)
            closer = d < f1
            f2 = np.where(closer, f1, np.minimum(f2, d))
            cid = np.where(closer, (cy % g) * g + (cx % g), cid)
            f1 = np.minimum(f1, d)
    return f1.astype(np.float32), f2.astype(np.float32), cid


def _smoothstep(e0: float, e1: float, x: np.ndarray) -> np.ndarray:
    t = np.clip((x - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _unit(x: np.ndarray) -> np.ndarray:
    """Rescale to [0, 1] (robust to outliers: 1st/99th percentiles)."""
    lo, hi = np.percentile(x, [1.0, 99.0])
    return np.clip((x - lo) / max(float(hi - lo), 1e-9), 0.0, 1.0).astype(np.float32)


def make_periodic(img: np.ndarray) -> np.ndarray:
    """Blend an image with its half-period rolled copies under sin² windows so that it tiles.

    Four copies (I, I rolled in x, in y, in both) weighted wx·wy, (1−wx)·wy, wx·(1−wy),
    (1−wx)·(1−wy) with wx = sin²(π(x+½)/R): each copy's seam lies where its weight is 0, and at
    the tile border only copies that are continuous across the wrap remain. Deviations from
    the mean are renormalised by 1/√Σw² so the blend keeps the photo's contrast.
    """
    r = img.shape[0]
    w = np.sin(np.pi * (np.arange(r) + 0.5) / r) ** 2
    wy, wx = w[:, None], w[None, :]
    m = float(img.mean())
    d = img - m
    h = r // 2
    copies = (d, np.roll(d, h, 1), np.roll(d, h, 0), np.roll(d, (h, h), (0, 1)))
    weights = (wx * wy, (1 - wx) * wy, wx * (1 - wy), (1 - wx) * (1 - wy))
    out = sum(wk * ck for wk, ck in zip(weights, copies))
    return (m + out / np.sqrt(sum(wk * wk for wk in weights))).astype(np.float32)


def _photo_crop(name: str, rng: np.random.Generator, res: int) -> np.ndarray:
    """A random square crop (random 90° rotation/flip) of a scikit-image photograph, grey in [0, 1]."""
    import skimage.data
    from skimage.transform import resize

    g = np.asarray(getattr(skimage.data, name)(), np.float32)
    if g.ndim == 3:
        g = g[..., :3].mean(-1)
    g /= 255.0
    c = int(rng.integers(min(g.shape) // 3, min(g.shape) * 2 // 3 + 1))
    y0, x0 = (int(rng.integers(0, s - c + 1)) for s in g.shape)
    crop = np.rot90(g[y0:y0 + c, x0:x0 + c], int(rng.integers(4)))
    if rng.random() < 0.5:
        crop = crop[:, ::-1]
    return resize(crop, (res, res), anti_aliasing=True).astype(np.float32)


def _photo(name: str, rng: np.random.Generator, res: int) -> np.ndarray:
    """Tileable photo texture in [0, 1]: random crop made periodic (:func:`make_periodic`)."""
    return _unit(make_periodic(_photo_crop(name, rng, res)))


def _blur(x: np.ndarray, cycles: float) -> np.ndarray:
    """Periodic Gaussian low-pass keeping frequencies up to ~``cycles`` per tile."""
    r = x.shape[0]
    fy = np.fft.fftfreq(r)[:, None] * r
    fx = np.fft.rfftfreq(r)[None, :] * r
    return np.fft.irfft2(np.fft.rfft2(x) * np.exp(-(fx**2 + fy**2) / (2 * cycles**2)), s=x.shape).astype(np.float32)


def _detail_normal(d: np.ndarray, rms_slope: float) -> np.ndarray:
    """Unit normals of a fine detail height d (periodic differences), scaled to an RMS slope."""
    gx = 0.5 * (np.roll(d, -1, 1) - np.roll(d, 1, 1))
    gy = 0.5 * (np.roll(d, -1, 0) - np.roll(d, 1, 0))
    s = rms_slope / max(float(np.sqrt(np.mean(gx**2 + gy**2))), 1e-12)
    n = np.stack([-gx * s, -gy * s, np.ones_like(d)], -1)
    return (n / np.linalg.norm(n, axis=-1, keepdims=True)).astype(np.float32)


def _colour(rng: np.random.Generator, base: Sequence[float], jitter: float = 0.15) -> np.ndarray:
    """A base linear-RGB colour with a random log-space tint."""
    return np.clip(np.asarray(base, np.float32) * np.exp(rng.normal(0.0, jitter, 3)), 0.0, 1.0).astype(np.float32)


def _ptp(h: np.ndarray, ptp: float) -> np.ndarray:
    """Height rescaled to [0, ptp] (tile units)."""
    return ((h - h.min()) * (ptp / max(float(np.ptp(h)), 1e-12))).astype(np.float32)


# -- families -----------------------------------------------------------------------------------
# Each returns (base_color, detail height for the normal map, RMS detail slope, height, roughness,
# metallic); heights are rescaled by the caller's per-family ptp range.

Maps = tuple[np.ndarray, np.ndarray, float, np.ndarray, np.ndarray, np.ndarray]


def _fabric(rng: np.random.Generator, res: int) -> Maps:
    n = 2 * int(rng.integers(5, 13))  # threads per tile; even so the over/under parity wraps
    u, v = _grid(res)
    x, y = n * u + rng.random(), n * v + rng.random()  # random phase: the seam is a typical column
    ix, iy = np.floor(x), np.floor(y)
    fx, fy = x - ix, y - iy
    # Plain weave: the warp (along v) is on top where the weft (along u) is below, alternating per cell.
    warp = np.sin(np.pi * fx) ** 0.6 * (0.35 + 0.65 * (0.5 + 0.5 * np.cos(np.pi * (y - 0.5 - ix))))
    weft = np.sin(np.pi * fy) ** 0.6 * (0.35 + 0.65 * (0.5 - 0.5 * np.cos(np.pi * (x - 0.5 - iy))))
    on_warp = warp >= weft
    top = np.maximum(warp, weft)
    jit = rng.normal(0.0, 0.08, (2, n))
    c_warp = _colour(rng, rng.uniform(0.1, 0.8, 3), 0.1)
    c_weft = c_warp if rng.random() < 0.5 else _colour(rng, rng.uniform(0.1, 0.8, 3), 0.1)
    shade = 1.0 + np.where(on_warp, jit[0, ix.astype(int) % n], jit[1, iy.astype(int) % n])
    base = np.where(on_warp[..., None], c_warp, c_weft) * ((0.6 + 0.4 * top) * shade)[..., None]
    along_v, along_u = _fft_noise(rng, res, 1.0, 8, stretch=(1, 6)), _fft_noise(rng, res, 1.0, 8, stretch=(6, 1))
    fibres = np.where(on_warp, along_v, along_u)
    height = top + 0.08 * _fft_noise(rng, res, 2.0, 4)
    rough = rng.uniform(0.65, 0.95) + 0.05 * _fft_noise(rng, res, 2.0)
    return base, fibres, 0.25, height, rough, np.zeros((res, res))


def _metal(rng: np.random.Generator, res: int) -> Maps:
    tint = [(0.56, 0.57, 0.58), (0.91, 0.92, 0.92), (1.0, 0.78, 0.34), (0.95, 0.64, 0.54), (0.53, 0.51, 0.49),
            (0.91, 0.78, 0.50)][int(rng.integers(6))]
    stretch = (12.0, 1.0) if rng.random() < 0.5 else (1.0, 12.0)  # brushing along u or v
    brushed = _fft_noise(rng, res, 1.0, 2, stretch=stretch)
    u, v = _grid(res)
    scratches = np.zeros((res, res), np.float32)
    for _ in range(int(rng.integers(3, 12))):
        a, b = (int(t) for t in rng.integers(-3, 4, 2))  # integer direction: straight periodic line
        if a == 0 and b == 0:
            continue
        t = (a * u + b * v + rng.random()) % 1.0
        line = np.exp(-(((np.minimum(t, 1 - t)) * res / rng.uniform(0.5, 1.5)) ** 2))
        seg = _smoothstep(0.3, 0.8, _fft_noise(rng, res, 3.0))  # only parts of each line are scratched
        scratches = np.maximum(scratches, line * seg)
    grime = _smoothstep(0.5, 1.5, _fft_noise(rng, res, 3.0)) * rng.uniform(0.0, 1.0)
    base = _colour(rng, tint, 0.04) * (1.0 + 0.03 * brushed)[..., None]
    base = base * (1 - grime[..., None]) + grime[..., None] * _colour(rng, (0.12, 0.08, 0.05), 0.2)
    height = _fft_noise(rng, res, 3.5) + 0.1 * brushed - 0.3 * scratches
    # Roughness ≥ 0.2 (α ≥ 0.04): with 64 random direction pairs per texel (the paper: 400) a narrower
    # lobe is hit by almost no sample, so its highlight can be neither learned nor measured at this size.
    rough = rng.uniform(0.2, 0.45) + 0.03 * brushed + 0.15 * scratches + 0.6 * grime
    return base, brushed - 2.0 * scratches, 0.06, height, rough, 1.0 - grime


def _stone(rng: np.random.Generator, res: int) -> Maps:
    f1, f2, cid = _voronoi(rng, res, int(rng.integers(9, 40)))
    gravel = _photo("gravel", rng, res)
    dome = np.sqrt(_smoothstep(0.0, rng.uniform(0.15, 0.4), f2 - f1))  # rounded stones, mortar between
    cell_h = rng.uniform(0.6, 1.0, cid.max() + 1)[cid]
    height = dome * cell_h + 0.35 * gravel
    cell_tone = rng.normal(1.0, 0.12, cid.max() + 1)[cid]
    stone = _colour(rng, (0.35, 0.32, 0.28), 0.15)
    base = stone * (cell_tone * (0.55 + 0.7 * gravel))[..., None]
    mortar = _colour(rng, (0.25, 0.24, 0.22), 0.1) * (0.8 + 0.3 * gravel)[..., None]
    base = np.where((dome < 0.3)[..., None], mortar, base)
    rough = rng.uniform(0.55, 0.85) + 0.15 * (1 - dome)
    return base, _fft_noise(rng, res, 0.5, 16), 0.15, height, rough, np.zeros((res, res))


def _wood(rng: np.random.Generator, res: int) -> Maps:
    nb = int(rng.integers(2, 6))  # boards along v, grain along u
    u, v = _grid(res)
    y = nb * v + rng.random()
    b = np.floor(y).astype(int) % nb
    fb = y - np.floor(y)
    gap = rng.uniform(0.01, 0.03)
    groove = _smoothstep(0.0, gap, fb) * _smoothstep(0.0, gap, 1.0 - fb)
    warp = _fft_noise(rng, res, 3.0, 1, stretch=(4.0, 1.0))
    rings = (rng.uniform(4, 12) * fb + 0.6 * warp + rng.random(nb)[b] * 10.0) % 1.0
    late = rings**4  # dark latewood at the end of each ring
    grain = _fft_noise(rng, res, 1.0, 4, stretch=(16.0, 1.0))
    light = _colour(rng, (0.55, 0.33, 0.16), 0.2)
    dark = light * rng.uniform(0.35, 0.6)
    tone = rng.normal(1.0, 0.1, nb)[b] * (1.0 + 0.05 * grain)
    base = (light * (1 - late[..., None]) + dark * late[..., None]) * tone[..., None] * (0.3 + 0.7 * groove)[..., None]
    height = groove + 0.05 * late + 0.02 * grain
    rough = rng.uniform(0.25, 0.7) + 0.1 * late + 0.3 * (1 - groove)
    return base, grain, 0.08, height, rough, np.zeros((res, res))


def _plaster(rng: np.random.Generator, res: int) -> Maps:
    brick = _blur(_photo("brick", rng, res), rng.uniform(6, 16))  # plaster over a brick wall
    bumps = _fft_noise(rng, res, 3.5)
    height = bumps + rng.uniform(0.5, 2.0) * (brick - brick.mean()) / max(float(brick.std()), 1e-6)
    colour = _colour(rng, (0.8, 0.78, 0.72) if rng.random() < 0.6 else rng.uniform(0.4, 0.85, 3), 0.08)
    mottle = 0.05 * _fft_noise(rng, res, 2.5) + 0.05 * (brick - brick.mean()) / max(float(brick.std()), 1e-6)
    base = colour * (1.0 + mottle)[..., None]
    rough = rng.uniform(0.8, 0.95) + 0.05 * _fft_noise(rng, res, 2.0)
    return base, _fft_noise(rng, res, 0.0, 32), 0.2, height, rough, np.zeros((res, res))


def _leather(rng: np.random.Generator, res: int) -> Maps:
    f1, f2, cid = _voronoi(rng, res, int(rng.integers(60, 200)))
    crease = 1.0 - _smoothstep(0.0, rng.uniform(0.08, 0.2), f2 - f1)
    folds = _fft_noise(rng, res, 3.0)
    height = -crease + 0.5 * folds + 0.3 * np.sqrt(np.clip(f2 - f1, 0, None))
    hides = [(0.25, 0.12, 0.05), (0.04, 0.035, 0.03), (0.35, 0.08, 0.05), (0.5, 0.35, 0.2)]  # brown, black, red, tan
    colour = _colour(rng, hides[int(rng.integers(4))], 0.1)
    base = colour * (1.0 - 0.35 * crease + 0.06 * _fft_noise(rng, res, 2.0))[..., None]
    rough = rng.uniform(0.35, 0.65) + 0.2 * crease
    return base, _fft_noise(rng, res, 0.0, 24), 0.12, height, rough, np.zeros((res, res))


def _ceramic(rng: np.random.Generator, res: int) -> Maps:
    nt = int(rng.integers(2, 6))  # tiles per side
    u, v = _grid(res)
    x, y = nt * u + rng.random(), nt * v + rng.random()
    ix, iy = np.floor(x).astype(int) % nt, np.floor(y).astype(int) % nt
    edge = np.minimum.reduce([x % 1.0, 1 - x % 1.0, y % 1.0, 1 - y % 1.0])  # distance to the tile edge
    gw = rng.uniform(0.02, 0.05)
    tile = _smoothstep(gw, gw + rng.uniform(0.02, 0.06), edge)  # bevelled tile, grout groove between
    brick = _photo("brick", rng, res)  # glaze mottling from a real photograph
    glaze = _colour(rng, rng.uniform(0.1, 0.9, 3), 0.1)
    per_tile = rng.normal(1.0, 0.04, (nt, nt))[iy, ix]
    base = glaze * (per_tile * (0.94 + 0.12 * brick))[..., None]
    base = base * tile[..., None] + _colour(rng, (0.45, 0.44, 0.42), 0.1) * (1 - tile)[..., None]
    height = tile + 0.03 * _fft_noise(rng, res, 3.0)
    rough = tile * rng.uniform(0.12, 0.3) + (1 - tile) * 0.9  # glaze: see _metal on lobe width vs slices
    return base, _fft_noise(rng, res, 1.5, 8), 0.02, height, rough, np.zeros((res, res))


def _ground(rng: np.random.Generator, res: int) -> Maps:
    gravel = _photo("gravel", rng, res)
    grass = _photo("grass", rng, res)
    mask = _smoothstep(-0.3, 0.3, _fft_noise(rng, res, 3.0) + rng.uniform(-1.0, 1.0))  # grass patches
    height = 0.7 * gravel + 0.6 * grass * mask
    soil = _colour(rng, (0.3, 0.22, 0.14), 0.12) * (0.5 + 0.8 * gravel)[..., None]
    green = _colour(rng, (0.12, 0.2, 0.05), 0.2) * (0.4 + 1.0 * grass)[..., None]
    base = soil * (1 - mask[..., None]) + green * mask[..., None]
    rough = rng.uniform(0.8, 0.95) + 0.05 * _fft_noise(rng, res, 2.0)
    return base, _fft_noise(rng, res, 0.5, 16), 0.2, height, rough, np.zeros((res, res))


_GENERATORS: dict[str, tuple[Callable[[np.random.Generator, int], Maps], tuple[float, float]]] = {
    # family: (generator, peak-to-peak height range in tile units)
    "fabric": (_fabric, (0.015, 0.03)),
    "metal": (_metal, (0.01, 0.025)),
    "stone": (_stone, (0.06, 0.12)),
    "wood": (_wood, (0.02, 0.05)),
    "plaster": (_plaster, (0.02, 0.05)),
    "leather": (_leather, (0.02, 0.04)),
    "ceramic": (_ceramic, (0.03, 0.06)),
    "ground": (_ground, (0.06, 0.12)),
}


def make_svbrdf(family: str, seed: int, res: int = 256) -> SVBRDF:
    """A tileable SVBRDF of a family (seed 002 §4.1's material maps), deterministic in (family, seed, res)."""
    if family not in _GENERATORS:
        raise ValueError(f"unknown SVBRDF family '{family}'; valid: {', '.join(FAMILIES)}")
    if int(res) < 16:
        raise ValueError(f"make_svbrdf: res = {res} must be >= 16")
    if int(seed) < 0:
        raise ValueError(f"make_svbrdf: seed = {seed} must be >= 0")
    gen, (lo, hi) = _GENERATORS[family]
    rng = np.random.default_rng([int(seed), FAMILIES.index(family)])
    base, detail, slope, height, rough, metal = gen(rng, int(res))
    return SVBRDF(
        name=f"{family}_{seed}", family=family, seed=int(seed),
        base_color=np.clip(base, 0.0, 1.0),
        normal=_detail_normal(detail, slope * rng.uniform(0.7, 1.3)),
        height=_ptp(height, rng.uniform(lo, hi)),
        roughness=np.clip(rough, 0.05, 1.0),
        metallic=np.clip(metal, 0.0, 1.0),
    )
