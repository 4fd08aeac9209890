"""The intrinsic-conditioned diffusion renderer (seed 000): G-buffers (A, I, S, N) of a morphed mesh → photo.

=================  ==========================================================================
module             what
=================  ==========================================================================
``renderer``       G-buffer data of morph benchmarks, the training stage, sampling, renders of views and scenes
``decomposition``  intrinsic decomposition network (image → A, I, S, N) trained on procedural Mitsuba scenes
=================  ==========================================================================

The model itself is the shared core of :mod:`generative.diffusion`. `photoreal diffrender` and
`photoreal bench diffrender` use only the names below.
"""

from .decomposition import (DecompDataSettings, DecompSettings, decompose, heldout_psnr, load_decomp_data,
                            load_decomposer, photographs, train_decomposer)
from .renderer import (DECOMPOSED, TRAIN_SOURCES, TRUTH, DiffRenderSettings, GBufferSettings, IntrinsicViews,
                       SampleSettings, load_diffrender, load_intrinsic_views, render_benchmark, render_gbuffers,
                       render_scene_file, render_views, train_diffrender, with_truth_layers)

__all__ = [
    "DECOMPOSED", "TRAIN_SOURCES", "TRUTH", "DecompDataSettings", "DecompSettings", "DiffRenderSettings",
    "GBufferSettings", "IntrinsicViews", "SampleSettings", "decompose", "heldout_psnr", "load_decomp_data",
    "load_decomposer", "load_diffrender", "load_intrinsic_views", "photographs", "render_benchmark",
    "render_gbuffers", "render_scene_file", "render_views", "train_decomposer", "train_diffrender",
    "with_truth_layers",
]
