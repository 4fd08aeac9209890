"""`photoreal diffrender …`: the intrinsic-conditioned diffusion renderer (train, render)."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..options import arg_opt, opt, settings_from
from .common import add_subcommands, out_opt, print_json, usage

HELP = "intrinsic-conditioned diffusion renderer: G-buffers (A, I, S, N) → photo (seed 000)"


def _cmd_diffrender(a) -> int:
    from foundation.files import check_output_dir, check_output_file, write_json
    from foundation.records import to_json
    from generative.diffrender import (
        TRUTH,
        DiffRenderSettings,
        SampleSettings,
        load_intrinsic_views,
        render_benchmark,
        render_scene_file,
        train_diffrender,
        with_truth_layers,
    )
    from inverse.morph import load_morph_benchmark

    if a.json:
        check_output_file(a.json, "--json")
    if a.dr_cmd == "train":
        morphs = a.morph or [str(Path(b) / "morph") for b in a.benchmarks]
        if len(morphs) != len(a.benchmarks):
            raise usage(f"--morph: {len(morphs)} folders for {len(a.benchmarks)} benchmarks (one each, in order)")
        s = settings_from(DiffRenderSettings, a)
        benches = [load_morph_benchmark(b) for b in a.benchmarks]  # all validated before any rendering
        cases = [load_intrinsic_views(b, m) for b, m in zip(benches, morphs)]
        if TRUTH in s.sources:  # the benchmarks' ground truth through the same integrator, at the same spp
            cases = [with_truth_layers(v, b, m) for v, b, m in zip(cases, benches, morphs)]
        r = train_diffrender(cases, a.out, s)
        m = to_json(r)
        if a.json:
            write_json(a.json, m)
        print_json({"train_seconds": r.training.train_seconds, "steps": r.training.steps, "parameters": r.parameters,
                "loss_first": r.training.loss_first, "loss_last": r.training.loss_last, "skipped": r.training.skipped_steps})
        return 0
    ss = settings_from(SampleSettings, a)
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
    print_json({k: v for k, v in m.items() if k != "files"} | {"files": len(r.files), "out": str(a.out)})
    return 0


def add(parser: argparse.ArgumentParser, wanted: str | None = None) -> None:
    parser.set_defaults(func=_cmd_diffrender)
    add_subcommands(parser, "dr_cmd", _SUBCOMMANDS, wanted)


def _add_train(t: argparse.ArgumentParser) -> None:
    from generative.diffrender import TRAIN_SOURCES, DiffRenderSettings

    t.add_argument("benchmarks", nargs="+", help="folders made by `photoreal morph make-benchmark` (with --spp 1024, "
                   "as the bench: the photos are the targets, and their Monte-Carlo noise would be learned as well)")
    t.add_argument("--morph", nargs="+", default=None, help="their morph run folders, in order (default BENCHMARK/morph)")
    out_opt(t, "--out", required=True, help="training folder (checkpoint.npz, metrics.json)")
    opt(t, DiffRenderSettings, "steps")
    opt(t, DiffRenderSettings, "max_seconds", "--seconds", type=float, help="training wall-time budget (summed over resumes)")
    opt(t, DiffRenderSettings, "batch")
    opt(t, DiffRenderSettings, "crop")
    opt(t, DiffRenderSettings, "lr")
    opt(t, DiffRenderSettings, "widths", type=int, help="UNet channels per level")
    opt(t, DiffRenderSettings, "attention_levels")
    opt(t, DiffRenderSettings, "global_source", choices=["R", "AIS", "none"],
         help="global tokens from the recomposition R (seed 000), from A, I, S separately, or none")
    opt(t, DiffRenderSettings, "p_uncond")
    opt(t, DiffRenderSettings, "residual", "--direct",
         help="generate the photo itself (the seed) instead of its residual over R = A·I + S")
    opt(t, DiffRenderSettings, "known_background", "--every-pixel",
         help="learn the residual on every pixel instead of holding it at 0 where the G-buffer sees no surface")
    opt(t, DiffRenderSettings, "sources", choices=list(TRAIN_SOURCES),
         help="whose G-buffers are training inputs: the morphed mesh's, the coarse mesh's (worse on held-out and "
              "unseen meshes, measured), the benchmark's ground truth's (exact intrinsics, the seed's pairs)")
    opt(t, DiffRenderSettings, "threads", help="torch threads (0: all cores)")
    opt(t, DiffRenderSettings, "seed")
    out_opt(t, "--json", kind="file", default=None, help="also write the training report here")


def _add_render(r: argparse.ArgumentParser) -> None:
    from generative.diffrender import SampleSettings, render_benchmark, render_scene_file

    r.add_argument("target", help="a morph benchmark folder, or a Mitsuba scene .xml (every sensor is rendered)")
    r.add_argument("--run", required=True, help="training folder of `diffrender train`")
    out_opt(r, "--out", required=True, help="output folder")
    r.add_argument("--morph", default=None, help="benchmark: morph run folder (default BENCHMARK/morph)")
    arg_opt(r, render_benchmark, "source", choices=["morphed", "coarse"], help="benchmark: whose G-buffers")
    arg_opt(r, render_benchmark, "views", choices=["test", "all"], help="benchmark: held-out views or all")
    arg_opt(r, render_scene_file, "spp", type=int, help="scene: samples per pixel of the G-buffers (as the bench's)")
    opt(r, SampleSettings, "steps", "--ddim-steps", help="DDIM steps")
    opt(r, SampleSettings, "guidance", type=float, help="classifier-free guidance weight on the global condition "
         "(default: 1 for a mean of draws, 1.5 for single samples: the bench's choices)")
    opt(r, SampleSettings, "draws", type=int, help="samples averaged per view (at 1 step: the posterior mean; "
         "default: 8 at 1 step, the bench's choice, 1 for more steps)")
    opt(r, SampleSettings, "seed")
    out_opt(r, "--json", kind="file", default=None, help="also write the report here")


_SUBCOMMANDS = {
    "train": ("train on morph benchmarks (morphed G-buffers → photos); resumes from OUT", _add_train),
    "render": ("diffusion renders of a benchmark's views or of a scene's sensors (EXR + PNG)", _add_render),
}


