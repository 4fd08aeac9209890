"""`photoreal bench …`: every benchmark of the registry (:mod:`photoreal.benchmarks`), each writing JSON; and
`photoreal bench all`, each with its defaults into one folder (``make bench``)."""

from __future__ import annotations

import argparse
import functools

from .common import out_opt, pool_options, pool_settings, print_json

HELP = "benchmarks writing JSON (speed as ratios measured in the same run)"


def _cmd(name: str, a: argparse.Namespace) -> int:
    from photoreal.benchmarks import load, run_benchmark, summary
    from photoreal.options import settings_from

    mod = load(name)
    s = settings_from(mod.SETTINGS, a)
    pool = pool_settings(a) if getattr(mod, "POOL", False) else None
    result = run_benchmark(name, s, a.json, pool=pool, clean=getattr(a, "clean", False))
    print_json(summary(name, result))
    return 0


def _cmd_all(a: argparse.Namespace) -> int:
    """Every benchmark of the registry that runs on its defaults, one after another, into ``--out-dir``."""
    from pathlib import Path

    from foundation.files import check_output_file

    from photoreal.benchmarks import REGISTRY, json_name, load, run_benchmark, summary

    names = [n for n, e in REGISTRY.items() if e.in_all and (not a.only or n in a.only)]
    unknown = sorted(set(a.only or ()) - {n for n, e in REGISTRY.items() if e.in_all})
    if unknown:
        raise ValueError(f"--only {' '.join(unknown)}: not a benchmark `bench all` runs "
                         f"({', '.join(n for n, e in REGISTRY.items() if e.in_all)})")
    out = Path(a.out_dir)
    for n in names:  # every output checked before the first benchmark runs
        check_output_file(out / json_name(n), "--out-dir")
    shown = {}
    for n in names:
        mod = load(n)
        pool = pool_settings(a) if getattr(mod, "POOL", False) else None
        result = run_benchmark(n, mod.SETTINGS(), out / json_name(n), pool=pool, clean=a.clean)
        shown[n] = summary(n, result)
        print_json({n: shown[n]})
    return 0


def _build(name: str, p: argparse.ArgumentParser) -> None:
    from photoreal.benchmarks import load
    from photoreal.options import options_from

    mod = load(name)
    if hasattr(mod, "options"):
        mod.options(p)
    else:
        options_from(p, mod.SETTINGS)
    if getattr(mod, "POOL", False):
        pool_options(p)
    out_opt(p, "--json", kind="file", required=True, help="output JSON path (charts and the work folder go beside it)")
    if getattr(mod, "WORK", True):
        p.add_argument("--clean", action="store_true",
                       help="remove the work folder once the result is written (default: kept, and a rerun re-reads "
                            "everything finished in it)")
    p.set_defaults(func=functools.partial(_cmd, name))


def _build_all(p: argparse.ArgumentParser) -> None:
    out_opt(p, "--out-dir", required=True, help="folder for NAME.json of every benchmark (charts and work beside)")
    p.add_argument("--only", nargs="+", metavar="NAME", default=None, help="these benchmarks only")
    p.add_argument("--clean", action="store_true", help="remove each work folder once its result is written")
    pool_options(p)
    p.set_defaults(func=_cmd_all)


def add(parser: argparse.ArgumentParser, wanted: str | None = None) -> None:
    """One subcommand per registered benchmark; only ``wanted`` (all when None) imports its module for its flags."""
    from photoreal.benchmarks import REGISTRY

    sub = parser.add_subparsers(dest="what", required=True)
    for name, entry in REGISTRY.items():
        p = sub.add_parser(name, help=entry.help)
        if wanted in (None, name):
            _build(name, p)
    p = sub.add_parser("all", help="every benchmark with its defaults, NAME.json each into --out-dir (make bench)")
    if wanted in (None, "all"):
        _build_all(p)
