"""UV-space GGX shader (seed 003, the T̂_shaded equation) — no rasterisation, no ray tracing.

    T̂_shaded(u) = M(u) [ Σ_k L_k (n·l_k)⁺ (f_d(u) + f_s(u, v, l_k)) + I_amb T̂_alb(u) ]

Every texel u of a template mesh's UV atlas carries its position, geometric
normal and tangent (precomputed maps). The shader displaces the position along
the geometric normal (``s_disp · d``), builds the tangent frame (Gram–Schmidt),
applies the tangent-space normal map, and evaluates the *same* GGX functions
as the ``ggx_uv`` BSDF (:mod:`mi_plugins.shading`): ``brdf_lobes`` already
includes the cosine (n·l)⁺, so a texel equals what Mitsuba renders for the
same surface point under the same light and view (test: ``test_uv_shader``).

Lights: ``directional`` (``vector`` = direction *towards* the light,
``intensity`` = irradiance on a surface facing it, as Mitsuba's
``directional`` emitter) or ``point`` (``vector`` = position, ``intensity`` =
radiant intensity, falloff 1/r²). The view is a camera position (perspective)
or a constant direction towards the camera (orthographic). Lights below the
geometric horizon give nothing (the surface itself blocks them); cast shadows
from other parts of the mesh are the visibility mask's job.

Environment light (``UVEnvironment``): radiance as real spherical harmonics (:mod:`mi_plugins.sh`),

    T̂_env(u) = M(u) [ (1 − metallic) T̂_alb/π · E(u, n') + DFG(n'·v, α) · s(u) · Σ_lm g_l(α) L_lm Y_lm(r) ]
    E(u, n') = h(n') Σ_lm L_lm [ T_lm(u) + a(u) Â_l (Y_lm(n') − Y_lm(n_geo)) ],   h = (1 + n'·n_geo) / 2

with n' the mapped normal, r the view mirrored about it, T_lm(u) the texel's precomputed transfer (occluded
cosine, :mod:`mi_plugins.sh`; without one, T_lm = Â_l Y_lm(n_geo): no occlusion), a(u) = T_00 / (π Y_00) its
visible cosine-weighted fraction, which also occludes the glossy term (s = a), h the share of the mapped normal's
cosine lobe above the geometric horizon (which cuts it, as in Mitsuba's ``normalmap``), and DFG the glossy lobe's
directional albedo (:func:`mi_plugins.shading.directional_albedo`). Exact for the diffuse term under band-limited
light at the geometric normal; the mapped normal's change is first order, the glossy term an approximation.

All inputs are Dr.Jit tensors/arrays, so gradients flow to every map.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal, Sequence

import drjit as dr
import mitsuba as mi
import numpy as np

from . import sh as harmonics
from . import shading as sh


@dataclass(frozen=True)
class UVLight:
    """A light; ``vector``/``intensity`` are triples, or Dr.Jit arrays when being optimised."""

    kind: Literal["directional", "point"]
    vector: tuple[float, float, float] | mi.Vector3f  #: towards the light (directional) or position (point)
    intensity: tuple[float, float, float] | mi.Color3f = (1.0, 1.0, 1.0)

    def __post_init__(self):
        if self.kind not in ("directional", "point"):
            raise ValueError(f"UVLight.kind must be 'directional' or 'point', got {self.kind!r}")
        for name in ("vector", "intensity"):
            v = getattr(self, name)
            if not dr.is_array_v(v) and not np.all(np.isfinite(np.asarray(v, float))):
                raise ValueError(f"UVLight.{name} is not finite: {v}")
        if self.kind == "directional" and not dr.is_array_v(self.vector) and np.linalg.norm(self.vector) == 0:
            raise ValueError("UVLight: a directional light needs a non-zero direction")


@dataclass(frozen=True)
class UVView:
    """Camera position (perspective) or direction towards the camera (orthographic)."""

    position: tuple[float, float, float] | None = None
    direction: tuple[float, float, float] | None = None

    def __post_init__(self):
        if (self.position is None) == (self.direction is None):
            raise ValueError("UVView needs exactly one of 'position' or 'direction'")


@dataclass
class UVEnvironment:
    """Environment radiance as SH coefficients and, optionally, each texel's occluded transfer.

    coeffs: (n_coeffs, 3) numbers, or a Color3f of n_coeffs entries when being optimised (order = √n − 1).
    transfer: (H, W, n_coeffs) tensor T_lm(u) = ∫ V (n_geo·ω)⁺ Y_lm dω of the texels (None: nothing occludes).
    """

    coeffs: np.ndarray | mi.Color3f
    transfer: mi.TensorXf | None = None

    @property
    def n(self) -> int:
        return dr.width(self.coeffs) if dr.is_array_v(self.coeffs) else len(self.coeffs)

    def __post_init__(self):
        n = self.n
        if int(np.sqrt(n)) ** 2 != n:
            raise ValueError(f"UVEnvironment: {n} coefficients is not (order + 1)²")
        if self.transfer is not None and self.transfer.shape[-1] != n:
            raise ValueError(f"UVEnvironment: transfer has {self.transfer.shape[-1]} channels for {n} coefficients")


@dataclass
class UVMaps:
    """Material maps in UV space, each an (H, W, C) tensor or a constant.

    albedo: C=3 linear RGB; normal: C=3 encoded tangent-space normal (2·rgb − 1);
    roughness, specular, metallic, displacement: C=1.
    """

    albedo: mi.TensorXf | float | Sequence[float] = 0.5
    normal: mi.TensorXf | Sequence[float] | None = None
    roughness: mi.TensorXf | float = 0.5
    specular: mi.TensorXf | float = 0.5
    metallic: mi.TensorXf | float = 0.0
    displacement: mi.TensorXf | float = 0.0
    s_disp: float = field(default=sh.S_DISP_DEFAULT)


def _const3(v) -> mi.Vector3f:
    if dr.is_array_v(v):
        return mi.Vector3f(v)
    return mi.Vector3f(*(float(c) for c in v))


def unravel_channels(arr: mi.Float, c: int) -> list[mi.Float]:
    """Split an interleaved (…, C) array into C channel arrays with plain gathers.

    Not ``dr.unravel``: in Dr.Jit 1.5 its backward pass *overwrites* the
    source's gradient, so when the same array is unravelled more than once
    (e.g. one shading call per light) only one call's gradient survives
    (``tests/plugins/test_uv_shader.py::test_gradients_accumulate_over_lights``).
    ``dr.gather`` accumulates correctly.
    """
    n = dr.width(arr) // c
    i = dr.arange(mi.UInt32, n) * c
    return [dr.gather(mi.Float, arr, i + k) for k in range(c)]


def _vec3(x, n: int) -> mi.Vector3f:
    """(H, W, 3) tensor or a constant triple as a wavefront of n Vector3f."""
    if isinstance(x, mi.TensorXf):
        if x.shape[-1] != 3 or len(x.shape) != 3:
            raise ValueError(f"expected an (H, W, 3) tensor, got shape {x.shape}")
        return mi.Vector3f(*unravel_channels(x.array, 3))
    c = np.broadcast_to(np.asarray(x, dtype=np.float32), (3,))
    return mi.Vector3f(*[dr.full(mi.Float, float(v), n) for v in c])


def _scalar(x, n: int) -> mi.Float:
    if isinstance(x, mi.TensorXf):
        if len(x.shape) == 3 and x.shape[-1] != 1:
            raise ValueError(f"expected an (H, W, 1) tensor, got shape {x.shape}")
        return mi.Float(x.array)
    return dr.full(mi.Float, float(x), n)


def shade_uv(
    position: mi.TensorXf,
    normal: mi.TensorXf,
    tangent: mi.TensorXf,
    maps: UVMaps,
    lights: Sequence[UVLight],
    view: UVView,
    ambient: float | Sequence[float] = 0.0,
    mask: mi.TensorXf | None = None,
    light_visibility: Sequence[mi.TensorXf | None] | None = None,
    environment: UVEnvironment | None = None,
) -> mi.TensorXf:
    """Shaded UV texture T̂_shaded, an (H, W, 3) tensor (seed 003).

    position/normal/tangent: (H, W, 3) geometry maps of the template mesh.
    mask: (H, W) or (H, W, 1) visibility M(u) in [0, 1]; None = all visible.
    ambient: I_amb (scalar or RGB), multiplies the albedo.
    light_visibility: per light, an optional (H, W) cast-shadow factor in [0, 1]
    (1 = the light reaches the texel), e.g. precomputed by ray tracing.
    environment: SH environment light added to the lights (see the module docstring).
    """
    if light_visibility is not None and len(light_visibility) != len(lights):
        raise ValueError(f"light_visibility has {len(light_visibility)} entries for {len(lights)} lights")
    if len(position.shape) != 3 or position.shape[-1] != 3:
        raise ValueError(f"position map must be (H, W, 3), got {position.shape}")
    h, w = position.shape[0], position.shape[1]
    n = h * w
    for name, t in (("normal", normal), ("tangent", tangent)):
        if tuple(t.shape) != tuple(position.shape):
            raise ValueError(f"{name} map shape {t.shape} differs from position map {position.shape}")

    # Geometry: displacement along the geometric normal, Gram–Schmidt tangent frame.
    n_geo = dr.normalize(_vec3(normal, n))
    p = sh.displace(_vec3(position, n), n_geo, _scalar(maps.displacement, n), maps.s_disp)
    geo = sh.frame_from_normal_tangent(n_geo, _vec3(tangent, n))

    if view.position is not None:
        v_world = dr.normalize(_const3(view.position) - p)
    else:
        v_world = dr.normalize(_const3(view.direction))
    wi = geo.to_local(v_world)

    n_local = None if maps.normal is None else sh.decode_normal(_vec3(maps.normal, n))
    frame, wi_p, valid_i = sh.perturbation(n_local, wi)

    albedo = mi.Color3f(_vec3(maps.albedo, n))
    rough, spec, metal = (_scalar(m, n) for m in (maps.roughness, maps.specular, maps.metallic))

    result = mi.Color3f(0.0)
    for k, light in enumerate(lights):
        if light.kind == "directional":
            l_world = dr.normalize(_const3(light.vector))
            radiance = mi.Color3f(_const3(light.intensity))
        else:
            d = _const3(light.vector) - p
            dist2 = dr.squared_norm(d)
            l_world = d * dr.rsqrt(dist2)
            radiance = mi.Color3f(_const3(light.intensity)) / dist2
        wo_p, valid_o = sh.to_perturbed(frame, geo.to_local(l_world))
        f_d, f_s = sh.brdf_lobes(albedo, rough, spec, metal, wi_p, wo_p)
        contrib = dr.select(valid_i & valid_o, radiance * (f_d + f_s), 0.0)
        if light_visibility is not None and light_visibility[k] is not None:
            contrib *= mi.Float(light_visibility[k].array)
        result += contrib

    if environment is not None:
        result += _environment(environment, geo, n_geo, v_world, frame, wi_p, valid_i, albedo, rough, spec, metal, n)

    amb = np.broadcast_to(np.asarray(ambient, dtype=np.float32), (3,))
    result += albedo * mi.Color3f(*[float(a) for a in amb])
    if mask is not None:
        result *= mi.Float(mask.array)
    return mi.TensorXf(dr.ravel(result), shape=(h, w, 3))


def _environment(env: UVEnvironment, geo: mi.Frame3f, n_geo: mi.Vector3f, v_world: mi.Vector3f,
                 frame: mi.Frame3f | None, wi_p: mi.Vector3f, valid_i: mi.Bool, albedo: mi.Color3f, rough: mi.Float,
                 spec: mi.Float, metal: mi.Float, n: int) -> mi.Color3f:
    """Diffuse and glossy reflection of an SH environment at every texel (module docstring, T̂_env)."""
    j_count = env.n
    order = int(np.sqrt(j_count)) - 1
    if dr.is_array_v(env.coeffs):
        coeff = [dr.gather(mi.Color3f, env.coeffs, j) for j in range(j_count)]
    else:
        c = np.asarray(env.coeffs, np.float64)
        coeff = [mi.Color3f(*map(float, c[j])) for j in range(j_count)]
    n_sh = n_geo if frame is None else geo.to_world(frame.n)
    y_sh = harmonics.basis(n_sh.x, n_sh.y, n_sh.z, order)
    lobe = [harmonics.cosine_lobe(harmonics.band(j)) for j in range(j_count)]
    irr = mi.Color3f(0.0)
    if env.transfer is None:
        for j in range(j_count):
            if lobe[j] != 0.0:
                irr += coeff[j] * (lobe[j] * y_sh[j])
        occl = mi.Float(1.0)
    else:
        t = unravel_channels(env.transfer.array, j_count)
        occl = dr.clip(t[0] / (dr.pi * harmonics.basis(0.0, 0.0, 1.0, 0)[0]), 0.0, 1.0)
        y_geo = harmonics.basis(n_geo.x, n_geo.y, n_geo.z, order)
        for j in range(j_count):
            irr += coeff[j] * (t[j] + occl * lobe[j] * (y_sh[j] - y_geo[j]))
    if frame is not None:
        # the mapped normal's hemisphere is cut by the geometric one (Mitsuba's normalmap): exact for uniform light
        irr *= 0.5 * (1.0 + dr.dot(n_sh, n_geo))
    diffuse = (1.0 - metal) * albedo * dr.inv_pi * irr
    r = 2.0 * dr.dot(v_world, n_sh) * n_sh - v_world
    y_r = harmonics.basis(r.x, r.y, r.z, order)
    alpha = sh.alpha_from_roughness(rough)
    refl = mi.Color3f(0.0)
    for j in range(j_count):
        refl += coeff[j] * (harmonics.glossy_lobe(harmonics.band(j), alpha) * y_r[j])
    f0 = sh.f0_from_maps(albedo, spec, metal)
    glossy = sh.directional_albedo(f0, sh.f90_from_f0(f0), rough, wi_p.z) * occl * refl
    return dr.select(valid_i, diffuse + glossy, mi.Color3f(0.0))
