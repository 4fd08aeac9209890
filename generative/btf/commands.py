"""The entry points of `photoreal btf train-diffusion` and `photoreal btf generate`: their parameters are the
commands' flags, and torch and the model load inside them, so that the commands' help answers at once."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from foundation import validate
from foundation.errors import UsageError

from .settings import MatDiffSettings

if TYPE_CHECKING:
    from .data import MaterialSet
    from .train import MatDiffResult


def train_matdiff(data: MaterialSet, out: str | Path, s: MatDiffSettings | None = None, budget_steps: int | None = None,
                  show_progress: bool = True, device: str = "cpu") -> MatDiffResult | None:
    """Train on ``data``'s materials (pass only the training split) in folder ``out`` (``checkpoint.npz``,
    ``metrics.json``); rerun to resume. ``budget_steps`` ends this call early (a later call continues).

    ``device`` (a torch device, e.g. ``cuda``) runs the model there; batches and the random stream stay on the CPU,
    so a run may resume on another device (the checkpoint is the same either way)."""
    import dataclasses

    from generative.diffusion import torch_device, train_stage

    from .model import EXEMPLAR_TOKENS, exemplar_features
    from .train import MatDiffStage, feature_scale, write_keyword_prior

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
    write_keyword_prior(out, data, stage.digest)  # the loop checked this digest against the checkpoint's
    return result


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
    from .sample import MaterialPrompt, read_exemplar, sample_materials, split_features
    from .train import load_matdiff, prior_keywords, run_sampler

    out = check_output_file(out, "--out")
    if out.suffix != ".npz":
        raise UsageError(f"--out {out}: a material is an .npz file")
    validate.seed("seed", seed)
    validate.integer("size", size, 4, 4096)
    if size % 4:
        raise UsageError(f"size must be a multiple of 4 (the model's feature grid; it tiles seamlessly), got {size}")
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
