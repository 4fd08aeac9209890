"""Scoring a morph against the benchmark's ground truth: geometry (Chamfer, normals, spikes, folds)
and held-out photos (the thesis' image metrics on views never fitted)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

import mi_plugins  # noqa: F401
import mitsuba as mi

from foundation import imageio
from foundation.mesh import load_mesh_any, write_ply
from foundation.mesh_metrics import chamfer, inverted_triangles, spikes
from foundation.metrics import ImageMetrics, image_metrics

from .benchmark import MorphBenchmark, sensor_dict
from .scene import morph_scene, photo_at


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
    #: vertices moved more than 3× their local edge length; −1 when remeshing during the run broke the
    #: per-vertex correspondence with the start
    spike_vertices: int
    inverted_triangles: int  #: triangles flipped w.r.t. the start of the optimisation (folds), −1 as above
    spikes: int  #: both
    facing_against_truth: int  #: triangles facing against the ground truth at their nearest truth triangle
    facing_against_truth_input: int
    scene_size: float


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
    per: dict[str, list[ImageMetrics]] = {"input": [], "morphed": []}
    for name, (v, f, c) in {"input": (v_in, f_in, c_in), "morphed": (v_out, f_out, c_out)}.items():
        ply = out / f".eval_{name}.ply"
        write_ply(ply, v, f, c)
        scene = morph_scene(ply, mode, meta.hdri, integrator={"type": "path", "max_depth": 3})
        for i in meta.test:
            sensor = mi.load_dict(sensor_dict(meta.cameras[i], res, meta.fov))
            img = np.array(mi.render(scene, sensor=sensor, spp=32, seed=int(i)))[..., :3]
            ref = photo_at(bench, i, res)
            per[name].append(image_metrics(img, ref))
            if i == meta.test[0]:
                imageio.write_png(out / f"heldout_{name}_view{i:02d}.png", img)
                imageio.write_png(out / f"heldout_photo_view{i:02d}.png", ref)
        del scene
        ply.unlink(missing_ok=True)
    mean = {n: ImageMetrics.mean(ms) for n, ms in per.items()}
    v0, f0 = start if start is not None else (v_in, f_in)
    if len(v0) == len(v_out) and np.array_equal(f0, f_out):
        sp = spikes(v0, v_out, f_out, gv, gf)
    else:  # remeshed during the run: no per-vertex displacement to judge
        sp = {"spike_vertices": -1, "inverted_triangles": -1, "spikes": -1,
              "facing_against_truth": inverted_triangles(v_out, f_out, gv, gf)}
    return MorphEvaluation(
        chamfer_input=ch_in["chamfer"], chamfer_morphed=ch_out["chamfer"],
        chamfer_reduction=1.0 - ch_out["chamfer"] / ch_in["chamfer"],
        normal_consistency_input=ch_in["normal_consistency"],
        normal_consistency_morphed=ch_out["normal_consistency"],
        psnr_heldout_input=mean["input"].psnr, psnr_heldout_morphed=mean["morphed"].psnr,
        heldout_input=mean["input"], heldout_morphed=mean["morphed"],
        spike_vertices=sp["spike_vertices"], inverted_triangles=sp["inverted_triangles"], spikes=sp["spikes"],
        facing_against_truth=sp["facing_against_truth"],
        facing_against_truth_input=inverted_triangles(v_in, f_in, gv, gf), scene_size=meta.scene_size)
