"""Typed records ↔ JSON: dataclasses written as JSON objects and read back with their types checked.

:func:`from_json` builds a dataclass from a parsed JSON object, recursing into nested dataclasses,
lists, tuples and dicts by the field annotations, and names the file and the field on a missing
key, an unknown key or a value of the wrong type — so a hand-edited or foreign ``benchmark.json``
fails with one line instead of a ``KeyError`` deep inside a run.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

from .errors import UsageError

T = TypeVar("T")


def to_json(obj: Any) -> Any:
    """Dataclasses → dicts, tuples → lists, recursively (JSON-ready)."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: to_json(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, (list, tuple)):
        return [to_json(v) for v in obj]
    if isinstance(obj, dict):
        return {str(k): to_json(v) for k, v in obj.items()}
    return obj


def json_digest(obj: Any, n: int = 16) -> str:
    """First ``n`` hex digits of the SHA-256 of ``obj`` as sorted-key JSON (via :func:`to_json`; other values as
    ``str``): a stable name for a set of settings and inputs."""
    import hashlib
    import json

    return hashlib.sha256(json.dumps(to_json(obj), sort_keys=True, default=str).encode()).hexdigest()[:n]


def _convert(tp: Any, value: Any, where: str) -> Any:
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if tp is Any:
        return value
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        errors = []
        for a in args:
            if a is type(None):
                continue
            try:
                return _convert(a, value, where)
            except UsageError as exc:
                errors.append(str(exc))
        raise UsageError(errors[0] if errors else f"{where}: unexpected null")
    if dataclasses.is_dataclass(tp):
        return from_json(tp, value, where)
    if origin in (list, tuple) or tp in (list, tuple):
        if not isinstance(value, (list, tuple)):
            raise UsageError(f"{where}: expected a list, got {type(value).__name__}")
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(args) != len(value):
                raise UsageError(f"{where}: expected {len(args)} values, got {len(value)}")
            return tuple(_convert(a, v, f"{where}[{i}]") for i, (a, v) in enumerate(zip(args, value)))
        item = args[0] if args else Any
        out = [_convert(item, v, f"{where}[{i}]") for i, v in enumerate(value)]
        return tuple(out) if (origin is tuple or tp is tuple) else out
    if origin is dict or tp is dict:
        if not isinstance(value, dict):
            raise UsageError(f"{where}: expected an object, got {type(value).__name__}")
        vt = args[1] if len(args) == 2 else Any
        return {k: _convert(vt, v, f"{where}.{k}") for k, v in value.items()}
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise UsageError(f"{where}: expected a number, got {value!r}")
        return float(value)
    if tp is int:
        if isinstance(value, bool) or not (isinstance(value, int) or (isinstance(value, float) and value.is_integer())):
            raise UsageError(f"{where}: expected an integer, got {value!r}")
        return int(value)
    if tp is str:
        if not isinstance(value, str):
            raise UsageError(f"{where}: expected a string, got {value!r}")
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise UsageError(f"{where}: expected true/false, got {value!r}")
        return value
    if origin is typing.Literal:
        if value not in args:
            raise UsageError(f"{where}: expected one of {', '.join(map(repr, args))}, got {value!r}")
        return value
    return value


def from_json(cls: type[T], data: Any, where: str) -> T:
    """Build ``cls`` from a parsed JSON object; ``where`` (e.g. the file name) starts every error."""
    if not isinstance(data, dict):
        raise UsageError(f"{where}: expected a JSON object, got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise UsageError(f"{where}: unknown field(s) {', '.join(unknown)} for {cls.__name__}")
    kwargs = {}
    for name, f in fields.items():
        if name not in data:
            if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                raise UsageError(f"{where}: missing field {name!r}")
            continue
        kwargs[name] = _convert(hints[name], data[name], f"{where}: {name}" if ":" not in where else f"{where}.{name}")
    try:
        return cls(**kwargs)
    except UsageError as exc:
        raise UsageError(f"{where}: {exc}") from None
    except (TypeError, ValueError) as exc:
        raise UsageError(f"{where}: {exc}") from None


def load_folder_record(folder: str | Path, marker: str, cls: type[T], fmt: str, what: str, maker: str) -> T:
    """The description ``folder/marker`` of an output folder (a benchmark, a run) as a ``cls``.

    A missing folder, a folder without the marker (``maker`` is the command that makes one), another
    format, or a malformed description is named.
    """
    from .files import read_json

    folder = Path(folder)
    path = folder / marker
    if not folder.is_dir():
        raise UsageError(f"{folder}: no such {what} folder")
    if not path.is_file():
        raise UsageError(f"{folder}: not a {what} folder (no {marker}; make one with `{maker}`)")
    raw = read_json(path, f"{what} description")
    if raw.get("format") != fmt:
        raise UsageError(f"{path}: unknown format {raw.get('format')!r} (expected {fmt!r})")
    return from_json(cls, raw, str(path))
