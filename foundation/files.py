"""Atomic writes, output-path checks, JSON results and file digests.

Every writer goes through :func:`atomic_path` (or :func:`atomic_dir` for a folder): data is
written beside the target and renamed into place, so a crash or an exception never leaves a
half-written output. Written files get the permissions a plain ``open(path, "w")`` would give
(``0o666`` minus the umask), not the ``0o600`` of a temporary file.

Output locations are checked *before* the work starts (:func:`check_output_file`,
:func:`check_output_dir`): an error after an hour of fitting because ``--json`` names a folder
helps nobody. A folder output never replaces a folder it did not write: an existing non-empty
folder is refused unless it holds the marker file of a previous output of the same command.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import os
import shutil
import tempfile
from collections import OrderedDict
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np

from .errors import UsageError

_FILE_MODE: int | None = None


def file_mode() -> int:
    """0o666 minus the process umask (what ``open(path, "w")`` creates)."""
    global _FILE_MODE
    if _FILE_MODE is None:
        old = os.umask(0)
        os.umask(old)
        _FILE_MODE = 0o666 & ~old
    return _FILE_MODE


# -- output locations ---------------------------------------------------------------------------------------------


def _existing_ancestor(path: Path) -> Path:
    p = path
    while not p.exists():
        if p.parent == p:
            break
        p = p.parent
    return p


def _check_parent(path: Path, what: str) -> None:
    anc = _existing_ancestor(path.parent)
    if not anc.is_dir():
        raise UsageError(f"{what} {path}: {anc} is a file, not a folder")
    if not os.access(anc, os.W_OK | os.X_OK):
        raise UsageError(f"{what} {path}: cannot write into {anc} (permission denied)")
    try:  # permissions are not everything (read-only or special file systems): try it
        fd, probe = tempfile.mkstemp(prefix=".photoreal-probe-", dir=anc)
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise UsageError(f"{what} {path}: cannot write into {anc} ({exc.strerror or exc})") from None


def check_output_file(path: str | os.PathLike, what: str = "output") -> Path:
    """A file can be written at ``path``: it is not a folder and its folder can be created. Nothing is created."""
    p = Path(path)
    if str(path) == "" or p.name in ("", ".", ".."):
        raise UsageError(f"{what} {str(path)!r}: not a file name")
    if p.is_dir():
        raise UsageError(f"{what} {p}: is a folder, expected a file path")
    if p.exists() and not os.access(p, os.W_OK):
        raise UsageError(f"{what} {p}: exists and is not writable")
    _check_parent(p, what)
    return p


MANIFEST = ".photoreal-manifest.json"  #: what an :func:`atomic_dir` output holds (written by it, last)
RECORD = ".photoreal-output.json"  #: which command an output folder belongs to ({"command": …}, see OutputPath)
_OWN = (MANIFEST, RECORD)


def recorded_command(path: str | os.PathLike) -> str | None:
    """The command whose output the folder is (its :data:`RECORD`), or None."""
    try:
        return str(json.loads((Path(path) / RECORD).read_text())["command"])
    except (OSError, ValueError, TypeError, KeyError):
        return None


def _entries(p: Path) -> list[str]:
    """What a folder holds besides its record."""
    return sorted(e.name for e in p.iterdir() if e.name != RECORD)


def holds_files(path: str | os.PathLike) -> bool:
    """The folder exists and holds something besides its :data:`RECORD` (a folder claimed for a command and
    nothing more is as good as empty)."""
    p = Path(path)
    return p.is_dir() and bool(_entries(p))


def _foreign_entries(p: Path, derived: tuple[str, ...] = ()) -> list[str]:
    """Entries of a previous :func:`atomic_dir` output that it did not write (added later by a user or a run);
    names matching a ``derived`` pattern (caches computed from the folder's own files) do not count."""
    import fnmatch

    rest = sorted(e.name for e in p.iterdir() if e.name not in _OWN
                  and not any(fnmatch.fnmatchcase(e.name, d) for d in derived))
    try:
        own = set(json.loads((p / MANIFEST).read_text()))
    except (OSError, ValueError, TypeError):  # only derived entries (a work folder): nothing of the user's
        return ["(no readable manifest: made by an older photoreal or by hand)"] if rest else []
    return [e for e in rest if e not in own]


def check_output_dir(path: str | os.PathLike, marker: str | None = None, what: str = "output folder",
                     replace: bool = False, derived: tuple[str, ...] = ()) -> Path:
    """A folder output can go to ``path``: absent, empty, or a previous output (holding ``marker``).

    Never anything else: replacing a folder the program did not write would destroy the user's files. With
    ``replace`` (the folder will be swapped for a new one, :func:`atomic_dir`), a previous output must also hold
    nothing it did not write itself — a morph run or notes saved inside a benchmark would go with it — except
    files matching a ``derived`` pattern: caches made from the folder's own contents, stale once it is remade.
    """
    p = Path(path)
    if str(path) == "":
        raise UsageError(f"{what}: empty path")
    if p.exists():
        if not p.is_dir():
            raise UsageError(f"{what} {p}: is a file, expected a folder")
        import fnmatch

        held = [e for e in _entries(p) if not any(fnmatch.fnmatchcase(e, d) for d in derived)]
        if held and (marker is None or not (p / marker).is_file()):
            hint = f" (no {marker}: not a previous output of this command)" if marker else ""
            raise UsageError(f"{what} {p}: folder exists and is not empty{hint}; choose another path or empty it")
        foreign = _foreign_entries(p, derived) if replace and _entries(p) else []
        if foreign:
            shown = ", ".join(foreign[:4]) + (", …" if len(foreign) > 4 else "")
            raise UsageError(f"{what} {p}: a previous output, but it also holds what this command did not write "
                             f"({shown}); it would be replaced with the folder: move those or choose another path")
        if not os.access(p, os.W_OK | os.X_OK):
            raise UsageError(f"{what} {p}: not writable")
    if p.resolve() == Path.cwd().resolve() or p.resolve() in Path.cwd().resolve().parents:
        raise UsageError(f"{what} {p}: is the working folder or one of its parents")
    _check_parent(p, what)
    return p


# -- the one rule for a command's outputs ---------------------------------------------------------------------------

FILE, FOLDER = "file", "folder"


def check_command_folder(path: str | os.PathLike, command: str, marker: str | None = None, what: str = "",
                         legacy: tuple[str, ...] = ()) -> Path:
    """``path`` can be the output folder of ``command``: absent, empty, or a previous output of it.

    A previous output is recognised by its :data:`RECORD` (written by :func:`claim_output_folder`) or, for a folder
    the library wrote with :func:`atomic_dir`, by its manifest and ``marker``; the command then resumes or
    replaces it. ``legacy``: names that together mark an output of the command written before records existed.
    A folder of another command, or one holding anything else, is refused: its files are the user's.
    """
    p = Path(path)
    if str(path) == "":
        raise UsageError(f"{what} empty path".strip())
    if p.exists():
        if not p.is_dir():
            raise UsageError(f"{what} {p}: is a file, expected a folder".strip())
        owner = recorded_command(p)
        if owner not in (None, command):
            raise UsageError(f"{what} {p}: holds the output of `photoreal {owner}`, not of `photoreal {command}`; "
                             "choose another path".strip())
        held = _entries(p)
        previous = (owner == command or bool(marker and (p / MANIFEST).is_file() and (p / marker).is_file())
                    or bool(legacy and all((p / n).exists() for n in legacy)))
        if held and not previous:
            shown = ", ".join(held[:4]) + (", …" if len(held) > 4 else "")
            raise UsageError(f"{what} {p}: holds files `photoreal {command}` did not write ({shown}); choose another "
                             "path or empty it".strip())
        if not os.access(p, os.W_OK | os.X_OK):
            raise UsageError(f"{what} {p}: not writable".strip())
    if p.resolve() == Path.cwd().resolve() or p.resolve() in Path.cwd().resolve().parents:
        raise UsageError(f"{what} {p}: is the working folder or one of its parents".strip())
    _check_parent(p, what)
    return p


class OutputPath:
    """How the command line checks an output path (an argparse ``type``: it runs while the command line is parsed,
    before any work, and the parser's error names the flag).

    ``FILE``: not a folder, and its folder can be made (the file is replaced, atomically, once the work is done).
    ``FOLDER``: see :func:`check_command_folder`; the command line then claims it (:func:`claim_output_folder`).
    ``tests/cli/test_outputs.py`` checks that every output flag of every subcommand has one.
    """

    def __init__(self, kind: str, command: str, marker: str | None = None, legacy: tuple[str, ...] = ()):
        if kind not in (FILE, FOLDER):
            raise ValueError(f"kind {kind!r}: expected {FILE!r} or {FOLDER!r}")
        self.kind, self.command, self.marker, self.legacy = kind, command, marker, tuple(legacy)
        self.__name__ = f"{kind} path"  # what argparse calls the value in its messages

    def __call__(self, value: str) -> str:
        import argparse

        try:
            if self.kind == FILE:
                check_output_file(value, "")
            else:
                check_command_folder(value, self.command, self.marker, legacy=self.legacy)
        except UsageError as exc:
            raise argparse.ArgumentTypeError(str(exc).strip()) from None
        return value

    def __repr__(self) -> str:
        return f"OutputPath({self.kind!r}, {self.command!r})"


def claim_output_folder(path: str | os.PathLike, command: str) -> Path | None:
    """Make the folder (checked by :func:`check_command_folder`) and record ``command`` in it; the outermost folder
    this made (None when it existed), for :func:`release_output_folder`."""
    p = Path(path)
    made = None
    for q in (p, *p.parents):
        if q.exists():
            break
        made = q
    p.mkdir(parents=True, exist_ok=True)
    if recorded_command(p) is None:
        write_json(p / RECORD, {"command": command})
    return made


def release_output_folder(path: str | os.PathLike, made: Path | None) -> None:
    """After a failed run: a claimed folder that holds nothing but its record is left as it was found (the record
    removed; the folders the claim made removed). One holding more (a checkpoint to resume) is kept."""
    p = Path(path)
    if not p.is_dir() or _entries(p):
        return
    (p / RECORD).unlink(missing_ok=True)
    if made is None:
        return
    q = p
    while True:
        try:
            q.rmdir()
        except OSError:
            return
        if q == made:
            return
        q = q.parent


# -- atomic writes --------------------------------------------------------------------------------------------------


@contextlib.contextmanager
def atomic_path(target: str | os.PathLike, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path in the target's folder; rename it over the target on success."""
    target = check_output_file(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=suffix or target.suffix, dir=target.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        os.chmod(tmp, file_mode())
        fd = os.open(tmp, os.O_RDONLY)
        try:
            os.fsync(fd)  # the data is on disk before the name points at it (a power cut leaves the old file)
        finally:
            os.close(fd)
        os.replace(tmp, target)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


@contextlib.contextmanager
def atomic_dir(target: str | os.PathLike, marker: str | None = None,
               derived: tuple[str, ...] = ()) -> Iterator[Path]:
    """Yield a hidden sibling folder; on success it replaces ``target``, on any error it is removed.

    ``target`` must be absent, empty or a previous output holding ``marker`` (see
    :func:`check_output_dir`, also for ``derived``); the work should write ``marker`` last.
    """
    target = check_output_dir(target, marker, replace=True, derived=derived)
    tmp = target.with_name(f".{target.name}.partial")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    try:
        yield tmp
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)  # no half-written folder
        raise
    if (target / RECORD).is_file():  # the new folder belongs to the same command
        shutil.copy2(target / RECORD, tmp / RECORD)
    (tmp / MANIFEST).write_text(json.dumps(sorted([e.name for e in tmp.iterdir()] + [MANIFEST])))
    os.chmod(tmp / MANIFEST, file_mode())
    old = None
    if target.exists():
        check_output_dir(target, marker, replace=True, derived=derived)  # still only a previous output after the work
        old = target.with_name(f".{target.name}.old")
        shutil.rmtree(old, ignore_errors=True)
        target.rename(old)
    tmp.rename(target)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def write_text(path: str | os.PathLike, text: str) -> Path:
    with atomic_path(path) as tmp:
        tmp.write_text(text)
    return Path(path)


# -- JSON results -------------------------------------------------------------------------------------------------


def jsonable(x: Any) -> Any:
    """``json.dumps`` default: numpy scalars and arrays, paths, dataclasses."""
    import dataclasses

    if isinstance(x, (np.floating, np.integer, np.bool_)):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, Path):
        return str(x)
    if dataclasses.is_dataclass(x) and not isinstance(x, type):
        return dataclasses.asdict(x)
    raise TypeError(f"not JSON serialisable: {type(x).__name__}")


def json_text(data: Any) -> str:
    """``data`` as indented JSON text (numpy values, paths and dataclasses allowed)."""
    return json.dumps(data, indent=2, default=jsonable) + "\n"


def write_json(path: str | os.PathLike, data: Any) -> Path:
    """Write ``data`` as indented JSON, atomically (numpy values, paths and dataclasses allowed)."""
    return write_text(path, json_text(data))


def read_json(path: str | os.PathLike, what: str = "JSON file", expect: type = dict) -> Any:
    """Read a JSON file; a missing, empty or malformed file, or one of another shape, names the file."""
    p = Path(path)
    if not p.is_file():
        raise UsageError(f"{p}: no such {what}" if not p.exists() else f"{p}: is not a file ({what} expected)")
    try:
        text = p.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise UsageError(f"{p}: cannot read {what} ({exc})") from None
    if not text.strip():
        raise UsageError(f"{p}: empty file ({what} expected)")
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise UsageError(f"{p}: not valid JSON (line {exc.lineno}, column {exc.colno}: {exc.msg})") from None
    if expect is not None and not isinstance(data, expect):
        raise UsageError(f"{p}: expected a JSON {'object' if expect is dict else expect.__name__} "
                         f"({what}), got {type(data).__name__}")
    return data


def finite_or_none(x: float | None) -> float | None:
    """NaN/Inf → None, so that a JSON result never holds the non-standard tokens ``NaN``/``Infinity``."""
    return None if x is None or not math.isfinite(x) else float(x)


def file_digest(path: str | os.PathLike, n: int = 16) -> str:
    """First ``n`` hex digits of the file's SHA-256 (identifies an input independent of its path)."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()[:n]


def cached_arrays(path: str | os.PathLike, key: str, compute) -> dict:
    """Arrays saved in ``path`` (.npz) under ``key``, or ``compute()`` (a dict of arrays) saved there atomically.

    A cache of another key, or a damaged one, is recomputed and replaced: it is only a cache.
    """
    import numpy as np

    path = Path(path)
    if path.is_file():
        try:
            with np.load(path, allow_pickle=False) as z:
                if str(z["key"]) == key:
                    return {k: z[k] for k in z.files if k != "key"}
        except Exception:
            pass
    arrays = compute()
    with atomic_path(path, suffix=".npz") as tmp:
        np.savez(tmp, key=key, **arrays)
    return arrays


def array_key(*arrays) -> tuple:
    """The content of numpy arrays (SHA-1 of their bytes, shapes, dtypes): equal keys mean equal arrays,
    whatever objects hold them."""
    arrays = [np.ascontiguousarray(a) for a in arrays]
    digest = hashlib.sha1(b"".join(a.tobytes() for a in arrays)).hexdigest()
    return (digest, *((a.shape, a.dtype.str) for a in arrays))


class Memo:
    """The last ``kept`` values of deterministic computations, by key (least recently used dropped first).

    For work that every run on a benchmark repeats on the same arrays (key them with :func:`array_key`);
    callers that hand out mutable values copy them.
    """

    def __init__(self, kept: int):
        self.kept = kept
        self._items: OrderedDict = OrderedDict()

    def get(self, key, make: Callable[[], Any]) -> Any:
        if key in self._items:
            self._items.move_to_end(key)
            return self._items[key]
        value = self._items[key] = make()
        while len(self._items) > self.kept:
            self._items.popitem(last=False)
        return value

    def clear(self) -> None:
        self._items.clear()

    def __len__(self) -> int:
        return len(self._items)
