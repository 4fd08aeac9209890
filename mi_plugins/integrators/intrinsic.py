"""``intrinsic``: path tracer that splits the image into intrinsic G-buffers (seed 000, eqs. 2–4).

.. list-table::
   :header-rows: 1

   * - Parameter
     - Type
     - Meaning
     - Default
     - Differentiable
   * - max_depth
     - int
     - longest path (-1 = infinite); 2 = direct lighting only
     - 6
     - no
   * - rr_depth
     - int
     - depth from which Russian roulette starts
     - 5
     - no

The first surface a camera ray hits decides where a path's light goes. Each
path is traced once (next-event estimation + BSDF sampling with MIS, like
Mitsuba's ``path``) and its contributions are *binned*:

* **D, diffuse radiance** — light whose first bounce went through the BSDF's
  ``Diffuse`` components (``BSDFContext.type_mask``): the emitter-sampling
  estimate is evaluated with only those components enabled, and BSDF-sampled
  continuations whose sampled lobe is diffuse carry all later light into D.
* **S, specular shading** — the same for every non-diffuse component (glossy,
  delta), *plus* directly visible emission (environment, area lights), so that
  nothing is lost.
* **A, albedo** — ``BSDF.eval_diffuse_reflectance`` at the first hit.
* **I, irradiance** — D / A per pixel, computed after pixel filtering by
  :func:`photoreal`'s writer (:func:`split_intrinsics`) so that the
  recomposition **R = A·I + S** (seed 000, eq. 4) equals the full render
  D + S exactly where A > 0. For a Lambertian surface I = E/π, the radiance a
  white diffuser would reflect under the incident irradiance E.

The main (RGB) output is the full render D + S. Extra AOVs: ``albedo``,
``diffuse``, ``specular``, ``normal`` (world shading normal), ``depth``
(distance along the camera ray), ``uv``, ``position``.

What A, I and S mean for builtin BSDFs: ``diffuse`` — A = reflectance,
S = 0 (except visible emitters). ``principled`` — A = base_color·(1 −
metallic)·(1 − spec_trans) (its ``eval_diffuse_reflectance``); D holds its
diffuse lobe (with retro-reflection and sheen, which are flagged diffuse), S
its specular, clearcoat and transmission lobes; so I = D/A carries the
principled diffuse lobe's deviations from Lambert. ``ggx_uv`` — A = albedo·(1
− metallic), D its Lambert lobe, S its GGX lobe.

Primal rendering only: this is a G-buffer integrator; differentiate with
``prb`` / ``direct_projective`` instead.

XML::

    <integrator type="intrinsic">
        <integer name="max_depth" value="6"/>
    </integrator>
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

AOV_GROUPS: dict[str, tuple[str, ...]] = {
    "albedo": ("R", "G", "B"),
    "diffuse": ("R", "G", "B"),
    "specular": ("R", "G", "B"),
    "normal": ("X", "Y", "Z"),
    "depth": ("T",),
    "uv": ("U", "V"),
    "position": ("X", "Y", "Z"),
}


def _mis(a: mi.Float, b: mi.Float) -> mi.Float:
    """Power heuristic (β = 2), safe for a = b = 0 and infinite a."""
    a2, b2 = a * a, b * b
    w = a2 / (a2 + b2)
    return dr.select(dr.isfinite(w), w, 0.0)


class IntrinsicIntegrator(mi.ad.integrators.common.ADIntegrator):
    def __init__(self, props: mi.Properties) -> None:
        super().__init__(props)

    def aov_names(self):
        return [f"{g}.{c}" for g, chans in AOV_GROUPS.items() for c in chans]

    @dr.syntax
    def sample(self, mode, scene, sampler, ray, δL=None, state_in=None, active=True, **kwargs):
        if mode != dr.ADMode.Primal:
            raise NotImplementedError(
                "intrinsic: primal rendering only (use 'prb' or a projective integrator for gradients)"
            )
        ctx = mi.BSDFContext()
        ctx_d = mi.BSDFContext()
        ctx_d.type_mask = +mi.BSDFFlags.Diffuse
        ctx_s = mi.BSDFContext()
        ctx_s.type_mask = +mi.BSDFFlags.All & ~(+mi.BSDFFlags.Diffuse)

        ray = mi.Ray3f(ray)
        active = mi.Bool(active)

        # -- First hit: G-buffers and the bin-splitting bounce ------------------------
        si = scene.ray_intersect(ray, active)
        valid = si.is_valid()
        bsdf = si.bsdf(ray)
        albedo = dr.select(valid, bsdf.eval_diffuse_reflectance(si, valid), 0.0)
        normal = dr.select(valid, si.sh_frame.n, 0.0)
        depth_t = dr.select(valid, si.t, 0.0)
        uv = dr.select(valid, si.uv, 0.0)
        position = dr.select(valid, si.p, 0.0)

        # Directly visible emission (and the environment) goes to S.
        L_s = mi.Color3f(si.emitter(scene).eval(si, active))
        L_d = mi.Color3f(0.0)

        act = valid & (self.max_depth > 1)
        # Emitter sampling, evaluated lobe by lobe; MIS uses the full pdf.
        act_em = act & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
        ds, em_w = scene.sample_emitter_direction(si, sampler.next_2d(), True, act_em)
        act_em &= ds.pdf != 0.0
        wo = si.to_local(ds.d)
        pdf_full = bsdf.pdf(ctx, si, wo, act_em)
        mis_em = dr.select(ds.delta, 1.0, _mis(ds.pdf, pdf_full))
        L_d += dr.select(act_em, mis_em * bsdf.eval(ctx_d, si, wo, act_em) * em_w, 0.0)
        L_s += dr.select(act_em, mis_em * bsdf.eval(ctx_s, si, wo, act_em) * em_w, 0.0)

        # BSDF sampling picks the bin for everything that follows.
        bs, bsdf_w = bsdf.sample(ctx, si, sampler.next_1d(), sampler.next_2d(), act)
        to_diffuse = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Diffuse)
        beta = mi.Color3f(bsdf_w)
        eta = mi.Float(bs.eta)
        prev_si = dr.detach(si, True)
        prev_pdf = mi.Float(bs.pdf)
        prev_delta = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
        ray = si.spawn_ray(si.to_world(bs.wo))
        depth = mi.UInt32(1)
        act &= dr.max(beta) != 0.0
        L_rest = mi.Color3f(0.0)

        # -- Remaining bounces: a standard MIS path tracer into one accumulator -----------
        while act:
            si = scene.ray_intersect(ray, act)
            ds = mi.DirectionSample3f(scene, si=si, ref=prev_si)
            mis = _mis(prev_pdf, scene.pdf_emitter_direction(prev_si, ds, ~prev_delta))
            L_rest += dr.select(act, beta * mis * ds.emitter.eval(si, act), 0.0)

            act_next = act & si.is_valid() & (depth + 1 < self.max_depth)
            bsdf = si.bsdf(ray)
            act_em = act_next & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
            ds, em_w = scene.sample_emitter_direction(si, sampler.next_2d(), True, act_em)
            act_em &= ds.pdf != 0.0
            wo = si.to_local(ds.d)
            val_em, pdf_em = bsdf.eval_pdf(ctx, si, wo, act_em)
            mis_em = dr.select(ds.delta, 1.0, _mis(ds.pdf, pdf_em))
            L_rest += dr.select(act_em, beta * mis_em * val_em * em_w, 0.0)

            bs, bsdf_w = bsdf.sample(ctx, si, sampler.next_1d(), sampler.next_2d(), act_next)
            beta *= bsdf_w
            eta *= bs.eta
            prev_si = dr.detach(si, True)
            prev_pdf = bs.pdf
            prev_delta = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
            ray = si.spawn_ray(si.to_world(bs.wo))

            beta_max = dr.max(beta)
            act_next &= beta_max != 0.0
            rr_prob = dr.minimum(beta_max * eta * eta, 0.95)
            rr_active = depth >= self.rr_depth
            beta[rr_active] *= dr.rcp(rr_prob)
            act_next &= ~rr_active | (sampler.next_1d() < rr_prob)
            depth += 1
            act = act_next

        L_d += dr.select(to_diffuse, L_rest, 0.0)
        L_s += dr.select(to_diffuse, 0.0, L_rest)

        aovs = []
        for vec in (albedo, L_d, L_s, normal):
            aovs += [vec[0], vec[1], vec[2]]
        aovs += [depth_t, uv[0], uv[1], position[0], position[1], position[2]]
        return L_d + L_s, valid, aovs, None

    def to_string(self):
        return f"IntrinsicIntegrator[max_depth={self.max_depth}, rr_depth={self.rr_depth}]"


def register() -> None:
    mi.register_integrator("intrinsic", lambda props: IntrinsicIntegrator(props))
