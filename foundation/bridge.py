"""Every torch ↔ Dr.Jit crossing of photoreal lives here (``dr.wrap``).

* :func:`torch_to_drjit_loss` exposes a Dr.Jit function (e.g. "render these
  vertices and compare with photos") to torch: torch tensors in, a torch
  scalar out, and ``loss.backward()`` runs Dr.Jit's reverse-mode AD through
  Mitsuba into the torch inputs.
* :func:`drjit_to_torch` exposes a torch module to Dr.Jit code: Dr.Jit
  tensors in and out, with Dr.Jit's ``dr.backward`` reaching the module's
  inputs (and its parameters' ``.grad`` through torch autograd).

Devices: ``dr.wrap`` hands torch's CPU tensors to Dr.Jit's LLVM backend and CUDA tensors to its CUDA backend
(DLPack, no copy). Under a ``cuda_ad_*`` variant, CPU tensors would arrive as LLVM arrays that no Mitsuba
array of the variant can be combined with (found on an H100, 2026-11-27), so the wrappers move tensors to the
variant's device on the way in and back to the caller's (or the torch module's) device on the way out; ``.to``
is differentiable, so gradients follow. Under ``llvm_ad_*`` with CPU modules nothing moves.

Notes measured on this machine (NOTES-mitsuba): the crossing is exact
(gradients equal torch's own autograd), costs < 1 ms for an MSE, and a
reduction comes back as a 0-d tensor.
"""

from __future__ import annotations

from typing import Callable

import drjit as dr
import mitsuba as mi
import torch


def variant_device() -> torch.device:
    """The torch device whose tensors share memory with the current Mitsuba variant's arrays."""
    return torch.device("cuda" if dr.backend_v(mi.Float) == dr.JitBackend.CUDA else "cpu")


def module_device(module, default: torch.device | str) -> torch.device | str:
    """Where a torch module's parameters (or buffers) live; ``default`` for a parameterless callable."""
    if isinstance(module, torch.nn.Module):
        for t in module.parameters():
            return t.device
        for t in module.buffers():
            return t.device
    return default


def torch_to_drjit_loss(fn: Callable[..., mi.Float]) -> Callable[..., torch.Tensor]:
    """Wrap ``fn(*drjit_tensors) -> scalar`` so that torch can call it and differentiate through it.

    Inputs arrive in ``fn`` as ``mi.TensorXf`` (float32, same shapes);
    the returned torch scalar has a grad_fn that backpropagates through Dr.Jit.
    """

    @dr.wrap(source="torch", target="drjit")
    def wrapped(*args):
        return fn(*args)

    def call(*tensors: torch.Tensor) -> torch.Tensor:
        for t in tensors:
            if t.dtype != torch.float32:
                raise TypeError(f"torch_to_drjit_loss: expected float32 tensors, got {t.dtype}")
        dev = variant_device()
        out = wrapped(*[t.to(dev) for t in tensors])
        out = out.to(tensors[0].device) if tensors else out
        return out.reshape(()) if out.numel() == 1 else out

    return call


def drjit_to_torch(module: Callable[[torch.Tensor], torch.Tensor]) -> Callable[[mi.TensorXf], mi.TensorXf]:
    """Wrap a torch callable so that Dr.Jit code can call it on ``mi.TensorXf`` and differentiate through it
    (the tensor visits the module's device and comes back)."""

    @dr.wrap(source="drjit", target="torch")
    def wrapped(x):
        return module(x.to(module_device(module, x.device))).to(x.device)

    return wrapped


def drjit_images_to_torch(fn: Callable[..., torch.Tensor],
                          device: torch.device | str | None = None) -> Callable[..., mi.Float]:
    """Let Dr.Jit images flow through a torch image function (e.g. a GAN generator and its loss).

    ``fn`` receives each Dr.Jit ``(H, W, C)`` image as a torch ``(1, C, H, W)``
    tensor (the layout torch convolutions expect) and returns a torch scalar;
    the wrapper returns it to Dr.Jit as a differentiable scalar. ``dr.backward``
    on anything built from it propagates into the Dr.Jit images (hence into a
    Mitsuba render and the scene parameters behind it) *and*, through torch
    autograd, into the ``.grad`` of every torch parameter ``fn`` used — one
    loss, both optimisers (joint geometry + GAN training, thesis §6). ``device``: where ``fn``'s modules live
    (None: the variant's device).
    """

    @dr.wrap(source="drjit", target="torch")
    def wrapped(*images):
        dev = images[0].device if device is None else torch.device(device)
        return fn(*[im.to(dev).permute(2, 0, 1).unsqueeze(0) for im in images]).reshape(()).to(images[0].device)

    def call(*images: mi.TensorXf) -> mi.Float:
        for im in images:
            if len(im.shape) != 3:
                raise ValueError(f"drjit_images_to_torch: expected (H, W, C) images, got shape {im.shape}")
        out = wrapped(*images)
        return out.array if isinstance(out, mi.TensorXf) else out

    return call
