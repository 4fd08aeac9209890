"""`make demo`: render the built-in scenes, their intrinsic layers, and an HTML report.

Sections are small HTML fragments stored under ``OUT/sections/`` (:func:`add_section`) and stitched
into ``index.html`` in name order. Benchmark tables come from the JSON files in ``bench_dir`` (what
``photoreal bench …`` wrote); the demo never reads the working directory or the tests.

=============  ==================================================================
module         what
=============  ==================================================================
``report``     settings, sections stitched into ``index.html``, figures, tables
``scenes``     the built-in scenes and their intrinsic layers
``capture``    a real capture through structure from motion, its coarse mesh at a held-out photo
``face``       a fit on a real scan, one photo to a face, the learned stages
``morph``      a morph and why its choices went so, the GANs, the diffusion renderer
``materials``  fitted and generated neural materials
``tables``     every registered benchmark's result, the pool and Ray
``export``     glTF exports in 3D viewers (``viewer``), the page checked in a browser (``browser``)
=============  ==================================================================
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

from foundation.files import check_output_dir, write_json

from .capture import demo_capture
from .export import check_report, demo_export
from .face import demo_face, demo_face_learned, demo_photo
from .materials import demo_btf, demo_matdiff
from .morph import demo_diffrender, demo_gan, demo_morph, demo_refiners
from .report import DemoSettings, bench_section, time_section, write_index
from .scenes import demo_scenes
from .tables import demo_benchmarks, demo_scale

__all__ = ["DemoSettings", "check_report", "demo_export", "demo_benchmarks", "demo_capture", "demo_btf", "demo_diffrender", "demo_face", "demo_face_learned",
           "demo_gan", "demo_matdiff", "demo_morph", "demo_photo", "demo_refiners", "demo_scale", "demo_scenes",
           "run_demo"]


def run_demo(out_dir: str | Path = "out/demo", s: DemoSettings | None = None,
             bench_dir: str | Path | None = None) -> Path:
    """Render every section into ``out_dir`` and write ``index.html``; bench tables from ``bench_dir``'s JSON."""
    s = s or DemoSettings()
    from ..benchmarks.plugins import PluginBenchSettings, bench_plugins

    out_dir = check_output_dir(out_dir, "index.html", "--out")
    bench_dir = Path(bench_dir) if bench_dir is not None else None
    out_dir.mkdir(parents=True, exist_ok=True)
    seconds: dict[str, float] = {}
    results: dict = {}

    def step(key: str, fn, *args, **kw):
        """Run one section, say so on stderr and keep its wall seconds (the report's time table)."""
        print(f"demo: {key} …", file=sys.stderr, flush=True)
        t = time.perf_counter()
        results[key] = fn(*args, **kw)
        seconds[key] = time.perf_counter() - t
        print(f"demo: {key} {seconds[key]:.1f} s", file=sys.stderr, flush=True)

    step("scenes", demo_scenes, out_dir, s)
    if s.face:
        # the camera renders follow --resolution/--spp, capped at the face benchmark's own defaults
        step("face", demo_face, out_dir, uv_res=s.face_uv_res, seed=s.seed, bench_dir=bench_dir,
             render_res=min(s.resolution, 192), render_spp=min(s.spp, 64))
        step("photo", demo_photo, out_dir, uv_res=s.face_uv_res, seed=s.seed,  # relit like the other renders
             relight_res=min(s.resolution, 256), relight_spp=min(s.spp, 64))
    if s.capture:
        step("capture", demo_capture, out_dir, resolution=min(s.resolution, 384), spp=min(s.spp, 16), seed=s.seed,
             bench_dir=bench_dir, morph_iterations=min(s.morph_iterations, 60))
    if s.morph_iterations > 0:
        step("morph", demo_morph, out_dir, iterations=s.morph_iterations, seed=s.seed, bench_dir=bench_dir)
        if s.refiner_seconds > 0:
            step("refiners", demo_refiners, out_dir, s.refiner_seconds, s.seed)
    if s.btf:
        step("btf", demo_btf, out_dir, s, bench_dir=bench_dir)
        step("matdiff", demo_matdiff, out_dir, s, bench_dir=bench_dir)
    step("gan", demo_gan, out_dir, bench_dir)  # reads the bench's gan.json when present; trains nothing
    step("scale", demo_scale, out_dir, bench_dir)
    step("diffrender", demo_diffrender, out_dir, bench_dir)
    step("face_learned", demo_face_learned, out_dir, bench_dir)
    step("benchmarks", demo_benchmarks, out_dir, bench_dir)
    if s.plugin_bench:
        def plugin_speed():
            bench = bench_plugins(PluginBenchSettings(resolution=128, spp=32, repetitions=3, rounds=2))
            write_json(out_dir / "bench_plugins.json", bench)
            bench_section(out_dir, bench)
            return {k: bench[k] for k in ("ggx_uv_ms", "principled_ms", "ggx_uv_vs_principled", "neural_btf_ms",
                                          "neural_btf_vs_principled", "neural_btf_vs_principled_evaluated")}
        step("bench_plugins", plugin_speed)
    if s.export:
        step("export", demo_export, out_dir, s.seed)
    results["seconds"] = seconds
    time_section(out_dir, seconds, _what_ran(s, results))
    write_json(out_dir / "demo.json", results)
    index = write_index(out_dir)
    if s.export:  # the finished page in a real browser: every viewer loaded, no console error, a screenshot
        print("demo: browser check …", file=sys.stderr, flush=True)
        results["browser"] = check_report(out_dir)
        write_json(out_dir / "demo.json", results)
        if results["browser"].get("ok") is False:
            print(f"demo: the report's browser check failed: {results['browser']}", file=sys.stderr, flush=True)
    return index


def _what_ran(s: DemoSettings, results: dict) -> dict[str, str]:
    """What each part of the report did in this run, in a few words (the time table's middle column)."""
    side = min(s.resolution, 384)
    photos = ((results.get("capture") or {}).get("sfm") or {}).get("photos", "the")
    out = {"scenes": f"3 scenes and their intrinsic layers, {s.resolution}², {s.spp} spp",
           "face": f"a benchmark of the bundled scan and its fit at {s.face_uv_res}² texels",
           "photo": "landmarks, unwrap, delighting and relighting of one photo" if results.get("photo") else
                    "skipped: MediaPipe is not installed",
           "capture": f"structure from motion of {photos} photos at {side} px, a {min(s.morph_iterations, 60)}-iteration "
                      "morph of its coarse mesh",
           "morph": f"a {s.morph_iterations}-iteration morph with its choices given",
           "refiners": f"Morph-GAN and the diffusion renderer, {s.refiner_seconds:g} s of training each",
           "btf": "the neural materials scene with the bundled basis",
           "matdiff": "materials the bundled model generated",
           "bench_plugins": "a short run of the plugin benchmark",
           "export": "glTF exports of the capture's morph, the face fit and a material's distilled GGX"}
    for k in ("gan", "scale", "diffrender", "face_learned", "benchmarks"):
        out[k] = "tables of the bench folder's JSON" if results.get(k) else "nothing: no such JSON in the bench folder"
    return out
