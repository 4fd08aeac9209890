"""Errors photoreal raises on purpose. Every message names the file or the parameter at fault.

The command line maps them to exit codes: 2 for what the user gave (a flag value, a path, an
input file that is missing or not what it should be), 1 for work that failed (a run that diverged,
a damaged checkpoint, a disk that refused a write).
"""

from __future__ import annotations


class PhotorealError(Exception):
    """Base class; ``exit_code`` is what ``photoreal`` exits with."""

    exit_code = 1


class UsageError(PhotorealError, ValueError):
    """A bad argument: an out-of-range parameter, an unusable output path, a missing or unreadable input."""

    exit_code = 2


class FailureError(PhotorealError, RuntimeError):
    """The work itself failed (not the user's input)."""

    exit_code = 1


class NonFiniteError(FailureError, FloatingPointError):
    """An optimisation produced NaN/Inf values step after step."""


class CheckpointError(FailureError):
    """A checkpoint cannot be resumed (damaged, another format, other settings or data)."""


class ForeignCheckpointError(CheckpointError):
    """A checkpoint of another kind of run, or of other settings, where the user named this one's (exit 2: the input
    named is the wrong one, nothing failed)."""

    exit_code = 2
