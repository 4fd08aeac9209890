"""The learned face stages' settings: no torch, so that `photoreal face train-models --help` answers at once."""

from __future__ import annotations

from dataclasses import dataclass, field

from foundation import validate
from foundation.errors import UsageError

from .data import FaceDataSettings
from .encoding import BRANCHES, VARIANTS


def _check_training(s) -> None:
    """The training fields every face model's settings share."""
    validate.integer("steps", s.steps, 1)
    validate.optional(validate.positive, "max_seconds", s.max_seconds)
    validate.integer("batch", s.batch, 1, 4096)
    validate.positive("lr", s.lr)
    validate.integer("checkpoint_every", s.checkpoint_every, 1)
    validate.integer("threads", s.threads, 0)
    validate.seed("seed", s.seed)


@dataclass
class CompletionSettings:
    """The completion/homogenisation diffusion model (the backbone of the decomposition) and its training run."""

    widths: tuple[int, ...] = (32, 64, 128)
    layers_per_block: int = 1
    attention_levels: int = 1  #: self-attention at the deepest level only (2 cores: attention at 32² costs ~4×)
    head_dim: int = 32
    res: int = 64  #: texels per side the model works at
    steps: int = 20000
    max_seconds: float | None = 720.0
    batch: int = 16
    lr: float = 3e-4
    checkpoint_every: int = 200
    threads: int = 0
    seed: int = 0
    sample_steps: int = 10  #: DDIM steps
    samples: int = 4  #: samples averaged into the returned albedo (the posterior mean: per-texel errors halve)

    def __post_init__(self):
        self.widths = tuple(int(w) for w in self.widths)
        if not self.widths or any(w < 8 or w % 8 for w in self.widths):
            raise UsageError(f"widths must be multiples of 8, got {self.widths}")
        validate.integer("layers_per_block", self.layers_per_block, 1)
        validate.integer("attention_levels", self.attention_levels, 1, len(self.widths))
        validate.integer("res", self.res, 8, 1024)
        if self.res % (1 << (len(self.widths) - 1)):
            raise UsageError(f"res {self.res} must divide by {1 << (len(self.widths) - 1)} (widths {self.widths})")
        _check_training(self)
        validate.integer("sample_steps", self.sample_steps, 1, 1000)
        validate.integer("samples", self.samples, 1, 256)


@dataclass
class DecompSettings:
    """The decomposition (one variant) and its training run."""

    variant: str = "cross_attention"  #: one of VARIANTS
    rank: int = 8  #: LoRA rank
    steps: int = 20000
    max_seconds: float | None = 360.0
    batch: int = 2  #: instances per step (× 4 branches through the backbone)
    lr: float = 1e-3  #: LoRA (the independent models: lr / 5, full fine-tuning)
    checkpoint_every: int = 100
    threads: int = 0
    seed: int = 0
    weights: tuple[float, ...] = (1.0, 1.0, 4.0, 4.0)  #: loss weight per branch (roughness/specular span less range)
    #: λ_img of seed 003's shading loss (0.5 there; 0 = off): predicted and true maps shaded by the UV-space GGX
    #: shader under two random directional lights + ambient, through dr.wrap
    shading_weight: float = 0.5

    def __post_init__(self):
        validate.one_of("variant", self.variant, VARIANTS)
        validate.integer("rank", self.rank, 1, 256)
        _check_training(self)
        validate.non_negative("shading_weight", self.shading_weight)
        self.weights = tuple(float(w) for w in self.weights)
        if len(self.weights) != len(BRANCHES) or min(self.weights) < 0:
            raise UsageError(f"weights: {len(BRANCHES)} non-negative numbers ({', '.join(BRANCHES)}), got {self.weights}")


@dataclass
class SuperResSettings:
    width: int = 48
    blocks: int = 6
    steps: int = 20000
    max_seconds: float | None = 180.0
    batch: int = 8
    lr: float = 1e-3
    checkpoint_every: int = 200
    threads: int = 0
    seed: int = 0

    def __post_init__(self):
        validate.integer("width", self.width, 4, 1024)
        validate.integer("blocks", self.blocks, 1, 64)
        _check_training(self)


@dataclass
class FaceModelsSettings:
    data: FaceDataSettings = field(default_factory=FaceDataSettings)
    completion: CompletionSettings = field(default_factory=CompletionSettings)
    decomposition: DecompSettings = field(default_factory=DecompSettings)
    superres: SuperResSettings = field(default_factory=SuperResSettings)
    variants: tuple[str, ...] = ("cross_attention",)  #: decomposition variants to train (the first is the one used)

    def __post_init__(self):
        self.variants = tuple(self.variants)
        if not self.variants:
            raise UsageError("variants: at least one decomposition variant")
        for v in self.variants:
            if v not in VARIANTS:
                raise UsageError(f"variants: {v!r} is not one of {', '.join(VARIANTS)}")
        if self.data.uv_res not in (self.completion.res, 2 * self.completion.res):
            raise UsageError(f"the data's uv_res ({self.data.uv_res}) must be the models' res ({self.completion.res}) "
                             "or twice it (super-resolution doubles)")
