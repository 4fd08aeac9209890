"""`photoreal` command line: a thin layer over the library functions."""

from __future__ import annotations

import argparse
import json
import sys


def _cmd_render(a: argparse.Namespace) -> int:
    from .render import RenderSettings, render_file

    settings = RenderSettings(spp=a.spp, resolution=tuple(a.resolution) if a.resolution else None,
                              aovs=a.aovs, seed=a.seed)
    summary = render_file(a.scene, a.output, settings)
    print(json.dumps(summary))
    return 0


def _cmd_bench(a: argparse.Namespace) -> int:
    from .bench import PluginBenchSettings, bench_plugins, write_json

    if a.what == "plugins":
        s = PluginBenchSettings(resolution=a.resolution, spp=a.spp, repetitions=a.repetitions, rounds=a.rounds)
        result = bench_plugins(s)
        write_json(a.json, result)
        print(json.dumps({k: result[k] for k in ("ggx_uv_ms", "principled_ms", "ggx_uv_vs_principled",
                                                 "compile_s")}, indent=2))
        return 0
    if a.what == "morph":
        from pathlib import Path

        from .morph_bench import MorphBenchSettings, bench_morph

        result = bench_morph(MorphBenchSettings(), out_dir=Path(a.json).parent)
        write_json(a.json, result)
        print(json.dumps({k: result[k] for k in ("chamfer_input", "chamfer_morphed", "chamfer_reduction",
                                                 "psnr_heldout_input", "psnr_heldout_morphed", "spikes",
                                                 "s_per_iter_10k_4views_128", "s_per_iter_baseline",
                                                 "chosen_vertices")}, indent=2))
        return 0
    if a.what == "btf":
        from pathlib import Path

        from .btf_bench import BTFBenchSettings, bench_btf

        result = bench_btf(BTFBenchSettings(), out_dir=Path(a.json).parent)
        write_json(a.json, result)
        print(json.dumps({k: result[k] for k in ("psnr_universal_mean", "psnr_per_material_mean", "neural_btf_ms",
                                                 "principled_ms", "neural_btf_vs_principled", "mlp_evals_per_s_drjit",
                                                 "mlp_evals_per_s_torch", "chosen")}, indent=2))
        return 0
    if a.what == "face":
        from pathlib import Path

        from .face import FaceBenchSettings, bench_face

        result = bench_face(FaceBenchSettings(scan=a.scan), out_dir=Path(a.json).parent)
        write_json(a.json, result)
        print(json.dumps({k: result[k] for k in ("albedo_psnr", "normal_err_deg", "roughness_mae", "specular_mae",
                                                 "relit_psnr", "relit_flip", "fit_seconds_256", "chosen_uv_res")},
                         indent=2))
        return 0
    if a.what == "gan":
        return _cmd_bench_gan(a)
    raise SystemExit(f"unknown benchmark {a.what!r}")


def _cmd_face(a: argparse.Namespace) -> int:
    if a.face_cmd == "make-benchmark":
        from inverse.face_data import FaceBenchmarkSettings, make_benchmark

        out = make_benchmark(a.scan, a.out, FaceBenchmarkSettings(uv_res=a.uv_res, n_lights=a.lights, seed=a.seed))
        print(f"benchmark: {out}")
        return 0
    if a.face_cmd == "fit":
        from inverse.face_fit import FaceFitSettings

        from .face import fit_benchmark_dir

        fs = FaceFitSettings(fit_lights=a.fit_lights, seed=a.seed,
                             iterations=tuple(a.iterations) if a.iterations else FaceFitSettings().iterations)
        from inverse.face_fit import RenderRefineSettings

        refine = RenderRefineSettings(iterations=a.refine_renders, seed=a.seed) if a.refine_renders else None
        m = fit_benchmark_dir(a.benchmark, a.json, a.maps, fs, refine=refine)
        print(json.dumps({k: m[k] for k in ("albedo_psnr", "normal_err_deg", "relit_psnr", "seconds")}, indent=2))
        return 0
    if a.face_cmd == "from-photo":
        from inverse.face_photo import PhotoFitSettings, load_landmarks, photo_to_face

        from .imageio import read_photo

        image = read_photo(a.image)
        lm = load_landmarks(a.landmarks) if a.landmarks else None
        r = photo_to_face(image, a.out, PhotoFitSettings(uv_res=a.uv_res, seed=a.seed), landmarks=lm)
        print(json.dumps({k: r[k] for k in ("landmark_reprojection_px", "rerender_psnr_visible_face",
                                            "visible_uv_fraction", "seconds")}, indent=2))
        return 0
    raise SystemExit(f"unknown face command {a.face_cmd!r}")


def _cmd_morph(a: argparse.Namespace) -> int:
    if a.morph_cmd == "make-benchmark":
        from inverse.morph_data import MorphBenchmarkSettings, make_morph_benchmark

        out = make_morph_benchmark(a.mesh, a.out, MorphBenchmarkSettings(n_views=a.views, resolution=a.resolution,
                                                                        spp=a.spp, seed=a.seed))
        print(f"benchmark: {out}")
        return 0
    if a.morph_cmd == "run":
        from pathlib import Path

        from inverse.morph import MorphSettings, run_gcn_morph, run_morph
        from inverse.morph_data import load_morph_benchmark

        from .bench import write_json

        bench = load_morph_benchmark(a.benchmark)
        s = MorphSettings(iterations=a.iterations, views_per_step=a.views_per_step, mode=a.mode,
                          parameterisation="plain" if a.plain_adam else "large_steps", lambda_=a.lambda_,
                          target_vertices=a.target_vertices, resolution=a.resolution, seed=a.seed,
                          forbid_flips=a.forbid_flips, repair_flips=not a.no_repair,
                          min_vertices=a.min_vertices or None, planarity_weight=a.planarity_weight)
        out = Path(a.out) if a.out else Path(a.benchmark) / "morph"
        m = run_gcn_morph(bench, out, s) if a.gcn else run_morph(bench, out, s)
        if a.json:
            write_json(a.json, m)
        print(json.dumps({k: m[k] for k in ("chamfer_input", "chamfer_morphed", "psnr_heldout_input",
                                            "psnr_heldout_morphed", "spikes", "seconds")}, indent=2))
        return 0
    raise SystemExit(f"unknown morph command {a.morph_cmd!r}")


def _cmd_btf(a: argparse.Namespace) -> int:
    from pathlib import Path

    from .bench import write_json

    if a.btf_cmd == "render-data":
        from inverse.btf_data import FAMILIES, BTFRenderSettings, render_dataset

        fams = tuple(a.families) if a.families else FAMILIES
        s = BTFRenderSettings(tex_res=a.tex_res, slices=a.slices, spp=a.spp, max_depth=a.max_depth, seed=a.seed)
        paths = render_dataset(a.out, families=fams, per_family=a.per_family, settings=s, base_seed=a.seed)
        print(json.dumps({"materials": len(paths), "out": str(a.out)}))
        return 0
    from inverse.btf_data import load_btf, load_dataset
    from inverse.btf_fit import OptimSettings, fit_material, fit_settings, heldout_psnr, split_slices, train_basis
    from mi_plugins.neural_basis import BasisConfig, load_basis, save_basis, save_material

    if a.btf_cmd == "train-basis":
        mats = load_dataset(a.data)
        cfg = BasisConfig(channels=a.channels, width=a.width, depth=a.depth)
        s = OptimSettings(iterations=a.iterations, batch=a.batch, seed=a.seed)
        ck = a.checkpoint or str(Path(a.out).with_suffix(".ckpt.npz"))
        basis, hist = train_basis(mats, cfg, s, checkpoint=ck)
        save_basis(a.out, basis)
        print(json.dumps({"basis": str(a.out), "materials": len(mats), "final_l1": hist[-1]["l1"],
                          "seconds": hist[-1]["seconds"], "checkpoint": ck}))
        return 0
    if a.btf_cmd == "fit":
        basis = load_basis(a.basis)
        data = load_btf(a.btf)
        fit, held = split_slices(data.values.shape[0], a.heldout_fraction)
        s = fit_settings(a.iterations, batch=a.batch, seed=a.seed, tex_res=a.tex_res)
        ck = a.checkpoint or str(Path(a.out).with_suffix(".ckpt.npz"))
        mat, hist = fit_material(basis, data, fit, s, checkpoint=ck)
        mat.meta["psnr_heldout"] = heldout_psnr(basis, mat, data, held)
        save_material(a.out, mat)
        m = {"material": str(a.out), "btf": str(a.btf), "psnr_heldout": mat.meta["psnr_heldout"],
             "heldout_slices": len(held), "final_l1": hist[-1]["l1"], "seconds": hist[-1]["seconds"]}
        if a.json:
            write_json(a.json, m)
        print(json.dumps(m))
        return 0
    raise SystemExit(f"unknown btf command {a.btf_cmd!r}")


def _cmd_bench_gan(a: argparse.Namespace) -> int:
    from dataclasses import replace
    from pathlib import Path

    from .bench import write_json
    from .gan_bench import GanBenchSettings, bench_gan

    s = GanBenchSettings()
    if a.seconds_per_model is not None:
        t = a.seconds_per_model  # the other budgets keep their default proportions
        s = replace(s, seconds_per_model=t, joint_seconds=1.5 * t, cyclegan_seconds=3 * t, finetune_seconds=0.75 * t)
    result = bench_gan(s, out_dir=Path(a.json).parent)
    write_json(a.json, result)
    print(json.dumps({k: result[k] for k in ("heldout", "train_seconds", "infer_ms_per_image", "ordering")}, indent=2))
    return 0


def _cmd_gan(a: argparse.Namespace) -> int:
    from pathlib import Path

    from generative.gan_data import load_paired_views
    from generative.gan_train import (GanTrainSettings, JointSettings, evaluate_model, load_trained, train_gan,
                                      train_joint)
    from inverse.morph_data import load_morph_benchmark

    from .bench import write_json

    bench = load_morph_benchmark(a.benchmark)
    morph = Path(a.morph) if a.morph else Path(a.benchmark) / "morph"
    data = load_paired_views(bench, morph)
    if a.gan_cmd == "train":
        gs = GanTrainSettings(model="morph_gan" if a.model == "joint" else a.model, steps=a.steps,
                              max_seconds=a.seconds, batch=a.batch, crop=a.crop, ngf=a.ngf, ndf=a.ngf, seed=a.seed,
                              residual=not a.paper_head, val_every=0 if a.init_from else 6,
                              init_from=None if a.model == "joint" else a.init_from)
        if a.model == "joint":
            # fine-tuning a finished Morph-GAN jointly starts from the morph run's mesh as well
            m = train_joint(bench, data, a.out, JointSettings(
                steps=a.steps, max_seconds=a.seconds, gan=gs, seed=a.seed, init_from=a.init_from,
                init_mesh=str(morph / "morphed.ply") if a.init_from else None))
        else:
            m = train_gan(data, a.out, gs)
        keys = ("mse", "one_minus_ssim", "flip", "psnr", "train_seconds", "steps", "infer_ms_per_image")
        if a.json:
            write_json(a.json, m)
        print(json.dumps({k: m[k] for k in keys}, indent=2))
        return 0
    if a.gan_cmd == "eval":
        model, _ = load_trained(a.run)
        m = evaluate_model(model, data)
        if a.json:
            write_json(a.json, m)
        print(json.dumps(m, indent=2))
        return 0
    raise SystemExit(f"unknown gan command {a.gan_cmd!r}")


def _add_gan_parser(sub) -> None:
    g = sub.add_parser("gan", help="GAN refinement of renders: pix2pix, CycleGAN, Morph-GAN, joint (REAL-DIBS §3, §5)")
    gsub = g.add_subparsers(dest="gan_cmd", required=True)
    gt = gsub.add_parser("train", help="train one model on a morph benchmark + morph run (resumes from OUT)")
    gt.add_argument("benchmark", help="folder made by `photoreal morph make-benchmark`")
    gt.add_argument("--morph", default=None, help="morph run folder with morphed.ply (default BENCHMARK/morph)")
    gt.add_argument("--model", choices=["pix2pix", "cyclegan", "morph_gan_partial", "morph_gan", "joint"],
                    default="morph_gan")
    gt.add_argument("--out", required=True, help="training folder (checkpoint.pt, metrics.json)")
    gt.add_argument("--steps", type=int, default=5000)
    gt.add_argument("--seconds", type=float, default=120.0, help="wall-time budget (summed over resumes)")
    gt.add_argument("--batch", type=int, default=4)
    gt.add_argument("--crop", type=int, default=64)
    gt.add_argument("--ngf", type=int, default=16, help="generator and discriminator width")
    gt.add_argument("--init-from", default=None,
                    help="fine-tune a finished run folder of the same model (joint: of morph_gan, + the morphed mesh)")
    gt.add_argument("--paper-head", action="store_true",
                    help="generator outputs tanh directly (papers' head) instead of input + tanh correction")
    gt.add_argument("--json", default=None)
    gt.add_argument("--seed", type=int, default=0)
    ge = gsub.add_parser("eval", help="held-out metrics of a trained model")
    ge.add_argument("benchmark")
    ge.add_argument("--morph", default=None, help="morph run folder (default BENCHMARK/morph)")
    ge.add_argument("--run", required=True, help="training folder of `gan train`")
    ge.add_argument("--json", default=None)
    g.set_defaults(func=_cmd_gan)


def _cmd_demo(a: argparse.Namespace) -> int:
    from .demo import DemoSettings, run_demo

    index = run_demo(a.out, DemoSettings(resolution=a.resolution, spp=a.spp, seed=a.seed, face=not a.no_face,
                                         face_uv_res=a.face_uv_res, morph_iterations=a.morph_iterations,
                                         btf=not a.no_btf),
                     with_bench=not a.no_bench)
    print(f"report: {index}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="photoreal", description=__doc__)
    sub = p.add_subparsers(dest="command", required=True)

    r = sub.add_parser("render", help="render a Mitsuba XML scene (our plugins register themselves)")
    r.add_argument("scene", help="scene .xml file")
    r.add_argument("-o", "--output", required=True, help="output .exr (a .png preview is written beside it)")
    r.add_argument("--spp", type=int, default=None, help="samples per pixel (default: the scene's)")
    r.add_argument("--resolution", type=int, nargs=2, metavar=("W", "H"), default=None)
    r.add_argument("--aovs", action="store_true",
                   help="render with the 'intrinsic' integrator: albedo, irradiance, specular, normal, depth, uv, position layers")
    r.add_argument("--seed", type=int, default=0)
    r.set_defaults(func=_cmd_render)

    b = sub.add_parser("bench", help="benchmarks writing JSON")
    b.add_argument("what", choices=["plugins", "face", "morph", "btf", "gan"])
    b.add_argument("--scan", default="josie", help="face bench: josie, paul, or an OBJ path")
    b.add_argument("--json", required=True, help="output JSON path")
    b.add_argument("--resolution", type=int, default=256)
    b.add_argument("--spp", type=int, default=64)
    b.add_argument("--repetitions", type=int, default=5)
    b.add_argument("--rounds", type=int, default=2)
    b.add_argument("--seconds-per-model", type=float, default=None, help="gan bench: training budget per GAN")
    b.set_defaults(func=_cmd_bench)

    f = sub.add_parser("face", help="face material fitting in UV space (seed 003)")
    fsub = f.add_subparsers(dest="face_cmd", required=True)
    fm = fsub.add_parser("make-benchmark", help="ground truth + Mitsuba observations from an OBJ scan with texture")
    fm.add_argument("--scan", required=True, help="OBJ with texture coordinates and a map_Kd texture")
    fm.add_argument("--out", required=True, help="benchmark folder to create")
    fm.add_argument("--uv-res", type=int, default=256)
    fm.add_argument("--lights", type=int, default=6)
    fm.add_argument("--seed", type=int, default=0)
    ff = fsub.add_parser("fit", help="fit UV maps to a benchmark and score them")
    ff.add_argument("benchmark", help="folder made by make-benchmark")
    ff.add_argument("--json", required=True, help="metrics JSON")
    ff.add_argument("--maps", default=None, help="folder for the fitted maps (EXR + PNG)")
    ff.add_argument("--fit-lights", action="store_true", help="treat lighting as unknown and fit it jointly")
    ff.add_argument("--iterations", type=int, nargs="+", default=None, help="Adam steps per pyramid level")
    ff.add_argument("--refine-renders", type=int, default=0, metavar="N",
                    help="then refine N Adam steps through full camera renders (prb through ggx_uv)")
    ff.add_argument("--seed", type=int, default=0)
    fp = fsub.add_parser("from-photo", help="one photograph -> relightable face (landmarks, unwrap, delight, relight)")
    fp.add_argument("image", help="image file, or 'astronaut' for scikit-image's photograph")
    fp.add_argument("--out", required=True)
    fp.add_argument("--landmarks", default=None, help="468x3 landmarks (.npy/.json) instead of running mediapipe")
    fp.add_argument("--uv-res", type=int, default=256)
    fp.add_argument("--seed", type=int, default=0)
    f.set_defaults(func=_cmd_face)

    m = sub.add_parser("morph", help="geometry morphing of coarse meshes against photos (REAL-DIBS §4)")
    msub = m.add_subparsers(dest="morph_cmd", required=True)
    mm = msub.add_parser("make-benchmark", help="ground truth + photos + degraded reconstruction")
    mm.add_argument("--mesh", required=True, help="OBJ/PLY/OFF mesh, or 'village'")
    mm.add_argument("--out", required=True)
    mm.add_argument("--views", type=int, default=32)
    mm.add_argument("--resolution", type=int, default=128)
    mm.add_argument("--spp", type=int, default=64)
    mm.add_argument("--seed", type=int, default=0)
    mr = msub.add_parser("run", help="morph the benchmark's coarse mesh (resumes from its checkpoint)")
    mr.add_argument("benchmark")
    mr.add_argument("--out", default=None, help="output folder (default BENCHMARK/morph)")
    mr.add_argument("--json", default=None, help="metrics JSON")
    mr.add_argument("--iterations", type=int, default=300)
    mr.add_argument("--views-per-step", type=int, default=3)
    mr.add_argument("--mode", choices=["lit", "unlit"], default="lit")
    mr.add_argument("--lambda", dest="lambda_", type=float, default=2.0, help="large-steps λ")
    mr.add_argument("--plain-adam", action="store_true", help="per-vertex Adam instead of large steps")
    mr.add_argument("--target-vertices", type=int, default=None)
    mr.add_argument("--resolution", type=int, default=None)
    mr.add_argument("--gcn", action="store_true", help="shape-aware GCN trained through the renderer")
    mr.add_argument("--forbid-flips", action="store_true",
                    help="undo a step at vertices of triangles it would flip (0 inverted, less accurate)")
    mr.add_argument("--min-vertices", type=int, default=10_000,
                    help="remesh a coarser input up to about this many vertices (0: keep its count)")
    mr.add_argument("--planarity-weight", type=float, default=None,
                    help="edge-preserving planarity prior (0: image loss only; default auto: on for scenes whose "
                         "largest plane holds ≥ 20%% of the area, e.g. a ground plane)")
    mr.add_argument("--no-repair", action="store_true",
                    help="keep folds: skip the final unfolding of triangles flipped w.r.t. the start (reported)")
    mr.add_argument("--seed", type=int, default=0)
    m.set_defaults(func=_cmd_morph)

    t = sub.add_parser("btf", help="universal neural BTF: data, basis training, per-material fitting (seed 002)")
    tsub = t.add_subparsers(dest="btf_cmd", required=True)
    tr = tsub.add_parser("render-data", help="render BTFs from procedural/photo SVBRDFs (resumes: skips finished files)")
    tr.add_argument("--out", required=True, help="dataset folder")
    tr.add_argument("--families", nargs="+", default=None, help="subset of the material families")
    tr.add_argument("--per-family", type=int, default=4)
    tr.add_argument("--tex-res", type=int, default=64)
    tr.add_argument("--slices", type=int, default=64)
    tr.add_argument("--spp", type=int, default=16)
    tr.add_argument("--max-depth", type=int, default=3)
    tr.add_argument("--seed", type=int, default=0)
    tb = tsub.add_parser("train-basis", help="train the universal MLPs on a dataset (resumes from --checkpoint)")
    tb.add_argument("data", help="folder made by render-data")
    tb.add_argument("--out", required=True, help="basis .npz")
    tb.add_argument("--iterations", type=int, default=2000)
    tb.add_argument("--batch", type=int, default=1 << 15)
    tb.add_argument("--width", type=int, default=64)
    tb.add_argument("--depth", type=int, default=4)
    tb.add_argument("--channels", type=int, default=8)
    tb.add_argument("--checkpoint", default=None, help="default: OUT with .ckpt.npz")
    tb.add_argument("--seed", type=int, default=0)
    tf = tsub.add_parser("fit", help="fit one material's feature textures with the basis frozen (resumes)")
    tf.add_argument("btf", help="a BTF .npz from render-data")
    tf.add_argument("--basis", required=True)
    tf.add_argument("--out", required=True, help="material .npz for the neural_btf plugin")
    tf.add_argument("--iterations", type=int, default=600)
    tf.add_argument("--batch", type=int, default=1 << 15)
    tf.add_argument("--tex-res", type=int, default=0, help="feature texture resolution (0 = the BTF's)")
    tf.add_argument("--heldout-fraction", type=float, default=0.25, help="slices held out for the PSNR")
    tf.add_argument("--checkpoint", default=None)
    tf.add_argument("--json", default=None)
    tf.add_argument("--seed", type=int, default=0)
    t.set_defaults(func=_cmd_btf)

    _add_gan_parser(sub)

    d = sub.add_parser("demo", help="render the built-in scenes and write an HTML report")
    d.add_argument("--out", default="out/demo")
    d.add_argument("--resolution", type=int, default=256)
    d.add_argument("--spp", type=int, default=64)
    d.add_argument("--seed", type=int, default=0)
    d.add_argument("--no-bench", action="store_true", help="skip the plugin speed section")
    d.add_argument("--no-face", action="store_true", help="skip the face fitting section")
    d.add_argument("--face-uv-res", type=int, default=256)
    d.add_argument("--morph-iterations", type=int, default=100, help="0 skips the morphing section")
    d.add_argument("--no-btf", action="store_true", help="skip the neural materials section")
    d.set_defaults(func=_cmd_demo)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from .imageio import ImageIOError
    from .render import SceneError
    from inverse.uv_bake import MeshError

    try:
        return args.func(args)
    except (SceneError, ImageIOError, ValueError, FileNotFoundError, FloatingPointError, MeshError, ImportError) as exc:
        print(f"photoreal: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("photoreal: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
