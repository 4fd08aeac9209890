"""`photoreal bench morph`: geometry morphing — accuracy vs time, speed vs the tutorial recipe, stability."""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from foundation import validate
from foundation.assets import ARMADILLO, pymeshlab_sample
from foundation.pool import Item, PoolSettings, run_items
from foundation.records import to_json
from inverse.morph import (KINDS, MORPH_SEED_MAX, SUITE, TRUTH_NORMALS, UNSEEN, Candidate, MorphBenchmarkSettings, MorphResult, MorphSettings, MorphStage,
                           candidate_settings, load_morph_benchmark, make_morph_benchmark, run_morph, silhouette_margins,
                           start_mesh, suite_mesh, benchmark_surface_errors, truth_start_benchmark)

from .charts import morph_chart, suite_chart


#: the fields of the silhouette loss (and its boundary samples) that the bench passes to every run as they are
SILHOUETTE_FIELDS = ("mask_weight", "mask_every", "mask_downsample", "boundary_spp")


@dataclass
class MorphBenchSettings:
    #: what to run: "cases" (village and armadillo: main run, speed vs the tutorial, vertex sweep, stability),
    #: "suite" (the generalisation suite: one run per mesh at the same defaults), "framing" (views and photo
    #: resolution of the benchmark, swept on the first suite mesh), "floor" (each suite mesh's morph started at
    #: its ground truth: how far the method drifts from the answer; not in the default parts), "iteration" (the
    #: cost of one iteration of today's defaults against the recipe issue 17 measured, same mesh and vertices,
    #: timed in turns in this process)
    parts: tuple[str, ...] = ("cases", "suite", "framing", "iteration")
    cases: tuple[str, ...] = ("village", "armadillo")
    #: suite meshes (inverse.morph.suite); "village"/"armadillo" and the ``UNSEEN`` ones may be added
    suite: tuple[str, ...] = SUITE
    framing_views: tuple[int, ...] = (8, 16, 32)
    framing_resolutions: tuple[int, ...] = (64, 128, 192)
    iterations: int = 600  #: the cap of the main and suite runs (they stop early: MorphSettings.early_stop)
    sweep_vertices: tuple[int, ...] = (2000, 4000, 8000, 16000)
    sweep_iterations: int = 120
    speed_vertices: int = 10_000
    speed_iterations: int = 60
    speed_views: int = 4
    speed_resolution: int = 128
    baseline_spp: int = 16  #: the tutorial recipe's samples per pixel
    stability_iterations: int = 80
    floor_iterations: int = 100  #: iterations of the truth-start runs ("floor"), constant λ
    cost_mesh: str = "village"  #: the "iteration" part's mesh (a suite mesh, "village" or "armadillo")
    cost_iterations: int = 25  #: steps per timed block of the "iteration" part
    cost_rounds: int = 3  #: timed blocks per recipe, interleaved (the median is reported)
    #: the "iteration" part's time to quality: the issue's recipe's iterations (constant length) and the cap of
    #: today's defaults (they stop early), both on ``cost_mesh`` in this process; 0: not measured
    ttq_iterations: int = 600
    #: every benchmark's draw (photos' noise, views) and every run's render seeds; another seed works in
    #: ``OUT/morph_work_seed<k>``, so that it never resumes from (or overwrites) another draw's finished runs
    seed: int = 0
    #: the suite's and the floor's benchmarks photograph their truth with these shading normals
    #: (:attr:`~inverse.morph.MorphBenchmarkSettings.truth_normals`; "face": folders ``*_face``, beside the others)
    truth_normals: str = "vertex"
    #: the suite's runs decide tied prior choices this way (:attr:`~inverse.morph.MorphSettings.prior_ties`)
    prior_ties: str = MorphSettings.prior_ties
    #: the suite's runs scale their steps by this quantile of Adam's second moments
    #: (:attr:`~inverse.morph.MorphSettings.adam_quantile`)
    adam_quantile: float = MorphSettings.adam_quantile
    lr: float = MorphSettings.lr  #: the suite's runs' position learning rate (:attr:`~inverse.morph.MorphSettings.lr`)
    #: the suite's runs' λ warm-up share, which sets where the photos' choices are made
    #: (:attr:`~inverse.morph.MorphSettings.lambda_warmup`)
    lambda_warmup: float = MorphSettings.lambda_warmup
    #: the suite's runs ask the photos about this quantile step (:attr:`~inverse.morph.MorphSettings.step_select_quantile`;
    #: 1: no such choice, the suite before 2026-11-28)
    step_select_quantile: float = MorphSettings.step_select_quantile
    #: the suite's runs leave pixels brighter than this × the photos' 99th percentile out of the loss
    #: (:attr:`~inverse.morph.MorphSettings.saturation`; 0: every pixel, the suite before 2026-11-28 evening)
    saturation: float = MorphSettings.saturation
    #: the suite's runs add a silhouette L1 at this weight (:attr:`~inverse.morph.MorphSettings.mask_weight`; 0: photos
    #: only, every suite before 2026-11-29 evening)
    mask_weight: float = MorphSettings.mask_weight
    #: the suite's runs' silhouette samples per pixel (:attr:`~inverse.morph.MorphSettings.boundary_spp`; None:
    #: the image's ``spp``)
    boundary_spp: int | None = MorphSettings.boundary_spp
    mask_every: int = MorphSettings.mask_every  #: (:attr:`~inverse.morph.MorphSettings.mask_every`)
    mask_downsample: int = MorphSettings.mask_downsample  #: (:attr:`~inverse.morph.MorphSettings.mask_downsample`)

    def silhouette_fields(self) -> dict:
        """The silhouette loss's settings and the boundary samples, as the runs' :class:`MorphSettings` take them."""
        return {k: getattr(self, k) for k in SILHOUETTE_FIELDS}

    def suite_settings(self) -> MorphSettings:
        """The suite's runs: today's defaults with this bench's fields of :class:`MorphSettings` (which checks them)."""
        return MorphSettings(iterations=self.iterations, seed=self.seed, prior_ties=self.prior_ties,
                             adam_quantile=self.adam_quantile, lr=self.lr, lambda_warmup=self.lambda_warmup,
                             step_select_quantile=self.step_select_quantile, saturation=self.saturation,
                             **self.silhouette_fields())

    def __post_init__(self):
        validate.one_of("truth_normals", self.truth_normals, TRUTH_NORMALS)
        self.suite_settings()  # the fields copied from MorphSettings are checked by it, once
        for name in ("iterations", "sweep_iterations", "speed_iterations", "stability_iterations",
                     "floor_iterations", "cost_iterations", "cost_rounds"):
            validate.integer(name, getattr(self, name), 1)
        validate.integer("ttq_iterations", self.ttq_iterations, 0)
        for n in (*self.sweep_vertices, self.speed_vertices):
            validate.integer("sweep_vertices", n, 100)
        validate.integer("speed_views", self.speed_views, 1)
        validate.integer("speed_resolution", self.speed_resolution, 8, 4096)
        validate.integer("baseline_spp", self.baseline_spp, 1)
        validate.seed("seed", self.seed, MORPH_SEED_MAX)  # refused before any benchmark is made
        for part in self.parts:
            validate.one_of("parts", part, ("cases", "suite", "framing", "floor", "iteration"))
        validate.one_of("cost_mesh", self.cost_mesh, (*SUITE, *UNSEEN, "village", "armadillo"))
        for name in self.suite:
            validate.one_of("suite", name, (*SUITE, *UNSEEN, "village", "armadillo"))
        for n in self.framing_views:
            validate.integer("framing_views", n, 4, 1024)
        for n in self.framing_resolutions:
            validate.integer("framing_resolutions", n, 16, 4096)


#: the suite's targets (issue 17): per mesh, at the same defaults
TARGETS = {"chamfer_reduction": 0.40, "psnr_gain_db": 3.0}
#: the per-mesh figures a suite's mean is taken over
MEAN_KEYS = ("chamfer_reduction", "psnr_gain_db", "spike_vertices", "inverted_triangles", "seconds", "s_per_iteration")


#: benchmark cases named by one of pymeshlab's sample meshes
PYMESHLAB_CASES = {"bunny": "bunny.obj", "cow": "cow.obj", "airplane": "airplane.obj", "bone": "bone.ply"}


def source(case: str) -> str:
    """A benchmark case: "village", "armadillo" (bundled), one of pymeshlab's sample meshes ("bunny": the Stanford
    bunny, "cow", "airplane", "bone") or a mesh file."""
    if case in PYMESHLAB_CASES:
        return str(pymeshlab_sample(PYMESHLAB_CASES[case]))
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
               colour_prior_weight=m.colour_prior.weight if m.colour_prior else None,
               input_colour_step=m.colour_prior.input_colour_step if m.colour_prior else None,
               dominant_plane_fraction=m.planarity.dominant_plane_fraction if m.planarity else None)
    return out


def bench_case(case: str, work: Path, s: MorphBenchSettings, pool: PoolSettings, show_progress: bool) -> dict:
    """One case. The main run and the speed comparison run here, alone (their seconds are headline figures and a
    ratio); the sweep and the stability runs are independent and go to ``pool`` (seconds of those runs are per-run
    seconds with the pool's threads per run, comparable among themselves)."""
    bench = load_morph_benchmark(make_morph_benchmark(source(case), work / f"bench_{case}",
                                                      MorphBenchmarkSettings(seed=s.seed), show_progress=False))
    main = run_morph(bench, work / f"{case}_main", MorphSettings(iterations=s.iterations, seed=s.seed),
                     show_progress=show_progress)
    # Speed: our recipe vs the tutorial's, same mesh (~10k vertices), views, resolution.
    base = MorphSettings(iterations=s.speed_iterations, views_per_step=s.speed_views,
                         resolution=s.speed_resolution, target_vertices=s.speed_vertices, seed=s.seed,
                         lambda_select=())  # per-iteration cost: one schedule
    ours = run_morph(bench, work / f"{case}_speed_ours", base, show_progress=show_progress)
    tutorial = run_morph(bench, work / f"{case}_speed_tutorial",
                         replace(base, spp=s.baseline_spp, lambda_=25.0, lr=0.05 * 10 / 2, lr_final=1.0,
                                 repair_flips=False, planarity_weight=0.0, colour_prior_weight=0.0,
                                 mask_weight=0.0, boundary_spp=None),  # the tutorial: photos only, one count
                         show_progress=show_progress)

    def item(key: str, settings: MorphSettings, **kw) -> Item:
        return _item(key, bench.path, work / f"{case}_{key}", settings, **kw)

    # Sweep over mesh resolution; stability (shorter runs): batch sizes, plain Adam vs large steps, few views,
    # GCN image-only — raw method behaviour: no final unfolding, so folds and spikes show as they are.
    short = MorphSettings(iterations=s.stability_iterations, seed=s.seed, repair_flips=False, lambda_select=())
    items = [item(f"v{n}", MorphSettings(iterations=s.sweep_iterations, target_vertices=n, seed=s.seed))
             for n in s.sweep_vertices]
    stab_runs = {"batch_1": replace(short, views_per_step=1), "batch_3": short,
                 "batch_6": replace(short, views_per_step=6),
                 "plain_adam": replace(short, parameterisation="plain", lr=0.05),
                 "large_steps_lambda25": replace(short, lambda_=25.0)}
    if main.planarity and main.planarity.weight:  # the prior's ablation, where the auto rule switched it on
        stab_runs["no_planarity_prior"] = replace(short, planarity_weight=0.0)
    if main.colour_prior and main.colour_prior.weight:  # the colour prior's ablation, where the rule switched it on
        stab_runs["no_colour_prior"] = replace(short, colour_prior_weight=0.0)
    items += [item(f"stab_{k}", v) for k, v in stab_runs.items()]
    # four neighbouring views only: border regions unseen
    items.append(item("stab_few_views_4", short, train=bench.meta.train[:4]))
    items.append(item("stab_gcn_image_loss_only", replace(short, iterations=min(60, short.iterations),
                                                          mask_weight=0.0), gcn=True))
    report = run_items(items, pool, desc=f"bench morph {case}", show_progress=show_progress)
    report.raise_if_failed()
    runs = {r.key: r.value for r in report.results}
    sweep = [{"mesh_vertices": runs[f"v{n}"].vertices, "target_vertices": n, "chamfer": runs[f"v{n}"].chamfer_morphed,
              "psnr": runs[f"v{n}"].psnr_heldout_morphed, "seconds": runs[f"v{n}"].seconds} for n in s.sweep_vertices]
    best = min(r["chamfer"] for r in sweep)
    chosen = min(r["mesh_vertices"] for r in sweep if r["chamfer"] <= 1.05 * best)
    stab = {k[5:]: _summary(v) for k, v in runs.items() if k.startswith("stab_")}
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
        "pool": {"workers": pool.workers, "threads_per_run": pool.threads, "ray": pool.ray},
    }


def suite_row(name: str, m: MorphResult) -> dict:
    """One mesh of the suite: the figures of issue 17 and whether each target holds."""
    row = {"kind": KINDS.get(name, "tuned on"), **_summary(m),
           "psnr_gain_db": m.psnr_heldout_morphed - m.psnr_heldout_input,
           "far_moved_vertices": m.far_moved_vertices,
           "facing_against_truth": {"input": m.facing_against_truth_input, "start": m.facing_against_truth_start,
                                    "morphed": m.facing_against_truth},
           "facing_against_truth_area": {"input": m.facing_against_truth_area_input,
                                         "start": m.facing_against_truth_area_start,
                                         "morphed": m.facing_against_truth_area},
           "normal_consistency": {"input": m.normal_consistency_input, "morphed": m.normal_consistency_morphed},
           "pleats": asdict(m.pleats) if m.pleats else None,
           "spike_ironing": asdict(m.spike_ironing) if m.spike_ironing else None,
           "border_turns": asdict(m.border_turns) if m.border_turns else None,
           "iterations": m.iterations, "stopped_early": m.stopped_early, "trace_chamfer_input": m.trace_chamfer_input,
           # per iteration of the run that finished (the candidates not chosen are in ``seconds``, not in this)
           "s_per_iteration": (m.seconds - m.trial_seconds) / max(m.iterations, 1),
           "validation_seconds": m.validation_seconds,
           "lambda_selection": asdict(m.lambda_selection) if m.lambda_selection else None,
           "colour_selection": asdict(m.colour_selection) if m.colour_selection else None,
           "light_selection": asdict(m.light_selection) if m.light_selection else None,
           "step_selection": asdict(m.step_selection) if m.step_selection else None,
           "planarity_weight": m.planarity.weight if m.planarity else None,
           "trace": [{"iteration": t.iteration, "seconds": t.seconds, "validation_l1": t.validation_l1,
                      "chamfer": t.chamfer} for t in m.trace]}
    row["checks"] = {
        "chamfer_reduction": row["chamfer_reduction"] >= TARGETS["chamfer_reduction"],
        "psnr_gain": row["psnr_gain_db"] >= TARGETS["psnr_gain_db"],
        "no_spikes": m.spike_vertices == 0, "no_inverted": m.inverted_triangles == 0,
        # counts differ between the coarse input and the remeshed result: the area fraction compares them
        "facing_not_worse": m.facing_against_truth_area <= m.facing_against_truth_area_input,
        "normal_consistency_up": m.normal_consistency_morphed > m.normal_consistency_input}
    row["passes"] = all(row["checks"].values())
    return row


def where_errors(bench, result: Path) -> dict:
    """:func:`inverse.morph.benchmark_surface_errors` of a result: both Chamfer directions, the truth's border band
    against the rest, the input's error left (in all and per spatial scale), new error; the facing area by the
    training views that see it, the result's and (``_input``) the coarse input's."""
    errs = benchmark_surface_errors(bench, {"morphed": result})
    e, i = errs["morphed"], errs["input"]
    return {**{k: getattr(e, k) for k in ("to_truth", "from_truth", "from_truth_border", "from_truth_interior",
                                          "border_share", "input_error_left", "input_error_correlation",
                                          "new_error_rms", "signed_mean", "input_error_left_by_scale",
                                          "facing_area_by_views", "unseen_area")},
            "facing_area_by_views_input": i.facing_area_by_views, "unseen_area_input": i.unseen_area}


def _item(key: str, bench_dir: Path, out: Path, settings: MorphSettings, **kw) -> Item:
    """One morph run of the pool (resumable: a finished run's metrics.json is its value)."""
    return Item(key, "inverse.morph:run_item", (str(bench_dir), str(out), settings), kw,
                output=str(out / "metrics.json"), loader="inverse.morph:load_result")


def _suite_bench(name: str, work: Path, bs: MorphBenchmarkSettings, tag: str = "") -> Path:
    """The benchmark of one suite mesh; a complete one made earlier from the same file and settings (a resumed
    bench) is kept as it is, with the start remeshes its runs stored (:func:`inverse.morph.stage.stored_remesh`)."""
    from foundation.errors import UsageError
    from foundation.files import file_digest

    src = source(name) if name in ("village", "armadillo") else str(suite_mesh(name, work / "meshes"))
    out = work / f"bench_{name}{tag}"
    try:
        meta = load_morph_benchmark(out).meta
        if meta.settings == bs and meta.source_sha256 == (None if src == "village" else file_digest(src, 64)):
            return out
    except UsageError:
        pass  # none yet, or damaged: made anew
    return make_morph_benchmark(src, out, bs, show_progress=False)


def normals_tag(s: MorphBenchSettings) -> str:
    return "" if s.truth_normals == "vertex" else f"_{s.truth_normals}"


def _suite_benchmark_settings(s: MorphBenchSettings) -> MorphBenchmarkSettings:
    return MorphBenchmarkSettings(seed=s.seed, truth_normals=s.truth_normals)


def bench_suite(work: Path, s: MorphBenchSettings, pool: PoolSettings, show_progress: bool) -> dict:
    """Every suite mesh morphed with the same defaults (the pool runs them side by side)."""
    tag = normals_tag(s)
    benches = {n: _suite_bench(n, work, _suite_benchmark_settings(s), tag) for n in s.suite}
    settings = s.suite_settings()
    for b in benches.values():  # the start remeshes made here, once, before the workers read them (stored_remesh)
        start_mesh(load_morph_benchmark(b), settings)
    items = [_item(n, benches[n], work / f"suite_{n}{tag}", settings) for n in s.suite]
    report = run_items(items, pool, desc="bench morph suite", show_progress=show_progress)
    report.raise_if_failed()
    rows = {r.key: suite_row(r.key, r.value) for r in report.results}
    rows = {n: rows[n] for n in s.suite}
    for n, row in rows.items():  # where the error sits (photoreal morph errors, without its maps)
        row["errors"] = where_errors(load_morph_benchmark(benches[n]), work / f"suite_{n}{tag}" / "morphed.ply")
    mean = {k: float(np.mean([r[k] for r in rows.values()])) for k in MEAN_KEYS}
    return {"meshes": rows, "mean": mean, "targets": TARGETS,
            "all_pass": all(r["passes"] for r in rows.values()),
            "failing": {n: [c for c, ok in r["checks"].items() if not ok] for n, r in rows.items() if not r["passes"]},
            "pool": {"workers": pool.workers, "threads_per_run": pool.threads}}


def floor_row(m: MorphResult, colour_only: MorphResult) -> dict:
    """A truth-start run: how far the morph left the answer, and whether the photos preferred where it went.

    ``colour_only`` is the same start with positions frozen: its validation L1 is what the *truth's* geometry
    reaches once its colours are fitted (the remesh resamples the truth's colours, so the start's L1 is no
    reference). The photos prefer the drift when the free run ends below that while moving away from the truth.
    """
    t0, t1 = m.trace[0], m.trace[-1]
    ref = colour_only.trace[-1].validation_l1
    return {"iterations": m.iterations,
            "chamfer_truth": m.chamfer_input,  # the truth against itself: the estimator's floor
            "chamfer_morphed": m.chamfer_morphed,
            "trace_chamfer": {"start": t0.chamfer, "end": t1.chamfer},  # start = after the remesh
            "validation_l1": {"start": t0.validation_l1, "end": t1.validation_l1, "truth_colours_fitted": ref},
            "photos_prefer_drift": bool(t1.validation_l1 < ref and t1.chamfer > t0.chamfer),
            "facing_against_truth_area": m.facing_against_truth_area,
            "normal_consistency": m.normal_consistency_morphed,
            "psnr_heldout": {"truth": m.psnr_heldout_input, "morphed": m.psnr_heldout_morphed,
                             "truth_colours_fitted": colour_only.psnr_heldout_morphed},
            "spike_vertices": m.spike_vertices, "inverted_triangles": m.inverted_triangles, "seconds": m.seconds}


def bench_floor(work: Path, s: MorphBenchSettings, pool: PoolSettings, show_progress: bool) -> dict:
    """Every suite mesh's morph started at its ground truth (:func:`truth_start_benchmark`), constant λ, beside
    the same run with positions frozen (colours fitted to the truth's geometry)."""
    items, tag = [], normals_tag(s)
    for n in s.suite:
        bench = _suite_bench(n, work, _suite_benchmark_settings(s), tag)
        start = work / f"truth_start_{n}{tag}"
        if not (start / "morph_benchmark.json").is_file():
            truth_start_benchmark(bench, start)
        free = MorphSettings(iterations=s.floor_iterations, lambda_select=(), seed=s.seed)
        items.append(_item(n, start, work / f"floor_{n}{tag}", free))
        items.append(_item(f"{n}:colour_only", start, work / f"floor_{n}{tag}_colour_only", replace(free, lr=0.0)))
    report = run_items(items, pool, desc="bench morph floor (truth start)", show_progress=show_progress)
    report.raise_if_failed()
    runs = {r.key: r.value for r in report.results}
    return {"meshes": {n: floor_row(runs[n], runs[f"{n}:colour_only"]) for n in s.suite},
            "pool": {"workers": pool.workers, "threads_per_run": pool.threads}}


def bench_framing(work: Path, s: MorphBenchSettings, pool: PoolSettings, show_progress: bool) -> dict:
    """Why the benchmark's defaults (views, photo resolution): the first suite mesh made with each, morphed at
    the same defaults. Held-out PSNR of different resolutions compares photos of different sizes: read Chamfer."""
    name = s.suite[0]
    base = MorphBenchmarkSettings(seed=s.seed)
    variants = {f"views_{n}": replace(base, n_views=n) for n in s.framing_views}
    variants.update({f"res_{r}": replace(base, resolution=r) for r in s.framing_resolutions})
    items = []
    for key, bs in variants.items():
        b = _suite_bench(name, work, bs, f"_{key}")
        items.append(_item(key, b, work / f"framing_{name}_{key}", MorphSettings(iterations=s.iterations,
                                                                                   seed=s.seed)))
    report = run_items(items, pool, desc=f"bench morph framing ({name})", show_progress=show_progress)
    report.raise_if_failed()
    runs = {r.key: r.value for r in report.results}
    margins = {}
    for key in variants:
        bench = load_morph_benchmark(work / f"bench_{name}_{key}")
        margins[key] = min(silhouette_margins(bench, list(range(len(bench.meta.cameras)))))

    def row(key: str, **kw) -> dict:
        m = runs[key]
        return {**kw, "chamfer_reduction": m.chamfer_reduction, "psnr_gain_db": m.psnr_heldout_morphed
                - m.psnr_heldout_input, "seconds": m.seconds, "min_silhouette_margin": margins[key]}
    return {"mesh": name,
            "views": [row(f"views_{n}", views=n, fitted_views=n - n // base.test_every
                          - len(runs[f"views_{n}"].validation_views)) for n in s.framing_views],
            "resolution": [row(f"res_{r}", resolution=r) for r in s.framing_resolutions]}


def cost_recipes(s: MorphBenchSettings) -> dict[str, MorphSettings]:
    """The recipes the "iteration" part times. ``issue_recipe``: the defaults issue 17 was filed against
    (constant λ 2, the planarity rule, plain colour steps, no validation renders). ``defaults``: today's defaults
    where the photos keep the plain run (validation renders every ``check_every``). ``defaults_light``: where they
    keep the light run (also the light estimate every ``light_select_every`` and colour large steps). Both with the
    bench's silhouette loss and boundary samples (``s.mask_weight`` …, ``s.boundary_spp``: today's defaults unless
    the command sets them); the issue's recipe had neither (weight 0, one sample count)."""
    d = MorphSettings(seed=s.seed, **s.silhouette_fields())
    issue = replace(d, lambda_select=(), planarity_select=(), colour_prior_weight=0.0, validation_views=0,
                    early_stop=False, light_select_every=0, mask_weight=0.0, boundary_spp=None)
    return {"issue_recipe": issue, "defaults": candidate_settings(d, Candidate(lambda_start=d.lambda_)),
            "defaults_light": candidate_settings(d, Candidate(lambda_start=d.lambda_, light=True))}


def iteration_cost(bench, recipes: dict[str, MorphSettings], iterations: int, rounds: int, tmp: Path,
                   show_progress: bool = False) -> dict:
    """Seconds per iteration of each recipe on ``bench``, timed in alternating blocks in this process with its
    thread count: ``iterations`` steps as the loop makes them (render, backward, optimiser step), plus what a recipe
    does every so many steps, per step (the light estimate every ``indirect_every``, the validation renders every
    ``check_every``). One untimed block per recipe first compiles the kernels; the median block is reported."""
    import drjit as dr
    from tqdm import tqdm

    blocks: dict[str, list] = {k: [] for k in recipes}
    vertices, pools = {}, {}

    def block(k: str) -> dict:
        """One timed block, the recipe's scene the only one alive (Mitsuba traces every live plugin instance)."""
        rs = recipes[k]
        (tmp / k).mkdir(parents=True, exist_ok=True)
        st = MorphStage(bench, tmp / k, rs)
        try:
            vertices[k] = int(len(st.vertices()))
            pools[k] = set(st.train_ids)
            if len(pools) == len(recipes):  # every recipe draws the same views (one seed): a view's cost varies
                st.train_ids = sorted(set.intersection(*pools.values()))
            st.estimate_indirect()  # a run's iteration 0 (nothing when the recipe has no estimate)
            for it in range(2):  # kernels from the cache; not timed
                st.step(it)
                st.apply(it)
            dr.eval(st.opt[st.key], st.opt["c"])
            t0 = time.perf_counter()
            for it in range(2, 2 + iterations):
                st.step(it)
                st.apply(it)
            dr.eval(st.opt[st.key], st.opt["c"])
            out = {"step": (time.perf_counter() - t0) / iterations}
            if rs.indirect_every:  # periodic work, per step
                t0 = time.perf_counter()
                st.estimate_indirect()
                out["light_estimate"] = (time.perf_counter() - t0) / rs.indirect_every
            if rs.validation_views:
                t0 = time.perf_counter()
                st.validation_l1()
                out["validation"] = (time.perf_counter() - t0) / rs.check_every
        finally:
            st.close()
        return {**out, "total": sum(out.values())}

    for k in recipes:  # compile every kernel once
        block(k)
    bar = tqdm(total=rounds * len(recipes), desc="bench morph iteration cost", disable=not show_progress)
    for r in range(rounds):
        for k in (list(recipes) if r % 2 == 0 else list(recipes)[::-1]):  # alternate who goes first
            blocks[k].append(block(k))
            bar.update()
    bar.close()
    med = {k: float(np.median([b["total"] for b in v])) for k, v in blocks.items()}
    return {"vertices": vertices, "threads": int(dr.thread_count()), "iterations_per_block": iterations,
            "views": sorted(set.intersection(*pools.values())),
            "recipes": {k: {"boundary_spp": rs.boundary_spp, "spp": rs.spp, "indirect_every": rs.indirect_every,
                            "indirect_spp": rs.indirect_spp, "indirect_reference": rs.indirect_reference,
                            "indirect_downsample": rs.indirect_downsample,
                            "colour_lambda": rs.colour_lambda,
                            "mask_weight": rs.mask_weight, "mask_every": rs.mask_every,
                            "mask_downsample": rs.mask_downsample,
                            "check_every": rs.check_every if rs.validation_views else None}
                        for k, rs in recipes.items()},
            "blocks": blocks, "s_per_iteration": med}


def bench_iteration_cost(work: Path, s: MorphBenchSettings, show_progress: bool) -> dict:
    """:func:`iteration_cost` of :func:`cost_recipes` on ``s.cost_mesh`` (the same remeshed start: the same vertex
    count); ``ratio``: each of today's recipes / the issue's."""
    import tempfile

    bench = load_morph_benchmark(_suite_bench(s.cost_mesh, work, MorphBenchmarkSettings(seed=s.seed)))
    with tempfile.TemporaryDirectory(dir=work) as tmp:
        out = iteration_cost(bench, cost_recipes(s), s.cost_iterations, s.cost_rounds, Path(tmp), show_progress)
    med = out["s_per_iteration"]
    return {"mesh": s.cost_mesh, **out,
            "ratio": {k: v / med["issue_recipe"] for k, v in med.items() if k != "issue_recipe"},
            "ratio_by_round": ratio_by_round(out["blocks"], "issue_recipe")}


#: the time-to-quality goals (issue 75): the defaults reach the issue's recipe's final Chamfer in a quarter of its time,
#: and a 10k-vertex mesh is done in 5 minutes on 2 cores
TTQ_GOALS = {"ratio": 0.25, "seconds_per_10k_vertices": 300.0}


def time_to_quality(recipe: MorphResult, defaults: MorphResult) -> dict:
    """Seconds the defaults' run takes to reach the recipe's final Chamfer (both by the trace's estimator, before any
    repair), against the recipe's own seconds. The trials the photos did not keep count in full, whenever the target
    is reached (the run cannot be used before its choices are made); trace seconds are set-up and optimisation, each
    run's validation renders added in proportion to the checks made so far."""
    def points(m: MorphResult) -> list[tuple[int, float, float]]:
        per_check = m.validation_seconds / max(len(m.trace), 1)
        return [(t.iteration, t.seconds + per_check * (k + 1), t.chamfer) for k, t in enumerate(m.trace)
                if t.chamfer is not None]

    rec, ours = points(recipe), points(defaults)
    if not rec or not ours:
        raise ValueError("time to quality needs both runs' Chamfer traces (a benchmark with its ground truth)")
    target, recipe_seconds = rec[-1][2], rec[-1][1]
    trials = defaults.trial_seconds
    at, kept = next(((it, sec) for it, sec, c in ours if c <= target), (None, None))
    to_target = None if kept is None else kept + trials
    ratio = None if to_target is None else to_target / recipe_seconds
    run_seconds = defaults.seconds + defaults.validation_seconds
    per_10k = run_seconds * 1e4 / defaults.vertices
    return {"target_chamfer": target, "recipe_seconds": recipe_seconds, "recipe_iterations": recipe.iterations,
            "defaults_trial_seconds": trials, "defaults_reached_at_iteration": at,
            "defaults_seconds_to_target": to_target, "ratio": ratio,
            # the run the photos kept, on its own (its trial included): what the choices cost is the difference
            "kept_run_seconds_to_target": kept,
            "defaults_final_chamfer": ours[-1][2], "defaults_seconds": run_seconds,
            "defaults_iterations": defaults.iterations, "vertices": defaults.vertices,
            "defaults_seconds_per_10k_vertices": per_10k,
            "chamfer_morphed": {"recipe": recipe.chamfer_morphed, "defaults": defaults.chamfer_morphed},
            "psnr_heldout_morphed": {"recipe": recipe.psnr_heldout_morphed,
                                     "defaults": defaults.psnr_heldout_morphed},
            "goals": dict(TTQ_GOALS),
            "met": {"ratio": ratio is not None and ratio <= TTQ_GOALS["ratio"],
                    "seconds_per_10k_vertices": per_10k <= TTQ_GOALS["seconds_per_10k_vertices"]}}


def bench_time_to_quality(work: Path, s: MorphBenchSettings, show_progress: bool) -> dict:
    """:func:`time_to_quality` on ``s.cost_mesh``: the recipe issue 17 was filed against (``issue_recipe`` of
    :func:`cost_recipes`, ``s.ttq_iterations`` long) and today's defaults capped there, one after the other in this
    process with its threads (each resumable in ``work/ttq_<mesh>_*``)."""
    import drjit as dr

    from foundation.records import json_digest

    bench = load_morph_benchmark(_suite_bench(s.cost_mesh, work, MorphBenchmarkSettings(seed=s.seed)))
    d = replace(s.suite_settings(), iterations=s.ttq_iterations)
    rs = replace(cost_recipes(s)["issue_recipe"], iterations=s.ttq_iterations)
    recipe = run_morph(bench, work / f"ttq_{s.cost_mesh}_issue_recipe", rs, show_progress=show_progress)
    # one folder per setting of the bench's suite fields: a rerun with other ones never meets a refused checkpoint
    key = json_digest(d, 8)
    ours = run_morph(bench, work / f"ttq_{s.cost_mesh}_defaults_{key}", d, show_progress=show_progress)
    row = suite_row(s.cost_mesh, ours)  # the defaults' run is the suite's run of this mesh: its targets too
    return {"mesh": s.cost_mesh, "threads": int(dr.thread_count()), **time_to_quality(recipe, ours),
            "suite_checks": row["checks"], "suite_passes": row["passes"],
            "chamfer_reduction": row["chamfer_reduction"], "psnr_gain_db": row["psnr_gain_db"]}


def ratio_by_round(blocks: dict[str, list[dict]], ref: str) -> dict:
    """Each recipe's block total over the ``ref`` recipe's block of the same round (the two ran minutes apart, so
    the machine's slow drifts cancel): per round, and their median, min and max."""
    base = [b["total"] for b in blocks[ref]]
    out = {}
    for k, v in blocks.items():
        if k != ref:
            r = [b["total"] / x for b, x in zip(v, base)]
            out[k] = {"per_round": r, "median": float(np.median(r)), "min": float(min(r)), "max": float(max(r))}
    return out


def work_name(s: MorphBenchSettings) -> str:
    """The bench's work folder: one per seed (finished runs are resumed by folder; ~1 GB for the whole bench)."""
    return "morph_work" if s.seed == 0 else f"morph_work_seed{s.seed}"


def bench_morph(s: MorphBenchSettings, work: Path, show_progress: bool = True,
                pool: PoolSettings | None = None) -> dict:
    """Run the bench's parts in ``work`` (a rerun re-reads every finished run in it)."""
    from foundation.pool import default_workers

    cores = default_workers()
    pool = pool or PoolSettings(workers=cores, threads=1)
    t0 = time.perf_counter()
    result: dict = {"settings": asdict(s)}
    if "cases" in s.parts:
        cases = {c: bench_case(c, work, s, pool, show_progress) for c in s.cases}
        first = cases[s.cases[0]]
        result.update({k: first[k] for k in ("chamfer_input", "chamfer_morphed", "psnr_heldout_input",
                                             "psnr_heldout_morphed", "spikes", "s_per_iter_10k_4views_128",
                                             "s_per_iter_baseline", "sweep", "chosen_vertices")})
        result.update(chamfer_reduction=first["chamfer_reduction"], cases=cases)
    if "suite" in s.parts:
        result["suite"] = bench_suite(work, s, pool, show_progress)
    if "framing" in s.parts:
        result["framing"] = bench_framing(work, s, pool, show_progress)
    if "floor" in s.parts:
        result["floor"] = bench_floor(work, s, pool, show_progress)
    if "iteration" in s.parts:
        result["iteration_cost"] = bench_iteration_cost(work, s, show_progress)
        if s.ttq_iterations:
            result["time_to_quality"] = bench_time_to_quality(work, s, show_progress)
    result["seconds"] = time.perf_counter() - t0
    return result




# -- the benchmark protocol (photoreal.benchmarks) -------------------------------------------------------------------

SETTINGS = MorphBenchSettings
POOL = True


def run(s: MorphBenchSettings, work: Path, pool, show_progress: bool) -> dict:
    return bench_morph(s, work, show_progress, pool)


def charts(result: dict, json_path: Path, work: Path | None) -> dict:
    out = {}
    if "cases" in result:
        out["chart"] = str(morph_chart(result, Path(json_path).parent / "morph_speed_accuracy.png"))
    if "suite" in result:
        out["suite_chart"] = str(suite_chart(result["suite"], Path(json_path).parent / "morph_suite.png"))
    return out


def summary(result: dict) -> dict:
    shown = {k: result[k] for k in ("chamfer_input", "chamfer_morphed", "chamfer_reduction", "psnr_heldout_input",
                                    "psnr_heldout_morphed", "spikes", "s_per_iter_10k_4views_128",
                                    "s_per_iter_baseline", "chosen_vertices") if k in result}
    if "suite" in result:
        shown.update(suite_mean=result["suite"]["mean"], suite_failing=result["suite"]["failing"])
    if "iteration_cost" in result:
        c = result["iteration_cost"]
        shown.update(s_per_iteration=c["s_per_iteration"], iteration_cost_ratio=c["ratio"],
                     iteration_cost_ratio_by_round={k: round(v["median"], 4) for k, v in c["ratio_by_round"].items()})
    if "time_to_quality" in result:
        q = result["time_to_quality"]
        shown.update(time_to_quality={k: q[k] for k in ("ratio", "defaults_seconds_to_target", "recipe_seconds",
                                                       "defaults_seconds_per_10k_vertices", "met")})
    return shown


def options(p) -> None:
    from inverse.morph import PRIOR_TIES, TRUTH_NORMALS
    from photoreal.options import opt

    opt(p, MorphBenchSettings, "parts", choices=["cases", "suite", "framing", "floor", "iteration"],
         help="cases: village/armadillo (speed, sweep, stability); suite: every suite mesh at the same defaults; "
              "framing: views and photo resolution swept on the first suite mesh; floor: each suite mesh morphed "
              "from its own ground truth (how far the method drifts from the answer); iteration: seconds per "
              "iteration of today's defaults against the recipe issue 17 was filed against, same mesh, in turns")
    opt(p, MorphBenchSettings, "floor_iterations", help="iterations of the truth-start runs (--parts floor)")
    opt(p, MorphBenchSettings, "truth_normals", choices=list(TRUTH_NORMALS),
         help="shading of the suite's and floor's photographed truths (face: flat, as the Chamfer measures them; "
              "their folders get _face)")
    opt(p, MorphBenchSettings, "prior_ties", choices=list(PRIOR_TIES),
         help="the suite's tied prior choices: keep (the run with the prior continues unless beaten by the margin) "
              "or drop (the run without continues unless beaten by the margin)")
    opt(p, MorphBenchSettings, "adam_quantile", type=float,
         help="the suite's runs: MorphSettings.adam_quantile (use a fresh --json folder: trials of another value "
              "are refused by name)")
    opt(p, MorphBenchSettings, "lr", type=float, help="the suite's runs' position learning rate (MorphSettings.lr)")
    opt(p, MorphBenchSettings, "lambda_warmup", type=float,
         help="the suite's runs' λ warm-up share; the photos' choices are made where it ends "
              "(MorphSettings.lambda_warmup)")
    opt(p, MorphBenchSettings, "step_select_quantile", type=float,
         help="the suite's runs ask the validation photos about this quantile step (MorphSettings.step_select_quantile; "
              "1: no such choice)")
    opt(p, MorphBenchSettings, "saturation", type=float,
         help="the suite's runs leave pixels brighter than this × the photos' 99th percentile out of the loss "
              "(MorphSettings.saturation; 0: every pixel counts)")
    opt(p, MorphBenchSettings, "mask_weight", type=float,
         help="the suite's runs add a silhouette L1 against the photos' masks at this weight "
              "(MorphSettings.mask_weight; 0: photos only)")
    opt(p, MorphBenchSettings, "boundary_spp", type=int, help="the suite's runs' silhouette samples per pixel "
         "(MorphSettings.boundary_spp; the image takes 4)")
    opt(p, MorphBenchSettings, "mask_every", help="the suite's runs render the masks every this many steps, at "
         "this × the weight (MorphSettings.mask_every)")
    opt(p, MorphBenchSettings, "mask_downsample", help="the suite's runs render the masks at the photos' resolution "
         "// this (MorphSettings.mask_downsample)")
    opt(p, MorphBenchSettings, "seed", help="another draw of every benchmark (photos' noise, views) and of every "
                                               "morph's render seeds (work folder: OUT/morph_work_seed<k>)")
    opt(p, MorphBenchSettings, "cost_mesh", help="the mesh of --parts iteration")
    opt(p, MorphBenchSettings, "cost_iterations", help="steps per timed block (--parts iteration)")
    opt(p, MorphBenchSettings, "cost_rounds", help="timed blocks per recipe, in turns (--parts iteration)")
    opt(p, MorphBenchSettings, "ttq_iterations", help="--parts iteration's time to quality: the issue's recipe's "
         "iterations and the defaults' cap, on --cost-mesh (0: not measured)")
    opt(p, MorphBenchSettings, "cases")
    opt(p, MorphBenchSettings, "suite", help="suite meshes (village and armadillo may be added; paul, face000 "
                                               "and bracket are meshes the defaults never saw)")
    opt(p, MorphBenchSettings, "iterations", help="morph iterations of the main and suite runs")
