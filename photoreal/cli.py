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
    raise SystemExit(f"unknown benchmark {a.what!r}")


def _cmd_demo(a: argparse.Namespace) -> int:
    from .demo import DemoSettings, run_demo

    index = run_demo(a.out, DemoSettings(resolution=a.resolution, spp=a.spp, seed=a.seed),
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
    b.add_argument("what", choices=["plugins"])
    b.add_argument("--json", required=True, help="output JSON path")
    b.add_argument("--resolution", type=int, default=256)
    b.add_argument("--spp", type=int, default=64)
    b.add_argument("--repetitions", type=int, default=5)
    b.add_argument("--rounds", type=int, default=2)
    b.set_defaults(func=_cmd_bench)

    d = sub.add_parser("demo", help="render the built-in scenes and write an HTML report")
    d.add_argument("--out", default="out/demo")
    d.add_argument("--resolution", type=int, default=256)
    d.add_argument("--spp", type=int, default=64)
    d.add_argument("--seed", type=int, default=0)
    d.add_argument("--no-bench", action="store_true", help="skip the plugin speed section")
    d.set_defaults(func=_cmd_demo)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from .imageio import ImageIOError
    from .render import SceneError

    try:
        return args.func(args)
    except (SceneError, ImageIOError, ValueError, FileNotFoundError, FloatingPointError) as exc:
        print(f"photoreal: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("photoreal: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
