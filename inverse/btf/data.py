"""BTF training data rendered with Mitsuba from SVBRDFs (seed 002 §4.1, CPU-sized).

Seed 002 §4.1 renders each SVBRDF (base colour, normal, height, roughness,
metallic) as a BTF: the height map becomes a densely tessellated, displaced
plane instanced 3×3 (so texels near the tile border see their neighbours), and
every texel gets N_s random (light, view) pairs, each path traced with a ray
towards the texel footprint along −ω_o, lit by a 2°-wide sun of unit
irradiance. Here the same recipe runs at CPU scale (64² texels × 64 slices by
default) with:

* **SVBRDFs** from seeded generators, one per family in :data:`FAMILIES`
  (:func:`make_svbrdf`): procedural FFT-filtered noise, periodic Voronoi cells,
  woven/tiled/board patterns, and scikit-image's shipped photographs (gravel,
  grass, brick) made periodic. Every map tiles.
* **Geometry**: one ``mi.Mesh`` covering [−1, 2]² (the 3×3 tiling of the unit
  tile) at z = height − mean(height), with UV = world (x, y), so the texture
  repeat and the geometry agree; vertex normals from periodic differences.
* **Material**: :mod:`mi_plugins.bsdfs.ggx_uv` with raw (linear) bitmap
  textures, bilinear, repeat-wrapped; constant ``specular`` (0.5 for every family).
* **Light transport**: a small path tracer in Dr.Jit (:func:`render_btf`):
  next-event estimation towards the sun at every vertex with a shadow ray,
  continuation by BSDF sampling up to ``max_depth`` vertices, so self-shadowing
  and interreflection are in the data. The sun is a uniform disk of angular
  diameter ``sun_diameter_deg`` (2°, as in §4.1) around ω_i, normalised to unit
  irradiance on a surface perpendicular to ω_i; ``sun_diameter_deg = 0`` is a
  directional light. Rays that miss the surface return 0 (no environment).

Conventions (the neural BTF plugin relies on these):

* Texel (y, x) of a ``tex_res`` × ``tex_res`` BTF covers u ∈ [x/W, (x+1)/W],
  v ∈ [y/H, (y+1)/H]; map row y of every SVBRDF map is v = (y + ½)/R (that is
  how Mitsuba's bitmap texture reads a row-major array).
* Tangent frame: x along +u, y along +v, z up; ω_i (towards the light) and
  ω_o (towards the viewer) are unit vectors in it with θ ≤ ``max_theta_deg``.
* Reference plane z = 0 = the mean height: camera rays aim at a jittered point
  of the texel's footprint on that plane (anti-aliasing and parallax included).
* :data:`CONVENTION`: a value is the outgoing radiance towards ω_o under a
  distant light of unit perpendicular irradiance from ω_i — for a flat surface
  exactly f(u, ω_i, ω_o)·cos θ_i, i.e. Mitsuba's
  ``bsdf.eval(ctx, si(wi=ω_o), wo=ω_i)``. Values are stored as float16,
  clipped to 65504 (float16's maximum; reached only by near-mirror peaks).
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

import mi_plugins  # noqa: F401  (sets the variant and registers ggx_uv)
import drjit as dr
import mitsuba as mi
from mi_plugins.arrays import aligned

from foundation.errors import UsageError
from foundation.files import atomic_path, check_output_dir
from foundation.progress import progress_bar

from .svbrdf import FAMILIES, SVBRDF, make_svbrdf


CONVENTION = (
    "value = outgoing radiance towards wo under a distant light of unit perpendicular irradiance from wi "
    "= f(u, wi, wo) * cos(theta_i) for a flat BRDF = mitsuba bsdf.eval(ctx, si(wi=wo), wo=wi); "
    "tangent frame x=+u, y=+v, z=up; texel (y, x) spans u in [x/W, (x+1)/W], v in [y/H, (y+1)/H]; "
    "camera rays aim at the texel footprint on the plane z = mean height"
)
FORMAT_VERSION = 1
_F16_MAX = 65504.0
_CHUNK_LANES = 1 << 20  # paths traced per kernel launch: bounds memory, amortises tracing


class BTFDataError(UsageError):
    """A BTF file is missing, unreadable or inconsistent (the message names the file)."""


# =============================================================================================
# SVBRDFs
# =============================================================================================




# =============================================================================================
# Rendering
# =============================================================================================


@dataclass
class BTFRenderSettings:
    """BTF rendering parameters (seed 002 §4.1 uses 512² texels, 400 slices, 128 spp; CPU-sized here)."""

    tex_res: int = 64  #: BTF texels per side
    slices: int = 64  #: random (light, view) pairs per texel, N_s
    spp: int = 16  #: paths per texel and slice
    max_depth: int = 3  #: path vertices (1 = direct light only)
    mesh_res: int = 128  #: quads per side of one tile of displaced geometry
    max_theta_deg: float = 80.0  #: directions are uniform on the hemisphere cap θ ≤ this
    seed: int = 0
    sun_diameter_deg: float = 2.0  #: angular diameter of the sun (0 = directional light)

    def __post_init__(self) -> None:
        ints = {"tex_res": 1, "slices": 1, "spp": 1, "max_depth": 1, "mesh_res": 2, "seed": 0}
        for name, lo in ints.items():
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < lo:
                raise ValueError(f"BTFRenderSettings: '{name}' = {value!r} must be an integer >= {lo}")
        if not (0.0 < float(self.max_theta_deg) < 90.0):
            raise ValueError(f"BTFRenderSettings: 'max_theta_deg' = {self.max_theta_deg} must be in (0, 90)")
        if not (0.0 <= float(self.sun_diameter_deg) <= 10.0):
            raise ValueError(f"BTFRenderSettings: 'sun_diameter_deg' = {self.sun_diameter_deg} must be in [0, 10]")


@dataclass
class BTFData:
    """Rendered BTF: ``values[s, y, x]`` for directions ``wi[s, y, x]`` (light), ``wo[s, y, x]`` (view)."""

    values: np.ndarray  #: (S, H, W, 3) float16, see CONVENTION
    wi: np.ndarray  #: (S, H, W, 3) float32 unit, towards the light, tangent frame
    wo: np.ndarray  #: (S, H, W, 3) float32 unit, towards the viewer, tangent frame
    meta: dict = field(default_factory=dict)


def sample_directions(n: tuple[int, ...], max_theta_deg: float, rng: np.random.Generator) -> np.ndarray:
    """Unit vectors uniform (in solid angle) on the cap θ ≤ max_theta_deg, shape n + (3,)."""
    cos_t = rng.uniform(math.cos(math.radians(max_theta_deg)), 1.0, n)
    phi = rng.uniform(0.0, 2.0 * math.pi, n)
    sin_t = np.sqrt(np.maximum(1.0 - cos_t**2, 0.0))
    return np.stack([sin_t * np.cos(phi), sin_t * np.sin(phi), cos_t], -1).astype(np.float32)


def _slice_directions(svbrdf: SVBRDF, s: BTFRenderSettings, k: int) -> tuple[np.ndarray, np.ndarray]:
    """(wi, wo) of slice k, (H, W, 3) each: seeded per slice, so chunking never changes the data."""
    rng = np.random.default_rng([s.seed, svbrdf.seed, k])
    shape = (s.tex_res, s.tex_res)
    return sample_directions(shape, s.max_theta_deg, rng), sample_directions(shape, s.max_theta_deg, rng)


def _bitmap(a: np.ndarray) -> mi.Texture:
    # raw: the maps are linear data (no sRGB decoding); repeat: the tile is periodic.
    return mi.load_dict({"type": "bitmap", "data": mi.TensorXf(aligned(a)), "raw": True,
                         "filter_type": "bilinear", "wrap_mode": "repeat"})


def make_bsdf(svbrdf: SVBRDF) -> mi.BSDF:
    """``ggx_uv`` with the SVBRDF's maps as raw, bilinear, repeat-wrapped bitmap textures (constant specular)."""
    return mi.load_dict({
        "type": "ggx_uv",
        "albedo": _bitmap(svbrdf.base_color),
        "normal": _bitmap(svbrdf.normal * 0.5 + 0.5),  # ggx_uv decodes n = 2·rgb − 1
        "roughness": _bitmap(svbrdf.roughness[..., None]),
        "metallic": _bitmap(svbrdf.metallic[..., None]),
        "specular": float(svbrdf.specular),
    })


def _periodic_bilinear(h: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear lookup of a periodic map (texel centres at (i + ½)/R) at (u, v)."""
    r = h.shape[0]
    x, y = u * r - 0.5, v * r - 0.5
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    tx, ty = x - x0, y - y0
    x0, y0, x1, y1 = x0 % r, y0 % r, (x0 + 1) % r, (y0 + 1) % r
    return (h[y0, x0] * (1 - tx) * (1 - ty) + h[y0, x1] * tx * (1 - ty)
            + h[y1, x0] * (1 - tx) * ty + h[y1, x1] * tx * ty)


def height_mesh(height: np.ndarray, mesh_res: int, bsdf: mi.BSDF | None = None, tiles: int = 3) -> mi.Mesh:
    """The displaced tile repeated tiles×tiles (3×3: [−1, 2]²) as one mesh, z = height − mean, UV = (x, y).

    One mesh with continuous UVs instead of nine instances: same geometry, no seams between copies,
    and the textures' repeat wrap maps every copy onto the same texels.
    """
    if tiles < 1 or tiles % 2 == 0:
        raise ValueError(f"height_mesh: 'tiles' = {tiles} must be odd and >= 1 (the unit tile sits in the middle)")
    m = mesh_res
    c = np.arange(m) / m
    vv, uu = np.meshgrid(c, c, indexing="ij")
    z = _periodic_bilinear(height.astype(np.float64), uu, vv) - float(height.mean())  # reference plane z = 0
    # Vertex normals from periodic central differences: no seam at the tile (or 3×3) borders.
    dzdu = (np.roll(z, -1, 1) - np.roll(z, 1, 1)) * (m / 2.0)
    dzdv = (np.roll(z, -1, 0) - np.roll(z, 1, 0)) * (m / 2.0)
    nrm = np.stack([-dzdu, -dzdv, np.ones_like(z)], -1)
    nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
    n = tiles * m + 1
    idx = np.arange(n) % m
    g = np.arange(n) / m - (tiles - 1) // 2
    gy, gx = np.meshgrid(g, g, indexing="ij")
    pos = np.stack([gx, gy, z[np.ix_(idx, idx)]], -1).reshape(-1, 3)
    nor = nrm[np.ix_(idx, idx)].reshape(-1, 3)
    a = (np.arange(n - 1)[:, None] * n + np.arange(n - 1)[None, :]).ravel()
    # Counter-clockwise seen from +z, so geometric normals point up.
    faces = np.concatenate([np.stack([a, a + 1, a + n + 1], 1), np.stack([a, a + n + 1, a + n], 1)])
    props = mi.Properties()
    if bsdf is not None:
        props["bsdf"] = bsdf
    mesh = mi.Mesh("btf_tile", len(pos), len(faces), props, has_vertex_normals=True, has_vertex_texcoords=True)
    p = mi.traverse(mesh)
    p["vertex_positions"] = mi.Float(aligned(pos).ravel())
    p["vertex_normals"] = mi.Float(aligned(nor).ravel())
    p["vertex_texcoords"] = mi.Float(aligned(pos[:, :2]).ravel())
    p["faces"] = mi.UInt32(aligned(faces, np.uint32).ravel())
    p.update()
    return mesh


def _trace_chunk(scene: mi.Scene, bsdf: mi.BSDF, wi_np: np.ndarray, wo_np: np.ndarray, s: BTFRenderSettings,
                 seed: int, lane0: int, z_top: float) -> tuple[np.ndarray, int]:
    """Mean radiance of ``spp`` paths per texel for a chunk of slices; (values (k, H, W, 3), #non-finite paths).

    The kernel depends only on the settings (constants) — the chunk's data, seeds and the relief's
    height are opaque inputs, its directions aligned host arrays — so Dr.Jit compiles it once per
    material shape and reuses it for every chunk and material (a literal height compiled it anew per material).
    """
    k, h, w = wi_np.shape[:3]
    n_tex = k * h * w
    lanes = n_tex * s.spp
    idx = dr.arange(mi.UInt32, lanes)
    tex = idx // s.spp
    pix = tex % (h * w)
    # Per-lane PCG streams keyed by the global lane index: results do not depend on chunking.
    off = dr.opaque(mi.UInt64, lane0)
    rng = mi.PCG32(lanes, dr.opaque(mi.UInt64, seed) + off, off)
    wi = dr.gather(mi.Vector3f, mi.Vector3f(aligned(wi_np.reshape(-1, 3).T)), tex)
    wo = dr.gather(mi.Vector3f, mi.Vector3f(aligned(wo_np.reshape(-1, 3).T)), tex)

    # Camera ray: towards a jittered point of the texel footprint on z = 0, along −ω_o, from above the relief.
    def u2() -> mi.Point2f:
        return mi.Point2f(rng.next_float32(), rng.next_float32())

    jitter = u2()
    target = mi.Point3f((mi.Float(pix % w) + jitter.x) / w, (mi.Float(pix // w) + jitter.y) / h, 0.0)
    ray = mi.Ray3f(target + wo * (dr.opaque(mi.Float, z_top) / wo.z), -wo)

    cos_half = math.cos(math.radians(0.5 * s.sun_diameter_deg))
    # Unit irradiance: L·Ω·E[cos] = 1 with E[cos] = (1 + cosδ)/2 over the uniform cone; MC weight 1/E[cos].
    sun_norm = 2.0 / (1.0 + cos_half)
    sun_frame = mi.Frame3f(wi)
    ctx = mi.BSDFContext()
    beta = mi.Spectrum(1.0)
    result = mi.Spectrum(0.0)
    active = mi.Bool(True)
    for depth in range(s.max_depth):  # unrolled: max_depth is small and fixed per kernel
        si = scene.ray_intersect(ray, active)
        active &= si.is_valid()
        # Next-event estimation towards the sun (a delta-like light: never hit by BSDF-sampled rays).
        if s.sun_diameter_deg > 0.0:
            wl = sun_frame.to_world(mi.warp.square_to_uniform_cone(u2(), cos_half))
        else:
            wl = wi
        occluded = scene.ray_test(si.spawn_ray(wl), active)
        f = bsdf.eval(ctx, si, si.to_local(wl), active & ~occluded)
        result += dr.select(active & ~occluded, beta * f * sun_norm, 0.0)
        if depth + 1 == s.max_depth:
            break
        bs, weight = bsdf.sample(ctx, si, rng.next_float32(), u2(), active)
        beta *= weight
        active &= bs.pdf > 0.0
        ray = si.spawn_ray(si.to_world(bs.wo))

    finite = dr.isfinite(result[0]) & dr.isfinite(result[1]) & dr.isfinite(result[2])
    result = dr.select(finite, result, 0.0)  # a rare float edge case must not poison a texel
    dr.eval(result, finite)  # once: each reduction below would otherwise trace and run the whole path tracer again
    out = mi.Color3f(*(dr.block_sum(result[c], s.spp) / s.spp for c in range(3)))
    bad = dr.count(~finite)
    dr.eval(out, bad)
    return np.asarray(out).T.reshape(k, h, w, 3), int(bad[0])


def render_btf(svbrdf: SVBRDF, settings: BTFRenderSettings | None = None, progress: bool = True,
               directions: tuple[np.ndarray, np.ndarray] | None = None) -> BTFData:
    """Path trace the BTF of an SVBRDF (seed 002 §4.1): displaced 3×3 geometry, sun NEE, interreflections.

    ``directions`` = (wi, wo), arrays broadcastable to (slices, tex_res, tex_res, 3), replaces the
    seeded random pairs (a testing hook: e.g. one fixed pair for every texel). See the module
    docstring for the value convention, frames and texel layout.
    """
    s = settings or BTFRenderSettings()
    t0 = time.perf_counter()
    shape = (s.slices, s.tex_res, s.tex_res, 3)
    wi_all, wo_all = np.zeros(shape, np.float32), np.zeros(shape, np.float32)
    if directions is not None:
        for name, d, out in zip(("wi", "wo"), directions, (wi_all, wo_all)):
            d = np.broadcast_to(np.asarray(d, np.float64), shape)
            out[:] = d / np.linalg.norm(d, axis=-1, keepdims=True)
            if not np.isfinite(out).all() or out[..., 2].min() <= 0.0:
                raise ValueError(f"render_btf: directions '{name}' must be finite with z > 0")
    bsdf = make_bsdf(svbrdf)
    scene = mi.load_dict({"type": "scene", "tile": height_mesh(svbrdf.height, s.mesh_res, bsdf)})
    h = svbrdf.height
    z_top = float(h.max() - h.mean()) + 1e-3  # camera rays start just above the highest point
    seed = int(np.random.SeedSequence([s.seed, svbrdf.seed, 0xB7F]).generate_state(1, np.uint64)[0] >> np.uint64(1))

    texels = s.tex_res * s.tex_res
    per_chunk = max(1, min(s.slices, _CHUNK_LANES // (texels * s.spp)))
    values = np.zeros(shape, np.float32)
    bad = 0
    with progress_bar(s.slices, desc=f"BTF {svbrdf.name}", unit="slice", disable=not progress) as bar:
        for k0 in range(0, s.slices, per_chunk):
            k1 = min(k0 + per_chunk, s.slices)
            if directions is None:
                for k in range(k0, k1):
                    wi_all[k], wo_all[k] = _slice_directions(svbrdf, s, k)
            values[k0:k1], nb = _trace_chunk(scene, bsdf, wi_all[k0:k1], wo_all[k0:k1], s, seed, k0 * texels * s.spp,
                                             z_top)
            bad += nb
            bar.update(k1 - k0)
    meta = {
        "format_version": FORMAT_VERSION, "name": svbrdf.name, "family": svbrdf.family, "seed": svbrdf.seed,
        "settings": asdict(s), "convention": CONVENTION, "render_seconds": time.perf_counter() - t0,
        "height_ptp": float(np.ptp(h)), "svbrdf_res": svbrdf.res, "nonfinite_paths": bad,
        "light": f"sun, uniform disk of {s.sun_diameter_deg} deg diameter" if s.sun_diameter_deg > 0 else "directional",
        "fixed_directions": directions is not None,
    }
    return BTFData(np.minimum(values, _F16_MAX).astype(np.float16), wi_all, wo_all, meta)


# =============================================================================================
# Files
# =============================================================================================

_KEYS = ("values", "wi", "wo", "meta")


def save_btf(path: str | Path, data: BTFData) -> Path:
    """Write a BTF as .npz (values float16, directions float32, meta as JSON), atomically."""
    path = Path(path)
    with atomic_path(path, suffix=".npz") as tmp:
        np.savez_compressed(tmp, values=data.values.astype(np.float16), wi=data.wi.astype(np.float32),
                            wo=data.wo.astype(np.float32), meta=np.array(json.dumps(data.meta)))
    return path


def load_btf(path: str | Path) -> BTFData:
    """Read and validate a BTF file; any problem raises :class:`BTFDataError` naming the file."""
    path = Path(path)
    if not path.is_file():
        raise BTFDataError(f"{path}: no such BTF file")
    try:
        with np.load(path, allow_pickle=False) as z:
            missing = [k for k in _KEYS if k not in z.files]
            if missing:
                raise BTFDataError(f"{path}: missing arrays {missing} (has {sorted(z.files)})")
            arrays = {k: z[k] for k in _KEYS}
    except BTFDataError:
        raise
    except Exception as exc:  # zipfile/pickle/OS errors of a corrupt or foreign file
        raise BTFDataError(f"{path}: not a readable BTF .npz file ({type(exc).__name__}: {exc})") from exc
    try:
        meta = json.loads(str(arrays["meta"]))
        assert isinstance(meta, dict)
    except Exception as exc:
        raise BTFDataError(f"{path}: 'meta' is not a JSON object") from exc
    values, wi, wo = arrays["values"], arrays["wi"], arrays["wo"]
    if values.ndim != 4 or values.shape[-1] != 3:
        raise BTFDataError(f"{path}: 'values' has shape {values.shape}, expected (S, H, W, 3)")
    for name, a in (("wi", wi), ("wo", wo)):
        if a.shape != values.shape:
            raise BTFDataError(f"{path}: '{name}' has shape {a.shape}, 'values' has {values.shape}")
    for name, a in (("values", values), ("wi", wi), ("wo", wo)):
        if not np.issubdtype(a.dtype, np.floating):
            raise BTFDataError(f"{path}: '{name}' has dtype {a.dtype}, expected floating point")
        bad = int(np.size(a) - np.count_nonzero(np.isfinite(a)))
        if bad:
            raise BTFDataError(f"{path}: '{name}' has {bad} NaN/Inf entries")
    for name, a in (("wi", wi), ("wo", wo)):
        if a.size and np.abs(np.linalg.norm(a, axis=-1) - 1.0).max() > 1e-3:
            raise BTFDataError(f"{path}: '{name}' holds non-unit directions")
    return BTFData(values.astype(np.float16), wi.astype(np.float32), wo.astype(np.float32), meta)


def material_seed(base_seed: int, family: str, k: int) -> int:
    """Deterministic material seed from the dataset seed, the family's index in FAMILIES and k."""
    return int(np.random.SeedSequence([int(base_seed), FAMILIES.index(family), int(k)]).generate_state(1)[0] >> 1)


def render_material(path: str, family: str, seed: int, settings: BTFRenderSettings, svbrdf_res: int = 256) -> dict:
    """Render one dataset material to ``path`` (the unit :func:`render_dataset` fans out); returns its index entry."""
    path = Path(path)
    sv = dataclasses.replace(make_svbrdf(family, seed, svbrdf_res), name=path.stem)
    data = render_btf(sv, settings, progress=False)
    save_btf(path, data)
    return {"file": path.name, "name": data.meta["name"], "family": family, "seed": seed,
            "render_seconds": data.meta["render_seconds"]}


def render_dataset(out_dir: str | Path, families: Sequence[str] = FAMILIES, per_family: int = 4,
                   settings: BTFRenderSettings | None = None, base_seed: int = 0, progress: bool = True,
                   svbrdf_res: int = 256, pool=None) -> list[Path]:
    """Render ``{family}_{k:03d}.npz`` for every family and k < per_family into out_dir, plus index.json.

    Checkpoint/resume: a file that already exists and loads is skipped, so a killed run continues
    where it stopped; one rendered with other settings raises (mixing would corrupt the dataset).
    ``pool`` (:class:`foundation.pool.PoolSettings`) renders the materials on worker processes or Ray;
    None renders them here, one after another. A material that fails is reported after the others finished.
    """
    from foundation.pool import Item, PoolSettings, run_items

    s = settings or BTFRenderSettings()
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise UsageError(f"--out {out}: is a file, expected a dataset folder")
    if out.exists() and any(p for p in out.iterdir() if p.suffix not in (".npz", ".json") and not p.name.startswith(".")):
        check_output_dir(out, "index.json", "--out")  # a folder of other things is not a dataset to add to
    bad = [f for f in families if f not in FAMILIES]
    if bad:
        raise UsageError(f"families: unknown {bad}; valid: {', '.join(FAMILIES)}")
    if isinstance(per_family, bool) or int(per_family) < 1:
        raise UsageError(f"per_family must be ≥ 1, got {per_family}")
    out.mkdir(parents=True, exist_ok=True)
    jobs = [(f, k) for f in families for k in range(int(per_family))]
    entries: dict[str, dict] = {}
    items = []
    for family, k in jobs:
        path = out / f"{family}_{k:03d}.npz"
        seed = material_seed(base_seed, family, k)
        meta = None
        if path.exists():
            try:
                meta = load_btf(path).meta
            except BTFDataError:
                meta = None  # half-written or corrupt: render it again
            if meta is not None and (meta.get("settings") != asdict(s) or meta.get("seed") != seed):
                raise UsageError(f"{path}: rendered with other settings or seed; use a fresh --out folder")
        if meta is not None:
            entries[path.name] = {"file": path.name, "name": meta["name"], "family": family, "seed": seed,
                                  "render_seconds": meta["render_seconds"]}
        else:
            items.append(Item(path.stem, "inverse.btf.data:render_material", (str(path), family, seed, s, svbrdf_res)))
    report = run_items(items, pool or PoolSettings(workers=0, threads=0), desc="BTF dataset", show_progress=progress)
    for r in report.ran:
        entries[r.value["file"]] = r.value
    order = [f"{f}_{k:03d}.npz" for f, k in jobs]
    _write_index(out, s, base_seed, [entries[n] for n in order if n in entries])
    report.raise_if_failed()
    return [out / n for n in order]


def _write_index(out: Path, s: BTFRenderSettings, base_seed: int, materials: list[dict]) -> None:
    with atomic_path(out / "index.json") as tmp:
        tmp.write_text(json.dumps({"format_version": FORMAT_VERSION, "convention": CONVENTION, "base_seed": base_seed,
                                   "settings": asdict(s), "materials": materials}, indent=1))


def load_dataset(directory: str | Path) -> list[BTFData]:
    """All BTFs of a dataset folder, in index.json order (or sorted file names without an index)."""
    d = Path(directory)
    if not d.is_dir():
        raise BTFDataError(f"{d}: no such BTF dataset folder")
    index = d / "index.json"
    if index.is_file():
        try:
            files = [d / m["file"] for m in json.loads(index.read_text())["materials"]]
        except Exception as exc:
            raise BTFDataError(f"{index}: not a valid dataset index ({exc})") from exc
    else:
        files = sorted(d.glob("*.npz"))
    if not files:
        raise BTFDataError(f"{d}: no BTF files")
    return [load_btf(f) for f in files]
