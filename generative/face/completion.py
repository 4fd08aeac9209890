"""Seed 003 §2, completion and light homogenisation: one conditional diffusion model from the partial lit texture to a
complete delit albedo. It is the backbone the decomposition adapts (:mod:`.decomposition`)."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from foundation.loop import RunState, Stage, TrainingSummary

from generative.diffusion import (ConditionalDiffusion, DiffusionConfig, OptimizerStage, count_parameters, load_trained,
                                  make_scheduler, train_stage)

from .data import FaceSet

#: lit (3), seen (1), covered (1), the baseline's albedo (3), position (3) and normal (3) in the face frame
from .encoding import (COND_CHANNELS, RESIDUAL, at_resolution, condition, decode_albedo, encode_albedo, mirror,
                       normalise_albedo)
from .settings import CompletionSettings


# -- 1. completion + light homogenisation: a conditional diffusion model ---------------------------------------------


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


