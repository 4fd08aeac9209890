"""What the command groups share beside their options (:mod:`photoreal.options`): batches on a pool, output
folders, usage errors, printing."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def add_subcommands(parser: argparse.ArgumentParser, dest: str, table: dict, wanted: str | None) -> None:
    """A group's subcommands ({name: (help, build)}) on its parser; only ``wanted`` gets its options (all when None,
    none when ""), so a command imports the settings of the one subcommand it runs."""
    sub = parser.add_subparsers(dest=dest, required=True)
    for name, (text, build) in table.items():
        p = sub.add_parser(name, help=text)
        if wanted in (None, name):
            build(p)


def print_json(d: dict) -> None:
    print(json.dumps(d, indent=2, default=str))


# -- batches of items (foundation.pool) -----------------------------------------------------------------------------


def pool_options(p: argparse.ArgumentParser) -> None:
    from foundation.pool import default_workers

    p.add_argument("--workers", type=int, default=None,
                   help=f"worker processes for the items (default: the cores here, {default_workers()}; 0: one after "
                        "another in this process)")
    p.add_argument("--ray", default=None, metavar="ADDRESS",
                   help="run the items as Ray tasks: 'local' starts Ray on this machine, 'auto' or HOST:PORT joins "
                        "a running cluster (docs/scale.md: beyond one machine)")


def pool_settings(a):
    from foundation.pool import PoolSettings, default_workers

    cores = default_workers()
    workers = a.workers if a.workers is not None else cores
    # One Dr.Jit thread per worker when the workers fill the cores: results are then bit-identical to a serial
    # run with one thread, wherever an item ran; fewer workers get the cores' share each.
    threads = 1 if a.ray else (max(1, cores // workers) if workers >= 1 else 0)
    return PoolSettings(workers=max(workers, 1) if a.ray else workers, ray=a.ray, threads=threads)


def run_batch(items, a, desc: str) -> int:
    from foundation.pool import ray_shutdown, run_items

    try:
        report = run_items(items, pool_settings(a), desc=desc)
    finally:
        ray_shutdown()
    print(json.dumps({"items": len(report.results), "done": len(report.ran), "skipped": len(report.skipped),
                      "failed": [{"item": r.key, "error": r.error} for r in report.failed],
                      "seconds": report.seconds}, indent=2))
    for r in report.failed:
        print(f"photoreal: error: {r.key}: {r.error}", file=sys.stderr)
    return 1 if report.failed else 0


def out_opt(p: argparse.ArgumentParser, *flags: str, kind: str = "folder", marker: str | None = None,
            **kw) -> argparse.Action:
    """An output flag under the one output rule (:class:`foundation.files.OutputPath`): checked as the command line is
    parsed; a folder is claimed for this subcommand before it runs, and given back if the run fails at once."""
    kw.setdefault("metavar", "FILE" if kind == "file" else "DIR")
    return p.add_argument(*flags, type=output_type(p, kind, marker), **kw)


def output_type(p: argparse.ArgumentParser, kind: str = "folder", marker: str | None = None,
                legacy: tuple[str, ...] = ()):
    """The argparse ``type`` of an output flag of the (sub)command ``p``."""
    from foundation.files import OutputPath

    command = p.prog.split(" ", 1)[1] if " " in p.prog else p.prog  # "photoreal btf fit" → "btf fit"
    return OutputPath(kind, command, marker, legacy)


def check_out_dir(path: str, flag: str = "--out-dir") -> Path:
    """A folder for many outputs: absent or a folder (items already in it are skipped, so a batch resumes)."""
    from foundation.files import check_output_file

    p = Path(path)
    if p.exists() and not p.is_dir():
        raise usage(f"{flag} {p}: is a file, expected a folder")
    check_output_file(p / ".probe", flag)
    return p

# -- errors ---------------------------------------------------------------------------------------------------------


def usage(msg: str):
    from foundation.errors import UsageError

    return UsageError(msg)

def benchmark_dirs(paths: list[str], marker: str) -> list[Path]:
    """The benchmark folders named, a folder of benchmarks standing for the benchmarks inside it."""
    out = []
    for p in map(Path, paths):
        if p.is_dir() and not (p / marker).is_file():
            inside = sorted(q.parent for q in p.glob(f"*/{marker}"))
            out += inside or [p]  # nothing inside: keep it, so that loading names it
        else:
            out.append(p)
    return out
