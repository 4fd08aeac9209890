"""The demo's real capture: the vendored ruins photos through structure from motion, and the coarse mesh it gives
rendered at a held-out photo."""

from __future__ import annotations

import html
import tempfile
from pathlib import Path

import numpy as np

from foundation import imageio

from .report import add_section, bench_json, figure, table


def demo_capture(out_dir: Path, resolution: int = 384, spp: int = 16, seed: int = 0,
                 bench_dir: Path | None = None) -> dict:
    """Ruins (10 real photos): cameras and points from `capture sfm`, the Poisson mesh coloured from the training
    photos, rendered at a held-out photo; the bench's figures of both captures when present."""
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
    cb = bench_json(bench_dir, "capture")
    if cb is not None:
        body += "<h3>Benchmark (<code>photoreal bench capture</code>)</h3>"
        brow = []
        for name, c in cb["captures"].items():
            m = (c.get("scores") or {}).get("mean") or {}
            brow.append({"capture": name, "registered": f"{c['sfm'].get('registered')}/{c['sfm'].get('photos')}",
                         "models": c["sfm"].get("models"), "reprojection_px": c["sfm"].get("reprojection_px"),
                         "psnr": m.get("psnr"), "flip": m.get("flip")})
        body += table(brow, ["capture", "registered", "models", "reprojection_px", "psnr", "flip"])
    add_section(out_dir, "35_capture", "A real capture: structure from motion, the coarse mesh, a held-out photo", body)
    return {"sfm": {k: sfm[k] for k in ("photos", "registered", "models", "points", "reprojection_px")},
            "heldout": r["mean"]}
