"""The scene a morph renders: the mesh with vertex colours under the benchmark's HDR environment."""

from __future__ import annotations

from pathlib import Path

import numpy as np

import mi_plugins  # noqa: F401
import mitsuba as mi
from mi_plugins.arrays import aligned

from foundation.assets import envmap
from foundation.scene import mitsuba_log_level

from .benchmark import Camera, MorphBenchmark, sensor_dict

MODES = ("unlit", "lit")


def morph_scene(mesh_ply: Path, mode: str, hdri: str | Path, integrator: dict | None = None) -> mi.Scene:
    """Scene with the morphable mesh (PLY with vertex colours) and the HDR environment.

    ``unlit``: the mesh emits its vertex colour (the thesis); ``lit``: diffuse vertex colour under ``hdri``
    (a bundled name or an EXR file).
    """
    colour = {"type": "mesh_attribute", "name": "vertex_color"}
    if mode == "unlit":
        shape = {"type": "ply", "filename": str(mesh_ply), "bsdf": {"type": "diffuse", "reflectance": 0.0},
                 "emitter": {"type": "area", "radiance": colour}}
    elif mode == "lit":
        shape = {"type": "ply", "filename": str(mesh_ply),
                 "bsdf": {"type": "twosided", "bsdf": {"type": "diffuse", "reflectance": colour}}}
    else:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
    # Remeshed/decimated reconstructions often have a few non-manifold vertices (expected here).
    with mitsuba_log_level(mi.LogLevel.Error):
        return mi.load_dict({"type": "scene", "integrator": integrator or {"type": "direct_projective", "sppi": 0},
                             "env": envmap(hdri), "mesh": shape})


def render_views(scene: mi.Scene, params, cameras: list[Camera], ids, res: int, fov: float, spp: int,
                 seed: int) -> list[mi.TensorXf]:
    """Differentiable renders of cameras ``ids`` (seed + view index each), films that sample their border."""
    out = []
    with mitsuba_log_level(mi.LogLevel.Error):  # projective integrators dump non-manifold meshes at first render
        for i in ids:
            sensor = mi.load_dict(sensor_dict(cameras[int(i)], res, fov, sample_border=True))
            out.append(mi.render(scene, params, sensor=sensor, spp=spp, seed=int(seed + i)))
    return out


def photo_at(bench: MorphBenchmark, i: int, res: int) -> np.ndarray:
    """Photo ``i`` at ``res``² (box-filtered when smaller than the benchmark's), float32 (res, res, 3)."""
    img = bench.photo(i)
    if img.shape[0] != res:
        from PIL import Image

        img = np.stack([np.asarray(Image.fromarray(img[..., k]).resize((res, res), Image.BOX)) for k in range(3)], -1)
    return np.ascontiguousarray(img, np.float32)


def photo_tensors(bench: MorphBenchmark, res: int) -> dict[int, mi.TensorXf]:
    return {i: mi.TensorXf(aligned(photo_at(bench, i, res))) for i in range(len(bench.meta.cameras))}
