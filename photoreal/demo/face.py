"""The face sections: a fit on a real scan, one photograph to a face, the learned stages."""

from __future__ import annotations

import html
from pathlib import Path

import numpy as np

from foundation import imageio
from foundation.assets import FACE
from foundation.records import to_json

from ..benchmarks import json_name, work_folder
from .report import add_section, bench_json, copy_chart, figure, table


def demo_face(out_dir: Path, uv_res: int = 256, seed: int = 0, bench_dir: Path | None = None,
              render_res: int = 192, render_spp: int = 64) -> dict:
    """Josie scan: benchmark, UV-space fit, maps and relit renders (``render_res``², ``render_spp``) against
    ground truth."""
    from inverse.face import (FaceBenchmarkSettings, FaceFitSettings, evaluate_fit, fit_face, load_benchmark,
                              make_benchmark)

    face_dir = Path(out_dir) / "face"
    bench = load_benchmark(make_benchmark(FACE / "cyberheads" / "josie.obj", face_dir / "benchmark",
                                          FaceBenchmarkSettings(uv_res=uv_res, seed=seed, render_res=render_res,
                                                                render_spp=render_spp)))
    result = fit_face(bench, FaceFitSettings(seed=seed))
    from foundation.export import ExportSettings
    from inverse.face import export_face, save_maps

    save_maps(result.maps, face_dir / "maps")
    export_face(face_dir / "maps", face_dir / "export", ExportSettings(seed=seed), input_path=face_dir / "benchmark")
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
        figs.append(figure(f"face/gt_{name}.png", f"{name}: ground truth") +
                    figure(f"face/fit_{name}.png", f"{name}: fitted"))
    imageio.write_png(face_dir / "observation.png", bench.observations["v0_l0"])
    relit_figs = []
    for hdri, img in relit.items():
        imageio.write_png(face_dir / f"relit_gt_{hdri}.png", bench.heldout[hdri])
        imageio.write_png(face_dir / f"relit_fit_{hdri}.png", img)
        relit_figs.append(figure(f"face/relit_gt_{hdri}.png", f"{hdri}: ground truth")
                          + figure(f"face/relit_fit_{hdri}.png",
                                    f"{hdri}: fitted maps ({m['relit'][hdri]['psnr']:.1f} dB)"))
    rows = [{"metric": k, "value": float(m[k])} for k in ("albedo_psnr", "albedo_ssim", "albedo_scale", "normal_err_deg",
                                                           "roughness_mae", "specular_mae", "relit_psnr", "relit_flip",
                                                           "observed_fraction", "seconds")]
    body = (f"<p>Real Cyberware scan <i>josie</i>; ground-truth maps {uv_res}² (scanned albedo + seeded relief, "
            f"roughness, specular); {len(bench.meta.lights)} directional lights × {len(bench.meta.views)} views "
            f"rendered by Mitsuba with ggx_uv, taken texel-aligned. Fit: Adam through the UV-space GGX shader "
            f"(the plugin's own functions). Held-out: real HDRIs.</p>"
            + figure("face/observation.png", "one observation (view 0, light 0)")
            + "<div>" + "".join(figs) + "</div>" + table(rows, ["metric", "value"])
            + "<h3>Relit under held-out HDRIs</h3><div>" + "".join(relit_figs) + "</div>")
    fb = bench_json(bench_dir, "face")
    if fb is not None:
        body += "<h3>Speed vs accuracy and stability (<code>photoreal bench face</code>)</h3>"
        body += table(fb["sweep"], ["uv_res", "seconds", "relit_psnr", "albedo_psnr", "normal_err_deg"])
        body += f"<p>chosen_uv_res = {fb['chosen_uv_res']} (smallest within 0.5 dB of the best relit PSNR)</p>"
        if copy_chart(fb, bench_dir, face_dir / "face_speed_accuracy.png"):
            body += "<img src='face/face_speed_accuracy.png'>"
        body += table([{"case": k, **v} for k, v in fb["stability"].items()],
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
    from foundation.export import ExportSettings
    from inverse.face import export_face

    export_face(photo_dir, Path(out_dir) / "photo_export", ExportSettings(seed=seed))  # the avatar as glTF
    figs = [figure("photo/photo.png", "input photo (scikit-image astronaut)"),
            figure("photo/photo_uv.png", "photo unwrapped into UV"),
            figure("photo/visibility.png", "visibility mask"),
            figure("photo/albedo.png", "delit albedo (filled)"),
            figure("photo/rerender.png",
                    f"re-rendered, fitted light ({r['rerender_psnr_visible_face']:.1f} dB on the face)")]
    figs += [figure(f"photo/relit_{h}.png", f"relit: {h} HDRI") for h in r["settings"]["hdris"]]
    body = (f"<p>Landmarks: {html.escape(source)}. Template: MediaPipe canonical face, similarity + Laplacian "
            f"deformation. Landmark reprojection error <b>{r['landmark_reprojection_px']:.2f} px</b> "
            f"(similarity alone {r['landmark_reprojection_px_rigid']:.2f} px). Lighting fitted jointly "
            f"({len(r['lighting']['lights'])} directional + ambient) and divided out; normal, roughness and "
            f"specular are the template's and skin defaults (a baseline where seed 003 uses learned models).</p>"
            f"<div>{''.join(figs)}</div>")
    add_section(out_dir, "31_photo", "One real photograph to a relightable face", body)
    return {k: r[k] for k in ("landmark_reprojection_px", "rerender_psnr_visible_face", "seconds")}


def _seed_spread(spread: dict | None) -> str:
    """The decomposition ablation over training seeds (bench face-learned --ablation-seeds): mean ± sd per metric."""
    if not spread:
        return ""
    keys = ("normal_err_deg", "roughness_mae", "specular_mae", "albedo_psnr_unseen")
    rows = [{"variant": v, **{k: f"{m[k]['mean']:.4g} ± {m[k]['std']:.2g}" for k in keys}}
            for v, m in spread.items() if v != "seeds"]
    return (f"<p>Over training seeds {', '.join(map(str, spread['seeds']))} (mean ± sample sd):</p>"
            + table(rows, ["variant", *keys]))


def demo_face_learned(out_dir: Path, bench_dir: Path | None = None) -> dict | None:
    """The `photoreal bench face-learned` tables and map figure, when that JSON exists (no training here)."""
    b = bench_json(bench_dir, "face-learned")
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
            + table([{"method": k, **c[k]} for k in ("baseline", "learned", "learned_one_sample")],
                     ["method", "albedo_psnr_seen", "albedo_psnr_unseen", "albedo_psnr_all"])
            + "<h4>Decomposition (equal training time)</h4>"
            + table([{"variant": k, **v} for k, v in b["decomposition"].items()],
                     ["variant", "normal_err_deg", "roughness_mae", "specular_mae", "trained_parameters", "steps"])
            + _seed_spread(b.get("decomposition_seeds"))
            + f"<h4>2× super-resolution ({b['superres']['from']}² → {b['superres']['to']}², true maps)</h4>"
            + table([{"method": k, **b["superres"][k]} for k in ("bicubic", "learned")],
                     ["method", "albedo_psnr", "normal_err_deg", "roughness_psnr", "specular_psnr"]))
    e = b["end_to_end"]
    rows = [{"method": k, **{m: v[m] for m in ("albedo_psnr_seen", "albedo_psnr_unseen", "normal_err_deg",
                                                "roughness_mae", "specular_mae")},
             "relit_psnr": v.get("relit", {}).get("psnr", ""), "relit_flip": v.get("relit", {}).get("flip", "")}
            for k, v in {"baseline": e["baseline"], **e["stages"]}.items()]
    body += (f"<h4>End to end ({e['relit_instances']} instances relit under {', '.join(e['relight_hdris'])})</h4>"
             + table(rows, ["method", "albedo_psnr_seen", "albedo_psnr_unseen", "normal_err_deg", "roughness_mae",
                             "specular_mae", "relit_psnr", "relit_flip"]))
    if b.get("cross_model_fit"):
        body += ("<h4>The existing fit on observations it did not render</h4>"
                 + table([{"benchmark": k, **v} for k, v in b["cross_model_fit"].items()],
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
                    body += figure(name, f"{k}: {pic[:-4].replace('_', ' ')}")
        body += "</div>"
    if copy_chart({"chart": b.get("figure")}, bench_dir, out_dir / "face_learned_maps.png"):
        body += "<img src='face_learned_maps.png' style='max-width:100%'>"
    add_section(out_dir, "42_face_learned", "Learned UV-space face stages (seed 003 §2–§4)", body)
    return b.get("verdict")
