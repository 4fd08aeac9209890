"""`photoreal bench face-learned`: the learned UV-space face stages (seed 003 §2–§4) against the optimisation
baseline, on a scan kept out of training, plus the existing fit on observations it did not render.

1. **Train** (``OUT/face_learned_work``, a `photoreal face train-models` run, reused by later bench runs): data
   from the training scan, the completion/homogenisation diffusion model (the backbone), the three decomposition
   variants (cross-intrinsic attention, shared LoRA without it, independent models) at equal time, the 2×
   upscaler.
2. **Completion** on the held-out scan's instances (held-out HDRIs, random poses) at the models' resolution:
   albedo PSNR over the texels the photo saw and over those it did not, learned vs baseline (mirror + harmonic
   fill, delit by fitted lights).
3. **Decomposition**: normal error, roughness and specular MAE of each variant against the template defaults.
4. **Super-resolution**: the held-out scan's true maps box-downsampled 2× and upscaled, learned vs bicubic.
5. **Cross-model fit**: the existing fit (`face fit`) on benchmarks of the held-out scan rendered by the fit's own
   model (``ggx_uv``, directional lights) and by models it does not know (Mitsuba's ``principled``; real HDRIs
   with interreflection and a subsurface-like albedo spread), the same metrics.
6. **End to end** at the data resolution on the held-out instances: baseline vs the learned stages, one by one
   (completion → + decomposition → + super-resolution); relit PSNR/ꟻLIP of the scan under other HDRIs.
7. **Astronaut** (no ground truth): ``face from-photo`` baseline vs learned, the re-render PSNR on the visible face.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from foundation import validate
from foundation.errors import UsageError
from foundation.progress import progress_bar


@dataclass
class FaceLearnedBenchSettings:
    train_instances: int = 192
    eval_instances: int = 24
    completion_seconds: float = 720.0
    decomp_seconds: float = 360.0  #: each decomposition variant (equal time)
    superres_seconds: float = 120.0
    relit_instances: int = 6  #: held-out instances relit (each under every relight HDRI)
    relight_hdris: tuple[str, ...] = ("studio", "city")
    cross_model: bool = True
    cross_uv_res: int = 128
    astronaut: bool = True
    layout: str = "template"  #: UV layout of the learned stages: the face template's or the scans' own
    workers: int = 2  #: data building
    seed: int = 0
    #: further training seeds of every decomposition variant (same data, same backbone, same budget): the spread
    #: that an ablation difference must exceed. Each seed costs len(variants) × decomp_seconds.
    ablation_seeds: tuple[int, ...] = ()

    def __post_init__(self):
        validate.integer("train_instances", self.train_instances, 2)
        validate.integer("eval_instances", self.eval_instances, 1)
        for k in ("completion_seconds", "decomp_seconds", "superres_seconds"):
            validate.positive(k, getattr(self, k))
        validate.integer("relit_instances", self.relit_instances, 0)
        validate.integer("cross_uv_res", self.cross_uv_res, 16, 1024)
        validate.integer("workers", self.workers, 0)
        validate.seed("seed", self.seed)
        self.ablation_seeds = tuple(self.ablation_seeds)
        for k in self.ablation_seeds:
            validate.seed("ablation_seeds", k)
        if self.seed in self.ablation_seeds or len(set(self.ablation_seeds)) != len(self.ablation_seeds):
            raise UsageError(f"ablation_seeds: seeds other than --seed ({self.seed}), each once; got "
                             f"{list(self.ablation_seeds)}")


def models_settings(s: FaceLearnedBenchSettings):
    from generative.face import (CompletionSettings, DecompSettings, FaceDataSettings, FaceModelsSettings,
                                 SuperResSettings)

    return FaceModelsSettings(
        data=FaceDataSettings(train_instances=s.train_instances, eval_instances=s.eval_instances, seed=s.seed,
                              layout=s.layout),
        completion=CompletionSettings(max_seconds=s.completion_seconds, seed=s.seed),
        decomposition=DecompSettings(max_seconds=s.decomp_seconds, seed=s.seed),
        superres=SuperResSettings(max_seconds=s.superres_seconds, seed=s.seed),
        variants=("cross_attention", "shared", "independent"))


def superres_scores(pred: dict[str, np.ndarray], gt: dict[str, np.ndarray], mask: np.ndarray) -> dict:
    """Per map: albedo PSNR (linear), normal error (degrees), roughness/specular PSNR; covered texels."""
    from foundation.metrics import angular_error_deg, psnr

    m = mask
    return {"albedo_psnr": psnr(pred["albedo"][m], gt["albedo"][m]),
            "normal_err_deg": float(angular_error_deg(pred["normal"][m], gt["normal"][m]).mean()),
            "roughness_psnr": psnr(pred["roughness"][m], gt["roughness"][m]),
            "specular_psnr": psnr(pred["specular"][m], gt["specular"][m])}


def cross_model_fit(scan: str, work: Path, res: int, seed: int, show_progress: bool) -> dict:
    """The existing fit on four benchmarks of ``scan``: its own model, unknown lights, another BSDF, real HDRIs."""
    from foundation.records import to_json
    from inverse.face import (FaceBenchmarkSettings, FaceFitSettings, evaluate_fit, fit_face, load_benchmark,
                              make_benchmark)

    from generative.face import scan_path

    cases = {
        "ggx_uv_directional": (FaceBenchmarkSettings(uv_res=res, seed=seed), FaceFitSettings(seed=seed)),
        "ggx_uv_directional_unknown_lights": (FaceBenchmarkSettings(uv_res=res, seed=seed),
                                              FaceFitSettings(fit_lights=True, seed=seed)),
        "principled_directional": (FaceBenchmarkSettings(uv_res=res, seed=seed, observation_bsdf="principled"),
                                   FaceFitSettings(seed=seed)),
        "principled_hdri_interreflection": (
            FaceBenchmarkSettings(uv_res=res, seed=seed, observation_bsdf="principled", lighting="hdri", max_depth=4,
                                  albedo_blur=1.5),
            FaceFitSettings(fit_lights=True, seed=seed)),
    }
    out = {}
    with progress_bar(total=len(cases), desc="cross-model fit", unit="case", disable=not show_progress) as bar:
        for name, (bs, fs) in cases.items():
            t0 = time.perf_counter()
            d = make_benchmark(scan_path(scan), work / f"cross_{name}", bs, show_progress=False)
            made = time.perf_counter() - t0
            bench = load_benchmark(d)
            result = fit_face(bench, fs, show_progress=False)
            m = to_json(evaluate_fit(bench, result))
            m.update(benchmark_seconds=made, fit_seconds=result.seconds, observation_bsdf=bs.observation_bsdf,
                     lighting=bs.lighting, fit_lights=fs.fit_lights)
            out[name] = m
            bar.update(1)
    return out


def astronaut(models, work: Path, seed: int) -> dict:
    """``face from-photo`` on scikit-image's astronaut: baseline and learned; re-render PSNR on the visible face."""
    from foundation.imageio import read_photo
    from inverse.face import PhotoFitSettings, photo_to_face

    from generative.face import photo_maps_fn

    img = read_photo("astronaut")
    s = PhotoFitSettings(seed=seed)
    out = {}
    if models.layout != "template":  # photos are unwrapped into the template's layout: nothing to measure
        return {"skipped": f"the learned stages are in the {models.layout!r} layout, photos in the template's"}
    for name, fn in (("baseline", None), ("learned", photo_maps_fn(models))):
        r = photo_to_face(img, work / f"astronaut_{name}", s, show_progress=False, maps_fn=fn)
        out[name] = {"rerender_psnr_visible_face": r.rerender_psnr_visible_face, "seconds": r.seconds,
                     "folder": str(work / f"astronaut_{name}")}
    return out


def decomposition_seeds(s: FaceLearnedBenchSettings, ms, work: Path, ev, albedo, low, dec: dict,
                        show_progress: bool) -> dict:
    """Every variant retrained with each of ``s.ablation_seeds`` (``work/ablation_seed<k>/``, resumable); per variant
    and metric the values over all seeds (the main run's first), their mean and sample standard deviation."""
    from generative.face import (completion_albedo, decompose_maps, DecompSettings, load_decomposer, load_face_dataset,
                                 map_scores, train_decomposer)

    train = load_face_dataset(work / "data", "train")
    albedo_train = completion_albedo(work, show_progress)
    keys = ("normal_err_deg", "roughness_mae", "specular_mae", "albedo_psnr_unseen")
    out: dict = {"seeds": [s.seed, *s.ablation_seeds]}
    for v in ms.variants:
        values = {k: [dec[v][k]] for k in keys}
        for seed in s.ablation_seeds:
            run = work / f"ablation_seed{seed}" / f"decomposition_{v}"
            ds = DecompSettings(**{**asdict(ms.decomposition), "variant": v, "seed": seed})
            train_decomposer(train, albedo_train, work / "completion", run, ds, show_progress=show_progress)
            sc = map_scores(decompose_maps(load_decomposer(run, work / "completion"), ev, albedo, low.res),
                            low.targets, low.seen, low.mask)
            for k in keys:
                values[k].append(sc[k])
        out[v] = {k: {"values": vals, "mean": float(np.mean(vals)), "std": float(np.std(vals, ddof=1))}
                  for k, vals in values.items()}
    return out


def bench_face_learned(s: FaceLearnedBenchSettings, work: Path, show_progress: bool = True) -> dict:
    """The bench in ``work``: a `photoreal face train-models` run (reused by later bench runs) and the figures'
    inputs."""
    from foundation.pool import PoolSettings
    from generative.face import (at_resolution, baseline_maps, complete, decompose_maps, default_maps, learned_maps,
                                 LearnedModels, load_completion, load_decomposer, load_face_dataset, load_superres,
                                 map_scores, relit_scores, train_face_models, upscale)

    work = Path(work)
    ms = models_settings(s)
    t0 = time.perf_counter()
    summary = train_face_models(work, ms, PoolSettings(workers=s.workers, threads=1) if s.workers else None,
                                progress=show_progress)
    train_wall = time.perf_counter() - t0
    ev = load_face_dataset(work / "data", "eval")
    model, cs = load_completion(work / "completion")
    low = at_resolution(ev, cs.res)
    result: dict = {"layout": ms.data.layout, "heldout_scan": ms.data.heldout_scan, "train_scans": list(ms.data.train_scans),
                    "eval_hdris": list(ms.data.eval_hdris), "instances": {"train": s.train_instances, "eval": len(ev)},
                    "model_res": cs.res, "data_res": ms.data.uv_res}

    # 2. completion
    t = time.perf_counter()
    albedo = complete(model, cs, ev, seed=s.seed)
    per_instance = (time.perf_counter() - t) / len(ev)
    albedo1 = complete(model, cs, ev, seed=s.seed, samples=1)
    keys = ("albedo_psnr_seen", "albedo_psnr_unseen", "albedo_psnr_all")
    pick = lambda d: {k: d[k] for k in keys}  # noqa: E731
    result["completion"] = {
        "baseline": pick(map_scores(baseline_maps(low), low.targets, low.seen, low.mask)),
        "learned": pick(map_scores(default_maps(albedo), low.targets, low.seen, low.mask)),
        "learned_one_sample": pick(map_scores(default_maps(albedo1), low.targets, low.seen, low.mask)),
        "samples_averaged": cs.samples, "ddim_steps": cs.sample_steps, "seconds_per_instance": per_instance,
        "seen_fraction": float(np.mean([r["seen_fraction"] for r in ev.records]))}

    # 3. decomposition variants (each on the same completed albedo)
    dec_keys = ("normal_err_deg", "roughness_mae", "specular_mae", "albedo_psnr_seen", "albedo_psnr_unseen")
    dec = {"template_defaults": {k: v for k, v in map_scores(default_maps(albedo), low.targets, low.seen, low.mask).items()
                                 if k in dec_keys}}
    for v in ms.variants:
        dm = load_decomposer(work / f"decomposition_{v}", work / "completion")
        sc = map_scores(decompose_maps(dm, ev, albedo, cs.res), low.targets, low.seen, low.mask)
        tr = summary[f"decomposition_{v}"]
        dec[v] = {**{k: sc[k] for k in dec_keys}, "trained_parameters": tr["parameters"],
                  "steps": tr["training"]["steps"], "train_seconds": tr["training"]["train_seconds"]}
    result["decomposition"] = dec
    if s.ablation_seeds:
        result["decomposition_seeds"] = decomposition_seeds(s, ms, work, ev, albedo, low, dec, show_progress)

    # 4. super-resolution of the true maps
    sr = load_superres(work / "superres")
    result["superres"] = {"bicubic": superres_scores(upscale(None, low.targets, low), ev.targets, ev.mask),
                          "learned": superres_scores(upscale(sr, low.targets, low), ev.targets, ev.mask),
                          "from": cs.res, "to": ev.res}

    # 6. end to end at the data resolution
    models = LearnedModels(model, cs, load_decomposer(work / f"decomposition_{ms.variants[0]}", work / "completion"), sr,
                           layout=ms.data.layout)
    stages = {"baseline": baseline_maps(ev)}
    for st in ("completion", "decomposition", "full"):
        stages[f"learned_{st}"] = learned_maps(ev, models, st, seed=s.seed)
    idx = list(range(min(s.relit_instances, len(ev))))
    e2e = {}
    with progress_bar(total=len(stages), desc="relight", unit="method", disable=not show_progress) as bar:
        for name, maps in stages.items():
            e2e[name] = map_scores(maps, ev.targets, ev.seen, ev.mask)
            if idx:
                e2e[name]["relit"] = relit_scores(ev, maps, s.relight_hdris, indices=idx)
            bar.update(1)
    result["end_to_end"] = {"baseline": e2e["baseline"], "learned": e2e["learned_full"],
                            "stages": {k: v for k, v in e2e.items() if k.startswith("learned_")},
                            "relit_instances": len(idx), "relight_hdris": list(s.relight_hdris)}

    # 5. cross-model fit
    if s.cross_model:
        result["cross_model_fit"] = cross_model_fit(ms.data.heldout_scan, work, s.cross_uv_res, s.seed, show_progress)
    # 7. astronaut
    if s.astronaut:
        result["astronaut"] = astronaut(models, work, s.seed)

    result["train_seconds"] = {k: v["training"]["train_seconds"] for k, v in summary.items()} | {"wall_incl_data": train_wall}
    result["trained_parameters"] = {k: v["parameters"] for k, v in summary.items()}
    e, c, d_ = result["end_to_end"], result["completion"], result["decomposition"]
    result["verdict"] = {
        "completion_beats_baseline_unseen": c["learned"]["albedo_psnr_unseen"] > c["baseline"]["albedo_psnr_unseen"],
        "cross_attention_beats_defaults_normal": d_["cross_attention"]["normal_err_deg"] < d_["template_defaults"]["normal_err_deg"],
        "cross_attention_beats_defaults_roughness": d_["cross_attention"]["roughness_mae"] < d_["template_defaults"]["roughness_mae"],
        "cross_attention_beats_defaults_specular": d_["cross_attention"]["specular_mae"] < d_["template_defaults"]["specular_mae"],
        "superres_beats_bicubic_albedo": result["superres"]["learned"]["albedo_psnr"] > result["superres"]["bicubic"]["albedo_psnr"],
        "end_to_end_learned_beats_baseline_relit": (e["learned"].get("relit", {}).get("psnr", -1)
                                                    > e["baseline"].get("relit", {}).get("psnr", 0)) if idx else None,
    }
    result["settings"] = asdict(s)
    result["figure"] = str(figure(ev, stages, work.parent / "face_learned_maps.png"))
    return result


def figure(ev, stages: dict, path: Path, n: int = 3) -> Path:
    """Rows: held-out instances; columns: lit photo in UV, seen mask, baseline albedo, learned albedo, true albedo,
    learned normal, true normal, learned roughness, true roughness."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from foundation.imageio import linear_to_srgb, save_figure
    from generative.face import normalise_albedo

    cols = ["photo (UV)", "baseline albedo", "learned albedo", "true albedo", "learned normal", "true normal",
            "learned roughness", "true roughness"]
    n = min(n, len(ev))
    fig, ax = plt.subplots(n, len(cols), figsize=(2 * len(cols), 2 * n), squeeze=False)
    lit = ev.lit / np.maximum(np.array([ev.lit[i][ev.seen[i]].mean() if ev.seen[i].any() else 1 for i in range(len(ev))]),
                              1e-6)[:, None, None, None] * 0.3
    learned, base = stages["learned_full"], stages["baseline"]
    for r in range(n):
        na = lambda a: normalise_albedo(a[r:r + 1], ev.seen[r:r + 1])[0]  # noqa: E731
        imgs = [linear_to_srgb(np.clip(lit[r], 0, 1)), linear_to_srgb(na(base["albedo"])),
                linear_to_srgb(na(learned["albedo"])), linear_to_srgb(na(ev.targets["albedo"])),
                learned["normal"][r] * 0.5 + 0.5, ev.targets["normal"][r] * 0.5 + 0.5,
                np.repeat(learned["roughness"][r], 3, -1), np.repeat(ev.targets["roughness"][r], 3, -1)]
        for c, im in enumerate(imgs):
            ax[r, c].imshow(np.clip(im, 0, 1), vmin=0, vmax=1)
            ax[r, c].axis("off")
            if r == 0:
                ax[r, c].set_title(cols[c], fontsize=8)
    fig.suptitle("held-out scan: learned stages vs the optimisation baseline and the truth")
    return save_figure(fig, path)


# -- the benchmark protocol (photoreal.benchmarks) -------------------------------------------------------------------

SETTINGS = FaceLearnedBenchSettings
SUMMARY = ("completion", "decomposition", "superres", "end_to_end", "verdict")


def run(s: FaceLearnedBenchSettings, work: Path, pool, show_progress: bool) -> dict:
    return bench_face_learned(s, work, show_progress)


def options(p) -> None:
    from photoreal.options import opt

    for name in ("train_instances", "eval_instances", "completion_seconds", "decomp_seconds", "superres_seconds",
                 "relit_instances", "cross_uv_res", "workers", "seed"):
        opt(p, FaceLearnedBenchSettings, name)
    opt(p, FaceLearnedBenchSettings, "layout", choices=["template", "scan"], help="UV layout of the learned stages")
    opt(p, FaceLearnedBenchSettings, "ablation_seeds", type=int,
         help="retrain every decomposition variant with these seeds too: the ablation's spread over training seeds")
    opt(p, FaceLearnedBenchSettings, "cross_model", "--no-cross-model", help="skip the cross-model fit")
    opt(p, FaceLearnedBenchSettings, "astronaut", "--no-astronaut", help="skip the astronaut photograph")
