"""Face fitting workflows behind `photoreal face ...` and `photoreal bench face`."""

from __future__ import annotations

import shutil
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from inverse.face_data import FaceBenchmarkSettings, load_benchmark, make_benchmark
from inverse.face_fit import (FaceFitSettings, RenderRefineSettings, evaluate_fit, fit_face, refine_through_renders,
                              save_maps)

from .bench import write_json
from .progress import progress_bar

SCANS = Path(__file__).resolve().parent.parent / "scenes" / "assets" / "face" / "cyberheads"


def fit_benchmark_dir(bench_dir: str | Path, json_path: str | Path | None, maps_out: str | Path | None,
                      settings: FaceFitSettings, relight: bool = True, show_progress: bool = True,
                      refine: RenderRefineSettings | None = None) -> dict:
    """`photoreal face fit`: fit, evaluate against the ground truth, write maps and metrics.

    With ``refine``, the UV-space fit is followed by refinement through full
    camera renders (``prb`` through the ggx_uv plugin); both stages are scored.
    """
    bench = load_benchmark(bench_dir)
    result = fit_face(bench, settings, show_progress=show_progress)
    metrics = evaluate_fit(bench, result, relight=relight)
    if refine is not None and refine.iterations > 0:
        t0 = time.perf_counter()
        maps, history = refine_through_renders(bench, result.maps, refine, show_progress=show_progress)
        result.maps = maps
        result.seconds += time.perf_counter() - t0
        metrics = {"uv_fit": metrics, **evaluate_fit(bench, result, relight=relight),
                   "render_refine": {"settings": asdict(refine), "camera_loss": history}}
    metrics["fit_settings"] = asdict(settings)
    metrics["benchmark"] = str(Path(bench_dir).resolve())
    if maps_out is not None:
        save_maps(result.maps, Path(maps_out))
    if json_path is not None:
        write_json(json_path, metrics)
    return metrics


@dataclass
class FaceBenchSettings:
    scan: str = "josie"
    uv_resolutions: tuple[int, ...] = (128, 256, 512)
    main_res: int = 256
    stability_res: int = 128
    seed: int = 0


def _run_case(scan: Path, work: Path, name: str, bs: FaceBenchmarkSettings, fs: FaceFitSettings) -> dict:
    d = make_benchmark(scan, work / name, bs, show_progress=False)
    bench = load_benchmark(d)
    t0 = time.perf_counter()
    result = fit_face(bench, fs, show_progress=False)
    fit_s = time.perf_counter() - t0
    m = evaluate_fit(bench, result)
    m["fit_seconds"] = fit_s
    m["finite"] = bool(all(np.isfinite(v).all() for v in result.maps.values()))
    return m


def bench_face(s: FaceBenchSettings, out_dir: Path | None = None, show_progress: bool = True) -> dict:
    """Accuracy vs time over UV resolution, plus a stability table; returns the JSON dict."""
    scan = Path(s.scan)
    if not scan.suffix:
        scan = SCANS / f"{s.scan}.obj"
    work = Path(tempfile.mkdtemp(prefix="photoreal_face_bench_"))
    stability_cases = {
        "baseline": (FaceBenchmarkSettings(uv_res=s.stability_res, seed=s.seed), FaceFitSettings(seed=s.seed)),
        "wrong_light_init_30deg": (FaceBenchmarkSettings(uv_res=s.stability_res, seed=s.seed),
                                   FaceFitSettings(fit_lights=True, light_init_error_deg=30.0, seed=s.seed)),
        "strong_cast_shadows": (FaceBenchmarkSettings(uv_res=s.stability_res, seed=s.seed, light_spread_deg=(85.0, 70.0)),
                                FaceFitSettings(seed=s.seed)),
        "occluded_regions_one_view": (FaceBenchmarkSettings(uv_res=s.stability_res, seed=s.seed, views=((40.0, 0.0),)),
                                      FaceFitSettings(seed=s.seed)),
        "single_light": (FaceBenchmarkSettings(uv_res=s.stability_res, seed=s.seed, n_lights=1),
                         FaceFitSettings(seed=s.seed)),
    }
    try:
        sweep, main = [], None
        total = len(s.uv_resolutions) + len(stability_cases)
        with progress_bar(total=total, desc="bench face", unit="case", disable=not show_progress) as bar:
            for res in s.uv_resolutions:
                m = _run_case(scan, work, f"res{res}", FaceBenchmarkSettings(uv_res=res, seed=s.seed),
                              FaceFitSettings(seed=s.seed))
                sweep.append({"uv_res": res, "seconds": m["fit_seconds"], "relit_psnr": m["relit_psnr"],
                              "albedo_psnr": m["albedo_psnr"], "normal_err_deg": m["normal_err_deg"],
                              "relit_flip": m["relit_flip"]})
                if res == s.main_res:
                    main = m
                bar.update(1)
            stability = {}
            for name, (bs, fs) in stability_cases.items():
                m = _run_case(scan, work, name, bs, fs)
                stability[name] = {k: m[k] for k in ("albedo_psnr", "normal_err_deg", "relit_psnr", "relit_flip",
                                                     "observed_fraction", "finite", "fit_seconds")}
                bar.update(1)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    if main is None:
        raise ValueError(f"main_res {s.main_res} is not among uv_resolutions {s.uv_resolutions}")
    best = max(r["relit_psnr"] for r in sweep)
    chosen = min(r["uv_res"] for r in sweep if r["relit_psnr"] >= best - 0.5)
    base = stability["baseline"]
    for name, row in stability.items():
        row["albedo_psnr_drop_db"] = base["albedo_psnr"] - row["albedo_psnr"]
        row["relit_psnr_drop_db"] = base["relit_psnr"] - row["relit_psnr"]
    result = {
        "scan": str(scan),
        "albedo_psnr": main["albedo_psnr"],
        "albedo_ssim": main["albedo_ssim"],
        "albedo_scale": main["albedo_scale"],
        "normal_err_deg": main["normal_err_deg"],
        "roughness_mae": main["roughness_mae"],
        "specular_mae": main["specular_mae"],
        "relit_psnr": main["relit_psnr"],
        "relit_flip": main["relit_flip"],
        "relit": main["relit"],
        "fit_seconds_256": next(r["seconds"] for r in sweep if r["uv_res"] == s.main_res),
        "sweep": sweep,
        "chosen_uv_res": chosen,
        "stability": stability,
        "settings": asdict(s),
    }
    if out_dir is not None:
        result["chart"] = str(face_chart(result, Path(out_dir) / "face_speed_accuracy.png"))
    return result


def face_chart(result: dict, path: Path) -> Path:
    """Error against time and UV resolution (relit PSNR and albedo PSNR vs fit seconds)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .imageio import save_figure

    sw = result["sweep"]
    fig, ax = plt.subplots(1, 2, figsize=(9, 3.6))
    for key, label, a in (("relit_psnr", "relit PSNR (dB)", ax[0]), ("normal_err_deg", "normal error (°)", ax[1])):
        x = [r["seconds"] for r in sw]
        y = [r[key] for r in sw]
        a.plot(x, y, "o-")
        for r, xi, yi in zip(sw, x, y):
            a.annotate(f"{r['uv_res']}²", (xi, yi), textcoords="offset points", xytext=(4, 4))
        a.set_xlabel("fit time (s, 2 CPU cores)")
        a.set_ylabel(label)
        a.grid(alpha=0.3)
    ax[0].axhline(35, color="gray", ls="--", lw=0.8)
    ax[1].axhline(5, color="gray", ls="--", lw=0.8)
    fig.suptitle(f"face fitting: accuracy vs time; chosen {result['chosen_uv_res']}²")
    return save_figure(fig, path)
