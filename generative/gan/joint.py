"""Joint geometry + GAN training (REAL-DIBS §6, "simultaneous training").

One loss L = L1(m_j, i_j) (eq. 4.3) + L_G(G(r_j ‖ m_j), i_j) (pix2pix: GAN + λ·L1), with
m_j = R(V, C; c_j) rendered by Mitsuba with AD. The generator is called from Dr.Jit through
:func:`foundation.bridge.drjit_images_to_torch` (``dr.wrap``), so one ``dr.backward`` reaches both
the vertex parameters (large steps, as :mod:`inverse.morph`) and G's weights. D is updated in torch
on the detached G output. A stage of the shared loop: budgets, checkpoints, exact resume, NaN policy.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

import mi_plugins  # noqa: F401
import drjit as dr
import mitsuba as mi
from mi_plugins.arrays import aligned

from foundation.bridge import drjit_images_to_torch, module_device
from foundation.errors import UsageError
from foundation.files import file_digest
from foundation.loop import (LoopSettings, RunState, Stage, StepResult, TrainingSummary, all_finite, rng_state,
                             run_loop, set_rng_state)
from foundation.mesh import read_ply_colours, write_ply
from foundation.metrics import ImageMetrics
from foundation.optim_state import load_optimizer_state, optimizer_state
from foundation.scene import mitsuba_log_level
from foundation.threads import torch_threads
from inverse.morph import MorphBenchmark, morph_scene, remesh, sensor_dict

from .data import GanDataSettings, PairedViews, render_mesh_views
from .train import (GanEvaluation, _optimisers, build_model, check_resolution, initial_state,
                    mean_metrics, predict, save_heldout_predictions, split_validation)
from .settings import JointSettings


@dataclass
class JointCurvePoint:
    step: int
    seconds: float
    train_loss: float


@dataclass
class JointResult:
    """``metrics.json`` of a joint run: G on the jointly optimised mesh, and that mesh's renders alone."""

    heldout: GanEvaluation
    mesh_only: ImageMetrics  #: the joint mesh rendered like the paired data (no G)
    settings: JointSettings
    curve: list[JointCurvePoint]
    training: TrainingSummary


class JointStage(Stage):
    unit = "step"

    def __init__(self, bench: MorphBenchmark, data: PairedViews, out: Path, s: JointSettings):
        self.bench, self.data, self.out, self.s = bench, data, out, s
        self.name = f"joint {data.case}"
        check_resolution(data.resolution, s.gan)
        meta = bench.meta
        self.res, self.size, self.fov = meta.resolution, meta.scene_size, meta.fov
        torch.manual_seed(s.seed)
        self.rng = np.random.default_rng(s.seed)
        if s.init_mesh:
            if not Path(s.init_mesh).is_file():
                raise UsageError(f"{s.init_mesh}: no such mesh (init_mesh)")
            v0, f0, c0 = read_ply_colours(Path(s.init_mesh))
        else:
            v0, f0, c0 = remesh(*read_ply_colours(bench.coarse))
        self.v0, self.f0 = v0, f0
        self.digests = {"coarse": file_digest(bench.coarse), "data": data.digest(),
                        "init_mesh": file_digest(s.init_mesh) if s.init_mesh else None}
        self.model = build_model(s.gan)
        self.opt_g, self.opt_d = _optimisers(self.model, s.gan)
        if s.init_from:
            self.model.load_state_dict(initial_state(s.init_from, "morph_gan"))
        self.model.train()
        self.work_ply = out / ".joint_work.ply"
        write_ply(self.work_ply, v0, f0, c0)
        integrator = ({"type": "direct_projective", "sppi": 0} if s.max_depth == 2
                      else {"type": "prb_projective", "max_depth": s.max_depth, "sppi": 0})
        self.scene = morph_scene(self.work_ply, "lit", meta.hdri, integrator=integrator)
        self.params = mi.traverse(self.scene)
        f_mi = mi.UInt32(aligned(f0, np.uint32).ravel())
        self.ls = mi.ad.LargeSteps(mi.Float(aligned(v0).ravel()), f_mi, s.lambda_)
        self.opt = mi.ad.Adam(lr=s.lr * self.size / 10.0, uniform=True)
        self.opt["u"] = self.ls.to_differential(mi.Float(aligned(v0).ravel()))
        self.opt["c"] = mi.Float(aligned(c0).ravel())
        self.opt.set_learning_rate({"c": s.lr_colour})
        self.photos = {i: mi.TensorXf(aligned(data.photos[i], None)) for i in data.train}
        self.coarse = {i: mi.TensorXf(aligned(data.rendered[i], None)) for i in data.train}
        self.stash: dict = {}
        self.gen = drjit_images_to_torch(self._generator_terms, device=module_device(self.model.G, "cpu"))
        self.train, _ = split_validation(data.train, s.gan.val_every)  # the views two-stage G trains on
        self.curve: list[JointCurvePoint] = []

    def _generator_terms(self, r: torch.Tensor, m: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        x = self.model.make_input(r, m)
        fake = self.model.G(x)
        self.stash["x"], self.stash["fake"], self.stash["y"] = x.detach(), fake.detach(), y
        loss, terms = self.model.generator_loss(x, y, fake)
        self.stash["terms"] = terms
        return loss

    def mesh_state(self) -> tuple[np.ndarray, np.ndarray]:
        vv = np.array(dr.detach(self.ls.from_differential(self.opt["u"])), np.float64).reshape(-1, 3)
        return vv, np.array(self.opt["c"], np.float32).reshape(-1, 3)

    def fingerprint(self) -> dict:
        return {"settings": self.s, "inputs": self.digests}

    def state(self) -> dict:
        return {"model": self.model.state_dict(), "opt_g": optimizer_state(self.opt_g),
                "opt_d": optimizer_state(self.opt_d), "mesh_opt": optimizer_state(self.opt),
                "rng": rng_state(self.rng), "torch_rng": torch.get_rng_state(),
                "curve": [vars(c) for c in self.curve]}

    def load_state(self, tree: dict) -> None:
        self.model.load_state_dict(tree["model"])
        load_optimizer_state(self.opt_g, tree["opt_g"], "generator optimizer")
        load_optimizer_state(self.opt_d, tree["opt_d"], "discriminator optimizer")
        load_optimizer_state(self.opt, tree["mesh_opt"], "mesh optimizer")
        set_rng_state(self.rng, tree["rng"])
        torch.set_rng_state(tree["torch_rng"])
        self.curve = [JointCurvePoint(**c) for c in tree["curve"]]

    def step(self, it: int) -> StepResult:
        s = self.s
        i = int(self.rng.choice(self.train))
        self.params["mesh.vertex_positions"] = dr.ravel(self.ls.from_differential(self.opt["u"]))
        self.params["mesh.vertex_color"] = self.opt["c"]
        with mitsuba_log_level(mi.LogLevel.Error):  # non-manifold vertices of remeshed inputs: expected
            self.params.update()
        sensor = mi.load_dict(sensor_dict(self.bench.meta.cameras[i], self.res, self.fov, sample_border=True))
        with mitsuba_log_level(mi.LogLevel.Error):  # the projective integrator's non-manifold mesh dumps
            img = mi.render(self.scene, self.params, sensor=sensor, spp=s.spp, seed=int(s.seed * 7919 + it * 101 + i))
        m = img[..., :3]
        l_morph = dr.mean(dr.abs(m - self.photos[i]), axis=None)  # eq. 4.3
        self.opt_g.zero_grad(set_to_none=True)
        total = s.morph_weight * l_morph + self.gen(self.coarse[i], m, self.photos[i])
        dr.backward(total)
        value = float(total.array[0])
        ok = all_finite(*(dr.grad(self.opt[k]) for k in self.opt.keys()),
                        *(p.grad for g in self.opt_g.param_groups for p in g["params"]))
        return StepResult(value, ok, log={"total": value, "morph_l1": float(l_morph.array[0]), **self.stash["terms"]})

    def _update_d(self) -> None:
        self.opt_d.zero_grad(set_to_none=True)
        ld, _ = self.model.discriminator_loss(self.stash["x"], self.stash["y"], self.stash["fake"])
        ld.backward()
        if all_finite(float(ld.detach()), *(p.grad for g in self.opt_d.param_groups for p in g["params"])):
            self.opt_d.step()

    def apply(self, it: int) -> None:
        self.opt.step()
        self.opt["c"] = dr.clip(self.opt["c"], 0.0, 1.0)
        self.opt_g.step()
        self._update_d()

    def discard(self, it: int) -> None:
        for k in self.opt.keys():
            dr.set_grad(self.opt[k], 0)
        self.opt_g.zero_grad(set_to_none=True)
        self._update_d()  # D's own loss is computed on detached images and is guarded on its own

    def after_step(self, it: int, run: RunState) -> None:
        if run.step % self.s.eval_every == 0 or run.done:
            self.curve.append(JointCurvePoint(run.step, run.train_seconds, run.losses[-1]))

    def finish(self, run: RunState) -> JointResult:
        s, data = self.s, self.data
        vv, cc = self.mesh_state()
        write_ply(self.out / "joint.ply", vv, self.f0, np.clip(cc, 0, 1))
        self.close()
        # At test time G gets m_j from the light transport it was trained on (path, the same max depth), at 32 spp.
        # The mesh-only row uses the paired data's renderer (max depth 3), comparable with the "morphed" row.
        mesh_render = render_mesh_views(self.out / "joint.ply", self.bench, data.test, GanDataSettings(),
                                        "render joint", False)
        m_direct = mesh_render if s.max_depth == GanDataSettings().max_depth else render_mesh_views(
            self.out / "joint.ply", self.bench, data.test, GanDataSettings(max_depth=s.max_depth), "render joint", False)
        pred, ms = predict(self.model, data.rendered[data.test], m_direct)
        save_heldout_predictions(self.out, self.model, data, morphed=m_direct)
        heldout = GanEvaluation(**vars(mean_metrics(pred, data.photos[data.test])), infer_ms_per_image=ms)
        return JointResult(heldout, mean_metrics(mesh_render, data.photos[data.test]), s, list(self.curve),
                           run.summary())

    def close(self) -> None:
        self.scene = self.params = None
        self.work_ply.unlink(missing_ok=True)


def train_joint(bench: MorphBenchmark, data: PairedViews, out: str | Path, s: JointSettings | None = None,
                show_progress: bool = True, budget_steps: int | None = None) -> JointResult | None:
    """Jointly optimise the coarse mesh (V, C) and a Morph-GAN G through one loss (see the module docstring).

    Starts from the benchmark's coarse mesh (isotropically remeshed, as ``run_morph``)
    and a fresh G, or — fine-tuning — from ``init_mesh`` and the G and D of ``init_from``;
    writes ``joint.ply``, ``checkpoint.npz``, ``heldout_pred.npz`` and ``metrics.json``.
    """
    s = s or JointSettings()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    with torch_threads(s.gan.threads):
        stage = JointStage(bench, data, out, s)
        try:
            loop = LoopSettings(steps=s.steps, max_seconds=s.max_seconds, checkpoint_every=s.checkpoint_every)
            return run_loop(stage, loop, checkpoint=out / "checkpoint.npz", budget_steps=budget_steps,
                            show_progress=show_progress, metrics_path=out / "metrics.json")
        finally:
            stage.close()
