"""The dataset of the material diffusion model (seed 002 §3.2, §4.4): many fitted neural materials.

Each material is made the way a user makes one (:mod:`inverse.btf`): a seeded SVBRDF of one of the 8
families, its BTF path traced by Mitsuba, its feature textures [T_off ‖ T_rgb] fitted to the frozen
universal basis (the bundled ``scenes/assets/neural/basis.npz`` unless another is given). Beside the
fit, each material gets

* **swatches** — Mitsuba path traces of the real SVBRDF at :data:`SWATCH_DIRECTIONS` (four fixed
  (light, view) pairs for every texel: three lights around a view from above, one mirror
  configuration that shows gloss): the "photo" of a material that the family classifier, KID, the
  exemplar condition and ꟻLIP use. A neural material is judged by decoding it at the same pairs
  (:func:`decode_swatches`), so real and generated materials are compared in one image space;
* **keywords** — family, colour and finish, read off the generated maps themselves (mean base colour
  in HSV, mean roughness): a closed vocabulary (:data:`VOCABULARY`), not free text.

The build is resumable and uses every core (:mod:`foundation.pool`): the BTFs through
``inverse.btf.render_dataset`` (skips what exists), then one pool item per material (fit, score on
held-out slices, swatches, keywords) whose output marks it done.
"""

from __future__ import annotations

import colorsys
import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from foundation import validate
from foundation.assets import bundled_basis
from foundation.errors import UsageError
from foundation.files import atomic_path, holds_files, read_json, write_json

FAMILIES = ("fabric", "metal", "stone", "wood", "plaster", "leather", "ceramic", "ground")  # = inverse.btf.FAMILIES
COLOURS = ("red", "orange", "brown", "yellow", "green", "blue", "purple", "black", "grey", "white")
FINISHES = ("polished", "satin", "rough")
#: the keyword vocabulary, in embedding order: a prompt is one word per slot (family, colour, finish)
VOCABULARY = FAMILIES + COLOURS + FINISHES
SLOTS = (FAMILIES, COLOURS, FINISHES)
FORMAT = "photoreal material diffusion dataset v1"


def _dirs(theta_deg: float, phi_deg: float) -> list[float]:
    t, p = math.radians(theta_deg), math.radians(phi_deg)
    return [math.sin(t) * math.cos(p), math.sin(t) * math.sin(p), math.cos(t)]


#: (ω_i towards the light, ω_o towards the viewer) per swatch, tangent frame
SWATCH_DIRECTIONS = np.array([
    [_dirs(45, 30), _dirs(0, 0)], [_dirs(45, 150), _dirs(0, 0)], [_dirs(45, 270), _dirs(0, 0)],
    [_dirs(30, 0), _dirs(30, 180)],  # mirror configuration: the specular lobe's peak
], np.float32)


@dataclass
class MaterialDataSettings:
    """How the materials of a dataset are made (CPU-sized: seed 002 uses 512² texels, 400 slices, 128 spp)."""

    count: int = 256  #: materials, spread evenly over the families (rounded up to a multiple of 8; > 8)
    tex_res: int = 32  #: texels per side of the BTF and of the fitted feature textures
    slices: int = 32  #: (light, view) pairs rendered per texel
    spp: int = 8  #: paths per texel and slice
    swatch_spp: int = 32  #: paths per texel of each swatch
    mesh_res: int = 64  #: quads per side of the displaced tile
    svbrdf_res: int = 128  #: resolution of the generated maps
    fit_iterations: int = 200  #: per-material fitting steps (measured: 33.0 dB held out at 200, 32.6 at 400)
    fit_batch: int = 8192
    seed: int = 0

    def __post_init__(self):
        validate.integer("count", self.count, 1, 1 << 20)
        if self.count <= len(FAMILIES):  # heldout_mask keeps ≥ 1 material per family for evaluation
            raise UsageError(f"count must be > {len(FAMILIES)}, got {self.count}: each of the {len(FAMILIES)} "
                             "families holds one material out for evaluation, so training needs two per family")
        validate.integer("tex_res", self.tex_res, 8, 1024)
        for k in ("slices", "spp", "swatch_spp", "fit_iterations", "fit_batch"):
            validate.integer(k, getattr(self, k), 1)
        validate.integer("mesh_res", self.mesh_res, 2)
        validate.integer("svbrdf_res", self.svbrdf_res, 16)
        validate.seed("seed", self.seed)

    @property
    def per_family(self) -> int:
        return -(-self.count // len(FAMILIES))


# -- keywords --------------------------------------------------------------------------------------------------------


def colour_word(base_color: np.ndarray) -> str:
    """Name of a material's mean colour (linear RGB → sRGB → HSV): black/grey/white by value and
    saturation, else the hue sector (brown = dark orange)."""
    c = np.clip(np.asarray(base_color, np.float64).reshape(-1, 3).mean(0), 0.0, 1.0)
    srgb = np.where(c <= 0.0031308, 12.92 * c, 1.055 * c ** (1 / 2.4) - 0.055)
    h, s, v = colorsys.rgb_to_hsv(*srgb)
    if v < 0.2:
        return "black"
    if s < 0.2:
        return "white" if v > 0.75 else "grey"
    deg = h * 360.0
    if deg < 20 or deg >= 330:
        return "red"
    if deg < 45:
        return "orange" if v > 0.6 else "brown"
    if deg < 70:
        return "yellow"
    if deg < 170:
        return "green"
    if deg < 260:
        return "blue"
    return "purple"


def finish_word(roughness: np.ndarray) -> str:
    """polished (mean perceptual roughness < 0.35), satin (< 0.6) or rough."""
    r = float(np.mean(roughness))
    return "polished" if r < 0.35 else "satin" if r < 0.6 else "rough"


def keywords_of(svbrdf) -> list[str]:
    return [svbrdf.family, colour_word(svbrdf.base_color), finish_word(svbrdf.roughness)]


def parse_keywords(text: str) -> list[str | None]:
    """"rough red leather" → [family, colour, finish] with None for a slot not given. Unknown words and two
    words for one slot are errors that list the vocabulary (this is keyword conditioning, not free text)."""
    out: list[str | None] = [None, None, None]
    words = [w for w in str(text).replace(",", " ").lower().split() if w]
    if not words:
        raise UsageError("--keywords: empty; give words such as 'rough red leather'")
    for w in words:
        w = {"gray": "grey", "glossy": "satin", "matte": "rough", "shiny": "polished"}.get(w, w)
        slot = next((i for i, words_ in enumerate(SLOTS) if w in words_), None)
        if slot is None:
            raise UsageError(f"--keywords: unknown word {w!r}; the vocabulary is families {', '.join(FAMILIES)}; "
                             f"colours {', '.join(COLOURS)}; finishes {', '.join(FINISHES)}")
        if out[slot] is not None and out[slot] != w:
            raise UsageError(f"--keywords: {out[slot]!r} and {w!r} name the same slot; give one of each")
        out[slot] = w
    return out


def keyword_onehots(prompts: list[list[str | None]]) -> np.ndarray:
    """(B, 3, len(VOCABULARY)): one token per slot, all zeros for a slot not given."""
    out = np.zeros((len(prompts), len(SLOTS), len(VOCABULARY)), np.float32)
    for b, p in enumerate(prompts):
        for slot, w in enumerate(p):
            if w is not None:
                out[b, slot, VOCABULARY.index(w)] = 1.0
    return out


# -- swatches --------------------------------------------------------------------------------------------------------


def render_swatches(svbrdf, tex_res: int, spp: int, mesh_res: int, seed: int = 0) -> np.ndarray:
    """Path-traced swatches of a real SVBRDF: (K, tex_res, tex_res, 3), one per :data:`SWATCH_DIRECTIONS` pair."""
    from inverse.btf import BTFRenderSettings, render_btf

    k = len(SWATCH_DIRECTIONS)
    s = BTFRenderSettings(tex_res=tex_res, slices=k, spp=spp, mesh_res=mesh_res, seed=seed)
    wi = SWATCH_DIRECTIONS[:, 0][:, None, None, :]
    wo = SWATCH_DIRECTIONS[:, 1][:, None, None, :]
    return np.asarray(render_btf(svbrdf, s, progress=False, directions=(wi, wo)).values, np.float32)


def decode_swatches(basis, t_off: np.ndarray, t_rgb: np.ndarray) -> np.ndarray:
    """A neural material decoded through the universal basis at the swatch pairs: (K, H, W, 3)."""
    from inverse.btf import BTFData, predict
    from mi_plugins.neural_basis import NeuralMaterial

    h, w = t_off.shape[:2]
    k = len(SWATCH_DIRECTIONS)
    shape = (k, h, w, 3)
    wi = np.broadcast_to(SWATCH_DIRECTIONS[:, 0][:, None, None, :], shape).astype(np.float32)
    wo = np.broadcast_to(SWATCH_DIRECTIONS[:, 1][:, None, None, :], shape).astype(np.float32)
    data = BTFData(np.zeros(shape, np.float16), wi, wo, {})
    mat = NeuralMaterial(np.ascontiguousarray(t_off, np.float32), np.ascontiguousarray(t_rgb, np.float32), {})
    return np.maximum(predict(basis, mat, data, np.arange(k)), 0.0).astype(np.float32)


# -- the build -------------------------------------------------------------------------------------------------------


def make_material(btf: str, family: str, seed: int, basis: str, fit_out: str, swatch_out: str,
                  s: MaterialDataSettings) -> dict:
    """One dataset material (the unit the pool fans out): fit its BTF to the basis, path trace its swatches,
    name its keywords. The swatch file is written last: it marks the material done."""
    from inverse.btf import fit_file, make_svbrdf

    ckpt = Path(fit_out).with_suffix(".ckpt.npz")
    summary = fit_file(btf, basis, fit_out, iterations=s.fit_iterations, batch=s.fit_batch, seed=s.seed,
                       checkpoint=str(ckpt))
    ckpt.unlink(missing_ok=True)
    sv = make_svbrdf(family, seed, s.svbrdf_res)
    sw = render_swatches(sv, s.tex_res, s.swatch_spp, s.mesh_res, s.seed)
    kw = keywords_of(sv)
    entry = {"name": Path(btf).stem, "family": family, "seed": int(seed), "keywords": kw,
             "psnr_heldout": float(summary["psnr_heldout"]), "fit_seconds": float(summary["seconds"])}
    with atomic_path(swatch_out, suffix=".npz") as tmp:
        np.savez_compressed(tmp, swatches=sw.astype(np.float32), entry=np.array(json.dumps(entry)))
    return entry


def load_entry(swatch_out: str) -> dict:
    with np.load(swatch_out) as d:
        return json.loads(str(d["entry"]))


def build_material_dataset(out: str | Path, s: MaterialDataSettings | None = None, basis: str | Path | None = None,
                           pool=None, progress: bool = True) -> Path:
    """Render, fit and describe ``s.count`` materials into ``out`` (``btf/``, ``fit/``, ``swatch/``,
    ``index.json``). Rerun the same call to continue a killed build; other settings in the same folder are refused."""
    from foundation.pool import Item, PoolSettings, run_items
    from inverse.btf import BTFRenderSettings, render_dataset
    from mi_plugins.neural_basis import load_basis

    s = s or MaterialDataSettings()
    out = Path(out)
    basis = Path(basis) if basis else bundled_basis()
    basis_id = load_basis(basis).meta.get("id", "")
    index = out / "index.json"
    want = {"format": FORMAT, "settings": asdict(s), "basis": basis_id}
    if index.is_file():
        have = read_json(index, "material dataset index")
        if {k: have.get(k) for k in want} != want:
            raise UsageError(f"{index}: a dataset made with other settings or basis; use a fresh --out folder")
    elif holds_files(out) and not (out / "btf").is_dir():
        raise UsageError(f"{out}: exists and is not a material dataset; give an empty or new folder")
    out.mkdir(parents=True, exist_ok=True)
    write_json(index, {**want, "materials": []})  # claims the folder before any work
    rs = BTFRenderSettings(tex_res=s.tex_res, slices=s.slices, spp=s.spp, mesh_res=s.mesh_res, seed=s.seed)
    pool = pool or PoolSettings(workers=0, threads=0)
    render_dataset(out / "btf", FAMILIES, s.per_family, rs, s.seed, progress, s.svbrdf_res, pool)
    btf_index = read_json(out / "btf" / "index.json", "BTF dataset index")
    (out / "fit").mkdir(exist_ok=True)
    (out / "swatch").mkdir(exist_ok=True)
    items = []
    for m in btf_index["materials"]:
        stem = Path(m["file"]).stem
        sw = out / "swatch" / f"{stem}.npz"
        items.append(Item(stem, "generative.btf.data:make_material",
                          (str(out / "btf" / m["file"]), m["family"], int(m["seed"]), str(basis),
                           str(out / "fit" / f"{stem}.npz"), str(sw), s),
                          output=str(sw), loader="generative.btf.data:load_entry"))
    report = run_items(items, pool, desc="fit + swatches", show_progress=progress)
    entries = [r.value for r in report.results if r.ok]
    write_json(index, {**want, "materials": entries, "seconds_last_batch": report.seconds})
    report.raise_if_failed()
    return out


@dataclass
class MaterialSet:
    """A loaded dataset: feature textures, swatches, keywords; ``heldout`` marks the evaluation materials."""

    names: list[str]
    families: np.ndarray  #: (N,) index into FAMILIES
    keywords: list[list[str]]
    features: np.ndarray  #: (N, 2C, H, W) float32: [T_off ‖ T_rgb] channels first
    swatches: np.ndarray  #: (N, K, H, W, 3) path-traced swatches of the real SVBRDFs
    psnr: np.ndarray  #: (N,) held-out-slice PSNR of each fit
    heldout: np.ndarray  #: (N,) bool
    basis_id: str = ""

    def subset(self, mask: np.ndarray) -> "MaterialSet":
        idx = np.flatnonzero(mask)
        return MaterialSet([self.names[i] for i in idx], self.families[idx], [self.keywords[i] for i in idx],
                           self.features[idx], self.swatches[idx], self.psnr[idx], self.heldout[idx], self.basis_id)


def heldout_mask(families: np.ndarray, fraction: float = 0.125) -> np.ndarray:
    """The last ``fraction`` (at least one) of every family's materials, in dataset order."""
    mask = np.zeros(len(families), bool)
    for f in np.unique(families):
        idx = np.flatnonzero(families == f)
        mask[idx[len(idx) - max(1, int(round(len(idx) * fraction))):]] = True
    return mask


def load_material_dataset(directory: str | Path, heldout_fraction: float = 0.125, limit: int | None = None) -> MaterialSet:
    """A built dataset's materials (those finished so far); ``limit`` keeps the first materials of each family
    (the dataset-size sweep). Errors name the folder or file."""
    from mi_plugins.neural_basis import load_material

    d = Path(directory)
    index = d / "index.json"
    if not index.is_file():
        raise UsageError(f"{d}: no material dataset (index.json missing; build it with `photoreal btf dataset`)")
    idx = read_json(index, "material dataset index")
    entries = idx.get("materials") or []
    if not entries:
        raise UsageError(f"{index}: no finished materials yet (rerun `photoreal btf dataset` to continue the build)")
    if limit is not None:
        per = {}
        kept = []
        for e in entries:
            per[e["family"]] = per.get(e["family"], 0) + 1
            if per[e["family"]] <= limit:
                kept.append(e)
        entries = kept
    feats, sws = [], []
    for e in entries:
        mat = load_material(d / "fit" / f"{e['name']}.npz")
        feats.append(np.concatenate([mat.t_off, mat.t_rgb], -1).transpose(2, 0, 1))
        with np.load(d / "swatch" / f"{e['name']}.npz") as z:
            sws.append(z["swatches"].astype(np.float32))
    fam = np.array([FAMILIES.index(e["family"]) for e in entries])
    return MaterialSet([e["name"] for e in entries], fam, [list(e["keywords"]) for e in entries],
                       np.stack(feats).astype(np.float32), np.stack(sws), np.array([e["psnr_heldout"] for e in entries]),
                       heldout_mask(fam, heldout_fraction), idx.get("basis", ""))


__all__ = ["COLOURS", "FAMILIES", "FINISHES", "FORMAT", "MaterialDataSettings", "MaterialSet", "SLOTS",
           "SWATCH_DIRECTIONS", "VOCABULARY", "build_material_dataset", "colour_word", "decode_swatches",
           "finish_word", "heldout_mask", "keyword_onehots", "keywords_of", "load_material_dataset",
           "make_material", "parse_keywords", "render_swatches"]
