"""Face materials in UV space (seed 003): benchmarks from scans, fitting through the UV-space GGX shader,
and one photograph to a relightable face.

=============  ===========================================================================
module         what
=============  ===========================================================================
``benchmark``  ground-truth maps + Mitsuba observations from a textured scan
``uv_bake``    UV-space geometry maps (position, normal, tangent) through Mitsuba's own parameterisation
``fit``        the pyramid fit through the UV-space shader (a stage of the shared loop), metrics
``refine``     the refinement through full Mitsuba renders
``batch``      `photoreal face fit` by paths (the unit a batch of benchmarks fans out)
``photo``      landmarks → template fit → unwrap → fill → delight → relight
=============  ===========================================================================

Other features use only the names below.
"""

from .benchmark import (FaceBenchmark, FaceBenchmarkMeta, FaceBenchmarkSettings, HeldoutCamera, Light, normals_from_height,
                        orbit_direction, scan_frame, scan_scene, scan_texture, skin_relief, smooth_noise,
                        key_light, load_benchmark, make_benchmark, render_heldout, texel_observation,
                        MARKER as BENCHMARK_MARKER, environment_transfer, rendered_maps)
from .batch import FaceFitReport, fit_benchmark_dir, fit_benchmark_item
from .fit import (FaceFitMetrics, FaceFitResult, FaceFitSettings, RelitMetrics, evaluate_fit, fill_unobserved, fit_face,
                  integrate_normals, save_maps)
from .refine import RenderRefineSettings, refine_through_renders
from .photo import (TEMPLATE, DelitTexture, PhotoFaceResult, PhotoFitSettings, fill_and_delight, check_landmarks, detect_landmarks, fit_template, load_landmarks,
                    photo_to_face)
from .register import ScanRegistration, frontal_render, register_scan
from .uv_bake import GeometryMaps, bake_geometry, texel_uvs

from .export import FaceExport, export_face, face_result

__all__ = [
    "FaceExport", "export_face", "face_result",
    "DelitTexture", "fill_and_delight", "normals_from_height", "orbit_direction", "scan_frame", "scan_scene",
    "scan_texture", "skin_relief", "smooth_noise", "key_light", "texel_observation", "ScanRegistration",
    "frontal_render", "register_scan", "TEMPLATE",
    "FaceBenchmark", "FaceBenchmarkMeta", "FaceBenchmarkSettings", "FaceFitMetrics", "FaceFitReport", "FaceFitResult",
    "FaceFitSettings", "GeometryMaps", "HeldoutCamera", "Light", "PhotoFaceResult", "PhotoFitSettings", "RelitMetrics",
    "RenderRefineSettings", "bake_geometry", "check_landmarks", "detect_landmarks", "evaluate_fit", "fill_unobserved",
    "fit_benchmark_dir", "fit_benchmark_item", "fit_face", "fit_template", "integrate_normals", "load_benchmark", "load_landmarks",
    "make_benchmark", "BENCHMARK_MARKER", "environment_transfer", "rendered_maps", "photo_to_face",
    "refine_through_renders", "render_heldout", "save_maps", "texel_uvs",
]
