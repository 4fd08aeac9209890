"""The one resumable training loop: every optimisation and training stage of photoreal runs through it.

A stage (:class:`Stage`) says how to take one step and what its state is; :func:`run_loop` owns the rest:

* **budgets** — a step budget and a training-time budget (summed over resumes), plus a per-call step
  budget (``budget_steps``: a cluster job's slice) after which it checkpoints and returns ``None``;
* **checkpoints** — atomic (:mod:`foundation.checkpoint`), every ``checkpoint_every`` steps, at the end
  and when a budget is used up; they hold the stage's state, the loop's counters and a fingerprint of
  the settings and data, and a checkpoint of other settings is refused with the fields that differ;
* **exact resume** — the stage saves everything its next step depends on (parameters, optimiser
  state through :mod:`foundation.optim_state`, RNG states): interrupted + resumed = uninterrupted;
* **one NaN/Inf policy** — a step whose loss or gradients are not finite is not applied (the stage's
  :meth:`Stage.discard`), it is counted (``skipped_steps``), and ``max_nonfinite`` such steps in a row
  stop the run with :class:`~foundation.errors.NonFiniteError` naming the stage and the step;
* **one progress bar** and **the metrics JSON** (the stage's :meth:`Stage.finish` result, a typed
  record that includes the loop's :class:`TrainingSummary`).

Evaluation inside the run (held-out curves, model selection) happens in :meth:`Stage.after_step`,
outside the timed part, so time budgets count training only; there a stage may end the run early by
setting ``run.stopped`` (convergence on a validation loss), which a resumed run keeps.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .checkpoint import load_tree, save_tree
from .errors import CheckpointError, ForeignCheckpointError, NonFiniteError, UsageError
from .files import finite_or_none, write_json
from .progress import progress_bar
from .records import to_json


@dataclass
class LoopSettings:
    steps: int  #: the run ends after this many steps in all (over resumes) ...
    max_seconds: float | None = None  #: ... or after this much training time (summed over resumes)
    checkpoint_every: int = 20  #: steps between checkpoints (plus one at the end and at a budget's end)
    max_nonfinite: int = 10  #: this many non-finite steps in a row stop the run with NonFiniteError
    log_every: int = 1  #: steps between entries of the per-step log (the loss of every step is kept)

    def __post_init__(self):
        if isinstance(self.steps, bool) or not isinstance(self.steps, (int, np.integer)) or self.steps < 0:
            raise UsageError(f"steps must be an integer ≥ 0, got {self.steps!r}")
        if self.max_seconds is not None and not (math.isfinite(self.max_seconds) and self.max_seconds > 0):
            raise UsageError(f"max_seconds must be > 0 (or None: no time budget), got {self.max_seconds}")
        if self.checkpoint_every < 1 or self.max_nonfinite < 1 or self.log_every < 1:
            raise UsageError(f"checkpoint_every, max_nonfinite and log_every must be ≥ 1, got "
                             f"{self.checkpoint_every}, {self.max_nonfinite}, {self.log_every}")


@dataclass
class StepResult:
    loss: float  #: the step's scalar loss (its history is kept)
    finite: bool = True  #: False when the stage saw NaN/Inf in its loss or gradients
    log: dict = field(default_factory=dict)  #: other scalars of the step, kept every ``log_every`` steps


@dataclass
class TrainingSummary:
    """The loop's account of a finished run (part of every stage's result)."""

    steps: int
    train_seconds: float  #: time in steps, summed over resumes (evaluation not counted)
    skipped_steps: int  #: non-finite steps that were not applied
    loss_first: float | None
    loss_last: float | None


@dataclass
class RunState:
    """The loop's own counters; checkpointed with the stage's state."""

    step: int = 0
    train_seconds: float = 0.0
    skipped_steps: int = 0
    nonfinite_in_a_row: int = 0
    losses: list = field(default_factory=list)
    log: list = field(default_factory=list)
    done: bool = False  #: a budget is used up (set before ``after_step``)
    #: the stage ended the run early (set in its ``after_step``: e.g. its validation loss stopped improving); a
    #: resumed run stays ended
    stopped: bool = False

    def to_tree(self) -> dict:
        d = asdict(self)
        d["losses"] = np.asarray(self.losses, np.float64)
        return d

    @classmethod
    def from_tree(cls, d: dict) -> "RunState":
        d = dict(d)
        d["losses"] = [float(x) for x in np.asarray(d["losses"]).ravel()]
        return cls(**d)

    def summary(self) -> TrainingSummary:
        finite = [x for x in self.losses if math.isfinite(x)]
        return TrainingSummary(self.step, self.train_seconds, self.skipped_steps,
                               finite_or_none(finite[0]) if finite else None,
                               finite_or_none(finite[-1]) if finite else None)


class Stage:
    """What a training or optimisation stage tells :func:`run_loop`. Override :meth:`step` at least."""

    name: str = "train"  #: progress bar label and error messages
    unit: str = "it"

    @property
    def kind(self) -> str:
        """What a checkpoint of this stage is a checkpoint of (a checkpoint of another kind is refused)."""
        return type(self).__name__

    def fingerprint(self) -> dict:
        """What a checkpoint must match to be resumed (settings, input digests), JSON-able."""
        return {}

    def fingerprint_against(self, saved: dict) -> dict:
        """:meth:`fingerprint` as compared with a checkpoint's ``saved`` one: a stage may carry over a saved value of
        a setting that, for its input, decides nothing differently (and the run goes on under that fingerprint)."""
        return self.fingerprint()

    def state(self) -> dict:
        """Everything the next step depends on, as a checkpoint tree (numpy / torch / plain values)."""
        return {}

    def load_state(self, tree: dict) -> None:
        """Restore :meth:`state`."""

    def start(self, run: RunState) -> None:
        """Once per call, after any resume and before the first step (untimed)."""

    def step(self, it: int) -> StepResult:
        """Compute step ``it``'s loss and gradients; apply nothing yet (see :meth:`apply`)."""
        raise NotImplementedError

    def apply(self, it: int) -> None:
        """Take the optimiser step of ``it`` (only called when its result was finite)."""

    def discard(self, it: int) -> None:
        """Drop the gradients of a non-finite step ``it`` (nothing of it is applied)."""

    def after_step(self, it: int, run: RunState) -> None:
        """Bookkeeping after step ``it`` (held-out curves, selection, remeshing); not timed."""

    def finish(self, run: RunState) -> Any:
        """The run is complete: write outputs, return the result (a dataclass holding ``run.summary()``)."""
        return run.summary()


class DrJitStage(Stage):
    """A stage whose parameters live in a Dr.Jit optimiser ``self.opt`` (``mi.ad.Adam`` / ``dr.opt``)."""

    opt: Any

    def grads_finite(self) -> bool:
        import drjit as dr

        return all_finite(*(dr.grad(self.opt[k]) for k in self.opt.keys()))

    def result(self, loss, log: dict | None = None) -> StepResult:
        """The step's result after ``dr.backward(loss)``: loss and gradients evaluated in one launch.

        Reading the loss alone first would evaluate the forward pass on its own, and the optimiser step
        would then run it again inside the backward kernel (measured: a face-fit step took ~15 % longer).
        """
        import drjit as dr

        grads = [dr.grad(self.opt[k]) for k in self.opt.keys()]
        dr.eval(loss, *grads)
        value = float(loss.array[0]) if hasattr(loss, "array") else float(loss[0])
        return StepResult(value, all_finite(*grads), log=log or {})

    def apply(self, it: int) -> None:
        self.opt.step()

    def discard(self, it: int) -> None:
        import drjit as dr

        for k in self.opt.keys():
            dr.set_grad(self.opt[k], 0)


class TorchStage(Stage):
    """A stage whose parameters live in a torch optimiser ``self.opt``."""

    opt: Any

    def grads_finite(self) -> bool:
        return all_finite(*(p.grad for group in self.opt.param_groups for p in group["params"]))

    def apply(self, it: int) -> None:
        self.opt.step()

    def discard(self, it: int) -> None:
        self.opt.zero_grad()


def all_finite(*values: Any) -> bool:
    """True when every value (float, numpy array, torch tensor, Dr.Jit array, or None) is finite.

    Arrays are reduced to their sums first — a NaN or Inf anywhere makes the sum non-finite — and the
    Dr.Jit sums are evaluated in one go, so the check costs one synchronisation per step, not one per
    parameter (it was 30 % of a face-fit step when each gradient was checked on its own).
    """
    drjit_sums, torch_sums = [], []
    for v in values:
        if v is None:
            continue
        if isinstance(v, (int, float)):
            if not math.isfinite(v):
                return False
            continue
        mod = type(v).__module__
        if mod.startswith("torch"):
            torch_sums.append(v.detach().sum())
        elif mod.startswith(("drjit", "mitsuba")):
            import drjit as dr

            drjit_sums.append(dr.sum(v, axis=None))
        elif not np.isfinite(np.asarray(v)).all():
            return False
    if torch_sums:
        import torch

        if not bool(torch.isfinite(torch.stack(torch_sums)).all()):
            return False
    if drjit_sums:
        import drjit as dr

        dr.eval(*drjit_sums)
        if not all(np.isfinite(np.asarray(x)).all() for x in drjit_sums):
            return False
    return True


def rng_state(rng: np.random.Generator) -> dict:
    return {"bit_generator": rng.bit_generator.state}


def set_rng_state(rng: np.random.Generator, state: dict) -> None:
    rng.bit_generator.state = state["bit_generator"]


def _differences(saved: Any, now: Any, prefix: str = "") -> list[str]:
    if isinstance(saved, dict) and isinstance(now, dict):
        out = []
        for k in sorted(set(saved) | set(now), key=str):
            if k not in saved:
                out.append(f"{prefix}{k} (new)")
            elif k not in now:
                out.append(f"{prefix}{k} (gone)")
            else:
                out += _differences(saved[k], now[k], f"{prefix}{k}.")
        return out
    return [] if saved == now else [f"{prefix.rstrip('.')}: {saved!r} → {now!r}"]


def _normalise(x: Any) -> Any:
    import json

    from .files import jsonable

    return json.loads(json.dumps(x, default=jsonable))


@dataclass
class Checkpoint:
    """What :func:`run_loop` saved: the stage kind, the fingerprint, the stage's state and the loop's counters."""

    kind: str
    fingerprint: dict
    stage: dict
    run: RunState

    @property
    def done(self) -> bool:
        return self.run.done


def read_checkpoint(path: str | Path) -> Checkpoint:
    """Read a training checkpoint (e.g. to load a finished model); errors name the file."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: no such checkpoint")
    tree = load_tree(path)
    if not isinstance(tree, dict) or not {"fingerprint", "stage", "loop", "stage_name"} <= set(tree):
        raise CheckpointError(f"{path}: not a photoreal training checkpoint; delete it to start over")
    return Checkpoint(tree["stage_name"], tree["fingerprint"], tree["stage"], RunState.from_tree(tree["loop"]))


def _half(x: Any) -> Any:
    """float32 arrays and tensors of a tree → float16 (a model loading them casts back on ``load_state_dict``)."""
    if isinstance(x, dict):
        return {k: _half(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return type(x)(_half(v) for v in x)
    if getattr(x, "dtype", None) is not None and str(x.dtype) in ("float32", "torch.float32"):
        return x.astype(np.float16) if isinstance(x, np.ndarray) else x.half()
    return x


def weights_only(path: str | Path, out: str | Path, keep: tuple[str, ...] = ("model", "ema"),
                 half: bool = False) -> Path:
    """Copy a finished run's checkpoint keeping only the stage entries ``keep`` (weights): no optimiser or random
    state, so about a third of the size, to share or move a trained model. It loads for sampling (same kind and
    fingerprint) and is refused by :func:`run_loop` as a run to resume. ``half`` stores the weights as float16
    (half again; samples then differ from the float32 weights' by the rounding: measure before relying on it)."""
    saved = read_checkpoint(path)
    if not saved.run.done:
        raise CheckpointError(f"{path}: the run is not finished (step {saved.run.step}); finish it before stripping")
    stage = {k: _half(saved.stage[k]) if half else saved.stage[k] for k in keep if k in saved.stage}
    if not stage:
        raise CheckpointError(f"{path}: holds none of {list(keep)} (it has {sorted(saved.stage)})")
    stage["weights_only"] = True
    out = Path(out)
    save_tree(out, {"stage_name": saved.kind, "fingerprint": saved.fingerprint, "stage": stage,
                    "loop": saved.run.to_tree()})
    return out


def run_loop(stage: Stage, settings: LoopSettings, checkpoint: str | Path | None = None,
             budget_steps: int | None = None, show_progress: bool = True,
             metrics_path: str | Path | None = None) -> Any:
    """Run ``stage`` to the end of its budgets (resuming from ``checkpoint``); see the module docstring.

    Returns the stage's result (:meth:`Stage.finish`) when the run is complete, ``None`` when
    ``budget_steps`` ended this call first (the checkpoint then holds everything to continue exactly).
    A complete run called again returns its result again without training.
    """
    checkpoint = Path(checkpoint) if checkpoint is not None else None
    if budget_steps is not None and budget_steps < 1:
        raise UsageError(f"budget_steps must be ≥ 1, got {budget_steps}")
    fingerprint = _normalise(stage.fingerprint())
    run = RunState()
    if checkpoint is not None and checkpoint.exists():
        saved = read_checkpoint(checkpoint)
        if saved.kind != stage.kind:
            raise ForeignCheckpointError(f"{checkpoint}: checkpoint of a {saved.kind} run, not of a "
                                  f"{stage.kind} run; delete it or use another output folder")
        fingerprint = _normalise(stage.fingerprint_against(saved.fingerprint))
        diff = _differences(saved.fingerprint, fingerprint)
        if diff:
            shown = "; ".join(diff[:4]) + ("; …" if len(diff) > 4 else "")
            raise ForeignCheckpointError(f"{checkpoint}: checkpoint was made with other settings or data ({shown}); "
                                  "delete it or use the same ones")
        if saved.stage.get("weights_only"):
            raise CheckpointError(f"{checkpoint}: a weights-only checkpoint (optimiser and random state stripped): it "
                                  "loads for sampling but cannot be resumed; use another output folder")
        stage.load_state(saved.stage)
        run = saved.run

    def budgets_used() -> bool:
        return run.stopped or run.step >= settings.steps or (settings.max_seconds is not None
                                                             and run.train_seconds >= settings.max_seconds)

    saved_step = run.step

    def save() -> None:
        nonlocal saved_step
        if checkpoint is not None:
            save_tree(checkpoint, {"stage_name": stage.kind, "fingerprint": fingerprint,
                                   "stage": stage.state(), "loop": run.to_tree()})
            saved_step = run.step

    run.done = budgets_used()
    stop = settings.steps if budget_steps is None else min(settings.steps, run.step + budget_steps)
    stage.start(run)
    with progress_bar(total=settings.steps, desc=stage.name, unit=stage.unit, disable=not show_progress) as bar:
        bar.update(run.step)
        while not run.done and run.step < stop:
            it = run.step
            t0 = time.perf_counter()
            res = stage.step(it)
            ok = bool(res.finite) and math.isfinite(res.loss)
            if ok:
                stage.apply(it)
                run.nonfinite_in_a_row = 0
            else:
                stage.discard(it)
                run.skipped_steps += 1
                run.nonfinite_in_a_row += 1
            run.train_seconds += time.perf_counter() - t0
            run.losses.append(float(res.loss))
            if res.log and (it % settings.log_every == 0 or it == settings.steps - 1):
                run.log.append({"step": it, "seconds": run.train_seconds, **{k: float(v) for k, v in res.log.items()}})
            run.step += 1
            bar.update(1)
            bar.set_postfix(loss=f"{res.loss:.4g}", refresh=False)
            if run.nonfinite_in_a_row >= settings.max_nonfinite:
                where = (f"the checkpoint {checkpoint} holds the run up to step {saved_step} and would replay them; "
                         "delete it to start over with other settings" if checkpoint else "nothing was saved")
                raise NonFiniteError(f"{stage.name}: {run.nonfinite_in_a_row} steps in a row gave NaN/Inf loss or "
                                     f"gradients (steps {run.step - run.nonfinite_in_a_row}–{run.step - 1}); {where}; "
                                     "lower the learning rate or check the inputs")
            run.done = budgets_used()
            stage.after_step(it, run)
            run.done = budgets_used()  # the stage may have stopped the run
            if run.step % settings.checkpoint_every == 0 or run.done or run.step == stop:
                save()
    if not run.done:
        return None
    result = stage.finish(run)
    if metrics_path is not None:
        write_json(metrics_path, to_json(result))
    return result
