"""Morph runs by paths: the unit that morphing many benchmarks (or a bench's sweep) fans out to workers."""

from __future__ import annotations

import dataclasses

from foundation.files import write_json
from foundation.records import to_json

from .benchmark import load_morph_benchmark
from .run import MorphResult, MorphSettings, run_morph


def run_item(bench_dir: str, out: str, s: MorphSettings, gcn: bool = False, train: list[int] | None = None,
             json_path: str | None = None) -> MorphResult:
    """One morph run by paths (the unit that morphing many benchmarks, or a bench's sweep, fans out).

    ``train`` replaces the benchmark's training views (e.g. a few-views stability case); ``json_path`` also
    writes the metrics there. Resumable like :func:`run_morph`.
    """
    from .gcn import run_gcn_morph  # torch: only where the GCN variant runs

    bench = load_morph_benchmark(bench_dir)
    if train is not None:
        bench.meta = dataclasses.replace(bench.meta, train=list(train))
    r = (run_gcn_morph if gcn else run_morph)(bench, out, s, show_progress=False)
    if json_path:
        write_json(json_path, to_json(r))
    return r


def load_result(metrics_path: str) -> MorphResult:
    """A finished run's ``metrics.json`` as a :class:`MorphResult` (the value of a batch item done before)."""
    from foundation.files import read_json
    from foundation.records import from_json

    return from_json(MorphResult, read_json(metrics_path, "morph metrics"), str(metrics_path))
