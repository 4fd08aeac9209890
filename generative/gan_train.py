"""Training and evaluation of the GAN refinement stages; joint geometry + GAN training (REAL-DIBS §3, §5, §6).

* :func:`train_gan` — pix2pix (r → i), CycleGAN (unpaired r ↔ i), partial Morph-GAN (m → i)
  and Morph-GAN (r ‖ m → i, eq. 5.2) on seeded random crops; Adam (lr 2e-4, β₁ 0.5, the
  papers' values); a step and a wall-time budget; atomic checkpoints with exact resume
  (model, optimisers, numpy and torch RNG states); a held-out MSE curve against
  training time (evaluation time not counted).
* :func:`train_joint` — thesis §6 "simultaneous training": one loss
  L = L1(m_j, i_j) (eq. 4.3) + L_G(G(r_j ‖ m_j), i_j) (pix2pix: GAN + λ·L1), with
  m_j = R(V, C; c_j) rendered by Mitsuba with AD. The generator is called from
  Dr.Jit through :func:`generative.bridge.drjit_images_to_torch` (``dr.wrap``), so one
  ``dr.backward`` reaches both the vertex parameters (large steps, as inverse/morph.py)
  and G's weights. D is updated in torch on the detached G output.
* :func:`evaluate_model` — held-out image metrics and inference time per image.
"""

from __future__ import annotations

import contextlib
import json
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Iterator, Literal

import numpy as np
import torch

from photoreal import imageio
from photoreal.progress import progress_bar

from .cyclegan import CycleGAN, CycleGANConfig
from .gan_data import PairedViews, random_crops, to_nchw
from .morph_gan import MorphGAN
from .pix2pix import Pix2Pix, Pix2PixConfig

ModelName = Literal["pix2pix", "cyclegan", "morph_gan_partial", "morph_gan"]
MODELS: tuple[str, ...] = ("pix2pix", "cyclegan", "morph_gan_partial", "morph_gan")


@dataclass
class GanTrainSettings:
    model: str = "pix2pix"  #: one of MODELS
    steps: int = 5000  #: upper bound; ``max_seconds`` usually ends the run first
    max_seconds: float | None = 120.0  #: training wall-time budget (summed over resumes); None = steps only
    batch: int = 4
    crop: int = 64  #: random crop side (whole images when ≥ the resolution)
    lr: float = 2e-4
    beta1: float = 0.5
    ngf: int = 16
    ndf: int = 16
    levels: int = 5
    residual: bool = True
    lambda_l1: float = 100.0
    checkpoint_every: int = 25
    eval_every: int = 50  #: steps between held-out MSE curve points
    threads: int = 1  #: torch intra-op threads while training (see :func:`torch_threads`)
    val_every: int = 6  #: every k-th train view is a validation view (not trained on); 0 = no selection
    init_from: str | None = None  #: a finished run folder of the same model: start from its selected G and D
    seed: int = 0

    def __post_init__(self):
        if self.model not in MODELS:
            raise ValueError(f"unknown GAN model {self.model!r}; choose one of {', '.join(MODELS)}")
        if self.steps < 0 or self.batch < 1 or self.crop < 4 or self.lr <= 0:
            raise ValueError(f"GAN training settings out of range: {self}")


@contextlib.contextmanager
def torch_threads(n: int) -> Iterator[None]:
    """Run with ``n`` torch intra-op threads (0 = leave as is), restoring the old count afterwards.

    Measured on this 2-core machine while another job used ~1.3 cores: a tiny
    pix2pix step took 4.2 s with torch's default 2 threads (spin-waiting on a busy
    core) and 0.03 s with 1 thread; hence 1 by default.
    """
    old = torch.get_num_threads()
    if n > 0:
        torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(old)


def build_model(s: GanTrainSettings) -> torch.nn.Module:
    """The model named by ``s.model``, seeded by ``s.seed``."""
    p = Pix2PixConfig(ngf=s.ngf, ndf=s.ndf, levels=s.levels, residual=s.residual, lambda_l1=s.lambda_l1)
    if s.model == "pix2pix":
        return Pix2Pix(p, seed=s.seed)
    if s.model == "cyclegan":
        return CycleGAN(CycleGANConfig(ngf=s.ngf, ndf=s.ndf, residual=s.residual), seed=s.seed)
    return MorphGAN(p, partial=s.model == "morph_gan_partial", seed=s.seed)


def model_input(model: torch.nn.Module, rendered: torch.Tensor, morphed: torch.Tensor) -> torch.Tensor:
    """The generator input of a model: r (pix2pix, CycleGAN), m (partial) or r ‖ m (Morph-GAN)."""
    return model.make_input(rendered, morphed) if isinstance(model, MorphGAN) else rendered


def split_validation(train: list[int], every: int) -> tuple[np.ndarray, np.ndarray]:
    """Train views → (views to train on, validation views): every ``every``-th view validates (0: none)."""
    t = np.asarray(train)
    if every <= 0 or len(t) < 2:
        return t, t[:0]
    sel = np.arange(len(t)) % every == every - 1
    return t[~sel], t[sel]


def _optimisers(model: torch.nn.Module, s: GanTrainSettings) -> tuple[torch.optim.Adam, torch.optim.Adam]:
    if isinstance(model, CycleGAN):
        g = list(model.G.parameters()) + list(model.F_.parameters())
        d = list(model.D_X.parameters()) + list(model.D_Y.parameters())
    else:
        g, d = list(model.G.parameters()), list(model.D.parameters())
    return (torch.optim.Adam(g, lr=s.lr, betas=(s.beta1, 0.999)),
            torch.optim.Adam(d, lr=s.lr, betas=(s.beta1, 0.999)))


def train_step(model: torch.nn.Module, x: torch.Tensor, y: torch.Tensor, opt_g: torch.optim.Optimizer,
               opt_d: torch.optim.Optimizer) -> dict:
    """One D and one G update (pix2pix order: D first; CycleGAN order: G first). x: (B, C, h, w), y: (B, 3, h, w)."""
    if isinstance(model, CycleGAN):
        opt_g.zero_grad(set_to_none=True)
        lg, terms, (fy, fx) = model.generator_loss(x, y)
        lg.backward()
        opt_g.step()
        opt_d.zero_grad(set_to_none=True)
        ld, dterms = model.discriminator_loss(x, y, fy, fx)
        ld.backward()
        opt_d.step()
    else:
        fake = model.G(x)
        opt_d.zero_grad(set_to_none=True)
        ld, dterms = model.discriminator_loss(x, y, fake)
        ld.backward()
        opt_d.step()
        opt_g.zero_grad(set_to_none=True)
        lg, terms = model.generator_loss(x, y, fake)
        lg.backward()
        opt_g.step()
    return {"g": float(lg.detach()), "d": float(ld.detach()), **terms, **dterms}


@torch.no_grad()
def predict(model: torch.nn.Module, rendered: np.ndarray, morphed: np.ndarray) -> tuple[np.ndarray, float]:
    """G on whole views, one at a time, eval mode: (N, H, W, 3) × 2 → (N, H, W, 3), ms per image."""
    was = model.training
    model.eval()
    out = np.empty_like(rendered, dtype=np.float32)
    t0 = time.perf_counter()
    for k in range(len(rendered)):
        x = model_input(model, to_nchw(rendered[k]), to_nchw(morphed[k]))
        out[k] = model(x)[0].permute(1, 2, 0).numpy()
    ms = 1000.0 * (time.perf_counter() - t0) / max(len(rendered), 1)
    model.train(was)
    return out, ms


def mean_metrics(pred: np.ndarray, ref: np.ndarray) -> dict:
    """Mean over views of :func:`photoreal.metrics.image_metrics` (MSE, ME, 1−SSIM, NRMSE, SAM, ꟻLIP, PSNR)."""
    from photoreal.metrics import image_metrics

    per = [image_metrics(p, r) for p, r in zip(pred, ref)]
    return {k: float(np.mean([m[k] for m in per])) for k in per[0]}


def evaluate_model(model: torch.nn.Module, data: PairedViews) -> dict:
    """Held-out metrics of G's output and its inference time (ms per whole image)."""
    ids = data.test
    pred, ms = predict(model, data.rendered[ids], data.morphed[ids])
    return {**mean_metrics(pred, data.photos[ids]), "infer_ms_per_image": ms}


# -- checkpoints -------------------------------------------------------------------------------------------------


def _save(path: Path, blob: dict) -> None:
    with imageio.atomic_path(path, suffix=".pt") as tmp:
        torch.save(blob, tmp)


def _load(path: Path, settings: dict) -> dict | None:
    if not path.is_file():
        return None
    blob = torch.load(path, weights_only=False)
    stored = dict(blob.get("settings") or {})
    for k, v in settings.items():  # options added later with a None default mean the old behaviour
        if k not in stored and v is None:
            stored[k] = None
    if stored != settings:
        raise ValueError(f"{path}: checkpoint was made with other settings; delete it or use the same ones")
    return blob


def _rng_state(rng: np.random.Generator) -> dict:
    return {"numpy": rng.bit_generator.state, "torch": torch.get_rng_state()}


def _set_rng_state(rng: np.random.Generator, st: dict) -> None:
    rng.bit_generator.state = st["numpy"]
    torch.set_rng_state(st["torch"])


# -- two-stage training ------------------------------------------------------------------------------------------


def train_gan(data: PairedViews, out: str | Path, s: GanTrainSettings | None = None, show_progress: bool = True,
              budget_steps: int | None = None) -> dict | None:
    """Train one model; write ``checkpoint.pt`` (resumable) and, when finished, ``metrics.json``.

    ``budget_steps`` stops after that many steps *in this call* with a checkpoint
    written and returns None; calling again with the same settings continues exactly.
    """
    s = s or GanTrainSettings()
    with torch_threads(s.threads):
        return _train_gan(data, Path(out), s, show_progress, budget_steps)


def _train_gan(data: PairedViews, out: Path, s: GanTrainSettings, show_progress: bool,
               budget_steps: int | None) -> dict | None:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(s.seed)
    rng = np.random.default_rng(s.seed)
    model = build_model(s)
    opt_g, opt_d = _optimisers(model, s)
    ckpt = out / "checkpoint.pt"
    sdict = json.loads(json.dumps(asdict(s)))
    blob = _load(ckpt, sdict)
    step, seconds, history, curve, done = 0, 0.0, [], [], False
    best = {"val_mse": float("inf"), "step": 0, "state": None}
    if blob is not None:
        model.load_state_dict(blob["model"])
        opt_g.load_state_dict(blob["opt_g"])
        opt_d.load_state_dict(blob["opt_d"])
        _set_rng_state(rng, blob["rng"])
        step, seconds, history, curve, done = (blob["step"], blob["seconds"], blob["history"], blob["curve"],
                                               blob.get("done", False))
        best = blob["best"]
    elif s.init_from:
        model.load_state_dict(initial_state(s.init_from, s.model))
    model.train()
    train, val = split_validation(data.train, s.val_every)
    x_stack = {"pix2pix": data.rendered, "cyclegan": data.rendered, "morph_gan_partial": data.morphed}.get(s.model)

    def checkpoint():
        _save(ckpt, {"settings": sdict, "model": model.state_dict(), "opt_g": opt_g.state_dict(),
                     "opt_d": opt_d.state_dict(), "rng": _rng_state(rng), "step": step, "seconds": seconds,
                     "history": history, "curve": curve, "done": done, "best": best})

    def mse_on(ids) -> float:
        pred, _ = predict(model, data.rendered[ids], data.morphed[ids])
        return float(np.mean((np.clip(pred, 0, 1) - np.clip(data.photos[ids], 0, 1)) ** 2))

    def curve_point():
        # held-out MSE is recorded for the chart only; model selection uses the validation views.
        point = {"step": step, "seconds": seconds, "heldout_mse": mse_on(data.test)}
        if len(val):
            point["val_mse"] = mse_on(val)
            if point["val_mse"] < best["val_mse"]:
                best.update(val_mse=point["val_mse"], step=step,
                            state={k: v.detach().clone() for k, v in model.state_dict().items()})
        curve.append(point)

    if not curve:
        curve_point()
    stop = s.steps if budget_steps is None else min(s.steps, step + budget_steps)
    with progress_bar(total=s.steps, desc=f"train {s.model} {data.case}", unit="step",
                      disable=not show_progress) as bar:
        bar.update(step)
        while not done and step < stop:
            t0 = time.perf_counter()
            ids = rng.choice(train, size=s.batch, replace=len(train) < s.batch)
            if s.model == "morph_gan":
                r, m, y = random_crops([data.rendered, data.morphed, data.photos], ids, s.crop, rng)
                x = model.make_input(r, m)
            elif s.model == "cyclegan":  # unpaired: photos of other, independently drawn views
                (x,) = random_crops([x_stack], ids, s.crop, rng)
                (y,) = random_crops([data.photos], rng.choice(train, size=s.batch), s.crop, rng)
            else:
                x, y = random_crops([x_stack, data.photos], ids, s.crop, rng)
            losses = train_step(model, x, y, opt_g, opt_d)
            seconds += time.perf_counter() - t0
            step += 1
            history.append(losses)
            bar.update(1)
            bar.set_postfix(g=f"{losses['g']:.3f}", d=f"{losses['d']:.3f}")
            if s.max_seconds is not None and seconds >= s.max_seconds:
                done = True
            if step >= s.steps:
                done = True
            if step % s.eval_every == 0 or done:
                curve_point()
            if step % s.checkpoint_every == 0 or done or step == stop:
                checkpoint()
    if not done:
        return None
    last = evaluate_model(model, data)
    if best["state"] is not None:  # the validation-selected generator is the result; the last one is reported too
        model.load_state_dict(best["state"])
    save_heldout_predictions(out, model, data)
    metrics = {**evaluate_model(model, data), "last": last, "best_step": best["step"] if len(val) else step,
               "train_seconds": seconds, "steps": step, "settings": sdict,
               "train_views": len(train), "val_views": len(val),
               "curve": curve, "loss_first": history[0] if history else None,
               "loss_last": history[-1] if history else None}
    with imageio.atomic_path(out / "metrics.json") as tmp:
        tmp.write_text(json.dumps(metrics, indent=2) + "\n")
    return metrics


def initial_state(run: str | Path, model: str) -> dict:
    """State dict (G and D) a fine-tuning run starts from: the selected weights of a finished run of ``model``."""
    ckpt = Path(run) / "checkpoint.pt"
    if not ckpt.is_file():
        raise FileNotFoundError(f"{ckpt}: no GAN checkpoint to start from (init_from)")
    blob = torch.load(ckpt, weights_only=False)
    got = blob.get("settings", {}).get("model", "joint" if "gan" in blob.get("settings", {}) else None)
    if got != model:
        raise ValueError(f"{ckpt}: init_from holds a {got!r} run, not {model!r}")
    if not blob.get("done", False):
        raise ValueError(f"{ckpt}: init_from run is unfinished; finish it first")
    best = blob.get("best", {}).get("state")
    return best if best is not None else blob["model"]


def save_heldout_predictions(out: Path, model: torch.nn.Module, data: PairedViews,
                             morphed: np.ndarray | None = None) -> Path:
    """G's held-out outputs as ``heldout_pred.npz`` (float16, with the view ids) for per-region errors."""
    ids = data.test
    pred, _ = predict(model, data.rendered[ids], data.morphed[ids] if morphed is None else morphed)
    path = Path(out) / "heldout_pred.npz"
    with imageio.atomic_path(path, suffix=".npz") as tmp:
        np.savez_compressed(tmp, pred=pred.astype(np.float16), ids=np.asarray(ids))
    return path


def load_heldout_predictions(out: str | Path, ids: list[int]) -> np.ndarray:
    path = Path(out) / "heldout_pred.npz"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no saved held-out predictions (train the model to the end first)")
    z = np.load(path, allow_pickle=False)
    if list(z["ids"]) != list(ids):
        raise ValueError(f"{path}: predictions are for views {list(z['ids'])}, not {list(ids)}")
    return z["pred"].astype(np.float32)


def load_trained(out: str | Path) -> tuple[torch.nn.Module, GanTrainSettings]:
    """The model of a training folder (its ``checkpoint.pt``; the validation-selected weights when there are any)."""
    ckpt = Path(out) / "checkpoint.pt"
    if not ckpt.is_file():
        raise FileNotFoundError(f"{ckpt}: no GAN checkpoint (run `photoreal gan train` first)")
    blob = torch.load(ckpt, weights_only=False)
    if "gan" in blob.get("settings", {}):
        raise ValueError(f"{ckpt}: a joint-training run; its held-out metrics are in {ckpt.parent / 'metrics.json'}")
    s = GanTrainSettings(**blob["settings"])
    model = build_model(s)
    best = blob.get("best", {}).get("state")
    model.load_state_dict(best if best is not None else blob["model"])  # the validation-selected G, as metrics.json
    return model, s


# -- joint training (thesis §6) ----------------------------------------------------------------------------------


@dataclass
class JointSettings:
    steps: int = 2000
    max_seconds: float | None = 180.0
    gan: GanTrainSettings = None  # type: ignore[assignment]  # Morph-GAN settings of G and D (model forced)
    morph_weight: float = 1.0  #: weight of the eq. 4.3 term L1(m_j, i_j) in the joint loss
    lambda_: float = 2.0  #: large-steps λ (inverse/morph.py's default)
    lr: float = 0.05  #: × scene size / 10 (positions; uniform Adam on u), as MorphSettings
    lr_colour: float = 0.01
    spp: int = 4
    max_depth: int = 3  #: path length of m_j while training and testing (3 = the paired data's renders);
    #: 2 = direct light only (``direct_projective``), larger = ``prb_projective``
    init_from: str | None = None  #: a finished Morph-GAN run folder: G and D start from its selected weights
    init_mesh: str | None = None  #: a coloured PLY to start from (e.g. a morph run's morphed.ply), not remeshed
    checkpoint_every: int = 25
    eval_every: int = 50
    seed: int = 0

    def __post_init__(self):
        self.gan = replace(self.gan or GanTrainSettings(), model="morph_gan", seed=self.seed)
        if self.steps < 0 or self.spp < 1 or self.morph_weight < 0 or self.max_depth < 2:
            raise ValueError(f"joint settings out of range: {self}")


def train_joint(bench, data: PairedViews, out: str | Path, s: JointSettings | None = None,
                show_progress: bool = True, budget_steps: int | None = None) -> dict | None:
    """Jointly optimise the coarse mesh (V, C) and a Morph-GAN G through one loss (see the module docstring).

    Starts from the benchmark's coarse mesh (isotropically remeshed, as ``run_morph``)
    and a fresh G, or — fine-tuning — from ``init_mesh`` and the G and D of ``init_from``;
    writes ``joint.ply``, ``checkpoint.pt``, ``heldout_pred.npz`` and ``metrics.json``.
    """
    s = s or JointSettings()
    with torch_threads(s.gan.threads):
        return _train_joint(bench, data, Path(out), s, show_progress, budget_steps)


def _train_joint(bench, data: PairedViews, out: Path, s: JointSettings, show_progress: bool,
                 budget_steps: int | None) -> dict | None:
    import drjit as dr
    import mitsuba as mi

    from inverse.morph import _adam_export, _adam_import, _read_ply_colours, morph_scene, remesh
    from inverse.morph_data import ASSETS, sensor_dict, write_ply

    from .bridge import drjit_images_to_torch
    from .gan_data import GanDataSettings, render_mesh_views

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(s.seed)
    rng = np.random.default_rng(s.seed)
    meta = bench.meta
    res, size, fov = meta["settings"]["resolution"], meta["scene_size"], meta["fov"]
    if s.init_mesh:
        if not Path(s.init_mesh).is_file():
            raise FileNotFoundError(f"{s.init_mesh}: no such mesh (init_mesh)")
        v0, f0, c0 = _read_ply_colours(Path(s.init_mesh))
    else:
        v0, f0, c0 = remesh(*_read_ply_colours(bench.coarse))
    model = build_model(s.gan)
    opt_g, opt_d = _optimisers(model, s.gan)
    ckpt = out / "checkpoint.pt"
    sdict = json.loads(json.dumps(asdict(s)))
    blob = _load(ckpt, sdict)
    v, c = v0.copy(), c0.copy()
    step, seconds, history, curve, done, adam = 0, 0.0, [], [], False, {}
    if blob is not None:
        model.load_state_dict(blob["model"])
        opt_g.load_state_dict(blob["opt_g"])
        opt_d.load_state_dict(blob["opt_d"])
        _set_rng_state(rng, blob["rng"])
        v, c, adam = blob["vertices"], blob["colours"], blob["adam"]
        step, seconds, history, curve, done = blob["step"], blob["seconds"], blob["history"], blob["curve"], blob["done"]
    elif s.init_from:
        model.load_state_dict(initial_state(s.init_from, "morph_gan"))
    model.train()

    hdri = ASSETS / "hdri" / f"{meta['hdri']}.exr"
    work_ply = out / ".joint_work.ply"
    write_ply(work_ply, v, f0, c)
    integrator = ({"type": "direct_projective", "sppi": 0} if s.max_depth == 2
                  else {"type": "prb_projective", "max_depth": s.max_depth, "sppi": 0})
    scene = morph_scene(work_ply, "lit", hdri, integrator=integrator)
    params = mi.traverse(scene)
    f_mi = mi.UInt32(np.ascontiguousarray(f0, np.uint32).ravel())
    ls = mi.ad.LargeSteps(mi.Float(np.ascontiguousarray(v0, np.float32).ravel()), f_mi, s.lambda_)
    opt = mi.ad.Adam(lr=s.lr * size / 10.0, uniform=True)
    opt["u"] = ls.to_differential(mi.Float(np.ascontiguousarray(v, np.float32).ravel()))
    opt["c"] = mi.Float(np.ascontiguousarray(c, np.float32).ravel())
    opt.set_learning_rate({"c": s.lr_colour})
    if adam:
        _adam_import(opt, adam)
    photos = {i: mi.TensorXf(np.ascontiguousarray(data.photos[i])) for i in data.train}
    coarse = {i: mi.TensorXf(np.ascontiguousarray(data.rendered[i])) for i in data.train}
    stash: dict = {}

    def generator_terms(r: torch.Tensor, m: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        x = model.make_input(r, m)
        fake = model.G(x)
        stash["x"], stash["fake"], stash["y"] = x.detach(), fake.detach(), y
        loss, terms = model.generator_loss(x, y, fake)
        stash["terms"] = terms
        return loss

    gen = drjit_images_to_torch(generator_terms)

    def mesh_state():
        vv = np.array(dr.detach(ls.from_differential(opt["u"])), np.float64).reshape(-1, 3)
        return vv, np.array(opt["c"], np.float32).reshape(-1, 3)

    def checkpoint():
        vv, cc = mesh_state()
        _save(ckpt, {"settings": sdict, "model": model.state_dict(), "opt_g": opt_g.state_dict(),
                     "opt_d": opt_d.state_dict(), "rng": _rng_state(rng), "vertices": vv, "colours": cc,
                     "adam": _adam_export(opt), "step": step, "seconds": seconds, "history": history,
                     "curve": curve, "done": done})

    train, _ = split_validation(data.train, s.gan.val_every)  # the views two-stage G trains on (no selection here)
    stop = s.steps if budget_steps is None else min(s.steps, step + budget_steps)
    try:
        with progress_bar(total=s.steps, desc=f"joint {data.case}", unit="step", disable=not show_progress) as bar:
            bar.update(step)
            while not done and step < stop:
                t0 = time.perf_counter()
                i = int(rng.choice(train))
                params["mesh.vertex_positions"] = dr.ravel(ls.from_differential(opt["u"]))
                params["mesh.vertex_color"] = opt["c"]
                params.update()
                sensor = mi.load_dict(sensor_dict(meta["cameras"][i], res, fov, sample_border=True))
                img = mi.render(scene, params, sensor=sensor, spp=s.spp, seed=int(s.seed * 7919 + step * 101 + i))
                m = img[..., :3]
                l_morph = dr.mean(dr.abs(m - photos[i]), axis=None)  # eq. 4.3
                opt_g.zero_grad(set_to_none=True)
                total = s.morph_weight * l_morph + gen(coarse[i], m, photos[i])
                dr.backward(total)
                value = float(total.array[0])
                grads_ok = all(np.isfinite(np.array(dr.grad(opt[k]))).all() for k in opt.keys())
                if np.isfinite(value) and grads_ok:
                    opt.step()
                    opt["c"] = dr.clip(opt["c"], 0.0, 1.0)
                    opt_g.step()
                else:
                    for k in opt.keys():
                        dr.set_grad(opt[k], 0)
                opt_d.zero_grad(set_to_none=True)
                ld, dterms = model.discriminator_loss(stash["x"], stash["y"], stash["fake"])
                ld.backward()
                opt_d.step()
                seconds += time.perf_counter() - t0
                step += 1
                history.append({"total": value, "morph_l1": float(l_morph.array[0]), **stash["terms"], **dterms})
                bar.update(1)
                bar.set_postfix(loss=f"{value:.3f}")
                if (s.max_seconds is not None and seconds >= s.max_seconds) or step >= s.steps:
                    done = True
                if step % s.eval_every == 0 or done:
                    curve.append({"step": step, "seconds": seconds, "train_loss": value})
                if step % s.checkpoint_every == 0 or done or step == stop:
                    checkpoint()
    finally:
        del scene, params
        work_ply.unlink(missing_ok=True)
    if not done:
        return None
    vv, cc = mesh_state()
    write_ply(out / "joint.ply", vv, f0, np.clip(cc, 0, 1))
    # At test time G gets m_j from the light transport it was trained on (path, the same max depth), at 32 spp.
    # The mesh-only row uses the paired data's renderer (max depth 3), comparable with the "morphed" row.
    mesh_render = render_mesh_views(out / "joint.ply", bench, data.test, GanDataSettings(), "render joint",
                                    show_progress)
    m_direct = mesh_render if s.max_depth == GanDataSettings().max_depth else render_mesh_views(
        out / "joint.ply", bench, data.test, GanDataSettings(max_depth=s.max_depth), "render joint", show_progress)
    pred, ms = predict(model, data.rendered[data.test], m_direct)
    save_heldout_predictions(out, model, data, morphed=m_direct)
    metrics = {**mean_metrics(pred, data.photos[data.test]), "infer_ms_per_image": ms, "train_seconds": seconds,
               "steps": step, "mesh_only": mean_metrics(mesh_render, data.photos[data.test]), "settings": sdict,
               "curve": curve, "loss_first": history[0] if history else None,
               "loss_last": history[-1] if history else None}
    with imageio.atomic_path(out / "metrics.json") as tmp:
        tmp.write_text(json.dumps(metrics, indent=2) + "\n")
    return metrics
