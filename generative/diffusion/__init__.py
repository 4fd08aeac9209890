"""Diffusion models of seeds 000, 002 and 003, one family on one core.

=================  ==========================================================================
module             what
=================  ==========================================================================
``core``           config, conditional pixel-space UNet (diffusers), v-prediction loss, DDIM + CFG
``renderer``       intrinsic-conditioned diffusion renderer: G-buffer data, training stage, sampling
``decomposition`` intrinsic decomposition network (image → A, I, S, N) trained on procedural Mitsuba scenes
``material_data``  seed 002's generative dataset: many fitted neural materials, path-traced swatches, keywords
``materials``      diffusion over [T_off ‖ T_rgb] (circular, shifted cosine, Min-SNR, cube root, multiscale, CFG)
``material_eval``  family classifier, feature spaces, baselines, aligned ꟻLIP, seam ratio
``face_data``      seed 003's instances: one scan multiplied (identity, skin, relief, warps, poses, HDRIs)
``face_models``    completion diffusion (the backbone), LoRA decomposition with cross-intrinsic attention, 2× SR
``face_eval``      the optimisation baseline, the learned pipeline stage by stage, map and relighting scores
``face_run``       `photoreal face train-models`: one resumable run folder; the learned stages for from-photo
=================  ==========================================================================

Other features and the application use only the names below.
"""

from .core import (ConditionalDiffusion, DiffusionConfig, count_parameters, diffusion_loss, make_scheduler, sample,
                   training_flops)
from .decomposition import (DecompDataSettings, DecompResult, DecompSettings, Decomposer, decompose, heldout_psnr,
                        load_decomp_data, load_decomposer, photographs, procedural_scene, render_decomp_data,
                        train_decomposer)
from .renderer import (DECOMPOSED, GLOBAL_SOURCES, TRAIN_SOURCES, TRUTH, truth_gbuffers, with_truth_layers, condition_to_layers, from_target_space, intrinsic_layers, target_space, LAYERS, DiffRenderOutput, DiffRenderResult, DiffRenderSettings, GBufferSettings, IntrinsicViews,
                       SampleSettings, global_condition, load_diffrender, load_intrinsic_views, local_condition,
                       model_to_photo, photo_to_model, render_benchmark, render_gbuffers, render_scene_file,
                       render_views, train_diffrender)

from .material_data import (VOCABULARY, MaterialDataSettings, MaterialSet, build_material_dataset, decode_swatches,
                            load_material_dataset, parse_keywords)
from .material_eval import (ClassifierSettings, aligned_flip, classify, copy_baseline, crop_baseline, decode_all,
                            denoising_check, family_gaussian_baseline, gaussian_baseline, mean_pairwise, mnv2_features,
                            nearest_distances, phase_randomised_baseline, random_roll, seam_ratio,
                            train_classifier)
from .face_data import FaceDataSettings, FaceSet, build_face_dataset, load_face_dataset, scan_path
from .face_eval import LearnedModels, baseline_maps, default_maps, learned_maps, map_scores, relit_scores
from .face_models import DecompSettings as FaceDecompSettings
from .face_models import load_decomposer as load_face_decomposer
from .face_models import train_decomposer as train_face_decomposer
from .face_models import (VARIANTS, CompletionSettings, SuperResSettings, at_resolution, complete, decompose_maps,
                          load_completion, load_superres, normalise_albedo, upscale)
from .face_run import FaceModelsSettings, completion_albedo, load_face_models, photo_maps_fn, train_face_models
from .materials import (MaterialPrompt, MatDiffSettings, data_digest, from_model_space, generate_material, load_matdiff,
                        prior_keywords, run_sampler, sample_materials, save_keyword_prior, save_sampler, split_features,
                        to_model_space, train_matdiff)

__all__ = [
    "FaceDataSettings", "FaceSet", "build_face_dataset", "load_face_dataset", "scan_path", "LearnedModels",
    "baseline_maps", "default_maps", "learned_maps", "map_scores", "relit_scores", "VARIANTS", "CompletionSettings",
    "FaceDecompSettings", "SuperResSettings", "at_resolution", "complete", "decompose_maps", "load_completion",
    "load_face_decomposer", "train_face_decomposer", "load_superres", "normalise_albedo", "upscale",
    "FaceModelsSettings", "completion_albedo", "load_face_models",
    "photo_maps_fn", "train_face_models",
    "VOCABULARY", "MaterialDataSettings", "MaterialSet", "build_material_dataset", "decode_swatches",
    "load_material_dataset", "parse_keywords", "ClassifierSettings", "aligned_flip", "classify", "copy_baseline",
    "denoising_check", "family_gaussian_baseline", "phase_randomised_baseline", "random_roll", "crop_baseline",
    "decode_all", "gaussian_baseline", "mean_pairwise", "mnv2_features", "nearest_distances",
    "seam_ratio", "train_classifier", "MaterialPrompt", "MatDiffSettings", "data_digest", "generate_material", "load_matdiff",
    "prior_keywords", "run_sampler", "sample_materials", "save_keyword_prior", "save_sampler", "split_features", "train_matdiff", "to_model_space", "from_model_space",
    "DECOMPOSED", "DecompDataSettings", "DecompResult", "DecompSettings", "Decomposer", "condition_to_layers", "decompose",
    "from_target_space", "heldout_psnr", "intrinsic_layers", "load_decomp_data", "load_decomposer", "photographs",
    "procedural_scene", "render_decomp_data", "target_space", "train_decomposer",
    "ConditionalDiffusion", "DiffRenderOutput", "DiffRenderResult", "DiffRenderSettings", "DiffusionConfig", "GBufferSettings",
    "GLOBAL_SOURCES", "IntrinsicViews", "LAYERS", "SampleSettings", "count_parameters", "diffusion_loss",
    "global_condition", "load_diffrender", "load_intrinsic_views", "local_condition", "make_scheduler",
    "model_to_photo", "photo_to_model", "render_benchmark", "render_gbuffers", "TRAIN_SOURCES", "TRUTH", "truth_gbuffers", "with_truth_layers", "render_scene_file", "render_views", "sample",
    "train_diffrender",
    "training_flops",
]
