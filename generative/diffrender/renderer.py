"""Intrinsic-conditioned diffusion renderer (seed 000): G-buffers (A, I, S, normal) of a mesh → a photo.

Paired data from 3D (§3.1): for every camera of a morph benchmark, the intrinsic layers of the
**coarse** and of the **morphed** mesh (Mitsuba's ``intrinsic`` integrator: albedo A, irradiance
I = D / A, specular-and-emission S, world normal N), beside the benchmark's path-traced photos.
By default only the morphed mesh's layers are training inputs (``sources``; the coarse ones can be
added: the bench ablates it); held-out views are never trained on.

The model (§3.2–3.3, :mod:`generative.diffusion`): local condition [A ‖ I ‖ S ‖ N] concatenated
with the noisy image (12 channels); global condition = MobileNetV2 tokens of the recomposition
R = A·I + S (seed 000 eq. 4) of the whole view — ``global_source`` "R" (the seed), "AIS" (the three
layers encoded separately: the recomposition ablation) or "none" (global features off). Training is
a stage of :mod:`foundation.loop` (budgets, checkpoints, exact resume, NaN policy, metrics JSON).

Value spaces: the photo is generated in sRGB mapped to [−1, 1] (linear ↔ sRGB at the boundary);
A in sRGB, I and S through x / (1 + x) (they exceed 1), N as is. With ``residual`` (the default) the
model generates the *difference* between the photo and the PBR recomposition R of its own G-buffers
(both in that sRGB space, × ``residual_scale`` to about unit variance): a model that has learned nothing
returns R, and what it learns is what R lacks (Monte-Carlo noise of the G-buffers, geometry and colour
errors of the mesh). The seed generates the image itself; ``residual=False`` does that.

Where a pixel sees no surface of the mesh (its G-buffer normal is 0 in every sample), R *is* the environment the
photo sees there, so the residual is the photos' zero-mean Monte-Carlo noise alone. With ``known_background`` (the
default) the residual is defined as 0 there: the loss covers the mesh's pixels only and sampling holds x̂₀ = 0 on
the others. Measured on the bench's held-out views, a model trained without it spent its errors there: masking its
output afterwards alone took ꟻLIP from 0.095 to 0.071 (PBR recomposition: 0.068).
"""

from __future__ import annotations

import hashlib
import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

import mi_plugins  # noqa: F401
import mitsuba as mi

from foundation import validate
from foundation.errors import UsageError
from foundation.features import feature_maps, load_mobilenet, normalise
from foundation.files import cached_arrays, file_digest
from foundation.loop import RunState, Stage, StepResult, TrainingSummary
from foundation.progress import progress_bar
from foundation.scene import recompose, split_intrinsics
from inverse.morph import MorphBenchmark, morph_scene, morph_views, sensor_dict, truth_scene

from generative.diffusion import (ConditionalDiffusion, OptimizerStage, check_size, diffusion_loss,
                                  load_trained, make_scheduler, sample, train_stage)
from .settings import (DECOMPOSED, GLOBAL_SOURCES, LAYERS, SOURCES, TRAIN_SOURCES, TRUTH, DiffRenderSettings,
                       GBufferSettings, SampleSettings)

ENCODER_SIZE = 128


@dataclass
class IntrinsicViews:
    """One benchmark's views: photos and the coarse/morphed G-buffers, (V, H, W, 3) float32 each."""

    photos: np.ndarray
    layers: dict  #: source ("coarse"/"morphed") → layer name → (V, H, W, 3)
    train: list[int]
    test: list[int]
    case: str = ""

    @property
    def resolution(self) -> int:
        return int(self.photos.shape[1])

    def recomposed(self, source: str) -> np.ndarray:
        """R = A·I + S of every view (the PBR recomposition baseline, seed 000 eq. 4)."""
        return recompose(self.layers[source])

    def digest(self) -> str:
        h = hashlib.sha256()
        h.update(np.ascontiguousarray(self.photos, np.float32).tobytes())
        for src in sorted(self.layers):
            h.update(src.encode())
            for name in LAYERS:
                h.update(np.ascontiguousarray(self.layers[src][name], np.float32).tobytes())
        h.update(json.dumps([list(map(int, self.train)), list(map(int, self.test))]).encode())
        return h.hexdigest()[:16]


def intrinsic_layers(img: np.ndarray) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """An ``intrinsic`` integrator's film (H, W, C) → (the RGB render, its layers incl. I = D / A)."""
    from foundation.scene import AOV_GROUPS

    names = [f"{g}.{c}" for g, chans in AOV_GROUPS.items() for c in chans]
    base = img.shape[-1] - len(names)  # RGB (+ alpha/weight) first, then the AOVs in their order
    aov = split_intrinsics({g: img[..., base + names.index(f"{g}.{ch[0]}"):][..., :len(ch)]
                            for g, ch in AOV_GROUPS.items()})
    return np.ascontiguousarray(img[..., :3]), aov


def render_gbuffers(mesh_ply: Path, bench: MorphBenchmark, ids: list[int], s: GBufferSettings,
                    desc: str = "G-buffers", show_progress: bool = True, seed: int = 0) -> dict[str, np.ndarray]:
    """Intrinsic layers of a coloured PLY at cameras ``ids`` under the benchmark's HDRI → layer → (N, H, W, 3).

    View ``i`` is rendered with seed ``seed + i``. At the photos' spp, seed 0 correlates the G-buffers' Monte-Carlo
    noise with the photos' (they use the benchmark's seed + i too): keep the spp apart, or the seed."""
    scene = morph_scene(Path(mesh_ply), "lit", bench.meta.hdri, integrator={"type": "intrinsic", "max_depth": s.max_depth})
    return _scene_layers(scene, bench, ids, s, desc, show_progress, seed, str(mesh_ply))


def _scene_layers(scene, bench: MorphBenchmark, ids: list[int], s: GBufferSettings, desc: str, show_progress: bool,
                  seed: int, what: str) -> dict[str, np.ndarray]:
    meta = bench.meta
    res = meta.resolution
    out = {k: np.empty((len(ids), res, res, 3), np.float32) for k in LAYERS}
    with progress_bar(total=len(ids), desc=desc, unit="view", disable=not show_progress) as bar:
        for k, i in enumerate(ids):
            sensor = mi.load_dict(sensor_dict(meta.cameras[i], res, meta.fov))
            img = np.array(mi.render(scene, sensor=sensor, spp=s.spp, seed=seed + int(i)), np.float32)
            aov = intrinsic_layers(img)[1]
            for name in LAYERS:
                out[name][k] = aov[name]
            bar.update(1)
    del scene
    for name, a in out.items():
        if not np.isfinite(a).all():
            raise FloatingPointError(f"{what}: the {name} G-buffer has {int((~np.isfinite(a)).sum())} NaN/Inf values")
    return out


def truth_gbuffers(bench: MorphBenchmark, ids: list[int], s: GBufferSettings, desc: str = "G-buffers truth",
                   show_progress: bool = True, seed: int = 0) -> dict[str, np.ndarray]:
    """:func:`render_gbuffers` of the benchmark's ground-truth scene (its own shapes, materials and textures)."""
    scene = truth_scene(bench, integrator={"type": "intrinsic", "max_depth": s.max_depth})
    return _scene_layers(scene, bench, ids, s, desc, show_progress, seed, f"{bench.path} (ground truth)")


def with_truth_layers(v: "IntrinsicViews", bench: MorphBenchmark, morph_dir: str | Path,
                      s: GBufferSettings | None = None, show_progress: bool = True) -> "IntrinsicViews":
    """``v`` with the ground truth's G-buffers of its *train* views as a further source (:data:`TRUTH`; zeros at the
    held-out views, which no training reads); cached in ``morph_dir`` by the benchmark's digest."""
    s = s or GBufferSettings()
    ids = [int(i) for i in v.train]
    key = json.dumps({"benchmark": file_digest(Path(bench.path) / "morph_benchmark.json"), "ids": ids, **asdict(s)},
                     sort_keys=True)
    flat = cached_arrays(Path(morph_dir) / "diffrender_truth_gbuffers.npz", key,
                         lambda: truth_gbuffers(bench, ids, s, show_progress=show_progress))
    full = {}
    for name in LAYERS:
        a = np.zeros_like(v.layers["morphed"][name])
        a[ids] = flat[name]
        full[name] = a
    return IntrinsicViews(v.photos, {**v.layers, TRUTH: full}, list(v.train), list(v.test), v.case)


def load_intrinsic_views(bench: MorphBenchmark, morph_dir: str | Path, s: GBufferSettings | None = None,
                         show_progress: bool = True) -> IntrinsicViews:
    """Photos and both meshes' G-buffers at every camera; G-buffers cached in ``morph_dir`` by mesh digests."""
    s = s or GBufferSettings()

    def render(meshes: dict, ids: list[int]) -> dict:
        return {f"{src}.{name}": a for src, mesh in meshes.items()
                for name, a in render_gbuffers(mesh, bench, ids, s, f"G-buffers {src}", show_progress).items()}

    photos, flat = morph_views(bench, morph_dir, "diffrender_gbuffers.npz", asdict(s), render)
    layers = {src: {name: flat[f"{src}.{name}"] for name in LAYERS} for src in SOURCES}
    meta = bench.meta
    return IntrinsicViews(photos, layers, list(meta.train), list(meta.test), meta.kind)


# -- value spaces ---------------------------------------------------------------------------------------------------


def _srgb(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(np.maximum(x, 1e-8), 1 / 2.4) - 0.055)


def _linear(s: np.ndarray) -> np.ndarray:
    s = np.clip(s, 0.0, 1.0)
    return np.where(s <= 0.04045, s / 12.92, ((s + 0.055) / 1.055) ** 2.4)


def photo_to_model(img: np.ndarray) -> np.ndarray:
    """Linear RGB (…, 3) → model space: sRGB in [−1, 1]."""
    return (2.0 * _srgb(img) - 1.0).astype(np.float32)


def model_to_photo(x: np.ndarray) -> np.ndarray:
    return _linear((np.asarray(x) + 1.0) / 2.0).astype(np.float32)


def local_condition(layers: dict[str, np.ndarray]) -> np.ndarray:
    """(…, H, W, 3) layers → (…, H, W, 12) condition in about [−1, 1]: A sRGB, I and S as x/(1+x), N as is."""
    for name in LAYERS:
        if name not in layers:
            raise UsageError(f"G-buffer lacks the {name!r} layer (has {sorted(layers)})")
        if not np.isfinite(layers[name]).all():
            raise UsageError(f"G-buffer layer {name!r} has {int((~np.isfinite(layers[name])).sum())} NaN/Inf values")
    a = 2 * _srgb(layers["albedo"]) - 1
    i = np.maximum(layers["irradiance"], 0)
    s = np.maximum(layers["specular"], 0)
    return np.concatenate([a, 2 * i / (1 + i) - 1, 2 * s / (1 + s) - 1, np.clip(layers["normal"], -1, 1)],
                          -1).astype(np.float32)


def condition_to_layers(c: np.ndarray) -> dict[str, np.ndarray]:
    """Inverse of :func:`local_condition`: (…, H, W, 12) → linear A, I, S and N (values outside the
    condition's range are clipped to it first)."""
    c = np.clip(np.asarray(c, np.float32), -1.0, 1.0)
    a = _linear((c[..., 0:3] + 1) / 2)
    u = np.minimum((c[..., 3:9] + 1) / 2, 0.999)  # x/(1+x) ≤ 0.999 ↔ x ≤ 999
    i_s = u / (1 - u)
    return {"albedo": a.astype(np.float32), "irradiance": i_s[..., :3].astype(np.float32),
            "specular": i_s[..., 3:].astype(np.float32), "normal": c[..., 9:12].copy()}


@torch.no_grad()
def global_condition(layers: dict[str, np.ndarray], source: str) -> np.ndarray | None:
    """MobileNetV2 tokens of whole views → (V, T, 1280): R (16 tokens), A‖I‖S (48 tokens) or None."""
    validate.one_of("global_source", source, GLOBAL_SOURCES)
    if source == "none":
        return None
    imgs = [recompose(layers)] if source == "R" else \
        [layers["albedo"], layers["irradiance"], layers["specular"]]
    net = load_mobilenet()
    toks = []
    for im in imgs:
        x = torch.from_numpy(np.ascontiguousarray(np.asarray(im, np.float32).transpose(0, 3, 1, 2)))
        x = torch.nn.functional.interpolate(x, size=(ENCODER_SIZE, ENCODER_SIZE), mode="bilinear",
                                            align_corners=False, antialias=True)
        f = feature_maps(net, normalise(x), stages=(18,))[0]  # (V, 1280, 4, 4)
        toks.append(f.flatten(2).transpose(1, 2))
    return torch.cat(toks, 1).numpy().astype(np.float32)


# -- training -------------------------------------------------------------------------------------------------------


@dataclass
class DiffRenderResult:
    """``metrics.json`` of a training run."""

    settings: DiffRenderSettings
    cases: list[str]
    train_pairs: int  #: (view, source) pairs trained on
    parameters: int
    training: TrainingSummary
    loss_curve: list[float] = field(default_factory=list)  #: mean loss per 50 steps


def coverage(layers: dict[str, np.ndarray]) -> np.ndarray:
    """(…, H, W) 1 where the G-buffer saw the mesh in some sample of the pixel (normal ≠ 0), else 0."""
    return (np.abs(layers["normal"]).sum(-1) > 0).astype(np.float32)


def known_mask(layers: dict[str, np.ndarray], s: DiffRenderSettings) -> np.ndarray | None:
    """(…, H, W) 0 where the generated value is known to be 0 (``known_background``), else None (nothing known)."""
    return coverage(layers) if s.residual and s.known_background else None


def target_space(photos: np.ndarray, layers: dict[str, np.ndarray], s: DiffRenderSettings) -> np.ndarray:
    """Linear photos → what the model generates: the photo in model space, or its residual over R (scaled)."""
    x = photo_to_model(photos)
    if s.residual:
        x = (x - photo_to_model(recompose(layers))) * s.residual_scale
        m = known_mask(layers, s)
        if m is not None:
            x = x * m[..., None]
    return x.astype(np.float32)


def from_target_space(x: np.ndarray, layers: dict[str, np.ndarray], s: DiffRenderSettings) -> np.ndarray:
    """Inverse of :func:`target_space` → linear photos."""
    if s.residual:
        m = known_mask(layers, s)
        x = np.asarray(x) * (1 if m is None else m[..., None])
        x = x / s.residual_scale + photo_to_model(recompose(layers))
    return model_to_photo(x)


class _Pairs:
    """Every (case, view, source) training pair as model-space arrays, with its global tokens.

    A case's sources are those of ``s.sources`` it has, plus "decomposed" (layers predicted from the photo by
    the decomposition network: the seed's pairs from images, §3.1).
    """

    def __init__(self, cases: list[IntrinsicViews], s: DiffRenderSettings):
        self.x, self.c, self.g, self.w = [], [], [], []
        for v in cases:
            ids = list(v.train)
            missing = [x for x in s.sources if x not in v.layers]
            if DECOMPOSED not in v.layers and missing:
                raise UsageError(f"{v.case or 'a training case'}: no {'/'.join(missing)} G-buffers among its sources "
                                 f"({', '.join(v.layers)}); the ground truth's come from with_truth_layers")
            for src in [k for k in v.layers if k in s.sources or k == DECOMPOSED]:
                L = {k: a[ids] for k, a in v.layers[src].items()}
                self.x.append(target_space(v.photos[ids], L, s))
                m = known_mask(L, s)
                if m is not None:
                    self.w.append(m)
                self.c.append(local_condition(L))
                g = global_condition(L, s.global_source)
                self.g.append(g if g is not None else np.zeros((len(ids), 0, 0), np.float32))
        self.x = np.concatenate(self.x)
        self.c = np.concatenate(self.c)
        self.g = np.concatenate(self.g)
        self.w = np.concatenate(self.w) if self.w else None  #: loss weights per pixel (known background only)
        self.use_global = s.global_source != "none"

    def __len__(self) -> int:
        return len(self.x)

    def batch(self, rng: np.random.Generator, size: int, crop: int):
        ids = rng.integers(0, len(self.x), size)
        h, w = self.x.shape[1:3]
        xs, cs, ws = [], [], []
        for i in ids:
            if crop >= min(h, w):
                y0 = x0 = 0
                ch = cw = min(h, w)
            else:
                y0, x0 = int(rng.integers(0, h - crop + 1)), int(rng.integers(0, w - crop + 1))
                ch = cw = crop
            xs.append(self.x[i, y0:y0 + ch, x0:x0 + cw])
            cs.append(self.c[i, y0:y0 + ch, x0:x0 + cw])
            if self.w is not None:
                ws.append(self.w[i, y0:y0 + ch, x0:x0 + cw])
        x = torch.from_numpy(np.ascontiguousarray(np.stack(xs).transpose(0, 3, 1, 2)))
        c = torch.from_numpy(np.ascontiguousarray(np.stack(cs).transpose(0, 3, 1, 2)))
        g = torch.from_numpy(self.g[ids]) if self.use_global else None
        w = torch.from_numpy(np.ascontiguousarray(np.stack(ws)[:, None])) if ws else None
        return x, c, g, w


class DiffRenderStage(OptimizerStage, Stage):
    """Seeded crops of (G-buffer → photo) pairs; one Adam step on the v-prediction loss per step."""

    unit = "step"

    def __init__(self, cases: list[IntrinsicViews], s: DiffRenderSettings):
        self.cases, self.s = cases, s
        self.name = "train diffusion renderer"
        res = {v.resolution for v in cases}
        cfg = s.model_config()
        for r in res:
            check_size(cfg, r, r)
        if s.crop < min(res):
            check_size(cfg, s.crop, s.crop)
        self.pairs = _Pairs(cases, s)
        self.rng = np.random.default_rng(s.seed)
        self.gen = torch.Generator().manual_seed(s.seed)
        self.model = ConditionalDiffusion(cfg, seed=s.seed)
        if s.channels_last:
            self.model = self.model.to(memory_format=torch.channels_last)
        self.model.train()
        self.scheduler = make_scheduler(cfg)
        self.opt = torch.optim.AdamW(self.model.parameters(), lr=s.lr, weight_decay=0.0)
        self.start_ema(s.ema)

    def fingerprint(self) -> dict:
        return {"settings": self.s, "data": [v.digest() for v in self.cases]}

    def step(self, it: int) -> StepResult:
        x, c, g, w = self.pairs.batch(self.rng, self.s.batch, self.s.crop)
        if self.s.channels_last:
            x, c = x.contiguous(memory_format=torch.channels_last), c.contiguous(memory_format=torch.channels_last)
        return self.backward(diffusion_loss(self.model, self.scheduler, x, c, g, self.gen, self.s.p_uncond, w))

    def finish(self, run: RunState) -> DiffRenderResult:
        losses = np.asarray(run.losses, np.float64)
        curve = [float(np.nanmean(losses[k:k + 50])) for k in range(0, len(losses), 50)]
        return DiffRenderResult(self.s, [v.case for v in self.cases], len(self.pairs),
                                sum(p.numel() for p in self.model.parameters()), run.summary(), curve)


def train_diffrender(cases: list[IntrinsicViews], out: str | Path, s: DiffRenderSettings | None = None,
                     show_progress: bool = True, budget_steps: int | None = None) -> DiffRenderResult | None:
    """Train on the train views of ``cases``; ``OUT/checkpoint.npz`` (resumable), ``OUT/metrics.json`` when done.

    ``budget_steps`` stops after that many steps in this call (checkpointed, returns None); calling
    again with the same settings and data continues exactly.
    """
    s = s or DiffRenderSettings()
    if not cases:
        raise UsageError("no benchmarks to train on")
    return train_stage(lambda: DiffRenderStage(cases, s), out, s, budget_steps, show_progress)[1]


def load_diffrender(run: str | Path) -> tuple[ConditionalDiffusion, DiffRenderSettings]:
    """The trained model of a run folder (its checkpoint's weights), eval mode, and its settings."""
    # runs from before the residual option generated the photo itself, and runs from before known_background
    # were trained on every pixel
    return load_trained(run, DiffRenderStage.__name__, "diffusion renderer",
                        " (train with `photoreal diffrender train`)", DiffRenderSettings,
                        lambda s: ConditionalDiffusion(s.model_config(), seed=s.seed),
                        defaults={"residual": False, "known_background": False, "ema": 0.0}, weights="ema")


def render_views(model: ConditionalDiffusion, s: DiffRenderSettings, layers: dict[str, np.ndarray],
                 sample_s: SampleSettings | None = None, show_progress: bool = True) -> tuple[np.ndarray, float]:
    """Generate photos of whole views from G-buffers (layer → (N, H, W, 3)) → (N, H, W, 3) linear, s per image.

    View k uses noise seed ``sample_s.seed + k`` (all its ``draws`` in one batch), so a view's image does not depend
    on the batch of views.
    """
    ss = sample_s or SampleSettings()
    local = local_condition(layers)
    glob = global_condition(layers, s.global_source)
    known = known_mask(layers, s)
    n, h, w, _ = local.shape
    out = np.empty((n, h, w, 3), np.float32)
    t0 = time.perf_counter()
    with progress_bar(total=n * ss.steps, desc="diffusion render", unit="step", disable=not show_progress) as bar:
        for k in range(n):
            d = ss.draws
            c = torch.from_numpy(np.ascontiguousarray(local[k:k + 1].transpose(0, 3, 1, 2))).expand(d, -1, -1, -1)
            g = None if glob is None else torch.from_numpy(glob[k:k + 1]).expand(d, -1, -1)
            kz = None if known is None else torch.from_numpy(np.ascontiguousarray(known[k:k + 1, None])).expand(
                d, -1, -1, -1)
            x = sample(model, c, g, (d, 3, h, w), steps=ss.steps, guidance=ss.guidance, seed=ss.seed + k,
                       progress=bar.update, known_zero=kz)
            x = x.mean(0)  # in model space, where the loss (and so the posterior mean) lives
            out[k] = from_target_space(x.permute(1, 2, 0).numpy(), {n: a[k] for n, a in layers.items()}, s)
    return out, (time.perf_counter() - t0) / max(n, 1)


def write_views(out_dir: Path, names: list[str], images: np.ndarray, layers: dict[str, np.ndarray]) -> list[str]:
    """Each view as ``NAME.exr`` (the image + its G-buffer layers) and ``NAME.png``, atomically."""
    from foundation.imageio import write_exr, write_png

    written = []
    for k, name in enumerate(names):
        exr = out_dir / f"{name}.exr"
        write_png(exr.with_suffix(".png"), images[k])
        write_exr(exr, {"": images[k], **{n: a[k] for n, a in layers.items()}})
        written.append(str(exr))
    return written


__all__ = ["DECOMPOSED", "TRUTH", "TRAIN_SOURCES", "truth_gbuffers", "with_truth_layers", "condition_to_layers", "coverage", "known_mask", "intrinsic_layers", "from_target_space", "target_space", "DiffRenderResult", "DiffRenderSettings", "GBufferSettings", "GLOBAL_SOURCES", "IntrinsicViews", "LAYERS",
           "SampleSettings", "global_condition", "load_diffrender", "load_intrinsic_views", "local_condition",
           "model_to_photo", "photo_to_model", "render_gbuffers", "render_views",
           "train_diffrender"]
