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
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

import mi_plugins  # noqa: F401
import drjit as dr
import mitsuba as mi

from mi_plugins.uv_shader import UVLight, UVMaps, UVView, shade_uv
from photoreal import imageio
from photoreal.progress import progress_bar

from .face_fit import fill_unobserved
from .uv_bake import UVMesh, bake_geometry, load_obj

ASSETS = Path(__file__).resolve().parent.parent / "scenes" / "assets"
TEMPLATE = ASSETS / "face" / "canonical_face_model.obj"
N_LANDMARKS = 468


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
        raise ValueError("no face found in the image")
    lm = np.array([[p.x, p.y, p.z] for p in res.multi_face_landmarks[0].landmark[:N_LANDMARKS]], np.float64)
    return lm


def load_landmarks(path: str | Path) -> np.ndarray:
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such landmark file")
    a = np.load(path) if path.suffix == ".npy" else np.asarray(json.loads(path.read_text()), np.float64)
    if a.ndim != 2 or a.shape[1] != 3 or a.shape[0] < N_LANDMARKS or not np.isfinite(a).all():
        raise ValueError(f"{path}: expected {N_LANDMARKS}×3 finite landmarks, got {a.shape}")
    return a[:N_LANDMARKS]


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


def graph_laplacian(n: int, faces: np.ndarray):
    import scipy.sparse as sp

    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    e = np.concatenate([e, e[:, ::-1]])
    adj = sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n)).tocsr()
    adj.data[:] = 1.0
    deg = np.asarray(adj.sum(1)).ravel()
    return sp.diags(deg) - adj


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


def write_obj(path: Path, vertices: np.ndarray, template: UVMesh) -> Path:
    """OBJ with the template's faces and texture coordinates (atomic write)."""
    lines = [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in vertices]
    lines += [f"vt {u:.6f} {w:.6f}" for u, w in template.uvs]
    lines += [f"f {a + 1}/{ta + 1} {b + 1}/{tb + 1} {c + 1}/{tc + 1}"
              for (a, b, c), (ta, tb, tc) in zip(template.faces, template.face_uvs)]
    with imageio.atomic_path(path) as tmp:
        tmp.write_text("\n".join(lines) + "\n")
    return path


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
    si = scene.shapes()[0].eval_parameterization(mi.Point2f(np.array(uv.x)[idx], np.array(uv.y)[idx]))
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
    lights: list[dict]
    ambient: float
    skin_colour: list[float]
    loss: list[float]


def fit_lighting(tex: np.ndarray, weight: np.ndarray, geo, s: PhotoFitSettings) -> FittedLighting:
    """Directional lights + ambient + one skin colour explaining the unwrapped photo (UV shader, Adam)."""
    rng = np.random.default_rng(s.seed)
    t = lambda a: mi.TensorXf(np.ascontiguousarray(a, np.float32))  # noqa: E731
    pos, nrm, tan = t(geo.position), t(geo.normal), t(geo.tangent)
    w = t(weight[..., None])
    target = t(tex)
    opt = mi.ad.Adam(lr=0.02)
    for k in range(s.n_lights):
        d = np.array([0.0, 0.0, 1.0]) + rng.normal(scale=0.3, size=3)
        opt[f"dir{k}"] = mi.Vector3f(*map(float, d / np.linalg.norm(d)))
        opt[f"int{k}"] = mi.Float(1.0)
    opt["ambient"] = mi.Float(0.2)
    opt["colour"] = mi.Color3f(*map(float, np.clip(np.median(tex[weight > 0.5], axis=0), 0.05, 1.0)))
    norm = max(1.0, float(weight.sum()))
    history = []
    for _ in range(s.light_iterations):
        lights = [UVLight("directional", dr.normalize(opt[f"dir{k}"]), mi.Color3f(opt[f"int{k}"]))
                  for k in range(s.n_lights)]
        colour = opt["colour"]
        albedo = mi.TensorXf(dr.ravel(dr.zeros(mi.Color3f, tex.shape[0] * tex.shape[1]) + colour), shape=tex.shape)
        maps = UVMaps(albedo=albedo, roughness=s.roughness, specular=s.specular)
        pred = shade_uv(pos, nrm, tan, maps, lights, UVView(direction=(0.0, 0.0, 1.0)))
        pred = pred + albedo * mi.TensorXf(opt["ambient"])
        diff = (pred - target) * w
        loss = dr.sum(diff * diff, axis=None) / norm
        dr.backward(loss)
        opt.step()
        for k in range(s.n_lights):
            opt[f"int{k}"] = dr.maximum(opt[f"int{k}"], 0.0)
            # Lights stay in front of the face (the photo is lit from the camera's side of it).
            d = opt[f"dir{k}"]
            opt[f"dir{k}"] = mi.Vector3f(d.x, d.y, dr.maximum(d.z, 0.05))
        opt["ambient"] = dr.maximum(opt["ambient"], 0.0)
        opt["colour"] = dr.clip(opt["colour"], 0.01, 1.0)
        history.append(float(loss.array[0]))
    lights = []
    for k in range(s.n_lights):
        d = np.array(opt[f"dir{k}"]).ravel()
        lights.append({"kind": "directional", "to_light": (d / np.linalg.norm(d)).tolist(),
                       "irradiance": [float(np.array(opt[f"int{k}"]).ravel()[0])] * 3})
    return FittedLighting(lights, float(np.array(opt["ambient"]).ravel()[0]),
                          np.array(opt["colour"]).ravel().tolist(), history)


def white_shading(geo, lighting: FittedLighting, s: PhotoFitSettings) -> np.ndarray:
    """Diffuse shading of a white, non-specular surface under the fitted lights + ambient."""
    t = lambda a: mi.TensorXf(np.ascontiguousarray(a, np.float32))  # noqa: E731
    lights = [UVLight("directional", tuple(l["to_light"]), tuple(l["irradiance"])) for l in lighting.lights]
    out = shade_uv(t(geo.position), t(geo.normal), t(geo.tangent), UVMaps(albedo=1.0, specular=0.0), lights,
                   UVView(direction=(0.0, 0.0, 1.0)), ambient=lighting.ambient)
    return np.array(out)


# -- 6–7. relight ----------------------------------------------------------------------------------------------


def _face_scene(mesh_path: Path, albedo: np.ndarray, s: PhotoFitSettings, emitters: dict, sensor: dict) -> mi.Scene:
    bsdf = {"type": "twosided", "bsdf": {
        "type": "ggx_uv", "albedo": {"type": "bitmap", "raw": True, "data": mi.TensorXf(albedo.astype(np.float32))},
        "roughness": s.roughness, "specular": s.specular}}
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


def photo_to_face(image: np.ndarray, out: str | Path, s: PhotoFitSettings | None = None,
                  landmarks: np.ndarray | None = None, show_progress: bool = True) -> dict:
    """Run steps 1–7; writes maps, mesh, renders and ``photo_face.json`` into ``out``."""
    from photoreal.metrics import masked_psnr

    s = s or PhotoFitSettings()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    if image.ndim != 3 or image.shape[2] < 3:
        raise ValueError(f"expected an RGB image, got shape {image.shape}")
    t0 = time.perf_counter()
    h, w = image.shape[:2]
    steps = 7 + len(s.hdris)
    with progress_bar(total=steps, desc="photo → face", unit="step", disable=not show_progress) as bar:
        lm = detect_landmarks(image) if landmarks is None else landmarks
        (out / "landmarks.json").write_text(json.dumps(lm.tolist()))
        bar.update(1)
        target = landmarks_to_image_space(lm, w, h)
        template = load_obj(TEMPLATE)
        fit = fit_template(template, target, s.laplacian_weight)
        mesh_path = write_obj(out / "face_fitted.obj", fit.vertices, template)
        bar.update(1)
        tex, weight, geo = unwrap_photo(image, mesh_path, s.uv_res, s.grazing_cos)
        bar.update(1)
        valid = geo.mask
        filled, seen = symmetric_fill(tex, weight, valid)
        filled = fill_unobserved({"t": filled}, seen, valid)["t"]
        bar.update(1)
        lighting = fit_lighting(tex, weight * valid, geo, s)
        bar.update(1)
        shading = white_shading(geo, lighting, s)
        # Floor the shading (a quarter of its median) so that texels the coarse template shades too
        # darkly (nostrils, creases) do not blow up into bright albedo.
        floor = 0.25 * float(np.median(shading[valid & seen]))
        albedo = np.clip(filled / np.maximum(shading, floor), 0.0, 1.0)
        albedo = fill_unobserved({"a": albedo}, valid & (shading.mean(-1) > 0.05), valid)["a"]
        albedo = np.where(valid[..., None], albedo, albedo[valid].mean(0))
        bar.update(1)

        # Re-render under the fitted lighting from the photo's camera; compare on the visible face.
        emit = {f"l{k}": {"type": "directional", "direction": (-np.asarray(l["to_light"])).tolist(),
                          "irradiance": {"type": "rgb", "value": l["irradiance"]}} for k, l in enumerate(lighting.lights)}
        emit["amb"] = {"type": "constant", "radiance": {"type": "rgb", "value": [lighting.ambient] * 3}}
        scene = _face_scene(mesh_path, albedo, s, emit, photo_camera(w, h))
        rerender = np.array(mi.render(scene, spp=s.relight_spp, seed=s.seed))[..., :3]
        cover = mi.load_dict({"type": "scene", "integrator": {"type": "aov", "aovs": "dd:depth"},
                              "face": {"type": "obj", "filename": str(mesh_path)},
                              "sensor": photo_camera(w, h)})
        from scipy.ndimage import binary_erosion

        # Visible face region: covered pixels, eroded by 2 px so that silhouette pixels (which
        # mix the face with the background) do not count.
        face_px = binary_erosion(np.array(mi.render(cover, spp=1))[..., 0] > 0, iterations=2)
        photo_lin = imageio.srgb_to_linear(image[..., :3].astype(np.float32) / 255.0)
        rerender_psnr = masked_psnr(rerender, photo_lin, face_px)
        del scene, cover
        bar.update(1)

        relit = {}
        lo, hi = fit.vertices[:, :2].min(0), fit.vertices[:, :2].max(0)
        side = 1.15 * float((hi - lo).max())
        for hdri in s.hdris:
            env = {"env": {"type": "envmap", "filename": str(ASSETS / "hdri" / f"{hdri}.exr")}}
            # Framed on the face, seen from the photo's viewpoint.
            cam = photo_camera(side, side, s.relight_res, s.relight_res, centre=tuple((lo + hi) / 2))
            scene = _face_scene(mesh_path, albedo, s, env, cam)
            relit[hdri] = np.array(mi.render(scene, spp=s.relight_spp, seed=s.seed))[..., :3]
            imageio.write_png(out / f"relit_{hdri}.png", relit[hdri])
            del scene
            bar.update(1)

    imageio.write_exr(out / "maps.exr", {"albedo": albedo, "photo_uv": tex, "visibility": weight,
                                         "shading": shading})
    imageio.write_png(out / "albedo.png", albedo)
    imageio.write_png(out / "photo_uv.png", tex * (weight[..., None] > 0))
    imageio.write_png(out / "visibility.png", np.repeat(weight[..., None], 3, -1), linear=False)
    imageio.write_png(out / "rerender.png", rerender)
    imageio.write_png(out / "photo.png", image[..., :3])
    result = {
        "landmark_reprojection_px": fit.reprojection_px,
        "landmark_reprojection_px_rigid": fit.reprojection_px_rigid,
        "rerender_psnr_visible_face": rerender_psnr,
        "visible_uv_fraction": float((weight[valid] > 0.3).mean()),
        "lighting": asdict(lighting) | {"loss": lighting.loss[-1:]},
        "settings": asdict(s),
        "image_size": [w, h],
        "seconds": time.perf_counter() - t0,
        "outputs": sorted(p.name for p in out.iterdir()),
    }
    with imageio.atomic_path(out / "photo_face.json") as tmp:
        tmp.write_text(json.dumps(result, indent=2) + "\n")
    return result
