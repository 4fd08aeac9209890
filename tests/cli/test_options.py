"""Flags come from settings, once: every option of every subcommand that has a default takes it from a settings
dataclass field or a library function's parameter (:mod:`photoreal.options`), and equals it.

Oracle: the parser itself (nothing runs) against ``dataclasses.fields`` / ``inspect.signature``."""

from __future__ import annotations

import argparse
import dataclasses
import inspect

from photoreal.cli import build_parser
from photoreal.options import default_of, field_docs


def leaves(parser: argparse.ArgumentParser, path: tuple[str, ...] = ()):
    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not subs:
        yield path, parser
        return
    for name, p in subs[0].choices.items():
        yield from leaves(p, path + (name,))


def literal_defaults() -> list[str]:
    """Options with a default that no settings field or function parameter gives."""
    bad = []
    for path, p in leaves(build_parser()):
        for act in p._actions:
            if not act.option_strings or isinstance(act, argparse._HelpAction):
                continue
            src = getattr(act, "source", None)
            if src is None:
                if act.default not in (None, False, argparse.SUPPRESS) and not act.required:
                    bad.append(f"photoreal {' '.join(path)} {act.option_strings[-1]}: default {act.default!r}")
                continue
            owner, name = src
            want = default_of(owner, name) if dataclasses.is_dataclass(owner) else \
                inspect.signature(owner).parameters[name].default
            if act.default != want:
                bad.append(f"photoreal {' '.join(path)} {act.option_strings[-1]}: {act.default!r} != {want!r}")
    return bad


def test_no_option_default_is_written_in_the_cli():
    assert literal_defaults() == []


def test_field_docs_reads_the_comments_sphinx_reads():
    @dataclasses.dataclass
    class S:
        a: int = 1  #: the first
        b: str = "x"
        #: the third, on two
        #: lines above it
        c: float = 2.0
        # a plain comment is no documentation
        d: int = 0

    assert field_docs(S) == {"a": "the first", "c": "the third, on two lines above it"}
