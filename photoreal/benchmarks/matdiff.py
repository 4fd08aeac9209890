"""`photoreal bench matdiff`: generative neural materials (seed 002 §3.2, §4.4) against baselines.

1. **Dataset** (``data``; built or continued first, on every core): ``count`` fitted materials over the 8
   families; the last 1/8 of each family is held out. Reported separately: build seconds, fit PSNR.
2. **Family classifier** trained on the path-traced swatches of the training materials; accuracy on the
   held-out materials' path-traced swatches and on their decoded fits.
3. **Main model** (``train_seconds`` here, or the finished run ``main_run``, e.g. trained on a GPU with
   ``btf train-diffusion --device cuda``: it must have been trained on this dataset's training split), then
   with ``steps`` DDIM steps and guidance ``guidance``:
   keyword accuracy (held-out materials' keyword triples, and family words alone) under the classifier,
   beside references that need no training (a rolled copy, a per-family Gaussian, a phase-randomised member,
   held-out fits plus noise: what the target demands of a generator);
   KID/FID of unconditional samples (and of samples whose keywords are drawn from the training materials' — a
   sample of p(x) = Σ_c p(c) p(x|c)) against the held-out materials (decoded fits, the same image formation
   as every generated material) in the classifier's and MobileNetV2's feature spaces, beside the baselines
   (training copies, the training Gaussian, random crops); memorisation (nearest-training distance of samples
   over that of held-out materials) and diversity; exemplar conditioning (aligned ꟻLIP to the held-out
   material's path-traced swatches) against unconditional samples and nearest-neighbour retrieval; the seam
   ratio of samples at 2× the training size.
4. **Speed**: seconds per sample at 64² and 256² against DDIM steps, quality (keyword accuracy, KID) against
   steps at the training size; the chosen step count = the fewest within ``tolerance`` of the best accuracy.
5. **Ablations** at equal training time (``ablation_seconds`` each): the full recipe and each of the seed's
   choices switched off in turn. **Dataset sweep**: the same budget on the first k materials per family.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from foundation import validate
from foundation.errors import UsageError
from foundation.threads import torch_threads

ABLATIONS = {  # name → the MatDiffSettings fields that switch one choice off
    "full": {},
    "no circular padding": {"circular": False},
    "epsilon instead of v": {"prediction": "epsilon"},
    "no schedule shift": {"shift_base": 0},
    "no Min-SNR weighting": {"min_snr_gamma": 0.0},
    "no cube-root scaling": {"cube_root": False},
    "no multiscale loss": {"multiscale": False},
    "no CFG (never dropped, guidance 1)": {"cfg": False},
    "keywords by cross-attention only (no time-embedding path)": {"keyword_embedding": False},
    "whole 32² textures, not 16² crops (2 attention levels, lr 5e-4: the earlier default)":
        {"train_crop": 0, "attention_levels": 2, "lr": 5e-4},
    "+ pure-noise floor on Min-SNR (x₀ weight min(SNR, γ) + 1)": {"snr_floor": True},
}


@dataclass
class MatDiffBenchSettings:
    data: str = "out/matdiff/data"  #: dataset folder (built, or continued, first)
    count: int = 256  #: materials of the dataset
    train_seconds: float = 900.0  #: the main model's training budget
    #: a finished `btf train-diffusion` run folder to evaluate as the main model instead of training one here
    #: (checked: trained on exactly this dataset's training split); the ablations still train here
    main_run: str = ""
    ablation_seconds: float = 120.0  #: each ablation / dataset-sweep run
    classifier_seconds: float = 90.0
    sweep_per_family: tuple[int, ...] = (4, 12)  #: training materials per family of the sweep (plus all: "full")
    samples: int = 64  #: unconditional samples of each method for KID / memorisation / diversity
    steps: int = 25  #: DDIM steps of the main evaluation (the speed sweep reports others)
    guidance: float = 2.0
    #: DDIM steps of the quality sweep (the GPU-trained model was most accurate at the fewest: 5 steps 0.75 vs
    #: 10 steps 0.64 on three scratch seed sets, 2026-11-26)
    quality_steps: tuple[int, ...] = (3, 5, 10, 25, 50)
    quality_guidance: tuple[float, ...] = (1.0, 2.0)  #: CFG weights of the quality sweep (× quality_steps)
    speed_sizes: tuple[int, ...] = (64, 256)
    speed_steps: tuple[int, ...] = (3, 5, 10, 25)
    tolerance: float = 0.05  #: keyword accuracy within this of the best counts as as good
    chosen_repeats: int = 4  #: fresh noise-seed sets the chosen (steps, guidance) is rescored on (the verdict's mean)
    ablations: bool = True
    seed: int = 0

    def __post_init__(self):
        validate.integer("count", self.count, 8)
        for k in ("train_seconds", "ablation_seconds", "classifier_seconds"):
            validate.positive(k, getattr(self, k))
        validate.integer("samples", self.samples, 4)
        validate.integer("chosen_repeats", self.chosen_repeats, 1)
        validate.integer("steps", self.steps, 1, 1000)
        validate.non_negative("guidance", self.guidance)
        validate.seed("seed", self.seed)


def _check_trained_on(run: Path, train) -> None:
    """``run`` must be a finished material-diffusion run on exactly ``train``'s materials (no held-out leak)."""
    from foundation.loop import read_checkpoint
    from generative.btf import data_digest

    ckpt = run / "checkpoint.npz"
    if not ckpt.is_file():
        raise UsageError(f"--main-run {run}: no checkpoint.npz (a `photoreal btf train-diffusion` run folder)")
    saved = read_checkpoint(ckpt)
    if saved.kind != "MatDiffStage":
        raise UsageError(f"--main-run {run}: a {saved.kind} checkpoint, not a material diffusion run")
    if not saved.run.done:
        raise UsageError(f"--main-run {run}: the run is not finished (step {saved.run.step}); resume it first")
    if saved.fingerprint.get("data") != data_digest(train):
        raise UsageError(f"--main-run {run}: trained on other materials than this dataset's training split "
                         f"(data digest {saved.fingerprint.get('data')} vs {data_digest(train)})")
    if not (run / "metrics.json").is_file():
        raise UsageError(f"--main-run {run}: metrics.json missing")


class _Judge:
    """Decodes feature textures and scores them against the held-out materials."""

    def __init__(self, basis, classifier, held_dec: np.ndarray, train_dec: np.ndarray, channels: int):
        from generative.btf import classify, mnv2_features

        self.basis, self.classifier, self.channels = basis, classifier, channels
        self.res = held_dec.shape[2]  #: the training texture size
        self.ref_mn = mnv2_features(held_dec)
        self.ref_cls = classify(classifier, held_dec, self.ref_mn)[1]
        self.train_mn = mnv2_features(train_dec)

    def decode(self, features: np.ndarray) -> np.ndarray:
        from generative.btf import decode_all

        return decode_all(self.basis, features, self.channels)

    def score(self, decoded: np.ndarray) -> dict:
        from foundation.features import fid, kid
        from generative.btf import classify, mnv2_features

        fm = mnv2_features(decoded)
        pred, fc = classify(self.classifier, decoded, fm)
        return {"pred": pred, "cls": fc, "mn": fm, "kid_classifier": kid(fc, self.ref_cls),
                "kid_mnv2": kid(fm, self.ref_mn), "fid_classifier": fid(fc, self.ref_cls)}


def _keyword_eval(model, ms, judge: _Judge, prompts: list, families: np.ndarray, steps: int, guidance: float,
                  seed: int) -> dict:
    from generative.btf import MaterialPrompt, sample_materials

    t = time.perf_counter()
    f = sample_materials(model, ms, [MaterialPrompt(p) for p in prompts], judge.res, steps, guidance, seed)
    secs = time.perf_counter() - t
    sc = judge.score(judge.decode(f))
    return {"accuracy": float(np.mean(sc["pred"] == families)), "kid_classifier": sc["kid_classifier"],
            "kid_mnv2": sc["kid_mnv2"], "seconds_per_sample": secs / len(prompts), "features": f, "pred": sc["pred"]}


def _keyword_references(judge: _Judge, ms, train, held, seed: int, per_family: int = 8,
                        sigmas: tuple[float, ...] = (0.05, 0.1, 0.2, 0.3)) -> dict:
    """What the keyword target demands of a generator, under the same classifier, with no training: the family
    accuracy of (a) a random rolled training member of the family (a copy: the ceiling), (b) each family's
    Gaussian, (c) a member with randomised Fourier phases (its spectrum, not its structure), all in the model's
    space (cube root), and (d) the held-out fits with Gaussian noise of σ added in the model's space (the residual
    noise a sample may keep)."""
    from generative.btf import (classify, family_gaussian_baseline, from_model_space, phase_randomised_baseline,
                                random_roll, to_model_space)

    rng = np.random.default_rng(seed)

    def accuracy(x: np.ndarray, fam: np.ndarray) -> float:
        f = np.asarray(from_model_space(x, ms), np.float32)
        return float(np.mean(classify(judge.classifier, judge.decode(f))[0] == fam))

    x, fams = to_model_space(train.features, ms).astype(np.float32), train.families
    pick = np.concatenate([rng.choice(np.flatnonzero(fams == f), per_family) for f in np.unique(fams)])
    copies = np.stack([random_roll(x[i], rng) for i in pick])
    held_x = to_model_space(held.features, ms).astype(np.float32)
    return {"rolled_training_copy": accuracy(copies, fams[pick]),
            "family_gaussian": accuracy(*family_gaussian_baseline(x, fams, per_family, rng)),
            "phase_randomised_member": accuracy(*phase_randomised_baseline(x, fams, per_family, rng)),
            "heldout_fits_plus_noise": {
                str(sg): accuracy(held_x + sg * rng.standard_normal(held_x.shape).astype(np.float32), held.families)
                for sg in sigmas}}


def _seam(model, ms, judge: _Judge, size: int, n: int, seed: int, steps: int) -> float:
    from generative.btf import MaterialPrompt, sample_materials, seam_ratio

    f = sample_materials(model, ms, [MaterialPrompt()] * n, size, steps, 1.0, seed)
    return float(np.mean([seam_ratio(d[0]) for d in judge.decode(f)]))


def _short_eval(model, ms, judge, held, s: MatDiffBenchSettings) -> dict:
    """What an ablation or sweep run is judged by: keyword-triple samples of the held-out materials, seams at 2× size."""
    r = _keyword_eval(model, ms, judge, held.keywords, held.families, s.steps, s.guidance if ms.cfg else 1.0, s.seed)
    r.pop("features"), r.pop("pred")
    r["seam_ratio_2x"] = _seam(model, ms, judge, 2 * judge.res, 4, s.seed, s.steps)
    return r


def bench_matdiff(s: MatDiffBenchSettings, work: Path, show_progress: bool = True) -> dict:
    """The bench in ``work`` (trained runs and samples are kept there and reused by later runs)."""
    from foundation.assets import bundled_basis
    from foundation.pool import PoolSettings, default_workers
    from foundation.files import read_json
    from foundation.records import from_json
    from generative.btf import (aligned_flip, build_material_dataset, ClassifierSettings, classify, copy_baseline,
                                crop_baseline, denoising_check, gaussian_baseline, load_matdiff, load_material_dataset,
                                MatDiffSettings, MaterialDataSettings, MaterialPrompt, mean_pairwise, mnv2_features,
                                nearest_distances, sample_materials, save_sampler, train_classifier, train_matdiff)
    from inverse.btf import FAMILIES
    from mi_plugins.neural_basis import load_basis

    work = Path(work)
    work.mkdir(parents=True, exist_ok=True)
    result: dict = {"settings": asdict(s)}
    t0 = time.perf_counter()
    index_path = Path(s.data) / "index.json"
    # An existing dataset is continued with its own settings (made by `photoreal btf dataset` with other flags).
    data_settings = (from_json(MaterialDataSettings, read_json(index_path, "material dataset index")["settings"],
                               str(index_path)) if index_path.is_file() else MaterialDataSettings(count=s.count))
    build_material_dataset(s.data, data_settings,
                           pool=PoolSettings(workers=default_workers(), threads=1), progress=show_progress)
    index = read_json(Path(s.data) / "index.json", "material dataset index")
    ds = load_material_dataset(s.data)
    train, held = ds.subset(~ds.heldout), ds.subset(ds.heldout)
    if s.samples < len(held.names):  # the exemplar comparison pairs one unconditional sample with each held-out one
        raise UsageError(f"--samples {s.samples}: at least the {len(held.names)} held-out materials of {s.data}")
    fams = [f for f in dict.fromkeys(e["family"] for e in index["materials"])]
    result["dataset"] = {
        "materials": len(ds.names), "train": len(train.names), "heldout": len(held.names),
        "fit_psnr_heldout_slices": {"median": float(np.median(ds.psnr)),
                                    "per_family_median": {f: float(np.median(ds.psnr[ds.families == FAMILIES.index(f)]))
                                                          for f in fams}},
        "fit_seconds_per_material": float(np.mean([e["fit_seconds"] for e in index["materials"]])),
        "build_seconds_last_call": float(index.get("seconds_last_batch", 0.0)),
        "keywords_seen": sorted({w for k in ds.keywords for w in k})}
    basis = load_basis(bundled_basis())
    with torch_threads(0):
        from generative.btf import decode_all

        held_dec, train_dec = decode_all(basis, held.features), decode_all(basis, train.features)
        clf = train_classifier(train.swatches, train.families, work / "classifier",
                               ClassifierSettings(max_seconds=s.classifier_seconds, seed=s.seed), show_progress)
        result["classifier_accuracy_real"] = float(np.mean(classify(clf, held.swatches)[0] == held.families))
        result["classifier_accuracy_decoded_fits"] = float(np.mean(classify(clf, held_dec)[0] == held.families))
        judge = _Judge(basis, clf, held_dec, train_dec, ds.features.shape[1] // 2)

        # -- main model ---------------------------------------------------------------------------------------------
        if s.main_run:
            main_dir = Path(s.main_run)
            _check_trained_on(main_dir, train)
        else:
            main_dir = work / f"main_{int(s.train_seconds)}s"
            train_matdiff(train, main_dir, MatDiffSettings(max_seconds=s.train_seconds, seed=s.seed),
                          show_progress=show_progress)
        model, ms = load_matdiff(main_dir)
        result["main"] = {"settings": asdict(ms), "run": str(main_dir), "trained_here": not s.main_run,
                          "training": read_json(main_dir / "metrics.json", "metrics")}
        if (main_dir / "device.json").is_file():  # written by a run trained elsewhere (e.g. on a GPU)
            result["main"]["device"] = read_json(main_dir / "device.json", "device record")
        kw = _keyword_eval(model, ms, judge, held.keywords, held.families, s.steps, s.guidance, s.seed)
        fam_prompts = [[f, None, None] for f in (held.keywords[i][0] for i in range(len(held.names)))]
        kwf = _keyword_eval(model, ms, judge, fam_prompts, held.families, s.steps, s.guidance, s.seed + 1)
        result["keyword_accuracy"] = kw["accuracy"]
        result["keyword_family_share"] = np.bincount(kw.pop("pred"), minlength=8).tolist()  # what the samples look like
        result["denoising"] = denoising_check(model, ms, held.features, held.keywords, seed=s.seed)
        result["keyword_accuracy_family_word_only"] = kwf["accuracy"]
        result["keyword_references"] = _keyword_references(judge, ms, train, held, s.seed)

        rng = np.random.default_rng(s.seed)
        n = s.samples
        uncond = sample_materials(model, ms, [MaterialPrompt()] * n, judge.res, s.steps, 1.0, s.seed + 2)
        # p(x) = Σ_c p(c) p(x | c): keyword triples drawn from the training materials' own (no held-out information)
        prior = np.random.default_rng(s.seed + 5).integers(0, len(train.names), n)
        prior_kw = sample_materials(model, ms, [MaterialPrompt(train.keywords[i]) for i in prior], judge.res, s.steps,
                                    s.guidance, s.seed + 6)
        methods = {"diffusion": uncond, "diffusion_keywords": kw["features"], "diffusion_prior_keywords": prior_kw,
                   "copy": copy_baseline(train.features, n, rng), "gaussian": gaussian_baseline(train.features, n, rng),
                   "crop": crop_baseline(train.features, n, rng)}
        scores = {k: judge.score(judge.decode(v)) for k, v in methods.items()}
        scores["heldout_real"] = {"mn": judge.ref_mn}
        result["kid_classifier"] = {k: v["kid_classifier"] for k, v in scores.items() if "kid_classifier" in v}
        result["kid_mnv2"] = {k: v["kid_mnv2"] for k, v in scores.items() if "kid_mnv2" in v}
        result["fid_classifier"] = {k: v["fid_classifier"] for k, v in scores.items() if "fid_classifier" in v}
        result["family_share_unconditional"] = np.bincount(scores["diffusion"]["pred"], minlength=8).tolist()

        # memorisation and diversity (MobileNetV2 space of the swatch mosaic)
        ref_nn = nearest_distances(judge.ref_mn, judge.train_mn)

        def nn_ratio(mn: np.ndarray) -> float:  # median nearest-training distance over held-out materials'
            return float(np.median(nearest_distances(mn, judge.train_mn)) / np.median(ref_nn))

        nn = {k: nn_ratio(v["mn"]) for k, v in scores.items() if k != "heldout_real"}
        result["nn_distance_ratio"] = nn["diffusion"]
        result["nn_distance_ratio_all"] = nn
        result["nn_distance_heldout_median"] = float(np.median(ref_nn))
        result["diversity"] = mean_pairwise(scores["diffusion"]["mn"])
        result["diversity_all"] = {k: mean_pairwise(v["mn"]) for k, v in scores.items()}
        result["diversity_train"] = mean_pairwise(judge.train_mn)

        # exemplar conditioning: the held-out material's path-traced swatch 0 as the image prompt
        ex = sample_materials(model, ms, [MaterialPrompt(None, held.swatches[i, 0]) for i in range(len(held.names))],
                              judge.res, s.steps, s.guidance, s.seed + 3)
        ex_dec = judge.decode(ex)
        un_dec = judge.decode(uncond[:len(held.names)])
        q = mnv2_features(np.repeat(held.swatches[:, :1], 4, 1))
        pool_ = mnv2_features(np.repeat(train.swatches[:, :1], 4, 1))
        nearest = np.argmin(((q[:, None] - pool_[None]) ** 2).sum(-1), 1)
        ret_dec = train_dec[nearest]
        fl = {name: [aligned_flip(d[i], held.swatches[i]) for i in range(len(held.names))]
              for name, d in (("diffusion", ex_dec), ("unconditional", un_dec), ("retrieval", ret_dec),
                              ("fit_of_the_exemplar_material", held_dec))}
        result["exemplar_flip"] = {k: float(np.mean(v)) for k, v in fl.items()}
        result["exemplar_flip_std"] = {k: float(np.std(v)) for k, v in fl.items()}
        result["exemplar_family_accuracy"] = float(np.mean(classify(clf, ex_dec)[0] == held.families))

        # tiling
        result["seam_error"] = _seam(model, ms, judge, 2 * judge.res, 8, s.seed + 4, s.steps)  # 2× the training size
        result["seam_error_training_size"] = _seam(model, ms, judge, judge.res, 8, s.seed + 4, s.steps)
        from generative.btf import seam_ratio

        result["seam_error_heldout_fits"] = float(np.mean([seam_ratio(d[0]) for d in held_dec]))
        result["seam_error_crop_baseline"] = float(np.mean([seam_ratio(d[0]) for d in judge.decode(methods["crop"][:8])]))

        # speed and quality against steps
        sp: dict = {}
        for size in s.speed_sizes:
            for st in s.speed_steps:
                t = time.perf_counter()
                sample_materials(model, ms, [MaterialPrompt(["leather", None, None])], size, st, s.guidance, s.seed)
                sp[f"{size}_steps{st}"] = time.perf_counter() - t
        result["sample_seconds"] = sp
        qs = []
        for gw in s.quality_guidance:
            for st in s.quality_steps:
                e = (kw if (st, gw) == (s.steps, s.guidance) else
                     _keyword_eval(model, ms, judge, held.keywords, held.families, st, gw, s.seed))
                qs.append({"steps": st, "guidance": gw, "accuracy": e["accuracy"], "kid_mnv2": e["kid_mnv2"],
                           "kid_classifier": e["kid_classifier"], "seconds_per_sample": e["seconds_per_sample"]})
        best = max(q["accuracy"] for q in qs)
        result["quality_vs_steps"] = qs
        # the fewest steps within tolerance of the best; among those, the most accurate guidance
        ok = [q for q in qs if q["accuracy"] >= best - s.tolerance]
        pick = max((q for q in ok if q["steps"] == min(o["steps"] for o in ok)), key=lambda q: q["accuracy"])
        result["chosen_steps"], result["chosen_guidance"] = pick["steps"], pick["guidance"]
        # chosen on the sweep's samples, so scored again on fresh ones (other noise seeds): no selection bias
        # (``chosen_repeats`` sets of noise seeds, averaging out the sampler's noise)
        chosen = {"steps": pick["steps"], "guidance": pick["guidance"], "repeats": s.chosen_repeats}
        for j, (name, pr) in enumerate((("triples", held.keywords), ("family_word_only", fam_prompts))):
            acc = [_keyword_eval(model, ms, judge, pr, held.families, pick["steps"], pick["guidance"],
                                 s.seed + 10 + j + 100 * r)["accuracy"] for r in range(s.chosen_repeats)]
            p = float(np.mean(acc))
            # two errors: over which 32 materials are held out (binomial; more seeds do not shrink it) and over
            # the noise seeds (the spread of the repeats)
            chosen.update({name: p, f"{name}_each": acc,
                           f"{name}_standard_error": float(np.sqrt(p * (1 - p) / len(pr))),
                           f"{name}_seed_error": float(np.std(acc, ddof=1) / np.sqrt(len(acc))) if len(acc) > 1
                           else None})
        result["keyword_accuracy_chosen"] = chosen
        # KID at the chosen sampler too: unconditional and prior-keyword samples against the same baselines
        at = {"diffusion": sample_materials(model, ms, [MaterialPrompt()] * n, judge.res, pick["steps"], 1.0,
                                            s.seed + 7),
              "diffusion_prior_keywords": sample_materials(
                  model, ms, [MaterialPrompt(train.keywords[i]) for i in prior], judge.res, pick["steps"],
                  pick["guidance"], s.seed + 8)}
        sc_at = {k: judge.score(judge.decode(v)) for k, v in at.items()}
        # few steps might trade detail for safety: memorisation and diversity of these samples too
        result["at_chosen_nn_distance_ratio"] = {k: nn_ratio(v["mn"]) for k, v in sc_at.items()}
        result["at_chosen_diversity"] = {k: mean_pairwise(v["mn"]) for k, v in sc_at.items()}
        result["kid_at_chosen"] = {
            "kid_classifier": {**{k: v["kid_classifier"] for k, v in sc_at.items()},
                               **{k: result["kid_classifier"][k] for k in ("copy", "gaussian", "crop")}},
            "kid_mnv2": {**{k: v["kid_mnv2"] for k, v in sc_at.items()},
                         **{k: result["kid_mnv2"][k] for k in ("copy", "gaussian", "crop")}}}
        np.savez_compressed(work / "samples.npz", keyword=kw["features"], exemplar=ex, unconditional=uncond[:16],
                            held_swatches=held.swatches, held_keywords=np.array([" ".join(k) for k in held.keywords]))

        # ablations and dataset sweep at equal time
        rows = []
        if s.ablations:
            for name, change in ABLATIONS.items():
                d = work / ("ablation_" + name.split(" (")[0].replace(" ", "_")) / f"{int(s.ablation_seconds)}s"
                train_matdiff(train, d, MatDiffSettings(max_seconds=s.ablation_seconds, seed=s.seed, **change),
                              show_progress=show_progress)
                m, mss = load_matdiff(d)
                row = {"name": name, **_short_eval(m, mss, judge, held, s),
                       "steps_trained": read_json(d / "metrics.json", "metrics")["training"]["steps"]}
                rows.append(row)
        result["ablation"] = rows
        sweep = []
        for k in s.sweep_per_family:
            sub = load_material_dataset(s.data, limit=k)
            sub = sub.subset(np.isin(sub.names, train.names))  # the first k of each family: never held out
            if len(sub.names) >= len(train.names):
                continue
            d = work / f"sweep_{k}" / f"{int(s.ablation_seconds)}s"
            train_matdiff(sub, d, MatDiffSettings(max_seconds=s.ablation_seconds, seed=s.seed), show_progress=show_progress)
            m, mss = load_matdiff(d)
            sweep.append({"train_materials": len(sub.names), **_short_eval(m, mss, judge, held, s)})
        if rows:
            sweep.append({"train_materials": len(train.names), **{k: v for k, v in rows[0].items() if k != "name"}})
        result["dataset_sweep"] = sweep
    result["seconds"] = time.perf_counter() - t0
    result["verdict"] = _verdict(result)
    # only a finished bench changes the run's recorded sampler (`btf generate` samples the run as chosen here)
    result["sampler_record"] = str(save_sampler(
        main_dir, result["chosen_steps"], result["chosen_guidance"],
        f"bench matdiff {time.strftime('%Y-%m-%d')}: fewest DDIM steps within {s.tolerance} of the best held-out "
        f"keyword accuracy ({max(q['accuracy'] for q in result['quality_vs_steps']):.3f})"))
    return result


def _beats(r: dict | None, a: str, b: str) -> bool | None:
    """Lower KID than ``b`` in both feature spaces (None when ``a`` was not measured)."""
    if not r or a not in r["kid_classifier"]:
        return None
    k1, k2 = r["kid_classifier"], r["kid_mnv2"]
    return k1[a] < k1[b] and k2[a] < k2[b]


def _verdict(r: dict) -> dict:
    k1, k2 = r["kid_classifier"], r["kid_mnv2"]
    return {
        "keyword_accuracy_at_least_0.7": r.get("keyword_accuracy_chosen", {}).get("triples", r["keyword_accuracy"]) >= 0.7,
        "beats_gaussian_kid_both": _beats(r, "diffusion", "gaussian"),
        "beats_crop_kid_both": _beats(r, "diffusion", "crop"),
        # the same with keywords drawn from the training prior (a sample of p(x), as the baselines are)
        "prior_keywords_beat_gaussian_kid_both": _beats(r, "diffusion_prior_keywords", "gaussian"),
        "prior_keywords_beat_crop_kid_both": _beats(r, "diffusion_prior_keywords", "crop"),
        "at_chosen_beats_gaussian_kid_both": _beats(r.get("kid_at_chosen"), "diffusion", "gaussian"),
        "at_chosen_beats_crop_kid_both": _beats(r.get("kid_at_chosen"), "diffusion", "crop"),
        "at_chosen_prior_keywords_beat_gaussian_kid_both": _beats(r.get("kid_at_chosen"), "diffusion_prior_keywords",
                                                                  "gaussian"),
        "at_chosen_prior_keywords_beat_crop_kid_both": _beats(r.get("kid_at_chosen"), "diffusion_prior_keywords",
                                                              "crop"),
        "not_copies": r["nn_distance_ratio"] >= 1.0,
        "exemplar_beats_unconditional_flip": r["exemplar_flip"]["diffusion"] < r["exemplar_flip"]["unconditional"],
        "exemplar_beats_retrieval_flip": r["exemplar_flip"]["diffusion"] < r["exemplar_flip"]["retrieval"],
    }


def speed_charts(result: dict, out: Path) -> list[str]:
    """Speed / quality vs steps, and the dataset sweep and ablations."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from foundation.imageio import save_figure

    fig, ax = plt.subplots(1, 3, figsize=(14, 4))
    sp = result["sample_seconds"]
    for size in sorted({int(k.split("_")[0]) for k in sp}):
        pts = sorted((int(k.split("steps")[1]), v) for k, v in sp.items() if k.startswith(f"{size}_"))
        ax[0].plot(*zip(*pts), "o-", label=f"{size}²")
    ax[0].set(xlabel="DDIM steps", ylabel="seconds per sample (2 cores, CFG)", title="sampling time")
    ax[0].legend()
    q = result["quality_vs_steps"]
    for gw in dict.fromkeys(e.get("guidance", 2.0) for e in q):
        row = [e for e in q if e.get("guidance", 2.0) == gw]
        ax[1].plot([e["steps"] for e in row], [e["accuracy"] for e in row], "o-", label=f"keyword accuracy, CFG {gw:g}")
        ax[1].plot([e["steps"] for e in row], [e["kid_mnv2"] for e in row], "s--", label=f"KID (MobileNetV2), CFG {gw:g}")
    ax[1].axvline(result["chosen_steps"], color="grey", lw=0.8)
    ax[1].set(xlabel="DDIM steps", title=f"quality vs steps (chosen {result['chosen_steps']}, "
              f"CFG {result.get('chosen_guidance', 2.0):g})")
    ax[1].legend()
    sw = result["dataset_sweep"]
    if sw:
        ax[2].plot([e["train_materials"] for e in sw], [e["accuracy"] for e in sw], "o-", label="keyword accuracy")
        ax[2].plot([e["train_materials"] for e in sw], [e["kid_mnv2"] for e in sw], "s--", label="KID (MobileNetV2)")
        ax[2].set(xlabel="training materials", title="dataset size (equal training time)")
        ax[2].legend()
    fig.tight_layout()
    return [str(save_figure(fig, out))]


def samples_figure(work: Path, out: Path) -> str:
    """Decoded swatches (view 0): keyword samples with their prompts, exemplar → sample pairs."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from foundation.assets import bundled_basis
    from foundation.imageio import linear_to_srgb, save_figure
    from generative.btf import decode_all
    from mi_plugins.neural_basis import load_basis

    z = np.load(work / "samples.npz")
    basis = load_basis(bundled_basis())
    n = min(8, len(z["keyword"]))
    kw, ex = decode_all(basis, z["keyword"][:n]), decode_all(basis, z["exemplar"][:n])
    fig, ax = plt.subplots(3, n, figsize=(1.6 * n, 5.2))
    for i in range(n):
        for r, (img, title) in enumerate(((kw[i, 0], z["held_keywords"][i]), (z["held_swatches"][i, 0], "exemplar"),
                                          (ex[i, 0], "from exemplar"))):
            ax[r, i].imshow(np.clip(linear_to_srgb(np.clip(img, 0, 1)), 0, 1))
            ax[r, i].set_title(str(title), fontsize=7)
            ax[r, i].axis("off")
    fig.tight_layout()
    return str(save_figure(fig, out))


# -- the benchmark protocol (photoreal.benchmarks) -------------------------------------------------------------------

SETTINGS = MatDiffBenchSettings
SUMMARY = ("classifier_accuracy_real", "keyword_accuracy", "kid_classifier", "kid_mnv2", "nn_distance_ratio", "diversity",
           "exemplar_flip", "seam_error", "sample_seconds", "chosen_steps", "chosen_guidance", "keyword_accuracy_chosen",
           "verdict")


def run(s: MatDiffBenchSettings, work: Path, pool, show_progress: bool) -> dict:
    return bench_matdiff(s, work, show_progress)


def charts(result: dict, json_path: Path, work: Path | None) -> dict:
    out = Path(json_path)
    return {"charts": speed_charts(result, out.with_name(out.stem + "_speed.png")),
            "samples_figure": samples_figure(work, out.with_name(out.stem + "_samples.png"))}


def options(p) -> None:
    from photoreal.options import opt

    for name in ("data", "count", "train_seconds", "ablation_seconds", "samples", "steps", "guidance", "seed"):
        opt(p, MatDiffBenchSettings, name)
    opt(p, MatDiffBenchSettings, "main_run", help="finished `btf train-diffusion` run (e.g. trained with --device "
         "cuda) to evaluate instead of training the main model here; default: train here")
    opt(p, MatDiffBenchSettings, "ablations", "--no-ablations", help="skip the ablation runs")
