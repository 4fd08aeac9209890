"""`run_morph`: a morph run of a benchmark's coarse mesh, with the validation photos' choices first where the
settings leave any (:mod:`.select`), else the optimisation stage as it is (:mod:`.stage`)."""

from __future__ import annotations

from pathlib import Path

from .benchmark import MorphBenchmark
from .results import MorphResult
from .select import run_selected, selection_point
from .settings import MorphSettings
from .stage import run_stage


def run_morph(bench: MorphBenchmark, out: str | Path, s: MorphSettings | None = None,
              show_progress: bool = True, budget_iterations: int | None = None) -> MorphResult | None:
    """Morph the benchmark's coarse mesh; write morphed.ply, held-out renders, metrics.json; resumable.

    ``budget_iterations`` stops after that many iterations *in this call* (e.g. a cluster job's
    wall-time slice) with a checkpoint written, and returns None; calling again with the same
    settings continues exactly.
    """
    s = s or MorphSettings()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    if selection_point(s) is not None:
        return run_selected(bench, out, s, show_progress, budget_iterations)
    return run_stage(bench, out, s, show_progress, budget_iterations)
