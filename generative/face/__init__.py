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
================  ===========================================================================

They serve :mod:`inverse.face` (the fit and `face from-photo`), whose UV-space shader their losses share.
`photoreal face train-models|from-photo` and `photoreal bench face-learned` use only the names below.
"""

from .data import FaceDataSettings, load_face_dataset, scan_path
from .evaluate import LearnedModels, baseline_maps, default_maps, learned_maps, map_scores, relit_scores
from .completion import CompletionSettings, complete, load_completion
from .decomposition import DecompSettings, decompose_maps, load_decomposer, train_decomposer
from .encoding import at_resolution, normalise_albedo
from .superres import SuperResSettings, load_superres, upscale
from .run import FaceModelsSettings, completion_albedo, load_face_models, photo_maps_fn, train_face_models

__all__ = [
    "CompletionSettings", "DecompSettings", "FaceDataSettings", "FaceModelsSettings", "LearnedModels",
    "SuperResSettings", "at_resolution", "baseline_maps", "complete", "completion_albedo", "decompose_maps",
    "default_maps", "learned_maps", "load_completion", "load_decomposer", "load_face_dataset", "load_face_models",
    "load_superres", "map_scores", "normalise_albedo", "photo_maps_fn", "relit_scores", "scan_path",
    "train_decomposer", "train_face_models", "upscale",
]
