"""Geometry morphing (REAL-DIBS §4): per-vertex positions and colours of a coarse mesh fitted to photos.

=================  ==========================================================================
module             what
=================  ==========================================================================
``benchmark``      benchmarks with ground truth: photos, degraded reconstruction, artifact masks
``cameras``        a benchmark's cameras: drone orbit, framing, Mitsuba sensors
``village``        the procedural village scene, colours for meshes without any
``scene``          the scene a morph renders (vertex colours under the benchmark's HDRI)
``settings``       the settings of a run (:class:`MorphSettings`)
``stage``          the morph (large steps, planarity prior) as a stage of the shared loop
``select``         the choices the validation photos make (λ, priors, step, light), each from the same start
``results``        what a run records: trace, decisions, the result
``run``            :func:`run_morph`: the choices where the settings leave any, then the stage
``prior``          edge-preserving planarity prior and plane detection
``mesh_edit``      isotropic remeshing, undoing and repairing folds
``gcn``            the shape-aware GCN variant, trained through the renderer (``dr.wrap``)
``evaluate``       Chamfer, normals, spikes, folds and held-out image metrics
``errors``         where a mesh lies against the truth: both Chamfer directions, border, input error left, maps
``batch``          a morph run by paths (the unit batches fan out to workers)
``views``          both meshes of a result rendered at every camera, cached (what the GAN and diffrender read)
``export``         a run's mesh as glTF/OBJ: UV atlas, texture baked from the photos or the colours, held-out scores
=================  ==========================================================================

Other features use only the names below.
"""

from .benchmark import (TRUTH_NORMALS, ARTIFACT_REGIONS, Camera, MorphBenchmark, MorphBenchmarkMeta, MorphBenchmarkSettings,
                        artifact_masks, benchmark_capture, load_morph_benchmark, make_morph_benchmark, sensor_dict,
                        silhouette_margins,
                        truth_scene, truth_start_benchmark)
from .evaluate import MorphEvaluation, evaluate_morph
from .errors import ErrorReport, SurfaceErrors, benchmark_errors, benchmark_surface_errors, surface_errors
from .prior import dihedral_pairs, dominant_plane_fraction, planarity_prior
from .mesh_edit import (PleatReport, RepairReport, SpikeReport, TurnReport, border_zone, iron_border_turns, iron_spikes,
                        remesh, repair_flips, unfold_pleats)
from .batch import load_result, run_item
from .results import (Candidate, ColourPriorDecision, ColourSelection, MorphResult, PlanarityDecision, StepSelection,
                      TracePoint)
from .run import run_morph
from .capture_input import CAPTURE_FIT_WIDTH, CaptureBenchmark, evaluate_capture_morph, is_capture, load_morph_input
from .results import ModeSelection, PhotoFit
from .select import candidate_settings, light_choice_draws
from .settings import MORPH_SEED_MAX, PLANARITY_WHERE, PRIOR_TIES, MorphSettings
from .stage import MorphStage, start_mesh
from .suite import SUITE, KINDS, UNSEEN, suite_mesh
from .views import morph_views
from .scene import (MODES, mask_integrator, mask_scene, morph_scene, photo_at, photo_masks, projective_integrator,
                    render_views, saturated_silhouette)

# The GCN variant is the one part that needs torch: it loads on first use, so `import inverse.morph` (and
# `photoreal morph … --help`) stays free of it.
_LAZY = {"GCNSettings": "gcn", "gcn_settings": "gcn", "run_gcn_morph": "gcn"}


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(f"{__name__}.{_LAZY[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


from .export import MorphExport, export_morph, find_input

__all__ = [
    "MorphExport", "export_morph", "find_input",
    "MORPH_SEED_MAX", "PLANARITY_WHERE", "PRIOR_TIES", "TRUTH_NORMALS", "ARTIFACT_REGIONS", "Camera", "ErrorReport", "SurfaceErrors", "benchmark_errors", "benchmark_surface_errors", "surface_errors", "Candidate", "ColourPriorDecision", "ColourSelection", "GCNSettings", "MODES", "MorphBenchmark", "MorphBenchmarkMeta",
    "MorphBenchmarkSettings", "MorphEvaluation", "MorphResult", "MorphSettings", "MorphStage", "PlanarityDecision",
    "RepairReport", "StepSelection", "artifact_masks", "candidate_settings", "light_choice_draws", "dihedral_pairs", "dominant_plane_fraction", "evaluate_morph", "load_result",
    "benchmark_capture", "load_morph_benchmark", "make_morph_benchmark", "mask_integrator", "morph_scene", "photo_at", "planarity_prior", "projective_integrator", "remesh",
    "render_views", "repair_flips", "run_gcn_morph", "gcn_settings", "run_item", "run_morph", "sensor_dict", "start_mesh",
    "KINDS", "UNSEEN", "PleatReport", "SpikeReport", "iron_spikes", "SUITE", "TracePoint", "silhouette_margins", "saturated_silhouette", "suite_mesh", "truth_scene",
    "truth_start_benchmark", "TurnReport", "border_zone", "iron_border_turns",
    "unfold_pleats", "mask_scene", "photo_masks", "morph_views",
    "CAPTURE_FIT_WIDTH", "CaptureBenchmark", "evaluate_capture_morph", "is_capture", "load_morph_input",
    "ModeSelection", "PhotoFit",
]
