"""Seed 003 §4, super-resolution: a small residual CNN upsamples the model-resolution maps 2× (pixel shuffle),
added to bicubic."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from foundation.errors import UsageError
from foundation.loop import RunState, Stage

from generative.diffusion import OptimizerStage, count_parameters, load_trained, train_stage

from .data import FaceSet

#: lit (3), seen (1), covered (1), the baseline's albedo (3), position (3) and normal (3) in the face frame
from .encoding import COND_CHANNELS, GEO, MAP_CHANNELS, at_resolution, condition, decode_maps, encode_maps, mirror
from .completion import FaceModelResult, data_digest
from .settings import SuperResSettings


# -- 3. super-resolution ----------------------------------------------------------------------------------------------


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
