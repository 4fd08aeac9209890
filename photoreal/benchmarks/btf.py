"""`photoreal bench btf`: neural BTF quality (seed 002 Table 1 / Fig. 4) and speed vs accuracy.

One run, on this machine, in this order:

1. data — 4 training + 1 held-out SVBRDF per family rendered as BTFs (cached and resumable);
2. universal bases, one per MLP width, trained on the training materials (§4.2, checkpointed);
3. per held-out material: feature textures fitted with the basis frozen (§4.3) vs a NeuMIP-style
   per-material network of the same architecture (§5.2); PSNR on held-out slices (directions never
   used in fitting);
4. sweep over widths × feature-texture resolutions: PSNR vs render time of a scene whose surfaces
   all use ``neural_btf``, against builtin ``principled`` rendered in the same run;
5. network throughput: M_rgb through the plugin's own code path (cooperative vectors) vs the same
   weights batched in torch on the CPU;
6. assets for the demo scene (the chosen basis and a few fitted materials).

PSNR is computed on BTF values clipped to [0, 1] (radiance under unit irradiance; 1 = a white
Lambertian at normal incidence × π), the displayable range of the slices; near-mirror peaks of
metal and ceramic reach 10²–10³ in our data and would otherwise dominate the MSE. The unclipped
PSNR is reported beside it (``psnr_hdr``).
"""

from __future__ import annotations

import gc
import statistics
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

import mi_plugins  # noqa: F401
import drjit as dr
import mitsuba as mi

from foundation import validate
from foundation.assets import envmap
from foundation.errors import UsageError
from foundation.imageio import save_figure
from foundation.progress import progress_bar
from inverse.btf import (FAMILIES, BTFRenderSettings, OptimSettings, load_dataset, predict,
                         psnr_pair, render_dataset, split_slices, train_basis, train_per_material)
from foundation.pool import Item, PoolSettings, default_workers, run_items
from mi_plugins.neural_basis import (Basis, BasisConfig, CoopNet, NeuralMaterial, load_material, save_basis,
                                     save_material)


@dataclass
class BTFBenchSettings:
    data_dir: str | None = None             #: train/ and heldout/ subfolders (rendered if missing); None: WORK/data
    train_per_family: int = 4               #: 8 families × 4 = 32 training materials (issue default)
    render: BTFRenderSettings = field(default_factory=BTFRenderSettings)
    widths: tuple[int, ...] = (16, 32, 64)
    tex_res: tuple[int, ...] = (32, 64)
    default_width: int = 64
    train_iterations: int = 2500
    train_batch: int = 1 << 15
    fit_iterations: int = 600
    fit_batch: int = 1 << 13
    neumip_iterations: int = 1000
    neumip_batch: int = 1 << 13
    render_resolution: int = 128
    render_spp: int = 16
    render_reps: int = 3
    mlp_evals: int = 1 << 20
    seed: int = 0

    def __post_init__(self):
        validate.integer("train_per_family", self.train_per_family, 1)
        for w in self.widths:
            validate.integer("widths", w, 1)
        for r in self.tex_res:
            validate.integer("tex_res", r, 2)
        if self.default_width not in self.widths:
            raise UsageError(f"default_width {self.default_width} is not among widths {self.widths}")
        for name in ("train_iterations", "train_batch", "fit_iterations", "fit_batch", "neumip_iterations",
                     "neumip_batch", "render_resolution", "render_spp", "render_reps", "mlp_evals"):
            validate.integer(name, getattr(self, name), 1)
        validate.seed("seed", self.seed)


def _score(basis: Basis, mat: NeuralMaterial, data, held) -> dict:
    ref = np.asarray(data.values, np.float32)[held]
    a, b = psnr_pair(predict(basis, mat, data, held), ref)
    return {"psnr": a, "psnr_hdr": b}


# -- render timing -------------------------------------------------------------------------------


def timing_scene(bsdf: dict, s: BTFBenchSettings) -> dict:
    """A sphere on a floor under a real HDRI; both surfaces use ``bsdf`` (UV-mapped, tiled 4×)."""
    return {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 4},
        "sensor": {"type": "perspective", "fov": 35,
                   "to_world": mi.ScalarTransform4f().look_at(origin=[0, 1.6, 4.2], target=[0, 0.7, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": s.render_resolution, "height": s.render_resolution},
                   "sampler": {"type": "independent", "sample_count": s.render_spp}},
        "env": envmap("forest"),
        "sphere": {"type": "sphere", "center": [0, 0.8, 0], "radius": 0.8, "bsdf": bsdf},
        "floor": {"type": "rectangle", "bsdf": bsdf, "to_world": mi.ScalarTransform4f().scale(4).rotate([1, 0, 0], -90)},
    }


def time_render(bsdf: dict, s: BTFBenchSettings, evaluated: bool = False) -> float:
    """Median ms of ``render_reps`` renders after a warm-up render (tracing + compile excluded).

    ``evaluated``: Dr.Jit's wavefront mode (symbolic loops/calls off), how photoreal renders scenes
    with ``neural_btf``. The scene is freed afterwards: Mitsuba traces every live BSDF in every render.
    """
    from mi_plugins.bsdfs.neural_btf import evaluated_mode

    scene = mi.load_dict(timing_scene(bsdf, s))
    with evaluated_mode(evaluated):
        dr.eval(mi.render(scene, spp=s.render_spp, seed=0))
        times = []
        for r in range(s.render_reps):
            t0 = time.perf_counter()
            img = mi.render(scene, spp=s.render_spp, seed=1 + r)
            dr.eval(img)
            dr.sync_thread()
            times.append(time.perf_counter() - t0)
    del scene, img
    gc.collect()
    return 1000.0 * statistics.median(times)


def mlp_throughput(basis: Basis, n: int, seed: int) -> dict:
    """M_rgb on n random inputs: plugin code path (CoopVec) vs torch with the same weights."""
    import torch

    rng = np.random.default_rng(seed)
    x = rng.standard_normal((basis.config.rgb_in, n)).astype(np.float32)
    net = CoopNet(basis.m_rgb, training=True)  # the plugin's own packing (it backpropagates into textures)
    ins = [mi.Float(r) for r in x]
    best_dr = np.inf
    for _ in range(4):  # first run compiles
        t0 = time.perf_counter()
        out = net(ins)
        dr.eval(out)
        dr.sync_thread()
        best_dr = min(best_dr, time.perf_counter() - t0)
    y_dr = np.stack([o.numpy() for o in out])
    layers = []
    for k, (w, b) in enumerate(basis.m_rgb):
        lin = torch.nn.Linear(w.shape[1], w.shape[0])
        with torch.no_grad():
            lin.weight.copy_(torch.from_numpy(w))
            lin.bias.copy_(torch.from_numpy(b))
        layers.append(lin)
        if k < len(basis.m_rgb) - 1:
            layers.append(torch.nn.ReLU())
    tnet = torch.nn.Sequential(*layers)
    xt = torch.from_numpy(np.ascontiguousarray(x.T))
    best_t = np.inf
    with torch.inference_mode():
        for _ in range(4):
            t0 = time.perf_counter()
            y_t = tnet(xt)
            best_t = min(best_t, time.perf_counter() - t0)
    err = float(np.abs(y_t.numpy().T - y_dr).max())
    return {"mlp_evals_per_s_drjit": n / best_dr, "mlp_evals_per_s_torch": n / best_t,
            "torch_threads": torch.get_num_threads(), "max_abs_diff_drjit_vs_torch": err,
            "network": f"M_rgb {basis.config.rgb_in}→" + "→".join(str(w.shape[0]) for w, _ in basis.m_rgb)}


# -- the bench -----------------------------------------------------------------------------------


def _chart(result: dict, path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for r in result["sweep"]:
        ax.scatter(r["ms"], r["psnr"], s=30 + r["tex_res"], label=f"width {r['width']}, {r['tex_res']}²")
        ax.annotate(f"w{r['width']}/{r['tex_res']}", (r["ms"], r["psnr"]), fontsize=7, xytext=(3, 3),
                    textcoords="offset points")
    ax.axvline(result["principled_ms"], color="k", ls="--", lw=1, label="principled (same scene)")
    c = result["chosen"]
    ax.scatter([c["ms"]], [c["psnr"]], marker="*", s=220, color="gold", edgecolor="k", zorder=5, label="chosen")
    ax.set_xlabel(f"render time, ms ({result['settings']['render_resolution']}², {result['settings']['render_spp']} spp)")
    ax.set_ylabel("held-out slice PSNR, dB (mean over families)")
    ax.set_title("neural BTF: accuracy vs render time")
    ax.legend(fontsize=7, loc="lower right")
    ax.grid(alpha=0.3)
    return save_figure(fig, path)


def bench_btf(s: BTFBenchSettings, work: Path, show_progress: bool = True, pool: PoolSettings | None = None) -> dict:
    """The whole bench (see the module docstring), in ``work``: the BTF data (``data/``, rendered once), the bases
    and fits, and the demo's assets (``assets/``: the chosen basis and the held-out materials fitted in it).
    ``pool`` renders the dataset and runs the held-out fits (independent items) on worker processes or Ray;
    trainings and every timing run here, alone."""
    work = Path(work)
    data_dir = Path(s.data_dir) if s.data_dir else work / "data"
    pool = pool or PoolSettings(workers=default_workers(), threads=1)
    t_start = time.perf_counter()
    render_dataset(data_dir / "heldout", per_family=1, settings=s.render, base_seed=1000 + s.seed,
                   progress=show_progress, pool=pool)
    render_dataset(data_dir / "train", per_family=s.train_per_family, settings=s.render, base_seed=s.seed,
                   progress=show_progress, pool=pool)
    train, held_mats = load_dataset(data_dir / "train"), load_dataset(data_dir / "heldout")
    n_slices = train[0].values.shape[0]
    fit_sl, held_sl = split_slices(n_slices)

    bases: dict[int, Basis] = {}
    train_s = {}
    for w in s.widths:
        cfg = BasisConfig(width=w)
        ts = OptimSettings(iterations=s.train_iterations, batch=s.train_batch, seed=s.seed)
        t0 = time.perf_counter()
        bases[w], hist = train_basis(train, cfg, ts, checkpoint=work / f"basis_w{w}.ckpt.npz", progress=show_progress)
        train_s[w] = {"final_l1": hist[-1]["l1"], "seconds_this_run": time.perf_counter() - t0,
                      "history": hist}
        save_basis(work / f"basis_w{w}.npz", bases[w])

    # Universal fit (every width × texture resolution) on every held-out material.
    fits: dict[tuple[int, int], list[dict]] = {}
    mats: dict[tuple[int, int], list[NeuralMaterial]] = {}
    configs = [(w, r) for w in s.widths for r in s.tex_res]
    # independent fits: items for the pool (each resumes from its checkpoint; a finished one is skipped)
    items = [Item(f"w{w}_r{r}_{d.meta['name']}", "inverse.btf:fit_file",
                  (str(data_dir / "heldout" / f"{d.meta['name']}.npz"), str(work / f"basis_w{w}.npz"),
                   str(work / f"fit_w{w}_r{r}_{d.meta['name']}.npz")),
                  {"iterations": s.fit_iterations, "batch": s.fit_batch, "tex_res": r, "seed": s.seed},
                  output=str(work / f"fit_w{w}_r{r}_{d.meta['name']}.npz"))
             for w, r in configs for d in held_mats]
    report = run_items(items, pool, desc="fit held-out", show_progress=show_progress)
    report.raise_if_failed()
    done = {r.key: r for r in report.results}
    for w, r in configs:
        fits[(w, r)], mats[(w, r)] = [], []
        for d in held_mats:
            key = f"w{w}_r{r}_{d.meta['name']}"
            mat = load_material(work / f"fit_{key}.npz")
            value = done[key].value or {}
            fits[(w, r)].append({"material": d.meta["name"], "family": d.meta["family"],
                                 **_score(bases[w], mat, d, held_sl), "fit_seconds": value.get("seconds")})
            mats[(w, r)].append(mat)

    # NeuMIP-style per-material networks (same architecture, default width, full texture res).
    neumip = []
    r_full = s.render.tex_res
    with progress_bar(total=len(held_mats), desc="NeuMIP baseline", disable=not show_progress) as bar:
        for d in held_mats:
            ns = OptimSettings(iterations=s.neumip_iterations, batch=s.neumip_batch, seed=s.seed)
            t0 = time.perf_counter()
            b, m, _ = train_per_material(d, fit_sl, BasisConfig(width=s.default_width), ns, progress=False,
                                         checkpoint=work / f"neumip_{d.meta['name']}.ckpt.npz")
            neumip.append({"material": d.meta["name"], "family": d.meta["family"], **_score(b, m, d, held_sl),
                           "train_seconds": time.perf_counter() - t0})
            bar.update(1)

    # Render time per configuration vs principled, in the same run.
    # Reference: principled in whichever mode is faster for it (symbolic, normally) — conservative.
    principled = {"type": "principled", "base_color": {"type": "rgb", "value": [0.5, 0.4, 0.3]}, "roughness": 0.4}
    ms_principled_modes = {"symbolic": time_render(principled, s), "evaluated": time_render(principled, s, True)}
    ms_principled = min(ms_principled_modes.values())
    sweep = []
    for w, r in configs:
        mat_path = work / f"timing_w{w}_r{r}.npz"
        save_material(mat_path, mats[(w, r)][0])
        nbsdf = {"type": "neural_btf", "basis": str(work / f"basis_w{w}.npz"), "material": str(mat_path), "tiling": 4.0}
        ms = time_render(nbsdf, s, evaluated=True)
        ms_sym = time_render(nbsdf, s, evaluated=False)
        sweep.append({"width": w, "tex_res": r, "psnr": float(np.mean([f["psnr"] for f in fits[(w, r)]])),
                      "psnr_hdr": float(np.mean([f["psnr_hdr"] for f in fits[(w, r)]])), "ms": ms,
                      "vs_principled": ms / ms_principled, "ms_symbolic": ms_sym,
                      "vs_principled_symbolic": ms_sym / ms_principled_modes["symbolic"]})
    best = max(x["psnr"] for x in sweep)
    # "Model no more than a scene needs": the cheapest configuration within 0.5 dB of the best.
    ok = [x for x in sweep if x["psnr"] >= best - 0.5]
    chosen = min(ok, key=lambda x: (x["ms"], x["width"], x["tex_res"]))

    main_key = (s.default_width, r_full)
    uni = fits[main_key]
    table = []
    for u, n in zip(uni, neumip):
        table.append({"family": u["family"], "material": u["material"], "psnr_universal": u["psnr"],
                      "psnr_per_material": n["psnr"], "psnr_universal_hdr": u["psnr_hdr"],
                      "psnr_per_material_hdr": n["psnr_hdr"]})
    thr = mlp_throughput(bases[s.default_width], s.mlp_evals, s.seed)

    # Demo assets: chosen basis + the held-out materials fitted in it.
    assets = work / "assets"
    save_basis(assets / "basis.npz", bases[chosen["width"]])
    for d, m in zip(held_mats, mats[(chosen["width"], chosen["tex_res"])]):
        save_material(assets / f"{d.meta['family']}.npz", m)

    result = {
        "psnr_universal_mean": float(np.mean([t["psnr_universal"] for t in table])),
        "psnr_per_material_mean": float(np.mean([t["psnr_per_material"] for t in table])),
        "psnr_universal_hdr_mean": float(np.mean([t["psnr_universal_hdr"] for t in table])),
        "psnr_per_material_hdr_mean": float(np.mean([t["psnr_per_material_hdr"] for t in table])),
        "neural_btf_ms": chosen["ms"], "principled_ms": ms_principled, "principled_ms_modes": ms_principled_modes,
        "render_mode_note": ("neural_btf timed in Dr.Jit's evaluated (wavefront) mode, as photoreal renders it; "
                             "ms_symbolic = the same render in the default symbolic mode; principled_ms = the "
                             "faster of its two modes"),
        "neural_btf_vs_principled": chosen["ms"] / ms_principled,
        "neural_btf_default_ms": next(x["ms"] for x in sweep if (x["width"], x["tex_res"]) == main_key),
        **{k: thr[k] for k in ("mlp_evals_per_s_drjit", "mlp_evals_per_s_torch")},
        "mlp_drjit_vs_torch": thr["mlp_evals_per_s_drjit"] / thr["mlp_evals_per_s_torch"],
        "mlp": thr,
        "sweep": sweep,
        "chosen": {k: chosen[k] for k in ("width", "tex_res", "psnr", "ms", "vs_principled")},
        "table": table,
        "fits": {f"w{w}_r{r}": v for (w, r), v in fits.items()},
        "neumip": neumip,
        "training": {f"w{w}": {k: v for k, v in t.items() if k != "history"} for w, t in train_s.items()},
        "training_curves": {f"w{w}": t["history"] for w, t in train_s.items()},
        "data": {"train_materials": [m.meta["name"] for m in train], "heldout_materials": [m.meta["name"] for m in held_mats],
                 "slices": n_slices, "fit_slices": len(fit_sl), "heldout_slices": len(held_sl),
                 "tex_res": r_full, "families": list(FAMILIES)},
        "psnr_note": "PSNR on BTF values clipped to [0, 1] (peak 1); *_hdr: unclipped values, peak 1",
        "settings": asdict(s),
        "seconds": time.perf_counter() - t_start,
    }
    return result


# -- the benchmark protocol (photoreal.benchmarks) -------------------------------------------------------------------

SETTINGS = BTFBenchSettings
POOL = True
SUMMARY = ("psnr_universal_mean", "psnr_per_material_mean", "neural_btf_ms", "principled_ms", "neural_btf_vs_principled",
           "mlp_evals_per_s_drjit", "mlp_evals_per_s_torch", "chosen")


def run(s: BTFBenchSettings, work: Path, pool, show_progress: bool) -> dict:
    return bench_btf(s, work, show_progress, pool)


def options(p) -> None:
    """Its settings are the issue's protocol (no flags beyond the runner's)."""


def charts(result: dict, json_path: Path, work: Path | None) -> dict:
    return {"chart": str(_chart(result, Path(json_path).parent / "btf_speed_accuracy.png"))}
