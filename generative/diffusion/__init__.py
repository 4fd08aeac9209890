"""The diffusion core that the renderer (seed 000), the materials (seed 002) and the face models (seed 003) share:
a conditional pixel-space UNet (diffusers), the v-prediction loss, DDIM sampling with classifier-free guidance,
and a training stage of the shared loop (:mod:`foundation.loop`).

Features of this layer (``generative.diffrender``, ``generative.btf``, ``generative.face``) build on the names
below; this package imports none of them. ``DiffusionConfig`` (``config``) loads without torch, the rest on first
use (:mod:`foundation.lazy`).
"""

from foundation.lazy import lazy_names

from .config import DiffusionConfig

#: every other name loads its module (and torch) on first use: `photoreal … --help` never does
__getattr__, __dir__ = lazy_names(__name__, {
    "core": ("ConditionalDiffusion", "OptimizerStage", "check_size", "count_parameters", "diffusion_loss",
        "load_trained", "make_scheduler", "sample", "torch_device", "train_stage", "training_flops",),
})

__all__ = [
    "ConditionalDiffusion", "DiffusionConfig", "OptimizerStage", "check_size", "count_parameters", "diffusion_loss",
    "load_trained", "make_scheduler", "sample", "torch_device", "train_stage", "training_flops",
]
