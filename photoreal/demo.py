"""`make demo`: render the built-in scenes, their intrinsic layers, and an HTML report.

Sections are small HTML fragments stored under ``OUT/sections/`` (:func:`add_section`) and stitched
into ``index.html`` in name order. Benchmark tables come from the JSON files in ``bench_dir`` (what
``photoreal bench …`` wrote); the demo never reads the working directory or the tests.
"""

from __future__ import annotations

import html
import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from foundation import imageio, validate
from foundation.assets import ARMADILLO, FACE, SCENES
from foundation.files import check_output_dir, read_json, write_json, write_text
from foundation.metrics import psnr
from foundation.records import to_json
from foundation.scene import RenderSettings, load_scene, recompose, render_scene

from .benchmarks import json_name, work_folder


@dataclass
class DemoSettings:
    resolution: int = 256  #: image side of the renders (the face's camera renders: at most 192; the photo's relit: 256)
    spp: int = 64  #: samples per pixel (the face's camera renders and the photo's relit: at most 64)
    seed: int = 0
    face: bool = True
    face_uv_res: int = 256
    morph_iterations: int = 100  #: 0 skips the morphing section
    btf: bool = True  #: neural materials scene (+ `photoreal bench btf` tables when present)
    plugin_bench: bool = True  #: time ggx_uv against principled (a short run of `photoreal bench plugins`)

    def __post_init__(self):
        validate.integer("resolution", self.resolution, 8, 4096)
        validate.integer("spp", self.spp, 1)
        validate.seed("seed", self.seed)
        validate.integer("face_uv_res", self.face_uv_res, 16, 4096)
        validate.integer("morph_iterations", self.morph_iterations, 0)


DEMO_SCENES = [
    ("josie", "Cyberware head 'josie' (real scan) — ggx_uv under the studio HDRI"),
    ("material_test", "Material test — ggx_uv (left) vs builtin principled (right), sunset HDRI"),
    ("armadillo", "Stanford Armadillo — ggx_uv under the forest HDRI"),
]


def add_section(out_dir: Path, key: str, title: str, body_html: str) -> Path:
    """Store one report section (HTML fragment); index.html is rebuilt from all of them."""
    path = Path(out_dir) / "sections" / f"{key}.html"
    return write_text(path, f"<section id='{html.escape(key)}'><h2>{html.escape(title)}</h2>\n{body_html}\n</section>\n")


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
    return write_text(out_dir / "index.html", page)


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
        scene = load_scene(SCENES / f"{name}.xml", settings)
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


def _table(rows: list[dict], cols: list[str]) -> str:
    def fmt(v):
        if isinstance(v, float):  # small errors (MSE ~1e-3) keep 4 significant digits
            return f"{v:.4g}" if 0 < abs(v) < 0.1 else f"{v:.3f}"
        return html.escape(str(v))

    head = "".join(f"<th>{html.escape(c)}</th>" for c in cols)
    body = "".join("<tr>" + "".join(f"<td>{fmt(r.get(c, ''))}</td>" for c in cols) + "</tr>" for r in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def _bench_json(bench_dir: Path | None, name: str) -> dict | None:
    """Benchmark ``name``'s JSON (as `photoreal bench all` names it) from ``bench_dir`` if it is there; else None."""
    path = None if bench_dir is None else Path(bench_dir) / json_name(name)
    if path is None or not path.is_file():
        return None
    return read_json(path, "benchmark result")


def demo_face(out_dir: Path, uv_res: int = 256, seed: int = 0, bench_dir: Path | None = None,
              render_res: int = 192, render_spp: int = 64) -> dict:
    """Josie scan: benchmark, UV-space fit, maps and relit renders (``render_res``², ``render_spp``) against
    ground truth."""
    from inverse.face import FaceBenchmarkSettings, FaceFitSettings, evaluate_fit, fit_face, load_benchmark, make_benchmark

    face_dir = Path(out_dir) / "face"
    bench = load_benchmark(make_benchmark(FACE / "cyberheads" / "josie.obj", face_dir / "benchmark",
                                          FaceBenchmarkSettings(uv_res=uv_res, seed=seed, render_res=render_res,
                                                                render_spp=render_spp)))
    result = fit_face(bench, FaceFitSettings(seed=seed))
    relit: dict = {}
    fm = evaluate_fit(bench, result, images=relit)
    m = to_json(fm)
    gt, fit = bench.ground_truth, result.maps
    figs = []
    for name, a, b, linear in (("albedo", gt["albedo"], fit["albedo"] * fm.albedo_scale, True),
                               ("normal", gt["normal"] * 0.5 + 0.5, fit["normal"] * 0.5 + 0.5, False),
                               ("roughness", np.repeat(gt["roughness"], 3, -1), np.repeat(fit["roughness"], 3, -1), False),
                               ("specular", np.repeat(gt["specular"], 3, -1), np.repeat(fit["specular"], 3, -1), False)):
        imageio.write_png(face_dir / f"gt_{name}.png", a, linear=linear)
        imageio.write_png(face_dir / f"fit_{name}.png", b, linear=linear)
        figs.append(_figure(f"face/gt_{name}.png", f"{name}: ground truth") +
                    _figure(f"face/fit_{name}.png", f"{name}: fitted"))
    imageio.write_png(face_dir / "observation.png", bench.observations["v0_l0"])
    relit_figs = []
    for hdri, img in relit.items():
        imageio.write_png(face_dir / f"relit_gt_{hdri}.png", bench.heldout[hdri])
        imageio.write_png(face_dir / f"relit_fit_{hdri}.png", img)
        relit_figs.append(_figure(f"face/relit_gt_{hdri}.png", f"{hdri}: ground truth")
                          + _figure(f"face/relit_fit_{hdri}.png",
                                    f"{hdri}: fitted maps ({m['relit'][hdri]['psnr']:.1f} dB)"))
    rows = [{"metric": k, "value": float(m[k])} for k in ("albedo_psnr", "albedo_ssim", "albedo_scale", "normal_err_deg",
                                                           "roughness_mae", "specular_mae", "relit_psnr", "relit_flip",
                                                           "observed_fraction", "seconds")]
    body = (f"<p>Real Cyberware scan <i>josie</i>; ground-truth maps {uv_res}² (scanned albedo + seeded relief, "
            f"roughness, specular); {len(bench.meta.lights)} directional lights × {len(bench.meta.views)} views "
            f"rendered by Mitsuba with ggx_uv, taken texel-aligned. Fit: Adam through the UV-space GGX shader "
            f"(the plugin's own functions). Held-out: real HDRIs.</p>"
            + _figure("face/observation.png", "one observation (view 0, light 0)")
            + "<div>" + "".join(figs) + "</div>" + _table(rows, ["metric", "value"])
            + "<h3>Relit under held-out HDRIs</h3><div>" + "".join(relit_figs) + "</div>")
    fb = _bench_json(bench_dir, "face")
    if fb is not None:
        body += "<h3>Speed vs accuracy and stability (<code>photoreal bench face</code>)</h3>"
        body += _table(fb["sweep"], ["uv_res", "seconds", "relit_psnr", "albedo_psnr", "normal_err_deg"])
        body += f"<p>chosen_uv_res = {fb['chosen_uv_res']} (smallest within 0.5 dB of the best relit PSNR)</p>"
        if _copy_chart(fb, bench_dir, face_dir / "face_speed_accuracy.png"):
            body += "<img src='face/face_speed_accuracy.png'>"
        body += _table([{"case": k, **v} for k, v in fb["stability"].items()],
                       ["case", "albedo_psnr", "normal_err_deg", "relit_psnr", "albedo_psnr_drop_db",
                        "relit_psnr_drop_db", "observed_fraction", "finite"])
    add_section(out_dir, "30_face", "Face PBR fitting in UV space (seed 003) on a real scan", body)
    return {k: m[k] for k in ("albedo_psnr", "normal_err_deg", "relit_psnr", "seconds")}


def demo_photo(out_dir: Path, uv_res: int = 256, seed: int = 0, relight_res: int = 256,
               relight_spp: int = 64) -> dict | None:
    """scikit-image's astronaut photograph → relightable face (landmarks from MediaPipe, run now)."""
    import skimage.data

    from inverse.face import PhotoFitSettings, photo_to_face

    try:
        import mediapipe  # noqa: F401
    except ImportError:
        add_section(out_dir, "31_photo", "One real photograph to a relightable face",
                    "<p>Skipped: MediaPipe (the landmark detector) is not installed; "
                    "<code>pip install mediapipe==0.10.14</code> (the project's <code>face</code> extra).</p>")
        return None
    photo_dir = Path(out_dir) / "photo"
    source = "MediaPipe Face Mesh 0.10.14 (run now)"
    r = to_json(photo_to_face(skimage.data.astronaut(), photo_dir, PhotoFitSettings(
        uv_res=uv_res, seed=seed, relight_res=relight_res, relight_spp=relight_spp)))
    figs = [_figure("photo/photo.png", "input photo (scikit-image astronaut)"),
            _figure("photo/photo_uv.png", "photo unwrapped into UV"),
            _figure("photo/visibility.png", "visibility mask"),
            _figure("photo/albedo.png", "delit albedo (filled)"),
            _figure("photo/rerender.png",
                    f"re-rendered, fitted light ({r['rerender_psnr_visible_face']:.1f} dB on the face)")]
    figs += [_figure(f"photo/relit_{h}.png", f"relit: {h} HDRI") for h in r["settings"]["hdris"]]
    body = (f"<p>Landmarks: {html.escape(source)}. Template: MediaPipe canonical face, similarity + Laplacian "
            f"deformation. Landmark reprojection error <b>{r['landmark_reprojection_px']:.2f} px</b> "
            f"(similarity alone {r['landmark_reprojection_px_rigid']:.2f} px). Lighting fitted jointly "
            f"({len(r['lighting']['lights'])} directional + ambient) and divided out; normal, roughness and "
            f"specular are the template's and skin defaults (a baseline where seed 003 uses learned models).</p>"
            f"<div>{''.join(figs)}</div>")
    add_section(out_dir, "31_photo", "One real photograph to a relightable face", body)
    return {k: r[k] for k in ("landmark_reprojection_px", "rerender_psnr_visible_face", "seconds")}


def _where(mr) -> str:
    """Where the planarity prior acted, when not on every edge."""
    p = mr.planarity
    if p.where == "all" or not p.weight:
        return ""
    why = "those beside a triangle a fitted photo sees" if p.where == "seen" else "those on parts that are not thin"
    return f" on {p.edges} of {p.edges_all} interior edges ({why})"


def _colour_why(mr) -> str:
    """Why the morph ran with its colour-prior weight, in words."""
    c = mr.colour_selection
    if c is not None:
        return (f"the input's colours are smooth; at iteration {c.at_iteration} the validation photos "
                f"{'kept' if c.kept else 'dropped'} the prior: L1 {c.validation_l1_with:.4f} with, "
                f"{c.validation_l1_without:.4f} without (kept only {c.margin:.1%} or more below)")
    if mr.colour_prior and mr.colour_prior.auto:
        return f"auto: mean colour step per edge of the input {mr.colour_prior.input_colour_step:.4f}, on below 0.015"
    return "given"


def _light_why(mr) -> str:
    """Whether the morph ran with the light estimate and colour large steps, and why, in words."""
    c = getattr(mr, "light_selection", None)
    if c is None:
        s = mr.settings
        return (f"given: light estimate every {s.indirect_every} iterations, colour λ {s.colour_lambda:g}"
                if s.indirect_every or s.colour_lambda else "off")
    return (f"{'on' if c.kept else 'off'}: at iteration {c.at_iteration} the validation photos, each run measured "
            f"after a fresh light estimate, gave L1 {c.validation_l1_with:.4f} with, {c.validation_l1_without:.4f} "
            f"without (kept only {c.margin:.1%} or more below)")


def _step_why(mr) -> str:
    """Which step the morph's positions took (uniform or quantile Adam), and why, in words."""
    c = getattr(mr, "step_selection", None)
    if c is None:
        q = mr.settings.adam_quantile
        return "uniform Adam (given)" if q == 1.0 else f"quantile {q:g} of Adam's second moments (given)"
    return (f"{f'quantile {c.quantile:g}, lr {c.lr:g}' if c.kept else 'uniform Adam'}: at iteration {c.at_iteration} "
            f"the validation photos gave L1 {c.validation_l1_quantile:.4f} with the quantile step, "
            f"{c.validation_l1_uniform:.4f} with uniform Adam (kept only {c.margin:.1%} or more below)")


def demo_morph(out_dir: Path, iterations: int = 100, seed: int = 0, bench_dir: Path | None = None) -> dict:
    """Armadillo morph benchmark: degraded input vs morphed vs photo, metrics; bench tables if present."""
    import shutil

    from inverse.morph import (MorphBenchmarkSettings, MorphSettings, benchmark_errors, load_morph_benchmark,
                               make_morph_benchmark, run_morph)

    mdir = Path(out_dir) / "morph"
    bench = load_morph_benchmark(make_morph_benchmark(ARMADILLO, mdir / "benchmark", MorphBenchmarkSettings(seed=seed)))
    shutil.rmtree(mdir / "run", ignore_errors=True)
    mr = run_morph(bench, mdir / "run", MorphSettings(iterations=iterations, seed=seed))
    m = to_json(mr)
    m.update(inverted_before_repair=mr.repair.inverted_before_repair if mr.repair else None,
             repaired_vertices=mr.repair.repaired_vertices if mr.repair else None,
             border_turned_before=mr.border_turns.turned_before if mr.border_turns else None,
             border_turned_after=mr.border_turns.turned_after if mr.border_turns else None)
    i = bench.meta.test[0]
    figs = "".join(_figure(f"morph/run/heldout_{k}_view{i:02d}.png", label) for k, label in
                   (("input", "coarse input (held-out view)"), ("morphed", "morphed"), ("photo", "photo")))
    rows = [{"metric": k, "value": float(m[k])} for k in
            ("chamfer_input", "chamfer_morphed", "chamfer_reduction", "psnr_heldout_input", "psnr_heldout_morphed",
             "spikes", "inverted_triangles", "inverted_before_repair", "repaired_vertices", "border_turned_before",
             "border_turned_after", "seconds")
            if m.get(k) is not None]
    # where the error sits (photoreal morph errors): what of the input's error the morph kept, what it made
    err = {e.name: e for e in benchmark_errors(bench, {"morphed": mdir / "run" / "morphed.ply"}, mdir / "errors").meshes}
    rows += [{"metric": "input's error left (slope)", "value": err["morphed"].input_error_left},
             {"metric": "new error (rms)", "value": err["morphed"].new_error_rms}]
    body = (f"<p>Stanford Armadillo, {len(bench.meta.cameras)} drone-orbit photos path traced under the "
            f"{bench.meta.hdri} HDRI; degraded input: {bench.meta.degradation.coarse_vertices} vertices "
            f"with bumps, wobble and misregistered colours. Morph: {iterations} iterations, large steps, lit mode, "
            f"3 views per step, input remeshed to {m['vertices']} vertices; folds left at the end are unfolded "
            f"locally and counted (inverted_before_repair), and so are curls of an open border (its triangles turned "
            f"more than {mr.settings.border_turn_deg:g}° from the start, border_turned_before / after). Planarity prior weight {mr.planarity.weight:g}"
            f"{_where(mr)} (auto: the input's largest plane holds {mr.planarity.dominant_plane_fraction or 0:.0%} of its area; "
            f"on from {mr.settings.planarity_auto_threshold:.0%}, as on the village). Colour prior weight {mr.colour_prior.weight:g} "
            f"({_colour_why(mr)}). Light estimate and colour large steps {_light_why(mr)}. Step {_step_why(mr)}.</p><div>{figs}</div>" + _table(rows, ["metric", "value"])
            + "<p>Where the error sits (<code>photoreal morph errors</code>): signed distance to the truth, blue "
              "behind it, red in front, coarse input above, morphed below; the input's error left is the slope of "
              "the result's signed distance on the input's (1: kept, 0: gone), the new error what that leaves.</p>"
            + _figure("morph/errors/errors.png", "signed distance to the truth")
            + "<p>Where the orientation is wrong: the triangles facing against the truth (the suite's facing "
              "target; the row's label gives their share of the area), from the camera that sees most of them.</p>"
            + _figure("morph/errors/facing.png", "triangles facing against the truth"))
    mb = _bench_json(bench_dir, "morph")
    if mb is not None:
        body += "<h3>Benchmark (<code>photoreal bench morph</code>)</h3>"
        for case, r in mb["cases"].items():
            cols = ["chamfer_input", "chamfer_morphed", "chamfer_reduction", "psnr_heldout_input",
                    "psnr_heldout_morphed", "spikes", "s_per_iter_10k_4views_128", "s_per_iter_baseline",
                    "chosen_vertices", "dominant_plane_fraction", "planarity_weight"]
            body += f"<h4>{html.escape(case)}</h4>" + _table([{k: r.get(k) for k in cols}], cols)
            body += "<p>Stability</p>" + _table([{"case": k, **v} for k, v in r["stability"].items()],
                                               ["case", "chamfer_input", "chamfer_morphed", "psnr_heldout_input",
                                                "psnr_heldout_morphed", "spikes", "inverted_triangles",
                                                "inverted_before_repair", "converged"])
        if _copy_chart(mb, bench_dir, mdir / "morph_speed_accuracy.png"):
            body += "<img src='morph/morph_speed_accuracy.png'>"
    add_section(out_dir, "40_morph", "Geometry morphing of a coarse reconstruction, against ground truth", body)
    return {k: m[k] for k in ("chamfer_input", "chamfer_morphed", "psnr_heldout_input", "psnr_heldout_morphed")}


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
    b = _bench_json(bench_dir, "btf")
    if b is not None:
        body += "<h3>Held-out slice PSNR per family (<code>photoreal bench btf</code>, seed 002 Table 1 / Fig. 4)</h3>"
        body += _table(b["table"] + [{"family": "mean", "psnr_universal": b["psnr_universal_mean"],
                                      "psnr_per_material": b["psnr_per_material_mean"]}],
                       ["family", "material", "psnr_universal", "psnr_per_material"])
        body += f"<p>{html.escape(b.get('psnr_note', ''))}. Universal = textures fitted with the basis frozen; " \
                "per-material = NeuMIP-style network of the same architecture trained on that material alone.</p>"
        body += "<h3>Speed vs accuracy</h3>" + _table(b["sweep"], ["width", "tex_res", "psnr", "ms", "vs_principled"])
        c = b["chosen"]
        body += (f"<p>principled: {b['principled_ms']:.0f} ms on the same scene; chosen (smallest within 0.5 dB of "
                 f"the best): width {c['width']}, {c['tex_res']}² → {c['ms']:.0f} ms = {c['vs_principled']:.1f}× "
                 f"principled. M_rgb throughput: Dr.Jit (plugin path) {b['mlp_evals_per_s_drjit'] / 1e6:.2f} M/s, "
                 f"torch {b['mlp_evals_per_s_torch'] / 1e6:.2f} M/s.</p>")
        if _copy_chart(b, bench_dir, out_dir / "btf_speed_accuracy.png"):
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
    b = _bench_json(bench_dir, "matdiff")
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
                 + _table(rows, ["method", "kid_classifier", "kid_mnv2", "nn_distance_ratio"])
                 + "<h4>Equal-time ablations</h4>"
                 + _table(b["ablation"], ["name", "accuracy", "kid_classifier", "kid_mnv2", "seam_ratio_2x",
                                          "steps_trained"]))
        for i, chart in enumerate(b.get("charts", []) + [b.get("samples_figure")]):
            name = f"matdiff_{i}.png"
            if chart and _copy_chart({"chart": chart}, bench_dir, out_dir / name):
                body += f"<img src='{name}' style='max-width:100%'>"
    add_section(out_dir, "52_matdiff", "Generated neural materials (seed 002 §4.4)", body)
    return {"seconds": seconds}


def run_demo(out_dir: str | Path = "out/demo", s: DemoSettings | None = None,
             bench_dir: str | Path | None = None) -> Path:
    """Render every section into ``out_dir`` and write ``index.html``; bench tables from ``bench_dir``'s JSON."""
    s = s or DemoSettings()
    from .benchmarks.plugins import PluginBenchSettings, bench_plugins

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


def demo_benchmarks(out_dir: Path, bench_dir: Path | None) -> dict:
    """One table of every registered benchmark whose JSON is in ``bench_dir``: the figures its summary shows, and
    the command that makes it."""
    from .benchmarks import REGISTRY, summary

    rows, found = [], {}
    for name, entry in REGISTRY.items():
        result = _bench_json(bench_dir, name)
        if result is None:
            continue
        try:
            shown = summary(name, result)
        except (KeyError, TypeError):  # a result written by an older version of the benchmark
            continue
        found[name] = sorted(shown)
        text = json.dumps(shown, default=str)
        rows.append(f"<tr><th>{html.escape(name)}</th><td><code>photoreal bench {html.escape(name)} --json "
                    f"{html.escape(json_name(name))}</code></td><td><small>{html.escape(text[:600])}"
                    f"{'…' if len(text) > 600 else ''}</small></td></tr>")
    missing = [n for n, e in REGISTRY.items() if e.in_all and n not in found]
    body = (f"<table><tr><th>benchmark</th><th>command</th><th>summary</th></tr>{''.join(rows)}</table>" if rows
            else "<p>No benchmark results in the bench folder.</p>")
    if missing:
        body += (f"<p>Not run yet: {html.escape(', '.join(missing))} (<code>photoreal bench all --out-dir "
                 f"{html.escape(str(bench_dir or 'out/bench'))}</code> runs every one).</p>")
    add_section(out_dir, "90_benchmarks", "Every benchmark", body)
    return found


def _copy_chart(result: dict, bench_dir: Path | None, dest: Path) -> bool:
    """Copy a benchmark's chart (found beside its JSON, by the file name it recorded) into the report."""
    import shutil

    if not result.get("chart") or bench_dir is None:
        return False
    src = Path(bench_dir) / Path(result["chart"]).name
    if not src.is_file():
        return False
    dest.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(src, dest)
    return True


def demo_gan(out_dir: Path, bench_dir: Path | None = None) -> dict | None:
    """The `photoreal bench gan` table and chart (held-out views), when that JSON exists; no training here."""
    b = _bench_json(bench_dir, "gan")
    if b is None:
        return None
    Path(out_dir).mkdir(parents=True, exist_ok=True)
    cols = ["model", "mse", "me", "one_minus_ssim", "nrmse", "sam_deg", "flip", "psnr", "train_s", "infer_ms"]

    def rows(r: dict) -> list[dict]:
        return [{"model": name, **m, "train_s": r["train_seconds"].get("morph" if name == "morphed" else name, ""),
                 "infer_ms": r["infer_ms_per_image"].get(name, "")} for name, m in r["heldout"].items()]

    s = b["settings"]
    body = (f"<p>Held-out views ({', '.join(s['cases'])}), mean over cases; input = coarse mesh render, morphed = "
            f"morph run ({s['morph_iterations']} iterations), GANs trained {s['seconds_per_model']:.0f} s each on "
            f"{s['crop']}² crops, joint {s['joint_seconds']:.0f} s from scratch; the two fine-tunes continue the "
            f"two-stage Morph-GAN for {s.get('finetune_seconds', 0):.0f} s more each, with the mesh fixed "
            f"(morph_gan_finetune) or optimised jointly through the renderer (joint_finetune). "
            f"Lower is better except PSNR.</p>" + _table(rows(b), cols))
    body += "<p>Thesis ordering on held-out views: " + ", ".join(
        f"{html.escape(k)} = {v}" for k, v in b.get("ordering", {}).items()) + "</p>"
    regions = b.get("artifact_regions") or {}
    if regions:
        rcols = ["region", "model", "mse", "me", "one_minus_ssim", "flip", "pixels"]
        body += ("<p>Errors per artifact region (held-out pixels of cut chimneys, lifted chimneys, geometric "
                 "edges, flat surfaces; from ground-truth renders; pixel-weighted over cases):</p>" + _table(
                     [{"region": reg, "model": row, **m} for reg, t in regions.items() for row, m in t.items() if m],
                     rcols))
    for case, r in b.get("cases", {}).items():
        body += f"<h4>{html.escape(case)}</h4>" + _table(rows(r), cols)
    if _copy_chart(b, bench_dir, Path(out_dir) / "gan_speed_accuracy.png"):
        body += "<img src='gan_speed_accuracy.png'>"
    add_section(out_dir, "45_gan", "GAN refinement: pix2pix, CycleGAN, Morph-GAN, joint training (REAL-DIBS §3, §5, §6)",
                body)
    return {k: v.get("mse") for k, v in b["heldout"].items()}


def demo_diffrender(out_dir: Path, bench_dir: Path | None = None) -> dict | None:
    """The `photoreal bench diffrender` tables, side-by-side views and sweep chart, when that JSON exists."""
    b = _bench_json(bench_dir, "diffrender")
    if b is None or "ablation" not in b:
        return None
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    cols = ["method", "psnr", "one_minus_ssim", "flip", "mse", "kid_mnv2", "fid_mnv2", "kid_mnv2_spatial"]
    rows = [{"method": k, **{c: m[c] for c in cols[1:5]}, "kid_mnv2": b["kid_mnv2"].get(k, ""),
             "fid_mnv2": b["fid_mnv2"].get(k, ""), "kid_mnv2_spatial": b.get("kid_mnv2_spatial", {}).get(k, "")}
            for k, m in b["heldout"].items()]
    s = b["settings"]
    body = (f"<p>Held-out views of {', '.join(s['cases'])} (mean over cases; diffusion: mean over {s['seeds']} sampling "
            f"seeds, {b['ddim_steps']} DDIM steps, mean of {b.get('draws', 1)} per view, guidance {b['guidance']}). diffusion = rendered from the morphed "
            f"mesh's G-buffers, diffusion_coarse = from the coarse mesh's. KID/FID use ImageNet MobileNetV2 "
            f"features (not Inception); kid_mnv2_spatial uses every position of their 4×4 last feature map (16 "
            f"vectors per image). Lower is better except PSNR.</p>" + _table(rows, cols))
    if b.get("references"):
        body += ("<h4>What the targets demand (nothing trained)</h4><p>pbr_morphed_clean = the morphed mesh's "
                 "recomposition from G-buffers at " + str(s.get("reference_spp", "")) + " spp (what denoising alone "
                 "can gain over pbr_morphed); truth_clean = the ground truth itself path traced at as many samples "
                 "(the photos' own noise floor).</p>"
                 + _table([{"method": k, **m} for k, m in b["references"].items()],
                          ["method", "psnr", "one_minus_ssim", "flip", "mse"]))
    dist = b.get("distribution", {})
    if "photos_clean" in dist:
        rows = [{"set": k, **{f"{m}_photos": dist["photos"].get(k, {}).get(m, "") for m in ("kid", "kid_std", "kid_spatial")},
                 **{f"{m}_clean": v[m] for m in ("kid", "kid_std", "kid_spatial", "kid_spatial_std")}}
                for k, v in dist["photos_clean"].items()]
        body += ("<h4>MobileNetV2-KID against the photos and against the same views without Monte-Carlo noise</h4>"
                 "<p>_clean = distances to the held-out views path traced again at the references' samples per "
                 "pixel (another seed); ± = jackknife over images. The features respond to the photos' "
                 f"Monte-Carlo noise ({s.get('photo_spp', 64)} spp) as to texture: truth_clean (the true scene, "
                 "clean) against the photos is the oracle of what the first columns can tell.</p>"
                 + _table(rows, ["set", "kid_photos", "kid_std_photos", "kid_spatial_photos", "kid_clean",
                                 "kid_std_clean", "kid_spatial_clean", "kid_spatial_std_clean"]))
    for c, u in b.get("unseen", {}).items():
        body += f"<h4>Unseen mesh: {html.escape(c)} (never trained on)</h4>" + _table(
            [{"method": k, **m} for k, m in u.items()], ["method", "psnr", "one_minus_ssim", "flip", "mse"])
    d = b["decomposition"]
    body += (f"<h4>Decomposition network</h4><p>{d['scenes']} procedural scenes ({d['heldout_scenes']} held out), "
             f"{d['steps']} steps; held-out PSNR per layer (dB): "
             + ", ".join(f"{k} {v:.2f}" for k, v in d["psnr"].items()) + " (trivial decomposition A = image, I = 1, "
             "S = 0: " + ", ".join(f"{k} {v:.2f}" for k, v in d.get("psnr_trivial", {}).items())
             + f"); {d['extra_pairs']} extra pairs.</p>")
    body += (f"<h4>Equal-time ablations ({s['ablation_seconds']:.0f} s each)</h4>"
             + _table([{**r, **{f"{c} flip": m["flip"] for c, m in r.get("unseen", {}).items()}} for r in b["ablation"]],
                      ["run", "global_source", "residual", "known_background", "decomposed_pairs", "sources",
                       "train_steps", "steps", "psnr", "flip", "one_minus_ssim", "mse",
                       *[f"{c} flip" for c in s.get("unseen", ())], "seconds_per_image"]))
    c = b["chosen"]
    tol = (f"{100 * c['tolerance_rel']:g} % of the best ꟻLIP" if "tolerance_rel" in c
           else f"{c.get('tolerance_flip')} ꟻLIP of the best")
    size = (f" The main model's size was chosen on the {c['size_from']}: widths <b>{c['main_widths']}</b>."
            if "main_widths" in c else "")
    body += (f"<p>Sampler chosen automatically (cheapest within {tol}): the <b>{c['model']}</b> row, "
             f"<b>{c['steps']}</b> DDIM steps, mean of {c.get('draws', 1)} per view, guidance "
             f"{c.get('guidance', b['guidance'])}, {c['seconds_per_image']:.2f} s per 128² image.{size}</p>")
    for key, name in (("chart", "diffrender_sweep.png"), ("views_figure", "diffrender_views.png")):
        if _copy_chart({"chart": b.get(key)}, bench_dir, out_dir / name):
            body += f"<img src='{name}' style='max-width:100%'>"
    add_section(out_dir, "48_diffrender", "Intrinsic-conditioned diffusion renderer (seed 000)", body)
    return {k: v.get("flip") for k, v in b["heldout"].items()}


def _seed_spread(spread: dict | None) -> str:
    """The decomposition ablation over training seeds (bench face-learned --ablation-seeds): mean ± sd per metric."""
    if not spread:
        return ""
    keys = ("normal_err_deg", "roughness_mae", "specular_mae", "albedo_psnr_unseen")
    rows = [{"variant": v, **{k: f"{m[k]['mean']:.4g} ± {m[k]['std']:.2g}" for k in keys}}
            for v, m in spread.items() if v != "seeds"]
    return (f"<p>Over training seeds {', '.join(map(str, spread['seeds']))} (mean ± sample sd):</p>"
            + _table(rows, ["variant", *keys]))


def demo_face_learned(out_dir: Path, bench_dir: Path | None = None) -> dict | None:
    """The `photoreal bench face-learned` tables and map figure, when that JSON exists (no training here)."""
    b = _bench_json(bench_dir, "face-learned")
    if b is None or "end_to_end" not in b:
        return None
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    c = b["completion"]
    body = (f"<p>Trained on instances of the scan(s) {', '.join(b['train_scans'])}; judged on the held-out scan "
            f"<b>{html.escape(b['heldout_scan'])}</b> under held-out HDRIs ({', '.join(b['eval_hdris'])}), one random "
            f"pose each ({c['seen_fraction']:.0%} of the texels seen on average). Albedo PSNR after one global scale "
            f"fitted on the seen texels; models at {b['model_res']}², maps at {b['data_res']}².</p>"
            "<h4>Completion + light homogenisation</h4>"
            + _table([{"method": k, **c[k]} for k in ("baseline", "learned", "learned_one_sample")],
                     ["method", "albedo_psnr_seen", "albedo_psnr_unseen", "albedo_psnr_all"])
            + "<h4>Decomposition (equal training time)</h4>"
            + _table([{"variant": k, **v} for k, v in b["decomposition"].items()],
                     ["variant", "normal_err_deg", "roughness_mae", "specular_mae", "trained_parameters", "steps"])
            + _seed_spread(b.get("decomposition_seeds"))
            + f"<h4>2× super-resolution ({b['superres']['from']}² → {b['superres']['to']}², true maps)</h4>"
            + _table([{"method": k, **b["superres"][k]} for k in ("bicubic", "learned")],
                     ["method", "albedo_psnr", "normal_err_deg", "roughness_psnr", "specular_psnr"]))
    e = b["end_to_end"]
    rows = [{"method": k, **{m: v[m] for m in ("albedo_psnr_seen", "albedo_psnr_unseen", "normal_err_deg",
                                                "roughness_mae", "specular_mae")},
             "relit_psnr": v.get("relit", {}).get("psnr", ""), "relit_flip": v.get("relit", {}).get("flip", "")}
            for k, v in {"baseline": e["baseline"], **e["stages"]}.items()]
    body += (f"<h4>End to end ({e['relit_instances']} instances relit under {', '.join(e['relight_hdris'])})</h4>"
             + _table(rows, ["method", "albedo_psnr_seen", "albedo_psnr_unseen", "normal_err_deg", "roughness_mae",
                             "specular_mae", "relit_psnr", "relit_flip"]))
    if b.get("cross_model_fit"):
        body += ("<h4>The existing fit on observations it did not render</h4>"
                 + _table([{"benchmark": k, **v} for k, v in b["cross_model_fit"].items()],
                          ["benchmark", "albedo_psnr", "normal_err_deg", "roughness_mae", "specular_mae", "relit_psnr",
                           "relit_flip"]))
    if b.get("astronaut") and "skipped" not in b["astronaut"]:
        import shutil

        body += "<p>Astronaut photograph (no ground truth), re-render PSNR on the visible face: " + ", ".join(
            f"{k} {v['rerender_psnr_visible_face']:.2f} dB" for k, v in b["astronaut"].items()) + "</p><div>"
        for k, v in b["astronaut"].items():
            for pic in ("albedo.png", "relit_studio.png", "relit_sunset.png"):
                src = Path(v.get("folder", "")) / pic
                if not src.is_file() and bench_dir is not None:  # the bench folder was moved: look beside its JSON
                    src = work_folder("face-learned", None, Path(bench_dir) / json_name("face-learned")) / Path(v.get("folder", "")).name / pic
                if src.is_file():
                    name = f"face_learned_astronaut_{k}_{pic}"
                    shutil.copyfile(src, out_dir / name)
                    body += _figure(name, f"{k}: {pic[:-4].replace('_', ' ')}")
        body += "</div>"
    if _copy_chart({"chart": b.get("figure")}, bench_dir, out_dir / "face_learned_maps.png"):
        body += "<img src='face_learned_maps.png' style='max-width:100%'>"
    add_section(out_dir, "42_face_learned", "Learned UV-space face stages (seed 003 §2–§4)", body)
    return b.get("verdict")


def demo_scale(out_dir: Path, bench_dir: Path | None = None) -> dict | None:
    """The `photoreal bench scale` table and chart (serial vs process pool vs Ray), when that JSON exists."""
    b = _bench_json(bench_dir, "scale")
    if b is None:
        return None
    rows = [{"run": "serial, one thread per item", "seconds": b["serial_s"]},
            {"run": "serial, all threads to Dr.Jit", "seconds": b["serial_all_threads_s"]},
            *({"run": f"process pool, {w} worker(s)", "seconds": t} for w, t in b["pool_s"].items()),
            *({"run": f"Ray, {w} CPUs", "seconds": t} for w, t in b.get("ray_s", {}).items())]
    for r in rows:
        r["items_per_s"] = b["items"] / r["seconds"]
    body = (f"<p>{b['items']} items ({html.escape(b['item'])}) on {b['cores']} cores: speed-up of the 2-worker pool "
            f"<b>{b['speedup_pool_2']:.2f}×</b>, Ray overhead {b.get('ray_overhead_per_item_s', float('nan')):.3f} s per "
            f"item, outputs identical to the serial run: <b>{b['identical']}</b>.</p>"
            + _table(rows, ["run", "seconds", "items_per_s"]))
    if _copy_chart(b, bench_dir, Path(out_dir) / "scale_throughput.png"):
        body += "<img src='scale_throughput.png'>"
    add_section(out_dir, "60_scale", "Many items: process pool and Ray (same results, measured throughput)", body)
    return {k: b[k] for k in ("speedup_pool_2", "identical")}
