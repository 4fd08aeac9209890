"""GAN refinement of renders (REAL-DIBS §3, §5, §6): pix2pix, CycleGAN, Morph-GAN, joint training.

=============  =============================================================================
module         what
=============  =============================================================================
``pix2pix``    U-Net generator + 70×70 PatchGAN (λ_L1 = 100)
``cyclegan``   ResNet generators, LSGAN, cycle and identity losses
``morph_gan``  pix2pix on rendered ‖ morphed (eq. 5.2) and the partial variant
``data``       paired views (photos, coarse renders, morphed renders) of a morph benchmark
``train``      two-stage training as a stage of the shared loop, evaluation, model loading
``joint``      one loss through G and the Mitsuba renderer into the mesh (``dr.wrap``)
=============  =============================================================================
"""

from .data import GanDataSettings, PairedViews, load_paired_views, random_crops, render_mesh_views, to_nchw
from .joint import JointResult, JointSettings, train_joint
from .train import (MODELS, CurvePoint, GanEvaluation, GanTrainResult, GanTrainSettings, build_model,
                    check_resolution, evaluate_model, load_heldout_predictions, load_trained, mean_metrics, predict,
                    split_validation, train_gan)

__all__ = [
    "CurvePoint", "GanDataSettings", "GanEvaluation", "GanTrainResult", "GanTrainSettings", "JointResult",
    "JointSettings", "MODELS", "PairedViews", "build_model", "check_resolution", "evaluate_model",
    "load_heldout_predictions", "load_paired_views", "load_trained", "mean_metrics", "predict", "random_crops",
    "render_mesh_views", "split_validation", "to_nchw", "train_gan", "train_joint",
]
