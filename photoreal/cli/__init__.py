"""`photoreal` command line: a thin layer over the library functions, one module per command group.

Every option's default is read from the settings dataclass it fills (:func:`common.opt`), so the two never
disagree; every option of a subcommand is used by it. Errors are one line naming the file or the flag: exit 2 for
what the user gave (a flag value, a path, an input file), 1 for work that failed (PHOTOREAL_DEBUG=1 shows the
traceback).

Start-up stays fast: a group module imports only the standard library at its top, and :func:`main` builds the
options of the one group that the command line names (``photoreal --help`` builds none), so the libraries behind
the other groups (torch, diffusers, Mitsuba) are never imported for it.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys

#: command groups in the order ``photoreal --help`` lists them (module of this package: HELP, add(parser))
GROUPS = ("render", "bench", "capture", "face", "morph", "btf", "gan", "diffrender", "export", "demo")


def _group(name: str):
    return importlib.import_module(f"{__name__}.{name}")


def build_parser(only: str | None | tuple[str, ...] = GROUPS, wanted: str | None = None) -> argparse.ArgumentParser:
    """The parser; the groups in ``only`` get their subcommands, the others just their name and help. Of a group's
    subcommands, ``wanted`` gets its options (all when None, none when "")."""
    full = (only,) if isinstance(only, str) else tuple(only or ())
    p = argparse.ArgumentParser(prog="photoreal", description="photoreal: coarse or low-quality 3D content rendered "
                                "photo-realistically (Mitsuba 3 / Dr.Jit)")
    sub = p.add_subparsers(dest="command", required=True)
    for name in GROUPS:
        mod = _group(name)
        g = sub.add_parser(name, help=mod.HELP)
        if name in full:
            mod.add(g, wanted)
    return p


def _actions(parser: argparse.ArgumentParser, argv: list[str]):
    """The options of the (sub)commands the command line names, outermost first."""
    for act in parser._actions:
        if isinstance(act, argparse._SubParsersAction):
            for name, sp in act.choices.items():
                if name in argv:
                    yield from _actions(sp, argv)
        elif act.option_strings:
            yield act


def _flags(parser: argparse.ArgumentParser, argv: list[str]) -> dict[str, str]:
    """dest → option string of the subcommand that ran (to name flags, not field names, in errors)."""
    out: dict[str, str] = {}
    for act in _actions(parser, argv):
        out.setdefault(act.dest, max(act.option_strings, key=len))
    return out


def _message(exc: BaseException, flags: dict[str, str]) -> str:
    msg = " ".join(str(exc).split()) or type(exc).__name__
    for dest, flag in flags.items():
        if msg.startswith(dest + " ") or msg.startswith(dest + ":"):
            return flag + msg[len(dest):]
    return msg


def _named(argv: list[str]) -> tuple[str | None, str | None]:
    """The command group and the subcommand the command line names: its first two words that are not options
    ("" for a group named without a subcommand: none gets its options)."""
    words = [w for w in argv if not w.startswith("-")][:2]
    group = words[0] if words and words[0] in GROUPS else None
    return group, (words[1] if len(words) > 1 else "") if group else None


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    group, wanted = _named(argv)
    try:
        if group is not None:
            import mi_plugins  # noqa: F401  (resolves libLLVM, picks and checks the variant)
        parser = build_parser(group, wanted)
    except ValueError as exc:  # e.g. PHOTOREAL_VARIANT names a variant the plugins cannot run on
        print(f"photoreal: error: {exc}", file=sys.stderr)
        return 2
    try:  # usage errors (argparse's, and the output rule's: foundation.files.OutputPath) exit 2, --help 0
        args = parser.parse_args(argv)
    except SystemExit as exc:
        return exc.code if isinstance(exc.code, int) else 2
    from foundation.errors import PhotorealError

    debug = os.environ.get("PHOTOREAL_DEBUG", "") not in ("", "0")
    claimed = []
    rc = 1
    try:
        claimed = _claim_outputs(parser, argv, args)
        rc = args.func(args)
        return rc
    except KeyboardInterrupt:
        print("photoreal: interrupted", file=sys.stderr)
        rc = 130
        return rc
    except Exception as exc:
        if debug:
            raise
        code = getattr(exc, "exit_code", None)
        if code is None:  # plain errors: a bad value or a missing file is the user's input; the rest, a failure
            code = 2 if isinstance(exc, (ValueError, FileNotFoundError, NotADirectoryError, IsADirectoryError,
                                         ImportError)) else 1
        msg = _message(exc, _flags(parser, argv))
        if not isinstance(exc, (PhotorealError, ValueError, OSError, ImportError, RuntimeError, FloatingPointError)):
            msg = f"internal error, {type(exc).__name__}: {msg} (PHOTOREAL_DEBUG=1 shows the traceback)"
        print(f"photoreal: error: {msg}", file=sys.stderr)
        rc = code
        return code
    finally:
        if rc != 0:
            from foundation.files import release_output_folder

            for path, made in claimed:
                release_output_folder(path, made)


def _claim_outputs(parser: argparse.ArgumentParser, argv: list[str], args) -> list:
    """Claim the output folders the command line names (see :func:`common.out_opt`): (path, folder made) each."""
    from foundation.files import FOLDER, OutputPath, claim_output_folder

    out = []
    for act in _actions(parser, argv):
        value = getattr(args, act.dest, None)
        if isinstance(act.type, OutputPath) and act.type.kind == FOLDER and value is not None:
            out.append((value, claim_output_folder(value, act.type.command)))
    return out

