"""`photoreal bench face`: face fitting accuracy against time over UV resolution, and a stability table."""

from __future__ import annotations

import shutil
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from foundation import validate
from foundation.assets import FACE
from foundation.errors import UsageError
from foundation.progress import progress_bar
from foundation.records import to_json
from inverse.face import FaceBenchmarkSettings, FaceFitSettings, evaluate_fit, fit_face, load_benchmark, make_benchmark

SCANS = FACE / "cyberheads"


@dataclass
class FaceBenchSettings:
    scan: str = "josie"
    uv_resolutions: tuple[int, ...] = (128, 256, 512)
    main_res: int = 256
    stability_res: int = 128
    seed: int = 0

    def __post_init__(self):
        for r in self.uv_resolutions:
            validate.integer("uv_resolutions", r, 16, 4096)
        if self.main_res not in self.uv_resolutions:
            raise UsageError(f"main_res {self.main_res} is not among uv_resolutions {self.uv_resolutions}")
        validate.integer("stability_res", self.stability_res, 16, 4096)
        validate.seed("seed", self.seed)

    def scan_path(self) -> Path:
        """The scan: a bundled head by name (josie, paul) or an OBJ path."""
        scan = Path(self.scan)
        if not scan.suffix:
            scan = SCANS / f"{self.scan}.obj"
            if not scan.is_file():
                names = ", ".join(sorted(p.stem for p in SCANS.glob("*.obj")))
                raise UsageError(f"--scan {self.scan}: not a bundled scan ({names}) or an OBJ file")
        return scan


def _run_case(scan: Path, work: Path, name: str, bs: FaceBenchmarkSettings, fs: FaceFitSettings) -> dict:
    d = make_benchmark(scan, work / name, bs, show_progress=False)
    bench = load_benchmark(d)
    t0 = time.perf_counter()
    result = fit_face(bench, fs, show_progress=False)
    fit_s = time.perf_counter() - t0
    m = to_json(evaluate_fit(bench, result))
    m["fit_seconds"] = fit_s
    m["finite"] = bool(all(np.isfinite(v).all() for v in result.maps.values()))
    return m


def bench_face(s: FaceBenchSettings, show_progress: bool = True) -> dict:
    """Accuracy vs time over UV resolution, plus a stability table; returns the JSON dict (the benchmarks and fits
    live in a temporary folder: every case is fitted and timed afresh)."""
    scan = s.scan_path()
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
    return result


def face_chart(result: dict, path: Path) -> Path:
    """Error against time and UV resolution (relit PSNR and albedo PSNR vs fit seconds)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from foundation.imageio import save_figure

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


# -- the benchmark protocol (photoreal.benchmarks) -------------------------------------------------------------------

SETTINGS = FaceBenchSettings
WORK = False
SUMMARY = ("albedo_psnr", "normal_err_deg", "roughness_mae", "specular_mae", "relit_psnr", "relit_flip",
           "fit_seconds_256", "chosen_uv_res")


def run(s: FaceBenchSettings, work, pool, show_progress: bool) -> dict:
    return bench_face(s, show_progress)


def options(p) -> None:
    from photoreal.options import opt

    opt(p, FaceBenchSettings, "scan", help="josie, paul, or an OBJ path")


def charts(result: dict, json_path: Path, work: Path | None) -> dict:
    return {"chart": str(face_chart(result, Path(json_path).parent / "face_speed_accuracy.png"))}
