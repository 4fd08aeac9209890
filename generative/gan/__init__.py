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
``settings``   the stages' settings (no torch: loaded with the package; the rest on first use)
=============  =============================================================================
"""

from foundation.lazy import lazy_names

from .settings import GanDataSettings, GanTrainSettings, JointSettings, MODELS

#: every other name loads its module (and torch) on first use: `photoreal … --help` never does
__getattr__, __dir__ = lazy_names(__name__, {
    "data": ("PairedViews", "load_paired_views", "random_crops", "render_mesh_views", "to_nchw",),
    "joint": ("JointResult", "train_joint",),
    "train": ("CurvePoint", "GanEvaluation", "GanTrainResult", "build_model", "check_resolution", "evaluate_model",
        "load_heldout_predictions", "load_trained", "mean_metrics", "predict", "split_validation", "train_gan",),
})

__all__ = [
    "CurvePoint", "GanDataSettings", "GanEvaluation", "GanTrainResult", "GanTrainSettings", "JointResult",
    "JointSettings", "MODELS", "PairedViews", "build_model", "check_resolution", "evaluate_model",
    "load_heldout_predictions", "load_paired_views", "load_trained", "mean_metrics", "predict", "random_crops",
    "render_mesh_views", "split_validation", "to_nchw", "train_gan", "train_joint",
]
