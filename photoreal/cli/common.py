"""What every command group shares: options filled from settings dataclasses, batches on a pool, output
folders, usage errors."""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path
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
    import inspect

    return inspect.signature(func).parameters[name].default


def opt(p: argparse.ArgumentParser, cls: type, name: str, *flags: str, help: str = "", **kw) -> None:
    """``--flag`` filling ``cls.name``; its default (shown in --help) is the dataclass's."""
    default = default_of(cls, name)
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
    p.add_argument(*(flags or (f"--{name.replace('_', '-')}",)), dest=name, default=default, help=text, **kw)


def settings_from(cls: type, a: argparse.Namespace, **extra):
    """``cls`` from the parsed options that name its fields (plus ``extra``)."""
    names = {f.name for f in dataclasses.fields(cls)}
    kw = {k: v for k, v in vars(a).items() if k in names}
    for k, v in list(kw.items()):
        if isinstance(default_of(cls, k), tuple) and isinstance(v, list):
            kw[k] = tuple(v)
    kw.update(extra)
    return cls(**kw)


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
                        "a running cluster (README: beyond one machine)")


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
