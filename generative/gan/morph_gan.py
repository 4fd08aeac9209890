"""Morph-GAN (REAL-DIBS §5.1): pix2pix on the 6-channel image r_j ‖ m_j → photo i_j (eq. 5.2).

Notation (thesis §5.1):

==============  ===========  ===========================================================
code            thesis       meaning
==============  ===========  ===========================================================
``rendered``    r_j          render of the original (coarse) mesh at camera c_j
``morphed``     m_j          render of the morphed mesh M' at c_j (eq. 5.1)
``paired``      p_j          r_j ‖ m_j, 6 channels (eq. 5.2)
``partial``     —            "partial Morph-GAN": input m_j only (3 channels)
==============  ===========  ===========================================================

G and D are pix2pix's (:mod:`generative.pix2pix`); with ``residual=True`` G corrects the
morphed image (the last 3 input channels), the thesis' better-geometry starting point.
"""

from __future__ import annotations

from dataclasses import replace

import torch

from .pix2pix import Pix2Pix, Pix2PixConfig


def paired_input(rendered: torch.Tensor, morphed: torch.Tensor) -> torch.Tensor:
    """Eq. 5.2: p = r ‖ m — (N, 3, H, W) × 2 → (N, 6, H, W); the morphed image comes last."""
    if rendered.shape != morphed.shape:
        raise ValueError(f"paired_input: shapes differ {tuple(rendered.shape)} vs {tuple(morphed.shape)}")
    return torch.cat([rendered, morphed], 1)


class MorphGAN(Pix2Pix):
    """pix2pix with a 6-channel input (complete) or the morphed image alone (``partial=True``)."""

    def __init__(self, cfg: Pix2PixConfig | None = None, partial: bool = False, seed: int = 0):
        cfg = replace(cfg or Pix2PixConfig(), in_channels=3 if partial else 6)
        super().__init__(cfg, seed=seed)
        self.partial = partial

    def make_input(self, rendered: torch.Tensor, morphed: torch.Tensor) -> torch.Tensor:
        """(N, 3, H, W) r and m → the model's input: m (partial) or r ‖ m (N, 6, H, W)."""
        return morphed if self.partial else paired_input(rendered, morphed)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x: (N, 6, H, W) = r ‖ m (or (N, 3, H, W) = m, partial) → (N, 3, H, W) photo estimate."""
        return self.G(x)
