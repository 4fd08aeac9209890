"""`photoreal export`: a morph result, a face avatar or a neural material as glTF/GLB/OBJ with its textures."""

from __future__ import annotations

import argparse

from ..options import opt
from .common import out_opt, print_json

HELP = "export a morph result, a face avatar or a neural material as glTF/GLB/OBJ"


def _cmd_export(a: argparse.Namespace) -> int:
    from foundation.export import ExportSettings
    from foundation.records import to_json

    from ..export import export_result
    from ..options import settings_from

    rec = to_json(export_result(a.result, a.out, settings_from(ExportSettings, a), input_path=a.input, basis=a.basis))
    keep = ("kind", "format", "files", "texture", "heldout", "model", "exported_heldout_psnr", "ggx_heldout_psnr",
            "constant_heldout_psnr",
            "preview_psnr", "reimport", "seconds")
    print_json({k: rec[k] for k in keep if k in rec})
    return 0


def add(parser: argparse.ArgumentParser, wanted: str | None = None) -> None:
    """The command's options (no subcommands)."""
    from foundation.export import FORMATS, ExportSettings

    p = parser
    p.add_argument("result", help="a morph run folder, a `face from-photo` folder, a `face fit` fit.json (or its "
                                  "--maps folder), or a neural material .npz")
    out_opt(p, "--out", marker="export.json", required=True,
            help="folder to write (absent, empty, or an earlier export): the model, its textures, export.json")
    opt(p, ExportSettings, "format", choices=list(FORMATS))
    opt(p, ExportSettings, "texture", choices=["auto", "photos", "colours"])
    opt(p, ExportSettings, "texture_size")
    opt(p, ExportSettings, "padding")
    opt(p, ExportSettings, "eval_width")
    opt(p, ExportSettings, "spp")
    opt(p, ExportSettings, "seed")
    p.add_argument("--input", default=None, help="morph runs: the capture or benchmark morphed (default: the folder "
                                                 "holding the run); face fits: the benchmark (default: fit.json's)")
    p.add_argument("--basis", default=None, help="neural materials: the universal basis .npz (default: the bundled one)")
    p.set_defaults(func=_cmd_export)
