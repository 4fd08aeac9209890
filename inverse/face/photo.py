"""One real photograph → a relightable face (seed 003's pipeline with optimisation baselines).

Steps (each a function; :func:`photo_to_face` runs them all):

1. **Landmarks**: MediaPipe Face Mesh (0.10.14, models inside the wheel, offline)
   gives 468 points; landmark i ↔ vertex i of MediaPipe's canonical face
   template. Landmarks can also come from a file (``.npy``/``.json``, 468×3
   normalised x, y, z as MediaPipe writes them), so nothing below needs mediapipe.
2. **Template fit**: similarity (Umeyama) + Laplacian-regularised per-vertex
   deformation, solved in closed form: (I + λ LᵀL) D = Q − V.
3. **Unwrap** the photo into the template's UV space with a visibility mask
   (self-occlusion by ray casting, grazing angles down-weighted).
4. **Fill** unseen texels: mirror across the UV layout's symmetry axis where
   the mirror texel was seen, then a harmonic (smooth) fill.
5. **Delight**: lighting is unknown, so a few directional lights + ambient
   are fitted jointly with a constant skin colour through the UV-space GGX
   shader; albedo = photo texture / fitted shading of a white surface.
6. **Decompose**: normal = the fitted template's (flat map), roughness and
   specular = skin defaults — a baseline, stated as such (the paper uses
   learned diffusion models here).
7. **Relight** the textured mesh in Mitsuba with ``ggx_uv`` under real HDRIs.

Coordinates: "image space" has X = column (px), Y = H − row (px, up), Z
towards the viewer (px), so an orthographic camera looking down −Z sees the photo.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

import mi_plugins  # noqa: F401
import drjit as dr
import mitsuba as mi
from mi_plugins.arrays import aligned

from foundation import imageio, validate
from foundation.assets import FACE, envmap, hdri_path
from foundation.errors import FailureError, UsageError
from foundation.files import atomic_dir, write_json
from foundation.loop import DrJitStage, LoopSettings, RunState, StepResult, run_loop
from foundation.mesh import UVMesh, graph_laplacian, load_obj, write_obj
from foundation.progress import progress_bar
from foundation.records import to_json
from mi_plugins.uv_shader import UVLight, UVMaps, UVView, shade_uv

from .benchmark import Light
from .fit import fill_unobserved
from .uv_bake import bake_geometry

TEMPLATE = FACE / "canonical_face_model.obj"
N_LANDMARKS = 468
MARKER = "photo_face.json"  #: written last: a folder holding it is a complete from-photo output
MIN_SIDE = 64  #: smallest photo side (px) a face can be unwrapped from
PHOTO_VIEW = UVView(direction=(0.0, 0.0, 1.0))  #: the photo's orthographic camera in image space


@dataclass
class PhotoFitSettings:
    uv_res: int = 256
    laplacian_weight: float = 2.0  #: λ of the deformation prior (template units: cm)
    grazing_cos: float = 0.2  #: texels whose normal·view is below this are unseen
    n_lights: int = 2
    light_iterations: int = 300
    roughness: float = 0.5  #: skin defaults for the decomposition baseline
    specular: float = 0.35
    hdris: tuple[str, ...] = ("studio", "sunset", "forest")
    relight_res: int = 256
    relight_spp: int = 64
    seed: int = 0

    def __post_init__(self):
        validate.integer("uv_res", self.uv_res, 16, 4096)
        validate.positive("laplacian_weight", self.laplacian_weight)
        validate.in_range("grazing_cos", self.grazing_cos, 0.0, 1.0, hi_open=True)
        validate.integer("n_lights", self.n_lights, 1, 16)
        validate.integer("light_iterations", self.light_iterations, 1)
        validate.in_range("roughness", self.roughness, 0.05, 1.0)
        validate.in_range("specular", self.specular, 0.0, 1.0)
        validate.integer("relight_res", self.relight_res, 8, 4096)
        validate.integer("relight_spp", self.relight_spp, 1)
        validate.seed("seed", self.seed)
        for h in self.hdris:
            hdri_path(h)


# -- 1. landmarks ---------------------------------------------------------------------------------


def detect_landmarks(image: np.ndarray) -> np.ndarray:
    """468×3 normalised landmarks (MediaPipe's x, y in [0, 1], z relative, x-scaled)."""
    try:
        import mediapipe as mp
    except ImportError as exc:
        raise ImportError("mediapipe is not installed: `pip install mediapipe==0.10.14` (the project's "
                          "'face' extra), or pass landmarks from a file") from exc
    with mp.solutions.face_mesh.FaceMesh(static_image_mode=True, max_num_faces=1, refine_landmarks=False) as fm:
        res = fm.process(np.ascontiguousarray(image[..., :3]))
    if not res.multi_face_landmarks:
        raise UsageError("no face found in the image (pass --landmarks FILE to give them)")
    lm = np.array([[p.x, p.y, p.z] for p in res.multi_face_landmarks[0].landmark[:N_LANDMARKS]], np.float64)
    return lm


def check_landmarks(a: np.ndarray, where: str = "landmarks") -> np.ndarray:
    """468×3 MediaPipe-style landmarks: finite, x and y normalised to the image (≈ [0, 1]), not collapsed."""
    a = np.asarray(a)
    if a.ndim != 2 or a.shape[1] != 3 or a.shape[0] < N_LANDMARKS:
        raise UsageError(f"{where}: expected {N_LANDMARKS}×3 landmarks, got shape {a.shape}")
    a = a[:N_LANDMARKS].astype(np.float64)
    if not np.isfinite(a).all():
        raise UsageError(f"{where}: landmarks contain NaN/Inf")
    xy = a[:, :2]
    if xy.min() < -0.5 or xy.max() > 1.5:
        raise UsageError(f"{where}: x, y must be normalised image coordinates (MediaPipe's, ≈ 0…1); "
                         f"got values from {xy.min():.3g} to {xy.max():.3g}")
    if float(np.ptp(xy, axis=0).min()) < 1e-3:
        raise UsageError(f"{where}: landmarks are collapsed to a point or a line (spread "
                         f"{np.ptp(xy, axis=0).round(5).tolist()})")
    return a


def load_landmarks(path: str | Path) -> np.ndarray:
    """Landmarks from ``.npy`` or ``.json`` (468×3 numbers); a damaged or foreign file is named."""
    path = Path(path)
    if not path.is_file():
        raise UsageError(f"{path}: no such landmark file")
    try:
        if path.suffix == ".npy":
            a = np.load(path, allow_pickle=False)
        else:
            a = np.asarray(json.loads(path.read_text()), dtype=np.float64)
    except (ValueError, TypeError, OSError, EOFError, UnicodeDecodeError) as exc:
        msg = " ".join(str(exc).split())
        raise UsageError(f"{path}: not a readable landmark file ({N_LANDMARKS}×3 numbers as .npy or JSON): "
                         f"{msg[:160]}") from None
    return check_landmarks(a, str(path))


def landmarks_to_image_space(lm: np.ndarray, width: int, height: int) -> np.ndarray:
    """MediaPipe normalised landmarks → image space (X right, Y up, Z towards viewer; pixels)."""
    return np.stack([lm[:, 0] * width, height - lm[:, 1] * height, -lm[:, 2] * width], axis=1)


# -- 2. template fit ------------------------------------------------------------------------------------


def umeyama(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Similarity (s, R, t) minimising Σ‖s R src_i + t − dst_i‖² (Umeyama 1991)."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    cov = b.T @ a / len(src)
    u, sig, vt = np.linalg.svd(cov)
    d = np.ones(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        d[-1] = -1
    r = u @ np.diag(d) @ vt
    s = float((sig * d).sum() / (a * a).sum() * len(src))
    return s, r, mu_d - s * r @ mu_s


@dataclass
class TemplateFit:
    vertices: np.ndarray  #: fitted vertices in image space
    scale: float
    rotation: np.ndarray
    translation: np.ndarray
    reprojection_px: float  #: mean 2D distance between projected vertices and landmarks
    reprojection_px_rigid: float  #: the same for the similarity alone


def fit_template(template: UVMesh, target: np.ndarray, laplacian_weight: float) -> TemplateFit:
    """Similarity + Laplacian-regularised deformation of the template onto 3D landmarks."""
    import scipy.sparse as sp
    import scipy.sparse.linalg as spla

    v = template.vertices[:N_LANDMARKS]
    s, r, t = umeyama(v, target)
    rigid = (s * (r @ v.T)).T + t
    q = (r.T @ (target - t).T).T / s  # landmarks in template space
    lap = graph_laplacian(len(template.vertices), template.faces)
    n = len(template.vertices)
    sel = sp.eye(n, format="csr")[:N_LANDMARKS]
    a = (sel.T @ sel + laplacian_weight * (lap.T @ lap)).tocsc()
    rhs = sel.T @ (q - v)
    d = np.stack([spla.spsolve(a, rhs[:, k]) for k in range(3)], axis=1)
    fitted = (s * (r @ (template.vertices + d).T)).T + t
    err = np.linalg.norm(fitted[:N_LANDMARKS, :2] - target[:, :2], axis=1).mean()
    err_rigid = np.linalg.norm(rigid[:, :2] - target[:, :2], axis=1).mean()
    return TemplateFit(fitted, s, r, t, float(err), float(err_rigid))


# -- 3–4. unwrap and fill --------------------------------------------------------------------------------


def unwrap_photo(image: np.ndarray, mesh_path: Path, uv_res: int, grazing_cos: float):
    """Photo colours in UV space (linear), visibility weight in [0, 1], and the baked geometry."""
    from scipy.ndimage import map_coordinates

    h_img = image.shape[0]
    mesh = load_obj(mesh_path)
    geo = bake_geometry(mesh, uv_res)
    scene = mi.load_dict({"type": "scene", "face": {"type": "obj", "filename": str(mesh_path), "face_normals": False}})
    idx = np.nonzero(geo.mask.ravel())[0]
    from .uv_bake import texel_uvs

    uv = texel_uvs(uv_res, uv_res)
    si = scene.shapes()[0].eval_parameterization(mi.Point2f(aligned(np.array(uv.x)[idx]), aligned(np.array(uv.y)[idx])))
    occluded = np.array(scene.ray_test(si.spawn_ray(mi.Vector3f(0, 0, 1))))
    n = geo.normal.reshape(-1, 3)[idx]
    facing = np.clip((n[:, 2] - grazing_cos) / (1.0 - grazing_cos), 0.0, 1.0) ** 0.5
    weight = np.zeros(uv_res * uv_res)
    weight[idx] = np.where(occluded, 0.0, facing)
    p = geo.position.reshape(-1, 3)[idx]
    rows, cols = h_img - p[:, 1], p[:, 0]
    lin = imageio.srgb_to_linear(image[..., :3].astype(np.float32) / 255.0)
    colours = np.zeros((uv_res * uv_res, 3), np.float32)
    for c in range(3):
        colours[idx, c] = map_coordinates(lin[..., c], [rows - 0.5, cols - 0.5], order=1, mode="nearest")
    return colours.reshape(uv_res, uv_res, 3), weight.reshape(uv_res, uv_res), geo


def symmetric_fill(tex: np.ndarray, weight: np.ndarray, valid: np.ndarray, threshold: float = 0.3):
    """Copy from the mirror texel (u → 1 − u) where a texel is unseen but its mirror was seen."""
    mirror_tex, mirror_w = tex[:, ::-1], weight[:, ::-1]
    take = valid & (weight < threshold) & (mirror_w >= threshold) & valid[:, ::-1]
    out = tex.copy()
    out[take] = mirror_tex[take]
    seen = (weight >= threshold) | take
    return out, seen


# -- 5. delighting ------------------------------------------------------------------------------------------


@dataclass
class FittedLighting:
    lights: list[Light]
    ambient: float
    skin_colour: list[float]
    loss: list[float] = field(default_factory=list)


class LightingStage(DrJitStage):
    """Directional lights + ambient + one skin colour explaining the unwrapped photo (UV shader, Adam)."""

    name = "fit lighting"

    def __init__(self, tex: np.ndarray, weight: np.ndarray, geo, s: PhotoFitSettings, view: UVView = PHOTO_VIEW):
        rng = np.random.default_rng(s.seed)
        self.view = view
        t = lambda a: mi.TensorXf(aligned(a))  # noqa: E731
        self.s, self.shape = s, tex.shape
        self.pos, self.nrm, self.tan = t(geo.position), t(geo.normal), t(geo.tangent)
        self.w, self.target = t(weight[..., None]), t(tex)
        self.opt = mi.ad.Adam(lr=0.02)
        for k in range(s.n_lights):
            d = np.array([0.0, 0.0, 1.0]) + rng.normal(scale=0.3, size=3)
            self.opt[f"dir{k}"] = mi.Vector3f(*map(float, d / np.linalg.norm(d)))
            self.opt[f"int{k}"] = mi.Float(1.0)
        self.opt["ambient"] = mi.Float(0.2)
        self.opt["colour"] = mi.Color3f(*map(float, np.clip(np.median(tex[weight > 0.5], axis=0), 0.05, 1.0)))
        self.norm = max(1.0, float(weight.sum()))

    def step(self, it: int) -> StepResult:
        s, opt = self.s, self.opt
        lights = [UVLight("directional", dr.normalize(opt[f"dir{k}"]), mi.Color3f(opt[f"int{k}"]))
                  for k in range(s.n_lights)]
        albedo = mi.TensorXf(dr.ravel(dr.zeros(mi.Color3f, self.shape[0] * self.shape[1]) + opt["colour"]),
                             shape=self.shape)
        maps = UVMaps(albedo=albedo, roughness=s.roughness, specular=s.specular)
        pred = shade_uv(self.pos, self.nrm, self.tan, maps, lights, self.view)
        pred = pred + albedo * mi.TensorXf(opt["ambient"])
        diff = (pred - self.target) * self.w
        loss = dr.sum(diff * diff, axis=None) / self.norm
        dr.backward(loss)
        return self.result(loss)

    def apply(self, it: int) -> None:
        opt = self.opt
        opt.step()
        for k in range(self.s.n_lights):
            opt[f"int{k}"] = dr.maximum(opt[f"int{k}"], 0.0)
            # Lights stay in front of the face (the photo is lit from the camera's side of it).
            d = opt[f"dir{k}"]
            opt[f"dir{k}"] = mi.Vector3f(d.x, d.y, dr.maximum(d.z, 0.05))
        opt["ambient"] = dr.maximum(opt["ambient"], 0.0)
        opt["colour"] = dr.clip(opt["colour"], 0.01, 1.0)

    def finish(self, run: RunState) -> FittedLighting:
        opt, lights = self.opt, []
        for k in range(self.s.n_lights):
            d = np.array(opt[f"dir{k}"]).ravel()
            lights.append(Light("directional", tuple(map(float, d / np.linalg.norm(d))),
                                (float(np.array(opt[f"int{k}"]).ravel()[0]),) * 3))
        return FittedLighting(lights, float(np.array(opt["ambient"]).ravel()[0]),
                              np.array(opt["colour"]).ravel().tolist(), list(run.losses))


def fit_lighting(tex: np.ndarray, weight: np.ndarray, geo, s: PhotoFitSettings,
                 show_progress: bool = False, view: UVView = PHOTO_VIEW) -> FittedLighting:
    """Fit :class:`LightingStage` (the shared loop, in memory: it takes seconds)."""
    return run_loop(LightingStage(tex, weight, geo, s, view), LoopSettings(steps=s.light_iterations),
                    show_progress=show_progress)


def white_shading(geo, lighting: FittedLighting, s: PhotoFitSettings, view: UVView = PHOTO_VIEW) -> np.ndarray:
    """Diffuse shading of a white, non-specular surface under the fitted lights + ambient."""
    t = lambda a: mi.TensorXf(aligned(a))  # noqa: E731
    lights = [UVLight("directional", tuple(l.to_light), tuple(l.irradiance)) for l in lighting.lights]
    out = shade_uv(t(geo.position), t(geo.normal), t(geo.tangent), UVMaps(albedo=1.0, specular=0.0), lights,
                   view, ambient=lighting.ambient)
    return np.array(out)


@dataclass
class DelitTexture:
    """Steps 4–5 of the baseline: the filled lit texture, the albedo, and how it was obtained."""

    albedo: np.ndarray  #: (H, W, 3) linear, complete over the valid texels
    filled: np.ndarray  #: the lit texture after the mirror + harmonic fill
    seen: np.ndarray  #: texels seen or mirror-filled
    shading: np.ndarray  #: fitted white shading
    lighting: FittedLighting


def fill_and_delight(tex: np.ndarray, weight: np.ndarray, geo, s: PhotoFitSettings, view: UVView = PHOTO_VIEW,
                     show_progress: bool = False) -> DelitTexture:
    """The optimisation baseline of completion + light homogenisation: mirror fill (u → 1 − u) and a harmonic fill
    of the lit texture, then albedo = texture ÷ the fitted white shading (directional lights + ambient through the
    UV shader, one constant skin colour). ``weight``: visibility in [0, 1] (> 0.3 counts as seen)."""
    valid = geo.mask
    filled, seen = symmetric_fill(tex, weight, valid)
    filled = fill_unobserved({"t": filled}, seen, valid)["t"]
    lighting = fit_lighting(tex, weight * valid, geo, s, show_progress, view)
    shading = white_shading(geo, lighting, s, view)
    # Floor the shading (a quarter of its median) so that texels the coarse template shades too
    # darkly (nostrils, creases) do not blow up into bright albedo.
    ok = valid & seen
    floor = 0.25 * float(np.median(shading[ok])) if ok.any() else 1e-3
    albedo = np.clip(filled / np.maximum(shading, max(floor, 1e-6)), 0.0, 1.0)
    albedo = fill_unobserved({"a": albedo}, valid & (shading.mean(-1) > 0.05), valid)["a"]
    albedo = np.where(valid[..., None], albedo, albedo[valid].mean(0))
    return DelitTexture(albedo.astype(np.float32), filled, seen, shading, lighting)


# -- 6–7. relight ----------------------------------------------------------------------------------------------


def _face_scene(mesh_path: Path, maps: dict[str, np.ndarray], s: PhotoFitSettings, emitters: dict, sensor: dict) -> mi.Scene:
    def bitmap(a):
        return {"type": "bitmap", "raw": True, "data": mi.TensorXf(aligned(a))}

    inner = {"type": "ggx_uv", "albedo": bitmap(maps["albedo"]),
             "roughness": bitmap(maps["roughness"]) if "roughness" in maps else s.roughness,
             "specular": bitmap(maps["specular"]) if "specular" in maps else s.specular}
    if "normal" in maps:
        inner["normal"] = bitmap(maps["normal"] * 0.5 + 0.5)
    bsdf = {"type": "twosided", "bsdf": inner}
    return mi.load_dict({"type": "scene", "integrator": {"type": "path", "max_depth": 4},
                         "face": {"type": "obj", "filename": str(mesh_path), "bsdf": bsdf, "face_normals": False},
                         "sensor": sensor, **emitters})


def photo_camera(width: float, height: float, res_w: int | None = None, res_h: int | None = None,
                 centre: tuple[float, float] | None = None) -> dict:
    """Orthographic camera seeing a width × height window of image space (the whole photo by default).

    Mitsuba's orthographic film spans ±1 horizontally and ±1/aspect vertically
    in camera space, hence one uniform scale of width/2.
    """
    cx, cy = centre if centre is not None else (width / 2, height / 2)
    return {"type": "orthographic",
            "to_world": mi.ScalarTransform4f().look_at(origin=[cx, cy, 1e4], target=[cx, cy, 0], up=[0, 1, 0])
            @ mi.ScalarTransform4f().scale([width / 2, width / 2, 1]),
            "film": {"type": "hdrfilm", "width": res_w or int(width), "height": res_h or int(height)},
            "sampler": {"type": "independent"}}


# -- the whole pipeline ---------------------------------------------------------------------------------------------


@dataclass
class PhotoFaceResult:
    """``photo_face.json``: how well the template and the fitted lighting explain the photo."""

    landmark_reprojection_px: float
    landmark_reprojection_px_rigid: float
    rerender_psnr_visible_face: float
    visible_uv_fraction: float
    lighting: FittedLighting  #: its loss history is cut to the last value
    settings: PhotoFitSettings
    stages: str  #: "baseline" (fill, delight, template defaults) or "learned" (maps_fn)
    image_size: tuple[int, int]
    seconds: float
    outputs: list[str]


def photo_to_face(image: np.ndarray, out: str | Path, s: PhotoFitSettings | None = None,
                  landmarks: np.ndarray | None = None, show_progress: bool = True, maps_fn=None) -> PhotoFaceResult:
    """Run steps 1–7; writes maps, mesh, renders and ``photo_face.json`` into the folder ``out``.

    ``maps_fn`` replaces steps 4–6 by learned stages: called as ``maps_fn(texture, weight, geometry, albedo)``
    with the unwrapped texture, its visibility, the template's geometry maps and the baseline's albedo, it
    returns the maps (albedo, normal, roughness, specular) at the texture's resolution (the application passes
    ``generative.diffusion.photo_maps_fn`` of a trained run; this layer does not import it).
    The folder appears complete or not at all (written beside it and renamed at the end).
    """
    from scipy.ndimage import binary_erosion

    from foundation.metrics import masked_psnr

    s = s or PhotoFitSettings()
    if image.ndim != 3 or image.shape[2] < 3:
        raise UsageError(f"expected an RGB image, got shape {image.shape}")
    h, w = image.shape[:2]
    if min(h, w) < MIN_SIDE:
        raise UsageError(f"the photo is {w}×{h} pixels; a face needs at least {MIN_SIDE}×{MIN_SIDE}")
    if landmarks is not None:
        landmarks = check_landmarks(landmarks)
    t0 = time.perf_counter()
    steps = 7 + len(s.hdris)
    with atomic_dir(out, MARKER) as tmp, \
            progress_bar(total=steps, desc="photo → face", unit="step", disable=not show_progress) as bar:
        lm = detect_landmarks(image) if landmarks is None else landmarks
        write_json(tmp / "landmarks.json", lm.tolist())
        bar.update(1)
        target = landmarks_to_image_space(lm, w, h)
        template = load_obj(TEMPLATE)
        fit = fit_template(template, target, s.laplacian_weight)
        if not np.isfinite(fit.vertices).all():
            raise FailureError("the template fit to the landmarks is not finite (degenerate landmarks?)")
        mesh_path = write_obj(tmp / "face_fitted.obj", fit.vertices, template)
        bar.update(1)
        tex, weight, geo = unwrap_photo(image, mesh_path, s.uv_res, s.grazing_cos)
        valid = geo.mask
        if not (weight[valid] > 0.3).any():
            raise UsageError("no texel of the face template is visible in the photo (do the landmarks belong to it?)")
        bar.update(1)
        delit = fill_and_delight(tex, weight, geo, s)
        albedo, shading, lighting = delit.albedo, delit.shading, delit.lighting
        maps = {"albedo": albedo}
        if maps_fn is not None:
            maps = maps_fn(tex, weight, geo, albedo)
            missing = {"albedo", "normal", "roughness", "specular"} - set(maps)
            if missing or any(maps[k].shape[:2] != albedo.shape[:2] for k in maps):
                raise FailureError(f"the learned stages returned maps {sorted(maps)} of shapes "
                                   f"{[maps[k].shape for k in maps]}; expected albedo, normal, roughness, specular at "
                                   f"{albedo.shape[:2]}")
            albedo = maps["albedo"]
        bar.update(3)

        # Re-render under the fitted lighting from the photo's camera; compare on the visible face.
        emit = {f"l{k}": {"type": "directional", "direction": (-np.asarray(l.to_light)).tolist(),
                          "irradiance": {"type": "rgb", "value": list(l.irradiance)}}
                for k, l in enumerate(lighting.lights)}
        emit["amb"] = {"type": "constant", "radiance": {"type": "rgb", "value": [lighting.ambient] * 3}}
        scene = _face_scene(mesh_path, maps, s, emit, photo_camera(w, h))
        rerender = np.array(mi.render(scene, spp=s.relight_spp, seed=s.seed))[..., :3]
        cover = mi.load_dict({"type": "scene", "integrator": {"type": "aov", "aovs": "dd:depth"},
                              "face": {"type": "obj", "filename": str(mesh_path)},
                              "sensor": photo_camera(w, h)})
        # Visible face region: covered pixels, eroded by 2 px so that silhouette pixels (which
        # mix the face with the background) do not count.
        face_px = binary_erosion(np.array(mi.render(cover, spp=1))[..., 0] > 0, iterations=2)
        if not face_px.any():
            raise UsageError(f"the fitted face covers no pixel of the {w}×{h} photo (landmarks outside the face?)")
        photo_lin = imageio.srgb_to_linear(image[..., :3].astype(np.float32) / 255.0)
        rerender_psnr = masked_psnr(rerender, photo_lin, face_px)
        del scene, cover
        bar.update(1)

        lo, hi = fit.vertices[:, :2].min(0), fit.vertices[:, :2].max(0)
        side = 1.15 * float((hi - lo).max())
        for hdri in s.hdris:
            # Framed on the face, seen from the photo's viewpoint.
            cam = photo_camera(side, side, s.relight_res, s.relight_res, centre=tuple((lo + hi) / 2))
            scene = _face_scene(mesh_path, maps, s, {"env": envmap(hdri)}, cam)
            imageio.write_png(tmp / f"relit_{hdri}.png", np.array(mi.render(scene, spp=s.relight_spp, seed=s.seed))[..., :3])
            del scene
            bar.update(1)

        imageio.write_exr(tmp / "maps.exr", {**maps, "photo_uv": tex, "visibility": weight, "shading": shading})
        if "normal" in maps:
            imageio.write_png(tmp / "normal.png", maps["normal"] * 0.5 + 0.5, linear=False)
            imageio.write_png(tmp / "roughness.png", np.repeat(maps["roughness"], 3, -1), linear=False)
            imageio.write_png(tmp / "specular.png", np.repeat(maps["specular"], 3, -1), linear=False)
        imageio.write_png(tmp / "albedo.png", albedo)
        imageio.write_png(tmp / "photo_uv.png", tex * (weight[..., None] > 0))
        imageio.write_png(tmp / "visibility.png", np.repeat(weight[..., None], 3, -1), linear=False)
        imageio.write_png(tmp / "rerender.png", rerender)
        imageio.write_png(tmp / "photo.png", image[..., :3])
        result = PhotoFaceResult(
            landmark_reprojection_px=fit.reprojection_px, landmark_reprojection_px_rigid=fit.reprojection_px_rigid,
            rerender_psnr_visible_face=rerender_psnr, visible_uv_fraction=float((weight[valid] > 0.3).mean()),
            lighting=FittedLighting(lighting.lights, lighting.ambient, lighting.skin_colour, lighting.loss[-1:]),
            settings=s, stages="baseline" if maps_fn is None else "learned", image_size=(w, h),
            seconds=time.perf_counter() - t0,
            outputs=sorted([*(p.name for p in tmp.iterdir()), MARKER]))
        write_json(tmp / MARKER, to_json(result))
    return result
