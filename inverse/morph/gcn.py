"""Shape-aware morphing: a graph convolutional network over the mesh (REAL-DIBS §4.4).

Notation (thesis §4.4):

==========  ==========  ==========================================================
code        thesis      meaning
==========  ==========  ==========================================================
``A``       A           mesh adjacency with self-loops (N×N, sparse)
``W_e``     W (eq 4.5)  learnable per-edge weights; Â = softplus(W_e) ⊙ A, row-normalised
``H``       H^(l)       vertex features of layer l; H^(l+1) = σ(Â H^(l) Θ^(l))
``x``       X           input features: normalised rest position and vertex colour
==========  ==========  ==========================================================

The network outputs per-vertex offsets (positions, scaled by ``offset_scale``)
and colour deltas. *Identity pre-training* first teaches it to output zero
(so the untrained GCN reproduces the input mesh); it is then trained through
the Mitsuba renderer: the render loss is a Dr.Jit function exposed to torch by
:func:`foundation.bridge.torch_to_drjit_loss` (``dr.wrap``). The loss is image-only, as in the
thesis (which found that this variant spikes); positions are v0 + tanh(GCN)·offset_scale·size, so
offsets are bounded but not smooth by construction.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch
from torch import nn

import mi_plugins  # noqa: F401
import drjit as dr
import mitsuba as mi

from foundation import validate
from foundation.bridge import torch_to_drjit_loss
from foundation.files import file_digest
from foundation.loop import LoopSettings, RunState, StepResult, TorchStage, rng_state, run_loop, set_rng_state
from foundation.mesh import read_ply_colours, write_ply
from foundation.optim_state import load_optimizer_state, optimizer_state
from foundation.scene import mitsuba_log_level

from .benchmark import MorphBenchmark
from .evaluate import evaluate_morph
from .results import MorphResult
from .settings import MorphSettings
from .stage import photos_digest
from .scene import morph_scene, photo_l1, photo_saturation, photo_tensors, render_views


def adjacency(n: int, faces: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    """Edge list (with self-loops) as (2, E) indices for a sparse Â."""
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    e = np.concatenate([e, e[:, ::-1], np.stack([np.arange(n)] * 2, 1)])
    e = np.unique(e, axis=0)
    return torch.as_tensor(e.T.copy(), dtype=torch.long), torch.as_tensor(n)


class EdgeWeightedGraphConv(nn.Module):
    """One layer H' = Â H Θ with Â = row-normalised softplus(W_e) on the mesh edges (eq. 4.5)."""

    def __init__(self, edges: torch.Tensor, n: int, c_in: int, c_out: int):
        super().__init__()
        self.register_buffer("edges", edges)
        self.n = int(n)
        self.edge_weight = nn.Parameter(torch.zeros(edges.shape[1]))  # softplus(0) = log 2 for every edge
        self.lin = nn.Linear(c_in, c_out)

    def forward(self, h: torch.Tensor) -> torch.Tensor:
        """h: (N, c_in) -> (N, c_out)."""
        w = nn.functional.softplus(self.edge_weight)
        row, col = self.edges
        deg = torch.zeros(self.n, dtype=h.dtype).index_add_(0, row, w)
        norm = w / deg[row].clamp_min(1e-12)
        msg = self.lin(h)[col] * norm[:, None]
        return torch.zeros(self.n, msg.shape[1], dtype=h.dtype).index_add_(0, row, msg)


class MeshGCN(nn.Module):
    """Per-vertex offsets and colour deltas from a stack of edge-weighted graph convolutions."""

    def __init__(self, edges: torch.Tensor, n: int, hidden: int = 64, layers: int = 4):
        super().__init__()
        dims = [6] + [hidden] * (layers - 1)
        self.convs = nn.ModuleList(EdgeWeightedGraphConv(edges, n, a, b) for a, b in zip(dims, dims[1:]))
        self.head = EdgeWeightedGraphConv(edges, n, hidden, 6)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x: (N, 6) [normalised position, colour] -> (N, 6) [offset, colour delta]."""
        h = x
        for conv in self.convs:
            h = torch.relu(conv(h))
        return self.head(h)


@dataclass
class GCNSettings:
    hidden: int = 64
    layers: int = 4
    pretrain_steps: int = 100
    lr: float = 1e-3
    offset_scale: float = 0.05  #: × scene size: bound on the offsets (tanh)
    seed: int = 0

    def __post_init__(self):
        validate.integer("hidden", self.hidden, 1)
        validate.integer("layers", self.layers, 2)
        validate.integer("pretrain_steps", self.pretrain_steps, 0)
        validate.positive("lr", self.lr)
        validate.positive("offset_scale", self.offset_scale)
        validate.seed("seed", self.seed)


def features(v: np.ndarray, c: np.ndarray) -> torch.Tensor:
    centre = v.mean(0)
    scale = np.abs(v - centre).max()
    return torch.as_tensor(np.concatenate([(v - centre) / scale, c], 1), dtype=torch.float32)


class IdentityPretrain(TorchStage):
    """The network learns to output zero offsets and zero colour change (so it starts at the input mesh)."""

    name = "gcn identity pre-training"

    def __init__(self, net: MeshGCN, x: torch.Tensor, lr: float):
        self.net, self.x = net, x
        self.opt = torch.optim.Adam(net.parameters(), lr=lr)

    def step(self, it: int) -> StepResult:
        self.opt.zero_grad()
        loss = self.net(self.x).pow(2).mean()
        loss.backward()
        return StepResult(float(loss.detach()), self.grads_finite())

    def finish(self, run: RunState) -> list[float]:
        return list(run.losses)


def pretrain_identity(net: MeshGCN, x: torch.Tensor, steps: int, lr: float) -> list[float]:
    """Identity pre-training (the shared loop, in memory: it takes a second); returns the losses."""
    return run_loop(IdentityPretrain(net, x, lr), LoopSettings(steps=steps), show_progress=False)


def apply_gcn(net: MeshGCN, x: torch.Tensor, v0: torch.Tensor, c0: torch.Tensor, size: float,
              s: GCNSettings) -> tuple[torch.Tensor, torch.Tensor]:
    """Vertex positions and colours predicted by the network (bounded offsets)."""
    out = net(x)
    v = v0 + torch.tanh(out[:, :3]) * (s.offset_scale * size)
    c = (c0 + out[:, 3:]).clamp(0.0, 1.0)
    return v, c


class GCNMorphStage(TorchStage):
    """The image loss of eq. 4.3 through Mitsuba, back into the GCN's weights (torch Adam)."""

    def __init__(self, bench: MorphBenchmark, out: Path, s: MorphSettings, g: GCNSettings):
        t0 = time.perf_counter()
        self.bench, self.out, self.s, self.g = bench, out, s, g
        self.name = f"gcn morph {bench.meta.kind}"
        meta = bench.meta
        self.res = s.resolution or meta.resolution
        self.photos = photo_tensors(bench, self.res)
        self.saturation_level, self.photo_hot = photo_saturation(self.photos, meta.train, s.saturation)
        self.v_in, self.f_in, self.c_in = read_ply_colours(bench.coarse)
        self.digest = file_digest(bench.coarse)
        self.photos_digest = photos_digest(bench)
        self.rng = np.random.default_rng(s.seed)
        self.work_ply = out / ".gcn_work.ply"
        write_ply(self.work_ply, self.v_in, self.f_in, self.c_in)
        self.scene = morph_scene(self.work_ply, s.mode, meta.hdri)
        self.params = mi.traverse(self.scene)
        self.batch: dict = {}
        self.loss_fn = torch_to_drjit_loss(self._render_loss)
        torch.manual_seed(g.seed)
        edges, n = adjacency(len(self.v_in), self.f_in)
        self.net = MeshGCN(edges, n, g.hidden, g.layers)
        self.x = features(self.v_in, self.c_in)
        self.v0 = torch.as_tensor(self.v_in, dtype=torch.float32)
        self.c0 = torch.as_tensor(self.c_in, dtype=torch.float32)
        self.pretrain = pretrain_identity(self.net, self.x, g.pretrain_steps, g.lr)
        self.opt = torch.optim.Adam(self.net.parameters(), lr=g.lr)
        self.setup_seconds = time.perf_counter() - t0

    def _render_loss(self, v: mi.TensorXf, c: mi.TensorXf) -> mi.Float:
        meta, s = self.bench.meta, self.s
        self.params["mesh.vertex_positions"] = v.array
        self.params["mesh.vertex_color"] = c.array
        with mitsuba_log_level(mi.LogLevel.Error):  # non-manifold vertices: expected in reconstructions
            self.params.update()
        views = self.batch["views"]
        imgs = render_views(self.scene, self.params, meta.cameras, views, self.res, meta.fov, s.spp, self.batch["seed"])
        loss = 0
        for img, i in zip(imgs, views):
            loss += photo_l1(img[..., :3], self.photos[int(i)], self.photo_hot.get(int(i)), self.saturation_level)
        return loss / len(views)

    def fingerprint(self) -> dict:
        return {"settings": self.s, "gcn": self.g, "input": self.digest, "photos": self.photos_digest}

    def state(self) -> dict:
        return {"net": self.net.state_dict(), "optimizer": optimizer_state(self.opt), "rng": rng_state(self.rng),
                "torch_rng": torch.get_rng_state()}

    def load_state(self, tree: dict) -> None:
        self.net.load_state_dict(tree["net"])
        load_optimizer_state(self.opt, tree["optimizer"], "GCN optimizer")
        set_rng_state(self.rng, tree["rng"])
        torch.set_rng_state(tree["torch_rng"])

    def step(self, it: int) -> StepResult:
        s, meta = self.s, self.bench.meta
        self.batch["views"] = self.rng.choice(meta.train, size=min(s.views_per_step, len(meta.train)), replace=False)
        self.batch["seed"] = s.seed * 7919 + it * 101
        self.opt.zero_grad()
        v, c = apply_gcn(self.net, self.x, self.v0, self.c0, meta.scene_size, self.g)
        loss = self.loss_fn(v, c)
        loss.backward()
        return StepResult(float(loss.detach()), self.grads_finite())

    def finish(self, run: RunState) -> MorphResult:
        with torch.no_grad():
            v, c = apply_gcn(self.net, self.x, self.v0, self.c0, self.bench.meta.scene_size, self.g)
        v_out, c_out = v.numpy().astype(np.float64), c.numpy()
        write_ply(self.out / "morphed.ply", v_out, self.f_in, c_out)
        seconds = self.setup_seconds + run.train_seconds
        self.close()
        ev = evaluate_morph(self.bench, self.v_in, self.f_in, self.c_in, v_out, self.f_in, c_out, self.s.mode,
                            self.res, self.out)
        return MorphResult(**vars(ev), seconds=seconds, iterations=self.s.iterations, vertices=int(len(v_out)),
                           method="gcn", settings=self.s, training=run.summary(),
                           pretrain_loss_last=self.pretrain[-1] if self.pretrain else None,
                           saturation_level=self.saturation_level)

    def close(self) -> None:
        self.scene = self.params = None
        self.work_ply.unlink(missing_ok=True)


def gcn_settings(s: MorphSettings) -> MorphSettings:
    """``s`` as the GCN morph runs it: without the silhouette loss, which lives in the large-steps stage only (a
    warning names it when ``s`` asks for one; the result's settings record 0)."""
    if not s.mask_weight:
        return s
    warnings.warn(f"mask_weight: the GCN morph has no silhouette loss; it runs on the photos alone "
                  f"(mask_weight {s.mask_weight} → 0)", stacklevel=3)
    return replace(s, mask_weight=0.0)


def run_gcn_morph(bench: MorphBenchmark, out: str | Path, s: MorphSettings | None = None,
                  g: GCNSettings | None = None, show_progress: bool = True,
                  budget_iterations: int | None = None) -> MorphResult | None:
    """Morph with a GCN whose offsets are trained by the image loss through Mitsuba (``dr.wrap``); resumable."""
    s = gcn_settings(s or MorphSettings())
    g = g or GCNSettings()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    stage = GCNMorphStage(bench, out, s, g)
    try:
        return run_loop(stage, LoopSettings(steps=s.iterations, checkpoint_every=s.checkpoint_every),
                        checkpoint=out / "checkpoint.npz", budget_steps=budget_iterations,
                        show_progress=show_progress, metrics_path=out / "metrics.json")
    finally:
        stage.close()
