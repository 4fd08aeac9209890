"""The neural materials sections: fitted and generated materials rendered in a scene."""

from __future__ import annotations

import html
import time
from pathlib import Path

from foundation import imageio
from foundation.assets import SCENES
from foundation.scene import RenderSettings, load_scene, render_scene

from .report import DemoSettings, add_section, bench_json, copy_chart, table


def demo_btf(out_dir: Path, s: DemoSettings, bench_dir: Path | None = None) -> dict:
    """Neural materials among classic ones (seed 002 Fig. 1); the bench's table and chart if present."""
    out_dir = Path(out_dir)
    settings = RenderSettings(spp=max(8, s.spp // 2), resolution=(int(s.resolution * 1.5), s.resolution), seed=s.seed)
    t0 = time.perf_counter()
    scene = load_scene(SCENES / "neural_materials.xml", settings)
    rgb, _ = render_scene(scene, settings, label="neural materials")
    seconds = time.perf_counter() - t0
    del scene
    imageio.write_exr(out_dir / "neural_materials.exr", {"": rgb})
    imageio.write_png(out_dir / "neural_materials.png", rgb)
    body = ("<p>Left to right: neural leather, builtin principled (metal), neural fabric, ggx_uv, neural wood; "
            "the floor is neural ceramic. All neural materials share one universal basis (M_off, M_rgb) and "
            "differ only in their 2×8-channel feature textures, fitted to held-out BTFs "
            "(<code>photoreal btf fit</code>).</p>"
            f"<div><figure><img style='width:480px' src='neural_materials.png'><figcaption>"
            f"{settings.resolution[0]}×{settings.resolution[1]}, {settings.spp} spp, {seconds:.1f} s</figcaption></figure></div>")
    b = bench_json(bench_dir, "btf")
    if b is not None:
        body += "<h3>Held-out slice PSNR per family (<code>photoreal bench btf</code>, seed 002 Table 1 / Fig. 4)</h3>"
        body += table(b["table"] + [{"family": "mean", "psnr_universal": b["psnr_universal_mean"],
                                      "psnr_per_material": b["psnr_per_material_mean"]}],
                       ["family", "material", "psnr_universal", "psnr_per_material"])
        body += f"<p>{html.escape(b.get('psnr_note', ''))}. Universal = textures fitted with the basis frozen; " \
                "per-material = NeuMIP-style network of the same architecture trained on that material alone.</p>"
        body += "<h3>Speed vs accuracy</h3>" + table(b["sweep"], ["width", "tex_res", "psnr", "ms", "vs_principled"])
        c = b["chosen"]
        body += (f"<p>principled: {b['principled_ms']:.0f} ms on the same scene; chosen (smallest within 0.5 dB of "
                 f"the best): width {c['width']}, {c['tex_res']}² → {c['ms']:.0f} ms = {c['vs_principled']:.1f}× "
                 f"principled. M_rgb throughput: Dr.Jit (plugin path) {b['mlp_evals_per_s_drjit'] / 1e6:.2f} M/s, "
                 f"torch {b['mlp_evals_per_s_torch'] / 1e6:.2f} M/s.</p>")
        if copy_chart(b, bench_dir, out_dir / "btf_speed_accuracy.png"):
            body += "<img src='btf_speed_accuracy.png'>"
    add_section(out_dir, "50_btf", "Universal neural BTF materials (seed 002)", body)
    return {"seconds": seconds}


def demo_matdiff(out_dir: Path, s: DemoSettings, bench_dir: Path | None = None) -> dict:
    """Generated materials beside fitted ones (``scenes/generated_materials.xml``); the bench's figures if present."""
    out_dir = Path(out_dir)
    settings = RenderSettings(spp=max(8, s.spp // 2), resolution=(int(s.resolution * 1.5), s.resolution), seed=s.seed)
    t0 = time.perf_counter()
    scene = load_scene(SCENES / "generated_materials.xml", settings)
    rgb, _ = render_scene(scene, settings, label="generated materials")
    seconds = time.perf_counter() - t0
    del scene
    imageio.write_png(out_dir / "generated_materials.png", rgb)
    body = ("<p>Back row: materials <b>generated</b> by the material diffusion model (keywords 'rough red leather', "
            "'wood', 'polished metal'; the last from scikit-image's brick photograph as exemplar); front row: "
            "materials <b>fitted</b> to held-out BTFs; floor: generated 'stone', tiled 8×. One universal basis decodes "
            "all of them (<code>photoreal btf generate</code>).</p>"
            f"<div><figure><img style='width:480px' src='generated_materials.png'><figcaption>"
            f"{settings.resolution[0]}×{settings.resolution[1]}, {settings.spp} spp, {seconds:.1f} s</figcaption></figure></div>")
    b = bench_json(bench_dir, "matdiff")
    if b is not None and "verdict" in b:
        rows = [{"method": k, "kid_classifier": b["kid_classifier"][k], "kid_mnv2": b["kid_mnv2"][k],
                 "nn_distance_ratio": b["nn_distance_ratio_all"].get(k, "")} for k in b["kid_mnv2"]]
        body += (f"<p><code>photoreal bench matdiff</code>: family classifier {b['classifier_accuracy_real']:.2f} on "
                 f"held-out real materials; keyword-conditioned samples classified as their family "
                 f"{b['keyword_accuracy']:.2f}" + (
                     f" ({c['triples']:.2f} ± {c.get('triples_standard_error', 0.0):.2f} at the chosen {c['steps']} steps, "
                     f"CFG {c['guidance']:g}, on {c.get('repeats', 1)} fresh sets of noise seeds)"
                     if (c := b.get("keyword_accuracy_chosen")) else "")
                 + (f"; main model trained on {html.escape(str(dv.get('name', dv.get('device'))))}"
                    if (dv := b.get("main", {}).get("device")) else "")
                 + "; exemplar ꟻLIP: " + ", ".join(
                     f"{html.escape(k)} {v:.3f}" for k, v in b["exemplar_flip"].items())
                 + f"; seam ratio at 2× size {b['seam_error']:.2f} (1 = seamless).</p>"
                 + table(rows, ["method", "kid_classifier", "kid_mnv2", "nn_distance_ratio"])
                 + "<h4>Equal-time ablations</h4>"
                 + table(b["ablation"], ["name", "accuracy", "kid_classifier", "kid_mnv2", "seam_ratio_2x",
                                          "steps_trained"]))
        for i, chart in enumerate(b.get("charts", []) + [b.get("samples_figure")]):
            name = f"matdiff_{i}.png"
            if chart and copy_chart({"chart": chart}, bench_dir, out_dir / name):
                body += f"<img src='{name}' style='max-width:100%'>"
    add_section(out_dir, "52_matdiff", "Generated neural materials (seed 002 §4.4)", body)
    return {"seconds": seconds}
