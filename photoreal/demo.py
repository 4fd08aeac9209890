"""`make demo`: render the built-in scenes, their intrinsic layers, and an HTML report.

Later capabilities add sections through :func:`add_section` (each section is
a small HTML fragment stored under ``out/demo/sections/`` and stitched into
``index.html`` in name order).
"""

from __future__ import annotations

import html
import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from . import imageio
from .metrics import psnr
from .render import RenderSettings, load_scene, recompose, render_scene

SCENES_DIR = Path(__file__).resolve().parent.parent / "scenes"


@dataclass
class DemoSettings:
    resolution: int = 256
    spp: int = 64
    seed: int = 0


DEMO_SCENES = [
    ("josie", "Cyberware head 'josie' (real scan) — ggx_uv under the studio HDRI"),
    ("material_test", "Material test — ggx_uv (left) vs builtin principled (right), sunset HDRI"),
    ("armadillo", "Stanford Armadillo — ggx_uv under the forest HDRI"),
]


def add_section(out_dir: Path, key: str, title: str, body_html: str) -> Path:
    """Store one report section (HTML fragment); index.html is rebuilt from all of them."""
    sec = Path(out_dir) / "sections"
    sec.mkdir(parents=True, exist_ok=True)
    path = sec / f"{key}.html"
    with imageio.atomic_path(path) as tmp:
        tmp.write_text(f"<section id='{html.escape(key)}'><h2>{html.escape(title)}</h2>\n{body_html}\n</section>\n")
    return path


def write_index(out_dir: Path) -> Path:
    out_dir = Path(out_dir)
    sections = sorted((out_dir / "sections").glob("*.html"))
    body = "\n".join(p.read_text() for p in sections)
    page = f"""<!doctype html>
<html><head><meta charset="utf-8"><title>photoreal demo report</title>
<style>
body {{ font-family: sans-serif; max-width: 1200px; margin: 2em auto; color: #222; }}
figure {{ display: inline-block; margin: 0.4em; text-align: center; }}
figure img {{ width: 240px; image-rendering: pixelated; border: 1px solid #ccc; }}
figcaption {{ font-size: 0.8em; }}
table {{ border-collapse: collapse; margin: 0.5em 0; }}
td, th {{ border: 1px solid #bbb; padding: 0.2em 0.6em; text-align: right; }}
</style></head><body>
<h1>photoreal — demo report</h1>
<p>Generated {time.strftime('%Y-%m-%d %H:%M:%S')} by <code>make demo</code>.</p>
{body}
</body></html>
"""
    index = out_dir / "index.html"
    with imageio.atomic_path(index) as tmp:
        tmp.write_text(page)
    return index


def _figure(src: str, caption: str) -> str:
    return f"<figure><img src='{html.escape(src)}'><figcaption>{html.escape(caption)}</figcaption></figure>"


def demo_scenes(out_dir: Path, s: DemoSettings) -> dict:
    """Render every built-in scene (full + intrinsic layers) and add the report section."""
    out_dir = Path(out_dir)
    results = {}
    parts = []
    for name, title in DEMO_SCENES:
        settings = RenderSettings(spp=s.spp, resolution=(s.resolution, s.resolution), aovs=True, seed=s.seed)
        t0 = time.perf_counter()
        scene = load_scene(SCENES_DIR / f"{name}.xml", settings)
        rgb, layers = render_scene(scene, settings, label=name)
        seconds = time.perf_counter() - t0
        del scene
        imageio.write_exr(out_dir / f"{name}.exr", {"": rgb, **layers})
        imageio.write_png(out_dir / f"{name}.png", rgb)
        r = recompose(layers)
        figs = [_figure(f"{name}.png", "full render")]
        for layer, label, exposure in (("albedo", "albedo A", 1.0), ("irradiance", "irradiance I", 1.0),
                                       ("specular", "specular S", 1.0)):
            imageio.write_png(out_dir / f"{name}_{layer}.png", layers[layer], exposure=exposure)
            figs.append(_figure(f"{name}_{layer}.png", label))
        imageio.write_png(out_dir / f"{name}_recomposed.png", r)
        figs.append(_figure(f"{name}_recomposed.png", "R = A·I + S"))
        imageio.write_png(out_dir / f"{name}_normal.png", layers["normal"] * 0.5 + 0.5, linear=False)
        figs.append(_figure(f"{name}_normal.png", "normal"))
        p = psnr(r, rgb)
        results[name] = {"seconds": seconds, "psnr_recomposed_vs_full_db": p, "spp": s.spp,
                         "resolution": s.resolution}
        parts.append(f"<h3>{html.escape(title)}</h3><div>{''.join(figs)}</div>"
                     f"<p>{s.resolution}², {s.spp} spp, {seconds:.1f} s (incl. JIT); "
                     f"PSNR(A·I+S, full) = {p:.1f} dB.</p>")
    add_section(out_dir, "10_scenes", "Built-in scenes and intrinsic layers (seed 000, R = A·I + S)",
                "\n".join(parts))
    return results


def bench_section(out_dir: Path, bench: dict) -> None:
    rows = "".join(
        f"<tr><th>{k}</th><td>{bench[k]:.3f}</td></tr>"
        for k in ("ggx_uv_ms", "principled_ms", "ggx_uv_vs_principled", "compile_s")
    )
    add_section(out_dir, "20_bench_plugins", "Plugin speed: ggx_uv vs builtin principled",
                f"<table>{rows}</table><p>{html.escape(bench.get('scene', ''))}; "
                f"{bench['settings']['resolution']}², {bench['settings']['spp']} spp, median of "
                f"{bench['settings']['repetitions'] * bench['settings']['rounds']} renders after warm-up.</p>")


def run_demo(out_dir: str | Path, s: DemoSettings, with_bench: bool = True) -> Path:
    from .bench import PluginBenchSettings, bench_plugins, write_json

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    results = {"scenes": demo_scenes(out_dir, s)}
    if with_bench:
        bench = bench_plugins(PluginBenchSettings(resolution=128, spp=32, repetitions=3, rounds=2))
        write_json(out_dir / "bench_plugins.json", bench)
        bench_section(out_dir, bench)
        results["bench_plugins"] = {k: bench[k] for k in ("ggx_uv_ms", "principled_ms", "ggx_uv_vs_principled")}
    imageio_path = out_dir / "demo.json"
    with imageio.atomic_path(imageio_path) as tmp:
        tmp.write_text(json.dumps(results, indent=2) + "\n")
    return write_index(out_dir)
