"""A neural material outside photoreal: its Mitsuba XML snippet with the files it needs, a preview render, and a
GGX/metallic-roughness SVBRDF distilled from it through the shared shader (:func:`mi_plugins.shading.brdf_lobes`, the
maths of ``ggx_uv``) — exported as a glTF material on a unit tile, with its fitting error on held-out directions.

The distillation: per texel of the material's tile, albedo, roughness, metallic, specular and a tangent-space normal
are fitted by Adam (the shared training loop) so that the GGX value f·cosθ matches the neural BTF's
(seed 002 eq. 3, f(u, ω_i, ω_o)·cosθ_i) on random direction pairs of the BTF's cap (θ ≤ 80°), L1 as the BTF's own fit
(§4.2). What a GGX cannot hold (parallax, inter-shadowing, the offset network's eq. 2) is what the error measures."""

from __future__ import annotations

import shutil
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

import drjit as dr
import mi_plugins  # noqa: F401
import mitsuba as mi
from mi_plugins import shading as sh
from mi_plugins.arrays import aligned
from mi_plugins.neural_basis import Basis, NeuralMaterial, check_pair, load_basis, load_material

from foundation import imageio
from foundation.export import ExportMaterial, ExportMesh, ExportSettings, reimport_check, write_model
from foundation.loop import DrJitStage, LoopSettings, RunState, run_loop

from .data import sample_directions
from .fit import _forward


@dataclass
class DistilSettings:
    """The GGX distillation of a neural material."""

    iterations: int = 300
    train_pairs: int = 96  #: direction pairs (ω_i, ω_o) every texel is fitted on
    #: other pairs that choose between the per-texel maps and one GGX for the tile (their mean): the one of lower mean
    #: absolute error there (the fit's own L1, less swayed by one grazing pair than PSNR) is exported
    validation_pairs: int = 32
    heldout_pairs: int = 32  #: other pairs again, for the error only
    #: of the training pairs, per Adam step (all texels each); all of them (the default) is a deterministic full batch:
    #: small random subsets leave per-texel noise that a held-out direction sees (measured: −2 dB)
    pairs_per_step: int = 96
    lr: float = 0.03
    max_theta_deg: float = 80.0  #: the BTF's cap (inverse/btf/data.py)
    seed: int = 0


@dataclass
class MaterialExport:
    """``export.json`` of a neural material."""

    kind: str  #: "material"
    material: str
    basis: str
    format: str
    files: list[str]
    texture_size: int
    #: the distilled GGX against the neural BTF on the held-out direction pairs (every texel): PSNR (peak 1, values
    #: as the BTF's bench reads them) and the mean absolute error; the same for one GGX over the tile (the fitted
    #: parameters' mean) beside it: what the per-texel maps add
    model: str  #: 'per-texel' or 'uniform' (one GGX for the tile): what the validation pairs preferred, exported
    validation: dict  #: both models on the validation pairs (PSNR, MAE)
    exported_heldout_psnr: float  #: the exported model on the held-out pairs
    ggx_heldout_psnr: float
    ggx_heldout_mae: float
    constant_heldout_psnr: float
    constant_heldout_mae: float
    train_psnr: float
    preview_psnr: float | None  #: the GGX tile's render against the neural one's (preview.png: neural | GGX)
    distil: DistilSettings
    iterations: int
    reimport: dict = field(default_factory=dict)
    seconds: float = 0.0


def neural_values(basis: Basis, mat: NeuralMaterial, wi: np.ndarray, wo: np.ndarray, chunk: int = 1 << 18) -> np.ndarray:
    """The neural BTF at every texel centre for each direction pair (P, 3) and (P, 3) → (P, R, R, 3); ``wi`` towards
    the light, ``wo`` towards the viewer (the network's own)."""
    r = mat.res
    yy, xx = np.meshgrid(np.arange(r), np.arange(r), indexing="ij")
    uv = np.stack([(xx + 0.5) / r, (yy + 0.5) / r], -1).reshape(-1, 2).astype(np.float32)
    params = basis.arrays()
    t_off, t_rgb = mi.Float(aligned(mat.t_off.ravel())), mi.Float(aligned(mat.t_rgb.ravel()))
    n = r * r
    out = np.empty((len(wi), n, 3), np.float32)
    per = max(1, chunk // n)
    for a in range(0, len(wi), per):
        b = min(a + per, len(wi))
        k = b - a
        pred, _, _ = _forward(basis.config, params, t_off, t_rgb, r, np.zeros(k * n, np.int64), np.tile(uv, (k, 1)),
                              np.repeat(wi[a:b], n, 0), np.repeat(wo[a:b], n, 0), False)
        out[a:b] = np.stack([p.numpy() for p in pred], 1).reshape(k, n, 3)
    return np.maximum(out.reshape(len(wi), r, r, 3), 0.0)


def _squash(x):
    return 1.0 / (1.0 + dr.exp(-x))


def ggx_values(p: dict, texel, view: mi.Vector3f, light: mi.Vector3f) -> mi.Color3f:
    """ggx_uv's f·cosθ (:func:`mi_plugins.shading.brdf_lobes`, normal map by :func:`~mi_plugins.shading.perturbation`)
    of the texels ``texel`` with the raw parameters ``p`` (logits; normal as two tangential components)."""
    g = {k: dr.gather(type(v), v, texel) for k, v in p.items()}
    albedo = mi.Color3f(_squash(g["a0"]), _squash(g["a1"]), _squash(g["a2"]))
    rough, metal, spec = _squash(g["rough"]), _squash(g["metal"]), _squash(g["spec"])
    nx, ny = 0.7 * dr.tanh(g["nx"]), 0.7 * dr.tanh(g["ny"])
    n = mi.Vector3f(nx, ny, dr.sqrt(dr.maximum(1.0 - nx * nx - ny * ny, 1e-6)))
    frame, wi_p, ok = sh.perturbation(n, view)
    wo_p, ok_o = sh.to_perturbed(frame, light)
    d, s = sh.brdf_lobes(albedo, rough, spec, metal, wi_p, wo_p)
    return dr.select(ok & ok_o, d + s, mi.Color3f(0.0))


def maps_of(p: dict, r: int) -> dict[str, np.ndarray]:
    """The fitted maps as numpy (R, R, ·), in their units."""
    def sq(x):
        return 1.0 / (1.0 + np.exp(-np.asarray(x, np.float64)))

    nx, ny = 0.7 * np.tanh(np.asarray(p["nx"])), 0.7 * np.tanh(np.asarray(p["ny"]))
    nz = np.sqrt(np.maximum(1 - nx * nx - ny * ny, 1e-6))
    return {"albedo": np.stack([sq(p[f"a{c}"]) for c in range(3)], -1).reshape(r, r, 3).astype(np.float32),
            "roughness": sq(p["rough"]).reshape(r, r).astype(np.float32),
            "metallic": sq(p["metal"]).reshape(r, r).astype(np.float32),
            "specular": sq(p["spec"]).reshape(r, r).astype(np.float32),
            "normal": np.stack([nx, ny, nz], -1).reshape(r, r, 3).astype(np.float32)}


class DistilStage(DrJitStage):
    """L1 between ggx_uv's value and the neural BTF's, all texels × ``pairs_per_step`` pairs per step (the pairs
    drawn from ``default_rng([seed, it])``: a resumed run sees the same ones)."""

    kind = "ggx-distil"

    def __init__(self, target: np.ndarray, wi: np.ndarray, wo: np.ndarray, s: DistilSettings, key: str):
        self.target, self.wi, self.wo, self.s, self.key = target, wi, wo, s, key
        self.r = target.shape[1]
        n = self.r * self.r
        init = {"a0": 0.0, "a1": 0.0, "a2": 0.0, "rough": 0.0, "metal": -3.0, "spec": 0.0, "nx": 0.0, "ny": 0.0}
        mean = target.mean(axis=(0, 1, 2))
        for c in range(3):  # start from the mean colour: the diffuse value ≈ albedo/π · cosθ
            a = float(np.clip(mean[c] * np.pi / 0.6, 0.02, 0.98))
            init[f"a{c}"] = float(np.log(a / (1 - a)))
        self.opt = mi.ad.Adam(lr=s.lr)
        for k, v in init.items():
            self.opt[k] = mi.Float(np.full(n, v, np.float32))
        self.texel = dr.arange(mi.UInt32, n)

    def fingerprint(self) -> dict:
        return {"material": self.key, "settings": {k: v for k, v in asdict(self.s).items() if k != "iterations"}}

    def state(self) -> dict:
        from foundation.optim_state import optimizer_state

        return {"adam": optimizer_state(self.opt)}

    def load_state(self, tree: dict) -> None:
        from foundation.optim_state import load_optimizer_state

        load_optimizer_state(self.opt, tree["adam"], "GGX distillation optimiser")

    def step(self, it: int):
        rng = np.random.default_rng([self.s.seed, it])
        pick = (np.arange(len(self.wi)) if self.s.pairs_per_step >= len(self.wi)
                else rng.choice(len(self.wi), self.s.pairs_per_step, replace=False))
        n = self.r * self.r
        texel = dr.tile(self.texel, len(pick))
        light = mi.Vector3f(*[mi.Float(np.repeat(self.wi[pick, k], n)) for k in range(3)])
        view = mi.Vector3f(*[mi.Float(np.repeat(self.wo[pick, k], n)) for k in range(3)])
        pred = ggx_values({k: self.opt[k] for k in self.opt.keys()}, texel, view, light)
        t = self.target[pick].reshape(-1, 3)
        loss = sum(dr.sum(dr.square(pred[c] - mi.Float(aligned(t[:, c])))) for c in range(3)) / (3 * len(t))
        dr.backward(loss)
        return self.result(loss)

    def finish(self, run: RunState):
        return {k: np.array(self.opt[k]) for k in self.opt.keys()}, run.step


def _psnr(pred: np.ndarray, ref: np.ndarray) -> float:
    mse = float(np.mean((np.clip(pred, 0, 1) - np.clip(ref, 0, 1)) ** 2))
    return float(10 * np.log10(1.0 / max(mse, 1e-20)))


def evaluate_pairs(p: dict, r: int, wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
    """The fitted GGX at every texel for the pairs → (P, R, R, 3)."""
    n = r * r
    out = []
    arrays = {k: mi.Float(np.asarray(v, np.float32)) for k, v in p.items()}
    for j in range(len(wi)):
        light = mi.Vector3f(*[mi.Float(np.full(n, wi[j, k], np.float32)) for k in range(3)])
        view = mi.Vector3f(*[mi.Float(np.full(n, wo[j, k], np.float32)) for k in range(3)])
        v = ggx_values(arrays, dr.arange(mi.UInt32, n), view, light)
        out.append(np.stack([np.array(v[c]) for c in range(3)], -1).reshape(r, r, 3))
    return np.stack(out)


def distil_ggx(basis: Basis, mat: NeuralMaterial, s: DistilSettings | None = None, checkpoint=None,
               show_progress: bool = True, key: str = "material") -> dict:
    """Fit the GGX maps to the neural material; returns the maps and their errors (train and held-out pairs)."""
    s = s or DistilSettings()
    rng = np.random.default_rng([s.seed, 7])
    n_pairs = s.train_pairs + s.validation_pairs + s.heldout_pairs
    wi = sample_directions((n_pairs,), s.max_theta_deg, rng)
    wo = sample_directions((n_pairs,), s.max_theta_deg, rng)
    target = neural_values(basis, mat, wi, wo)
    tr, va = slice(0, s.train_pairs), slice(s.train_pairs, s.train_pairs + s.validation_pairs)
    ho = slice(s.train_pairs + s.validation_pairs, n_pairs)
    stage = DistilStage(target[tr], wi[tr], wo[tr], s, key)
    params, steps = run_loop(stage, LoopSettings(steps=s.iterations, checkpoint_every=max(1, s.iterations)),
                             checkpoint, show_progress=show_progress)
    r = mat.res
    pred_ho = evaluate_pairs(params, r, wi[ho], wo[ho])
    pred_tr = evaluate_pairs(params, r, wi[tr][:16], wo[tr][:16])
    mean = {k: np.full_like(v, float(np.mean(v))) for k, v in params.items()}
    const_ho = evaluate_pairs(mean, r, wi[ho], wo[ho])
    val = {}
    if s.validation_pairs:
        for name, p in (("per-texel", params), ("uniform", mean)):
            pred = evaluate_pairs(p, r, wi[va], wo[va])
            val[name] = {"psnr": _psnr(pred, target[va]), "mae": float(np.mean(np.abs(pred - target[va])))}
    chosen = "uniform" if val and val["uniform"]["mae"] < val["per-texel"]["mae"] else "per-texel"
    return {"maps": maps_of(params if chosen == "per-texel" else mean, r), "iterations": steps, "model": chosen,
            "validation": val,
            "exported_heldout_psnr": _psnr(pred_ho if chosen == "per-texel" else const_ho, target[ho]),
            "constant_heldout_mae": float(np.mean(np.abs(const_ho - target[ho]))),
            "heldout_psnr": _psnr(pred_ho, target[ho]), "heldout_mae": float(np.mean(np.abs(pred_ho - target[ho]))),
            "constant_heldout_psnr": _psnr(const_ho, target[ho]), "train_psnr": _psnr(pred_tr, target[tr][:16])}


def _tile_mesh() -> ExportMesh:
    """A unit tile in the XZ plane (+Y up: a floor sample), UV (0, 0) at its −X, −Z corner."""
    v = np.array([[-0.5, 0, -0.5], [0.5, 0, -0.5], [0.5, 0, 0.5], [-0.5, 0, 0.5]], np.float64)
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float64)
    return ExportMesh(v, np.array([[0, 2, 1], [0, 3, 2]]), uv)


def snippet(basis_name: str, material_name: str) -> str:
    return (f'<!-- photoreal neural material: `import mi_plugins` registers neural_btf -->\n'
            f'<bsdf type="neural_btf" id="{Path(material_name).stem}">\n'
            f'    <string name="basis" value="{basis_name}"/>\n'
            f'    <string name="material" value="{material_name}"/>\n'
            f'    <float name="tiling" value="1"/>\n</bsdf>\n')


def preview(basis_path: Path, mat_path: Path, maps: dict, res: int, spp: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """The neural material and the fitted GGX on the same tile under the bundled sunset HDRI, seen at 45°."""
    from foundation.assets import envmap

    def bitmap(a, raw=True):
        return {"type": "bitmap", "raw": raw, "data": mi.TensorXf(aligned(np.ascontiguousarray(a, np.float32)))}

    bsdfs = {"neural": {"type": "neural_btf", "basis": str(basis_path), "material": str(mat_path)},
             "ggx": {"type": "ggx_uv", "albedo": bitmap(maps["albedo"]),
                     "normal": bitmap(maps["normal"] * 0.5 + 0.5),
                     "roughness": bitmap(maps["roughness"][..., None]), "specular": bitmap(maps["specular"][..., None]),
                     "metallic": bitmap(maps["metallic"][..., None])}}
    out = []
    for name in ("neural", "ggx"):
        scene = mi.load_dict({
            "type": "scene", "integrator": {"type": "path", "max_depth": 2}, "env": envmap("sunset"),
            "tile": {"type": "rectangle", "bsdf": bsdfs[name]},
            "sensor": {"type": "perspective", "fov": 32,
                       "to_world": mi.ScalarTransform4f().look_at(origin=[0, -2.6, 2.6], target=[0, 0, 0],
                                                                  up=[0, 0, 1]),
                       "film": {"type": "hdrfilm", "width": res, "height": res}}})
        out.append(np.array(mi.render(scene, spp=spp, seed=seed))[..., :3])
        del scene
    return out[0], out[1]


def export_material(material: str | Path, out: str | Path, s: ExportSettings | None = None,
                    basis: str | Path | None = None, distil: DistilSettings | None = None, stem: str = "model",
                    show_progress: bool = True) -> MaterialExport:
    """Write ``out/``: the material's XML snippet with copies of its two ``.npz`` files, ``preview.png``, and the
    distilled GGX tile as ``stem.{glb,gltf,obj}``; complete or not at all."""
    from foundation.assets import bundled_basis
    from foundation.files import atomic_dir, write_json, write_text
    from foundation.records import to_json

    s = s or ExportSettings()
    distil = distil or DistilSettings(seed=s.seed)
    t0 = time.perf_counter()
    mat_path = Path(material)
    basis_path = Path(basis) if basis is not None else bundled_basis()
    mat = load_material(mat_path)
    b = load_basis(basis_path)
    check_pair(b, mat, str(basis_path), str(mat_path))
    with atomic_dir(out, "export.json") as tmp:
        fit = distil_ggx(b, mat, distil, checkpoint=tmp / "distil.ckpt.npz", show_progress=show_progress,
                         key=mat_path.name)
        (tmp / "distil.ckpt.npz").unlink(missing_ok=True)
        maps = fit["maps"]
        shutil.copyfile(basis_path, tmp / "basis.npz")
        shutil.copyfile(mat_path, tmp / mat_path.name)
        write_text(tmp / "material.xml", snippet("basis.npz", mat_path.name))
        neural, ggx = preview(tmp / "basis.npz", tmp / mat_path.name, maps, 192, max(s.spp, 32), s.seed)
        imageio.write_png(tmp / "preview.png", np.concatenate([neural, ggx], 1))
        preview_psnr = _psnr(ggx, neural)
        tile = _tile_mesh()
        gm = ExportMaterial(name=mat_path.stem, base_colour=maps["albedo"], normal=maps["normal"],
                            roughness=maps["roughness"], metallic=maps["metallic"], metallic_factor=1.0,
                            specular=maps["specular"])
        files = write_model(tmp, stem, s.format, tile, gm)
        check = reimport_check(files[0], tile, gm, spp=s.spp)
        rec = MaterialExport(kind="material", material=str(mat_path), basis=str(basis_path), format=s.format,
                             files=sorted([p.name for p in files] + ["material.xml", "basis.npz", mat_path.name,
                                                                     "preview.png"]),
                             texture_size=mat.res, model=fit["model"], validation=fit["validation"],
                             exported_heldout_psnr=fit["exported_heldout_psnr"], ggx_heldout_psnr=fit["heldout_psnr"],
                             ggx_heldout_mae=fit["heldout_mae"], constant_heldout_psnr=fit["constant_heldout_psnr"],
                             constant_heldout_mae=fit["constant_heldout_mae"],
                             train_psnr=fit["train_psnr"], preview_psnr=preview_psnr, distil=distil,
                             iterations=fit["iterations"], reimport=check, seconds=time.perf_counter() - t0)
        write_json(tmp / "export.json", to_json(rec))
    return rec


def is_neural_material(path: str | Path) -> bool:
    """A ``.npz`` holding a neural material's feature textures."""
    p = Path(path)
    if not (p.is_file() and p.suffix == ".npz"):
        return False
    try:
        with np.load(p, allow_pickle=False) as z:
            return {"t_off", "t_rgb"} <= set(z.files)
    except Exception:
        return False

