"""Learned UV-space face stages (seed 003 §2–§4) on one shared backbone.

Notation (seed 003 → code):

=====================  ===================================================================================
T_inc, M               ``lit`` (the photo resampled into UV, zero where unseen) and ``seen``
T_hom ≈ T_alb          the completion model's output: a complete, delit albedo
f_inp, f_hom           one conditional diffusion model here (:class:`CompletionStage`): completion and light
                       homogenisation in a single step, since our target is the albedo itself
LoRA_i, i ∈ {alb, n,   one low-rank adapter per intrinsic (``peft``) on the *frozen* completion backbone
r, s}
h_i = Attn(q_i, K, V)  :class:`CrossIntrinsicAttention`: each branch's queries attend to the keys and values
                       of every branch (concatenated along the token axis)
=====================  ===================================================================================

**The backbone.** The seed adapts one large pretrained diffusion transformer to every task. None exists
offline, so the completion model *is* the backbone: a ``diffusers`` UNet (the shared
:class:`core.ConditionalDiffusion`) trained as a conditional diffusion model (v-prediction, DDIM) that maps the
partial lit texture, its mask and the template geometry to a complete delit albedo. The decomposition then
freezes it and adds one LoRA adapter per intrinsic (albedo, normal, roughness, specular), all four branches run
in one batch (branch-major), each with its own adapter (``peft``'s mixed-adapter batches), and the backbone's
self-attention layers become cross-intrinsic. The decomposition is used as a single-step deterministic
predictor (the backbone at t = 0, the completed albedo in its image slot): on two cores a stochastic multi-step
decomposition would cost ~10× more and, judged by per-texel errors, do worse than its own mean (measured for the
diffusion renderer, issue 13). Ablations: *shared* (the same adapters, plain self-attention) and *independent*
(four full copies of the backbone, each fine-tuned alone: no sharing, 4× the parameters).

**Super-resolution** (§4): a small residual CNN upsamples the model-resolution maps 2× (pixel shuffle), added to
bicubic; it is trained on the training scans' maps and judged against bicubic on the held-out scan.

Every stage trains on the shared loop (checkpoint, budget, resume, NaN policy, progress, metrics JSON).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from foundation import validate
from foundation.errors import CheckpointError, UsageError
from foundation.loop import RunState, Stage, TrainingSummary

from generative.diffusion import (ConditionalDiffusion, DiffusionConfig, OptimizerStage, count_parameters, load_trained, make_scheduler,
                   train_stage)
from .data import FaceSet, TARGETS

#: lit (3), seen (1), covered (1), the baseline's albedo (3), position (3) and normal (3) in the face frame
COND_CHANNELS = 14
GEO = slice(8, 14)  #: the geometry channels of the condition
ALBEDO_LEVEL = 0.35  #: albedos are compared up to a global scale: each is scaled to this mean over the seen texels
RESIDUAL = 2.0  #: the completion model generates RESIDUAL × (albedo − baseline) in the encoded space
BRANCHES = tuple(TARGETS)  #: albedo, normal, roughness, specular
VARIANTS = ("cross_attention", "shared", "independent")
MAP_CHANNELS = sum(TARGETS.values())  #: 8: the super-resolution model's channels


# -- encodings ---------------------------------------------------------------------------------------------------------


def _pool(a: np.ndarray, f: int) -> np.ndarray:
    """Box average by ``f`` over axes 1, 2 of (N, H, W, …)."""
    if f == 1:
        return a
    n, h, w = a.shape[:3]
    return a.reshape(n, h // f, f, w // f, f, *a.shape[3:]).mean(axis=(2, 4))


def at_resolution(d: FaceSet, res: int) -> FaceSet:
    """The set box-filtered to ``res``: a texel is seen (covered) when all its sub-texels are; lit is averaged over
    seen sub-texels; normals are renormalised."""
    if d.res % res:
        raise UsageError(f"the data's {d.res}² maps do not divide into {res}²")
    f = d.res // res
    if f == 1:
        return d
    seen = _pool(d.seen.astype(np.float32), f) > 0.999
    mask = _pool(d.mask.astype(np.float32), f) > 0.999
    unit = lambda a: a / np.maximum(np.linalg.norm(a, axis=-1, keepdims=True), 1e-8)  # noqa: E731
    lit = _pool(d.lit * d.seen[..., None], f) * seen[..., None]
    base = _pool(d.baseline, f)
    t = {k: _pool(v, f) for k, v in d.targets.items()}
    t["normal"] = unit(t["normal"])
    g = {k: _pool(v, f) for k, v in d.geometry.items()}
    g["normal_geo"], g["tangent"] = unit(g["normal_geo"]), unit(g["tangent"])
    g["bitangent_sign"] = np.sign(g["bitangent_sign"])
    return FaceSet(d.names, d.records, lit.astype(np.float32), seen & mask, mask,
                   (_pool(d.position_face, f) * mask[..., None]).astype(np.float32),
                   (unit(_pool(d.normal_face, f)) * mask[..., None]).astype(np.float32), base.astype(np.float32),
                   {k: v.astype(np.float32) for k, v in t.items()}, {k: v.astype(np.float32) for k, v in g.items()})


def encode_lit(lit: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """(N, H, W, 3) linear radiance → [−1, 1], exposure-free: divided by twice the mean seen luminance (lighting's
    absolute level is unknowable from one photo), gamma 1/2.2, 0 where unseen."""
    lum = lit.mean(-1)
    mean = np.array([lum[i][seen[i]].mean() if seen[i].any() else 1.0 for i in range(len(lit))], np.float32)
    e = np.clip(lit / (2.0 * mean[:, None, None, None] + 1e-8), 0.0, 2.0) ** (1 / 2.2)
    return np.where(seen[..., None], e * 2.0 / 2.0 ** (1 / 2.2) - 1.0, 0.0).astype(np.float32)


def normalise_albedo(albedo: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """(N, H, W, 3) albedos scaled to a mean of ALBEDO_LEVEL over each one's seen texels (a photo fixes albedo × light
    intensity only: the models work, and are judged, up to that scale), clipped to [0, 1]."""
    out = np.empty_like(albedo, dtype=np.float32)
    for i in range(len(albedo)):
        ref = seen[i] if seen[i].any() else np.ones(seen[i].shape, bool)
        out[i] = np.clip(albedo[i] * ALBEDO_LEVEL / max(float(albedo[i][ref].mean()), 1e-4), 0.0, 1.0)
    return out


def condition(d: FaceSet) -> np.ndarray:
    """(N, 14, H, W): the local condition of every face model."""
    c = np.concatenate([encode_lit(d.lit, d.seen), d.seen[..., None] * 2.0 - 1.0, d.mask[..., None] * 2.0 - 1.0,
                        encode_albedo(normalise_albedo(d.baseline, d.seen)), d.position_face, d.normal_face], -1)
    return np.ascontiguousarray(c.transpose(0, 3, 1, 2), np.float32)


def encode_albedo(albedo: np.ndarray) -> np.ndarray:
    """Linear albedo (…, 3) → sRGB in [−1, 1]."""
    from foundation.imageio import linear_to_srgb

    return (linear_to_srgb(np.clip(albedo, 0.0, 1.0)) * 2.0 - 1.0).astype(np.float32)


def decode_albedo(x: np.ndarray) -> np.ndarray:
    from foundation.imageio import srgb_to_linear

    return srgb_to_linear(np.clip((x + 1.0) * 0.5, 0.0, 1.0)).astype(np.float32)


def encode_maps(maps: dict[str, np.ndarray]) -> np.ndarray:
    """Maps (N, H, W, C) → (N, 8, H, W) in [−1, 1]: sRGB albedo, unit normal, roughness and specular ×2 − 1."""
    x = np.concatenate([encode_albedo(maps["albedo"]), maps["normal"], maps["roughness"] * 2 - 1,
                        maps["specular"] * 2 - 1], -1)
    return np.ascontiguousarray(x.transpose(0, 3, 1, 2), np.float32)


def decode_maps(x: np.ndarray) -> dict[str, np.ndarray]:
    """Inverse of :func:`encode_maps` (normals renormalised, ranges clipped)."""
    x = np.asarray(x, np.float32).transpose(0, 2, 3, 1)
    n = x[..., 3:6]
    n = n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-6)
    n[..., 2] = np.maximum(n[..., 2], 0.0)
    n = n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-6)
    return {"albedo": decode_albedo(x[..., :3]), "normal": n.astype(np.float32),
            "roughness": np.clip((x[..., 6:7] + 1) * 0.5, 0.05, 1.0), "specular": np.clip((x[..., 7:8] + 1) * 0.5, 0.0, 1.0)}


def mirror(cond: np.ndarray, maps: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray | None]:
    """The same face mirrored across its midline: u flipped, the side components of position and normal negated,
    and the tangent-space normal's x negated (the tangent ∂p/∂u reverses under the reflection)."""
    c = cond[..., ::-1].copy()
    c[:, GEO.start] *= -1  # side component of the position
    c[:, GEO.start + 3] *= -1  # ... and of the normal
    if maps is None:
        return c, None
    m = maps[..., ::-1].copy()
    m[:, 3] *= -1
    return c, m


# -- 1. completion + light homogenisation: a conditional diffusion model ---------------------------------------------


@dataclass
class CompletionSettings:
    """The completion/homogenisation diffusion model (the backbone of the decomposition) and its training run."""

    widths: tuple[int, ...] = (32, 64, 128)
    layers_per_block: int = 1
    attention_levels: int = 1  #: self-attention at the deepest level only (2 cores: attention at 32² costs ~4×)
    head_dim: int = 32
    res: int = 64  #: texels per side the model works at
    steps: int = 20000
    max_seconds: float | None = 720.0
    batch: int = 16
    lr: float = 3e-4
    checkpoint_every: int = 200
    threads: int = 0
    seed: int = 0
    sample_steps: int = 10  #: DDIM steps
    samples: int = 4  #: samples averaged into the returned albedo (the posterior mean: per-texel errors halve)

    def __post_init__(self):
        self.widths = tuple(int(w) for w in self.widths)
        if not self.widths or any(w < 8 or w % 8 for w in self.widths):
            raise UsageError(f"widths must be multiples of 8, got {self.widths}")
        validate.integer("layers_per_block", self.layers_per_block, 1)
        validate.integer("attention_levels", self.attention_levels, 1, len(self.widths))
        validate.integer("res", self.res, 8, 1024)
        if self.res % (1 << (len(self.widths) - 1)):
            raise UsageError(f"res {self.res} must divide by {1 << (len(self.widths) - 1)} (widths {self.widths})")
        validate.integer("steps", self.steps, 1)
        validate.optional(validate.positive, "max_seconds", self.max_seconds)
        validate.integer("batch", self.batch, 1, 4096)
        validate.positive("lr", self.lr)
        validate.integer("checkpoint_every", self.checkpoint_every, 1)
        validate.integer("threads", self.threads, 0)
        validate.seed("seed", self.seed)
        validate.integer("sample_steps", self.sample_steps, 1, 1000)
        validate.integer("samples", self.samples, 1, 256)


def completion_config(s: CompletionSettings) -> DiffusionConfig:
    # no global condition: the null tokens are the only cross-attention input
    return DiffusionConfig(image_channels=3, cond_channels=COND_CHANNELS, widths=s.widths, layers_per_block=s.layers_per_block,
                           attention_levels=s.attention_levels, head_dim=s.head_dim, global_dim=0, global_tokens=1,
                           cross_dim=32)


def build_completion(s: CompletionSettings) -> ConditionalDiffusion:
    return ConditionalDiffusion(completion_config(s), seed=s.seed)


def data_digest(d: FaceSet) -> str:
    import hashlib

    h = hashlib.sha256(json.dumps(d.names).encode())
    for a in (d.lit, d.seen, d.targets["albedo"], d.targets["normal"], d.targets["roughness"], d.targets["specular"]):
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()[:16]


@dataclass
class FaceModelResult:
    what: str
    settings: object
    instances: int
    parameters: int  #: trained parameters
    training: TrainingSummary


class CompletionStage(OptimizerStage, Stage):
    """Random instances (mirrored half of the time) at the model resolution; v-prediction MSE at uniform t."""

    unit = "step"
    name = "train face completion"

    def __init__(self, d: FaceSet, s: CompletionSettings):
        d = at_resolution(d, s.res)
        self.s, self.digest = s, data_digest(d)
        self.cond = condition(d)
        # the residual over the baseline, both at the same albedo level (seen texels)
        target = encode_albedo(normalise_albedo(d.targets["albedo"], d.seen))
        self.x0 = np.ascontiguousarray((RESIDUAL * (target - self.cond[:, 5:8].transpose(0, 2, 3, 1))).transpose(0, 3, 1, 2))
        self.rng = np.random.default_rng(s.seed)
        self.gen = torch.Generator().manual_seed(s.seed)
        self.model = build_completion(s).to(memory_format=torch.channels_last)
        self.sched = make_scheduler(self.model.cfg)
        self.opt = torch.optim.AdamW(self.model.parameters(), lr=s.lr, weight_decay=0.0)

    def fingerprint(self) -> dict:
        return {"settings": self.s, "data": self.digest}

    def step(self, it: int):
        idx = self.rng.integers(0, len(self.cond), self.s.batch)
        flip = self.rng.random(self.s.batch) < 0.5
        cond, x0 = self.cond[idx], self.x0[idx]
        if flip.any():
            mc, mx = mirror(cond[flip], np.concatenate([x0[flip], np.zeros((int(flip.sum()), 5) + x0.shape[2:], np.float32)], 1))
            cond[flip], x0[flip] = mc, mx[:, :3]
        x0 = torch.from_numpy(x0).contiguous(memory_format=torch.channels_last)
        cond = torch.from_numpy(cond).contiguous(memory_format=torch.channels_last)
        b = x0.shape[0]
        t = torch.randint(0, self.model.cfg.train_timesteps, (b,), generator=self.gen)
        noise = torch.randn(x0.shape, generator=self.gen)
        noisy = self.sched.add_noise(x0, noise, t)
        pred = self.model(noisy, t, cond, self.model.tokens(None, b))
        loss = torch.mean((pred - self.sched.get_velocity(x0, noise, t)) ** 2)
        return self.backward(loss)

    def finish(self, run: RunState) -> FaceModelResult:
        return FaceModelResult("completion", self.s, len(self.cond), count_parameters(self.model),
                               run.summary())


def train_completion(d: FaceSet, out: str | Path, s: CompletionSettings | None = None, budget_steps: int | None = None,
                     show_progress: bool = True) -> FaceModelResult | None:
    """Train the completion model on ``d`` (training instances) in folder ``out``; rerun to resume."""
    s = s or CompletionSettings()
    _, result = train_stage(lambda: CompletionStage(d, s), out, s, budget_steps, show_progress)
    return result


def load_completion(run: str | Path) -> tuple[ConditionalDiffusion, CompletionSettings]:
    return load_trained(run, "CompletionStage", "face completion model", " (train one with `photoreal face train-models`)",
                        CompletionSettings, build_completion)


@torch.no_grad()
def complete(model: ConditionalDiffusion, s: CompletionSettings, d: FaceSet, seed: int = 0, samples: int | None = None,
             steps: int | None = None, batch: int = 8) -> np.ndarray:
    """Complete delit albedo (N, res, res, 3), linear, at the model resolution and at the level of
    :func:`normalise_albedo`: the baseline plus the mean of ``samples`` generated residuals (DDIM, η = 0);
    instance i, sample j uses noise seeded by (seed, i, j)."""
    d = at_resolution(d, s.res)
    cond = torch.from_numpy(condition(d))
    samples, steps = samples or s.samples, steps or s.sample_steps
    sched = make_scheduler(model.cfg)
    sched.set_timesteps(steps)
    model.eval()
    out = np.zeros((len(d), 3, s.res, s.res), np.float32)
    jobs = [(i, j) for i in range(len(d)) for j in range(samples)]
    for a in range(0, len(jobs), batch):
        part = jobs[a:a + batch]
        c = cond[[i for i, _ in part]]
        x = torch.stack([torch.randn(3, s.res, s.res, generator=torch.Generator().manual_seed(
            seed * 1_000_003 + i * 1009 + j)) for i, j in part])
        tok = model.tokens(None, len(part))
        for t in sched.timesteps:
            tt = torch.full((len(part),), int(t), dtype=torch.long)
            x = sched.step(model(x, tt, c, tok), t, x, eta=0.0).prev_sample
        for (i, _), xi in zip(part, x.numpy()):
            out[i] += xi / samples
    return decode_albedo(cond[:, 5:8].numpy().transpose(0, 2, 3, 1) + out.transpose(0, 2, 3, 1) / RESIDUAL)


# -- 2. decomposition: LoRA adapters per intrinsic on the frozen backbone, cross-intrinsic attention --------------


class CrossIntrinsicAttention:
    """A ``diffusers`` attention processor for self-attention over K branches stacked branch-major in the batch:
    queries stay per branch, keys and values are concatenated over the branches (seed 003 §3,
    h_i = Attn(q_i, [K_1 … K_K], [V_1 … V_K])). With ``branches = 1`` it is ordinary self-attention."""

    def __init__(self, branches: int):
        self.branches = branches

    def __call__(self, attn, hidden_states: torch.Tensor, encoder_hidden_states=None, attention_mask=None,
                 temb=None, **kwargs) -> torch.Tensor:
        if encoder_hidden_states is not None or attention_mask is not None or hidden_states.ndim != 3:
            raise UsageError("CrossIntrinsicAttention is for unmasked self-attention over (B, N, C) tokens")
        residual = hidden_states
        kb, n, _ = hidden_states.shape
        k = self.branches
        if kb % k:
            raise UsageError(f"batch {kb} is not {k} branches of equal size")
        b = kb // k
        q, key, v = attn.to_q(hidden_states), attn.to_k(hidden_states), attn.to_v(hidden_states)
        heads = attn.heads
        d = q.shape[-1] // heads

        def tokens(x):  # (K·B, N, H·D) → (B, H, K·N, D): branch k's tokens at [k·N, (k+1)·N)
            return x.view(k, b, n, heads, d).permute(1, 3, 0, 2, 4).reshape(b, heads, k * n, d)

        out = F.scaled_dot_product_attention(tokens(q), tokens(key), tokens(v))
        out = out.view(b, heads, k, n, d).permute(2, 0, 3, 1, 4).reshape(kb, n, heads * d)
        out = attn.to_out[1](attn.to_out[0](out))
        if attn.residual_connection:
            out = out + residual
        return out / attn.rescale_output_factor


@dataclass
class DecompSettings:
    """The decomposition (one variant) and its training run."""

    variant: str = "cross_attention"  #: one of VARIANTS
    rank: int = 8  #: LoRA rank
    steps: int = 20000
    max_seconds: float | None = 360.0
    batch: int = 2  #: instances per step (× 4 branches through the backbone)
    lr: float = 1e-3  #: LoRA (the independent models: lr / 5, full fine-tuning)
    checkpoint_every: int = 100
    threads: int = 0
    seed: int = 0
    weights: tuple[float, ...] = (1.0, 1.0, 4.0, 4.0)  #: loss weight per branch (roughness/specular span less range)
    #: λ_img of seed 003's shading loss (0.5 there; 0 = off): predicted and true maps shaded by the UV-space GGX
    #: shader under two random directional lights + ambient, through dr.wrap
    shading_weight: float = 0.5

    def __post_init__(self):
        validate.one_of("variant", self.variant, VARIANTS)
        validate.integer("rank", self.rank, 1, 256)
        validate.integer("steps", self.steps, 1)
        validate.optional(validate.positive, "max_seconds", self.max_seconds)
        validate.integer("batch", self.batch, 1, 4096)
        validate.positive("lr", self.lr)
        validate.integer("checkpoint_every", self.checkpoint_every, 1)
        validate.integer("threads", self.threads, 0)
        validate.seed("seed", self.seed)
        validate.non_negative("shading_weight", self.shading_weight)
        self.weights = tuple(float(w) for w in self.weights)
        if len(self.weights) != len(BRANCHES) or min(self.weights) < 0:
            raise UsageError(f"weights: {len(BRANCHES)} non-negative numbers ({', '.join(BRANCHES)}), got {self.weights}")


#: the seed injects LoRA "into attention and feedforward projections"; conv_in too, so that each branch reads its input
#: its own way (each branch writes its map through its own head)
def torch_maps(x: torch.Tensor) -> dict[str, torch.Tensor]:
    """Encoded maps (B, 8, H, W) → (B, H, W, C) tensors in the UV shader's units (differentiable): linear albedo,
    normal-map rgb (n/2 + ½), roughness, specular."""
    x = x.permute(0, 2, 3, 1)
    a = ((x[..., :3] + 1.0) * 0.5).clamp(0.0, 1.0)
    albedo = torch.where(a <= 0.04045, a / 12.92, ((a + 0.055) / 1.055).clamp(min=1e-6) ** 2.4)  # sRGB decode
    n = F.normalize(x[..., 3:6], dim=-1, eps=1e-6)
    return {"albedo": albedo.contiguous(), "normal": (n * 0.5 + 0.5).contiguous(),
            "roughness": ((x[..., 6:7] + 1.0) * 0.5).clamp(0.05, 1.0).contiguous(),
            "specular": ((x[..., 7:8] + 1.0) * 0.5).clamp(0.0, 1.0).contiguous()}


def uv_shading_error(lights: list, eyes: list, ambient: list):
    """Seed 003's shading loss ‖T̂_shaded(predicted maps) − T_shaded(true maps)‖² over covered texels, through the
    UV-space GGX shader (:func:`mi_plugins.uv_shader.shade_uv`, Dr.Jit) called from torch (``dr.wrap`` in
    :mod:`foundation.bridge`). ``lights[i]``: instance i's :class:`UVLight` list; ``eyes[i]``: its camera
    position; ``ambient[i]``: I_amb (the seed samples it from U(0.15, 0.3)). Returns ``f(pred_maps, true_maps,
    position, normal, tangent, covered)`` on torch tensors."""
    import drjit as dr
    import mitsuba as mi

    from foundation.bridge import torch_to_drjit_loss
    from mi_plugins.uv_shader import UVMaps, UVView, shade_uv

    def fn(pa, pn, pr, ps, ta, tn, tr, ts, pos, nrm, tan, covered):
        total = mi.Float(0.0)
        count = 0.0
        for i in range(len(eyes)):
            def shade(a, n, r, s_):
                maps = UVMaps(albedo=a[i], normal=n[i], roughness=r[i], specular=s_[i])
                return shade_uv(pos[i], nrm[i], tan[i], maps, lights[i], UVView(position=eyes[i]), ambient=ambient[i])
            d = (shade(pa, pn, pr, ps) - shade(ta, tn, tr, ts)) * covered[i]
            total += dr.sum(d * d, axis=None)
            count += 3.0 * float(np.prod(covered[i].shape))
        return total / count

    loss = torch_to_drjit_loss(fn)

    def call(pred: dict, true: dict, pos, nrm, tan, covered):
        return loss(pred["albedo"], pred["normal"], pred["roughness"], pred["specular"], true["albedo"], true["normal"],
                    true["roughness"], true["specular"], pos, nrm, tan, covered)

    return call


LORA_TARGETS = r".*(conv_in|proj_in|proj_out|to_q|to_k|to_v|to_out\.0|ff\.net\.0\.proj|ff\.net\.2)$"


def _set_adapter_names(module, args, kwargs, names):
    kwargs["adapter_names"] = names
    return args, kwargs


#: the template defaults in the encoded space (normal (0, 0, 1), roughness 0.5, specular 0.35); the albedo branch
#: starts from its input, the completed albedo
DEFAULT_ENCODED = (0.0, 0.0, 1.0, 0.0, -0.3)


class Decomposer(nn.Module):
    """The four intrinsics from (albedo estimate, condition): one forward pass over all branches.

    Each branch reads the backbone's last feature map (its ``conv_out`` removed) and the condition through its own
    small head (two 3×3 convolutions, the last zero-initialised), added to where the branch starts: the input albedo, or the template's defaults — an untrained
    decomposition *is* the baseline. ``cross_attention`` / ``shared``: the frozen backbone with one ``peft`` LoRA
    adapter per branch (a mixed-adapter batch, branch-major); ``cross_attention`` also swaps the backbone's
    self-attention for :class:`CrossIntrinsicAttention`. ``independent``: one full copy of the backbone per branch,
    all of it trained. Outputs are in the encoded spaces of :func:`encode_maps`.
    """

    def __init__(self, backbone: ConditionalDiffusion, s: DecompSettings):
        super().__init__()
        import copy
        import warnings

        self.s = s
        self.variant = s.variant
        width = backbone.cfg.widths[0]
        torch.manual_seed(s.seed)
        self.heads = nn.ModuleList([nn.Sequential(nn.Conv2d(width + COND_CHANNELS, 32, 3, padding=1), nn.SiLU(),
                                                  nn.Conv2d(32, c, 3, padding=1)) for c in TARGETS.values()])
        for h in self.heads:
            nn.init.zeros_(h[-1].weight)
            nn.init.zeros_(h[-1].bias)
        self.register_buffer("defaults", torch.tensor(DEFAULT_ENCODED, dtype=torch.float32).view(1, -1, 1, 1))

        def trunk():
            net = copy.deepcopy(backbone)
            net.unet.conv_out = nn.Identity()  # the backbone's features, not its v-prediction
            return net

        if s.variant == "independent":
            self.nets = nn.ModuleList([trunk() for _ in BRANCHES])
            return
        from peft import LoraConfig, inject_adapter_in_model
        from peft.tuners.lora import LoraLayer

        self.net = trunk()
        for name in BRANCHES:
            # lora_dropout 0: the branches are mixed in one batch (peft's adapter_names), which peft allows at
            # inference only because dropout would differ per branch; without dropout training is the same function
            cfg = LoraConfig(r=s.rank, lora_alpha=s.rank, lora_dropout=0.0, target_modules=LORA_TARGETS,
                             init_lora_weights=True)
            with warnings.catch_warnings():  # peft warns that a second adapter joins the first: that is the design
                warnings.filterwarnings("ignore", message="Already found a `peft_config`")
                self.net.unet = inject_adapter_in_model(cfg, self.net.unet, adapter_name=name)
        for n, p in self.net.named_parameters():
            p.requires_grad_("lora_" in n)
        self.lora_layers = [m for m in self.net.unet.modules() if isinstance(m, LoraLayer)]
        if s.variant == "cross_attention":
            procs = dict(self.net.unet.attn_processors)
            for k in procs:
                if k.endswith("attn1.processor"):
                    procs[k] = CrossIntrinsicAttention(len(BRANCHES))
            self.net.unet.set_attn_processor(procs)

    def trainable(self) -> list[nn.Parameter]:
        return [p for p in self.parameters() if p.requires_grad]

    def features(self, albedo: torch.Tensor, cond: torch.Tensor) -> list[torch.Tensor]:
        """Each branch's last feature map (B, width, H, W) of the (adapted) backbone at t = 0."""
        b = albedo.shape[0]
        k = len(BRANCHES)
        t = torch.zeros(b, dtype=torch.long)
        if self.variant == "independent":
            return [net(albedo, t, cond, net.tokens(None, b)) for net in self.nets]
        names = [n for n in BRANCHES for _ in range(b)]
        hooks = [m.register_forward_pre_hook(lambda mod, a, kw: _set_adapter_names(mod, a, kw, names), with_kwargs=True)
                 for m in self.lora_layers]
        try:
            rep = lambda x: x.repeat(k, *([1] * (x.ndim - 1)))  # noqa: E731
            y = self.net(rep(albedo), t.repeat(k), rep(cond), self.net.tokens(None, k * b))
        finally:
            for h in hooks:
                h.remove()
        return list(y.view(k, b, *y.shape[1:]))

    def forward(self, albedo: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        """albedo (B, 3, H, W) encoded, cond (B, 14, H, W) → (B, 8, H, W) encoded maps."""
        f = self.features(albedo, cond)
        start = torch.cat([albedo, self.defaults.expand(albedo.shape[0], -1, *albedo.shape[2:])], 1)
        return start + torch.cat([h(torch.cat([x, cond], 1)) for h, x in zip(self.heads, f)], 1)


def decomposition_loss(pred: torch.Tensor, target: torch.Tensor, covered: torch.Tensor, weights) -> tuple[torch.Tensor, dict]:
    """Weighted mean squared error per branch over covered texels; returns the total and the per-branch terms."""
    terms, a = {}, 0
    m = covered.float()
    denom = m.sum().clamp(min=1.0)
    total = 0.0
    for (name, c), w in zip(TARGETS.items(), weights):
        e = ((pred[:, a:a + c] - target[:, a:a + c]) ** 2).mean(1, keepdim=True)
        terms[name] = (e * m).sum() / denom
        total = total + w * terms[name]
        a += c
    return total, terms


class DecompStage(OptimizerStage, Stage):
    """Batches of (completed albedo, condition) → the four target maps; mirrored half of the time."""

    unit = "step"

    def __init__(self, d: FaceSet, albedo_in: np.ndarray, backbone: ConditionalDiffusion, backbone_id: str,
                 s: DecompSettings, res: int):
        d = at_resolution(d, res)
        self.s, self.name = s, f"train face decomposition ({s.variant})"
        self.digest, self.backbone_id = data_digest(d), backbone_id
        self.cond = condition(d)
        self.alb = np.ascontiguousarray(encode_albedo(albedo_in).transpose(0, 3, 1, 2))
        self.maps = encode_maps({**d.targets, "albedo": normalise_albedo(d.targets["albedo"], d.seen)})
        self.covered = d.mask
        self.geometry = {k: d.geometry[k] for k in ("position", "normal_geo", "tangent")}
        self.eyes = [tuple(map(float, r.get("eye", (0.0, 0.0, 10.0)))) for r in d.records]
        self.fronts = [np.asarray(r["frame"])[2] if "frame" in r else np.array([0.0, 0.0, 1.0]) for r in d.records]
        self.rng = np.random.default_rng(s.seed)
        torch.manual_seed(s.seed)
        self.model = Decomposer(backbone, s)
        lr = s.lr / 5 if s.variant == "independent" else s.lr
        heads = list(self.model.heads.parameters())
        ids = {id(p) for p in heads}
        # the heads start at zero and carry each map's own structure: they learn at 3 × the adapters' rate
        self.opt = torch.optim.AdamW([{"params": [p for p in self.model.trainable() if id(p) not in ids], "lr": lr},
                                      {"params": heads, "lr": 3 * s.lr}], weight_decay=0.0)

    def fingerprint(self) -> dict:
        return {"settings": self.s, "data": self.digest, "backbone": self.backbone_id}

    def step(self, it: int):
        idx = self.rng.integers(0, len(self.cond), self.s.batch)
        flip = self.rng.random(self.s.batch) < 0.5
        cond, maps, alb = self.cond[idx], self.maps[idx], self.alb[idx]
        cov = self.covered[idx][:, None]
        if flip.any():
            both = np.concatenate([maps[flip], alb[flip]], 1)
            cond[flip], mm = mirror(cond[flip], both)
            maps[flip], alb[flip] = mm[:, :MAP_CHANNELS], mm[:, MAP_CHANNELS:]
            cov[flip] = cov[flip][..., ::-1]
        pred = self.model(torch.from_numpy(alb), torch.from_numpy(cond))
        target, covered = torch.from_numpy(maps), torch.from_numpy(cov.copy())
        loss, terms = decomposition_loss(pred, target, covered, self.s.weights)
        if self.s.shading_weight > 0:
            terms["shading"] = self.shading(idx, flip, pred, target, covered)
            loss = loss + self.s.shading_weight * terms["shading"]
        res = self.backward(loss)
        res.log = {k: float(v.detach()) for k, v in terms.items()}
        return res

    def shading(self, idx, flip, pred, target, covered) -> torch.Tensor:
        """The shading term: two lights within 60° of the face's front (seeded by the stage's rng) + ambient."""
        from mi_plugins.uv_shader import UVLight

        lights, amb = [], []
        for i in idx:
            ls = []
            for _ in range(2):
                d = self.fronts[i] + self.rng.normal(scale=0.6, size=3)
                ls.append(UVLight("directional", tuple(map(float, d / np.linalg.norm(d))), (2.0, 2.0, 2.0)))
            lights.append(ls)
            amb.append(float(self.rng.uniform(0.15, 0.3)))
        geo = {k: v[idx].copy() for k, v in self.geometry.items()}
        for k in geo:  # the maps were mirrored: mirror the texels' geometry with them (same surface points)
            geo[k][flip] = geo[k][flip][:, :, ::-1]
        t = lambda a: torch.from_numpy(np.ascontiguousarray(a, np.float32))  # noqa: E731
        err = uv_shading_error(lights, [self.eyes[i] for i in idx], amb)
        return err(torch_maps(pred), torch_maps(target), t(geo["position"]), t(geo["normal_geo"]), t(geo["tangent"]),
                   covered.permute(0, 2, 3, 1).float().contiguous())

    def finish(self, run: RunState) -> FaceModelResult:
        return FaceModelResult(f"decomposition/{self.s.variant}", self.s, len(self.cond),
                               sum(p.numel() for p in self.model.trainable()), run.summary())


def backbone_id(run: str | Path) -> str:
    from foundation.files import file_digest

    return file_digest(Path(run) / "checkpoint.npz")


def train_decomposer(d: FaceSet, albedo_in: np.ndarray, completion_run: str | Path, out: str | Path,
                     s: DecompSettings | None = None, budget_steps: int | None = None,
                     show_progress: bool = True) -> FaceModelResult | None:
    """Train one decomposition variant on ``d`` with ``albedo_in`` (the completion model's albedo of each instance,
    at the model resolution) on the frozen backbone of ``completion_run``; rerun to resume."""
    s = s or DecompSettings()
    backbone, cs = load_completion(completion_run)
    if albedo_in.shape != (len(d), cs.res, cs.res, 3):
        raise UsageError(f"albedo_in must be ({len(d)}, {cs.res}, {cs.res}, 3), got {albedo_in.shape}")
    bid = backbone_id(completion_run)
    _, result = train_stage(lambda: DecompStage(d, albedo_in, backbone, bid, s, cs.res), out, s, budget_steps, show_progress)
    return result


def load_decomposer(run: str | Path, completion_run: str | Path) -> Decomposer:
    """A trained decomposition variant on its backbone; a checkpoint of another backbone is refused."""
    from foundation.loop import read_checkpoint
    from foundation.records import from_json

    ckpt = Path(run) / "checkpoint.npz"
    if not ckpt.is_file():
        raise UsageError(f"{ckpt}: no face decomposition checkpoint (train one with `photoreal face train-models`)")
    saved = read_checkpoint(ckpt)
    if saved.kind != "DecompStage":
        raise CheckpointError(f"{ckpt}: a {saved.kind} checkpoint, not a face decomposition's")
    if saved.fingerprint.get("backbone") != backbone_id(completion_run):
        raise CheckpointError(f"{ckpt}: trained on another completion backbone than {completion_run}")
    s = from_json(DecompSettings, saved.fingerprint["settings"], str(ckpt))
    backbone, _ = load_completion(completion_run)
    model = Decomposer(backbone, s)
    try:
        model.load_state_dict(saved.stage["model"])
    except RuntimeError as exc:
        raise CheckpointError(f"{ckpt}: weights do not fit the architecture its settings describe "
                              f"({str(exc).splitlines()[0]})") from None
    return model.eval()


@torch.no_grad()
def decompose_maps(model: Decomposer, d: FaceSet, albedo_in: np.ndarray, res: int, batch: int = 4) -> dict[str, np.ndarray]:
    """The four maps (N, res, res, C) of every instance, decoded."""
    d = at_resolution(d, res)
    cond = condition(d)
    alb = np.ascontiguousarray(encode_albedo(albedo_in).transpose(0, 3, 1, 2))
    out = [model(torch.from_numpy(alb[a:a + batch]), torch.from_numpy(cond[a:a + batch])).numpy()
           for a in range(0, len(d), batch)]
    return decode_maps(np.concatenate(out))


# -- 3. super-resolution ----------------------------------------------------------------------------------------------


@dataclass
class SuperResSettings:
    width: int = 48
    blocks: int = 6
    steps: int = 20000
    max_seconds: float | None = 180.0
    batch: int = 8
    lr: float = 1e-3
    checkpoint_every: int = 200
    threads: int = 0
    seed: int = 0

    def __post_init__(self):
        validate.integer("width", self.width, 4, 1024)
        validate.integer("blocks", self.blocks, 1, 64)
        validate.integer("steps", self.steps, 1)
        validate.optional(validate.positive, "max_seconds", self.max_seconds)
        validate.integer("batch", self.batch, 1, 4096)
        validate.positive("lr", self.lr)
        validate.integer("checkpoint_every", self.checkpoint_every, 1)
        validate.integer("threads", self.threads, 0)
        validate.seed("seed", self.seed)


class UVUpscaler(nn.Module):
    """2× upscaler of the encoded maps (8 channels): residual blocks at the low resolution, pixel shuffle, added to
    bicubic (ESPCN/EDSR-style; the seed fine-tunes Real-ESRGAN, whose weights are not available offline)."""

    def __init__(self, s: SuperResSettings):
        super().__init__()
        torch.manual_seed(s.seed)
        c = MAP_CHANNELS
        self.head = nn.Conv2d(c + 6, s.width, 3, padding=1)  # + position and normal in the face frame
        self.body = nn.ModuleList([nn.Sequential(nn.Conv2d(s.width, s.width, 3, padding=1), nn.ReLU(),
                                                 nn.Conv2d(s.width, s.width, 3, padding=1)) for _ in range(s.blocks)])
        self.tail = nn.Conv2d(s.width, 4 * c, 3, padding=1)
        nn.init.zeros_(self.tail.weight)  # starts as bicubic
        nn.init.zeros_(self.tail.bias)

    def forward(self, low: torch.Tensor, geo: torch.Tensor) -> torch.Tensor:
        """low (B, 8, H, W) encoded maps, geo (B, 6, H, W) → (B, 8, 2H, 2W)."""
        h = self.head(torch.cat([low, geo], 1))
        for blk in self.body:
            h = h + blk(F.relu(h))
        up = F.interpolate(low, scale_factor=2, mode="bicubic", align_corners=False)
        return up + F.pixel_shuffle(self.tail(h), 2)


def bicubic_up(low: np.ndarray) -> np.ndarray:
    return F.interpolate(torch.from_numpy(low), scale_factor=2, mode="bicubic", align_corners=False).numpy()


class SuperResStage(OptimizerStage, Stage):
    """High-resolution targets → box-downsampled inputs; L1 over covered texels; mirrored half of the time."""

    unit = "step"
    name = "train face super-resolution"

    def __init__(self, d: FaceSet, s: SuperResSettings):
        if d.res % 2:
            raise UsageError(f"super-resolution needs even map sizes, got {d.res}")
        lo = at_resolution(d, d.res // 2)
        self.s, self.digest = s, data_digest(d)
        self.high = encode_maps(d.targets)
        self.low = encode_maps(lo.targets)
        self.geo = condition(lo)[:, GEO]
        self.covered = d.mask[:, None]
        self.rng = np.random.default_rng(s.seed)
        self.model = UVUpscaler(s)
        self.opt = torch.optim.AdamW(self.model.parameters(), lr=s.lr, weight_decay=0.0)

    def fingerprint(self) -> dict:
        return {"settings": self.s, "data": self.digest}

    def step(self, it: int):
        idx = self.rng.integers(0, len(self.high), self.s.batch)
        low, geo, high, cov = self.low[idx], self.geo[idx], self.high[idx], self.covered[idx]
        flip = self.rng.random(self.s.batch) < 0.5
        if flip.any():
            # mirror() works on the whole condition; geometry is its GEO channels
            pad = np.zeros((int(flip.sum()), GEO.start) + geo.shape[2:], np.float32)
            c, lo_m = mirror(np.concatenate([pad, geo[flip]], 1), low[flip])
            geo[flip], low[flip] = c[:, GEO], lo_m
            high[flip] = mirror(np.zeros((int(flip.sum()), COND_CHANNELS) + high.shape[2:], np.float32), high[flip])[1]
            cov[flip] = cov[flip][..., ::-1]
        pred = self.model(torch.from_numpy(low), torch.from_numpy(geo))
        m = torch.from_numpy(cov.copy()).float()
        loss = ((pred - torch.from_numpy(high)).abs() * m).sum() / (m.sum() * MAP_CHANNELS).clamp(min=1.0)
        return self.backward(loss)

    def finish(self, run: RunState) -> FaceModelResult:
        return FaceModelResult("superres", self.s, len(self.high), count_parameters(self.model),
                               run.summary())


def train_superres(d: FaceSet, out: str | Path, s: SuperResSettings | None = None, budget_steps: int | None = None,
                   show_progress: bool = True) -> FaceModelResult | None:
    s = s or SuperResSettings()
    _, result = train_stage(lambda: SuperResStage(d, s), out, s, budget_steps, show_progress)
    return result


def load_superres(run: str | Path) -> UVUpscaler:
    model, _ = load_trained(run, "SuperResStage", "face super-resolution model",
                            " (train one with `photoreal face train-models`)", SuperResSettings, UVUpscaler)
    return model


@torch.no_grad()
def upscale(model: UVUpscaler | None, maps: dict[str, np.ndarray], low: FaceSet) -> dict[str, np.ndarray]:
    """Maps at ``low``'s resolution → 2×: the learned upscaler, or bicubic when ``model`` is None."""
    x = encode_maps(maps)
    if model is None:
        return decode_maps(bicubic_up(x))
    geo = condition(low)[:, GEO]
    return decode_maps(model(torch.from_numpy(x), torch.from_numpy(geo)).numpy())


__all__ = ["BRANCHES", "COND_CHANNELS", "CompletionSettings", "CrossIntrinsicAttention", "DecompSettings", "Decomposer",
           "FaceModelResult", "SuperResSettings", "UVUpscaler", "VARIANTS", "at_resolution", "bicubic_up", "complete",
           "condition", "decode_albedo", "decode_maps", "decompose_maps", "encode_albedo", "encode_lit", "encode_maps",
           "load_completion", "load_decomposer", "load_superres", "mirror", "normalise_albedo", "train_completion", "train_decomposer",
           "train_superres", "upscale"]
