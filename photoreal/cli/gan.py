"""`photoreal gan …`: GAN refinement of renders (train, eval)."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from ..options import opt
from .common import add_subcommands, out_opt, print_json

HELP = "GAN refinement of renders: pix2pix, CycleGAN, Morph-GAN, joint (REAL-DIBS §3, §5)"


def _cmd_gan(a) -> int:
    from foundation.files import check_output_file, write_json
    from foundation.records import to_json
    from generative.gan import (
        GanTrainSettings,
        JointSettings,
        check_resolution,
        evaluate_model,
        load_paired_views,
        load_trained,
        train_gan,
        train_joint,
    )
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
        print_json({"mse": h.mse, "one_minus_ssim": h.one_minus_ssim, "flip": h.flip, "psnr": h.psnr,
                "train_seconds": r.training.train_seconds, "steps": r.training.steps,
                "infer_ms_per_image": h.infer_ms_per_image})
        return 0
    bench = load_morph_benchmark(a.benchmark)
    model, _ = load_trained(a.run)
    data = load_paired_views(bench, Path(a.morph) if a.morph else Path(a.benchmark) / "morph")
    m = to_json(evaluate_model(model, data))
    if a.json:
        write_json(a.json, m)
    print_json(m)
    return 0




def add(parser: argparse.ArgumentParser, wanted: str | None = None) -> None:
    parser.set_defaults(func=_cmd_gan)
    add_subcommands(parser, "gan_cmd", _SUBCOMMANDS, wanted)


def _add_train(gt: argparse.ArgumentParser) -> None:
    from generative.gan import GanTrainSettings

    gt.add_argument("benchmark", help="folder made by `photoreal morph make-benchmark`")
    gt.add_argument("--morph", default=None, help="morph run folder with morphed.ply (default BENCHMARK/morph)")
    opt(gt, GanTrainSettings, "model", choices=["pix2pix", "cyclegan", "morph_gan_partial", "morph_gan", "joint"],
        help="joint: mesh and Morph-GAN together")
    out_opt(gt, "--out", required=True, help="training folder (checkpoint.npz, metrics.json)")
    opt(gt, GanTrainSettings, "steps")
    opt(gt, GanTrainSettings, "max_seconds", "--seconds", type=float, help="wall-time budget (summed over resumes)")
    opt(gt, GanTrainSettings, "batch")
    opt(gt, GanTrainSettings, "crop")
    opt(gt, GanTrainSettings, "ngf", help="generator and discriminator width")
    gt.add_argument("--init-from", default=None,
                    help="fine-tune a finished run folder of the same model (joint: of morph_gan, + the morphed mesh)")
    gt.add_argument("--paper-head", action="store_true",
                    help="generator outputs tanh directly (papers' head) instead of input + tanh correction")
    out_opt(gt, "--json", kind="file", default=None, help="also write the training report here")
    opt(gt, GanTrainSettings, "seed")


def _add_eval(ge: argparse.ArgumentParser) -> None:

    ge.add_argument("benchmark")
    ge.add_argument("--morph", default=None, help="morph run folder (default BENCHMARK/morph)")
    ge.add_argument("--run", required=True, help="training folder of `gan train`")
    out_opt(ge, "--json", kind="file", default=None, help="also write the report here")


_SUBCOMMANDS = {
    "train": ("train one model on a morph benchmark + morph run (resumes from OUT)", _add_train),
    "eval": ("held-out metrics of a trained model", _add_eval),
}


