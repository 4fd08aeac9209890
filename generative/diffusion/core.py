"""The diffusion core every diffusion stage of photoreal shares (seed 000 §3.2–3.3; reused by seeds 002, 003).

* :class:`DiffusionConfig` (``config``) — the architecture and noise schedule as a typed record (it is stored in
  checkpoints, and a checkpoint of another architecture is refused with the fields that differ);
* :class:`ConditionalDiffusion` — a ``diffusers`` ``UNet2DConditionModel`` in pixel space (no Stable
  Diffusion VAE: its weights do not exist offline) whose input is the noisy image concatenated with a
  *local* condition (seed 000: A, I, S, normal, eq. 5's channel concatenation), and whose
  cross-attention reads *global* tokens (pretrained-encoder features projected to the UNet's width)
  or, for classifier-free guidance, a learned null token set;
* :func:`diffusion_loss` — v-prediction (Salimans & Ho 2022): target v = α_t ε − σ_t x₀ through
  ``DDIMScheduler.get_velocity``; the global condition is dropped with probability ``p_uncond``
  (CFG training, Ho & Salimans 2022);
* :func:`sample` — DDIM (η = 0, deterministic given the seed) with classifier-free guidance
  ε̂ = u + w (c − u) applied to the v output, which is linear in (x₀, ε).

The schedulers are diffusers' own; nothing here re-implements one.
"""

from __future__ import annotations


import torch
from torch import nn

from foundation import validate
from foundation.errors import ForeignCheckpointError, UsageError
from .config import PREDICTIONS, SCHEDULES, DiffusionConfig


def make_scheduler(cfg: DiffusionConfig):
    """diffusers' DDIM scheduler for ``cfg`` (used for the training noise and for sampling)."""
    from diffusers import DDIMScheduler

    return DDIMScheduler(num_train_timesteps=cfg.train_timesteps, beta_schedule=cfg.schedule,
                         prediction_type=cfg.prediction, clip_sample=False, set_alpha_to_one=True,
                         timestep_spacing="trailing")  # "trailing": the last step starts at pure noise


class ConditionalDiffusion(nn.Module):
    """UNet2DConditionModel over [noisy image ‖ local condition], cross-attending to global tokens."""

    def __init__(self, cfg: DiffusionConfig, seed: int = 0):
        super().__init__()
        from diffusers import UNet2DConditionModel

        self.cfg = cfg
        torch.manual_seed(seed)
        n = len(cfg.widths)
        attn = [i >= n - cfg.attention_levels for i in range(n)]
        down = tuple("CrossAttnDownBlock2D" if a else "DownBlock2D" for a in attn)
        up = tuple("CrossAttnUpBlock2D" if a else "UpBlock2D" for a in reversed(attn))
        self.unet = UNet2DConditionModel(
            in_channels=cfg.image_channels + cfg.cond_channels, out_channels=cfg.image_channels,
            block_out_channels=cfg.widths, down_block_types=down, up_block_types=up,
            mid_block_type="UNetMidBlock2DCrossAttn" if cfg.attention_levels else None,
            layers_per_block=cfg.layers_per_block, norm_num_groups=cfg.norm_groups,
            # diffusers reads ``attention_head_dim`` as the number of heads (its documented naming quirk)
            cross_attention_dim=cfg.cross_dim, attention_head_dim=tuple(cfg.heads(w) for w in cfg.widths),
            class_embed_type="projection" if cfg.class_dim else None,
            projection_class_embeddings_input_dim=cfg.class_dim or None)
        self.project = nn.Linear(cfg.global_dim, cfg.cross_dim) if cfg.global_dim else None
        # The unconditional branch of CFG attends to these learned tokens (also the "global off" input).
        self.null_tokens = nn.Parameter(torch.randn(1, cfg.global_tokens, cfg.cross_dim) * 0.02)

    def tokens(self, global_cond: torch.Tensor | None, batch: int, drop: torch.Tensor | None = None) -> torch.Tensor:
        """Global condition (B, T, global_dim) → cross-attention tokens (B, T, cross_dim); None or ``drop``
        (a (B,) bool mask) → the null tokens."""
        null = self.null_tokens.expand(batch, -1, -1)
        if global_cond is None or self.project is None:
            return null
        if global_cond.shape[1:] != (self.cfg.global_tokens, self.cfg.global_dim):
            raise UsageError(f"global condition must be (B, {self.cfg.global_tokens}, {self.cfg.global_dim}), "
                             f"got {tuple(global_cond.shape)}")
        tok = self.project(global_cond)
        if drop is not None:
            tok = torch.where(drop.view(-1, 1, 1), null, tok)
        return tok

    def forward(self, noisy: torch.Tensor, t: torch.Tensor, local: torch.Tensor | None, tokens: torch.Tensor,
                class_vec: torch.Tensor | None = None):
        """``class_vec`` (B, class_dim) is added to the time embedding of a model with ``class_dim`` (None = zeros:
        the unconditional input)."""
        x = noisy if local is None or self.cfg.cond_channels == 0 else torch.cat([noisy, local], 1)
        if x.shape[1] != self.cfg.image_channels + self.cfg.cond_channels:
            raise UsageError(f"model input has {x.shape[1]} channels, the model takes "
                             f"{self.cfg.image_channels} + {self.cfg.cond_channels}")
        labels = None
        if self.cfg.class_dim:
            labels = class_vec if class_vec is not None else x.new_zeros(x.shape[0], self.cfg.class_dim)
        return self.unet(x, t, encoder_hidden_states=tokens, class_labels=labels, return_dict=False)[0]


def check_size(cfg: DiffusionConfig, h: int, w: int) -> None:
    if h % cfg.multiple or w % cfg.multiple:
        raise UsageError(f"image size {h}×{w} must divide by {cfg.multiple} (2^(levels−1) of widths {cfg.widths})")


def diffusion_loss(model: ConditionalDiffusion, scheduler, x0: torch.Tensor, local: torch.Tensor | None,
                   global_cond: torch.Tensor | None, generator: torch.Generator, p_uncond: float = 0.1,
                   weight: torch.Tensor | None = None) -> torch.Tensor:
    """One Monte-Carlo estimate of the training loss: MSE to the v (or ε) target at uniform t.

    ``weight`` (B, 1, H, W), optional: per-pixel weights; the loss is then their weighted mean (pixels of weight 0,
    e.g. where the sample is known, teach the model nothing). A batch of zero total weight gives a zero loss.
    """
    b = x0.shape[0]
    check_size(model.cfg, *x0.shape[-2:])
    t = torch.randint(0, model.cfg.train_timesteps, (b,), generator=generator)
    noise = torch.randn(x0.shape, generator=generator, dtype=x0.dtype)
    drop = torch.rand(b, generator=generator) < p_uncond
    noisy = scheduler.add_noise(x0, noise, t)
    target = scheduler.get_velocity(x0, noise, t) if model.cfg.prediction == "v_prediction" else noise
    pred = model(noisy, t, local, model.tokens(global_cond, b, drop))
    if weight is None:
        return torch.mean((pred - target) ** 2)
    w = weight.to(pred.dtype).expand_as(pred)
    return torch.sum(w * (pred - target) ** 2) / torch.clamp(torch.sum(w), min=1.0)


def _known_zero(out: torch.Tensor, x: torch.Tensor, t, sch, mask: torch.Tensor, prediction: str) -> torch.Tensor:
    """Model output → the output whose x̂₀ is 0 where ``mask`` is 0 (samples known to be zero there), with ε̂ taken
    consistent with x_t = α x̂₀ + σ ε̂ — the deterministic form of inpainting a known region: those pixels follow the
    trajectory of x₀ = 0 and the rest is the model's."""
    a = sch.alphas_cumprod[int(t)].to(x.dtype)
    al, sg = a.sqrt(), (1 - a).sqrt()
    x0 = al * x - sg * out if prediction == "v_prediction" else (x - sg * out) / al
    x0 = x0 * mask
    eps = (x - al * x0) / sg
    return al * eps - sg * x0 if prediction == "v_prediction" else eps


@torch.no_grad()
def sample(model: ConditionalDiffusion, local: torch.Tensor | None, global_cond: torch.Tensor | None,
           shape: tuple[int, int, int, int], steps: int = 20, guidance: float = 1.0, seed: int = 0,
           progress=None, known_zero: torch.Tensor | None = None) -> torch.Tensor:
    """DDIM sampling (η = 0) with classifier-free guidance ``guidance`` (1 = conditional only, 0 = unconditional).

    ``shape`` = (B, C, H, W); returns x₀ in the model's space. Deterministic given ``seed``. ``known_zero``
    (B, 1, H, W), optional: 0 where x₀ is known to be 0 — every step's x̂₀ is held there (:func:`_known_zero`).
    """
    validate.integer("steps", steps, 1, model.cfg.train_timesteps)
    validate.non_negative("guidance", guidance)
    check_size(model.cfg, shape[2], shape[3])
    was = model.training
    model.eval()
    sch = make_scheduler(model.cfg)
    sch.set_timesteps(steps)
    g = torch.Generator().manual_seed(int(seed))
    x = torch.randn(shape, generator=g)
    b = shape[0]
    cond = model.tokens(global_cond, b)
    use_cfg = global_cond is not None and model.project is not None and guidance != 1.0
    uncond = model.tokens(None, b) if use_cfg else None
    for t in sch.timesteps:
        tt = torch.full((b,), int(t), dtype=torch.long)
        if use_cfg:  # one batched pass for both branches
            out = model(torch.cat([x, x]), torch.cat([tt, tt]), None if local is None else torch.cat([local, local]),
                        torch.cat([cond, uncond]))
            c, u = out.chunk(2)
            out = u + guidance * (c - u)
        else:
            out = model(x, tt, local, cond)
        if known_zero is not None:
            out = _known_zero(out, x, t, sch, known_zero, model.cfg.prediction)
        x = sch.step(out, t, x, eta=0.0).prev_sample
        if progress is not None:
            progress(1)
    model.train(was)
    return x


class OptimizerStage:
    """Mixin for a :class:`foundation.loop.Stage` with one torch ``model``, one optimiser ``opt``, a numpy ``rng`` and
    optionally a torch generator ``gen``: ``backward`` a loss into a :class:`StepResult` (the loop applies the step only
    when the loss and every gradient are finite), and the checkpoint state of all four.

    With ``ema_decay`` > 0 (set by the stage; call :meth:`start_ema` after building the model) it also keeps an
    exponential moving average of the weights, saved as the checkpoint's ``ema`` entry (what sampling loads)."""

    model: nn.Module
    opt: torch.optim.Optimizer
    ema_decay: float = 0.0
    ema: dict | None = None

    def start_ema(self, decay: float) -> None:
        self.ema_decay = float(decay)
        self.ema = {k: v.detach().clone() for k, v in self.model.state_dict().items()} if decay else None

    def backward(self, loss: torch.Tensor):
        from foundation.loop import StepResult, all_finite

        self.opt.zero_grad(set_to_none=True)
        loss.backward()
        value = float(loss.detach())
        return StepResult(value, all_finite(value, *[p.grad for p in self.model.parameters() if p.grad is not None]))

    def apply(self, it: int) -> None:
        self.opt.step()
        if self.ema is not None:  # warm-up (1 + it)/(10 + it) so the average forgets the initialisation early
            d = min(self.ema_decay, (1.0 + it) / (10.0 + it))
            with torch.no_grad():
                for k, v in self.model.state_dict().items():
                    self.ema[k].lerp_(v, 1.0 - d) if v.is_floating_point() else self.ema[k].copy_(v)

    def discard(self, it: int) -> None:
        self.opt.zero_grad(set_to_none=True)

    def state(self) -> dict:
        """The model, the optimiser, the numpy ``rng`` and, when the stage has one, the torch generator ``gen``."""
        import numpy as np

        from foundation.loop import rng_state
        from foundation.optim_state import optimizer_state

        tree = {"model": self.model.state_dict(), "opt": optimizer_state(self.opt), "rng": rng_state(self.rng)}
        if getattr(self, "gen", None) is not None:
            tree["gen"] = np.asarray(self.gen.get_state().numpy())
        if self.ema is not None:
            tree["ema"] = self.ema
        return tree

    def load_state(self, tree: dict) -> None:
        import numpy as np

        from foundation.loop import set_rng_state
        from foundation.optim_state import load_optimizer_state

        self.model.load_state_dict(tree["model"])
        load_optimizer_state(self.opt, tree["opt"], f"{getattr(self, 'name', 'training')} optimizer")
        set_rng_state(self.rng, tree["rng"])
        if getattr(self, "gen", None) is not None:
            self.gen.set_state(torch.as_tensor(np.asarray(tree["gen"]), dtype=torch.uint8))
        if self.ema is not None:
            live = self.model.state_dict()
            self.ema = {k: torch.as_tensor(v).to(live[k].device).clone() for k, v in tree["ema"].items()}


def torch_device(name: str) -> str:
    """``name`` checked as a torch device that exists here (``cpu``, ``cuda``, ``cuda:1``, ``mps``), by name."""
    try:
        dev = torch.device(name)
    except (RuntimeError, TypeError):
        raise UsageError(f"--device {name!r}: not a torch device name (cpu, cuda, cuda:N, mps)") from None
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise UsageError(f"--device {name}: torch sees no CUDA device here (torch {torch.__version__})")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise UsageError(f"--device {name}: only {torch.cuda.device_count()} CUDA device(s)")
    elif dev.type == "mps" and not torch.backends.mps.is_available():
        raise UsageError(f"--device {name}: torch sees no MPS device here")
    elif dev.type not in ("cpu", "cuda", "mps"):
        raise UsageError(f"--device {name}: only cpu, cuda and mps are supported")
    return str(dev)


def train_stage(make_stage, out, s, budget_steps: int | None, show_progress: bool, metrics: bool = True):
    """Build a stage with ``s.threads`` torch threads and run it on the shared loop in folder ``out``
    (``checkpoint.npz``; ``metrics.json`` when ``metrics``) with ``s``'s steps / max_seconds / checkpoint_every.
    Returns (stage, the loop's result or None when ``budget_steps`` ended the call)."""
    from pathlib import Path

    from foundation.loop import LoopSettings, run_loop
    from foundation.threads import torch_threads

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    with torch_threads(s.threads):
        stage = make_stage()
        loop = LoopSettings(steps=s.steps, max_seconds=s.max_seconds, checkpoint_every=s.checkpoint_every)
        return stage, run_loop(stage, loop, checkpoint=out / "checkpoint.npz", budget_steps=budget_steps,
                               show_progress=show_progress, metrics_path=out / "metrics.json" if metrics else None)


def load_trained(run, stage_kind: str, what: str, hint: str, settings_cls, build, defaults: dict | None = None,
                 weights: str = "model"):
    """The trained model of a run folder in eval mode, and its settings: the checkpoint's stage kind must be
    ``stage_kind`` and its weights must fit ``build(settings)``; errors name the file. ``defaults`` fill
    settings fields that older checkpoints lack. ``weights`` names the checkpoint entry to load (e.g. an EMA);
    a checkpoint without it gives its raw ``model`` weights."""
    from pathlib import Path

    from foundation.errors import CheckpointError
    from foundation.loop import read_checkpoint
    from foundation.records import from_json

    ckpt = Path(run) / "checkpoint.npz"
    if not ckpt.is_file():
        raise UsageError(f"{ckpt}: no {what} checkpoint{hint}")
    saved = read_checkpoint(ckpt)
    if saved.kind != stage_kind:
        raise ForeignCheckpointError(f"{ckpt}: a {saved.kind} checkpoint, not a {what}'s")
    s = from_json(settings_cls, {**(defaults or {}), **saved.fingerprint["settings"]}, str(ckpt))
    model = build(s)
    state = saved.stage.get(weights) or saved.stage.get("model")
    if state is None:
        raise CheckpointError(f"{ckpt}: holds no model weights (entries: {sorted(saved.stage)})")
    try:
        model.load_state_dict(state)
    except RuntimeError as exc:
        raise CheckpointError(f"{ckpt}: weights do not fit the architecture its settings describe "
                              f"({str(exc).splitlines()[0]})") from None
    model.eval()
    return model, s


def count_parameters(model: nn.Module) -> int:
    return int(sum(p.numel() for p in model.parameters()))


def training_flops(model: ConditionalDiffusion, batch: int, size: int) -> float:
    """FLOPs of one training step (forward + backward) counted by torch's FlopCounterMode."""
    from torch.utils.flop_counter import FlopCounterMode

    cfg = model.cfg
    x = torch.randn(batch, cfg.image_channels, size, size)
    local = torch.randn(batch, cfg.cond_channels, size, size) if cfg.cond_channels else None
    g = torch.randn(batch, cfg.global_tokens, cfg.global_dim) if cfg.global_dim else None
    t = torch.randint(0, cfg.train_timesteps, (batch,))
    with FlopCounterMode(display=False) as fc:
        out = model(x, t, local, model.tokens(g, batch))
        out.square().mean().backward()
    model.zero_grad(set_to_none=True)
    return float(fc.get_total_flops())


__all__ = ["ConditionalDiffusion", "DiffusionConfig", "OptimizerStage", "load_trained", "torch_device", "train_stage", "PREDICTIONS", "SCHEDULES", "check_size", "count_parameters",
           "diffusion_loss", "make_scheduler", "sample", "training_flops"]
