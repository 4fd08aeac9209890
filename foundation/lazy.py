"""Packages whose names load on first use (PEP 562), so that a command imports only what it runs.

A feature package of torch models keeps its settings in a torch-free module, imported at once, and names the
modules of everything else; ``from generative.gan import train_gan`` then imports ``generative.gan.train`` (and
torch) at that moment, while ``from generative.gan import GanTrainSettings`` never does::

    __getattr__, __dir__ = lazy_names(__name__, {"train": ("train_gan", "load_trained"), ...})
"""

from __future__ import annotations

import importlib
import sys


def lazy_names(package: str, where: dict[str, tuple[str, ...]]):
    """The package's ``__getattr__`` and ``__dir__``: each name of ``where[module]`` comes from
    ``package.module``, imported on the first look-up and then kept in the package."""
    owner = {name: module for module, names in where.items() for name in names}

    def __getattr__(name: str):
        if name not in owner:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(f"{package}.{owner[name]}"), name)
        setattr(sys.modules[package], name, value)
        return value

    def __dir__() -> list[str]:
        return sorted(set(vars(sys.modules[package])) | set(owner))

    return __getattr__, __dir__
