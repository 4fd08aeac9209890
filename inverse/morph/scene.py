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


def projective_integrator(spp: int, boundary_spp: int) -> dict:
    """The morph's differentiable direct-light integrator: ``spp`` samples per pixel for the image and its
    continuous derivative, ``boundary_spp`` for the silhouettes' (primarily visible discontinuities), no indirect
    discontinuities. Render with :func:`render_views` and ``integrator_spp=True`` so that these counts hold."""
    return {"type": "direct_projective", "sppc": int(spp), "sppp": int(boundary_spp), "sppi": 0}


def render_views(scene: mi.Scene, params, cameras: list[Camera], ids, res: int, fov: float, spp: int,
                 seed: int, integrator_spp: bool = False) -> list[mi.TensorXf]:
    """Differentiable renders of cameras ``ids`` (seed + view index each), films that sample their border.

    ``integrator_spp``: the scene's integrator keeps its own per-part sample counts (:func:`projective_integrator`);
    ``spp`` then sets the sampler, i.e. the image's own samples. Otherwise ``spp`` is every part's count."""
    out = []
    with mitsuba_log_level(mi.LogLevel.Error):  # projective integrators dump non-manifold meshes at first render
        for i in ids:
            sd = sensor_dict(cameras[int(i)], res, fov, sample_border=True)
            if integrator_spp:
                sd["sampler"] = {"type": "independent", "sample_count": int(spp)}
            sensor = mi.load_dict(sd)
            # a run-time spp overrides every count of a projective integrator; 0 leaves them to it (and the sampler)
            out.append(mi.render(scene, params, sensor=sensor, spp=0 if integrator_spp else spp, seed=int(seed + i)))
    return out


def upsample_bilinear(img: np.ndarray, size: int) -> np.ndarray:
    """(h, w, c) image of a square frame resampled to (size, size, c) by bilinear interpolation between pixel
    centres (both grids span the same frame; beyond the outermost centres the edge value holds)."""
    def along(x: np.ndarray, axis: int) -> np.ndarray:
        n = x.shape[axis]
        if n == size:
            return x
        u = np.clip((np.arange(size) + 0.5) * n / size - 0.5, 0.0, n - 1)
        i0 = np.floor(u).astype(np.int64)
        i1 = np.minimum(i0 + 1, n - 1)
        t = (u - i0).astype(x.dtype)
        shape = [1] * x.ndim
        shape[axis] = size
        t = t.reshape(shape)
        return np.take(x, i0, axis) * (1 - t) + np.take(x, i1, axis) * t
    return along(along(np.asarray(img), 0), 1)


def photo_at(bench: MorphBenchmark, i: int, res: int) -> np.ndarray:
    """Photo ``i`` at ``res``² (box-filtered when smaller than the benchmark's), float32 (res, res, 3)."""
    img = bench.photo(i)
    if img.shape[0] != res:
        from PIL import Image

        img = np.stack([np.asarray(Image.fromarray(img[..., k]).resize((res, res), Image.BOX)) for k in range(3)], -1)
    return np.ascontiguousarray(img, np.float32)


def photo_tensors(bench: MorphBenchmark, res: int) -> dict[int, mi.TensorXf]:
    return {i: mi.TensorXf(aligned(photo_at(bench, i, res))) for i in range(len(bench.meta.cameras))}
