"""Noise-free references of held-out views and distribution metrics (MobileNetV2-KID / FID) against photo sets."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import mi_plugins  # noqa: F401
import mitsuba as mi

from foundation.features import fid, image_features, kid, kid_std, spatial_features
from foundation.files import cached_arrays, file_digest
from foundation.scene import recompose
from generative.diffrender import (GBufferSettings, render_gbuffers)
from inverse.morph import sensor_dict, truth_scene


#: render seeds of the references (seed + view index): apart from the photos' (the benchmark's seed + view) and
#: the bench's G-buffers' (the view index), whose noise they must not share
REFERENCE_SEEDS = {"pbr_morphed_clean": 900_000, "truth_clean": 800_000, "photos_clean": 700_000}


def truth_renders(bench, ids: list[int], spp: int, seed: int) -> np.ndarray:
    """(views, H, W, 3) linear renders of the benchmark's ground truth at held-out views ``ids``, ``spp`` samples,
    render seed ``seed`` + view index."""
    meta = bench.meta
    scene = truth_scene(bench)
    out = []
    for i in ids:
        sensor = mi.load_dict(sensor_dict(meta.cameras[i], meta.resolution, meta.fov))
        out.append(np.array(mi.render(scene, sensor=sensor, spp=spp, seed=seed + int(i)))[..., :3])
    del scene
    return np.stack(out).astype(np.float32)


def references(bench, morph_dir: Path, ids: list[int], spp: int, show_progress: bool = False) -> dict:
    """What the paired targets demand, from renders alone (nothing trained): held-out views ``ids`` of

    * ``pbr_morphed_clean`` — R = A·I + S from the morphed mesh's G-buffers at ``spp`` samples: PBR recomposition
      with its Monte-Carlo noise gone, the most a renderer that only denoises its G-buffers can gain over
      ``pbr_morphed`` (:class:`GBufferSettings` spp, 32);
    * ``truth_clean`` — the ground truth itself, path traced at ``spp`` (:func:`inverse.morph.truth_scene`): a
      perfect renderer of the *true* scene, scored against the benchmark's photos (``photo_spp``) — their noise floor.

    Returns name → (views, H, W, 3) linear images."""
    gs = GBufferSettings(spp=spp)
    L = render_gbuffers(Path(morph_dir) / "morphed.ply", bench, ids, gs, "reference G-buffers", show_progress,
                        seed=REFERENCE_SEEDS["pbr_morphed_clean"])
    return {"pbr_morphed_clean": recompose(L),
            "truth_clean": truth_renders(bench, ids, spp, REFERENCE_SEEDS["truth_clean"])}


def cached_references(bench, morph_dir: Path, ids: list[int], spp: int, photos_clean: bool,
                      show_progress: bool = False) -> dict:
    """:func:`references` (and, with ``photos_clean``, the held-out views path traced again with
    ``REFERENCE_SEEDS["photos_clean"]``), cached in ``morph_dir`` under the benchmark, the morphed mesh, the views,
    the sample count and the seeds."""
    key = json.dumps({"benchmark": file_digest(Path(bench.path) / "morph_benchmark.json"),
                      "morphed": file_digest(Path(morph_dir) / "morphed.ply"), "ids": [int(i) for i in ids],
                      "spp": int(spp), "seeds": REFERENCE_SEEDS, "photos_clean": bool(photos_clean)}, sort_keys=True)

    def render() -> dict:
        out = references(bench, morph_dir, ids, spp, show_progress)
        if photos_clean:
            out["photos_clean"] = truth_renders(bench, ids, spp, REFERENCE_SEEDS["photos_clean"])
        return out

    return cached_arrays(Path(morph_dir) / "diffrender_references.npz", key, render)


def set_features(images: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """An image set's MobileNetV2 features for :func:`distribution`: per image and per last-map position."""
    return image_features(images), spatial_features(images)


def distribution(sets: dict[str, tuple], reference: tuple) -> dict:
    """MobileNetV2 distribution distances of each set in ``sets`` (name → :func:`set_features`) to ``reference``
    (its :func:`set_features`): image-level KID (with its jackknife standard error over images) and FID, and the
    spatial KID over the last map's positions (jackknife over images, each image's positions leaving together)."""
    f_ref, f_ref_sp = reference
    per = len(f_ref_sp) // len(f_ref)
    g_ref = np.repeat(np.arange(len(f_ref)), per)
    out = {}
    for k, (f, f_sp) in sets.items():
        g = np.repeat(np.arange(len(f)), per)
        out[k] = {"kid": kid(f, f_ref), "kid_std": kid_std(f, f_ref), "fid": fid(f, f_ref),
                  "kid_spatial": kid(f_sp, f_ref_sp), "kid_spatial_std": kid_std(f_sp, f_ref_sp, g, g_ref)}
    return out
