"""`photoreal capture …`: real captures in (import, sfm), out (export), and scored on held-out photos (score)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ..options import arg_opt, opt, settings_from
from .common import add_subcommands, out_opt, print_json, usage

SFM_WORK = ".sfm"  #: COLMAP's database and model while `capture sfm` runs (inside --out)
HELP = "real captures: import COLMAP / transforms.json / LLFF, structure from motion, export, held-out scores"


def _say(msg: str) -> None:
    print(f"capture: {msg}", file=sys.stderr, flush=True)


def _summary(out: Path) -> dict:
    from inverse.capture import load_capture

    cap = load_capture(out)
    m = cap.meta
    return {"capture": str(out), "photos": len(m.cameras), "train": len(m.train), "test": len(m.test),
            "resolution": [m.cameras[0].width, m.cameras[0].height], "mesh": m.mesh, "masks": m.masks,
            "points": m.points, **({"sfm": m.sfm} if m.sfm else {})}


def _cmd_import(a) -> int:
    from inverse.capture import import_capture, read_source

    src = read_source(a.source, images=a.images, masks=a.masks)
    _say(f"{len(src.frames)} photos with {src.kind} cameras from {src.path}")
    import_capture(src, a.out, a.resolution, mesh=a.mesh, coarse=a.coarse)
    print_json(_summary(Path(a.out)))
    return 0


def _cmd_sfm(a) -> int:
    from inverse.capture import SfmSettings, import_capture, run_sfm

    s = settings_from(SfmSettings, a)
    # COLMAP's work inside the output folder: an interrupted run resumes from its last finished step; the finished
    # capture replaces it
    src = run_sfm(a.photos, Path(a.out) / SFM_WORK, s, progress=_say)
    fig = src.notes["sfm"]
    _say(f"registered {fig['registered']}/{fig['photos']} photos in {fig['models']} model(s), {fig['points']} "
         f"points, {fig['reprojection_px']:.2f} px")
    if fig["unregistered"]:
        _say(f"not registered (too few matches with the others): {', '.join(fig['unregistered'])}")
    import_capture(src, a.out, a.resolution, mesh=a.mesh, derived=(SFM_WORK,))
    print_json(_summary(Path(a.out)))
    return 0


def _load_any(path: str):
    """A capture folder, or a morph benchmark as a capture."""
    from inverse.capture import MARKER, load_capture

    p = Path(path)
    if (p / "morph_benchmark.json").is_file() and not (p / MARKER).is_file():
        from inverse.morph import benchmark_capture, load_morph_benchmark

        return benchmark_capture(load_morph_benchmark(p))
    return load_capture(p)


def _cmd_export(a) -> int:
    from inverse.capture import export_capture

    out = export_capture(_load_any(a.capture), a.out, a.format)
    print_json({"out": str(out), "format": a.format})
    return 0


def _cmd_score(a) -> int:
    from foundation.files import write_json
    from foundation.mesh import read_ply
    from inverse.capture import heldout_scores, load_coarse_mesh

    cap = _load_any(a.capture)
    mesh = a.mesh or (str(cap.mesh) if cap.mesh else None)
    if mesh is None:
        raise usage(f"{a.capture}: the capture has no mesh; give --mesh")
    v, f, _ = read_ply(mesh) if mesh.endswith(".ply") else load_coarse_mesh(mesh)
    r = heldout_scores(cap, v, f, spp=a.spp)
    r.pop("renders")
    r["mesh"] = mesh
    if a.json:
        write_json(a.json, r)
    print_json(r["mean"] | {"views": len(r["views"]), "masked": r["masked"]})
    return 0


def add(parser: argparse.ArgumentParser, wanted: str | None = None) -> None:
    add_subcommands(parser, "capture_cmd", _SUBCOMMANDS, wanted)


def _add_import(p: argparse.ArgumentParser) -> None:
    from inverse.capture import import_capture

    p.add_argument("source", help="a COLMAP model (its folder, or the project holding sparse/0), a transforms.json "
                   "(or its folder), or an LLFF folder (poses_bounds.npy)")
    out_opt(p, "--out", required=True, help="capture folder to write")
    p.add_argument("--images", default=None, help="COLMAP: the photos' folder (default: images/ beside the model)")
    p.add_argument("--masks", default=None, help="folder of masks, one per photo by name (white: the object)")
    p.add_argument("--mesh", default=None, help="the tool's coarse mesh (OBJ with MTL texture, PLY, GLB); without "
                   "it, one is made from the model's points or from points triangulated with the cameras")
    arg_opt(p, import_capture, "resolution", type=int, help="longest side of the working photos (never enlarged)")
    arg_opt(p, import_capture, "coarse", choices=["auto", "poisson", "hull"],
            help="without --mesh: the Poisson surface of the points, or the masks' visual hull (auto: Poisson when the "
                 "source has points, else the hull when it has masks)")
    p.set_defaults(func=_cmd_import)


def _add_sfm(p: argparse.ArgumentParser) -> None:
    from inverse.capture import SfmSettings, import_capture

    p.add_argument("photos", help="folder of photos (JPEG/PNG/TIFF)")
    out_opt(p, "--out", required=True, help="capture folder to write")
    p.add_argument("--mesh", default=None, help="a coarse mesh to use instead of the Poisson surface of the points")
    arg_opt(p, import_capture, "resolution", type=int, help="longest side of the working photos (never enlarged)")
    for name in ("max_size", "max_features", "exhaustive_up_to", "seed"):
        opt(p, SfmSettings, name)
    opt(p, SfmSettings, "relaxed", "--default-mapper", help="COLMAP's default mapper options (they split "
        "low-texture captures into several models)")
    opt(p, SfmSettings, "single_camera", "--per-photo-cameras", help="a camera of its own for every photo (zoom "
        "lenses, several bodies); by default photos of one size share one")
    opt(p, SfmSettings, "distortion", choices=["auto", "on", "off"])
    p.set_defaults(func=_cmd_sfm)


def _add_export(p: argparse.ArgumentParser) -> None:
    from inverse.capture import FORMATS

    p.add_argument("capture", help="a capture folder, or a morph benchmark")
    out_opt(p, "--out", required=True, help="folder to write (images/ and the cameras)")
    p.add_argument("--format", required=True, choices=FORMATS, help="colmap (binary), colmap-text, transforms "
                   "(nerfstudio / instant-ngp), llff")
    p.set_defaults(func=_cmd_export)


def _add_score(p: argparse.ArgumentParser) -> None:
    from inverse.capture import heldout_scores

    p.add_argument("capture", help="a capture folder, or a morph benchmark")
    p.add_argument("--mesh", default=None, help="mesh to score (default: the capture's coarse mesh)")
    arg_opt(p, heldout_scores, "spp", type=int, help="samples per pixel of the renders")
    out_opt(p, "--json", kind="file", default=None, help="per held-out photo and mean scores")
    p.set_defaults(func=_cmd_score)


_SUBCOMMANDS = {
    "import": ("photos + cameras from COLMAP, transforms.json or LLFF → a capture (undistorted, linear)", _add_import),
    "sfm": ("structure from motion on the CPU (pycolmap): photos → cameras, points, a coarse mesh", _add_sfm),
    "export": ("a capture (or a morph benchmark) → COLMAP, transforms.json or LLFF", _add_export),
    "score": ("renders of a mesh against the capture's held-out photos (PSNR, SSIM, ꟻLIP, MobileNetV2)", _add_score),
}
