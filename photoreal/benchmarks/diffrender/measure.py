"""What the diffusion-renderer bench measures with: paired image metrics, sampling of held-out views, training throughput."""

from __future__ import annotations

import time

import numpy as np
import torch
import mi_plugins  # noqa: F401

from foundation.metrics import image_metrics
from foundation.threads import torch_threads
from generative.diffrender import (DiffRenderSettings,
                                   IntrinsicViews, render_views,
                                   SampleSettings)
from generative.diffusion import ConditionalDiffusion, diffusion_loss, make_scheduler, training_flops


PAIRED = ("psnr", "one_minus_ssim", "flip", "mse")


def _gemm_flops_per_s(n: int = 2048, reps: int = 5) -> float:
    a, b = torch.randn(n, n), torch.randn(n, n)
    a @ b
    t = time.perf_counter()
    for _ in range(reps):
        a @ b
    return 2.0 * n ** 3 * reps / (time.perf_counter() - t)


def throughput(s: DiffRenderSettings, reps: int = 4) -> dict:
    """Training FLOPs per second of the renderer's model at its batch and crop, against a GEMM (same threads)."""
    cfg = s.model_config()
    model = ConditionalDiffusion(cfg, seed=s.seed)
    flops = training_flops(model, s.batch, s.crop)
    if s.channels_last:
        model = model.to(memory_format=torch.channels_last)
    sch, gen = make_scheduler(cfg), torch.Generator().manual_seed(0)
    opt = torch.optim.AdamW(model.parameters(), lr=s.lr)
    x = torch.rand(s.batch, 3, s.crop, s.crop) * 2 - 1
    c = torch.rand(s.batch, cfg.cond_channels, s.crop, s.crop)
    if s.channels_last:
        x, c = x.contiguous(memory_format=torch.channels_last), c.contiguous(memory_format=torch.channels_last)
    g = torch.randn(s.batch, cfg.global_tokens, cfg.global_dim) if cfg.global_dim else None
    gemm = [_gemm_flops_per_s()]
    times = []
    for i in range(reps + 1):
        t = time.perf_counter()
        opt.zero_grad(set_to_none=True)
        diffusion_loss(model, sch, x, c, g, gen).backward()
        opt.step()
        if i:  # the first step warms up
            times.append(time.perf_counter() - t)
    gemm.append(_gemm_flops_per_s())
    step = float(np.median(times))
    return {"flops_per_step": flops, "seconds_per_step": step, "train_flops_per_s": flops / step,
            "gemm_flops_per_s": max(gemm), "train_flops_fraction": flops / step / max(gemm),
            "batch": s.batch, "crop": s.crop, "threads": torch.get_num_threads()}


def paired_metrics(pred: np.ndarray, ref: np.ndarray) -> dict:
    """Mean and spread over images of the paired metrics; ``pred`` may carry a leading seeds axis."""
    pred = np.asarray(pred)
    if pred.ndim == 5:  # (seeds, views, H, W, 3): spread over views and seeds
        per_seed = [paired_metrics(p, ref) for p in pred]
        out = {k: float(np.mean([d[k] for d in per_seed])) for k in PAIRED}
        for k in PAIRED:
            out[f"{k}_std"] = float(np.mean([d[f"{k}_std"] for d in per_seed]))  # over views, mean over seeds
            out[f"{k}_seed_std"] = float(np.std([d[k] for d in per_seed]))  # of the per-seed means
        out["seeds"] = len(pred)
        out["flip_per_view"] = np.mean([d["flip_per_view"] for d in per_seed], axis=0).tolist()  # mean over seeds
        return out
    per = [image_metrics(p, r) for p, r in zip(pred, ref)]
    out = {}
    for k in PAIRED:
        v = np.array([getattr(m, k) for m in per], np.float64)
        out[k] = float(v.mean())
        out[f"{k}_std"] = float(v.std())
    out["flip_per_view"] = [float(m.flip) for m in per]
    return out


def heldout_layers(v: IntrinsicViews, source: str, ids: list[int]) -> dict:
    return {k: a[ids] for k, a in v.layers[source].items()}


def sample_views(trained: tuple, layers: dict, steps: int, guidance: float, seeds: int, show_progress: bool,
            draws: int = 1):
    """(seeds, N, H, W, 3) renders of a loaded run (:func:`load_diffrender`) and seconds per image (mean over seeds)."""
    model, ds = trained
    imgs, secs = [], []
    with torch_threads(0):
        for k in range(seeds):
            im, sec = render_views(model, ds, layers, SampleSettings(steps=steps, guidance=guidance, seed=1000 * k,
                                                                     draws=draws), show_progress)
            imgs.append(im)
            secs.append(sec)
    return np.stack(imgs), float(np.mean(secs))
