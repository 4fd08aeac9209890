"""`photoreal face fit` by paths: one benchmark folder fitted, scored and written (the unit a batch of benchmarks fans out to workers)."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import mi_plugins  # noqa: F401

from foundation.loop import TrainingSummary

from .refine import RenderRefineSettings, refine_through_renders
from .fit import FaceFitMetrics, FaceFitSettings, evaluate_fit, fit_face, save_maps


@dataclass
class FaceFitReport:
    """``photoreal face fit``'s JSON: the final maps' metrics, and the UV-space fit's when refined after it."""

    metrics: FaceFitMetrics
    fit_settings: FaceFitSettings
    benchmark: str
    training: TrainingSummary
    uv_fit: FaceFitMetrics | None = None  #: before the refinement through renders
    render_refine: RenderRefineSettings | None = None
    camera_loss: list[float] = field(default_factory=list)  #: per refinement step


def fit_benchmark_dir(bench_dir: str | Path, json_path: str | Path | None, maps_out: str | Path | None,
                      settings: FaceFitSettings, relight: bool = True, show_progress: bool = True,
                      refine: RenderRefineSettings | None = None) -> FaceFitReport:
    """`photoreal face fit`: fit, evaluate against the ground truth, write maps and metrics.

    With ``refine``, the UV-space fit is followed by refinement through full camera renders
    (``prb`` through the ggx_uv plugin); both stages are scored. Output locations are checked
    before the fit; both stages checkpoint beside the JSON (or the maps) and resume.
    """
    from foundation.files import check_output_dir, check_output_file, write_json
    from foundation.records import to_json

    from .benchmark import load_benchmark

    if json_path is not None:
        check_output_file(json_path, "--json")
    if maps_out is not None:
        check_output_dir(maps_out, "maps.exr", "--maps")
    bench = load_benchmark(bench_dir)
    base = Path(json_path) if json_path is not None else (Path(maps_out) / "fit" if maps_out is not None else None)
    ckpt = base.with_name(base.stem + ".ckpt.npz") if base is not None else None
    result = fit_face(bench, settings, show_progress=show_progress, checkpoint=ckpt)
    metrics = evaluate_fit(bench, result, relight=relight)
    report = FaceFitReport(metrics, settings, str(Path(bench_dir)), result.training)
    if refine is not None and refine.iterations > 0:
        t0 = time.perf_counter()
        rckpt = base.with_name(base.stem + ".refine.ckpt.npz") if base is not None else None
        maps, history = refine_through_renders(bench, result.maps, refine, show_progress=show_progress,
                                               checkpoint=rckpt)
        result.maps = maps
        result.seconds += time.perf_counter() - t0
        report = FaceFitReport(evaluate_fit(bench, result, relight=relight), settings, str(Path(bench_dir)),
                               result.training, uv_fit=metrics, render_refine=refine, camera_loss=history)
    if maps_out is not None:
        save_maps(result.maps, Path(maps_out))
    if json_path is not None:
        write_json(json_path, to_json(report))
    return report


def fit_benchmark_item(bench_dir: str, json_path: str, maps_out: str | None, settings: FaceFitSettings,
                       refine: RenderRefineSettings | None = None) -> dict:
    """:func:`fit_benchmark_dir` by paths, quietly (the unit that fitting a folder of benchmarks fans out)."""
    r = fit_benchmark_dir(bench_dir, json_path, maps_out, settings, show_progress=False, refine=refine)
    m = r.metrics
    return {"benchmark": str(bench_dir), "albedo_psnr": m.albedo_psnr, "normal_err_deg": m.normal_err_deg,
            "relit_psnr": m.relit_psnr, "seconds": m.seconds}
