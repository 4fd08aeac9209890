"""Save and restore optimiser state for exact resume: Dr.Jit optimisers and torch-style ones.

Dr.Jit 1.5's optimisers (``dr.opt.Adam``, ``mi.ad.Adam``) have no ``state_dict``. Their state is the
documented ``Optimizer.state`` mapping (parameter name → a tuple of the value, flags, a learning rate
and optimiser-specific extras such as Adam's step count and moments), whose tuple layout has changed
between Dr.Jit versions. Nothing here indexes into that tuple: :func:`optimizer_state` walks each entry
as a tree and saves every Dr.Jit array in it as numpy; :func:`load_optimizer_state` walks the fresh
optimiser's entry (the caller has registered the same parameters) in lockstep and replaces each array
by the saved one, converted to the template's own type. If the saved tree and the fresh one do not
have the same shape — another Dr.Jit version, another optimiser — resuming stops with an error that
says so instead of silently restarting the moments.

torch optimisers (and anything with ``state_dict``/``load_state_dict``) use those methods.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from .errors import CheckpointError


def _is_drjit_optimizer(opt: Any) -> bool:
    try:
        import drjit as dr

        return isinstance(opt, dr.opt.Optimizer)
    except (ImportError, AttributeError):
        return False


def _walk_save(x: Any) -> Any:
    import drjit as dr

    if dr.is_array_v(x):
        return {"drjit": type(x).__name__, "data": np.array(dr.detach(x))}
    if isinstance(x, (tuple, list)):
        return [_walk_save(v) for v in x]
    if x is None or isinstance(x, (bool, int, float, str)):
        return {"py": x}
    raise TypeError(f"optimizer state holds a {type(x).__name__}; cannot save it")


def _walk_load(tmpl: Any, saved: Any, where: str) -> Any:
    import drjit as dr

    if dr.is_array_v(tmpl):
        if not isinstance(saved, dict) or "drjit" not in saved:
            raise CheckpointError(f"optimizer state differs at {where}: saved {type(saved).__name__}, "
                                  f"expected a {type(tmpl).__name__}")
        data = np.asarray(saved["data"])
        want = tuple(dr.shape(tmpl)) if dr.is_tensor_v(tmpl) else None
        value = type(tmpl)(data)
        if want is not None and tuple(value.shape) != want:
            raise CheckpointError(f"optimizer state differs at {where}: shape {tuple(value.shape)} vs {want}")
        if dr.width(value) != dr.width(tmpl):
            raise CheckpointError(f"optimizer state differs at {where}: {dr.width(value)} vs {dr.width(tmpl)} "
                                  "entries (another mesh or resolution?)")
        if dr.grad_enabled(tmpl):
            dr.enable_grad(value)
        return value
    if isinstance(tmpl, (tuple, list)):
        if not isinstance(saved, list) or len(saved) != len(tmpl):
            raise CheckpointError(f"optimizer state differs at {where}: saved by another Dr.Jit version or "
                                  "optimiser (its state has another layout); cannot resume exactly")
        out = [_walk_load(t, s, f"{where}[{i}]") for i, (t, s) in enumerate(zip(tmpl, saved))]
        return tuple(out) if isinstance(tmpl, tuple) else out
    if not isinstance(saved, dict) or "py" not in saved:
        raise CheckpointError(f"optimizer state differs at {where}: cannot resume exactly")
    return saved["py"]  # plain values (flags, per-parameter learning rates) are taken as saved


def optimizer_state(opt: Any) -> dict:
    """A checkpointable tree (numpy arrays and plain values) of ``opt``'s full state."""
    if _is_drjit_optimizer(opt):
        import drjit as dr

        lr = opt.lr if isinstance(opt.lr, (int, float)) else None
        return {"kind": "drjit", "class": type(opt).__name__, "drjit": dr.__version__, "lr": lr,
                "params": {k: _walk_save(opt.state[k]) for k in opt.keys()}}
    if hasattr(opt, "state_dict"):
        return {"kind": "state_dict", "class": type(opt).__name__, "state": opt.state_dict()}
    raise TypeError(f"do not know how to save the state of a {type(opt).__name__}")


def load_optimizer_state(opt: Any, saved: dict, name: str = "optimizer") -> None:
    """Restore ``saved`` (from :func:`optimizer_state`) into ``opt``, which holds the same parameters."""
    if saved.get("class") != type(opt).__name__:
        raise CheckpointError(f"{name}: saved state is of a {saved.get('class')}, not a {type(opt).__name__}")
    if saved["kind"] == "drjit":
        if not _is_drjit_optimizer(opt):
            raise CheckpointError(f"{name}: saved Dr.Jit optimizer state, got a {type(opt).__name__}")
        keys = list(opt.keys())
        if sorted(keys) != sorted(saved["params"]):
            raise CheckpointError(f"{name}: saved parameters {sorted(saved['params'])} differ from {sorted(keys)}")
        if saved.get("lr") is not None:
            opt.lr = saved["lr"]
        for k in keys:
            opt.state[k] = _walk_load(opt.state[k], saved["params"][k], f"{name}[{k!r}]")
        return
    opt.load_state_dict(saved["state"])
