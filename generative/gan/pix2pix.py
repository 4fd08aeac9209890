"""pix2pix (Isola et al. 2017): U-Net generator, 70×70 PatchGAN discriminator, GAN + λ·L1 loss (REAL-DIBS §3.3).

Notation (pix2pix paper, eq. 1–4):

=================  ==========  ==============================================================
code               paper       meaning
=================  ==========  ==============================================================
``x``              x           input image (rendered; N×C_in×H×W, linear RGB in [0, 1])
``y``              y           target photo (N×3×H×W)
``G``              G           :class:`UNetGenerator`
``D``              D           :class:`PatchDiscriminator` on (x ‖ y) — conditional GAN
``lambda_l1``      λ           weight of the L1 term (100)
``gan_loss``       L_cGAN      BCE-with-logits ("vanilla") or least squares ("lsgan")
=================  ==========  ==============================================================

Deviations from the paper's reference defaults, forced by a 2-core CPU budget
(minutes per model, 128² crops instead of 256²), all settable:

* ``ngf = ndf = 16`` instead of 64 (measured here, one 128² training step: ngf 32 ≈ 3–8 s,
  ngf 16 ≈ 0.5 s on 2 shared cores);
* 5 U-Net levels (64² training crops → 2², full 128² views → 4² at inference) instead of 8 (256 → 1);
* InstanceNorm instead of BatchNorm (the paper's batch size 1 makes BatchNorm an
  instance norm; here batches of 1–4 crops);
* ``residual=True`` by default: G predicts a correction that is added to the input
  render (its last 3 channels), instead of the paper's plain tanh image. With a few
  hundred steps this starts G at "copy the input" (its last layer starts at zero, so G(x) = x at
  step 0); ``residual=False`` gives the paper's head.

Images are linear RGB in [0, 1]; G maps them to [−1, 1] internally (×2 − 1), as the paper's tanh.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn


@dataclass
class Pix2PixConfig:
    in_channels: int = 3
    out_channels: int = 3
    ngf: int = 16  #: generator width (paper: 64)
    ndf: int = 16  #: discriminator width (paper: 64)
    levels: int = 5  #: U-Net down-sampling levels (paper: 8 for 256²); input side must be divisible by 2^levels
    d_layers: int = 3  #: PatchGAN strided layers; 3 gives the 70×70 receptive field
    dropout: float = 0.5  #: in the 3 innermost decoder blocks (the paper's noise z)
    residual: bool = True  #: G outputs input + correction (see the module docstring)
    lambda_l1: float = 100.0
    gan_mode: str = "vanilla"  #: "vanilla" (BCE) or "lsgan"

    def __post_init__(self):
        if self.levels < 2 or self.ngf < 1 or self.ndf < 1 or self.d_layers < 1:
            raise ValueError(f"pix2pix config out of range: {self}")
        if self.gan_mode not in ("vanilla", "lsgan"):
            raise ValueError(f"gan_mode must be 'vanilla' or 'lsgan', got {self.gan_mode!r}")


def init_weights(module: nn.Module, seed: int, gain: float = 0.02) -> nn.Module:
    """The paper's init, seeded: conv weights ~ N(0, 0.02), norm scales ~ N(1, 0.02), biases 0."""
    g = torch.Generator().manual_seed(int(seed))
    for m in module.modules():
        if isinstance(m, (nn.Conv2d, nn.ConvTranspose2d)):
            with torch.no_grad():
                m.weight.copy_(torch.randn(m.weight.shape, generator=g) * gain)
                if m.bias is not None:
                    m.bias.zero_()
        elif isinstance(m, (nn.InstanceNorm2d, nn.BatchNorm2d)) and m.weight is not None:
            with torch.no_grad():
                m.weight.copy_(1.0 + torch.randn(m.weight.shape, generator=g) * gain)
                m.bias.zero_()
    return module


class _UNetBlock(nn.Module):
    """One U-Net level: down (conv 4×4/2) → inner → up (transposed conv 4×4/2), with the skip concatenation."""

    def __init__(self, outer: int, inner: int, sub: nn.Module | None, in_ch: int | None = None,
                 outermost: bool = False, dropout: float = 0.0):
        super().__init__()
        in_ch = in_ch or outer
        down = nn.Conv2d(in_ch, inner, 4, 2, 1, bias=outermost or sub is None)
        self.outermost = outermost
        if outermost:
            self.down = nn.Sequential(down)
            self.sub = sub
            self.up = nn.Sequential(nn.ReLU(True), nn.ConvTranspose2d(inner * 2, outer, 4, 2, 1))
        elif sub is None:  # innermost: no norm on the bottleneck
            self.down = nn.Sequential(nn.LeakyReLU(0.2, True), down)
            self.sub = None
            self.up = nn.Sequential(nn.ReLU(True), nn.ConvTranspose2d(inner, outer, 4, 2, 1, bias=False),
                                    nn.InstanceNorm2d(outer, affine=True))
        else:
            self.down = nn.Sequential(nn.LeakyReLU(0.2, True), down, nn.InstanceNorm2d(inner, affine=True))
            self.sub = sub
            up = [nn.ReLU(True), nn.ConvTranspose2d(inner * 2, outer, 4, 2, 1, bias=False),
                  nn.InstanceNorm2d(outer, affine=True)]
            if dropout > 0:
                up.append(nn.Dropout(dropout))
            self.up = nn.Sequential(*up)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = self.down(x)
        if self.sub is not None:
            h = self.sub(h)
        h = self.up(h)
        return h if self.outermost else torch.cat([x, h], 1)


class UNetGenerator(nn.Module):
    """pix2pix U-Net G: (N, C_in, H, W) in [0, 1] → (N, C_out, H, W); H, W divisible by 2^levels."""

    def __init__(self, cfg: Pix2PixConfig, seed: int = 0):
        super().__init__()
        self.cfg = cfg
        ngf, L = cfg.ngf, cfg.levels
        widths = [min(ngf * 2**i, ngf * 8) for i in range(L)]  # encoder widths: 64-128-256-512-512-… in the paper
        block = _UNetBlock(widths[L - 2], widths[L - 1], None)
        for i in range(L - 2, 0, -1):
            drop = cfg.dropout if (L - 2 - i) < 3 and widths[i - 1] == ngf * 8 else 0.0  # the paper: ngf·8 blocks
            block = _UNetBlock(widths[i - 1], widths[i], block, dropout=drop)
        self.net = _UNetBlock(cfg.out_channels, widths[0], block, in_ch=cfg.in_channels, outermost=True)
        init_weights(self, seed)
        if cfg.residual:  # zero last layer: G starts as the identity on the input render (then learns a correction)
            last = self.net.up[-1]
            nn.init.zeros_(last.weight)
            nn.init.zeros_(last.bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x: (N, C_in, H, W) linear RGB [0, 1] → (N, C_out, H, W) in [0, 1] (tanh head, or residual on x[:, -3:])."""
        k = 2**self.cfg.levels
        if x.shape[-1] % k or x.shape[-2] % k:
            raise ValueError(f"UNetGenerator: input {tuple(x.shape)} must have H, W divisible by {k}")
        h = self.net(x * 2 - 1)
        if self.cfg.residual:
            return x[:, -self.cfg.out_channels:] + 0.5 * torch.tanh(h)
        return 0.5 * (torch.tanh(h) + 1)


class PatchDiscriminator(nn.Module):
    """70×70 PatchGAN D: (N, C, H, W) → (N, 1, H', W') logits, one per overlapping 70×70 patch (d_layers=3)."""

    def __init__(self, in_channels: int, ndf: int = 32, d_layers: int = 3, seed: int = 1):
        super().__init__()
        layers: list[nn.Module] = [nn.Conv2d(in_channels, ndf, 4, 2, 1), nn.LeakyReLU(0.2, True)]
        mult = 1
        for n in range(1, d_layers + 1):
            prev, mult = mult, min(2**n, 8)
            stride = 2 if n < d_layers else 1
            layers += [nn.Conv2d(ndf * prev, ndf * mult, 4, stride, 1, bias=False),
                       nn.InstanceNorm2d(ndf * mult, affine=True), nn.LeakyReLU(0.2, True)]
        layers.append(nn.Conv2d(ndf * mult, 1, 4, 1, 1))
        self.net = nn.Sequential(*layers)
        init_weights(self, seed)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x: (N, C, H, W) in [0, 1] → patch logits (N, 1, H/8 − 2, W/8 − 2) for d_layers = 3."""
        return self.net(x * 2 - 1)


def receptive_field(d_layers: int = 3) -> int:
    """Receptive field (pixels) of :class:`PatchDiscriminator`: 70 for 3 layers (kernel 4; strides 2…2,1,1)."""
    strides = [2] * d_layers + [1, 1]
    rf = 1
    for s in reversed(strides):
        rf = (rf - 1) * s + 4
    return rf


def gan_loss(logits: torch.Tensor, real: bool, mode: str = "vanilla") -> torch.Tensor:
    """L_GAN for one side: BCE-with-logits against 1/0 ("vanilla") or mean (D − 1)² / D² ("lsgan")."""
    target = torch.ones_like(logits) if real else torch.zeros_like(logits)
    if mode == "vanilla":
        return F.binary_cross_entropy_with_logits(logits, target)
    if mode == "lsgan":
        return F.mse_loss(logits, target)
    raise ValueError(f"unknown GAN mode {mode!r}")


class Pix2Pix(nn.Module):
    """G and a conditional D, with the paper's two objectives (D sees x ‖ y)."""

    def __init__(self, cfg: Pix2PixConfig | None = None, seed: int = 0):
        super().__init__()
        self.cfg = cfg or Pix2PixConfig()
        self.G = UNetGenerator(self.cfg, seed=seed)
        self.D = PatchDiscriminator(self.cfg.in_channels + self.cfg.out_channels, self.cfg.ndf, self.cfg.d_layers,
                                    seed=seed + 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x: (N, C_in, H, W) → ŷ = G(x): (N, 3, H, W)."""
        return self.G(x)

    def generator_loss(self, x: torch.Tensor, y: torch.Tensor,
                       fake: torch.Tensor | None = None) -> tuple[torch.Tensor, dict]:
        """L_G = L_cGAN(G(x) judged real) + λ·‖y − G(x)‖₁ (mean); returns the loss and its terms."""
        fake = self.G(x) if fake is None else fake
        adv = gan_loss(self.D(torch.cat([x, fake], 1)), True, self.cfg.gan_mode)
        l1 = F.l1_loss(fake, y)
        return adv + self.cfg.lambda_l1 * l1, {"g_gan": float(adv.detach()), "g_l1": float(l1.detach())}

    def discriminator_loss(self, x: torch.Tensor, y: torch.Tensor, fake: torch.Tensor) -> tuple[torch.Tensor, dict]:
        """L_D = ½ [L(D(x‖y), real) + L(D(x‖ŷ), fake)] with ŷ detached (the paper halves D's objective)."""
        real = gan_loss(self.D(torch.cat([x, y], 1)), True, self.cfg.gan_mode)
        fk = gan_loss(self.D(torch.cat([x, fake.detach()], 1)), False, self.cfg.gan_mode)
        return 0.5 * (real + fk), {"d_real": float(real.detach()), "d_fake": float(fk.detach())}
