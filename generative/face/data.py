"""Training and evaluation data of the learned UV-space face stages (seed 003 §2–§4, "Data Preparation").

The seed multiplies < 100 scans into 100 000 instances by assigning scanned PBR textures to fitted geometries
and rendering them under 2 041 HDRIs. Here there are two real scans (the Cyberware heads ``paul`` and
``josie``); one is kept entirely out of training (:attr:`FaceDataSettings.heldout_scan`) and the other is
multiplied, honestly and with every knob seeded, into instances:

* **identity** — a single scan would be memorised (measured: a completion model trained on it returned the training
  face for the held-out one), so every training instance is another person (:func:`synthetic_identity`): the
  texture warped symmetrically, chromophores varied in space (tan, blotches, flush, freckles), and a third of the
  time new hair from a photograph's texture in a random hair colour;
* **skin tone** — the albedo is moved in a physically motivated colour space: optical density
  −ln(albedo) split per texel into melanin, haemoglobin and a grey baseline (Beer–Lambert with the two
  chromophores' RGB absorption directions, after Tsumura et al. 2003), and the melanin and haemoglobin
  concentrations are scaled (log-uniform) — darker and lighter, paler and redder skin (and hair: its colour is
  melanin too);
* **relief** — seeded pores + wrinkles + broad undulation (:func:`inverse.face.benchmark.skin_relief`) as
  displacement and its normal map, RMS tilt drawn per instance;
* **roughness and specular** — smooth seeded fields with face structure: an oily T-zone (forehead, nose: less
  rough, more specular) placed from the baked geometry, so a model can infer them from where a texel is;
* **geometry warps** — anisotropic scaling and a smooth bulge along the normals, so the baked geometry maps
  (and the visibility of a pose) vary;
* **the baseline** — each instance also carries today's optimisation baseline of its photo
  (:func:`inverse.face.fill_and_delight`: mirror + harmonic fill, albedo = texture ÷ fitted shading), which the
  learned completion refines and is judged against;
* **pose and lighting** — a random head pose seen by a camera gives the single photo's visibility mask (texels
  whose first hit from the camera is their own point, facing it by more than ``grazing_cos``); lighting is a real
  HDRI at a random rotation and exposure, path traced by Mitsuba (interreflection, cast shadows), the material
  ``ggx_uv`` with the instance's maps. The lit observation is taken texel-aligned (one camera ray through each
  texel's point, ``spp`` paths): a photo resampled into UV without filtering.

Each instance is one ``.npz`` (inputs: lit partial texture, mask, geometry in the face frame; targets: albedo,
normal, roughness, specular, displacement; the camera and lights for re-shading). The held-out scan's instances
use held-out HDRIs and no warp or colour change. Building is resumable and runs on the pool.
"""

from __future__ import annotations

import json
import tempfile
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from foundation import validate
from foundation.assets import FACE, hdri_path
from foundation.errors import UsageError
from foundation.files import atomic_path, holds_files, read_json, write_json

FORMAT = "photoreal face instances v4"
SCANS = FACE / "cyberheads"
#: RGB absorption directions in optical density (−ln reflectance): melanin absorbs more towards blue,
#: oxy-haemoglobin most in green (its 540–580 nm Q bands) and blue, least in red (Tsumura et al. 2003, Fig. 3)
MELANIN = np.array([1.0, 1.55, 2.2]) / np.linalg.norm([1.0, 1.55, 2.2])
HAEMOGLOBIN = np.array([0.25, 1.0, 0.7]) / np.linalg.norm([0.25, 1.0, 0.7])
#: the maps a model predicts, with their channel counts
TARGETS = {"albedo": 3, "normal": 3, "roughness": 1, "specular": 1}


@dataclass
class FaceDataSettings:
    """How instances are made. Two scans exist: ``train_scans`` are multiplied, ``heldout_scan`` is only evaluated."""

    #: UV layout of every map: ``template`` — MediaPipe's face template registered to each scan
    #: (:func:`inverse.face.register_scan`), the layout `from-photo` unwraps photos into; ``scan`` — the scan's own
    layout: str = "template"
    train_scans: tuple[str, ...] = ("paul",)
    heldout_scan: str = "josie"
    train_instances: int = 192
    eval_instances: int = 24
    uv_res: int = 128  #: texels per side of every map (models work at half of it, super-resolution doubles)
    train_hdris: tuple[str, ...] = ("city", "courtyard", "night", "studio", "sunrise")
    eval_hdris: tuple[str, ...] = ("sunset", "forest", "interior")
    spp: int = 32  #: paths per texel of the lit observation
    max_depth: int = 4  #: interreflection between face parts (nose → cheek) and the two-sided surface
    yaw_deg: float = 70.0  #: |yaw| of the head pose, uniform
    pitch_deg: tuple[float, float] = (-20.0, 25.0)
    exposure: tuple[float, float] = (0.5, 2.0)  #: log-uniform factor on the HDRI
    grazing_cos: float = 0.2  #: texels seen at a flatter angle count as unseen (their colour is unreliable)
    melanin: tuple[float, float] = (0.45, 2.2)  #: log-uniform scale of the melanin concentration (training only)
    haemoglobin: tuple[float, float] = (0.6, 1.7)
    warp: float = 0.06  #: anisotropic scale ±warp, and a bulge of warp/3 radii (training only)
    identity_warp: float = 0.08  #: texture warp of :func:`synthetic_identity` (training only)
    seed: int = 0

    def __post_init__(self):
        validate.one_of("layout", self.layout, ("template", "scan"))
        validate.integer("train_instances", self.train_instances, 1, 1 << 20)
        validate.integer("eval_instances", self.eval_instances, 1, 1 << 20)
        validate.integer("uv_res", self.uv_res, 16, 2048)
        if self.uv_res % 8:
            raise UsageError(f"uv_res must divide by 8 (models work at half of it), got {self.uv_res}")
        validate.integer("spp", self.spp, 1, 1 << 16)
        validate.integer("max_depth", self.max_depth, 2, 64)
        validate.in_range("yaw_deg", self.yaw_deg, 0.0, 90.0)
        validate.in_range("grazing_cos", self.grazing_cos, 0.0, 1.0, hi_open=True)
        validate.non_negative("warp", self.warp)
        validate.in_range("identity_warp", self.identity_warp, 0.0, 0.3)
        validate.seed("seed", self.seed)
        for lo, hi, name in (self.pitch_deg + ("pitch_deg",), self.exposure + ("exposure",),
                             self.melanin + ("melanin",), self.haemoglobin + ("haemoglobin",)):
            if not lo <= hi:
                raise UsageError(f"{name}: low {lo} above high {hi}")
        if min(self.exposure + self.melanin + self.haemoglobin) <= 0:
            raise UsageError("exposure, melanin and haemoglobin ranges must be positive")
        if not self.train_scans:
            raise UsageError("train_scans: at least one scan")
        if self.heldout_scan in self.train_scans:
            raise UsageError(f"heldout_scan {self.heldout_scan!r} is also a training scan: it would not be held out")
        if set(self.train_hdris) & set(self.eval_hdris):
            raise UsageError(f"an HDRI is in both train_hdris and eval_hdris: {sorted(set(self.train_hdris) & set(self.eval_hdris))}")
        for h in self.train_hdris + self.eval_hdris:
            hdri_path(h)
        for scan in self.train_scans + (self.heldout_scan,):
            scan_path(scan)


def scan_path(scan: str) -> Path:
    """A bundled head by name (``paul``, ``josie``) or an OBJ with a texture."""
    p = Path(scan)
    if p.suffix.lower() == ".obj":
        if not p.is_file():
            raise UsageError(f"{p}: no such scan")
        return p
    q = SCANS / f"{scan}.obj"
    if not q.is_file():
        raise UsageError(f"scan {scan!r}: not a bundled scan ({', '.join(sorted(x.stem for x in SCANS.glob('*.obj')))}) "
                         "or an .obj file")
    return q


# -- identity ------------------------------------------------------------------------------------------------------


def chromophores(albedo: np.ndarray) -> np.ndarray:
    """Per-texel (melanin, haemoglobin, baseline) concentrations c with −ln(albedo) = c·[m, h, 1] (exact: three
    directions span RGB)."""
    od = -np.log(np.clip(albedo, 1e-3, 1.0))
    basis = np.stack([MELANIN, HAEMOGLOBIN, np.ones(3) / np.sqrt(3)])  # rows: directions
    return od @ np.linalg.inv(basis)


def skin_variation(albedo: np.ndarray, melanin: float, haemoglobin: float) -> np.ndarray:
    """The albedo with its melanin and haemoglobin concentrations scaled (Beer–Lambert in optical density)."""
    c = chromophores(albedo)
    c[..., 0] *= melanin
    c[..., 1] *= haemoglobin
    basis = np.stack([MELANIN, HAEMOGLOBIN, np.ones(3) / np.sqrt(3)])
    return np.clip(np.exp(-(c @ basis)), 0.0, 1.0).astype(np.float32)


HAIR_SOURCES = ("chelsea", "grass", "gravel", "brick", "coffee")  #: scikit-image photographs (in its wheel)
#: linear RGB hair colours: black, dark brown, brown, auburn, red, blonde, grey
HAIR_COLOURS = np.array([[0.02, 0.015, 0.012], [0.06, 0.035, 0.02], [0.12, 0.07, 0.04], [0.2, 0.08, 0.04],
                         [0.35, 0.12, 0.05], [0.45, 0.32, 0.16], [0.4, 0.4, 0.4]])


def _hair_texture(res: int, rng: np.random.Generator) -> np.ndarray:
    """A (res, res) luminance pattern in [0, 2] (mean 1) from a random crop of a scikit-image photograph."""
    import skimage.data
    from scipy.ndimage import zoom

    img = np.asarray(getattr(skimage.data, HAIR_SOURCES[rng.integers(len(HAIR_SOURCES))])(), np.float32)
    img = img.mean(-1) if img.ndim == 3 else img
    side = int(rng.integers(res // 2, min(img.shape) + 1))
    y, x = rng.integers(0, img.shape[0] - side + 1), rng.integers(0, img.shape[1] - side + 1)
    crop = zoom(img[y:y + side, x:x + side], res / side, order=1)[:res, :res]
    crop = crop / max(float(crop.mean()), 1e-3)
    return np.clip(crop, 0.0, 2.0)


def symmetric_warp(image: np.ndarray, rng: np.random.Generator, warp: float) -> np.ndarray:
    """(H, W, C) image resampled through a smooth displacement that is antisymmetric in u and symmetric in v about
    the vertical midline: a left–right symmetric image stays symmetric. Displacements up to ``warp`` of the side."""
    from scipy.ndimage import map_coordinates

    from inverse.face import smooth_noise

    res = image.shape[0]
    fu, fv = smooth_noise(rng, res, 4), smooth_noise(rng, res, 4)
    du = 0.5 * (fu - fu[:, ::-1]) * warp * res
    dv = 0.5 * (fv + fv[:, ::-1]) * warp * res
    rows, cols = np.meshgrid(np.arange(res, dtype=np.float64), np.arange(image.shape[1], dtype=np.float64), indexing="ij")
    return np.stack([map_coordinates(image[..., c], [rows + dv, cols + du], order=1, mode="nearest")
                     for c in range(image.shape[-1])], -1).astype(np.float32)


def synthetic_identity(albedo: np.ndarray, position_face: np.ndarray, mask: np.ndarray, rng: np.random.Generator,
                       warp: float = 0.08) -> np.ndarray:
    """Another person from one scan's albedo, so that a model cannot just memorise the training face:

    * a smooth warp of the texture that keeps its left–right symmetry (u displaced antisymmetrically about the
      midline, v symmetrically), by up to ``warp`` of the map — features move, mirroring still holds;
    * chromophore variation in space: smooth fields scaling melanin (tan, blotches) and haemoglobin (flush), and
      freckles (small melanin dots);
    * a third of the time a new head of hair: outside the face (|side| or height above the brow beyond a random border)
      the albedo becomes a random hair colour modulated by a scikit-image photograph's texture (fur, grass,
      gravel, …), blended by a smooth mask.
    """
    from scipy.ndimage import gaussian_filter

    from inverse.face import smooth_noise

    res = albedo.shape[0]
    out = symmetric_warp(albedo, rng, warp)
    c = chromophores(out)
    c[..., 0] *= np.exp(0.35 * smooth_noise(rng, res, 6))
    c[..., 1] *= np.exp(0.3 * smooth_noise(rng, res, 8))
    dots = np.zeros((res, res))
    n = int(rng.poisson(rng.uniform(0, 40)))
    dots[rng.integers(0, res, n), rng.integers(0, res, n)] = rng.uniform(0.5, 2.0, n)
    c[..., 0] += gaussian_filter(dots, 0.7 * res / 128) * np.abs(c[..., 0]).mean()
    basis = np.stack([MELANIN, HAEMOGLOBIN, np.ones(3) / np.sqrt(3)])
    out = np.clip(np.exp(-(c @ basis)), 0.0, 1.0)
    if rng.random() < 0.3:
        side, up = np.abs(position_face[..., 0]), position_face[..., 1]
        border_side, border_up = rng.uniform(0.35, 0.55), rng.uniform(0.3, 0.5)
        m = np.clip(np.maximum((side - border_side) / 0.08, (up - border_up) / 0.08), 0.0, 1.0)
        m = gaussian_filter(m * mask, 1.0 * res / 128)[..., None]
        colour = HAIR_COLOURS[rng.integers(len(HAIR_COLOURS))] * np.exp(rng.normal(0.0, 0.2, 3))
        hair = np.clip(colour[None, None, :] * _hair_texture(res, rng)[..., None], 0.0, 1.0)
        out = out * (1.0 - m) + hair * m
    return out.astype(np.float32)


def face_frame(centre: np.ndarray, front: np.ndarray) -> np.ndarray:
    """Rows (side, up, front) of the face's frame; up is the world's +y made orthogonal to the front."""
    up = np.array([0.0, 1.0, 0.0]) - front * front[1]
    up /= np.linalg.norm(up)
    side = np.cross(up, front)
    return np.stack([side, up, front])


def tzone(position_face: np.ndarray, normal_face: np.ndarray) -> np.ndarray:
    """Weight in [0, 1] of the oily T-zone: near the face's midline, from the nose up the forehead, facing front."""
    side, up = position_face[..., 0], position_face[..., 1]
    across = np.exp(-0.5 * (side / 0.12) ** 2)
    along = 1.0 / (1.0 + np.exp(-(up + 0.05) / 0.04))  # above the upper lip
    facing = np.clip(normal_face[..., 2], 0.0, 1.0) ** 2
    return (across * along * facing).astype(np.float32)


def material_fields(position_face: np.ndarray, normal_face: np.ndarray, mask: np.ndarray,
                    rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Roughness and specular (H, W, 1): per-instance base levels, the T-zone, smooth seeded noise."""
    from inverse.face import smooth_noise

    res = mask.shape[0]
    t = tzone(position_face, normal_face)
    r0, s0 = rng.uniform(0.42, 0.58), rng.uniform(0.25, 0.45)
    rough = r0 - rng.uniform(0.08, 0.18) * t + 0.05 * smooth_noise(rng, res, 6)
    spec = s0 + rng.uniform(0.15, 0.3) * t + 0.06 * smooth_noise(rng, res, 6)
    rough = np.where(mask, np.clip(rough, 0.15, 0.8), 0.5)
    spec = np.where(mask, np.clip(spec, 0.05, 0.9), 0.35)
    return rough[..., None].astype(np.float32), spec[..., None].astype(np.float32)


def warp_vertices(v: np.ndarray, centre: np.ndarray, frame: np.ndarray, radius: float, normals: np.ndarray,
                  amount: float, rng: np.random.Generator) -> np.ndarray:
    """Anisotropic scaling in the face frame and a smooth bulge along the normals (sum of 3 Gaussian bumps)."""
    if amount == 0:
        return v
    local = (v - centre) @ frame.T
    local *= 1.0 + rng.uniform(-amount, amount, 3)
    out = centre + local @ frame
    bump = np.zeros(len(v))
    for _ in range(3):
        c = centre + rng.normal(scale=0.4 * radius, size=3)
        bump += rng.uniform(-1, 1) * np.exp(-np.sum((v - c) ** 2, 1) / (2 * (0.3 * radius) ** 2))
    return out + normals * (amount / 3.0 * radius * bump)[:, None]


# -- one instance ----------------------------------------------------------------------------------------------------


@dataclass
class InstanceSpec:
    """Everything random about one instance (drawn from the seed; recorded in the instance)."""

    scan: str
    role: str  #: "train" or "eval"
    index: int
    hdri: str
    rotation_deg: float
    exposure: float
    yaw_deg: float
    pitch_deg: float
    melanin: float = 1.0
    haemoglobin: float = 1.0
    warp: float = 0.0
    seed: int = 0


def instance_specs(s: FaceDataSettings) -> list[InstanceSpec]:
    """The dataset's instances: ``train_instances`` over the training scans, ``eval_instances`` of the held-out one."""
    out = []
    for role, count, scans, hdris in (("train", s.train_instances, s.train_scans, s.train_hdris),
                                      ("eval", s.eval_instances, (s.heldout_scan,), s.eval_hdris)):
        rng = np.random.default_rng([s.seed, 0 if role == "train" else 1])
        for i in range(count):
            train = role == "train"
            out.append(InstanceSpec(
                scan=scans[i % len(scans)], role=role, index=i, hdri=hdris[i % len(hdris)],
                rotation_deg=float(rng.uniform(0, 360)), exposure=float(np.exp(rng.uniform(*np.log(s.exposure)))),
                yaw_deg=float(rng.uniform(-s.yaw_deg, s.yaw_deg)), pitch_deg=float(rng.uniform(*s.pitch_deg)),
                melanin=float(np.exp(rng.uniform(*np.log(s.melanin)))) if train else 1.0,
                haemoglobin=float(np.exp(rng.uniform(*np.log(s.haemoglobin)))) if train else 1.0,
                warp=s.warp if train else 0.0, seed=int(rng.integers(0, 2**31 - 1))))
    return out


def mesh_of(d: "FaceSet", i: int) -> Path:
    """The geometry instance ``i`` was rendered with, unwarped: the registered template or the scan itself."""
    rec = d.records[i]
    if rec.get("mesh"):
        if d.directory is None:
            raise UsageError(f"{rec['name']}: its mesh {rec['mesh']} lies in its dataset folder, which is not known")
        return Path(d.directory) / rec["mesh"]
    return scan_path(rec["spec"]["scan"])


def instance_name(spec: InstanceSpec) -> str:
    return f"{spec.role}_{spec.index:05d}"


def registration_files(directory: Path, scan: str) -> tuple[Path, Path]:
    """The dataset's registration of ``scan`` to the template: arrays (.npz) and the fitted template mesh (.obj)."""
    stem = Path(scan).stem
    return directory / f"registration_{stem}.npz", directory / f"registration_{stem}.obj"


def save_registration(directory: Path, scan: str, uv_res: int) -> dict:
    """Register ``scan`` to the template once (MediaPipe on a frontal render; see :mod:`inverse.face.register`) and
    keep it beside the instances; returns its summary."""
    from foundation.mesh import load_obj, write_obj
    from inverse.face import TEMPLATE, register_scan

    arrays, mesh_file = registration_files(directory, scan)
    if not (arrays.is_file() and mesh_file.is_file()):
        reg = register_scan(scan_path(scan), uv_res)
        write_obj(mesh_file, reg.vertices, load_obj(TEMPLATE))
        with atomic_path(arrays, suffix=".npz") as tmp:
            np.savez(tmp, vertices=reg.vertices, scan_uv=reg.scan_uv, valid=reg.valid,
                     landmark_px=np.array(reg.landmark_px))
    with np.load(arrays) as z:
        return {"scan": scan, "landmark_px": float(z["landmark_px"]), "valid_fraction": float(z["valid"].mean())}


def load_registration(directory: Path, scan: str):
    from inverse.face import ScanRegistration

    arrays, _ = registration_files(directory, scan)
    with np.load(arrays) as z:
        return ScanRegistration(z["vertices"], z["scan_uv"], z["valid"], float(z["landmark_px"]))


def make_instance(spec: InstanceSpec, s: FaceDataSettings, out: str) -> dict:
    """Render one instance into ``out`` (.npz, written atomically); returns its record. With the template layout the
    scan's registration must be in ``out``'s folder (:func:`save_registration`)."""
    import mi_plugins  # noqa: F401
    import mitsuba as mi

    from foundation import imageio
    from foundation.assets import envmap
    from foundation.mesh import UVMesh, load_obj, write_obj
    from inverse.face import (TEMPLATE, FaceBenchmarkSettings, PhotoFitSettings, bake_geometry, fill_and_delight,
                              normals_from_height, orbit_direction, scan_frame, scan_scene, scan_texture, skin_relief,
                              texel_observation)
    from mi_plugins.uv_shader import UVView

    rng = np.random.default_rng(spec.seed)
    scan = load_obj(scan_path(spec.scan))
    tex = imageio.srgb_to_linear(scan_texture(scan).astype(np.float32) / 255.0)
    if s.layout == "template":
        reg = load_registration(Path(out).parent, spec.scan)
        if reg.scan_uv.shape[0] != s.uv_res:
            raise UsageError(f"{registration_files(Path(out).parent, spec.scan)[0]}: registered at "
                             f"{reg.scan_uv.shape[0]}², the dataset is {s.uv_res}²")
        template = load_obj(TEMPLATE)
        mesh = UVMesh(reg.vertices, template.faces, template.uvs, template.face_uvs)
        albedo = reg.to_template(tex)
        found = reg.valid
        mesh_name = registration_files(Path(out).parent, spec.scan)[1].name
    else:
        from PIL import Image

        mesh = scan
        small = np.asarray(Image.fromarray((np.clip(imageio.linear_to_srgb(tex), 0, 1) * 255 + 0.5).astype(np.uint8))
                           .resize((s.uv_res, s.uv_res), Image.BICUBIC), np.float32) / 255.0
        albedo = imageio.srgb_to_linear(small)
        found, mesh_name = None, None
    centre, radius, front = scan_frame(mesh)
    frame = face_frame(centre, front)
    with tempfile.TemporaryDirectory(prefix="photoreal_face_") as tmp:
        mesh_file = Path(tmp) / "mesh.obj"
        verts = warp_vertices(mesh.vertices, centre, frame, radius, mesh.vertex_normals(), spec.warp, rng)
        write_obj(mesh_file, verts, mesh)
        warped = load_obj(mesh_file)
        geo = bake_geometry(warped, s.uv_res)
        mask = geo.mask if found is None else geo.mask & found
        pos_f = np.where(mask[..., None], (geo.position - centre) @ frame.T / radius, 0.0).astype(np.float32)
        nrm_f = np.where(mask[..., None], geo.normal @ frame.T, 0.0).astype(np.float32)
        if spec.role == "train":
            albedo = synthetic_identity(albedo, pos_f, mask, rng, s.identity_warp)
        albedo = skin_variation(albedo, spec.melanin, spec.haemoglobin)
        height = skin_relief(s.uv_res, rng)
        normal = normals_from_height(height, geo, float(rng.uniform(6.0, 14.0)))
        rough, spec_map = material_fields(pos_f, nrm_f, mask, rng)
        gt = {"albedo": albedo, "normal": normal, "roughness": rough, "specular": spec_map,
              "displacement": height[..., None].astype(np.float32)}
        env = envmap(spec.hdri, scale=spec.exposure, to_world=mi.ScalarTransform4f().rotate([0, 1, 0], spec.rotation_deg))
        bs = FaceBenchmarkSettings(uv_res=s.uv_res)
        scene = scan_scene(mesh_file, gt, bs, {"env": env}, integrator={"type": "path", "max_depth": s.max_depth})
        eye = centre + orbit_direction(front, spec.yaw_deg, spec.pitch_deg) * 4.0 * radius
        lit, seen = texel_observation(scene, geo, eye, radius, spec.seed % (2**31), s.spp, s.grazing_cos)
        seen = (seen > 0) & mask  # texels the registration did not find on the scan are not part of the face
        lit = lit * seen[..., None]
        del scene
        # the optimisation baseline of the same photo: what the learned completion refines (and is judged against)
        base = fill_and_delight(lit, seen.astype(np.float32), geo, PhotoFitSettings(uv_res=s.uv_res),
                                UVView(position=tuple(map(float, eye))))
    arrays = {"lit": lit, "seen": seen, "mask": mask, "position_face": pos_f, "normal_face": nrm_f,
              "position": geo.position, "normal_geo": geo.normal, "tangent": geo.tangent,
              "bitangent_sign": geo.bitangent_sign, "baseline": base.albedo, **gt}
    if not all(np.isfinite(a).all() for a in arrays.values()):
        raise UsageError(f"instance {instance_name(spec)}: rendering gave NaN/Inf")
    record = {"name": instance_name(spec), "spec": asdict(spec), "eye": eye.tolist(), "centre": centre.tolist(),
              "radius": radius, "frame": frame.tolist(), "seen_fraction": float(seen[mask].mean()),
              "mesh": mesh_name}  #: the geometry rendered (a file beside the instance), None: the scan itself
    with atomic_path(out, suffix=".npz") as tmp:
        np.savez_compressed(tmp, **{k: (v.astype(np.float16) if v.dtype == np.float32 and k in ("lit",) else v)
                                    for k, v in arrays.items()}, record=np.array(json.dumps(record)))
    return record


def load_record(path: str) -> dict:
    with np.load(path) as z:
        return json.loads(str(z["record"]))


# -- the dataset -------------------------------------------------------------------------------------------------------


def build_face_dataset(out: str | Path, s: FaceDataSettings | None = None, pool=None, progress: bool = True) -> Path:
    """Render every instance of ``s`` into ``out`` (``index.json`` + one ``.npz`` per instance). Rerun the same call to
    continue a killed build; a folder made with other settings is refused."""
    from foundation.pool import Item, PoolSettings, run_items

    s = s or FaceDataSettings()
    out = Path(out)
    index = out / "index.json"
    want = {"format": FORMAT, "settings": json.loads(json.dumps(asdict(s)))}
    if index.is_file():
        have = read_json(index, "face dataset index")
        if {k: have.get(k) for k in want} != want:
            raise UsageError(f"{index}: a face dataset made with other settings; use a fresh folder")
    elif holds_files(out):
        raise UsageError(f"{out}: exists and is not a face dataset; give an empty or new folder")
    out.mkdir(parents=True, exist_ok=True)
    write_json(index, {**want, "instances": []})  # claims the folder before any work
    registrations = ([save_registration(out, scan, s.uv_res) for scan in s.train_scans + (s.heldout_scan,)]
                     if s.layout == "template" else [])
    items = [Item(instance_name(sp), "generative.face.data:make_instance", (sp, s, str(out / f"{instance_name(sp)}.npz")),
                  output=str(out / f"{instance_name(sp)}.npz"), loader="generative.face.data:load_record")
             for sp in instance_specs(s)]
    report = run_items(items, pool or PoolSettings(workers=0, threads=0), desc="face instances", show_progress=progress)
    write_json(index, {**want, "instances": [r.value for r in report.results if r.ok],
                       "registrations": registrations, "seconds_last_batch": report.seconds})
    report.raise_if_failed()
    return out


@dataclass
class FaceSet:
    """Instances stacked: inputs, targets and per-instance records. Arrays are (N, H, W, C)."""

    names: list[str]
    records: list[dict]
    lit: np.ndarray
    seen: np.ndarray  #: (N, H, W) bool
    mask: np.ndarray  #: (N, H, W) bool: covered by the UV layout
    position_face: np.ndarray
    normal_face: np.ndarray
    baseline: np.ndarray  #: (N, H, W, 3) the optimisation baseline's albedo (mirror + harmonic fill, delit)
    targets: dict[str, np.ndarray]  #: albedo, normal, roughness, specular, displacement
    geometry: dict[str, np.ndarray]  #: world position, normal_geo, tangent, bitangent_sign
    directory: Path | None = None  #: the dataset folder (the rendered meshes of the template layout are there)

    def __len__(self) -> int:
        return len(self.names)

    def subset(self, idx) -> "FaceSet":
        idx = np.asarray(idx)
        return FaceSet([self.names[i] for i in idx], [self.records[i] for i in idx], self.lit[idx], self.seen[idx],
                       self.mask[idx], self.position_face[idx], self.normal_face[idx], self.baseline[idx],
                       {k: v[idx] for k, v in self.targets.items()}, {k: v[idx] for k, v in self.geometry.items()},
                       self.directory)

    @property
    def res(self) -> int:
        return int(self.lit.shape[1])


def load_face_dataset(directory: str | Path, role: str | None = None) -> FaceSet:
    """The finished instances of a dataset folder (``role``: "train", "eval" or both). Errors name the folder."""
    d = Path(directory)
    index = d / "index.json"
    if not index.is_file():
        raise UsageError(f"{d}: no face dataset (index.json missing; build it with `photoreal face train-models`)")
    idx = read_json(index, "face dataset index")
    recs = [r for r in idx.get("instances") or [] if role is None or r["spec"]["role"] == role]
    if not recs:
        raise UsageError(f"{index}: no finished {role or ''} instances (rerun the build to continue it)")
    cols: dict[str, list] = {}
    for r in recs:
        f = d / f"{r['name']}.npz"
        try:
            with np.load(f) as z:
                for k in z.files:
                    if k != "record":
                        cols.setdefault(k, []).append(z[k])
        except (OSError, ValueError, KeyError) as exc:
            raise UsageError(f"{f}: not a readable face instance ({exc}); delete it and rerun the build") from None
    st = {k: np.stack(v) for k, v in cols.items()}
    for k in ("roughness", "specular", "displacement"):
        st[k] = st[k].astype(np.float32)
    return FaceSet([r["name"] for r in recs], recs, st["lit"].astype(np.float32), st["seen"].astype(bool),
                   st["mask"].astype(bool), st["position_face"], st["normal_face"], st["baseline"].astype(np.float32),
                   {k: st[k] for k in ("albedo", "normal", "roughness", "specular", "displacement")},
                   {k: st[k] for k in ("position", "normal_geo", "tangent", "bitangent_sign")}, d)


__all__ = ["FORMAT", "FaceDataSettings", "FaceSet", "InstanceSpec", "TARGETS", "build_face_dataset", "chromophores",
           "face_frame", "instance_specs", "load_face_dataset", "load_registration", "make_instance", "material_fields", "mesh_of",
           "registration_files", "save_registration",
           "scan_path", "skin_variation", "symmetric_warp", "synthetic_identity", "tzone", "warp_vertices"]
