"""The report's page: its settings, sections stitched into ``index.html``, figures, tables, benchmark results read from the bench folder."""

from __future__ import annotations

import html
import time
from dataclasses import dataclass
from pathlib import Path

from foundation import validate
from foundation.files import read_json, write_text

from ..benchmarks import json_name


@dataclass
class DemoSettings:
    resolution: int = 256  #: image side of the renders (the face's camera renders: at most 192; the photo's relit: 256)
    spp: int = 64  #: samples per pixel (the face's camera renders and the photo's relit: at most 64)
    seed: int = 0
    face: bool = True
    face_uv_res: int = 256
    morph_iterations: int = 100  #: 0 skips the morphing section
    #: training budget of each demo-sized learned refiner (Morph-GAN, diffusion renderer) on the morph; 0 skips them
    refiner_seconds: float = 10.0
    btf: bool = True  #: neural materials scene (+ `photoreal bench btf` tables when present)
    plugin_bench: bool = True  #: time ggx_uv against principled (a short run of `photoreal bench plugins`)
    capture: bool = True  #: a real capture (the vendored ruins) through structure from motion
    export: bool = True  #: glTF exports in 3D viewers, and the report opened in headless Chromium (where installed)

    def __post_init__(self):
        validate.integer("resolution", self.resolution, 8, 4096)
        validate.integer("spp", self.spp, 1)
        validate.seed("seed", self.seed)
        validate.integer("face_uv_res", self.face_uv_res, 16, 4096)
        validate.integer("morph_iterations", self.morph_iterations, 0)
        validate.non_negative("refiner_seconds", self.refiner_seconds)


def add_section(out_dir: Path, key: str, title: str, body_html: str) -> Path:
    """Store one report section (HTML fragment); index.html is rebuilt from all of them."""
    path = Path(out_dir) / "sections" / f"{key}.html"
    return write_text(path, f"<section id='{html.escape(key)}'><h2>{html.escape(title)}</h2>\n{body_html}\n</section>\n")


def write_index(out_dir: Path) -> Path:
    from .viewer import page_scripts

    out_dir = Path(out_dir)
    sections = sorted((out_dir / "sections").glob("*.html"))
    body = "\n".join(p.read_text() for p in sections)
    head, tail = page_scripts(out_dir)
    page = f"""<!doctype html>
<html><head><meta charset="utf-8"><title>photoreal demo report</title>
<style>
body {{ font-family: sans-serif; max-width: 1200px; margin: 2em auto; color: #222; }}
figure {{ display: inline-block; margin: 0.4em; text-align: center; }}
figure img {{ width: 240px; image-rendering: pixelated; border: 1px solid #ccc; }}
figcaption {{ font-size: 0.8em; }}
table {{ border-collapse: collapse; margin: 0.5em 0; }}
td, th {{ border: 1px solid #bbb; padding: 0.2em 0.6em; text-align: right; }}
</style>{head}</head><body>
<h1>photoreal — demo report</h1>
<p>Generated {time.strftime('%Y-%m-%d %H:%M:%S')} by <code>make demo</code>.</p>
{body}
{tail}
</body></html>
"""
    return write_text(out_dir / "index.html", page)


def figure(src: str, caption: str) -> str:
    return f"<figure><img src='{html.escape(src)}'><figcaption>{html.escape(caption)}</figcaption></figure>"


def table(rows: list[dict], cols: list[str]) -> str:
    def fmt(v):
        if isinstance(v, float):  # small errors (MSE ~1e-3) keep 4 significant digits
            return f"{v:.4g}" if 0 < abs(v) < 0.1 else f"{v:.3f}"
        return html.escape(str(v))

    head = "".join(f"<th>{html.escape(c)}</th>" for c in cols)
    body = "".join("<tr>" + "".join(f"<td>{fmt(r.get(c, ''))}</td>" for c in cols) + "</tr>" for r in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def bench_json(bench_dir: Path | None, name: str) -> dict | None:
    """Benchmark ``name``'s JSON (as `photoreal bench all` names it) from ``bench_dir`` if it is there; else None."""
    path = None if bench_dir is None else Path(bench_dir) / json_name(name)
    if path is None or not path.is_file():
        return None
    return read_json(path, "benchmark result")


def copy_chart(result: dict, bench_dir: Path | None, dest: Path) -> bool:
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


def bench_section(out_dir: Path, bench: dict) -> None:
    modes = bench["modes_ms"]
    rows = "".join(f"<tr><th>{name}</th>" + "".join(f"<td>{modes[m][name]:.1f}</td>" for m in modes)
                   + "".join(f"<td>{modes[m][name] / modes[m]['principled']:.2f}</td>" for m in modes) + "</tr>"
                   for name in modes["symbolic"])
    nb = bench["neural_btf"]
    psnr = f"{nb['heldout_psnr']:.1f} dB" if nb.get("heldout_psnr") is not None else "not recorded"
    add_section(out_dir, "20_bench_plugins", "Plugin speed: ggx_uv and neural_btf vs builtin principled",
                "<table><tr><th>plugin</th>" + "".join(f"<th>{m} ms</th>" for m in modes)
                + "".join(f"<th>× principled, {m}</th>" for m in modes) + f"</tr>{rows}</table>"
                f"<p>{html.escape(bench.get('scene', ''))}; {bench['settings']['resolution']}², "
                f"{bench['settings']['spp']} spp, median of "
                f"{bench['settings']['repetitions'] * bench['settings']['rounds']} renders after warm-up. symbolic: "
                f"what a plain <code>mi.render</code> runs (one megakernel); evaluated: wavefront. neural_btf: basis width {nb['basis_width']}, {html.escape(nb['material'])} (held-out "
                f"PSNR {psnr}); first ggx_uv render's compile {bench['compile_s']:.2f} s.</p>")


#: what each part of the demo runs in full (the demo runs demo-sized versions, or reads the bench's JSON)
FULL_COMMANDS = {
    "scenes": "photoreal render scenes/SCENE.xml -o out.exr --aovs",
    "face": "photoreal face make-benchmark --scan SCAN.obj --out B && photoreal face fit B; photoreal bench face",
    "photo": "photoreal face from-photo PHOTO --out DIR",
    "capture": "photoreal capture sfm IMAGES --out CAPTURE && photoreal morph run CAPTURE; photoreal bench capture",
    "morph": "photoreal morph make-benchmark --mesh MESH --out B && photoreal morph run B; photoreal bench morph",
    "btf": "photoreal bench btf (renders BTFs, trains the universal basis, fits the materials)",
    "matdiff": "photoreal btf generate --keywords 'rough red leather' --out M.npz; photoreal bench matdiff",
    "refiners": "photoreal gan train B --out RUN; photoreal diffrender train B --out RUN; photoreal bench gan; "
                "photoreal bench diffrender",
    "gan": "photoreal bench gan",
    "scale": "photoreal bench scale",
    "diffrender": "photoreal bench diffrender",
    "face_learned": "photoreal face train-models --out RUN; photoreal bench face-learned",
    "benchmarks": "make bench (photoreal bench all)",
    "bench_plugins": "photoreal bench plugins",
    "export": "photoreal export RESULT --out DIR (a morph run, a face fit or from-photo folder, a neural material)",
}


def time_section(out_dir: Path, seconds: dict[str, float], ran: dict[str, str]) -> None:
    """The report's last section: each part's wall seconds in this run, what it did, and its full command."""
    rows = "".join(
        f"<tr><th style='text-align:left'>{html.escape(k)}</th><td>{v:.1f}</td>"
        f"<td style='text-align:left'>{html.escape(ran.get(k, ''))}</td>"
        f"<td style='text-align:left'><code>{html.escape(FULL_COMMANDS.get(k, ''))}</code></td></tr>"
        for k, v in seconds.items())
    add_section(out_dir, "99_time", "How long each part took, and the command that runs it in full",
                f"<p>Wall seconds of this run ({sum(seconds.values()):.0f} s in all). The demo runs each stage "
                "demo-sized, or shows what <code>photoreal bench …</code> wrote into the bench folder.</p>"
                "<table><tr><th>part</th><th>seconds</th><th>here</th><th>in full</th></tr>" + rows + "</table>")
