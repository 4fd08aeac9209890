"""`photoreal bench scale`: one batch of real items, serially, on a local process pool and on Ray.

Items: ``items`` renders of the built-in scenes (each a :func:`foundation.scene.render_item`: load the XML, render,
write EXR + PNG). Every configuration renders the same items into its own folder; ``identical`` says whether all
outputs are bit-identical to the serial run's (one Dr.Jit thread per item everywhere). Times are wall-clock times of
the whole batch as a user sees them, start-up included:

* ``serial_s`` — one after another in this process, one thread each (the pool workers' setting);
* ``serial_all_threads_s`` — one after another with all cores to Dr.Jit (what a user without a pool gets);
* ``pool_s`` — a spawn pool of 1 and 2 worker processes (start, import, JIT kernels from the shared disk cache);
* ``ray_s`` — a local Ray instance with 2 CPUs (``ray_start_s``: starting it, not in ``ray_s``);
* ``ray_overhead_per_item_s`` — (Ray batch − the same items on the 2-worker pool) / items.

The chart plots throughput (items/s) against workers beside the ideal line (serial throughput × workers).
A material item (render one BTF at the default settings, fit it at the default settings) is timed once, alone, for
the projection of a seed-002-sized dataset in docs/results/scale.md.
"""

from __future__ import annotations

import shutil
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from foundation import validate
from foundation.assets import SCENES
from foundation.pool import Item, PoolSettings, default_workers, ray_shutdown, run_items
from foundation.scene import RenderSettings

SCALE_SCENES = ("material_test", "josie", "armadillo", "neural_materials")


@dataclass
class ScaleBenchSettings:
    items: int = 16  #: renders in the batch (the built-in scenes in turn, each with its own seed)
    resolution: int = 128
    spp: int = 64
    ray: bool = True  #: include the Ray configuration
    material_item: bool = True  #: time one BTF render + fit at the default settings
    seed: int = 0

    def __post_init__(self):
        validate.integer("items", self.items, 2, 10_000)
        validate.integer("resolution", self.resolution, 8, 4096)
        validate.integer("spp", self.spp, 1)
        validate.seed("seed", self.seed)


def _items(s: ScaleBenchSettings, out: Path) -> list[Item]:
    items = []
    for k in range(s.items):
        name = SCALE_SCENES[k % len(SCALE_SCENES)]
        exr = out / f"{k:03d}_{name}.exr"
        rs = RenderSettings(spp=s.spp, resolution=(s.resolution, s.resolution), seed=s.seed + k)
        items.append(Item(f"{k:03d}_{name}", "foundation.scene:render_item", (str(SCENES / f"{name}.xml"), str(exr), rs),
                          output=str(exr)))
    return items


def _same_outputs(a: Path, b: Path, keys: list[str]) -> bool:
    from foundation.imageio import read_exr

    for k in keys:
        x, y = read_exr(a / f"{k}.exr"), read_exr(b / f"{k}.exr")
        if sorted(x) != sorted(y) or any(not np.array_equal(x[c], y[c]) for c in x):
            return False
    return True


def _material_item_seconds(work: Path) -> dict:
    """One dataset material at the default settings: render its BTF, fit it to the bundled basis (one thread)."""
    from foundation.assets import ASSETS
    from foundation.threads import drjit_threads
    from inverse.btf import BTFRenderSettings, fit_file, render_material

    with drjit_threads(1):
        t0 = time.perf_counter()
        render_material(str(work / "fabric_000.npz"), "fabric", 12345, BTFRenderSettings())
        t1 = time.perf_counter()
        fit_file(str(work / "fabric_000.npz"), str(ASSETS / "neural" / "basis.npz"), str(work / "fabric_fit.npz"))
        t2 = time.perf_counter()
    return {"render_s": t1 - t0, "fit_s": t2 - t1, "settings": asdict(BTFRenderSettings())}


def bench_scale(s: ScaleBenchSettings, work: Path, show_progress: bool = True) -> dict:
    """Every configuration renders the same items afresh in ``work`` (cleared before each and at the end)."""
    work = Path(work)
    shutil.rmtree(work, ignore_errors=True)
    cores = default_workers()
    keys = [it.key for it in _items(s, work)]
    configs = {"serial": PoolSettings(workers=0, threads=1),
               "serial_all_threads": PoolSettings(workers=0, threads=cores),
               "pool_1": PoolSettings(workers=1, threads=1), "pool_2": PoolSettings(workers=2, threads=1)}
    if s.ray:
        configs["ray_2"] = PoolSettings(workers=2, ray="local", threads=1)
    seconds, per_item, ray_start = {}, {}, None
    try:
        for name, ps in configs.items():
            if name == "ray_2":
                import ray

                t0 = time.perf_counter()
                ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
                ray_start = time.perf_counter() - t0
                ps = PoolSettings(workers=2, ray="auto", threads=1)
            report = run_items(_items(s, work / name), ps, desc=f"scale {name}", show_progress=show_progress)
            report.raise_if_failed()
            seconds[name] = report.seconds
            per_item[name] = float(np.mean([r.seconds for r in report.results]))
    finally:
        if s.ray:
            import ray

            if ray.is_initialized():
                ray.shutdown()
        ray_shutdown()
    identical = all(_same_outputs(work / "serial", work / name, keys) for name in configs if name != "serial_all_threads")
    n = s.items
    result = {
        "items": n, "item": f"render {s.resolution}² at {s.spp} spp of the built-in scenes ({', '.join(SCALE_SCENES)})",
        "cores": cores,
        "serial_s": seconds["serial"], "serial_all_threads_s": seconds["serial_all_threads"],
        "pool_s": {"1": seconds["pool_1"], "2": seconds["pool_2"]},
        "speedup_pool_2": seconds["serial"] / seconds["pool_2"],
        "speedup_pool_2_vs_all_threads": seconds["serial_all_threads"] / seconds["pool_2"],
        "item_seconds_mean": per_item,
        "identical": identical,
        "identical_note": "serial, pool and Ray outputs compared bit for bit (one Dr.Jit thread per item); "
                          "serial_all_threads is not compared (several threads sum in another order)",
        "settings": asdict(s),
    }
    if s.ray:
        result["ray_s"] = {"2": seconds["ray_2"]}
        result["ray_start_s"] = ray_start
        result["ray_overhead_per_item_s"] = (seconds["ray_2"] - seconds["pool_2"]) / n
    if s.material_item:
        result["material_item"] = _material_item_seconds(work)
    shutil.rmtree(work, ignore_errors=True)
    return result


def scale_chart(result: dict, path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from foundation.imageio import save_figure

    n = result["items"]
    base = n / result["serial_s"]
    fig, ax = plt.subplots(figsize=(5.6, 3.8))
    w = [1, 2]
    ax.plot([0, 1, 2], [0, base, 2 * base], "k--", lw=1, label="ideal (serial × workers)")
    ax.plot(w, [n / result["pool_s"]["1"], n / result["pool_s"]["2"]], "o-", label="local process pool (spawn)")
    if "ray_s" in result:
        ax.plot([2], [n / result["ray_s"]["2"]], "s", ms=9, label="Ray (local, 2 CPUs)")
    ax.axhline(n / result["serial_all_threads_s"], color="gray", ls=":", label="serial, all threads to Dr.Jit")
    ax.set_xlabel("workers")
    ax.set_ylabel("items / s")
    ax.set_xticks([0, 1, 2])
    ax.set_title(f"throughput: {n} renders on {result['cores']} cores (speed-up {result['speedup_pool_2']:.2f}×)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return save_figure(fig, path)


# -- the benchmark protocol (photoreal.benchmarks) -------------------------------------------------------------------

SETTINGS = ScaleBenchSettings
SUMMARY = ("items", "serial_s", "pool_s", "ray_s", "speedup_pool_2", "ray_overhead_per_item_s", "identical")


def run(s: ScaleBenchSettings, work: Path, pool, show_progress: bool) -> dict:
    return bench_scale(s, work, show_progress)


def charts(result: dict, json_path: Path, work: Path | None) -> dict:
    return {"chart": str(scale_chart(result, Path(json_path).parent / "scale_throughput.png"))}


def options(p) -> None:
    from photoreal.options import opt

    for name in ("items", "resolution", "spp"):
        opt(p, ScaleBenchSettings, name)
    opt(p, ScaleBenchSettings, "ray", "--no-ray", help="leave out the Ray configuration")
    opt(p, ScaleBenchSettings, "material_item", "--no-material", help="leave out timing one BTF material")
