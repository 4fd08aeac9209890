"""GGX shading maths: the one implementation behind ``ggx_uv`` and the UV-space shader.

Notation (seed 003, "UV-space differentiable GGX BRDF"; Walter et al. 2007;
Heitz 2014/2018):

=========  =====================  =============================================
code       paper                  meaning
=========  =====================  =============================================
wi, wo     v, l                   unit directions in the *local* shading frame
                                  (z = shading normal), pointing away
h          h                      half vector normalize(wi + wo)
alpha      α = roughness²         GGX width (perceptual-roughness convention)
f0         F0                     normal-incidence reflectance
f90        F90                    grazing reflectance
albedo     T_alb                  diffuse albedo (linear RGB)
=========  =====================  =============================================

Model (per texel u):

* diffuse   ``f_d = (1 - metallic) · albedo / π``                      (Lambert)
* specular  ``f_s = D(h) · G(wi, wo, h) · F(wi·h) / (4 cosθi cosθo)``  (Cook–Torrance)
* ``f = f_d + f_s`` — the plain sum of seed 003's T̂_shaded equation. Like the
  paper's "GGX proxy" it is not strictly energy conserving (the diffuse lobe is
  not reduced by 1 − F); at F0 = 0.08·specular ≤ 0.08 the excess is small.
* ``D``: GGX / Trowbridge–Reitz, isotropic, α = roughness².
* ``G``: **separable** Smith, G = G1(wi)·G1(wo) (not height-correlated), the
  same form as Mitsuba's builtin microfacet plugins so that ``roughconductor``
  is an exact oracle.
* ``F``: Schlick, ``F = F0 + (F90 − F0)(1 − cos)^5`` with cos = wi·h.
  Convention (UE4/Filament): ``F0 = lerp(0.08 · specular, albedo, metallic)``
  (``specular`` ∈ [0, 1], default 0.5 → F0 = 0.04, skin ≈ 0.35 → 0.028), and
  ``F90 = clamp(50 · luminance(F0), 0, 1)`` so that ``specular = 0`` really
  means "no specular reflection" (pure Lambert, which the white-furnace test
  relies on).

Geometry (seed 003 appendix): tangent-space normal maps store
``n_ts = 2·rgb − 1`` relative to the frame (T, B, N); T is re-orthogonalised
against N by Gram–Schmidt and B = N × T. Displacement moves points along the
geometric normal by ``s_disp · d`` (default ``s_disp = 0.01``).

All functions are plain Dr.Jit expressions on Mitsuba's types and so work on
one direction, on a wavefront inside a render, and on every texel of a UV map.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

S_DISP_DEFAULT = 0.01
F0_PER_SPECULAR = 0.08
ALPHA_MIN = 1e-4  # keeps D finite for roughness -> 0 (α = 1e-4 is mirror-like)

# -- Fresnel ------------------------------------------------------------------


def luminance(c: mi.Color3f) -> mi.Float:
    """Rec. 709 luminance of a linear RGB colour."""
    return c[0] * 0.212671 + c[1] * 0.715160 + c[2] * 0.072169


def f0_from_maps(albedo: mi.Color3f, specular: mi.Float, metallic: mi.Float) -> mi.Color3f:
    """F0 = lerp(0.08·specular, albedo, metallic) (see module docstring)."""
    dielectric = mi.Color3f(F0_PER_SPECULAR * specular)
    return dr.lerp(dielectric, albedo, metallic)


def f90_from_f0(f0: mi.Color3f) -> mi.Float:
    """F90 = clamp(50·lum(F0)): zero F0 switches the specular lobe fully off."""
    return dr.clip(50.0 * luminance(f0), 0.0, 1.0)


def schlick(f0: mi.Color3f, f90: mi.Float, cos_theta: mi.Float) -> mi.Color3f:
    """Schlick's approximation F0 + (F90 − F0)(1 − cosθ)^5."""
    m = dr.clip(1.0 - cos_theta, 0.0, 1.0)
    m2 = m * m
    return f0 + (f90 - f0) * (m2 * m2 * m)


# -- GGX distribution ------------------------------------------------------------


def alpha_from_roughness(roughness: mi.Float) -> mi.Float:
    """α = roughness², clamped below at ALPHA_MIN."""
    return dr.maximum(roughness * roughness, ALPHA_MIN)


def ggx_d(alpha: mi.Float, m: mi.Vector3f) -> mi.Float:
    """GGX normal distribution D(m), isotropic."""
    # 1 / (π α² ((x² + y²)/α² + z²)²): better conditioned in float32 than
    # α² / (π (cos²θ (α² − 1) + 1)²), which cancels catastrophically for small α.
    a2 = alpha * alpha
    denom = dr.fma(m.x, m.x, m.y * m.y) / a2 + m.z * m.z
    d = dr.rcp(dr.pi * a2 * denom * denom)
    return dr.select(m.z > 0.0, d, 0.0)


def smith_g1(alpha: mi.Float, v: mi.Vector3f, m: mi.Vector3f) -> mi.Float:
    """Smith masking G1(v, m) = 2 / (1 + sqrt(1 + α² tan²θ_v)), zero on the wrong side."""
    xy2 = dr.fma(v.x, v.x, v.y * v.y)
    tan2 = xy2 / dr.maximum(v.z * v.z, 1e-20)
    g = 2.0 / (1.0 + dr.sqrt(dr.fma(alpha * alpha, tan2, 1.0)))
    g = dr.select(xy2 == 0.0, 1.0, g)
    return dr.select(dr.dot(v, m) * v.z > 0.0, g, 0.0)


def sample_vndf(alpha: mi.Float, wi: mi.Vector3f, u: mi.Point2f) -> mi.Vector3f:
    """Sample a microfacet normal from the visible-normal distribution (Heitz 2018)."""
    # Stretch wi to the unit-roughness configuration.
    vh = dr.normalize(mi.Vector3f(alpha * wi.x, alpha * wi.y, wi.z))
    lensq = dr.fma(vh.x, vh.x, vh.y * vh.y)
    inv_len = dr.rsqrt(dr.maximum(lensq, 1e-30))
    t1 = dr.select(lensq > 0.0, mi.Vector3f(-vh.y * inv_len, vh.x * inv_len, 0.0), mi.Vector3f(1.0, 0.0, 0.0))
    t2 = dr.cross(vh, t1)
    # Uniform disk sample, warped towards the projected hemisphere.
    r = dr.sqrt(u.x)
    sin_phi, cos_phi = dr.sincos(2.0 * dr.pi * u.y)
    p1 = r * cos_phi
    p2 = r * sin_phi
    s = 0.5 * (1.0 + vh.z)
    p2 = dr.lerp(dr.safe_sqrt(1.0 - p1 * p1), p2, s)
    nh = t1 * p1 + t2 * p2 + vh * dr.safe_sqrt(1.0 - p1 * p1 - p2 * p2)
    # Unstretch.
    return dr.normalize(mi.Vector3f(alpha * nh.x, alpha * nh.y, dr.maximum(nh.z, 1e-6)))


def pdf_vndf_reflect(alpha: mi.Float, wi: mi.Vector3f, wo: mi.Vector3f) -> mi.Float:
    """Solid-angle pdf of wo = reflect(wi, m) with m ~ visible normals of wi."""
    h = dr.normalize(wi + wo)
    d_visible = smith_g1(alpha, wi, h) * dr.maximum(dr.dot(wi, h), 0.0) * ggx_d(alpha, h) / wi.z
    pdf = d_visible / (4.0 * dr.maximum(dr.dot(wo, h), 1e-20))
    return dr.select((wi.z > 0.0) & (wo.z > 0.0), pdf, 0.0)


# -- BRDF lobes ------------------------------------------------------------------


def brdf_lobes(
    albedo: mi.Color3f,
    roughness: mi.Float,
    specular: mi.Float,
    metallic: mi.Float,
    wi: mi.Vector3f,
    wo: mi.Vector3f,
) -> tuple[mi.Color3f, mi.Color3f]:
    """(f_d·cosθo, f_s·cosθo) for local directions; zero unless both are above the horizon.

    The returned values include the foreshortening cosθo, as Mitsuba's
    ``BSDF.eval`` does; the UV-space shader multiplies by light intensity only.
    """
    valid = (wi.z > 0.0) & (wo.z > 0.0)
    cos_o = dr.maximum(wo.z, 0.0)
    diffuse = (1.0 - metallic) * albedo * (dr.inv_pi * cos_o)

    alpha = alpha_from_roughness(roughness)
    h = dr.normalize(wi + wo)
    f0 = f0_from_maps(albedo, specular, metallic)
    fres = schlick(f0, f90_from_f0(f0), dr.dot(wi, h))
    d = ggx_d(alpha, h)
    g = smith_g1(alpha, wi, h) * smith_g1(alpha, wo, h)
    # f_s·cosθo = D G F / (4 cosθi)
    glossy = fres * (d * g / (4.0 * dr.maximum(wi.z, 1e-20)))
    zero = mi.Color3f(0.0)
    return dr.select(valid, diffuse, zero), dr.select(valid, glossy, zero)


def specular_sampling_weight(
    albedo: mi.Color3f, specular: mi.Float, metallic: mi.Float, cos_i: mi.Float
) -> mi.Float:
    """Probability of sampling the glossy lobe: its Fresnel-weighted share at wi."""
    f0 = f0_from_maps(albedo, specular, metallic)
    e_s = luminance(schlick(f0, f90_from_f0(f0), cos_i))
    e_d = luminance((1.0 - metallic) * albedo)
    total = e_s + e_d
    return dr.select(total > 0.0, e_s / dr.maximum(total, 1e-20), 0.5)


# -- Geometry: normal mapping, Gram–Schmidt, displacement ------------------------------


def decode_normal(rgb: mi.Color3f | mi.Vector3f) -> mi.Vector3f:
    """Tangent-space normal from a normal-map texel: normalize(2·rgb − 1)."""
    n = mi.Vector3f(rgb[0], rgb[1], rgb[2]) * 2.0 - 1.0
    return dr.normalize(n)


def gram_schmidt(t: mi.Vector3f, n: mi.Vector3f) -> mi.Vector3f:
    """Unit tangent orthogonal to unit normal n: normalize(t − (t·n)n)."""
    return dr.normalize(t - n * dr.dot(t, n))


def frame_from_normal_tangent(n: mi.Vector3f, t: mi.Vector3f) -> mi.Frame3f:
    """Orthonormal frame (T', N × T', N) with T' = Gram–Schmidt(t, n)."""
    s = gram_schmidt(t, n)
    frame = mi.Frame3f(n)
    frame.s = s
    frame.t = dr.cross(n, s)
    return frame


def perturbed_local_frame(n_local: mi.Vector3f) -> mi.Frame3f:
    """Frame around a perturbed normal given in a local frame whose tangent is +x."""
    return frame_from_normal_tangent(n_local, mi.Vector3f(1.0, 0.0, 0.0))


def face_incident_side(n_local: mi.Vector3f, wi: mi.Vector3f) -> mi.Vector3f:
    """Mirror the tangential part of a perturbed normal that faces away from wi.

    Same rule as Mitsuba's ``normalmap``/``bumpmap`` (``flip_invalid_normals``):
    a shading normal must never put the viewer below its horizon.
    """
    flip = wi.z * dr.dot(wi, n_local) <= 0.0
    return dr.select(flip, mi.Vector3f(-n_local.x, -n_local.y, n_local.z), n_local)


def displace(p: mi.Point3f, n_geo: mi.Vector3f, d: mi.Float, s_disp: float = S_DISP_DEFAULT) -> mi.Point3f:
    """Point moved along the geometric normal: p + s_disp · d · n (seed 003 appendix)."""
    return p + n_geo * (s_disp * d)


def bumped_local_normal(
    dp_du_local: mi.Vector3f, dp_dv_local: mi.Vector3f, grad_uv: mi.Vector2f
) -> mi.Vector3f:
    """Shading normal of the displaced surface p + h(u, v)·n, in the local frame.

    ``grad_uv`` = s_disp·(∂d/∂u, ∂d/∂v). The displaced tangents are
    dp/du + (∂h/∂u)·n (their normal components replaced), and the new normal is
    their cross product. Degenerate tangents (no UV parameterisation) leave the
    normal unchanged.
    """
    du = mi.Vector3f(dp_du_local.x, dp_du_local.y, grad_uv.x)
    dv = mi.Vector3f(dp_dv_local.x, dp_dv_local.y, grad_uv.y)
    c = dr.cross(du, dv)
    norm2 = dr.squared_norm(c)
    n = c * dr.rsqrt(dr.maximum(norm2, 1e-30))
    n = dr.select(n.z < 0.0, -n, n)
    return dr.select(norm2 > 1e-20, n, mi.Vector3f(0.0, 0.0, 1.0))


def perturbation(n_local: mi.Vector3f | None, wi: mi.Vector3f) -> tuple[mi.Frame3f | None, mi.Vector3f, mi.Bool]:
    """Frame of a perturbed shading normal (local coords), wi in it, and wi's validity.

    ``n_local`` is first mirrored to face wi (:func:`face_incident_side`);
    ``None`` means "unperturbed" and skips the work. Valid means wi is above
    both the unperturbed and the perturbed horizon.
    """
    if n_local is None:
        return None, wi, wi.z > 0.0
    frame = perturbed_local_frame(face_incident_side(n_local, wi))
    wi_p = frame.to_local(wi)
    return frame, wi_p, (wi.z > 0.0) & (wi_p.z > 0.0)


def to_perturbed(frame: mi.Frame3f | None, wo: mi.Vector3f) -> tuple[mi.Vector3f, mi.Bool]:
    """wo in a perturbed frame and its validity (above both horizons, as Mitsuba's normalmap)."""
    if frame is None:
        return wo, wo.z > 0.0
    wo_p = frame.to_local(wo)
    return wo_p, (wo.z > 0.0) & (wo_p.z > 0.0)


# -- directional albedo of the glossy lobe (environment light) ----------------------------------

_ALBEDO_TABLE: dict[int, tuple] = {}


def directional_albedo_table(n: int = 32, samples: int = 1024) -> tuple[mi.Float, mi.Float]:
    """(A, B) on an n×n grid over (roughness j/(n−1), cosθi i/(n−1)): ∫ f_s cosθo dωo = F0·A + F90·B.

    Schlick's F is linear in F0 and F90, so the lobe's white-furnace albedo splits into these two tables
    (the "split sum" of prefiltered environment lighting). Estimated with the VNDF samples of
    :func:`sample_vndf` (weight F·G1(wo) for the separable Smith G) on a fixed stratified sequence: deterministic.
    Flat arrays of n² entries, index j·n + i.
    """
    key = (n, samples)
    if key in _ALBEDO_TABLE:
        return _ALBEDO_TABLE[key]
    import numpy as np

    k = int(np.sqrt(samples))
    g = (np.arange(k) + 0.5) / k
    su, sv = [a.ravel() for a in np.meshgrid(g, g, indexing="ij")]
    grid = np.arange(n) / (n - 1)
    rj, ci, s = np.meshgrid(grid, grid, np.arange(k * k), indexing="ij")
    rough = mi.Float(rj.ravel().astype(np.float32))
    cos_i = mi.Float(np.maximum(ci.ravel(), 1e-3).astype(np.float32))
    u = mi.Point2f(mi.Float(su[s.ravel()].astype(np.float32)), mi.Float(sv[s.ravel()].astype(np.float32)))
    wi = mi.Vector3f(dr.safe_sqrt(1.0 - cos_i * cos_i), 0.0, cos_i)
    alpha = alpha_from_roughness(rough)
    m = sample_vndf(alpha, wi, u)
    wo = 2.0 * dr.dot(wi, m) * m - wi
    g1 = dr.select(wo.z > 0.0, smith_g1(alpha, wo, m), 0.0)
    t = dr.clip(1.0 - dr.dot(wi, m), 0.0, 1.0)
    t5 = (t * t) * (t * t) * t
    a = np.array(g1 * (1.0 - t5)).reshape(n * n, k * k).mean(1)
    b = np.array(g1 * t5).reshape(n * n, k * k).mean(1)
    _ALBEDO_TABLE[key] = (mi.Float(a.astype(np.float32)), mi.Float(b.astype(np.float32)))
    return _ALBEDO_TABLE[key]


def directional_albedo(f0: mi.Color3f, f90: mi.Float, roughness: mi.Float, cos_i: mi.Float,
                       n: int = 32) -> mi.Color3f:
    """∫ f_s cosθo dωo for view cosine ``cos_i``: F0·A + F90·B, bilinear in the tables (differentiable)."""
    a_tab, b_tab = directional_albedo_table(n)
    # a NaN cosine (a texel no view sees) must not become a table index: UInt32(NaN) reads out of bounds (a segfault
    # of the LLVM backend on AVX2 machines); NaN > 0 is false, so it reads row 0
    x = dr.clip(cos_i, 0.0, 1.0) * (n - 1)
    y = dr.clip(roughness, 0.0, 1.0) * (n - 1)
    x, y = dr.select(x > 0.0, x, 0.0), dr.select(y > 0.0, y, 0.0)
    i0 = mi.UInt32(dr.minimum(dr.floor(x), n - 2))
    j0 = mi.UInt32(dr.minimum(dr.floor(y), n - 2))
    fx, fy = x - mi.Float(i0), y - mi.Float(j0)

    def lookup(tab):
        at = lambda j, i: dr.gather(mi.Float, tab, j * n + i)  # noqa: E731
        return dr.lerp(dr.lerp(at(j0, i0), at(j0, i0 + 1), fx), dr.lerp(at(j0 + 1, i0), at(j0 + 1, i0 + 1), fx), fy)

    return f0 * lookup(a_tab) + f90 * lookup(b_tab)
