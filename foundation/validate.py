"""Checks of settings values that name the parameter (used in the settings dataclasses' ``__post_init__``).

A NaN compares false with everything, so ``x < 0`` lets it through; these helpers reject it first.
The ``name`` is the settings field; the command line maps fields to flags when it reports them.
"""

from __future__ import annotations

import math
from typing import Any, Iterable

from .errors import UsageError


def _number(name: str, x: Any) -> float:
    if isinstance(x, bool) or not isinstance(x, (int, float)):
        try:
            x = float(x)
        except (TypeError, ValueError):
            raise UsageError(f"{name} must be a number, got {x!r}") from None
    if not math.isfinite(x):
        raise UsageError(f"{name} must be a finite number, got {x}")
    return float(x)


def positive(name: str, x: Any) -> None:
    if _number(name, x) <= 0:
        raise UsageError(f"{name} must be > 0, got {x}")


def non_negative(name: str, x: Any) -> None:
    if _number(name, x) < 0:
        raise UsageError(f"{name} must be ≥ 0, got {x}")


def at_least(name: str, x: Any, lo: float) -> None:
    if _number(name, x) < lo:
        raise UsageError(f"{name} must be ≥ {lo:g}, got {x}")


def in_range(name: str, x: Any, lo: float, hi: float, lo_open: bool = False, hi_open: bool = False) -> None:
    v = _number(name, x)
    if (v <= lo if lo_open else v < lo) or (v >= hi if hi_open else v > hi):
        raise UsageError(f"{name} must be in {'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}, got {x}")


def integer(name: str, x: Any, lo: int | None = None, hi: int | None = None) -> None:
    if isinstance(x, bool) or not isinstance(x, int):
        if isinstance(x, float) and x.is_integer():
            x = int(x)
        else:
            raise UsageError(f"{name} must be an integer, got {x!r}")
    if lo is not None and x < lo:
        raise UsageError(f"{name} must be ≥ {lo}, got {x}")
    if hi is not None and x > hi:
        raise UsageError(f"{name} must be ≤ {hi}, got {x}")


def one_of(name: str, x: Any, choices: Iterable[Any]) -> None:
    choices = tuple(choices)
    if x not in choices:
        raise UsageError(f"{name} must be one of {', '.join(map(str, choices))}, got {x!r}")


def optional(check, name: str, x: Any, *args) -> None:
    if x is not None:
        check(name, x, *args)


SEED_MAX = 2**31 - 1  #: Mitsuba's sampler seed is 32-bit; photoreal multiplies seeds by small factors


def seed(name: str, x: Any, hi: int = SEED_MAX) -> None:
    integer(name, x, 0, hi)
