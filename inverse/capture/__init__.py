"""Real captures in: one capture format (photos, pinhole cameras, an optional coarse mesh, masks, points, a held-out
split, a ground truth), importers of COLMAP models, ``transforms.json`` and LLFF, structure from motion on the CPU,
exports back to those formats. A shared core of the inverse layer: features build on it, it uses none of them.

========================  =============================================================
module                    what
========================  =============================================================
``format``                the capture folder, its cameras (COLMAP axes), Mitsuba sensors, the split
``sources``               readers of COLMAP (pycolmap), transforms.json, LLFF → photos + the tool's cameras
``build``                 a source → a capture: linear photos, area resize, undistortion, masks, mesh
``coarse``                the tool's mesh (OBJ+MTL, PLY, GLB), a Poisson mesh of sparse points, a visual hull
``align``                 similarity alignment of recovered cameras to known ones (Umeyama)
``backdrop``              masks from a uniform backdrop, and the test of whether the photos have one
``sfm``                   structure from motion and triangulation with known cameras (pycolmap)
``export``                a capture → COLMAP, transforms.json, LLFF
``scores``                held-out photos against renders of a mesh (PSNR, SSIM, ꟻLIP, MobileNetV2)
========================  =============================================================
"""

from .align import camera_errors, similarity
from .backdrop import BackdropDecision, backdrop_mask, decide_backdrop
from .build import area_resize, import_capture, undistort
from .coarse import coarse_mesh_from_points, load_coarse_mesh, visual_hull
from .export import FORMATS, export_capture
from .format import (FORMAT, HELD_OUT_EVERY, MARKER, MITSUBA_FROM_COLMAP, Capture, CaptureCamera, CaptureMeta,
                     check_camera,
                     load_capture, sensor, split)
from .scores import colour_from_photos, heldout_scores, project_photos, render_mesh
from .sfm import SfmSettings, focal_prior, run_sfm, triangulate_known
from .sources import Source, SourceFrame, camera, read_colmap, read_llff, read_source, read_transforms

__all__ = ["FORMAT", "FORMATS", "HELD_OUT_EVERY", "MARKER", "MITSUBA_FROM_COLMAP", "BackdropDecision", "Capture", "CaptureCamera", "CaptureMeta", "SfmSettings",
           "Source", "SourceFrame", "area_resize", "backdrop_mask", "camera", "camera_errors", "check_camera", "coarse_mesh_from_points", "colour_from_photos", "decide_backdrop", "project_photos",
           "export_capture", "focal_prior", "heldout_scores", "import_capture", "load_capture", "load_coarse_mesh", "read_colmap",
           "read_llff", "read_source", "read_transforms", "render_mesh", "run_sfm", "sensor", "similarity", "split", "triangulate_known",
           "undistort", "visual_hull"]
