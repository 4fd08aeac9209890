"""`photoreal face …`: face benchmarks, UV-space fits, one photo to a face, the learned stages."""

from __future__ import annotations

import argparse

from ..options import default_of, opt, settings_from, settings_named
from .common import (
    add_subcommands,
    benchmark_dirs,
    check_out_dir,
    out_opt,
    pool_options,
    pool_settings,
    print_json,
    run_batch,
    usage,
)

HELP = "face material fitting in UV space (seed 003)"


def _cmd_face_make_benchmark(a) -> int:
    from foundation.files import check_output_dir
    from inverse.face import FaceBenchmarkSettings, make_benchmark

    check_output_dir(a.out, "benchmark.json", "--out", replace=True)
    out = make_benchmark(a.scan, a.out, settings_from(FaceBenchmarkSettings, a))
    print(f"benchmark: {out}")
    return 0



def _cmd_face_fit(a) -> int:
    from foundation.pool import Item
    from inverse.face import FaceFitSettings, RenderRefineSettings, fit_benchmark_dir

    fs = settings_from(FaceFitSettings, a)
    refine = RenderRefineSettings(iterations=a.refine_renders, seed=a.seed) if a.refine_renders else None
    benches = benchmark_dirs(a.benchmark, "benchmark.json")
    if len(benches) > 1 or a.out_dir:
        if a.json or a.maps:
            raise usage("--json and --maps name one benchmark's outputs; several go to --out-dir")
        if not a.out_dir:
            raise usage("several benchmarks: give --out-dir DIR (DIR/NAME/fit.json and DIR/NAME/maps each)")
        out = check_out_dir(a.out_dir)
        names = [b.name for b in benches]
        if len(set(names)) != len(names):
            raise usage("two benchmarks share a folder name; their fits would overwrite each other in --out-dir")
        items = [Item(b.name, "inverse.face:fit_benchmark_item",
                      (str(b), str(out / b.name / "fit.json"), str(out / b.name / "maps"), fs, refine),
                      output=str(out / b.name / "fit.json")) for b in benches]
        return run_batch(items, a, "face fits")
    if not a.json:
        raise usage("give --json FILE (or --out-dir for several benchmarks)")
    r = fit_benchmark_dir(benches[0], a.json, a.maps, fs, refine=refine)
    m = r.metrics
    print_json({"albedo_psnr": m.albedo_psnr, "normal_err_deg": m.normal_err_deg, "relit_psnr": m.relit_psnr,
            "seconds": m.seconds})
    return 0


def _cmd_face_from_photo(a) -> int:
    from foundation.files import check_output_dir
    from foundation.imageio import read_photo
    from inverse.face import PhotoFitSettings, load_landmarks, photo_to_face

    s = settings_from(PhotoFitSettings, a)
    check_output_dir(a.out, "photo_face.json", "--out", replace=True)
    maps_fn = None
    if a.learned:
        from generative.face import load_face_models, photo_maps_fn

        maps_fn = photo_maps_fn(load_face_models(a.learned, a.variant))  # a bad run is named before any work
    image = read_photo(a.image)
    lm = load_landmarks(a.landmarks) if a.landmarks else None
    r = photo_to_face(image, a.out, s, landmarks=lm, maps_fn=maps_fn)
    print_json({"stages": r.stages, "landmark_reprojection_px": r.landmark_reprojection_px,
            "rerender_psnr_visible_face": r.rerender_psnr_visible_face,
            "visible_uv_fraction": r.visible_uv_fraction, "seconds": r.seconds})
    return 0


def _cmd_face_train_models(a) -> int:
    from foundation.pool import ray_shutdown
    from generative.face import (
        CompletionSettings,
        FaceDataSettings,
        FaceModelsSettings,
        SuperResSettings,
        train_face_models,
    )
    from generative.face import DecompSettings as FaceDecompSettings

    s = FaceModelsSettings(
        data=settings_from(FaceDataSettings, a),
        completion=settings_named(CompletionSettings, {"max_seconds": "--completion-seconds"},
                                  max_seconds=a.completion_seconds, seed=a.seed),
        decomposition=settings_named(FaceDecompSettings, {"max_seconds": "--decomp-seconds"},
                                     max_seconds=a.decomp_seconds, seed=a.seed),
        superres=settings_named(SuperResSettings, {"max_seconds": "--superres-seconds"},
                                max_seconds=a.superres_seconds, seed=a.seed),
        variants=tuple(a.variants))
    try:
        summary = train_face_models(a.out, s, pool_settings(a))
    finally:
        ray_shutdown()
    print_json({k: {"parameters": v["parameters"], "steps": v["training"]["steps"],
                "train_seconds": v["training"]["train_seconds"], "loss_last": v["training"]["loss_last"]}
            for k, v in summary.items()})
    return 0




def add(parser: argparse.ArgumentParser, wanted: str | None = None) -> None:
    add_subcommands(parser, "face_cmd", _SUBCOMMANDS, wanted)


def _add_make_benchmark(fm: argparse.ArgumentParser) -> None:
    from inverse.face import FaceBenchmarkSettings

    fm.add_argument("--scan", required=True, help="OBJ with texture coordinates and a map_Kd texture")
    out_opt(fm, "--out", marker="benchmark.json", required=True,
            help="benchmark folder to create (absent, empty, or an earlier benchmark)")
    opt(fm, FaceBenchmarkSettings, "uv_res")
    opt(fm, FaceBenchmarkSettings, "n_lights", "--lights", help="directional training lights")
    opt(fm, FaceBenchmarkSettings, "seed")
    opt(fm, FaceBenchmarkSettings, "heldout_hdris", "--hdri", metavar="HDRI",
         help="held-out relighting environments: bundled names or your own .exr files (copied into the benchmark); "
              "the training photos stay under directional lights unless --lighting hdri")
    opt(fm, FaceBenchmarkSettings, "observation_bsdf", choices=["ggx_uv", "principled"],
         help="BSDF the observations are rendered with (principled: a model the fit does not know)")
    opt(fm, FaceBenchmarkSettings, "lighting", choices=["directional", "hdri"],
         help="each observation under one directional light, or under a real HDRI at a seeded rotation")
    opt(fm, FaceBenchmarkSettings, "lighting_hdris", metavar="HDRI", help="environments of --lighting hdri")
    opt(fm, FaceBenchmarkSettings, "max_depth", help="path length of the observations (> 2: interreflection)")
    opt(fm, FaceBenchmarkSettings, "albedo_blur", type=float,
         help="rendered albedo blurred by this many texels at 256² (subsurface-like spread; the truth is not blurred)")
    fm.set_defaults(func=_cmd_face_make_benchmark)


def _add_fit(ff: argparse.ArgumentParser) -> None:
    from inverse.face import FaceFitSettings, RenderRefineSettings

    ff.add_argument("benchmark", nargs="+", help="folder(s) made by make-benchmark, or a folder of them")
    out_opt(ff, "--json", kind="file", default=None,
            help="metrics JSON of one benchmark (the checkpoint goes beside it)")
    out_opt(ff, "--out-dir", default=None, help="several benchmarks: DIR/NAME/fit.json and DIR/NAME/maps")
    out_opt(ff, "--maps", default=None, help="folder for the fitted maps (EXR + PNG)")
    opt(ff, FaceFitSettings, "fit_lights", help="treat lighting as unknown and fit it jointly")
    opt(ff, FaceFitSettings, "light_model", choices=["directional", "sh"],
        help="unknown lighting as one directional light + ambient per observation, or an environment in spherical "
             "harmonics per observation, occluded by the mesh (see docs/face.md)")
    opt(ff, FaceFitSettings, "sh_order", type=int)
    opt(ff, FaceFitSettings, "occlusion", "--no-occlusion", help="with --light-model sh: the environments reach every "
        "texel unoccluded (no ray-traced transfer)")
    opt(ff, FaceFitSettings, "grey_world", "--no-grey-world", help="with --light-model sh: leave the split of each "
        "colour channel between albedo and light to the fit (by default the lights average to white)")
    opt(ff, FaceFitSettings, "iterations", type=int, help="Adam steps per pyramid level")
    ff.add_argument("--refine-renders", type=int, default=0, metavar="N",
                    help=f"then refine N Adam steps through full camera renders (prb through ggx_uv; "
                         f"suggested {default_of(RenderRefineSettings, 'iterations')}; default: 0, off)")
    opt(ff, FaceFitSettings, "seed")
    pool_options(ff)
    ff.set_defaults(func=_cmd_face_fit)


def _add_from_photo(fp: argparse.ArgumentParser) -> None:
    from inverse.face import PhotoFitSettings

    fp.add_argument("image", help="image file, or 'astronaut' for scikit-image's photograph")
    out_opt(fp, "--out", marker="photo_face.json", required=True,
            help="output folder (absent, empty, or an earlier from-photo output)")
    fp.add_argument("--landmarks", default=None, help="468x3 landmarks (.npy/.json) instead of running mediapipe")
    opt(fp, PhotoFitSettings, "uv_res")
    opt(fp, PhotoFitSettings, "seed")
    fp.add_argument("--learned", default=None, metavar="RUN",
                    help="replace fill, delighting and template defaults by the learned stages of a "
                         "`face train-models` run (default: the optimisation baseline)")
    fp.add_argument("--variant", default=None, help="decomposition variant of the run (default: the run's first)")
    fp.set_defaults(func=_cmd_face_from_photo)


def _add_train_models(ft: argparse.ArgumentParser) -> None:
    from generative.face import CompletionSettings, FaceDataSettings, FaceModelsSettings, SuperResSettings
    from generative.face import DecompSettings as FaceDecompSettings

    out_opt(ft, "--out", required=True, help="run folder (absent, empty, or this command's earlier run)")
    for name in ("train_instances", "eval_instances", "spp", "seed"):
        opt(ft, FaceDataSettings, name)
    res = default_of(CompletionSettings, "res")  # the models' side: the data is that or twice it (super-resolution)
    opt(ft, FaceDataSettings, "uv_res", type=int, choices=[res, 2 * res],
        help=f"texels per side of the data's maps: {res} (the models' side) or {2 * res} (also trains the 2× upscaler)")
    opt(ft, FaceDataSettings, "layout", choices=["template", "scan"],
         help="UV layout of the maps: the face template's (what from-photo unwraps into) or the scans' own")
    opt(ft, CompletionSettings, "max_seconds", "--completion-seconds", dest="completion_seconds", type=float,
        help="training budget of the completion model")
    opt(ft, FaceDecompSettings, "max_seconds", "--decomp-seconds", dest="decomp_seconds", type=float,
        help="training budget of each decomposition variant")
    opt(ft, SuperResSettings, "max_seconds", "--superres-seconds", dest="superres_seconds", type=float,
        help="training budget of the upscaler")
    opt(ft, FaceModelsSettings, "variants", choices=["cross_attention", "shared", "independent"],
        help="decomposition variants to train; the first is the one from-photo uses")
    pool_options(ft)
    ft.set_defaults(func=_cmd_face_train_models)


_SUBCOMMANDS = {
    "make-benchmark": ("ground truth + Mitsuba observations from an OBJ scan with texture", _add_make_benchmark),
    "fit": ("fit UV maps to benchmarks and score them (resumes from a checkpoint)", _add_fit),
    "from-photo": ("one photograph -> relightable face (landmarks, unwrap, delight, relight)", _add_from_photo),
    "train-models": ("learned UV-space stages (seed 003 §2–§4): data from the training "
                         "scan, completion diffusion (the backbone), LoRA decomposition, 2× super-resolution (resumes)", _add_train_models),
}
