"""`photoreal bench plugins`: ggx_uv and neural_btf against builtin principled, as ratios measured in the same run.

Each plugin renders the same scene in the mode a plain ``mi.render`` uses (Dr.Jit's symbolic loops and calls: one
megakernel) and in evaluated (wavefront) mode; neural_btf uses the bundled basis and a bundled fitted material, whose
held-out PSNR (``photoreal bench btf`` records it in the material's meta) is reported beside its speed.
"""

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
from foundation.assets import ARMADILLO, NEURAL, envmap
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
    "neural_btf": {"type": "neural_btf", "basis": str(NEURAL / "basis.npz"), "material": str(NEURAL / "leather.npz"),
                   "tiling": 4.0},
}
MODES = ("symbolic", "evaluated")  #: a plain mi.render's megakernel; wavefront (symbolic loops and calls off)
NEURAL_TARGET = {"max_vs_principled": 2.0, "min_heldout_psnr": 32.0}


def _network_form(desc: dict) -> str:
    """The MLP form the plugin picks for this basis (`network` = auto): constants, cooperative vectors or, for a wide
    basis, constants in symbolic mode and cooperative vectors in evaluated mode."""
    from mi_plugins.neural_basis import ConstantNet, ModeNet

    net = mi.load_dict(desc).m_rgb
    return "constants" if isinstance(net, ConstantNet) else "by mode" if isinstance(net, ModeNet) else "coop"


def _material_psnr(path: str) -> float | None:
    """The held-out slice PSNR ``bench btf`` recorded in a fitted material's meta (None if it did not)."""
    from mi_plugins.neural_basis import load_material

    return load_material(path).meta.get("heldout_psnr")


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
    """Render the same scene with ggx_uv, neural_btf and builtin principled in both modes; report ms per render.

    Each plugin's scene is loaded on its own and freed before the other is
    loaded: Mitsuba traces every *live* BSDF instance in every render, so a
    scene alive in the background would inflate the other's timings. The first
    render of each load (tracing + JIT compilation, or a kernel-cache hit) is
    timed separately as the warm-up and excluded from the medians.
    """
    from mi_plugins.bsdfs.neural_btf import evaluated_mode
    from mi_plugins.neural_basis import load_basis

    runs = [(name, mode) for name in BENCH_BSDFS for mode in MODES]
    times: dict[tuple, list[float]] = {k: [] for k in runs}
    first: dict[tuple, list[float]] = {k: [] for k in runs}
    jit: dict[tuple, list[dict]] = {k: [] for k in runs}
    means: dict[tuple, list[float]] = {k: [] for k in runs}
    total = s.rounds * len(runs) * (s.repetitions + 1)
    with progress_bar(total=total, desc="bench plugins", unit="render", disable=not show_progress) as bar:
        for r in range(s.rounds):
            for name, mode in runs if r % 2 == 0 else runs[::-1]:
                scene = mi.load_dict(plugin_bench_scene(BENCH_BSDFS[name], s))
                with evaluated_mode(mode == "evaluated"):
                    wall, mean, info = _first_render(scene, s.spp, s.seed)
                    first[name, mode].append(wall)
                    means[name, mode].append(mean)
                    jit[name, mode].append(info)
                    bar.update(1)
                    for i in range(s.repetitions):
                        t, mean = _time_render(scene, s.spp, s.seed + 1 + i)
                        times[name, mode].append(t)
                        means[name, mode].append(mean)
                        bar.update(1)
                del scene
                gc.collect()
    modes = {m: {k: 1000.0 * statistics.median(times[k, m]) for k in BENCH_BSDFS} for m in MODES}
    ms = modes["symbolic"]
    # Code generation + LLVM compilation of the first ggx_uv render (Dr.Jit kernel history); kernels
    # found in the on-disk cache (~/.drjit) cost only their code generation.
    compile_s = statistics.median(i["compile_s"] for i in jit["ggx_uv", "symbolic"])
    nb = BENCH_BSDFS["neural_btf"]
    vs = {m: modes[m]["neural_btf"] / modes[m]["principled"] for m in MODES}
    fastest = min(modes[m]["principled"] for m in MODES)
    psnr = _material_psnr(nb["material"])
    neural = {
        "ms": {m: modes[m]["neural_btf"] for m in MODES}, "vs_principled": vs,
        "vs_fastest_principled": {m: modes[m]["neural_btf"] / fastest for m in MODES},
        "basis_width": load_basis(nb["basis"]).config.width, "network": _network_form(nb),
        "material": nb["material"].rsplit("/", 1)[-1],
        "heldout_psnr": psnr, "target": NEURAL_TARGET,
        "met": bool(max(vs.values()) <= NEURAL_TARGET["max_vs_principled"]
                    and psnr is not None and psnr >= NEURAL_TARGET["min_heldout_psnr"]),
        "first_render_s": {m: statistics.median(first["neural_btf", m]) for m in MODES},
    }
    return {
        "ggx_uv_ms": ms["ggx_uv"],
        "principled_ms": ms["principled"],
        "ggx_uv_vs_principled": ms["ggx_uv"] / ms["principled"],
        "neural_btf_ms": ms["neural_btf"],
        "neural_btf_vs_principled": vs["symbolic"],
        "neural_btf_vs_principled_evaluated": vs["evaluated"],
        "neural_btf": neural,
        "modes_ms": modes,
        "compile_s": compile_s,
        "first_render_s": {k: statistics.median(first[k, "symbolic"]) for k in BENCH_BSDFS},
        "jit": {k: jit[k, "symbolic"][0] for k in BENCH_BSDFS},
        "compile_note": ("compile_s = code generation + LLVM compile time of the first ggx_uv render from "
                         "Dr.Jit's kernel history; kernels already in Dr.Jit's memory or on-disk cache "
                         "(~/.drjit) cost ~0, so a warm machine reports ~0"),
        "all_ms": {k: [1000.0 * t for t in times[k, "symbolic"]] for k in BENCH_BSDFS},
        "all_ms_evaluated": {k: [1000.0 * t for t in times[k, "evaluated"]] for k in BENCH_BSDFS},
        "mean_value": {k: statistics.fmean(means[k, "symbolic"]) for k in BENCH_BSDFS},
        "mean_value_evaluated": {k: statistics.fmean(means[k, "evaluated"]) for k in BENCH_BSDFS},
        "settings": asdict(s),
        "variant": mi.variant(),
        "machine": {"cpus": os.cpu_count(), "platform": platform.platform()},
        "scene": ("armadillo + floor, forest.exr envmap, path tracer; every surface uses the plugin (neural_btf: the "
                  "bundled basis and leather, tiled 4× on the floor; the armadillo has no UVs: one texel)"),
    }


# -- the benchmark protocol (photoreal.benchmarks) -------------------------------------------------------------------

SETTINGS = PluginBenchSettings
WORK = False
SUMMARY = ("ggx_uv_ms", "principled_ms", "ggx_uv_vs_principled", "neural_btf_ms", "neural_btf_vs_principled",
           "neural_btf_vs_principled_evaluated", "compile_s")


def run(s: PluginBenchSettings, work, pool, show_progress: bool) -> dict:
    return bench_plugins(s, show_progress)


def options(p) -> None:
    from photoreal.options import opt

    for name in ("resolution", "spp", "repetitions", "rounds"):
        opt(p, PluginBenchSettings, name)
