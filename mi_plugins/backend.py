"""Backend selection: libLLVM discovery and Mitsuba variant choice.

Dr.Jit's LLVM backend (the CPU path) loads ``libLLVM`` at run time. Versions
matter: LLVM 14 is refused by Dr.Jit 1.5 and LLVM 15 *aborts the process*
with ``LLVM ERROR: Cannot select ... fminimum`` on the first kernel that uses
``fminimum``. Many Linux images ship only those two, and Dr.Jit picks the
broken one when left to itself. :func:`resolve_libllvm` therefore runs
*before* ``drjit`` is imported and sets ``DRJIT_LIBLLVM_PATH``:

1. ``DRJIT_LIBLLVM_PATH`` already set: kept (the user's word), unless the file
   is missing or its name says LLVM <= 15, which is an error.
2. ``libLLVM`` inside the active environment: the PyPI wheel
   ``karellen-llvm-core`` (a Linux dependency of photoreal) installs
   ``<prefix>/lib/libLLVM.so.<major>.<minor>``.
3. The system's libraries (``/usr/lib/x86_64-linux-gnu``, ``/usr/lib/llvm-*``,
   ...), newest version >= 16 first.

If only LLVM <= 15 is found, :class:`LLVMVersionError` explains why it cannot
be used and how to fix it. If no libLLVM is found at all, nothing is set (a
CUDA-only machine needs none); choosing an ``llvm_*`` variant then fails in
Dr.Jit with its own message.

:func:`choose_variant` returns ``PHOTOREAL_VARIANT`` when set, else
``cuda_ad_rgb`` when a CUDA device *actually computes* (Mitsuba lists CUDA
variants on machines without a GPU, and ``set_variant`` succeeds there; only
the first array operation fails), else ``llvm_ad_rgb``.

:func:`setup` is what ``import mi_plugins`` calls: it resolves libLLVM, imports
Mitsuba and sets the chosen variant *only if the user has not set one already*.
It is the single place in photoreal that calls ``mi.set_variant``.
"""

from __future__ import annotations

import glob
import os
import re
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Mapping, MutableMapping, Sequence

MIN_LLVM_MAJOR = 16
ENV_LLVM = "DRJIT_LIBLLVM_PATH"
ENV_VARIANT = "PHOTOREAL_VARIANT"
DEFAULT_VARIANTS = ("cuda_ad_rgb", "llvm_ad_rgb")

# Folders searched for a system libLLVM, in order. Globs are expanded.
SYSTEM_LLVM_DIRS: tuple[str, ...] = (
    "/usr/lib/x86_64-linux-gnu",
    "/usr/lib/aarch64-linux-gnu",
    "/usr/lib/llvm-*/lib",
    "/usr/lib64",
    "/usr/lib",
    "/usr/local/lib",
    "/opt/homebrew/opt/llvm/lib",
    "/usr/local/opt/llvm/lib",
)

_VERSION_RE = re.compile(r"libLLVM(?:[-.]so)?[-.](\d+)")


class LLVMVersionError(RuntimeError):
    """Raised when the only libLLVM available is one Dr.Jit cannot use."""


@dataclass(frozen=True)
class LLVMChoice:
    path: str | None  #: library to load, or None if none was found
    source: str  #: "env", "venv", "system" or "none"
    major: int | None  #: major version parsed from the file name, if any


def llvm_major(path: str | os.PathLike) -> int | None:
    """Major version of a libLLVM file from its name (``libLLVM-15.so``,
    ``libLLVM.so.23.1``, ``libLLVM-14.0.6.so.1``); symlinks are followed when
    the name itself carries no version (``libLLVM.so``)."""
    for name in (Path(path).name, Path(os.path.realpath(path)).name):
        m = _VERSION_RE.search(name)
        if m:
            return int(m.group(1))
    return None


def too_old_message(path: str, major: int) -> str:
    return (
        f"libLLVM {major} ({path}) cannot run Dr.Jit's LLVM backend: Dr.Jit 1.5 refuses "
        f"LLVM 14 as too old, and LLVM 15 aborts the whole process with "
        f"'LLVM ERROR: Cannot select ... fminimum' on the first kernel. photoreal needs "
        f"libLLVM >= {MIN_LLVM_MAJOR}. Fix: `pip install karellen-llvm-core` into this "
        f"environment (installs <prefix>/lib/libLLVM.so.23.x, found automatically), or "
        f"`apt-get install libllvm19`, or set {ENV_LLVM} to a libLLVM >= {MIN_LLVM_MAJOR}."
    )


def _candidates(dirs: Iterable[str]) -> list[str]:
    found: list[str] = []
    for pattern in dirs:
        for d in sorted(glob.glob(pattern)):
            found.extend(sorted(glob.glob(os.path.join(d, "libLLVM*.so*"))))
            found.extend(sorted(glob.glob(os.path.join(d, "libLLVM*.dylib"))))
    # Same file reachable through several names: keep the first name seen.
    seen: set[str] = set()
    unique = []
    for f in found:
        real = os.path.realpath(f)
        if real not in seen and os.path.isfile(real):
            seen.add(real)
            unique.append(f)
    return unique


def _best(paths: Sequence[str]) -> tuple[str | None, int | None, list[tuple[str, int]]]:
    """Newest usable library among ``paths`` and the too-old ones seen."""
    usable: list[tuple[int, str]] = []
    old: list[tuple[str, int]] = []
    for p in paths:
        major = llvm_major(p)
        if major is None:
            continue
        if major >= MIN_LLVM_MAJOR:
            usable.append((major, p))
        else:
            old.append((p, major))
    if usable:
        major, p = max(usable, key=lambda t: t[0])
        return p, major, old
    return None, None, old


def venv_llvm_dirs(prefixes: Sequence[str] | None = None) -> list[str]:
    """Folders where a pip-installed libLLVM lands (``<prefix>/lib``)."""
    prefixes = prefixes if prefixes is not None else [sys.prefix]
    return [os.path.join(p, "lib") for p in prefixes]


def resolve_libllvm(
    environ: Mapping[str, str] | None = None,
    venv_dirs: Sequence[str] | None = None,
    system_dirs: Sequence[str] | None = None,
) -> LLVMChoice:
    """Choose a libLLVM for Dr.Jit (see module docstring for the order).

    Pure: reads ``environ`` and the file system, changes nothing.
    Raises :class:`LLVMVersionError` (message says why and how to fix) when the
    only libraries available are LLVM <= 15, or when ``DRJIT_LIBLLVM_PATH``
    names a missing file or an LLVM <= 15.
    """
    environ = os.environ if environ is None else environ
    given = environ.get(ENV_LLVM)
    if given:
        if not os.path.exists(given):
            raise LLVMVersionError(f"{ENV_LLVM}={given!r}: no such file.")
        major = llvm_major(given)
        if major is not None and major < MIN_LLVM_MAJOR:
            raise LLVMVersionError(f"{ENV_LLVM} points at " + too_old_message(given, major))
        return LLVMChoice(given, "env", major)

    old_seen: list[tuple[str, int]] = []
    for source, dirs in (
        ("venv", venv_llvm_dirs() if venv_dirs is None else venv_dirs),
        ("system", SYSTEM_LLVM_DIRS if system_dirs is None else system_dirs),
    ):
        path, major, old = _best(_candidates(dirs))
        old_seen += old
        if path:
            return LLVMChoice(path, source, major)
    if old_seen:
        path, major = max(old_seen, key=lambda t: t[1])
        raise LLVMVersionError(too_old_message(path, major))
    return LLVMChoice(None, "none", None)


def configure_libllvm(environ: MutableMapping[str, str] | None = None) -> LLVMChoice:
    """Resolve libLLVM and export it as ``DRJIT_LIBLLVM_PATH``.

    Must run before ``drjit`` is first imported; afterwards it only reports.
    """
    environ = os.environ if environ is None else environ
    choice = resolve_libllvm(environ)
    if choice.path and "drjit" not in sys.modules:
        environ[ENV_LLVM] = choice.path
    return choice


def cuda_works() -> bool:
    """True when a CUDA device exists *and* computes (a real operation runs)."""
    import drjit as dr

    try:
        if not dr.has_backend(dr.JitBackend.CUDA):
            return False
        from drjit.cuda import Float

        return float(dr.sum(Float(1.0, 2.0))[0]) == 3.0
    except Exception:  # any failure to initialise means "no usable GPU"
        return False


class VariantError(ValueError):
    """``PHOTOREAL_VARIANT`` names a variant photoreal cannot run on (the message says which and why)."""


def choose_variant(environ: Mapping[str, str] | None = None) -> str:
    """``PHOTOREAL_VARIANT`` if set, else ``cuda_ad_rgb`` if CUDA works, else ``llvm_ad_rgb``.

    The plugins need an RGB variant with automatic differentiation (``*_ad_rgb``); a CUDA variant is
    refused up front on a machine where CUDA does not compute (Mitsuba would fail at the first render).
    """
    environ = os.environ if environ is None else environ
    forced = environ.get(ENV_VARIANT)
    if forced:
        import mitsuba as mi

        usable = [v for v in mi.variants() if v.endswith("_ad_rgb")]
        if forced not in mi.variants():
            raise VariantError(f"{ENV_VARIANT}={forced!r} is not a Mitsuba variant; photoreal runs on "
                               f"{', '.join(usable)}")
        if forced not in usable:
            raise VariantError(f"{ENV_VARIANT}={forced!r}: photoreal needs an RGB variant with automatic "
                               f"differentiation ({', '.join(usable)})")
        if forced.startswith("cuda") and not cuda_works():
            raise VariantError(f"{ENV_VARIANT}={forced!r}: no CUDA device computes on this machine; "
                               "use llvm_ad_rgb (or unset it)")
        return forced
    return "cuda_ad_rgb" if cuda_works() else "llvm_ad_rgb"


def loaded_libllvm(maps_file: str = "/proc/self/maps") -> list[str]:
    """libLLVM files mapped into this process (Linux), e.g. after drjit was imported."""
    try:
        with open(maps_file) as f:
            paths = {line.split()[-1] for line in f if "libLLVM" in line and "/" in line}
    except OSError:
        return []
    return sorted(paths)


def check_loaded_libllvm(maps_file: str = "/proc/self/maps") -> None:
    """Raise (instead of letting the process abort later) if Dr.Jit already loaded LLVM <= 15."""
    for path in loaded_libllvm(maps_file):
        major = llvm_major(path)
        if major is not None and major < MIN_LLVM_MAJOR:
            raise LLVMVersionError(
                "drjit was imported before mi_plugins and has already loaded " + too_old_message(path, major)
                + " Or import mi_plugins before drjit/mitsuba, so that it can choose the library."
            )


def setup() -> str:
    """Resolve libLLVM, import Mitsuba and set a variant unless one is set.

    Returns the active variant. Called once by ``import mi_plugins``.
    """
    early = "drjit" in sys.modules
    configure_libllvm()
    import mitsuba as mi

    if early:
        check_loaded_libllvm()

    if mi.variant() is None:
        mi.set_variant(choose_variant())
    return mi.variant()


def write_pth() -> Path | None:
    """Write ``photoreal_libllvm.pth`` into site-packages: sets DRJIT_LIBLLVM_PATH at start-up.

    Only the environment variable is set (with ``setdefault``, so a user's own
    value wins); nothing is imported.
    """
    import sysconfig

    choice = resolve_libllvm({})
    if choice.path is None:
        return None
    target = Path(sysconfig.get_paths()["purelib"]) / "photoreal_libllvm.pth"
    target.write_text(f"import os; os.environ.setdefault({ENV_LLVM!r}, {os.path.abspath(choice.path)!r})\n")
    return target


if __name__ == "__main__":
    if sys.argv[1:] == ["--write-pth"]:
        print(write_pth())
    else:
        print(resolve_libllvm())
