"""The GAN stages' settings: plain dataclasses, no torch, so that `photoreal gan … --help` answers at once."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Literal

from foundation import validate
from inverse.morph import MODES


@dataclass
class GanDataSettings:
    spp: int = 32
    max_depth: int = 3
    mode: str = "lit"  #: appearance mode of inverse.morph's scene

    def __post_init__(self):
        validate.integer("spp", self.spp, 1)
        validate.integer("max_depth", self.max_depth, 2)
        validate.one_of("mode", self.mode, MODES)


ModelName = Literal["pix2pix", "cyclegan", "morph_gan_partial", "morph_gan"]


MODELS: tuple[str, ...] = ("pix2pix", "cyclegan", "morph_gan_partial", "morph_gan")


@dataclass
class GanTrainSettings:
    model: str = "morph_gan"  #: one of MODELS
    steps: int = 5000  #: upper bound; ``max_seconds`` usually ends the run first
    max_seconds: float | None = 120.0  #: training wall-time budget (summed over resumes); None = steps only
    batch: int = 4
    crop: int = 64  #: random crop side (whole images when ≥ the resolution)
    lr: float = 2e-4
    beta1: float = 0.5
    ngf: int = 16
    ndf: int = 16
    levels: int = 5
    residual: bool = True
    lambda_l1: float = 100.0
    checkpoint_every: int = 25
    eval_every: int = 50  #: steps between held-out MSE curve points
    threads: int = 1  #: torch intra-op threads while training (see :func:`torch_threads`)
    val_every: int = 6  #: every k-th train view is a validation view (not trained on); 0 = no selection
    init_from: str | None = None  #: a finished run folder of the same model: start from its selected G and D
    seed: int = 0

    def __post_init__(self):
        validate.one_of("model", self.model, MODELS)
        validate.integer("steps", self.steps, 1)
        validate.optional(validate.positive, "max_seconds", self.max_seconds)
        validate.integer("batch", self.batch, 1, 1024)
        validate.integer("crop", self.crop, 8)
        validate.positive("lr", self.lr)
        validate.in_range("beta1", self.beta1, 0.0, 1.0, hi_open=True)
        validate.integer("ngf", self.ngf, 1)
        validate.integer("ndf", self.ndf, 1)
        validate.integer("levels", self.levels, 1, 8)
        validate.non_negative("lambda_l1", self.lambda_l1)
        validate.integer("checkpoint_every", self.checkpoint_every, 1)
        validate.integer("eval_every", self.eval_every, 1)
        validate.integer("threads", self.threads, 0)
        validate.integer("val_every", self.val_every, 0)
        validate.seed("seed", self.seed)


@dataclass
class JointSettings:
    steps: int = 2000
    max_seconds: float | None = 180.0
    gan: GanTrainSettings = None  # type: ignore[assignment]  # Morph-GAN settings of G and D (model forced)
    morph_weight: float = 1.0  #: weight of the eq. 4.3 term L1(m_j, i_j) in the joint loss
    lambda_: float = 2.0  #: large-steps λ (inverse.morph's default)
    lr: float = 0.05  #: × scene size / 10 (positions; uniform Adam on u), as MorphSettings
    lr_colour: float = 0.01
    spp: int = 4
    max_depth: int = 3  #: path length of m_j while training and testing (3 = the paired data's renders);
    #: 2 = direct light only (``direct_projective``), larger = ``prb_projective``
    init_from: str | None = None  #: a finished Morph-GAN run folder: G and D start from its selected weights
    init_mesh: str | None = None  #: a coloured PLY to start from (e.g. a morph run's morphed.ply), not remeshed
    checkpoint_every: int = 25
    eval_every: int = 50
    seed: int = 0

    def __post_init__(self):
        self.gan = replace(self.gan or GanTrainSettings(), model="morph_gan", seed=self.seed)
        validate.integer("steps", self.steps, 1)
        validate.optional(validate.positive, "max_seconds", self.max_seconds)
        validate.non_negative("morph_weight", self.morph_weight)
        validate.positive("lambda_", self.lambda_)
        validate.non_negative("lr", self.lr)  # 0 keeps the mesh fixed (a fine-tune of G alone, through the renderer)
        validate.non_negative("lr_colour", self.lr_colour)
        validate.integer("spp", self.spp, 1)
        validate.integer("max_depth", self.max_depth, 2)
        validate.integer("checkpoint_every", self.checkpoint_every, 1)
        validate.integer("eval_every", self.eval_every, 1)
        validate.seed("seed", self.seed, 200_000)
