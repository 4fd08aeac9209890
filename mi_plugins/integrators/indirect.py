"""``indirect``: Mitsuba's path tracer, keeping only the light of paths of ``min_depth`` segments or more.

.. list-table::
   :header-rows: 1

   * - Parameter
     - Type
     - Meaning
     - Default
     - Differentiable
   * - max_depth
     - int
     - longest path kept, in segments (-1 = infinite), as Mitsuba's ``path``
     - -1
     - no
   * - min_depth
     - int
     - shortest path kept; 3 = everything a direct-lighting render (``path`` at ``max_depth`` 2) misses;
       1 = the whole of ``path``
     - 3
     - no
   * - rr_depth
     - int
     - depth from which Russian roulette starts, as ``path``
     - 5
     - no

Why: the indirect light of a scene is ``path`` minus ``path`` at ``max_depth`` 2. Rendered with one seed, the two
draw the same random numbers for the same first bounce, so the first bounce cancels sample for sample — but that
costs two renders, the second one repeating the first's first bounce. This integrator draws the random numbers in
``path``'s order (emitter sample, BSDF sample, Russian roulette, at every vertex: ``src/integrators/path.cpp``) and
adds a contribution only where its path is long enough, so one render equals the difference of the two to rounding
(tested: ``tests/plugins/test_indirect.py``, against ``path`` at ``min_depth`` 1 and against the difference at 3).

A path of ``k`` segments is a camera ray, ``k − 2`` bounces and a last segment to a light: the emission a path finds
after ``d`` bounces is a ``d + 1``-segment path, the emitter sample taken at its ``d``-th bounce (``d`` ≥ 1) a
``d + 1``-segment one as well (``path``'s own convention: ``max_depth`` 2 is direct light).

Primal rendering only (no gradients: the morph's light estimate is a constant added to its renders).

XML::

    <integrator type="indirect">
        <integer name="max_depth" value="4"/>
    </integrator>
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi


def _mis(a: mi.Float, b: mi.Float) -> mi.Float:
    """Power heuristic (β = 2), as ``path``'s ``mis_weight``: 0 where undefined."""
    a2, b2 = a * a, b * b
    w = a2 / (a2 + b2)
    return dr.detach(dr.select(dr.isfinite(w), w, 0.0))


class IndirectIntegrator(mi.SamplingIntegrator):
    def __init__(self, props: mi.Properties) -> None:
        super().__init__(props)
        max_depth = props.get("max_depth", -1)
        if max_depth < -1:
            raise ValueError(f"indirect: max_depth must be -1 (infinite) or ≥ 0, got {max_depth}")
        self.max_depth = 0xFFFFFFFF if max_depth == -1 else int(max_depth)
        self.min_depth = int(props.get("min_depth", 3))
        if self.min_depth < 1:
            raise ValueError(f"indirect: min_depth must be ≥ 1, got {self.min_depth}")
        self.rr_depth = int(props.get("rr_depth", 5))
        if self.rr_depth <= 0:
            raise ValueError(f"indirect: rr_depth must be > 0, got {self.rr_depth}")

    @dr.syntax
    def sample(self, scene, sampler, ray, medium=None, active=True):
        ctx = mi.BSDFContext()
        ray = mi.Ray3f(ray)
        active = mi.Bool(active) & (self.max_depth > 0)
        throughput = mi.Spectrum(1.0)
        result = mi.Spectrum(0.0)
        eta = mi.Float(1.0)
        depth = mi.UInt32(0)
        valid_ray = mi.Bool(scene.environment() is not None)  # path's hide_emitters false
        prev_si = dr.zeros(mi.Interaction3f)
        prev_bsdf_pdf = mi.Float(1.0)
        prev_bsdf_delta = mi.Bool(True)

        while active:
            si = scene.ray_intersect(ray, active)

            # Emission found after `depth` bounces: a (depth + 1)-segment path
            ds = mi.DirectionSample3f(scene, si=si, ref=prev_si)
            em_pdf = scene.pdf_emitter_direction(prev_si, ds, ~prev_bsdf_delta)
            em_pdf = dr.select(prev_bsdf_delta, 0.0, em_pdf)
            mis_bsdf = _mis(prev_bsdf_pdf, em_pdf)
            keep = active & (depth + 1 >= self.min_depth)
            result[keep] = dr.fma(throughput, ds.emitter.eval(si, prev_bsdf_pdf > 0.0) * mis_bsdf, result)

            active_next = (depth + 1 < self.max_depth) & si.is_valid()
            bsdf = si.bsdf(ray)

            # Emitter sampling at this vertex: a (depth + 2)-segment path
            active_em = active_next & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
            ds, em_weight = scene.sample_emitter_direction(si, sampler.next_2d(), True, active_em)
            active_em &= ds.pdf != 0.0
            wo = si.to_local(ds.d)

            sample_1 = sampler.next_1d()
            sample_2 = sampler.next_2d()
            bsdf_val, bsdf_pdf, bsdf_sample, bsdf_weight = bsdf.eval_pdf_sample(ctx, si, wo, sample_1, sample_2)

            bsdf_val = si.to_world_mueller(bsdf_val, -wo, si.wi)
            mis_em = dr.select(ds.delta, 1.0, _mis(ds.pdf, bsdf_pdf))
            keep_em = active_em & (depth + 2 >= self.min_depth)
            result[keep_em] = dr.fma(throughput, bsdf_val * em_weight * mis_em, result)

            # BSDF sampling: the next segment
            bsdf_weight = si.to_world_mueller(bsdf_weight, -bsdf_sample.wo, si.wi)
            ray = si.spawn_ray(si.to_world(bsdf_sample.wo))
            throughput *= bsdf_weight
            eta *= bsdf_sample.eta
            valid_ray |= active & si.is_valid() & ~mi.has_flag(bsdf_sample.sampled_type, mi.BSDFFlags.Null)
            prev_si = mi.Interaction3f(si)
            prev_bsdf_pdf = mi.Float(bsdf_sample.pdf)
            prev_bsdf_delta = mi.has_flag(bsdf_sample.sampled_type, mi.BSDFFlags.Delta)

            depth[si.is_valid()] += 1
            throughput_max = dr.max(mi.unpolarized_spectrum(throughput))
            rr_prob = dr.minimum(throughput_max * dr.square(eta), 0.95)
            rr_active = depth >= self.rr_depth
            rr_continue = sampler.next_1d() < rr_prob
            throughput[rr_active] *= dr.rcp(rr_prob)
            active = active_next & (~rr_active | rr_continue) & (throughput_max != 0.0)

        return dr.select(valid_ray, result, 0.0), valid_ray, []

    def aov_names(self):
        return []

    def to_string(self):
        return f"IndirectIntegrator[min_depth={self.min_depth}, max_depth={self.max_depth}, rr_depth={self.rr_depth}]"


def register() -> None:
    mi.register_integrator("indirect", lambda props: IndirectIntegrator(props))
