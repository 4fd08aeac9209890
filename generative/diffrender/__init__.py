"""The intrinsic-conditioned diffusion renderer (seed 000): G-buffers (A, I, S, N) of a morphed mesh → photo.

=================  ==========================================================================
module             what
=================  ==========================================================================
``renderer``       G-buffer data of morph benchmarks, the training stage, sampling, renders of views
``render``         `photoreal diffrender render`: a benchmark's views or a scene's sensors (torch loads inside)
``decomposition``  intrinsic decomposition network (image → A, I, S, N) trained on procedural Mitsuba scenes
``settings``       the settings and source names (no torch: loaded with the package; the rest on first use)
=================  ==========================================================================

The model itself is the shared core of :mod:`generative.diffusion`. `photoreal diffrender` and
`photoreal bench diffrender` use only the names below.
"""

from foundation.lazy import lazy_names

from .settings import (DECOMPOSED, DecompDataSettings, DecompSettings, DiffRenderSettings, GBufferSettings,
    SampleSettings, TRAIN_SOURCES, TRUTH)

#: every other name loads its module (and torch) on first use: `photoreal … --help` never does
__getattr__, __dir__ = lazy_names(__name__, {
    "decomposition": ("decompose", "heldout_psnr", "load_decomp_data", "load_decomposer", "photographs",
        "train_decomposer",),
    "renderer": ("IntrinsicViews", "load_diffrender", "load_intrinsic_views", "render_gbuffers", "render_views",
        "train_diffrender", "with_truth_layers",),
    "render": ("render_benchmark", "render_scene_file",),
})

__all__ = [
    "DECOMPOSED", "TRAIN_SOURCES", "TRUTH", "DecompDataSettings", "DecompSettings", "DiffRenderSettings",
    "GBufferSettings", "IntrinsicViews", "SampleSettings", "decompose", "heldout_psnr", "load_decomp_data",
    "load_decomposer", "load_diffrender", "load_intrinsic_views", "photographs", "render_benchmark",
    "render_gbuffers", "render_scene_file", "render_views", "train_decomposer", "train_diffrender",
    "with_truth_layers",
]
