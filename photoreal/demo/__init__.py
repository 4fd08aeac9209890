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
=============  ==================================================================
"""

from __future__ import annotations

from pathlib import Path

from foundation.files import check_output_dir, write_json

from .capture import demo_capture
from .face import demo_face, demo_face_learned, demo_photo
from .materials import demo_btf, demo_matdiff
from .morph import demo_diffrender, demo_gan, demo_morph
from .report import DemoSettings, bench_section, write_index
from .scenes import demo_scenes
from .tables import demo_benchmarks, demo_scale

__all__ = ["DemoSettings", "demo_benchmarks", "demo_capture", "demo_btf", "demo_diffrender", "demo_face", "demo_face_learned",
           "demo_gan", "demo_matdiff", "demo_morph", "demo_photo", "demo_scale", "demo_scenes", "run_demo"]


def run_demo(out_dir: str | Path = "out/demo", s: DemoSettings | None = None,
             bench_dir: str | Path | None = None) -> Path:
    """Render every section into ``out_dir`` and write ``index.html``; bench tables from ``bench_dir``'s JSON."""
    s = s or DemoSettings()
    from ..benchmarks.plugins import PluginBenchSettings, bench_plugins

    out_dir = check_output_dir(out_dir, "index.html", "--out")
    bench_dir = Path(bench_dir) if bench_dir is not None else None
    out_dir.mkdir(parents=True, exist_ok=True)
    results = {"scenes": demo_scenes(out_dir, s)}
    if s.face:
        # the camera renders follow --resolution/--spp, capped at the face benchmark's own defaults
        results["face"] = demo_face(out_dir, uv_res=s.face_uv_res, seed=s.seed, bench_dir=bench_dir,
                                    render_res=min(s.resolution, 192), render_spp=min(s.spp, 64))
        results["photo"] = demo_photo(out_dir, uv_res=s.face_uv_res, seed=s.seed,  # relit like the other renders
                                      relight_res=min(s.resolution, 256), relight_spp=min(s.spp, 64))
    if s.capture:
        results["capture"] = demo_capture(out_dir, resolution=min(s.resolution, 384), spp=min(s.spp, 16), seed=s.seed,
                                          bench_dir=bench_dir, morph_iterations=min(s.morph_iterations, 60))
    if s.morph_iterations > 0:
        results["morph"] = demo_morph(out_dir, iterations=s.morph_iterations, seed=s.seed, bench_dir=bench_dir)
    if s.btf:
        results["btf"] = demo_btf(out_dir, s, bench_dir=bench_dir)
        results["matdiff"] = demo_matdiff(out_dir, s, bench_dir=bench_dir)
    results["gan"] = demo_gan(out_dir, bench_dir)  # reads the bench's gan.json when present; trains nothing
    results["scale"] = demo_scale(out_dir, bench_dir)
    results["diffrender"] = demo_diffrender(out_dir, bench_dir)
    results["face_learned"] = demo_face_learned(out_dir, bench_dir)
    results["benchmarks"] = demo_benchmarks(out_dir, bench_dir)
    if s.plugin_bench:
        bench = bench_plugins(PluginBenchSettings(resolution=128, spp=32, repetitions=3, rounds=2))
        write_json(out_dir / "bench_plugins.json", bench)
        bench_section(out_dir, bench)
        results["bench_plugins"] = {k: bench[k] for k in ("ggx_uv_ms", "principled_ms", "ggx_uv_vs_principled")}
    write_json(out_dir / "demo.json", results)
    return write_index(out_dir)
