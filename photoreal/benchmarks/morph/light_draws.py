"""`photoreal bench morph-light-draws`: every light choice of ``bench morph --parts suite`` results (their work
folders kept beside them) scored again under other draws of the light estimate."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from foundation import validate
from inverse.morph import MorphSettings, light_choice_draws, load_morph_benchmark

from .bench import SILHOUETTE_FIELDS, MorphBenchSettings, normals_tag, work_name
from .seeds import recorded_run_settings, suite_of

def light_draws(paths: list[str | Path], draws: int, show_progress: bool = True) -> dict:
    """Every light choice of ``bench morph --parts suite`` results (their work folders beside them)
    scored again under ``draws`` draws of the light estimate (:func:`inverse.morph.select.light_choice_draws`; draw 0
    is the choice's own): per mesh-draw the light run's advantage at each draw and its spread, and the choices
    another draw of the estimate would overturn."""
    from tqdm import tqdm

    from foundation.errors import UsageError
    from foundation.files import read_json

    validate.integer("draws", draws, 1, 64)
    todo = []
    for p in map(Path, paths):
        data = read_json(p, "bench morph result")
        seed, suite = suite_of(p, data)
        got = recorded_run_settings(data["settings"])
        bs = MorphBenchSettings(seed=seed, truth_normals=got["truth_normals"])
        work, tag = p.parent / work_name(bs), normals_tag(bs)
        if not work.is_dir():
            raise UsageError(f"{p}: its work folder {work} is gone (the bench keeps it unless run with --clean)")
        s = MorphSettings(iterations=got["iterations"], seed=seed, adam_quantile=got["adam_quantile"], lr=got["lr"],
                          step_select_quantile=got["step_select_quantile"], saturation=got["saturation"],
                          **{k: got[k] for k in SILHOUETTE_FIELDS})
        todo += [(f"{n}@{seed}", work / f"bench_{n}{tag}", work / f"suite_{n}{tag}", s) for n in suite["meshes"]]
    todo = [t for t in todo if (t[2] / "lambda_select" / "light_decision.json").is_file()]  # others made none
    rows = {key: light_choice_draws(load_morph_benchmark(bench), out, s, draws)
            for key, bench, out, s in tqdm(todo, desc="light choices", disable=not show_progress)}
    if not rows:
        raise UsageError("no light choice in these results' work folders (made where the photos were asked, "
                         "light_select_every > 0)")
    sd = np.array([r["advantage_sd"] for r in rows.values() if r["advantage_sd"] is not None])
    return {"draws": draws, "rows": rows,
            # draw 0 is the choice's own: equal to its stored score up to the threads' summation order (~1e-7)
            "draw0_vs_stored_max": max((abs(r["advantage"][0] - r["stored_advantage"]) for r in rows.values()
                                        if r["stored_advantage"] is not None), default=None),
            "advantage_sd": {"min": float(sd.min()), "median": float(np.median(sd)), "max": float(sd.max())}
            if len(sd) else None,
            "margin": sorted({r["margin"] for r in rows.values()}),
            "overturned_by_a_draw": {k: r["draws_against_stored"] for k, r in rows.items()
                                     if r["draws_against_stored"]}}


def light_draws_chart(result: dict, path: Path) -> Path:
    """Per mesh-draw, the light run's validation advantage at each draw of the estimate (the choice's own filled),
    the margin it had to clear as a line: how close each choice sits to the line against the draws' spread."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from foundation.imageio import save_figure

    keys = list(result["rows"])
    fig, ax = plt.subplots(figsize=(max(8.0, 0.32 * len(keys) + 2), 4))
    for x, k in enumerate(keys):
        adv = np.array(result["rows"][k]["advantage"]) * 100
        ax.plot([x] * (len(adv) - 1), adv[1:], "o", ms=4, mfc="none", color="tab:blue")
        ax.plot([x], adv[:1], "o", ms=5, color="tab:blue" if result["rows"][k]["kept"] else "0.4")
    for m in result["margin"]:
        ax.axhline(m * 100, color="tab:red", ls="--", lw=0.8, label=f"margin {m * 100:g} %")
    ax.axhline(0, color="0.5", lw=0.5)
    ax.set_xticks(range(len(keys)), keys, rotation=60, ha="right", fontsize=7)
    ax.set_ylabel("light run's validation advantage (%)")
    ax.grid(alpha=0.3, axis="y")
    ax.legend(fontsize=7)
    sd = result["advantage_sd"]
    fig.suptitle(f"light choices under {result['draws']} draws of the estimate (filled: the choice's own; blue: kept)"
                 + (f"; SD {sd['min'] * 100:.2f}–{sd['max'] * 100:.2f} points" if sd else ""), fontsize=9)
    return save_figure(fig, path)




# -- the benchmark protocol (photoreal.benchmarks) -------------------------------------------------------------------


@dataclass
class LightDrawsSettings:
    results: tuple[str, ...] = ()  #: bench morph JSON files with a suite, their work folders beside them
    draws: int = 4  #: draws of the estimate per run, the choice's own first

    def __post_init__(self):
        validate.integer("draws", self.draws, 1, 64)


SETTINGS = LightDrawsSettings
WORK = False
SUMMARY = ("draws", "draw0_vs_stored_max", "advantage_sd", "overturned_by_a_draw")


def run(s: LightDrawsSettings, work, pool, show_progress: bool) -> dict:
    return light_draws(s.results, s.draws, show_progress)


def charts(result: dict, json_path: Path, work: Path | None) -> dict:
    out = Path(json_path)
    return {"chart": str(light_draws_chart(result, out.with_name(out.stem + ".png")))}


def options(p) -> None:
    from photoreal.options import opt

    p.add_argument("results", nargs="+", help="bench morph JSON files with a suite, their work folders kept")
    opt(p, LightDrawsSettings, "draws")
