"""Face material benchmark from a real scan: ground-truth maps + Mitsuba observations.

A scan in OBJ + texture form (the Cyberware heads ``josie``/``paul``, or any
other) becomes a benchmark with known answers:

* **Ground truth maps** at ``uv_res``: albedo = the scanned texture (sRGB →
  linear); displacement = seeded procedural skin relief (pores + wrinkles);
  normal = the tangent-space normal of that relief (so the two agree);
  roughness and specular = seeded smooth fields in skin-like ranges.
* **Light-stage observations**: Mitsuba renders the mesh with ``ggx_uv`` and
  the ground-truth maps under ``K`` directional lights from ``V`` viewpoints
  (direct lighting with cast shadows, ``path`` with max_depth 2). Each
  observation is taken *texel-aligned*: one camera ray per UV texel, from the
  viewpoint through the texel's 3D point; a texel counts as seen when the ray's
  first hit is that point. This is what a camera sees, resampled into UV
  without filtering blur.
* **Per-light visibility** (cast shadows of the known geometry) and per-view
  visibility masks, as the UV-space shader needs them.
* **Camera images** of the same views and lights (ordinary renders), for
  fitting through full Mitsuba renders instead of UV bakes.
* **Held-out lighting**: camera renders under real HDR environments, kept for
  relighting the fitted maps.

Everything is written to one folder (EXR layers + ``benchmark.json``);
:func:`load_benchmark` reads it back.
"""

from __future__ import annotations

import shutil
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

import mi_plugins  # noqa: F401
import mitsuba as mi
from mi_plugins.arrays import aligned

from foundation import imageio, validate
from foundation.assets import HDRI_DIR, envmap, hdri_label, hdri_path
from foundation.errors import UsageError
from foundation.files import atomic_dir, write_json
from foundation.mesh import MeshError, UVMesh, load_obj
from foundation.progress import progress_bar
from foundation.records import load_folder_record, to_json

from .uv_bake import GeometryMaps, bake_geometry

MARKER = "benchmark.json"  #: written last: a folder holding it is a complete face benchmark
FORMAT = "photoreal-face-benchmark/1"


@dataclass
class FaceBenchmarkSettings:
    uv_res: int = 256
    n_lights: int = 6  #: directional training lights on the frontal hemisphere
    light_spread_deg: tuple[float, float] = (60.0, 45.0)  #: max |yaw|, |pitch| of the lights from the front
    light_irradiance: float = 3.0
    views: tuple[tuple[float, float], ...] = ((0.0, 0.0), (-35.0, 5.0), (35.0, 5.0))  #: (yaw, pitch) degrees
    camera_distance: float = 4.0  #: in units of the mesh's bounding radius
    heldout_hdris: tuple[str, ...] = ("sunset", "forest", "interior")
    render_res: int = 192  #: held-out camera renders
    render_spp: int = 64
    normal_strength_deg: float = 10.0  #: RMS tilt of the ground-truth normal map
    s_disp: float = 0.01
    seed: int = 0
    #: the BSDF the observations are rendered with: ``ggx_uv`` (the fitting model itself) or Mitsuba's builtin
    #: ``principled`` (a model the fit does not know: Burley diffuse, its own Fresnel; its ``specular`` is a scalar in
    #: Mitsuba 3, so the truth's specular map is its mean there)
    observation_bsdf: str = "ggx_uv"
    #: ``directional`` (one light per observation, direct lighting, as the fit models it) or ``hdri`` (each of the
    #: ``n_lights`` observations lit by a real HDRI of ``lighting_hdris`` at a seeded rotation, path traced with
    #: interreflection; the fit then sees one directional "key light" per HDRI, its initial direction the HDRI's
    #: radiance-weighted mean direction)
    lighting: str = "directional"
    lighting_hdris: tuple[str, ...] = ("city", "courtyard", "studio", "sunrise")
    observation_spp: int = 64  #: paths per texel of an HDRI-lit observation (directional lighting is exact at 1)
    max_depth: int = 2  #: path length of the observations (2: direct light only; > 2 adds interreflection)
    albedo_blur: float = 0.0  #: rendered albedo blurred by this many texels at uv_res 256 (a thin subsurface-like spread)

    def __post_init__(self):
        validate.one_of("observation_bsdf", self.observation_bsdf, ("ggx_uv", "principled"))
        validate.one_of("lighting", self.lighting, ("directional", "hdri"))
        validate.integer("observation_spp", self.observation_spp, 1, 1 << 16)
        validate.integer("max_depth", self.max_depth, 2, 64)
        validate.non_negative("albedo_blur", self.albedo_blur)
        if self.lighting == "hdri" and not self.lighting_hdris:
            raise UsageError("lighting_hdris: at least one HDRI is needed for lighting = hdri")
        validate.integer("uv_res", self.uv_res, 8, 4096)
        validate.integer("n_lights", self.n_lights, 1, 64)
        validate.integer("render_res", self.render_res, 8, 4096)
        validate.integer("render_spp", self.render_spp, 1, 1 << 16)
        validate.positive("light_irradiance", self.light_irradiance)
        validate.positive("camera_distance", self.camera_distance)
        validate.in_range("normal_strength_deg", self.normal_strength_deg, 0.0, 80.0)
        validate.non_negative("s_disp", self.s_disp)
        validate.seed("seed", self.seed, 10_000_000)
        if not self.views:
            raise UsageError("views: at least one (yaw, pitch) view is needed")
        if not self.heldout_hdris:
            raise UsageError("heldout_hdris: at least one HDRI is needed")
        labels = [hdri_label(h) for h in self.heldout_hdris]
        if len(set(labels)) != len(labels):
            raise UsageError(f"heldout_hdris: two HDRIs share a name ({', '.join(labels)}); rename one")
        # The files are checked when a benchmark is made (.exr files are copied in; a record need not find them).


@dataclass
class Light:
    """A directional light: unit direction towards the light and RGB irradiance."""

    kind: str
    to_light: tuple[float, float, float]
    irradiance: tuple[float, float, float]
    hdri: str | None = None  #: kind "hdri": the environment that really lit the observation (to_light: its key direction)
    rotation_deg: float = 0.0  #: the environment's rotation about +y


@dataclass
class HeldoutCamera:
    eye: tuple[float, float, float]
    target: tuple[float, float, float]
    fov: float


@dataclass
class FaceBenchmarkMeta:
    """``benchmark.json`` of a face benchmark."""

    scan: str  #: the OBJ it was made from (as given)
    mesh: str  #: the benchmark's own copy of the geometry, relative to the folder
    settings: FaceBenchmarkSettings
    lights: list[Light]
    views: list[tuple[float, float, float]]  #: camera positions
    centre: tuple[float, float, float]
    radius: float
    front: tuple[float, float, float]
    heldout_camera: HeldoutCamera
    camera_fov: float
    seconds: float
    format: str = FORMAT


# -- the scan and its frame -------------------------------------------------------------


def scan_frame(mesh: UVMesh) -> tuple[np.ndarray, float, np.ndarray]:
    """Centre, bounding radius, and the direction the face looks at (mean normal)."""
    lo, hi = mesh.vertices.min(0), mesh.vertices.max(0)
    centre = 0.5 * (lo + hi)
    radius = 0.5 * float(np.linalg.norm(hi - lo))
    n = mesh.vertex_normals().mean(0)
    front = n / max(np.linalg.norm(n), 1e-12)
    return centre, radius, front


def orbit_direction(front: np.ndarray, yaw_deg: float, pitch_deg: float, up=(0.0, 1.0, 0.0)) -> np.ndarray:
    """Unit direction obtained by turning ``front`` by yaw about ``up`` and pitch about the side axis."""
    up = np.asarray(up, float)
    f = front - up * np.dot(front, up)
    f = f / max(np.linalg.norm(f), 1e-12) if np.linalg.norm(f) > 1e-6 else front
    side = np.cross(up, f)
    y, p = np.radians(yaw_deg), np.radians(pitch_deg)
    d = np.cos(p) * (np.cos(y) * f + np.sin(y) * side) + np.sin(p) * up
    return d / np.linalg.norm(d)


def training_lights(front: np.ndarray, n: int, irradiance: float, seed: int,
                    spread: tuple[float, float] = (60.0, 45.0)) -> list[Light]:
    """``n`` directional lights spread over the frontal hemisphere (seeded jitter)."""
    rng = np.random.default_rng(seed + 17)
    lights = []
    golden = np.pi * (3 - np.sqrt(5))
    for k in range(n):
        # Fibonacci-like spiral in yaw/pitch within the spread, jittered.
        r = np.sqrt((k + 0.5) / n)
        yaw = spread[0] * r * np.cos(k * golden) + rng.uniform(-5, 5)
        pitch = spread[1] * r * np.sin(k * golden) + rng.uniform(-5, 5)
        d = orbit_direction(front, yaw, pitch)
        lights.append(Light("directional", tuple(map(float, d)), (float(irradiance),) * 3))
    return lights


# -- ground-truth maps ---------------------------------------------------------------------


def smooth_noise(rng: np.random.Generator, res: int, cells: int) -> np.ndarray:
    """Bicubic-upsampled random grid in [-1, 1] (periodic-free value noise)."""
    from scipy.ndimage import zoom

    grid = rng.uniform(-1, 1, (cells + 3, cells + 3))
    up = zoom(grid, (res + 3 * res / cells) / (cells + 3), order=3)
    off = int(round(res / cells))
    return np.clip(up[off:off + res, off:off + res], -1.5, 1.5)


def skin_relief(res: int, rng: np.random.Generator) -> np.ndarray:
    """Height field in [0, 1]: pores (fine) + wrinkles (elongated) + broad undulation."""
    from scipy.ndimage import gaussian_filter

    pores = gaussian_filter(rng.normal(size=(res, res)), 0.8 * res / 256)
    pores = pores / (pores.std() + 1e-12)
    wrinkles = gaussian_filter(rng.normal(size=(res, res)), sigma=(0.7 * res / 256, 6.0 * res / 256))
    wrinkles = wrinkles / (wrinkles.std() + 1e-12)
    broad = smooth_noise(rng, res, 6)
    h = 0.35 * pores + 0.45 * wrinkles + 0.6 * broad
    return (h - h.min()) / (h.max() - h.min())


def normals_from_height(height: np.ndarray, geo: GeometryMaps, strength_deg: float) -> np.ndarray:
    """Tangent-space normal map (H, W, 3) of a height field, RMS tilt ``strength_deg``.

    The tangent frame is (t, n × t) with t = ∂p/∂u; ``bitangent_sign`` maps the
    image's y axis onto n × t.
    """
    gy, gx = np.gradient(height)
    gy = gy * geo.bitangent_sign
    slope = np.stack([-gx, -gy], axis=-1)
    rms = np.sqrt(np.mean(np.sum(slope[geo.mask] ** 2, axis=-1)))
    slope *= np.tan(np.radians(strength_deg)) / max(rms, 1e-12)
    n = np.concatenate([slope, np.ones(height.shape + (1,))], axis=-1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    return n.astype(np.float32)


def scan_texture(mesh: UVMesh) -> np.ndarray:
    """The scan's texture (map_Kd of its material) as 8-bit RGB; a missing or damaged file is named."""
    if mesh.texture is None:
        raise MeshError(f"{mesh.path}: the scan needs a texture (mtllib with map_Kd), none found")
    if not Path(mesh.texture).is_file():
        raise MeshError(f"{mesh.path}: its texture {mesh.texture} does not exist")
    return imageio.read_photo(str(mesh.texture))


def ground_truth_maps(mesh: UVMesh, geo: GeometryMaps, s: FaceBenchmarkSettings) -> dict[str, np.ndarray]:
    """Seeded ground truth: albedo (scan texture), normal (tangent space, unit), roughness, specular, displacement."""
    from PIL import Image

    tex = scan_texture(mesh)
    res = s.uv_res
    rng = np.random.default_rng(s.seed)
    tex = Image.fromarray(tex).resize((res, res), Image.BICUBIC)
    albedo = imageio.srgb_to_linear(np.asarray(tex, np.float32) / 255.0)
    height = skin_relief(res, rng)
    normal = normals_from_height(height, geo, s.normal_strength_deg)
    roughness = np.clip(0.45 + 0.15 * smooth_noise(rng, res, 5), 0.25, 0.7)
    specular = np.clip(0.45 + 0.2 * smooth_noise(rng, res, 5), 0.15, 0.8)
    return {
        "albedo": albedo.astype(np.float32),
        "normal": normal,
        "roughness": roughness[..., None].astype(np.float32),
        "specular": specular[..., None].astype(np.float32),
        "displacement": height[..., None].astype(np.float32),
    }


# -- Mitsuba scene of the scan with given maps -----------------------------------------------


def _bitmap(arr: np.ndarray) -> dict:
    # raw: the maps are linear data already; bilinear like the UV shader's texel lookup.
    return {"type": "bitmap", "raw": True, "data": mi.TensorXf(aligned(arr))}


def material_dict(maps: dict[str, np.ndarray], s_disp: float, bsdf: str = "ggx_uv") -> dict:
    """ggx_uv (two-sided) with the given UV maps; displacement shades as bump in the plugin. ``principled``: Mitsuba's
    builtin with the same maps (roughness, base colour; its scalar ``specular`` = the map's mean) under a
    ``normalmap``."""
    if bsdf == "principled":
        inner = {"type": "normalmap", "normalmap": _bitmap(maps["normal"] * 0.5 + 0.5),
                 "bsdf": {"type": "principled", "base_color": _bitmap(maps["albedo"]),
                          "roughness": _bitmap(maps["roughness"]), "specular": float(np.mean(maps["specular"]))}}
        return {"type": "twosided", "bsdf": inner}
    inner = {
        "type": "ggx_uv",
        "albedo": _bitmap(maps["albedo"]),
        "normal": _bitmap(maps["normal"] * 0.5 + 0.5),
        "roughness": _bitmap(maps["roughness"]),
        "specular": _bitmap(maps["specular"]),
    }
    return {"type": "twosided", "bsdf": inner}


def scan_scene(mesh_path: Path, maps: dict, s: FaceBenchmarkSettings, emitters: dict,
               sensor: dict | None = None, integrator: dict | None = None, bsdf: str = "ggx_uv") -> mi.Scene:
    shape = {"type": "obj", "filename": str(mesh_path), "bsdf": material_dict(maps, s.s_disp, bsdf),
             "face_normals": False}
    d = {"type": "scene", "integrator": integrator or {"type": "path", "max_depth": 2}, "scan": shape, **emitters}
    if sensor is not None:
        d["sensor"] = sensor
    return mi.load_dict(d)


def directional_emitters(lights: list[Light]) -> dict:
    return {
        f"light{k}": {"type": "directional", "direction": (-np.asarray(l.to_light)).tolist(),
                      "irradiance": {"type": "rgb", "value": list(l.irradiance)}}
        for k, l in enumerate(lights)
    }


# -- texel-aligned observation ------------------------------------------------------------------


def _texel_interactions(scene: mi.Scene, geo: GeometryMaps) -> tuple[np.ndarray, mi.SurfaceInteraction3f]:
    """Covered texel indices and Mitsuba's surface interactions at their uv (the scan is shape 0)."""
    from .uv_bake import texel_uvs

    h, w = geo.mask.shape
    idx = np.nonzero(geo.mask.ravel())[0]
    uv = texel_uvs(h, w)
    uv = mi.Point2f(aligned(np.array(uv.x)[idx]), aligned(np.array(uv.y)[idx]))
    return idx, scene.shapes()[0].eval_parameterization(uv)


def texel_observation(scene: mi.Scene, geo: GeometryMaps, eye: np.ndarray, radius: float,
                      seed: int = 0, spp: int = 1, grazing_cos: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Radiance seen from ``eye`` at every texel's 3D point, and the texels actually seen.

    ``spp`` rays per covered texel through its point (their mean radiance); seen = the first hit is within
    1e-3·radius of the point, on the front side of its shading normal by more than ``grazing_cos`` (the UV-space
    shader is one-sided). Directional lighting with direct light only is deterministic: one sample is exact.
    """
    h, w = geo.mask.shape
    idx = np.nonzero(geo.mask.ravel())[0]
    p = geo.position.reshape(-1, 3)[idx].astype(np.float64)
    n = geo.normal.reshape(-1, 3)[idx].astype(np.float64)
    d = p - eye[None, :]
    d /= np.linalg.norm(d, axis=1)[:, None]
    o = np.repeat(np.tile(eye, (len(idx), 1)), spp, 0)
    ray = mi.Ray3f(mi.Point3f(aligned(o.T)), mi.Vector3f(aligned(np.repeat(d, spp, 0).T)))
    si = scene.ray_intersect(ray)
    first = np.arange(len(idx)) * spp
    hit = np.array(si.p, dtype=np.float64).T[first]
    seen = (np.array(si.is_valid())[first] & (np.linalg.norm(hit - p, axis=1) < 1e-3 * radius)
            & (np.sum(n * d, axis=1) < -grazing_cos))
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(seed, len(idx) * spp)
    value, _, _ = scene.integrator().sample(scene, sampler, ray)
    value = np.array(value, dtype=np.float64).T.reshape(len(idx), spp, 3).mean(1).astype(np.float32)
    out = np.zeros((h * w, 3), np.float32)
    out[idx] = np.where(seen[:, None], value, 0.0)
    vis = np.zeros(h * w, np.float32)
    vis[idx] = seen
    return out.reshape(h, w, 3), vis.reshape(h, w)


def key_light(hdri: str, rotation_deg: float) -> tuple[np.ndarray, float]:
    """An HDRI's radiance-weighted mean direction (world, after the rotation about +y) and the irradiance of a
    surface facing it: the one directional light a fit that models only directional lights starts from."""
    from foundation.assets import hdri_pixels

    px = hdri_pixels(hdri).astype(np.float64)
    h, w = px.shape[:2]
    theta = (np.arange(h) + 0.5) / h * np.pi
    phi = (np.arange(w) + 0.5) / w * 2 * np.pi
    th, ph = np.meshgrid(theta, phi, indexing="ij")
    # Mitsuba's envmap: u = atan2(x, −z)/2π, v = acos(y)/π (local frame)
    dirs = np.stack([np.sin(th) * np.sin(ph), np.cos(th), -np.sin(th) * np.cos(ph)], -1)
    lum = np.clip(px @ np.array([0.2126, 0.7152, 0.0722]), 0.0, None)
    dw = np.sin(th) * (np.pi / h) * (2 * np.pi / w)
    mean = (dirs * (lum * dw)[..., None]).sum((0, 1))
    key = mean / max(np.linalg.norm(mean), 1e-12)
    irr = float((lum * np.clip(dirs @ key, 0.0, None) * dw).sum())
    world = np.array(mi.ScalarTransform4f().rotate([0, 1, 0], rotation_deg) @ mi.ScalarVector3f(*key))
    return world / np.linalg.norm(world), irr


def light_visibility(scene: mi.Scene, geo: GeometryMaps, to_light: np.ndarray) -> np.ndarray:
    """1 where the texel's point sees the directional light (no cast shadow), else 0.

    The shadow ray is spawned from Mitsuba's own surface interaction at the
    texel, with Mitsuba's offset, exactly as its renderer does.
    """
    idx, si = _texel_interactions(scene, geo)
    ray = si.spawn_ray(mi.Vector3f(*map(float, to_light)))
    blocked = np.array(scene.ray_test(ray)) | ~np.array(si.is_valid())
    out = np.zeros(geo.mask.size, np.float32)
    out[idx] = ~blocked
    return out.reshape(geo.mask.shape)


def environment_transfer(mesh_path: Path, geo: GeometryMaps, order: int, rays: int = 256,
                         seed: int = 0) -> np.ndarray:
    """Each texel's SH transfer T_lm = ∫ V(ω) (n·ω)⁺ Y_lm(ω) dω (H, W, (order + 1)²): what it receives of an SH
    environment, its own geometry's occlusion included (:mod:`mi_plugins.uv_shader`, ``UVEnvironment``).

    ``rays`` cosine-weighted directions per texel about Mitsuba's shading normal there (a stratified grid,
    shifted per texel by a seeded offset), each tested for an occluder by a shadow ray spawned as Mitsuba's
    renderer does; the estimate is π/N Σ V Y_lm. Uncovered texels are 0.
    """
    from mi_plugins import sh

    scene = mi.load_dict({"type": "scene", "scan": {"type": "obj", "filename": str(mesh_path), "face_normals": False}})
    idx, si = _texel_interactions(scene, geo)
    n_tex, k = len(idx), int(np.ceil(np.sqrt(rays)))
    rng = np.random.default_rng(seed)
    shift = rng.random((n_tex, 2))
    g = np.arange(k) / k
    su, sv = [a.ravel() for a in np.meshgrid(g, g, indexing="ij")]
    out = np.zeros((geo.mask.size, sh.n_coeffs(order)), np.float64)
    valid = np.array(si.is_valid())
    frame_n = np.array(si.sh_frame.n).T
    frame_s = np.array(si.sh_frame.s).T
    frame_t = np.array(si.sh_frame.t).T
    for j in range(k * k):  # one wavefront of every texel per direction: memory stays at one ray per texel
        u = (shift + np.array([su[j], sv[j]])) % 1.0
        r = np.sqrt(u[:, 0])
        phi = 2 * np.pi * u[:, 1]
        local = np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(np.maximum(1 - u[:, 0], 0))], 1)
        d = local[:, :1] * frame_s + local[:, 1:2] * frame_t + local[:, 2:] * frame_n
        ray = si.spawn_ray(mi.Vector3f(aligned(d.T.astype(np.float32))))
        lit = ~np.array(scene.ray_test(ray)) & valid
        y = np.stack(sh.basis(d[:, 0], d[:, 1], d[:, 2], order), 1)
        out[idx] += y * lit[:, None]
    out *= np.pi / (k * k)
    return out.reshape(geo.mask.shape + (sh.n_coeffs(order),)).astype(np.float32)


def camera_sensor(eye: np.ndarray, target: np.ndarray, res: int, fov: float = 30.0) -> dict:
    return {
        "type": "perspective", "fov": fov,
        "to_world": mi.ScalarTransform4f().look_at(origin=eye.tolist(), target=target.tolist(), up=[0, 1, 0]),
        "film": {"type": "hdrfilm", "width": res, "height": res, "rfilter": {"type": "box"}},
        "sampler": {"type": "independent"},
    }


def render_heldout(mesh_path: Path, maps: dict, s: FaceBenchmarkSettings, hdri: str, eye: np.ndarray,
                   target: np.ndarray, fov: float, bsdf: str = "ggx_uv") -> tuple[np.ndarray, np.ndarray]:
    """Camera render under a real HDRI (full path tracing) and the fully covered face pixels."""
    scene = scan_scene(mesh_path, maps, s, {"env": envmap(hdri)},
                       camera_sensor(eye, target, s.render_res, fov), {"type": "intrinsic", "max_depth": 4}, bsdf)
    img = np.array(mi.render(scene, spp=s.render_spp, seed=s.seed + 7))
    rgb = img[..., :3]
    depth = img[..., 3 + 3 * 3 + 3]  # albedo, diffuse, specular, normal (3 each), then depth
    mask = depth > 0
    return rgb.astype(np.float32), mask


# -- the whole benchmark ------------------------------------------------------------------------------


def rendered_maps(gt: dict[str, np.ndarray], s: FaceBenchmarkSettings) -> dict[str, np.ndarray]:
    """The maps the observations are rendered with: the truth, its albedo spread by ``albedo_blur`` (light
    scattered under the skin leaves the surface beside where it entered), and for ``principled`` the specular map's
    mean (a scalar there). The truth records the latter, not the blur (the fit should find the skin's colour)."""
    out = dict(gt)
    if s.albedo_blur > 0:
        from scipy.ndimage import gaussian_filter

        sigma = s.albedo_blur * s.uv_res / 256
        out["albedo"] = np.stack([gaussian_filter(gt["albedo"][..., c], sigma, mode="nearest") for c in range(3)], -1)
    return out


def make_benchmark(scan: str | Path, out: str | Path, s: FaceBenchmarkSettings | None = None,
                   show_progress: bool = True) -> Path:
    """Build a face benchmark folder from an OBJ scan with a texture; returns the folder.

    Written atomically: everything goes to a hidden sibling folder that is
    renamed into place at the end.
    """
    s = s or FaceBenchmarkSettings()
    scan, out = Path(scan), Path(out)
    mesh = load_obj(scan)
    scan_texture(mesh)  # a missing or damaged texture is named before any rendering
    hdris = tuple(s.heldout_hdris) + (tuple(s.lighting_hdris) if s.lighting == "hdri" else ())
    for h in hdris:
        envmap(h)  # a missing or unreadable HDRI is named before any rendering
    t0 = time.perf_counter()
    with atomic_dir(out, MARKER) as tmp:
        # The benchmark carries its own copy of the geometry (self-contained folder) and of the user's HDRIs.
        shutil.copyfile(scan, tmp / "mesh.obj")
        own = {h: f"hdri/{hdri_label(h)}.exr" for h in hdris
               if hdri_path(h).resolve().parent != HDRI_DIR.resolve()}
        if own:
            (tmp / "hdri").mkdir()
            for h, rel in own.items():
                shutil.copyfile(hdri_path(h), tmp / rel)
        geo = bake_geometry(mesh, s.uv_res)
        gt = ground_truth_maps(mesh, geo, s)
        if s.observation_bsdf == "principled":
            gt["specular"] = np.full_like(gt["specular"], float(np.mean(gt["specular"])))
        centre, radius, front = scan_frame(mesh)
        fov = float(np.degrees(2 * np.arctan(1.15 / s.camera_distance)))
        if s.lighting == "hdri":
            rng = np.random.default_rng(s.seed + 23)
            lights = []
            for k in range(s.n_lights):
                h, rot = s.lighting_hdris[k % len(s.lighting_hdris)], float(rng.uniform(0.0, 360.0))
                key, irr = key_light(h, rot)
                # a bundled HDRI by name, a user's by its copy in the benchmark
                lights.append(Light("hdri", tuple(map(float, key)), (irr,) * 3, own.get(h, hdri_label(h)), rot))
        else:
            lights = training_lights(front, s.n_lights, s.light_irradiance, s.seed, s.light_spread_deg)
        views = [centre + orbit_direction(front, yaw, pitch) * s.camera_distance * radius for yaw, pitch in s.views]
        rendered = rendered_maps(gt, s)

        obs, vis_view, vis_light, camera = {}, {}, {}, {}
        steps = len(lights) * (len(views) + 1) + len(s.heldout_hdris)
        with progress_bar(total=steps, desc=f"face benchmark {scan.stem}", unit="render",
                          disable=not show_progress) as bar:
            for k, light in enumerate(lights):
                if light.kind == "hdri":
                    env = tmp / light.hdri if light.hdri in own.values() else light.hdri
                    emit = {"env": envmap(env, to_world=mi.ScalarTransform4f().rotate([0, 1, 0], light.rotation_deg))}
                else:
                    emit = directional_emitters([light])
                scene = scan_scene(scan, rendered, s, emit, integrator={"type": "path", "max_depth": s.max_depth},
                                   bsdf=s.observation_bsdf)
                vis_light[f"light{k}"] = light_visibility(scene, geo, np.asarray(light.to_light))
                bar.update(1)
                for v, eye in enumerate(views):
                    spp = s.observation_spp if (light.kind == "hdri" or s.max_depth > 2) else 1
                    img, seen = texel_observation(scene, geo, eye, radius, seed=s.seed + 31 * k + v, spp=spp)
                    obs[f"v{v}_l{k}"] = img
                    vis_view[f"v{v}"] = seen
                    # The same view as an ordinary camera image (for fitting through full renders).
                    sensor = mi.load_dict(camera_sensor(eye, centre, s.render_res, fov))
                    camera[f"v{v}_l{k}"] = np.array(mi.render(scene, sensor=sensor, spp=s.render_spp,
                                                              seed=s.seed + 97 * k + v))[..., :3]
                    bar.update(1)
                del scene
            heldout = {}
            for hdri in s.heldout_hdris:
                rgb, mask = render_heldout(scan, rendered, s, hdri, views[0], centre, fov, s.observation_bsdf)
                heldout[hdri_label(hdri)] = rgb
                heldout[f"{hdri_label(hdri)}_mask"] = mask.astype(np.float32)
                bar.update(1)

        imageio.write_exr(tmp / "geometry.exr", {"position": geo.position, "normal": geo.normal,
                                                 "tangent": geo.tangent, "bitangent_sign": geo.bitangent_sign,
                                                 "mask": geo.mask.astype(np.float32)})
        imageio.write_exr(tmp / "ground_truth.exr", gt)
        imageio.write_exr(tmp / "observations.exr", obs)
        imageio.write_exr(tmp / "visibility.exr", {**vis_view, **vis_light})
        imageio.write_exr(tmp / "heldout.exr", heldout)
        imageio.write_exr(tmp / "camera.exr", camera)
        imageio.write_png(tmp / "albedo_gt.png", gt["albedo"])
        imageio.write_png(tmp / "observation_v0_l0.png", obs["v0_l0"])
        meta = FaceBenchmarkMeta(
            scan=str(scan), mesh="mesh.obj",
            settings=replace(s, heldout_hdris=tuple(own.get(h, hdri_label(h)) for h in s.heldout_hdris)), lights=lights, views=[tuple(map(float, v)) for v in views],
            centre=tuple(map(float, centre)), radius=radius, front=tuple(map(float, front)),
            heldout_camera=HeldoutCamera(tuple(map(float, views[0])), tuple(map(float, centre)), fov),
            camera_fov=fov, seconds=time.perf_counter() - t0)
        write_json(tmp / MARKER, to_json(meta))  # last: its presence marks a complete benchmark
    return out


@dataclass
class FaceBenchmark:
    path: Path
    meta: FaceBenchmarkMeta
    geometry: dict[str, np.ndarray]
    ground_truth: dict[str, np.ndarray]
    observations: dict[str, np.ndarray]  #: "v{view}_l{light}" -> (H, W, 3)
    visibility: dict[str, np.ndarray]  #: "v{view}" and "light{k}" -> (H, W)
    heldout: dict[str, np.ndarray] = field(default_factory=dict)
    camera: dict[str, np.ndarray] = field(default_factory=dict)  #: "v{view}_l{light}" camera images

    @property
    def mesh_path(self) -> Path:
        return self.path / self.meta.mesh

    @property
    def settings(self) -> FaceBenchmarkSettings:
        return self.meta.settings


def _layers(path: Path) -> dict[str, np.ndarray]:
    ch = imageio.read_exr(path)
    names = sorted({k.rsplit(".", 1)[0] if "." in k else "" for k in ch})
    return {n: imageio.exr_layer(ch, n) for n in names}


def load_benchmark(path: str | Path) -> FaceBenchmark:
    """Read a face benchmark folder; a missing file, a foreign EXR or a bad description is named."""
    path = Path(path)
    meta = load_folder_record(path, MARKER, FaceBenchmarkMeta, FORMAT, "face benchmark",
                              "photoreal face make-benchmark")
    if not (path / meta.mesh).is_file():
        raise UsageError(f"{path / meta.mesh}: missing from the benchmark")
    # HDRIs copied into the benchmark are named relative to it
    hdris = tuple(str(path / h) if h.startswith("hdri/") else h for h in meta.settings.heldout_hdris)
    for h in hdris:
        if h.startswith(str(path)) and not Path(h).is_file():
            raise UsageError(f"{h}: missing from the benchmark (its held-out renders were lit by it)")
    meta.settings = replace(meta.settings, heldout_hdris=hdris)
    geometry = _layers(path / "geometry.exr")
    geometry = {k: (v[..., 0] if v.shape[-1] == 1 else v) for k, v in geometry.items()}
    vis = {k: v[..., 0] for k, v in _layers(path / "visibility.exr").items()}
    camera = _layers(path / "camera.exr") if (path / "camera.exr").is_file() else {}
    bench = FaceBenchmark(path, meta, geometry, _layers(path / "ground_truth.exr"),
                          _layers(path / "observations.exr"), vis, _layers(path / "heldout.exr"), camera)
    need = {"geometry.exr": (bench.geometry, ["mask", "position", "normal", "tangent", "bitangent_sign"]),
            "ground_truth.exr": (bench.ground_truth, ["albedo", "normal", "roughness", "specular", "displacement"]),
            "observations.exr": (bench.observations, [f"v{v}_l{k}" for v in range(len(meta.views))
                                                      for k in range(len(meta.lights))]),
            "visibility.exr": (bench.visibility, [f"v{v}" for v in range(len(meta.views))]
                               + [f"light{k}" for k in range(len(meta.lights))]),
            "heldout.exr": (bench.heldout, [hdri_label(h) for h in meta.settings.heldout_hdris])}
    for name, (layers, keys) in need.items():
        missing = [k for k in keys if k not in layers]
        if missing:
            raise UsageError(f"{path / name}: not this benchmark's layers (missing {', '.join(missing[:4])})")
    return bench


def benchmark_digest(bench: FaceBenchmark) -> str:
    """Digest of the benchmark's files (its content, not its path: a benchmark re-made in place is another one)."""
    import hashlib

    from foundation.files import file_digest

    names = sorted(p.name for p in bench.path.iterdir() if p.suffix in (".exr", ".obj", ".json") and
                   not p.name.startswith("."))
    return hashlib.sha256("".join(f"{n}:{file_digest(bench.path / n)}" for n in names).encode()).hexdigest()[:16]
