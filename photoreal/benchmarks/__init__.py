"""`photoreal bench …`: one module per benchmark, one protocol, one registry.

A benchmark module defines

=====================================  ===========================================================================
``SETTINGS``                           its settings dataclass (every flag is a field: :func:`photoreal.options.opt`)
``run(s, work, pool, show_progress)``  the measurement; returns the result dict (JSON-ready)
``SUMMARY`` or ``summary(result)``     what a person reads on the terminal (keys of the result, or a dict)
``options(parser)`` (optional)         its flags; default: one per settings field
``charts(result, json, work)``     figures beside the JSON (optional); returns ``{key: path}``, merged into the result
``POOL = True`` (optional)             it fans items out: it takes ``--workers`` / ``--ray``
``WORK = False`` (optional)            it keeps nothing between runs (no work folder)
``work_name(s)`` (optional)            its work folder's name (default ``<name>_work``)
=====================================  ===========================================================================

and one line in :data:`REGISTRY`. :func:`run_benchmark` owns the rest, the same for every benchmark: the ``--json``
check before any work, the work folder (``<name>_work`` beside the JSON: kept, so a rerun re-reads what is
finished; ``--clean`` removes it after the result is written), the result file, the charts and Ray's shut-down.
The CLI (``photoreal bench NAME``), ``photoreal bench all`` (``make bench``) and the demo's tables loop over the
registry. Speed is always a ratio against a reference measured in the same run.
"""

from __future__ import annotations

import importlib
import shutil
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType


@dataclass(frozen=True)
class Entry:
    module: str  #: the benchmark's module (imported only when it runs or its flags are built)
    help: str  #: one line for `photoreal bench --help`
    in_all: bool = True  #: `photoreal bench all` (`make bench`) runs it with its defaults


REGISTRY: dict[str, Entry] = {
    "plugins": Entry(f"{__name__}.plugins", "ggx_uv vs builtin principled on the same scene"),
    "face": Entry(f"{__name__}.face", "face fitting: accuracy vs time over UV resolution, stability"),
    "morph": Entry(f"{__name__}.morph.bench", "geometry morphing: accuracy vs time, speed vs the tutorial recipe, "
                                        "stability, the generalisation suite, the benchmark's framing"),
    "morph-seeds": Entry(f"{__name__}.morph.seeds", "the morph suite over several draws: `bench morph --parts suite "
                         "--seed K` results, one per seed, summed up per mesh (mean, worst, at how many seeds every "
                         "target holds) with a chart", in_all=False),
    "morph-light-draws": Entry(f"{__name__}.morph.light_draws", "every light choice of `bench morph --parts suite` "
                               "results scored again under other draws of the light estimate: how much of each "
                               "choice the estimate's own noise decides", in_all=False),
    "btf": Entry(f"{__name__}.btf", "neural BTF: universal vs NeuMIP, width × texture sweep, render time"),
    "gan": Entry(f"{__name__}.gan", "GAN refinement stages on held-out views"),
    "scale": Entry(f"{__name__}.scale", "a batch of renders serially, on a process pool and on Ray (identical?)"),
    "diffrender": Entry(f"{__name__}.diffrender.bench", "diffusion renderer vs PBR recomposition and the GANs on held-out "
                        "views; decomposition network, ablations, steps × size sweep, an unseen mesh"),
    "matdiff": Entry(f"{__name__}.matdiff", "material diffusion: keyword/exemplar conditioning, KID vs baselines, "
                     "memorisation, seams, speed, ablations, dataset sweep (builds/continues its dataset first)"),
    "face-learned": Entry(f"{__name__}.face_learned", "learned face stages vs the optimisation baseline on a "
                          "held-out scan: completion, decomposition variants, super-resolution, cross-model fit, "
                          "end to end"),
    "face-light": Entry(f"{__name__}.face_light", "the face fit under unknown environment light (principled, "
                        "HDRIs, interreflection) per light model: directional vs spherical-harmonic orders, with "
                        "each order's model floor"),
    "capture": Entry(f"{__name__}.capture", "real captures (skull, ruins) through structure from motion on the CPU, "
                     "and the held-out-photo scores of the coarse mesh"),
    "startup": Entry(f"{__name__}.startup", "`photoreal … --help` and argument errors: median wall seconds, each "
                     "in a fresh interpreter, beside a bare Python"),
}


def load(name: str) -> ModuleType:
    return importlib.import_module(REGISTRY[name].module)


def json_name(name: str) -> str:
    """The result file `photoreal bench all` writes and the demo reads: ``face-learned`` → ``face_learned.json``."""
    return name.replace("-", "_") + ".json"


def work_folder(name: str, s, json_path: str | Path) -> Path | None:
    """Where the benchmark keeps its work: ``<name>_work`` beside the JSON (or the module's ``work_name(s)``)."""
    mod = load(name)
    if not getattr(mod, "WORK", True):
        return None
    folder = mod.work_name(s) if hasattr(mod, "work_name") else f"{name.replace('-', '_')}_work"
    return Path(json_path).parent / folder


def summary(name: str, result: dict) -> dict:
    mod = load(name)
    if hasattr(mod, "summary"):
        return mod.summary(result)
    return {k: result[k] for k in mod.SUMMARY if k in result}


def run_benchmark(name: str, s, json_path: str | Path, pool=None, clean: bool = False,
                  show_progress: bool = True) -> dict:
    """Run one benchmark by the protocol: check ``json_path`` before any work, run in its work folder, add the
    charts, write the result; ``clean`` removes the work folder once the result is written."""
    from foundation.files import check_output_file, write_json
    from foundation.pool import ray_shutdown

    mod = load(name)
    out = check_output_file(json_path, "--json")
    work = work_folder(name, s, out)
    try:
        result = mod.run(s, work, pool, show_progress)
    finally:
        if getattr(mod, "POOL", False):
            ray_shutdown()
    if hasattr(mod, "charts"):
        result.update(mod.charts(result, out, work))
    write_json(out, result)
    if clean and work is not None:
        shutil.rmtree(work, ignore_errors=True)
    return result
