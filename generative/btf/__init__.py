"""Material diffusion (seed 002): new neural BTF materials from keywords and/or an exemplar photo.

============  ================================================================================
module        what
============  ================================================================================
``data``      the generative dataset: many fitted neural materials, path-traced swatches, keywords
``model``     diffusion over [T_off ‖ T_rgb] (circular, shifted cosine, Min-SNR, cube root, multiscale, CFG)
``train``     its training on the shared loop; the run's keyword prior and chosen sampler
``sample``    materials from prompts (keywords, an exemplar photo)
``commands``  `photoreal btf train-diffusion` and `generate` (torch loads inside them)
``evaluate``  family classifier, feature spaces, baselines, aligned ꟻLIP, seam ratio
``settings``  the model's and the classifier's settings (no torch: loaded with the package)
============  ================================================================================

The materials it makes are those of :mod:`inverse.btf` (the same universal basis) and load in the
``neural_btf`` plugin. `photoreal btf dataset|train-diffusion|generate` and `photoreal bench matdiff` use only
the names below.
"""

from foundation.lazy import lazy_names

from .data import MaterialDataSettings, build_material_dataset, load_material_dataset
from .settings import ClassifierSettings, MatDiffSettings

#: every other name loads its module (and torch) on first use: `photoreal … --help` never does
__getattr__, __dir__ = lazy_names(__name__, {
    "evaluate": ("aligned_flip", "classify", "copy_baseline", "crop_baseline", "decode_all", "denoising_check",
        "family_gaussian_baseline", "gaussian_baseline", "mean_pairwise", "mnv2_features", "nearest_distances",
        "phase_randomised_baseline", "random_roll", "seam_ratio", "train_classifier",),
    "model": ("from_model_space", "to_model_space",),
    "sample": ("MaterialPrompt", "sample_materials",),
    "commands": ("generate_material", "train_matdiff",),
    "train": ("data_digest", "load_matdiff", "save_keyword_prior", "save_sampler",),
})

__all__ = [
    "ClassifierSettings", "MatDiffSettings", "MaterialDataSettings", "MaterialPrompt", "aligned_flip",
    "build_material_dataset", "classify", "copy_baseline", "crop_baseline", "data_digest", "decode_all",
    "denoising_check", "family_gaussian_baseline", "from_model_space", "gaussian_baseline", "generate_material",
    "load_material_dataset", "load_matdiff", "mean_pairwise", "mnv2_features", "nearest_distances",
    "phase_randomised_baseline", "random_roll", "sample_materials", "save_keyword_prior", "save_sampler",
    "seam_ratio", "to_model_space", "train_classifier", "train_matdiff",
]
