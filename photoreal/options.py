"""Command-line options from settings dataclasses: each flag fills one field (or one library function's parameter)
and takes its default from there, so no default is written twice.

:func:`opt` and :func:`arg_opt` record on the argparse action where its default comes from (``action.source``);
``tests/cli/test_options.py`` walks every subcommand and checks that each option with a default has one.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import functools
import inspect
import textwrap
from typing import Any


def default_of(cls: type, name: str) -> Any:
    f = {f.name: f for f in dataclasses.fields(cls)}[name]
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    raise KeyError(f"{cls.__name__}.{name} has no default")


def arg_default(func, name: str) -> Any:
    """The default of a library function's parameter (for options that fill a function argument)."""
    return inspect.signature(func).parameters[name].default


@functools.lru_cache(maxsize=None)
def field_docs(cls: type) -> dict[str, str]:
    """Each field's documentation as Sphinx reads it: the ``#:`` comment on its line, else the ``#:`` lines just
    above it, by field name."""
    out: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if not dataclasses.is_dataclass(klass):
            continue
        try:
            lines = textwrap.dedent(inspect.getsource(klass)).splitlines()
        except (OSError, TypeError):
            continue
        for node in ast.walk(ast.parse("\n".join(lines))):
            if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
                text = lines[node.end_lineno - 1]
                if "#:" in text:
                    out[node.target.id] = text.split("#:", 1)[1].strip()
                    continue
                above, k = [], node.lineno - 2
                while k >= 0 and lines[k].strip().startswith("#:"):
                    above.insert(0, lines[k].strip()[2:].strip())
                    k -= 1
                if above:
                    out[node.target.id] = " ".join(above)
    return out


def _add(p: argparse.ArgumentParser, source: tuple, name: str, default: Any, flags: tuple[str, ...], help: str,
         kw: dict) -> argparse.Action:
    dest = kw.pop("dest", name)
    if isinstance(default, bool) and "action" not in kw:
        kw["action"] = "store_false" if default else "store_true"
    elif "type" not in kw and "action" not in kw:
        kw["type"] = type(default) if isinstance(default, (int, float, str)) else str
    if isinstance(default, tuple) and "nargs" not in kw:
        kw["nargs"] = "+"
    shown = " ".join(map(str, default)) if isinstance(default, tuple) else default
    if isinstance(default, bool) or "default" in help:
        text = help
    else:
        text = f"{help} (default: {shown})" if help else f"default: {shown}"
    text = text.replace("%", "%%")  # argparse formats help with %: a field's "90 %" would break --help
    act = p.add_argument(*(flags or (f"--{dest.replace('_', '-')}",)), dest=dest, default=default, help=text, **kw)
    act.source = source
    return act


def opt(p: argparse.ArgumentParser, cls: type, name: str, *flags: str, help: str = "", **kw) -> argparse.Action:
    """``--flag`` filling ``cls.name``; its default (shown in --help) is the dataclass's, its help the field's
    ``#:`` comment unless given. ``dest=`` names the parsed value otherwise (one field of several settings)."""
    return _add(p, (cls, name), name, default_of(cls, name), flags, help or field_docs(cls).get(name, ""), kw)


def arg_opt(p: argparse.ArgumentParser, func, name: str, *flags: str, help: str = "", **kw) -> argparse.Action:
    """``--flag`` filling the parameter ``name`` of the library function ``func``, with its default."""
    return _add(p, (func, name), name, arg_default(func, name), flags, help, kw)


def options_from(p: argparse.ArgumentParser, cls: type, skip: tuple[str, ...] = ()) -> None:
    """One flag per field of ``cls`` (``--field-name``), default and help from the field."""
    for f in dataclasses.fields(cls):
        if f.name not in skip and not f.name.startswith("_"):
            opt(p, cls, f.name)


def settings_from(cls: type, a: argparse.Namespace, **extra):
    """``cls`` from the parsed options that name its fields (plus ``extra``)."""
    names = {f.name for f in dataclasses.fields(cls)}
    kw = {k: v for k, v in vars(a).items() if k in names}
    for k, v in list(kw.items()):
        if isinstance(default_of(cls, k), tuple) and isinstance(v, list):
            kw[k] = tuple(v)
    kw.update(extra)
    return cls(**kw)


def settings_named(cls: type, flags: dict[str, str], **values):
    """``cls(**values)`` for fields filled from options of other names (``dest=``): an error naming one of those
    fields names its flag (``flags``: field → flag) instead, as errors of :func:`settings_from` do."""
    from foundation.errors import UsageError

    try:
        return cls(**values)
    except UsageError as exc:
        msg = str(exc)
        for name, flag in flags.items():
            if msg.startswith((name + " ", name + ":")):
                raise UsageError(flag + msg[len(name):]) from None
        raise
