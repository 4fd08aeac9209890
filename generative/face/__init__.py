"""Learned face stages (seed 003) in UV space: completion, decomposition and super-resolution.

================  ===========================================================================
module            what
================  ===========================================================================
``data``           training instances: one scan multiplied (identity, skin, relief, warps, poses, HDRIs)
``encoding``       the models' shared encodings of maps, lit textures and conditions
``completion``     completion diffusion (§2): the backbone
``decomposition``  LoRA decomposition with cross-intrinsic attention (§3)
``superres``       2× super-resolution of the maps (§4)
``evaluate``       the optimisation baseline, the learned pipeline stage by stage, map and relighting scores
``run``            `photoreal face train-models`: one resumable run folder; the learned stages for from-photo
``settings``      the learned stages' settings (no torch: loaded with the package; the rest on first use)
================  ===========================================================================

They serve :mod:`inverse.face` (the fit and `face from-photo`), whose UV-space shader their losses share.
`photoreal face train-models|from-photo` and `photoreal bench face-learned` use only the names below.
"""

from foundation.lazy import lazy_names

from .data import FaceDataSettings, load_face_dataset, scan_path
from .settings import CompletionSettings, DecompSettings, FaceModelsSettings, SuperResSettings
from .encoding import at_resolution, normalise_albedo

#: every other name loads its module (and torch) on first use: `photoreal … --help` never does
__getattr__, __dir__ = lazy_names(__name__, {
    "evaluate": ("LearnedModels", "baseline_maps", "default_maps", "learned_maps", "map_scores", "relit_scores",),
    "completion": ("complete", "load_completion",),
    "decomposition": ("decompose_maps", "load_decomposer", "train_decomposer",),
    "superres": ("load_superres", "upscale",),
    "run": ("completion_albedo", "load_face_models", "photo_maps_fn", "train_face_models",),
})

__all__ = [
    "CompletionSettings", "DecompSettings", "FaceDataSettings", "FaceModelsSettings", "LearnedModels",
    "SuperResSettings", "at_resolution", "baseline_maps", "complete", "completion_albedo", "decompose_maps",
    "default_maps", "learned_maps", "load_completion", "load_decomposer", "load_face_dataset", "load_face_models",
    "load_superres", "map_scores", "normalise_albedo", "photo_maps_fn", "relit_scores", "scan_path",
    "train_decomposer", "train_face_models", "upscale",
]
