"""Generative neural materials (seed 002 §3.2, §4, §4.4): diffusion over the universal basis' feature textures.

A sample is a 2C-channel image [T_off ‖ T_rgb] (C = 8: 16 channels); decoded through the *frozen* universal
MLPs it is a neural BTF that the ``neural_btf`` plugin renders. Every choice the seed makes is a switch of
:class:`MatDiffSettings`, so each can be ablated at equal training time:

* ``circular`` — periodic (circular) padding in every convolution (§3.2): samples tile, at any size;
* ``prediction`` — v-prediction (default) or ε;
* ``shift_base`` — shifted cosine schedule, SNR_shift(t) = SNR(t)·(base/H)² (§4, Simple Diffusion). The seed
  shifts only above its base 64 at its 512² textures; our textures are 32², so the base is a parameter
  (default 16: SNR × ¼) and 0 switches it off;
* ``min_snr_gamma`` — Min-SNR-γ loss weighting (§4, Hang et al. 2023, the seed's w(t)): for v-prediction
  w = min(SNR, γ)/(SNR + 1), for ε min(SNR, γ)/SNR; 0 = unweighted;
* ``cube_root`` — the model sees cbrt(f / s) (s: the 99.9th percentile of |f| in the training set), the
  inverse is applied after sampling (§4 "nonlinear scaling");
* ``multiscale`` — eq. 4: the error is also compared after average-pooling to H/2, H/4, … ≥ 8, each scale
  weighted by 8/H_i (the seed: 64/H_i from 64 up; linear, so it is applied to the v error directly);
* ``cfg`` — conditions dropped during training (keywords and exemplar each kept with p = 0.6, so 16 % of
  samples see neither: unconditional generation) and classifier-free guidance at sampling.

Conditioning (§3.2, §4.4), all in one model through cross-attention tokens:

* keywords — one token per slot (family, colour, finish) of the closed vocabulary of
  :mod:`.material_data`, a one-hot vector through a learned linear map (an embedding); the seed conditions
  on CLIP text, unavailable offline: this is keyword conditioning, not free text;
* exemplar — 16 tokens of pretrained MobileNetV2 features of an image of the material (the seed: CLIP
  ViT-L/14 image features), and the image itself, mean-normalised and resized to the texture, concatenated
  with the noisy input (the seed's "normalized render ... concatenated with the diffusion inputs").

The model is the shared :class:`core.ConditionalDiffusion` (``diffusers`` UNet2DConditionModel) with its
convolutions switched to circular padding; the schedulers are ``diffusers``' DDIM with the shifted betas.
Training runs on the shared loop (checkpoint, budget, resume, NaN policy, progress, metrics JSON), by default on
random wrapped 16² crops of the textures (``train_crop``: a CPU budget buys 4.4× the steps; sampling is at any size).
"""

from __future__ import annotations

import contextlib
import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from foundation import validate
from foundation.errors import UsageError
from foundation.loop import RunState, Stage, StepResult, TrainingSummary

from generative.diffusion import ConditionalDiffusion, DiffusionConfig, OptimizerStage, load_trained, train_stage
from .data import SLOTS, VOCABULARY, MaterialSet, keyword_onehots

FEATURE_DIM = 1280  #: MobileNetV2's last feature width
EXEMPLAR_TOKENS = 16  #: a 4×4 feature map of the exemplar at 128²
KEYWORD_TOKENS = len(SLOTS)
TOKENS = KEYWORD_TOKENS + EXEMPLAR_TOKENS
GLOBAL_DIM = FEATURE_DIM + len(VOCABULARY)  #: exemplar features in the first 1280 dims, one-hot words in the rest
MULTISCALE_MIN = 8
#: default clamp of the predicted x₀ while sampling (None = off, as measured by `bench matdiff`). Clamping to 1.2
#: (the data lie in about [−1.1, 1.1] after scaling) removed the cubed outliers of the 900 s model's samples but
#: barely moved its scores (keyword accuracy 0.16 → 0.19, MobileNetV2-KID 0.222 → 0.205 on 32 samples)
CLIP = None


@dataclass
class MatDiffSettings:
    """Architecture, the seed's switches, and the training run of a material diffusion model."""

    widths: tuple[int, ...] = (32, 64, 96)  #: 1.3 s per batch-16 step at 32² on one core ((64, 96, 128): 3.1 s)
    layers_per_block: int = 1
    #: the deepest level and the middle block (2: also the 16² level, +50 % time per step; see train_crop)
    attention_levels: int = 1
    head_dim: int = 32
    circular: bool = True
    prediction: str = "v_prediction"
    shift_base: int = 16  #: SNR × (base/H)²; 0 = the plain cosine schedule
    min_snr_gamma: float = 5.0  #: 0 = no Min-SNR weighting
    snr_floor: bool = False  #: v-prediction: weight the x₀ error by min(SNR, γ) + 1, not min(SNR, γ) (see loss_weight)
    cube_root: bool = True
    multiscale: bool = True
    cfg: bool = True  #: drop conditions in training (p_keep below) and guide at sampling
    p_keep: float = 0.6  #: probability that the keywords (independently: the exemplar) are kept in a training sample
    exemplar_local: bool = True  #: also concatenate the exemplar image with the noisy input
    keyword_embedding: bool = True  #: also add the keywords to the time embedding (ADM-style class conditioning)
    steps: int = 20000  #: upper bound; ``max_seconds`` usually ends the run first
    max_seconds: float | None = 900.0
    batch: int = 16
    #: texels per side of the random (wrapped) crops trained on; 0 = the whole texture. 16 with one attention level
    #: and lr 1e-3: 4.4× the steps of whole 32² textures with two levels and lr 5e-4 in equal time, and the held-out
    #: x̂₀ error at t = 79 / 159 of 0.034 / 0.063 instead of 0.053 / 0.122 (480 s, one thread; docs/results/material-diffusion.md)
    train_crop: int = 16
    lr: float = 1e-3
    ema: float = 0.0  #: decay of the weights' exponential moving average that sampling uses; 0 = the raw weights
    checkpoint_every: int = 200
    threads: int = 0
    seed: int = 0
    feature_scale: float = 0.0  #: s of the scaling; 0 = measured on the training set when training starts
    channels: int = 8  #: C of T_off and of T_rgb (the basis')
    basis_id: str = ""  #: the basis the training materials were fitted to (samples carry it)
    train_res: int = 0  #: texels per side of the training textures (set when training starts)

    def __post_init__(self):
        self.widths = tuple(int(w) for w in self.widths)
        if not self.widths or any(w < 8 or w % 8 for w in self.widths):
            raise UsageError(f"widths must be multiples of 8, got {self.widths}")
        validate.integer("layers_per_block", self.layers_per_block, 1)
        validate.integer("attention_levels", self.attention_levels, 0, len(self.widths))
        validate.integer("head_dim", self.head_dim, 1)
        validate.one_of("prediction", self.prediction, ("v_prediction", "epsilon"))
        validate.integer("shift_base", self.shift_base, 0)
        validate.non_negative("min_snr_gamma", self.min_snr_gamma)
        validate.in_range("p_keep", self.p_keep, 0.0, 1.0)
        validate.integer("steps", self.steps, 1)
        validate.optional(validate.positive, "max_seconds", self.max_seconds)
        validate.integer("batch", self.batch, 1, 4096)
        validate.integer("train_crop", self.train_crop, 0)
        if self.train_crop and self.train_crop % self.multiple:
            raise UsageError(f"train_crop {self.train_crop} must divide by {self.multiple} (widths {self.widths})")
        validate.positive("lr", self.lr)
        validate.in_range("ema", self.ema, 0.0, 0.99999)
        validate.integer("checkpoint_every", self.checkpoint_every, 1)
        validate.integer("threads", self.threads, 0)
        validate.seed("seed", self.seed)
        validate.non_negative("feature_scale", self.feature_scale)
        validate.integer("channels", self.channels, 1)

    @property
    def multiple(self) -> int:
        return 1 << (len(self.widths) - 1)


# -- the model ------------------------------------------------------------------------------------------------------


def diffusion_config(s: MatDiffSettings) -> DiffusionConfig:
    return DiffusionConfig(image_channels=2 * s.channels, cond_channels=3 if s.exemplar_local else 0,
                           widths=s.widths, layers_per_block=s.layers_per_block, attention_levels=s.attention_levels,
                           head_dim=s.head_dim, global_dim=GLOBAL_DIM, global_tokens=TOKENS, prediction=s.prediction,
                           class_dim=KEYWORD_TOKENS * len(VOCABULARY) if s.keyword_embedding else 0)


def _padded_convs(model: torch.nn.Module) -> list[torch.nn.Conv2d]:
    return [m for m in model.modules() if isinstance(m, torch.nn.Conv2d) and max(m.padding) > 0]


@contextlib.contextmanager
def padding_mode(model: torch.nn.Module, mode: str | None):
    """Temporarily set every padded convolution of ``model`` to ``mode`` (None: leave as built)."""
    convs = _padded_convs(model) if mode else []
    old = [m.padding_mode for m in convs]
    for m in convs:
        m.padding_mode = mode
    try:
        yield
    finally:
        for m, o in zip(convs, old):
            m.padding_mode = o


def build_model(s: MatDiffSettings) -> ConditionalDiffusion:
    model = ConditionalDiffusion(diffusion_config(s), seed=s.seed)
    if s.circular:
        for m in _padded_convs(model):  # §3.2: periodic boundaries in every convolution → tileable feature textures
            m.padding_mode = "circular"
    return model


def alphas_cumprod(s: MatDiffSettings, res: int, timesteps: int = 1000) -> np.ndarray:
    """ᾱ_t of the cosine schedule (diffusers' squaredcos_cap_v2) with its SNR scaled by (shift_base/res)²."""
    from diffusers import DDIMScheduler

    base = DDIMScheduler(num_train_timesteps=timesteps, beta_schedule="squaredcos_cap_v2").alphas_cumprod.double().numpy()
    if not s.shift_base:
        return base
    snr = base / (1.0 - base) * (s.shift_base / float(res)) ** 2
    return snr / (1.0 + snr)


def make_material_scheduler(s: MatDiffSettings, res: int, clip: float | None = None):
    """diffusers' DDIM scheduler on the (shifted) schedule: betas from ᾱ, β_t = 1 − ᾱ_t/ᾱ_{t−1}. ``clip`` clamps
    each step's predicted x₀ to [−clip, clip] in the model's space (static thresholding, Saharia et al. 2022)."""
    from diffusers import DDIMScheduler

    ac = alphas_cumprod(s, res)
    betas = 1.0 - ac / np.concatenate([[1.0], ac[:-1]])
    return DDIMScheduler(num_train_timesteps=len(ac), trained_betas=np.clip(betas, 0.0, 0.999).tolist(),
                         prediction_type=s.prediction, clip_sample=clip is not None,
                         clip_sample_range=float(clip or 1.0), set_alpha_to_one=True, timestep_spacing="trailing")


def to_model_space(f: np.ndarray | torch.Tensor, s: MatDiffSettings):
    """Feature values → the model's space: cbrt(f/s) (or f/s with cube_root off)."""
    x = f / s.feature_scale
    if not s.cube_root:
        return x
    return torch.sign(x) * x.abs() ** (1 / 3) if isinstance(x, torch.Tensor) else np.cbrt(x)


def from_model_space(x: np.ndarray | torch.Tensor, s: MatDiffSettings):
    return (x ** 3 if s.cube_root else x) * s.feature_scale


def exemplar_local(images: np.ndarray, res: int) -> torch.Tensor:
    """Linear (N, H, W, 3) images → (N, 3, res, res) in [−1, 1]: divided by twice their mean (exposure-free),
    clipped, sRGB-encoded, area-resized to the texture."""
    from foundation.features import to_srgb

    x = torch.from_numpy(np.ascontiguousarray(np.asarray(images, np.float32).transpose(0, 3, 1, 2)))
    x = x / (2.0 * x.mean(dim=(1, 2, 3), keepdim=True) + 1e-6)
    if x.shape[-1] != res or x.shape[-2] != res:
        x = F.interpolate(x, size=(res, res), mode="bilinear", antialias=True, align_corners=False)
    return to_srgb(x) * 2.0 - 1.0


@torch.no_grad()
def exemplar_features(images: np.ndarray, batch: int = 64) -> np.ndarray:
    """Linear (N, H, W, 3) images → (N, 16, 1280) MobileNetV2 tokens (4×4 map of the image resized to 128²)."""
    from foundation.features import feature_maps, load_mobilenet, normalise

    net = load_mobilenet()
    out = []
    images = np.asarray(images, np.float32)
    for a in range(0, len(images), batch):
        x = torch.from_numpy(np.ascontiguousarray(images[a:a + batch].transpose(0, 3, 1, 2)))
        x = x / (2.0 * x.mean(dim=(1, 2, 3), keepdim=True) + 1e-6)  # the same exposure normalisation as the local image
        x = F.interpolate(x, size=(128, 128), mode="bilinear", align_corners=False)
        f = feature_maps(net, normalise(x), stages=(18,))[0]
        out.append(f.flatten(2).transpose(1, 2).numpy())
    return np.concatenate(out).astype(np.float32)


def global_tokens(keywords: np.ndarray | None, exemplar: np.ndarray | None, batch: int) -> tuple[np.ndarray, np.ndarray]:
    """(B, TOKENS, GLOBAL_DIM) condition and the (B, TOKENS) mask of present tokens (absent → the null token)."""
    g = np.zeros((batch, TOKENS, GLOBAL_DIM), np.float32)
    present = np.zeros((batch, TOKENS), bool)
    if keywords is not None:
        g[:, :KEYWORD_TOKENS, FEATURE_DIM:] = keywords
        present[:, :KEYWORD_TOKENS] = keywords.sum(-1) > 0
    if exemplar is not None:
        g[:, KEYWORD_TOKENS:, :FEATURE_DIM] = exemplar
        present[:, KEYWORD_TOKENS:] = True
    return g, present


def keyword_vector(g: torch.Tensor) -> torch.Tensor:
    """The keyword one-hots of a condition (B, TOKENS, GLOBAL_DIM) as one (B, 3·|vocabulary|) vector (zeros where
    no keyword is given: the unconditional input of the time-embedding path)."""
    return g[:, :KEYWORD_TOKENS, FEATURE_DIM:].reshape(g.shape[0], -1)


def cross_tokens(model: ConditionalDiffusion, g: torch.Tensor, present: torch.Tensor) -> torch.Tensor:
    """Project the condition; every absent token is the learned null token of its position."""
    b = g.shape[0]
    null = model.null_tokens.expand(b, -1, -1)
    return torch.where(present[..., None], model.project(g), null)


def loss_weight(snr: torch.Tensor, s: MatDiffSettings) -> torch.Tensor:
    """Min-SNR-γ weight of the squared v (or ε) error at signal-to-noise ratio ``snr``; 1 when switched off.

    In x₀ terms the squared v error is (SNR + 1)·|x₀ − x̂₀|² and the ε error SNR·|x₀ − x̂₀|²; Min-SNR-γ makes the
    x₀ weight min(SNR, γ), which vanishes at pure noise — the only regime where the condition alone must set the
    texture's colour and layout (at lower noise the input reveals them). With ``snr_floor`` (v-prediction) the x₀
    weight is min(SNR, γ) + 1: plain v-loss at pure noise, capped at γ + 1 where the signal dominates."""
    if not s.min_snr_gamma:
        return torch.ones_like(snr)
    if s.prediction == "v_prediction":
        return (torch.clamp(snr, max=s.min_snr_gamma) + (1.0 if s.snr_floor else 0.0)) / (snr + 1.0)
    return torch.clamp(snr, max=s.min_snr_gamma) / snr


def material_loss(model: ConditionalDiffusion, sched, s: MatDiffSettings, x0: torch.Tensor, local: torch.Tensor | None,
                  g: torch.Tensor, present: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
    """One Monte-Carlo estimate of eq. 4 (with the switches of ``s``)."""
    b, _, h, _ = x0.shape
    # drawn on the CPU generator whatever the device: a run's random stream (and its checkpoint) is device-free
    t = torch.randint(0, sched.config.num_train_timesteps, (b,), generator=gen)
    noise = torch.randn(x0.shape, generator=gen, dtype=x0.dtype).to(x0.device)
    t_dev = t.to(x0.device)
    noisy = sched.add_noise(x0, noise, t_dev)
    target = sched.get_velocity(x0, noise, t_dev) if s.prediction == "v_prediction" else noise
    err = model(noisy, t_dev, local, cross_tokens(model, g, present), keyword_vector(g)) - target
    ac = sched.alphas_cumprod.to(x0.device, x0.dtype)[t_dev]
    w = loss_weight(ac / (1.0 - ac), s)
    per = err.square().mean(dim=(1, 2, 3))
    if s.multiscale:
        per = per * (MULTISCALE_MIN / h)
        e, r = err, h
        while r // 2 >= MULTISCALE_MIN:
            e, r = F.avg_pool2d(e, 2), r // 2
            per = per + (MULTISCALE_MIN / r) * e.square().mean(dim=(1, 2, 3))
    return torch.mean(w * per)


# -- training -------------------------------------------------------------------------------------------------------


@dataclass
class MatDiffResult:
    settings: MatDiffSettings
    materials: int
    parameters: int
    training: TrainingSummary


class MatDiffStage(OptimizerStage, Stage):
    """Batches of training materials, each rolled by a random offset (a tileable texture has no origin; the
    exemplar image rolls with it), with keywords and one of its swatches as exemplar, each kept with p_keep."""

    unit = "step"

    def __init__(self, data: MaterialSet, s: MatDiffSettings, tokens: np.ndarray, device: str = "cpu"):
        self.s = s
        self.device = torch.device(device)
        self.name = "train material diffusion"
        self.x = to_model_space(data.features, s).astype(np.float32)
        self.kw = keyword_onehots(data.keywords)
        self.swatches = data.swatches
        self.tokens = tokens  #: (N, K, 16, 1280) exemplar tokens of every swatch
        self.res = data.features.shape[-1]
        self.digest = data_digest(data)
        self.rng = np.random.default_rng(s.seed)
        self.gen = torch.Generator().manual_seed(s.seed)
        self.model = build_model(s).to(self.device)
        self.sched = make_material_scheduler(s, self.res)
        self.opt = torch.optim.AdamW(self.model.parameters(), lr=s.lr, weight_decay=0.0)
        self.start_ema(s.ema)

    def fingerprint(self) -> dict:
        return {"settings": self.s, "data": self.digest}

    def step(self, it: int) -> StepResult:
        s, rng = self.s, self.rng
        idx = rng.integers(0, len(self.x), s.batch)
        view = rng.integers(0, self.swatches.shape[1], s.batch)
        shifts = rng.integers(0, self.res, (s.batch, 2))
        p = s.p_keep if s.cfg else 1.0
        keep_kw, keep_ex = rng.random(s.batch) < p, rng.random(s.batch) < p
        x0 = np.stack([np.roll(self.x[i], tuple(d), (1, 2)) for i, d in zip(idx, shifts)])
        c = min(s.train_crop or self.res, self.res)  # after the random roll, the corner crop is a random wrapped crop
        x0 = np.ascontiguousarray(x0[:, :, :c, :c])
        g, present = global_tokens(self.kw[idx] * keep_kw[:, None, None], self.tokens[idx, view], s.batch)
        present[:, KEYWORD_TOKENS:] &= keep_ex[:, None]
        local = None
        if s.exemplar_local:
            ex = np.stack([np.roll(self.swatches[i, v], tuple(d), (0, 1)) for i, v, d in zip(idx, view, shifts)])
            local = exemplar_local(ex, self.res)[..., :c, :c] * torch.from_numpy(keep_ex.astype(np.float32)).view(-1, 1, 1, 1)
            local = local.to(self.device)
        # A crop is not periodic: its convolutions pad with zeros (the interior statistics are what is learned;
        # sampling at the full size pads circularly again, so samples still tile).
        with padding_mode(self.model, "zeros" if c < self.res and s.circular else None):
            dev = self.device
            loss = material_loss(self.model, self.sched, s, torch.from_numpy(x0).to(dev), local,
                                 torch.from_numpy(g).to(dev), torch.from_numpy(present).to(dev), self.gen)
            return self.backward(loss)

    def finish(self, run: RunState) -> MatDiffResult:
        return MatDiffResult(self.s, len(self.x), sum(p.numel() for p in self.model.parameters()), run.summary())


def data_digest(data: MaterialSet) -> str:
    """What a run was trained on: names, keywords and feature textures (a run is resumed or evaluated only on these)."""
    import hashlib

    h = hashlib.sha256()
    h.update(json.dumps([data.names, data.keywords]).encode())
    h.update(np.ascontiguousarray(data.features, np.float32).tobytes())
    return h.hexdigest()[:16]


#: the keyword triples of a run's training materials and their counts: p(c) of p(x) = Σ_c p(c) p(x | c)
PRIOR_FILE = "keyword_prior.json"


def save_keyword_prior(run: str | Path, data: MaterialSet) -> Path:
    """Record the training materials' keyword triples in ``run`` (``train_matdiff`` does; for a run trained elsewhere,
    pass its exact training split: when the run has a checkpoint, the data digest must match it)."""
    from foundation.loop import read_checkpoint

    ckpt, digest = Path(run) / "checkpoint.npz", data_digest(data)
    if ckpt.is_file():
        got = read_checkpoint(ckpt).fingerprint.get("data")
        if got != digest:
            raise UsageError(f"{ckpt}: trained on other materials (data digest {got} vs {digest})")
    return _write_keyword_prior(run, data, digest)


def _write_keyword_prior(run: str | Path, data: MaterialSet, digest: str) -> Path:
    from foundation.files import write_json

    triples, counts = np.unique(np.array([[w or "" for w in k] for k in data.keywords], dtype=object).astype(str),
                                axis=0, return_counts=True)
    return write_json(Path(run) / PRIOR_FILE, {"data": digest, "triples": triples.tolist(), "counts": counts.tolist()})


def prior_keywords(run: str | Path, n: int, seed: int) -> list[list]:
    """``n`` keyword triples drawn (seeded) from the run's training prior (:data:`PRIOR_FILE`)."""
    from foundation.files import read_json

    p = Path(run) / PRIOR_FILE
    if not p.is_file():
        raise UsageError(f"{p}: this run records no keyword prior (train it with this photoreal, or write one with "
                         "generative.btf.save_keyword_prior)")
    d = read_json(p, "keyword prior")
    try:
        triples, w = d["triples"], np.asarray(d["counts"], np.float64)
        if len(triples) != len(w) or not len(w) or (w <= 0).any():
            raise ValueError("triples and positive counts of one length")
        from .data import SLOTS

        if any(not isinstance(t, list) or len(t) != len(SLOTS) or not all(isinstance(word, str) for word in t)
               for t in triples):
            raise ValueError(f"each triple is {len(SLOTS)} words (empty: slot not given)")
    except (KeyError, TypeError, ValueError) as e:
        raise UsageError(f"{p}: malformed keyword prior ({e})") from None
    pick = np.random.default_rng(seed).choice(len(w), n, p=w / w.sum())
    return [[w_ or None for w_ in triples[i]] for i in pick]


def feature_scale(features: np.ndarray) -> float:
    return float(max(np.percentile(np.abs(features), 99.9), 1e-6))


def train_matdiff(data: MaterialSet, out: str | Path, s: MatDiffSettings | None = None, budget_steps: int | None = None,
                  show_progress: bool = True, device: str = "cpu") -> MatDiffResult | None:
    """Train on ``data``'s materials (pass only the training split) in folder ``out`` (``checkpoint.npz``,
    ``metrics.json``); rerun to resume. ``budget_steps`` ends this call early (a later call continues).

    ``device`` (a torch device, e.g. ``cuda``) runs the model there; batches and the random stream stay on the CPU,
    so a run may resume on another device (the checkpoint is the same either way)."""
    import dataclasses

    from generative.diffusion import torch_device

    device = torch_device(device)
    s = s or MatDiffSettings()
    if len(data.names) < 2:
        raise UsageError(f"material diffusion needs at least 2 training materials, got {len(data.names)}")
    res = data.features.shape[-1]
    if res % s.multiple:
        raise UsageError(f"feature textures of {res}² do not divide by {s.multiple} (widths {s.widths})")
    if data.features.shape[1] != 2 * s.channels:
        s = dataclasses.replace(s, channels=data.features.shape[1] // 2)
    if not s.feature_scale:
        s = dataclasses.replace(s, feature_scale=feature_scale(data.features))
    if not s.basis_id:
        s = dataclasses.replace(s, basis_id=data.basis_id)
    if not s.train_res:
        s = dataclasses.replace(s, train_res=res)
    n, k = data.swatches.shape[:2]
    tokens = exemplar_features(data.swatches.reshape(n * k, *data.swatches.shape[2:])).reshape(n, k, EXEMPLAR_TOKENS, -1)
    stage, result = train_stage(lambda: MatDiffStage(data, s, tokens, device), out, s, budget_steps, show_progress)
    _write_keyword_prior(out, data, stage.digest)  # the loop checked this digest against the checkpoint's
    return result


def load_matdiff(run: str | Path) -> tuple[ConditionalDiffusion, MatDiffSettings]:
    return load_trained(run, "MatDiffStage", "material diffusion model", " (train one with `photoreal btf train-diffusion`)",
                        MatDiffSettings, build_model,
                        defaults={"keyword_embedding": False, "ema": 0.0, "train_crop": 0},  # older runs
                        weights="ema")


#: a run's recorded sampler (``bench matdiff`` writes it: the fewest DDIM steps within tolerance of the best keyword
#: accuracy); ``btf generate`` uses it unless told otherwise
SAMPLER_FILE = "sampler.json"
DEFAULT_SAMPLER = {"steps": 25, "guidance": 2.0}


def save_sampler(run: str | Path, steps: int, guidance: float, chosen_by: str) -> Path:
    """Record the sampler ``chosen_by`` picked for ``run`` (written atomically beside its checkpoint)."""
    from foundation.files import write_json

    validate.integer("steps", steps, 1, 1000)
    validate.non_negative("guidance", guidance)
    return write_json(Path(run) / SAMPLER_FILE, {"steps": int(steps), "guidance": float(guidance),
                                                 "chosen_by": chosen_by})


def run_sampler(run: str | Path) -> dict:
    """The run's recorded sampler, else the defaults (25 steps, CFG 2), with ``source`` saying which."""
    from foundation.files import read_json

    p = Path(run) / SAMPLER_FILE
    if not p.is_file():
        return {**DEFAULT_SAMPLER, "source": "default"}
    d = read_json(p, "sampler record")
    try:
        steps, guidance = d["steps"], float(d["guidance"])
    except (KeyError, TypeError, ValueError) as e:
        raise UsageError(f"{p}: needs integer 'steps' and number 'guidance' ({e})") from None
    validate.integer(f"{p}: steps", steps, 1, 1000)
    steps = int(steps)
    validate.non_negative(f"{p}: guidance", guidance)
    return {"steps": steps, "guidance": guidance, "source": str(p), "chosen_by": d.get("chosen_by", "")}


# -- sampling -------------------------------------------------------------------------------------------------------


@dataclass
class MaterialPrompt:
    """What a sample is conditioned on: keywords ([family, colour, finish], None = slot not given), an exemplar
    image (linear (H, W, 3)), both, or neither (unconditional)."""

    keywords: list | None = None
    exemplar: np.ndarray | None = None


@torch.no_grad()
def sample_materials(model: ConditionalDiffusion, s: MatDiffSettings, prompts: list[MaterialPrompt], size: int,
                     steps: int = 25, guidance: float = 2.0, seed: int = 0, batch: int = 16,
                     progress: bool = False, clip: float | None = CLIP) -> np.ndarray:
    """DDIM (η = 0) samples, one per prompt, with classifier-free guidance ``guidance`` (1 = conditional only) →
    feature textures (N, 2C, size, size) in feature units. Sample i uses noise seeded by (seed, i), so a sample
    does not depend on its batch. ``size`` may exceed the training size (circular padding: still tileable)."""
    from foundation.progress import progress_bar

    validate.integer("steps", steps, 1, 1000)
    validate.non_negative("guidance", guidance)
    validate.integer("size", size, s.multiple, 4096)
    if size % s.multiple:
        raise UsageError(f"--size {size} must divide by {s.multiple}")
    model.eval()
    # The schedule of the training size: a larger tileable texture has the same per-texel statistics.
    sched = make_material_scheduler(s, s.train_res or size, clip)
    sched.set_timesteps(steps)
    out = []
    kw_all = keyword_onehots([p.keywords or [None] * KEYWORD_TOKENS for p in prompts])
    has_ex = [p.exemplar is not None for p in prompts]
    ex_imgs = [p.exemplar for p in prompts if p.exemplar is not None]
    ex_tok = exemplar_features(np.stack(ex_imgs)) if ex_imgs else None
    ex_loc = exemplar_local(np.stack(ex_imgs), size) if ex_imgs and s.exemplar_local else None
    pos = np.cumsum(has_ex) - 1
    with progress_bar(total=len(prompts) * steps, desc="sample materials", unit="step", disable=not progress) as bar:
        for a in range(0, len(prompts), batch):
            sl = range(a, min(a + batch, len(prompts)))
            b = len(sl)
            tok = np.zeros((b, EXEMPLAR_TOKENS, FEATURE_DIM), np.float32)
            loc = torch.zeros(b, 3, size, size) if s.exemplar_local else None
            for j, i in enumerate(sl):
                if has_ex[i]:
                    tok[j] = ex_tok[pos[i]]
                    if loc is not None:
                        loc[j] = ex_loc[pos[i]]
            g, present = global_tokens(kw_all[list(sl)], tok, b)
            present[:, KEYWORD_TOKENS:] = np.array([has_ex[i] for i in sl])[:, None]
            cond = cross_tokens(model, torch.from_numpy(g), torch.from_numpy(present))
            uncond = cross_tokens(model, torch.from_numpy(g), torch.zeros(b, TOKENS, dtype=torch.bool))
            kv = keyword_vector(torch.from_numpy(g))
            use_cfg = s.cfg and guidance != 1.0 and bool(present.any())
            x = torch.stack([torch.randn(2 * s.channels, size, size, generator=torch.Generator().manual_seed(seed * 1_000_003 + i))
                             for i in sl])
            for t in sched.timesteps:
                tt = torch.full((b,), int(t), dtype=torch.long)
                if use_cfg:
                    both = model(torch.cat([x, x]), torch.cat([tt, tt]),
                                 None if loc is None else torch.cat([loc, torch.zeros_like(loc)]), torch.cat([cond, uncond]),
                                 torch.cat([kv, torch.zeros_like(kv)]))
                    c, u = both.chunk(2)
                    pred = u + guidance * (c - u)
                else:
                    pred = model(x, tt, loc, cond, kv)
                x = sched.step(pred, t, x, eta=0.0).prev_sample
                bar.update(b)
            out.append(from_model_space(x, s).numpy())
    return np.concatenate(out).astype(np.float32)


def split_features(f: np.ndarray, channels: int) -> tuple[np.ndarray, np.ndarray]:
    """(2C, H, W) → (T_off, T_rgb), each (H, W, C)."""
    return (np.ascontiguousarray(f[:channels].transpose(1, 2, 0)), np.ascontiguousarray(f[channels:].transpose(1, 2, 0)))


def read_exemplar(path: str | Path) -> np.ndarray:
    """An exemplar image as linear RGB (H, W, 3): an EXR as stored, an 8-bit photo (or a scikit-image photograph by
    name, e.g. ``brick``) sRGB-decoded."""
    from foundation.imageio import exr_layer, read_exr, read_photo, srgb_to_linear

    if str(path).lower().endswith(".exr"):
        return np.asarray(exr_layer(read_exr(path), ""), np.float32)[..., :3]
    if not Path(path).is_file():
        import skimage.data

        if hasattr(skimage.data, str(path)) and str(path) in ("brick", "grass", "gravel"):
            img = np.asarray(getattr(skimage.data, str(path))(), np.float32) / 255.0
            img = img if img.ndim == 3 else np.repeat(img[..., None], 3, -1)
            return srgb_to_linear(img[..., :3]).astype(np.float32)
    return srgb_to_linear(read_photo(str(path)).astype(np.float32) / 255.0).astype(np.float32)


def _shown(path) -> str:
    """A path as a material's meta records it: relative to the repository when inside it (files are shared)."""
    from foundation.assets import ROOT

    try:
        return str(Path(path).resolve().relative_to(ROOT))
    except ValueError:
        return str(path)


def generate_material(run: str | Path, out: str | Path, keywords: str | None = None, image: str | Path | None = None,
                      seed: int = 0, size: int = 32, steps: int | None = None, guidance: float | None = None,
                      from_prior: bool = False) -> dict:
    """`photoreal btf generate`: one material from a trained model, written as a ``neural_btf`` material .npz
    (fitted-material layout; meta names the basis it decodes through). Returns its summary. ``steps`` and
    ``guidance`` left None come from the run's recorded sampler (:func:`run_sampler`)."""
    from foundation.files import check_output_file
    from mi_plugins.neural_basis import NeuralMaterial, save_material

    from .data import parse_keywords

    out = check_output_file(out, "--out")
    if out.suffix != ".npz":
        raise UsageError(f"--out {out}: a material is an .npz file")
    validate.seed("seed", seed)
    model, s = load_matdiff(run)
    source = "arguments"
    if steps is None or guidance is None:  # a malformed record matters only when it is used
        rec = run_sampler(run)
        shown = rec["source"] if rec["source"] == "default" else _shown(rec["source"])
        source = shown if steps is None and guidance is None else f"arguments and {shown}"
        steps = rec["steps"] if steps is None else steps
        guidance = rec["guidance"] if guidance is None else guidance
    validate.integer("steps", steps, 1, 1000)
    validate.non_negative("guidance", guidance)
    validate.integer("size", size, 4, 4096)
    if size % 4:
        raise UsageError(f"size must be a multiple of 4 (the model's feature grid; it tiles seamlessly), got {size}")
    if from_prior and keywords:
        raise UsageError("give --keywords or --from-prior, not both")
    # a keyword triple drawn from the training materials' (the null token alone collapses to few families: docs/results/material-diffusion.md)
    words = parse_keywords(keywords) if keywords else prior_keywords(run, 1, seed)[0] if from_prior else None
    ex = None
    if image is not None:
        ex = read_exemplar(image)
        if not np.isfinite(ex).all() or ex.max() <= 0:
            raise UsageError(f"--image {image}: empty or non-finite pixels")
    f = sample_materials(model, s, [MaterialPrompt(words, ex)], size, steps, guidance, seed)[0]
    t_off, t_rgb = split_features(f, s.channels)
    shown_image = None if not image else _shown(image) if Path(image).exists() else str(image)  # a file, or "brick"
    meta = {"basis": s.basis_id, "generated": {"run": _shown(run), "keywords": words, "image": shown_image,
                                               "seed": seed, "size": size, "steps": steps, "guidance": guidance,
                                               "sampler_from": source, "keywords_from_prior": bool(from_prior)}}
    save_material(out, NeuralMaterial(t_off, t_rgb, meta))
    return {"material": str(out), **meta["generated"], "basis": s.basis_id}


__all__ = ["MaterialPrompt", "MatDiffResult", "MatDiffSettings", "alphas_cumprod", "build_model", "data_digest", "exemplar_features",
           "exemplar_local", "feature_scale", "from_model_space", "generate_material", "global_tokens", "keyword_vector", "load_matdiff", "loss_weight",
           "make_material_scheduler", "material_loss", "run_sampler", "sample_materials", "save_sampler",
           "split_features", "to_model_space", "train_matdiff", "SAMPLER_FILE", "PRIOR_FILE", "prior_keywords",
           "save_keyword_prior"]
