"""The learned face stages against the optimisation baseline, on instances whose ground truth is known.

* :func:`baseline_maps` — today's pipeline (:func:`inverse.face.fill_and_delight`): mirror + harmonic fill of the
  lit texture, albedo = texture ÷ fitted white shading; normal, roughness and specular are the template's
  defaults (flat, 0.5, 0.35);
* :func:`learned_maps` — completion (diffusion) → decomposition (LoRA + cross-intrinsic attention) →
  super-resolution, any prefix of it (the rest from the baseline's defaults or bicubic), so stages can be
  judged one by one;
* :func:`map_scores` — albedo PSNR over the texels the photo saw and over those it did not (after one global
  scale fitted on the seen texels: lighting's absolute level is unknowable from a photo), normal angle error,
  roughness and specular MAE;
* :func:`relit_scores` — the maps rendered by Mitsuba (``ggx_uv``, path traced) on the scan under other HDRIs
  from the front, against the same render of the true maps: PSNR and ꟻLIP over the face pixels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .data import FaceSet, mesh_of

DEFAULTS = {"roughness": 0.5, "specular": 0.35}  #: the template's skin defaults (inverse.face.PhotoFitSettings)


def default_maps(albedo: np.ndarray) -> dict[str, np.ndarray]:
    """Template defaults around an albedo (N, H, W, 3): flat normal, constant roughness and specular."""
    shape = albedo.shape[:3]
    normal = np.zeros(shape + (3,), np.float32)
    normal[..., 2] = 1.0
    return {"albedo": albedo.astype(np.float32), "normal": normal,
            "roughness": np.full(shape + (1,), DEFAULTS["roughness"], np.float32),
            "specular": np.full(shape + (1,), DEFAULTS["specular"], np.float32)}


def geometry_of(d: FaceSet, i: int):
    from inverse.face import GeometryMaps

    g = d.geometry
    return GeometryMaps(position=g["position"][i], normal=g["normal_geo"][i], tangent=g["tangent"][i],
                        bitangent_sign=g["bitangent_sign"][i], mask=d.mask[i],
                        texel_size=np.zeros(d.mask[i].shape + (2,), np.float32))


def baseline_maps(d: FaceSet) -> dict[str, np.ndarray]:
    """The optimisation baseline of every instance (its albedo is computed with the instance: ``d.baseline``)."""
    return default_maps(d.baseline)


@dataclass
class LearnedModels:
    """Loaded models of a ``photoreal face train-models`` run (any may be None)."""

    completion: object = None
    completion_settings: object = None
    decomposer: object = None
    superres: object = None
    layout: str = "template"  #: the UV layout they were trained in (FaceDataSettings.layout)


def learned_maps(d: FaceSet, m: LearnedModels, stages: str = "full", seed: int = 0,
                 samples: int | None = None) -> dict[str, np.ndarray]:
    """Maps at the set's resolution from the learned stages.

    ``stages``: ``completion`` (learned albedo + template defaults), ``decomposition`` (+ learned maps,
    bicubic to full size) or ``full`` (+ learned super-resolution)."""
    from .completion import complete
    from .decomposition import decompose_maps
    from .encoding import at_resolution
    from .superres import upscale

    cs = m.completion_settings
    albedo = complete(m.completion, cs, d, seed=seed, samples=samples)
    if stages == "completion" or m.decomposer is None:
        maps = default_maps(albedo)
    else:
        maps = decompose_maps(m.decomposer, d, albedo, cs.res)
    if d.res % cs.res:
        raise ValueError(f"the maps ({d.res}²) must be the model's {cs.res}² times a power of two")
    low = at_resolution(d, cs.res)
    while maps["albedo"].shape[1] < d.res:
        first = maps["albedo"].shape[1] == cs.res
        # the learned upscaler knows one step (2×); any further doubling is bicubic
        maps = upscale(m.superres if stages == "full" and first else None, maps, low)
    return maps


def map_scores(pred: dict[str, np.ndarray], gt: dict[str, np.ndarray], seen: np.ndarray, mask: np.ndarray) -> dict:
    """Per-instance means of the map errors (see the module docstring). Arrays (N, H, W, C); seen, mask (N, H, W)."""
    from foundation.metrics import angular_error_deg, global_scale, psnr

    out = {"albedo_psnr_seen": [], "albedo_psnr_unseen": [], "albedo_psnr_all": [], "normal_err_deg": [],
           "normal_err_deg_unseen": [], "roughness_mae": [], "specular_mae": []}
    for i in range(len(mask)):
        m, s = mask[i], seen[i] & mask[i]
        u = m & ~s
        ref = s if s.any() else m
        k = global_scale(pred["albedo"][i][ref], gt["albedo"][i][ref])
        a = np.clip(pred["albedo"][i] * k, 0.0, 1.0)
        out["albedo_psnr_seen"].append(psnr(a[s], gt["albedo"][i][s]) if s.any() else np.nan)
        out["albedo_psnr_unseen"].append(psnr(a[u], gt["albedo"][i][u]) if u.any() else np.nan)
        out["albedo_psnr_all"].append(psnr(a[m], gt["albedo"][i][m]))
        err = angular_error_deg(pred["normal"][i][m], gt["normal"][i][m])
        out["normal_err_deg"].append(float(err.mean()))
        out["normal_err_deg_unseen"].append(float(angular_error_deg(pred["normal"][i][u], gt["normal"][i][u]).mean())
                                            if u.any() else np.nan)
        for k2 in ("roughness", "specular"):
            out[f"{k2}_mae"].append(float(np.abs(pred[k2][i][m] - gt[k2][i][m]).mean()))
    return {k: float(np.nanmean(v)) for k, v in out.items()} | {"instances": int(len(mask))}


def relit_scores(d: FaceSet, maps: dict[str, np.ndarray], hdris: tuple[str, ...], res: int = 128, spp: int = 32,
                 indices=None, images: dict | None = None) -> dict:
    """Render every instance's scan (unwarped: held-out instances only) with ``maps`` and with the true maps under
    each HDRI from the front; PSNR and ꟻLIP over the face pixels, mean over instances and HDRIs. The albedo is
    scaled by the global factor fitted on the seen texels first (as :func:`map_scores`)."""
    from foundation.assets import hdri_label
    from foundation.metrics import flip, global_scale, masked_psnr
    from inverse.face import FaceBenchmarkSettings, orbit_direction, render_heldout, scan_frame
    from foundation.mesh import load_obj

    idx = range(len(d)) if indices is None else indices
    bs = FaceBenchmarkSettings(render_res=res, render_spp=spp)
    ps, fs = [], []
    for i in idx:
        rec = d.records[i]
        if rec["spec"]["warp"]:
            raise ValueError(f"{rec['name']}: relighting needs an unwarped instance (a held-out one)")
        mesh_file = mesh_of(d, i)
        centre, radius, front = scan_frame(load_obj(mesh_file))
        eye = centre + orbit_direction(front, 0.0, 5.0) * 4.0 * radius
        fov = float(np.degrees(2 * np.arctan(1.15 / 4.0)))
        s = d.seen[i] & d.mask[i]
        ref = s if s.any() else d.mask[i]
        k = global_scale(maps["albedo"][i][ref], d.targets["albedo"][i][ref])
        mine = {n: maps[n][i] for n in ("normal", "roughness", "specular")} | {"albedo": np.clip(maps["albedo"][i] * k, 0, 1)}
        true = {n: d.targets[n][i] for n in ("albedo", "normal", "roughness", "specular")}
        for h in hdris:
            img, mask = render_heldout(mesh_file, mine, bs, h, eye, centre, fov)
            gt, _ = render_heldout(mesh_file, true, bs, h, eye, centre, fov)
            ps.append(masked_psnr(img, gt, mask))
            fs.append(flip(img, gt, mask=mask))
            if images is not None:
                images[(rec["name"], hdri_label(h))] = (img, gt)
    return {"psnr": float(np.mean(ps)), "flip": float(np.mean(fs)), "renders": len(ps)}


__all__ = ["DEFAULTS", "LearnedModels", "baseline_maps", "default_maps", "geometry_of", "learned_maps", "map_scores",
           "relit_scores"]
