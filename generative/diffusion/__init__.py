"""The diffusion core that the renderer (seed 000), the materials (seed 002) and the face models (seed 003) share:
a conditional pixel-space UNet (diffusers), the v-prediction loss, DDIM sampling with classifier-free guidance,
and a training stage of the shared loop (:mod:`foundation.loop`).

Features of this layer (``generative.diffrender``, ``generative.btf``, ``generative.face``) build on the names
below; this package imports none of them.
"""

from .core import (ConditionalDiffusion, DiffusionConfig, OptimizerStage, check_size, count_parameters,
                   diffusion_loss, load_trained, make_scheduler, sample, torch_device, train_stage, training_flops)

__all__ = [
    "ConditionalDiffusion", "DiffusionConfig", "OptimizerStage", "check_size", "count_parameters", "diffusion_loss",
    "load_trained", "make_scheduler", "sample", "torch_device", "train_stage", "training_flops",
]
