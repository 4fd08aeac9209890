"""Universal neural BTF basis: training (seed 002 §4.2), per-material fitting (§4.3), NeuMIP baseline.

All network maths lives in :mod:`mi_plugins.neural_basis` (Dr.Jit), so the weights trained here
run unchanged in the ``neural_btf`` plugin. This module only owns the optimisation: batches of
random (material, slice, texel) samples, the Gaussian prefilter schedule, Adam, checkpoints.

Prefilter (§4.2): before every lookup the feature textures are blurred with a Gaussian of std
τ(t) = max(INIT·2^(−t/h), FINAL) texels. The textures repeat (tileable BTFs), so the blur is a
*periodic* convolution, done exactly in the Fourier domain; it is self-adjoint, so the gradient
w.r.t. the raw texture is the same blur applied to the gradient w.r.t. the blurred one. After
fitting, the textures are blurred with FINAL once and stored: the plugin does plain bilinear lookups.

The paper's schedule constants are in texels at 512²; our defaults are for 64² textures and a few
thousand iterations (every value is a parameter, the paper's run unchanged on a larger machine).
"""

from __future__ import annotations

import hashlib
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Sequence

import mi_plugins  # noqa: F401
import drjit as dr
import mitsuba as mi
import numpy as np

from foundation import validate
from foundation.errors import CheckpointError
from foundation.loop import LoopSettings, RunState, Stage, StepResult, all_finite, run_loop
from foundation.optim_state import load_optimizer_state, optimizer_state
from mi_plugins.arrays import aligned
from mi_plugins.neural_basis import (Basis, BasisConfig, NeuralBTFError, NeuralMaterial, _to_tensor_layers, bilinear,
                                     evaluate_tensor, mlp_tensor, offset, rows)

__all__ = ["Prefilter", "OptimSettings", "train_basis", "fit_material", "fit_settings", "fit_prefilter", "train_per_material", "predict",
           "heldout_psnr", "psnr", "psnr_pair", "split_slices", "gaussian_periodic", "fit_file"]


@dataclass
class Prefilter:
    """τ(t) = max(init · 2^(−t/half_life), final), in texels of the feature texture (§4.2)."""

    init: float
    final: float
    half_life: float

    def tau(self, t: int) -> float:
        return max(self.init * 2.0 ** (-t / max(self.half_life, 1e-9)), self.final)


@dataclass
class OptimSettings:
    """One optimisation run (universal training, per-material fitting or the NeuMIP baseline)."""

    iterations: int = 2000
    batch: int = 1 << 15                 #: random (material, slice, texel) samples per step
    lr_net: float = 1e-3                 #: paper 3e-4 over 100 epochs; we train ~100× fewer steps
    lr_tex: float = 1e-2                 #: paper 1e-3 (training) / 1e-2 (fitting)
    tex_res: int = 0                     #: feature texture resolution; 0 = the BTF's resolution
    tau_rgb: Prefilter = field(default_factory=lambda: Prefilter(4.0, 0.5, 250.0))
    tau_off: Prefilter = field(default_factory=lambda: Prefilter(4.0, 1.0, 250.0))
    tex_init_std: float = 0.1            #: N(0, 0.01) as in §4.2/§4.3
    seed: int = 0
    checkpoint_every: int = 200
    log_every: int = 25

    def __post_init__(self) -> None:
        for name in ("iterations", "batch", "checkpoint_every", "log_every"):
            validate.integer(name, getattr(self, name), 1)
        for name in ("lr_net", "lr_tex", "tex_init_std"):
            validate.positive(name, getattr(self, name))
        validate.integer("tex_res", self.tex_res, 0, 4096)  # 0 = the BTF's resolution
        validate.seed("seed", self.seed)

    def validate(self) -> None:
        self.__post_init__()


# -- prefilter -----------------------------------------------------------------------------------


def _periodic_kernel_matrix(r: int, tau: float) -> np.ndarray:
    """Circulant R×R matrix of the periodic Gaussian (transfer function exp(−2π²τ²f²)); symmetric."""
    f = np.fft.fftfreq(r)  # cycles per texel
    k = np.real(np.fft.ifft(np.exp(-2.0 * np.pi**2 * tau**2 * f**2)))
    i = np.arange(r)
    return k[(i[:, None] - i[None, :]) % r].astype(np.float32)


def gaussian_periodic(t: np.ndarray, tau: float) -> np.ndarray:
    """Blur [..., R, R, C] textures with a periodic Gaussian of std ``tau`` texels (exact).

    Separable: one circulant matrix product per axis (BLAS), ~20× faster here than a 2D FFT of
    the whole stack, and symmetric, so the same call is its own adjoint.
    """
    if tau <= 1e-3:
        return t
    r, c = t.shape[-2], t.shape[-1]
    g = _periodic_kernel_matrix(r, tau)
    lead = t.shape[:-3]
    x = np.asarray(t, np.float32).reshape(-1, r, r, c)
    # Two single large GEMMs: move the blurred axis last, multiply, move it back.
    x = (np.ascontiguousarray(x.transpose(0, 2, 3, 1)).reshape(-1, r) @ g.T).reshape(-1, r, c, r)  # y
    x = x.transpose(0, 3, 2, 1)                                                                  # [m, y, c, x]
    x = (np.ascontiguousarray(x).reshape(-1, r) @ g.T).reshape(-1, r, c, r)                       # x
    return np.ascontiguousarray(x.transpose(0, 1, 3, 2)).reshape(*lead, r, r, c)


# -- data ----------------------------------------------------------------------------------------


def split_slices(n_slices: int, heldout_fraction: float = 0.25) -> tuple[np.ndarray, np.ndarray]:
    """Fit on the first slices, hold out the last ones (slices are i.i.d. random direction pairs)."""
    validate.in_range("heldout_fraction", heldout_fraction, 0.0, 1.0, lo_open=True, hi_open=True)
    n_held = max(1, int(round(n_slices * heldout_fraction)))
    if n_held >= n_slices:
        raise ValueError(f"cannot hold out {n_held} of {n_slices} slices")
    return np.arange(n_slices - n_held), np.arange(n_slices - n_held, n_slices)


def _stack(materials: Sequence) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    shapes = {m.values.shape for m in materials}
    if len(shapes) != 1:
        raise NeuralBTFError(f"all BTFs must have the same [slices, H, W, 3] shape, got {sorted(shapes)}")
    vals = np.stack([np.asarray(m.values, np.float32) for m in materials])
    wi = np.stack([np.asarray(m.wi, np.float32) for m in materials])
    wo = np.stack([np.asarray(m.wo, np.float32) for m in materials])
    if vals.shape[2] != vals.shape[3]:
        raise NeuralBTFError(f"BTF texels must be square, got {vals.shape[2]}×{vals.shape[3]}")
    return vals, wi, wo


def psnr(pred: np.ndarray, ref: np.ndarray, peak: float = 1.0) -> float:
    """PSNR of linear BTF values (radiance under unit irradiance), peak 1, no clipping."""
    mse = float(np.mean((np.asarray(pred, np.float64) - np.asarray(ref, np.float64)) ** 2))
    return float("inf") if mse == 0 else 10.0 * np.log10(peak**2 / mse)


def psnr_pair(pred: np.ndarray, ref: np.ndarray) -> tuple[float, float]:
    """(PSNR on values clipped to [0, 1], PSNR on raw values), peak 1; predictions clamped at 0 like the plugin."""
    pred = np.maximum(pred, 0)
    return psnr(np.clip(pred, 0, 1), np.clip(ref, 0, 1)), psnr(pred, ref)


# -- Adam ----------------------------------------------------------------------------------------


class _Adam:
    def __init__(self, lrs: dict[str, float], b1: float = 0.9, b2: float = 0.999, eps: float = 1e-8) -> None:
        self.lrs, self.b1, self.b2, self.eps = lrs, b1, b2, eps
        self.m: dict[str, np.ndarray] = {}
        self.v: dict[str, np.ndarray] = {}
        self.t = 0

    def step(self, params: dict[str, np.ndarray], grads: dict[str, np.ndarray]) -> None:
        self.t += 1
        for k, g in grads.items():
            m = self.m.setdefault(k, np.zeros_like(g))
            v = self.v.setdefault(k, np.zeros_like(g))
            m *= self.b1
            m += (1 - self.b1) * g
            v *= self.b2
            v += (1 - self.b2) * g * g
            mh = m / (1 - self.b1**self.t)
            vh = v / (1 - self.b2**self.t)
            params[k] -= (self.lrs[k.split(".")[0]] * mh / (np.sqrt(vh) + self.eps)).astype(np.float32)

    def state_dict(self) -> dict:
        return {"t": self.t, "m": dict(self.m), "v": dict(self.v)}

    def load_state_dict(self, d: dict) -> None:
        self.t = int(d["t"])
        self.m = {k: np.array(a) for k, a in d["m"].items()}
        self.v = {k: np.array(a) for k, a in d["v"].items()}


# -- the optimisation (a stage of the shared loop) --------------------------------------------


def _net_layers(params: dict[str, np.ndarray], net: str, depth: int):
    return [(params[f"{net}.{k}.W"], params[f"{net}.{k}.b"]) for k in range(depth)]


def _forward(cfg: BasisConfig, params, t_off, t_rgb, res, m, uv, wi, wo, grad_net: bool, taps=None):
    """Upload one batch and evaluate eqs. 2–3 → (pred rows, net tensors, feature leaves).

    With ``taps`` (a dict), the textures are treated as constants and each lookup gets a zero-valued
    gradient leaf added; ``taps`` receives the leaves and bilinear taps so the caller can scatter
    dL/dT deterministically (Dr.Jit's atomic scatter-add reorders float sums between runs, and a
    resumed run must reproduce an uninterrupted one).
    """
    m_off = _to_tensor_layers(_net_layers(params, "m_off", cfg.depth), grad_net)
    m_rgb = _to_tensor_layers(_net_layers(params, "m_rgb", cfg.depth), grad_net)
    u, v = mi.Float(aligned(uv[:, 0])), mi.Float(aligned(uv[:, 1]))
    wi_, wo_ = [mi.Float(aligned(wi[:, k])) for k in range(3)], [mi.Float(aligned(wo[:, k])) for k in range(3)]
    base = mi.UInt32(aligned(m.astype(np.uint32) * np.uint32(res * res), np.uint32))
    if taps is None:
        return evaluate_tensor(cfg, m_off, m_rgb, t_off, t_rgb, res, u, v, wi_, wo_, base), m_off, m_rgb

    def leaf_lookup(tex, uu, vv, name):
        tp: list = []
        f = bilinear(tex, res, cfg.channels, uu, vv, base, tp)
        leaves = [dr.zeros(mi.Float, len(uv)) for _ in f]
        dr.enable_grad(leaves)
        taps[name] = (leaves, tp)
        return [a + b for a, b in zip(f, leaves)]

    du, dv = offset(cfg, leaf_lookup(t_off, u, v, "t_off"), wo_, m_off)
    f = leaf_lookup(t_rgb, u + du, v + dv, "t_rgb")
    return rows(mlp_tensor(m_rgb, dr.stack(f + wi_ + wo_))), m_off, m_rgb


def _scatter_taps(leaves, tp, n_texels: int, channels: int) -> np.ndarray:
    """dL/dT from per-sample dL/df and the bilinear taps (one np.bincount: fixed summation order)."""
    g = np.stack([dr.grad(x).numpy() for x in leaves], 1)  # [B, C]
    ch = np.arange(channels)
    ids = np.concatenate([(dr.detach(i).numpy().astype(np.int64)[:, None] * channels + ch).ravel() for i, _ in tp])
    wts = np.concatenate([(dr.detach(w).numpy()[:, None] * g).ravel() for _, w in tp])
    return np.bincount(ids, weights=wts, minlength=n_texels * channels).astype(np.float32)


class BTFStage(Stage):
    """L1 (§4.2) on random (material, slice, texel) batches, prefiltered textures, Adam in numpy.

    ``train_net``: the MLPs train with the textures (§4.2, NeuMIP); otherwise they are frozen (§4.3).
    Each iteration draws its batch from ``default_rng([seed, it])``, so a resumed run sees the same batches.
    """

    def __init__(self, cfg: BasisConfig, basis: Basis | None, materials: Sequence, slices: np.ndarray,
                 s: OptimSettings, train_net: bool, desc: str):
        self.cfg, self.basis, self.s, self.train_net, self.name = cfg, basis, s, train_net, desc
        self.vals, self.wi, self.wo = _stack(materials)
        self.slices = np.asarray(slices)
        self.res = s.tex_res or self.vals.shape[2]
        names = [m.meta.get("name", str(i)) for i, m in enumerate(materials)]
        self.key = {"cfg": asdict(cfg), "settings": {k: v for k, v in asdict(s).items()
                                                     if k not in ("iterations", "checkpoint_every", "log_every")},
                    "materials": names, "slices": self.slices.tolist(), "train_net": train_net,
                    "basis": None if basis is None else basis.meta.get("id", "given")}
        lrs = {"t_off": s.lr_tex, "t_rgb": s.lr_tex, "m_off": s.lr_net, "m_rgb": s.lr_net}
        rng = np.random.default_rng([s.seed, 2**31 - 1])
        start = basis if basis is not None else Basis.init(cfg, s.seed)
        self.params = {k: v.copy() for k, v in start.arrays().items()}
        for t in ("t_off", "t_rgb"):
            self.params[t] = (rng.standard_normal((len(materials), self.res, self.res, cfg.channels))
                              * s.tex_init_std).astype(np.float32)
        self.adam = _Adam(lrs)
        self.grads: dict[str, np.ndarray] = {}

    # The schedule depends only on t, so rerunning with more iterations continues the same run:
    # the iteration count is not part of the fingerprint.
    def fingerprint(self) -> dict:
        return self.key

    def start(self, run: RunState) -> None:
        if run.step > self.s.iterations:
            raise CheckpointError(f"{self.name}: the checkpoint has run {run.step} iterations, more than the "
                                  f"{self.s.iterations} asked for; ask for at least {run.step} or delete it")

    def state(self) -> dict:
        return {"params": dict(self.params), "adam": optimizer_state(self.adam)}

    def load_state(self, tree: dict) -> None:
        self.params = {k: np.array(v) for k, v in tree["params"].items()}
        load_optimizer_state(self.adam, tree["adam"], f"{self.name} optimizer")

    def step(self, it: int) -> StepResult:
        s, cfg, vals = self.s, self.cfg, self.vals
        n_mat, _, h, w, _ = vals.shape
        rng = np.random.default_rng([s.seed, it])  # per-iteration stream: resume reproduces the batch
        m = rng.integers(0, n_mat, s.batch)
        sl = self.slices[rng.integers(0, len(self.slices), s.batch)]
        y, x = rng.integers(0, h, s.batch), rng.integers(0, w, s.batch)
        uv = np.stack([(x + 0.5) / w, (y + 0.5) / h], 1).astype(np.float32)
        target = vals[m, sl, y, x]

        t_off = mi.Float(aligned(gaussian_periodic(self.params["t_off"], s.tau_off.tau(it)).ravel()))
        t_rgb = mi.Float(aligned(gaussian_periodic(self.params["t_rgb"], s.tau_rgb.tau(it)).ravel()))
        taps: dict = {}
        pred, m_off, m_rgb = _forward(cfg, self.params, t_off, t_rgb, self.res, m, uv, self.wi[m, sl, y, x],
                                      self.wo[m, sl, y, x], self.train_net, taps)
        loss = 0
        for c in range(3):
            loss = loss + dr.sum(dr.abs(pred[c] - mi.Float(aligned(target[:, c]))))
        loss = loss / (3 * s.batch)  # L1 (§4.2)
        dr.backward(loss)

        shape = self.params["t_off"].shape
        n_tex = n_mat * self.res * self.res
        grads = {k: gaussian_periodic(_scatter_taps(*taps[k], n_tex, cfg.channels).reshape(shape),
                                      (s.tau_off if k == "t_off" else s.tau_rgb).tau(it)) for k in ("t_off", "t_rgb")}
        if self.train_net:
            for net, layers in (("m_off", m_off), ("m_rgb", m_rgb)):
                for k in range(cfg.depth):
                    grads[f"{net}.{k}.W"] = dr.grad(layers[k][0]).numpy()
                    grads[f"{net}.{k}.b"] = dr.grad(layers[k][1]).numpy()
        self.grads = grads
        l1 = float(loss.numpy()[0]) if hasattr(loss, "numpy") else float(loss)
        return StepResult(l1, all_finite(*grads.values()), log={"l1": l1})

    def apply(self, it: int) -> None:
        self.adam.step(self.params, self.grads)

    def discard(self, it: int) -> None:
        self.grads = {}

    def finish(self, run: RunState):
        s, p = self.s, self.params
        out_basis = Basis.from_arrays(self.cfg, {k: v for k, v in p.items() if k.startswith("m_")})
        out_basis.meta = dict(self.basis.meta) if self.basis is not None and not self.train_net else {}
        t_off = gaussian_periodic(p["t_off"], s.tau_off.final)  # §4.3: store the FINAL-blurred textures
        t_rgb = gaussian_periodic(p["t_rgb"], s.tau_rgb.final)
        history = [{"iteration": e["step"], "l1": e["l1"], "seconds": e["seconds"]} for e in run.log]
        return out_basis, t_off, t_rgb, history


def _run(cfg: BasisConfig, basis: Basis | None, materials: Sequence, slices: np.ndarray, s: OptimSettings,
         train_net: bool, checkpoint, desc: str, progress: bool) -> tuple[Basis, np.ndarray, np.ndarray, list]:
    s.validate()
    stage = BTFStage(cfg, basis, materials, slices, s, train_net, desc)
    loop = LoopSettings(steps=s.iterations, checkpoint_every=s.checkpoint_every, log_every=s.log_every)
    return run_loop(stage, loop, checkpoint=Path(checkpoint) if checkpoint else None, show_progress=progress)


def weights_digest(basis: Basis) -> str:
    """Short SHA-256 of the MLP weights: two bases with the same settings but other data get other ids."""
    h = hashlib.sha256()
    for k, a in sorted(basis.arrays().items()):
        if k.startswith("m_"):
            h.update(k.encode())
            h.update(np.ascontiguousarray(a, np.float32).tobytes())
    return h.hexdigest()[:10]


def train_basis(materials: Sequence, cfg: BasisConfig | None = None, s: OptimSettings | None = None,
                slices: np.ndarray | None = None, checkpoint=None, progress: bool = True) -> tuple[Basis, list]:
    """§4.2: train M_off and M_rgb jointly with one pair of textures per material (textures discarded)."""
    cfg = cfg or BasisConfig()
    s = s or OptimSettings(lr_tex=1e-2)
    slices = np.arange(materials[0].values.shape[0]) if slices is None else np.asarray(slices)
    basis, _, _, hist = _run(cfg, None, materials, slices, s, True, checkpoint, "train basis", progress)
    basis.meta = {"id": f"basis-seed{s.seed}-{len(materials)}mats-{s.iterations}it-{weights_digest(basis)}",
                  "materials": [m.meta.get("name", "") for m in materials], "settings": asdict(s),
                  "iterations": s.iterations}
    return basis, hist


def fit_prefilter(which: str, iterations: int) -> Prefilter:
    """Default §4.3 schedule scaled to the run: τ reaches FINAL after ~40% of the iterations."""
    final = 0.5 if which == "rgb" else 1.0
    return Prefilter(4.0, final, max(iterations * 0.4 / np.log2(4.0 / final), 1.0))


def fit_settings(iterations: int = 600, **kw) -> OptimSettings:
    return OptimSettings(iterations=iterations, lr_tex=kw.pop("lr_tex", 2e-2), tau_rgb=fit_prefilter("rgb", iterations),
                         tau_off=fit_prefilter("off", iterations), **kw)


def fit_material(basis: Basis, data, slices: np.ndarray, s: OptimSettings | None = None, checkpoint=None,
                 progress: bool = True) -> tuple[NeuralMaterial, list]:
    """§4.3: optimise only T_off and T_rgb of one material, universal MLPs frozen."""
    s = s or fit_settings()
    _, t_off, t_rgb, hist = _run(basis.config, basis, [data], np.asarray(slices), s, False, checkpoint,
                                 f"fit {data.meta.get('name', '')}", progress)
    meta = {"btf": data.meta.get("name", ""), "family": data.meta.get("family", ""),
            "basis": basis.meta.get("id", ""), "fit_slices": np.asarray(slices).tolist(), "iterations": s.iterations}
    return NeuralMaterial(t_off[0], t_rgb[0], meta), hist


def train_per_material(data, slices: np.ndarray, cfg: BasisConfig | None = None, s: OptimSettings | None = None,
                       checkpoint=None, progress: bool = True) -> tuple[Basis, NeuralMaterial, list]:
    """NeuMIP-style baseline (§5.2): same architecture, MLPs and textures trained on one material alone."""
    cfg = cfg or BasisConfig()
    s = s or OptimSettings()
    basis, t_off, t_rgb, hist = _run(cfg, None, [data], np.asarray(slices), s, True, checkpoint,
                                     f"NeuMIP {data.meta.get('name', '')}", progress)
    basis.meta = {"id": f"neumip-{data.meta.get('name', '')}-{weights_digest(basis)}"}
    return basis, NeuralMaterial(t_off[0], t_rgb[0], {"btf": data.meta.get("name", "")}), hist


def predict(basis: Basis, mat: NeuralMaterial, data, slices: np.ndarray, chunk: int = 1 << 18) -> np.ndarray:
    """Evaluate the neural BTF on the data's own (texel, ω_i, ω_o) samples of ``slices`` → [S, H, W, 3]."""
    cfg = basis.config
    s_, h, w = len(slices), data.values.shape[1], data.values.shape[2]
    yy, xx = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    uv = np.stack([(xx + 0.5) / w, (yy + 0.5) / h], -1).reshape(-1, 2).astype(np.float32)
    uv = np.tile(uv, (s_, 1))
    wi = np.asarray(data.wi, np.float32)[slices].reshape(-1, 3)
    wo = np.asarray(data.wo, np.float32)[slices].reshape(-1, 3)
    params = basis.arrays()
    t_off, t_rgb = mi.Float(aligned(mat.t_off.ravel())), mi.Float(aligned(mat.t_rgb.ravel()))
    out = np.empty((len(uv), 3), np.float32)
    for a in range(0, len(uv), chunk):
        b = min(a + chunk, len(uv))
        pred, _, _ = _forward(cfg, params, t_off, t_rgb, mat.res, np.zeros(b - a, np.int64), uv[a:b], wi[a:b],
                              wo[a:b], False)
        out[a:b] = np.stack([p.numpy() for p in pred], 1)
    return out.reshape(s_, h, w, 3)


def heldout_psnr(basis: Basis, mat: NeuralMaterial, data, slices: np.ndarray) -> float:
    """Unclipped held-out PSNR (the second of :func:`psnr_pair`)."""
    return psnr_pair(predict(basis, mat, data, slices), np.asarray(data.values, np.float32)[slices])[1]


def fit_file(btf: str, basis_path: str, out: str, iterations: int = 600, batch: int = 1 << 15, tex_res: int = 0,
             heldout_fraction: float = 0.25, seed: int = 0, checkpoint: str | None = None,
             progress: bool = False) -> dict:
    """`photoreal btf fit` for one BTF file: fit, score on held-out slices, write the material; returns a summary.

    The unit that fitting many materials fans out (on worker processes or Ray); resumable through ``checkpoint``.
    """
    from mi_plugins.neural_basis import load_basis, save_material

    from .data import load_btf

    s = fit_settings(iterations, batch=batch, seed=seed, tex_res=tex_res)
    basis = load_basis(basis_path)
    data = load_btf(btf)
    fit, held = split_slices(data.values.shape[0], heldout_fraction)
    ck = checkpoint or str(Path(out).with_suffix(".ckpt.npz"))
    mat, hist = fit_material(basis, data, fit, s, checkpoint=ck, progress=progress)
    mat.meta["psnr_heldout"] = heldout_psnr(basis, mat, data, held)
    save_material(out, mat)
    return {"material": str(out), "btf": str(btf), "basis": basis.meta.get("id"), "psnr_heldout": mat.meta["psnr_heldout"],
            "heldout_slices": len(held), "final_l1": hist[-1]["l1"], "seconds": hist[-1]["seconds"]}
