"""``ggx_uv``: Lambert + GGX BSDF driven by UV-space material maps (seed 003).

.. list-table::
   :header-rows: 1

   * - Parameter
     - Type
     - Meaning
     - Default
     - Differentiable
   * - albedo
     - spectrum or texture
     - diffuse albedo T_alb (linear RGB, bitmap textures are sRGB-decoded by Mitsuba)
     - 0.5
     - yes
   * - normal
     - texture (``raw="true"`` bitmap or rgb)
     - tangent-space normal map, ``n = normalize(2·rgb − 1)``; absent = no perturbation
     - none
     - yes (discontinuous)
   * - roughness
     - float or texture
     - perceptual roughness, GGX α = roughness², in [0, 1]
     - 0.5
     - yes
   * - specular
     - float or texture
     - dielectric specular level, F0 = 0.08 · specular, in [0, 1]
     - 0.5
     - yes
   * - metallic
     - float or texture
     - blends F0 towards albedo and removes the diffuse lobe, in [0, 1]
     - 0.0
     - yes
   * - displacement
     - float or texture
     - height along the geometric normal, scaled by ``s_disp``; shades as the
       displaced surface's normal (bump mapping); absent/constant = none
     - none
     - yes (discontinuous)
   * - s_disp
     - float
     - displacement scale (seed 003 appendix)
     - 0.01
     - no

Components (select through ``mi.BSDFContext``, by index or type mask):
0 = ``DiffuseReflection`` (Lambert), 1 = ``GlossyReflection`` (GGX).
The maths lives in :mod:`mi_plugins.shading`, shared with the UV-space shader.
``eval`` returns f·cosθo (Mitsuba's convention); ``sample`` draws from a
mixture of cosine-hemisphere and visible-normal GGX sampling, weighted by the
lobes' Fresnel-weighted albedos at wi. Reflection only, front side only: wrap
in ``twosided`` for open scans.

XML::

    <bsdf type="ggx_uv">
        <texture type="bitmap" name="albedo" filename="albedo.png"/>
        <texture type="bitmap" name="normal" filename="normal.png" raw="true"/>
        <float name="roughness" value="0.4"/>
        <float name="specular" value="0.5"/>
    </bsdf>
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from .. import shading as sh

_FLOAT_PARAMS = {
    # name: (default, lower, upper)
    "roughness": (0.5, 0.0, 1.0),
    "specular": (0.5, 0.0, 1.0),
    "metallic": (0.0, 0.0, 1.0),
}


def _check_range(name: str, props: mi.Properties, lo: float, hi: float) -> None:
    """Reject an out-of-range *constant* parameter with a message naming it."""
    if name not in props:
        return
    try:
        value = float(props.get(name))
    except (TypeError, ValueError):
        return  # a texture; its texels are the user's business
    if not (lo <= value <= hi):
        raise ValueError(f"ggx_uv: parameter '{name}' = {value} is outside [{lo}, {hi}]")


class GGXUV(mi.BSDF):
    def __init__(self, props: mi.Properties) -> None:
        mi.BSDF.__init__(self, props)
        for name, (_, lo, hi) in _FLOAT_PARAMS.items():
            _check_range(name, props, lo, hi)
        self.s_disp = float(props.get("s_disp", sh.S_DISP_DEFAULT))
        if not dr.isfinite(self.s_disp):
            raise ValueError(f"ggx_uv: parameter 's_disp' = {self.s_disp} is not finite")

        self.albedo = props.get_texture("albedo", 0.5)
        self.roughness = props.get_texture("roughness", _FLOAT_PARAMS["roughness"][0])
        self.specular = props.get_texture("specular", _FLOAT_PARAMS["specular"][0])
        self.metallic = props.get_texture("metallic", _FLOAT_PARAMS["metallic"][0])
        self.normal = props.get_texture("normal") if "normal" in props else None
        self.displacement = (
            props.get_unbounded_texture("displacement") if "displacement" in props else None
        )

        diffuse = mi.BSDFFlags.DiffuseReflection | mi.BSDFFlags.FrontSide
        glossy = mi.BSDFFlags.GlossyReflection | mi.BSDFFlags.FrontSide
        textures = (self.albedo, self.roughness, self.specular, self.metallic, self.normal)
        if any(t is not None and t.is_spatially_varying() for t in textures) or self._bumped():
            diffuse |= mi.BSDFFlags.SpatiallyVarying
            glossy |= mi.BSDFFlags.SpatiallyVarying
        self.m_components = [int(diffuse), int(glossy)]
        self.m_flags = int(diffuse | glossy)

    # -- Shading frame: displacement (bump) then tangent-space normal map ----------

    def _bumped(self) -> bool:
        # Constant displacement moves the surface rigidly: no shading change.
        return self.displacement is not None and self.displacement.is_spatially_varying()

    def _perturbed_normal(self, si: mi.SurfaceInteraction3f, active: mi.Bool) -> mi.Vector3f | None:
        """Perturbed normal in si's local shading frame, or None when unperturbed."""
        if self.normal is None and not self._bumped():
            return None
        if self._bumped():
            grad = self.displacement.eval_1_grad(si, active) * self.s_disp
            n_base = sh.bumped_local_normal(si.to_local(si.dp_du), si.to_local(si.dp_dv), grad)
        else:
            n_base = mi.Vector3f(0.0, 0.0, 1.0)
        if self.normal is None:
            return n_base
        # Tangent-space normal relative to the (bumped) frame, T re-orthogonalised.
        n_ts = sh.decode_normal(self.normal.eval(si, active))
        return sh.perturbed_local_frame(n_base).to_world(n_ts)

    def _local(self, si: mi.SurfaceInteraction3f, active: mi.Bool):
        """(frame or None, wi in the perturbed frame, validity of wi)."""
        frame, wi_p, valid = sh.perturbation(self._perturbed_normal(si, active), si.wi)
        return frame, wi_p, active & valid

    def _maps(self, si: mi.SurfaceInteraction3f, active: mi.Bool):
        return (
            self.albedo.eval(si, active),
            self.roughness.eval_1(si, active),
            self.specular.eval_1(si, active),
            self.metallic.eval_1(si, active),
        )

    def _lobe_switches(self, ctx: mi.BSDFContext) -> tuple[bool, bool]:
        return (
            ctx.is_enabled(mi.BSDFFlags.DiffuseReflection, 0),
            ctx.is_enabled(mi.BSDFFlags.GlossyReflection, 1),
        )

    def _eval_pdf_local(self, ctx, maps, wi_p, wo_p, valid):
        """f·cos and pdf for directions in the perturbed frame."""
        albedo, rough, spec, metal = maps
        has_d, has_s = self._lobe_switches(ctx)
        f_d, f_s = sh.brdf_lobes(albedo, rough, spec, metal, wi_p, wo_p)
        value = mi.Color3f(0.0)
        if has_d:
            value += f_d
        if has_s:
            value += f_s
        p_s = self._p_spec(maps, wi_p, has_d, has_s)
        pdf_s = sh.pdf_vndf_reflect(sh.alpha_from_roughness(rough), wi_p, wo_p)
        pdf_d = dr.maximum(wo_p.z, 0.0) * dr.inv_pi
        pdf = dr.lerp(pdf_d, pdf_s, p_s)
        return dr.select(valid, value, 0.0), dr.select(valid, pdf, 0.0)

    @staticmethod
    def _p_spec(maps, wi_p, has_d: bool, has_s: bool):
        if has_d and has_s:
            albedo, _, spec, metal = maps
            return sh.specular_sampling_weight(albedo, spec, metal, wi_p.z)
        return mi.Float(1.0 if has_s else 0.0)

    # -- BSDF interface ------------------------------------------------------------

    def eval_pdf(self, ctx, si, wo, active=True):
        has_d, has_s = self._lobe_switches(ctx)
        if not (has_d or has_s):
            return mi.Color3f(0.0), mi.Float(0.0)
        frame, wi_p, valid = self._local(si, active)
        wo_p, valid_o = sh.to_perturbed(frame, wo)
        return self._eval_pdf_local(ctx, self._maps(si, active), wi_p, wo_p, valid & valid_o)

    def eval(self, ctx, si, wo, active=True):
        return self.eval_pdf(ctx, si, wo, active)[0]

    def pdf(self, ctx, si, wo, active=True):
        return self.eval_pdf(ctx, si, wo, active)[1]

    def sample(self, ctx, si, sample1, sample2, active=True):
        bs = dr.zeros(mi.BSDFSample3f)
        has_d, has_s = self._lobe_switches(ctx)
        if not (has_d or has_s):
            return bs, mi.Color3f(0.0)
        frame, wi_p, valid = self._local(si, active)
        maps = self._maps(si, active)
        p_s = self._p_spec(maps, wi_p, has_d, has_s)
        pick_s = sample1 < p_s

        m = sh.sample_vndf(sh.alpha_from_roughness(maps[1]), wi_p, sample2)
        wo_s = mi.reflect(wi_p, m)
        wo_d = mi.warp.square_to_cosine_hemisphere(sample2)
        wo_p = dr.select(pick_s, wo_s, wo_d)
        wo = wo_p if frame is None else frame.to_world(wo_p)
        valid &= (wo.z > 0.0) & (wo_p.z > 0.0)

        value, pdf = self._eval_pdf_local(ctx, maps, wi_p, wo_p, valid)
        valid &= pdf > 0.0
        bs.wo = wo
        bs.pdf = dr.select(valid, pdf, 0.0)
        bs.eta = 1.0
        bs.sampled_type = dr.select(
            pick_s, mi.UInt32(+mi.BSDFFlags.GlossyReflection), mi.UInt32(+mi.BSDFFlags.DiffuseReflection)
        )
        bs.sampled_component = dr.select(pick_s, mi.UInt32(1), mi.UInt32(0))
        weight = dr.select(valid, value / dr.maximum(pdf, 1e-20), 0.0)
        return bs, weight

    def eval_diffuse_reflectance(self, si, active=True):
        return self.albedo.eval(si, active) * (1.0 - self.metallic.eval_1(si, active))

    def traverse(self, callback):
        flags = mi.ParamFlags.Differentiable
        callback.put("albedo", self.albedo, flags)
        callback.put("roughness", self.roughness, flags)
        callback.put("specular", self.specular, flags)
        callback.put("metallic", self.metallic, flags)
        if self.normal is not None:
            callback.put("normal", self.normal, flags | mi.ParamFlags.Discontinuous)
        if self.displacement is not None:
            callback.put("displacement", self.displacement, flags | mi.ParamFlags.Discontinuous)

    def parameters_changed(self, keys=[]):
        pass  # textures own their state; nothing derived is cached here

    def to_string(self):
        return (
            f"GGXUV[albedo={self.albedo}, roughness={self.roughness}, specular={self.specular}, "
            f"metallic={self.metallic}, normal={self.normal}, displacement={self.displacement}, "
            f"s_disp={self.s_disp}]"
        )


def register() -> None:
    mi.register_bsdf("ggx_uv", lambda props: GGXUV(props))
