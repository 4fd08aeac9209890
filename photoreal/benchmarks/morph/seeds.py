"""`photoreal bench morph-seeds`: the morph suite over several draws (``bench morph --parts suite --seed K``
results, one per seed), summed up per mesh, and two settings compared draw by draw."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .bench import MEAN_KEYS, TARGETS, MorphBenchSettings



def suite_of(path: Path, data: dict) -> tuple[int, dict]:
    """(seed, suite) of one ``bench morph`` JSON; a file without a suite, or without its settings, is named."""
    from foundation.errors import UsageError

    suite, settings = data.get("suite"), data.get("settings")
    if not isinstance(suite, dict) or not isinstance(suite.get("meshes"), dict) or not isinstance(settings, dict):
        raise UsageError(f"{path}: not a `photoreal bench morph` result with a suite (run it with --parts suite)")
    seed = settings.get("seed", 0)  # results written before --seed existed are seed 0's
    if not isinstance(seed, int) or isinstance(seed, bool):
        raise UsageError(f"{path}: settings.seed is {seed!r}, not an integer")
    return seed, suite


def merged_suites(a: dict, b: dict) -> dict:
    """Two parts of one draw's suite (disjoint meshes) as one: rows joined, the mean and the failing list remade."""
    meshes = {**a["meshes"], **b["meshes"]}
    mean = {k: float(np.mean([r[k] for r in meshes.values()])) for k in MEAN_KEYS
            if all(k in r for r in meshes.values())}
    return {**a, "meshes": meshes, "mean": mean, "failing": {**a.get("failing", {}), **b.get("failing", {})}}


def recorded_run_settings(settings: dict) -> dict:
    """The settings of a ``bench morph`` result that change its runs, as the file recorded them; a file written
    before a field existed ran at what is now its default (vertex normals, uniform Adam's maximum, lr 0.05), except
    the step choice, the saturation mask and the silhouette loss: files before them ran without (quantile 1,
    saturation 0, mask weight 0; before its cheaper form, masks every step at full resolution with one sample count
    for the photo's and the silhouettes' gradients)."""
    d = MorphBenchSettings()
    got = {k: settings.get(k) or getattr(d, k) for k in ("iterations", "truth_normals", "adam_quantile", "lr")}
    return {**got, "step_select_quantile": settings.get("step_select_quantile") or 1.0,
            "saturation": settings.get("saturation") or 0.0, "mask_weight": settings.get("mask_weight") or 0.0,
            "mask_every": settings.get("mask_every") or 1, "mask_downsample": settings.get("mask_downsample") or 1,
            "boundary_spp": settings.get("boundary_spp")}


def seeds_summary(paths: list[str | Path]) -> dict:
    """The suite over several draws (``photoreal bench morph --seed K`` results, one file per seed): per mesh its
    figures at each seed, their mean and worst, and at how many seeds it meets every target; per seed the meshes that
    pass. Files must agree on everything but the seed (cap, truth shading): draws of one experiment. Files of one
    seed with different meshes are parts of one draw and are merged; a mesh some seeds lack is reported over the
    seeds that have it (``seeds`` says which)."""
    from foundation.errors import UsageError
    from foundation.files import read_json

    runs: dict[int, dict] = {}
    where: dict[int, list[Path]] = {}
    same: dict | None = None
    for p in map(Path, paths):
        data = read_json(p, "bench morph result")
        seed, suite = suite_of(p, data)
        s = data["settings"]
        fixed = recorded_run_settings(s)
        if same is None:
            same, first = fixed, p
        elif fixed != same:
            raise UsageError(f"{p}: settings {fixed} differ from {first}'s {same}: not draws of one experiment")
        if seed in runs:  # one draw run in parts (e.g. the suite, then the unseen meshes): merged, meshes disjoint
            again = sorted(set(runs[seed]["meshes"]) & set(suite["meshes"]))
            if again:
                raise UsageError(f"{p}: seed {seed} again with {', '.join(again)} (also in "
                                 f"{', '.join(map(str, where[seed]))}): one result per mesh and draw")
            runs[seed] = merged_suites(runs[seed], suite)
            where[seed].append(p)
        else:
            runs[seed], where[seed] = suite, [p]
    seeds = sorted(runs)
    if len(seeds) < 2:
        raise UsageError("the suite over draws needs results of at least two seeds")
    names = list(dict.fromkeys(n for k in seeds for n in runs[k]["meshes"]))
    meshes = {}
    for n in names:
        at = {k: runs[k]["meshes"][n] for k in seeds if n in runs[k]["meshes"]}
        cr = np.array([r["chamfer_reduction"] for r in at.values()])
        pg = np.array([r["psnr_gain_db"] for r in at.values()])
        meshes[n] = {
            "kind": next(iter(at.values())).get("kind"), "seeds": list(at),
            "per_seed": {str(k): {"chamfer_reduction": r["chamfer_reduction"], "psnr_gain_db": r["psnr_gain_db"],
                                  "spike_vertices": r["spike_vertices"], "inverted_triangles": r["inverted_triangles"],
                                  "facing_area": r["facing_against_truth_area"],
                                  "normal_consistency": r["normal_consistency"], "seconds": r["seconds"],
                                  "passes": r["passes"],
                                  "failing": [c for c, ok in r["checks"].items() if not ok]} for k, r in at.items()},
            "chamfer_reduction": {"mean": float(cr.mean()), "worst": float(cr.min()), "best": float(cr.max()),
                                  "sd": float(cr.std(ddof=1)) if len(cr) > 1 else None},
            "psnr_gain_db": {"mean": float(pg.mean()), "worst": float(pg.min()), "best": float(pg.max())},
            "spike_vertices_max": int(max(r["spike_vertices"] for r in at.values())),
            "inverted_triangles_max": int(max(r["inverted_triangles"] for r in at.values())),
            "passes": int(sum(r["passes"] for r in at.values())), "of": len(at)}
    per_seed = {str(k): {"files": [str(p) for p in where[k]], "passing": sum(r["passes"] for r in runs[k]["meshes"].values()),
                         "of": len(runs[k]["meshes"]), "mean": runs[k]["mean"], "failing": runs[k]["failing"]}
                for k in seeds}
    return {"seeds": seeds, "settings": same, "targets": TARGETS, "meshes": meshes, "per_seed": per_seed,
            "every_seed_pass": [n for n, m in meshes.items() if m["passes"] == m["of"]],
            "chamfer_reduction_mean": float(np.mean([m["chamfer_reduction"]["mean"] for m in meshes.values()])),
            "chamfer_reduction_worst_mean": float(np.mean([m["chamfer_reduction"]["worst"] for m in meshes.values()])),
            "psnr_gain_db_mean": float(np.mean([m["psnr_gain_db"]["mean"] for m in meshes.values()]))}


def seeds_chart(summary: dict, path: Path) -> Path:
    """Per mesh, its Chamfer reduction and held-out PSNR gain at every draw (one marker per seed), the mean as a
    bar, the targets as lines: how far one draw's verdict can be trusted."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from foundation.imageio import save_figure

    names = list(summary["meshes"])
    x = np.arange(len(names))
    fig, ax = plt.subplots(1, 2, figsize=(max(8.0, 0.9 * len(names) + 3), 4))
    for j, (key, scale, target, label) in enumerate((
            ("chamfer_reduction", 100.0, TARGETS["chamfer_reduction"] * 100, "Chamfer reduction (%)"),
            ("psnr_gain_db", 1.0, TARGETS["psnr_gain_db"], "held-out PSNR gain (dB)"))):
        a = ax[j]
        a.bar(x, [summary["meshes"][n][key]["mean"] * scale for n in names], color="0.85", label="mean")
        for i, k in enumerate(summary["seeds"]):
            at = [(xi, summary["meshes"][n]["per_seed"][str(k)]) for xi, n in zip(x, names)
                  if str(k) in summary["meshes"][n]["per_seed"]]
            xs = np.array([xi for xi, _ in at]) + 0.12 * (i - (len(summary["seeds"]) - 1) / 2)
            ys = np.array([r[key] * scale for _, r in at])
            ok = np.array([r["passes"] for _, r in at], bool)
            line, = a.plot(xs[ok], ys[ok], "o", ms=5, label=f"seed {k}")
            # a draw that misses any target (not only this panel's): hollow
            a.plot(xs[~ok], ys[~ok], "o", ms=5, mfc="none", color=line.get_color())
        a.axhline(target, color="tab:red", ls="--", lw=0.8, label="target")
        # how many draws each mesh ran and passed: a mesh run at one draw only is not "held at every draw"
        a.set_xticks(x, [f"{n} {summary['meshes'][n]['passes']}/{summary['meshes'][n]['of']}" for n in names],
                     rotation=45, ha="right", fontsize=8)
        a.set_ylabel(label)
        a.grid(alpha=0.3, axis="y")
    ax[0].legend(fontsize=7, title="hollow: a target missed", title_fontsize=7)
    n_pass = len(summary["every_seed_pass"])
    runs = sorted({m["of"] for m in summary["meshes"].values()})  # a mesh need not run at every seed
    fig.suptitle(f"morph suite over {len(summary['seeds'])} seeds: {n_pass} of {len(names)} meshes meet every "
                 "target at every draw they ran" + (f" ({runs[0]}–{runs[-1]} draws a mesh)" if len(runs) > 1 else "")
                 + "; ticks: draws passed / run")
    return save_figure(fig, path)


def sign_test(wins: int, losses: int) -> float:
    """Two-sided sign test: the chance of a split at least this uneven if either side were as likely (ties out)."""
    from math import comb

    n = wins + losses
    if n == 0:
        return 1.0
    k = min(wins, losses)
    return min(1.0, 2.0 * sum(comb(n, i) for i in range(k + 1)) / 2.0 ** n)


def seeds_compare(new: dict, base: dict) -> dict:
    """Two settings of the suite over the same draws (two :func:`seeds_summary` results), paired by mesh and seed:
    what one change did, beside how much a draw alone moves a mesh. Per pair the change in Chamfer reduction and PSNR
    gain (new − base; positive: the new is better) and whether every target holds in each; over the pairs the mean
    change with its standard error, wins and losses with a two-sided sign test, the targets gained and lost."""
    from foundation.errors import UsageError

    if new["settings"] != base["settings"]:
        raise UsageError(f"the two sets differ in {new['settings']} against {base['settings']}: not the same "
                         "experiment under two settings")
    pairs, meshes = [], {}
    for n, m in new["meshes"].items():
        b = base["meshes"].get(n)
        common = [k for k in m["per_seed"] if b is not None and k in b["per_seed"]]
        if not common:
            continue
        rows = []
        for k in sorted(common, key=int):
            x, y = m["per_seed"][k], b["per_seed"][k]
            rows.append({"seed": int(k), "chamfer_reduction": {"base": y["chamfer_reduction"],
                                                               "new": x["chamfer_reduction"]},
                         "chamfer_delta": x["chamfer_reduction"] - y["chamfer_reduction"],
                         "psnr_delta_db": x["psnr_gain_db"] - y["psnr_gain_db"],
                         "passes": {"base": y["passes"], "new": x["passes"]},
                         "failing": {"base": y["failing"], "new": x["failing"]}})
        pairs += [(n, r) for r in rows]
        meshes[n] = {"per_seed": rows, "chamfer_delta_mean": float(np.mean([r["chamfer_delta"] for r in rows])),
                     "passes": {"base": sum(r["passes"]["base"] for r in rows),
                                "new": sum(r["passes"]["new"] for r in rows), "of": len(rows)}}
    if not pairs:
        raise UsageError("the two sets share no mesh at any seed: nothing to compare")
    d = np.array([r["chamfer_delta"] for _, r in pairs])
    g = np.array([r["psnr_delta_db"] for _, r in pairs])
    wins, losses = int((d > 0).sum()), int((d < 0).sum())

    def spread(x: np.ndarray) -> dict:
        sd = float(x.std(ddof=1)) if len(x) > 1 else None
        return {"mean": float(x.mean()), "sd": sd, "se": None if sd is None else sd / np.sqrt(len(x))}

    return {"pairs": len(pairs), "seeds": sorted({r["seed"] for _, r in pairs}), "meshes": meshes,
            "chamfer_delta": spread(d), "psnr_delta_db": spread(g),
            "wins": wins, "losses": losses, "sign_test_p": sign_test(wins, losses),
            "passes": {"base": sum(r["passes"]["base"] for _, r in pairs),
                       "new": sum(r["passes"]["new"] for _, r in pairs), "of": len(pairs)},
            "gained": [f"{n}@{r['seed']}" for n, r in pairs if r["passes"]["new"] and not r["passes"]["base"]],
            "lost": [f"{n}@{r['seed']}" for n, r in pairs if r["passes"]["base"] and not r["passes"]["new"]],
            "every_seed_pass": {"base": [n for n, m in meshes.items() if m["passes"]["base"] == m["passes"]["of"]],
                                "new": [n for n, m in meshes.items() if m["passes"]["new"] == m["passes"]["of"]]}}


def compare_chart(comparison: dict, path: Path) -> Path:
    """Per mesh the change in Chamfer reduction at each draw (new − base, points; above zero the new is better):
    ▲ a draw that now meets every target and did not, ▼ one that no longer does, ● no change of verdict."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from foundation.imageio import save_figure

    names = list(comparison["meshes"])
    seeds = comparison["seeds"]
    x = np.arange(len(names))
    fig, ax = plt.subplots(figsize=(max(7.0, 0.7 * len(names) + 3), 4))
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for i, k in enumerate(seeds):
        labelled = False  # one legend entry per seed
        for xi, n in zip(x, names):
            r = next((r for r in comparison["meshes"][n]["per_seed"] if r["seed"] == k), None)
            if r is None:
                continue
            p = r["passes"]
            marker = "^" if p["new"] and not p["base"] else "v" if p["base"] and not p["new"] else "o"
            ax.plot(xi + 0.12 * (i - (len(seeds) - 1) / 2), r["chamfer_delta"] * 100, marker, ms=6,
                    color=colours[i % len(colours)], label=None if labelled else f"seed {k}")
            labelled = True
    ax.axhline(0.0, color="0.3", lw=0.8)
    ax.set_xticks(x, names, rotation=45, ha="right", fontsize=8)
    ax.set_ylabel("Chamfer reduction, new − base (points)")
    ax.grid(alpha=0.3, axis="y")
    ax.legend(fontsize=7, title="▲ gained every target, ▼ lost", title_fontsize=7)
    c, p = comparison["chamfer_delta"], comparison["passes"]
    se = f" ± {c['se'] * 100:.2f}" if c["se"] is not None else ""
    fig.suptitle(f"new against base over {comparison['pairs']} mesh-draws: Chamfer "
                 f"{c['mean'] * 100:+.2f}{se} points, {comparison['wins']} better / {comparison['losses']} worse; "
                 f"every target {p['base']} → {p['new']} of {p['of']}", fontsize=9)
    return save_figure(fig, path)


# -- the benchmark protocol (photoreal.benchmarks) -------------------------------------------------------------------


@dataclass
class MorphSeedsSettings:
    results: tuple[str, ...] = ()  #: bench morph JSON files with a suite, one per seed (or parts of one seed's suite)
    against: tuple[str, ...] = ()  #: the same draws under other settings, compared with these draw by draw


SETTINGS = MorphSeedsSettings
WORK = False


def run(s: MorphSeedsSettings, work, pool, show_progress: bool) -> dict:
    summary = seeds_summary(s.results)  # every file read and checked before anything is written
    if s.against:
        summary["against"] = seeds_summary(s.against)
        summary["comparison"] = seeds_compare(summary, summary["against"])
    return summary


def charts(result: dict, json_path: Path, work: Path | None) -> dict:
    out = Path(json_path)
    if "comparison" in result:
        result["comparison"]["chart"] = str(compare_chart(result["comparison"], out.with_name(out.stem + "_against.png")))
    return {"chart": str(seeds_chart(result, out.with_name(out.stem + ".png")))}


def summary(result: dict) -> dict:
    shown = {"seeds": result["seeds"], "every_seed_pass": result["every_seed_pass"],
             "passes": {n: f"{m['passes']} of {m['of']}" for n, m in result["meshes"].items()},
             "chamfer_reduction_worst": {n: round(m["chamfer_reduction"]["worst"], 4)
                                         for n, m in result["meshes"].items()}}
    if "comparison" in result:
        c = result["comparison"]
        shown["against"] = {"pairs": c["pairs"], "chamfer_delta_mean": round(c["chamfer_delta"]["mean"], 4),
                            "chamfer_delta_se": c["chamfer_delta"]["se"] and round(c["chamfer_delta"]["se"], 4),
                            "wins": c["wins"], "losses": c["losses"], "sign_test_p": round(c["sign_test_p"], 3),
                            "passes_every_target": c["passes"], "gained": c["gained"], "lost": c["lost"]}
    return shown


def options(p) -> None:
    from photoreal.options import opt

    p.add_argument("results", nargs="+", help="bench morph JSON files with a suite, one per seed (a seed's suite "
                                              "run in parts: its files, each with other meshes)")
    opt(p, MorphSeedsSettings, "against", metavar="RESULT",
        help="the same draws under other settings (e.g. before a change): paired by mesh and seed, the change per "
             "draw, its mean and standard error, wins and losses (sign test), targets gained and lost, and a chart "
             "OUT_against.png")
