"""Mitsuba 3 plugins of photoreal, usable from any Mitsuba project.

``import mi_plugins`` resolves libLLVM and, if no Mitsuba variant is set yet,
sets one (``cuda_ad_rgb`` when a GPU works, else ``llvm_ad_rgb``;
``PHOTOREAL_VARIANT`` overrides), then registers the plugins for the active
variant: BSDFs ``ggx_uv`` and ``neural_btf``, integrators ``intrinsic`` and ``indirect``. After switching
variants yourself, call :func:`register` again.
"""

from __future__ import annotations

from . import backend

variant = backend.setup()


def register() -> str:
    """Register every photoreal plugin for the active variant; returns it."""
    import mitsuba as mi

    from .bsdfs import ggx_uv, neural_btf
    from .integrators import indirect, intrinsic

    ggx_uv.register()
    neural_btf.register()
    intrinsic.register()
    indirect.register()
    return mi.variant()


register()
