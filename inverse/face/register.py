"""A scan registered to the face template, so that its maps can be expressed in the template's UV layout.

``from-photo`` works in the UV layout of MediaPipe's canonical face template; a scan has its own layout (the
Cyberware heads: a cylinder). Learned UV-space models must see one layout, the one photos are unwrapped into, so
each scan is registered once:

1. a noise-free frontal render of the scan (orthographic; its albedo shaded by n·v) with Mitsuba's position AOV;
2. MediaPipe's 468 landmarks on it (the same detector ``from-photo`` runs) lifted to the scan's surface points
   through the position AOV;
3. the template fitted to those 3D points (:func:`inverse.face.photo.fit_template`: similarity + Laplacian
   deformation, the same fit as for a photo);
4. every template texel's point cast onto the scan along its normal: the scan's uv there, so any scan-UV map can be
   resampled into the template layout (:meth:`ScanRegistration.to_template`).

The template's sides, beyond what the frontal render shows, still find the scan along their normals; texels whose
cast misses keep ``valid = False``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from foundation.errors import UsageError
from foundation.mesh import UVMesh, load_obj


@dataclass
class ScanRegistration:
    """The template fitted to a scan (world space of the scan) and the scan uv of every template texel."""

    vertices: np.ndarray  #: (468, 3) template vertices on the scan
    scan_uv: np.ndarray  #: (R, R, 2) Mitsuba uv on the scan of each template texel (row-major, v down)
    valid: np.ndarray  #: (R, R) bool: covered by the template layout and found on the scan
    landmark_px: float  #: mean distance (render pixels) between the fitted template's landmarks and MediaPipe's

    def to_template(self, scan_map: np.ndarray) -> np.ndarray:
        """Resample an (H, W, C) scan-UV map (bilinear) into the template layout (R, R, C); invalid texels get the
        map's mean over the valid ones."""
        from scipy.ndimage import map_coordinates

        h, w = scan_map.shape[:2]
        rows = self.scan_uv[..., 1] * h - 0.5
        cols = self.scan_uv[..., 0] * w - 0.5
        out = np.stack([map_coordinates(scan_map[..., c], [rows, cols], order=1, mode="nearest")
                        for c in range(scan_map.shape[-1])], -1)
        if self.valid.any():
            out[~self.valid] = out[self.valid].mean(0)
        return out.astype(np.float32)


def frontal_render(mesh_path: Path, mesh: UVMesh, res: int = 512):
    """Noise-free frontal view of a scan (albedo × (0.35 + 0.65 |n·v|), 8-bit sRGB) and its position AOV."""
    import mitsuba as mi
    from mi_plugins.arrays import aligned

    from foundation import imageio

    from .benchmark import scan_frame, scan_texture

    centre, radius, front = scan_frame(mesh)
    up = np.array([0.0, 1.0, 0.0]) - front * front[1]
    up /= np.linalg.norm(up)
    tex = imageio.srgb_to_linear(scan_texture(mesh).astype(np.float32) / 255.0)
    half = 0.62 * radius
    sensor = {"type": "orthographic",
              "to_world": mi.ScalarTransform4f().look_at(origin=(centre + front * 4 * radius).tolist(),
                                                         target=centre.tolist(), up=up.tolist())
              @ mi.ScalarTransform4f().scale([half, half, 1]),
              "film": {"type": "hdrfilm", "width": res, "height": res, "rfilter": {"type": "box"}},
              "sampler": {"type": "independent"}}
    bsdf = {"type": "twosided", "bsdf": {"type": "diffuse", "reflectance": {
        "type": "bitmap", "raw": True, "data": mi.TensorXf(aligned(tex, None))}}}
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "aov", "aovs": "a:albedo,n:sh_normal,p:position"},
                          "scan": {"type": "obj", "filename": str(mesh_path), "bsdf": bsdf, "face_normals": False},
                          "sensor": sensor})
    img = np.array(mi.render(scene, spp=4))
    albedo, normal, position = img[..., 0:3], img[..., 3:6], img[..., 6:9]
    shaded = albedo * (0.35 + 0.65 * np.clip(np.abs(normal @ front), 0.0, 1.0))[..., None]
    photo = (np.clip(imageio.linear_to_srgb(np.clip(shaded, 0.0, 1.0)), 0.0, 1.0) * 255 + 0.5).astype(np.uint8)
    covered = np.linalg.norm(normal, axis=-1) > 0.5
    return photo, position, covered


def register_scan(mesh_path: str | Path, uv_res: int, landmarks: np.ndarray | None = None,
                  render_res: int = 512) -> ScanRegistration:
    """Register a textured scan to the face template (see the module docstring). ``landmarks`` (468×3, MediaPipe's
    normalised coordinates on the frontal render) skip the detector."""
    import mitsuba as mi
    from scipy.ndimage import map_coordinates

    from .photo import TEMPLATE, check_landmarks, detect_landmarks, fit_template
    from .uv_bake import bake_geometry

    from foundation.mesh import write_obj

    mesh_path = Path(mesh_path)
    mesh = load_obj(mesh_path)
    photo, position, covered = frontal_render(mesh_path, mesh, render_res)
    lm = check_landmarks(landmarks) if landmarks is not None else detect_landmarks(photo)
    # the landmarks' surface points: the position AOV at their pixels (nearest covered pixel where one falls off)
    cols, rows = lm[:, 0] * render_res - 0.5, lm[:, 1] * render_res - 0.5
    if not covered.any():
        raise UsageError(f"{mesh_path}: the frontal render shows no surface")
    from scipy.ndimage import distance_transform_edt

    _, (ir, ic) = distance_transform_edt(~covered, return_indices=True)
    pos = position[ir, ic]  # every pixel holds its nearest surface point
    target = np.stack([map_coordinates(pos[..., c], [rows, cols], order=1, mode="nearest") for c in range(3)], -1)
    template = load_obj(TEMPLATE)
    fit = fit_template(template, target, laplacian_weight=2.0)  # λ in template units, as from-photo
    # pixels per world unit of the render (its half-width is 0.62 radii), to report the fit in pixels like from-photo
    px = render_res / (2 * 0.62 * 0.5 * float(np.linalg.norm(np.ptp(mesh.vertices, 0))))
    err_px = float(np.linalg.norm(fit.vertices[:len(target)] - target, axis=1).mean() * px)
    import tempfile

    with tempfile.TemporaryDirectory(prefix="photoreal_reg_") as tmp:
        fitted = load_obj(write_obj(Path(tmp) / "template.obj", fit.vertices, template))
        geo = bake_geometry(fitted, uv_res)
    scene = mi.load_dict({"type": "scene", "scan": {"type": "obj", "filename": str(mesh_path), "face_normals": False}})
    idx = np.nonzero(geo.mask.ravel())[0]
    p = geo.position.reshape(-1, 3)[idx].astype(np.float64)
    n = geo.normal.reshape(-1, 3)[idx].astype(np.float64)
    reach = 0.15 * float(np.linalg.norm(np.ptp(fit.vertices, 0)))
    uv = np.zeros((len(idx), 2), np.float32)
    found = np.zeros(len(idx), bool)
    best = np.full(len(idx), np.inf)
    for sign in (1.0, -1.0):  # from outside inwards, then from inside outwards: the nearer hit along the normal
        o = p + sign * n * reach
        ray = mi.Ray3f(mi.Point3f(o.T.astype(np.float32)), mi.Vector3f((-sign * n).T.astype(np.float32)))
        ray.maxt = float(2 * reach)
        si = scene.ray_intersect(ray)
        ok = np.array(si.is_valid())
        dist = np.abs(np.array(si.t, dtype=np.float64) - reach)
        take = ok & (dist < best)
        best[take] = dist[take]
        uv[take] = np.array(si.uv).T[take]
        found |= ok
    res = uv_res
    scan_uv = np.zeros((res * res, 2), np.float32)
    scan_uv[idx] = uv
    valid = np.zeros(res * res, bool)
    valid[idx] = found
    return ScanRegistration(fit.vertices.astype(np.float64), scan_uv.reshape(res, res, 2), valid.reshape(res, res),
                            err_px)


__all__ = ["ScanRegistration", "frontal_render", "register_scan"]
