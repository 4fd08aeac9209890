"""`photoreal bench morph`: geometry morphing — accuracy vs time, speed vs the tutorial recipe, stability."""

from __future__ import annotations

import shutil
import tempfile
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

from foundation import validate
from foundation.assets import ARMADILLO
from foundation.progress import progress_bar
from foundation.records import to_json
from inverse.morph import (MorphBenchmarkSettings, MorphResult, MorphSettings, load_morph_benchmark,
                           make_morph_benchmark, run_gcn_morph, run_morph)


@dataclass
class MorphBenchSettings:
    cases: tuple[str, ...] = ("village", "armadillo")
    iterations: int = 300
    sweep_vertices: tuple[int, ...] = (2000, 4000, 8000, 16000)
    sweep_iterations: int = 120
    speed_vertices: int = 10_000
    speed_iterations: int = 60
    speed_views: int = 4
    speed_resolution: int = 128
    baseline_spp: int = 16  #: the tutorial recipe's samples per pixel
    stability_iterations: int = 80
    seed: int = 0

    def __post_init__(self):
        for name in ("iterations", "sweep_iterations", "speed_iterations", "stability_iterations"):
            validate.integer(name, getattr(self, name), 1)
        for n in (*self.sweep_vertices, self.speed_vertices):
            validate.integer("sweep_vertices", n, 100)
        validate.integer("speed_views", self.speed_views, 1)
        validate.integer("speed_resolution", self.speed_resolution, 8, 4096)
        validate.integer("baseline_spp", self.baseline_spp, 1)
        validate.seed("seed", self.seed)


def source(case: str) -> str:
    """A benchmark case: "village", "armadillo" (bundled) or a mesh file."""
    return "village" if case == "village" else str(ARMADILLO if case == "armadillo" else case)


def _summary(m: MorphResult) -> dict:
    keys = ("chamfer_input", "chamfer_morphed", "chamfer_reduction", "psnr_heldout_input", "psnr_heldout_morphed",
            "spikes", "inverted_triangles", "spike_vertices", "seconds", "vertices")
    out = {k: getattr(m, k) for k in keys}
    out["skipped_steps"] = m.training.skipped_steps
    out.update(inverted_before_repair=m.repair.inverted_before_repair if m.repair else None,
               repaired_vertices=m.repair.repaired_vertices if m.repair else None,
               repair_max_move=m.repair.repair_max_move if m.repair else None,
               planarity_weight=m.planarity.weight if m.planarity else None,
               dominant_plane_fraction=m.planarity.dominant_plane_fraction if m.planarity else None)
    return out


def bench_case(case: str, work: Path, s: MorphBenchSettings, bar) -> dict:
    bench = load_morph_benchmark(make_morph_benchmark(source(case), work / f"bench_{case}",
                                                      MorphBenchmarkSettings(seed=s.seed), show_progress=False))
    main = run_morph(bench, work / f"{case}_main", MorphSettings(iterations=s.iterations, seed=s.seed),
                     show_progress=False)
    bar.update(1)
    sweep = []
    for n in s.sweep_vertices:
        m = run_morph(bench, work / f"{case}_v{n}", MorphSettings(iterations=s.sweep_iterations, target_vertices=n,
                                                                  seed=s.seed), show_progress=False)
        sweep.append({"mesh_vertices": m.vertices, "target_vertices": n, "chamfer": m.chamfer_morphed,
                      "psnr": m.psnr_heldout_morphed, "seconds": m.seconds})
        bar.update(1)
    best = min(r["chamfer"] for r in sweep)
    chosen = min(r["mesh_vertices"] for r in sweep if r["chamfer"] <= 1.05 * best)

    # Speed: our recipe vs the tutorial's, same mesh (~10k vertices), views, resolution.
    base = MorphSettings(iterations=s.speed_iterations, views_per_step=s.speed_views,
                         resolution=s.speed_resolution, target_vertices=s.speed_vertices, seed=s.seed)
    ours = run_morph(bench, work / f"{case}_speed_ours", base, show_progress=False)
    tutorial = run_morph(bench, work / f"{case}_speed_tutorial",
                         replace(base, spp=s.baseline_spp, lambda_=25.0, lr=0.05 * 10 / 2, lr_final=1.0,
                                 repair_flips=False, planarity_weight=0.0),
                         show_progress=False)
    bar.update(2)
    # Stability (shorter runs): batch sizes, plain Adam vs large steps, few views, GCN image-only.
    stab = {}
    # raw method behaviour: no final unfolding, so folds and spikes show as they are
    short = MorphSettings(iterations=s.stability_iterations, seed=s.seed, repair_flips=False)
    for name, st in {"batch_1": replace(short, views_per_step=1), "batch_3": short,
                     "batch_6": replace(short, views_per_step=6),
                     "plain_adam": replace(short, parameterisation="plain", lr=0.05),
                     "large_steps_lambda25": replace(short, lambda_=25.0)}.items():
        stab[name] = _summary(run_morph(bench, work / f"{case}_stab_{name}", st, show_progress=False))
        bar.update(1)
    if main.planarity and main.planarity.weight:  # the prior's ablation, where the auto rule switched it on
        stab["no_planarity_prior"] = _summary(run_morph(bench, work / f"{case}_stab_noplan",
                                                        replace(short, planarity_weight=0.0), show_progress=False))
    bar.update(1)
    few = load_morph_benchmark(bench.path)
    few.meta = replace(few.meta, train=few.meta.train[:4])  # four neighbouring views only: border regions unseen
    stab["few_views_4"] = _summary(run_morph(few, work / f"{case}_stab_few", short, show_progress=False))
    bar.update(1)
    stab["gcn_image_loss_only"] = _summary(run_gcn_morph(bench, work / f"{case}_stab_gcn",
                                                         replace(short, iterations=min(60, short.iterations)),
                                                         show_progress=False))
    bar.update(1)
    for row in stab.values():
        row["converged"] = bool(row["chamfer_morphed"] < row["chamfer_input"]
                                and row["psnr_heldout_morphed"] > row["psnr_heldout_input"])
    return {
        **_summary(main),
        "s_per_iter_10k_4views_128": ours.seconds / s.speed_iterations,
        "s_per_iter_baseline": tutorial.seconds / s.speed_iterations,
        "speed_ratio": (ours.seconds / s.speed_iterations) / (tutorial.seconds / s.speed_iterations),
        "chamfer_ours_speed_run": ours.chamfer_morphed, "chamfer_baseline_speed_run": tutorial.chamfer_morphed,
        "speed_vertices": ours.vertices,
        "sweep": sweep, "chosen_vertices": chosen, "stability": stab,
        "degradation": to_json(bench.meta.degradation),
    }


def bench_morph(s: MorphBenchSettings, out_dir: Path | None = None, show_progress: bool = True) -> dict:
    work = Path(tempfile.mkdtemp(prefix="photoreal_morph_bench_"))
    per_case = 1 + len(s.sweep_vertices) + 2 + 8
    t0 = time.perf_counter()
    try:
        with progress_bar(total=per_case * len(s.cases), desc="bench morph", unit="run",
                          disable=not show_progress) as bar:
            cases = {c: bench_case(c, work, s, bar) for c in s.cases}
    finally:
        shutil.rmtree(work, ignore_errors=True)
    first = cases[s.cases[0]]
    result = {**{k: first[k] for k in ("chamfer_input", "chamfer_morphed", "psnr_heldout_input",
                                        "psnr_heldout_morphed", "spikes", "s_per_iter_10k_4views_128",
                                        "s_per_iter_baseline", "sweep", "chosen_vertices")},
              "chamfer_reduction": first["chamfer_reduction"], "cases": cases, "settings": asdict(s),
              "seconds": time.perf_counter() - t0}
    if out_dir is not None:
        result["chart"] = str(morph_chart(result, Path(out_dir) / "morph_speed_accuracy.png"))
    return result


def morph_chart(result: dict, path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from foundation.imageio import save_figure

    fig, ax = plt.subplots(1, 2, figsize=(10, 3.8))
    for case, r in result["cases"].items():
        x = [p["seconds"] for p in r["sweep"]]
        rel = [p["chamfer"] / r["chamfer_input"] for p in r["sweep"]]
        ax[0].plot(x, rel, "o-", label=case)
        ax[1].plot(x, [p["psnr"] for p in r["sweep"]], "o-", label=case)
        for p, xi, yi in zip(r["sweep"], x, rel):
            ax[0].annotate(f"{p['mesh_vertices']}", (xi, yi), textcoords="offset points", xytext=(3, 3), fontsize=7)
    ax[0].axhline(0.5, color="gray", ls="--", lw=0.8)
    ax[0].set_ylabel("Chamfer / input Chamfer")
    ax[1].set_ylabel("held-out PSNR (dB)")
    for a in ax:
        a.set_xlabel("morph wall time (s, 2 CPU cores)")
        a.grid(alpha=0.3)
        a.legend()
    fig.suptitle("geometry morphing: accuracy vs time over mesh resolution (labels: vertices)")
    return save_figure(fig, path)

