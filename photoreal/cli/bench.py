"""`photoreal bench …`: the benchmarks, each writing JSON (speed as ratios measured in the same run)."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from .common import default_of, opt, pool_options, pool_settings, print_json, settings_from

HELP = "benchmarks writing JSON (speed as ratios measured in the same run)"


def _bench_out(a) -> Path:
    from foundation.files import check_output_file

    return check_output_file(a.json, "--json")


def _cmd_bench_plugins(a) -> int:
    from foundation.files import write_json

    from ..benchmarks.plugins import PluginBenchSettings, bench_plugins

    out = _bench_out(a)
    result = bench_plugins(settings_from(PluginBenchSettings, a))
    write_json(out, result)
    print_json({k: result[k] for k in ("ggx_uv_ms", "principled_ms", "ggx_uv_vs_principled", "compile_s")})
    return 0


def _cmd_bench_morph(a) -> int:
    from foundation.files import write_json
    from foundation.pool import ray_shutdown

    from ..benchmarks.morph import MorphBenchSettings, bench_morph

    out = _bench_out(a)
    try:
        result = bench_morph(settings_from(MorphBenchSettings, a), out_dir=out.parent, pool=pool_settings(a))
    finally:
        ray_shutdown()
    write_json(out, result)
    shown = {k: result[k] for k in ("chamfer_input", "chamfer_morphed", "chamfer_reduction", "psnr_heldout_input",
                                    "psnr_heldout_morphed", "spikes", "s_per_iter_10k_4views_128",
                                    "s_per_iter_baseline", "chosen_vertices") if k in result}
    if "suite" in result:
        shown.update(suite_mean=result["suite"]["mean"], suite_failing=result["suite"]["failing"])
    if "iteration_cost" in result:
        c = result["iteration_cost"]
        shown.update(s_per_iteration=c["s_per_iteration"], iteration_cost_ratio=c["ratio"],
                     iteration_cost_ratio_by_round={k: round(v["median"], 4) for k, v in c["ratio_by_round"].items()})
    print_json(shown)
    return 0


def _cmd_bench_morph_seeds(a) -> int:
    from foundation.files import write_json

    from ..benchmarks.morph import compare_chart, seeds_chart, seeds_compare, seeds_summary

    out = _bench_out(a)
    summary = seeds_summary(a.results)  # every file read and checked before anything is written
    if a.against:
        base = seeds_summary(a.against)
        summary["against"] = base
        summary["comparison"] = seeds_compare(summary, base)
    summary["chart"] = str(seeds_chart(summary, out.with_name(out.stem + ".png")))
    if a.against:
        summary["comparison"]["chart"] = str(compare_chart(summary["comparison"],
                                                           out.with_name(out.stem + "_against.png")))
    write_json(out, summary)
    shown = {"seeds": summary["seeds"], "every_seed_pass": summary["every_seed_pass"],
             "passes": {n: f"{m['passes']} of {m['of']}" for n, m in summary["meshes"].items()},
             "chamfer_reduction_worst": {n: round(m["chamfer_reduction"]["worst"], 4)
                                         for n, m in summary["meshes"].items()}}
    if a.against:
        c = summary["comparison"]
        shown["against"] = {"pairs": c["pairs"], "chamfer_delta_mean": round(c["chamfer_delta"]["mean"], 4),
                            "chamfer_delta_se": c["chamfer_delta"]["se"] and round(c["chamfer_delta"]["se"], 4),
                            "wins": c["wins"], "losses": c["losses"], "sign_test_p": round(c["sign_test_p"], 3),
                            "passes_every_target": c["passes"],
                            "gained": c["gained"], "lost": c["lost"]}
    print_json(shown)
    return 0


def _cmd_bench_morph_light_draws(a) -> int:
    from foundation.files import write_json

    from ..benchmarks.morph import light_draws, light_draws_chart

    out = _bench_out(a)
    result = light_draws(a.results, a.draws)
    result["chart"] = str(light_draws_chart(result, out.with_name(out.stem + ".png")))
    write_json(out, result)
    print_json({"light_choices": len(result["rows"]), "draws": result["draws"],
            "draw0_vs_stored_max": result["draw0_vs_stored_max"], "advantage_sd": result["advantage_sd"],
            "overturned_by_a_draw": result["overturned_by_a_draw"]})
    return 0


def _cmd_bench_btf(a) -> int:
    from foundation.files import write_json
    from foundation.pool import ray_shutdown

    from ..benchmarks.btf import BTFBenchSettings, bench_btf

    out = _bench_out(a)
    try:
        result = bench_btf(settings_from(BTFBenchSettings, a), out_dir=out.parent, pool=pool_settings(a))
    finally:
        ray_shutdown()
    write_json(out, result)
    print_json({k: result[k] for k in ("psnr_universal_mean", "psnr_per_material_mean", "neural_btf_ms", "principled_ms",
                                   "neural_btf_vs_principled", "mlp_evals_per_s_drjit", "mlp_evals_per_s_torch",
                                   "chosen")})
    return 0


def _cmd_bench_face(a) -> int:
    from foundation.files import write_json

    from ..benchmarks.face import FaceBenchSettings, bench_face

    out = _bench_out(a)
    s = settings_from(FaceBenchSettings, a)
    s.scan_path()
    result = bench_face(s, out_dir=out.parent)
    write_json(out, result)
    print_json({k: result[k] for k in ("albedo_psnr", "normal_err_deg", "roughness_mae", "specular_mae", "relit_psnr",
                                   "relit_flip", "fit_seconds_256", "chosen_uv_res")})
    return 0


def _cmd_bench_scale(a) -> int:
    from foundation.files import write_json

    from ..benchmarks.scale import ScaleBenchSettings, bench_scale

    out = _bench_out(a)
    result = bench_scale(settings_from(ScaleBenchSettings, a), out_dir=out.parent)
    write_json(out, result)
    print_json({k: result.get(k) for k in ("items", "serial_s", "pool_s", "ray_s", "speedup_pool_2",
                                       "ray_overhead_per_item_s", "identical")})
    return 0


def _cmd_bench_gan(a) -> int:
    from foundation.files import write_json

    from ..benchmarks.gan import GanBenchSettings, bench_gan

    out = _bench_out(a)
    s = GanBenchSettings()
    if a.seconds_per_model is not None:
        t = a.seconds_per_model  # the other budgets keep their default proportions
        s = dataclasses.replace(s, seconds_per_model=t, joint_seconds=1.5 * t, cyclegan_seconds=3 * t,
                                finetune_seconds=0.75 * t)
    result = bench_gan(s, out_dir=out.parent)
    write_json(out, result)
    print_json({k: result[k] for k in ("heldout", "train_seconds", "infer_ms_per_image", "ordering")})
    return 0


def _cmd_bench_diffrender(a) -> int:
    from foundation.files import write_json

    from ..benchmarks.diffrender import DiffRenderBenchSettings, bench_diffrender, sweep_chart, views_figure

    out = _bench_out(a)
    result = bench_diffrender(settings_from(DiffRenderBenchSettings, a), out_dir=out.parent)
    result["chart"] = str(sweep_chart(result, out.with_name(out.stem + "_sweep.png")))
    result["views_figure"] = str(views_figure(result, out.parent, out.with_name(out.stem + "_views.png")))
    write_json(out, result)
    print_json({k: result[k] for k in ("heldout", "unseen", "kid_mnv2", "fid_mnv2", "kid_mnv2_clean", "decomposition_psnr",
                                   "chosen", "sample_seconds_128", "train_flops_fraction", "verdict") if k in result})
    return 0


def _cmd_bench_matdiff(a) -> int:
    from foundation.files import write_json

    from ..benchmarks.matdiff import MatDiffBenchSettings, bench_matdiff, charts, samples_figure

    out = _bench_out(a)
    result = bench_matdiff(settings_from(MatDiffBenchSettings, a), out_dir=out.parent)
    result["charts"] = charts(result, out.with_name(out.stem + "_speed.png"))
    result["samples_figure"] = samples_figure(out.parent / "matdiff_work", out.with_name(out.stem + "_samples.png"))
    write_json(out, result)
    print_json({k: result[k] for k in ("classifier_accuracy_real", "keyword_accuracy", "kid_classifier", "kid_mnv2",
                                   "nn_distance_ratio", "diversity", "exemplar_flip", "seam_error", "sample_seconds",
                                   "chosen_steps", "chosen_guidance", "keyword_accuracy_chosen", "verdict")})
    return 0


def _cmd_bench_face_learned(a) -> int:
    from foundation.files import write_json

    from ..benchmarks.face_learned import FaceLearnedBenchSettings, bench_face_learned

    out = _bench_out(a)
    result = bench_face_learned(settings_from(FaceLearnedBenchSettings, a), out_dir=out.parent)
    write_json(out, result)
    print_json({k: result.get(k) for k in ("completion", "decomposition", "superres", "end_to_end", "verdict")})
    return 0


def _cmd_bench_startup(a) -> int:
    from foundation.files import write_json

    from ..benchmarks.startup import StartupBenchSettings, bench_startup

    out = _bench_out(a)
    result = bench_startup(settings_from(StartupBenchSettings, a))
    write_json(out, result)
    print_json({"python_s": result["python_s"], "slowest": result["slowest"],
                "all_within_target": result["all_within_target"],
                "median_s": {n: round(r["median_s"], 3) for n, r in result["commands"].items()}})
    return 0


def add(parser: argparse.ArgumentParser, wanted: str | None = None) -> None:
    """The group's subcommands on its parser; only ``wanted`` (all when None) gets its options, so a command
    imports the settings of the one subcommand it runs."""
    sub = parser.add_subparsers(dest="what", required=True)
    for name, (text, build) in _SUBCOMMANDS.items():
        p = sub.add_parser(name, help=text)
        if wanted in (None, name):
            build(p)


def _add_plugins(bp: argparse.ArgumentParser) -> None:
    from ..benchmarks.plugins import PluginBenchSettings

    for name in ("resolution", "spp", "repetitions", "rounds"):
        opt(bp, PluginBenchSettings, name)
    bp.set_defaults(func=_cmd_bench_plugins)
    bp.add_argument("--json", required=True, help="output JSON path (charts and work folders go beside it)")


def _add_morph(bm: argparse.ArgumentParser) -> None:
    from inverse.morph import PRIOR_TIES, TRUTH_NORMALS

    from ..benchmarks.morph import MorphBenchSettings

    opt(bm, MorphBenchSettings, "parts", choices=["cases", "suite", "framing", "floor", "iteration"],
         help="cases: village/armadillo (speed, sweep, stability); suite: every suite mesh at the same defaults; "
              "framing: views and photo resolution swept on the first suite mesh; floor: each suite mesh morphed "
              "from its own ground truth (how far the method drifts from the answer); iteration: seconds per "
              "iteration of today's defaults against the recipe issue 17 was filed against, same mesh, in turns")
    opt(bm, MorphBenchSettings, "floor_iterations", help="iterations of the truth-start runs (--parts floor)")
    opt(bm, MorphBenchSettings, "truth_normals", choices=list(TRUTH_NORMALS),
         help="shading of the suite's and floor's photographed truths (face: flat, as the Chamfer measures them; "
              "their folders get _face)")
    opt(bm, MorphBenchSettings, "prior_ties", choices=list(PRIOR_TIES),
         help="the suite's tied prior choices: keep (the run with the prior continues unless beaten by the margin) "
              "or drop (the run without continues unless beaten by the margin)")
    opt(bm, MorphBenchSettings, "adam_quantile", type=float,
         help="the suite's runs: MorphSettings.adam_quantile (use a fresh --json folder: trials of another value "
              "are refused by name)")
    opt(bm, MorphBenchSettings, "lr", type=float, help="the suite's runs' position learning rate (MorphSettings.lr)")
    opt(bm, MorphBenchSettings, "step_select_quantile", type=float,
         help="the suite's runs ask the validation photos about this quantile step (MorphSettings.step_select_quantile; "
              "1: no such choice)")
    opt(bm, MorphBenchSettings, "saturation", type=float,
         help="the suite's runs leave pixels brighter than this × the photos' 99th percentile out of the loss "
              "(MorphSettings.saturation; 0: every pixel counts)")
    opt(bm, MorphBenchSettings, "mask_weight", type=float,
         help="the suite's runs add a silhouette L1 against the photos' masks at this weight "
              "(MorphSettings.mask_weight; 0: photos only)")
    opt(bm, MorphBenchSettings, "boundary_spp", type=int, help="the suite's runs' silhouette samples per pixel "
         "(MorphSettings.boundary_spp; the image takes 4)")
    opt(bm, MorphBenchSettings, "mask_every", help="the suite's runs render the masks every this many steps, at "
         "this × the weight (MorphSettings.mask_every)")
    opt(bm, MorphBenchSettings, "mask_downsample", help="the suite's runs render the masks at the photos' resolution "
         "// this (MorphSettings.mask_downsample)")
    opt(bm, MorphBenchSettings, "seed", help="another draw of every benchmark (photos' noise, views) and of every "
                                               "morph's render seeds (work folder: OUT/morph_work_seed<k>)")
    opt(bm, MorphBenchSettings, "cost_mesh", help="the mesh of --parts iteration")
    opt(bm, MorphBenchSettings, "cost_iterations", help="steps per timed block (--parts iteration)")
    opt(bm, MorphBenchSettings, "cost_rounds", help="timed blocks per recipe, in turns (--parts iteration)")
    opt(bm, MorphBenchSettings, "cases")
    opt(bm, MorphBenchSettings, "suite", help="suite meshes (village and armadillo may be added; paul, face000 "
                                               "and bracket are meshes the defaults never saw)")
    opt(bm, MorphBenchSettings, "iterations", help="morph iterations of the main and suite runs")
    opt(bm, MorphBenchSettings, "keep_work", help="keep OUT/morph_work after the bench: a rerun re-reads the "
                                                   "finished runs instead of recomputing them (default: removed)")
    pool_options(bm)
    bm.set_defaults(func=_cmd_bench_morph)
    bm.add_argument("--json", required=True, help="output JSON path (charts and work folders go beside it)")


def _add_morph_seeds(bms: argparse.ArgumentParser) -> None:

    bms.add_argument("results", nargs="+", help="bench morph JSON files with a suite, one per seed (a seed's suite "
                                                "run in parts: its files, each with other meshes)")
    bms.add_argument("--against", nargs="+", metavar="RESULT",
                     help="the same draws under other settings (e.g. before a change): paired by mesh and seed, "
                          "the change per draw, its mean and standard error, wins and losses (sign test), targets "
                          "gained and lost, and a chart OUT_against.png")
    bms.set_defaults(func=_cmd_bench_morph_seeds)
    bms.add_argument("--json", required=True, help="output JSON path (charts and work folders go beside it)")


def _add_morph_light_draws(bld: argparse.ArgumentParser) -> None:

    bld.add_argument("results", nargs="+", help="bench morph JSON files with a suite, their work folders kept")
    bld.add_argument("--draws", type=int, default=4, help="draws of the estimate per run, the choice's own first "
                                                         "(default: 4)")
    bld.set_defaults(func=_cmd_bench_morph_light_draws)
    bld.add_argument("--json", required=True, help="output JSON path (charts and work folders go beside it)")


def _add_btf(bb: argparse.ArgumentParser) -> None:

    pool_options(bb)
    bb.set_defaults(func=_cmd_bench_btf)
    bb.add_argument("--json", required=True, help="output JSON path (charts and work folders go beside it)")


def _add_face(bf: argparse.ArgumentParser) -> None:
    from ..benchmarks.face import FaceBenchSettings

    opt(bf, FaceBenchSettings, "scan", help="josie, paul, or an OBJ path")
    bf.set_defaults(func=_cmd_bench_face)
    bf.add_argument("--json", required=True, help="output JSON path (charts and work folders go beside it)")


def _add_gan(bg: argparse.ArgumentParser) -> None:
    from ..benchmarks.gan import GanBenchSettings

    bg.add_argument("--seconds-per-model", type=float, default=None,
                    help=f"training budget per GAN (default: {default_of(GanBenchSettings, 'seconds_per_model')} s; "
                         "the joint, CycleGAN and fine-tune budgets keep their proportions)")
    bg.set_defaults(func=_cmd_bench_gan)
    bg.add_argument("--json", required=True, help="output JSON path (charts and work folders go beside it)")


def _add_diffrender(bd: argparse.ArgumentParser) -> None:
    from ..benchmarks.diffrender import DiffRenderBenchSettings

    opt(bd, DiffRenderBenchSettings, "train_seconds", type=float, help="the main model's training budget")
    opt(bd, DiffRenderBenchSettings, "ablation_seconds", type=float, help="training budget of each ablation run")
    opt(bd, DiffRenderBenchSettings, "decomp_seconds", type=float, help="decomposition network's training budget")
    opt(bd, DiffRenderBenchSettings, "decomp_scenes", help="procedural scenes for the decomposition network")
    opt(bd, DiffRenderBenchSettings, "sweep_steps", nargs="+", type=int, help="DDIM steps of the sweep")
    opt(bd, DiffRenderBenchSettings, "seeds", help="sampling seeds of the main model's held-out renders")
    opt(bd, DiffRenderBenchSettings, "guidance")
    opt(bd, DiffRenderBenchSettings, "mean_draws", type=int,
         help="the sweep's means of one-step samples per view it tries (1: none)")
    opt(bd, DiffRenderBenchSettings, "sweep_guidance", type=float, help="guidance weights tried with those means")
    opt(bd, DiffRenderBenchSettings, "tolerance_rel", type=float,
         help="the choice: cheapest within this fraction of the sweep's best ꟻLIP")
    opt(bd, DiffRenderBenchSettings, "input_spp", help="samples per pixel of every method's input renders")
    opt(bd, DiffRenderBenchSettings, "photo_spp", help="samples per pixel of the benchmarks' photos (the targets)")
    opt(bd, DiffRenderBenchSettings, "reference_spp", help="samples per pixel of the noise-free references")
    opt(bd, DiffRenderBenchSettings, "validation", nargs="*",
         help="meshes never trained on that choose the main model's size at the main budget (none: the sweep's)")
    opt(bd, DiffRenderBenchSettings, "gans", "--no-gans", help="skip training the GAN baselines")
    opt(bd, DiffRenderBenchSettings, "gan_seconds", type=float, help="pix2pix / Morph-GAN budget each")
    opt(bd, DiffRenderBenchSettings, "cyclegan_seconds", type=float)
    opt(bd, DiffRenderBenchSettings, "workers",
         help="trainings and renders run this many at a time, one thread each (0: one after another, all threads)")
    opt(bd, DiffRenderBenchSettings, "seed")
    bd.set_defaults(func=_cmd_bench_diffrender)
    bd.add_argument("--json", required=True, help="output JSON path (charts and work folders go beside it)")


def _add_matdiff(bmd: argparse.ArgumentParser) -> None:
    from ..benchmarks.matdiff import MatDiffBenchSettings

    for name in ("data", "count", "train_seconds", "ablation_seconds", "samples", "steps", "guidance", "seed"):
        opt(bmd, MatDiffBenchSettings, name)
    opt(bmd, MatDiffBenchSettings, "main_run", help="finished `btf train-diffusion` run (e.g. trained with --device "
         "cuda) to evaluate instead of training the main model here; default: train here")
    opt(bmd, MatDiffBenchSettings, "ablations", "--no-ablations", help="skip the ablation runs")
    bmd.set_defaults(func=_cmd_bench_matdiff)
    bmd.add_argument("--json", required=True, help="output JSON path (charts and work folders go beside it)")


def _add_face_learned(bfl: argparse.ArgumentParser) -> None:
    from ..benchmarks.face_learned import FaceLearnedBenchSettings

    for name in ("train_instances", "eval_instances", "completion_seconds", "decomp_seconds", "superres_seconds",
                 "relit_instances", "cross_uv_res", "workers", "seed"):
        opt(bfl, FaceLearnedBenchSettings, name)
    opt(bfl, FaceLearnedBenchSettings, "layout", choices=["template", "scan"], help="UV layout of the learned stages")
    opt(bfl, FaceLearnedBenchSettings, "ablation_seeds", type=int,
         help="retrain every decomposition variant with these seeds too: the ablation's spread over training seeds")
    opt(bfl, FaceLearnedBenchSettings, "cross_model", "--no-cross-model", help="skip the cross-model fit")
    opt(bfl, FaceLearnedBenchSettings, "astronaut", "--no-astronaut", help="skip the astronaut photograph")
    bfl.set_defaults(func=_cmd_bench_face_learned)
    bfl.add_argument("--json", required=True, help="output JSON path (charts and work folders go beside it)")


def _add_scale(bs: argparse.ArgumentParser) -> None:
    from ..benchmarks.scale import ScaleBenchSettings

    for name in ("items", "resolution", "spp"):
        opt(bs, ScaleBenchSettings, name)
    opt(bs, ScaleBenchSettings, "ray", "--no-ray", help="leave out the Ray configuration")
    opt(bs, ScaleBenchSettings, "material_item", "--no-material", help="leave out timing one BTF material")
    bs.set_defaults(func=_cmd_bench_scale)
    bs.add_argument("--json", required=True, help="output JSON path (charts and work folders go beside it)")


def _add_startup(bst: argparse.ArgumentParser) -> None:
    from ..benchmarks.startup import StartupBenchSettings

    opt(bst, StartupBenchSettings, "repetitions")
    opt(bst, StartupBenchSettings, "target_s", "--target", help="seconds a command must answer within")
    bst.set_defaults(func=_cmd_bench_startup)
    bst.add_argument("--json", required=True, help="output JSON path (charts and work folders go beside it)")


_SUBCOMMANDS = {
    "plugins": ("ggx_uv vs builtin principled on the same scene", _add_plugins),
    "morph": ("geometry morphing: accuracy vs time, speed vs the tutorial recipe, stability, "
                                       "the generalisation suite, the benchmark's framing", _add_morph),
    "morph-seeds": ("the morph suite over several draws: `bench morph --parts suite "
                                              "--seed K` results, one per seed, summed up per mesh (mean, worst, "
                                              "at how many seeds every target holds) with a chart", _add_morph_seeds),
    "morph-light-draws": ("every light choice of `bench morph --parts suite --keep-work` "
                                                    "results scored again under other draws of the light estimate: "
                                                    "how much of each choice the estimate's own noise decides", _add_morph_light_draws),
    "btf": ("neural BTF: universal vs NeuMIP, width × texture sweep, render time", _add_btf),
    "face": ("face fitting: accuracy vs time over UV resolution, stability", _add_face),
    "gan": ("GAN refinement stages on held-out views", _add_gan),
    "diffrender": ("diffusion renderer vs PBR recomposition and the GANs on held-out views; "
                         "decomposition network, ablations, steps × size sweep, an unseen mesh", _add_diffrender),
    "matdiff": ("material diffusion: keyword/exemplar conditioning, KID vs baselines, "
                         "memorisation, seams, speed, ablations, dataset sweep (builds/continues its dataset first)", _add_matdiff),
    "face-learned": ("learned face stages vs the optimisation baseline on a held-out scan: "
                          "completion, decomposition variants, super-resolution, cross-model fit, end to end", _add_face_learned),
    "scale": ("a batch of renders serially, on a process pool and on Ray (identical?)", _add_scale),
    "startup": ("`photoreal … --help` and argument errors: median wall seconds, each in a "
                                          "fresh interpreter, beside a bare Python", _add_startup),
}
