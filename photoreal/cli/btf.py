"""`photoreal btf …`: neural BTF data, basis, fits, and the material diffusion model."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from ..options import arg_opt, opt, settings_from
from .common import add_subcommands, check_out_dir, out_opt, pool_options, pool_settings, run_batch, usage

HELP = "universal neural BTF: data, basis training, per-material fitting (seed 002)"


def _checkpoint_path(a) -> Path:
    from foundation.files import check_output_file

    ck = Path(a.checkpoint) if a.checkpoint else Path(a.out).with_suffix(".ckpt.npz")
    return check_output_file(ck, "--checkpoint")


def _cmd_btf_render_data(a) -> int:
    from foundation.pool import ray_shutdown
    from inverse.btf import FAMILIES, BTFRenderSettings, render_dataset

    s = settings_from(BTFRenderSettings, a)
    try:
        paths = render_dataset(a.out, families=tuple(a.families) if a.families else FAMILIES,
                               per_family=a.per_family, settings=s, base_seed=a.seed, pool=pool_settings(a))
    finally:
        ray_shutdown()
    print(json.dumps({"materials": len(paths), "out": str(a.out)}))
    return 0


def _cmd_btf_train_basis(a) -> int:
    from foundation.files import check_output_file
    from inverse.btf import OptimSettings, load_dataset, train_basis
    from mi_plugins.neural_basis import BasisConfig, save_basis

    cfg = settings_from(BasisConfig, a)
    s = settings_from(OptimSettings, a)
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
            raise usage("--out, --json and --checkpoint name one material; several go to --out-dir")
        if not a.out_dir:
            raise usage("several BTFs: give --out-dir DIR (DIR/NAME.npz each)")
        out = check_out_dir(a.out_dir)
        names = [Path(b).stem for b in a.btf]
        if len(set(names)) != len(names):
            raise usage("two BTFs share a file name; their materials would overwrite each other in --out-dir")
        for b in a.btf:
            if not Path(b).is_file():
                raise usage(f"{b}: no such BTF file")
        if not Path(a.basis).is_file():
            raise usage(f"--basis {a.basis}: no such file")
        items = [Item(n, "inverse.btf:fit_file", (str(b), str(a.basis), str(out / f"{n}.npz")), kw,
                      output=str(out / f"{n}.npz")) for n, b in zip(names, a.btf)]
        return run_batch(items, a, "fit materials")
    if not a.out:
        raise usage("give --out MATERIAL.npz (or --out-dir for several BTFs)")
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
    from generative.btf import MaterialDataSettings, build_material_dataset, load_material_dataset

    s = settings_from(MaterialDataSettings, a)
    if a.basis and not Path(a.basis).is_file():
        raise usage(f"--basis {a.basis}: no such file")
    try:
        build_material_dataset(a.out, s, basis=a.basis, pool=pool_settings(a))
    finally:
        ray_shutdown()
    ds = load_material_dataset(a.out)
    print(json.dumps({"out": str(a.out), "materials": len(ds.names), "heldout": int(ds.heldout.sum()),
                      "fit_psnr_median": float(sorted(ds.psnr)[len(ds.psnr) // 2])}))
    return 0


def _cmd_btf_train_diffusion(a) -> int:
    from foundation.records import to_json
    from generative.btf import MatDiffSettings, load_material_dataset, train_matdiff

    s = settings_from(MatDiffSettings, a)
    ds = load_material_dataset(a.data)
    r = train_matdiff(ds.subset(~ds.heldout), a.out, s, device=a.device)
    print(json.dumps({"run": str(a.out), "device": a.device, "materials": r.materials, "parameters": r.parameters,
                      "training": to_json(r.training)}, default=str))
    return 0


def _cmd_btf_generate(a) -> int:
    from generative.btf import generate_material

    if not a.keywords and not a.image and not a.unconditional and not a.from_prior:
        raise usage("give --keywords WORDS, --image PHOTO (or both), --from-prior or --unconditional")
    if a.run is None:
        from foundation.assets import bundled_matdiff

        a.run = bundled_matdiff()
    print(json.dumps(generate_material(a.run, a.out, a.keywords, a.image, a.seed, a.size, a.steps, a.guidance,
                                       from_prior=a.from_prior)))
    return 0




def add(parser: argparse.ArgumentParser, wanted: str | None = None) -> None:
    add_subcommands(parser, "btf_cmd", _SUBCOMMANDS, wanted)


def _add_render_data(tr: argparse.ArgumentParser) -> None:
    from inverse.btf import BTFRenderSettings, render_dataset

    out_opt(tr, "--out", required=True, help="dataset folder")
    tr.add_argument("--families", nargs="+", default=None, help="subset of the material families (default: all 8)")
    arg_opt(tr, render_dataset, "per_family", type=int, help="materials per family")
    for name in ("tex_res", "slices", "spp", "max_depth", "seed"):
        opt(tr, BTFRenderSettings, name)
    pool_options(tr)
    tr.set_defaults(func=_cmd_btf_render_data)


def _add_train_basis(tb: argparse.ArgumentParser) -> None:
    from inverse.btf import OptimSettings
    from mi_plugins.neural_basis import BasisConfig

    tb.add_argument("data", help="folder made by render-data")
    out_opt(tb, "--out", kind="file", required=True, help="basis .npz")
    opt(tb, OptimSettings, "iterations")
    opt(tb, OptimSettings, "batch")
    opt(tb, BasisConfig, "width")
    opt(tb, BasisConfig, "depth")
    opt(tb, BasisConfig, "channels")
    out_opt(tb, "--checkpoint", kind="file", default=None, help="default: OUT with .ckpt.npz")
    opt(tb, OptimSettings, "seed")
    tb.set_defaults(func=_cmd_btf_train_basis)


def _add_fit(tf: argparse.ArgumentParser) -> None:
    from inverse.btf import OptimSettings, fit_settings, split_slices

    tf.add_argument("btf", nargs="+", help="BTF .npz file(s) from render-data")
    tf.add_argument("--basis", required=True)
    out_opt(tf, "--out", kind="file", default=None, help="material .npz for the neural_btf plugin (one BTF)")
    out_opt(tf, "--out-dir", default=None, help="folder for several materials: DIR/NAME.npz")
    arg_opt(tf, fit_settings, "iterations", type=int, help="Adam steps")
    opt(tf, OptimSettings, "batch", type=int, help="samples per step")
    opt(tf, OptimSettings, "tex_res", help="feature texture resolution (0 = the BTF's)")
    arg_opt(tf, split_slices, "heldout_fraction", type=float, help="slices held out for the PSNR")
    out_opt(tf, "--checkpoint", kind="file", default=None, help="default: OUT with .ckpt.npz")
    out_opt(tf, "--json", kind="file", default=None, help="metrics JSON")
    opt(tf, OptimSettings, "seed")
    pool_options(tf)
    tf.set_defaults(func=_cmd_btf_fit)


def _add_dataset(td: argparse.ArgumentParser) -> None:
    from generative.btf import MaterialDataSettings

    out_opt(td, "--out", required=True, help="dataset folder")
    for name in ("count", "tex_res", "slices", "spp", "fit_iterations", "seed"):
        opt(td, MaterialDataSettings, name)
    td.add_argument("--basis", default=None, help="universal basis .npz (default: the bundled one)")
    pool_options(td)
    td.set_defaults(func=_cmd_btf_dataset)


def _add_train_diffusion(tt: argparse.ArgumentParser) -> None:
    from generative.btf import MatDiffSettings, train_matdiff

    tt.add_argument("data", help="folder made by `btf dataset`")
    out_opt(tt, "--out", required=True, help="run folder (checkpoint.npz, metrics.json)")
    opt(tt, MatDiffSettings, "max_seconds", "--seconds", type=float, help="training budget (summed over resumes)")
    for name in ("steps", "batch", "train_crop", "lr", "widths", "attention_levels", "ema", "seed"):
        opt(tt, MatDiffSettings, name, **({"type": int} if name == "widths" else {}))
    arg_opt(tt, train_matdiff, "device", help="torch device of the model (cpu, cuda, cuda:N, mps); a run resumes on "
            "any device")
    tt.set_defaults(func=_cmd_btf_train_diffusion)


def _add_generate(tg: argparse.ArgumentParser) -> None:
    from generative.btf import generate_material


    tg.add_argument("--run", default=None, help="run folder of `btf train-diffusion` (default: the bundled model, "
                    "scenes/assets/neural/matdiff, trained on a GPU; see its README)")
    tg.add_argument("--keywords", default=None, help="e.g. 'rough red leather' (family, colour, finish words)")
    tg.add_argument("--image", default=None, help="exemplar photo (PNG/JPG/EXR, or brick/grass/gravel)")
    tg.add_argument("--from-prior", action="store_true", help="a random material: keywords drawn (by --seed) from "
                    "the run's training materials (keyword_prior.json)")
    tg.add_argument("--unconditional", action="store_true", help="neither keywords nor image (the null condition: "
                    "its samples collapse to few families; --from-prior is the better random material)")
    arg_opt(tg, generate_material, "seed", type=int)
    arg_opt(tg, generate_material, "size", type=int, help="texels per side (any multiple of 4: tiles seamlessly)")
    tg.add_argument("--steps", type=int, default=None, help="DDIM steps (default: the run's sampler.json, which "
                    "`bench matdiff` writes; else 25)")
    tg.add_argument("--guidance", type=float, default=None, help="classifier-free guidance (default: the run's "
                    "sampler.json; else 2)")
    out_opt(tg, "--out", kind="file", required=True, help="material .npz")
    tg.set_defaults(func=_cmd_btf_generate)


_SUBCOMMANDS = {
    "render-data": ("render BTFs from procedural/photo SVBRDFs (resumes: skips finished files)", _add_render_data),
    "train-basis": ("train the universal MLPs on a dataset (resumes from --checkpoint)", _add_train_basis),
    "fit": ("fit materials' feature textures with the basis frozen (resumes)", _add_fit),
    "dataset": ("many fitted materials for the material diffusion model: BTFs, fits, "
                         "path-traced swatches, keywords (resumes; every core)", _add_dataset),
    "train-diffusion": ("train the material diffusion model on a dataset's training "
                         "materials (resumes)", _add_train_diffusion),
    "generate": ("a new material from keywords and/or an exemplar image; loads in "
                         "neural_btf with the basis the model was trained on", _add_generate),
}
