"""Refining fitted maps through full Mitsuba renders of the camera images (`face fit --refine-renders N`), a stage of the shared loop."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import mi_plugins  # noqa: F401
import drjit as dr
import mitsuba as mi
from mi_plugins.arrays import aligned

from foundation import validate
from foundation.errors import UsageError
from foundation.loop import DrJitStage, LoopSettings, RunState, StepResult, run_loop
from foundation.optim_state import load_optimizer_state, optimizer_state

from .benchmark import FaceBenchmark, benchmark_digest


@dataclass
class RenderRefineSettings:
    iterations: int = 10
    spp: int = 4
    lr: float = 0.005
    seed: int = 0

    def __post_init__(self):
        validate.integer("iterations", self.iterations, 0)
        validate.integer("spp", self.spp, 1)
        validate.positive("lr", self.lr)
        validate.seed("seed", self.seed, 1_000_000)


class RenderRefineStage(DrJitStage):
    """L2 between ``prb`` renders of the ``ggx_uv`` scan and the benchmark's camera images, into the bitmaps."""

    name = "refine through renders"
    PREFIX = "scan.bsdf.brdf_0."

    def __init__(self, bench: FaceBenchmark, maps: dict[str, np.ndarray], s: RenderRefineSettings):
        from .benchmark import camera_sensor, directional_emitters, scan_scene

        if not bench.camera:
            raise UsageError(f"{bench.path}: benchmark has no camera images (made by an older version?)")
        self.bench, self.maps, self.s = bench, maps, s
        bs, meta = bench.settings, bench.meta
        self.lights = meta.lights
        centre = np.asarray(meta.centre)
        self.scene = scan_scene(bench.mesh_path, maps, bs, directional_emitters(self.lights),
                                integrator={"type": "prb", "max_depth": 2})
        self.sensors = [mi.load_dict(camera_sensor(np.asarray(eye), centre, bs.render_res, meta.camera_fov))
                        for eye in meta.views]
        self.params = mi.traverse(self.scene)
        self.keys = {n: self.PREFIX + f"{n}.data" for n in ("albedo", "roughness", "normal")}
        self.irr = {k: mi.Color3f(self.params[f"light{k}.irradiance.value"]) for k in range(len(self.lights))}
        self.targets = {key: mi.TensorXf(aligned(img)) for key, img in bench.camera.items()}
        self.opt = mi.ad.Adam(lr=s.lr)
        for key in self.keys.values():
            self.opt[key] = self.params[key]
        self.params.update(self.opt)

    def fingerprint(self) -> dict:
        import hashlib

        h = hashlib.sha256()
        for k in sorted(self.maps):
            h.update(k.encode())
            h.update(np.ascontiguousarray(self.maps[k], np.float32).tobytes())
        return {"settings": self.s, "benchmark": benchmark_digest(self.bench), "start_maps": h.hexdigest()[:16]}

    def state(self) -> dict:
        return {"optimizer": optimizer_state(self.opt)}

    def load_state(self, tree: dict) -> None:
        load_optimizer_state(self.opt, tree["optimizer"], "refine optimizer")
        self.params.update(self.opt)

    def step(self, it: int) -> StepResult:
        s, params = self.s, self.params
        n_img = len(self.lights) * len(self.sensors)
        total = 0.0
        for k in range(len(self.lights)):
            for j in range(len(self.lights)):  # one light at a time, as in the benchmark images
                params[f"light{j}.irradiance.value"] = self.irr[j] if j == k else mi.Color3f(0.0)
            params.update(self.opt)
            for v, sensor in enumerate(self.sensors):
                img = mi.render(self.scene, params, sensor=sensor, spp=s.spp, seed=s.seed + it * 1000 + k * 10 + v)
                loss = dr.mean(dr.square(img[..., :3] - self.targets[f"v{v}_l{k}"]), axis=None) / n_img
                dr.backward(loss)
                total += float(loss.array[0])
        return StepResult(total, self.grads_finite())

    def apply(self, it: int) -> None:
        opt, keys = self.opt, self.keys
        opt.step()
        opt[keys["albedo"]] = dr.clip(opt[keys["albedo"]], 0.0, 1.0)
        opt[keys["roughness"]] = dr.clip(opt[keys["roughness"]], 0.05, 1.0)
        opt[keys["normal"]] = dr.clip(opt[keys["normal"]], 0.0, 1.0)
        self.params.update(opt)

    def finish(self, run: RunState) -> tuple[dict[str, np.ndarray], list[float]]:
        out = dict(self.maps)
        out["albedo"] = np.array(self.opt[self.keys["albedo"]])
        out["roughness"] = np.array(self.opt[self.keys["roughness"]])
        n = np.array(self.opt[self.keys["normal"]]) * 2.0 - 1.0
        out["normal"] = (n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-8)).astype(np.float32)
        return out, list(run.losses)

    def close(self) -> None:
        self.scene = self.params = self.opt = None


def refine_through_renders(bench: FaceBenchmark, maps: dict[str, np.ndarray], s: RenderRefineSettings | None = None,
                           show_progress: bool = True,
                           checkpoint: str | Path | None = None) -> tuple[dict[str, np.ndarray], list[float]]:
    """Refine albedo, roughness and normal maps by differentiating *camera renders* (``prb``).

    The scan is rendered with the ``ggx_uv`` plugin from the benchmark's views
    under each training light and compared (L2) with the benchmark's camera
    images; gradients flow through Mitsuba into the plugin's bitmap textures.
    This exercises the plugin's derivatives the way an image-space pipeline
    would use them; the UV-space fit is the fast path. Returns the refined
    maps and the per-iteration camera-space loss.
    """
    s = s or RenderRefineSettings()
    stage = RenderRefineStage(bench, maps, s)
    try:
        return run_loop(stage, LoopSettings(steps=s.iterations, checkpoint_every=5), checkpoint=checkpoint,
                        show_progress=show_progress)
    finally:
        stage.close()
