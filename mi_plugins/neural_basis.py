"""The universal neural BTF basis of seed 002 §3.1: feature textures + two MLPs, in Dr.Jit.

One implementation, used both to train (``inverse/btf_fit.py``, Dr.Jit *tensor mode*: ``W @ X``
on ``TensorXf``, ≈4× faster to differentiate on LLVM than cooperative vectors) and to render
(``mi_plugins/bsdfs/neural_btf.py``, *cooperative vectors* packed from the very same weights,
the only mode that traces inside a symbolic Mitsuba render).

Notation (code ↔ seed 002):

==============  ===========================================================================
``t_off``       T_off, per-material offset feature texture, [R, R, C] (C = 8)
``t_rgb``       T_rgb, per-material reflectance feature texture, [R, R, C]
``m_off``       M_off, universal offset MLP: (T_off[u], ω_o) → Δu            (eq. 2)
``m_rgb``       M_rgb, universal reflectance MLP: (T_rgb[u+Δu], ω_i, ω_o) → RGB (eq. 3)
``wi``          ω_i, direction *to the light*, tangent space (z = normal)
``wo``          ω_o, direction *to the viewer*, tangent space
==============  ===========================================================================

Value convention (shared with ``inverse/btf/data.py``): the network predicts the radiance leaving
towards ω_o under a distant light of unit perpendicular irradiance from ω_i, i.e. f·cosθ_i — which
is what Mitsuba's ``BSDF.eval(ctx, si, wo)`` returns with ``si.wi`` = viewer and ``wo`` = light.

Eq. 2 of the paper feeds ω_i to M_off. Parallax moves the visible texel with the direction it is
*seen* from, so here M_off takes the view direction ω_o (NeuMIP's choice); see the docstring of
:func:`offset`.

Texture lookups are bilinear with repeat wrap (tileable materials, §4.1); texel centres sit at
(i + ½)/R like Mitsuba's and Dr.Jit's textures.
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np
from mi_plugins.arrays import aligned

__all__ = [
    "BasisConfig", "Basis", "NeuralMaterial", "NeuralBTFError", "bilinear", "mlp_tensor", "rows",
    "evaluate_tensor", "ConstantNet", "CoopNet", "render_net", "save_basis", "load_basis", "save_material", "load_material",
]


class NeuralBTFError(ValueError):
    """A basis or material file is missing, corrupt or inconsistent."""


@dataclass
class BasisConfig:
    """Architecture of the universal basis (seed 002 §5.1: depth 4, width 64, 8 channels)."""

    channels: int = 8          #: C, feature channels of T_off and of T_rgb
    width: int = 64            #: hidden width of both MLPs
    depth: int = 4             #: number of linear layers of each MLP (depth − 1 hidden layers)
    offset_range: float = 0.5  #: |Δu| ≤ this, in tile units (Δu = range · tanh(M_off))

    def __post_init__(self) -> None:
        for name in ("channels", "width", "depth"):
            if int(getattr(self, name)) < 1:
                raise NeuralBTFError(f"BasisConfig.{name} must be ≥ 1, got {getattr(self, name)}")
        if not 0.0 < self.offset_range <= 1.0:
            raise NeuralBTFError(f"BasisConfig.offset_range must be in (0, 1], got {self.offset_range}")

    @property
    def off_in(self) -> int:
        return self.channels + 3

    @property
    def rgb_in(self) -> int:
        return self.channels + 6

    def layer_shapes(self, n_in: int, n_out: int) -> list[tuple[int, int]]:
        sizes = [n_in] + [self.width] * (self.depth - 1) + [n_out]
        return [(sizes[k + 1], sizes[k]) for k in range(self.depth)]


@dataclass
class Basis:
    """Universal MLP weights, numpy f32: lists of (W [out, in], b [out])."""

    config: BasisConfig
    m_off: list[tuple[np.ndarray, np.ndarray]]
    m_rgb: list[tuple[np.ndarray, np.ndarray]]
    meta: dict = field(default_factory=dict)

    @staticmethod
    def init(config: BasisConfig, seed: int) -> "Basis":
        """He-uniform initialisation (ReLU); M_off's last layer is shrunk so training starts at Δu ≈ 0."""
        rng = np.random.default_rng(seed)

        def layers(n_in: int, n_out: int, last_scale: float):
            out = []
            shapes = config.layer_shapes(n_in, n_out)
            for k, (o, i) in enumerate(shapes):
                k_lim = np.sqrt(6.0 / i) if k < len(shapes) - 1 else np.sqrt(3.0 / i) * last_scale
                out.append((rng.uniform(-k_lim, k_lim, (o, i)).astype(np.float32), np.zeros(o, np.float32)))
            return out

        return Basis(config, layers(config.off_in, 2, 0.1), layers(config.rgb_in, 3, 1.0))

    def arrays(self) -> dict[str, np.ndarray]:
        d = {}
        for net in ("m_off", "m_rgb"):
            for k, (w, b) in enumerate(getattr(self, net)):
                d[f"{net}.{k}.W"], d[f"{net}.{k}.b"] = w, b
        return d

    @staticmethod
    def from_arrays(config: BasisConfig, d: dict[str, np.ndarray], meta: dict | None = None) -> "Basis":
        nets = {}
        for net, n_in, n_out in (("m_off", config.off_in, 2), ("m_rgb", config.rgb_in, 3)):
            layers = []
            for k, (o, i) in enumerate(config.layer_shapes(n_in, n_out)):
                w, b = np.asarray(d[f"{net}.{k}.W"], np.float32), np.asarray(d[f"{net}.{k}.b"], np.float32)
                if w.shape != (o, i) or b.shape != (o,):
                    raise NeuralBTFError(f"{net} layer {k}: expected W {(o, i)} and b {(o,)}, got {w.shape}, {b.shape}")
                layers.append((w, b))
            nets[net] = layers
        return Basis(config, nets["m_off"], nets["m_rgb"], dict(meta or {}))


@dataclass
class NeuralMaterial:
    """Per-material feature textures (numpy f32 [R, R, C]), already prefiltered for rendering."""

    t_off: np.ndarray
    t_rgb: np.ndarray
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        for name in ("t_off", "t_rgb"):
            t = getattr(self, name)
            if t.ndim != 3 or t.shape[0] != t.shape[1] or t.shape[0] < 2 or t.shape[2] < 1:
                raise NeuralBTFError(f"{name} must be a square [R, R, C] texture with R ≥ 2, C ≥ 1, got shape {t.shape}")
            if not np.isfinite(t).all():
                raise NeuralBTFError(f"{name} contains NaN or Inf")

    @property
    def res(self) -> int:
        return int(self.t_rgb.shape[0])


# -- lookups and networks (Dr.Jit) ------------------------------------------------------------


def bilinear(tex, res: int, channels: int, u, v, base=None, taps: list | None = None) -> list:
    """Bilinear lookup with repeat wrap in a flat texture ``tex`` laid out [..., R, R, C].

    ``base`` (UInt32, optional) is the first texel of the material's slab, so one flat array can
    hold many materials during universal training. Differentiable w.r.t. ``tex`` and ``(u, v)``.
    """
    Float, UInt = mi.Float, mi.UInt32
    x, y = u * res - 0.5, v * res - 0.5
    x0, y0 = dr.floor(dr.detach(x)), dr.floor(dr.detach(y))
    fx, fy = x - x0, y - y0
    # wrap in float first: negative coordinates must map into [0, R)
    x0 = x0 - res * dr.floor(x0 / res)
    y0 = y0 - res * dr.floor(y0 / res)
    ix0, iy0 = UInt(x0), UInt(y0)
    ix0 = dr.minimum(ix0, res - 1)
    iy0 = dr.minimum(iy0, res - 1)
    ix1 = dr.select(ix0 + 1 >= res, 0, ix0 + 1)
    iy1 = dr.select(iy0 + 1 >= res, 0, iy0 + 1)
    b = UInt(0) if base is None else base
    corners = [(iy0 * res + ix0 + b, (1 - fx) * (1 - fy)), (iy0 * res + ix1 + b, fx * (1 - fy)),
               (iy1 * res + ix0 + b, (1 - fx) * fy), (iy1 * res + ix1 + b, fx * fy)]
    if taps is not None:
        taps.extend(corners)
    out = []
    for c in range(channels):
        acc = Float(0)
        for idx, w in corners:
            acc = dr.fma(dr.gather(Float, tex, idx * channels + c), w, acc)
        out.append(acc)
    return out


def mlp_tensor(layers, x):
    """Tensor-mode MLP: ``layers`` = [(W TensorXf [o, i], b TensorXf [o])], x TensorXf [i, N] → [o, N]."""
    for k, (w, b) in enumerate(layers):
        x = w @ x + dr.reshape(type(b), b, (b.shape[0], 1))
        if k < len(layers) - 1:
            x = dr.maximum(x, 0)
    return x


def rows(t) -> list:
    """Split a [k, N] tensor into k Float rows (AD-preserving gathers)."""
    k, n = t.shape
    idx = dr.arange(mi.UInt32, n)
    return [dr.gather(mi.Float, t.array, idx + i * n) for i in range(k)]


def _to_tensor_layers(layers, grad: bool = False):
    out = []
    for w, b in layers:
        wt, bt = mi.TensorXf(aligned(w)), mi.TensorXf(aligned(b))
        if grad:
            dr.enable_grad(wt, bt)
        out.append((wt, bt))
    return out


def offset(cfg: BasisConfig, f_off: list, wo: list, m_off) -> tuple:
    """Eq. 2: Δu = range · tanh(M_off(T_off[u], ω_o)), tensor mode.

    The paper writes ω_i in eq. 2; the offset models parallax, which depends on the direction the
    texel is seen from, so the view direction is the input (our data shoot camera rays along −ω_o).
    """
    d = rows(mlp_tensor(m_off, dr.stack(list(f_off) + list(wo))))
    return cfg.offset_range * dr.tanh(d[0]), cfg.offset_range * dr.tanh(d[1])


def evaluate_tensor(cfg: BasisConfig, m_off, m_rgb, t_off, t_rgb, res: int, u, v, wi, wo, base=None) -> list:
    """Eqs. 2–3 for N queries in tensor mode → [R, G, B] Floats (unclamped)."""
    du, dv = offset(cfg, bilinear(t_off, res, cfg.channels, u, v, base), wo, m_off)
    f = bilinear(t_rgb, res, cfg.channels, u + du, v + dv, base)
    return rows(mlp_tensor(m_rgb, dr.stack(f + list(wi) + list(wo))))


class ConstantNet:
    """An MLP of the basis with its weights written into the kernel as constants: one fused multiply-add per weight.

    On LLVM this is the fast form inside Mitsuba's symbolic megakernel: a cooperative-vector matrix read inside a
    symbolic call (every BSDF method is one) runs ~9× slower than in a kernel of its own, while constants run at the
    same speed in both modes (measured at width 64: `photoreal bench plugins`). The kernel grows by one instruction
    per weight (~18 k at width 64, compiled once and cached by Dr.Jit); gradients flow into the inputs (the feature
    textures), not into the weights.
    """

    def __init__(self, layers: list[tuple[np.ndarray, np.ndarray]]) -> None:
        self.layers = [(np.asarray(w, np.float32).tolist(), np.asarray(b, np.float32).tolist()) for w, b in layers]
        self.n_out = len(self.layers[-1][1])

    def __call__(self, inputs: list) -> list:
        h = list(inputs)
        last = len(self.layers) - 1
        for k, (w, b) in enumerate(self.layers):
            out = []
            for row, bias in zip(w, b):
                acc = mi.Float(bias)
                for wij, x in zip(row, h):
                    acc = dr.fma(wij, x, acc)
                out.append(acc if k == last else dr.maximum(acc, 0.0))
            h = out
        return h


NET_FORMS = ("auto", "constants", "coop")
#: ``auto`` writes an MLP of at most this many weights (a width-32 basis) into every kernel; a wider one only into
#: symbolic kernels: the bundled width-64 basis as constants compiled for ~50 s in the demo's evaluated-mode renders
#: on an empty kernel cache (2 cores), in cooperative vectors for ~1 s
CONSTANT_WEIGHTS = 4096


class ModeNet:
    """Constants inside Dr.Jit's symbolic calls (a plain ``mi.render``), cooperative vectors in evaluated mode, where
    they run at full speed and compile in a fraction of the time."""

    def __init__(self, layers: list[tuple[np.ndarray, np.ndarray]]) -> None:
        self.constants, self.coop = ConstantNet(layers), CoopNet(layers, training=True)

    def __call__(self, inputs: list) -> list:
        return (self.constants if dr.flag(dr.JitFlag.SymbolicCalls) else self.coop)(inputs)


def render_net(layers: list[tuple[np.ndarray, np.ndarray]], form: str = "auto"):
    """The network form a render uses: constants (:class:`ConstantNet`), cooperative vectors (:class:`CoopNet`, half
    precision on CUDA's tensor cores) or, on LLVM for ``auto`` above :data:`CONSTANT_WEIGHTS` weights, the one that
    suits the Dr.Jit mode (:class:`ModeNet`). CUDA always takes cooperative vectors."""
    if form not in NET_FORMS:
        raise ValueError(f"network form {form!r}: expected one of {', '.join(NET_FORMS)}")
    if dr.backend_v(mi.Float) == dr.JitBackend.CUDA or form == "coop":
        return CoopNet(layers, training=True)
    if form == "auto" and sum(w.size for w, _ in layers) > CONSTANT_WEIGHTS:
        return ModeNet(layers)
    return ConstantNet(layers)


class CoopNet:
    """An MLP of the basis packed for cooperative-vector evaluation (inside Mitsuba kernels).

    ``half``: weights, inputs and products in float16. Dr.Jit 1.5 packs cooperative-vector matrices into the
    CUDA/OptiX layouts for half precision only (float32 is refused: "conversion to optimal layout is currently
    limited to half precision data", seen on an H100 under ``cuda_ad_rgb``), so None means half on CUDA and
    float32 on LLVM (the precision of the training code path, :func:`evaluate_tensor`).
    """

    def __init__(self, layers: list[tuple[np.ndarray, np.ndarray]], training: bool = False,
                 half: bool | None = None) -> None:
        import drjit.nn as nn

        self.half = dr.backend_v(mi.Float) == dr.JitBackend.CUDA if half is None else bool(half)
        tensor = dr.float16_array_t(mi.TensorXf) if self.half else mi.TensorXf
        dtype = np.float16 if self.half else np.float32
        mods = []
        for k, (w, _) in enumerate(layers):
            mods.append(nn.Linear(w.shape[1], w.shape[0]))
            if k < len(layers) - 1:
                mods.append(nn.ReLU())
        net = nn.Sequential(*mods).alloc(tensor, layers[0][0].shape[1])
        for k, (w, b) in enumerate(layers):
            net[f"layers.{2 * k}.weights"] = tensor(aligned(w, dtype))
            net[f"layers.{2 * k}.bias"] = tensor(aligned(b, dtype))
        self.net = nn.pack(net, layout="training" if training else "inference")
        self.n_out = layers[-1][0].shape[0]

    def __call__(self, inputs: list) -> list:
        import drjit.nn as nn

        if not self.half:
            return list(self.net(nn.CoopVec(*inputs)))
        f16 = dr.float16_array_t(mi.Float)
        return [mi.Float(y) for y in self.net(nn.CoopVec(*[f16(x) for x in inputs]))]


# -- files --------------------------------------------------------------------------------------


def _atomic_savez(path: Path, arrays: dict) -> Path:
    import tempfile

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".npz", dir=path.parent)
    os.close(fd)
    try:
        np.savez_compressed(tmp, **arrays)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # what open(path, "w") would give, not mkstemp's 0o600
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return path


def _load_npz(path, kind: str) -> dict:
    path = Path(path)
    if not path.is_file():
        raise NeuralBTFError(f"{kind} file not found: {path}")
    try:
        with np.load(path, allow_pickle=False) as z:
            d = {k: z[k] for k in z.files}
    except Exception as e:  # zipfile/ValueError/OSError: report the file, not numpy's internals
        raise NeuralBTFError(f"{kind} file {path} is not a readable .npz ({type(e).__name__}: {e})") from None
    for k, a in d.items():
        if a.dtype.kind == "f" and not np.isfinite(a).all():
            raise NeuralBTFError(f"{kind} file {path}: array {k!r} contains NaN or Inf")
    return d


def save_basis(path, basis: Basis) -> Path:
    """Write the universal MLPs (npz: ``m_off.K.W``, ``m_off.K.b``, ``m_rgb.K.*``, ``config`` JSON)."""
    d = basis.arrays()
    d["config"] = np.array(json.dumps(asdict(basis.config)))
    d["meta"] = np.array(json.dumps(basis.meta))
    return _atomic_savez(path, d)


def load_basis(path) -> Basis:
    d = _load_npz(path, "neural basis")
    if "config" not in d:
        raise NeuralBTFError(f"neural basis file {path} has no 'config' entry (not written by save_basis?)")
    try:
        cfg = BasisConfig(**json.loads(str(d["config"])))
        meta = json.loads(str(d.get("meta", "{}")))
        return Basis.from_arrays(cfg, d, meta)
    except KeyError as e:
        raise NeuralBTFError(f"neural basis file {path} lacks array {e}") from None
    except (TypeError, json.JSONDecodeError, NeuralBTFError) as e:
        raise NeuralBTFError(f"neural basis file {path}: {e}") from None


def check_pair(basis: Basis, mat: NeuralMaterial, basis_path="basis", mat_path="material") -> None:
    """Refuse a material whose feature textures were fitted to another basis (they decode to garbage)."""
    want, got = basis.meta.get("id"), mat.meta.get("basis")
    if want and got and want != got:
        raise NeuralBTFError(f"neural material {mat_path} was fitted to basis {got!r}, but {basis_path} is "
                             f"basis {want!r}; fit the material to this basis (photoreal btf fit) or use its own")


def save_material(path, mat: NeuralMaterial) -> Path:
    return _atomic_savez(path, {"t_off": mat.t_off.astype(np.float32), "t_rgb": mat.t_rgb.astype(np.float32),
                                "meta": np.array(json.dumps(mat.meta))})


def load_material(path, channels: int | None = None) -> NeuralMaterial:
    d = _load_npz(path, "neural material")
    for k in ("t_off", "t_rgb"):
        if k not in d:
            raise NeuralBTFError(f"neural material file {path} lacks array {k!r}")
    try:
        mat = NeuralMaterial(d["t_off"].astype(np.float32), d["t_rgb"].astype(np.float32),
                             json.loads(str(d.get("meta", "{}"))))
    except NeuralBTFError as e:
        raise NeuralBTFError(f"neural material file {path}: {e}") from None
    if mat.t_off.shape != mat.t_rgb.shape:
        raise NeuralBTFError(f"neural material file {path}: t_off {mat.t_off.shape} and t_rgb {mat.t_rgb.shape} differ")
    if channels is not None and mat.t_rgb.shape[2] != channels:
        raise NeuralBTFError(f"neural material file {path} has {mat.t_rgb.shape[2]} channels, the basis expects {channels}")
    return mat
