"""What a real photo adds to the morph's forward model: a correction of each camera's pose, a colour gain per photo
(exposure and white balance), and an environment map fitted where the light is not known.

Camera corrections are rigid motions G about each camera's centre in world axes (to_world' = G · to_world,
G(x) = R(ω)(x − c) + c + t). Rendering the scene through the corrected camera is rendering the scene moved by G⁻¹
through the imported one, so the correction is applied to the mesh's vertices of that view
(:func:`view_positions`): the gradients reach ω and t through the vertices, silhouettes included, with no change
to the sensor. In 'lit' mode the environment does not move with the mesh: for the small corrections the prior allows
(about a degree) the light's turn is left out.
"""

from __future__ import annotations

import numpy as np

import mi_plugins  # noqa: F401
import drjit as dr
import mitsuba as mi

#: the camera prior's scales: a correction of this rotation (radians, 0.5°) or this shift (× scene size) costs 1
CAMERA_PRIOR_ROT = np.radians(0.5)
CAMERA_PRIOR_SHIFT = 0.01
CAMERA_PRIOR_FOCAL = 0.05  #: a focal length 5 % off costs 1


def focal_positions(flat, cam_to_world: np.ndarray, log_k):
    """Flat positions as the camera with focal length × e^``log_k`` sees them through its imported focal length: in
    the camera's axes (COLMAP: x right, y down, z forward) x and y scale by k about the optical axis, which scales the
    image about the principal point. x' = x + (k − 1)(r₀(r₀·d) + r₁(r₁·d)), d = x − c."""
    p = dr.unravel(mi.Point3f, flat)
    m = np.asarray(cam_to_world, np.float64)
    c = mi.Point3f(*[float(x) for x in m[:3, 3]])
    r0, r1 = (mi.Vector3f(*[float(x) for x in m[:3, j]]) for j in (0, 1))
    d = p - c
    k1 = dr.exp(log_k) - 1.0
    return dr.ravel(p + k1 * (r0 * dr.dot(r0, d) + r1 * dr.dot(r1, d)))


def rotate_inverse(p, w):
    """R(ω)ᵀ p by Rodrigues' formula (``w``: mi.Vector3f of width 1, the rotation vector; ``p``: mi.Point3f)."""
    theta = dr.sqrt(dr.squared_norm(w) + 1e-20)
    k = w / theta
    c, s = dr.cos(theta), dr.sin(theta)
    return p * c - dr.cross(k, p) * s + k * dr.dot(k, p) * (1.0 - c)


def view_positions(flat, centre: np.ndarray, w, t):
    """Flat vertex positions (x, y, z per vertex) moved by G⁻¹: R(ω)ᵀ(v − c − t) + c."""
    p = dr.unravel(mi.Point3f, flat)
    c = mi.Point3f(*[float(x) for x in centre])
    return dr.ravel(rotate_inverse(p - c - t, w) + c)


def remove_gauge(rot: np.ndarray, shift: np.ndarray, centres: np.ndarray, size: float) -> tuple[np.ndarray, np.ndarray]:
    """Camera corrections (``rot``: radians, ``shift``: world units, (n, 3) each; ``centres``: the imported cameras'
    centres) less their part that moves every camera by one world similarity W(x) = x + ω × x + τ + s·x. That part
    (ω_k = ω, t_k = ω × c_k + τ + s·c_k to first order) changes no render once the mesh moves by W too, so the photos
    cannot tell it from the mesh's own motion: left in, the fitted cameras and mesh turn together, away from the frame
    the held-out cameras were imported in. Least squares in the camera prior's metric (:data:`CAMERA_PRIOR_ROT`,
    :data:`CAMERA_PRIOR_SHIFT` × ``size``): the corrections kept are those nearest the imported poses."""
    rot, shift = np.asarray(rot, np.float64), np.asarray(shift, np.float64)
    n = len(rot)
    if n == 0:
        return rot.copy(), shift.copy()
    c = (np.asarray(centres, np.float64) - np.mean(centres, axis=0)) / size
    a = np.zeros((n, 6, 7))  # per camera: (ω_k, t_k / size) from (ω, τ / size, s)
    a[:, :3, :3] = np.eye(3)
    a[:, 3:, :3] = -np.cross(c[:, :, None], np.eye(3)[None], axis=1)  # ω × c = −c × ω: columns −c × e_j
    a[:, 3:, 3:6] = np.eye(3)
    a[:, 3:, 6] = c
    w = np.r_[np.full(3, 1.0 / CAMERA_PRIOR_ROT), np.full(3, 1.0 / CAMERA_PRIOR_SHIFT)]
    x = np.concatenate([rot, shift / size], axis=1)
    g = np.linalg.lstsq((a * w[None, :, None]).reshape(-1, 7), (x * w).ravel(), rcond=None)[0]
    x = x - a @ g
    return x[:, :3], x[:, 3:] * size


def pick3(values, i: int):
    """Entries 3i … 3i+2 of a flat Float as a width-1 mi.Vector3f (differentiable)."""
    return mi.Vector3f(*[dr.gather(mi.Float, values, mi.UInt32(3 * int(i) + k)) for k in range(3)])


def moved_cameras(cameras: list, ids: list[int], rot: np.ndarray, shift: np.ndarray, focal_scale: float = 1.0) -> list:
    """Capture cameras ``ids`` with the fitted corrections applied (``rot``, ``shift``: (len(ids), 3), world units;
    ``focal_scale``: every camera's focal length × this)."""
    from dataclasses import replace

    from scipy.spatial.transform import Rotation

    out = list(cameras)
    for k, i in enumerate(ids):
        m = cameras[i].matrix.copy()
        r = Rotation.from_rotvec(rot[k]).as_matrix()
        c = m[:3, 3].copy()
        m[:3, :3] = r @ m[:3, :3]
        m[:3, 3] = c + shift[k]
        out[i] = replace(cameras[i], cam_to_world=m.tolist(), f=cameras[i].f * focal_scale)
    return out


def camera_movement(rot: np.ndarray, shift: np.ndarray, size: float) -> dict:
    """How far the refined cameras moved from the imported ones: per camera and at most, degrees and × scene size."""
    deg = np.degrees(np.linalg.norm(rot, axis=1))
    rel = np.linalg.norm(shift, axis=1) / size
    return {"rotation_deg": [float(x) for x in deg], "shift_rel": [float(x) for x in rel],
            "rotation_deg_max": float(deg.max(initial=0.0)), "rotation_deg_mean": float(deg.mean()) if len(deg) else 0.0,
            "shift_rel_max": float(rel.max(initial=0.0)), "shift_rel_mean": float(rel.mean()) if len(rel) else 0.0}


def nearest_fitted(centres: np.ndarray, fitted: list[int], k: int = 2) -> dict[int, list[int]]:
    """Per camera not in ``fitted``: its ``k`` nearest fitted cameras by centre (a held-out photo's gain is their
    mean: from its neighbours, never from its own pixels)."""
    out = {}
    fc = centres[fitted]
    for i in range(len(centres)):
        if i in fitted:
            continue
        d = np.linalg.norm(fc - centres[i], axis=1)
        out[i] = [fitted[j] for j in np.argsort(d, kind="stable")[:k]]
    return out


def exposure_slope(log_exposure: np.ndarray, log_gain: np.ndarray) -> float:
    """How the fitted gains follow the photos' EXIF exposures: the least-squares slope of the log gain (RGB mean) on
    the log exposure over the fitted photos, clipped to [0, 1]. 1 is a linear camera; a JPEG's tone curve, which
    compresses the highlights a longer exposure brightens, gives less. 0 where fewer than 3 photos have an exposure
    or their exposures do not differ (the neighbours' mean then stands alone)."""
    known = np.isfinite(log_exposure)
    x, y = log_exposure[known], np.asarray(log_gain, np.float64)[known].mean(axis=1)
    if len(x) < 3 or np.ptp(x) < 1e-3:
        return 0.0
    x = x - x.mean()
    return float(np.clip(np.dot(x, y - y.mean()) / np.dot(x, x), 0.0, 1.0))


def neighbour_log_gain(log_gain: np.ndarray, neighbours: list[int], log_exposure: float,
                       neighbour_exposures: np.ndarray, slope: float) -> np.ndarray:
    """A photo not fitted: the mean log gain of its fitted ``neighbours`` (rows of ``log_gain``), each moved by
    ``slope`` × the log ratio of the photo's exposure to the neighbour's, where both are known (never its pixels)."""
    g = np.asarray(log_gain, np.float64)[neighbours]
    d = float(log_exposure) - np.asarray(neighbour_exposures, np.float64)
    return (g + np.where(np.isfinite(d), slope * d, 0.0)[:, None]).mean(axis=0)


def envmap_index(height: int, width: int) -> np.ndarray:
    """Flat indices into an (height, width, 3) map that give Mitsuba ``envmap``'s stored ``data`` (its columns wrapped
    at both ends, small maps' rows padded), so that the map itself is what the fit optimises. Read from Mitsuba: an
    envmap of the texel indices themselves."""
    idx = np.zeros((height, width, 3), np.float32)
    idx[..., 0] = np.arange(height * width, dtype=np.float32).reshape(height, width) + 1.0  # exact below 2²⁴
    data = np.array(mi.traverse(mi.load_dict(fitted_envmap(idx)))["data"])[..., 0]
    base = np.rint(data).astype(np.int64) - 1
    if base.min() < 0 or base.max() >= height * width or np.abs(data - np.rint(data)).max() > 0:
        raise RuntimeError("Mitsuba's envmap stores its texels in a way this fit does not know")
    return (base[..., None] * 3 + np.arange(3)).astype(np.uint32).ravel()


def fitted_envmap(values: np.ndarray) -> dict:
    """An ``envmap`` emitter of an (height, width, 3) map (linear RGB)."""
    return {"type": "envmap", "bitmap": mi.Bitmap(np.ascontiguousarray(values, np.float32))}


def env_from_photos(cameras: list, photos: list[np.ndarray], v: np.ndarray, f: np.ndarray, height: int,
                    width: int = 64, reached: bool = False):
    """A start for the fitted environment: each texel the mean of the photos' pixels whose rays miss the coarse mesh
    (``v``, ``f``) and end in it, weighted as Mitsuba's envmap interpolates (the normal equations' diagonal: Wᵀy / Wᵀ1,
    both from one backward pass through ``envmap.eval``). The photos are read ``width`` pixels across; a texel no ray
    reaches takes the mean of those that are reached. ``reached``: also return which texels rays reach."""
    from inverse.capture import area_resize

    from .scene import _ray_scene

    dirs, colours = [], []
    blocker = _ray_scene(v, f, "env-start")
    for cam, img in zip(cameras, photos):
        c = cam.scaled(min(width, cam.width))
        small = area_resize(img, c.width, c.height).reshape(-1, 3)
        ys, xs = np.mgrid[0:c.height, 0:c.width].astype(np.float64) + 0.5
        d = np.stack([(xs - c.cx) / c.f, (ys - c.cy) / c.f, np.ones_like(xs)], -1).reshape(-1, 3) @ c.matrix[:3, :3].T
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        o = np.broadcast_to(c.centre, d.shape)
        ray = mi.Ray3f(mi.Point3f(*[mi.Float(o[:, k].astype(np.float32)) for k in range(3)]),
                       mi.Vector3f(*[mi.Float(d[:, k].astype(np.float32)) for k in range(3)]))
        miss = ~np.array(blocker.ray_intersect(ray).is_valid())
        dirs.append(d[miss])
        colours.append(small[miss])
    d, y = np.concatenate(dirs), np.concatenate(colours)
    fallback = np.mean(y, axis=0) if len(y) else np.full(3, 0.5)
    if not len(y):
        out = np.tile(fallback.astype(np.float32), (height, 2 * height, 1))
        return (out, np.zeros(out.shape, bool)) if reached else out
    index = mi.UInt32(envmap_index(height, 2 * height))
    em = mi.load_dict(fitted_envmap(np.ones((height, 2 * height, 3), np.float32)))
    params = mi.traverse(em)
    shape = tuple(params["data"].shape)
    si = dr.zeros(mi.SurfaceInteraction3f, len(d))
    si.wi = mi.Vector3f(*[mi.Float((-d[:, k]).astype(np.float32)) for k in range(3)])
    sums = []
    for weights in (y, np.ones_like(y)):
        e = dr.zeros(mi.Float, height * 2 * height * 3)
        dr.enable_grad(e)
        params["data"] = mi.TensorXf(dr.gather(mi.Float, e, index), shape)
        params.update()
        val = em.eval(si)
        w = mi.Color3f(*[mi.Float(weights[:, k].astype(np.float32)) for k in range(3)])
        dr.backward(dr.sum(val.x * w.x + val.y * w.y + val.z * w.z))
        sums.append(np.array(dr.grad(e), np.float64).reshape(height, 2 * height, 3))
    hit = sums[1] > 1e-6
    out = np.clip(np.where(hit, sums[0] / np.maximum(sums[1], 1e-12), fallback), 0.0, None).astype(np.float32)
    return (out, hit) if reached else out
