"""The diffusion-renderer bench's sweep chart: ꟻLIP against sampling seconds per model size."""

from __future__ import annotations

from pathlib import Path

import mi_plugins  # noqa: F401


def sweep_chart(result: dict, path: Path) -> Path:
    """ꟻLIP against sampling seconds per 128² image, one line per model size, points labelled by DDIM steps."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from foundation.imageio import save_figure

    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    for model in sorted({r["model"] for r in result["sweep"]}):
        rows = [r for r in result["sweep"] if r["model"] == model and r.get("draws", 1) == 1]
        line, = ax.plot([r["seconds_per_image"] for r in rows], [r["flip"] for r in rows], "-o",
                        label=f"{model} ({rows[0]['parameters'] / 1e6:.2f} M params)")
        means = [r for r in result["sweep"] if r["model"] == model and r.get("draws", 1) > 1]
        for r in rows:
            ax.annotate(f"{r['steps']}", (r["seconds_per_image"], r["flip"]), fontsize=7, xytext=(3, 3),
                        textcoords="offset points")
        for k, r in enumerate(means):  # "×draws g guidance", above and below in turn so neighbours stay legible
            ax.annotate(f"×{r['draws']} g{r.get('guidance', '')}", (r["seconds_per_image"], r["flip"]), fontsize=6,
                        xytext=(-8, 6 if k % 2 == 0 else -11), textcoords="offset points", color=line.get_color())
        if means:
            ax.plot([r["seconds_per_image"] for r in means], [r["flip"] for r in means], "s", color=line.get_color())
    c = result["chosen"]
    how = f"{c['steps']} steps" + (f", mean of {c['draws']}, guidance {c.get('guidance')}"
                                   if c.get("draws", 1) > 1 else "")
    ax.plot([c["seconds_per_image"]], [c["flip"]], "k*", ms=13, label=f"chosen sampler ({c['model']} row, {how})")
    sub = result["heldout"]
    for name, ls in (("pbr_coarse", "--"), ("pbr_morphed", ":")):
        ax.axhline(sub[name]["flip"], color="gray", ls=ls, lw=1, label=f"{name} (all held-out views)")
    ax.set_xscale("log")
    ax.set_xlabel("s per 128² image, 2 cores (labels: DDIM steps; squares: 1 step, mean of ×N draws, guidance g)", fontsize=8)
    ax.set_ylabel("held-out ꟻLIP (lower is better)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    ax.set_title("Diffusion renderer: quality vs sampling cost")
    return save_figure(fig, path)
