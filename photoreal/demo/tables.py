"""Tables of benchmark results: every registered benchmark, and the pool and Ray throughput."""

from __future__ import annotations

import html
import json
from pathlib import Path

from ..benchmarks import json_name
from .report import add_section, bench_json, copy_chart, table


def demo_benchmarks(out_dir: Path, bench_dir: Path | None) -> dict:
    """One table of every registered benchmark whose JSON is in ``bench_dir``: the figures its summary shows, and
    the command that makes it."""
    from ..benchmarks import REGISTRY, summary

    rows, found = [], {}
    for name, entry in REGISTRY.items():
        result = bench_json(bench_dir, name)
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


def demo_scale(out_dir: Path, bench_dir: Path | None = None) -> dict | None:
    """The `photoreal bench scale` table and chart (serial vs process pool vs Ray), when that JSON exists."""
    b = bench_json(bench_dir, "scale")
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
            + table(rows, ["run", "seconds", "items_per_s"]))
    if copy_chart(b, bench_dir, Path(out_dir) / "scale_throughput.png"):
        body += "<img src='scale_throughput.png'>"
    add_section(out_dir, "60_scale", "Many items: process pool and Ray (same results, measured throughput)", body)
    return {k: b[k] for k in ("speedup_pool_2", "identical")}
