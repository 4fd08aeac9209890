"""The morph sections: a morph of a coarse reconstruction and why its choices went as they did, the GAN refinement, the diffusion renderer."""

from __future__ import annotations

import html
from pathlib import Path

from foundation.assets import ARMADILLO
from foundation.records import to_json

from .report import add_section, bench_json, copy_chart, figure, table


def _where(mr) -> str:
    """Where the planarity prior acted, when not on every edge."""
    p = mr.planarity
    if p.where == "all" or not p.weight:
        return ""
    why = "those beside a triangle a fitted photo sees" if p.where == "seen" else "those on parts that are not thin"
    return f" on {p.edges} of {p.edges_all} interior edges ({why})"


def _colour_why(mr) -> str:
    """Why the morph ran with its colour-prior weight, in words."""
    c = mr.colour_selection
    if c is not None:
        return (f"the input's colours are smooth; at iteration {c.at_iteration} the validation photos "
                f"{'kept' if c.kept else 'dropped'} the prior: L1 {c.validation_l1_with:.4f} with, "
                f"{c.validation_l1_without:.4f} without (kept only {c.margin:.1%} or more below)")
    if mr.colour_prior and mr.colour_prior.auto:
        return f"auto: mean colour step per edge of the input {mr.colour_prior.input_colour_step:.4f}, on below 0.015"
    return "given"


def _light_why(mr) -> str:
    """Whether the morph ran with the light estimate and colour large steps, and why, in words."""
    c = getattr(mr, "light_selection", None)
    if c is None:
        s = mr.settings
        return (f"given: light estimate every {s.indirect_every} iterations, colour λ {s.colour_lambda:g}"
                if s.indirect_every or s.colour_lambda else "off")
    return (f"{'on' if c.kept else 'off'}: at iteration {c.at_iteration} the validation photos, each run measured "
            f"after a fresh light estimate, gave L1 {c.validation_l1_with:.4f} with, {c.validation_l1_without:.4f} "
            f"without (kept only {c.margin:.1%} or more below)")


def _step_why(mr) -> str:
    """Which step the morph's positions took (uniform or quantile Adam), and why, in words."""
    c = getattr(mr, "step_selection", None)
    if c is None:
        q = mr.settings.adam_quantile
        return "uniform Adam (given)" if q == 1.0 else f"quantile {q:g} of Adam's second moments (given)"
    return (f"{f'quantile {c.quantile:g}, lr {c.lr:g}' if c.kept else 'uniform Adam'}: at iteration {c.at_iteration} "
            f"the validation photos gave L1 {c.validation_l1_quantile:.4f} with the quantile step, "
            f"{c.validation_l1_uniform:.4f} with uniform Adam (kept only {c.margin:.1%} or more below)")


def demo_sized(s):
    """A morph's settings with each choice given instead of asked of the validation photos: the first λ candidate,
    no planarity or colour prior candidates, uniform Adam, no light estimate (one run, not a run per candidate)."""
    from dataclasses import replace

    return replace(s, lambda_select=s.lambda_select[:1], planarity_select=(), colour_prior_weight=0.0,
                   step_select_quantile=1.0, light_select_every=0)


def demo_morph(out_dir: Path, iterations: int = 100, seed: int = 0, bench_dir: Path | None = None) -> dict:
    """Armadillo morph benchmark: degraded input vs morphed vs photo, metrics; bench tables if present."""
    import shutil

    from inverse.morph import (MorphBenchmarkSettings, MorphSettings, benchmark_errors, load_morph_benchmark,
                               make_morph_benchmark, run_morph)

    mdir = Path(out_dir) / "morph"
    bench = load_morph_benchmark(make_morph_benchmark(ARMADILLO, mdir / "benchmark", MorphBenchmarkSettings(seed=seed)))
    shutil.rmtree(mdir / "run", ignore_errors=True)
    mr = run_morph(bench, mdir / "run", demo_sized(MorphSettings(iterations=iterations, seed=seed)))
    m = to_json(mr)
    m.update(inverted_before_repair=mr.repair.inverted_before_repair if mr.repair else None,
             repaired_vertices=mr.repair.repaired_vertices if mr.repair else None,
             border_turned_before=mr.border_turns.turned_before if mr.border_turns else None,
             border_turned_after=mr.border_turns.turned_after if mr.border_turns else None)
    i = bench.meta.test[0]
    figs = "".join(figure(f"morph/run/heldout_{k}_view{i:02d}.png", label) for k, label in
                   (("input", "coarse input (held-out view)"), ("morphed", "morphed"), ("photo", "photo")))
    rows = [{"metric": k, "value": float(m[k])} for k in
            ("chamfer_input", "chamfer_morphed", "chamfer_reduction", "psnr_heldout_input", "psnr_heldout_morphed",
             "spikes", "inverted_triangles", "inverted_before_repair", "repaired_vertices", "border_turned_before",
             "border_turned_after", "seconds")
            if m.get(k) is not None]
    # where the error sits (photoreal morph errors): what of the input's error the morph kept, what it made
    err = {e.name: e for e in benchmark_errors(bench, {"morphed": mdir / "run" / "morphed.ply"}, mdir / "errors").meshes}
    rows += [{"metric": "input's error left (slope)", "value": err["morphed"].input_error_left},
             {"metric": "new error (rms)", "value": err["morphed"].new_error_rms}]
    body = (f"<p>Stanford Armadillo, {len(bench.meta.cameras)} drone-orbit photos path traced under the "
            f"{bench.meta.hdri} HDRI; degraded input: {bench.meta.degradation.coarse_vertices} vertices "
            f"with bumps, wobble and misregistered colours. Morph (demo-sized: each choice given, one run; "
            f"<code>photoreal morph run BENCHMARK</code> asks the validation photos for λ, planarity, colour prior, "
            f"step and light, a trial run each): {iterations} iterations, large steps, lit mode, "
            f"3 views per step, input remeshed to {m['vertices']} vertices; folds left at the end are unfolded "
            f"locally and counted (inverted_before_repair), and so are curls of an open border (its triangles turned "
            f"more than {mr.settings.border_turn_deg:g}° from the start, border_turned_before / after). Planarity prior weight {mr.planarity.weight:g}"
            f"{_where(mr)} (auto: the input's largest plane holds {mr.planarity.dominant_plane_fraction or 0:.0%} of its area; "
            f"on from {mr.settings.planarity_auto_threshold:.0%}, as on the village). Colour prior weight {mr.colour_prior.weight:g} "
            f"({_colour_why(mr)}). Light estimate and colour large steps {_light_why(mr)}. Step {_step_why(mr)}.</p><div>{figs}</div>" + table(rows, ["metric", "value"])
            + "<p>Where the error sits (<code>photoreal morph errors</code>): signed distance to the truth, blue "
              "behind it, red in front, coarse input above, morphed below; the input's error left is the slope of "
              "the result's signed distance on the input's (1: kept, 0: gone), the new error what that leaves.</p>"
            + figure("morph/errors/errors.png", "signed distance to the truth")
            + "<p>Where the orientation is wrong: the triangles facing against the truth (the suite's facing "
              "target; the row's label gives their share of the area), from the camera that sees most of them.</p>"
            + figure("morph/errors/facing.png", "triangles facing against the truth"))
    mb = bench_json(bench_dir, "morph")
    if mb is not None:
        body += "<h3>Benchmark (<code>photoreal bench morph</code>)</h3>"
        for case, r in mb["cases"].items():
            cols = ["chamfer_input", "chamfer_morphed", "chamfer_reduction", "psnr_heldout_input",
                    "psnr_heldout_morphed", "spikes", "s_per_iter_10k_4views_128", "s_per_iter_baseline",
                    "chosen_vertices", "dominant_plane_fraction", "planarity_weight"]
            body += f"<h4>{html.escape(case)}</h4>" + table([{k: r.get(k) for k in cols}], cols)
            body += "<p>Stability</p>" + table([{"case": k, **v} for k, v in r["stability"].items()],
                                               ["case", "chamfer_input", "chamfer_morphed", "psnr_heldout_input",
                                                "psnr_heldout_morphed", "spikes", "inverted_triangles",
                                                "inverted_before_repair", "converged"])
        if copy_chart(mb, bench_dir, mdir / "morph_speed_accuracy.png"):
            body += "<img src='morph/morph_speed_accuracy.png'>"
    add_section(out_dir, "40_morph", "Geometry morphing of a coarse reconstruction, against ground truth", body)
    return {k: m[k] for k in ("chamfer_input", "chamfer_morphed", "psnr_heldout_input", "psnr_heldout_morphed")}


def demo_gan(out_dir: Path, bench_dir: Path | None = None) -> dict | None:
    """The `photoreal bench gan` table and chart (held-out views), when that JSON exists; no training here."""
    b = bench_json(bench_dir, "gan")
    if b is None:
        return None
    Path(out_dir).mkdir(parents=True, exist_ok=True)
    cols = ["model", "mse", "me", "one_minus_ssim", "nrmse", "sam_deg", "flip", "psnr", "train_s", "infer_ms"]

    def rows(r: dict) -> list[dict]:
        return [{"model": name, **m, "train_s": r["train_seconds"].get("morph" if name == "morphed" else name, ""),
                 "infer_ms": r["infer_ms_per_image"].get(name, "")} for name, m in r["heldout"].items()]

    s = b["settings"]
    body = (f"<p>Held-out views ({', '.join(s['cases'])}), mean over cases; input = coarse mesh render, morphed = "
            f"morph run ({s['morph_iterations']} iterations), GANs trained {s['seconds_per_model']:.0f} s each on "
            f"{s['crop']}² crops, joint {s['joint_seconds']:.0f} s from scratch; the two fine-tunes continue the "
            f"two-stage Morph-GAN for {s.get('finetune_seconds', 0):.0f} s more each, with the mesh fixed "
            f"(morph_gan_finetune) or optimised jointly through the renderer (joint_finetune). "
            f"Lower is better except PSNR.</p>" + table(rows(b), cols))
    body += "<p>Thesis ordering on held-out views: " + ", ".join(
        f"{html.escape(k)} = {v}" for k, v in b.get("ordering", {}).items()) + "</p>"
    regions = b.get("artifact_regions") or {}
    if regions:
        rcols = ["region", "model", "mse", "me", "one_minus_ssim", "flip", "pixels"]
        body += ("<p>Errors per artifact region (held-out pixels of cut chimneys, lifted chimneys, geometric "
                 "edges, flat surfaces; from ground-truth renders; pixel-weighted over cases):</p>" + table(
                     [{"region": reg, "model": row, **m} for reg, t in regions.items() for row, m in t.items() if m],
                     rcols))
    for case, r in b.get("cases", {}).items():
        body += f"<h4>{html.escape(case)}</h4>" + table(rows(r), cols)
    if copy_chart(b, bench_dir, Path(out_dir) / "gan_speed_accuracy.png"):
        body += "<img src='gan_speed_accuracy.png'>"
    add_section(out_dir, "45_gan", "GAN refinement: pix2pix, CycleGAN, Morph-GAN, joint training (REAL-DIBS §3, §5, §6)",
                body)
    return {k: v.get("mse") for k, v in b["heldout"].items()}


def demo_diffrender(out_dir: Path, bench_dir: Path | None = None) -> dict | None:
    """The `photoreal bench diffrender` tables, side-by-side views and sweep chart, when that JSON exists."""
    b = bench_json(bench_dir, "diffrender")
    if b is None or "ablation" not in b:
        return None
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    cols = ["method", "psnr", "one_minus_ssim", "flip", "mse", "kid_mnv2", "fid_mnv2", "kid_mnv2_spatial"]
    rows = [{"method": k, **{c: m[c] for c in cols[1:5]}, "kid_mnv2": b["kid_mnv2"].get(k, ""),
             "fid_mnv2": b["fid_mnv2"].get(k, ""), "kid_mnv2_spatial": b.get("kid_mnv2_spatial", {}).get(k, "")}
            for k, m in b["heldout"].items()]
    s = b["settings"]
    body = (f"<p>Held-out views of {', '.join(s['cases'])} (mean over cases; diffusion: mean over {s['seeds']} sampling "
            f"seeds, {b['ddim_steps']} DDIM steps, mean of {b.get('draws', 1)} per view, guidance {b['guidance']}). diffusion = rendered from the morphed "
            f"mesh's G-buffers, diffusion_coarse = from the coarse mesh's. KID/FID use ImageNet MobileNetV2 "
            f"features (not Inception); kid_mnv2_spatial uses every position of their 4×4 last feature map (16 "
            f"vectors per image). Lower is better except PSNR.</p>" + table(rows, cols))
    if b.get("references"):
        body += ("<h4>What the targets demand (nothing trained)</h4><p>pbr_morphed_clean = the morphed mesh's "
                 "recomposition from G-buffers at " + str(s.get("reference_spp", "")) + " spp (what denoising alone "
                 "can gain over pbr_morphed); truth_clean = the ground truth itself path traced at as many samples "
                 "(the photos' own noise floor).</p>"
                 + table([{"method": k, **m} for k, m in b["references"].items()],
                          ["method", "psnr", "one_minus_ssim", "flip", "mse"]))
    dist = b.get("distribution", {})
    if "photos_clean" in dist:
        rows = [{"set": k, **{f"{m}_photos": dist["photos"].get(k, {}).get(m, "") for m in ("kid", "kid_std", "kid_spatial")},
                 **{f"{m}_clean": v[m] for m in ("kid", "kid_std", "kid_spatial", "kid_spatial_std")}}
                for k, v in dist["photos_clean"].items()]
        body += ("<h4>MobileNetV2-KID against the photos and against the same views without Monte-Carlo noise</h4>"
                 "<p>_clean = distances to the held-out views path traced again at the references' samples per "
                 "pixel (another seed); ± = jackknife over images. The features respond to the photos' "
                 f"Monte-Carlo noise ({s.get('photo_spp', 64)} spp) as to texture: truth_clean (the true scene, "
                 "clean) against the photos is the oracle of what the first columns can tell.</p>"
                 + table(rows, ["set", "kid_photos", "kid_std_photos", "kid_spatial_photos", "kid_clean",
                                 "kid_std_clean", "kid_spatial_clean", "kid_spatial_std_clean"]))
    for c, u in b.get("unseen", {}).items():
        body += f"<h4>Unseen mesh: {html.escape(c)} (never trained on)</h4>" + table(
            [{"method": k, **m} for k, m in u.items()], ["method", "psnr", "one_minus_ssim", "flip", "mse"])
    d = b["decomposition"]
    body += (f"<h4>Decomposition network</h4><p>{d['scenes']} procedural scenes ({d['heldout_scenes']} held out), "
             f"{d['steps']} steps; held-out PSNR per layer (dB): "
             + ", ".join(f"{k} {v:.2f}" for k, v in d["psnr"].items()) + " (trivial decomposition A = image, I = 1, "
             "S = 0: " + ", ".join(f"{k} {v:.2f}" for k, v in d.get("psnr_trivial", {}).items())
             + f"); {d['extra_pairs']} extra pairs.</p>")
    body += (f"<h4>Equal-time ablations ({s['ablation_seconds']:.0f} s each)</h4>"
             + table([{**r, **{f"{c} flip": m["flip"] for c, m in r.get("unseen", {}).items()}} for r in b["ablation"]],
                      ["run", "global_source", "residual", "known_background", "decomposed_pairs", "sources",
                       "train_steps", "steps", "psnr", "flip", "one_minus_ssim", "mse",
                       *[f"{c} flip" for c in s.get("unseen", ())], "seconds_per_image"]))
    c = b["chosen"]
    tol = (f"{100 * c['tolerance_rel']:g} % of the best ꟻLIP" if "tolerance_rel" in c
           else f"{c.get('tolerance_flip')} ꟻLIP of the best")
    size = (f" The main model's size was chosen on the {c['size_from']}: widths <b>{c['main_widths']}</b>."
            if "main_widths" in c else "")
    body += (f"<p>Sampler chosen automatically (cheapest within {tol}): the <b>{c['model']}</b> row, "
             f"<b>{c['steps']}</b> DDIM steps, mean of {c.get('draws', 1)} per view, guidance "
             f"{c.get('guidance', b['guidance'])}, {c['seconds_per_image']:.2f} s per 128² image.{size}</p>")
    for key, name in (("chart", "diffrender_sweep.png"), ("views_figure", "diffrender_views.png")):
        if copy_chart({"chart": b.get(key)}, bench_dir, out_dir / name):
            body += f"<img src='{name}' style='max-width:100%'>"
    add_section(out_dir, "48_diffrender", "Intrinsic-conditioned diffusion renderer (seed 000)", body)
    return {k: v.get("flip") for k, v in b["heldout"].items()}


def demo_refiners(out_dir: Path, seconds: float = 15.0, seed: int = 0) -> dict:
    """Morph-GAN and the diffusion renderer trained demo-sized (``seconds`` each, from scratch, all cores) on the
    demo morph's training views (``OUT/morph``, made by :func:`demo_morph`), beside the morphed mesh's renders at the
    held-out views. `photoreal bench gan` and `photoreal bench diffrender` train them in full."""
    import numpy as np

    from foundation import imageio
    from foundation.metrics import ImageMetrics, image_metrics
    from generative.diffrender import (DiffRenderSettings, SampleSettings, load_diffrender, load_intrinsic_views,
                                       render_views, train_diffrender)
    from generative.gan import GanTrainSettings, load_heldout_predictions, load_paired_views, train_gan
    from inverse.morph import load_morph_benchmark

    mdir = Path(out_dir) / "morph"
    bench = load_morph_benchmark(mdir / "benchmark")
    run, work = mdir / "run", mdir / "refiners"
    pairs = load_paired_views(bench, run, show_progress=False)
    ids = list(pairs.test)
    gan = train_gan(pairs, work / "morph_gan", GanTrainSettings(max_seconds=seconds, threads=0, seed=seed),
                    show_progress=False)
    views = load_intrinsic_views(bench, run, show_progress=False)
    ds = DiffRenderSettings(max_seconds=seconds, widths=(16, 32, 48, 64), seed=seed)  # a smaller UNet: more steps
    dr_result = train_diffrender([views], work / "diffrender", ds, show_progress=False)
    model, s = load_diffrender(work / "diffrender")
    diffusion, _ = render_views(model, s, {k: a[ids] for k, a in views.layers["morphed"].items()},
                                SampleSettings(draws=2, seed=seed), show_progress=False)
    images = {"coarse input": pairs.rendered[ids], "morphed (path traced)": pairs.morphed[ids],
              "morphed, PBR recomposition": views.recomposed("morphed")[ids],
              f"Morph-GAN ({gan.training.steps} steps)": load_heldout_predictions(work / "morph_gan", ids),
              f"diffusion renderer ({dr_result.training.steps} steps)": diffusion}
    rows, figs = [], []
    for k, (name, im) in enumerate(images.items()):
        m = ImageMetrics.mean([image_metrics(p, r) for p, r in zip(im, pairs.photos[ids])])
        rows.append({"render": name, "psnr": m.psnr, "flip": m.flip, "one_minus_ssim": m.one_minus_ssim})
        imageio.write_png(work / f"view_{k}.png", np.clip(im[0], 0, 1))
        figs.append(figure(f"morph/refiners/view_{k}.png", name))
    imageio.write_png(work / "photo.png", pairs.photos[ids[0]])
    figs.append(figure("morph/refiners/photo.png", "photo"))
    body = (f"<p>Demo-sized: Morph-GAN and the diffusion renderer each trained <b>{seconds:g} s</b> from scratch on "
            f"the morph's {len(pairs.train)} training views (the full runs: <code>photoreal bench gan</code>, "
            "<code>photoreal bench diffrender</code>; their tables follow where the bench folder has them). Held-out "
            f"view {ids[0]} and the mean over the {len(ids)} held-out views; lower is better except PSNR.</p>"
            f"<div>{''.join(figs)}</div>" + table(rows, ["render", "psnr", "flip", "one_minus_ssim"]))
    add_section(out_dir, "44_refiners", "Learned refinement of the morphed mesh's renders, demo-sized", body)
    return {r["render"]: {"psnr": r["psnr"], "flip": r["flip"]} for r in rows}
