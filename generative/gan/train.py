"""Training and evaluation of the GAN refinement stages (REAL-DIBS §3, §5).

* :func:`train_gan` — pix2pix (r → i), CycleGAN (unpaired r ↔ i), partial Morph-GAN (m → i)
  and Morph-GAN (r ‖ m → i, eq. 5.2) on seeded random crops; Adam (lr 2e-4, β₁ 0.5, the
  papers' values); a step and a wall-time budget, checkpoints and exact resume through the
  shared loop (:mod:`foundation.loop`; model, optimisers, numpy and torch RNG states); a held-out
  MSE curve against training time (evaluation time not counted) and model selection on
  validation views (never on held-out views).
* :func:`evaluate_model` — held-out image metrics and inference time per image.

Joint geometry + GAN training (thesis §6) is in :mod:`generative.gan.joint`.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from foundation.errors import CheckpointError, UsageError
from foundation.files import atomic_path
from foundation.loop import (LoopSettings, RunState, Stage, StepResult, TrainingSummary, all_finite, read_checkpoint,
                             rng_state, run_loop, set_rng_state)
from foundation.metrics import ImageMetrics, image_metrics
from foundation.optim_state import load_optimizer_state, optimizer_state
from foundation.records import from_json
from foundation.threads import torch_threads

from .cyclegan import CycleGAN, CycleGANConfig
from .data import PairedViews, random_crops, to_nchw
from .morph_gan import MorphGAN
from .pix2pix import Pix2Pix, Pix2PixConfig
from .settings import GanTrainSettings


def check_resolution(res: int, s: GanTrainSettings) -> None:
    """The U-Net halves the image ``levels`` times: whole views must divide by 2^levels (checked before training)."""
    if s.model != "cyclegan" and res % (1 << s.levels):
        raise UsageError(f"the benchmark's {res}² views do not divide by 2^levels = {1 << s.levels} "
                         f"(the U-Net's depth); make the benchmark at a multiple of {1 << s.levels} px")
    if s.crop < res and s.crop % (1 << s.levels) and s.model != "cyclegan":
        raise UsageError(f"crop = {s.crop} must divide by 2^levels = {1 << s.levels}")


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


def _grads(opt: torch.optim.Optimizer):
    return [p.grad for group in opt.param_groups for p in group["params"]]


class GANUpdate:
    """One D and one G update, split for the loop's NaN policy (pix2pix order: D first; CycleGAN: G first).

    :meth:`compute` runs everything up to G's optimiser step; a D update whose loss or gradients are
    not finite is skipped there, and a non-finite G update is reported so that the loop skips it
    (:meth:`apply` / :meth:`discard`). x: (B, C, h, w), y: (B, 3, h, w).
    """

    def __init__(self, model: torch.nn.Module, opt_g: torch.optim.Optimizer, opt_d: torch.optim.Optimizer):
        self.model, self.opt_g, self.opt_d = model, opt_g, opt_d
        self.pending: tuple | None = None

    def compute(self, x: torch.Tensor, y: torch.Tensor) -> StepResult:
        model, opt_g, opt_d = self.model, self.opt_g, self.opt_d
        if isinstance(model, CycleGAN):
            opt_g.zero_grad(set_to_none=True)
            lg, terms, fakes = model.generator_loss(x, y)
            lg.backward()
            self.pending = (x, y, fakes)
            ok = all_finite(float(lg.detach()), *_grads(opt_g))
            return StepResult(float(lg.detach()), ok, log={"g": float(lg.detach()), **terms})
        fake = model.G(x)
        opt_d.zero_grad(set_to_none=True)
        ld, dterms = model.discriminator_loss(x, y, fake)
        ld.backward()
        d_ok = all_finite(float(ld.detach()), *_grads(opt_d))
        if d_ok:
            opt_d.step()
        opt_g.zero_grad(set_to_none=True)
        lg, terms = model.generator_loss(x, y, fake)
        lg.backward()
        ok = d_ok and all_finite(float(lg.detach()), *_grads(opt_g))
        return StepResult(float(lg.detach()), ok, log={"g": float(lg.detach()), "d": float(ld.detach()), **terms, **dterms})

    def apply(self) -> dict:
        self.opt_g.step()
        if self.pending is not None:  # CycleGAN: D after G, on the fakes of the G step
            x, y, (fy, fx) = self.pending
            self.pending = None
            self.opt_d.zero_grad(set_to_none=True)
            ld, dterms = self.model.discriminator_loss(x, y, fy, fx)
            ld.backward()
            if all_finite(float(ld.detach()), *_grads(self.opt_d)):
                self.opt_d.step()
            return {"d": float(ld.detach()), **dterms}
        return {}

    def discard(self) -> None:
        self.pending = None
        self.opt_g.zero_grad(set_to_none=True)
        self.opt_d.zero_grad(set_to_none=True)


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


def mean_metrics(pred: np.ndarray, ref: np.ndarray) -> ImageMetrics:
    """Mean over views of :func:`foundation.metrics.image_metrics` (MSE, ME, 1−SSIM, NRMSE, SAM, ꟻLIP, PSNR)."""
    return ImageMetrics.mean([image_metrics(p, r) for p, r in zip(pred, ref)])


@dataclass
class GanEvaluation(ImageMetrics):
    """Held-out image metrics of G's output and its inference time."""

    infer_ms_per_image: float = 0.0


def evaluate_model(model: torch.nn.Module, data: PairedViews) -> GanEvaluation:
    """Held-out metrics of G's output and its inference time (ms per whole image)."""
    ids = data.test
    pred, ms = predict(model, data.rendered[ids], data.morphed[ids])
    return GanEvaluation(**vars(mean_metrics(pred, data.photos[ids])), infer_ms_per_image=ms)


# -- two-stage training ------------------------------------------------------------------------------------------


@dataclass
class CurvePoint:
    step: int
    seconds: float  #: training time so far
    heldout_mse: float  #: for the chart only; selection uses the validation views
    val_mse: float | None = None


@dataclass
class GanTrainResult:
    """``metrics.json`` of a GAN training run."""

    heldout: GanEvaluation  #: the validation-selected generator (the run's result)
    last: GanEvaluation  #: the last generator
    best_step: int
    settings: GanTrainSettings
    train_views: int
    val_views: int
    curve: list[CurvePoint]
    training: TrainingSummary


class GANStage(Stage):
    """Seeded crops of the paired views → one D and one G update per step (see :class:`GANUpdate`)."""

    unit = "step"

    def __init__(self, data: PairedViews, out: Path, s: GanTrainSettings):
        self.data, self.out, self.s = data, out, s
        self.name = f"train {s.model} {data.case}"
        check_resolution(data.resolution, s)
        torch.manual_seed(s.seed)
        self.rng = np.random.default_rng(s.seed)
        self.model = build_model(s)
        self.opt_g, self.opt_d = _optimisers(self.model, s)
        if s.init_from:
            self.model.load_state_dict(initial_state(s.init_from, s.model))
        self.model.train()
        self.update = GANUpdate(self.model, self.opt_g, self.opt_d)
        self.train, self.val = split_validation(data.train, s.val_every)
        self.x_stack = {"pix2pix": data.rendered, "cyclegan": data.rendered, "morph_gan_partial": data.morphed}.get(s.model)
        self.curve: list[CurvePoint] = []
        self.best = {"val_mse": float("inf"), "step": 0, "state": None}

    @property
    def kind(self) -> str:
        return f"GANStage/{self.s.model}"

    def fingerprint(self) -> dict:
        return {"settings": self.s, "data": self.data.digest()}

    def state(self) -> dict:
        return {"model": self.model.state_dict(), "opt_g": optimizer_state(self.opt_g),
                "opt_d": optimizer_state(self.opt_d), "rng": rng_state(self.rng), "torch_rng": torch.get_rng_state(),
                "curve": [asdict(c) for c in self.curve], "best": dict(self.best)}

    def load_state(self, tree: dict) -> None:
        self.model.load_state_dict(tree["model"])
        load_optimizer_state(self.opt_g, tree["opt_g"], "generator optimizer")
        load_optimizer_state(self.opt_d, tree["opt_d"], "discriminator optimizer")
        set_rng_state(self.rng, tree["rng"])
        torch.set_rng_state(tree["torch_rng"])
        self.curve = [CurvePoint(**c) for c in tree["curve"]]
        self.best = dict(tree["best"])

    def _mse_on(self, ids) -> float:
        d = self.data
        pred, _ = predict(self.model, d.rendered[ids], d.morphed[ids])
        return float(np.mean((np.clip(pred, 0, 1) - np.clip(d.photos[ids], 0, 1)) ** 2))

    def _curve_point(self, run: RunState) -> None:
        point = CurvePoint(run.step, run.train_seconds, self._mse_on(self.data.test))
        if len(self.val):
            point.val_mse = self._mse_on(self.val)
            if point.val_mse < self.best["val_mse"]:
                self.best.update(val_mse=point.val_mse, step=run.step,
                                 state={k: v.detach().clone() for k, v in self.model.state_dict().items()})
        self.curve.append(point)

    def start(self, run: RunState) -> None:
        if not self.curve:
            self._curve_point(run)

    def step(self, it: int) -> StepResult:
        s, d, rng = self.s, self.data, self.rng
        ids = rng.choice(self.train, size=s.batch, replace=len(self.train) < s.batch)
        if s.model == "morph_gan":
            r, m, y = random_crops([d.rendered, d.morphed, d.photos], ids, s.crop, rng)
            x = self.model.make_input(r, m)
        elif s.model == "cyclegan":  # unpaired: photos of other, independently drawn views
            (x,) = random_crops([self.x_stack], ids, s.crop, rng)
            (y,) = random_crops([d.photos], rng.choice(self.train, size=s.batch), s.crop, rng)
        else:
            x, y = random_crops([self.x_stack, d.photos], ids, s.crop, rng)
        return self.update.compute(x, y)

    def apply(self, it: int) -> None:
        self.update.apply()

    def discard(self, it: int) -> None:
        self.update.discard()

    def after_step(self, it: int, run: RunState) -> None:
        if run.step % self.s.eval_every == 0 or run.done:
            self._curve_point(run)

    def finish(self, run: RunState) -> GanTrainResult:
        last = evaluate_model(self.model, self.data)
        if self.best["state"] is not None:  # the validation-selected generator is the result; the last one is reported too
            self.model.load_state_dict(self.best["state"])
        save_heldout_predictions(self.out, self.model, self.data)
        return GanTrainResult(evaluate_model(self.model, self.data), last,
                              self.best["step"] if len(self.val) else run.step, self.s, len(self.train),
                              len(self.val), list(self.curve), run.summary())


def train_gan(data: PairedViews, out: str | Path, s: GanTrainSettings | None = None, show_progress: bool = True,
              budget_steps: int | None = None) -> GanTrainResult | None:
    """Train one model; write ``checkpoint.npz`` (resumable) and, when finished, ``metrics.json``.

    ``budget_steps`` stops after that many steps *in this call* with a checkpoint
    written and returns None; calling again with the same settings continues exactly.
    A finished run called again re-evaluates and re-writes its outputs without training.
    """
    s = s or GanTrainSettings()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    with torch_threads(s.threads):
        stage = GANStage(data, out, s)
        loop = LoopSettings(steps=s.steps, max_seconds=s.max_seconds, checkpoint_every=s.checkpoint_every)
        return run_loop(stage, loop, checkpoint=out / "checkpoint.npz", budget_steps=budget_steps,
                        show_progress=show_progress, metrics_path=out / "metrics.json")


def _finished_run(run: str | Path) -> tuple[Path, "object"]:
    ckpt = Path(run) / "checkpoint.npz"
    if not ckpt.is_file():
        raise UsageError(f"{ckpt}: no GAN checkpoint (train with `photoreal gan train` first)")
    return ckpt, read_checkpoint(ckpt)


def initial_state(run: str | Path, model: str) -> dict:
    """State dict (G and D) a fine-tuning run starts from: the selected weights of a finished run of ``model``."""
    ckpt, saved = _finished_run(run)
    got = saved.kind.split("/", 1)[1] if saved.kind.startswith("GANStage/") else \
        ("joint" if saved.kind == "JointStage" else saved.kind)
    if got != model:
        raise UsageError(f"{ckpt}: init_from holds a {got!r} run, not {model!r}")
    if not saved.done:
        raise UsageError(f"{ckpt}: init_from run is unfinished; finish it first")
    best = saved.stage.get("best", {}).get("state")
    return best if best is not None else saved.stage["model"]


def save_heldout_predictions(out: Path, model: torch.nn.Module, data: PairedViews,
                             morphed: np.ndarray | None = None) -> Path:
    """G's held-out outputs as ``heldout_pred.npz`` (float16, with the view ids) for per-region errors."""
    ids = data.test
    pred, _ = predict(model, data.rendered[ids], data.morphed[ids] if morphed is None else morphed)
    path = Path(out) / "heldout_pred.npz"
    with atomic_path(path, suffix=".npz") as tmp:
        np.savez_compressed(tmp, pred=pred.astype(np.float16), ids=np.asarray(ids))
    return path


def load_heldout_predictions(out: str | Path, ids: list[int]) -> np.ndarray:
    path = Path(out) / "heldout_pred.npz"
    if not path.is_file():
        raise UsageError(f"{path}: no saved held-out predictions (train the model to the end first)")
    with np.load(path, allow_pickle=False) as z:
        if list(z["ids"]) != list(ids):
            raise UsageError(f"{path}: predictions are for views {list(z['ids'])}, not {list(ids)}")
        return z["pred"].astype(np.float32)


def load_trained(out: str | Path) -> tuple[torch.nn.Module, GanTrainSettings]:
    """The model of a training folder (its checkpoint; the validation-selected weights when there are any)."""
    ckpt, saved = _finished_run(out)
    if not saved.kind.startswith("GANStage/"):
        raise UsageError(f"{ckpt}: a {saved.kind} run, not a two-stage GAN; its held-out metrics are in "
                         f"{ckpt.parent / 'metrics.json'}")
    s = from_json(GanTrainSettings, saved.fingerprint["settings"], str(ckpt))
    model = build_model(s)
    best = saved.stage.get("best", {}).get("state")
    try:
        model.load_state_dict(best if best is not None else saved.stage["model"])  # the validation-selected G
    except RuntimeError as exc:
        raise CheckpointError(f"{ckpt}: weights do not fit a {s.model} of these settings ({str(exc).splitlines()[0]})") from None
    return model, s
