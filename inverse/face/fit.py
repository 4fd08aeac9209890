"""Face PBR material fitting in UV space through the shared GGX shader (seed 003).

Unknowns per texel u: albedo T_alb (3), tangent-space normal (2 slopes), roughness,
specular; displacement follows from the fitted normals (see :func:`integrate_normals`).
Loss (seed 003's shading loss, L2 on shaded textures, plus regularisers):

    L = Σ_{v,k} mean_u M_v(u) ‖T̂_shaded(u; maps, light k, view v) − T_{v,k}(u)‖²
        + λ_r ‖∇ roughness‖² + λ_s ‖∇ specular‖² + λ_n ‖∇ slopes‖² + λ_c chroma(T_alb)

T̂ is :func:`mi_plugins.uv_shader.shade_uv` — the same GGX functions as the
``ggx_uv`` plugin. Optimised with Adam in Dr.Jit over a coarse-to-fine pyramid
(each level initialised by upsampling the previous one).

Lighting: known (light stage) or fitted jointly (``fit_lights``), either as an
environment per observation — real spherical harmonics of order ``sh_order``
with each texel's occlusion by the geometry (precomputed transfer,
:mod:`mi_plugins.sh`), started by alternating least squares of albedo and
light — or as directional lights (directions, RGB intensities, an ambient
term). Albedo and light intensity share a global scale that no image can
resolve, so metrics compare albedo after the least-squares global scale.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

import mi_plugins  # noqa: F401
import drjit as dr
import mitsuba as mi
from mi_plugins.arrays import aligned

from foundation import validate
from foundation.assets import hdri_label
from foundation.errors import UsageError
from foundation.loop import DrJitStage, LoopSettings, RunState, StepResult, TrainingSummary, run_loop
from foundation.mesh import load_obj
from foundation.optim_state import load_optimizer_state, optimizer_state
from mi_plugins.uv_shader import UVEnvironment, UVLight, UVMaps, UVView, shade_uv, unravel_channels

from .benchmark import FaceBenchmark, Light, benchmark_digest, environment_transfer
from .uv_bake import bake_geometry




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
    fit_lights: bool = False  #: unknown lighting: fit it jointly with the maps (``light_model``)
    #: unknown lighting as ``sh`` (an environment per observation, spherical harmonics) or ``directional`` (one
    #: directional light + a shared ambient per observation)
    light_model: str = "directional"
    sh_order: int = 2  #: bands 0…order of the fitted environments ((order + 1)² RGB coefficients each)
    occlusion: bool = True  #: environments occluded by the mesh itself (per-texel transfer, ray traced once)
    transfer_rays: int = 256  #: rays per texel for the transfer
    #: unknown lighting: the lights average to white (grey world), which fixes the per-channel split of colour
    #: between albedo and light that images cannot resolve
    grey_world: bool = True
    light_init_error_deg: float = 0.0  #: perturb the initial light directions (stability tests)
    init_roughness: float = 0.5
    init_specular: float = 0.5
    seed: int = 0

    def __post_init__(self):
        if len(self.levels) != len(self.iterations):
            raise UsageError(f"iterations: one Adam step count per pyramid level ({len(self.levels)}: "
                             f"{', '.join(f'{f:g}' for f in self.levels)} of the resolution), got {len(self.iterations)}")
        for f in self.levels:
            validate.in_range("levels", f, 0.0, 1.0, lo_open=True)
        for n in self.iterations:
            validate.integer("iterations", n, 0, 1_000_000)
        validate.positive("lr", self.lr)
        validate.positive("lr_normal", self.lr_normal)
        for name in ("w_smooth_roughness", "w_smooth_specular", "w_smooth_normal", "w_chroma"):
            validate.non_negative(name, getattr(self, name))
        validate.in_range("light_init_error_deg", self.light_init_error_deg, 0.0, 180.0)
        validate.one_of("light_model", self.light_model, ("sh", "directional"))
        validate.integer("sh_order", self.sh_order, 0, 6)
        validate.integer("transfer_rays", self.transfer_rays, 1, 1 << 16)
        validate.in_range("init_roughness", self.init_roughness, 0.05, 1.0)
        validate.in_range("init_specular", self.init_specular, 0.0, 1.0)
        validate.seed("seed", self.seed)


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
    return mi.TensorXf(aligned(a))


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



def _env_init(basis: np.ndarray, mask: np.ndarray, vis: list, obs: dict, n_views: int, n_lights: int,
              rounds: int = 10, grey_world: bool = False) -> tuple[np.ndarray, list[np.ndarray]]:
    """Albedo (H, W, 3) and per-light SH coefficients (n_coeffs, 3) by alternating least squares of the diffuse
    model O_vk(u) ≈ ρ(u)/π Σ_j L_kj B_j(u) (flat normals, no gloss): each half is linear in its unknowns.

    The scale shared by albedo and light is fixed by putting the albedo's 99th percentile at 0.8; each channel's
    scale, as ambiguous (a bluer light on a less blue skin), by ``grey_world``: the lights average to white.
    """
    m = mask.ravel()
    b = basis.reshape(-1, basis.shape[-1])[m].astype(np.float64) / np.pi  # (P, J)
    vs = [np.array(vis[v]).reshape(-1)[m] > 0.5 for v in range(n_views)]
    o = {key: np.array(val).reshape(-1, 3)[m].astype(np.float64) for key, val in obs.items()}
    rho = np.full((b.shape[0], 3), 0.5)
    coeffs = [np.zeros((b.shape[1], 3)) for _ in range(n_lights)]
    ridge = 1e-3 * float(np.mean(b * b)) * len(b)  # keeps directions the texels hardly see from growing
    for _ in range(rounds):
        for k in range(n_lights):
            for c in range(3):
                ata = np.zeros((b.shape[1],) * 2)
                atb = np.zeros(b.shape[1])
                for v in range(n_views):
                    a = b[vs[v]] * rho[vs[v], c:c + 1]
                    ata += a.T @ a
                    atb += a.T @ o[v, k][vs[v], c]
                coeffs[k][:, c] = np.linalg.solve(ata + ridge * np.eye(len(atb)), atb)
        num, den = np.zeros_like(rho), np.zeros_like(rho)
        for k in range(n_lights):
            shade = b @ coeffs[k]  # (P, 3)
            for v in range(n_views):
                num[vs[v]] += o[v, k][vs[v]] * shade[vs[v]]
                den[vs[v]] += shade[vs[v]] ** 2
        seen = den.min(1) > 1e-12
        rho = np.where(seen[:, None], num / np.maximum(den, 1e-12), np.median(rho[seen], 0) if seen.any() else 0.5)
        if grey_world:  # the lights' mean colour (their DC terms) white; the albedo keeps every product ρ·L
            dc = np.mean([c[0] for c in coeffs], 0)
            tint = np.where(dc > 0, dc / max(float(dc.mean()), 1e-12), 1.0)
            rho *= tint
            coeffs = [c / tint for c in coeffs]
        scale = 0.8 / max(float(np.percentile(rho[seen], 99)) if seen.any() else 1.0, 1e-6)
        rho *= scale
        coeffs = [c / scale for c in coeffs]
    out = np.full(mask.shape + (3,), 0.4, np.float32)
    out.reshape(-1, 3)[m] = np.clip(rho, 0.0, 1.0)
    return out, coeffs


@dataclass
class FaceFitResult:
    maps: dict[str, np.ndarray]  #: albedo (H,W,3), normal (H,W,3 unit tangent-space), roughness, specular, displacement (H,W,1)
    observed: np.ndarray  #: (H, W) bool: texel lit and seen at least once
    lights: list[Light]  #: fitted (or given) lights
    ambient: float
    loss_history: list[float]
    seconds: float
    training: TrainingSummary | None = None
    environments: list[np.ndarray] | None = None  #: light_model "sh": per observation light, (n_coeffs, 3) SH radiance


_MAPS = ("albedo", "slope", "roughness", "specular")




class FaceFitStage(DrJitStage):
    """Adam through the UV-space shader over a coarse-to-fine pyramid: one loop over all levels' steps."""

    name = "face fit"

    def __init__(self, bench: FaceBenchmark, s: FaceFitSettings):
        self.bench, self.s = bench, s
        rng = np.random.default_rng(s.seed)
        self.mesh = load_obj(bench.mesh_path)
        self.full = bench.geometry["mask"].shape[0]
        self.views = [np.asarray(v) for v in bench.meta.views]
        self.lights_meta = bench.meta.lights
        if not s.fit_lights and any(l.kind == "hdri" for l in self.lights_meta):
            raise UsageError(f"{bench.path}: its observations are lit by HDRIs; their key directions are only a start "
                             "for a fit of the lighting (--fit-lights / FaceFitSettings(fit_lights=True))")
        self.n_views, self.n_lights = len(self.views), len(self.lights_meta)
        # Light parameters (directions normalised in the loss; intensities positive).
        self.dirs0 = [_rotate_towards_random(np.asarray(l.to_light), s.light_init_error_deg, rng)
                      for l in self.lights_meta]
        if s.fit_lights:
            self.inten0 = [np.full(3, float(np.mean(l.irradiance))) * 0.7 for l in self.lights_meta]
        else:
            self.inten0 = [np.asarray(l.irradiance, float) for l in self.lights_meta]
        self.env = s.fit_lights and s.light_model == "sh"
        self.transfer = None
        if self.env and s.occlusion:
            self.transfer = environment_transfer(bench.mesh_path, bake_geometry(self.mesh, self.full), s.sh_order,
                                                 s.transfer_rays, s.seed)
        self.bounds = np.cumsum([0, *s.iterations])  #: first step of every level
        self.level = -1
        self.opt = None
        self.light_params: dict = {}

    # -- levels ---------------------------------------------------------------------------------------------------

    def _level_of(self, it: int) -> int:
        return int(np.searchsorted(self.bounds, it, side="right") - 1)

    def _enter(self, level: int, maps_np: dict | None) -> None:
        """Level data (box averages of the observations) and a fresh Adam started from ``maps_np``."""
        s, bench = self.s, self.bench
        res = max(8, int(round(self.full * s.levels[level])))
        factor = self.full // res
        res = self.full // factor
        geo = bake_geometry(self.mesh, res)
        self.mask_np = geo.mask.astype(np.float32)
        # Level data: visibility-weighted box averages; a texel counts only if every sub-texel was seen.
        self.obs_l, self.vis_l = {}, {}
        for v in range(self.n_views):
            vis_lv = _downsample(bench.visibility[f"v{v}"], factor)
            self.vis_l[v] = _tensor(((vis_lv > 0.999) & geo.mask).astype(np.float32)[..., None])
            for k in range(self.n_lights):
                self.obs_l[v, k] = _tensor(_downsample(bench.observations[f"v{v}_l{k}"], factor))
        self.lvis = [_tensor(_downsample(bench.visibility[f"light{k}"], factor)[..., None]) for k in range(self.n_lights)]
        self.pos, self.nrm, self.tan = _tensor(geo.position), _tensor(geo.normal), _tensor(geo.tangent)
        self.res = res
        env0 = None
        if self.env:
            basis = self._env_basis(geo, factor)
            self.transfer_l = None if self.transfer is None else _tensor(basis)
            if level == 0:
                albedo0, env0 = _env_init(basis, geo.mask, [self.vis_l[v] for v in range(self.n_views)],
                                          self.obs_l, self.n_views, self.n_lights, grey_world=s.grey_world)
        if maps_np is None:
            params = {
                "albedo": albedo0 if env0 is not None else _albedo_init(
                    self.pos, self.nrm, self.tan, self.views, self.dirs0, self.inten0, self.vis_l, self.lvis,
                    self.obs_l, res),
                "slope": np.zeros((res, res, 2), np.float32),
                "roughness": np.full((res, res, 1), s.init_roughness, np.float32),
                "specular": np.full((res, res, 1), s.init_specular, np.float32),
            }
        else:
            params = {k: (v if v.shape[0] == res else _upsample(v, (res, res))).astype(np.float32)
                      for k, v in maps_np.items()}
        self.opt = mi.ad.Adam(lr=s.lr)
        for k, v in params.items():
            self.opt[k] = _tensor(v)
        self.opt.set_learning_rate({"slope": s.lr_normal})
        if self.env:
            for k in range(self.n_lights):
                c = env0[k] if level == 0 else np.array(self.light_params[f"sh{k}"]).T  # (n_coeffs, 3)
                self.opt[f"sh{k}"] = mi.Color3f(aligned(np.ascontiguousarray(c.T)))
                # Adam moves every coefficient by ~lr per step: in units of the environment's largest coefficient
                self.opt.set_learning_rate({f"sh{k}": s.lr * max(float(np.abs(c).max()), 1e-6)})
        elif s.fit_lights:
            for k in range(self.n_lights):
                if level == 0:
                    self.opt[f"dir{k}"] = mi.Vector3f(*map(float, self.dirs0[k]))
                    self.opt[f"int{k}"] = mi.Color3f(*map(float, self.inten0[k]))
                else:
                    self.opt[f"dir{k}"] = self.light_params[f"dir{k}"]
                    self.opt[f"int{k}"] = self.light_params[f"int{k}"]
            self.opt["ambient"] = mi.Float(0.0 if level == 0 else self.light_params["ambient"])
        self.n_valid = max(1.0, float(self.mask_np.sum()))
        self.level = level

    def _env_basis(self, geo, factor: int) -> np.ndarray:
        """Per texel of a level, what each SH coefficient gives a flat-normal texel: the transfer (box average of
        the full-resolution one) or, unoccluded, Â_l Y_lm(n)."""
        from mi_plugins import sh

        if self.transfer is not None:
            return _downsample(self.transfer, factor).astype(np.float32)
        n = geo.normal
        y = sh.basis(n[..., 0], n[..., 1], n[..., 2], self.s.sh_order)
        return np.stack([sh.cosine_lobe(sh.band(j)) * y[j] for j in range(len(y))], -1).astype(np.float32)

    def _leave(self) -> dict:
        """The current level's maps (numpy) and fitted lights (kept for the next level)."""
        maps = {k: np.array(self.opt[k]) for k in _MAPS}
        if self.s.fit_lights:
            self.light_params = {k: type(self.opt[k])(self.opt[k]) for k in self.opt.keys()
                                 if k.startswith(("dir", "int", "ambient", "sh"))}
        return maps

    # -- the loop's interface -------------------------------------------------------------------------------------

    def fingerprint(self) -> dict:
        return {"settings": self.s, "benchmark": benchmark_digest(self.bench)}

    def state(self) -> dict:
        if self.opt is None:
            return {"level": -1}
        return {"level": self.level, "optimizer": optimizer_state(self.opt),
                "maps": {k: np.array(self.opt[k]) for k in _MAPS}}

    def load_state(self, tree: dict) -> None:
        if tree["level"] < 0:
            return
        if self.env and tree["level"] > 0:
            from mi_plugins import sh

            self.light_params = {f"sh{k}": mi.Color3f(np.zeros((3, sh.n_coeffs(self.s.sh_order)), np.float32))
                                 for k in range(self.n_lights)}
        elif self.s.fit_lights and tree["level"] > 0:
            # the level was entered with the previous level's lights; its optimiser state holds the current ones
            self.light_params = {f"dir{k}": mi.Vector3f(0.0) for k in range(self.n_lights)}
            self.light_params.update({f"int{k}": mi.Color3f(0.0) for k in range(self.n_lights)})
            self.light_params["ambient"] = mi.Float(0.0)
        self._enter(tree["level"], tree["maps"])
        load_optimizer_state(self.opt, tree["optimizer"], "face fit optimizer")

    def step(self, it: int) -> StepResult:
        s, opt = self.s, None
        level = self._level_of(it)
        if level != self.level:
            self._enter(level, self._leave() if self.opt is not None else None)
        opt, res = self.opt, self.res
        slope = opt["slope"]
        sx, sy = unravel_channels(slope.array, 2)
        n_ts = dr.normalize(mi.Vector3f(sx, sy, 1.0))
        enc = mi.TensorXf(dr.ravel(n_ts * 0.5 + 0.5), shape=(res, res, 3))
        maps = UVMaps(albedo=opt["albedo"], normal=enc, roughness=opt["roughness"], specular=opt["specular"])
        loss = mi.Float(0.0)
        for k in range(self.n_lights):
            if self.env:
                env = UVEnvironment(opt[f"sh{k}"], self.transfer_l)
                for v in range(self.n_views):
                    pred = shade_uv(self.pos, self.nrm, self.tan, maps, [], UVView(position=tuple(self.views[v])),
                                    mask=self.vis_l[v], environment=env)
                    diff = pred - self.obs_l[v, k] * self.vis_l[v]
                    loss += dr.sum(diff * diff, axis=None) / (self.n_valid * self.n_views * self.n_lights)
                continue
            if s.fit_lights:
                light = UVLight("directional", dr.normalize(opt[f"dir{k}"]), opt[f"int{k}"])
                amb = opt["ambient"]
            else:
                light = UVLight("directional", tuple(self.dirs0[k]), tuple(self.inten0[k]))
                amb = 0.0
            for v in range(self.n_views):
                pred = shade_uv(self.pos, self.nrm, self.tan, maps, [light], UVView(position=tuple(self.views[v])),
                                ambient=0.0, mask=self.vis_l[v], light_visibility=[self.lvis[k]])
                if s.fit_lights:
                    pred = pred + opt["albedo"] * mi.TensorXf(amb) * self.vis_l[v]
                diff = pred - self.obs_l[v, k] * self.vis_l[v]
                loss += dr.sum(diff * diff, axis=None) / (self.n_valid * self.n_views * self.n_lights)
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
        return self.result(total, log={"level": level})

    def apply(self, it: int) -> None:
        opt, s = self.opt, self.s
        opt.step()
        # Keep maps in their valid ranges (projected Adam).
        opt["albedo"] = dr.clip(opt["albedo"], 0.0, 1.0)
        opt["roughness"] = dr.clip(opt["roughness"], 0.05, 1.0)
        opt["specular"] = dr.clip(opt["specular"], 0.0, 1.0)
        opt["slope"] = dr.clip(opt["slope"], -3.0, 3.0)
        if self.env and s.grey_world:
            self._grey_world()
        if s.fit_lights and not self.env:
            for k in range(self.n_lights):
                opt[f"int{k}"] = dr.maximum(opt[f"int{k}"], 0.0)
            opt["ambient"] = dr.maximum(opt["ambient"], 0.0)

    def _grey_world(self) -> None:
        """Project onto lights that average to white: albedo × tint, every environment ÷ tint (the diffuse
        products unchanged), tint = the environments' mean DC colour over its grey level."""
        opt = self.opt
        dc = sum(dr.gather(mi.Color3f, opt[f"sh{k}"], 0) for k in range(self.n_lights)) / self.n_lights
        grey = (dc.x + dc.y + dc.z) / 3.0
        tint = dr.select(dc > 0, dc / dr.maximum(grey, 1e-12), 1.0)
        for k in range(self.n_lights):
            opt[f"sh{k}"] = opt[f"sh{k}"] / tint
        r_, g_, b_ = unravel_channels(opt["albedo"].array, 3)
        tinted = mi.Vector3f(r_ * tint.x, g_ * tint.y, b_ * tint.z)
        opt["albedo"] = mi.TensorXf(dr.ravel(dr.clip(tinted, 0.0, 1.0)), shape=opt["albedo"].shape)

    def finish(self, run: RunState) -> FaceFitResult:
        s, bench, full = self.s, self.bench, self.full
        if self.opt is None:  # no steps at all: the first level's initial maps
            self._enter(0, None)
        maps_np = self._leave()
        observed_full = np.zeros((full, full), bool)
        for v in range(self.n_views):
            for k in range(self.n_lights):
                obs = bench.observations[f"v{v}_l{k}"]
                observed_full |= (bench.visibility[f"v{v}"] > 0) & (obs.sum(-1) > 1e-6)
        slope = maps_np["slope"]
        n = np.concatenate([slope, np.ones(slope.shape[:2] + (1,), np.float32)], axis=-1)
        n /= np.linalg.norm(n, axis=-1, keepdims=True)
        observed = observed_full if maps_np["albedo"].shape[0] == full else _downsample(
            observed_full.astype(np.float32), full // maps_np["albedo"].shape[0]) > 0.5
        maps_out = {"albedo": maps_np["albedo"], "normal": n.astype(np.float32), "roughness": maps_np["roughness"],
                    "specular": maps_np["specular"]}
        maps_out = fill_unobserved(maps_out, observed, bench.geometry["mask"] > 0)
        geo_full = bake_geometry(self.mesh, maps_out["albedo"].shape[0])
        maps_out["displacement"] = integrate_normals(maps_out["normal"], geo_full.bitangent_sign, geo_full.mask)
        environments = None
        if self.env:
            environments = [np.array(self.light_params[f"sh{k}"]).reshape(3, -1).T.copy() for k in range(self.n_lights)]
            lights, ambient = list(self.lights_meta), 0.0
        elif s.fit_lights:
            lp = self.light_params
            lights = [Light("directional",
                            tuple(map(float, np.array(lp[f"dir{k}"]).ravel() / np.linalg.norm(np.array(lp[f"dir{k}"]).ravel()))),
                            tuple(map(float, np.array(lp[f"int{k}"]).ravel()))) for k in range(self.n_lights)]
            ambient = float(np.array(lp["ambient"]).ravel()[0])
        else:
            lights, ambient = list(self.lights_meta), 0.0
        return FaceFitResult(maps_out, observed, lights, ambient, list(run.losses), run.train_seconds,
                             run.summary(), environments)


def fit_face(bench: FaceBenchmark, s: FaceFitSettings | None = None, show_progress: bool = True,
             checkpoint: str | Path | None = None) -> FaceFitResult:
    """Fit UV material maps to a benchmark's texel-aligned observations (resumable with ``checkpoint``)."""
    s = s or FaceFitSettings()
    t0 = time.perf_counter()
    result = run_loop(FaceFitStage(bench, s), LoopSettings(steps=int(sum(s.iterations)), checkpoint_every=50),
                      checkpoint=checkpoint, show_progress=show_progress)
    result.seconds = time.perf_counter() - t0
    return result


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
    from foundation import imageio

    out.mkdir(parents=True, exist_ok=True)
    imageio.write_exr(out / "maps.exr", maps)
    imageio.write_png(out / "albedo.png", maps["albedo"])
    imageio.write_png(out / "normal.png", maps["normal"] * 0.5 + 0.5, linear=False)
    imageio.write_png(out / "roughness.png", np.repeat(maps["roughness"], 3, -1), linear=False)
    imageio.write_png(out / "specular.png", np.repeat(maps["specular"], 3, -1), linear=False)
    imageio.write_png(out / "displacement.png", np.repeat(maps["displacement"], 3, -1), linear=False)


@dataclass
class RelitMetrics:
    psnr: float  #: on the face pixels of the held-out camera
    flip: float


@dataclass
class FaceFitMetrics:
    """Fitted maps against the benchmark's ground truth (and relit under held-out HDRIs)."""

    albedo_psnr: float  #: after the least-squares global scale ``albedo_scale``
    albedo_ssim: float
    albedo_scale: float
    normal_err_deg: float
    normal_err_deg_median: float
    roughness_mae: float
    specular_mae: float
    displacement_corr: float
    observed_fraction: float  #: share of the covered texels that an observation constrains
    seconds: float
    uv_res: int
    relit: dict[str, RelitMetrics] = field(default_factory=dict)  #: per held-out HDRI (empty: not relit)
    relit_psnr: float | None = None
    relit_flip: float | None = None


def evaluate_fit(bench: FaceBenchmark, result: FaceFitResult, relight: bool = True,
                 images: dict | None = None) -> FaceFitMetrics:
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
    from foundation.metrics import angular_error_deg, flip, global_scale, masked_psnr, psnr, ssim

    from .benchmark import render_heldout

    gt, fit, m = bench.ground_truth, result.maps, result.observed
    covered = bench.geometry["mask"] > 0
    scale = global_scale(fit["albedo"][m], gt["albedo"][m])
    albedo = np.clip(fit["albedo"] * scale, 0, 1)
    a_img, g_img = np.where(m[..., None], albedo, 0), np.where(m[..., None], gt["albedo"], 0)
    disp_corr = float(np.corrcoef(fit["displacement"][covered].ravel(), gt["displacement"][covered].ravel())[0, 1])
    out = FaceFitMetrics(
        albedo_psnr=psnr(albedo[m], gt["albedo"][m]),
        albedo_ssim=ssim(a_img, g_img),
        albedo_scale=scale,
        normal_err_deg=float(angular_error_deg(fit["normal"][m], gt["normal"][m]).mean()),
        normal_err_deg_median=float(np.median(angular_error_deg(fit["normal"][m], gt["normal"][m]))),
        roughness_mae=float(np.abs(fit["roughness"][m] - gt["roughness"][m]).mean()),
        specular_mae=float(np.abs(fit["specular"][m] - gt["specular"][m]).mean()),
        displacement_corr=disp_corr,
        observed_fraction=float(m[covered].mean()),
        seconds=result.seconds,
        uv_res=int(m.shape[0]))
    if relight:
        s = bench.settings
        cam = bench.meta.heldout_camera
        maps = dict(fit, albedo=albedo)
        for hdri in s.heldout_hdris:
            rgb, _ = render_heldout(bench.mesh_path, maps, s, hdri, np.asarray(cam.eye), np.asarray(cam.target),
                                    cam.fov)
            name = hdri_label(hdri)
            ref = bench.heldout[name]
            mask = bench.heldout[f"{name}_mask"][..., 0] > 0.5
            out.relit[name] = RelitMetrics(masked_psnr(rgb, ref, mask), flip(rgb, ref, mask=mask))
            if images is not None:
                images[name] = rgb
        out.relit_psnr = float(np.mean([v.psnr for v in out.relit.values()]))
        out.relit_flip = float(np.mean([v.flip for v in out.relit.values()]))
    return out


# -- fitting through full Mitsuba renders ------------------------------------------------------




# -- the `photoreal face fit` workflow ------------------------------------------------------------


