"""How generated neural materials are judged (seed 002 §4.4; the seed reports no numbers, so these are ours).

Every material — generated, a baseline's, or a fitted real one — is decoded through the universal basis at
the swatch pairs (:func:`material_data.decode_swatches`) and judged in that image space:

* :class:`FamilyClassifier` — a head over frozen MobileNetV2 features of the swatch mosaic, trained on the
  *path-traced* swatches of training materials (under random rolls); its held-out accuracy is reported on real
  held-out swatches and on the decoded fits of the same materials (the basis' own error). Its 64-d hidden
  activations are one KID feature space;
* MobileNetV2 (ImageNet weights, :mod:`foundation.features`) pooled features of the 2×2 swatch mosaic:
  the second space, also the memorisation and diversity distances;
* baselines that need no training: copies of training materials, a Gaussian fitted to the training
  feature textures (mean + principal components, i.e. the maximum-likelihood Gaussian of rank N − 1), and
  random crops (a random quarter of a training material tiled 2×2);
* :func:`aligned_flip` — ꟻLIP after the best circular shift (FFT cross-correlation of view 0): a tileable
  texture has no origin, so every method, retrieval included, is aligned the same way before comparing;
* :func:`seam_ratio` — mean jump across the wrap-around border over the mean jump between neighbouring
  interior columns/rows (1 = no seam).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from foundation.loop import RunState, Stage, StepResult, TrainingSummary

from generative.diffusion import OptimizerStage, train_stage
from .data import FAMILIES, decode_swatches
from .settings import ClassifierSettings


def decode_all(basis, features: np.ndarray, channels: int = 8) -> np.ndarray:
    """(N, 2C, H, W) feature textures → (N, K, H, W, 3) decoded swatches."""
    return np.stack([decode_swatches(basis, f[:channels].transpose(1, 2, 0), f[channels:].transpose(1, 2, 0))
                     for f in features])


class FamilyClassifier(torch.nn.Module):
    """Frozen ImageNet MobileNetV2 (pooled features of the 2×2 swatch mosaic, :func:`mnv2_features`) → standardised
    → a learned ``width``-d hidden layer (SiLU) → the 8 families. The hidden layer is the classifier's own feature
    space (family-discriminative; the pooled MobileNetV2 features are the generic one).

    Measured on the 256-material dataset (224 train / 32 held out): the CNN trained from scratch on the swatches
    that this replaces reached 0.56 held-out accuracy (0.47 on decoded fits); this head 1.00 (0.94), as did a plain
    linear probe — 28 materials per family are too few to learn image features from scratch."""

    def __init__(self, width: int = 64, seed: int = 0, dim: int = 1280):
        super().__init__()
        torch.manual_seed(seed)
        self.register_buffer("mean", torch.zeros(dim))
        self.register_buffer("std", torch.ones(dim))
        self.hidden = torch.nn.Linear(dim, width)
        self.head = torch.nn.Linear(width, len(FAMILIES))
        self.drop = torch.nn.Dropout(0.2)

    def features(self, f: torch.Tensor) -> torch.Tensor:
        """MobileNetV2 features (N, 1280) → the hidden layer (N, width)."""
        return F.silu(self.hidden(self.drop((f - self.mean) / self.std)))

    def forward(self, f: torch.Tensor) -> torch.Tensor:
        return self.head(self.features(f))


@dataclass
class ClassifierResult:
    settings: ClassifierSettings
    training: TrainingSummary


def rolled(swatches: np.ndarray, rolls: int, rng: np.random.Generator) -> np.ndarray:
    """(N, K, H, W, 3) → (N·rolls, K, H, W, 3): each material under ``rolls`` random circular shifts (one per copy,
    the same for its K swatches; the first copy unshifted)."""
    n, _, h, w, _ = swatches.shape
    out = []
    for i in range(n):
        for r in range(rolls):
            dy, dx = (0, 0) if r == 0 else (int(rng.integers(h)), int(rng.integers(w)))
            out.append(np.roll(swatches[i], (dy, dx), (1, 2)))
    return np.stack(out)


class ClassifierStage(OptimizerStage, Stage):
    unit = "step"

    def __init__(self, swatches: np.ndarray, families: np.ndarray, s: ClassifierSettings):
        self.s, self.name = s, "train family classifier"
        self.rng = np.random.default_rng(s.seed)
        self.f = torch.from_numpy(mnv2_features(rolled(swatches, s.rolls, self.rng)).astype(np.float32))
        self.y = torch.from_numpy(np.repeat(np.asarray(families, np.int64), s.rolls))
        self.model = FamilyClassifier(s.width, s.seed, self.f.shape[1])
        self.model.mean.copy_(self.f.mean(0))
        sd = self.f.std(0)
        self.model.std.copy_(sd + 0.1 * sd.mean() + 1e-6)  # a floor: features constant over a few swatches stay small
        self.opt = torch.optim.AdamW(self.model.parameters(), lr=s.lr, weight_decay=s.weight_decay)

    def fingerprint(self) -> dict:
        return {"settings": self.s, "n": int(len(self.y)), "sum": float(self.f.double().sum())}

    def step(self, it: int) -> StepResult:
        self.model.train()
        idx = torch.from_numpy(self.rng.integers(0, len(self.y), self.s.batch))
        return self.backward(F.cross_entropy(self.model(self.f[idx]), self.y[idx]))

    def finish(self, run: RunState) -> ClassifierResult:
        return ClassifierResult(self.s, run.summary())


def train_classifier(swatches: np.ndarray, families: np.ndarray, out, s: ClassifierSettings | None = None,
                     show_progress: bool = True) -> FamilyClassifier:
    """Train the family classifier on (path-traced) swatches in folder ``out`` (resumable; ``metrics.json``)."""
    s = s or ClassifierSettings()
    stage, _ = train_stage(lambda: ClassifierStage(swatches, families, s), out, s, None, show_progress)
    stage.model.eval()
    return stage.model


@torch.no_grad()
def classify(model: FamilyClassifier, swatches: np.ndarray, mnv2: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(predicted family index (N,), the classifier's hidden features (N, width)); ``mnv2`` passes the swatches'
    :func:`mnv2_features` when they are already computed."""
    model.eval()
    f = torch.from_numpy(np.asarray(mnv2 if mnv2 is not None else mnv2_features(swatches), np.float32))
    h = model.features(f)
    return model.head(h).argmax(1).numpy(), h.double().numpy()


@torch.no_grad()
def denoising_check(model, s, features: np.ndarray, keywords: list, timesteps=(39, 79, 159, 319, 699),
                    taus=(0.5, 1.0, 1.5), seed: int = 0) -> list[dict]:
    """How well a trained material model denoises held-out feature textures, against fixed denoisers.

    At each training timestep t: noise the textures (model space), predict x̂₀ with the keywords as condition, and
    report the mean squared x̂₀ error beside (a) the naive x_t/α (no denoising) and (b) the best periodic Gaussian
    blur of x_t/α over ``taus`` texels — a denoiser with no learned parameters. A model that loses to (b) at low t
    leaves texel-scale noise in its samples (what `bench matdiff` found at CPU training budgets)."""
    from inverse.btf import gaussian_periodic

    from .data import keyword_onehots
    from .model import cross_tokens, global_tokens, keyword_vector, make_material_scheduler, to_model_space

    model.eval()
    x0 = torch.from_numpy(to_model_space(np.asarray(features, np.float32), s).astype(np.float32))
    b, _, h, _ = x0.shape
    sched = make_material_scheduler(s, s.train_res or h)
    g, present = global_tokens(keyword_onehots(keywords), None, b)
    cond = cross_tokens(model, torch.from_numpy(g), torch.from_numpy(present))
    kv = keyword_vector(torch.from_numpy(g))
    local = torch.zeros(b, 3, h, h) if s.exemplar_local else None
    gen = torch.Generator().manual_seed(seed)
    rows = []
    for t in timesteps:
        tt = torch.full((b,), int(t), dtype=torch.long)
        xt = sched.add_noise(x0, torch.randn(x0.shape, generator=gen), tt)
        ac = sched.alphas_cumprod[int(t)].double()
        a, sg = float(ac.sqrt()), float((1 - ac).sqrt())
        out = model(xt, tt, local, cond, kv)
        xhat = a * xt - sg * out if s.prediction == "v_prediction" else (xt - sg * out) / a
        naive = (xt / a).numpy()
        blur = {tau: float(np.mean((gaussian_periodic(naive.transpose(0, 2, 3, 1), tau).transpose(0, 3, 1, 2)
                                    - x0.numpy()) ** 2)) for tau in taus}
        best = min(blur, key=blur.get)
        rows.append({"t": int(t), "noise_to_signal": sg / a, "model": float((xhat - x0).square().mean()),
                     "naive": float(np.mean((naive - x0.numpy()) ** 2)), "blur": blur[best], "blur_tau": best})
    return rows


def mosaic(swatches: np.ndarray) -> np.ndarray:
    """(N, 4, H, W, 3) → (N, 2H, 2W, 3): the four swatches as one image."""
    a = np.asarray(swatches, np.float32)
    top = np.concatenate([a[:, 0], a[:, 1]], 2)
    bottom = np.concatenate([a[:, 2], a[:, 3]], 2)
    return np.concatenate([top, bottom], 1)


def mnv2_features(swatches: np.ndarray) -> np.ndarray:
    from foundation.features import image_features

    return image_features(np.clip(mosaic(swatches), 0.0, 1.0), linear=True, size=128)


def best_shift(a: np.ndarray, b: np.ndarray) -> tuple[int, int]:
    """Circular shift (dy, dx) that best aligns image a (H, W, 3) to b: argmax of their cross-correlation."""
    la, lb = a.mean(-1) - a.mean(), b.mean(-1) - b.mean()
    corr = np.fft.ifft2(np.fft.fft2(lb) * np.conj(np.fft.fft2(la))).real
    dy, dx = np.unravel_index(int(np.argmax(corr)), corr.shape)
    return int(dy), int(dx)


def aligned_flip(test: np.ndarray, ref: np.ndarray) -> float:
    """Mean ꟻLIP over the K swatches of ``test`` (K, H, W, 3) against ``ref``, after the circular shift that
    aligns view 0 best (both clipped to [0, 1]: LDR ꟻLIP)."""
    from foundation.metrics import flip

    dy, dx = best_shift(test[0], ref[0])
    t = np.roll(test, (dy, dx), (1, 2))
    return float(np.mean([flip(np.clip(t[k], 0, 1), np.clip(ref[k], 0, 1)) for k in range(len(ref))]))


def seam_ratio(image: np.ndarray) -> float:
    """Mean |jump| across the wrap-around border / mean |jump| between neighbouring interior columns and rows."""
    x = np.asarray(image, np.float64)
    seam = 0.5 * (np.abs(x[:, 0] - x[:, -1]).mean() + np.abs(x[0] - x[-1]).mean())
    inner = 0.5 * (np.abs(np.diff(x, axis=1)).mean() + np.abs(np.diff(x, axis=0)).mean())
    return float(seam / max(inner, 1e-12))


def nearest_distances(a: np.ndarray, b: np.ndarray, exclude_self: bool = False) -> np.ndarray:
    """For every row of a, the Euclidean distance to its nearest row of b."""
    d = np.sqrt(np.maximum(((a[:, None, :] - b[None, :, :]) ** 2).sum(-1), 0.0))
    if exclude_self:
        np.fill_diagonal(d, np.inf)
    return d.min(1)


def mean_pairwise(a: np.ndarray) -> float:
    d = np.sqrt(np.maximum(((a[:, None, :] - a[None, :, :]) ** 2).sum(-1), 0.0))
    n = len(a)
    return float(d.sum() / (n * (n - 1)))


# -- baselines -------------------------------------------------------------------------------------------------------


def copy_baseline(train: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    return train[rng.integers(0, len(train), n)].copy()


def gaussian_baseline(train: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """Samples of the maximum-likelihood Gaussian of the flattened training textures (rank N − 1, through the SVD)."""
    flat = train.reshape(len(train), -1).astype(np.float64)
    mean = flat.mean(0)
    _, sv, vt = np.linalg.svd(flat - mean, full_matrices=False)
    z = rng.standard_normal((n, len(sv)))
    out = mean + (z * (sv / np.sqrt(max(len(train) - 1, 1)))) @ vt
    return out.reshape((n,) + train.shape[1:]).astype(np.float32)


def crop_baseline(train: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """A random (H/2)² crop (circular) of a random training material, tiled 2×2."""
    h = train.shape[-1]
    out = []
    for i in rng.integers(0, len(train), n):
        y, x = rng.integers(0, h, 2)
        c = np.roll(train[i], (-int(y), -int(x)), (1, 2))[:, :h // 2, :h // 2]
        out.append(np.tile(c, (1, 2, 2)))
    return np.stack(out).astype(np.float32)


def random_roll(texture: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A (C, H, W) tileable texture under a random circular shift (it has no origin)."""
    return np.roll(texture, tuple(int(d) for d in rng.integers(0, texture.shape[-1], 2)), (1, 2))


def family_gaussian_baseline(x: np.ndarray, families: np.ndarray, per_family: int, rng: np.random.Generator,
                             rolls: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """``per_family`` samples of each family's maximum-likelihood Gaussian over its members' textures, each member
    under ``rolls`` random circular shifts (a tileable texture has no origin). A reference for keyword accuracy: a
    generator that knows each family's first and second moments and nothing else. Returns (samples, families)."""
    out, fam = [], []
    for f in np.unique(families):
        shifted = np.stack([random_roll(m, rng) for m in x[families == f] for _ in range(rolls)])
        out.append(gaussian_baseline(shifted, per_family, rng))
        fam += [int(f)] * per_family
    return np.concatenate(out), np.array(fam)


def phase_randomised_baseline(x: np.ndarray, families: np.ndarray, per_family: int,
                              rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A random member of each family with its Fourier phases replaced by those of white noise (one phase field for
    all channels, so the channels' cross-spectra are kept): every channel's mean and power spectrum exactly as the
    member's, its structure (edges, grains, fibres) gone. Returns (samples, families)."""
    out, fam = [], []
    for f in np.unique(families):
        members = x[families == f]
        for _ in range(per_family):
            m = members[rng.integers(len(members))].astype(np.float64)
            phase = np.fft.fft2(rng.standard_normal(m.shape[1:]))  # Hermitian: the result stays real
            out.append(np.real(np.fft.ifft2(np.fft.fft2(m) * np.exp(1j * np.angle(phase)))))
            out[-1] += m.mean((1, 2), keepdims=True) - out[-1].mean((1, 2), keepdims=True)  # the DC term's phase
            fam.append(int(f))
    return np.stack(out).astype(np.float32), np.array(fam)
