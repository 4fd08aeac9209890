"""The renderer's and the decomposition network's settings and names: no torch, so that `photoreal diffrender …
--help` answers at once."""

from __future__ import annotations

from dataclasses import dataclass

from foundation import validate
from foundation.errors import UsageError
from generative.diffusion import DiffusionConfig


LAYERS = ("albedo", "irradiance", "specular", "normal")


SOURCES = ("coarse", "morphed")


#: the benchmark's ground truth itself (its own materials and textures) through the same integrator: the seed's
#: pairs (exact intrinsics → photo, §3.1), which a synthetic training benchmark has and a user's data does not;
#: loaded only on request (:func:`with_truth_layers`), never an input at test time
TRUTH = "truth"


TRAIN_SOURCES = (*SOURCES, TRUTH)


DECOMPOSED = "decomposed"  #: the source name of pairs made by the decomposition network from photos


GLOBAL_SOURCES = ("R", "AIS", "none")


TOKEN_GRID = 4  #: the encoder's last feature map is 4×4 at its 128² input: 16 tokens per encoded image


@dataclass
class GBufferSettings:
    #: as many as the GAN stages' input renders (:class:`generative.gan.data.GanDataSettings`): the bench compares
    #: them on the same views, and at 16 spp the PBR recomposition carried twice their Monte-Carlo variance (held-out
    #: armadillo ꟻLIP 0.039 at 16 spp, 0.036 at 32, Morph-GAN 0.037, 2026-11-26)
    spp: int = 32
    max_depth: int = 3  #: intrinsic integrator path depth (the photos use the benchmark's photo_max_depth, 4 by default)

    def __post_init__(self):
        validate.integer("spp", self.spp, 1)
        validate.integer("max_depth", self.max_depth, 2)


def token_count(source: str) -> int:
    return {"R": TOKEN_GRID ** 2, "AIS": 3 * TOKEN_GRID ** 2, "none": TOKEN_GRID ** 2}[source]


@dataclass
class DiffRenderSettings:
    steps: int = 4000  #: upper bound; ``max_seconds`` usually ends the run first
    max_seconds: float | None = 600.0  #: training wall-time budget (summed over resumes)
    batch: int = 8
    crop: int = 64  #: random crop side (whole views when ≥ the resolution)
    lr: float = 2e-4
    #: four levels with attention only at the deepest (8² tokens on 64² crops): attention at 16² cost 3.6× the
    #: step time for 20 % of the FLOPs on this CPU (measured, photoreal bench diffrender's throughput section)
    widths: tuple[int, ...] = (32, 64, 96, 128)
    attention_levels: int = 1
    layers_per_block: int = 1
    cross_dim: int = 64
    global_source: str = "R"  #: "R" (seed 000), "AIS" (recomposition ablation), "none" (global features off)
    p_uncond: float = 0.1  #: probability of dropping the global condition (classifier-free guidance)
    #: whose G-buffers are training inputs. The morphed mesh's alone: the coarse mesh's residuals (photo − R) are
    #: its large geometry errors, and a model trained on both learns corrections that overshoot on the morphed
    #: G-buffers it is applied to and do not transfer to a mesh it never saw. Measured 2026-11-26 (scratch, H200, at
    #: the CPU bench's 780 steps, 1 step × mean of 8; ꟻLIP held-out village + armadillo / unseen bunny; PBR morphed
    #: 0.0650 / 0.0391): both sources 0.0670 / 0.0415, morphed only 0.0632 / 0.0391; at 1500 steps 0.0563 / 0.0387.
    #: The ground truth's own G-buffers beside them ("truth": the seed's exact-intrinsics pairs) are worse too:
    #: 960 s at one thread, default UNet, ꟻLIP village / armadillo / bunny / cow 0.0895 / 0.0342 / 0.0418 / 0.0400
    #: against morphed only 0.0829 / 0.0333 / 0.0411 / 0.0395 (2026-11-27, the ninth bench run's data)
    sources: tuple[str, ...] = ("morphed",)
    checkpoint_every: int = 50
    threads: int = 0  #: torch intra-op threads while training (0: all cores)
    channels_last: bool = True  #: NHWC convolutions (1.3–1.6× faster steps on this CPU, measured)
    #: generate (photo − R) × residual_scale instead of the photo (R = A·I + S of the same G-buffers); the scale
    #: brings the residual's standard deviation (0.065–0.14 in sRGB units on the village/armadillo pairs,
    #: measured) near the photos' (0.3–0.4)
    residual: bool = True
    residual_scale: float = 4.0
    #: the residual is 0 where the G-buffer sees no surface (R is the photo's environment there): trained on the
    #: mesh's pixels only, held at 0 elsewhere while sampling (residual only; see the module docstring)
    known_background: bool = True
    #: decay of the weights' moving average that sampling uses (0: the last weights). The last weights of a short
    #: CPU run wander: three 720 s runs of the same settings, stopped by the budget at 1913–2126 steps, gave held-out
    #: ꟻLIP 0.070–0.079; the average (0.995) of one of them 0.071 against its last weights' 0.076
    ema: float = 0.995
    seed: int = 0

    def __post_init__(self):
        self.widths = tuple(int(w) for w in self.widths)
        self.sources = tuple(self.sources)
        validate.integer("steps", self.steps, 1)
        validate.optional(validate.positive, "max_seconds", self.max_seconds)
        validate.integer("batch", self.batch, 1, 1024)
        validate.integer("crop", self.crop, 8)
        multiple = 1 << (len(self.widths) - 1)  # the U-Net halves a crop once per level below the first
        if self.crop % multiple:
            raise UsageError(f"crop {self.crop} must divide by {multiple} (2^(levels−1) of widths {self.widths})")
        validate.positive("lr", self.lr)
        validate.one_of("global_source", self.global_source, GLOBAL_SOURCES)
        validate.in_range("p_uncond", self.p_uncond, 0.0, 1.0)
        if not self.sources or any(x not in TRAIN_SOURCES for x in self.sources):
            raise UsageError(f"sources must be a non-empty subset of {TRAIN_SOURCES}, got {self.sources}")
        validate.integer("checkpoint_every", self.checkpoint_every, 1)
        validate.integer("threads", self.threads, 0)
        validate.positive("residual_scale", self.residual_scale)
        validate.in_range("ema", self.ema, 0.0, 0.99999)
        validate.seed("seed", self.seed)
        self._config(0)  # validates widths / levels

    def model_config(self) -> DiffusionConfig:
        from foundation.features import FEATURE_DIM  # MobileNetV2's width: torch loads with the model, not here

        return self._config(0 if self.global_source == "none" else FEATURE_DIM)

    def _config(self, global_dim: int) -> DiffusionConfig:
        return DiffusionConfig(image_channels=3, cond_channels=12, widths=self.widths,
                               layers_per_block=self.layers_per_block, attention_levels=self.attention_levels,
                               global_dim=global_dim, global_tokens=token_count(self.global_source),
                               cross_dim=self.cross_dim)


@dataclass
class SampleSettings:
    #: DDIM steps; 1 (from pure noise: the posterior mean) is what `bench diffrender` chose, its lowest ꟻLIP on
    #: held-out views (0.087 vs 0.110 at 5 steps, 0.120 at 40; 2026-11-26); more steps give sharper, stochastic samples
    steps: int = 1
    #: classifier-free guidance weight on the global condition (1 = none, one network pass). None = the bench's
    #: choices: 1 for a mean of draws (ꟻLIP 0.0726 at 1 and 1.5 alike for the small UNet, 2026-11-26: the cheaper
    #: wins), 1.5 for single samples (the guidance the sweep's step rows use)
    guidance: float | None = None
    #: samples averaged per view. At 1 step from pure noise each sample is x̂₀(x_T) ≈ E[x₀ | G-buffers, x_T], and x_T
    #: carries nothing about x₀ (ᾱ_T ≈ 2e-9), so their mean over x_T estimates the posterior mean E[x₀ | G-buffers]
    #: without the noise an imperfect model lets through from x_T (cost: ``draws`` × the network evaluations). None =
    #: the bench's choice at 1 step, 8 (held-out ꟻLIP 0.0726 vs 0.0749 for one draw, 2026-11-26), and 1 for more
    #: steps, so that ``steps`` > 1 gives samples, not their mean
    draws: int | None = None
    seed: int = 0

    def __post_init__(self):
        validate.integer("steps", self.steps, 1, 1000)
        if self.draws is None:
            self.draws = 8 if self.steps == 1 else 1
        validate.integer("draws", self.draws, 1, 256)
        if self.guidance is None:
            self.guidance = 1.0 if self.draws > 1 else 1.5
        validate.non_negative("guidance", self.guidance)
        validate.seed("seed", self.seed)


@dataclass
class DecompDataSettings:
    """Procedural training scenes of the decomposition network."""

    count: int = 160  #: scenes rendered (the last ``holdout`` fraction is held out)
    resolution: int = 128
    spp: int = 32
    max_depth: int = 3
    holdout: float = 0.15
    seed: int = 0

    def __post_init__(self):
        validate.integer("count", self.count, 2)
        validate.integer("resolution", self.resolution, 8, 4096)
        validate.integer("spp", self.spp, 1)
        validate.integer("max_depth", self.max_depth, 2)
        validate.in_range("holdout", self.holdout, 0.0, 0.9)
        validate.seed("seed", self.seed)

    @property
    def n_test(self) -> int:
        return max(1, int(round(self.count * self.holdout)))


@dataclass
class DecompSettings:
    steps: int = 3000
    max_seconds: float | None = 300.0
    batch: int = 8
    crop: int = 64
    lr: float = 3e-4
    widths: tuple[int, ...] = (32, 64, 96, 128)
    checkpoint_every: int = 100
    threads: int = 0
    seed: int = 0

    def __post_init__(self):
        self.widths = tuple(int(w) for w in self.widths)
        validate.integer("steps", self.steps, 1)
        validate.optional(validate.positive, "max_seconds", self.max_seconds)
        validate.integer("batch", self.batch, 1, 1024)
        validate.integer("crop", self.crop, 8)
        validate.positive("lr", self.lr)
        if not self.widths or any(w < 8 or w % 8 for w in self.widths):
            raise UsageError(f"widths must be multiples of 8, got {self.widths}")
        validate.integer("checkpoint_every", self.checkpoint_every, 1)
        validate.integer("threads", self.threads, 0)
        validate.seed("seed", self.seed)

    @property
    def multiple(self) -> int:
        return 1 << (len(self.widths) - 1)
