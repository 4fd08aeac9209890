"""Image metrics. Conventions: float images, linear or display-referred as stated."""

from __future__ import annotations

import numpy as np


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
