"""`photoreal render`: Mitsuba XML scenes to EXR + PNG, one scene or a resumable batch."""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

from ..options import opt
from .common import check_out_dir, out_opt, pool_options, run_batch, usage

HELP = "render Mitsuba XML scenes (our plugins register themselves)"


def _cmd_render(a: argparse.Namespace) -> int:
    from foundation.pool import Item
    from foundation.scene import RenderSettings, prepare_scene_xml, render_file, sensor_count

    settings = RenderSettings(spp=a.spp, resolution=tuple(a.resolution) if a.resolution else None, aovs=a.aovs,
                              seed=a.seed)
    many = len(a.scene) > 1 or a.all_sensors
    if a.output and many:
        raise usage("-o names one output; give --out-dir for several scenes or --all-sensors")
    if not a.output and not a.out_dir:
        raise usage("give -o FILE.exr (one scene) or --out-dir DIR (several)")
    if a.output:
        print(json.dumps(render_file(a.scene[0], a.output, settings)))
        return 0
    out = check_out_dir(a.out_dir)
    stems = [Path(sc).stem for sc in a.scene]
    if len(set(stems)) != len(stems):
        raise usage("two scenes share a file name; their renders would overwrite each other in --out-dir")
    items = []
    for sc in a.scene:
        prepare_scene_xml(Path(sc), settings)  # a missing or malformed scene is named before any work
        n = sensor_count(sc) if a.all_sensors else 1
        for k in range(n):
            key = Path(sc).stem + (f"_s{k}" if a.all_sensors else "")
            exr = out / f"{key}.exr"
            items.append(Item(key, "foundation.scene:render_item",
                              (str(sc), str(exr), dataclasses.replace(settings, sensor=k)), output=str(exr)))
    return run_batch(items, a, "render")




def add(parser: argparse.ArgumentParser, wanted: str | None = None) -> None:
    """The command's options (it has no subcommands: ``wanted`` is not used)."""
    from foundation.scene import RenderSettings


    r = parser
    r.add_argument("scene", nargs="+", help="scene .xml file(s)")
    out_opt(r, "-o", "--output", kind="file", default=None,
            help="output .exr of one scene (a .png preview is written beside it)")
    out_opt(r, "--out-dir", default=None,
                   help="folder for several renders: DIR/SCENE.exr (DIR/SCENE_s<k>.exr with --all-sensors); "
                        "renders already there are kept, so a killed batch resumes")
    r.add_argument("--all-sensors", action="store_true", help="render every sensor (camera, frame) of each scene")
    pool_options(r)
    opt(r, RenderSettings, "spp", type=int, help="samples per pixel (default: the scene's)")
    r.add_argument("--resolution", type=int, nargs=2, metavar=("W", "H"), default=None,
                   help="film size (default: the scene's)")
    opt(r, RenderSettings, "aovs", help="render with the 'intrinsic' integrator: albedo, irradiance, specular, "
                                         "normal, depth, uv, position layers")
    opt(r, RenderSettings, "seed", help="random seed (0 … 2³¹−1)")
    r.set_defaults(func=_cmd_render)
