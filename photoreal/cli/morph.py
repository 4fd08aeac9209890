"""`photoreal morph …`: morph benchmarks, morph runs, where a mesh lies, saturated pixels."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..options import opt, settings_from
from .common import add_subcommands, benchmark_dirs, check_out_dir, out_opt, pool_options, print_json, run_batch, usage

HELP = "geometry morphing of coarse meshes against photos (REAL-DIBS §4)"


def _cmd_morph_make_benchmark(a) -> int:
    from foundation.files import check_output_dir
    from inverse.morph import MorphBenchmarkSettings, make_morph_benchmark

    s = settings_from(MorphBenchmarkSettings, a)
    check_output_dir(a.out, "morph_benchmark.json", "--out", replace=True)
    print(f"benchmark: {make_morph_benchmark(a.mesh, a.out, s)}")
    return 0


def _cmd_morph_run(a) -> int:
    from foundation.files import check_output_file, write_json
    from foundation.pool import Item
    from foundation.records import to_json
    from inverse.morph import MorphSettings, load_morph_benchmark, load_morph_input, run_gcn_morph, run_morph

    s = settings_from(MorphSettings, a, parameterisation="plain" if a.plain_adam else "large_steps",
                  repair_flips=not a.no_repair, min_vertices=a.min_vertices or None)
    benches = benchmark_dirs(a.benchmark, "morph_benchmark.json")
    captures = [b for b in benches if (b / "capture.json").is_file()]
    if captures and len(benches) > 1:
        raise usage(f"{captures[0]}: a capture is morphed on its own (one CAPTURE per `morph run`)")
    if len(benches) > 1:
        if a.out or a.json:
            raise usage("--out and --json name one run; several benchmarks go to --out-dir (or BENCHMARK/morph)")
        for b in benches:
            load_morph_benchmark(b)  # a missing or damaged benchmark is named before any work
        base = check_out_dir(a.out_dir) if a.out_dir else None
        names = [b.name for b in benches]
        if base is not None and len(set(names)) != len(names):
            raise usage("two benchmarks share a folder name; their runs would overwrite each other in --out-dir")
        items = []
        for b in benches:
            out = base / b.name if base is not None else b / "morph"
            key = b.name if base is not None else str(b)
            items.append(Item(key, "inverse.morph:run_item", (str(b), str(out), s, a.gcn), {"json_path": None},
                              output=str(out / "metrics.json")))
        return run_batch(items, a, "morph runs")
    if a.out_dir:
        raise usage("--out-dir is for several benchmarks; one run goes to --out (default BENCHMARK/morph)")
    if a.json:
        check_output_file(a.json, "--json")
    out = Path(a.out) if a.out else benches[0] / "morph"
    if out.exists() and not out.is_dir():
        raise usage(f"--out {out}: is a file, expected a folder")
    if captures and a.gcn:
        raise usage("--gcn: the GCN variant morphs benchmarks only; a capture runs the default morph")
    bench = load_morph_input(benches[0], out / ".capture_input")
    m = run_gcn_morph(bench, out, s) if a.gcn else run_morph(bench, out, s)
    if a.json:
        write_json(a.json, to_json(m))
    summary = {"psnr_heldout_input": m.psnr_heldout_input, "psnr_heldout_morphed": m.psnr_heldout_morphed,
               "flip_heldout_input": m.heldout_input.flip, "flip_heldout_morphed": m.heldout_morphed.flip,
               "spikes": m.spikes, "inverted_triangles": m.inverted_triangles, "seconds": m.seconds}
    if not captures:
        summary = {"chamfer_input": m.chamfer_input, "chamfer_morphed": m.chamfer_morphed, **summary}
    elif m.photo_fit is not None:
        summary["mode"] = m.photo_fit.mode
        summary["masks"] = m.photo_fit.masks
        if m.photo_fit.camera_movement:
            summary["cameras_moved_deg_max"] = m.photo_fit.camera_movement["rotation_deg_max"]
            summary["cameras_moved_shift_max"] = m.photo_fit.camera_movement["shift_rel_max"]
        if m.photo_fit.exposure_slope:  # the photos' EXIF exposures differ: held-out gains follow them
            summary["exposure_slope"] = m.photo_fit.exposure_slope
    print_json(summary)
    return 0


def _cmd_morph_saturation(a) -> int:
    from foundation.files import check_output_file, write_json
    from inverse.morph import load_morph_benchmark, saturated_silhouette

    if a.json:
        check_output_file(a.json, "--json")
    if not a.factor > 0:
        raise usage(f"--factor must be > 0, got {a.factor}")
    benches = [load_morph_benchmark(b) for b in a.benchmarks]  # every folder checked before any render
    out = {str(b.path): saturated_silhouette(b, a.factor) for b in benches}
    if a.json:
        write_json(a.json, out)
    print_json(out)
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
            raise usage(f"{item}: no such mesh file" + (" (a folder without morphed.ply)" if p.is_dir() else ""))
        name = (p.name if p.is_dir() else p.parent.name if p.stem == "morphed" else p.stem) or "result"
        base, k = name, 2
        while name in results or name == "input":
            name, k = f"{base}_{k}", k + 1
        results[name] = ply
    if a.json:
        check_output_file(a.json, "--json")
    if a.band is not None and not a.band > 0:
        raise usage(f"--band must be > 0, got {a.band}")
    if Path(a.out).exists() and not Path(a.out).is_dir():
        raise usage(f"--out {a.out}: is a file, expected a folder")
    r = benchmark_errors(bench, results, Path(a.out), band=a.band)
    if a.json:
        write_json(a.json, to_json(r))
    for e in r.meshes:
        print_json({"mesh": e.name, "chamfer": e.chamfer, "to_truth": e.to_truth, "from_truth": e.from_truth,
                "from_truth_border": e.from_truth_border, "from_truth_interior": e.from_truth_interior,
                "input_error_left": e.input_error_left, "new_error_rms": e.new_error_rms,
                "input_error_left_by_scale": None if e.input_error_left_by_scale is None else
                {b.band: None if b.slope is None else round(b.slope, 3) for b in e.input_error_left_by_scale},
                "facing_area": e.facing_area, "facing_area_by_views": e.facing_area_by_views,
                "unseen_area": e.unseen_area})
    print(f"maps: {a.out}/errors_*.ply, {a.out}/facing_*.ply; figures: {r.files['figure']}, {r.files['facing_figure']}")
    return 0




def add(parser: argparse.ArgumentParser, wanted: str | None = None) -> None:
    add_subcommands(parser, "morph_cmd", _SUBCOMMANDS, wanted)


def _add_make_benchmark(mm: argparse.ArgumentParser) -> None:
    from inverse.morph import TRUTH_NORMALS, MorphBenchmarkSettings

    mm.add_argument("--mesh", required=True, help="OBJ/PLY/OFF mesh, or 'village'")
    out_opt(mm, "--out", marker="morph_benchmark.json", required=True,
            help="benchmark folder (absent, empty, or an earlier benchmark)")
    opt(mm, MorphBenchmarkSettings, "n_views", "--views", help="photos on the drone orbit (every 4th is held out)")
    opt(mm, MorphBenchmarkSettings, "resolution")
    opt(mm, MorphBenchmarkSettings, "spp")
    opt(mm, MorphBenchmarkSettings, "seed")
    opt(mm, MorphBenchmarkSettings, "hdri", help="lighting of the photos (and of the morph's lit renders): a bundled "
                                                  "HDRI's name or your own .exr, copied into the benchmark")
    opt(mm, MorphBenchmarkSettings, "elevation_deg", "--elevation", type=float, nargs=2, metavar=("LOW", "HIGH"),
         help="camera elevation range in degrees (default: 25 45 for the village, -15 65 for an object)")
    opt(mm, MorphBenchmarkSettings, "framing_margin",
         help="objects: free border around the bounding sphere, fraction of the half-image")
    opt(mm, MorphBenchmarkSettings, "truth_normals", choices=list(TRUTH_NORMALS),
         help="shading of the photographed truth: interpolated vertex normals (smooth) or each triangle flat, the "
              "geometry the Chamfer measures (they disagree for truths with few vertices)")
    opt(mm, MorphBenchmarkSettings, "photo_max_depth",
         help="path length of the photos; 2 = direct light only, what the morph renders (no interreflections to "
              "explain)")
    mm.set_defaults(func=_cmd_morph_make_benchmark)


def _add_run(mr: argparse.ArgumentParser) -> None:
    from inverse.morph import PLANARITY_WHERE, PRIOR_TIES, MorphSettings

    mr.add_argument("benchmark", nargs="+", help="benchmark folder(s), or a folder of them, or one capture folder "
                    "(`photoreal capture import|sfm`: its light and exposures are fitted, its cameras with "
                    "--refine-cameras auto)")
    out_opt(mr, "--out", default=None, help="output folder of one benchmark (default BENCHMARK/morph)")
    out_opt(mr, "--out-dir", default=None, help="several benchmarks: DIR/NAME (default: each BENCHMARK/morph)")
    out_opt(mr, "--json", kind="file", default=None, help="metrics JSON")
    opt(mr, MorphSettings, "iterations")
    opt(mr, MorphSettings, "views_per_step")
    opt(mr, MorphSettings, "mode", choices=["lit", "unlit"])
    opt(mr, MorphSettings, "lambda_", "--lambda", help="large-steps λ")
    opt(mr, MorphSettings, "lr", type=float,
         help="position learning rate, × the scene size / 10 (0: positions frozen, a colour-only fit)")
    mr.add_argument("--plain-adam", action="store_true", help="per-vertex Adam instead of large steps")
    opt(mr, MorphSettings, "target_vertices", type=int,
         help="remesh the input to about this many vertices (default: see --min-vertices)")
    opt(mr, MorphSettings, "resolution", type=int, help="working resolution (default: the benchmark's; a capture's "
        "photos are fitted 128 pixels across, their aspect kept)")
    opt(mr, MorphSettings, "refine_cameras", choices=["auto", "on", "off"],
        help="refine each training photo's camera pose with the mesh, pulled toward the imported pose; auto: where the "
             "cameras were estimated (captures); off by default (on the vendored captures it lost on held-out photos)")
    opt(mr, MorphSettings, "refine_focal", help="with refined cameras, also refine one focal length shared by all "
        "photos (capture cameras)")
    opt(mr, MorphSettings, "lr_camera", help="step of the camera corrections (radians; × scene size for shifts)")
    opt(mr, MorphSettings, "camera_weight", help="weight of the pull toward the imported poses")
    opt(mr, MorphSettings, "exposure", choices=["auto", "on", "off"],
        help="an RGB gain per photo (exposure, white balance); auto: on for captures")
    opt(mr, MorphSettings, "lr_exposure", help="step of the per-photo log-gains")
    opt(mr, MorphSettings, "env_resolution", help="captures: height of the fitted environment map (width twice it)")
    opt(mr, MorphSettings, "lr_env", help="step of the fitted environment's texels")
    opt(mr, MorphSettings, "flash", choices=["auto", "on", "off"],
        help="captures, lit mode: a light at the camera, its intensity fitted; auto: for the photos whose EXIF says "
             "the flash fired")
    opt(mr, MorphSettings, "lr_flash", help="step of the flash's log-intensity")
    opt(mr, MorphSettings, "mode_select", "--no-mode-select",
        help="captures: keep --mode as given (by default a lit run's unlit twin is asked of the photos)")
    mr.add_argument("--gcn", action="store_true", help="shape-aware GCN trained through the renderer")
    opt(mr, MorphSettings, "forbid_flips",
         help="undo a step at vertices of triangles it would flip (0 inverted, less accurate)")
    opt(mr, MorphSettings, "min_vertices", type=int,
         help="remesh a coarser input up to about this many vertices (0: keep its count)")
    opt(mr, MorphSettings, "planarity_weight", type=float,
         help="edge-preserving planarity prior (0: image loss only; default auto: on for scenes whose "
              "largest plane holds ≥ 26%% of the area, e.g. a ground plane)")
    opt(mr, MorphSettings, "colour_prior_weight", type=float,
         help="colour prior: a piecewise-smooth albedo, so that the geometry, not the vertex colour, explains "
              "shading (0: off; default auto: 0.1 where the input's own colours are smooth, off for textured ones, "
              "and with --lambda-select the validation photos confirm it against the winner without it)")
    mr.add_argument("--no-repair", action="store_true",
                    help="keep folds: skip the final unfolding of triangles flipped w.r.t. the start (reported)")
    opt(mr, MorphSettings, "border_turn_deg", type=float,
         help="after the flip repair, iron back into line the open border's triangles (border and 1-ring) turned more "
              "than this many degrees from the start: a curl of an open scan's border (reported; 0: off)")
    opt(mr, MorphSettings, "validation_views",
         help="training photos kept out of the fit to watch convergence (0: fit all)")
    opt(mr, MorphSettings, "early_stop", "--no-early-stop",
         help="run all --iterations (default: stop when the validation loss stops improving; --iterations caps it)")
    opt(mr, MorphSettings, "lambda_start", type=float,
         help="large-steps λ at the start, falling geometrically to --lambda over the first 30%% of the iterations "
              "(e.g. 25: steadier first steps on thin parts; setting it turns --lambda-select off)")
    opt(mr, MorphSettings, "lambda_select", type=float,
         help="λ start values tried side by side to the end of that warm-up; the one the validation photos prefer "
              "continues (a value ≤ --lambda: constant λ; one value: no choice)")
    opt(mr, MorphSettings, "planarity_select", type=float, nargs="*",
         help="planarity-prior weights that join that choice as candidates at constant λ when the input has no "
              "dominant plane (the option alone: the plane rule decides; --planarity-weight turns the choice off)")
    opt(mr, MorphSettings, "planarity_where", choices=list(PLANARITY_WHERE),
         help="edges the planarity prior acts on: all; seen (beside a triangle a fitted training photo sees); thick "
              "(between triangles of parts at least --planarity-min-thickness thick)")
    opt(mr, MorphSettings, "planarity_select_where", choices=list(PLANARITY_WHERE),
         help="the same for the --planarity-select candidates")
    opt(mr, MorphSettings, "planarity_min_thickness", type=float,
         help="with 'thick': the least thickness of a part the prior acts on (ray cast along the start's inward "
              "normals), × the start's largest extent")
    opt(mr, MorphSettings, "prior_margin", type=float,
         help="a prior those choices ask the photos about (planarity candidate, colour prior) is kept only where its "
              "validation L1 is this fraction below the best run without it (0: the lower L1 wins)")
    opt(mr, MorphSettings, "prior_ties", choices=list(PRIOR_TIES),
         help="within that margin: keep the prior (the run without must beat it by the margin) or drop it (the "
              "prior must win by the margin)")
    opt(mr, MorphSettings, "adam_quantile", type=float,
         help="large steps: the quantile of Adam's second moments that scales every step (1: their maximum, "
              "uniform Adam; lower: the silhouettes' noisy gradient no longer sets the step of the whole surface)")
    opt(mr, MorphSettings, "indirect_every", type=int,
         help="re-estimate the light the direct-only renders miss (path traced at the photos' depth minus direct "
              "light, per photo) every N iterations and add it to the renders (0: off)")
    opt(mr, MorphSettings, "indirect_spp", type=int, help="samples per pixel of each render of that estimate")
    opt(mr, MorphSettings, "indirect_reference", choices=["direct", "depth2"],
         help="what that estimate subtracts: the direct integrator, or the path tracer at depth 2 with the same seed "
              "(the first bounce cancels: 3× less noise at the same spp)")
    opt(mr, MorphSettings, "indirect_downsample", type=int,
         help="render that estimate at 1/N of the fitting resolution and upsample it bilinearly (the indirect light "
              "varies slowly: at 2 less error than at 1 for a third of the time; 1: full resolution)")
    opt(mr, MorphSettings, "boundary_spp", type=int,
         help="samples per pixel of the silhouettes' gradient (the image and the rest of its gradient take 4)")
    opt(mr, MorphSettings, "colour_lambda", type=float,
         help="large-steps λ for the vertex colours' steps (0: plain per-vertex steps): smooth colour changes come "
              "fast, bump-sized ones slowly, so that the geometry explains the bumps' shading (default 0: off)")
    opt(mr, MorphSettings, "light_select_every", type=int,
         help="where both of those are off, the selection's winner also runs with the light estimate every N "
              "iterations and colour large steps to the selection point, and the validation photos (each run "
              "measured after a fresh light estimate on its own mesh) decide by --prior-margin (0: no such "
              "candidate)")
    opt(mr, MorphSettings, "light_select_colour_lambda", type=float,
         help="colour λ of that candidate")
    opt(mr, MorphSettings, "step_select_quantile", type=float,
         help="where --adam-quantile is 1, the winner of the λ and colour choices also runs with this quantile step "
              "and --step-select-lr to the selection point, and the validation photos decide by --prior-margin "
              "(1: no such candidate)")
    opt(mr, MorphSettings, "step_select_lr", type=float, help="position learning rate of that candidate")
    opt(mr, MorphSettings, "saturation", type=float,
         help="pixels brighter than this × the training photos' 99th percentile, in a photo or its render, and their "
              "neighbours stay out of the loss, as a camera clips them (a silhouette against the sun otherwise "
              "swamps every step); 0: every pixel counts")
    opt(mr, MorphSettings, "mask_weight", type=float,
         help="weight of a silhouette L1 beside the photos': the mesh's coverage of each pixel against the photos' "
              "masks (the benchmark's truth), so that every silhouette pulls with contrast 1; 0: photos only")
    opt(mr, MorphSettings, "mask_every", help="the silhouette L1 every this many steps only, at this × the weight "
         "(the same mean gradient, cheaper)")
    opt(mr, MorphSettings, "mask_downsample", help="the masks and their renders at the photos' resolution // this "
         "(cheaper; a coarser mask still places a silhouette to a fraction of its pixel)")
    opt(mr, MorphSettings, "backdrop", choices=["auto", "off"],
        help="a capture without masks: auto derives them where its photos show the object on a plain backdrop "
             "(written to OUT/backdrop_masks/); off: no silhouette loss")
    opt(mr, MorphSettings, "seed")
    pool_options(mr)
    mr.set_defaults(func=_cmd_morph_run)


def _add_errors(me: argparse.ArgumentParser) -> None:

    me.add_argument("benchmark", help="folder made by `photoreal morph make-benchmark`")
    me.add_argument("results", nargs="+", help="result meshes (OBJ/PLY/OFF) or morph output folders (their morphed.ply)")
    out_opt(me, "--out", required=True, help="folder for errors.json, errors_<name>.ply, facing_<name>.ply, "
                    "errors.png and facing.png")
    out_opt(me, "--json", kind="file", default=None, help="also write the report here")
    me.add_argument("--band", type=float, default=None,
                    help="width of the truth's border band (default 2.5%% of its bounding-box diagonal)")
    me.set_defaults(func=_cmd_morph_errors)


def _add_saturation(ms_: argparse.ArgumentParser) -> None:
    from inverse.morph import MorphSettings

    ms_.add_argument("benchmarks", nargs="+", help="folders made by `photoreal morph make-benchmark`")
    opt(ms_, MorphSettings, "saturation", "--factor", dest="factor", type=float,
        help="the saturation level: this × the training photos' 99th percentile (the morph's own)")
    out_opt(ms_, "--json", kind="file", default=None, help="also write the report here")
    ms_.set_defaults(func=_cmd_morph_saturation)


_SUBCOMMANDS = {
    "make-benchmark": ("ground truth + photos + degraded reconstruction", _add_make_benchmark),
    "run": ("morph benchmarks' coarse meshes (resumes from their checkpoints)", _add_run),
    "errors": ("where meshes lie against a benchmark's truth: both Chamfer directions, its "
                                        "open border against its interior, the input's error a result kept (in all "
                                        "and per spatial scale), the area facing against the truth by how many "
                                        "training views see it; signed-distance PLYs, PLYs marking the "
                                        "triangles facing against the truth, and a figure of each", _add_errors),
    "saturation": ("per training view, the pixels where the lighting is saturated (as "
                                            "`morph run --saturation` sees it) and how many lie at the truth's "
                                            "silhouette, where an edge's gradient is scaled by that light", _add_saturation),
}
