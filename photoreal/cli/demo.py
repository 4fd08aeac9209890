"""`photoreal demo`: the built-in scenes and every stage in one HTML report."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..options import arg_opt, opt, settings_from
from .common import output_type

HELP = "render the built-in scenes and write an HTML report"
#: what marks a report written before output folders carried their record: it is replaced like a recorded one
DEMO_FILES = ("index.html", "demo.json", "sections")


def _cmd_demo(a) -> int:
    from ..demo import DemoSettings, run_demo

    s = settings_from(DemoSettings, a)
    bench_dir = Path(a.bench_dir) if a.bench_dir else Path(a.out).parent / "bench"
    print(f"report: {run_demo(a.out, s, bench_dir=bench_dir)}")
    return 0




def add(parser: argparse.ArgumentParser, wanted: str | None = None) -> None:
    """The command's options (it has no subcommands: ``wanted`` is not used)."""

    from ..demo import DemoSettings, run_demo

    d = parser
    arg_opt(d, run_demo, "out_dir", "--out", dest="out", type=output_type(d, "folder", "index.html", DEMO_FILES),
            metavar="DIR", help="report folder")
    d.add_argument("--bench-dir", default=None,
                   help="folder with `photoreal bench` JSON files for the report's tables (default: OUT/../bench)")
    opt(d, DemoSettings, "resolution", help="image side of the renders (the face's camera renders: at most 192)")
    opt(d, DemoSettings, "spp", help="samples per pixel (the face's camera renders: at most 64)")
    opt(d, DemoSettings, "seed")
    opt(d, DemoSettings, "plugin_bench", "--no-bench", help="skip the plugin speed section")
    opt(d, DemoSettings, "face", "--no-face", help="skip the face sections")
    opt(d, DemoSettings, "face_uv_res")
    opt(d, DemoSettings, "morph_iterations", help="0 skips the morphing section")
    opt(d, DemoSettings, "refiner_seconds")
    opt(d, DemoSettings, "btf", "--no-btf", help="skip the neural materials section")
    opt(d, DemoSettings, "capture", "--no-capture", help="skip the real capture section")
    opt(d, DemoSettings, "export", "--no-export", help="skip the exports section and the browser check")
    d.set_defaults(func=_cmd_demo)
