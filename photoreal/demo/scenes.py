"""The built-in scenes and their intrinsic layers."""

from __future__ import annotations

import html
import time
from pathlib import Path

from foundation import imageio
from foundation.assets import SCENES
from foundation.metrics import psnr
from foundation.scene import RenderSettings, load_scene, recompose, render_scene

from .report import DemoSettings, add_section, figure


DEMO_SCENES = [
    ("josie", "Cyberware head 'josie' (real scan) — ggx_uv under the studio HDRI"),
    ("material_test", "Material test — ggx_uv (left) vs builtin principled (right), sunset HDRI"),
    ("armadillo", "Stanford Armadillo — ggx_uv under the forest HDRI"),
]


def demo_scenes(out_dir: Path, s: DemoSettings) -> dict:
    """Render every built-in scene (full + intrinsic layers) and add the report section."""
    out_dir = Path(out_dir)
    results = {}
    parts = []
    for name, title in DEMO_SCENES:
        settings = RenderSettings(spp=s.spp, resolution=(s.resolution, s.resolution), aovs=True, seed=s.seed)
        t0 = time.perf_counter()
        scene = load_scene(SCENES / f"{name}.xml", settings)
        rgb, layers = render_scene(scene, settings, label=name)
        seconds = time.perf_counter() - t0
        del scene
        imageio.write_exr(out_dir / f"{name}.exr", {"": rgb, **layers})
        imageio.write_png(out_dir / f"{name}.png", rgb)
        r = recompose(layers)
        figs = [figure(f"{name}.png", "full render")]
        for layer, label, exposure in (("albedo", "albedo A", 1.0), ("irradiance", "irradiance I", 1.0),
                                       ("specular", "specular S", 1.0)):
            imageio.write_png(out_dir / f"{name}_{layer}.png", layers[layer], exposure=exposure)
            figs.append(figure(f"{name}_{layer}.png", label))
        imageio.write_png(out_dir / f"{name}_recomposed.png", r)
        figs.append(figure(f"{name}_recomposed.png", "R = A·I + S"))
        imageio.write_png(out_dir / f"{name}_normal.png", layers["normal"] * 0.5 + 0.5, linear=False)
        figs.append(figure(f"{name}_normal.png", "normal"))
        p = psnr(r, rgb)
        results[name] = {"seconds": seconds, "psnr_recomposed_vs_full_db": p, "spp": s.spp,
                         "resolution": s.resolution}
        parts.append(f"<h3>{html.escape(title)}</h3><div>{''.join(figs)}</div>"
                     f"<p>{s.resolution}², {s.spp} spp, {seconds:.1f} s (incl. JIT); "
                     f"PSNR(A·I+S, full) = {p:.1f} dB.</p>")
    add_section(out_dir, "10_scenes", "Built-in scenes and intrinsic layers (seed 000, R = A·I + S)",
                "\n".join(parts))
    return results
