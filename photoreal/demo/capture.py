"""The demo's real capture: the vendored ruins photos through structure from motion, the coarse mesh it gives
rendered at a held-out photo, and a demo-sized morph of it (before/after at that photo)."""

from __future__ import annotations

import html
import tempfile
from pathlib import Path

from foundation import imageio

from .report import add_section, bench_json, figure, table


def demo_capture(out_dir: Path, resolution: int = 384, spp: int = 16, seed: int = 0,
                 bench_dir: Path | None = None, morph_iterations: int = 60) -> dict:
    """Ruins (10 real photos): cameras and points from `capture sfm`, the Poisson mesh coloured from the training
    photos, rendered at a held-out photo; a morph of ``morph_iterations`` (0: none) with the light and exposures
    fitted, in 'unlit' mode without the validation photos' choices (a demo-sized run; `photoreal morph run
    CAPTURE` makes them); the bench's figures of both captures when present."""
    from foundation.mesh import read_ply
    from inverse.capture import SfmSettings, heldout_scores, import_capture, load_capture, run_sfm

    from ..benchmarks.capture import CAPTURES

    cdir = Path(out_dir) / "capture"
    cdir.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="photoreal-demo-sfm-") as work:
        # features at twice the working side (at least 384 px): enough for this well-textured set, seconds on 2 cores
        src = run_sfm(CAPTURES / "ruins" / "images", work, SfmSettings(max_size=max(384, 2 * resolution), seed=seed))
        cap = load_capture(import_capture(src, Path(work) / "capture", resolution, show_progress=False))
        v, f, _ = read_ply(cap.mesh)
        r = heldout_scores(cap, v, f, spp=spp, seed=seed)
        morph = _demo_morph(cap, Path(work) / "morph", cdir, morph_iterations, seed) if morph_iterations else None
        if morph is not None:  # the morphed mesh as glTF, its texture from the photos (the report's 3D viewer)
            from foundation.export import ExportSettings
            from inverse.morph import export_morph

            export_morph(Path(work) / "morph", cdir / "export", ExportSettings(eval_width=min(resolution, 256), seed=seed),
                         input_path=Path(work) / "capture")
    test, train = cap.meta.test[0], cap.meta.train[0]
    for name, img in (("train_photo", cap.photo(train)), ("heldout_photo", cap.photo(test)),
                      ("heldout_mesh", r["renders"][test])):
        imageio.write_png(cdir / f"{name}.png", img)
    sfm = cap.meta.sfm
    figs = "".join(figure(f"capture/{k}.png", label) for k, label in
                   (("train_photo", f"a training photo ({html.escape(train)})"),
                    ("heldout_mesh", "the coarse mesh at the held-out camera"),
                    ("heldout_photo", f"the held-out photo ({html.escape(test)})")))
    rows = [{"figure": k, "value": sfm[k]} for k in ("photos", "registered", "models", "points", "reprojection_px")]
    rows += [{"figure": f"held-out {k}", "value": v} for k, v in r["mean"].items()]
    body = (f"<p>Stone ruins, {sfm['photos']} real photos (no cameras, no mesh). <code>photoreal capture sfm</code> "
            "found the cameras and sparse points with pycolmap on the CPU (SIFT, exhaustive matching, incremental "
            f"mapping: {sum(sfm['seconds'].values()):.0f} s); the coarse mesh is the screened Poisson surface of "
            f"the {sfm['points']} points, coloured from the training photos and rendered unlit at a photo no step "
            "has seen. This is the honest coarse photogrammetry start a morph of a real capture improves on.</p>"
            f"<div>{figs}</div>" + table(rows, ["figure", "value"]))
    if morph is not None:
        body += (f"<h3>Morphed ({morph['iterations']} iterations, a demo-sized run)</h3><p>The coarse mesh morphed "
                 "against the 9 training photos with the environment and a gain per photo fitted beside it; both "
                 "meshes rendered at the held-out photo under the same fitted environment and exposure. The full run is <code>photoreal morph run CAPTURE</code> (the validation photos choose "
                 "λ, the priors, the step and lit or unlit).</p><div>"
                 + "".join(figure(f"capture/{k}.png", label) for k, label in
                           (("morph_input", "input mesh"), ("morph_morphed", "morphed"),
                            ("morph_photo", "held-out photo")))
                 + "</div>" + table([{"mesh": k, "psnr": morph[k]["psnr"], "flip": morph[k]["flip"]}
                                     for k in ("input", "morphed")], ["mesh", "psnr", "flip"]))
    cb = bench_json(bench_dir, "capture")
    if cb is not None:
        body += "<h3>Benchmark (<code>photoreal bench capture</code>)</h3>"
        brow = []
        for name, c in cb["captures"].items():
            m = (c.get("scores") or {}).get("mean") or {}
            brow.append({"capture": name, "registered": f"{c['sfm'].get('registered')}/{c['sfm'].get('photos')}",
                         "models": c["sfm"].get("models"), "reprojection_px": c["sfm"].get("reprojection_px"),
                         "psnr": m.get("psnr"), "flip": m.get("flip")})
            mm = c.get("morph")
            if mm:
                brow[-1].update(morph_psnr=f"{mm['input']['psnr']:.2f} → {mm['morphed']['psnr']:.2f}",
                                morph_flip=f"{mm['input']['flip']:.3f} → {mm['morphed']['flip']:.3f}")
        body += table(brow, ["capture", "registered", "models", "reprojection_px", "psnr", "flip", "morph_psnr",
                             "morph_flip"])
    add_section(out_dir, "35_capture", "A real capture: structure from motion, the coarse mesh, a held-out photo", body)
    return {"sfm": {k: sfm[k] for k in ("photos", "registered", "models", "points", "reprojection_px")},
            "heldout": r["mean"], **({"morph": morph} if morph is not None else {})}


def _demo_morph(cap, work: Path, cdir: Path, iterations: int, seed: int) -> dict:
    """A short morph of the capture; its held-out before/after images copied into ``cdir``."""
    import shutil

    from inverse.morph import CaptureBenchmark, MorphSettings, run_morph

    s = MorphSettings(iterations=iterations, mode="unlit", lambda_select=(), planarity_select=(),
                      step_select_quantile=1.0, early_stop=False, min_vertices=None, check_every=max(1, iterations),
                      checkpoint_every=max(1, iterations), seed=seed)
    r = run_morph(CaptureBenchmark(cap, work / ".capture_input"), work, s, show_progress=False)
    for name in ("input", "morphed", "photo"):
        src = next(work.glob(f"heldout_{name}_view*.png"))
        shutil.copyfile(src, cdir / f"morph_{name}.png")
    return {"iterations": r.iterations, "seconds": r.seconds,
            "input": {"psnr": r.heldout_input.psnr, "flip": r.heldout_input.flip},
            "morphed": {"psnr": r.heldout_morphed.psnr, "flip": r.heldout_morphed.flip}}
