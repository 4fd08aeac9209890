"""Checkpoint files: a tree of arrays, tensors and plain values in one ``.npz`` (no pickle).

A tree is nested dicts (str or int keys), lists and tuples whose leaves are numpy arrays, torch
tensors, Python scalars, strings, ``None`` or numpy scalars. :func:`save_tree` stores every array
as an npz member and the tree's shape (with container and key types, so tuples stay tuples and
integer keys stay integers, as torch optimiser state needs) as JSON beside them; :func:`load_tree`
gives back an equal tree. Nothing is unpickled, so loading a file from elsewhere runs no code.

Written atomically: a killed process leaves the previous checkpoint intact. A damaged or foreign
file raises :class:`~foundation.errors.CheckpointError` naming it ("delete it to start over").
"""

from __future__ import annotations

import json
import os
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from .errors import CheckpointError
from .files import atomic_path

FORMAT = "photoreal-checkpoint/2"


def _encode(x: Any, arrays: dict[str, np.ndarray]) -> Any:
    if isinstance(x, dict):
        items = []
        for k, v in x.items():
            if not isinstance(k, (str, int)) or isinstance(k, bool):
                raise TypeError(f"checkpoint keys must be str or int, got {type(k).__name__}")
            items.append([k, "i" if isinstance(k, int) else "s", _encode(v, arrays)])
        return {"t": "dict", "items": items}
    if isinstance(x, (list, tuple)):
        return {"t": "list" if isinstance(x, list) else "tuple", "items": [_encode(v, arrays) for v in x]}
    if isinstance(x, np.ndarray):
        key = f"a{len(arrays)}"
        arrays[key] = x
        return {"t": "nd", "k": key}
    if isinstance(x, np.generic):
        return {"t": "py", "v": x.item()}
    if x is None or isinstance(x, (bool, int, float, str)):
        return {"t": "py", "v": x}
    mod = type(x).__module__
    if mod.startswith("torch"):
        import torch

        if isinstance(x, torch.Tensor):
            key = f"a{len(arrays)}"
            arrays[key] = x.detach().cpu().numpy()
            return {"t": "torch", "k": key}
    raise TypeError(f"cannot store a {type(x).__name__} in a checkpoint (convert it to numpy first)")


def _decode(node: Any, z) -> Any:
    t = node["t"]
    if t == "dict":
        return {(int(k) if kt == "i" else k): _decode(v, z) for k, kt, v in node["items"]}
    if t in ("list", "tuple"):
        items = [_decode(v, z) for v in node["items"]]
        return items if t == "list" else tuple(items)
    if t == "nd":
        return z[node["k"]]
    if t == "torch":
        import torch

        return torch.from_numpy(np.array(z[node["k"]]))
    if t == "py":
        return node["v"]
    raise ValueError(f"unknown node type {t!r}")


def save_tree(path: str | os.PathLike, tree: Any) -> Path:
    """Write ``tree`` to ``path`` (an ``.npz``), atomically."""
    arrays: dict[str, np.ndarray] = {}
    structure = json.dumps({"format": FORMAT, "tree": _encode(tree, arrays)})
    with atomic_path(path, suffix=".npz") as tmp:
        np.savez(tmp, __tree__=np.array(structure), **arrays)
    return Path(path)


def load_tree(path: str | os.PathLike) -> Any:
    """Read a tree written by :func:`save_tree`; errors name the file and say how to recover."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            if "__tree__" not in z.files:
                raise CheckpointError(f"{path}: checkpoint written by an older photoreal (another format); "
                                      "delete it to start over")
            meta = json.loads(str(z["__tree__"]))
            if meta.get("format") != FORMAT:
                raise CheckpointError(f"{path}: checkpoint format {meta.get('format')!r}, this photoreal reads "
                                      f"{FORMAT!r}; delete it to start over")
            return _decode(meta["tree"], {k: z[k] for k in z.files if k != "__tree__"})
    except CheckpointError:
        raise
    except FileNotFoundError:
        raise CheckpointError(f"{path}: no such checkpoint") from None
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile, json.JSONDecodeError) as exc:
        why = "not an .npz file" if "pickle" in str(exc) else f"{type(exc).__name__}: {exc}"
        raise CheckpointError(f"{path}: damaged checkpoint ({why}); delete it to start over") from None
