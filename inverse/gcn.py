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
:func:`generative.bridge.torch_to_drjit_loss` (``dr.wrap``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import nn


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


def features(v: np.ndarray, c: np.ndarray) -> torch.Tensor:
    centre = v.mean(0)
    scale = np.abs(v - centre).max()
    return torch.as_tensor(np.concatenate([(v - centre) / scale, c], 1), dtype=torch.float32)


def pretrain_identity(net: MeshGCN, x: torch.Tensor, steps: int, lr: float) -> list[float]:
    """Identity pre-training: the network learns to output zero offsets and zero colour change."""
    opt = torch.optim.Adam(net.parameters(), lr=lr)
    hist = []
    for _ in range(steps):
        opt.zero_grad()
        loss = net(x).pow(2).mean()
        loss.backward()
        opt.step()
        hist.append(float(loss.detach()))
    return hist


def apply_gcn(net: MeshGCN, x: torch.Tensor, v0: torch.Tensor, c0: torch.Tensor, size: float,
              s: GCNSettings) -> tuple[torch.Tensor, torch.Tensor]:
    """Vertex positions and colours predicted by the network (bounded offsets)."""
    out = net(x)
    v = v0 + torch.tanh(out[:, :3]) * (s.offset_scale * size)
    c = (c0 + out[:, 3:]).clamp(0.0, 1.0)
    return v, c
