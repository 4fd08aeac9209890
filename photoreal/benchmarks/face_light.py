"""`photoreal bench face-light`: the face fit under light it does not know, per light model.

For each scan, the cross-model benchmark (Mitsuba's ``principled`` observations under the bundled lighting HDRIs
at seeded rotations, path length ``max_depth`` with interreflection, albedo spread by ``albedo_blur``) is fitted
with unknown lighting by every light model of ``models``: ``directional`` (one key light + an ambient per
observation) and ``sh<order>`` (an environment per observation in spherical harmonics, occluded by the mesh's
own transfer; ``sh<order>-unoccluded`` without it). Each row: albedo PSNR (after the global scale), normal error,
relit PSNR under each held-out HDRI, fit seconds — the speed-vs-accuracy chart over the light model.

The **model floor** of each SH order says what the model could reach at best: the observations predicted by the
UV shader from the *true* maps (as rendered, blur included) and the *true* HDRIs projected onto that order, with
the transfer, against the observations (PSNR on the seen texels). The **fitted floor** replaces the projection by
each observation's least-squares best coefficients of that order (what a fit of the light could explain with the
true maps; never below the projected floor). The **relit floor** relights the true maps through the fit's own
relighting: a target above it cannot be met by any fit on this benchmark.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from foundation import validate
from foundation.errors import UsageError
from foundation.progress import progress_bar

TARGETS = {"albedo_psnr": 30.0, "normal_err_deg": 8.0, "relit_psnr_each": 32.0, "fit_seconds": 120.0}


@dataclass
class FaceLightBenchSettings:
    scans: tuple[str, ...] = ("josie", "paul")  #: bundled heads or OBJ paths
    uv_res: int = 256
    models: tuple[str, ...] = ("directional", "sh0", "sh1", "sh2", "sh4", "sh2-unoccluded")
    max_depth: int = 4
    albedo_blur: float = 1.5
    iterations: tuple[int, ...] = (80, 300)  #: the fit's Adam steps per pyramid level (face fit's default)
    render_res: int = 192  #: the benchmark's camera and held-out renders
    seed: int = 0

    def __post_init__(self):
        validate.integer("uv_res", self.uv_res, 16, 4096)
        validate.integer("render_res", self.render_res, 8, 4096)
        for m in self.models:
            _model_settings(m)
        if not self.scans:
            raise UsageError("scans: at least one scan is needed")
        validate.seed("seed", self.seed)


def _model_settings(name: str) -> dict:
    """FaceFitSettings fields of a light model's name: ``directional``, ``sh<order>``, ``sh<order>-unoccluded``."""
    if name == "directional":
        return {"light_model": "directional"}
    base, _, tail = name.partition("-")
    if not (base.startswith("sh") and base[2:].isdigit()) or tail not in ("", "unoccluded"):
        raise UsageError(f"models: {name!r} is not directional, sh<order> or sh<order>-unoccluded")
    return {"light_model": "sh", "sh_order": int(base[2:]), "occlusion": tail != "unoccluded"}


def _small(px: np.ndarray, rows: int = 128) -> np.ndarray:
    """A lat-long map box-averaged to about ``rows`` rows: a sun keeps its energy, and orders ≤ 6 need no more."""
    f = max(1, px.shape[0] // rows)
    h, w = px.shape[0] // f * f, px.shape[1] // f * f
    return px[:h, :w].reshape(h // f, f, w // f, f, -1).mean((1, 3))


def _truth_shading(bench):
    """The UV shader's inputs for the true maps (as rendered, blur included) and a numpy → tensor helper."""
    import mitsuba as mi

    from inverse.face import rendered_maps
    from mi_plugins.arrays import aligned
    from mi_plugins.uv_shader import UVMaps

    g, gt = bench.geometry, rendered_maps(bench.ground_truth, bench.settings)
    t = lambda a: mi.TensorXf(aligned(np.ascontiguousarray(a, np.float32)))  # noqa: E731
    maps = UVMaps(albedo=t(gt["albedo"]), normal=t(gt["normal"] * 0.5 + 0.5), roughness=t(gt["roughness"]),
                  specular=t(gt["specular"]))
    return maps, (t(g["position"]), t(g["normal"]), t(g["tangent"])), t


def model_floor(bench, order: int, transfer: np.ndarray) -> float:
    """PSNR of the observations predicted from the true maps and the true HDRIs projected onto SH ``order``
    (``transfer``: that order's channels, or more: the basis is nested, so the first (order + 1)² are used)."""
    import mitsuba as mi

    from foundation.assets import hdri_pixels
    from foundation.metrics import psnr
    from mi_plugins import sh
    from mi_plugins.uv_shader import UVEnvironment, UVView, shade_uv

    maps, (pos, nrm, tan), t = _truth_shading(bench)
    transfer = t(transfer[..., :sh.n_coeffs(order)])
    pred_all, obs_all = [], []
    for k, light in enumerate(bench.meta.lights):
        rot = np.array(mi.ScalarTransform4f().rotate([0, 1, 0], light.rotation_deg).matrix)[:3, :3]
        hdri = str(bench.path / light.hdri) if light.hdri.startswith("hdri/") else light.hdri
        env = UVEnvironment(sh.project_envmap(_small(hdri_pixels(hdri)), order, rot), transfer)
        for v, eye in enumerate(bench.meta.views):
            seen = bench.visibility[f"v{v}"] > 0
            pred = np.array(shade_uv(pos, nrm, tan, maps, [], UVView(position=tuple(eye)), environment=env))
            pred_all.append(pred[seen])
            obs_all.append(bench.observations[f"v{v}_l{k}"][seen])
    return psnr(np.concatenate(pred_all), np.concatenate(obs_all))


def fitted_floor(bench, order: int, transfer: np.ndarray) -> float:
    """PSNR of the observations predicted from the true maps under each observation's *best* SH light of
    ``order``: its coefficients by linear least squares against the observation (per RGB channel) — the most a
    fit of the light can explain with the true maps, where :func:`model_floor` projects the true HDRI."""
    from foundation.metrics import psnr
    from mi_plugins import sh
    from mi_plugins.uv_shader import UVEnvironment, UVView, shade_uv

    maps, (pos, nrm, tan), t = _truth_shading(bench)
    n = sh.n_coeffs(order)
    transfer = t(transfer[..., :n])
    seen = [bench.visibility[f"v{v}"] > 0 for v in range(len(bench.meta.views))]
    # the shading is linear in the coefficients: one render per unit (white) coefficient serves every observation
    cols = []
    for j in range(n):
        unit = np.zeros((n, 3))
        unit[j] = 1.0
        env = UVEnvironment(unit, transfer)
        cols.append(np.concatenate([np.array(shade_uv(pos, nrm, tan, maps, [], UVView(position=tuple(eye)),
                                                      environment=env))[m] for eye, m in zip(bench.meta.views, seen)]))
    design = [np.stack([col[:, c] for col in cols], 1).astype(np.float64) for c in range(3)]  # per channel
    pred_all, obs_all = [], []
    for k in range(len(bench.meta.lights)):
        obs = np.concatenate([bench.observations[f"v{v}_l{k}"][m] for v, m in enumerate(seen)])
        pred = np.empty_like(obs)
        for c, a in enumerate(design):
            pred[:, c] = a @ np.linalg.lstsq(a, obs[:, c], rcond=None)[0]
        pred_all.append(pred)
        obs_all.append(obs)
    return psnr(np.concatenate(pred_all), np.concatenate(obs_all))


def relit_floor(bench) -> dict[str, float]:
    """Relit PSNR of the *true* maps under each held-out HDRI, through the same relighting as a fit's (the UV
    shader's ``ggx_uv`` render against the benchmark's reference): the most any fit can score there."""
    from inverse.face import FaceFitResult, evaluate_fit

    truth = FaceFitResult(dict(bench.ground_truth), bench.geometry["mask"] > 0, [], 0.0, [], 0.0)
    return {h: v.psnr for h, v in evaluate_fit(bench, truth).relit.items()}


def bench_face_light(s: FaceLightBenchSettings, work: Path, show_progress: bool = True) -> dict:
    from foundation.mesh import load_obj
    from foundation.records import to_json
    from inverse.face import (BENCHMARK_MARKER, FaceBenchmarkSettings, FaceFitSettings, bake_geometry,
                              environment_transfer, evaluate_fit, fit_face, load_benchmark, make_benchmark)

    from .face import FaceBenchSettings

    work = Path(work)
    out: dict = {"settings": asdict(s), "targets": TARGETS, "scans": {}}
    orders = sorted({_model_settings(m).get("sh_order", 2) for m in s.models if m != "directional"})
    with progress_bar(total=len(s.scans) * (len(s.models) + 1), desc="bench face-light", unit="fit",
                      disable=not show_progress) as bar:
        for scan in s.scans:
            path = FaceBenchSettings(scan=scan).scan_path()
            folder = work / f"{path.stem}_cross"
            bs = FaceBenchmarkSettings(uv_res=s.uv_res, seed=s.seed, observation_bsdf="principled", lighting="hdri",
                                       max_depth=s.max_depth, albedo_blur=s.albedo_blur,
                                       render_res=s.render_res)
            t0 = time.perf_counter()
            if not (folder / BENCHMARK_MARKER).is_file():  # the work folder keeps the benchmark between runs
                make_benchmark(path, folder, bs, show_progress=False)
            bench = load_benchmark(folder)
            row: dict = {"benchmark_seconds": time.perf_counter() - t0, "models": {}, "floor_psnr": {}}
            # one transfer at the highest order serves every lower one (same rays; the SH basis is nested)
            transfer = environment_transfer(bench.mesh_path, bake_geometry(load_obj(bench.mesh_path), s.uv_res),
                                            max(orders)) if orders else None
            row["fitted_floor_psnr"] = {}
            for order in orders:
                row["floor_psnr"][f"sh{order}"] = model_floor(bench, order, transfer)
                row["fitted_floor_psnr"][f"sh{order}"] = fitted_floor(bench, order, transfer)
            row["relit_floor"] = relit_floor(bench)
            bar.update(1)
            for name in s.models:
                fs = FaceFitSettings(fit_lights=True, seed=s.seed, iterations=tuple(s.iterations),
                                     **_model_settings(name))
                result = fit_face(bench, fs, show_progress=False)
                m = to_json(evaluate_fit(bench, result))
                relit = {h: v["psnr"] for h, v in m["relit"].items()}
                row["models"][name] = {
                    "albedo_psnr": m["albedo_psnr"], "normal_err_deg": m["normal_err_deg"],
                    "normal_err_deg_median": m["normal_err_deg_median"], "roughness_mae": m["roughness_mae"],
                    "specular_mae": m["specular_mae"], "displacement_corr": m["displacement_corr"],
                    "relit_psnr": m["relit_psnr"], "relit": relit, "relit_flip": m["relit_flip"],
                    "fit_seconds": result.seconds,
                    "meets_targets": bool(m["albedo_psnr"] >= TARGETS["albedo_psnr"]
                                          and m["normal_err_deg"] <= TARGETS["normal_err_deg"]
                                          and min(relit.values()) >= TARGETS["relit_psnr_each"]
                                          and result.seconds <= TARGETS["fit_seconds"])}
                bar.update(1)
            out["scans"][path.stem] = row
    out["any_model_meets_targets_on_every_scan"] = any(
        all(r["models"][m]["meets_targets"] for r in out["scans"].values()) for m in s.models)
    return out


def light_chart(result: dict, path: Path) -> Path:
    """Albedo PSNR and normal error against fit seconds, one marker per light model, one colour per scan."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from foundation.imageio import save_figure

    fig, ax = plt.subplots(1, 2, figsize=(10, 3.8))
    for scan, row in result["scans"].items():
        for key, a in (("albedo_psnr", ax[0]), ("normal_err_deg", ax[1])):
            xs = [r["fit_seconds"] for r in row["models"].values()]
            ys = [r[key] for r in row["models"].values()]
            a.plot(xs, ys, "o", label=scan)
            for name, x, y in zip(row["models"], xs, ys):
                a.annotate(name, (x, y), textcoords="offset points", xytext=(3, 3), fontsize=7)
    ax[0].axhline(TARGETS["albedo_psnr"], color="gray", ls="--", lw=0.8)
    ax[1].axhline(TARGETS["normal_err_deg"], color="gray", ls="--", lw=0.8)
    ax[0].set_ylabel("albedo PSNR (dB)")
    ax[1].set_ylabel("normal error (°)")
    for a in ax:
        a.set_xlabel("fit seconds (2 CPU cores)")
        a.grid(alpha=0.3)
        a.legend(fontsize=8)
    fig.suptitle("face fit under unknown environment light: light model vs accuracy and time (dashed: targets)")
    return save_figure(fig, path)


# -- the benchmark protocol (photoreal.benchmarks) -------------------------------------------------------------------

SETTINGS = FaceLightBenchSettings


def summary(result: dict) -> dict:
    return {f"{scan}.{name}": f"albedo {r['albedo_psnr']:.2f} dB, normals {r['normal_err_deg']:.2f}°, relit "
                              f"{r['relit_psnr']:.2f} dB, {r['fit_seconds']:.0f} s"
            for scan, row in result["scans"].items() for name, r in row["models"].items()}


def options(p) -> None:
    from photoreal.options import opt

    opt(p, FaceLightBenchSettings, "scans", metavar="SCAN", help="josie, paul, or OBJ paths")
    opt(p, FaceLightBenchSettings, "uv_res", type=int)
    opt(p, FaceLightBenchSettings, "models", metavar="MODEL",
        help="directional, sh<order>, sh<order>-unoccluded")
    opt(p, FaceLightBenchSettings, "seed", type=int)


def charts(result: dict, json_path: Path, work: Path | None) -> dict:
    return {"chart": str(light_chart(result, Path(json_path).parent / "face_light.png"))}


def run(s: FaceLightBenchSettings, work, pool, show_progress: bool) -> dict:
    return bench_face_light(s, work, show_progress)
