"""The scene a morph renders: the mesh with vertex colours under the benchmark's HDR environment."""

from __future__ import annotations

from pathlib import Path

import numpy as np

import mi_plugins  # noqa: F401
import mitsuba as mi
from mi_plugins.arrays import aligned

from foundation.assets import envmap
from foundation.mesh import face_normals
from foundation.scene import mitsuba_log_level

from .benchmark import Camera, MorphBenchmark, sensor_dict

MODES = ("unlit", "lit")


def morph_scene(mesh_ply: Path, mode: str, hdri: str | Path | dict, integrator: dict | None = None,
                flash: bool = False) -> mi.Scene:
    """Scene with the morphable mesh (PLY with vertex colours) and the HDR environment.

    ``unlit``: the mesh emits its vertex colour (the thesis); ``lit``: diffuse vertex colour under ``hdri``
    (a bundled name or an EXR file). ``flash`` ('lit' only): also a point light ``flash``, placed at each view's
    camera and given its intensity by :func:`set_flash` before a render.
    """
    colour = {"type": "mesh_attribute", "name": "vertex_color"}
    env = hdri if isinstance(hdri, dict) else envmap(hdri)  # a dict: a fitted map (photo_model.fitted_envmap)
    if mode == "unlit":
        shape = {"type": "ply", "filename": str(mesh_ply), "bsdf": {"type": "diffuse", "reflectance": 0.0},
                 "emitter": {"type": "area", "radiance": colour}}
    elif mode == "lit":
        shape = {"type": "ply", "filename": str(mesh_ply),
                 "bsdf": {"type": "twosided", "bsdf": {"type": "diffuse", "reflectance": colour}}}
    else:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
    scene = {"type": "scene", "integrator": integrator or {"type": "direct_projective", "sppi": 0}, "env": env,
             "mesh": shape}
    if flash and mode == "lit":
        scene[FLASH] = flash_emitter()
    # Remeshed/decimated reconstructions often have a few non-manifold vertices (expected here).
    with mitsuba_log_level(mi.LogLevel.Error):
        return mi.load_dict(scene)


#: the scene key of the light attached to the camera (:func:`morph_scene`)
FLASH = "flash"


def flash_emitter() -> dict:
    """The flash: a point light, placed and given its intensity per view by :func:`set_flash`."""
    return {"type": "point", "position": [0.0, 0.0, 0.0], "intensity": {"type": "rgb", "value": 0.0}}


def set_flash(params, position, intensity, sampling_weight: float | None = None) -> None:
    """Put the scene's flash at ``position`` (the camera's centre) with RGB ``intensity`` (W/sr: a diffuse surface
    of albedo ρ at distance r, turned θ from the light, then has radiance ρ·I·cos θ / (π r²)); a differentiable
    ``intensity`` (mi.Color3f) carries gradients. ``sampling_weight``: :func:`flash_sampling_weight` (None: kept); a
    flash of zero intensity (a photo taken without it) takes no light samples. The caller updates ``params``."""
    if not isinstance(intensity, mi.Color3f) and not np.any(intensity):
        sampling_weight = 1e-6
    if sampling_weight is not None:
        params[f"{FLASH}.sampling_weight"] = float(sampling_weight)
    params[f"{FLASH}.position"] = mi.Point3f(*[float(x) for x in position])
    params[f"{FLASH}.intensity.value"] = intensity if isinstance(intensity, mi.Color3f) else \
        mi.Color3f(*[float(x) for x in intensity])


#: the flash's share of the light samples stays within these (the environment keeps at least 1 in 20)
FLASH_SAMPLE_SHARE = (0.5, 0.95)


def flash_distance(centres: np.ndarray, v: np.ndarray) -> float:
    """The median distance from the cameras (``centres``) to the nearest vertex of the mesh ``v``: how far the flash
    is from what it lights."""
    from scipy.spatial import cKDTree

    r, _ = cKDTree(np.asarray(v, np.float64)).query(np.asarray(centres, np.float64))
    return float(np.median(r))


def flash_sampling_weight(intensity, env: np.ndarray, distance: float) -> float:
    """The flash's ``sampling_weight`` against the environment's 1. Each light sample of the direct integrator goes to
    one emitter, so the flash's share p of them should follow its share of the light: the irradiance of the flash at
    ``distance`` (mean cos θ 2/3 over a sphere's lit half) against the environment's (π × its mean radiance over the
    sphere, an (h, w, 3) equirectangular map), p clipped to :data:`FLASH_SAMPLE_SHARE`; the weight is p/(1 − p).
    At even shares a flash-lit surface's pixel noise at 4 spp was 36 % of its value, at p = 0.9 14 %."""
    env = np.asarray(env, np.float64)
    rows = np.sin((np.arange(env.shape[0]) + 0.5) * np.pi / env.shape[0])  # equal-angle rows: area ∝ sin θ
    e_env = np.pi * float(np.sum(env.mean(axis=(1, 2)) * rows) / np.sum(rows))
    e_flash = float(np.mean(intensity)) * (2.0 / 3.0) / max(distance, 1e-12) ** 2
    lo, hi = FLASH_SAMPLE_SHARE
    p = float(np.clip(e_flash / max(e_flash + e_env, 1e-30), lo, hi))
    return p / (1.0 - p)


def camera_centre(cam) -> np.ndarray:
    """Where a camera is: a capture camera's centre, a benchmark camera's eye."""
    return np.asarray(cam.centre if hasattr(cam, "centre") else cam.eye, np.float64)


def mask_scene(mesh_ply: Path, integrator: dict | None = None) -> mi.Scene:
    """The mesh black under a constant white sky: a render is 1 − the mesh's coverage of each pixel. Every
    silhouette then has contrast 1 for the projective integrator's boundary term, whatever the lighting and colours
    beside it (the photos' own contrast there can be small: a head's skin against the sky). Compared with
    :func:`photo_masks` by ``MorphSettings.mask_weight``."""
    shape = {"type": "ply", "filename": str(mesh_ply), "bsdf": {"type": "diffuse", "reflectance": 0.0}}
    with mitsuba_log_level(mi.LogLevel.Error):
        return mi.load_dict({"type": "scene", "integrator": integrator or mask_integrator(),
                             "env": {"type": "constant", "radiance": 1.0}, "mesh": shape})


def mask_integrator(boundary_spp: int | None = None) -> dict:
    """The mask render's differentiable integrator: the silhouettes' boundary samples only, ``boundary_spp`` per
    pixel (None: the render's spp). The mesh is black under a sky that does not vary, so the continuous derivative
    (every pixel's interior change) is exactly zero and takes no samples (``sppc`` 0): the primal and the gradient are
    the same bit for bit, and a mask render and its backward pass cost about 30 % less (docs/results/morph.md:
    "Full-resolution masks, the default")."""
    d = {"type": "direct_projective", "sppc": 0, "sppi": 0}
    if boundary_spp is not None:
        d["sppp"] = int(boundary_spp)
    return d


def photo_masks(bench: MorphBenchmark, res: int, views: list[int] | None = None, spp: int = 64
                ) -> dict[int, np.ndarray]:
    """The photos' masks (alpha): per view (``views``; None: every camera), the fraction of each pixel the truth
    covers, (res, res) float32 in [0, 1], rendered from the benchmark's truth at ``spp`` (seed = the view), as a
    segmentation of the photos gives. A capture gives its own masks (none where it has none)."""
    if hasattr(bench, "masks_at"):
        return bench.masks_at(res, range(len(bench.meta.cameras)) if views is None else views)
    meta = bench.meta
    scene = mask_scene(bench.ground_truth, integrator={"type": "direct"})
    out = {}
    for i in (range(len(meta.cameras)) if views is None else views):
        sensor = mi.load_dict(sensor_dict(meta.cameras[int(i)], res, meta.fov))
        sky = np.asarray(mi.render(scene, sensor=sensor, spp=spp, seed=int(i)))[..., 0]
        out[int(i)] = np.clip(1.0 - sky, 0.0, 1.0).astype(np.float32)
    return out


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
    """Photo ``i`` at ``res``² (box-filtered when smaller than the benchmark's), float32 (res, res, 3); a capture's at
    ``res`` pixels across, its aspect kept."""
    if hasattr(bench, "photo_at"):
        return bench.photo_at(i, res)
    img = bench.photo(i)
    if img.shape[0] != res:
        from PIL import Image

        img = np.stack([np.asarray(Image.fromarray(img[..., k]).resize((res, res), Image.BOX)) for k in range(3)], -1)
    return np.ascontiguousarray(img, np.float32)


def photo_tensors(bench: MorphBenchmark, res: int) -> dict[int, mi.TensorXf]:
    return {i: mi.TensorXf(aligned(photo_at(bench, i, res))) for i in range(len(bench.meta.cameras))}


def saturation_level(photos: list[np.ndarray], factor: float) -> float:
    """Radiance above which a pixel counts as saturated: ``factor`` × the photos' 99th percentile (of each pixel's
    brightest channel); 0 when ``factor`` is 0 (no pixel is). The bundled sunrise lighting gives 15–18 at factor 4,
    over a sky that reaches 6 and diffuse objects below 2; its sun reaches 30,000."""
    if factor <= 0 or not photos:
        return 0.0
    return float(factor * np.quantile(np.concatenate([p.max(axis=-1).ravel() for p in photos]), 0.99))


def unsaturated_mask(photo_hot: np.ndarray, render: np.ndarray, level: float) -> np.ndarray | None:
    """(H, W, 3) float32 weights, 0 on pixels saturated in the photo (``photo_hot``) or in the render (brighter
    than ``level``) and on their 8-neighbours, 1 elsewhere; None where no pixel is saturated (the loss is then
    computed exactly as without the mask).

    Why: a camera clips there, and an edge of the mesh against the sun carries a silhouette gradient scaled by
    the sun's radiance. Against the sunrise HDRI's sun (30,000) one view's gradient reached 10.6 at one vertex
    where the other views' stayed below 0.004 (paul at seed 1), and uniform Adam's maximum then held every step
    of the run near zero (Chamfer −13 %); with these pixels left out the view's maximum is 0.010.
    """
    if level <= 0:
        return None
    hot = photo_hot | (np.asarray(render)[..., :3].max(axis=-1) > level)
    if not hot.any():
        return None
    from scipy import ndimage

    keep = ~ndimage.binary_dilation(hot, structure=np.ones((3, 3), bool))
    return np.ascontiguousarray(np.repeat(keep[..., None], 3, axis=-1), np.float32)


def photo_l1(img, photo: mi.TensorXf, photo_hot: np.ndarray | None, level: float):
    """Mean L1 of a render's RGB ``img`` against ``photo`` over the pixels :func:`unsaturated_mask` keeps (eq. 4.3);
    the mean stays over every pixel, so a view without saturated pixels gives exactly the plain L1."""
    import drjit as dr

    r = dr.abs(img - photo)
    m = unsaturated_mask(photo_hot, dr.detach(img), level) if level and photo_hot is not None else None
    return dr.mean(r if m is None else r * mi.TensorXf(m), axis=None)


def photo_saturation(photos: dict[int, mi.TensorXf], train: list[int], factor: float
                     ) -> tuple[float, dict[int, np.ndarray]]:
    """The saturation level of ``factor`` (:func:`saturation_level` over the ``train`` photos) and, per photo, its
    saturated pixels (empty when the level is 0)."""
    level = saturation_level([np.asarray(photos[i]) for i in train], factor)
    return level, ({i: np.asarray(p).max(axis=-1) > level for i, p in photos.items()} if level else {})


def saturated_silhouette(bench: MorphBenchmark, factor: float, spp: int = 4) -> dict:
    """Where a benchmark's lighting is saturated behind its truth's silhouette: per training view with saturated
    light (the environment alone, brighter than :func:`saturation_level` of ``factor``), how many of those pixels
    there are and how many lie within one pixel of the truth's silhouette — an edge there carries a gradient scaled
    by that radiance (:func:`unsaturated_mask`). ``factor``: the morph's ``MorphSettings.saturation`` (the CLI's
    default). The truth's coverage is rendered at ``spp``."""
    from scipy import ndimage

    from foundation.assets import envmap

    meta = bench.meta
    level = saturation_level([bench.photo(i) for i in meta.train], factor)
    env = mi.load_dict({"type": "scene", "integrator": {"type": "direct"}, "env": envmap(meta.hdri)})
    truth = mi.load_dict({"type": "scene", "integrator": {"type": "aov", "aovs": "d:depth"},
                          "gt": {"type": "ply", "filename": str(bench.ground_truth)}})
    views = {}
    for i in meta.train:
        sensor = mi.load_dict(sensor_dict(meta.cameras[i], meta.resolution, meta.fov))
        hot = np.asarray(mi.render(env, sensor=sensor, spp=spp, seed=int(i)))[..., :3].max(axis=-1) > level
        if not level or not hot.any():
            continue
        hit = np.asarray(mi.render(truth, sensor=sensor, spp=spp, seed=int(i)))[..., 0] > 0
        border = ndimage.binary_dilation(hit, np.ones((3, 3), bool)) & ~ndimage.binary_erosion(hit, np.ones((3, 3), bool))
        views[int(i)] = {"saturated": int(hot.sum()), "at_silhouette": int((hot & border).sum())}
    return {"level": level, "factor": factor, "views": views,
            "at_silhouette": int(sum(v["at_silhouette"] for v in views.values()))}


def _ray_scene(v: np.ndarray, f: np.ndarray, name: str):
    """A scene holding the one mesh (v, f), for ray casts against it."""
    mesh = mi.Mesh(name, len(v), len(f))
    p = mi.traverse(mesh)
    p["vertex_positions"] = mi.Float(v.astype(np.float32).ravel())
    p["faces"] = mi.UInt32(f.astype(np.uint32).ravel())
    p.update()
    return mi.load_dict({"type": "scene", "mesh": mesh})


def inward_thickness(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Per triangle, the distance from its centroid along its inward normal (against the winding's normal) to the
    next surface the ray meets: the local thickness of the part on a closed, outward-wound mesh (a leg, an ear, a
    plate); inf where the ray leaves the mesh (an open sheet seen from its outer side, an inward-wound patch)."""
    v, f = np.asarray(v, np.float64), np.asarray(f, np.int64)
    scene = _ray_scene(v, f, "thickness")
    n = face_normals(v, f)
    # start a hair inside the triangle, so that the ray does not meet the triangle itself
    o = v[f].mean(axis=1) - 1e-5 * np.ptp(v, axis=0).max() * n
    ray = mi.Ray3f(mi.Point3f(*[mi.Float(o[:, k].astype(np.float32)) for k in range(3)]),
                   mi.Vector3f(*[mi.Float((-n[:, k]).astype(np.float32)) for k in range(3)]))
    si = scene.ray_intersect(ray)
    t = np.array(si.t, np.float64)
    t[~np.array(si.is_valid())] = np.inf
    return t


def views_seeing(v: np.ndarray, f: np.ndarray, cameras: list, fov: float, per_camera: bool = False) -> np.ndarray:
    """Per triangle, how many of ``cameras`` (look-at, y up, square images, ``fov`` degrees) see its centroid: inside
    the view and the first thing the ray from the eye meets (either side of it: a flipped triangle is seen too).
    ``per_camera``: instead, whether each camera sees it (cameras × triangles, bool)."""
    v, f = np.asarray(v, np.float64), np.asarray(f, np.int64)
    scene = _ray_scene(v, f, "visibility")
    c = v[f].mean(axis=1)
    ids = np.arange(len(f))
    tan_half = np.tan(np.radians(fov / 2))
    seen = np.zeros((len(cameras), len(f)), bool)
    for k, cam in enumerate(cameras):
        eye, target = np.asarray(cam.eye, np.float64), np.asarray(cam.target, np.float64)
        fwd = (target - eye) / np.linalg.norm(target - eye)
        right = np.cross(fwd, [0.0, 1.0, 0.0])
        if np.linalg.norm(right) < 1e-9:  # looking straight up or down: any horizontal axis frames it
            right = np.array([1.0, 0.0, 0.0])
        right /= np.linalg.norm(right)
        up = np.cross(right, fwd)
        d = c - eye
        depth = d @ fwd
        inside = (depth > 0) & (np.abs(d @ right) <= tan_half * depth) & (np.abs(d @ up) <= tan_half * depth)
        dist = np.linalg.norm(d, axis=1)
        d = d / np.maximum(dist, 1e-30)[:, None]
        o = [mi.Float(np.full(len(c), x, np.float32)) for x in eye]
        ray = mi.Ray3f(mi.Point3f(*o), mi.Vector3f(*[mi.Float(d[:, k].astype(np.float32)) for k in range(3)]))
        si = scene.ray_intersect(ray)
        valid, t, prim = np.array(si.is_valid()), np.array(si.t), np.array(si.prim_index)
        first = ~valid | (prim == ids) | (t >= dist * (1.0 - 1e-5))
        seen[k] = inside & first
    return seen if per_camera else seen.sum(axis=0, dtype=np.int64)
