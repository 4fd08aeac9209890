"""``neural_btf``: a universal neural BTF (seed 002 §3.1) as a Mitsuba BSDF.

.. list-table::
   :header-rows: 1

   * - Parameter
     - Type
     - Meaning
     - Default
     - Differentiable
   * - basis
     - string
     - ``.npz`` with the universal MLPs M_off, M_rgb (``photoreal btf train-basis``);
       resolved like every Mitsuba file path (relative to the scene)
     - required
     - no
   * - material
     - string
     - ``.npz`` with the material's feature textures T_off, T_rgb (``photoreal btf fit``)
     - required
     - —
   * - t_off, t_rgb
     - tensor (scene parameters)
     - the feature textures [R, R, C], exposed by ``traverse``
     - from ``material``
     - yes
   * - tiling
     - float
     - texture repeats per unit of the mesh's UV (the material tile spans 1/tiling)
     - 1.0
     - no
   * - gain
     - float
     - multiplies the BTF value (exposure of a captured material)
     - 1.0
     - no
   * - network
     - string
     - how the MLPs run on LLVM: ``constants`` (weights written into the kernel, one speed in
       both Dr.Jit modes, a compile that grows with the weights), ``coop`` (cooperative
       vectors: quick to compile, fast in evaluated mode only) or ``auto`` (``constants`` up to
       4096 weights per MLP, a basis of width ≤ 32; above, ``constants`` in symbolic mode and
       ``coop`` in evaluated mode). CUDA always uses ``coop``
     - auto
     - no

Cosine convention: the network is trained on f(u, ω_i, ω_o)·cosθ_i — radiance towards ω_o under a
distant light of unit perpendicular irradiance from ω_i (``inverse/btf/data.py``). Mitsuba's
``eval(ctx, si, wo)`` returns f·cosθ_wo with ``si.wi`` pointing to the viewer and ``wo`` to the
light, so ``eval`` is exactly the network with ω_o = ``si.wi`` and ω_i = ``wo``, clamped at 0;
no cosine is added or removed. Like measured BTFs, the value is not reciprocal: paths must be
traced from the camera (``path``, ``prb``; not light tracing).

Sampling is cosine-weighted on the upper hemisphere, ``pdf`` = cosθ/π, reflection only, front side
only. Gradients flow into ``t_off`` and ``t_rgb`` (fit a material through full renders); the MLP
weights are constants of the kernel. On LLVM a narrow basis (``network`` = ``auto``, ≤ 4096 weights
per MLP) is written into it one fused multiply-add per weight
(:class:`~mi_plugins.neural_basis.ConstantNet`): inside the symbolic megakernel of a plain
``mi.render``, cooperative vectors read inside a BSDF call ran ~9× slower than in a kernel of their
own, constants run at one speed in both modes. A wider basis (the bundled one, width 64) is written
as constants into symbolic kernels only: in evaluated mode (below) cooperative vectors run as fast
and compile in a second where its constants take tens of seconds on an empty kernel cache. Under ``cuda_ad_*`` variants the MLPs are cooperative
vectors in float16 (Dr.Jit packs CUDA/OptiX cooperative vectors for half precision only): values
within 1 % (+0.5 % of the largest) of the float32 training path, texture gradients within 5 % of
central differences (tests, H100).

Speed: ``photoreal bench plugins`` times it against ``principled`` on one scene in both Dr.Jit modes
(symbolic, what ``mi.render`` runs, and evaluated: ``with neural_btf.evaluated_mode(): mi.render(...)``);
the cost grows with the basis width (``photoreal bench btf`` charts width against PSNR). The first
render of a scene compiles the network into the kernel (seconds at width 64; kept in Dr.Jit's cache).

XML::

    <bsdf type="neural_btf">
        <string name="basis" value="basis.npz"/>
        <string name="material" value="leather.npz"/>
        <float name="tiling" value="4"/>
    </bsdf>
"""

from __future__ import annotations

import contextlib

import drjit as dr
import mitsuba as mi
import numpy as np

from .. import neural_basis as nb
from ..arrays import aligned


def _resolve(props: mi.Properties, name: str) -> str:
    if name not in props:
        raise ValueError(f"neural_btf: parameter '{name}' (a .npz file) is required")
    path = str(props.get(name))
    return str(mi.file_resolver().resolve(path))


class NeuralBTF(mi.BSDF):
    def __init__(self, props: mi.Properties) -> None:
        mi.BSDF.__init__(self, props)
        basis_path, mat_path = _resolve(props, "basis"), _resolve(props, "material")
        basis = nb.load_basis(basis_path)
        mat = nb.load_material(mat_path, basis.config.channels)
        nb.check_pair(basis, mat, basis_path, mat_path)
        self.tiling = float(props.get("tiling", 1.0))
        self.gain = float(props.get("gain", 1.0))
        for name, v in (("tiling", self.tiling), ("gain", self.gain)):
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"neural_btf: parameter '{name}' = {v} must be a positive number")
        self.cfg = basis.config
        self.res = mat.res
        self.t_off = mi.TensorXf(aligned(mat.t_off))
        self.t_rgb = mi.TensorXf(aligned(mat.t_rgb))
        # constants in the kernel or cooperative vectors (render_net); both backpropagate into the textures
        form = str(props.get("network", "auto"))
        if form not in nb.NET_FORMS:
            raise ValueError(f"neural_btf: parameter 'network' = {form!r} must be one of {', '.join(nb.NET_FORMS)}")
        self.m_off = nb.render_net(basis.m_off, form)
        self.m_rgb = nb.render_net(basis.m_rgb, form)
        flags = mi.BSDFFlags.GlossyReflection | mi.BSDFFlags.FrontSide | mi.BSDFFlags.SpatiallyVarying
        self.m_components = [int(flags)]
        self.m_flags = int(flags)
        self.files = (props.get("basis"), props.get("material"))

    # -- eqs. 2–3 in cooperative-vector form ----------------------------------------------------

    def network(self, uv: mi.Point2f, wi_light: mi.Vector3f, wo_view: mi.Vector3f) -> mi.Color3f:
        """The BTF value f·cosθ_i at texture coordinate ``uv`` (tangent-space directions)."""
        u, v = uv.x * self.tiling, uv.y * self.tiling
        c, r = self.cfg.channels, self.res
        f_off = nb.bilinear(self.t_off.array, r, c, u, v)
        d = self.m_off(f_off + [wo_view.x, wo_view.y, wo_view.z])               # eq. 2
        du, dv = self.cfg.offset_range * dr.tanh(d[0]), self.cfg.offset_range * dr.tanh(d[1])
        f_rgb = nb.bilinear(self.t_rgb.array, r, c, u + du, v + dv)
        rgb = self.m_rgb(f_rgb + [wi_light.x, wi_light.y, wi_light.z, wo_view.x, wo_view.y, wo_view.z])  # eq. 3
        return mi.Color3f(*[dr.maximum(x, 0.0) * self.gain for x in rgb])

    def _active(self, ctx, si, wo, active):
        enabled = ctx.is_enabled(mi.BSDFFlags.GlossyReflection, 0)
        return enabled, active & (mi.Frame3f.cos_theta(si.wi) > 0) & (mi.Frame3f.cos_theta(wo) > 0)

    def eval(self, ctx, si, wo, active=True):
        enabled, active = self._active(ctx, si, wo, active)
        if not enabled:
            return mi.Color3f(0.0)
        return dr.select(active, self.network(si.uv, wo, si.wi), 0.0)

    def pdf(self, ctx, si, wo, active=True):
        enabled, active = self._active(ctx, si, wo, active)
        if not enabled:
            return mi.Float(0.0)
        return dr.select(active, mi.warp.square_to_cosine_hemisphere_pdf(wo), 0.0)

    def eval_pdf(self, ctx, si, wo, active=True):
        enabled, active = self._active(ctx, si, wo, active)
        if not enabled:
            return mi.Color3f(0.0), mi.Float(0.0)
        value = dr.select(active, self.network(si.uv, wo, si.wi), 0.0)
        return value, dr.select(active, mi.warp.square_to_cosine_hemisphere_pdf(wo), 0.0)

    def sample(self, ctx, si, sample1, sample2, active=True):
        bs = dr.zeros(mi.BSDFSample3f)
        if not ctx.is_enabled(mi.BSDFFlags.GlossyReflection, 0):
            return bs, mi.Color3f(0.0)
        wo = mi.warp.square_to_cosine_hemisphere(sample2)
        pdf = mi.warp.square_to_cosine_hemisphere_pdf(wo)
        active = active & (mi.Frame3f.cos_theta(si.wi) > 0) & (pdf > 0)
        bs.wo = wo
        bs.pdf = dr.select(active, pdf, 0.0)
        bs.eta = 1.0
        bs.sampled_type = mi.UInt32(+mi.BSDFFlags.GlossyReflection)
        bs.sampled_component = mi.UInt32(0)
        value = self.network(si.uv, wo, si.wi)
        return bs, dr.select(active, value / dr.maximum(pdf, 1e-20), 0.0)

    def eval_diffuse_reflectance(self, si, active=True):
        # Albedo estimate for AOVs: π·f at normal incidence and view (f·cos = f there).
        n = mi.Vector3f(0, 0, 1)
        return self.network(si.uv, n, n) * dr.pi

    def traverse(self, callback):
        callback.put("t_off", self.t_off, mi.ParamFlags.Differentiable)
        callback.put("t_rgb", self.t_rgb, mi.ParamFlags.Differentiable)

    def parameters_changed(self, keys=[]):
        for name in ("t_off", "t_rgb"):
            t = getattr(self, name)
            if t.shape != (self.res, self.res, self.cfg.channels):
                raise ValueError(f"neural_btf: parameter '{name}' must keep shape "
                                 f"{(self.res, self.res, self.cfg.channels)}, got {t.shape}")

    def to_string(self):
        return (f"NeuralBTF[basis={self.files[0]!r}, material={self.files[1]!r}, res={self.res}, "
                f"channels={self.cfg.channels}, width={self.cfg.width}, depth={self.cfg.depth}, tiling={self.tiling}]")


@contextlib.contextmanager
def evaluated_mode(enabled: bool = True):
    """Render with symbolic loops and calls off (wavefront): each bounce is its own set of kernels."""
    flags = (dr.JitFlag.SymbolicLoops, dr.JitFlag.SymbolicCalls)
    old = [dr.flag(f) for f in flags]
    try:
        if enabled:
            for f in flags:
                dr.set_flag(f, False)
        yield
    finally:
        for f, v in zip(flags, old):
            dr.set_flag(f, v)


def uses_neural_btf(scene: mi.Scene) -> bool:
    """Whether any shape of ``scene`` has a ``neural_btf`` BSDF."""
    return any(isinstance(sh.bsdf(), NeuralBTF) for sh in scene.shapes() if sh.bsdf() is not None)


def register() -> None:
    mi.register_bsdf("neural_btf", lambda props: NeuralBTF(props))
