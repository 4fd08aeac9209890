"""The material diffusion model's and the family classifier's settings: no torch, so that `photoreal btf … --help`
and `photoreal bench matdiff --help` answer at once."""

from __future__ import annotations

from dataclasses import dataclass

from foundation import validate
from foundation.errors import UsageError


@dataclass
class MatDiffSettings:
    """Architecture, the seed's switches, and the training run of a material diffusion model."""

    widths: tuple[int, ...] = (32, 64, 96)  #: 1.3 s per batch-16 step at 32² on one core ((64, 96, 128): 3.1 s)
    layers_per_block: int = 1
    #: the deepest level and the middle block (2: also the 16² level, +50 % time per step; see train_crop)
    attention_levels: int = 1
    head_dim: int = 32
    circular: bool = True
    prediction: str = "v_prediction"
    shift_base: int = 16  #: SNR × (base/H)²; 0 = the plain cosine schedule
    min_snr_gamma: float = 5.0  #: 0 = no Min-SNR weighting
    snr_floor: bool = False  #: v-prediction: weight the x₀ error by min(SNR, γ) + 1, not min(SNR, γ) (see loss_weight)
    cube_root: bool = True
    multiscale: bool = True
    cfg: bool = True  #: drop conditions in training (p_keep below) and guide at sampling
    p_keep: float = 0.6  #: probability that the keywords (independently: the exemplar) are kept in a training sample
    exemplar_local: bool = True  #: also concatenate the exemplar image with the noisy input
    keyword_embedding: bool = True  #: also add the keywords to the time embedding (ADM-style class conditioning)
    steps: int = 20000  #: upper bound; ``max_seconds`` usually ends the run first
    max_seconds: float | None = 900.0
    batch: int = 16
    #: texels per side of the random (wrapped) crops trained on; 0 = the whole texture. 16 with one attention level
    #: and lr 1e-3: 4.4× the steps of whole 32² textures with two levels and lr 5e-4 in equal time, and the held-out
    #: x̂₀ error at t = 79 / 159 of 0.034 / 0.063 instead of 0.053 / 0.122 (480 s, one thread; docs/results/material-diffusion.md)
    train_crop: int = 16
    lr: float = 1e-3
    ema: float = 0.0  #: decay of the weights' exponential moving average that sampling uses; 0 = the raw weights
    checkpoint_every: int = 200
    threads: int = 0
    seed: int = 0
    feature_scale: float = 0.0  #: s of the scaling; 0 = measured on the training set when training starts
    channels: int = 8  #: C of T_off and of T_rgb (the basis')
    basis_id: str = ""  #: the basis the training materials were fitted to (samples carry it)
    train_res: int = 0  #: texels per side of the training textures (set when training starts)

    def __post_init__(self):
        self.widths = tuple(int(w) for w in self.widths)
        if not self.widths or any(w < 8 or w % 8 for w in self.widths):
            raise UsageError(f"widths must be multiples of 8, got {self.widths}")
        validate.integer("layers_per_block", self.layers_per_block, 1)
        validate.integer("attention_levels", self.attention_levels, 0, len(self.widths))
        validate.integer("head_dim", self.head_dim, 1)
        validate.one_of("prediction", self.prediction, ("v_prediction", "epsilon"))
        validate.integer("shift_base", self.shift_base, 0)
        validate.non_negative("min_snr_gamma", self.min_snr_gamma)
        validate.in_range("p_keep", self.p_keep, 0.0, 1.0)
        validate.integer("steps", self.steps, 1)
        validate.optional(validate.positive, "max_seconds", self.max_seconds)
        validate.integer("batch", self.batch, 1, 4096)
        validate.integer("train_crop", self.train_crop, 0)
        if self.train_crop and self.train_crop % self.multiple:
            raise UsageError(f"train_crop {self.train_crop} must divide by {self.multiple} (widths {self.widths})")
        validate.positive("lr", self.lr)
        validate.in_range("ema", self.ema, 0.0, 0.99999)
        validate.integer("checkpoint_every", self.checkpoint_every, 1)
        validate.integer("threads", self.threads, 0)
        validate.seed("seed", self.seed)
        validate.non_negative("feature_scale", self.feature_scale)
        validate.integer("channels", self.channels, 1)

    @property
    def multiple(self) -> int:
        return 1 << (len(self.widths) - 1)


@dataclass
class ClassifierSettings:
    steps: int = 1500
    max_seconds: float | None = 120.0
    batch: int = 64
    lr: float = 1e-3
    weight_decay: float = 1e-2
    width: int = 64
    rolls: int = 4  #: random circular shifts of every training material (a tileable swatch has no origin)
    checkpoint_every: int = 500
    threads: int = 0
    seed: int = 0

    def __post_init__(self):
        validate.integer("steps", self.steps, 1)
        validate.optional(validate.positive, "max_seconds", self.max_seconds)
        validate.integer("batch", self.batch, 1)
        validate.positive("lr", self.lr)
        validate.non_negative("weight_decay", self.weight_decay)
        validate.integer("width", self.width, 8)
        validate.integer("rolls", self.rolls, 1)
        validate.seed("seed", self.seed)
