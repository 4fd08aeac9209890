"""Training the material diffusion model on the shared loop, and what a run folder records beside its weights: the keyword prior and the sampler the bench chose."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from foundation import validate
from foundation.errors import UsageError
from foundation.loop import RunState, Stage, StepResult, TrainingSummary
from generative.diffusion import ConditionalDiffusion, OptimizerStage, load_trained

from .data import MaterialSet, keyword_onehots
from .model import (KEYWORD_TOKENS, MatDiffSettings, build_model, exemplar_local,
                    global_tokens, make_material_scheduler, material_loss, padding_mode, to_model_space)


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
    return write_keyword_prior(run, data, digest)


def write_keyword_prior(run: str | Path, data: MaterialSet, digest: str) -> Path:
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
