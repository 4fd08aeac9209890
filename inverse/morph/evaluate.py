"""Scoring a morph against the benchmark's ground truth: geometry (Chamfer, normals, spikes, folds)
and held-out photos (the thesis' image metrics on views never fitted)."""

from __future__ import annotations

from dataclasses import KW_ONLY, dataclass
from pathlib import Path

import numpy as np

import mi_plugins  # noqa: F401
import mitsuba as mi

from foundation import imageio
from foundation.mesh import load_mesh_any, write_ply
from foundation.mesh_metrics import chamfer, facing_against_truth, spikes, truth_surface
from foundation.metrics import ImageMetrics, image_metrics

from .benchmark import MorphBenchmark, sensor_dict
from .scene import camera_centre, morph_scene, photo_at, set_flash


@dataclass
class MorphEvaluation:
    chamfer_input: float
    chamfer_morphed: float
    chamfer_reduction: float  #: 1 − morphed / input
    normal_consistency_input: float
    normal_consistency_morphed: float
    psnr_heldout_input: float
    psnr_heldout_morphed: float
    heldout_input: ImageMetrics  #: mean over the held-out views, coarse input rendered
    heldout_morphed: ImageMetrics
    #: vertices whose displacement departs from their 1-ring's mean displacement by more than 3× their local
    #: edge length (see foundation.mesh_metrics.spikes); −1 when remeshing during the run broke the per-vertex
    #: correspondence with the start
    spike_vertices: int
    inverted_triangles: int  #: triangles flipped w.r.t. the start of the optimisation (folds), −1 as above
    spikes: int  #: both
    #: triangles facing against the ground truth at the truth's nearest surface point: the result, the coarse
    #: input and the mesh the optimisation started from (the input remeshed); counts and area fractions
    facing_against_truth: int
    facing_against_truth_input: int
    scene_size: float
    _: KW_ONLY  # added later: results written before them still load
    far_moved_vertices: int = -1  #: vertices moved more than 3× their edge length at all (−1 as above)
    facing_against_truth_start: int = -1
    facing_against_truth_area: float = float("nan")
    facing_against_truth_area_input: float = float("nan")
    facing_against_truth_area_start: float = float("nan")
    #: the ImageNet MobileNetV2 distance of the held-out renders (captures; NaN where not measured)
    perceptual_heldout_input: float = float("nan")
    perceptual_heldout_morphed: float = float("nan")
    #: captures: the held-out scores over the object's region only (the pixels either mesh covers; NaN elsewhere) and
    #: that region's share of the photos
    object_share: float = float("nan")
    psnr_object_input: float = float("nan")
    psnr_object_morphed: float = float("nan")
    flip_object_input: float = float("nan")
    flip_object_morphed: float = float("nan")


def heldout_renders(bench, meshes: dict, light, res: int, out: Path, max_depth: int,
                    gain=None, flash=None, flash_weight: float = 1.0) -> dict[str, list[tuple[np.ndarray, np.ndarray]]]:
    """Per mesh (``name: (v, f, colours, mode)``), its render and the photo at every held-out camera: ``path`` at
    ``max_depth``, 32 spp, seed = view index, under ``light`` (an HDRI or a fitted envmap dict), times ``gain(i)``
    where given; 'lit' meshes also under a flash at the camera of RGB intensity ``flash(i)`` where given, with
    sampling weight ``flash_weight`` (:func:`~inverse.morph.scene.set_flash`). The first held-out view's renders and
    photo are written to ``out`` as PNGs."""
    meta = bench.meta
    result: dict[str, list] = {}
    for name, (v, f, c, mode) in meshes.items():
        ply = out / f".eval_{name}.ply"
        write_ply(ply, v, f, c)
        lit_by_flash = flash is not None and mode == "lit"
        scene = morph_scene(ply, mode, light, integrator={"type": "path", "max_depth": max_depth}, flash=lit_by_flash)
        params = mi.traverse(scene) if lit_by_flash else None
        result[name] = []
        for i in meta.test:
            if lit_by_flash:
                set_flash(params, camera_centre(meta.cameras[i]), flash(i), flash_weight)
                params.update()
            sensor = mi.load_dict(sensor_dict(meta.cameras[i], res, meta.fov))
            img = np.array(mi.render(scene, sensor=sensor, spp=32, seed=int(i)))[..., :3]
            if gain is not None:
                img = img * gain(i)
            ref = photo_at(bench, i, res)
            result[name].append((img, ref))
            if i == meta.test[0]:
                imageio.write_png(out / f"heldout_{name}_view{i:02d}.png", img)
                imageio.write_png(out / f"heldout_photo_view{i:02d}.png", ref)
        del scene
        ply.unlink(missing_ok=True)
    return result


def start_spikes(v0, f0, v_out, f_out) -> dict:
    """Spikes and folds of the result against the mesh the optimisation started from (``v0``, ``f0``); −1 each when
    remeshing during the run broke the per-vertex correspondence."""
    if len(v0) == len(v_out) and np.array_equal(f0, f_out):
        return spikes(v0, v_out, f_out)
    return {"spike_vertices": -1, "far_moved_vertices": -1, "inverted_triangles": -1, "spikes": -1}


def evaluate_morph(bench: MorphBenchmark, v_in, f_in, c_in, v_out, f_out, c_out, mode: str, res: int,
                   out: Path, start: tuple[np.ndarray, np.ndarray] | None = None) -> MorphEvaluation:
    """Chamfer / normal consistency to the ground truth, spikes, and held-out image metrics.

    Held-out renders: ``path`` (max depth 3), 32 spp, seed = view index. Spikes and inverted
    triangles compare the result with the mesh the optimisation started from (``start``, default
    the input), which has the same topology unless remeshing happened during the run.
    """
    meta = bench.meta
    gv, gf = load_mesh_any(bench.ground_truth)
    ch_in = chamfer(v_in, f_in, gv, gf)
    ch_out = chamfer(v_out, f_out, gv, gf)
    renders = heldout_renders(bench, {"input": (v_in, f_in, c_in, mode), "morphed": (v_out, f_out, c_out, mode)},
                              meta.hdri, res, out, max_depth=3)
    mean = {n: ImageMetrics.mean([image_metrics(img, ref) for img, ref in pairs]) for n, pairs in renders.items()}
    v0, f0 = start if start is not None else (v_in, f_in)
    sp = start_spikes(v0, f0, v_out, f_out)
    truth = truth_surface(gv, gf)
    fa_out, fa_in = facing_against_truth(v_out, f_out, truth), facing_against_truth(v_in, f_in, truth)
    fa_start = fa_in if start is None else facing_against_truth(v0, f0, truth)
    return MorphEvaluation(
        chamfer_input=ch_in["chamfer"], chamfer_morphed=ch_out["chamfer"],
        chamfer_reduction=1.0 - ch_out["chamfer"] / ch_in["chamfer"],
        normal_consistency_input=ch_in["normal_consistency"],
        normal_consistency_morphed=ch_out["normal_consistency"],
        psnr_heldout_input=mean["input"].psnr, psnr_heldout_morphed=mean["morphed"].psnr,
        heldout_input=mean["input"], heldout_morphed=mean["morphed"],
        spike_vertices=sp["spike_vertices"], inverted_triangles=sp["inverted_triangles"], spikes=sp["spikes"],
        far_moved_vertices=sp["far_moved_vertices"],
        facing_against_truth=fa_out["count"], facing_against_truth_area=fa_out["area_fraction"],
        facing_against_truth_input=fa_in["count"], facing_against_truth_area_input=fa_in["area_fraction"],
        facing_against_truth_start=fa_start["count"], facing_against_truth_area_start=fa_start["area_fraction"],
        scene_size=meta.scene_size)
