"""The exports section: the demo's morphed capture, fitted face and a neural material's GGX tile as glTF, each in a
3D viewer beside what the export measured; and the report checked in a headless browser."""

from __future__ import annotations

import html
from pathlib import Path

from foundation.files import read_json

from .report import add_section, table
from .viewer import add_model


def demo_export(out_dir: Path, seed: int = 0, material_iterations: int = 150) -> dict:
    """Export the bundled leather (its GGX distilled in ``material_iterations`` steps); show it with the capture's,
    the face fit's and the photo's exports (written by their sections) in viewers."""
    from foundation.assets import NEURAL
    from foundation.export import ExportSettings
    from inverse.btf import DistilSettings, export_material

    out_dir = Path(out_dir)
    export_material(NEURAL / "leather.npz", out_dir / "material" / "export", ExportSettings(seed=seed),
                    distil=DistilSettings(iterations=material_iterations, seed=seed), show_progress=False)
    parts = {"capture": ("the morphed ruins, texture baked from the photos", out_dir / "capture" / "export"),
             "face": ("the fitted face (josie), maps as a PBR material", out_dir / "face" / "export"),
             "photo": ("the astronaut photograph's avatar (delit albedo, skin defaults)", out_dir / "photo_export"),
             "material": ("leather: the GGX SVBRDF distilled from the neural BTF", out_dir / "material" / "export")}
    viewers, rows, figures = [], [], {}
    for name, (caption, folder) in parts.items():
        if not (folder / "export.json").is_file():
            continue
        rec = read_json(folder / "export.json", "export record")
        glb = folder / "model.glb"
        viewers.append(f"<figure>{add_model(out_dir, name, glb, rec.get('view_orbit_deg'))}<figcaption>{html.escape(caption)}</figcaption></figure>")
        row = {"model": name, "vertices": rec.get("exported_vertices", rec.get("reimport", {}).get("vertices")),
               "texture": "×".join(map(str, rec.get("texture_size") if isinstance(rec.get("texture_size"), list)
                                       else [rec.get("texture_size")] * 2)),
               "re-import PSNR": rec["reimport"].get("render_psnr"), "MB": round(glb.stat().st_size / 1e6, 2)}
        if name == "capture" and rec.get("heldout"):
            h = rec["heldout"]
            row["held-out"] = "; ".join(f"{k} {v['psnr']:.2f} dB / ꟻLIP {v['flip']:.3f}" for k, v in h.items())
        if name == "material":
            row["held-out"] = (f"exported ({rec['model']}) GGX vs neural {rec['exported_heldout_psnr']:.2f} dB "
                               f"(per texel {rec['ggx_heldout_psnr']:.2f}, one GGX for the tile "
                               f"{rec['constant_heldout_psnr']:.2f}); preview {rec['preview_psnr']:.2f} dB")
        rows.append(row)
        figures[name] = row
    body = ("<p>Each model as <code>photoreal export</code> writes it (glTF 2.0 binary, +Y up; base colour sRGB, the "
            "other maps linear), in an interactive viewer (drag to turn; <code>&lt;model-viewer&gt;</code>, vendored: "
            "the page works offline). The Khronos validator checks every file the tests write.</p>"
            f"<div>{''.join(viewers)}</div>"
            + table(rows, ["model", "vertices", "texture", "re-import PSNR", "MB", "held-out"])
            + ("<p>Leather: the neural material (left) and its distilled GGX tile (right) under the sunset HDRI.</p>"
               "<img src='material/export/preview.png'>" if (out_dir / "material" / "export" / "preview.png").is_file()
               else ""))
    add_section(out_dir, "45_export", "Results that leave Mitsuba: glTF exports in a 3D viewer", body)
    return figures


def check_report(out_dir: Path) -> dict:
    """Open the finished report in headless Chromium: its viewers' load count, console errors and a screenshot
    (``report_screenshot.png``); where no Chromium is installed, says so."""
    from .browser import check_page, find_browser

    if find_browser() is None:
        return {"skipped": "no Chromium on PATH (Debian: apt install chromium)"}
    r = check_page(Path(out_dir) / "index.html", Path(out_dir) / "report_screenshot.png")
    return {"viewers": r.viewers, "loaded": r.loaded, "console_errors": r.console_errors,
            "screenshot": "report_screenshot.png", "seconds": r.seconds, "ok": r.ok}
