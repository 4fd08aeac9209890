"""The diffusion model's architecture and noise schedule as a typed record: no torch, so that settings holding one
load without it."""

from __future__ import annotations

from dataclasses import dataclass

from foundation import validate
from foundation.errors import UsageError


PREDICTIONS = ("v_prediction", "epsilon")


SCHEDULES = ("squaredcos_cap_v2", "linear", "scaled_linear")


@dataclass
class DiffusionConfig:
    """Architecture and noise schedule of a conditional pixel-space diffusion model."""

    image_channels: int = 3  #: channels of the generated image
    cond_channels: int = 12  #: local condition channels concatenated with the noisy image (0 = none)
    widths: tuple[int, ...] = (32, 64, 96)  #: UNet channels per level (the image divides by 2^(levels−1))
    layers_per_block: int = 1
    attention_levels: int = 2  #: the deepest levels with cross-attention (and the middle block)
    head_dim: int = 16
    norm_groups: int = 8
    global_dim: int = 1280  #: width of the global tokens (MobileNetV2 features); 0 = no global condition
    global_tokens: int = 16  #: tokens per image (a 4×4 feature map)
    cross_dim: int = 64  #: width the global tokens are projected to
    class_dim: int = 0  #: width of a global vector added to the time embedding (ADM-style class conditioning); 0 = none
    prediction: str = "v_prediction"
    schedule: str = "squaredcos_cap_v2"  #: cosine schedule (Nichol & Dhariwal 2021)
    train_timesteps: int = 1000

    def __post_init__(self):
        self.widths = tuple(int(w) for w in self.widths)
        validate.integer("image_channels", self.image_channels, 1)
        validate.integer("cond_channels", self.cond_channels, 0)
        if not self.widths or any(w < 1 for w in self.widths):
            raise UsageError(f"widths must be positive integers, got {self.widths}")
        if any(w % self.norm_groups for w in self.widths):
            raise UsageError(f"every width in {self.widths} must divide by norm_groups = {self.norm_groups}")
        validate.integer("layers_per_block", self.layers_per_block, 1)
        validate.integer("attention_levels", self.attention_levels, 0, len(self.widths))
        validate.integer("head_dim", self.head_dim, 1)
        validate.integer("global_dim", self.global_dim, 0)
        validate.integer("global_tokens", self.global_tokens, 1)
        validate.integer("cross_dim", self.cross_dim, 1)
        validate.integer("class_dim", self.class_dim, 0)
        validate.one_of("prediction", self.prediction, PREDICTIONS)
        validate.one_of("schedule", self.schedule, SCHEDULES)
        validate.integer("train_timesteps", self.train_timesteps, 10)

    def heads(self, width: int) -> int:
        """Attention heads of a level: ``width // head_dim`` (at least one)."""
        return max(1, width // self.head_dim)

    @property
    def multiple(self) -> int:
        """Image sides must divide by this."""
        return 1 << (len(self.widths) - 1)
