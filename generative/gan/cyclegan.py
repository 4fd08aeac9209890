"""CycleGAN (Zhu et al. 2017): ResNet generators, LSGAN, cycle λ = 10, identity 0.5·λ (REAL-DIBS §3.3).

Notation (CycleGAN paper, eq. 1–3, identity loss §5.2):

==============  =========  ==================================================================
code            paper      meaning
==============  =========  ==================================================================
``G``           G: X → Y   render → photo (:class:`ResnetGenerator`)
``F_``          F: Y → X   photo → render
``D_Y``, D_X    D_Y, D_X   70×70 PatchGANs (unconditional), least-squares loss
``lambda_cyc``  λ          ‖F(G(x)) − x‖₁ + ‖G(F(y)) − y‖₁ weight (10)
``lambda_id``   0.5·λ      ‖G(y) − y‖₁ + ‖F(x) − x‖₁ weight (0.5 × λ_cyc)
==============  =========  ==================================================================

The data are unpaired on purpose (x and y come from different views). CPU-budget
deviations: ``ngf = ndf = 16`` (paper 64; a 128² step with ngf 32 took ~10 s here); 6 residual blocks (the paper's choice for
128² images); no 50-image history pool for D (batches are tiny); ``residual=True``
adds G's tanh correction to its input (as in pix2pix.py; ``False`` = the paper's head).
Measured on the village: with the residual head G stays at the identity (held-out MSE unchanged
to 1e-5 after 350 steps, also at lr 1e-3 — the cycle and identity losses hold it there), so
`photoreal bench gan` trains the paper's head, from scratch, for 3× the pix2pix budget.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from .pix2pix import PatchDiscriminator, gan_loss, init_weights


@dataclass
class CycleGANConfig:
    channels: int = 3
    ngf: int = 16
    ndf: int = 16
    n_blocks: int = 6
    d_layers: int = 3
    residual: bool = True
    lambda_cyc: float = 10.0
    identity: float = 0.5  #: λ_id = identity × λ_cyc

    def __post_init__(self):
        if self.n_blocks < 0 or self.ngf < 1 or self.ndf < 1 or self.lambda_cyc < 0 or self.identity < 0:
            raise ValueError(f"cyclegan config out of range: {self}")


class _ResBlock(nn.Module):
    def __init__(self, ch: int):
        super().__init__()
        self.body = nn.Sequential(nn.ReflectionPad2d(1), nn.Conv2d(ch, ch, 3, bias=False),
                                  nn.InstanceNorm2d(ch, affine=True), nn.ReLU(True),
                                  nn.ReflectionPad2d(1), nn.Conv2d(ch, ch, 3, bias=False),
                                  nn.InstanceNorm2d(ch, affine=True))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.body(x)


class ResnetGenerator(nn.Module):
    """c7s1-ngf, d2ngf, d4ngf, n_blocks × R4ngf, u2ngf, ungf, c7s1-3: (N, C, H, W) → (N, C, H, W); H, W % 4 == 0."""

    def __init__(self, cfg: CycleGANConfig, seed: int = 0):
        super().__init__()
        self.cfg = cfg
        c, n = cfg.channels, cfg.ngf
        layers: list[nn.Module] = [nn.ReflectionPad2d(3), nn.Conv2d(c, n, 7, bias=False),
                                   nn.InstanceNorm2d(n, affine=True), nn.ReLU(True)]
        for k in (1, 2):
            layers += [nn.Conv2d(n * k, n * 2 * k, 3, 2, 1, bias=False), nn.InstanceNorm2d(n * 2 * k, affine=True),
                       nn.ReLU(True)]
        layers += [_ResBlock(n * 4) for _ in range(cfg.n_blocks)]
        for k in (4, 2):
            layers += [nn.ConvTranspose2d(n * k, n * k // 2, 3, 2, 1, output_padding=1, bias=False),
                       nn.InstanceNorm2d(n * k // 2, affine=True), nn.ReLU(True)]
        layers += [nn.ReflectionPad2d(3), nn.Conv2d(n, c, 7)]
        self.net = nn.Sequential(*layers)
        init_weights(self, seed)
        if cfg.residual:  # zero last layer: G starts as the identity (as pix2pix.py's residual head)
            nn.init.zeros_(self.net[-1].weight)
            nn.init.zeros_(self.net[-1].bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x: (N, C, H, W) linear RGB [0, 1] → (N, C, H, W) in [0, 1] (or x + correction when residual)."""
        if x.shape[-1] % 4 or x.shape[-2] % 4:
            raise ValueError(f"ResnetGenerator: input {tuple(x.shape)} must have H, W divisible by 4")
        h = self.net(x * 2 - 1)
        return x + 0.5 * torch.tanh(h) if self.cfg.residual else 0.5 * (torch.tanh(h) + 1)


class CycleGAN(nn.Module):
    """G: X→Y, F: Y→X and their PatchGANs, with the paper's LSGAN + cycle + identity objectives."""

    def __init__(self, cfg: CycleGANConfig | None = None, seed: int = 0):
        super().__init__()
        self.cfg = cfg or CycleGANConfig()
        c = self.cfg
        self.G = ResnetGenerator(c, seed=seed)
        self.F_ = ResnetGenerator(c, seed=seed + 1)
        self.D_Y = PatchDiscriminator(c.channels, c.ndf, c.d_layers, seed=seed + 2)
        self.D_X = PatchDiscriminator(c.channels, c.ndf, c.d_layers, seed=seed + 3)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x: (N, 3, H, W) render → G(x): (N, 3, H, W) photo-like."""
        return self.G(x)

    def generator_loss(self, x: torch.Tensor, y: torch.Tensor) -> tuple[torch.Tensor, dict, tuple]:
        """L = L_LSGAN(G) + L_LSGAN(F) + λ·L_cyc + 0.5λ·L_id; returns (loss, terms, (G(x), F(y)))."""
        c = self.cfg
        fake_y, fake_x = self.G(x), self.F_(y)
        adv = gan_loss(self.D_Y(fake_y), True, "lsgan") + gan_loss(self.D_X(fake_x), True, "lsgan")
        cyc = F.l1_loss(self.F_(fake_y), x) + F.l1_loss(self.G(fake_x), y)
        idt = F.l1_loss(self.G(y), y) + F.l1_loss(self.F_(x), x) if c.identity > 0 else torch.zeros(())
        loss = adv + c.lambda_cyc * cyc + c.identity * c.lambda_cyc * idt
        terms = {"g_gan": float(adv.detach()), "cycle": float(cyc.detach()), "identity": float(idt.detach())}
        return loss, terms, (fake_y, fake_x)

    def discriminator_loss(self, x: torch.Tensor, y: torch.Tensor, fake_y: torch.Tensor,
                           fake_x: torch.Tensor) -> tuple[torch.Tensor, dict]:
        """½[(D_Y(y) − 1)² + D_Y(G(x))²] + ½[(D_X(x) − 1)² + D_X(F(y))²], fakes detached."""
        dy = 0.5 * (gan_loss(self.D_Y(y), True, "lsgan") + gan_loss(self.D_Y(fake_y.detach()), False, "lsgan"))
        dx = 0.5 * (gan_loss(self.D_X(x), True, "lsgan") + gan_loss(self.D_X(fake_x.detach()), False, "lsgan"))
        return dy + dx, {"d_y": float(dy.detach()), "d_x": float(dx.detach())}
