"""Scores without a ground truth: renders of a mesh against the capture's held-out photos (never fitted).

The mesh is coloured from the training photos (each vertex: the mean colour of the photos that see it, visibility by
ray casting, weighted by how squarely they see it) and rendered unlit (each surface point emits its colour: the
photos' lighting is baked in, as the morph's unlit mode assumes), at the held-out cameras. PSNR, SSIM, ꟻLIP and the
ImageNet MobileNetV2 perceptual distance are taken inside the object's mask where the capture has masks, over the
whole photo otherwise."""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np

from .format import Capture, CaptureCamera, sensor


def _scene(v: np.ndarray, f: np.ndarray, colours: np.ndarray | None):
    import mi_plugins  # noqa: F401  (the variant)
    import mitsuba as mi

    from foundation.mesh import write_ply

    with tempfile.TemporaryDirectory(prefix="photoreal-score-") as tmp:
        ply = write_ply(Path(tmp) / "m.ply", v, f, colours)
        shape = {"type": "ply", "filename": str(ply), "bsdf": {"type": "diffuse", "reflectance": 0.0}}
        if colours is not None:
            shape["emitter"] = {"type": "area", "radiance": {"type": "mesh_attribute", "name": "vertex_color"}}
        return mi.load_dict({"type": "scene", "integrator": {"type": "path", "max_depth": 1}, "mesh": shape})


def _bilinear(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    from scipy.ndimage import map_coordinates

    col, row = uv[:, 0] - 0.5, uv[:, 1] - 0.5
    return np.stack([map_coordinates(img[..., c], [row, col], order=1, mode="nearest") for c in range(3)], -1)


def colour_from_photos(cap: Capture, v: np.ndarray, f: np.ndarray, names: list[str] | None = None) -> np.ndarray:
    """(V, 3) linear vertex colours: the mean of the photos ``names`` (default: the training photos) that see each
    vertex, weighted by the cosine between its normal and the view ray; grey where none does."""
    from foundation.mesh import vertex_normals

    names = names or cap.meta.train
    cams = cap.cameras
    acc, wsum = project_photos(v, f, v, vertex_normals(v, f), [cams[n] for n in names], [cap.photo(n) for n in names])
    out = np.full((len(v), 3), 0.5, np.float32)
    seen = wsum > 0
    out[seen] = (acc[seen] / wsum[seen, None]).astype(np.float32)
    return out


def project_photos(v: np.ndarray, f: np.ndarray, points: np.ndarray, normals: np.ndarray,
                   cameras: list[CaptureCamera], photos: list[np.ndarray], gains: list | None = None
                   ) -> tuple[np.ndarray, np.ndarray]:
    """The photos seen at surface ``points`` of the mesh (``v``, ``f``): Σ w·photo/gain (N, 3) and Σ w (N,), w the
    cosine between the ``normals`` and the view ray (0.05 at grazing views), 0 where the point is outside the frame
    or another part of the mesh hides it (a ray from the camera centre, Mitsuba's intersector). The classic
    photogrammetry texturing step, at vertices or texels; ``gains`` (per photo, RGB: render × gain ≈ photo) are
    divided out."""
    import mi_plugins  # noqa: F401  (the variant)
    import mitsuba as mi

    scene = _scene(v, f, None)
    size = float(np.ptp(v, axis=0).max())
    points = np.asarray(points, np.float64)
    acc, wsum = np.zeros((len(points), 3)), np.zeros(len(points))
    for k, (c, photo) in enumerate(zip(cameras, photos)):
        uv, z = c.project(points)
        ok = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < c.width) & (uv[:, 1] >= 0) & (uv[:, 1] < c.height)
        d = points - c.centre
        dist = np.linalg.norm(d, axis=1)
        d = d / np.maximum(dist, 1e-12)[:, None]
        ray = mi.Ray3f(mi.Point3f(*[mi.Float(np.full(len(points), c.centre[j], np.float32)) for j in range(3)]),
                       mi.Vector3f(*[mi.Float(d[:, j].astype(np.float32)) for j in range(3)]))
        t = np.array(scene.ray_intersect(ray).t, np.float64)
        seen = ok & (np.abs(t - dist) < 2e-3 * size)
        w = np.clip(-(normals * d).sum(1), 0.0, 1.0)
        w = np.where(seen, np.where(w > 0, w, 0.05), 0.0)  # a grazing view still counts a little
        colour = _bilinear(photo, np.nan_to_num(uv))
        if gains is not None:
            colour = colour / np.maximum(np.asarray(gains[k], np.float64), 1e-6)
        acc += w[:, None] * colour
        wsum += w
    return acc, wsum


def render_mesh(v: np.ndarray, f: np.ndarray, colours: np.ndarray, cam: CaptureCamera, spp: int = 16,
                seed: int = 0) -> np.ndarray:
    """The unlit render (H, W, 3) of a coloured mesh at a capture camera."""
    return _render(_scene(v, f, colours), cam, spp, seed)


def _render(scene, cam: CaptureCamera, spp: int, seed: int) -> np.ndarray:
    import mi_plugins  # noqa: F401  (the variant)
    import mitsuba as mi

    return np.array(mi.render(scene, sensor=mi.load_dict(sensor(cam)), spp=spp, seed=seed))[..., :3]


def heldout_scores(cap: Capture, v: np.ndarray, f: np.ndarray, colours: np.ndarray | None = None, spp: int = 16,
                   seed: int = 0) -> dict:
    """Per held-out photo and their mean: PSNR, SSIM, ꟻLIP, MobileNetV2 distance of the unlit render of the mesh
    (coloured from the training photos unless ``colours`` are given)."""
    from foundation import metrics
    from foundation.features import perceptual_distance

    colours = colour_from_photos(cap, v, f) if colours is None else colours
    rows = {}
    renders = {}
    scene = _scene(v, f, colours)  # one scene for every held-out camera
    for name in cap.meta.test:
        img = _render(scene, cap.cameras[name], spp, seed)
        ref = cap.photo(name)
        m = cap.mask(name)
        a, b = (img, ref) if m is None else (img * m[..., None], ref * m[..., None])
        rows[name] = {"psnr": metrics.psnr(img, ref) if m is None else metrics.masked_psnr(img, ref, m),
                      "ssim": metrics.ssim(a, b), "flip": metrics.flip(img, ref, mask=m),
                      "perceptual": float(perceptual_distance(a[None], b[None])[0])}
        renders[name] = img
    keys = ("psnr", "ssim", "flip", "perceptual")
    mean = {k: float(np.mean([r[k] for r in rows.values()])) for k in keys}
    return {"views": rows, "mean": mean, "masked": cap.meta.masks, "spp": spp, "renders": renders}
