"""Charts of `photoreal bench morph`: the suite's convergence traces, accuracy against time of the cases."""

from __future__ import annotations

from pathlib import Path


def suite_line_style(i: int) -> dict:
    """The ``i``-th suite mesh's line: ten colours, then the same ten dashed, then dotted (the whole suite is 13
    meshes; ten colours alone repeated three of them)."""
    return {"color": f"C{i % 10}", "ls": ("-", "--", ":")[i // 10 % 3]}


def suite_chart(suite: dict, path: Path) -> Path:
    """Chamfer reduction against time for every suite mesh (the runs' traces), the target as a line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from foundation.imageio import save_figure

    fig, ax = plt.subplots(1, 2, figsize=(14, 4.5))
    for i, (name, r) in enumerate(suite["meshes"].items()):
        tr = [t for t in r["trace"] if t["chamfer"] is not None]
        if not tr:
            continue
        style = suite_line_style(i)
        # The trace's Chamfer uses a coarser estimator than the headline figure: relative to the coarse input
        # measured with the same estimator.
        c0 = r["trace_chamfer_input"]
        ax[0].plot([t["seconds"] for t in tr], [1 - t["chamfer"] / c0 for t in tr], **style,
                   label=f"{name} ({r['kind']})")
        if r.get("chamfer_reduction") is not None:  # the headline figure (final mesh, the reference estimator)
            ax[0].plot([tr[-1]["seconds"]], [r["chamfer_reduction"]], marker="o", ms=4, ls="", color=style["color"])
        vl = [t for t in r["trace"] if t["validation_l1"] is not None]
        if vl:
            ax[1].plot([t["iteration"] for t in vl], [t["validation_l1"] / vl[0]["validation_l1"] for t in vl],
                       **style, label=name)
    ax[0].axhline(suite["targets"]["chamfer_reduction"], color="gray", ls="--", lw=0.8)
    ax[0].set_xlabel("seconds (one run per worker, 1 thread each)")
    ax[0].set_ylabel("Chamfer reduction vs the coarse input\n(lines: the trace's coarser estimate; dot: the result)",
                     fontsize=9)
    ax[1].set_xlabel("iteration")
    ax[1].set_ylabel("validation L1 / at start (photos not fitted)")
    for a in ax:
        a.grid(alpha=0.3)
    # one legend for both panels (same colours), beside them: inside, it hid the curves it names
    ax[1].legend(*ax[0].get_legend_handles_labels(), loc="center left", bbox_to_anchor=(1.02, 0.5), fontsize=7)
    fig.suptitle("morph generalisation suite at the same defaults")
    return save_figure(fig, path)


def morph_chart(result: dict, path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from foundation.imageio import save_figure

    fig, ax = plt.subplots(1, 2, figsize=(10, 3.8))
    for case, r in result["cases"].items():
        x = [p["seconds"] for p in r["sweep"]]
        rel = [p["chamfer"] / r["chamfer_input"] for p in r["sweep"]]
        ax[0].plot(x, rel, "o-", label=case)
        ax[1].plot(x, [p["psnr"] for p in r["sweep"]], "o-", label=case)
        for p, xi, yi in zip(r["sweep"], x, rel):
            ax[0].annotate(f"{p['mesh_vertices']}", (xi, yi), textcoords="offset points", xytext=(3, 3), fontsize=7)
    ax[0].axhline(0.5, color="gray", ls="--", lw=0.8)
    ax[0].set_ylabel("Chamfer / input Chamfer")
    ax[1].set_ylabel("held-out PSNR (dB)")
    for a in ax:
        a.set_xlabel("morph wall time (s, 2 CPU cores)")
        a.grid(alpha=0.3)
        a.legend()
    fig.suptitle("geometry morphing: accuracy vs time over mesh resolution (labels: vertices)")
    return save_figure(fig, path)
