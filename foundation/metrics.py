"""Image metrics. Conventions: float images, linear or display-referred as stated."""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np


@dataclass
class ImageMetrics:
    """The thesis' image metrics plus PSNR and ꟻLIP (see :func:`image_metrics`); lower is better except PSNR."""

    psnr: float
    mse: float
    me: float  #: mean absolute error
    one_minus_ssim: float
    nrmse: float  #: RMSE / (max − min of the reference)
    sam_deg: float  #: mean spectral angle between RGB vectors, degrees
    flip: float  #: mean ꟻLIP (LDR, sRGB-encoded)

    @classmethod
    def mean(cls, items: "list[ImageMetrics]") -> "ImageMetrics":
        """Field-wise mean (e.g. over views)."""
        if not items:
            raise ValueError("mean of no metrics")
        return cls(**{f.name: float(np.mean([getattr(m, f.name) for m in items])) for f in fields(cls)})


def mse(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))


def psnr(test: np.ndarray, ref: np.ndarray, peak: float = 1.0, clip: bool = True) -> float:
    """PSNR in dB with a fixed peak (default 1, on values clipped to [0, peak]).

    Clipping makes HDR images comparable the way a display shows them; pass
    ``clip=False`` to compare raw values. Identical images give +inf.
    """
    a, b = np.asarray(test, np.float64), np.asarray(ref, np.float64)
    if a.shape != b.shape:
        raise ValueError(f"psnr: shapes differ {a.shape} vs {b.shape}")
    if clip:
        a, b = np.clip(a, 0, peak), np.clip(b, 0, peak)
    m = float(np.mean((a - b) ** 2))
    return float("inf") if m == 0 else float(10.0 * np.log10(peak * peak / m))


def masked_psnr(test: np.ndarray, ref: np.ndarray, mask: np.ndarray, peak: float = 1.0, clip: bool = True) -> float:
    """PSNR over the pixels where ``mask`` (H, W) is true."""
    m = np.asarray(mask, bool)
    return psnr(np.asarray(test)[m], np.asarray(ref)[m], peak=peak, clip=clip)


def ssim(test: np.ndarray, ref: np.ndarray, data_range: float = 1.0) -> float:
    """Structural similarity (scikit-image, Gaussian-weighted as Wang et al. 2004), RGB averaged."""
    from skimage.metrics import structural_similarity

    a, b = np.clip(np.asarray(test, np.float64), 0, data_range), np.clip(np.asarray(ref, np.float64), 0, data_range)
    return float(structural_similarity(a, b, data_range=data_range, channel_axis=-1 if a.ndim == 3 else None,
                                       gaussian_weights=True, sigma=1.5, use_sample_covariance=False))


def flip(test: np.ndarray, ref: np.ndarray, hdr: bool = False, mask: np.ndarray | None = None) -> float:
    """Mean ꟻLIP error (NVIDIA, weight-free perceptual metric); LDR inputs are linear, encoded to sRGB here."""
    import flip_evaluator

    from .imageio import linear_to_srgb

    a, b = np.asarray(test, np.float32)[..., :3], np.asarray(ref, np.float32)[..., :3]
    if hdr:
        err, mean, _ = flip_evaluator.evaluate(np.maximum(b, 0), np.maximum(a, 0), "HDR", applyMagma=False)
    else:
        err, mean, _ = flip_evaluator.evaluate(linear_to_srgb(b), linear_to_srgb(a), "LDR", applyMagma=False)
    err = np.asarray(err)
    if err.ndim == 3:
        err = err[..., 0]
    return float(err[np.asarray(mask, bool)].mean()) if mask is not None else float(mean)


def angular_error_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle in degrees between unit vectors along the last axis."""
    an = a / np.maximum(np.linalg.norm(a, axis=-1, keepdims=True), 1e-12)
    bn = b / np.maximum(np.linalg.norm(b, axis=-1, keepdims=True), 1e-12)
    return np.degrees(np.arccos(np.clip(np.sum(an * bn, axis=-1), -1.0, 1.0)))


def global_scale(test: np.ndarray, ref: np.ndarray) -> float:
    """Least-squares s minimising ‖s·test − ref‖² (the scale delighting cannot resolve)."""
    t, r = np.asarray(test, np.float64).ravel(), np.asarray(ref, np.float64).ravel()
    den = float(t @ t)
    return float(t @ r / den) if den > 0 else 1.0


def image_metrics(test: np.ndarray, ref: np.ndarray) -> ImageMetrics:
    """The thesis' image metrics plus PSNR and ꟻLIP, on linear RGB clipped to [0, 1].

    MSE, ME (mean absolute error), 1−SSIM, NRMSE (RMSE / (max − min of the
    reference)), SAM (mean spectral angle between RGB vectors, degrees).
    """
    a = np.clip(np.asarray(test, np.float64)[..., :3], 0, 1)
    b = np.clip(np.asarray(ref, np.float64)[..., :3], 0, 1)
    rmse = float(np.sqrt(np.mean((a - b) ** 2)))
    dot = np.sum(a * b, -1)
    norm = np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1)
    sam = np.degrees(np.arccos(np.clip(np.where(norm > 1e-8, dot / np.maximum(norm, 1e-8), 1.0), -1, 1)))
    s = ssim(a, b)
    return ImageMetrics(psnr=psnr(a, b), mse=mse(a, b), me=float(np.abs(a - b).mean()), one_minus_ssim=1.0 - s,
                        nrmse=rmse / max(float(b.max() - b.min()), 1e-8), sam_deg=float(sam.mean()),
                        flip=flip(a, b))


def region_metrics(test: np.ndarray, ref: np.ndarray, mask: np.ndarray) -> dict:
    """MSE, ME, 1−SSIM and ꟻLIP restricted to the pixels of ``mask`` (H, W), on linear RGB clipped to [0, 1].

    SSIM is computed on the whole image (its 11×11 windows need context) and its
    per-pixel map averaged over the mask; ``pixels`` is the mask's size (0: all NaN).
    """
    from skimage.metrics import structural_similarity

    m = np.asarray(mask, bool)
    if not m.any():
        return {"mse": float("nan"), "me": float("nan"), "one_minus_ssim": float("nan"), "flip": float("nan"),
                "pixels": 0}
    a = np.clip(np.asarray(test, np.float64)[..., :3], 0, 1)
    b = np.clip(np.asarray(ref, np.float64)[..., :3], 0, 1)
    d = a[m] - b[m]
    _, smap = structural_similarity(a, b, data_range=1.0, channel_axis=-1, gaussian_weights=True, sigma=1.5,
                                    use_sample_covariance=False, full=True)
    return {"mse": float(np.mean(d**2)), "me": float(np.mean(np.abs(d))),
            "one_minus_ssim": float(1.0 - smap.mean(axis=-1)[m].mean()), "flip": flip(a, b, mask=m),
            "pixels": int(m.sum())}
