"""`photoreal bench plugins`: ggx_uv against builtin principled, as a ratio measured in the same run."""

from __future__ import annotations

import gc
import os
import platform
import statistics
import time
from dataclasses import asdict, dataclass

import mi_plugins  # noqa: F401
import drjit as dr
import mitsuba as mi

from foundation import validate
from foundation.assets import ARMADILLO, envmap
from foundation.progress import progress_bar


@dataclass
class PluginBenchSettings:
    resolution: int = 256
    spp: int = 64
    repetitions: int = 5  #: timed renders per plugin per round
    rounds: int = 2  #: rounds alternate which plugin goes first
    max_depth: int = 6
    seed: int = 0

    def __post_init__(self):
        validate.integer("resolution", self.resolution, 8, 4096)
        validate.integer("spp", self.spp, 1)
        validate.integer("repetitions", self.repetitions, 1)
        validate.integer("rounds", self.rounds, 1)
        validate.integer("max_depth", self.max_depth, 1)
        validate.seed("seed", self.seed)


def plugin_bench_scene(bsdf: dict, s: PluginBenchSettings) -> dict:
    """Armadillo on a floor under a real HDRI; every surface uses ``bsdf``."""
    return {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": s.max_depth},
        "sensor": {
            "type": "perspective", "fov": 38,
            "to_world": mi.ScalarTransform4f().look_at(origin=[0.6, 1.3, 3.4], target=[0, 0.35, 0], up=[0, 1, 0]),
            "film": {"type": "hdrfilm", "width": s.resolution, "height": s.resolution},
            "sampler": {"type": "independent", "sample_count": s.spp},
        },
        "env": envmap("forest"),
        "armadillo": {
            "type": "ply", "filename": str(ARMADILLO), "bsdf": bsdf,
            "to_world": mi.ScalarTransform4f().scale(0.01).translate([0, 54.2, 0]).rotate([0, 1, 0], 180),
        },
        "floor": {"type": "rectangle", "bsdf": bsdf,
                  "to_world": mi.ScalarTransform4f().scale(5).rotate([1, 0, 0], -90)},
    }


# Matching parameters: base colour, roughness (α = r² in both), specular level.
BENCH_BSDFS = {
    "ggx_uv": {"type": "ggx_uv", "albedo": {"type": "rgb", "value": [0.55, 0.45, 0.3]},
               "roughness": 0.3, "specular": 0.5},
    "principled": {"type": "principled", "base_color": {"type": "rgb", "value": [0.55, 0.45, 0.3]},
                   "roughness": 0.3, "specular": 0.5},
}


def _time_render(scene: mi.Scene, spp: int, seed: int) -> tuple[float, float]:
    """Wall time of one render and its mean pixel value (a check that the timed render is the scene)."""
    t0 = time.perf_counter()
    img = mi.render(scene, spp=spp, seed=seed)
    dr.eval(img)
    dr.sync_thread()
    return time.perf_counter() - t0, float(dr.mean(img, axis=None).array[0])


def _first_render(scene: mi.Scene, spp: int, seed: int) -> tuple[float, float, dict]:
    """Wall time and mean value of the first render, and Dr.Jit's kernel history for it (compile vs cache)."""
    dr.kernel_history_clear()
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        wall, mean = _time_render(scene, spp, seed)
        hist = dr.kernel_history()
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    ms = sum(h.get("codegen_time", 0.0) + h.get("backend_time", 0.0) for h in hist)
    return wall, mean, {"compile_s": ms / 1000.0, "kernels": len(hist),
                        "from_disk_cache": int(sum(1 for h in hist if h.get("cache_disk")))}


def bench_plugins(s: PluginBenchSettings, show_progress: bool = True) -> dict:
    """Render the same scene with ggx_uv and builtin principled; report ms per render.

    Each plugin's scene is loaded on its own and freed before the other is
    loaded: Mitsuba traces every *live* BSDF instance in every render, so a
    scene alive in the background would inflate the other's timings. The first
    render of each load (tracing + JIT compilation, or a kernel-cache hit) is
    timed separately as the warm-up and excluded from the medians.
    """
    times: dict[str, list[float]] = {k: [] for k in BENCH_BSDFS}
    first: dict[str, list[float]] = {k: [] for k in BENCH_BSDFS}
    jit: dict[str, list[dict]] = {k: [] for k in BENCH_BSDFS}
    means: dict[str, list[float]] = {k: [] for k in BENCH_BSDFS}
    order = list(BENCH_BSDFS)
    total = s.rounds * len(order) * (s.repetitions + 1)
    with progress_bar(total=total, desc="bench plugins", unit="render", disable=not show_progress) as bar:
        for r in range(s.rounds):
            for name in order if r % 2 == 0 else order[::-1]:
                scene = mi.load_dict(plugin_bench_scene(BENCH_BSDFS[name], s))
                wall, mean, info = _first_render(scene, s.spp, s.seed)
                first[name].append(wall)
                means[name].append(mean)
                jit[name].append(info)
                bar.update(1)
                for i in range(s.repetitions):
                    t, mean = _time_render(scene, s.spp, s.seed + 1 + i)
                    times[name].append(t)
                    means[name].append(mean)
                    bar.update(1)
                del scene
                gc.collect()
    ms = {k: 1000.0 * statistics.median(v) for k, v in times.items()}
    # Code generation + LLVM compilation of the first ggx_uv render (Dr.Jit kernel history); kernels
    # found in the on-disk cache (~/.drjit) cost only their code generation.
    compile_s = statistics.median(i["compile_s"] for i in jit["ggx_uv"])
    return {
        "ggx_uv_ms": ms["ggx_uv"],
        "principled_ms": ms["principled"],
        "ggx_uv_vs_principled": ms["ggx_uv"] / ms["principled"],
        "compile_s": compile_s,
        "first_render_s": {k: statistics.median(v) for k, v in first.items()},
        "jit": {k: v[0] for k, v in jit.items()},
        "compile_note": ("compile_s = code generation + LLVM compile time of the first ggx_uv render from "
                         "Dr.Jit's kernel history; kernels already in Dr.Jit's memory or on-disk cache "
                         "(~/.drjit) cost ~0, so a warm machine reports ~0"),
        "all_ms": {k: [1000.0 * t for t in v] for k, v in times.items()},
        "mean_value": {k: statistics.fmean(v) for k, v in means.items()},
        "settings": asdict(s),
        "variant": mi.variant(),
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform()},
        "scene": "armadillo + floor, forest.exr envmap, path tracer; every surface uses the plugin",
    }


# -- the benchmark protocol (photoreal.benchmarks) -------------------------------------------------------------------

SETTINGS = PluginBenchSettings
WORK = False
SUMMARY = ("ggx_uv_ms", "principled_ms", "ggx_uv_vs_principled", "compile_s")


def run(s: PluginBenchSettings, work, pool, show_progress: bool) -> dict:
    return bench_plugins(s, show_progress)


def options(p) -> None:
    from photoreal.options import opt

    for name in ("resolution", "spp", "repetitions", "rounds"):
        opt(p, PluginBenchSettings, name)
