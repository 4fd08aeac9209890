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

import numpy as np
import torch
import torch.nn.functional as F


from generative.diffusion import ConditionalDiffusion, DiffusionConfig
from .data import SLOTS, VOCABULARY
from .settings import MatDiffSettings


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
