"""Face PBR material fitting in UV space through the shared GGX shader (seed 003).

Unknowns per texel u: albedo T_alb (3), tangent-space normal (2 slopes), roughness,
specular; displacement follows from the fitted normals (see :func:`integrate_normals`).
Loss (seed 003's shading loss, L2 on shaded textures, plus regularisers):

    L = Σ_{v,k} mean_u M_v(u) ‖T̂_shaded(u; maps, light k, view v) − T_{v,k}(u)‖²
        + λ_r ‖∇ roughness‖² + λ_s ‖∇ specular‖² + λ_n ‖∇ slopes‖² + λ_c chroma(T_alb)

T̂ is :func:`mi_plugins.uv_shader.shade_uv` — the same GGX functions as the
``ggx_uv`` plugin. Optimised with Adam in Dr.Jit over a coarse-to-fine pyramid
(each level initialised by upsampling the previous one).

Lighting: known (light stage) or fitted jointly (``fit_lights``): directions,
RGB intensities and an ambient term; albedo and light intensity then share a
global scale that no image can resolve, so metrics compare albedo after the
least-squares global scale (stated in the results).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

import mi_plugins  # noqa: F401
import drjit as dr
import mitsuba as mi

from mi_plugins.uv_shader import UVLight, UVMaps, UVView, shade_uv, unravel_channels
from photoreal.progress import progress_bar

from .face_data import FaceBenchmark
from .uv_bake import bake_geometry, load_obj


@dataclass
class FaceFitSettings:
    levels: tuple[float, ...] = (0.5, 1.0)  #: resolution fractions, coarse to fine
    iterations: tuple[int, ...] = (80, 300)  #: Adam steps per level
    lr: float = 0.02
    lr_normal: float = 0.01  #: slopes move slowly: fast normals explain shadows/albedo away
    w_smooth_roughness: float = 2.0
    w_smooth_specular: float = 2.0
    w_smooth_normal: float = 0.0
    w_chroma: float = 0.0  #: smoothness of albedo chromaticity (useful when lighting is unknown)
    fit_lights: bool = False  #: unknown lighting: fit directions, intensities and ambient
    light_init_error_deg: float = 0.0  #: perturb the initial light directions (stability tests)
    init_roughness: float = 0.5
    init_specular: float = 0.5
    seed: int = 0

    def __post_init__(self):
        if len(self.levels) != len(self.iterations):
            raise ValueError("levels and iterations must have the same length")
        if not all(0 < f <= 1 for f in self.levels):
            raise ValueError(f"levels must be fractions in (0, 1], got {self.levels}")
        if self.lr <= 0:
            raise ValueError(f"lr must be > 0, got {self.lr}")


# -- pyramid helpers -----------------------------------------------------------------------


def _downsample(img: np.ndarray, factor: int, weight: np.ndarray | None = None) -> np.ndarray:
    """Box-filter by an integer factor, optionally weighted (weights (H, W))."""
    if factor == 1:
        return img
    h, w = img.shape[:2]
    shp = (h // factor, factor, w // factor, factor) + img.shape[2:]
    if weight is None:
        return img.reshape(shp).mean(axis=(1, 3))
    wt = weight.reshape(h // factor, factor, w // factor, factor)
    num = (img * weight.reshape(weight.shape + (1,) * (img.ndim - 2))).reshape(shp).sum(axis=(1, 3))
    den = wt.sum(axis=(1, 3))
    return num / np.maximum(den, 1e-12).reshape(den.shape + (1,) * (img.ndim - 2))


def _upsample(img: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    from scipy.ndimage import zoom

    f = (shape[0] / img.shape[0], shape[1] / img.shape[1]) + (1,) * (img.ndim - 2)
    return zoom(img, f, order=1, mode="nearest")


def _tensor(a: np.ndarray) -> mi.TensorXf:
    return mi.TensorXf(np.ascontiguousarray(a, dtype=np.float32))


def _grad_penalty(t: mi.TensorXf, h: int, w: int) -> mi.Float:
    """Mean squared finite differences along rows and columns of an (H, W, C) tensor."""
    c = t.shape[2]
    flat = t.array
    idx = dr.arange(mi.UInt32, h * w * c)
    col = (idx // c) % w
    row = idx // (c * w)
    right = dr.gather(mi.Float, flat, dr.minimum(idx + c, h * w * c - 1), col < w - 1)
    down = dr.gather(mi.Float, flat, dr.minimum(idx + c * w, h * w * c - 1), row < h - 1)
    dx = dr.select(col < w - 1, right - flat, 0.0)
    dy = dr.select(row < h - 1, down - flat, 0.0)
    return dr.mean(dx * dx + dy * dy, axis=None)


# -- lights ----------------------------------------------------------------------------------


def _rotate_towards_random(d: np.ndarray, angle_deg: float, rng: np.random.Generator) -> np.ndarray:
    if angle_deg == 0:
        return d
    axis = np.cross(d, rng.normal(size=3))
    axis /= np.linalg.norm(axis)
    a = np.radians(angle_deg)
    return d * np.cos(a) + np.cross(axis, d) * np.sin(a) + axis * np.dot(axis, d) * (1 - np.cos(a))


# -- the fit ----------------------------------------------------------------------------------------


def _albedo_init(pos, nrm, tan, views, dirs, intens, vis_l, lvis, obs_l, res) -> np.ndarray:
    """Per-texel least-squares Lambert albedo on the flat template: Σ T·S / Σ S².

    S is the UV shader's diffuse shading of a white, non-specular surface, so
    this is the closed-form optimum before normals and specular are freed.
    """
    white = UVMaps(albedo=1.0, specular=0.0)
    num = np.zeros((res, res, 3))
    den = np.zeros((res, res, 1))
    for k in range(len(dirs)):
        light = UVLight("directional", tuple(dirs[k]), tuple(intens[k]))
        for v in range(len(views)):
            shade = np.array(shade_uv(pos, nrm, tan, white, [light], UVView(position=tuple(views[v])),
                                      mask=vis_l[v], light_visibility=[lvis[k]]))[..., :1]
            num += np.array(obs_l[v, k]) * shade
            den += shade * shade
    albedo = np.where(den > 1e-8, num / np.maximum(den, 1e-8), 0.4)
    return np.clip(albedo, 0.0, 1.0).astype(np.float32)



@dataclass
class FaceFitResult:
    maps: dict[str, np.ndarray]  #: albedo (H,W,3), normal (H,W,3 unit tangent-space), roughness, specular, displacement (H,W,1)
    observed: np.ndarray  #: (H, W) bool: texel lit and seen at least once
    lights: list[dict]  #: fitted (or given) lights
    ambient: float
    loss_history: list[float]
    seconds: float


def fit_face(bench: FaceBenchmark, s: FaceFitSettings | None = None, show_progress: bool = True) -> FaceFitResult:
    """Fit UV material maps to a benchmark's texel-aligned observations."""
    s = s or FaceFitSettings()
    t0 = time.perf_counter()
    rng = np.random.default_rng(s.seed)
    mesh = load_obj(bench.mesh_path)
    full = bench.geometry["mask"].shape[0]
    views = [np.asarray(v) for v in bench.meta["views"]]
    lights_meta = bench.meta["lights"]
    n_views, n_lights = len(views), len(lights_meta)

    # Light parameters (directions normalised in the loss; intensities positive).
    dirs0 = [_rotate_towards_random(np.asarray(l["to_light"]), s.light_init_error_deg, rng) for l in lights_meta]
    if s.fit_lights:
        inten0 = [np.full(3, float(np.mean(l["irradiance"]))) * 0.7 for l in lights_meta]
    else:
        inten0 = [np.asarray(l["irradiance"], float) for l in lights_meta]

    observed_full = np.zeros((full, full), bool)
    for v in range(n_views):
        for k in range(n_lights):
            obs = bench.observations[f"v{v}_l{k}"]
            observed_full |= (bench.visibility[f"v{v}"] > 0) & (obs.sum(-1) > 1e-6)

    maps_np: dict[str, np.ndarray] | None = None
    history: list[float] = []
    total_steps = sum(s.iterations)
    bar = progress_bar(total=total_steps, desc="face fit", unit="it", disable=not show_progress)
    light_params = {}
    for level, (frac, n_it) in enumerate(zip(s.levels, s.iterations)):
        res = max(8, int(round(full * frac)))
        factor = full // res
        res = full // factor
        geo = bake_geometry(mesh, res)
        mask_np = geo.mask.astype(np.float32)
        # Level data: visibility-weighted box averages; a texel counts only if every sub-texel was seen.
        obs_l, vis_l = {}, {}
        for v in range(n_views):
            vis = bench.visibility[f"v{v}"]
            vis_lv = _downsample(vis, factor)
            vis_l[v] = _tensor(((vis_lv > 0.999) & geo.mask).astype(np.float32)[..., None])
            for k in range(n_lights):
                obs_l[v, k] = _tensor(_downsample(bench.observations[f"v{v}_l{k}"], factor))
        lvis = [_tensor(_downsample(bench.visibility[f"light{k}"], factor)[..., None]) for k in range(n_lights)]
        pos, nrm, tan = _tensor(geo.position), _tensor(geo.normal), _tensor(geo.tangent)

        if maps_np is None:
            params = {
                "albedo": _albedo_init(pos, nrm, tan, views, dirs0, inten0, vis_l, lvis, obs_l, res),
                "slope": np.zeros((res, res, 2), np.float32),
                "roughness": np.full((res, res, 1), s.init_roughness, np.float32),
                "specular": np.full((res, res, 1), s.init_specular, np.float32),
            }
        else:
            params = {k: _upsample(v, (res, res)).astype(np.float32) for k, v in maps_np.items()}
        opt = mi.ad.Adam(lr=s.lr)
        for k, v in params.items():
            opt[k] = _tensor(v)
        opt.set_learning_rate({"slope": s.lr_normal})
        if s.fit_lights:
            for k in range(n_lights):
                if level == 0:
                    opt[f"dir{k}"] = mi.Vector3f(*map(float, dirs0[k]))
                    opt[f"int{k}"] = mi.Color3f(*map(float, inten0[k]))
                else:
                    opt[f"dir{k}"] = light_params[f"dir{k}"]
                    opt[f"int{k}"] = light_params[f"int{k}"]
            opt["ambient"] = mi.Float(0.0 if level == 0 else light_params["ambient"])
        n_valid = max(1.0, float(mask_np.sum()))

        for it in range(n_it):
            slope = opt["slope"]
            sx, sy = unravel_channels(slope.array, 2)
            n_ts = dr.normalize(mi.Vector3f(sx, sy, 1.0))
            enc = mi.TensorXf(dr.ravel(n_ts * 0.5 + 0.5), shape=(res, res, 3))
            maps = UVMaps(albedo=opt["albedo"], normal=enc, roughness=opt["roughness"], specular=opt["specular"])
            loss = mi.Float(0.0)
            for k in range(n_lights):
                if s.fit_lights:
                    light = UVLight("directional", dr.normalize(opt[f"dir{k}"]), opt[f"int{k}"])
                    amb = opt["ambient"]
                else:
                    light = UVLight("directional", tuple(dirs0[k]), tuple(inten0[k]))
                    amb = 0.0
                for v in range(n_views):
                    pred = shade_uv(pos, nrm, tan, maps, [light], UVView(position=tuple(views[v])),
                                    ambient=0.0, mask=vis_l[v], light_visibility=[lvis[k]])
                    if s.fit_lights:
                        pred = pred + opt["albedo"] * mi.TensorXf(amb) * vis_l[v]
                    diff = pred - obs_l[v, k] * vis_l[v]
                    loss += dr.sum(diff * diff, axis=None) / (n_valid * n_views * n_lights)
            reg = (s.w_smooth_roughness * _grad_penalty(opt["roughness"], res, res)
                   + s.w_smooth_specular * _grad_penalty(opt["specular"], res, res))
            if s.w_smooth_normal > 0:
                reg += s.w_smooth_normal * _grad_penalty(opt["slope"], res, res)
            if s.w_chroma > 0:
                # Chromaticity a / (r + g + b): shading changes brightness, rarely hue, so hue
                # edges in the albedo should be rare (a Retinex-style prior).
                alb = opt["albedo"]
                r_, g_, b_ = unravel_channels(alb.array, 3)
                total_c = dr.maximum(r_ + g_ + b_, 1e-3)
                chroma = mi.TensorXf(dr.ravel(mi.Vector3f(r_, g_, b_) / total_c), shape=alb.shape)
                reg += s.w_chroma * _grad_penalty(chroma, res, res)
            total = loss + reg
            dr.backward(total)
            opt.step()
            # Keep maps in their valid ranges (projected Adam).
            opt["albedo"] = dr.clip(opt["albedo"], 0.0, 1.0)
            opt["roughness"] = dr.clip(opt["roughness"], 0.05, 1.0)
            opt["specular"] = dr.clip(opt["specular"], 0.0, 1.0)
            opt["slope"] = dr.clip(opt["slope"], -3.0, 3.0)
            if s.fit_lights:
                for k in range(n_lights):
                    opt[f"int{k}"] = dr.maximum(opt[f"int{k}"], 0.0)
                opt["ambient"] = dr.maximum(opt["ambient"], 0.0)
            value = float(total.array[0]) if hasattr(total, "array") else float(total[0])
            if not np.isfinite(value):
                raise FloatingPointError(f"face fit: loss became {value} at level {level}, iteration {it}")
            history.append(value)
            bar.update(1)
            bar.set_postfix(level=f"{res}²", loss=f"{value:.3e}")
        maps_np = {k: np.array(opt[k]) for k in ("albedo", "slope", "roughness", "specular")}
        if s.fit_lights:
            light_params = {k: type(opt[k])(opt[k]) for k in opt.keys() if k.startswith(("dir", "int", "ambient"))}
    bar.close()

    slope = maps_np["slope"]
    n = np.concatenate([slope, np.ones(slope.shape[:2] + (1,), np.float32)], axis=-1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    observed = observed_full if maps_np["albedo"].shape[0] == full else _downsample(
        observed_full.astype(np.float32), full // maps_np["albedo"].shape[0]) > 0.5
    maps_out = {
        "albedo": maps_np["albedo"],
        "normal": n.astype(np.float32),
        "roughness": maps_np["roughness"],
        "specular": maps_np["specular"],
    }
    maps_out = fill_unobserved(maps_out, observed, bench.geometry["mask"] > 0)
    geo_full = bake_geometry(mesh, maps_out["albedo"].shape[0])
    maps_out["displacement"] = integrate_normals(maps_out["normal"], geo_full.bitangent_sign, geo_full.mask)
    if s.fit_lights:
        lights = [{"kind": "directional",
                   "to_light": (np.array(light_params[f"dir{k}"]).ravel() /
                                np.linalg.norm(np.array(light_params[f"dir{k}"]).ravel())).tolist(),
                   "irradiance": np.array(light_params[f"int{k}"]).ravel().tolist()} for k in range(n_lights)]
        ambient = float(np.array(light_params["ambient"]).ravel()[0])
    else:
        lights, ambient = lights_meta, 0.0
    return FaceFitResult(maps_out, observed, lights, ambient, history, time.perf_counter() - t0)


def fill_unobserved(maps: dict[str, np.ndarray], observed: np.ndarray, valid: np.ndarray,
                    iterations: int = 200) -> dict[str, np.ndarray]:
    """Harmonic fill of texels that no observation constrains (baseline inpainting)."""
    hole = valid & ~observed
    if not hole.any():
        return maps
    out = {}
    for name, m in maps.items():
        a = m.copy()
        known = observed.copy()
        if known.any():
            mean = a[known].mean(axis=0)
            a[~known] = mean
        for _ in range(iterations):
            p = np.pad(a, ((1, 1), (1, 1)) + ((0, 0),) * (a.ndim - 2), mode="edge")
            avg = 0.25 * (p[:-2, 1:-1] + p[2:, 1:-1] + p[1:-1, :-2] + p[1:-1, 2:])
            a[hole] = avg[hole]
        if name == "normal":
            a /= np.linalg.norm(a, axis=-1, keepdims=True)
        out[name] = a.astype(np.float32)
    return out


def integrate_normals(normal: np.ndarray, bitangent_sign: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Height field (H, W, 1) in [0, 1] whose gradient best matches the normals (Poisson, FFT).

    Shading constrains displacement only through its gradient (s_disp = 0.01
    moves points by 1% of a unit, invisible to directional lights and a far
    camera), so displacement is recovered up to scale and offset from the
    fitted normals, normalised to [0, 1] like the ground truth.
    """
    nz = np.maximum(normal[..., 2], 1e-3)
    gx = np.where(mask, -normal[..., 0] / nz, 0.0)
    gy = np.where(mask, -normal[..., 1] / nz * np.where(bitangent_sign == 0, 1, bitangent_sign), 0.0)
    h, w = gx.shape
    # Divergence, then solve Δz = div with the FFT (periodic boundary, zero-mean).
    div = np.zeros_like(gx)
    div[:, 1:] += gx[:, 1:] - gx[:, :-1]
    div[1:, :] += gy[1:, :] - gy[:-1, :]
    fy = np.fft.fftfreq(h)[:, None]
    fx = np.fft.fftfreq(w)[None, :]
    denom = (2 * np.cos(2 * np.pi * fx) - 2) + (2 * np.cos(2 * np.pi * fy) - 2)
    denom[0, 0] = 1.0
    z = np.real(np.fft.ifft2(np.fft.fft2(div) / denom))
    z -= z[mask].min() if mask.any() else z.min()
    rng = z[mask].max() if mask.any() else z.max()
    return (z / max(rng, 1e-12))[..., None].astype(np.float32)


def save_maps(maps: dict[str, np.ndarray], out: Path) -> None:
    """Write fitted maps: one EXR plus PNG previews (albedo sRGB, normal encoded)."""
    from photoreal import imageio

    out.mkdir(parents=True, exist_ok=True)
    imageio.write_exr(out / "maps.exr", maps)
    imageio.write_png(out / "albedo.png", maps["albedo"])
    imageio.write_png(out / "normal.png", maps["normal"] * 0.5 + 0.5, linear=False)
    imageio.write_png(out / "roughness.png", np.repeat(maps["roughness"], 3, -1), linear=False)
    imageio.write_png(out / "specular.png", np.repeat(maps["specular"], 3, -1), linear=False)
    imageio.write_png(out / "displacement.png", np.repeat(maps["displacement"], 3, -1), linear=False)


def evaluate_fit(bench: FaceBenchmark, result: FaceFitResult, relight: bool = True,
                 images: dict | None = None) -> dict:
    """Metrics against the benchmark's ground truth and held-out relighting.

    Albedo is compared after the least-squares global scale (reported as
    ``albedo_scale``): with unknown lighting, albedo × light intensity is only
    known up to that factor. Map metrics use the texels that at least one
    observation constrains (``observed_fraction`` of the covered ones).
    Relighting renders the fitted maps (scaled albedo) under each held-out
    HDRI with the benchmark's camera, spp and seed, and compares with the
    ground-truth render on the face pixels. Pass a dict as ``images`` to
    receive the relit renders ({hdri: (H, W, 3)}).
    """
    from photoreal.metrics import angular_error_deg, flip, global_scale, masked_psnr, psnr, ssim

    from .face_data import render_heldout

    gt, fit, m = bench.ground_truth, result.maps, result.observed
    covered = bench.geometry["mask"] > 0
    scale = global_scale(fit["albedo"][m], gt["albedo"][m])
    albedo = np.clip(fit["albedo"] * scale, 0, 1)
    a_img, g_img = np.where(m[..., None], albedo, 0), np.where(m[..., None], gt["albedo"], 0)
    disp_corr = float(np.corrcoef(fit["displacement"][covered].ravel(), gt["displacement"][covered].ravel())[0, 1])
    out = {
        "albedo_psnr": psnr(albedo[m], gt["albedo"][m]),
        "albedo_ssim": ssim(a_img, g_img),
        "albedo_scale": scale,
        "normal_err_deg": float(angular_error_deg(fit["normal"][m], gt["normal"][m]).mean()),
        "normal_err_deg_median": float(np.median(angular_error_deg(fit["normal"][m], gt["normal"][m]))),
        "roughness_mae": float(np.abs(fit["roughness"][m] - gt["roughness"][m]).mean()),
        "specular_mae": float(np.abs(fit["specular"][m] - gt["specular"][m]).mean()),
        "displacement_corr": disp_corr,
        "observed_fraction": float(m[covered].mean()),
        "seconds": result.seconds,
        "uv_res": int(m.shape[0]),
    }
    if relight:
        s = bench.settings
        cam = bench.meta["heldout_camera"]
        maps = dict(fit, albedo=albedo)
        per = {}
        for hdri in s.heldout_hdris:
            rgb, _ = render_heldout(bench.mesh_path, maps, s, hdri, np.asarray(cam["eye"]),
                                    np.asarray(cam["target"]), cam["fov"])
            ref = bench.heldout[hdri]
            mask = bench.heldout[f"{hdri}_mask"][..., 0] > 0.5
            per[hdri] = {"psnr": masked_psnr(rgb, ref, mask), "flip": flip(rgb, ref, mask=mask)}
            if images is not None:
                images[hdri] = rgb
        out["relit"] = per
        out["relit_psnr"] = float(np.mean([v["psnr"] for v in per.values()]))
        out["relit_flip"] = float(np.mean([v["flip"] for v in per.values()]))
    return out


# -- fitting through full Mitsuba renders ------------------------------------------------------


@dataclass
class RenderRefineSettings:
    iterations: int = 10
    spp: int = 4
    lr: float = 0.005
    seed: int = 0


def refine_through_renders(bench: FaceBenchmark, maps: dict[str, np.ndarray], s: RenderRefineSettings | None = None,
                           show_progress: bool = True) -> tuple[dict[str, np.ndarray], list[float]]:
    """Refine albedo, roughness and normal maps by differentiating *camera renders* (``prb``).

    The scan is rendered with the ``ggx_uv`` plugin from the benchmark's views
    under each training light and compared (L2) with the benchmark's camera
    images; gradients flow through Mitsuba into the plugin's bitmap textures.
    This exercises the plugin's derivatives the way an image-space pipeline
    would use them; the UV-space fit is the fast path. Returns the refined
    maps and the per-iteration camera-space loss.
    """
    from .face_data import camera_sensor, directional_emitters, scan_scene

    s = s or RenderRefineSettings()
    if not bench.camera:
        raise ValueError(f"{bench.path}: benchmark has no camera images (made by an older version?)")
    bs = bench.settings
    lights = bench.meta["lights"]
    centre = np.asarray(bench.meta["centre"])
    fov = bench.meta.get("camera_fov", bench.meta["heldout_camera"]["fov"])
    scene = scan_scene(bench.mesh_path, maps, bs, directional_emitters(lights), integrator={"type": "prb", "max_depth": 2})
    sensors = [mi.load_dict(camera_sensor(np.asarray(eye), centre, bs.render_res, fov)) for eye in bench.meta["views"]]
    params = mi.traverse(scene)
    prefix = "scan.bsdf.brdf_0."
    keys = {"albedo": prefix + "albedo.data", "roughness": prefix + "roughness.data", "normal": prefix + "normal.data"}
    irr = {k: mi.Color3f(params[f"light{k}.irradiance.value"]) for k in range(len(lights))}
    opt = mi.ad.Adam(lr=s.lr)
    for name, key in keys.items():
        opt[key] = params[key]
    params.update(opt)
    history = []
    n_img = len(lights) * len(sensors)
    with progress_bar(total=s.iterations, desc="refine through renders", unit="it", disable=not show_progress) as bar:
        for it in range(s.iterations):
            total = 0.0
            for k in range(len(lights)):
                for j in range(len(lights)):  # one light at a time, as in the benchmark images
                    params[f"light{j}.irradiance.value"] = irr[j] if j == k else mi.Color3f(0.0)
                params.update(opt)
                for v, sensor in enumerate(sensors):
                    img = mi.render(scene, params, sensor=sensor, spp=s.spp, seed=s.seed + it * 1000 + k * 10 + v)
                    target = mi.TensorXf(np.ascontiguousarray(bench.camera[f"v{v}_l{k}"], np.float32))
                    loss = dr.mean(dr.square(img[..., :3] - target), axis=None) / n_img
                    dr.backward(loss)
                    total += float(loss.array[0])
            opt.step()
            opt[keys["albedo"]] = dr.clip(opt[keys["albedo"]], 0.0, 1.0)
            opt[keys["roughness"]] = dr.clip(opt[keys["roughness"]], 0.05, 1.0)
            opt[keys["normal"]] = dr.clip(opt[keys["normal"]], 0.0, 1.0)
            params.update(opt)
            if not np.isfinite(total):
                raise FloatingPointError(f"refine_through_renders: loss became {total} at iteration {it}")
            history.append(total)
            bar.update(1)
    out = dict(maps)
    out["albedo"] = np.array(params[keys["albedo"]])
    out["roughness"] = np.array(params[keys["roughness"]])
    n = np.array(params[keys["normal"]]) * 2.0 - 1.0
    out["normal"] = (n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-8)).astype(np.float32)
    del scene, params, opt
    return out, history
