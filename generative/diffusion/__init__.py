"""Diffusion models (seed 000 now; seeds 002 and 003 next), one family on one core.

=================  ==========================================================================
module             what
=================  ==========================================================================
``core``           config, conditional pixel-space UNet (diffusers), v-prediction loss, DDIM + CFG
``renderer``       intrinsic-conditioned diffusion renderer: G-buffer data, training stage, sampling
=================  ==========================================================================

Other features and the application use only the names below.
"""

from .core import (ConditionalDiffusion, DiffusionConfig, count_parameters, diffusion_loss, make_scheduler, sample,
                   training_flops)
from .renderer import (GLOBAL_SOURCES, LAYERS, DiffRenderOutput, DiffRenderResult, DiffRenderSettings, GBufferSettings, IntrinsicViews,
                       SampleSettings, global_condition, load_diffrender, load_intrinsic_views, local_condition,
                       model_to_photo, photo_to_model, render_benchmark, render_gbuffers, render_scene_file,
                       render_views, train_diffrender)

__all__ = [
    "ConditionalDiffusion", "DiffRenderOutput", "DiffRenderResult", "DiffRenderSettings", "DiffusionConfig", "GBufferSettings",
    "GLOBAL_SOURCES", "IntrinsicViews", "LAYERS", "SampleSettings", "count_parameters", "diffusion_loss",
    "global_condition", "load_diffrender", "load_intrinsic_views", "local_condition", "make_scheduler",
    "model_to_photo", "photo_to_model", "render_benchmark", "render_gbuffers", "render_scene_file", "render_views", "sample",
    "train_diffrender",
    "training_flops",
]
