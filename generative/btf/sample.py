"""Sampling materials from a trained model: prompts of keywords and/or an exemplar photo; `photoreal btf generate`."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from foundation import validate
from foundation.errors import UsageError
from generative.diffusion import ConditionalDiffusion

from .data import keyword_onehots
from .model import (CLIP, EXEMPLAR_TOKENS, FEATURE_DIM, KEYWORD_TOKENS, MatDiffSettings, TOKENS, cross_tokens,
                    exemplar_features, exemplar_local, from_model_space, global_tokens, keyword_vector,
                    make_material_scheduler)


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
    """An exemplar image as linear RGB (H, W, 3): an EXR as stored, any other image (8 or 16 bit, any mode: see
    :func:`foundation.imageio.read_image`; or a scikit-image photograph by name, e.g. ``brick``) sRGB-decoded."""
    from foundation.imageio import exr_layer, read_exr, read_image, srgb_to_linear

    if str(path).lower().endswith(".exr"):
        return np.asarray(exr_layer(read_exr(path), ""), np.float32)[..., :3]
    if not Path(path).is_file():
        import skimage.data

        if hasattr(skimage.data, str(path)) and str(path) in ("brick", "grass", "gravel"):
            img = np.asarray(getattr(skimage.data, str(path))(), np.float32) / 255.0
            img = img if img.ndim == 3 else np.repeat(img[..., None], 3, -1)
            return srgb_to_linear(img[..., :3]).astype(np.float32)
    return read_image(path, channels=3, linear=True, what="exemplar")


