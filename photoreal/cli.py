"""`photoreal` command line: a thin layer over the library functions.

Every option's default is read from the settings dataclass it fills (:func:`_opt`), so the two
never disagree; every option of a subcommand is used by it. Errors are one line naming the file or
the flag: exit 2 for what the user gave (a flag value, a path, an input file), 1 for work that failed
(PHOTOREAL_DEBUG=1 shows the traceback).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
from pathlib import Path
from typing import Any


# -- options from settings dataclasses ------------------------------------------------------------------------------


def _default(cls: type, name: str) -> Any:
    f = {f.name: f for f in dataclasses.fields(cls)}[name]
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    raise KeyError(f"{cls.__name__}.{name} has no default")


def _arg(func, name: str) -> Any:
    """The default of a library function's parameter (for options that fill a function argument)."""
    import inspect

    return inspect.signature(func).parameters[name].default


def _opt(p: argparse.ArgumentParser, cls: type, name: str, *flags: str, help: str = "", **kw) -> None:
    """``--flag`` filling ``cls.name``; its default (shown in --help) is the dataclass's."""
    default = _default(cls, name)
    if isinstance(default, bool) and "action" not in kw:
        kw["action"] = "store_false" if default else "store_true"
    elif "type" not in kw and "action" not in kw:
        kw["type"] = type(default) if isinstance(default, (int, float, str)) else str
    if isinstance(default, tuple) and "nargs" not in kw:
        kw["nargs"] = "+"
    shown = " ".join(map(str, default)) if isinstance(default, tuple) else default
    if isinstance(default, bool) or "default" in help:
        text = help
    else:
        text = f"{help} (default: {shown})" if help else f"default: {shown}"
    p.add_argument(*(flags or (f"--{name.replace('_', '-')}",)), dest=name, default=default, help=text, **kw)


def _settings(cls: type, a: argparse.Namespace, **extra):
    """``cls`` from the parsed options that name its fields (plus ``extra``)."""
    names = {f.name for f in dataclasses.fields(cls)}
    kw = {k: v for k, v in vars(a).items() if k in names}
    for k, v in list(kw.items()):
        if isinstance(_default(cls, k), tuple) and isinstance(v, list):
            kw[k] = tuple(v)
    kw.update(extra)
    return cls(**kw)


def _print(d: dict) -> None:
    print(json.dumps(d, indent=2, default=str))


# -- batches of items (foundation.pool) -----------------------------------------------------------------------------


def _pool_opts(p: argparse.ArgumentParser) -> None:
    from foundation.pool import default_workers

    p.add_argument("--workers", type=int, default=None,
                   help=f"worker processes for the items (default: the cores here, {default_workers()}; 0: one after "
                        "another in this process)")
    p.add_argument("--ray", default=None, metavar="ADDRESS",
                   help="run the items as Ray tasks: 'local' starts Ray on this machine, 'auto' or HOST:PORT joins "
                        "a running cluster (README: beyond one machine)")


def _pool(a):
    from foundation.pool import PoolSettings, default_workers

    cores = default_workers()
    workers = a.workers if a.workers is not None else cores
    # One Dr.Jit thread per worker when the workers fill the cores: results are then bit-identical to a serial
    # run with one thread, wherever an item ran; fewer workers get the cores' share each.
    threads = 1 if a.ray else (max(1, cores // workers) if workers >= 1 else 0)
    return PoolSettings(workers=max(workers, 1) if a.ray else workers, ray=a.ray, threads=threads)


def _run_batch(items, a, desc: str) -> int:
    from foundation.pool import ray_shutdown, run_items

    try:
        report = run_items(items, _pool(a), desc=desc)
    finally:
        ray_shutdown()
    print(json.dumps({"items": len(report.results), "done": len(report.ran), "skipped": len(report.skipped),
                      "failed": [{"item": r.key, "error": r.error} for r in report.failed],
                      "seconds": report.seconds}, indent=2))
    for r in report.failed:
        print(f"photoreal: error: {r.key}: {r.error}", file=sys.stderr)
    return 1 if report.failed else 0


def _out_dir(path: str, flag: str = "--out-dir") -> Path:
    """A folder for many outputs: absent or a folder (items already in it are skipped, so a batch resumes)."""
    from foundation.files import check_output_file

    p = Path(path)
    if p.exists() and not p.is_dir():
        raise _usage(f"{flag} {p}: is a file, expected a folder")
    check_output_file(p / ".probe", flag)
    return p


# -- render ---------------------------------------------------------------------------------------------------------


def _cmd_render(a: argparse.Namespace) -> int:
    from foundation.pool import Item
    from foundation.scene import RenderSettings, prepare_scene_xml, render_file, sensor_count

    settings = RenderSettings(spp=a.spp, resolution=tuple(a.resolution) if a.resolution else None, aovs=a.aovs,
                              seed=a.seed)
    many = len(a.scene) > 1 or a.all_sensors
    if a.output and many:
        raise _usage("-o names one output; give --out-dir for several scenes or --all-sensors")
    if not a.output and not a.out_dir:
        raise _usage("give -o FILE.exr (one scene) or --out-dir DIR (several)")
    if a.output:
        print(json.dumps(render_file(a.scene[0], a.output, settings)))
        return 0
    out = _out_dir(a.out_dir)
    stems = [Path(sc).stem for sc in a.scene]
    if len(set(stems)) != len(stems):
        raise _usage("two scenes share a file name; their renders would overwrite each other in --out-dir")
    items = []
    for sc in a.scene:
        prepare_scene_xml(Path(sc), settings)  # a missing or malformed scene is named before any work
        n = sensor_count(sc) if a.all_sensors else 1
        for k in range(n):
            key = Path(sc).stem + (f"_s{k}" if a.all_sensors else "")
            exr = out / f"{key}.exr"
            items.append(Item(key, "foundation.scene:render_item",
                              (str(sc), str(exr), dataclasses.replace(settings, sensor=k)), output=str(exr)))
    return _run_batch(items, a, "render")


# -- bench ----------------------------------------------------------------------------------------------------------


def _bench_out(a) -> Path:
    from foundation.files import check_output_file

    return check_output_file(a.json, "--json")


def _cmd_bench_plugins(a) -> int:
    from foundation.files import write_json

    from .benchmarks.plugins import PluginBenchSettings, bench_plugins

    out = _bench_out(a)
    result = bench_plugins(_settings(PluginBenchSettings, a))
    write_json(out, result)
    _print({k: result[k] for k in ("ggx_uv_ms", "principled_ms", "ggx_uv_vs_principled", "compile_s")})
    return 0


def _cmd_bench_morph(a) -> int:
    from foundation.files import write_json

    from .benchmarks.morph import MorphBenchSettings, bench_morph

    from foundation.pool import ray_shutdown

    out = _bench_out(a)
    try:
        result = bench_morph(_settings(MorphBenchSettings, a), out_dir=out.parent, pool=_pool(a))
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
    _print(shown)
    return 0


def _cmd_bench_morph_seeds(a) -> int:
    from foundation.files import write_json

    from .benchmarks.morph import compare_chart, seeds_chart, seeds_compare, seeds_summary

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
    _print(shown)
    return 0


def _cmd_bench_morph_light_draws(a) -> int:
    from foundation.files import write_json

    from .benchmarks.morph import light_draws, light_draws_chart

    out = _bench_out(a)
    result = light_draws(a.results, a.draws)
    result["chart"] = str(light_draws_chart(result, out.with_name(out.stem + ".png")))
    write_json(out, result)
    _print({"light_choices": len(result["rows"]), "draws": result["draws"],
            "draw0_vs_stored_max": result["draw0_vs_stored_max"], "advantage_sd": result["advantage_sd"],
            "overturned_by_a_draw": result["overturned_by_a_draw"]})
    return 0


def _cmd_bench_btf(a) -> int:
    from foundation.files import write_json

    from .benchmarks.btf import BTFBenchSettings, bench_btf

    from foundation.pool import ray_shutdown

    out = _bench_out(a)
    try:
        result = bench_btf(_settings(BTFBenchSettings, a), out_dir=out.parent, pool=_pool(a))
    finally:
        ray_shutdown()
    write_json(out, result)
    _print({k: result[k] for k in ("psnr_universal_mean", "psnr_per_material_mean", "neural_btf_ms", "principled_ms",
                                   "neural_btf_vs_principled", "mlp_evals_per_s_drjit", "mlp_evals_per_s_torch",
                                   "chosen")})
    return 0


def _cmd_bench_face(a) -> int:
    from foundation.files import write_json

    from .benchmarks.face import FaceBenchSettings, bench_face

    out = _bench_out(a)
    s = _settings(FaceBenchSettings, a)
    s.scan_path()
    result = bench_face(s, out_dir=out.parent)
    write_json(out, result)
    _print({k: result[k] for k in ("albedo_psnr", "normal_err_deg", "roughness_mae", "specular_mae", "relit_psnr",
                                   "relit_flip", "fit_seconds_256", "chosen_uv_res")})
    return 0


def _cmd_bench_scale(a) -> int:
    from foundation.files import write_json

    from .benchmarks.scale import ScaleBenchSettings, bench_scale

    out = _bench_out(a)
    result = bench_scale(_settings(ScaleBenchSettings, a), out_dir=out.parent)
    write_json(out, result)
    _print({k: result.get(k) for k in ("items", "serial_s", "pool_s", "ray_s", "speedup_pool_2",
                                       "ray_overhead_per_item_s", "identical")})
    return 0


def _cmd_bench_gan(a) -> int:
    from foundation.files import write_json

    from .benchmarks.gan import GanBenchSettings, bench_gan

    out = _bench_out(a)
    s = GanBenchSettings()
    if a.seconds_per_model is not None:
        t = a.seconds_per_model  # the other budgets keep their default proportions
        s = dataclasses.replace(s, seconds_per_model=t, joint_seconds=1.5 * t, cyclegan_seconds=3 * t,
                                finetune_seconds=0.75 * t)
    result = bench_gan(s, out_dir=out.parent)
    write_json(out, result)
    _print({k: result[k] for k in ("heldout", "train_seconds", "infer_ms_per_image", "ordering")})
    return 0


def _cmd_bench_diffrender(a) -> int:
    from foundation.files import write_json

    from .benchmarks.diffrender import DiffRenderBenchSettings, bench_diffrender, sweep_chart, views_figure

    out = _bench_out(a)
    result = bench_diffrender(_settings(DiffRenderBenchSettings, a), out_dir=out.parent)
    result["chart"] = str(sweep_chart(result, out.with_name(out.stem + "_sweep.png")))
    result["views_figure"] = str(views_figure(result, out.parent, out.with_name(out.stem + "_views.png")))
    write_json(out, result)
    _print({k: result[k] for k in ("heldout", "unseen", "kid_mnv2", "fid_mnv2", "kid_mnv2_clean", "decomposition_psnr",
                                   "chosen", "sample_seconds_128", "train_flops_fraction", "verdict") if k in result})
    return 0


def _cmd_bench_matdiff(a) -> int:
    from foundation.files import write_json

    from .benchmarks.matdiff import MatDiffBenchSettings, bench_matdiff, charts, samples_figure

    out = _bench_out(a)
    result = bench_matdiff(_settings(MatDiffBenchSettings, a), out_dir=out.parent)
    result["charts"] = charts(result, out.with_name(out.stem + "_speed.png"))
    result["samples_figure"] = samples_figure(out.parent / "matdiff_work", out.with_name(out.stem + "_samples.png"))
    write_json(out, result)
    _print({k: result[k] for k in ("classifier_accuracy_real", "keyword_accuracy", "kid_classifier", "kid_mnv2",
                                   "nn_distance_ratio", "diversity", "exemplar_flip", "seam_error", "sample_seconds",
                                   "chosen_steps", "chosen_guidance", "keyword_accuracy_chosen", "verdict")})
    return 0


def _cmd_bench_face_learned(a) -> int:
    from foundation.files import write_json

    from .benchmarks.face_learned import FaceLearnedBenchSettings, bench_face_learned

    out = _bench_out(a)
    result = bench_face_learned(_settings(FaceLearnedBenchSettings, a), out_dir=out.parent)
    write_json(out, result)
    _print({k: result.get(k) for k in ("completion", "decomposition", "superres", "end_to_end", "verdict")})
    return 0


# -- face -----------------------------------------------------------------------------------------------------------


def _cmd_face_make_benchmark(a) -> int:
    from foundation.files import check_output_dir
    from inverse.face import FaceBenchmarkSettings, make_benchmark

    check_output_dir(a.out, "benchmark.json", "--out", replace=True)
    out = make_benchmark(a.scan, a.out, _settings(FaceBenchmarkSettings, a))
    print(f"benchmark: {out}")
    return 0


def _benchmarks(paths: list[str], marker: str) -> list[Path]:
    """The benchmark folders named, a folder of benchmarks standing for the benchmarks inside it."""
    out = []
    for p in map(Path, paths):
        if p.is_dir() and not (p / marker).is_file():
            inside = sorted(q.parent for q in p.glob(f"*/{marker}"))
            out += inside or [p]  # nothing inside: keep it, so that loading names it
        else:
            out.append(p)
    return out


def _cmd_face_fit(a) -> int:
    from foundation.pool import Item
    from inverse.face import FaceFitSettings, RenderRefineSettings, fit_benchmark_dir

    fs = _settings(FaceFitSettings, a)
    refine = RenderRefineSettings(iterations=a.refine_renders, seed=a.seed) if a.refine_renders else None
    benches = _benchmarks(a.benchmark, "benchmark.json")
    if len(benches) > 1 or a.out_dir:
        if a.json or a.maps:
            raise _usage("--json and --maps name one benchmark's outputs; several go to --out-dir")
        if not a.out_dir:
            raise _usage("several benchmarks: give --out-dir DIR (DIR/NAME/fit.json and DIR/NAME/maps each)")
        out = _out_dir(a.out_dir)
        names = [b.name for b in benches]
        if len(set(names)) != len(names):
            raise _usage("two benchmarks share a folder name; their fits would overwrite each other in --out-dir")
        items = [Item(b.name, "inverse.face:fit_benchmark_item",
                      (str(b), str(out / b.name / "fit.json"), str(out / b.name / "maps"), fs, refine),
                      output=str(out / b.name / "fit.json")) for b in benches]
        return _run_batch(items, a, "face fits")
    if not a.json:
        raise _usage("give --json FILE (or --out-dir for several benchmarks)")
    r = fit_benchmark_dir(benches[0], a.json, a.maps, fs, refine=refine)
    m = r.metrics
    _print({"albedo_psnr": m.albedo_psnr, "normal_err_deg": m.normal_err_deg, "relit_psnr": m.relit_psnr,
            "seconds": m.seconds})
    return 0


def _cmd_face_from_photo(a) -> int:
    from foundation.files import check_output_dir
    from foundation.imageio import read_photo
    from inverse.face import PhotoFitSettings, load_landmarks, photo_to_face

    s = _settings(PhotoFitSettings, a)
    check_output_dir(a.out, "photo_face.json", "--out", replace=True)
    maps_fn = None
    if a.learned:
        from generative.diffusion import load_face_models, photo_maps_fn

        maps_fn = photo_maps_fn(load_face_models(a.learned, a.variant))  # a bad run is named before any work
    image = read_photo(a.image)
    lm = load_landmarks(a.landmarks) if a.landmarks else None
    r = photo_to_face(image, a.out, s, landmarks=lm, maps_fn=maps_fn)
    _print({"stages": r.stages, "landmark_reprojection_px": r.landmark_reprojection_px,
            "rerender_psnr_visible_face": r.rerender_psnr_visible_face,
            "visible_uv_fraction": r.visible_uv_fraction, "seconds": r.seconds})
    return 0


def _cmd_face_train_models(a) -> int:
    from foundation.pool import ray_shutdown
    from generative.diffusion import (CompletionSettings, FaceDataSettings, FaceDecompSettings, FaceModelsSettings,
                                      SuperResSettings, train_face_models)

    s = FaceModelsSettings(
        data=_settings(FaceDataSettings, a),
        completion=CompletionSettings(max_seconds=a.completion_seconds, seed=a.seed),
        decomposition=FaceDecompSettings(max_seconds=a.decomp_seconds, seed=a.seed),
        superres=SuperResSettings(max_seconds=a.superres_seconds, seed=a.seed),
        variants=tuple(a.variants))
    try:
        summary = train_face_models(a.out, s, _pool(a))
    finally:
        ray_shutdown()
    _print({k: {"parameters": v["parameters"], "steps": v["training"]["steps"],
                "train_seconds": v["training"]["train_seconds"], "loss_last": v["training"]["loss_last"]}
            for k, v in summary.items()})
    return 0


# -- morph ----------------------------------------------------------------------------------------------------------


def _cmd_morph_make_benchmark(a) -> int:
    from foundation.files import check_output_dir
    from inverse.morph import MorphBenchmarkSettings, make_morph_benchmark

    s = _settings(MorphBenchmarkSettings, a)
    check_output_dir(a.out, "morph_benchmark.json", "--out", replace=True)
    print(f"benchmark: {make_morph_benchmark(a.mesh, a.out, s)}")
    return 0


def _cmd_morph_run(a) -> int:
    from foundation.files import check_output_file, write_json
    from foundation.pool import Item
    from foundation.records import to_json
    from inverse.morph import MorphSettings, load_morph_benchmark, run_gcn_morph, run_morph

    s = _settings(MorphSettings, a, parameterisation="plain" if a.plain_adam else "large_steps",
                  repair_flips=not a.no_repair, min_vertices=a.min_vertices or None)
    benches = _benchmarks(a.benchmark, "morph_benchmark.json")
    if len(benches) > 1:
        if a.out or a.json:
            raise _usage("--out and --json name one run; several benchmarks go to --out-dir (or BENCHMARK/morph)")
        for b in benches:
            load_morph_benchmark(b)  # a missing or damaged benchmark is named before any work
        base = _out_dir(a.out_dir) if a.out_dir else None
        names = [b.name for b in benches]
        if base is not None and len(set(names)) != len(names):
            raise _usage("two benchmarks share a folder name; their runs would overwrite each other in --out-dir")
        items = []
        for b in benches:
            out = base / b.name if base is not None else b / "morph"
            key = b.name if base is not None else str(b)
            items.append(Item(key, "inverse.morph:run_item", (str(b), str(out), s, a.gcn), {"json_path": None},
                              output=str(out / "metrics.json")))
        return _run_batch(items, a, "morph runs")
    if a.out_dir:
        raise _usage("--out-dir is for several benchmarks; one run goes to --out (default BENCHMARK/morph)")
    if a.json:
        check_output_file(a.json, "--json")
    bench = load_morph_benchmark(benches[0])
    out = Path(a.out) if a.out else benches[0] / "morph"
    if out.exists() and not out.is_dir():
        raise _usage(f"--out {out}: is a file, expected a folder")
    m = run_gcn_morph(bench, out, s) if a.gcn else run_morph(bench, out, s)
    if a.json:
        write_json(a.json, to_json(m))
    _print({"chamfer_input": m.chamfer_input, "chamfer_morphed": m.chamfer_morphed,
            "psnr_heldout_input": m.psnr_heldout_input, "psnr_heldout_morphed": m.psnr_heldout_morphed,
            "spikes": m.spikes, "seconds": m.seconds})
    return 0


def _cmd_morph_saturation(a) -> int:
    from foundation.files import check_output_file, write_json
    from inverse.morph import load_morph_benchmark, saturated_silhouette

    if a.json:
        check_output_file(a.json, "--json")
    if not a.factor > 0:
        raise _usage(f"--factor must be > 0, got {a.factor}")
    benches = [load_morph_benchmark(b) for b in a.benchmarks]  # every folder checked before any render
    out = {str(b.path): saturated_silhouette(b, a.factor) for b in benches}
    if a.json:
        write_json(a.json, out)
    _print(out)
    return 0


def _cmd_morph_errors(a) -> int:
    from foundation.files import check_output_file, write_json
    from foundation.records import to_json
    from inverse.morph import benchmark_errors, load_morph_benchmark

    bench = load_morph_benchmark(a.benchmark)
    results: dict[str, Path] = {}
    for item in a.results:
        p = Path(item)
        ply = p / "morphed.ply" if p.is_dir() else p
        if not ply.is_file():
            raise _usage(f"{item}: no such mesh file" + (" (a folder without morphed.ply)" if p.is_dir() else ""))
        name = (p.name if p.is_dir() else p.parent.name if p.stem == "morphed" else p.stem) or "result"
        base, k = name, 2
        while name in results or name == "input":
            name, k = f"{base}_{k}", k + 1
        results[name] = ply
    if a.json:
        check_output_file(a.json, "--json")
    if a.band is not None and not a.band > 0:
        raise _usage(f"--band must be > 0, got {a.band}")
    if Path(a.out).exists() and not Path(a.out).is_dir():
        raise _usage(f"--out {a.out}: is a file, expected a folder")
    r = benchmark_errors(bench, results, Path(a.out), band=a.band)
    if a.json:
        write_json(a.json, to_json(r))
    for e in r.meshes:
        _print({"mesh": e.name, "chamfer": e.chamfer, "to_truth": e.to_truth, "from_truth": e.from_truth,
                "from_truth_border": e.from_truth_border, "from_truth_interior": e.from_truth_interior,
                "input_error_left": e.input_error_left, "new_error_rms": e.new_error_rms,
                "input_error_left_by_scale": None if e.input_error_left_by_scale is None else
                {b.band: None if b.slope is None else round(b.slope, 3) for b in e.input_error_left_by_scale},
                "facing_area": e.facing_area, "facing_area_by_views": e.facing_area_by_views,
                "unseen_area": e.unseen_area})
    print(f"maps: {a.out}/errors_*.ply, {a.out}/facing_*.ply; figures: {r.files['figure']}, {r.files['facing_figure']}")
    return 0


# -- btf ------------------------------------------------------------------------------------------------------------


def _checkpoint_path(a) -> Path:
    from foundation.files import check_output_file

    ck = Path(a.checkpoint) if a.checkpoint else Path(a.out).with_suffix(".ckpt.npz")
    return check_output_file(ck, "--checkpoint")


def _cmd_btf_render_data(a) -> int:
    from inverse.btf import FAMILIES, BTFRenderSettings, render_dataset

    from foundation.pool import ray_shutdown

    s = _settings(BTFRenderSettings, a)
    try:
        paths = render_dataset(a.out, families=tuple(a.families) if a.families else FAMILIES,
                               per_family=a.per_family, settings=s, base_seed=a.seed, pool=_pool(a))
    finally:
        ray_shutdown()
    print(json.dumps({"materials": len(paths), "out": str(a.out)}))
    return 0


def _cmd_btf_train_basis(a) -> int:
    from foundation.files import check_output_file
    from inverse.btf import OptimSettings, load_dataset, train_basis
    from mi_plugins.neural_basis import BasisConfig, save_basis

    cfg = _settings(BasisConfig, a)
    s = _settings(OptimSettings, a)
    check_output_file(a.out, "--out")
    ck = _checkpoint_path(a)
    mats = load_dataset(a.data)
    basis, hist = train_basis(mats, cfg, s, checkpoint=ck)
    save_basis(a.out, basis)
    print(json.dumps({"basis": str(a.out), "id": basis.meta["id"], "materials": len(mats),
                      "final_l1": hist[-1]["l1"], "seconds": hist[-1]["seconds"], "checkpoint": str(ck)}))
    return 0


def _cmd_btf_fit(a) -> int:
    from foundation import validate
    from foundation.files import check_output_file, write_json
    from foundation.pool import Item
    from inverse.btf import fit_file, fit_settings

    validate.in_range("heldout_fraction", a.heldout_fraction, 0.0, 1.0, lo_open=True, hi_open=True)
    fit_settings(a.iterations, batch=a.batch, seed=a.seed, tex_res=a.tex_res)  # flags checked before any work
    kw = dict(iterations=a.iterations, batch=a.batch, tex_res=a.tex_res, heldout_fraction=a.heldout_fraction,
              seed=a.seed)
    if len(a.btf) > 1 or a.out_dir:
        if a.out or a.json or a.checkpoint:
            raise _usage("--out, --json and --checkpoint name one material; several go to --out-dir")
        if not a.out_dir:
            raise _usage("several BTFs: give --out-dir DIR (DIR/NAME.npz each)")
        out = _out_dir(a.out_dir)
        names = [Path(b).stem for b in a.btf]
        if len(set(names)) != len(names):
            raise _usage("two BTFs share a file name; their materials would overwrite each other in --out-dir")
        for b in a.btf:
            if not Path(b).is_file():
                raise _usage(f"{b}: no such BTF file")
        if not Path(a.basis).is_file():
            raise _usage(f"--basis {a.basis}: no such file")
        items = [Item(n, "inverse.btf:fit_file", (str(b), str(a.basis), str(out / f"{n}.npz")), kw,
                      output=str(out / f"{n}.npz")) for n, b in zip(names, a.btf)]
        return _run_batch(items, a, "fit materials")
    if not a.out:
        raise _usage("give --out MATERIAL.npz (or --out-dir for several BTFs)")
    check_output_file(a.out, "--out")
    if a.json:
        check_output_file(a.json, "--json")
    ck = _checkpoint_path(a)
    m = fit_file(a.btf[0], a.basis, a.out, checkpoint=str(ck), progress=True, **kw)
    if a.json:
        write_json(a.json, m)
    print(json.dumps(m))
    return 0


def _cmd_btf_dataset(a) -> int:
    from foundation.pool import ray_shutdown
    from generative.diffusion import MaterialDataSettings, build_material_dataset, load_material_dataset

    s = _settings(MaterialDataSettings, a)
    if a.basis and not Path(a.basis).is_file():
        raise _usage(f"--basis {a.basis}: no such file")
    try:
        build_material_dataset(a.out, s, basis=a.basis, pool=_pool(a))
    finally:
        ray_shutdown()
    ds = load_material_dataset(a.out)
    print(json.dumps({"out": str(a.out), "materials": len(ds.names), "heldout": int(ds.heldout.sum()),
                      "fit_psnr_median": float(sorted(ds.psnr)[len(ds.psnr) // 2])}))
    return 0


def _cmd_btf_train_diffusion(a) -> int:
    from foundation.records import to_json
    from generative.diffusion import MatDiffSettings, load_material_dataset, train_matdiff

    s = _settings(MatDiffSettings, a)
    ds = load_material_dataset(a.data)
    r = train_matdiff(ds.subset(~ds.heldout), a.out, s, device=a.device)
    print(json.dumps({"run": str(a.out), "device": a.device, "materials": r.materials, "parameters": r.parameters,
                      "training": to_json(r.training)}, default=str))
    return 0


def _cmd_btf_generate(a) -> int:
    from generative.diffusion import generate_material

    if not a.keywords and not a.image and not a.unconditional and not a.from_prior:
        raise _usage("give --keywords WORDS, --image PHOTO (or both), --from-prior or --unconditional")
    if a.run is None:
        from foundation.assets import bundled_matdiff

        a.run = bundled_matdiff()
    print(json.dumps(generate_material(a.run, a.out, a.keywords, a.image, a.seed, a.size, a.steps, a.guidance,
                                       from_prior=a.from_prior)))
    return 0


# -- gan ------------------------------------------------------------------------------------------------------------


def _cmd_gan(a) -> int:
    from foundation.files import check_output_file, write_json
    from foundation.records import to_json
    from generative.gan import (GanTrainSettings, JointSettings, check_resolution, evaluate_model, load_paired_views,
                                load_trained, train_gan, train_joint)
    from inverse.morph import load_morph_benchmark

    if a.json:
        check_output_file(a.json, "--json")
    if a.gan_cmd == "train":
        gs = GanTrainSettings(model="morph_gan" if a.model == "joint" else a.model, steps=a.steps,
                              max_seconds=a.max_seconds, batch=a.batch, crop=a.crop, ngf=a.ngf, ndf=a.ngf, seed=a.seed,
                              residual=not a.paper_head, val_every=0 if a.init_from else 6,
                              init_from=None if a.model == "joint" else a.init_from)
        js = JointSettings(steps=a.steps, max_seconds=a.max_seconds, gan=gs, seed=a.seed, init_from=a.init_from,
                           init_mesh=None) if a.model == "joint" else None
        bench = load_morph_benchmark(a.benchmark)
        check_resolution(bench.meta.resolution, gs)  # before any rendering
        morph = Path(a.morph) if a.morph else Path(a.benchmark) / "morph"
        data = load_paired_views(bench, morph)
        if js is not None:
            # fine-tuning a finished Morph-GAN jointly starts from the morph run's mesh as well
            js = dataclasses.replace(js, init_mesh=str(morph / "morphed.ply") if a.init_from else None)
            r = train_joint(bench, data, a.out, js)
        else:
            r = train_gan(data, a.out, gs)
        if a.json:
            write_json(a.json, to_json(r))
        h = r.heldout
        _print({"mse": h.mse, "one_minus_ssim": h.one_minus_ssim, "flip": h.flip, "psnr": h.psnr,
                "train_seconds": r.training.train_seconds, "steps": r.training.steps,
                "infer_ms_per_image": h.infer_ms_per_image})
        return 0
    bench = load_morph_benchmark(a.benchmark)
    model, _ = load_trained(a.run)
    data = load_paired_views(bench, Path(a.morph) if a.morph else Path(a.benchmark) / "morph")
    m = to_json(evaluate_model(model, data))
    if a.json:
        write_json(a.json, m)
    _print(m)
    return 0


# -- diffrender -----------------------------------------------------------------------------------------------------


def _cmd_diffrender(a) -> int:
    from foundation.files import check_output_dir, check_output_file, write_json
    from foundation.records import to_json
    from generative.diffusion import (TRUTH, DiffRenderSettings, SampleSettings, load_intrinsic_views, render_benchmark,
                                      render_scene_file, train_diffrender, with_truth_layers)
    from inverse.morph import load_morph_benchmark

    if a.json:
        check_output_file(a.json, "--json")
    if a.dr_cmd == "train":
        morphs = a.morph or [str(Path(b) / "morph") for b in a.benchmarks]
        if len(morphs) != len(a.benchmarks):
            raise _usage(f"--morph: {len(morphs)} folders for {len(a.benchmarks)} benchmarks (one each, in order)")
        s = _settings(DiffRenderSettings, a)
        benches = [load_morph_benchmark(b) for b in a.benchmarks]  # all validated before any rendering
        cases = [load_intrinsic_views(b, m) for b, m in zip(benches, morphs)]
        if TRUTH in s.sources:  # the benchmarks' ground truth through the same integrator, at the same spp
            cases = [with_truth_layers(v, b, m) for v, b, m in zip(cases, benches, morphs)]
        r = train_diffrender(cases, a.out, s)
        m = to_json(r)
        if a.json:
            write_json(a.json, m)
        _print({"train_seconds": r.training.train_seconds, "steps": r.training.steps, "parameters": r.parameters,
                "loss_first": r.training.loss_first, "loss_last": r.training.loss_last, "skipped": r.training.skipped_steps})
        return 0
    ss = _settings(SampleSettings, a)
    check_output_dir(a.out, "diffrender.json", "--out")
    target = Path(a.target)
    if target.suffix.lower() == ".xml":
        r = render_scene_file(a.run, target, a.out, spp=a.spp, sample_s=ss)
    else:
        bench = load_morph_benchmark(target)
        r = render_benchmark(a.run, bench, a.morph or target / "morph", a.out, a.source, a.views, ss)
    m = to_json(r)
    write_json(Path(a.out) / "diffrender.json", m)  # also marks the folder as this command's output
    if a.json:
        write_json(a.json, m)
    _print({k: v for k, v in m.items() if k != "files"} | {"files": len(r.files), "out": str(a.out)})
    return 0


def _add_diffrender_parser(sub) -> None:
    from generative.diffusion import TRAIN_SOURCES, DiffRenderSettings, SampleSettings

    g = sub.add_parser("diffrender", help="intrinsic-conditioned diffusion renderer: G-buffers (A, I, S, N) → photo "
                                          "(seed 000)")
    gs = g.add_subparsers(dest="dr_cmd", required=True)
    t = gs.add_parser("train", help="train on morph benchmarks (morphed G-buffers → photos); resumes from OUT")
    t.add_argument("benchmarks", nargs="+", help="folders made by `photoreal morph make-benchmark` (with --spp 1024, "
                   "as the bench: the photos are the targets, and their Monte-Carlo noise would be learned as well)")
    t.add_argument("--morph", nargs="+", default=None, help="their morph run folders, in order (default BENCHMARK/morph)")
    t.add_argument("--out", required=True, help="training folder (checkpoint.npz, metrics.json)")
    _opt(t, DiffRenderSettings, "steps")
    _opt(t, DiffRenderSettings, "max_seconds", "--seconds", type=float, help="training wall-time budget (summed over resumes)")
    _opt(t, DiffRenderSettings, "batch")
    _opt(t, DiffRenderSettings, "crop")
    _opt(t, DiffRenderSettings, "lr")
    _opt(t, DiffRenderSettings, "widths", type=int, help="UNet channels per level")
    _opt(t, DiffRenderSettings, "attention_levels")
    _opt(t, DiffRenderSettings, "global_source", choices=["R", "AIS", "none"],
         help="global tokens from the recomposition R (seed 000), from A, I, S separately, or none")
    _opt(t, DiffRenderSettings, "p_uncond")
    _opt(t, DiffRenderSettings, "residual", "--direct",
         help="generate the photo itself (the seed) instead of its residual over R = A·I + S")
    _opt(t, DiffRenderSettings, "known_background", "--every-pixel",
         help="learn the residual on every pixel instead of holding it at 0 where the G-buffer sees no surface")
    _opt(t, DiffRenderSettings, "sources", choices=list(TRAIN_SOURCES),
         help="whose G-buffers are training inputs: the morphed mesh's, the coarse mesh's (worse on held-out and "
              "unseen meshes, measured), the benchmark's ground truth's (exact intrinsics, the seed's pairs)")
    _opt(t, DiffRenderSettings, "threads", help="torch threads (0: all cores)")
    _opt(t, DiffRenderSettings, "seed")
    t.add_argument("--json", default=None)
    r = gs.add_parser("render", help="diffusion renders of a benchmark's views or of a scene's sensors (EXR + PNG)")
    r.add_argument("target", help="a morph benchmark folder, or a Mitsuba scene .xml (every sensor is rendered)")
    r.add_argument("--run", required=True, help="training folder of `diffrender train`")
    r.add_argument("--out", required=True, help="output folder")
    r.add_argument("--morph", default=None, help="benchmark: morph run folder (default BENCHMARK/morph)")
    r.add_argument("--source", choices=["morphed", "coarse"], default="morphed", help="benchmark: whose G-buffers")
    r.add_argument("--views", choices=["test", "all"], default="test", help="benchmark: held-out views or all")
    r.add_argument("--spp", type=int, default=32, help="scene: samples per pixel of the G-buffers (default: 32, as "
                   "the bench's)")
    _opt(r, SampleSettings, "steps", "--ddim-steps", help="DDIM steps")
    _opt(r, SampleSettings, "guidance", type=float, help="classifier-free guidance weight on the global condition "
         "(default: 1 for a mean of draws, 1.5 for single samples: the bench's choices)")
    _opt(r, SampleSettings, "draws", type=int, help="samples averaged per view (at 1 step: the posterior mean; "
         "default: 8 at 1 step, the bench's choice, 1 for more steps)")
    _opt(r, SampleSettings, "seed")
    r.add_argument("--json", default=None)
    g.set_defaults(func=_cmd_diffrender)


# -- demo -----------------------------------------------------------------------------------------------------------


def _cmd_demo(a) -> int:
    from .demo import DemoSettings, run_demo

    s = _settings(DemoSettings, a)
    bench_dir = Path(a.bench_dir) if a.bench_dir else Path(a.out).parent / "bench"
    print(f"report: {run_demo(a.out, s, bench_dir=bench_dir)}")
    return 0


# -- the parser -----------------------------------------------------------------------------------------------------


def build_parser() -> argparse.ArgumentParser:
    from foundation.scene import RenderSettings
    from inverse.btf import BTFRenderSettings, OptimSettings, fit_settings, render_dataset, split_slices
    from inverse.face import FaceBenchmarkSettings, FaceFitSettings, PhotoFitSettings, RenderRefineSettings
    from inverse.morph import PLANARITY_WHERE, PRIOR_TIES, TRUTH_NORMALS, MorphBenchmarkSettings, MorphSettings
    from mi_plugins.neural_basis import BasisConfig

    from .benchmarks.face import FaceBenchSettings
    from .benchmarks.gan import GanBenchSettings
    from .benchmarks.morph import MorphBenchSettings
    from .benchmarks.plugins import PluginBenchSettings
    from .benchmarks.scale import ScaleBenchSettings
    from .demo import DemoSettings

    p = argparse.ArgumentParser(prog="photoreal", description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="command", required=True)

    r = sub.add_parser("render", help="render Mitsuba XML scenes (our plugins register themselves)")
    r.add_argument("scene", nargs="+", help="scene .xml file(s)")
    r.add_argument("-o", "--output", default=None, help="output .exr of one scene (a .png preview is written beside it)")
    r.add_argument("--out-dir", default=None,
                   help="folder for several renders: DIR/SCENE.exr (DIR/SCENE_s<k>.exr with --all-sensors); "
                        "renders already there are kept, so a killed batch resumes")
    r.add_argument("--all-sensors", action="store_true", help="render every sensor (camera, frame) of each scene")
    _pool_opts(r)
    _opt(r, RenderSettings, "spp", type=int, help="samples per pixel (default: the scene's)")
    r.add_argument("--resolution", type=int, nargs=2, metavar=("W", "H"), default=None,
                   help="film size (default: the scene's)")
    _opt(r, RenderSettings, "aovs", help="render with the 'intrinsic' integrator: albedo, irradiance, specular, "
                                         "normal, depth, uv, position layers")
    _opt(r, RenderSettings, "seed", help="random seed (0 … 2³¹−1)")
    r.set_defaults(func=_cmd_render)

    b = sub.add_parser("bench", help="benchmarks writing JSON (speed as ratios measured in the same run)")
    bsub = b.add_subparsers(dest="what", required=True)
    bp = bsub.add_parser("plugins", help="ggx_uv vs builtin principled on the same scene")
    for name in ("resolution", "spp", "repetitions", "rounds"):
        _opt(bp, PluginBenchSettings, name)
    bp.set_defaults(func=_cmd_bench_plugins)
    bm = bsub.add_parser("morph", help="geometry morphing: accuracy vs time, speed vs the tutorial recipe, stability, "
                                       "the generalisation suite, the benchmark's framing")
    _opt(bm, MorphBenchSettings, "parts", choices=["cases", "suite", "framing", "floor", "iteration"],
         help="cases: village/armadillo (speed, sweep, stability); suite: every suite mesh at the same defaults; "
              "framing: views and photo resolution swept on the first suite mesh; floor: each suite mesh morphed "
              "from its own ground truth (how far the method drifts from the answer); iteration: seconds per "
              "iteration of today's defaults against the recipe issue 17 was filed against, same mesh, in turns")
    _opt(bm, MorphBenchSettings, "floor_iterations", help="iterations of the truth-start runs (--parts floor)")
    _opt(bm, MorphBenchSettings, "truth_normals", choices=list(TRUTH_NORMALS),
         help="shading of the suite's and floor's photographed truths (face: flat, as the Chamfer measures them; "
              "their folders get _face)")
    _opt(bm, MorphBenchSettings, "prior_ties", choices=list(PRIOR_TIES),
         help="the suite's tied prior choices: keep (the run with the prior continues unless beaten by the margin) "
              "or drop (the run without continues unless beaten by the margin)")
    _opt(bm, MorphBenchSettings, "adam_quantile", type=float,
         help="the suite's runs: MorphSettings.adam_quantile (use a fresh --json folder: trials of another value "
              "are refused by name)")
    _opt(bm, MorphBenchSettings, "lr", type=float, help="the suite's runs' position learning rate (MorphSettings.lr)")
    _opt(bm, MorphBenchSettings, "step_select_quantile", type=float,
         help="the suite's runs ask the validation photos about this quantile step (MorphSettings.step_select_quantile; "
              "1: no such choice)")
    _opt(bm, MorphBenchSettings, "saturation", type=float,
         help="the suite's runs leave pixels brighter than this × the photos' 99th percentile out of the loss "
              "(MorphSettings.saturation; 0: every pixel counts)")
    _opt(bm, MorphBenchSettings, "mask_weight", type=float,
         help="the suite's runs add a silhouette L1 against the photos' masks at this weight "
              "(MorphSettings.mask_weight; 0: photos only)")
    _opt(bm, MorphBenchSettings, "boundary_spp", type=int, help="the suite's runs' silhouette samples per pixel "
         "(MorphSettings.boundary_spp; the image takes 4)")
    _opt(bm, MorphBenchSettings, "mask_every", help="the suite's runs render the masks every this many steps, at "
         "this × the weight (MorphSettings.mask_every)")
    _opt(bm, MorphBenchSettings, "mask_downsample", help="the suite's runs render the masks at the photos' resolution "
         "// this (MorphSettings.mask_downsample)")
    _opt(bm, MorphBenchSettings, "seed", help="another draw of every benchmark (photos' noise, views) and of every "
                                               "morph's render seeds (work folder: OUT/morph_work_seed<k>)")
    _opt(bm, MorphBenchSettings, "cost_mesh", help="the mesh of --parts iteration")
    _opt(bm, MorphBenchSettings, "cost_iterations", help="steps per timed block (--parts iteration)")
    _opt(bm, MorphBenchSettings, "cost_rounds", help="timed blocks per recipe, in turns (--parts iteration)")
    _opt(bm, MorphBenchSettings, "cases")
    _opt(bm, MorphBenchSettings, "suite", help="suite meshes (village and armadillo may be added; paul, face000 "
                                               "and bracket are meshes the defaults never saw)")
    _opt(bm, MorphBenchSettings, "iterations", help="morph iterations of the main and suite runs")
    _opt(bm, MorphBenchSettings, "keep_work", help="keep OUT/morph_work after the bench: a rerun re-reads the "
                                                   "finished runs instead of recomputing them (default: removed)")
    _pool_opts(bm)
    bm.set_defaults(func=_cmd_bench_morph)
    bms = bsub.add_parser("morph-seeds", help="the morph suite over several draws: `bench morph --parts suite "
                                              "--seed K` results, one per seed, summed up per mesh (mean, worst, "
                                              "at how many seeds every target holds) with a chart")
    bms.add_argument("results", nargs="+", help="bench morph JSON files with a suite, one per seed (a seed's suite "
                                                "run in parts: its files, each with other meshes)")
    bms.add_argument("--against", nargs="+", metavar="RESULT",
                     help="the same draws under other settings (e.g. before a change): paired by mesh and seed, "
                          "the change per draw, its mean and standard error, wins and losses (sign test), targets "
                          "gained and lost, and a chart OUT_against.png")
    bms.set_defaults(func=_cmd_bench_morph_seeds)
    bld = bsub.add_parser("morph-light-draws", help="every light choice of `bench morph --parts suite --keep-work` "
                                                    "results scored again under other draws of the light estimate: "
                                                    "how much of each choice the estimate's own noise decides")
    bld.add_argument("results", nargs="+", help="bench morph JSON files with a suite, their work folders kept")
    bld.add_argument("--draws", type=int, default=4, help="draws of the estimate per run, the choice's own first "
                                                         "(default: 4)")
    bld.set_defaults(func=_cmd_bench_morph_light_draws)
    bb = bsub.add_parser("btf", help="neural BTF: universal vs NeuMIP, width × texture sweep, render time")
    _pool_opts(bb)
    bb.set_defaults(func=_cmd_bench_btf)
    bf = bsub.add_parser("face", help="face fitting: accuracy vs time over UV resolution, stability")
    _opt(bf, FaceBenchSettings, "scan", help="josie, paul, or an OBJ path")
    bf.set_defaults(func=_cmd_bench_face)
    bg = bsub.add_parser("gan", help="GAN refinement stages on held-out views")
    bg.add_argument("--seconds-per-model", type=float, default=None,
                    help=f"training budget per GAN (default: {_default(GanBenchSettings, 'seconds_per_model')} s; "
                         "the joint, CycleGAN and fine-tune budgets keep their proportions)")
    bg.set_defaults(func=_cmd_bench_gan)
    from .benchmarks.diffrender import DiffRenderBenchSettings

    bd = bsub.add_parser("diffrender", help="diffusion renderer vs PBR recomposition and the GANs on held-out views; "
                         "decomposition network, ablations, steps × size sweep, an unseen mesh")
    _opt(bd, DiffRenderBenchSettings, "train_seconds", type=float, help="the main model's training budget")
    _opt(bd, DiffRenderBenchSettings, "ablation_seconds", type=float, help="training budget of each ablation run")
    _opt(bd, DiffRenderBenchSettings, "decomp_seconds", type=float, help="decomposition network's training budget")
    _opt(bd, DiffRenderBenchSettings, "decomp_scenes", help="procedural scenes for the decomposition network")
    _opt(bd, DiffRenderBenchSettings, "sweep_steps", nargs="+", type=int, help="DDIM steps of the sweep")
    _opt(bd, DiffRenderBenchSettings, "seeds", help="sampling seeds of the main model's held-out renders")
    _opt(bd, DiffRenderBenchSettings, "guidance")
    _opt(bd, DiffRenderBenchSettings, "mean_draws", type=int,
         help="the sweep's means of one-step samples per view it tries (1: none)")
    _opt(bd, DiffRenderBenchSettings, "sweep_guidance", type=float, help="guidance weights tried with those means")
    _opt(bd, DiffRenderBenchSettings, "tolerance_rel", type=float,
         help="the choice: cheapest within this fraction of the sweep's best ꟻLIP")
    _opt(bd, DiffRenderBenchSettings, "input_spp", help="samples per pixel of every method's input renders")
    _opt(bd, DiffRenderBenchSettings, "photo_spp", help="samples per pixel of the benchmarks' photos (the targets)")
    _opt(bd, DiffRenderBenchSettings, "reference_spp", help="samples per pixel of the noise-free references")
    _opt(bd, DiffRenderBenchSettings, "validation", nargs="*",
         help="meshes never trained on that choose the main model's size at the main budget (none: the sweep's)")
    _opt(bd, DiffRenderBenchSettings, "gans", "--no-gans", help="skip training the GAN baselines")
    _opt(bd, DiffRenderBenchSettings, "gan_seconds", type=float, help="pix2pix / Morph-GAN budget each")
    _opt(bd, DiffRenderBenchSettings, "cyclegan_seconds", type=float)
    _opt(bd, DiffRenderBenchSettings, "workers",
         help="trainings and renders run this many at a time, one thread each (0: one after another, all threads)")
    _opt(bd, DiffRenderBenchSettings, "seed")
    bd.set_defaults(func=_cmd_bench_diffrender)
    from .benchmarks.matdiff import MatDiffBenchSettings

    bmd = bsub.add_parser("matdiff", help="material diffusion: keyword/exemplar conditioning, KID vs baselines, "
                         "memorisation, seams, speed, ablations, dataset sweep (builds/continues its dataset first)")
    for name in ("data", "count", "train_seconds", "ablation_seconds", "samples", "steps", "guidance", "seed"):
        _opt(bmd, MatDiffBenchSettings, name)
    _opt(bmd, MatDiffBenchSettings, "main_run", help="finished `btf train-diffusion` run (e.g. trained with --device "
         "cuda) to evaluate instead of training the main model here; default: train here")
    _opt(bmd, MatDiffBenchSettings, "ablations", "--no-ablations", help="skip the ablation runs")
    bmd.set_defaults(func=_cmd_bench_matdiff)
    from .benchmarks.face_learned import FaceLearnedBenchSettings

    bfl = bsub.add_parser("face-learned", help="learned face stages vs the optimisation baseline on a held-out scan: "
                          "completion, decomposition variants, super-resolution, cross-model fit, end to end")
    for name in ("train_instances", "eval_instances", "completion_seconds", "decomp_seconds", "superres_seconds",
                 "relit_instances", "cross_uv_res", "workers", "seed"):
        _opt(bfl, FaceLearnedBenchSettings, name)
    _opt(bfl, FaceLearnedBenchSettings, "layout", choices=["template", "scan"], help="UV layout of the learned stages")
    _opt(bfl, FaceLearnedBenchSettings, "ablation_seeds", type=int,
         help="retrain every decomposition variant with these seeds too: the ablation's spread over training seeds")
    _opt(bfl, FaceLearnedBenchSettings, "cross_model", "--no-cross-model", help="skip the cross-model fit")
    _opt(bfl, FaceLearnedBenchSettings, "astronaut", "--no-astronaut", help="skip the astronaut photograph")
    bfl.set_defaults(func=_cmd_bench_face_learned)
    bs = bsub.add_parser("scale", help="a batch of renders serially, on a process pool and on Ray (identical?)")
    for name in ("items", "resolution", "spp"):
        _opt(bs, ScaleBenchSettings, name)
    _opt(bs, ScaleBenchSettings, "ray", "--no-ray", help="leave out the Ray configuration")
    _opt(bs, ScaleBenchSettings, "material_item", "--no-material", help="leave out timing one BTF material")
    bs.set_defaults(func=_cmd_bench_scale)
    for q in (bp, bm, bms, bld, bb, bf, bg, bd, bmd, bfl, bs):
        q.add_argument("--json", required=True, help="output JSON path (charts and work folders go beside it)")

    f = sub.add_parser("face", help="face material fitting in UV space (seed 003)")
    fsub = f.add_subparsers(dest="face_cmd", required=True)
    fm = fsub.add_parser("make-benchmark", help="ground truth + Mitsuba observations from an OBJ scan with texture")
    fm.add_argument("--scan", required=True, help="OBJ with texture coordinates and a map_Kd texture")
    fm.add_argument("--out", required=True, help="benchmark folder to create (absent, empty, or an earlier benchmark)")
    _opt(fm, FaceBenchmarkSettings, "uv_res")
    _opt(fm, FaceBenchmarkSettings, "n_lights", "--lights", help="directional training lights")
    _opt(fm, FaceBenchmarkSettings, "seed")
    _opt(fm, FaceBenchmarkSettings, "heldout_hdris", "--hdri", metavar="HDRI",
         help="held-out relighting environments: bundled names or your own .exr files (copied into the benchmark); "
              "the training photos stay under directional lights unless --lighting hdri")
    _opt(fm, FaceBenchmarkSettings, "observation_bsdf", choices=["ggx_uv", "principled"],
         help="BSDF the observations are rendered with (principled: a model the fit does not know)")
    _opt(fm, FaceBenchmarkSettings, "lighting", choices=["directional", "hdri"],
         help="each observation under one directional light, or under a real HDRI at a seeded rotation")
    _opt(fm, FaceBenchmarkSettings, "lighting_hdris", metavar="HDRI", help="environments of --lighting hdri")
    _opt(fm, FaceBenchmarkSettings, "max_depth", help="path length of the observations (> 2: interreflection)")
    _opt(fm, FaceBenchmarkSettings, "albedo_blur", type=float,
         help="rendered albedo blurred by this many texels at 256² (subsurface-like spread; the truth is not blurred)")
    fm.set_defaults(func=_cmd_face_make_benchmark)
    ff = fsub.add_parser("fit", help="fit UV maps to benchmarks and score them (resumes from a checkpoint)")
    ff.add_argument("benchmark", nargs="+", help="folder(s) made by make-benchmark, or a folder of them")
    ff.add_argument("--json", default=None, help="metrics JSON of one benchmark (the checkpoint goes beside it)")
    ff.add_argument("--out-dir", default=None, help="several benchmarks: DIR/NAME/fit.json and DIR/NAME/maps")
    ff.add_argument("--maps", default=None, help="folder for the fitted maps (EXR + PNG)")
    _opt(ff, FaceFitSettings, "fit_lights", help="treat lighting as unknown and fit it jointly")
    _opt(ff, FaceFitSettings, "iterations", type=int, help="Adam steps per pyramid level")
    ff.add_argument("--refine-renders", type=int, default=0, metavar="N",
                    help=f"then refine N Adam steps through full camera renders (prb through ggx_uv; "
                         f"suggested {_default(RenderRefineSettings, 'iterations')}; default: 0, off)")
    _opt(ff, FaceFitSettings, "seed")
    _pool_opts(ff)
    ff.set_defaults(func=_cmd_face_fit)
    fp = fsub.add_parser("from-photo", help="one photograph -> relightable face (landmarks, unwrap, delight, relight)")
    fp.add_argument("image", help="image file, or 'astronaut' for scikit-image's photograph")
    fp.add_argument("--out", required=True, help="output folder (absent, empty, or an earlier from-photo output)")
    fp.add_argument("--landmarks", default=None, help="468x3 landmarks (.npy/.json) instead of running mediapipe")
    _opt(fp, PhotoFitSettings, "uv_res")
    _opt(fp, PhotoFitSettings, "seed")
    fp.add_argument("--learned", default=None, metavar="RUN",
                    help="replace fill, delighting and template defaults by the learned stages of a "
                         "`face train-models` run (default: the optimisation baseline)")
    fp.add_argument("--variant", default=None, help="decomposition variant of the run (default: the run's first)")
    fp.set_defaults(func=_cmd_face_from_photo)
    from generative.diffusion import CompletionSettings, FaceDataSettings, FaceDecompSettings, SuperResSettings

    ft = fsub.add_parser("train-models", help="learned UV-space stages (seed 003 §2–§4): data from the training "
                         "scan, completion diffusion (the backbone), LoRA decomposition, 2× super-resolution (resumes)")
    ft.add_argument("--out", required=True, help="run folder (absent, empty, or this command's earlier run)")
    for name in ("train_instances", "eval_instances", "uv_res", "spp", "seed"):
        _opt(ft, FaceDataSettings, name)
    _opt(ft, FaceDataSettings, "layout", choices=["template", "scan"],
         help="UV layout of the maps: the face template's (what from-photo unwraps into) or the scans' own")
    ft.add_argument("--completion-seconds", type=float, default=_default(CompletionSettings, "max_seconds"),
                    help="training budget of the completion model (default: %(default)s)")
    ft.add_argument("--decomp-seconds", type=float, default=_default(FaceDecompSettings, "max_seconds"),
                    help="training budget of each decomposition variant (default: %(default)s)")
    ft.add_argument("--superres-seconds", type=float, default=_default(SuperResSettings, "max_seconds"),
                    help="training budget of the upscaler (default: %(default)s)")
    ft.add_argument("--variants", nargs="+", default=["cross_attention"],
                    choices=["cross_attention", "shared", "independent"],
                    help="decomposition variants to train; the first is the one from-photo uses (default: cross_attention)")
    _pool_opts(ft)
    ft.set_defaults(func=_cmd_face_train_models)

    m = sub.add_parser("morph", help="geometry morphing of coarse meshes against photos (REAL-DIBS §4)")
    msub = m.add_subparsers(dest="morph_cmd", required=True)
    mm = msub.add_parser("make-benchmark", help="ground truth + photos + degraded reconstruction")
    mm.add_argument("--mesh", required=True, help="OBJ/PLY/OFF mesh, or 'village'")
    mm.add_argument("--out", required=True, help="benchmark folder (absent, empty, or an earlier benchmark)")
    _opt(mm, MorphBenchmarkSettings, "n_views", "--views", help="photos on the drone orbit (every 4th is held out)")
    _opt(mm, MorphBenchmarkSettings, "resolution")
    _opt(mm, MorphBenchmarkSettings, "spp")
    _opt(mm, MorphBenchmarkSettings, "seed")
    _opt(mm, MorphBenchmarkSettings, "hdri", help="lighting of the photos (and of the morph's lit renders): a bundled "
                                                  "HDRI's name or your own .exr, copied into the benchmark")
    _opt(mm, MorphBenchmarkSettings, "elevation_deg", "--elevation", type=float, nargs=2, metavar=("LOW", "HIGH"),
         help="camera elevation range in degrees (default: 25 45 for the village, -15 65 for an object)")
    _opt(mm, MorphBenchmarkSettings, "framing_margin",
         help="objects: free border around the bounding sphere, fraction of the half-image")
    _opt(mm, MorphBenchmarkSettings, "truth_normals", choices=list(TRUTH_NORMALS),
         help="shading of the photographed truth: interpolated vertex normals (smooth) or each triangle flat, the "
              "geometry the Chamfer measures (they disagree for truths with few vertices)")
    _opt(mm, MorphBenchmarkSettings, "photo_max_depth",
         help="path length of the photos; 2 = direct light only, what the morph renders (no interreflections to "
              "explain)")
    mm.set_defaults(func=_cmd_morph_make_benchmark)
    mr = msub.add_parser("run", help="morph benchmarks' coarse meshes (resumes from their checkpoints)")
    mr.add_argument("benchmark", nargs="+", help="benchmark folder(s), or a folder of them")
    mr.add_argument("--out", default=None, help="output folder of one benchmark (default BENCHMARK/morph)")
    mr.add_argument("--out-dir", default=None, help="several benchmarks: DIR/NAME (default: each BENCHMARK/morph)")
    mr.add_argument("--json", default=None, help="metrics JSON")
    _opt(mr, MorphSettings, "iterations")
    _opt(mr, MorphSettings, "views_per_step")
    _opt(mr, MorphSettings, "mode", choices=["lit", "unlit"])
    _opt(mr, MorphSettings, "lambda_", "--lambda", help="large-steps λ")
    _opt(mr, MorphSettings, "lr", type=float,
         help="position learning rate, × the scene size / 10 (0: positions frozen, a colour-only fit)")
    mr.add_argument("--plain-adam", action="store_true", help="per-vertex Adam instead of large steps")
    _opt(mr, MorphSettings, "target_vertices", type=int,
         help="remesh the input to about this many vertices (default: see --min-vertices)")
    _opt(mr, MorphSettings, "resolution", type=int, help="working resolution (default: the benchmark's)")
    mr.add_argument("--gcn", action="store_true", help="shape-aware GCN trained through the renderer")
    _opt(mr, MorphSettings, "forbid_flips",
         help="undo a step at vertices of triangles it would flip (0 inverted, less accurate)")
    _opt(mr, MorphSettings, "min_vertices", type=int,
         help="remesh a coarser input up to about this many vertices (0: keep its count)")
    _opt(mr, MorphSettings, "planarity_weight", type=float,
         help="edge-preserving planarity prior (0: image loss only; default auto: on for scenes whose "
              "largest plane holds ≥ 26%% of the area, e.g. a ground plane)")
    _opt(mr, MorphSettings, "colour_prior_weight", type=float,
         help="colour prior: a piecewise-smooth albedo, so that the geometry, not the vertex colour, explains "
              "shading (0: off; default auto: 0.1 where the input's own colours are smooth, off for textured ones, "
              "and with --lambda-select the validation photos confirm it against the winner without it)")
    mr.add_argument("--no-repair", action="store_true",
                    help="keep folds: skip the final unfolding of triangles flipped w.r.t. the start (reported)")
    _opt(mr, MorphSettings, "border_turn_deg", type=float,
         help="after the flip repair, iron back into line the open border's triangles (border and 1-ring) turned more "
              "than this many degrees from the start: a curl of an open scan's border (reported; 0: off)")
    _opt(mr, MorphSettings, "validation_views",
         help="training photos kept out of the fit to watch convergence (0: fit all)")
    _opt(mr, MorphSettings, "early_stop", "--no-early-stop",
         help="run all --iterations (default: stop when the validation loss stops improving; --iterations caps it)")
    _opt(mr, MorphSettings, "lambda_start", type=float,
         help="large-steps λ at the start, falling geometrically to --lambda over the first 30%% of the iterations "
              "(e.g. 25: steadier first steps on thin parts; setting it turns --lambda-select off)")
    _opt(mr, MorphSettings, "lambda_select", type=float,
         help="λ start values tried side by side to the end of that warm-up; the one the validation photos prefer "
              "continues (a value ≤ --lambda: constant λ; one value: no choice)")
    _opt(mr, MorphSettings, "planarity_select", type=float, nargs="*",
         help="planarity-prior weights that join that choice as candidates at constant λ when the input has no "
              "dominant plane (the option alone: the plane rule decides; --planarity-weight turns the choice off)")
    _opt(mr, MorphSettings, "planarity_where", choices=list(PLANARITY_WHERE),
         help="edges the planarity prior acts on: all; seen (beside a triangle a fitted training photo sees); thick "
              "(between triangles of parts at least --planarity-min-thickness thick)")
    _opt(mr, MorphSettings, "planarity_select_where", choices=list(PLANARITY_WHERE),
         help="the same for the --planarity-select candidates")
    _opt(mr, MorphSettings, "planarity_min_thickness", type=float,
         help="with 'thick': the least thickness of a part the prior acts on (ray cast along the start's inward "
              "normals), × the start's largest extent")
    _opt(mr, MorphSettings, "prior_margin", type=float,
         help="a prior those choices ask the photos about (planarity candidate, colour prior) is kept only where its "
              "validation L1 is this fraction below the best run without it (0: the lower L1 wins)")
    _opt(mr, MorphSettings, "prior_ties", choices=list(PRIOR_TIES),
         help="within that margin: keep the prior (the run without must beat it by the margin) or drop it (the "
              "prior must win by the margin)")
    _opt(mr, MorphSettings, "adam_quantile", type=float,
         help="large steps: the quantile of Adam's second moments that scales every step (1: their maximum, "
              "uniform Adam; lower: the silhouettes' noisy gradient no longer sets the step of the whole surface)")
    _opt(mr, MorphSettings, "indirect_every", type=int,
         help="re-estimate the light the direct-only renders miss (path traced at the photos' depth minus direct "
              "light, per photo) every N iterations and add it to the renders (0: off)")
    _opt(mr, MorphSettings, "indirect_spp", type=int, help="samples per pixel of each render of that estimate")
    _opt(mr, MorphSettings, "indirect_reference", choices=["direct", "depth2"],
         help="what that estimate subtracts: the direct integrator, or the path tracer at depth 2 with the same seed "
              "(the first bounce cancels: 3× less noise at the same spp)")
    _opt(mr, MorphSettings, "indirect_downsample", type=int,
         help="render that estimate at 1/N of the fitting resolution and upsample it bilinearly (the indirect light "
              "varies slowly: at 2 less error than at 1 for a third of the time; 1: full resolution)")
    _opt(mr, MorphSettings, "boundary_spp", type=int,
         help="samples per pixel of the silhouettes' gradient (the image and the rest of its gradient take 4)")
    _opt(mr, MorphSettings, "colour_lambda", type=float,
         help="large-steps λ for the vertex colours' steps (0: plain per-vertex steps): smooth colour changes come "
              "fast, bump-sized ones slowly, so that the geometry explains the bumps' shading (default 0: off)")
    _opt(mr, MorphSettings, "light_select_every", type=int,
         help="where both of those are off, the selection's winner also runs with the light estimate every N "
              "iterations and colour large steps to the selection point, and the validation photos (each run "
              "measured after a fresh light estimate on its own mesh) decide by --prior-margin (0: no such "
              "candidate)")
    _opt(mr, MorphSettings, "light_select_colour_lambda", type=float,
         help="colour λ of that candidate")
    _opt(mr, MorphSettings, "step_select_quantile", type=float,
         help="where --adam-quantile is 1, the winner of the λ and colour choices also runs with this quantile step "
              "and --step-select-lr to the selection point, and the validation photos decide by --prior-margin "
              "(1: no such candidate)")
    _opt(mr, MorphSettings, "step_select_lr", type=float, help="position learning rate of that candidate")
    _opt(mr, MorphSettings, "saturation", type=float,
         help="pixels brighter than this × the training photos' 99th percentile, in a photo or its render, and their "
              "neighbours stay out of the loss, as a camera clips them (a silhouette against the sun otherwise "
              "swamps every step); 0: every pixel counts")
    _opt(mr, MorphSettings, "mask_weight", type=float,
         help="weight of a silhouette L1 beside the photos': the mesh's coverage of each pixel against the photos' "
              "masks (the benchmark's truth), so that every silhouette pulls with contrast 1; 0: photos only")
    _opt(mr, MorphSettings, "mask_every", help="the silhouette L1 every this many steps only, at this × the weight "
         "(the same mean gradient, cheaper)")
    _opt(mr, MorphSettings, "mask_downsample", help="the masks and their renders at the photos' resolution // this "
         "(cheaper; a coarser mask still places a silhouette to a fraction of its pixel)")
    _opt(mr, MorphSettings, "seed")
    _pool_opts(mr)
    mr.set_defaults(func=_cmd_morph_run)

    me = msub.add_parser("errors", help="where meshes lie against a benchmark's truth: both Chamfer directions, its "
                                        "open border against its interior, the input's error a result kept (in all "
                                        "and per spatial scale), the area facing against the truth by how many "
                                        "training views see it; signed-distance PLYs, PLYs marking the "
                                        "triangles facing against the truth, and a figure of each")
    me.add_argument("benchmark", help="folder made by `photoreal morph make-benchmark`")
    me.add_argument("results", nargs="+", help="result meshes (OBJ/PLY/OFF) or morph output folders (their morphed.ply)")
    me.add_argument("--out", required=True, help="folder for errors.json, errors_<name>.ply, facing_<name>.ply, "
                    "errors.png and facing.png")
    me.add_argument("--json", default=None, help="also write the report here")
    me.add_argument("--band", type=float, default=None,
                    help="width of the truth's border band (default 2.5%% of its bounding-box diagonal)")
    me.set_defaults(func=_cmd_morph_errors)

    ms_ = msub.add_parser("saturation", help="per training view, the pixels where the lighting is saturated (as "
                                            "`morph run --saturation` sees it) and how many lie at the truth's "
                                            "silhouette, where an edge's gradient is scaled by that light")
    ms_.add_argument("benchmarks", nargs="+", help="folders made by `photoreal morph make-benchmark`")
    ms_.add_argument("--factor", type=float, default=MorphSettings.saturation,
                     help="the saturation level: this × the training photos' 99th percentile (default: the morph's "
                          "MorphSettings.saturation, %(default)s)")
    ms_.add_argument("--json", default=None, help="also write the report here")
    ms_.set_defaults(func=_cmd_morph_saturation)

    t = sub.add_parser("btf", help="universal neural BTF: data, basis training, per-material fitting (seed 002)")
    tsub = t.add_subparsers(dest="btf_cmd", required=True)
    tr = tsub.add_parser("render-data", help="render BTFs from procedural/photo SVBRDFs (resumes: skips finished files)")
    tr.add_argument("--out", required=True, help="dataset folder")
    tr.add_argument("--families", nargs="+", default=None, help="subset of the material families (default: all 8)")
    tr.add_argument("--per-family", type=int, default=_arg(render_dataset, "per_family"),
                    help=f"materials per family (default: {_arg(render_dataset, 'per_family')})")
    for name in ("tex_res", "slices", "spp", "max_depth", "seed"):
        _opt(tr, BTFRenderSettings, name)
    _pool_opts(tr)
    tr.set_defaults(func=_cmd_btf_render_data)
    tb = tsub.add_parser("train-basis", help="train the universal MLPs on a dataset (resumes from --checkpoint)")
    tb.add_argument("data", help="folder made by render-data")
    tb.add_argument("--out", required=True, help="basis .npz")
    _opt(tb, OptimSettings, "iterations")
    _opt(tb, OptimSettings, "batch")
    _opt(tb, BasisConfig, "width")
    _opt(tb, BasisConfig, "depth")
    _opt(tb, BasisConfig, "channels")
    tb.add_argument("--checkpoint", default=None, help="default: OUT with .ckpt.npz")
    _opt(tb, OptimSettings, "seed")
    tb.set_defaults(func=_cmd_btf_train_basis)
    tf = tsub.add_parser("fit", help="fit materials' feature textures with the basis frozen (resumes)")
    tf.add_argument("btf", nargs="+", help="BTF .npz file(s) from render-data")
    tf.add_argument("--basis", required=True)
    tf.add_argument("--out", default=None, help="material .npz for the neural_btf plugin (one BTF)")
    tf.add_argument("--out-dir", default=None, help="folder for several materials: DIR/NAME.npz")
    tf.add_argument("--iterations", type=int, default=_arg(fit_settings, "iterations"),
                    help=f"Adam steps (default: {_arg(fit_settings, 'iterations')})")
    tf.add_argument("--batch", type=int, default=_default(OptimSettings, "batch"),
                    help=f"samples per step (default: {_default(OptimSettings, 'batch')})")
    _opt(tf, OptimSettings, "tex_res", help="feature texture resolution (0 = the BTF's)")
    tf.add_argument("--heldout-fraction", type=float, default=_arg(split_slices, "heldout_fraction"),
                    help=f"slices held out for the PSNR (default: {_arg(split_slices, 'heldout_fraction')})")
    tf.add_argument("--checkpoint", default=None, help="default: OUT with .ckpt.npz")
    tf.add_argument("--json", default=None)
    _opt(tf, OptimSettings, "seed")
    _pool_opts(tf)
    tf.set_defaults(func=_cmd_btf_fit)

    from generative.diffusion import MaterialDataSettings, MatDiffSettings

    td = tsub.add_parser("dataset", help="many fitted materials for the material diffusion model: BTFs, fits, "
                         "path-traced swatches, keywords (resumes; every core)")
    td.add_argument("--out", required=True, help="dataset folder")
    for name in ("count", "tex_res", "slices", "spp", "fit_iterations", "seed"):
        _opt(td, MaterialDataSettings, name)
    td.add_argument("--basis", default=None, help="universal basis .npz (default: the bundled one)")
    _pool_opts(td)
    td.set_defaults(func=_cmd_btf_dataset)
    tt = tsub.add_parser("train-diffusion", help="train the material diffusion model on a dataset's training "
                         "materials (resumes)")
    tt.add_argument("data", help="folder made by `btf dataset`")
    tt.add_argument("--out", required=True, help="run folder (checkpoint.npz, metrics.json)")
    _opt(tt, MatDiffSettings, "max_seconds", "--seconds", type=float, help="training budget (summed over resumes)")
    for name in ("steps", "batch", "train_crop", "lr", "widths", "attention_levels", "ema", "seed"):
        _opt(tt, MatDiffSettings, name, **({"type": int} if name == "widths" else {}))
    tt.add_argument("--device", default="cpu", help="torch device of the model (cpu, cuda, cuda:N, mps; default: cpu); "
                    "a run resumes on any device")
    tt.set_defaults(func=_cmd_btf_train_diffusion)
    tg = tsub.add_parser("generate", help="a new material from keywords and/or an exemplar image; loads in "
                         "neural_btf with the basis the model was trained on")
    tg.add_argument("--run", default=None, help="run folder of `btf train-diffusion` (default: the bundled model, "
                    "scenes/assets/neural/matdiff, trained on a GPU; see its README)")
    tg.add_argument("--keywords", default=None, help="e.g. 'rough red leather' (family, colour, finish words)")
    tg.add_argument("--image", default=None, help="exemplar photo (PNG/JPG/EXR, or brick/grass/gravel)")
    tg.add_argument("--from-prior", action="store_true", help="a random material: keywords drawn (by --seed) from "
                    "the run's training materials (keyword_prior.json)")
    tg.add_argument("--unconditional", action="store_true", help="neither keywords nor image (the null condition: "
                    "its samples collapse to few families; --from-prior is the better random material)")
    tg.add_argument("--seed", type=int, default=0)
    tg.add_argument("--size", type=int, default=32, help="texels per side (any multiple of 4: tiles seamlessly)")
    tg.add_argument("--steps", type=int, default=None, help="DDIM steps (default: the run's sampler.json, which "
                    "`bench matdiff` writes; else 25)")
    tg.add_argument("--guidance", type=float, default=None, help="classifier-free guidance (default: the run's "
                    "sampler.json; else 2)")
    tg.add_argument("--out", required=True, help="material .npz")
    tg.set_defaults(func=_cmd_btf_generate)

    _add_gan_parser(sub)
    _add_diffrender_parser(sub)

    d = sub.add_parser("demo", help="render the built-in scenes and write an HTML report")
    d.add_argument("--out", default="out/demo", help="report folder (default: out/demo)")
    d.add_argument("--bench-dir", default=None,
                   help="folder with `photoreal bench` JSON files for the report's tables (default: OUT/../bench)")
    _opt(d, DemoSettings, "resolution", help="image side of the renders (the face's camera renders: at most 192)")
    _opt(d, DemoSettings, "spp", help="samples per pixel (the face's camera renders: at most 64)")
    _opt(d, DemoSettings, "seed")
    _opt(d, DemoSettings, "plugin_bench", "--no-bench", help="skip the plugin speed section")
    _opt(d, DemoSettings, "face", "--no-face", help="skip the face sections")
    _opt(d, DemoSettings, "face_uv_res")
    _opt(d, DemoSettings, "morph_iterations", help="0 skips the morphing section")
    _opt(d, DemoSettings, "btf", "--no-btf", help="skip the neural materials section")
    d.set_defaults(func=_cmd_demo)
    return p


def _add_gan_parser(sub) -> None:
    from generative.gan import GanTrainSettings

    g = sub.add_parser("gan", help="GAN refinement of renders: pix2pix, CycleGAN, Morph-GAN, joint (REAL-DIBS §3, §5)")
    gsub = g.add_subparsers(dest="gan_cmd", required=True)
    gt = gsub.add_parser("train", help="train one model on a morph benchmark + morph run (resumes from OUT)")
    gt.add_argument("benchmark", help="folder made by `photoreal morph make-benchmark`")
    gt.add_argument("--morph", default=None, help="morph run folder with morphed.ply (default BENCHMARK/morph)")
    gt.add_argument("--model", choices=["pix2pix", "cyclegan", "morph_gan_partial", "morph_gan", "joint"],
                    default=_default(GanTrainSettings, "model"),
                    help=f"default: {_default(GanTrainSettings, 'model')}; joint: mesh and Morph-GAN together")
    gt.add_argument("--out", required=True, help="training folder (checkpoint.npz, metrics.json)")
    _opt(gt, GanTrainSettings, "steps")
    _opt(gt, GanTrainSettings, "max_seconds", "--seconds", type=float, help="wall-time budget (summed over resumes)")
    _opt(gt, GanTrainSettings, "batch")
    _opt(gt, GanTrainSettings, "crop")
    _opt(gt, GanTrainSettings, "ngf", help="generator and discriminator width")
    gt.add_argument("--init-from", default=None,
                    help="fine-tune a finished run folder of the same model (joint: of morph_gan, + the morphed mesh)")
    gt.add_argument("--paper-head", action="store_true",
                    help="generator outputs tanh directly (papers' head) instead of input + tanh correction")
    gt.add_argument("--json", default=None)
    _opt(gt, GanTrainSettings, "seed")
    ge = gsub.add_parser("eval", help="held-out metrics of a trained model")
    ge.add_argument("benchmark")
    ge.add_argument("--morph", default=None, help="morph run folder (default BENCHMARK/morph)")
    ge.add_argument("--run", required=True, help="training folder of `gan train`")
    ge.add_argument("--json", default=None)
    g.set_defaults(func=_cmd_gan)


# -- errors ---------------------------------------------------------------------------------------------------------


def _usage(msg: str):
    from foundation.errors import UsageError

    return UsageError(msg)


def _flags(parser: argparse.ArgumentParser, argv: list[str]) -> dict[str, str]:
    """dest → option string of the subcommand that ran (to name flags, not field names, in errors)."""
    out: dict[str, str] = {}

    def walk(p: argparse.ArgumentParser) -> None:
        for act in p._actions:
            if isinstance(act, argparse._SubParsersAction):
                for name, sp in act.choices.items():
                    if name in argv:
                        walk(sp)
            elif act.option_strings:
                out.setdefault(act.dest, max(act.option_strings, key=len))

    walk(parser)
    return out


def _message(exc: BaseException, flags: dict[str, str]) -> str:
    msg = " ".join(str(exc).split()) or type(exc).__name__
    for dest, flag in flags.items():
        if msg.startswith(dest + " ") or msg.startswith(dest + ":"):
            return flag + msg[len(dest):]
    return msg


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    try:
        import mi_plugins  # noqa: F401  (resolves libLLVM, picks and checks the variant)

        parser = build_parser()
    except ValueError as exc:  # e.g. PHOTOREAL_VARIANT names a variant the plugins cannot run on
        print(f"photoreal: error: {exc}", file=sys.stderr)
        return 2
    args = parser.parse_args(argv)
    from foundation.errors import PhotorealError

    debug = os.environ.get("PHOTOREAL_DEBUG", "") not in ("", "0")
    try:
        return args.func(args)
    except KeyboardInterrupt:
        print("photoreal: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:
        if debug:
            raise
        code = getattr(exc, "exit_code", None)
        if code is None:  # plain errors: a bad value or a missing file is the user's input; the rest, a failure
            code = 2 if isinstance(exc, (ValueError, FileNotFoundError, NotADirectoryError, IsADirectoryError,
                                         ImportError)) else 1
        msg = _message(exc, _flags(parser, argv))
        if not isinstance(exc, (PhotorealError, ValueError, OSError, ImportError, RuntimeError, FloatingPointError)):
            msg = f"internal error, {type(exc).__name__}: {msg} (PHOTOREAL_DEBUG=1 shows the traceback)"
        print(f"photoreal: error: {msg}", file=sys.stderr)
        return code


if __name__ == "__main__":
    sys.exit(main())
