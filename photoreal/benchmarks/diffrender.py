"""`photoreal bench diffrender`: the intrinsic-conditioned diffusion renderer on held-out views (seed 000 §4.3).

Per case (village, armadillo): the morph benchmark and a morph run (the GAN bench's recipe, reused from
the work folder), the coarse and morphed G-buffers. One diffusion model is trained on the train views
of all cases (reused from the work folder when finished: training resumes through the shared loop).
On the held-out views:

* paired metrics against the photos (PSNR, 1−SSIM, ꟻLIP, MSE; mean and spread over views) of the PBR
  recomposition R = A·I + S of the coarse and of the morphed G-buffers, of the diffusion renders
  (from the morphed G-buffers) and, with ``gans`` on, of CycleGAN, pix2pix and Morph-GAN trained
  on the same views;
* MobileNetV2-KID / -FID between each method's renders and the held-out photos (ImageNet MobileNetV2
  features, *not* Inception's), and the MobileNetV2 perceptual distance;
* sampling seconds per 128² image, and training throughput: FLOPs per step (torch's FlopCounterMode)
  ÷ step time, as a fraction of a 2048² float32 GEMM measured in the same run (best of two, the
  ceiling of this CPU).

Not here yet (issue 13): the decomposition network and its data ablation, the global-condition
ablations, ≥ 3 seeds, the steps × model-size sweep and its automatic choice, the unseen-mesh case.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import torch

from foundation import validate
from foundation.features import fid, image_features, kid, perceptual_distance
from foundation.metrics import image_metrics
from foundation.progress import progress_bar
from foundation.threads import torch_threads
from generative.diffusion import (ConditionalDiffusion, DiffRenderSettings, SampleSettings, diffusion_loss,
                                  load_diffrender, load_intrinsic_views, make_scheduler, render_views,
                                  train_diffrender, training_flops)
from generative.gan import GanTrainSettings, load_heldout_predictions, load_paired_views, train_gan

from .gan import GanBenchSettings, _prepare

PAIRED = ("psnr", "one_minus_ssim", "flip", "mse")


@dataclass
class DiffRenderBenchSettings:
    cases: tuple[str, ...] = ("village", "armadillo")
    train_seconds: float = 1800.0  #: diffusion training budget (one model for all cases)
    ddim_steps: int = 20
    guidance: float = 1.5
    gans: bool = True  #: also train CycleGAN, pix2pix and Morph-GAN on the same views (the GAN bench's budgets)
    gan_seconds: float = 120.0
    cyclegan_seconds: float = 360.0
    morph_iterations: int = 100  #: as the GAN bench: work folders are interchangeable
    seed: int = 0

    def __post_init__(self):
        self.cases = tuple(self.cases)
        for name in ("train_seconds", "gan_seconds", "cyclegan_seconds"):
            validate.positive(name, getattr(self, name))
        validate.integer("ddim_steps", self.ddim_steps, 1, 1000)
        validate.non_negative("guidance", self.guidance)
        validate.integer("morph_iterations", self.morph_iterations, 1)
        validate.seed("seed", self.seed)


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


def _paired(pred: np.ndarray, ref: np.ndarray) -> dict:
    per = [image_metrics(p, r) for p, r in zip(pred, ref)]
    out = {}
    for k in PAIRED:
        v = np.array([getattr(m, k) for m in per], np.float64)
        out[k] = float(v.mean())
        out[f"{k}_std"] = float(v.std())
    return out


def bench_diffrender(s: DiffRenderBenchSettings | None = None, out_dir: str | Path = "out/bench",
                     show_progress: bool = True) -> dict:
    s = s or DiffRenderBenchSettings()
    work = Path(out_dir) / "diffrender_work"
    t0 = time.perf_counter()
    gb = GanBenchSettings(cases=s.cases, morph_iterations=s.morph_iterations, seed=s.seed)
    prepared = {c: _prepare(c, work, gb, show_progress)[:2] for c in s.cases}
    views = {c: load_intrinsic_views(b, m, show_progress=show_progress) for c, (b, m) in prepared.items()}
    ds = DiffRenderSettings(max_seconds=s.train_seconds, seed=s.seed)
    with torch_threads(ds.threads):
        tput = throughput(ds)
    result = train_diffrender(list(views.values()), work / "diffusion", ds, show_progress=show_progress)
    model, ds = load_diffrender(work / "diffusion")
    ss = SampleSettings(steps=s.ddim_steps, guidance=s.guidance, seed=s.seed)
    cases, sample_s = {}, []
    all_pred: dict[str, list] = {}
    all_photos = []
    for c, v in views.items():
        ids = list(v.test)
        photos = v.photos[ids]
        preds = {"pbr_coarse": v.recomposed("coarse")[ids], "pbr_morphed": v.recomposed("morphed")[ids]}
        with torch_threads(0):
            preds["diffusion"], sec = render_views(model, ds, {k: a[ids] for k, a in v.layers["morphed"].items()}, ss,
                                                   show_progress)
        sample_s.append(sec)
        if s.gans:
            bench, mdir = prepared[c]
            data = load_paired_views(bench, mdir, show_progress=show_progress)
            for name in ("cyclegan", "pix2pix", "morph_gan"):
                gs = GanTrainSettings(model=name, max_seconds=s.cyclegan_seconds if name == "cyclegan" else s.gan_seconds,
                                      residual=name != "cyclegan", seed=s.seed)
                train_gan(data, work / c / name, gs, show_progress=show_progress)
                preds[name] = load_heldout_predictions(work / c / name, ids)
        cases[c] = {"heldout": {k: _paired(p, photos) for k, p in preds.items()},
                    "perceptual_mnv2": {k: float(perceptual_distance(p, photos).mean()) for k, p in preds.items()},
                    "views": {"train": len(v.train), "test": len(ids), "resolution": v.resolution}}
        for k, p in preds.items():
            all_pred.setdefault(k, []).append(p)
        all_photos.append(photos)
    photos = np.concatenate(all_photos)
    f_photo = image_features(photos)
    kid_mnv2, fid_mnv2, heldout = {}, {}, {}
    for k, ps in all_pred.items():
        p = np.concatenate(ps)
        f = image_features(p)
        kid_mnv2[k], fid_mnv2[k] = kid(f, f_photo), fid(f, f_photo)
        heldout[k] = _paired(p, photos)
    return {"heldout": heldout, "cases": cases, "kid_mnv2": kid_mnv2, "fid_mnv2": fid_mnv2,
            "sample_seconds_128": float(np.mean(sample_s)), "ddim_steps": s.ddim_steps, "guidance": s.guidance,
            "train_flops_fraction": tput["train_flops_fraction"], "throughput": tput,
            "training": asdict(result.training) if result else None, "parameters": result.parameters if result else None,
            "loss_curve": result.loss_curve if result else None, "settings": asdict(s), "model": asdict(ds),
            "seconds": time.perf_counter() - t0}
