"""`photoreal bench startup`: how long `photoreal … --help` and an argument error take, beside a bare Python.

Each command runs in a fresh interpreter, as a user starts it; the rounds alternate the order of the commands, and
the figure kept is the median wall time. The bare interpreter (``python -c pass``) runs in the same rounds, so
``vs_python`` is a ratio that a loaded machine moves less than the seconds.
"""

from __future__ import annotations

import os
import statistics
import subprocess
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

from foundation import validate
from foundation.progress import progress_bar

TARGET_S = 1.0  #: help and argument errors answer within this (wall seconds)


@dataclass
class StartupBenchSettings:
    repetitions: int = 3  #: runs of each command (the median is kept)
    target_s: float = TARGET_S

    def __post_init__(self):
        validate.integer("repetitions", self.repetitions, 1, 100)
        validate.positive("target_s", self.target_s)


def commands() -> dict[str, list[str]]:
    """The command lines timed: the top-level help, each group's and each subcommand's help, two argument errors."""
    import argparse

    from photoreal.cli import GROUPS, build_parser

    out = {"--help": ["--help"]}
    groups = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction)).choices
    for g in GROUPS:
        out[f"{g} --help"] = [g, "--help"]
        subs = [a for a in groups[g]._actions if isinstance(a, argparse._SubParsersAction)]
        for name in (subs[0].choices if subs else ()):
            out[f"{g} {name} --help"] = [g, name, "--help"]
    out["render (no scene: usage error)"] = ["render"]
    out["morph run --iterations many (usage error)"] = ["morph", "run", "--iterations", "many"]
    return out


def _entry() -> list[str]:
    """The installed `photoreal` script beside this interpreter, else ``python -m photoreal.cli``."""
    script = Path(sys.executable).parent / "photoreal"
    return [str(script)] if script.is_file() else [sys.executable, "-m", "photoreal.cli"]


def _time(argv: list[str]) -> tuple[float, int]:
    t = time.perf_counter()
    r = subprocess.run(argv, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, timeout=300,
                       env={**os.environ, "PHOTOREAL_DEBUG": ""})
    return time.perf_counter() - t, r.returncode


def bench_startup(s: StartupBenchSettings, show_progress: bool = True) -> dict:
    cmds = commands()
    entry = _entry()
    runs: dict[str, list[float]] = {name: [] for name in cmds}
    codes: dict[str, int] = {}
    python: list[float] = []
    names = list(cmds)
    with progress_bar(total=s.repetitions * (len(names) + 1), desc="bench startup", disable=not show_progress) as bar:
        for k in range(s.repetitions):
            python.append(_time([sys.executable, "-c", "pass"])[0])
            bar.update(1)
            for name in (names if k % 2 == 0 else names[::-1]):
                secs, codes[name] = _time(entry + cmds[name])
                runs[name].append(secs)
                bar.update(1)
    py = statistics.median(python)
    table = {}
    for name in names:
        med = statistics.median(runs[name])
        table[name] = {"median_s": med, "min_s": min(runs[name]), "vs_python": med / py, "exit_code": codes[name],
                       "within_target": med <= s.target_s}
    slow = {n: r["median_s"] for n, r in table.items() if not r["within_target"]}
    return {"settings": asdict(s), "entry": " ".join(Path(e).name for e in entry), "python_s": py,
            "commands": table, "slowest": max(table, key=lambda n: table[n]["median_s"]),
            "all_within_target": not slow, "over_target": slow, "cores": os.cpu_count()}


# -- the benchmark protocol (photoreal.benchmarks) -------------------------------------------------------------------

SETTINGS = StartupBenchSettings
WORK = False


def run(s: StartupBenchSettings, work, pool, show_progress: bool) -> dict:
    return bench_startup(s, show_progress)


def summary(result: dict) -> dict:
    return {"python_s": result["python_s"], "slowest": result["slowest"],
            "all_within_target": result["all_within_target"],
            "median_s": {n: round(r["median_s"], 3) for n, r in result["commands"].items()}}


def options(p) -> None:
    from photoreal.options import opt

    opt(p, StartupBenchSettings, "repetitions")
    opt(p, StartupBenchSettings, "target_s", "--target", help="seconds a command must answer within")
